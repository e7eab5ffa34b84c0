"""``fabkit time`` and its permissive reader (fabkit/machine/program.py) against closed
forms: grbl's arc segmentation (mc_arc's segment count, the points on the arc, the
helix), the arc centre from R, grbl's dwell in 50 ms steps, grbl 1.1h's buffer-sync
rules (a repeated M3 or the same S does not empty the buffer; a new S while the
spindle runs, a spindle or coolant state change do), incremental and inch moves, G53,
G18/G19, and the words refused with their line. (Against grbl 1.1h's own parser and
planner: benchmarks/time_reference.py, docs/machine.md.)"""

import dataclasses
import json
import math

import numpy as np
import pytest

from fabkit.errors import SpecError
from fabkit.machine.planner import run_time
from fabkit.machine.profile import grbl_defaults
from fabkit.machine.program import read_moves

GRBL = grbl_defaults()          # 500 mm/min, 10 mm/s^2, $12 = 0.002 mm


def test_arc_segments_as_grbl_mc_arc():
    # a half circle of radius 10 CCW in XY: floor(|0.5 theta r| / sqrt(tol (2r - tol))) segments
    mv = read_moves("G21 G90\nG0 X10 Y0\nG3 X-10 Y0 I-10 J0 F300\n", "grbl", 0.002)
    n = math.floor(0.5 * math.pi * 10 / math.sqrt(0.002 * (20 - 0.002)))
    assert mv.arc_segments == n == 78
    pts = mv.points[1:]
    assert np.allclose(np.hypot(pts[:, 0], pts[:, 1]), 10.0, rtol=0, atol=1e-5)  # on the arc (grbl's floats)
    assert np.all(pts[:-1, 1] > 0)                                                # CCW from +X: through +Y
    assert pts[-1] == pytest.approx([-10, 0, 0])
    chord = 2 * 10 * math.sin(math.pi / n / 2)
    assert np.allclose(np.linalg.norm(np.diff(mv.points[0:], axis=0)[1:], axis=1), chord, rtol=1e-4)


@pytest.mark.parametrize("plane,axes", [(18, (2, 0, 1)), (19, (1, 2, 0))])
def test_arcs_in_xz_and_yz_with_a_helix(plane, axes):
    a0, a1, al = axes
    names = "XYZ"
    centre = "IJK"
    # a full circle (end = start) of radius 5 with 3 mm along the third axis, CW
    text = (f"G21 G90 G{plane}\nG1 {names[a0]}5 {names[a1]}0 F600\n"
            f"G2 {names[a0]}5 {names[a1]}0 {names[al]}3 {centre[a0]}-5 {centre[a1]}0\n")
    mv = read_moves(text, "grbl", 0.01)
    n = math.floor(0.5 * 2 * math.pi * 5 / math.sqrt(0.01 * (10 - 0.01)))
    assert mv.arc_segments == n
    p = mv.points[1:]
    assert np.allclose(np.hypot(p[:, a0], p[:, a1]), 5.0)
    assert np.allclose(np.diff(p[:, al]), 3.0 / n)
    # the time: one block per segment; the path's length is the helix over n chords
    chord = math.hypot(2 * 5 * math.sin(math.pi / n), 3.0 / n)
    rt = run_time(text, dataclasses.replace(GRBL, max_rate=(6000.0,) * 3, arc_tolerance=0.01))
    assert rt.arcs == 1 and rt.arc_segments == n
    assert rt.length_over_feed_s == pytest.approx((5 + n * chord) / 600 * 60, rel=2e-4)   # whole steps


def test_arc_by_radius_as_grbl_gcode():
    # R > 0: the shorter arc (90 degrees), R < 0: the longer one (270): both on the circle
    # through both ends, CW from (0, 0) to (5, 5): centres (5, 0) and (0, 5)
    short = read_moves("G21\nG2 X5 Y5 R5 F100\n", "grbl", 0.002)
    long_ = read_moves("G21\nG2 X5 Y5 R-5 F100\n", "grbl", 0.002)
    for mv, c in ((short, (5, 0)), (long_, (0, 5))):
        assert mv.points[-1] == pytest.approx([5, 5, 0])
        assert np.allclose(np.hypot(mv.points[:, 0] - c[0], mv.points[:, 1] - c[1]), 5.0)
    n = math.floor(0.5 * (math.pi / 2) * 5 / math.sqrt(0.002 * (10 - 0.002)))
    assert short.arc_segments == n and long_.arc_segments == math.floor(3 * 0.5 * (math.pi / 2) * 5 /
                                                                        math.sqrt(0.002 * (10 - 0.002)))
    with pytest.raises(SpecError, match="line 2.*error:34"):
        read_moves("G21\nG2 X10 Y0 R4 F100\n", "grbl")
    with pytest.raises(SpecError, match="line 2.*error:33"):
        read_moves("G21\nG2 X10 Y0 I4 J0 F100\n", "grbl")          # end point 2 mm off the circle


def test_dwell_in_grbl_steps_and_exact_in_linuxcnc():
    text = "G21\nG4 P0.12\nG4 P1\n"
    assert read_moves(text, "grbl").dwell_s == pytest.approx(0.15 + 1.0)        # ceil(20 P) x 50 ms
    assert read_moves(text, "linuxcnc").dwell_s == pytest.approx(1.12)
    # a dwell between two moves: both stop, the dwell adds
    rt = run_time("G21\nG1 X10 F300\nG4 P0.5\nG1 X20\n", GRBL)
    v, a = 5.0, 10.0
    assert rt.total_s == pytest.approx(2 * (10 / v + v / a) + 0.5, rel=1e-12)


def _syncs(body):
    return read_moves("G21\n" + body, "grbl").syncs


def test_grbl_sync_rules():
    assert _syncs("M3 S1000\nG1 X1 F100\nM3\nG1 X2\nM3 S1000\n") == 1       # only the first turns it on
    assert _syncs("M3 S1000\nG1 X1 F100\nS2000\nG1 X2\n") == 2                # a new S while it runs
    assert _syncs("S1000\nS2000\nM5\n") == 0                                  # spindle off: no sync
    assert _syncs("M8\nM8\nG1 X1 F100\nM7\nM9\nM9\n") == 3                    # coolant state changes
    assert _syncs("G1 X1 F100\nM2\n") == 1
    # LinuxCNC: every spindle, speed and coolant word stops the queue
    assert read_moves("G21\nM3 S1000\nM3\nS1000\nM8\nM8\n", "linuxcnc").syncs == 5


def test_repeated_m3_keeps_the_look_ahead():
    # 40 short moves in a line: M3 repeated between them costs nothing in grbl 1.1h,
    # a new S every move stops at each
    moves = "".join(f"G1 X{i}\n" for i in range(1, 41))
    plain = run_time("G21\nM3 S1000\nG1 X0 F3000\n" + moves, GRBL).total_s
    rep = run_time("G21\nM3 S1000\nG1 X0 F3000\n" + moves.replace("\n", "\nM3\n"), GRBL).total_s
    new_s = run_time("G21\nM3 S1000\nG1 X0 F3000\n" + "".join(f"G1 X{i}\nS{1000 + i}\n" for i in range(1, 41)),
                     GRBL).total_s
    assert rep == pytest.approx(plain, rel=1e-12)
    # stopping at every 1 mm move: 40 triangles of peak sqrt(a L)
    assert new_s == pytest.approx(40 * 2 * math.sqrt(1 / 10.0), rel=1e-9)


def test_incremental_inch_g53_and_offsets():
    mv = read_moves("G20 G91\nG1 X1 Y1 F10\nX1\nG90 G53 G0 Z0\nG92 X0\nG1 X1 F10\n", "grbl")
    np.testing.assert_allclose(mv.points[:2, :2], [[25.4, 25.4], [50.8, 25.4]])
    assert mv.feed[0] == pytest.approx(254.0)
    assert mv.points[3][0] == pytest.approx(50.8 + 25.4)                  # G92 X0 here: X1 is 1 in further
    assert any("G53" in w for w in mv.warnings)


def test_words_refused_with_their_line():
    for text, what in [("G0 X1\nG10 L2 P1 X0\n", "line 2: G10"), ("G0 X1\nG1 X#1 F100\n", "line 2: unsupported text"),
                       ("G1 X1 F10\nG1 B5\n", "line 2: B words"), ("G21\nG64 P0.1\n", "G64 is not supported by grbl"),
                       ("G21\nM6 T2\n", "M6 is not supported by grbl"),
                       ("G21\nG1 X1\n", "line 2: G1 without a feed")]:
        with pytest.raises(SpecError, match=what):
            read_moves(text, "grbl")
    with pytest.raises(SpecError, match="line 2: unclosed comment"):
        read_moves("G21\n(open\nG1 X1 F1\n", "linuxcnc")
    # grbl reads comments left to right: a ';' inside ( ) is part of it, an unclosed ( ends the line
    mv = read_moves("G21\n(a; b) G1 X1 F100\nG1 X2 ; c (d\n(open G1 X9\n", "grbl")
    np.testing.assert_allclose(mv.points[:, 0], [1, 2])
    # LinuxCNC takes its own words (tool call, path control) and `%`, line numbers, comments
    mv = read_moves("%\nN10 G21 G64 P0.05 (path)\nN20 T2 M6 G43 H2\nN30 G1 X5 F100 ; cut\n%\n", "linuxcnc")
    assert len(mv) == 1 and mv.tolerance[0] == pytest.approx(0.05) and mv.tool_changes == 1


def test_time_command(cli, tmp_path):
    prog = tmp_path / "p.nc"
    prog.write_text("\ufeff%\n(by hand)\nG21 G90\nM3 S1000\nG1 X100 F300\nG4 P1\nM5\nM30\n%\n")
    code, out, err = cli("time", prog, "--machine", "grbl", "--json")
    assert code == 0, err
    d = json.loads(out)
    v, a = 5.0, 10.0
    assert d["total_s"] == pytest.approx(100 / v + v / a + 1.0, abs=0.05)
    assert d["dwell_s"] == 1.0 and d["buffer_syncs"] == 4 and d["controller"] == "grbl"
    code, out, err = cli("time", prog)
    # under a minute, the run time is said in seconds: 100/5 + 5/10 + 1 = 21.5 s
    assert code == 0 and "no --machine" in out and f"{100 / v + v / a + 1.0:.1f} s" in out and "0 min" not in out
    bad = tmp_path / "bad.nc"
    bad.write_text("G21\nG1 X1 F100\nG81 Z-1 R1\n")
    code, out, err = cli("time", bad)
    assert code == 2 and "bad.nc: line 3: G81" in err and len(err.strip().splitlines()) == 1


def test_g28_goes_to_its_stored_position():
    # grbl and LinuxCNC: G28 without words goes to its stored position (machine zero unless
    # G28.1 set it), with words through them to the stored position on those axes only
    mv = read_moves("G21 G90\nG0 X10 Y4 Z5\nG28 G91 Z0\nG90 G0 X20\nG28\n", "grbl")
    np.testing.assert_allclose(mv.points, [[10, 4, 5], [10, 4, 5], [10, 4, 0], [20, 4, 0], [0, 0, 0]])
    assert any("G28" in w for w in mv.warnings)
    rt = run_time("G21 G90\nG0 X10\nG28\n", GRBL)            # 10 mm out and back at 500 mm/min
    v, a = 500 / 60, 10.0
    assert rt.total_s == pytest.approx(2 * (10 / v + v / a), rel=1e-12)
    mv = read_moves("G21\nG0 X3\nG28.1\nG0 X9\nG28\n", "linuxcnc")
    assert mv.points[-1][0] == 3.0 and not mv.warnings
