"""Steep walls meeting the top face: write the cases of benchmarks/notes_steep_rim.md as
specs and run ``fabkit gcode --json`` on each (about 10 s a case on this machine).

    python benchmarks/steep_cases.py [OUTDIR]      (default /tmp/fabkit_steep_cases)

Prints one row per case: verified gouge and material left (normal), in the program's
units, lines, and the verdict.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

SPEC = """name: {name}
units: mm
surface:
  height: {h}
  x: {x}
  y: {y}
  top: {top}
stock:
  thickness: {thick}
  depth_limit: {limit}
tool:
  shape: ball
  diameter: {d}
  reach: {reach}
machining:
  scallop: 0.05
  tolerance: 0.01
  direction: {dir}
{extra}"""


def cases():
    """(name, what, spec keys): slope 4, 8, 12 rising along x; a falling wall (crease at
    the footprint's start, and mid-wall); the top face at another height; a 6 mm ball;
    inch units; an oblique wall; each with the passes along x and along y."""
    base = dict(y="[-15, 15]", thick=40, limit=30, d=3, reach=40, extra="")
    out = []
    for dr in ("x", "y"):
        out += [
            (f"s4_{dr}", "slope 4 rising, crease 0-0.56 mm before the end",
             dict(base, h="4*x + 0.02*y**2", x="[0, 6]", top=24)),
            (f"s8_{dr}", "slope 8 (benchmarks/specs/steep.yaml)",
             dict(base, h="8*x + 0.02*y**2", x="[0, 3]", top=24)),
            (f"s12_{dr}", "slope 12",
             dict(base, h="12*x + 0.02*y**2", x="[0, 3]", top=36, thick=45, limit=40, reach=45)),
            (f"fallrim8_{dr}", "slope 8 falling, crease 0-0.56 mm after the start",
             dict(base, h="24 - 8*x + 0.02*y**2", x="[0, 3]", top=24)),
            (f"fall8_{dr}", "slope 8 falling, top face cuts it 4 mm down",
             dict(base, h="24 - 8*x + 0.02*y**2", x="[0, 3]", top=20)),
            (f"s8top12_{dr}", "slope 8, top face halfway up (crease mid-footprint)",
             dict(base, h="8*x + 0.02*y**2", x="[0, 3]", top=12)),
            (f"s8d6_{dr}", "slope 8, 6 mm ball",
             dict(base, h="8*x + 0.02*y**2", x="[0, 6]", top=48, thick=60, limit=54, d=6, reach=60)),
            (f"s8in_{dr}", "slope 8, inch program",
             dict(base, h="8*x + 0.02*y**2", x="[0, 3]", top=24, extra="  units: in\n")),
            (f"oblique8_{dr}", "8*x + 2*y: a wall oblique to the passes",
             dict(base, h="8*x + 2*y", x="[0, 3]", y="[-4, 4]", top=24, limit=36)),
        ]
    return [(n, w, dict(k, name=n, dir=n[-1])) for n, w, k in out]


def main(argv):
    out = Path(argv[1] if len(argv) > 1 else "/tmp/fabkit_steep_cases")
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, SOURCE_DATE_EPOCH="1700000000")
    print("| case | what | gouge | material left (normal) | lines | verdict |")
    print("|---|---|---|---|---|---|")
    for name, what, keys in cases():
        spec = out / f"{name}.yaml"
        spec.write_text(SPEC.format(**keys))
        r = subprocess.run([sys.executable, "-m", "fabkit", "gcode", str(spec), "-o", str(out / f"{name}.ngc"),
                            "--no-progress", "--json"], capture_output=True, text=True, env=env)
        if r.returncode not in (0, 1):
            print(f"| {name} | {what} | exit {r.returncode}: {r.stderr.strip()[:100]} | | | |")
            continue
        j = json.loads(r.stdout)
        u = j["units"]
        print(f"| {name} | {what} | {j['max_gouge']:.4f} {u} | {j['max_material_left']:.4f} {u} | "
              f"{j['lines']} | {'ok' if j['ok'] else 'FAIL'} |", flush=True)


if __name__ == "__main__":
    main(sys.argv)
