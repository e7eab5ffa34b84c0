"""The stage bars of ``fabkit sweep`` and ``fabkit check``: on a terminal each stage is
named as it starts (the launches with their count, then the refinement and the error
estimate), the summary is printed on stdout after the bar is closed, and nothing is drawn
with --json, --no-progress or off a terminal."""

from __future__ import annotations

import contextlib
import io
import json

import pytest

from conftest import SMALL_STUDY, mutated, write_spec


class Terminal(io.StringIO):
    def isatty(self):
        return True


def _run(argv, err):
    from fabkit.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    return write_spec(tmp_path_factory.mktemp("stages"), mutated(SMALL_STUDY), "small.yaml")


def test_sweep_names_its_stages_on_a_terminal(small, monkeypatch):
    from fabkit.commands import _common

    monkeypatch.setattr(_common, "BAR_DELAY_S", 0.0)
    code, out, err = _run(["sweep", small, "--v-in", "30", "80", "16"], Terminal())
    assert code == 0, err
    for name in ("compiling or loading the simulator", "launching 16 speeds", "refining v_critical and the windows",
                 "estimating the v_out error"):
        assert name in err, name
    # the stages in the order they run
    assert err.index("launching 16 speeds") < err.index("refining") < err.index("estimating")
    assert out.startswith("sweep: 16 launches") and "stages" not in out
    # --json, --no-progress: nothing on the terminal, the same numbers
    code, js, quiet = _run(["sweep", small, "--v-in", "30", "80", "16", "--json"], Terminal())
    assert code == 0 and quiet == ""
    assert json.loads(js)["v_critical"] is not None
    code, _, quiet = _run(["sweep", small, "--v-in", "30", "80", "16", "--no-progress"], Terminal())
    assert code == 0 and quiet == ""


def test_check_names_its_stages_on_a_terminal(small, monkeypatch):
    from fabkit.commands import _common

    monkeypatch.setattr(_common, "BAR_DELAY_S", 0.0)
    code, out, err = _run(["check", small], Terminal())
    assert code in (0, 1), err
    assert "launching the ramp's 8 heights" in err and "refining v_critical and the windows" in err
    assert out.startswith("check: 8 release heights")
    code, _, quiet = _run(["check", small, "--json"], Terminal())
    assert code in (0, 1) and quiet == ""


def test_ramp_and_analyze_name_their_stages_on_a_terminal(tmp_path, monkeypatch):
    import lab_sim as L
    from conftest import PAPER
    from fabkit.commands import _common
    from test_lab_analyze import _write

    monkeypatch.setattr(_common, "BAR_DELAY_S", 0.0)
    spec = write_spec(tmp_path, mutated({"ramp.samples": 60, "simulation.rtol": 1e-7, "simulation.atol": 1e-9,
                                         "simulation.t_max": 20}))
    code, out, err = _run(["ramp", spec, "-o", tmp_path / "r.stl"], Terminal())
    assert code == 0, err
    names = ["calibrating the ramp", "checking: launching the ramp's 60 heights", "placing the marks",
             "building the solid"]
    assert all(n in err for n in names) and [err.index(n) for n in names] == sorted(err.index(n) for n in names)
    assert out.startswith("ramp: ")
    code, _, quiet = _run(["ramp", spec, "-o", tmp_path / "r2.stl", "--no-progress"], Terminal())
    assert code == 0 and quiet == ""
    track = _write(tmp_path, "release.csv", L.run((-28.0, 6.0, 0.0, 0.0), 0.15, 3.0, escape=False), seed=1)
    code, out, err = _run(["analyze", PAPER, track], Terminal())
    assert code == 0, err
    assert "reading 1 track" in err and "simulating the tracks and fitting the losses" in err
    code, _, quiet = _run(["analyze", PAPER, track, "--json"], Terminal())
    assert code == 0 and quiet == ""


def test_the_compile_notice_becomes_the_running_stage(small, monkeypatch):
    """On a terminal with a bar, the simulator's 'compiling ...' line names the running stage
    instead of being written into the bar; with --no-progress it is printed as before."""
    from fabkit.commands import _common
    from fabkit.physics.engine import batch

    real = batch.engine

    def engine(problem, notify=None):
        if notify is not None:      # the load before the launches (the launches load it quietly)
            notify("compiling the simulator for this surface (once, about 20 s)")
        return real(problem)

    monkeypatch.setattr(_common, "BAR_DELAY_S", 0.0)
    monkeypatch.setattr(batch, "engine", engine)
    code, out, err = _run(["sweep", small, "--v-in", "30", "80", "16"], Terminal())
    assert code == 0, err
    assert "stages" in err and "| 00:00, compiling the simulator for this surface (once, about 20 s)" in err
    assert "\ncompiling" not in err and not err.startswith("compiling")
    code, out, err = _run(["sweep", small, "--v-in", "30", "80", "16", "--no-progress"], Terminal())
    assert code == 0 and err == "compiling the simulator for this surface (once, about 20 s)\n"


def test_a_launch_bar_never_reads_100_percent_while_the_refinement_runs(monkeypatch):
    """explore and phi4's sweep launch more than they estimate (the refinement): the bar's
    total moves ahead of the count and the bar says it is refining, instead of sitting at
    100 % for tens of seconds."""
    import re
    import sys

    from fabkit.commands import _common

    monkeypatch.setattr(_common, "BAR_DELAY_S", 0.0)
    err = Terminal()
    monkeypatch.setattr(sys, "stderr", err)
    cb, close = _common.progress_bar(10, False, "explore")
    import time

    for done in (4, 10, 13, 20, 31):
        time.sleep(0.12)          # tqdm redraws at most every 0.1 s
        cb(done)
    close()
    frames = [f for f in err.getvalue().replace("\r", "\n").split("\n") if "%" in f]
    percents = [int(m.group(1)) for f in frames for m in [re.search(r"(\d+)%", f)] if m]
    assert percents and max(percents) < 100, frames
    assert any("explore: refining" in f and "31/" in f for f in frames), frames
