"""Track readers (Tracker text, CSV t,x,y and frame,x,y, trackpy) and the video map;
bad files get one line naming the file and the line, exit 2, nothing written."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import PAPER
from fabkit.errors import SpecError
from fabkit.lab.tracks import VideoMap, read_track

T = np.arange(20) / 125.0
X = -30 + 40 * T
Y = 0.5 * np.sin(9 * T)


def test_tracker_export_with_blank_cells(tmp_path):
    rows = ["mass A", "t\tx\ty\tv"]
    for i, (t, x, y) in enumerate(zip(T, X, Y)):
        rows.append(f"{t}\t\t{y}\t1" if i == 5 else f"{t}\t{x}\t{y}\t")   # frame 5 unmarked
    p = tmp_path / "tracker.txt"
    p.write_text("\n".join(rows) + "\n")
    tr = read_track(p)
    assert tr.format == "tracker" and tr.name == "mass A" and tr.skipped_rows == 1
    keep = np.arange(20) != 5
    np.testing.assert_array_equal(tr.t, T[keep])
    np.testing.assert_allclose(tr.x, X[keep], rtol=0, atol=1e-12)


def test_csv_t_and_frame_columns(tmp_path):
    p = tmp_path / "a.csv"
    p.write_text("x,t,y\n" + "".join(f"{x},{t},{y}\n" for t, x, y in zip(T, X, Y)))
    tr = read_track(p)
    assert tr.format == "csv"
    np.testing.assert_allclose(tr.x, X, atol=1e-12)
    q = tmp_path / "b.csv"
    q.write_text("frame;x;y\n" + "".join(f"{i + 100};{x};{y}\n" for i, (x, y) in enumerate(zip(X, Y))))
    tr = read_track(q, fps=125.0)
    assert tr.format == "frame-csv"
    np.testing.assert_allclose(tr.t, T + 100 / 125.0, rtol=1e-14)
    with pytest.raises(SpecError, match="--fps"):
        read_track(q)


def test_trackpy_longest_particle_sorted(tmp_path):
    rows = [",y,x,mass,size,ecc,signal,raw_mass,ep,frame,particle"]
    order = np.random.default_rng(0).permutation(20)
    for k, i in enumerate(order):
        rows.append(f"{k},{Y[i]},{X[i]},1,2,0.1,3,4,0.01,{i},7")
    rows += [f"{30 + i},1,2,1,2,0.1,3,4,0.01,{i},3" for i in range(4)]   # a short second particle
    p = tmp_path / "tp.csv"
    p.write_text("\n".join(rows) + "\n")
    tr = read_track(p, fps=125.0)
    assert tr.format == "trackpy" and tr.particle == 7 and "2 particles" in tr.notes[0]
    np.testing.assert_allclose(tr.x, X, atol=1e-12)
    np.testing.assert_allclose(tr.t, T, atol=1e-15)


def test_video_map_exact():
    vm = VideoMap(scale=0.05, origin=(320.0, 240.0), rotate=30.0, flip_y=True)
    x, y = vm.apply(np.array([420.0]), np.array([140.0]))
    # (100, -100) from the origin, flipped to (100, 100), turned 30 deg, times 0.05
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    assert x[0] == pytest.approx(0.05 * (100 * c - 100 * s), abs=1e-12)
    assert y[0] == pytest.approx(0.05 * (100 * s + 100 * c), abs=1e-12)


@pytest.mark.parametrize("body, needle", [
    ("t,x,y\n0,1,2\n0.1,abc,2\n", "line 3: x: not a number: 'abc'"),
    ("t,x,y\n0,1,2\n0,1,2\n", "line 3: t = 0 repeats line 2"),
    ("t,u,v\n0,1,2\n", "line 1: header"),
    ("t,x,y\n" + "".join(f"{i},{i},0\n" for i in range(5)), "only 5 tracked points"),
    ("", "empty file"),
    ("t,x,y\n0,inf,2\n", "line 2: x: not finite"),
])
def test_bad_track_files_one_line_exit_2(cli, tmp_path, body, needle):
    p = tmp_path / "bad.csv"
    p.write_text(body)
    code, out, err = cli("analyze", PAPER, p, "--plot", "fig.png")
    assert code == 2
    assert err.count("\n") == 1 and str(p) in err and needle in err, err
    assert out == "" and not (tmp_path / "fig.png").exists()


def test_missing_file_and_bad_flags(cli, tmp_path):
    code, _, err = cli("analyze", PAPER, tmp_path / "nope.csv")
    assert code == 2 and "nope.csv: file not found" in err
    good = tmp_path / "g.csv"
    good.write_text("t,x,y\n" + "".join(f"{t},{x},{y}\n" for t, x, y in zip(T, X, Y)))
    code, _, err = cli("analyze", PAPER, good, "--scale", "-1")
    assert code == 2 and "--scale: must be > 0" in err


def test_a_track_that_is_a_pipe_or_device_is_refused_not_read(cli, tmp_path):
    """A named pipe would block the read forever and /dev/zero never ends: both refused at once."""
    import os

    fifo = tmp_path / "track.csv"
    os.mkfifo(fifo)
    for p, needle in ((fifo, "a named pipe"), (os.devnull, "a device")):
        code, out, err = cli("analyze", PAPER, p)
        assert code == 2 and out == "" and f"{p}: is {needle}" in err and err.count("\n") == 1, err


# ----------------------------------------------------------------------------
# headers that state units (Logger Pro, PASCO Capstone, Kinovea)
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("cell, expected", [
    ("Time (s)", ("t", "s")), ("Latest: X (m)", ("x", "m")), ('"Run 1: Y (m)"', ("y", "m")),
    ("x [cm]", ("x", "cm")), ("t/ms", ("t", "ms")), ("X Position (mm) Run #1", ("x", "mm")),
    ("Position Y (px)", ("y", "px")), ("x", ("x", None)), ("Frame", ("frame", None)),
    ("X Velocity (m/s)", ("x velocity", "m/s")),
])
def test_header_cells_name_and_unit(cell, expected):
    from fabkit.lab.tracks import parse_header_cell

    assert parse_header_cell(cell) == expected


def test_logger_pro_export_in_metres_read_in_the_specs_cm(tmp_path):
    """Logger Pro's CSV: data-set prefixes, quoted cells, velocity columns beside; metres
    to the spec's cm is exactly 100."""
    rows = ['"Latest: Time (s)","Latest: X (m)","Latest: Y (m)","Latest: X Velocity (m/s)"']
    rows += [f"{t!r},{x / 100!r},{y / 100!r},0.4" for t, x, y in zip(T.tolist(), X.tolist(), Y.tolist())]
    p = tmp_path / "lp.csv"
    p.write_text("\n".join(rows) + "\n")
    tr = read_track(p, units="cm")
    np.testing.assert_allclose(tr.t, T, rtol=0, atol=0)
    np.testing.assert_allclose(tr.x, X, rtol=1e-15, atol=1e-13)
    np.testing.assert_allclose(tr.y, Y, rtol=1e-15, atol=1e-15)
    assert "units converted: x in m, y in m -> s, cm" in tr.notes
    # the same file for an inch spec: 1 m = 1000 / 25.4 in
    np.testing.assert_allclose(read_track(p, units="in").x, X / 100 * 1000 / 25.4, rtol=1e-15)


def test_kinovea_ms_and_pasco_run_suffix(tmp_path):
    k = tmp_path / "kinovea.txt"
    TXY = list(zip(T.tolist(), X.tolist(), Y.tolist()))
    k.write_text("Time (ms)\tX (mm)\tY (mm)\n" + "".join(f"{t * 1000!r}\t{x * 10!r}\t{y * 10!r}\n" for t, x, y in TXY))
    tr = read_track(k, units="cm")
    np.testing.assert_allclose(tr.t, T, rtol=1e-15, atol=1e-17)
    np.testing.assert_allclose(tr.x, X, rtol=1e-15)
    assert "t in ms" in tr.notes[0]
    pa = tmp_path / "pasco.csv"
    pa.write_text("Time (s) Run #1,X Position (in) Run #1,Y Position (in) Run #1\n"
                  + "".join(f"{t!r},{x / 2.54!r},{y / 2.54!r}\n" for t, x, y in TXY))
    np.testing.assert_allclose(read_track(pa, units="cm").x, X, rtol=1e-14)


def test_pixels_keep_the_video_map_and_stated_units_refuse_scale(tmp_path):
    TXY = list(zip(T.tolist(), X.tolist(), Y.tolist()))
    p = tmp_path / "px.csv"
    p.write_text("t (s),x (px),y (px)\n" + "".join(f"{t!r},{x / 0.05!r},{y / 0.05!r}\n" for t, x, y in TXY))
    tr = read_track(p, units="cm", video=VideoMap(scale=0.05))
    np.testing.assert_allclose(tr.x, X, rtol=1e-14)
    m = tmp_path / "m.csv"
    m.write_text("t (s),x (m),y (m)\n" + "".join(f"{t!r},{x / 100!r},{y / 100!r}\n" for t, x, y in TXY))
    with pytest.raises(SpecError, match="--scale: .*m.csv states its positions in a length unit"):
        read_track(m, units="cm", video=VideoMap(scale=0.05))
    u = tmp_path / "u.csv"
    u.write_text("t (s),x (furlong),y (m)\n0,1,2\n")
    with pytest.raises(SpecError, match=r"line 1: x: unknown length unit 'furlong'"):
        read_track(u, units="cm")
    u.write_text("t (fortnight),x,y\n0,1,2\n")
    with pytest.raises(SpecError, match=r"line 1: t: unknown time unit 'fortnight'"):
        read_track(u, units="cm")


def test_analyze_reads_a_launch_exported_in_metres_and_ms(cli, tmp_path):
    """The whole command on a launch exported by a tool in m and ms: the same v_in (2 %)
    as the independent simulation's, and the screen's acceleration ratio near 1."""
    import json

    import lab_sim as L

    truth = L.run((L.START, 0.0, 47.5, 0.0), 0.15, 4.0)
    t, x, y = L.frames(truth, fps=125.0, noise=0.03, seed=8)
    p = tmp_path / "launch.csv"
    p.write_text('"Time (ms)","X (m)","Y (m)"\n' + "".join(f"{a * 1000:.4f},{b / 100:.8f},{c / 100:.8f}\n"
                                                         for a, b, c in zip(t, x, y)))
    code, out, err = cli("analyze", PAPER, p, "--json")
    assert code == 0, err
    r = json.loads(out)["tracks"][0]
    assert r["kind"] == "launch" and abs(r["v_in"] / 47.5 - 1) < 0.02
    assert abs(r["accel_ratio"] - 1) < 0.1 and "units converted" in r["notes"][0]


def test_sigma_columns_read_mapped_and_weighted(tmp_path):
    """``t,x,y,sigma_x,sigma_y`` (what ``fabkit track`` writes): the sigmas come in the
    positions' unit through the video map (scale, and a rotation of 90 degrees swaps them
    exactly); a blank sigma is the track's median; the weights are median / sigma; a
    negative sigma is refused naming the line."""
    p = tmp_path / "s.csv"
    p.write_text("t,x,y,sigma_x,sigma_y\n0,1,2,0.1,0.3\n0.01,1,2,0.2,0.3\n0.02,1,2,,0.3\n0.03,,,,\n"
                 "0.04,1,2,0.4,0.6\n" + "".join(f"{0.05 + i / 100:.2f},1,2,0.2,0.3\n" for i in range(10)))
    tr = read_track(p)
    assert tr.skipped_rows == 1 and len(tr) == 14
    np.testing.assert_array_equal(tr.sigma_x[[0, 1, 3]], [0.1, 0.2, 0.4])
    wx, wy = tr.weights()
    assert wx[2] == 1.0 and wx[0] == 2.0 and wx[3] == 0.5 and wy[3] == 0.5     # median 0.2 and 0.3
    tr = read_track(p, video=VideoMap(scale=0.5, rotate=90.0))
    np.testing.assert_allclose(tr.sigma_x[0], 0.5 * 0.3, rtol=1e-12)
    np.testing.assert_allclose(tr.sigma_y[0], 0.5 * 0.1, rtol=1e-12)
    p2 = tmp_path / "plain.csv"
    p2.write_text("t,x,y\n" + "".join(f"{i / 100},{i},0\n" for i in range(14)))
    assert read_track(p2).sigma_x is None and np.all(read_track(p2).weights()[0] == 1.0)
    p.write_text("t,x,y,sigma_x,sigma_y\n0,1,2,0.1,0.3\n0.01,1,2,-0.2,0.3\n"
                 + "".join(f"{0.02 + i / 100:.2f},1,2,0.2,0.3\n" for i in range(12)))
    with pytest.raises(SpecError, match="line 3.*sigma_x"):
        read_track(p)
