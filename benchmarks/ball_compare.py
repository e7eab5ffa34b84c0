"""How much the finite ball matters: `fabkit check` of the paper's apparatus with the
models full, simplified and ball side by side (v_critical, the reachable two-bounce
windows, the largest |F_t|/N over the ramp's heights).

    python benchmarks/ball_compare.py [SPEC] [--out results.json]

Prints a Markdown table (docs/ball.md, README). Each check is the command's own
computation (fabkit.physics.check.check) with simulation.model replaced.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None):
    from fabkit.physics.check import check
    from fabkit.spec import load_spec

    ap = argparse.ArgumentParser()
    ap.add_argument("spec", nargs="?", default=str(ROOT / "specs" / "surface.yaml"))
    ap.add_argument("--out", default=None)
    ap.add_argument("--models", default="full,simplified,ball")
    args = ap.parse_args(argv)
    base = load_spec(args.spec)
    rows, heights = {}, {}
    for model in args.models.split(","):
        spec = base.with_overrides({"simulation.model": model})
        t0 = time.perf_counter()
        r = check(spec).to_json()
        dt = time.perf_counter() - t0
        rows[model] = {"v_critical": r["v_critical"], "critical_height": r["critical_height"],
                       "reachable_windows": r["reachable_windows"], "safe": r["safe"],
                       "first_failure": r["first_failure"], "highest_safe_height": r["highest_safe_height"],
                       "ball": r.get("ball"), "seconds": dt}
        heights[model] = r["heights"]
        print(f"{model}: v_critical {r['v_critical']}, {len(r['reachable_windows'])} windows, safe {r['safe']}, "
              f"{dt:.1f} s", flush=True)
    u = base.units
    print(f"\n| model | v_critical ({u}/s) | release height ({u}) | reachable two-bounce windows, v_in ({u}/s) |")
    print("|---|---|---|---|")
    for model, r in rows.items():
        vc = "-" if r["v_critical"] is None else f"{r['v_critical']:.4f}"
        hc = "-" if r["critical_height"] is None else f"{r['critical_height']:.4f}"
        ws = "; ".join(f"{w['lo']:.3f}..{w['hi']:.3f}" for w in r["reachable_windows"]) or "none"
        print(f"| {model} | {vc} | {hc} | {ws} |")
    b = rows.get("ball", {}).get("ball")
    if b:
        print(f"\nball: largest |F_t|/N {b['max_slip']:.4f} at release height {b['max_slip_height']:.4f} {u}; "
              f"unsafe counts {b['unsafe_counts']}")
        # the slip ratio along the ramp (the ramp's heights nearest to a few round ones) and
        # the lowest heights from which it exceeds 0.3 and 0.5 (docs/ball.md, README)
        H = np.asarray(heights["ball"], dtype=float)
        s = np.asarray([np.nan if x is None else x for x in b["max_slip_per_height"]], dtype=float)
        at = [int(np.argmin(np.abs(H - h))) for h in (0.2, 1, 2, 3, 4, 4.5)]
        print("ball: |F_t|/N along the ramp: " + ", ".join(f"{s[i]:.3f} at {H[i]:.4f} {u}" for i in at))
        for t in (0.3, 0.5):
            over = np.flatnonzero(s > t)
            print(f"ball: |F_t|/N exceeds {t:g} from release height "
                  + (f"{H[over[0]]:.4f} {u}" if len(over) else "- (never)"))
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
