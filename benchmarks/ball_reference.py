"""fabkit's ball model against an independent implementation (tests/ball_newton_euler.py:
3-D Newton-Euler in the angular velocity, the contact force solved from the rolling
constraint, scipy DOP853 at rtol 1e-11).

    python benchmarks/ball_reference.py [--n N] [--t-max T]

For the paper's surface (cm) and another formula in mm, both with a 2.5 cm ball:
* v_critical from fabkit's sweep (1e-6 relative); the independent implementation
  launched at v_critical (1 -/+ 1e-4) must agree on the bounce counts there;
* N launches spread over the range: outcome and bounce counts exact, v_out where both
  escape after two bounces (the relative difference reported; acceptance 1e-3).
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

MM_FORMULA = ("eta*(exp(a*x) - exp(b*x)) + c*y**2*(1 + 0.2*tanh(x/40)) + eps*y/cosh(d*x)",
              dict(a=0.0389, b=0.0306, eta=32.7, c=0.00764, eps=0.25, d=0.03))


def problems(t_max):
    from fabkit.expr import compile_surface
    from fabkit.physics.models import problem_from_spec
    from fabkit.spec import load_spec

    spec = load_spec(ROOT / "specs" / "surface.yaml")
    paper = problem_from_spec(spec.with_overrides({"simulation.model": "ball"})).with_(t_max=t_max)
    mm = paper.with_(fns=compile_surface(*MM_FORMULA), g=9806.65, units="mm", radius=12.5, start=-300.0,
                     x_range=(-440.0, 60.0), y_range=(-125.0, 125.0), top=50.0, margin=5.0,
                     damping=0.127, atol=1e-11)
    return {"paper (cm)": (paper, (16.7, 79.4)), "mm formula": (mm, (167.0, 794.0))}


def main(argv=None):
    from ball_newton_euler import NewtonEuler

    from fabkit.physics.integrate import launch_batch
    from fabkit.physics.models import OUTCOMES
    from fabkit.physics.sweep import sweep

    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--t-max", type=float, default=20.0)
    args = ap.parse_args(argv)
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
