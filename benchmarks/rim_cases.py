"""Convex rims at any angle to the passes: write the cases as specs, run ``fabkit gcode
--json`` on each, and measure each finish program independently (#37 item 3).

    python benchmarks/rim_cases.py [OUTDIR] [--only NAME ...] [--cut]

Per case: exit code, the job's verified gouge and material left, lines, the verdict,
and the largest rise of the exact tip path (the drop cutter at 65 points of each feed
move and at points 2^-6 .. 2^-29 of its length from either end) above the program's
feed moves as written (4 decimals, read back by the parser of tests/test_steep_rim.py):
the vertical gouge any material point can see from a chord is at most that
(benchmarks/notes_steep_rim.md). ``--cut`` also runs benchmarks/roughing_acceptance.py
(rs274's moves cut by brute force with each tool's shape) on each job with roughing.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

SPEC = """name: {name}
units: mm
surface:
  height: {h}
  x: {x}
  y: {y}
  top: 0
stock:
  thickness: {thick}
  depth_limit: {limit}
tool:
  shape: ball
  diameter: {d}
  reach: {reach}
  number: 2
  depth_of_cut: {doc}
{rough}machining:
  scallop: {scallop}
  tolerance: {tol}
  direction: {dir}
  dialect: {dialect}
  units: {munits}
  feed: {feed}
  plunge: {plunge}
  spindle: 16000
"""

ROUGH = """tools:
  - number: 1
    shape: flat
    diameter: {rd}
    reach: {reach}
    depth_of_cut: {rdoc}
    feed: {feed}
    plunge: {plunge}
    spindle: 12000
roughing:
  tool: 1
  stepdown: {sd}
  stepover: {so}
  leave: {leave}
  strategy: offset
  entry: helix
"""


def vee(theta_deg, slope=20.0, depth=8.0):
    """A V trench along the direction theta (degrees from the passes' x), walls of
    ``slope`` across it, ``depth`` deep, through the origin."""
    t = math.radians(theta_deg)
    return f"{slope}*abs({math.cos(t):.12g}*y - {math.sin(t):.12g}*x) - {depth}"


def cases():
    mm = dict(units="mm", x="[-10, 10]", y="[-10, 10]", d=3, doc=3, scallop=0.05, tol=0.01, dir="x",
              dialect="linuxcnc", feed=2000, plunge=600, rough="", thick=20, limit=15, reach=30, munits="mm")
    rough = ROUGH.format(rd=8, feed=2000, plunge=600, sd=3, so=3.5, leave=0.5, reach=30, rdoc=8)
    inch = dict(munits="in", feed=80, plunge=24)       # the program in inches (feeds in/min)
    out = []
    for th in (10, 30, 45, 60, 80):
        out.append((f"v{th}", f"slope-20 V at {th} deg to the passes (narrower than the ball)",
                    dict(mm, h=vee(th))))
        out.append((f"w{th}", f"slope-3 V at {th} deg (the ball reaches in: convex rims, concave floor)",
                    dict(mm, h=vee(th, 3.0, 6.0))))
    out += [
        ("v30_grbl_rough", "slope-20 V at 30 deg, grbl, 8 mm flat roughing",
         dict(mm, h=vee(30), dialect="grbl", rough=rough)),
        ("w60_rough", "slope-3 V at 60 deg, LinuxCNC, 8 mm flat roughing",
         dict(mm, h=vee(60, 3.0, 6.0), rough=rough)),
        ("v45_d6", "slope-20 V at 45 deg, 6 mm ball", dict(mm, h=vee(45), d=6, doc=6)),
        ("w30_d6", "slope-3 V at 30 deg, 6 mm ball", dict(mm, h=vee(30, 3.0, 6.0), d=6, doc=6)),
        ("v60_y", "slope-20 V at 60 deg, passes along y", dict(mm, h=vee(60), dir="y")),
        ("ring", "a ridge 6*abs(x^2 + y^2 - 36) - 6 clipped: curved convex rims",
         dict(mm, h="6*abs(x**2 + y**2 - 36)/6 - 6")),
        ("cone", "a cone 12*sqrt(x^2 + y^2) - 10 (its rim a circle)", dict(mm, h="12*sqrt(x**2 + y**2) - 10")),
        ("ring_off", "the ring's rims running off the stock's edge (x [0, 12])",
         dict(mm, h="6*abs(x**2 + y**2 - 36)/6 - 6", x="[0, 12]", y="[-4, 8]")),
        ("v20_in", "slope-20 V at 20 deg, inch program, 3/32 in ball",
         dict(mm, **inch, h=vee(20), d=2.38125, doc=3)),
        ("w45_in_grbl_rough", "slope-3 V at 45 deg, inch program, grbl, 1/8 in ball, 1/4 in flat roughing",
         dict(mm, **inch, h=vee(45, 3.0, 6.0), d=3.175, doc=3, dialect="grbl",
              rough=ROUGH.format(rd=6.35, feed=80, plunge=24, sd=3, so=3, leave=0.5, reach=30, rdoc=8))),
    ]
    return [(n, w, dict(k, name=n)) for n, w, k in out]


def chord_rise(spec_path, prog):
    """Largest rise (mm) of the exact tip path above the written feed moves, and where."""
    from test_steep_rim import parse_moves

    from fabkit.spec import load_spec
    from fabkit.surface import Surface
    from fabkit.toolpath.finish.compensate import WorkSurface, compensate

    spec = load_spec(spec_path)
    ws = WorkSurface(Surface.from_spec(spec))
    R = 0.5 * float(spec.tool.diameter) * (25.4 if spec.units == "in" else 1.0)
    text = Path(prog).read_text()
    lines = text.splitlines()
    m6 = [i for i, line in enumerate(lines) if "M6" in line.split("(")[0].upper()]
    if m6:                              # one program, several tools: the last tool's moves
        units = [line for line in lines[:m6[-1]] if "G20" in line or "G21" in line]
        text = "\n".join(units[-1:] + lines[m6[-1]:])
    moves, feed = parse_moves(text)
    m = moves[feed]
    keep = (np.hypot(*(m[:, 1, :2] - m[:, 0, :2]).T) > 0) & (np.minimum(m[:, 0, 2], m[:, 1, 2]) < 0)
    m = m[keep]
    g = np.unique(np.r_[np.linspace(0, 1, 65), 2.0 ** -np.arange(6, 30), 1 - 2.0 ** -np.arange(6, 30)])
    worst, at = -np.inf, None
    for i in range(0, len(m), 4000):
        a, b = m[i:i + 4000, 0], m[i:i + 4000, 1]
        P = a[:, None, :] + g[None, :, None] * (b - a)[:, None, :]
        Z = compensate(ws, P[..., 0], P[..., 1], R)
        e = np.where(np.isfinite(Z) & (P[..., 2] < 0), Z - P[..., 2], -np.inf)
        k = np.unravel_index(np.argmax(e), e.shape)
        if e[k] > worst:
            worst, at = float(e[k]), (float(P[k][0]), float(P[k][1]))
    return worst, at


def main(argv):
    args = [a for a in argv[1:] if not a.startswith("--")]
    only = set(argv[argv.index("--only") + 1:]) if "--only" in argv else None
    out = Path(args[0] if args and (only is None or args[0] not in only) else "/tmp/fabkit_rim_cases")
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, SOURCE_DATE_EPOCH="1700000000")
    print("| case | what | exit | gouge | material left (normal) | lines | verdict | chord rise (mm) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, what, keys in cases():
        if only and name not in only:
            continue
        spec = out / f"{name}.yaml"
        spec.write_text(SPEC.format(**keys))
        r = subprocess.run([sys.executable, "-m", "fabkit", "gcode", str(spec), "-o", str(out / f"{name}.ngc"),
                            "--no-progress", "--json"], capture_output=True, text=True, env=env)
        if r.returncode not in (0, 1):
            print(f"| {name} | {what} | {r.returncode} | {r.stderr.strip()[-160:]} | | | | |", flush=True)
            continue
        j = json.loads(r.stdout)
        u = j["units"]
        progs = sorted(out.glob(f"{name}*.n*c"))
        fin = [p for p in progs if "finish" in p.name] or [out / f"{name}.ngc"]
        rise, at = chord_rise(spec, fin[0])
        why = "" if j["ok"] else " (" + "; ".join(j.get("failures", []) or [str(j.get("message", ""))])[:200] + ")"
        print(f"| {name} | {what} | {r.returncode} | {j['max_gouge']:.4f} {u} | {j['max_material_left']:.4f} {u} | "
              f"{j['lines']} | {'ok' if j['ok'] else 'FAIL' + why} | {rise:.4f} at X{at[0]:.3f} Y{at[1]:.3f} |",
              flush=True)
        if "--cut" in argv and keys["rough"]:          # (the script needs a roughing section)
            prog = out / f"{name}.ngc"    # a grbl job: its -o path (the script reads one program a tool)
            c = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "roughing_acceptance.py"), str(spec),
                                str(prog), "--h", "0.1", "--step", "0.05"], capture_output=True, text=True, env=env)
            for line in (c.stdout + c.stderr).strip().splitlines():
                print("    " + line)


if __name__ == "__main__":
    main(sys.argv)
