"""A job of several operations (roughing, rest, finishing), each with its own tool:
the programs per dialect (fabkit/toolpath/program/gcode.py ``write_job``), the job's figures and
the setup sheet (fabkit/toolpath/job.py, setup.py) and ``fabkit gcode``'s outputs.

The operations are built by hand here: a flat end mill's rectangle whose length and
time are known in closed form, and the ball's finishing toolpath from the planner on a
small spec. ``fabkit gcode`` is run with a stand-in for the roughing planner
(fabkit/toolpath/rough/roughing.py) returning those operations, so the wiring is tested
without it. A one-tool job is the same program, byte for byte (also the golden tests).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import types

import numpy as np
import pytest

from conftest import write_spec
from test_gcode_cli import small_raw

RS274 = shutil.which("rs274")

SAFE = 3.0
ROUGH = dict(number=2, feed=3000.0, plunge=500.0, spindle=18000.0)
REST = dict(number=3, feed=2000.0, plunge=400.0, spindle=20000.0)
# the rectangle the flat end mill cuts: rapid down to 1 mm, plunge to -1, three sides, rapid up
RECT = np.array([[2, 2, 1], [2, 2, -1], [20, 2, -1], [20, 10, -1], [2, 10, -1], [2, 10, 3]], float)


def _spec(**machining):
    from fabkit.spec import validate

    raw = small_raw(**machining)
    raw["tool"]["number"] = 1
    return validate(raw, "small.yaml")


@pytest.fixture(scope="module")
def finish():
    """(spec, surface, finishing toolpath) of the small bowl, LinuxCNC and mm."""
    from fabkit.surface import Surface
    from fabkit.toolpath.finish.raster import plan_toolpath

    spec = _spec()
    surface = Surface.from_spec(spec)
    return spec, surface, plan_toolpath(spec, surface)


def _rough_ops():
    from fabkit.toolpath.operations import Operation
    from fabkit.toolpath.path import CUT, PLUNGE, RAPID, Toolpath
    from fabkit.toolpath.tools import Tool

    kinds = np.array([RAPID, PLUNGE, CUT, CUT, CUT, RAPID])
    rough = Operation("rough", Tool("flat", 12.7, **ROUGH), Toolpath(RECT, kinds, 6.35, SAFE),
                      leave=0.5, levels=1, passes=2)
    rest = Operation("rest", Tool("bull", 8.0, corner_radius=1.0, **REST),
                     Toolpath(RECT + [5, 5, -0.5], kinds, 4.0, SAFE), leave=0.3, levels=1, passes=1)
    return [rough, rest]


def _job(finish_tp, ops=None):
    from fabkit.toolpath.operations import Operation
    from fabkit.toolpath.tools import Tool

    ops = _rough_ops() if ops is None else ops
    return ops + [Operation("finish", Tool.ball(6.0, number=1), finish_tp, passes=finish_tp.passes)]


def _assert_same_program(got, want):
    """Two parses (reader.Program) equal field for field (arrays: dtype and values, nan
    equal to nan)."""
    import dataclasses

    for f in dataclasses.fields(want):
        a, b = getattr(got, f.name), getattr(want, f.name)
        if isinstance(b, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), f.name
        else:
            assert a == b, f.name


def _code(text: str) -> list[str]:
    """The program's lines with comments removed, empty ones dropped."""
    out = []
    for ln in text.splitlines():
        ln = re.sub(r"\([^)]*\)", "", ln).strip()
        if ln:
            out.append(ln)
    return out


def _feeds(lines: list[str]) -> set[float]:
    return {float(v) for ln in lines for v in re.findall(r"F([-+0-9.]+)", ln)}


# ----------------------------------------------------------------------------
# the writer
# ----------------------------------------------------------------------------
def test_one_finish_operation_is_todays_program(finish):
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job, write_program

    spec, surface, tp = finish
    profile = profile_from_spec(spec, surface)
    (suffix, text), = write_job(_job(tp, ops=[]), profile)
    assert suffix == "" and text == write_program(tp, profile)


def test_linuxcnc_one_program_tool_changes_in_order(finish):
    """One program; before each operation a retract, M5 (from the second on), the tool
    call, a rapid to the safe height and the operation's own spindle speed; each
    operation's moves carry exactly its tool's feeds."""
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job

    spec, surface, tp = finish
    profile = profile_from_spec(spec, surface)
    (suffix, text), = write_job(_job(tp), profile)
    assert suffix == ""
    code = _code(text)
    calls = [i for i, ln in enumerate(code) if " M6 " in f" {ln} "]
    assert [code[i] for i in calls] == ["T2 M6 G43 H2", "T3 M6 G43 H3", "T1 M6 G43 H1"]
    spindles = [18000, 20000, profile.spindle]
    for j, i in enumerate(calls):
        assert code[i + 1] == "G0 Z3" and code[i + 2] == f"M3 S{spindles[j]:.0f}"
        if j:
            assert code[i - 1] == "M5" and code[i - 2] in ("G0 Z3", "Z3")   # retract, spindle off, change
    bounds = calls + [len(code)]
    want = [{3000.0, 500.0}, {2000.0, 400.0}, {profile.feed, profile.plunge}]
    for j in range(3):
        assert _feeds(code[bounds[j]:bounds[j + 1]]) == want[j]
    assert code[-2:] == ["M5", "M2"]
    assert text.count("M3 ") == 3
    # the header lists the three operations in order
    head = [ln for ln in text.splitlines() if ln.startswith("(operation ")]
    assert [h.split(":")[1].split(",")[0].strip() for h in head] == ["rough", "rest", "finish"]


def test_linuxcnc_job_needs_tool_numbers(finish):
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job
    from fabkit.toolpath.operations import Operation
    from fabkit.toolpath.tools import Tool

    spec, surface, tp = finish
    op = _rough_ops()[0]
    bare = Operation("rough", Tool("flat", 12.7), op.toolpath, levels=1, passes=2)
    with pytest.raises(ValueError, match="needs a number"):
        write_job(_job(tp, ops=[bare]), profile_from_spec(spec, surface))


def test_grbl_one_complete_program_per_operation(finish):
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job

    spec, surface, tp = finish
    gspec = _spec(dialect="grbl")
    profile = profile_from_spec(gspec, surface)
    progs = write_job(_job(tp), profile)
    assert [s for s, _ in progs] == [".1-rough.nc", ".2-rest.nc", ".3-finish.nc"]
    want = [(18000, {3000.0, 500.0}), (20000, {2000.0, 400.0}), (profile.spindle, {profile.feed, profile.plunge})]
    for (suffix, text), (rpm, feeds), n in zip(progs, want, (2, 3, 1)):
        code = _code(text)
        assert code[0] == "G17 G21 G90 G94 G54"
        assert code[1] == "G0 Z3" and code[2] == f"M3 S{rpm:.0f}"
        assert code[-2:] == ["M5", "M30"]
        assert not any(re.search(r"\b[TH]\d|M6\b|G43", ln) for ln in code)
        assert _feeds(code) == feeds
        assert f"load T{n} by hand" in text                       # the tool, in a comment
        assert max(len(ln) for ln in text.splitlines()) <= 70


def test_programs_read_back_to_the_operations(finish):
    """Each operation's moves read back from the written text are its toolpath, to the
    rounding of 4 decimals (0.5e-4 mm per axis); the split of a one-program job by tool
    change gives the same moves as one program per operation."""
    from fabkit.toolpath.program.gcode import profile_from_spec
    from fabkit.toolpath.job import job_figures
    from fabkit.toolpath.program.gcode import write_job

    spec, surface, tp = finish
    ops = _job(tp)
    for sp in (spec, _spec(dialect="grbl")):
        profile = profile_from_spec(sp, surface)
        figures, back = job_figures(ops, write_job(ops, profile), profile)
        for op, prog in zip(ops, back):
            ours = op.toolpath.points
            # moves that round to the previous position are dropped: compare the kept ones
            # (the first against the position above it at the safe height)
            seq = np.round(np.vstack([[*ours[0, :2], SAFE], ours]), 4)
            keep = np.any(np.diff(seq, axis=0) != 0, axis=1)
            want = ours[keep]
            # before: up to the safe height, across to above the first point; after: the
            # retract and (the last program) the park, all at the safe height
            assert prog.points[0, 2] == SAFE and np.allclose(prog.points[1], [*want[0, :2], SAFE], atol=0.5e-4)
            got, after = prog.points[2:2 + len(want)], prog.points[2 + len(want):]
            assert np.max(np.abs(got - want)) <= 0.5e-4 + 1e-12
            assert len(after) <= 2 and np.all(after[:, 2] == SAFE)
        assert [f.kind for f in figures] == ["rough", "rest", "finish"]


def test_per_program_readback_is_the_parse_of_its_text(finish):
    """job_figures' parse of each program (one per operation for grbl, one for LinuxCNC)
    is, field for field, the reader's parse of that text (the machine's checks use it, not
    a second parse)."""
    from fabkit.toolpath.job import job_figures
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job
    from fabkit.toolpath.program.reader import read_program

    spec, surface, tp = finish
    ops = _job(tp)
    for sp, count in ((_spec(dialect="grbl"), len(ops)), (spec, 1)):
        profile = profile_from_spec(sp, surface)
        programs = write_job(ops, profile)
        parsed: list = []
        _, back = job_figures(ops, programs, profile, parsed=parsed)
        assert len(programs) == len(parsed) == count and len(back) == len(ops)
        for (_, text), got in zip(programs, parsed):
            _assert_same_program(got, read_program(text))


def test_operation_time_is_length_over_feed(finish):
    """The rectangle's time in closed form: 2 mm rapid down and 4 mm up at 5000 mm/min,
    2 mm plunge at 500, 44 mm cut at 3000."""
    from fabkit.toolpath.program.gcode import operation_seconds, profile_from_spec

    spec, surface, tp = finish
    want = (6 / 5000 + 2 / 500 + 44 / 3000) * 60.0
    assert operation_seconds(_rough_ops()[0], profile_from_spec(spec, surface)) == pytest.approx(want, rel=1e-12)


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
def test_rs274_reads_the_two_tool_program(finish, tmp_path):
    """LinuxCNC's interpreter accepts the program, M6 included, and executes the tool
    changes, spindle speeds and feeds in the order written."""
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job

    spec, surface, tp = finish
    ops = _job(tp, ops=_rough_ops()[:1])
    (_, text), = write_job(ops, profile_from_spec(spec, surface))
    path = tmp_path / "job.ngc"
    path.write_text(text)
    run = subprocess.run([RS274, "-g", str(path)], stdin=subprocess.DEVNULL, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0 and run.stderr.strip() in ("", "executing"), run.stderr
    out = run.stdout
    assert re.findall(r"CHANGE_TOOL\((\d+)\)", out) == ["2", "1"]
    speeds = [float(v) for v in re.findall(r"SET_SPINDLE_SPEED\(\d+, ([0-9.]+)\)", out)]
    assert speeds == [18000.0, 16000.0]
    feeds = [float(v) for v in re.findall(r"SET_FEED_RATE\(([0-9.]+)\)", out) if float(v) > 0]
    assert feeds[:2] == [500.0, 3000.0] and set(feeds[2:]) == {1200.0, 300.0}
    assert out.count("STOP_SPINDLE_TURNING") >= 2


# ----------------------------------------------------------------------------
# the job and `fabkit gcode`, with a stand-in roughing planner
# ----------------------------------------------------------------------------
from fabkit.toolpath.job import _stock_verification as _STOCK_VERIFICATION


@pytest.fixture
def roughing(monkeypatch):
    """fabkit.toolpath.rough.roughing replaced by one returning the hand-built rough and rest
    operations; every spec counts as asking for roughing."""
    from fabkit.toolpath import job
    from fabkit.toolpath.tools import Tool

    fake = types.ModuleType("fabkit.toolpath.rough.roughing")
    fake.plan_operations = lambda spec, surface, finish: _rough_ops()
    fake.finish_tool = lambda spec: Tool.ball(spec.tool.diameter, number=spec.tool.number)
    monkeypatch.setitem(sys.modules, "fabkit.toolpath.rough.roughing", fake)
    import fabkit.toolpath.rough as pkg

    monkeypatch.setattr(pkg, "roughing", fake, raising=False)
    monkeypatch.setattr(job, "has_roughing", lambda spec: True)
    # the hand-built operations are a rectangle cut into the block, not a roughing of its
    # design: the whole job's simulation on the stock is tested in tests/test_stock.py and
    # with the real planner in tests/test_roughing_job.py
    monkeypatch.setattr(job, "_stock_verification", lambda spec, surface, ops, readback: (None, {}))
    return fake


def _numbered(**machining):
    raw = small_raw(**machining)
    raw["tool"]["number"] = 1
    return raw


def test_gcode_grbl_writes_every_program_and_reports_each(cli, tmp_path, roughing):
    spec = write_spec(tmp_path, _numbered(dialect="grbl"))
    code, out, err = cli("gcode", spec, "-o", "job.ngc", "--json")
    assert code == 0, err
    s = json.loads(out)
    names = ["job.1-rough.nc", "job.2-rest.nc", "job.3-finish.nc"]
    assert s["programs"] == names and s["program_paths"] == names
    assert s["program"] == s["program_path"] == "job.3-finish.nc"      # the finishing program
    for n in names:
        assert (tmp_path / n).is_file()
    assert not (tmp_path / "job.ngc").exists()
    ops = s["operations"]
    assert [o["kind"] for o in ops] == ["rough", "rest", "finish"]
    assert [o["tool"]["number"] for o in ops] == [2, 3, 1]
    assert [o["lines"] for o in ops] == [(tmp_path / n).read_text().count("\n") for n in names]
    assert s["lines"] == sum(o["lines"] for o in ops)
    assert all(o["estimator"] == "length/feed" for o in ops)
    # read back: the rectangle and the park from its last point (2, 10) to X0 Y0 at the safe height
    want = (6 / 5000 + 2 / 500 + 44 / 3000 + np.hypot(2, 10) / 5000) * 60.0
    assert ops[0]["time_s"] == pytest.approx(want, abs=0.05)
    assert s["estimated_time_s"] == pytest.approx(sum(o["length_over_feed_s"] for o in ops), abs=0.2)
    assert s["steps"][0].startswith("rough: load T2") and "job.1-rough.nc" in s["steps"][0]
    md = (tmp_path / "job.setup.md").read_text()
    assert "## Operations" in md and "`job.2-rest.nc`" in md


def test_gcode_json_keeps_every_key(cli, tmp_path, monkeypatch):
    """The job with roughing adds keys; every key of today's --json stays."""
    spec = write_spec(tmp_path, _numbered())
    code, out, err = cli("gcode", spec, "-o", "one.ngc", "--json")
    assert code == 0, err
    before = set(json.loads(out))
    from fabkit.toolpath.tools import Tool
    from fabkit.toolpath import job

    fake = types.ModuleType("fabkit.toolpath.rough.roughing")
    fake.plan_operations = lambda spec, surface, finish: _rough_ops()
    fake.finish_tool = lambda spec: Tool.ball(spec.tool.diameter, number=spec.tool.number)
    monkeypatch.setitem(sys.modules, "fabkit.toolpath.rough.roughing", fake)
    import fabkit.toolpath.rough as pkg

    monkeypatch.setattr(pkg, "roughing", fake, raising=False)   # also when the real one is imported
    monkeypatch.setattr(job, "has_roughing", lambda spec: True)
    monkeypatch.setattr(job, "_stock_verification", lambda spec, surface, ops, readback: (None, {}))
    code, out, err = cli("gcode", spec, "-o", "two.ngc", "--json")
    assert code == 0, err
    after = json.loads(out)
    assert before <= set(after)
    assert {"operations", "programs", "steps", "program_paths"} <= set(after) - before
    assert after["programs"] == ["two.ngc"]
    assert [o["program"] for o in after["operations"]] == ["two.ngc"] * 3
    text = (tmp_path / "two.ngc").read_text()
    assert [ln for ln in text.splitlines() if "M6" in ln] == ["T2 M6 G43 H2", "T3 M6 G43 H3", "T1 M6 G43 H1"]
    # the operations' lines and times partition the program's
    assert sum(o["lines"] for o in after["operations"]) == text.count("\n")
    from fabkit.toolpath.program.reader import estimate_time, read_program

    whole = estimate_time(read_program(text), 5000.0)
    assert after["estimated_time_s"] == pytest.approx(whole, abs=0.05)
    assert sum(o["length_over_feed_s"] for o in after["operations"]) == pytest.approx(whole, abs=0.15)


def test_gcode_summary_names_each_operation(cli, tmp_path, roughing):
    spec = write_spec(tmp_path, _numbered())
    code, out, err = cli("gcode", spec, "-o", "s.ngc")
    assert code == 0, err
    ops = [ln.strip() for ln in out.splitlines() if re.match(r"\s+\d\. ", ln)]
    assert [o.split(":")[0] for o in ops] == ["1. rough", "2. rest", "3. finish"]
    assert "T2 flat 12.7 mm, 1 level, 2 passes" in ops[0] and "(length/feed)" in ops[0]
    assert "operations: 3" in out


def test_gcode_writes_nothing_when_a_later_program_fails(cli, tmp_path, roughing, monkeypatch):
    """All or nothing: the second program's write fails, so no program, sheet or
    preview appears (the first program's staged file is discarded too)."""
    import fabkit.io as fio
    from fabkit.errors import OutputError

    real = fio._Outputs.write
    calls = []

    def failing(self, path, data):
        calls.append(path)
        if len(calls) == 2:
            raise OutputError("cannot write output: disk full (simulated)", file=str(path))
        return real(self, path, data)

    monkeypatch.setattr(fio._Outputs, "write", failing)
    spec = write_spec(tmp_path, _numbered(dialect="grbl"))
    before = set(p.name for p in tmp_path.iterdir())
    code, out, err = cli("gcode", spec, "-o", "job.ngc")
    assert code != 0 and "disk full" in err
    assert set(p.name for p in tmp_path.iterdir()) == before      # no program, sheet, temporary


def test_gcode_refuses_a_program_path_before_planning(cli, tmp_path, roughing):
    """A grbl job's per-operation file that cannot be written is refused at once (exit 2)."""
    (tmp_path / "job.2-rest.nc").mkdir()
    spec = write_spec(tmp_path, _numbered(dialect="grbl"))
    code, out, err = cli("gcode", spec, "-o", "job.ngc")
    assert code == 2 and "job.2-rest.nc" in err
    assert not (tmp_path / "job.1-rough.nc").exists() and not (tmp_path / "job.setup.json").exists()


def test_machine_time_per_operation(finish):
    """With a machine profile each operation's time is the controller's planner on its
    own program (grbl: the very file written), and the estimator is named so."""
    from fabkit.machine.planner import run_time
    from fabkit.machine.profile import grbl_defaults
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job
    from fabkit.toolpath.job import job_figures

    spec, surface, tp = finish
    machine = grbl_defaults()
    profile = profile_from_spec(_spec(dialect="grbl"), surface)
    ops = _job(tp)
    progs = write_job(ops, profile)
    figures, _ = job_figures(ops, progs, profile, machine)
    for f, (_, text) in zip(figures, progs):
        assert f.estimator == "machine planner"
        assert f.run_s == pytest.approx(run_time(text, machine).total_s, rel=1e-12)
        # acceleration and grbl's default 500 mm/min rates only slow it down
        assert f.run_s >= f.estimate_s


def test_report_page_shows_operations_and_stock(finish, roughing):
    """The report's setup-sheet section carries the steps (a numbered list) and the
    operations table; the stock pictures get their own section."""
    import base64

    from fabkit.report import _stock_section, markdown_html
    from fabkit.toolpath.job import run_job
    from fabkit.toolpath.program.setup_sheet import sheet_markdown

    spec, surface, tp = finish
    res = run_job(spec, surface, verify=False)
    html = markdown_html(sheet_markdown(res.sheet, None))
    steps = re.search(r"<ol>(.*?)</ol>", html).group(1)
    assert steps.count("<li>") == 4 and "T2 flat end mill 12.7" in steps   # three tools, then run
    table = re.search(r"<table>(.*?)</table>", html).group(1)
    rows = re.findall(r"<tr>(.*?)</tr>", table)
    assert len(rows) == 4 and "<th>operation</th>" in rows[0]
    assert [re.findall(r"<td>(.*?)</td>", r)[1] for r in rows[1:]] == ["rough", "rest", "finish"]
    page = "".join(_stock_section({"rough": b"\x89PNG-rough", "finish": b"\x89PNG-finish"}))
    assert base64.b64encode(b"\x89PNG-rough").decode() in page and "after finishing" in page
    assert _stock_section({}) == []


def test_same_tool_twice_is_not_changed_again(finish):
    """Rest passes with the finishing ball, then the finish: one tool change for both
    (LinuxCNC), and the sheet's steps keep the tool; the operations still split the
    program (each from its own comment) and their lines add up to it."""
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job
    from fabkit.toolpath.job import job_figures
    from fabkit.toolpath.operations import Operation
    from fabkit.toolpath.tools import Tool

    spec, surface, tp = finish
    rough, rest = _rough_ops()
    rest_ball = Operation("rest", Tool.ball(6.0, number=1), rest.toolpath, leave=0.3, levels=1, passes=1)
    ops = _job(tp, ops=[rough, rest_ball])
    profile = profile_from_spec(spec, surface)
    (_, text), = write_job(ops, profile)
    code = _code(text)
    assert [ln for ln in code if "M6" in ln] == ["T2 M6 G43 H2", "T1 M6 G43 H1"]
    assert code.count("M5") == 2                       # before the one change, and at the end
    figures, back = job_figures(ops, [("", text)], profile)
    assert sum(f.lines for f in figures) == text.count("\n")
    assert [len(b) > 0 for b in back] == [True, True, True]
    rest_feeds = back[1].feed[np.isfinite(back[1].feed)]
    assert set(rest_feeds.tolist()) == {profile.feed, profile.plunge}     # the ball's own feeds


def test_sheet_job_verification_is_plain_json(finish):
    """Whatever the stock model reports (numpy numbers, tuples, inf) the sheet stays
    strict JSON."""
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job
    from fabkit.toolpath.job import job_figures
    from fabkit.toolpath.program.setup_sheet import setup_sheet, sheet_json

    class Check:
        failures = []

        def to_json(self):
            return {"ok": np.bool_(True), "seconds": 1.5, "operations": [{"bounds": (np.float64(0.49), np.inf),
                                                                           "moves": np.int64(7)}]}

    spec, surface, tp = finish
    profile = profile_from_spec(spec, surface)
    ops = _job(tp)
    figures, _ = job_figures(ops, write_job(ops, profile), profile)
    sheet = setup_sheet(spec, surface, tp, profile, "a.ngc", None, 1.0, 10, operations=figures, job_check=Check())
    back = json.loads(sheet_json(sheet))
    assert back["job_verification"] == {"ok": True, "operations": [{"bounds": [0.49, None], "moves": 7}]}


@pytest.fixture
def stock_model(monkeypatch):
    """fabkit.toolpath.cut.stock replaced by a recorder: it receives the moves READ BACK per
    operation and answers with a given verdict and one picture per snapshot."""
    import fabkit.toolpath.cut as pkg
    from fabkit.toolpath import job

    # the job's own stock verification (the `roughing` fixture turns it off), on this recorder
    monkeypatch.setattr(job, "_stock_verification", _STOCK_VERIFICATION)
    seen = {}
    verdict = {"failures": []}

    class Cut:
        def __init__(self, n):
            self.snapshots = [f"after {i}" for i in range(n)]
            self.design = "design"
            self.failures = list(verdict["failures"])

        def to_json(self):
            return {"ok": not self.failures, "failures": self.failures}

    def verify_job(surface, operations, tolerance, *, scallop=None, depth_of_cut=None, measure="normal"):
        seen.update(operations=operations, tolerance=tolerance, scallop=scallop, depth_of_cut=depth_of_cut)
        return Cut(len(operations))

    def stock_png(snapshot, design, *, title="", tolerance=0.0):
        return f"PNG {snapshot}: {title}".encode()

    fake = types.ModuleType("fabkit.toolpath.cut.stock")
    fake.verify_job, fake.stock_png = verify_job, stock_png
    monkeypatch.setitem(sys.modules, "fabkit.toolpath.cut.stock", fake)
    monkeypatch.setattr(pkg, "stock", fake, raising=False)
    return seen, verdict


def test_gcode_writes_the_stock_pictures_and_the_whole_job_verdict(cli, tmp_path, roughing, stock_model):
    seen, verdict = stock_model
    spec = write_spec(tmp_path, _numbered())
    code, out, err = cli("gcode", spec, "-o", "w.ngc", "--json")
    assert code == 0, err
    s = json.loads(out)
    # the stock model replayed the three operations from the program text, each with its tool
    ops = seen["operations"]
    assert [(o.kind, o.tool.number) for o in ops] == [("rough", 2), ("rest", 3), ("finish", 1)]
    assert np.max(np.abs(ops[0].toolpath.points[2:8] - RECT)) <= 0.5e-4
    assert seen["tolerance"] == 0.02 and seen["scallop"] == 0.1
    # after roughing: the stock after the last operation before the finish (rest)
    assert (tmp_path / "w.stock-rough.png").read_bytes() == b"PNG after 1: stock after roughing"
    assert (tmp_path / "w.stock-finish.png").read_bytes() == b"PNG after 2: stock after finishing"
    assert s["stock_paths"] == {"rough": "w.stock-rough.png", "finish": "w.stock-finish.png"}
    assert s["job_verification"] == {"ok": True, "failures": []}
    md = (tmp_path / "w.setup.md").read_text()
    assert "![stock after rough](w.stock-rough.png)" in md and "within its bounds" in md
    # a failure of the whole job fails the command (exit 1, outputs kept for inspection)
    verdict["failures"] = ["operation 3 (finish): removes 7.3 mm, more than its depth of cut 6 mm"]
    code, out, err = cli("gcode", spec, "-o", "w.ngc")
    assert code == 1 and "whole job: operation 3 (finish): removes 7.3 mm" in err
    assert "FAILED" in out


def test_sheet_says_where_a_tool_left_material_for_the_next(finish):
    """The stock check's areas above a bound become the sheet's ``left_for_next``: where a
    tool could not reach (the next operation takes it) and where it reached but did not
    hold the bound; lengths in program units (an inch program: mm / 25.4, areas / 25.4^2)."""
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job
    from fabkit.toolpath.job import job_figures
    from fabkit.toolpath.program.setup_sheet import _left_for_next, setup_sheet, sheet_markdown

    cuts = [{"unreachable_area": 12.5, "unreachable": 0.25, "unreachable_at": (254.0, 50.8),
             "over_area": 0.0, "over_reachable": 0.0, "over_at": None},
            {"unreachable_area": 0.0, "unreachable": 0.0, "unreachable_at": None,
             "over_area": 2.54 * 2.54, "over_reachable": 0.0254, "over_at": (25.4, 2.54)},
            {"unreachable_area": 0.0, "unreachable": 0.0, "unreachable_at": None,
             "over_area": 0.0, "over_reachable": 0.0, "over_at": None}]

    class Check:
        failures = []

        def to_json(self):
            return {"ok": True, "operations": cuts}

    spec, surface, tp = finish
    profile = profile_from_spec(spec, surface)
    ops = _job(tp)
    figures, _ = job_figures(ops, write_job(ops, profile), profile)
    sheet = setup_sheet(spec, surface, tp, profile, "a.ngc", None, 1.0, 10, operations=figures, job_check=Check())
    numbers = [o["tool"]["number"] for o in sheet["operations"]]
    assert sheet["left_for_next"] == [
        {"operation": "rough", "tool": numbers[0], "kind": "unreachable", "area": 12.5, "largest": 0.25,
         "at": [254.0, 50.8], "taken_by": {"operation": "rest", "tool": numbers[1]}},
        {"operation": "rest", "tool": numbers[1], "kind": "over", "area": 6.4516, "largest": 0.0254,
         "at": [25.4, 2.54], "taken_by": {"operation": "finish", "tool": numbers[2]}}]
    md = sheet_markdown(sheet, None)
    assert "cannot reach its allowance over 12.5 mm^2, up to 0.25 mm above its bound (largest at X254 Y50.8)" in md
    assert "the rest" in md and "takes what is left" in md
    # an inch program: the same places in inches
    inch = _left_for_next(sheet["operations"], {"operations": cuts}, 1.0 / 25.4)
    assert inch[0]["at"] == [10.0, 2.0]
    assert inch[1]["area"] == pytest.approx(0.01, rel=1e-9)
    assert inch[1]["largest"] == pytest.approx(0.001, rel=1e-9)
    assert inch[1]["taken_by"]["operation"] == "finish"


@pytest.mark.parametrize("units", ["mm", "in"])
@pytest.mark.parametrize("same_tool", [False, True])
def test_the_finish_written_and_read_alone_is_taken_as_it_is(finish, units, same_tool):
    """write_job(..., finish=(toolpath, text)) and job_figures(..., finish=(text, Program))
    take the finishing operation's lines and moves from its program written and read
    alone: the job's text is the same string as written whole, and its parse the same,
    field for field, as the reader's of the whole text (mm and inch; the finish after a
    tool change, and after a rest with its own tool, no change); a finishing tool with
    its own feed writes and reads the job whole (the same text either way)."""
    from fabkit.toolpath.job import job_figures
    from fabkit.toolpath.operations import Operation
    from fabkit.toolpath.program.gcode import profile_from_spec, write_job, write_program
    from fabkit.toolpath.program.reader import read_program
    from fabkit.toolpath.tools import Tool

    spec, surface, tp = finish
    sp = _spec(units=units)
    profile = profile_from_spec(sp, surface)
    ops = _rough_ops()
    if same_tool:     # the rest with the finishing ball: no tool change before the finish
        ops[-1] = Operation("rest", Tool.ball(6.0, number=1), ops[-1].toolpath, leave=ops[-1].leave)
    cases = [Tool.ball(6.0, number=1), Tool.ball(6.0, number=1, feed=777.0)]
    for fin_tool in cases:
        job = ops + [Operation("finish", fin_tool, tp, passes=tp.passes)]
        alone = write_program(tp, profile)
        whole = write_job(job, profile)
        shared = write_job(job, profile, finish=(tp, alone))
        assert shared == whole
        (_, text), = shared
        want = read_program(text)
        parsed: list = []
        _, back = job_figures(job, shared, profile, parsed=parsed, finish=(alone, read_program(alone)))
        got, = parsed
        # the lines after the job's last operation comment are the finish's own: taken as
        # they are for the ball with the job's feeds, read whole for the one with its own
        from fabkit.toolpath.job import _op_line_ranges, _read_with_finish

        first = _op_line_ranges(text, len(job))[-1][0]
        took = _read_with_finish(text.splitlines(), first, (alone, read_program(alone)))
        assert (took is not None) == (fin_tool.feed is None)
        _assert_same_program(got, want)
