"""Frames per second of ``fabkit track`` on a 1280x1024 video at 125 frames/s.

    python benchmarks/bench_track.py [SECONDS]      # default 4 s of video (500 frames)

Renders the paper's block and a launch with tests/video_render.py (once, cached in
benchmarks/.track_cache/), then times, in this process, best of 3:

* the floor: PyAV decoding every frame to grey (fabkit.lab.video.frames), nothing else;
* the whole of track_video (sample, markers, calibration, background, the ball in every
  frame, the rays to the offset surface), the imports excluded (they are paid once per
  run: timed separately, in a fresh interpreter).

Target (issue 24): at least 125 frames/s (real time). Prints the load average: the
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


def make_video(seconds: float) -> tuple[Path, Path]:
    import video_render as vr

    CACHE.mkdir(exist_ok=True)
    video = CACHE / f"paper_1280x1024_{seconds:g}s.mp4"
    spec = CACHE / "paper.yaml"
    spec.write_text(vr.SPEC_TEXT + f"lab:\n  markers: {vr.MARKERS}\n  camera_height: 1400\n")
    if not video.exists():
        H = 1400.0
        cam = vr.Cam.looking_down(H, 7.0, 30.0, 0.85 * 1280 * H / (vr.L + 60), 0.03, 1280, 1024)
        t0 = time.perf_counter()
        rend = vr.Renderer(cam, vr.MARKERS)
        launch = vr.Launch(v_in=60.0)
        n = int(round(seconds * 125))
        vr.render_video(video, rend, launch, np.arange(n) / 125.0)
        print(f"rendered {n} frames in {time.perf_counter() - t0:.0f} s -> {video}")
    return spec, video


def import_seconds() -> float:
    code = ("import time; t = time.perf_counter(); import av, cv2, scipy.optimize, fabkit.lab.track, "
            "fabkit.surface, fabkit.spec; print(time.perf_counter() - t)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip())


def main() -> None:
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 4.0
    spec_path, video = make_video(seconds)
    from fabkit.lab import video as vid
    from fabkit.lab.track import track_video
    from fabkit.spec import load_spec
    from fabkit.surface import Surface

    spec = load_spec(spec_path)
    surface = Surface.from_spec(spec)
    n = sum(1 for _ in vid.frames(video))
    floor, full = [], []
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in vid.frames(video):
            pass
        floor.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        res = track_video(spec, surface, video)
        full.append(time.perf_counter() - t0)
    imp = import_seconds()
    load = os.getloadavg()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    print(f"video: {video.name}, {n} frames 1280x1024, H.264")
    print(f"decode only (the floor): {n / min(floor):.0f} frames/s")
    print(f"fabkit track (one video, imports excluded): {n / min(full):.0f} frames/s "
          f"({min(full):.2f} s; {100 * res.fraction:.1f} % tracked; target 125)")
    print(f"imports (once per run): {imp:.2f} s; with them: {n / (min(full) + imp):.0f} frames/s")


if __name__ == "__main__":
    main()
