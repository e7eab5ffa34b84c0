"""The lab loop end to end WITH THE VIDEO STEP: launches at several release heights on the
paper's block, each with a launch scatter (speed, entry y and vy), and one release from
rest, simulated by an INDEPENDENT model (tests/lab_sim.py: eq. xyODE and rolling
resistance written out by hand, scipy DOP853 at rtol 1e-12) with losses the spec does not
know (viscous 0.11 1/s and rolling resistance 0.0015); each run RENDERED by
tests/video_render.py (its own ray caster, surface and camera: nothing of fabkit) at
640x512 with a lamp's cast shadow, uneven light, motion blur, sensor noise and H.264;
then ``fabkit track``'s pipeline (``track_video``) on each video, its ``t,x,y,sigma_x,
sigma_y`` tracks read back like the files the command writes, and ``fabkit analyze``'s
(``analyze``) on all of them at once. Compared with the truth:

* tracking: the ball centre's error per reported frame (mm rms, max) and |error| / sigma;
* each launch's bounce count and outcome (exact), bounce times, v_in and v_out
  (|error| / the stated sigma);
* T_n of a two-bounce launch; the loss law and its coefficients (|error| / sigma);
* the two-bounce windows in v_in: the fitted spec's simulator (fabkit's engine) against
  the independent model, both swept at 0.05 cm/s.

``fabkit track`` reports the ball's centre seen from above; the point models (this spec's
``model: full``) fit a track as the contact point's path. ``--contact`` maps each tracked
centre to the contact point under it (fabkit's ``contact_of``) before the analysis; without
it the loop measures what ``fabkit analyze`` does with the command's file as written.

    nice python benchmarks/lab_loop_video.py [N_LAUNCHES] [--fps 100] [--keep DIR] [--contact]

Videos are rendered into a temporary directory (``--keep DIR``: kept there).
"""

from __future__ import annotations

import argparse
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
sys.path.insert(0, str(ROOT / "benchmarks"))

import lab_sim as L  # noqa: E402
from lab_loop import score_launch  # noqa: E402

MU, CRR = 0.11, 0.0015
CAPTURED_FILM_S = 6.0        # a captured launch is filmed this long (it never leaves)
W, H_PX, CAM_H = 640, 512, 1000.0


def render(path: Path, truth: dict, t_end: float, fps: float, seed: int):
    """One run on video (a lamp 55 degrees up, 80 mm wide: a soft cast shadow); returns the
    spec path, the frames' times and the true centres (n, 3) work mm."""
    import json

    import video_render as vr

    f = 0.85 * W * CAM_H / (vr.L + 60)
    cam = vr.Cam.looking_down(CAM_H, 8.0, 200.0, f, -0.04, W, H_PX)
    rend = vr.Renderer(cam, vr.MARKERS, lamps=[vr.Lamp.at(55, 40, 1800, 80, 0.7)], ambient=0.25)
    times = np.arange(0.0, t_end, 1.0 / fps)
    spec = path.with_suffix(".yaml")
    if path.exists() and spec.exists():      # kept from an earlier run (--keep): the same frames
        times = np.round(times * 90000) / 90000
        return spec, times, vr.Trajectory(truth).centre(times)
    times, centres = vr.render_video(path, rend, vr.Trajectory(truth), times, noise=1.5, seed=seed,
                                     exposure=0.5)
    spec.write_text(vr.SPEC_TEXT + f"lab:\n  markers: {json.dumps(vr.MARKERS)}\n  camera_height: {CAM_H + 8:g}\n")
    return spec, times, centres


def to_contact(problem, res):
    """The track's centres (X, Y) mapped to the contact points under them (fabkit's
    ``contact_of``: the point models' state is the contact point, a camera sees the
    centre); each sigma carried through the map's diagonal derivative."""
    import dataclasses

    from fabkit.lab.fitting import contact_of

    ok = np.isfinite(res.xy).all(axis=1)
    X, Y = res.xy[ok, 0], res.xy[ok, 1]
    x, y = contact_of(problem, X, Y)
    h = 1e-4
    dxx = (contact_of(problem, X + h, Y)[0] - contact_of(problem, X - h, Y)[0]) / (2 * h)
    dyy = (contact_of(problem, X, Y + h)[1] - contact_of(problem, X, Y - h)[1]) / (2 * h)
    xy, sig = res.xy.copy(), res.sigma.copy()
    xy[ok] = np.c_[x, y]
    sig[ok] = np.c_[res.sigma[ok, 0] * np.abs(dxx), res.sigma[ok, 1] * np.abs(dyy)]
    return dataclasses.replace(res, xy=xy, sigma=sig)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("n", nargs="?", type=int, default=4)
    ap.add_argument("--fps", type=float, default=100.0)
    ap.add_argument("--keep", default=None)
    ap.add_argument("--contact", action="store_true",
                    help="map each tracked centre to its contact point before analyze")
    args = ap.parse_args()
    from fabkit.lab.analyze import analyze
    from fabkit.lab.track import track_video
    from fabkit.lab.tracks import read_track
    from fabkit.physics.models import problem_from_spec
    from fabkit.spec import load_spec
    from fabkit.surface import Surface
    from lab_accuracy import track_errors

    load0 = os.getloadavg()
    print(f"load average {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f} (2 cores)", flush=True)
    heights = np.linspace(0.85, 1.75, args.n)
    launches = L.scattered_launches(heights, MU, CRR, seed=5)
    rel = L.run((-27.5, 5.0, 0.0, 0.0), MU, 3.0, escape=False, crr=CRR)
    runs = [(f"launch_H{H:.3f}", tr, tr["t_end"] if tr["escaped"] else CAPTURED_FILM_S)
            for H, _, _, _, tr in launches] + [("release", rel, 3.0)]
    tmpdir = tempfile.TemporaryDirectory()
    out_dir = Path(args.keep) if args.keep else Path(tmpdir.name)
    out_dir.mkdir(parents=True, exist_ok=True)
    cpu_render = cpu_track = 0.0
    tracks, zs, worst = [], [], (0.0, 0.0)
    print(" run              frames  tracked  error rms / max (mm)  |e|<=3 sigma  gaps")
    for i, (name, truth, t_end) in enumerate(runs):
        video = out_dir / f"{name}.mp4"
        c0 = time.process_time()
        spec_path, _, centres = render(video, truth, t_end, args.fps, seed=40 + i)
        cpu_render += time.process_time() - c0
        spec = load_spec(spec_path)
        c0 = time.process_time()
        res = track_video(spec, Surface.from_spec(spec), video)
        cpu_track += time.process_time() - c0
        e = track_errors(res, centres, np.zeros(len(centres)))
        zs.append(e["z"])
        worst = (max(worst[0], e["rms_mm"]), max(worst[1], e["max_mm"]))
        gaps = ", ".join(f"{k} {v}" for k, v in res.gaps().items() if v) or "none"
        print(f" {name:15s}  {e['frames']:5d}  {e['tracked']:6d}   {e['rms_mm']:.3f} / {e['max_mm']:.3f}"
              f"          {100 * e['within_3_sigma']:5.1f} %     {gaps}", flush=True)
        csv = out_dir / f"{name}{'_contact' if args.contact else ''}.csv"
        if args.contact:
            res = to_contact(problem_from_spec(spec), res)
        csv.write_text(res.csv_text())
        tracks.append(read_track(csv, units="cm"))
    problem = problem_from_spec(load_spec(spec_path))
    c0 = time.process_time()
    res = analyze(problem, tracks)
    cpu_an = time.process_time() - c0
    z = np.concatenate(zs)
    print(f"tracking: worst rms {worst[0]:.3f} mm, worst max {worst[1]:.3f} mm; |e|/sigma <= 3 on "
          f"{100 * np.mean(np.abs(z) <= 3):.2f} % of {z.size} axis-frames")
    print(f"CPU: render {cpu_render:.0f} s, track {cpu_track:.0f} s, analyze {cpu_an:.1f} s")
    rows = res["tracks"]
    print(" H (cm)  bounces  outcome            v_in true / found (sigma) dv/s   v_out true / found (sigma) dv/s"
          "   bounce |dt|/sigma max")
    bad, zt, zv = 0, [], []
    for (H, v, y0, vy0, truth), r in zip(launches, rows):
        nb_true, out_true, ok, dts, dv = score_launch(r, v, truth)
        vo_t, vo = truth.get("v_out"), r.get("v_out")
        dvo = abs(vo - vo_t) / r["v_out_error"] if vo is not None and vo_t is not None and r.get("v_out_error") \
            else math.nan
        zt += dts
        zv += [dv, dvo]
        ok = ok and not (dv > 3) and not (dvo > 3)
        bad += not ok
        nb_s = f"{nb_true}" if nb_true is not None else "-"
        print(f" {H:6.3f}  {r['bounces']:2d} / {nb_s:>2}  {r['outcome'] or '-':8s} / {out_true:8s}  "
              f"{v:7.3f} / {r.get('v_in') or math.nan:7.3f} ({r.get('v_in_error') or math.nan:.2g}) {dv:4.1f}   "
              f"{vo_t or math.nan:7.3f} / {vo or math.nan:7.3f} ({r.get('v_out_error') or math.nan:.2g}) {dvo:4.1f}"
              f"   {max(dts) if dts else 0:5.2f}  {'ok' if ok else 'WRONG'}")
    if zt:
        print(f"bounce times: |error| / stated sigma median {np.median(zt):.2f}, max {max(zt):.2f} over {len(zt)}")
    for r, (_, _, _, _, tr) in zip(rows, launches):
        if r.get("T_n") is not None and tr["escaped"] and len(tr["bounce_times"]) == 2:
            true_T = tr["bounce_times"][1] - tr["bounce_times"][0]
            print(f"T_n {r['T_n']:.4f} s (n = {r['n']}) against {true_T:.4f} s: {r['T_n'] - true_T:+.4f} s")
    lo = res["losses"]
    law_ok = False
    if lo and lo.get("chosen"):
        law = lo["chosen"]
        f = lo["laws"][law]
        print(f"losses: {law} (evidence {lo['evidence']})")
        law_ok = True
        for kname, truth in (("damping", MU), ("rolling_resistance", CRR)):
            val, err = f["coefficients"].get(kname), f["errors"].get(kname)
            if val is None:
                print(f"  {kname}: not in this law (truth {truth:g})")
                law_ok = False
                continue
            zk = abs(val - truth) / err if err else math.inf
            law_ok = law_ok and zk <= 3
            print(f"  {kname}: {val:.5g} ± {err:.2g}, truth {truth:g}: {val / truth - 1:+.2%}, {zk:.1f} sigma")
        # the two-bounce windows: the fitted spec (fabkit's engine) against the independent model
        from fabkit.physics.integrate import launch_batch
        from lab_loop import windows

        vs = np.arange(L.speed_from_height(heights[0]) - 1, L.speed_from_height(heights[-1]) + 1, 0.05)
        p_fit = problem.with_(damping=f["coefficients"]["damping"],
                              rolling_resistance=f["coefficients"].get("rolling_resistance", 0.0))
        rb = launch_batch(p_fit, vs, np.zeros_like(vs), np.zeros_like(vs), workers=1)
        w_fit = windows(vs, np.asarray(rb.bounces), np.asarray(rb.outcome) == 0)
        c0 = time.process_time()
        tw = [L.run((L.START, 0.0, v, 0.0), MU, 15.0, crr=CRR) for v in vs]
        w_true = windows(vs, np.array([len(t["bounce_times"]) for t in tw]), np.array([t["escaped"] for t in tw]))
        edges = [abs(a - b) for (a1, b1), (a2, b2) in zip(w_fit, w_true) for a, b in ((a1, a2), (b1, b2))]
        print(f"two-bounce windows in v_in (cm/s, 0.05 steps; independent sweep {time.process_time() - c0:.0f} s CPU):")
        print(f"  fitted spec: {', '.join(f'{a:.2f}-{b:.2f}' for a, b in w_fit)}")
        print(f"  truth:       {', '.join(f'{a:.2f}-{b:.2f}' for a, b in w_true)}")
        win_ok = len(w_fit) == len(w_true) and max(edges, default=0.0) <= 0.05 + 1e-9
        print(f"  windows: {'every edge within one step' if win_ok else 'DIFFER'}"
              + (f" (largest edge difference {max(edges):.2f} cm/s)" if edges else ""))
        law_ok = law_ok and win_ok
    else:
        print(f"losses: none chosen ({lo})")
    for r in rows:
        if r.get("kind") == "release" or r["file"].endswith("release.csv"):
            if r.get("damping") is not None:
                print(f"release alone (viscous law): damping {r['damping']:.5g} ± {r.get('damping_error') or math.nan:.2g}")
    load1 = os.getloadavg()
    print(f"load average at the end {load1[0]:.2f} {load1[1]:.2f} {load1[2]:.2f}")
    ok = bad == 0 and law_ok
    print("loop with video: " + ("ok" if ok else "FAILED"))
    tmpdir.cleanup()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
