"""Coverage of the stated bounce-time errors: launches from five release heights x 12
scatter seeds (tests/lab_sim.py, the independent model; viscous 0.11 1/s and rolling
resistance 0.0015; 125 frames/s, 0.3 mm noise); every escaped launch whose bounces are
all found gives |bounce time - truth| / bounce_time_error. A Gaussian error with an
honest sigma has median 0.67 and 0.3 % beyond 3.

    python benchmarks/lab_bounce_errors.py
"""
import numpy as np, sys
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))          # this tree's fabkit
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import lab_sim as L
from fabkit.lab.events import extrema, _vertex_errors, noise_sigma
z = []
for seed in range(12):
    ls = L.scattered_launches([0.95, 1.1, 1.25, 1.4, 1.75], 0.11, 0.0015, seed=seed)
    for i, (H, v, y0, vy0, tr) in enumerate(ls):
        if not tr["escaped"]:
            continue
        t, x, y = L.frames(tr, fps=125.0, noise=0.03, seed=1000 * seed + i)
        s = max(noise_sigma(x), noise_sigma(y))
        bt, _, _ = extrema(t, x, s, +1)
        if len(bt) != len(tr["bounce_times"]):
            continue
        e = _vertex_errors(t, x, bt, s)
        z += list((bt - np.asarray(tr["bounce_times"])) / np.asarray(e))
z = np.abs(np.array(z))
print(len(z), "median", np.median(z), "frac>3", np.mean(z > 3), "max", z.max(), "p95", np.percentile(z, 95))
