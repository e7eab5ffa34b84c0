"""fabkit's ball model against an independent implementation (tests/ball_newton_euler.py:
3-D Newton-Euler in the angular velocity, the contact force solved from the rolling
constraint, scipy DOP853 at rtol 1e-11).

    python benchmarks/ball_reference.py [--n N] [--t-max T]

For the paper's surface (cm) and another formula in mm (tests/fixtures/ball/mm_formula.yaml),
both with a 2.5 cm ball:
* v_critical from fabkit's sweep (1e-6 relative); the independent implementation
  launched at v_critical (1 -/+ 1e-4) must agree on the bounce counts there;
* N launches spread over the range: outcome and bounce counts exact, v_out where both
  escape after two bounces (the relative difference reported; acceptance 1e-3);
* ``--vc``: the mm formula's v_critical (t_max 8 s) by a plain bisection of the
  independent implementation, against fabkit's sweep.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

MM_SPEC = ROOT / "tests" / "fixtures" / "ball" / "mm_formula.yaml"


def problems(t_max):
    from fabkit.physics.models import problem_from_spec
    from fabkit.spec import load_spec

    spec = load_spec(ROOT / "specs" / "surface.yaml")
    paper = problem_from_spec(spec.with_overrides({"simulation.model": "ball"})).with_(t_max=t_max)
    mm = problem_from_spec(load_spec(MM_SPEC)).with_(t_max=t_max)
    return {"paper (cm)": (paper, (16.7, 79.4)), "mm formula": (mm, (167.0, 794.0))}


def independent_vc(ne, lo: float, hi: float, rel: float = 2e-7) -> tuple[float, float]:
    """v_critical by plain bisection of the independent implementation from a bracket
    [lo, hi] it verifies (lo not a one-bounce escape, hi one); (midpoint, half-width)."""
    one = lambda v: (lambda r: r["outcome"] == "escaped" and r["bounces"] == 1)(ne.launch(v))  # noqa: E731
    assert not one(lo) and one(hi), "not a bracket"
    while hi - lo > rel * hi:
        m = 0.5 * (lo + hi)
        if one(m):
            hi = m
        else:
            lo = m
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def main(argv=None):
    from ball_newton_euler import NewtonEuler

    from fabkit.physics.integrate import launch_batch
    from fabkit.physics.models import OUTCOMES
    from fabkit.physics.sweep import sweep

    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--t-max", type=float, default=20.0)
    ap.add_argument("--vc", action="store_true",
                    help="only the mm formula's v_critical at its spec's t_max (8 s), fabkit's sweep against a "
                         "bisection of the independent implementation, and its launch at 232.85 mm/s (the "
                         "constants in tests/test_ball_cli.py)")
    args = ap.parse_args(argv)
    if args.vc:
        from fabkit.physics.models import problem_from_spec
        from fabkit.spec import load_spec

        p = problem_from_spec(load_spec(MM_SPEC))
        sw = sweep(p, [408.47, 408.57], error_samples=0, tn=False)
        vc, err = independent_vc(NewtonEuler(p), 408.4759, 408.5576)
        print(f"mm formula, t_max {p.t_max:g} s: fabkit sweep v_critical {sw['v_critical']:.6f} "
              f"+- {sw['v_critical_error']:.1e}; independent {vc:.6f} +- {err:.1e} mm/s; relative difference "
              f"{abs(sw['v_critical'] - vc) / vc:.1e}")
        r = NewtonEuler(p).launch(232.85)
        print(f"mm formula at 232.85 mm/s (window 204..262): independent {r['outcome']}, {r['bounces']} bounces, "
              f"v_out {r['v_out']!r} mm/s")
        return
    for name, (p, (lo, hi)) in problems(args.t_max).items():
        ne = NewtonEuler(p)
        v = np.linspace(lo, hi, args.n)
        t0 = time.perf_counter()
        fab = launch_batch(p, v)
        t_fab = time.perf_counter() - t0
        t0 = time.perf_counter()
        ref = [ne.launch(float(x)) for x in v]
        t_ref = time.perf_counter() - t0
        same = [OUTCOMES[o] == r["outcome"] and b == r["bounces"] for o, b, r in zip(fab.outcome, fab.bounces, ref)]
        two = [i for i, r in enumerate(ref) if r["outcome"] == "escaped" and r["bounces"] == 2 and same[i]]
        dv = [abs(fab.v_out[i] - ref[i]["v_out"]) / ref[i]["v_out"] for i in two]
        print(f"{name}: {len(v)} launches {lo:g}..{hi:g}: outcome and bounces agree in {sum(same)}/{len(v)}; "
              f"two-bounce escapes {len(two)}, max |dv_out|/v_out {max(dv) if dv else float('nan'):.2e}; "
              f"fabkit {t_fab:.1f} s, independent {t_ref:.1f} s", flush=True)
        for i in np.flatnonzero(~np.array(same)):
            print(f"   differ at v_in {v[i]:.6g}: fabkit {OUTCOMES[fab.outcome[i]]}/{fab.bounces[i]}, "
                  f"independent {ref[i]['outcome']}/{ref[i]['bounces']}")
        sw = sweep(p, np.linspace(lo, hi, 200), error_samples=0, tn=False)
        vc = sw["v_critical"]
        print(f"   fabkit v_critical {vc} (+- {sw['v_critical_error']}); two-bounce windows "
              f"{[(round(w['lo'], 4), round(w['hi'], 4)) for w in sw['windows'] if w['bounces'] == 2]}")
        if vc is not None:
            for f in (1 - 1e-4, 1 + 1e-4):
                a = launch_batch(p, [vc * f])
                b = ne.launch(vc * f)
                print(f"   at v_critical x {f}: fabkit {OUTCOMES[a.outcome[0]]}/{a.bounces[0]}, "
                      f"independent {b['outcome']}/{b['bounces']}")
        for w in [w for w in sw["windows"] if w["bounces"] == 2][:4]:
            for f in (0.25, 0.5, 0.75):
                x = w["lo"] + f * (w["hi"] - w["lo"])
                a = launch_batch(p, [x])
                b = ne.launch(x)
                print(f"   window {w['lo']:.4f}..{w['hi']:.4f} at {x:.5f}: fabkit {OUTCOMES[a.outcome[0]]}/"
                      f"{a.bounces[0]} v_out {a.v_out[0]:.9g}, independent {b['outcome']}/{b['bounces']} "
                      f"v_out {b['v_out']:.9g}, rel diff {abs(a.v_out[0] - b['v_out']) / b['v_out']:.1e}")


if __name__ == "__main__":
    main()
