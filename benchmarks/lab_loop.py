"""The lab loop end to end: launches at several release heights on the designed block
(tests/fixtures/paper_full.yaml, the paper's surface, point model), each with a launch
scatter, simulated by an INDEPENDENT model (tests/lab_sim.py: eq. xyODE and the rolling
resistance written out by hand, scipy DOP853 at rtol 1e-12) with losses the spec does not
know (viscous 0.11 1/s and rolling resistance 0.0015), filmed at 125 frames/s with 0.3 mm
of Gaussian noise into ``t,x,y,sigma_x,sigma_y`` tracks, plus one release; then
``fabkit analyze`` on all of them at once. Compared with the truth:

* each launch's bounce count and outcome (exact), its bounce times (|error| / the stated
  sigma), v_in (|error| / its sigma);
* T_n of the two-bounce launches and eq. (tn)'s fit;
* the loss law and its coefficients (|error| / sigma, relative);
* the two-bounce windows in v_in: the fitted spec's simulator (fabkit's engine) against
  the independent model, both swept at 0.05 cm/s over the heights' speeds.

    python benchmarks/lab_loop.py [N_LAUNCHES] [--plot PNG]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))           # this tree's fabkit, not an installed one
sys.path.insert(0, str(ROOT / "tests"))

import lab_sim as L  # noqa: E402

PAPER = ROOT / "tests" / "fixtures" / "paper_full.yaml"
MU, CRR = 0.11, 0.0015
FPS, NOISE = 125.0, 0.03


def windows(v, nb, escaped):
    """The v_in intervals of two-bounce escapes: [(lo, hi)] of consecutive samples."""
    two = (nb == 2) & escaped
    out, start = [], None
    for i, flag in enumerate(two):
        if flag and start is None:
            start = i
        if (not flag or i == len(two) - 1) and start is not None:
            end = i if flag else i - 1
            out.append((float(v[start]), float(v[end])))
            start = None
    return out


def score_launch(r, v, truth):
    """One analysed launch ``r`` against its truth (entry speed ``v``, the independent model's
    run): the true bounce count (None when captured), the true outcome, whether the outcome and
    the count agree, each bounce time's |error| / stated sigma, and v_in's."""
    nb_true = len(truth["bounce_times"]) if truth["escaped"] else None
    out_true = "escaped" if truth["escaped"] else "captured"
    ok = r["outcome"] == out_true and (nb_true is None or r["bounces"] == nb_true)
    k = min(r["bounces"], len(truth["bounce_times"])) if truth["escaped"] else 0
    dts = [abs(a - b) / e for a, b, e in zip(r["bounce_times"][:k], truth["bounce_times"][:k],
                                               r["bounce_time_errors"][:k])]
    dv = abs(r["v_in"] - v) / r["v_in_error"] if r.get("v_in") is not None and r.get("v_in_error") else math.nan
    return nb_true, out_true, ok, dts, dv


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("n", nargs="?", type=int, default=8)
    ap.add_argument("--plot", default=None)
    args = ap.parse_args()
    from fabkit.lab.analyze import analyze
    from fabkit.lab.tracks import read_track
    from fabkit.physics.integrate import launch_batch
    from fabkit.physics.models import problem_from_spec
    from fabkit.spec import load_spec

    print(f"load average {os.getloadavg()[0]:.2f} (2 cores)")
    heights = np.linspace(0.85, 1.75, args.n)
    c0 = time.process_time()
    launches = L.scattered_launches(heights, MU, CRR, seed=5)
    rel = L.run((-27.5, 5.0, 0.0, 0.0), MU, 3.0, escape=False, crr=CRR)
    sim_cpu = time.process_time() - c0
    spec = load_spec(PAPER)
    problem = problem_from_spec(spec)
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i, (H, v, y0, vy0, truth) in enumerate(launches):
            p = Path(tmp) / f"launch_H{H:.3f}.csv"
            p.write_text(L.track_csv(truth, fps=FPS, noise=NOISE, seed=100 + i))
            paths.append(p)
        p = Path(tmp) / "release.csv"
        p.write_text(L.track_csv(rel, fps=FPS, noise=NOISE, seed=99, t_end=3.0))
        paths.append(p)
        tracks = [read_track(q, units="cm") for q in paths]
        c0 = time.process_time()
        res = analyze(problem, tracks)
        an_cpu = time.process_time() - c0
    rows = res["tracks"]
    print(f"independent simulation {sim_cpu:.1f} s CPU; analyze of {len(tracks)} tracks {an_cpu:.1f} s CPU")
    print(" H (cm)  v_in true  v_in fit (sigma)   bounces  outcome            |dt|/sigma max  dv/sigma")
    bad = 0
    zt, zv = [], []
    for (H, v, y0, vy0, truth), r in zip(launches, rows):
        nb_true, out_true, ok, dts, dv = score_launch(r, v, truth)
        zt += dts
        zv.append(dv)
        bad += not ok
        print(f" {H:6.3f}  {v:9.4f}  {r['v_in'] or math.nan:9.4f} ({r.get('v_in_error') or math.nan:.2g})  "
              f"{r['bounces']:2d} / {nb_true if nb_true is not None else '-':>2}  {r['outcome']:8s} / {out_true:8s}"
              f"  {max(dts) if dts else 0:6.2f}         {dv:5.2f}  {'ok' if ok else 'WRONG'}")
    print(f"bounce times: |error| / stated sigma median {np.median(zt):.2f}, max {max(zt):.2f} over {len(zt)}; "
          f"v_in: median {np.nanmedian(zv):.2f}, max {np.nanmax(zv):.2f} sigma")
    tn = res["tn_fit"]
    two = [(r, tr) for r, (_, _, _, _, tr) in zip(rows, launches) if r.get("T_n") is not None and tr["escaped"]
           and len(tr["bounce_times"]) == 2]
    for r, tr in two:
        true_T = tr["bounce_times"][1] - tr["bounce_times"][0]
        print(f"T_n {r['T_n']:.4f} s (n = {r['n']}) against {true_T:.4f} s: {r['T_n'] - true_T:+.4f} s")
    if tn:
        print(f"eq. (tn): T = {tn['T']:.4f} ± {tn.get('T_error', math.nan):.2g} s, delta = {tn['delta']:.4f} s")
    lo = res["losses"]
    law = lo["chosen"]
    f = lo["laws"][law]
    print(f"losses: {law} (evidence {lo['evidence']})")
    for kname, truth in (("damping", MU), ("rolling_resistance", CRR)):
        val, err = f["coefficients"][kname], f["errors"][kname]
        print(f"  {kname}: {val:.5g} ± {err:.2g}, truth {truth:g}: {val / truth - 1:+.2%}, "
              f"{abs(val - truth) / err:.1f} sigma")
    # the two-bounce windows: fitted spec (fabkit's engine) against the independent model
    vs = np.arange(L.speed_from_height(heights[0]) - 1, L.speed_from_height(heights[-1]) + 1, 0.05)
    p_fit = problem.with_(damping=f["coefficients"]["damping"], rolling_resistance=f["coefficients"]["rolling_resistance"])
    rb = launch_batch(p_fit, vs, np.zeros_like(vs), np.zeros_like(vs), workers=1)
    w_fit = windows(vs, np.asarray(rb.bounces), np.asarray(rb.outcome) == 0)
    c0 = time.process_time()
    tr = [L.run((L.START, 0.0, v, 0.0), MU, 15.0, crr=CRR) for v in vs]
    w_true = windows(vs, np.array([len(t["bounce_times"]) for t in tr]), np.array([t["escaped"] for t in tr]))
    print(f"two-bounce windows in v_in (cm/s, 0.05 steps; independent sweep {time.process_time() - c0:.0f} s CPU):")
    print(f"  fitted spec: {', '.join(f'{a:.2f}-{b:.2f}' for a, b in w_fit)}")
    print(f"  truth:       {', '.join(f'{a:.2f}-{b:.2f}' for a, b in w_true)}")
    ok = (bad == 0 and law == "both" and all(abs(f["coefficients"][k] - t) <= 3 * f["errors"][k]
                                              for k, t in (("damping", MU), ("rolling_resistance", CRR))))
    print("loop: " + ("ok" if ok else "FAILED"))
    if args.plot:
        _plot(args.plot, w_fit, w_true, launches, rows)
    return 0 if ok else 1


def _plot(path, w_fit, w_true, launches, rows):
    from fabkit.plots import new_figure, png_bytes

    plt, fig = new_figure(figsize=(7.5, 2.8), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    for a, b in w_true:
        ax.axvspan(a, b, ymin=0.55, ymax=0.95, color="tab:blue", alpha=0.35)
    for a, b in w_fit:
        ax.axvspan(a, b, ymin=0.05, ymax=0.45, color="tab:orange", alpha=0.35)
    for (H, v, _, _, truth), r in zip(launches, rows):
        ax.plot([v], [0.75], "o", color="black" if truth["escaped"] else "0.6")
        ax.plot([r["v_in"]], [0.25], "s", color="black" if r["outcome"] == "escaped" else "0.6")
        ax.annotate(str(r["bounces"]), (r["v_in"], 0.25), textcoords="offset points", xytext=(0, 6), ha="center")
    ax.set_yticks([0.25, 0.75], ["analyze / fitted spec", "independent truth"])
    ax.set_ylim(0, 1)
    ax.set_xlabel("v_in (cm/s)")
    ax.set_title("two-bounce windows (shaded) and the launches (bounces counted; grey: captured)", fontsize=9)
    fig.tight_layout()
    Path(path).write_bytes(png_bytes(plt, fig))


if __name__ == "__main__":
    sys.exit(main())
