"""Speed of a sweep of the paper's full model: fabkit's batched integrator against
scipy ``solve_ivp(method="DOP853")`` run one launch at a time, measured side by side.

    python benchmarks/bench_sweep.py [--n 10000] [--sample 30] [--spec specs/surface.yaml]

The sweep: N entry speeds evenly over the ramp's calibrated range, damping 0
(the paper's apparatus, full model eq. xyODE). scipy is timed on an evenly spread
subsample, two ways: the project's reference path (``reference.solve_launch``, all
events, energy over the steps) and a lean loop (the same generated right-hand side,
only the bounce, escape and top events). Accuracy: v_out against a converged
reference (DOP853 rtol 1e-12, atol 1e-14) on the subsample, where the bounce
counts agree. Prints per-launch times, the ratios, and the accuracy of each.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fabkit.physics.calibrate import calibration_table  # noqa: E402
from fabkit.physics.integrate import launch_batch  # noqa: E402
from fabkit.physics.models import fused, problem_from_spec  # noqa: E402
from fabkit.physics.reference import solve_launch  # noqa: E402
from fabkit.spec import load_spec  # noqa: E402


def lean_scipy(problem, v, rtol, atol):
    """Minimal single-launch scipy loop: generated RHS, bounce/escape/top events."""
    from scipy.integrate import solve_ivp

    f = fused(problem)
    start, z_lim = problem.start, problem.top - problem.margin
    h = problem.fns.h

    def fun(t, s):
        ax, ay = f(s[0], s[1], s[2], s[3])[:2]
        return [s[2], s[3], ax, ay]

    def bounce(t, s):
        return s[2]
    bounce.direction = -1

    def escape(t, s):
        return (s[0] - start) if t > 0 else 1.0
    escape.terminal, escape.direction = True, -1

    def top(t, s):
        return float(h(s[0], s[1])) - z_lim
    top.terminal, top.direction = True, 1

    sol = solve_ivp(fun, (0, problem.t_max), [start, problem.y0, v, problem.vy0], method="DOP853", rtol=rtol,
                    atol=atol, events=[bounce, escape, top])
    nb = len(sol.t_events[0])
    v_out = abs(sol.y_events[1][0][2]) if len(sol.t_events[1]) else np.nan
    return nb, v_out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(Path(__file__).resolve().parents[1] / "specs" / "surface.yaml"))
    ap.add_argument("--n", type=int, default=10_000, help="launches in the fabkit sweep")
    ap.add_argument("--sample", type=int, default=30, help="launches timed with scipy")
    ap.add_argument("--rtol", type=float, default=1e-8)
    ap.add_argument("--atol", type=float, default=1e-10)
    ap.add_argument("--repeat", type=int, default=3, help="timing rounds (best of)")
    args = ap.parse_args(argv)

    spec = load_spec(args.spec)
    problem = problem_from_spec(spec, damping=0.0, nonlinear_damping=0.0, model="full")
    cal = calibration_table(spec)
    v = np.linspace(cal["v_in"].min(), cal["v_in"].max(), args.n)
    sub = v[np.linspace(0, args.n - 1, args.sample).round().astype(int)]
    launch_batch(problem, v[:8])  # compile and warm up
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}; python {platform.python_version()}")
    print(f"sweep: {spec.name}, full model, damping 0, v_in {v[0]:.3f}..{v[-1]:.3f} {spec.units}/s, "
          f"rtol {args.rtol:g}, atol {args.atol:g}")

    # timings interleaved, best of --repeat rounds (the machine may be shared)
    best: dict = {}
    sweep = None
    for _ in range(args.repeat):
        for label, kw, rtol in (("fabkit DOP853, 1 process", {"workers": 1}, args.rtol),
                                ("fabkit DOP853, 2 processes", {"workers": 2}, args.rtol),
                                ("fabkit DOP853 rtol 1e-10, 1 process", {"workers": 1}, 1e-10),
                                ("fabkit RK45, 1 process", {"workers": 1, "method": "RK45"}, args.rtol)):
            vv = v if "RK45" not in label else v[::5]
            t0, c0 = time.perf_counter(), time.process_time()
            r = launch_batch(problem, vv, rtol=rtol, atol=rtol * args.atol / args.rtol, **kw)
            dt, cpu = time.perf_counter() - t0, time.process_time() - c0
            if label not in best or dt < best[label][2]:
                best[label] = (label, len(r), dt, dt / len(r), cpu)
            if sweep is None:
                sweep = r
        for label, fn in (("scipy DOP853 reference path",
                           lambda x: solve_launch(problem, x, method="DOP853", rtol=args.rtol, atol=args.atol)),
                          ("scipy DOP853 lean loop", lambda x: lean_scipy(problem, x, args.rtol, args.atol))):
            t0, c0 = time.perf_counter(), time.process_time()
            for x in sub:
                fn(float(x))
            dt, cpu = time.perf_counter() - t0, time.process_time() - c0
            if label not in best or dt < best[label][2]:
                best[label] = (label, len(sub), dt, dt / len(sub), cpu)
    rows = [best[k] for k in best if k.startswith("fabkit")]
    t_ref, c_ref = best["scipy DOP853 reference path"][3], best["scipy DOP853 reference path"][4] / len(sub)
    t_lean, c_lean = best["scipy DOP853 lean loop"][3], best["scipy DOP853 lean loop"][4] / len(sub)

    # well-conditioned launches: escaped, and the 2 neighbours on each side have the same bounce count
    nb = np.where(sweep.outcome == 0, sweep.bounces, -1)
    good = np.zeros(len(v), dtype=bool)
    good[2:-2] = nb[2:-2] >= 1
    for d in (-2, -1, 1, 2):
        good[2:-2] &= nb[2 + d:len(v) - 2 + d] == nb[2:-2]
    gi = np.flatnonzero(good)
    gi = gi[np.linspace(0, len(gi) - 1, min(args.sample, len(gi))).round().astype(int)]

    conv = [solve_launch(problem, float(x), method="DOP853", rtol=1e-12, atol=1e-14) for x in v[gi]]
    sci = [lean_scipy(problem, float(x), args.rtol, args.atol) for x in v[gi]]

    def acc(nbs, vo):
        errs = [abs(a - c["v_out"]) / c["v_out"] for b, a, c in zip(nbs, vo, conv)
                if c["outcome"] == "escaped" and b == c["bounces"] and np.isfinite(a)]
        agree = sum(b == c["bounces"] for b, c in zip(nbs, conv))
        return (max(errs) if errs else np.nan), (float(np.median(errs)) if errs else np.nan), agree

    a_fab = acc(sweep.bounces[gi], sweep.v_out[gi])
    a_sci = acc([b for b, _ in sci], [x for _, x in sci])

    print(f"\n{'method':38} {'launches':>9} {'wall s':>8} {'cpu s':>7} {'ms/launch':>10}")
    for label, n, dt, per, cpu in rows:
        print(f"{label:38} {n:9d} {dt:8.2f} {cpu:7.2f} {per * 1e3:10.4f}")
    print(f"{'scipy DOP853 reference path':38} {len(sub):9d} {t_ref * len(sub):8.2f} {c_ref * len(sub):7.2f} "
          f"{t_ref * 1e3:10.3f}")
    print(f"{'scipy DOP853 lean loop':38} {len(sub):9d} {t_lean * len(sub):8.2f} {c_lean * len(sub):7.2f} "
          f"{t_lean * 1e3:10.3f}")
    best = min(per for label, _, _, per, _ in rows if "DOP853, " in label)
    cpu1 = rows[0][4] / rows[0][1]
    print(f"\nratio per launch (same rtol {args.rtol:g}), wall: {t_ref / best:.0f}x against the scipy reference "
          f"path, {t_lean / best:.0f}x against the lean scipy loop")
    print(f"ratio per launch, cpu time (1 process): {c_ref / cpu1:.0f}x against the reference path, "
          f"{c_lean / cpu1:.0f}x against the lean loop")
    print(f"fabkit: {args.n} launches in {min(dt for label, n, dt, _, _ in rows if n == args.n):.2f} s "
          f"(best of {args.repeat})")
    print(f"\naccuracy on {len(gi)} well-conditioned launches (escaped, same bounce count as 2 neighbours each "
          "side),\n|v_out - v_out(DOP853 rtol 1e-12)| / v_out where bounce counts agree:")
    for name, (mx, med, agree) in (("fabkit", a_fab), ("scipy DOP853 lean", a_sci)):
        print(f"  {name:20} max {mx:.2e}  median {med:.2e}  bounce counts agree {agree}/{len(gi)}")
    print(f"load average at the end {os.getloadavg()[0]:.1f} (other work on the machine slows the wall times)")


if __name__ == "__main__":
    main()
