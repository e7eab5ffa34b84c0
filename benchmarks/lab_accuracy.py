"""Accuracy of ``fabkit analyze`` against an independent simulation, over noise seeds;
and (``track``) of ``fabkit track`` on rendered videos with cast shadows.

Tracks come from tests/lab_sim.py (the paper's eq. xyODE written out by hand, scipy
DOP853 at rtol 1e-12), sampled at 125 frames/s with 0.3 mm of Gaussian noise. Releases:
the damping (0.08..0.25 1/s) and the amplitude (3..7 cm) vary with the seed; launches:
damping 0.15 1/s at four entry speeds (two-bounce and one-bounce). The analysis is told
neither damping (the spec says 0.127). Prints the worst relative errors.

    python benchmarks/lab_accuracy.py [SEEDS]
    python benchmarks/lab_accuracy.py track [CASE ...]

``track``: a matrix of hard conditions rendered by tests/video_render.py (cached in
benchmarks/.track_cache/): lamps at several places, soft (a disc 40-105 mm wide) and
hard (a point), one or two, 35-60 degrees up; tilt up to 15 degrees, k1 down to -0.1;
640x512 to 1920x1080; 60-250 frames/s with the exposure 1/125 s or half the frame
interval; H.264 and MPEG-4, noise 1.5-3 grey levels; a hand over the ball; a white ball
on white paint. Per case: the frames tracked, the centre's error against the renderer's
truth (rms and max, work mm, over the reported frames), the share of reported frames
with |error| <= 3 sigma on each axis, the frames the hand covers that were reported, and
the gaps by reason.
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


TRACK_CACHE = ROOT / "benchmarks" / ".track_cache"


def track_cases():
    import video_render as vr

    soft = lambda e, a, d=1800, r=60, p=0.7: vr.Lamp.at(e, a, d, r, p)   # noqa: E731
    return {
        "soft60": dict(w=640, h=512, H=1000, tilt=8, az=200, k1=-0.04, fps=125, lamps=[soft(60, 30, 2000, 105)]),
        "hard40": dict(w=640, h=512, H=1100, tilt=5, az=30, k1=0.02, fps=125, lamps=[soft(40, 150, 1800, 0)]),
        "two_low": dict(w=640, h=512, H=1200, tilt=10, az=100, k1=-0.06, fps=100, ambient=0.2,
                        lamps=[soft(35, 250, 1500, 60, 0.5), soft(45, 20, 1500, 0, 0.35)]),
        "tilt15_k1": dict(w=1280, h=1024, H=1300, tilt=15, az=250, k1=-0.1, fps=250, exposure=1.0,
                          lamps=[soft(38, 120, 1600, 0, 0.7)], n=50),
        "hd60_blur": dict(w=1920, h=1080, H=1500, tilt=6, az=160, k1=-0.03, fps=60, exposure=0.48, v=75.0,
                          lamps=[soft(45, 330, 900, 40, 0.6)], n=36),
        "mpeg4_noisy": dict(w=800, h=640, H=1100, tilt=12, az=45, k1=0.03, fps=90, codec="mpeg4", noise=3.0,
                            lamps=[soft(50, 200, 1700, 0, 0.75)]),
        "hand": dict(w=640, h=512, H=1000, tilt=8, az=200, k1=-0.04, fps=125, hand=True,
                     lamps=[soft(45, 300, 1600, 50, 0.7)]),
        "grey_ball_two_hard": dict(w=640, h=512, H=1150, tilt=14, az=300, k1=-0.09, fps=60, exposure=0.48, v=75.0,
                                   ambient=0.3, ball_grey=0.3, lamps=[soft(36, 200, 1400, 0, 0.45),
                                                                      soft(42, 340, 1400, 0, 0.4)]),
        "white_on_white": dict(w=640, h=512, H=1000, tilt=6, az=300, k1=0.0, fps=125, dark=False, albedo=1.0,
                               lamps=[soft(50, 60, 1600, 40, 0.65)]),
        "white_soft_top": dict(w=640, h=512, H=1000, tilt=4, az=10, k1=-0.02, fps=125, dark=False, albedo=1.0,
                               lamps=[soft(75, 100, 2000, 150, 0.6)]),
    }


def render_case(name, c):
    """Render one case (once: cached): the video, its spec, the truth (n, 3) work mm and the
    share of the ball the hand covers per frame."""
    import json

    import video_render as vr

    TRACK_CACHE.mkdir(exist_ok=True)
    video, spec, npz = (TRACK_CACHE / f"acc_{name}.{ext}" for ext in ("mp4", "yaml", "npz"))
    if not npz.exists():
        w, h = c["w"], c["h"]
        f = 0.85 * w * c["H"] / (vr.L + 60)
        cam = vr.Cam.looking_down(c["H"], c["tilt"], c["az"], f, c["k1"], w, h)
        rend = vr.Renderer(cam, vr.MARKERS, ball_dark=c.get("dark", True), albedo=c.get("albedo", 1.0),
                           lamps=c["lamps"], ambient=c.get("ambient", 0.25), ball_grey=c.get("ball_grey"))
        launch = vr.Launch(v_in=c.get("v", 60.0))
        times = np.arange(c.get("n", 60)) / c["fps"]
        hand = None
        if c.get("hand"):
            uv = cam.project(launch.centre(times + 0.25))
            rb = f * vr.RADIUS * vr.SCALE / c["H"]
            hand = {i: (uv[i, 0] + 1.6 * rb - 0.1 * rb * (i - 20), uv[i, 1] - 0.5 * rb, 1.5 * rb) for i in range(20, 40)}
        rep = {}
        times, truth = vr.render_video(video, rend, launch, times, t_offset=0.25, hand=hand, report=rep,
                                       noise=c.get("noise", 1.5), codec=c.get("codec", "libx264"),
                                       exposure=c.get("exposure", 0.5))
        spec.write_text(vr.SPEC_TEXT + f"lab:\n  markers: {json.dumps(vr.MARKERS)}\n  camera_height: {c['H'] + 8:g}\n")
        np.savez(npz, truth=truth, covered=rep["covered"])
    z = np.load(npz)
    return video, spec, z["truth"], z["covered"]


def track_errors(res, truth, covered):
    """The reported frames' errors against the truth (work mm) and what they say."""
    import video_render as vr

    X = (res.xy[:, 0] - vr.X_RANGE[0]) * vr.SCALE
    Y = (res.xy[:, 1] - vr.Y_RANGE[0]) * vr.SCALE
    ok = np.isfinite(X) & np.isfinite(truth[:, 0])
    ex, ey = X[ok] - truth[ok, 0], Y[ok] - truth[ok, 1]
    sx, sy = res.sigma[ok, 0] * vr.SCALE, res.sigma[ok, 1] * vr.SCALE
    e = np.hypot(ex, ey)
    within = (np.abs(ex) <= 3 * sx) & (np.abs(ey) <= 3 * sy)
    return {"frames": len(truth), "tracked": int(ok.sum()),
            "rms_mm": float(np.sqrt(np.mean(e * e))) if ok.any() else float("nan"),
            "max_mm": float(e.max()) if ok.any() else float("nan"),
            "within_3_sigma": float(within.mean()) if ok.any() else float("nan"),
            "z_max": float(np.max(np.maximum(np.abs(ex) / sx, np.abs(ey) / sy))) if ok.any() else float("nan"),
            "sigma_median_mm": float(np.median(np.hypot(sx, sy))) if ok.any() else float("nan"),
            "covered_frames": int((covered > 0.02).sum()), "covered_reported": int(((covered > 0.02) & ok).sum()),
            "z": np.r_[ex / sx, ey / sy]}


def track_main(names) -> None:
    import os
    import warnings

    from fabkit.errors import SpecError
    from fabkit.lab.track import track_video
    from fabkit.surface import Surface

    cases = track_cases()
    names = names or list(cases)
    load = os.getloadavg()
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    zs, worst = [], (0.0, 0.0)
    for name in names:
        video, spec_path, truth, covered = render_case(name, cases[name])
        spec = load_spec(spec_path)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            try:
                res = track_video(spec, Surface.from_spec(spec), video)
            except SpecError as exc:
                print(f"{name:15s} refused: {exc}")
                continue
        r = track_errors(res, truth, covered)
        zs.append(r["z"])
        worst = (max(worst[0], r["rms_mm"]), max(worst[1], r["max_mm"]))
        gaps = ", ".join(f"{k} {v}" for k, v in res.gaps().items() if v) or "none"
        print(f"{name:15s} {r['tracked']:3d}/{r['frames']:3d} tracked; error {r['rms_mm']:.3f} mm rms, "
              f"{r['max_mm']:.3f} max; |e| <= 3 sigma {100 * r['within_3_sigma']:.1f} % (max |e|/sigma "
              f"{r['z_max']:.2f}, sigma {r['sigma_median_mm']:.3f} mm); hand-covered frames reported "
              f"{r['covered_reported']}/{r['covered_frames']}; gaps: {gaps}", flush=True)
    z = np.concatenate(zs) if zs else np.array([np.nan])
    print(f"all: worst rms {worst[0]:.3f} mm, worst max {worst[1]:.3f} mm; |e|/sigma <= 3 on "
          f"{100 * np.mean(np.abs(z) <= 3):.2f} % of the {z.size} axis-frames, <= 1 on {100 * np.mean(np.abs(z) <= 1):.1f} %")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "track":
        track_main(sys.argv[2:])
    else:
        main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
