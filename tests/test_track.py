"""fabkit track and fabkit markers, on videos rendered here (tests/video_render.py).

The truth is independent of fabkit: the ball's path is tests/lab_sim.py's launch
(scipy DOP853 on the paper's eq. (xyODE), hand-written surface), its centre put on
C = P + r n; the renderer's camera, ray casting and marker texture are its own. The
acceptance of issue 24: >= 98 % of the frames where the ball is in view tracked, the
centre within 0.5 mm rms and 2 mm max (work mm), timestamps within 0.1 ms, with the
camera 1.0-1.6 m up, tilted up to 10 degrees, |k1| <= 0.05 and lab.camera_height
off by 10 mm, one video at a variable frame rate, both encoded lossily.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import video_render as vr
from fabkit.cli import main

W_IMG, H_IMG = 640, 512
N_FRAMES = 90
HIDDEN = (50, 51, 52)            # frames where the ball is taken out of view: gaps


def _spec(tmp_path, camera_height=None, markers=True, name="paper"):
    text = vr.SPEC_TEXT.replace("name: paper", f"name: {name}")
    if markers or camera_height is not None:
        text += "lab:\n"
        if markers:
            text += f"  markers: {json.dumps(vr.MARKERS)}\n"
        if camera_height is not None:
            text += f"  camera_height: {camera_height}\n"
    p = tmp_path / f"{name}.yaml"
    p.write_text(text)
    return p


def _camera(height, tilt, azimuth, k1, w=W_IMG, h=H_IMG):
    f = 0.85 * w * height / (vr.L + 60)            # the block fills most of the frame
    return vr.Cam.looking_down(height, tilt, azimuth, f, k1, w, h)


def _work(xy):
    """Design (cm) -> work mm, written out (the block's corner at x = -44, y = -12.5)."""
    return np.stack([(xy[:, 0] - vr.X_RANGE[0]) * vr.SCALE, (xy[:, 1] - vr.Y_RANGE[0]) * vr.SCALE], axis=1)


@pytest.fixture(scope="module")
def dark(tmp_path_factory):
    """1.0 m up, tilted 10 degrees, k1 = +0.05, H.264 at 125 frames/s, a dark ball,
    camera_height given 10 mm high; three frames without the ball."""
    d = tmp_path_factory.mktemp("dark")
    rend = vr.Renderer(_camera(1000.0, 10.0, 200.0, 0.05), vr.MARKERS, ball_dark=True)
    times, truth = vr.render_video(d / "dark.mp4", rend, vr.Launch(v_in=60.0), np.arange(N_FRAMES) / 125.0,
                                   t_offset=0.25, hide=HIDDEN)
    return {"dir": d, "video": d / "dark.mp4", "spec": _spec(d, camera_height=1010), "times": times,
            "truth": truth, "renderer": rend}


@pytest.fixture(scope="module")
def light(tmp_path_factory):
    """1.6 m up, tilted 4 degrees, k1 = -0.05, MPEG-4 at a variable frame rate (6-11 ms
    between frames), a white ball on a grey block, camera_height given 10 mm low."""
    d = tmp_path_factory.mktemp("light")
    rend = vr.Renderer(_camera(1600.0, 4.0, 60.0, -0.05), vr.MARKERS, ball_dark=False, albedo=0.5)
    rng = np.random.default_rng(1)
    times = np.cumsum(np.r_[0.0, rng.uniform(0.006, 0.011, N_FRAMES - 1)])
    times, truth = vr.render_video(d / "light.mp4", rend, vr.Launch(v_in=75.0), times, codec="mpeg4",
                                   t_offset=0.3)
    return {"dir": d, "video": d / "light.mp4", "spec": _spec(d, camera_height=1590), "times": times,
            "truth": truth}


def _track(case, tmp_path, *extra):
    out = tmp_path / "out.track.csv"
    code = main(["track", str(case["spec"]), str(case["video"]), "-o", str(out), "--json", "--no-progress",
                 *extra])
    assert code == 0
    return out


def _read(out):
    rows = out.read_text().splitlines()
    assert rows[0] == "t,x,y,sigma_x,sigma_y"
    t = np.array([float(r.split(",")[0]) for r in rows[1:]])
    vals = np.array([[float(c) if c else np.nan for c in r.split(",")[1:]] for r in rows[1:]])
    return t, vals[:, :2], vals[:, 2:]


def _acceptance(case, t, xy, visible):
    assert np.max(np.abs(t - case["times"])) < 1e-4           # 0.1 ms
    tracked = np.all(np.isfinite(xy), axis=1)
    assert tracked[visible].mean() >= 0.98
    e = np.hypot(*(_work(xy[visible & tracked]) - case["truth"][visible & tracked, :2]).T)
    assert math.sqrt(np.mean(e * e)) <= 0.5 and e.max() <= 2.0, (math.sqrt(np.mean(e * e)), e.max())
    return e


def test_dark_ball_h264(dark, tmp_path, capsys):
    out = _track(dark, tmp_path)
    payload = json.loads(capsys.readouterr().out)
    t, xy, sig = _read(out)
    visible = np.ones(N_FRAMES, bool)
    visible[list(HIDDEN)] = False
    e = _acceptance(dark, t, xy, visible)
    assert np.all(np.isnan(xy[list(HIDDEN)]))                  # a hidden ball is a gap, not a guess
    rec = payload["tracks"][0]
    assert rec["frames"] == N_FRAMES and rec["tracked"] == N_FRAMES - len(HIDDEN)
    assert rec["reprojection_rms_px"] < 0.5 and rec["reprojection_rms_mm"] < 0.6
    assert abs(rec["camera"]["height_mm"] - 1000.0) < 15.0
    # the stated 1-sigma is the right order: the errors' rms within a factor of 10 of it
    s = np.hypot(sig[np.isfinite(sig[:, 0]), 0], sig[np.isfinite(sig[:, 0]), 1]) * vr.SCALE
    assert 0.1 < math.sqrt(np.mean(e * e)) / np.median(s) < 10


def test_light_ball_variable_rate_mpeg4(light, tmp_path, capsys):
    out = _track(light, tmp_path)
    payload = json.loads(capsys.readouterr().out)
    t, xy, _ = _read(out)
    _acceptance(light, t, xy, np.ones(N_FRAMES, bool))
    assert payload["tracks"][0]["variable_frame_rate"] is True


def test_analyze_reads_the_track(dark, tmp_path):
    """The track file is what `fabkit analyze` reads; its gaps are skipped rows."""
    from fabkit.lab.tracks import read_track

    out = _track(dark, tmp_path, "--plot", str(tmp_path / "frame.png"))
    tr = read_track(out)
    assert len(tr) == N_FRAMES - len(HIDDEN) and tr.skipped_rows == len(HIDDEN)
    assert (tmp_path / "frame.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_analyze_counts_the_true_bounces(tmp_path, capsys):
    """A whole launch, entry to escape, rendered at 50 frames/s and tracked: analyze
    counts the launch's own bounces (lab_sim's vx zero crossings)."""
    launch = vr.Launch(v_in=60.0)
    rend = vr.Renderer(_camera(1300.0, 6.0, 300.0, 0.02, 480, 384), vr.MARKERS)
    t_end = launch.truth["t_end"]
    times, _ = vr.render_video(tmp_path / "launch.mp4", rend, launch, np.arange(0.0, t_end, 0.02))
    spec = _spec(tmp_path, camera_height=1305)
    out = tmp_path / "launch.track.csv"
    assert main(["track", str(spec), str(tmp_path / "launch.mp4"), "-o", str(out), "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["analyze", str(spec), str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["tracks"][0]["bounces"] == len(launch.truth["bounce_times"]) >= 1


# ---------------------------------------------------------------------------- geometry, exactly
def test_ray_meets_offset_plane_exactly():
    """On an inclined plane h = a x + b y + c the offset surface is the plane moved r along
    its unit normal: the ray's parameter is closed form."""
    from fabkit.spec import validate
    from fabkit.surface import Surface
    from fabkit.lab.camera import ray_offset_surface

    spec = validate({"units": "mm", "surface": {"height": "0.3*x - 0.2*y - 40", "x": [0, 300], "y": [0, 200],
                                                "top": 500}}, "<t>")      # never clipped here
    s = Surface.from_spec(spec)
    r = 12.7
    rng = np.random.default_rng(3)
    O = np.array([150.0, 100.0, 1400.0])
    target = np.c_[rng.uniform(80, 220, 20), rng.uniform(60, 140, 20), np.zeros(20)]
    d = target - O
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    C, P = ray_offset_surface(s, r, O, d)
    nrm = np.array([-0.3, 0.2, 1.0]) / math.sqrt(1.13)
    # plane: nrm . X = nrm . (0, 0, -40) ; offset: + r
    k = (nrm @ np.array([0, 0, -40.0]) + r - nrm @ O) / (d @ nrm)
    exact = O + k[:, None] * d
    assert np.max(np.abs(C - exact)) < 1e-7
    assert np.max(np.abs(P - (exact[:, :2] - r * nrm[:2]))) < 1e-7


def test_calibration_recovers_the_camera():
    """Noiseless corners from the renderer's own camera: f, k1 and the camera's centre back
    to 1e-6 relative (the height given exactly)."""
    from fabkit.lab.camera import MarkerLayout, calibrate

    cam = _camera(1200.0, 9.0, 40.0, -0.04)
    lay = MarkerLayout(30.0, np.array(vr.MARKERS))
    corners = cam.project(lay.corners().reshape(-1, 3)).reshape(4, 4, 2)
    cal = calibrate(corners, lay, (W_IMG, H_IMG), camera_height=float(cam.C[2]))
    assert abs(cal.camera.f / cam.f - 1) < 1e-6 and abs(cal.camera.k1 - cam.k1) < 1e-6
    assert np.max(np.abs(cal.camera.centre - cam.C)) < 1e-3 and cal.rms_px < 1e-6


# ---------------------------------------------------------------------------- bad input
def _noise_video(path, n=6):
    import av

    out = av.open(str(path), "w")
    st = out.add_stream("libx264", rate=25)
    st.width, st.height, st.pix_fmt = 64, 64, "yuv420p"
    rng = np.random.default_rng(0)
    for i in range(n):
        fr = av.VideoFrame.from_ndarray(rng.integers(0, 255, (96, 64), dtype=np.uint8), format="yuv420p")
        fr.pts = i
        for p in st.encode(fr):
            out.mux(p)
    for p in st.encode():
        out.mux(p)
    out.close()


def test_bad_inputs_exit_2_and_write_nothing(dark, tmp_path, capsys):
    spec = dark["spec"]
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n")
    noise = tmp_path / "noise.mp4"
    _noise_video(noise)
    empty = tmp_path / "empty.mp4"
    vr.render_video(empty, dark["renderer"], vr.Launch(v_in=60.0), np.arange(8) / 125.0, hide=range(8))
    out = tmp_path / "o"
    for video, words in ((text, "not a video"), (noise, "not found"), (empty, "ball was not found")):
        capsys.readouterr()
        code = main(["track", str(spec), str(dark["video"]), str(video), "--out-dir", str(out), "--no-progress"])
        err = capsys.readouterr().err.strip()
        assert code == 2 and words in err and str(video) in err and "\n" not in err, err
        assert not out.exists()                      # not even the good video's track
    code = main(["track", str(spec), str(dark["video"]), str(dark["video"]), "-o", str(tmp_path / "x.csv")])
    assert code == 2 and "--output" in capsys.readouterr().err


def test_spec_lab_keys(tmp_path, capsys):
    p = tmp_path / "s.yaml"
    p.write_text(vr.SPEC_TEXT + "lab:\n  markers: [[20, 20], [330, 20], [480, 230]]\n")
    assert main(["markers", str(p), "-o", str(tmp_path / "m.pdf")]) == 2
    assert "lab.markers: must be a list of 4 points" in capsys.readouterr().err
    # the old default corner (L, 0) lies over the paper surface's rising end: given, refused
    # naming the marker; the default now places all four on the uncut top face, unwarned
    p.write_text(vr.SPEC_TEXT + "lab:\n  markers: [[20, 20], [480, 20], [480, 230], [20, 230]]\n")
    assert main(["markers", str(p), "-o", str(tmp_path / "m.pdf")]) == 2
    err = capsys.readouterr().err
    assert "marker 1 at [480, 20]" in err and "lab.markers[1]" in err
    p.write_text(vr.SPEC_TEXT)
    assert main(["markers", str(p), "-o", str(tmp_path / "m.pdf")]) == 0
    assert capsys.readouterr().err == ""


# ---------------------------------------------------------------------------- the page to print
def test_markers_page_true_size(tmp_path, capsys):
    import cv2

    spec = _spec(tmp_path, camera_height=1500)
    png = tmp_path / "markers.png"
    assert main(["markers", str(spec), "-o", str(png), "--json"]) == 0
    rec = json.loads(capsys.readouterr().out)
    assert rec["centres_mm"] == vr.MARKERS and rec["marker_size_mm"] == 30.0
    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    corners, ids, _ = det.detectMarkers(img)
    assert sorted(ids.ravel().tolist()) == [0, 1, 2, 3]
    for c in corners:
        c = c.reshape(4, 2)
        side_mm = np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)) / 600 * 25.4
        assert abs(side_mm - 30.0) < 0.1                           # true size at 600 dpi
        assert c[0, 1] < c[3, 1]                                   # printed upright: corner 0 at the top
    for ext, head in ((".pdf", b"%PDF"), (".svg", b"<?xml")):
        assert main(["markers", str(spec), "-o", str(tmp_path / f"m{ext}")]) == 0
        assert (tmp_path / f"m{ext}").read_bytes()[:5].startswith(head)


def test_corners_matched_whatever_the_markers_turn():
    """A marker stuck down turned by 90, 180 or 270 degrees: OpenCV lists its corners from
    the printed top-left; matched by position they come back in the layout's order."""
    from fabkit.lab.camera import MarkerLayout, match_corners

    cam = _camera(1300.0, 5.0, 10.0, 0.0)
    lay = MarkerLayout(30.0, np.array(vr.MARKERS))
    exact = cam.project(lay.corners().reshape(-1, 3)).reshape(4, 4, 2)
    turned = {i: np.roll(exact[i], -i, axis=0) for i in range(4)}      # marker i turned i quarter turns
    assert np.array_equal(match_corners(turned, lay), exact)
