"""The toolpath job's time guard is a budget: ``machining.max_time`` in the spec,
``--max-time SECONDS`` on gcode and report (the option wins). A job estimated
beyond it is refused before planning (exit 2, one line naming both ways to raise
it, nothing written); a raised budget lets the same job run."""

from __future__ import annotations

import pytest
from conftest import write_spec

from fabkit.tolerances import DEFAULT

# a cheap job: a 6 x 10 mm plane of slope 0.5, 6 mm ball, coarse scallop (a few passes)
RAW = {"name": "tiny", "units": "mm",
       "surface": {"height": "0.5*x", "x": [0, 6], "y": [0, 10], "top": 3.0},
       "stock": {"thickness": 20, "depth_limit": 10},
       "tool": {"shape": "ball", "diameter": 6, "reach": 30},
       "machining": {"scallop": 0.2, "tolerance": 0.02, "direction": "x"}}


def _spec(tmp_path, **machining):
    raw = {**RAW, "machining": {**RAW["machining"], **machining}}
    return write_spec(tmp_path, raw)


def _refused(code, err, tmp_path):
    assert code == 2
    assert "--max-time" in err and "machining.max_time" in err
    assert "limit 0.001 s" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not list(tmp_path.glob("p*")), "nothing is written on a refusal"


def test_the_option_refuses_beyond_a_tiny_budget_and_names_both_ways(cli, tmp_path):
    code, out, err = cli("gcode", _spec(tmp_path), "--no-verify", "-o", tmp_path / "p.ngc",
                         "--max-time", "0.001")
    _refused(code, err, tmp_path)


def test_the_spec_key_refuses_and_the_option_overrides_it(cli, tmp_path):
    spec = _spec(tmp_path, max_time=0.001)
    code, out, err = cli("gcode", spec, "--no-verify", "-o", tmp_path / "p.ngc")
    _refused(code, err, tmp_path)
    # the same job with the budget raised on the command line runs and writes its program
    code, out, err = cli("gcode", spec, "--no-verify", "-o", tmp_path / "p.ngc", "--max-time", "1e5")
    assert code == 0, err
    text = (tmp_path / "p.ngc").read_text()
    assert "G1" in text and text.rstrip().endswith(("M30", "M2"))


def test_a_raised_spec_key_lets_the_job_run(cli, tmp_path):
    code, out, err = cli("gcode", _spec(tmp_path, max_time=1e5), "--no-verify", "-o", tmp_path / "p.ngc")
    assert code == 0, err
    assert (tmp_path / "p.ngc").exists()


@pytest.mark.parametrize("value", ["0", "-3"])
def test_a_budget_not_above_zero_is_refused_naming_the_option(cli, tmp_path, value):
    code, out, err = cli("gcode", _spec(tmp_path), "-o", tmp_path / "p.ngc", f"--max-time={value}")
    assert code == 2 and "--max-time" in err and "> 0" in err
    assert not (tmp_path / "p.ngc").exists()


def test_the_spec_key_is_validated_and_defaults_to_the_tolerance(tmp_path):
    from fabkit.errors import SpecError
    from fabkit.spec import load_spec

    assert load_spec(_spec(tmp_path)).machining.max_time is None     # the guard uses DEFAULT's 60 s
    assert DEFAULT.max_plan_seconds == 60.0
    with pytest.raises(SpecError) as e:
        load_spec(_spec(tmp_path, max_time=-1))
    assert "machining.max_time" in str(e.value)


def test_report_takes_the_option(tmp_path):
    from fabkit.cli import build_parser

    args = build_parser().parse_args(["report", "s.yaml", "--max-time", "300"])
    assert args.max_time == 300.0
