"""How `fabkit gcode`'s CPU time scales with the work: the footprint's area, 1 / scallop
and the number of passes (issue 28: cost grows with the work and nothing else).

    python benchmarks/scaling.py [--out benchmarks/scaling.png] [--json FILE]

Jobs: a smooth dish h = -0.002 (x^2 + y^2) - 0.004 x y (mm, the bowl spec's 1/8 in
ball, passes along x, verification on), (a) square footprints of side 20-120 mm at
scallop 0.05 mm, (b) the 40 mm square at scallop 0.2-0.01 mm. Each job runs in a
fresh process (benchmarks/bench_gcode.py's child: the command's stage timers read CPU
time); its CPU time (user + sys) is plotted with the import floor measured in the same
run (``import numpy, scipy.integrate, sympy``) and the guard's estimate; the load
average of each run is printed. Warm kernels (FABKIT_CACHE_DIR): run a job once first.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_gcode import CHILD, FLOOR, _child  # noqa: E402

SPEC = """name: dish
units: mm
surface:
  height: -0.002*(x**2 + y**2) - 0.004*x*y
  x: [{x0}, {x1}]
  y: [{x0}, {x1}]
  top: 0
stock:
  thickness: 50
  depth_limit: 40
tool:
  shape: ball
  diameter: 1/8 in
  reach: 30
machining:
  scallop: {scallop}
  tolerance: 0.01
  direction: x
  feed: 1500
  plunge: 400
  spindle: 18000
  safe_height: 3
  dialect: grbl
  units: mm
"""


def run(side, scallop, tmp):
    p = Path(tmp) / f"dish_{side}_{scallop}.yaml"
    p.write_text(SPEC.format(x0=-side / 2, x1=side / 2, scallop=scallop))
    r = _child(["-c", CHILD, "gcode", str(p), "--no-progress", "--json", "--max-time", "600",
                "-o", str(p.with_suffix(".ngc"))], tmp)
    if r["code"] not in (0, 1):
        raise SystemExit(f"{p.name}: exit {r['code']}: {r['err'][-400:]}")
    j = json.loads(r["out"])
    est = next((json.loads(line[9:]) for line in r["err"].splitlines() if line.startswith("ESTIMATE ")), {})
    row = {"side": side, "area": side * side, "scallop": scallop, "cpu": r["cpu"], "rss_mb": r["rss_mb"],
           "load": r["load"], "passes": j["passes"], "lines": j["lines"], "stages": j["timings_s"],
           "estimate": est.get("seconds")}
    print(f"side {side} mm, scallop {scallop} mm: {r['cpu']:.2f} s CPU, {j['passes']} passes, {j['lines']} lines, "
          f"estimate {row['estimate']:.2f} s, load {r['load']:.1f}", flush=True)
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE / "scaling.png"))
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    rows = []
    floors = []
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [("area", s, 0.05) for s in (20, 40, 80, 120)] + \
               [("scallop", 40, c) for c in (0.2, 0.1, 0.02, 0.01)]
        for i, (kind, side, sc) in enumerate(jobs):
            if i % 3 == 0:
                floors.append(_child(["-c", FLOOR], tmp))
            rows.append({"series": kind, **run(side, sc, tmp)})
    floor = min(f["cpu"] for f in floors)
    loads = ", ".join(f"{f['load']:.1f}" for f in floors)
    print(f"import floor: {floor:.2f} s CPU (best of {len(floors)}; load {loads})")
    base = next(r for r in rows if r["side"] == 40 and r["scallop"] == 0.05)
    rows.append({"series": "scallop", **{k: v for k, v in base.items() if k != "series"}})
    if a.json:
        Path(a.json).write_text(json.dumps({"floor": floor, "rows": rows}, indent=1))

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(13, 4.2))
    for k, (key, xl, f) in enumerate((("area", "footprint area (mm$^2$), scallop 0.05 mm", lambda r: r["area"]),
                                      ("scallop", "1 / scallop (1/mm), 40 x 40 mm", lambda r: 1 / r["scallop"]),
                                      (None, "passes (all jobs)", lambda r: r["passes"]))):
        sel = sorted((r for r in rows if key is None or r["series"] == key), key=f)
        if key is None:
            sel = sorted({(r["side"], r["scallop"]): r for r in rows}.values(), key=f)
        x = [f(r) for r in sel]
        a_ = ax[k]
        a_.plot(x, [r["cpu"] for r in sel], "o-", label="measured CPU s")
        a_.plot(x, [r["stages"]["plan"] for r in sel], "s--", label="of it: plan")
        a_.plot(x, [r["stages"]["verify"] for r in sel], "^--", label="of it: verify")
        a_.plot(x, [r["estimate"] for r in sel], "x:", label="guard's estimate")
        a_.axhline(floor, color="grey", lw=1, label=f"import floor {floor:.2f} s")
        a_.set_xlabel(xl)
        a_.set_ylabel("CPU seconds")
        a_.set_ylim(bottom=0)
        a_.grid(alpha=0.3)
    ax[0].legend(fontsize=8)
    fig.suptitle("fabkit gcode: CPU time against the work (dish -0.002(x$^2$+y$^2$) - 0.004xy, 1/8 in ball, "
                 "warm kernels)", fontsize=10)
    fig.tight_layout()
    fig.savefig(a.out, dpi=90)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
