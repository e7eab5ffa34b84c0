"""Checks before cutting: ``fabkit gcode --machine`` refuses travel, spindle speeds and
tool changes beyond the machine (exit 2, nothing written) and warns of feeds above
its rates with the time they cost; the setup sheet carries the controller's run time."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from fabkit.machine.limits import check_program
from fabkit.machine.profile import grbl_defaults, parse_grbl
from fabkit.toolpath.program.reader import read_program

from conftest import write_spec
from test_gcode_cli import plain_planner, small_raw  # noqa: F401  (fixture)

DUMP = """$11=0.010
$30={smax}
$31=0
$110={rate}
$111={rate}
$112={rate}
$120=10.000
$121=10.000
$122=10.000
$130={tx}
$131=200.000
$132=200.000
"""


def dump(tmp_path, rate=500.0, tx=200.0, smax=24000):
    p = tmp_path / "grbl.txt"
    p.write_text(DUMP.format(rate=rate, tx=tx, smax=smax))
    return p


def outputs(tmp_path):
    return sorted(p.name for p in (tmp_path / "toolpaths").glob("*")) if (tmp_path / "toolpaths").exists() else []


def test_travel_shorter_than_block_refused(cli, tmp_path, plain_planner):
    spec = write_spec(tmp_path, small_raw(dialect="grbl"))          # a 60 x 40 mm block
    code, out, err = cli("gcode", spec, "--machine", dump(tmp_path, tx=50.0), "--no-verify")
    assert code == 2
    line = err.strip()
    assert "\n" not in line and "X travel" in line and "60 mm" in line and "50 mm" in line
    assert outputs(tmp_path) == []


def test_spindle_outside_range_refused(cli, tmp_path, plain_planner):
    spec = write_spec(tmp_path, small_raw(dialect="grbl", spindle=30000))
    code, out, err = cli("gcode", spec, "--machine", dump(tmp_path), "--no-verify")
    assert code == 2 and "spindle 30000 rpm" in err and "0-24000" in err
    assert outputs(tmp_path) == []


def test_tool_change_without_changer_refused(cli, tmp_path, plain_planner):
    raw = small_raw(dialect="linuxcnc")
    raw["tool"]["number"] = 3
    spec = write_spec(tmp_path, raw)
    code, out, err = cli("gcode", spec, "--machine", dump(tmp_path), "--no-verify")
    # an explicit dialect the machine contradicts: refused naming both
    assert code == 2 and "machining.dialect is linuxcnc" in err and "runs grbl" in err
    del raw["machining"]["dialect"]                  # no dialect: the grbl machine makes a grbl program
    code, out, err = cli("gcode", write_spec(tmp_path, raw), "--machine", dump(tmp_path), "--no-verify")
    assert code == 0, err
    text = (tmp_path / "toolpaths" / "small.ngc").read_text()
    code_only = "\n".join(ln.split("(")[0] for ln in text.splitlines())
    assert "grbl dialect" in text and "M6" not in code_only and "G64" not in code_only
    # the sheet compares every need with this machine (its $130 travel, $110 rate, $30 spindle)
    sheet = json.loads((tmp_path / "toolpaths" / "small.setup.json").read_text())
    cmp_ = sheet["machine_comparison"]
    assert cmp_["travel_x"] == {"need": sheet["machine_needs"]["travel"]["x"], "machine": 200.0, "ok": True}
    assert cmp_["axis_rate_x"]["machine"] == 500.0 and cmp_["spindle"]["machine"] == [0.0, 24000.0]
    md = (tmp_path / "toolpaths" / "small.setup.md").read_text()
    assert "| X travel used / available |" in md and "grbl's default" not in md
    raw["machine"] = {"controller": "linuxcnc", "max_rate": [3000, 3000, 1000], "tool_changer": True,
                      "travel": [500, 500, 100]}
    spec = write_spec(tmp_path, raw)                 # the spec's own machine section
    code, out, err = cli("gcode", spec, "--no-verify", "--json")
    assert code == 0, err
    assert json.loads(out)["machine"]["tool_changer"] is True


def test_feed_above_rate_warns_with_its_cost(cli, tmp_path, plain_planner):
    spec = write_spec(tmp_path, small_raw(dialect="grbl", feed=1200))
    code, out, err = cli("gcode", spec, "--machine", dump(tmp_path, rate=500.0), "--no-verify", "--json")
    assert code == 0, err
    sheet = json.loads((tmp_path / "toolpaths" / "small.setup.json").read_text())
    rt = sheet["run_time"]
    assert rt["total_s"] > rt["length_over_feed_s"]
    assert rt["feed_s"] + rt["plunge_s"] + rt["rapid_s"] == pytest.approx(rt["total_s"], abs=0.2)
    # the cost of the clipped feed, computed here: sum over G1 moves of L (1/min(F, cap) - 1/F),
    # cap = min over moving axes of rate / |u_axis|
    p = read_program((tmp_path / "toolpaths" / "small.ngc").read_text())
    a, b = p.segments()
    g1 = p.kinds == 1
    d = np.nan_to_num(b[g1] - a[g1])
    L = np.linalg.norm(d, axis=1)
    m = L > 0
    u = np.abs(d[m]) / L[m, None]
    cap = np.min(np.where(u > 0, 500.0 / np.where(u > 0, u, 1), np.inf), axis=1)
    f = p.feed[g1][m]
    lost = float(np.sum(L[m] * (1 / np.minimum(f, cap) - 1 / f)) * 60)
    # the cap's cost is planned (the rates raised to F): acceleration already slows these
    # short moves, so it is below the length/feed difference
    cost = rt["time_lost_to_axis_rates_s"]
    assert 0 < cost < lost
    said = re.search(r"\+(\d+) s of run time", err)
    assert rt["feed_cap_cost_s"] == cost and said and abs(int(said.group(1)) - cost) <= 0.51
    assert "above the machine's rates" in err and "Run time on this machine" in \
        (tmp_path / "toolpaths" / "small.setup.md").read_text()


def test_check_program_units():
    m = parse_grbl(DUMP.format(rate=500, tx=100, smax=1000), "d")
    ok = read_program("G21 G90\nG0 X0 Y0 Z0\nM3 S1000\nG1 X100 F400\nM5\n")
    chk = check_program(ok, "G21 G90\nG0 X0 Y0 Z0\nM3 S1000\nG1 X100 F400\nM5\n", m)
    assert chk.ok and not chk.warnings and chk.travel["x"] == (100.0, 100.0)
    text = "G20 G90\nG0 X0 Y0 Z0\nM3 S1200\nG1 X4 F30\nM6\n"        # 4 in = 101.6 mm; 30 in/min = 762 mm/min
    chk = check_program(read_program(text), text, m)
    assert any("X travel" in r and "101.6 mm" in r for r in chk.refusals)
    assert any("1200 rpm" in r for r in chk.refusals) and any("M6" in r for r in chk.refusals)
    assert chk.warnings and "F762" in chk.warnings[0]
    lcnc = "G21 G90 G64 P0.005\nG0 X0 Y0 Z0\nG1 X10 F400\nM2\n"
    chk = check_program(read_program(lcnc), lcnc, m)
    assert chk.refusals == ["the program uses G64, which grbl 1.1 does not accept (error:20): write it with "
                            "machining.dialect: grbl"]
    assert grbl_defaults().tool_changer is False and math.isclose(grbl_defaults().max_rate[0], 500.0)


def test_report_sheet_shows_the_machine(tmp_path, plain_planner):
    from fabkit.commands.report import _toolpath
    from fabkit.machine.profile import load_machine
    from fabkit.report import _sheet_section
    from fabkit.spec import load_spec
    from fabkit.surface import Surface

    spec = load_spec(write_spec(tmp_path, small_raw(dialect="grbl")))
    tool = _toolpath(spec, Surface.from_spec(spec), load_machine(dump(tmp_path, tx=50.0)))
    sheet = tool["sheet"]
    assert sheet["run_time"]["total_s"] > sheet["run_time"]["length_over_feed_s"] > 0
    assert not sheet["machine_check"]["ok"] and "X travel" in sheet["machine_check"]["refusals"][0]
    html = _sheet_section(sheet)
    assert "Run time on this machine" in html and "X travel" in html
