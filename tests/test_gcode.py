"""The G-code writer: round trip through the reader, LinuxCNC's interpreter on
every dialect and unit, grbl's word subset and line limits, modal words, determinism."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from fabkit.toolpath.program.gcode import DIALECTS, MachineProfile, used_words, write_program
from fabkit.toolpath.path import CUT, PLUNGE, RAPID, Toolpath
from fabkit.toolpath.program.reader import read_program

RS274 = shutil.which("rs274")
COMBOS = [("linuxcnc", "mm"), ("linuxcnc", "in"), ("grbl", "mm"), ("grbl", "in")]


def wavy_toolpath(seed=0):
    """Three zigzag passes of random-walk heights, a link, repeated points and
    axis-aligned runs (so some axis words are unchanged), plunges and rapids."""
    rng = np.random.default_rng(seed)
    pts, kinds = [(0.0, 0.0, 1.0)], [RAPID]
    y = 0.0
    for p in range(3):
        x = np.linspace(0, 50, 40)[:: 1 if p % 2 == 0 else -1]
        z = -2 + np.cumsum(rng.normal(0, 0.05, x.size))
        z[10:15] = z[10]                      # flat run: Z unchanged
        if p == 0:
            pts.append((x[0], y, z[0]))
            kinds.append(PLUNGE)
        for xi, zi in zip(x, z):
            pts.append((xi, y, zi))
            kinds.append(CUT)
        pts.append(pts[-1])                   # a repeated point: dropped
        kinds.append(CUT)
        y += 1.234567
        pts.append((x[-1], y, z[-1] + 0.5))   # a link at clearance
        kinds.append(RAPID)
        pts.append((x[-1], y, z[-1]))
        kinds.append(PLUNGE)
    pts.append((pts[-1][0], pts[-1][1], 5.0))
    kinds.append(RAPID)
    return Toolpath(np.array(pts), np.array(kinds), tool_radius=3.0, safe_z=5.0, passes=3, stepover=1.234567,
                    stepover_min=1.234567, info={})


def profile(dialect, units, **kw):
    return MachineProfile(dialect=dialect, units=units, feed=2500, plunge=600, spindle=16000, safe_z=5.0,
                          tolerance=0.01, header=(("spec", "specs/a (b).yaml"), ("name", "wavy"),
                                                  ("note", "x" * 150)), **kw)


@pytest.mark.parametrize("dialect, units", COMBOS)
def test_round_trip_through_reader(dialect, units):
    tp = wavy_toolpath()
    prof = profile(dialect, units)
    prog = read_program(write_program(tp, prof))
    # every distinct point is reached, in order, within the rounding of one coordinate
    keep = np.r_[True, np.any(tp.points[1:] != tp.points[:-1], axis=1)]
    expected = tp.points[keep]
    # after "G0 Z<safe>" and "G0 X Y" (the toolpath ends at the safe height: no extra retract),
    # before the park move to X0 Y0
    got = prog.points[2:-1]
    np.testing.assert_allclose(prog.points[-1], [0, 0, 5.0], atol=prof.rounding_mm)
    assert got.shape == expected.shape
    np.testing.assert_allclose(got, expected, atol=prof.rounding_mm * (1 + 1e-9), rtol=0)
    assert prof.rounding_mm <= prof.tolerance / 20
    kinds = tp.kinds[keep]
    np.testing.assert_array_equal(prog.kinds[2:-1], (kinds != RAPID).astype(int))
    feed = prog.feed[2:-1]
    k = 25.4 if units == "in" else 1.0
    rounding = 0.5 * 10.0 ** -(3 if units == "in" else 1) * k
    np.testing.assert_allclose(feed[kinds == CUT], 2500, atol=rounding)
    np.testing.assert_allclose(feed[kinds == PLUNGE], 600, atol=rounding)
    assert prog.points[0, 2] == pytest.approx(5.0, abs=prof.rounding_mm)  # first: up to the safe height
    assert prog.points[-1, 2] == pytest.approx(5.0, abs=prof.rounding_mm)
    assert prog.units == units


@pytest.mark.parametrize("dialect, units", COMBOS)
def test_structure_and_modal_words(dialect, units):
    text = write_program(wavy_toolpath(), profile(dialect, units))
    lines = text.splitlines()
    code = [ln for ln in lines if not ln.startswith("(")]
    d = DIALECTS[dialect]
    assert code[0].split() == ["G17", "G21" if units == "mm" else "G20", "G90", "G94", "G54"]
    assert "M3 S16000" in code and code[-2:] == ["M5", d.program_end]
    assert code.index("M3 S16000") < next(i for i, c in enumerate(code) if c.split()[0] == "G1")
    # header: comment block first, with the required items
    header = " ".join(ln for ln in lines if ln.startswith("("))
    for item in ("spec:", "name:", "work zero", "X0 Y0", "Z0 on the stock top face", "scallop",
                 "tolerance", "passes", "stepover", "estimated time"):
        assert item in header
    # modal: no G0/G1 twice in a row, no repeated F, no axis word that does not change the position
    motion, feed, pos = None, None, {}
    for ln in code:
        for w in re.findall(r"[A-Z][-0-9.]+", ln):
            letter, val = w[0], w[1:]
            if w in ("G0", "G1"):
                assert w != motion, ln
                motion = w
            elif letter == "F":
                assert val != feed, ln
                feed = val
            elif letter in "XYZ":
                assert pos.get(letter) != float(val), ln
                pos[letter] = float(val)
    # G0 and G1 are the only motions; fixed decimals at most
    nd = 4 if units == "mm" else 5
    for x in re.findall(r"[XYZ](-?\d+\.?\d*)", text):
        assert len(x.split(".")[1]) <= nd if "." in x else True


@pytest.mark.parametrize("units", ["mm", "in"])
def test_grbl_subset(units):
    text = write_program(wavy_toolpath(), profile("grbl", units))
    allowed = {"G0", "G1", "G17", "G20", "G21", "G90", "G94", "G54", "M3", "M5", "M2", "M30", "S", "F", "X", "Y",
               "Z"}
    assert used_words(text) <= allowed
    # a tool number: grbl (no M6, no tool table) gets a comment, never T/M6/G43
    tooled = write_program(wavy_toolpath(), profile("grbl", units, tool_number=7))
    assert used_words(tooled) <= allowed and "load T7 by hand" in tooled
    for ln in text.splitlines():
        assert len(ln) <= 70 and ln.isascii() and "%" not in ln
        if "(" in ln:
            assert ln.startswith("(") and ln.endswith(")") and ln.count("(") == 1 and ln.count(")") == 1


def test_deterministic_and_decimals_follow_the_tolerance():
    tp = wavy_toolpath()
    assert write_program(tp, profile("linuxcnc", "mm")) == write_program(wavy_toolpath(), profile("linuxcnc", "mm"))
    fine = MachineProfile(tolerance=0.0005)
    assert fine.decimals == 5 and fine.rounding_mm <= 0.0005 / 20
    assert MachineProfile(units="in", tolerance=0.001).decimals == 6


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
@pytest.mark.parametrize("dialect, units", COMBOS)
def test_linuxcnc_interpreter_reads_every_dialect(tmp_path, dialect, units):
    tp = wavy_toolpath(1)
    text = write_program(tp, profile(dialect, units))
    path = tmp_path / "p.ngc"
    path.write_text(text)
    run = subprocess.run([RS274, "-g", str(path)], stdin=subprocess.DEVNULL, capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 0 and run.stderr.strip() in ("", "executing"), run.stderr
    # LinuxCNC's canonical moves (in program units, 4 decimals) are our moves
    moves = re.findall(r"STRAIGHT_(?:FEED|TRAVERSE)\(([-0-9.]+), ([-0-9.]+), ([-0-9.]+)", run.stdout)
    got = np.array(moves, dtype=float) * (25.4 if units == "in" else 1.0)
    ours = read_program(text).points
    assert got.shape == ours.shape
    assert got[0, 2] == pytest.approx(ours[0, 2], abs=0.51e-4 * 25.4)  # "G0 Z<safe>" (rs274 starts at the origin; we leave X, Y unknown)
    np.testing.assert_allclose(got[1:], ours[1:], atol=0.5e-4 * (25.4 if units == "in" else 1.0) + 1e-9)
    if dialect == "linuxcnc":
        assert "SET_MOTION_CONTROL_MODE" in run.stdout   # G64 P blending held to the tolerance


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
@pytest.mark.parametrize("units", ["mm", "in"])
def test_linuxcnc_tool_call_work_offset_and_park(tmp_path, units):
    """G54 before any motion, T7 M6 G43 H7 applying tool 7's length from the tool table,
    and the program parked at (X, Y) at the safe height: as LinuxCNC's interpreter runs it."""
    text = write_program(wavy_toolpath(2), profile("linuxcnc", units, tool_number=7, park=(-12.7, 25.4)))
    code = [ln for ln in text.splitlines() if not ln.startswith("(")]
    assert "G54" in code[0].split() and "T7 M6 G43 H7" in code
    assert code.index("T7 M6 G43 H7") < code.index("M3 S16000")
    (tmp_path / "tools.tbl").write_text("T7 P7 Z1.25 D0.25 ;ball end\n")   # machine units: inch without an INI
    (tmp_path / "p.ngc").write_text(text)
    run = subprocess.run([RS274, "-t", str(tmp_path / "tools.tbl"), "-g", str(tmp_path / "p.ngc")],
                         stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and run.stderr.strip() in ("", "executing"), run.stderr
    out = run.stdout
    assert "not found" not in out
    k = 25.4 if units == "in" else 1.0
    # tool 7's length from the table (1.25 in) is applied, in program units
    offset = re.search(r"USE_TOOL_LENGTH_OFFSET\(([-0-9.]+) ([-0-9.]+) ([-0-9.]+)", out)
    assert offset and float(offset.group(3)) * k == pytest.approx(1.25 * 25.4, abs=1e-3)
    assert out.index("SELECT_TOOL(7)") < out.index("CHANGE_TOOL") < out.index("USE_TOOL_LENGTH_OFFSET") \
        < out.index("STRAIGHT_FEED")
    moves = re.findall(r"STRAIGHT_(FEED|TRAVERSE)\(([-0-9.]+), ([-0-9.]+), ([-0-9.]+)", out)
    kind, *last = moves[-1]
    assert kind == "TRAVERSE"
    atol = 0.6e-4 * k       # rs274 prints 4 decimals of the program's unit
    np.testing.assert_allclose(np.array(last, dtype=float) * k, [-12.7, 25.4, 5.0], atol=atol)
    # the move before the park is the retract to the safe height at the last cut's X, Y
    assert float(moves[-2][3]) * k == pytest.approx(5.0, abs=atol)


def _inch_grbl_job():
    """A grbl inch job on a 5 x 3 x 2 in stock, 1/4 in ball (work mm inside): (spec, surface)."""
    from types import SimpleNamespace

    spec = SimpleNamespace(
        path="specs/x.yaml", name="x", units="mm",
        tool=SimpleNamespace(shape="ball", diameter=6.35, number=None),
        stock=SimpleNamespace(thickness=50.8),
        machining=SimpleNamespace(dialect="grbl", units="in", feed=1270, plunge=254, spindle=18000,
                                  safe_height=5.08, tolerance=0.0254, scallop=0.127, park=(0.0, 0.0)))
    return spec, SimpleNamespace(stock_size_mm=(127.0, 76.2))


def test_header_speaks_the_program_units():
    """A G20 program's comments give tool, stock, scallop and tolerance in inches,
    computed here from the millimetre inputs."""
    from fabkit.toolpath.program.gcode import profile_from_spec

    spec, surface = _inch_grbl_job()
    text = write_program(wavy_toolpath(), profile_from_spec(spec, surface))
    header = " ".join(ln.strip("()") for ln in text.splitlines() if ln.startswith("("))
    assert "diameter 0.25 in" in header
    assert "5 x 3 x 2 in" in header
    assert "scallop: 0.005 in" in header and "tolerance: 0.001 in" in header
    assert "cut 50, plunge 10 in/min" in header and "safe height: Z0.2 in" in header
    assert "stepover: 0.0486 in" in header                 # 1.234567 mm
    assert "mm" not in header


def test_header_names_the_gap_to_passes_beyond_the_edges():
    """The stepover line gives the stepover between passes over the stock; where the gap to
    a pass beyond a stock edge is larger, the header names it for what it is (1.234567 mm
    stepover, a 2.69 mm gap: 0.0486 and 0.1059 in)."""
    from fabkit.toolpath.program.gcode import profile_from_spec

    spec, surface = _inch_grbl_job()
    tp = wavy_toolpath()
    plain = write_program(tp, profile_from_spec(spec, surface))
    tp.info["edge_pass_gap_max"] = 2.69
    text = write_program(tp, profile_from_spec(spec, surface))
    header = " ".join(" ".join(ln.strip("()") for ln in text.splitlines() if ln.startswith("(")).split())
    assert "stepover: 0.0486 in" in header
    assert "edge pass gap: up to 0.1059 in from the passes over the stock to those beyond its edges" in header
    assert "edge pass gap" not in plain
    tp.info["edge_pass_gap_max"] = 1.0                     # smaller than the stepover: not named
    assert write_program(tp, profile_from_spec(spec, surface)) == plain
