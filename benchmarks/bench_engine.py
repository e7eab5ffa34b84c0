"""The compiled launch engine end to end, as ratios measured in one run.

    python benchmarks/bench_engine.py [--spec specs/surface.yaml] [--sample 12] [--accuracy 200]
                                      [--jobs 2] [--skip-cold] [--only-accuracy]

Rows (every time is wall and CPU of a fresh ``fabkit`` process unless stated):

1. marginal cost per launch through ``fabkit sweep`` at ``simulation.rtol`` 1e-8
   (atol 1e-10): (t(20 000 launches) - t(2 000)) / 18 000, against scipy
   ``solve_ivp(DOP853)`` one launch at a time with the same events
   (``reference.solve_launch``, same rtol and atol) on ``--sample`` launches spread
   over the same range;
1b. accuracy on ``--accuracy`` launches (default 200) evenly spread over the ramp's
   range: bounce counts of the engine and of scipy DOP853 at rtol 1e-8 against
   scipy DOP853 at rtol 1e-12 (atol 1e-14), and the v_out error of each where the
   counts agree (the scipy solves run on ``--jobs`` processes, untimed);
2. fixed cost: ``fabkit sweep`` of 200 launches against the start-up floor
   ``python -c "import numpy, scipy.integrate, sympy"``;
3. ``fabkit check SPEC`` against the same floor (warm cache);
4. compile: ``fabkit simulate`` of one launch with an empty cache (cold) and again
   (warm), in a scratch ``FABKIT_CACHE_DIR``;
5. threads: ``launch_batch`` of 20 000 launches with ``workers=2`` against 1, in
   this process;
6. the finite ball (``simulation.model: ball``, the same spec and rtol): its marginal
   cost per launch, (t(N2) - t(N1)) / (N2 - N1) of ``launch_batch`` in this process
   (``--ball-n``), against the point model's (``full``) measured the same way, and
   against scipy ``solve_ivp(DOP853)`` of the ball one launch at a time (same
   events, ``--sample`` launches). ``--ball-only`` runs this row alone.

Each timed command runs ``--repeat`` times, interleaved; the best is kept. The
machine is shared: read the ratios, not the absolute times.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def timed(cmd: list[str], env=None) -> tuple[float, float]:
    """(wall, cpu) seconds of one subprocess (cpu: user + system of the child)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def best(rows):
    return min(r[0] for r in rows), min(r[1] for r in rows)


def timing(args, fabkit, spec8, problem, lo, hi) -> float:
    """Rows 1-3 (marginal cost against scipy, fixed costs); returns the start-up floor
    (best wall seconds)."""
    from fabkit.physics.reference import solve_launch

    # 1. marginal cost per launch, and scipy one launch at a time
    rows = {2000: [], 20000: [], "floor": [], "sweep200": [], "check": []}
    sub = np.linspace(lo, hi, args.sample)
    scipy_rows = []
    for _ in range(args.repeat):
        for n in (2000, 20000):
            rows[n].append(timed([*fabkit, "sweep", str(spec8), "--v-in", str(lo), str(hi), str(n), "--no-progress"]))
        rows["floor"].append(timed([sys.executable, "-c", "import numpy, scipy.integrate, sympy"]))
        rows["sweep200"].append(timed([*fabkit, "sweep", args.spec, "--v-in", str(lo), str(hi), "200",
                                       "--no-progress"]))
        rows["check"].append(timed([*fabkit, "check", args.spec, "--no-progress"]))
        c0, t0 = time.process_time(), time.perf_counter()
        for v in sub:
            solve_launch(problem, float(v), method="DOP853", rtol=1e-8, atol=1e-10)
        scipy_rows.append(((time.perf_counter() - t0) / len(sub), (time.process_time() - c0) / len(sub)))
    w2, c2 = best(rows[2000])
    w20, c20 = best(rows[20000])
    mw, mc = (w20 - w2) / 18000, (c20 - c2) / 18000
    sw, sc = best(scipy_rows)
    print("\n| row | wall | CPU |")
    print("|---|---|---|")
    print(f"| fabkit sweep, 2 000 launches | {w2:.2f} s | {c2:.2f} s |")
    print(f"| fabkit sweep, 20 000 launches | {w20:.2f} s | {c20:.2f} s |")
    print(f"| marginal cost per launch | {mw * 1e3:.4f} ms | {mc * 1e3:.4f} ms |")
    print(f"| scipy DOP853 one launch at a time (reference.solve_launch) | {sw * 1e3:.2f} ms | {sc * 1e3:.2f} ms |")
    print(f"| **ratio** scipy / marginal | **{sw / mw:.0f}x** | **{sc / mc:.0f}x** |")
    fw, fc = best(rows["floor"])
    s2w, s2c = best(rows["sweep200"])
    chw, chc = best(rows["check"])
    print(f"| floor: python -c 'import numpy, scipy.integrate, sympy' | {fw:.2f} s | {fc:.2f} s |")
    print(f"| fabkit sweep, 200 launches | {s2w:.2f} s ({s2w / fw:.2f}x floor) | {s2c:.2f} s ({s2c / fc:.2f}x) |")
    print(f"| fabkit check {Path(args.spec).name} | {chw:.2f} s ({chw / fw:.2f}x floor) | {chc:.2f} s "
          f"({chc / fc:.2f}x) |")
    return fw


def _reference_row(args):
    """One launch by scipy DOP853 at rtol 1e-12 and at 1e-8 (a worker process)."""
    spec_path, v = args
    from fabkit.physics.models import problem_from_spec
    from fabkit.physics.reference import solve_launch
    from fabkit.spec import load_spec

    problem = problem_from_spec(load_spec(spec_path))
    ref = solve_launch(problem, float(v), method="DOP853", rtol=1e-12, atol=1e-14)
    sci = solve_launch(problem, float(v), method="DOP853", rtol=1e-8, atol=1e-10)
    return ref, sci


def accuracy(problem, spec8, v, jobs: int) -> None:
    """Row 1b: the engine at rtol 1e-8 on ``v`` against scipy DOP853 at rtol 1e-12
    (bounce counts, v_out), with scipy DOP853 at rtol 1e-8 as the peer."""
    from concurrent.futures import ProcessPoolExecutor

    from fabkit.physics.integrate import launch_batch

    t0 = time.perf_counter()
    eng = launch_batch(problem, v, rtol=1e-8, atol=1e-10)
    with ProcessPoolExecutor(max(int(jobs), 1)) as ex:
        rows = list(ex.map(_reference_row, [(str(spec8), float(x)) for x in v], chunksize=4))
    ref = [r for r, _ in rows]
    sci = [s for _, s in rows]
    n = len(v)
    same_e = sum(int(eng.bounces[i]) == r["bounces"] for i, r in enumerate(ref))
    same_s = sum(s["bounces"] == r["bounces"] for s, r in zip(sci, ref))
    err_e, err_s = [], []
    for i, (s, r) in enumerate(zip(sci, ref)):
        if r["outcome"] == "escaped" and int(eng.bounces[i]) == r["bounces"] == s["bounces"]:
            err_e.append(abs(eng.v_out[i] - r["v_out"]) / r["v_out"])
            err_s.append(abs(s["v_out"] - r["v_out"]) / r["v_out"])
    print(f"\naccuracy on {n} launches over v_in {v[0]:.4g}..{v[-1]:.4g} (reference: DOP853 rtol 1e-12, "
          f"{time.perf_counter() - t0:.0f} s on {jobs} processes)")
    print(f"bounce counts equal to the reference: engine {same_e}/{n}, scipy DOP853 rtol 1e-8 {same_s}/{n}")
    for i, r in enumerate(ref):
        if int(eng.bounces[i]) != r["bounces"] or sci[i]["bounces"] != r["bounces"]:
            print(f"  differs at v_in {v[i]:.6f}: reference {r['outcome']} {r['bounces']}, engine "
                  f"{int(eng.bounces[i])}, scipy 1e-8 {sci[i]['bounces']}")
    if err_e:
        print(f"v_out relative error on {len(err_e)} escaped launches: engine median {np.median(err_e):.1e} "
              f"max {np.max(err_e):.1e}; scipy rtol 1e-8 median {np.median(err_s):.1e} max {np.max(err_s):.1e}")


def rest(args, fabkit, tmp, problem, lo, hi, fw) -> None:
    """Rows 4-5: compile cold and warm, threads."""
    from fabkit.physics.integrate import launch_batch

    # 4. compile cold / warm
    if not args.skip_cold:
        env = dict(os.environ, FABKIT_CACHE_DIR=str(tmp / "cold-cache"))
        cold = timed([*fabkit, "simulate", args.spec, "--v-in", "40"], env=env)
        warm = best([timed([*fabkit, "simulate", args.spec, "--v-in", "40"], env=env) for _ in range(args.repeat)])
        print(f"\nfabkit simulate, empty cache (compiles): {cold[0]:.1f} s wall, {cold[1]:.1f} s CPU; "
              f"warm: {warm[0]:.2f} s wall, {warm[1]:.2f} s CPU ({cold[0] / warm[0]:.0f}x); "
              f"floor {fw:.2f} s")

    # 5. threads in this process
    v = np.linspace(lo, hi, 20000)
    t_rows = {1: [], 2: []}
    for _ in range(args.repeat):
        for w in (1, 2):
            t0 = time.perf_counter()
            launch_batch(problem, v, rtol=1e-8, atol=1e-10, workers=w)
            t_rows[w].append(time.perf_counter() - t0)
    print(f"launch_batch 20 000 launches: 1 thread {min(t_rows[1]):.2f} s, 2 threads {min(t_rows[2]):.2f} s "
          f"(speed-up {min(t_rows[1]) / min(t_rows[2]):.2f}x); load average {os.getloadavg()[0]:.1f} at the end")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spec", default=str(ROOT / "specs" / "surface.yaml"))
    ap.add_argument("--sample", type=int, default=12, help="launches timed with scipy")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--accuracy", type=int, default=200, help="launches compared with the rtol-1e-12 reference")
    ap.add_argument("--jobs", type=int, default=2, help="processes for the untimed scipy accuracy solves")
    ap.add_argument("--skip-cold", action="store_true", help="skip the cold compile row")
    ap.add_argument("--only-accuracy", action="store_true", help="only the accuracy row (1b)")
    ap.add_argument("--ball-n", type=int, nargs=2, default=(1000, 5000), help="N1 N2 of the ball row")
    ap.add_argument("--ball-only", action="store_true", help="run only the ball row (6)")
    args = ap.parse_args(argv)

    from fabkit.physics.integrate import launch_batch
    from fabkit.physics.models import problem_from_spec
    from fabkit.spec import load_spec

    fabkit = [sys.executable, "-m", "fabkit"]
    tmp = Path(tempfile.mkdtemp(prefix="fabkit-bench-"))
    raw = yaml.safe_load(Path(args.spec).read_text())
    raw.setdefault("simulation", {})
    raw["simulation"]["rtol"] = 1e-8
    raw["simulation"]["atol"] = 1e-10
    spec8 = tmp / "rtol8.yaml"
    spec8.write_text(yaml.safe_dump(raw, sort_keys=False))
    spec = load_spec(spec8)
    problem = problem_from_spec(spec)
    from fabkit.physics.calibrate import calibration_table

    cal = calibration_table(spec)
    lo, hi = float(cal["v_in"].min()), float(cal["v_in"].max())
    print(f"# {platform.machine()} {os.cpu_count()} cores, Python {platform.python_version()}, "
          f"load average {os.getloadavg()[0]:.1f} at the start")
    print(f"# spec {args.spec} at rtol 1e-8 / atol 1e-10, v_in {lo:.4g}..{hi:.4g}, model {problem.model}, "
          f"damping {problem.damping:g}")

    if args.ball_only:
        ball_row(problem, lo, hi, args)
        return 0

    # warm the cache (and this process)
    subprocess.run([*fabkit, "simulate", str(spec8), "--v-in", "40"], check=True, stdout=subprocess.DEVNULL)
    launch_batch(problem, [40.0])

    if not args.only_accuracy:
        fw = timing(args, fabkit, spec8, problem, lo, hi)
    # 1b. accuracy: bounce counts against rtol 1e-12, v_out errors (untimed)
    accuracy(problem, spec8, np.linspace(lo, hi, args.accuracy), args.jobs)
    if not args.only_accuracy:
        rest(args, fabkit, tmp, problem, lo, hi, fw)
        ball_row(problem, lo, hi, args)
    return 0


def ball_row(problem, lo, hi, args) -> None:
    """6. the ball's marginal cost per launch against the point model's and scipy's."""
    from fabkit.physics.integrate import launch_batch
    from fabkit.physics.reference import solve_launch

    ball = problem.with_(model="ball")
    full = problem.with_(model="full")
    n1, n2 = args.ball_n
    for p in (ball, full):   # compile or load, and warm this process
        launch_batch(p, [40.0])
    rows = {("ball", n1): [], ("ball", n2): [], ("full", n1): [], ("full", n2): [], "scipy": []}
    sub = np.linspace(lo, hi, args.sample)
    for _ in range(args.repeat):
        for name, p in (("ball", ball), ("full", full)):
            for n in (n1, n2):
                c0 = time.process_time()
                r = launch_batch(p, np.linspace(lo, hi, n))
                rows[(name, n)].append((time.process_time() - c0, int(r.steps.sum())))
        c0 = time.process_time()
        for v in sub:
            solve_launch(ball, float(v), method="DOP853", rtol=ball.rtol, atol=ball.atol)
        rows["scipy"].append(((time.process_time() - c0) / len(sub), 0))
    m = {name: (min(t for t, _ in rows[(name, n2)]) - min(t for t, _ in rows[(name, n1)])) / (n2 - n1)
         for name in ("ball", "full")}
    steps = {name: rows[(name, n2)][0][1] / n2 for name in ("ball", "full")}
    sc = min(t for t, _ in rows["scipy"])
    print(f"\n| ball row (rtol {ball.rtol:g}, atol {ball.atol:g}, CPU) | per launch | accepted steps a launch |")
    print("|---|---|---|")
    print(f"| ball, marginal ({n2} - {n1} launches) | {m['ball'] * 1e3:.4f} ms | {steps['ball']:.0f} |")
    print(f"| full (point), marginal | {m['full'] * 1e3:.4f} ms | {steps['full']:.0f} |")
    print(f"| scipy DOP853, the ball one launch at a time | {sc * 1e3:.2f} ms | |")
    print(f"| **ratios** ball / point: **{m['ball'] / m['full']:.2f}x** ({m['ball'] / m['full'] * steps['full'] / steps['ball']:.2f}x a step); "
          f"scipy / ball: **{sc / m['ball']:.0f}x** | | |")
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    raise SystemExit(main())
