"""Accuracy of ``fabkit analyze`` against an independent simulation, over noise seeds.

Tracks come from tests/lab_sim.py (the paper's eq. xyODE written out by hand, scipy
DOP853 at rtol 1e-12), sampled at 125 frames/s with 0.3 mm of Gaussian noise. Releases:
the damping (0.08..0.25 1/s) and the amplitude (3..7 cm) vary with the seed; launches:
damping 0.15 1/s at four entry speeds (two-bounce and one-bounce). The analysis is told
neither damping (the spec says 0.127). Prints the worst relative errors.

    python benchmarks/lab_accuracy.py [SEEDS]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import lab_sim as L  # noqa: E402
from fabkit.lab import analyze as A  # noqa: E402
from fabkit.lab.tracks import Track  # noqa: E402
from fabkit.physics.models import problem_from_spec  # noqa: E402
from fabkit.spec import load_spec  # noqa: E402


def main(seeds: int = 5) -> None:
    prob = problem_from_spec(load_spec(ROOT / "specs" / "surface.yaml"))
    rng = np.random.default_rng(2026)
    worst = {k: 0.0 for k in ("damping", "omega", "bounce_frames", "v_in", "v_out", "logdec")}
    bounces_ok = bounces_n = 0
    t0 = time.perf_counter()
    for seed in range(seeds):
        mu, amp = rng.uniform(0.08, 0.25), rng.uniform(3.0, 7.0)
        rel = L.run((-28.0, amp, 0.0, 0.0), mu, 4.0, escape=False)
        t, x, y = L.frames(rel, seed=100 + seed)
        r = A.analyze_track(prob, Track("rel", t, x, y, "csv"))
        ext = L.transverse_extrema(rel, t[0], t[-1])
        om = np.pi * (ext.size - 1) / (ext[-1] - ext[0])
        worst["damping"] = max(worst["damping"], abs(r["damping"] / mu - 1))
        worst["omega"] = max(worst["omega"], abs(r["omega"] / om - 1))
        worst["logdec"] = max(worst["logdec"], abs(r["damping_logdec"] / mu - 1))
        print(f"release mu {mu:.4f} amp {amp:.2f}: fit {r['damping']:.4f} ± {r['damping_error']:.1e}, "
              f"logdec {r['damping_logdec']:.4f}, omega err {r['omega'] / om - 1:+.1e}", flush=True)
        for v in (40.0, 47.5, 49.5, 59.5):
            la = L.run((L.START, 0.0, v, 0.0), 0.15, 15.0)
            t, x, y = L.frames(la, seed=200 + 10 * seed + int(v))
            r = A.analyze_track(prob, Track("la", t, x, y, "csv"), 0.127)
            bt = np.asarray(la["bounce_times"])
            bounces_n += 1
            if r["bounces"] == bt.size:
                bounces_ok += 1
                worst["bounce_frames"] = max(worst["bounce_frames"],
                                             float(np.max(np.abs(np.asarray(r["bounce_times"]) - bt))) * 125)
            worst["v_in"] = max(worst["v_in"], abs(r["v_in"] / v - 1))
            worst["v_out"] = max(worst["v_out"], abs(r["v_out"] / la["v_out"] - 1))
    print(f"{seeds} seeds: bounces exact {bounces_ok}/{bounces_n}; worst: damping {worst['damping']:.2%}, "
          f"omega {worst['omega']:.1e} (relative), bounce time {worst['bounce_frames']:.2f} frames, v_in {worst['v_in']:.3%}, "
          f"v_out {worst['v_out']:.3%}; the paper's log-decrement off by up to {worst['logdec']:.1%}; "
          f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
