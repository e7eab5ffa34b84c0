"""Frames per second of ``fabkit track`` on a 1280x1024 video at 125 frames/s.

    python benchmarks/bench_track.py [SECONDS] [--both]   # default 2 s of video (250 frames)

H.264 with a key frame every 25 frames (as phones and cameras write them: the sample is
read from the key frames, each frame decoded once); with ``--both`` also x264's default
(a key frame every 250: too few, so the sample costs a second decode).
The ball's run ends at 2.55 s; the frames after it have no ball.

Renders the paper's block, lit by a lamp 45 degrees up (a soft cast shadow), and a launch
with tests/video_render.py (once, cached in
benchmarks/.track_cache/), then times, in this process, best of 5:

* the floor: PyAV decoding every frame to grey (fabkit.lab.video.frames), nothing else;
* the whole of track_video (sample, markers, calibration, background, the ball in every
  frame, the rays to the offset surface), the imports excluded (they are paid once per
  run: timed separately, in a fresh interpreter).

Target (issue 35): at least 250 frames/s. Prints the load average: the
machine is shared, and a busy one reads slower.
"""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
CACHE = ROOT / "benchmarks" / ".track_cache"


H_MM = 1400.0


def _lamps():
    import video_render as vr

    return [vr.Lamp.at(45.0, 210.0, 1800.0, radius=60.0, power=0.7)]   # a soft shadow, 45 degrees up


LAMPS = None


def make_video(seconds: float, gop) -> tuple[Path, Path]:
    import video_render as vr

    global LAMPS
    LAMPS = _lamps()
    CACHE.mkdir(exist_ok=True)
    video = CACHE / f"paper_1280x1024_lamp_{seconds:g}s{'' if gop is None else f'_gop{gop}'}.mp4"
    spec = CACHE / "paper.yaml"
    spec.write_text(vr.SPEC_TEXT + f"lab:\n  markers: {vr.MARKERS}\n  camera_height: {H_MM + 8:g}\n")
    if not video.exists():
        cam = vr.Cam.looking_down(H_MM, 7.0, 30.0, 0.85 * 1280 * H_MM / (vr.L + 60), 0.03, 1280, 1024)
        t0 = time.perf_counter()
        rend = vr.Renderer(cam, vr.MARKERS, lamps=LAMPS, ambient=0.25)
        n = int(round(seconds * 125))
        vr.render_video(video, rend, vr.Launch(v_in=60.0), np.arange(n) / 125.0, gop=gop)
        print(f"rendered {n} frames in {time.perf_counter() - t0:.0f} s -> {video}")
    return spec, video


def accuracy(res) -> str:
    """The centre's error against the launch (work mm) over the frames with the ball."""
    import video_render as vr

    truth = vr.Launch(v_in=60.0).centre(res.t)
    seen = np.all(np.isfinite(truth), axis=1)
    ok = seen & np.all(np.isfinite(res.xy), axis=1)
    X = (res.xy[ok, 0] - vr.X_RANGE[0]) * vr.SCALE
    Y = (res.xy[ok, 1] - vr.Y_RANGE[0]) * vr.SCALE
    e = np.hypot(X - truth[ok, 0], Y - truth[ok, 1])
    return (f"{ok.sum()} of {seen.sum()} frames with the ball tracked, {(~seen & np.all(np.isfinite(res.xy), axis=1)).sum()} "
            f"found without one; centre error {np.sqrt(np.mean(e * e)):.3f} mm rms, {e.max():.3f} mm max")


def import_seconds() -> float:
    code = ("import time; t = time.perf_counter(); import av, cv2, scipy.optimize, fabkit.lab.track, "
            "fabkit.surface, fabkit.spec; print(time.perf_counter() - t)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


def main() -> None:
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    seconds = float(args[0]) if args else 2.0
    from fabkit.lab import video as vid
    from fabkit.lab.track import track_video
    from fabkit.spec import load_spec
    from fabkit.surface import Surface

    load = os.getloadavg()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (before)")
    gops = (25, None) if "--both" in sys.argv else (25,)
    for gop in gops:
        spec_path, video = make_video(seconds, gop)
        spec = load_spec(spec_path)
        surface = Surface.from_spec(spec)
        n = sum(1 for _ in vid.frames(video))
        floor, full = [], []
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in vid.frames(video):
                pass
            floor.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            res = track_video(spec, surface, video)
            full.append(time.perf_counter() - t0)
        print(f"video: {video.name}, {n} frames 1280x1024 at 125 frames/s, H.264, key frame every "
              f"{gop or 250} frames")
        print(f"  decode only (the floor): {n / min(floor):.0f} frames/s")
        print(f"  fabkit track (imports excluded): {n / min(full):.0f} frames/s ({min(full):.2f} s; target 250); "
              f"{min(full) / min(floor):.2f} x the decoding's time")
        print(f"  {accuracy(res)}; markers {res.calibration.rms_px:.2f} px rms, camera "
              f"{res.calibration.camera.centre[2]:.1f} mm up (true {H_MM:g}, given {H_MM + 8:g})")
    imp = import_seconds()
    load = os.getloadavg()
    print(f"imports (once per run, a fresh interpreter): {imp:.2f} s")
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (after)")


if __name__ == "__main__":
    main()
