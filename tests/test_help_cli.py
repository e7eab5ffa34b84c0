"""What fabkit tells a new user: --help with every option's meaning and unit, every
exit code, and a readable calibration table."""

from __future__ import annotations

import argparse
import math

import pytest

from fabkit.cli import build_parser

from conftest import PAPER


def _subparsers():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return parser, sub.choices


def test_top_level_help_lists_every_exit_code(cli):
    code, out, err = cli("--help")
    assert code == 0
    for line in ("0  ok", "1  a check failed", "2  bad input", "3  internal error", "130  interrupted"):
        assert line in out, line


@pytest.mark.parametrize("option, words", [
    ("--v-in", ("units/s",)), ("--sigma-y", ("design units",)), ("--sigma-vy", ("units/s",)),
    ("--samples", ("per entry speed",)), ("--out", ("row per launch", ".csv")),
    ("--plot", ("extension", ".pdf")), ("--scheduler", ("Dask", "address")), ("--tolerance", ("mm",)),
    ("--dt", ("time unit",)), ("--dx", ("kink length",)), ("--t-max", ("time unit",)), ("--fps", ("1/s",)),
])
def test_every_option_says_what_it_is_and_its_unit(option, words):
    _, commands = _subparsers()
    seen = 0
    for name, sub in commands.items():
        for action in sub._actions:
            if option in action.option_strings:
                seen += 1
                assert action.help and all(w in action.help for w in words), (name, option, action.help)
    assert seen


def test_no_option_without_help():
    _, commands = _subparsers()
    for name, sub in commands.items():
        for action in sub._actions:
            assert action.help, (name, action.option_strings or action.dest)


def test_calibrate_prints_a_short_table_unless_asked(cli, tmp_path):
    from conftest import mutated, write_spec

    lossless = write_spec(tmp_path, mutated({"simulation.damping": 0}))      # the closed form's table
    code, out, err = cli("calibrate", lossless)
    assert code == 0
    lines = out.splitlines()
    assert len(lines) < 20 and "392 more rows; --all prints every row" in out
    # the range line, against the closed form computed here: v = sqrt(2 g H / (1 + k)), k = 2/5, cm
    lo, hi = (math.sqrt(2 * 980.665 * h / 1.4) for h in (0.2, 4.5))
    assert f"range: H 0.2 .. 4.5 cm, v_in {lo:.8g} .. {hi:.8g} cm/s, 400 rows" in out
    code, out_all, err = cli("calibrate", lossless, "--all")
    assert code == 0 and "more rows" not in out_all
    rows = [ln for ln in out_all.splitlines() if ln[:14].strip().replace(".", "", 1).isdigit()]
    assert len(rows) == 400


def test_stage_bar_names_the_running_stage_on_a_terminal(monkeypatch):
    """gcode and precision show their stages (after the delay), nothing when quick or off a terminal."""
    import io
    import sys
    import time

    from fabkit.commands._common import stage_bar

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    step, close = stage_bar(3, False, "gcode", delay=0.2)
    step("planning the passes")
    time.sleep(0.5)
    step("writing the program")
    close()
    shown = term.getvalue()
    assert "gcode: 1/3 stages" in shown and "writing the program" in shown
    quick = Terminal()
    monkeypatch.setattr(sys, "stderr", quick)
    step, close = stage_bar(3, False, "gcode", delay=30)
    step("planning the passes")
    close()
    assert "stages" not in quick.getvalue()
    step, close = stage_bar(3, True, "gcode")     # --no-progress
    step("x")
    close()
