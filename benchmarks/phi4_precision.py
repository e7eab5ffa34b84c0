"""Error against run time for the phi^4 collisions (docs/numerics.md, "phi^4").

    nice python benchmarks/phi4_precision.py [--quick]

For each grid spacing dx, step dt and absorbing layer, measures:
* v_out at three speeds: the centre of the first two-bounce window (0.1988), a
  three-bounce window (0.2236) and a one-bounce escape (0.27);
* v_critical by k-section (8 launches a round, 2 rounds from [0.2599, 0.2604]) with
  the default escape criterion (X back at X0 by t_max = 800);
and the wall time of each, and compares with the finest run (dx 1/8, dt 1/20).
Also the time per collision of a 64-launch batch against one launch at a time.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fabkit.waves.phi4 import DEFAULT_CONFIG, collide  # noqa: E402

SPEEDS = np.array([0.1988, 0.2236, 0.27])


def v_critical(cfg, lo=0.2599, hi=0.2604, k=8, rounds=2):
    for _ in range(rounds):
        p = lo + (hi - lo) * np.arange(1, k + 1) / (k + 1)
        r = collide(p, cfg, stop_after=2)
        bad = np.flatnonzero(~r.one_bounce)
        if len(bad):
            j = int(bad[-1])
            lo, hi = float(p[j]), (float(p[j + 1]) if j + 1 < k else hi)
        else:
            hi = float(p[0])
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    a = ap.parse_args()
    cases = [("dx 1/2, dt 1/5", dict(dx=0.5, dt=0.2)), ("dx 1/2, dt 1/10", dict(dx=0.5, dt=0.1)),
             ("dx 1/4, dt 1/5", dict(dx=0.25, dt=0.2)), ("dx 1/4, dt 1/10 (default)", dict()),
             ("dx 1/4, dt 1/20", dict(dx=0.25, dt=0.05)), ("dx 1/8, dt 1/10", dict(dx=0.125, dt=0.1)),
             ("default, layer 40", dict(layer=40.0)), ("default, gap 20", dict(gap=20.0)),
             ("default, sigma 0.5", dict(sigma=0.5)),
             ("dx 1/8, dt 1/20 (reference)", dict(dx=0.125, dt=0.05))]
    if a.quick:
        cases = cases[:4]
    rows = []
    for name, kw in cases:
        cfg = DEFAULT_CONFIG.with_(**kw)
        t0 = time.perf_counter()
        r = collide(SPEEDS, cfg)
        t1 = time.perf_counter()
        vc, vc_err = v_critical(cfg)
        t2 = time.perf_counter()
        rows.append((name, r.bounces.tolist(), r.v_out, t1 - t0, vc, vc_err, t2 - t1))
        print(f"{name:30s} bounces {r.bounces.tolist()} v_out {np.round(r.v_out, 7).tolist()} "
              f"{t1 - t0:6.1f} s   v_c {vc:.6f} ± {vc_err:.1e} {t2 - t1:6.1f} s", flush=True)
    ref = rows[-1]
    print("\n| run | v_out error (0.1988 / 0.2236 / 0.27) | time, 3 collisions | v_critical | "
          "its change from the reference | time, 16 collisions |")
    print("|---|---|---|---|---|---|")
    for name, b, vo, t_a, vc, vc_err, t_b in rows:
        err = " / ".join(f"{abs(x - y):.1e}" for x, y in zip(vo, ref[2]))
        print(f"| {name} | {err} | {t_a:.1f} s | {vc:.6f} ± {vc_err:.0e} | {vc - ref[4]:+.1e} | {t_b:.1f} s |")
    # batching: 64 launches on one grid against one at a time (same run, same machine load)
    cfg = DEFAULT_CONFIG.with_(t_max=200.0)
    v = np.linspace(0.2, 0.3, 64)
    t0 = time.perf_counter()
    collide(v, cfg)
    tb = (time.perf_counter() - t0) / len(v)
    t0 = time.perf_counter()
    for x in v[::8]:
        collide([x], cfg)
    ts = (time.perf_counter() - t0) / len(v[::8])
    print(f"\nbatch of 64 (t_max 200): {1e3 * tb:.0f} ms a collision; one at a time: {1e3 * ts:.0f} ms "
          f"({ts / tb:.1f}x)")


if __name__ == "__main__":
    main()
