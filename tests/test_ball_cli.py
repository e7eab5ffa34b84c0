"""simulation.model: ball through the commands (simulate, sweep, check, explore, robustness).

A ball wider than the channel's valley (radius 1/(2c) = 6.5 cm on the paper's
surface) bridges at once: the cheap case that still runs every command's ball
path; a 2.5 cm ball on the cheap study spec runs the real dynamics.
"""

from __future__ import annotations

import json

import pytest

from conftest import ROOT, SMALL_STUDY, mutated, run_cli, write_spec

WIDE = {"simulation.model": "ball", "ball.diameter": 15.0, "ramp.samples": 6}


def test_check_names_bridging(tmp_path):
    spec = write_spec(tmp_path, mutated(WIDE))
    code, out, err = run_cli(["check", spec, "--json", "--no-progress"])
    assert code == 1
    assert err.count("\n") == 1 and "bridged" in err and "bridges" in err and "two points" in err
    d = json.loads(out)
    assert d["safe"] is False and d["first_failure"]["outcome"] == "bridged"
    assert d["ball"]["unsafe_counts"]["bridged"] == 6


def test_model_must_name_a_ball(tmp_path):
    spec = write_spec(tmp_path, mutated({"simulation.model": "ball"}, drop=("ball",)))
    code, out, err = run_cli(["simulate", spec, "--v-in", "40"])
    assert code == 2 and "simulation.model" in err and "ball section" in err
    spec = write_spec(tmp_path, mutated({"simulation.model": "marble"}))
    code, out, err = run_cli(["simulate", spec, "--v-in", "40"])
    assert code == 2 and "simulation.model" in err
    spec = write_spec(tmp_path, mutated({"simulation.model": "ball", "simulation.nonlinear_damping": 0.1}))
    code, out, err = run_cli(["simulate", spec, "--v-in", "40"])
    assert code == 2 and "simulation.nonlinear_damping" in err
    spec = write_spec(tmp_path, mutated({"simulation.model": "ball", "ball.friction": -1}))
    code, out, err = run_cli(["simulate", spec, "--v-in", "40"])
    assert code == 2 and "ball.friction" in err


def test_simulate_with_the_ball(tmp_path):
    raw = mutated({**SMALL_STUDY, "simulation.model": "ball", "simulation.t_max": 8.0})
    spec = write_spec(tmp_path, raw)
    code, out, err = run_cli(["simulate", spec, "--v-in", "50", "--json"])
    assert code == 0, err
    d = json.loads(out)
    assert d["model"] == "ball" and d["outcome"] == "escaped" and d["bounces"] == 2
    assert 0.1 < d["max_slip"] < 1.0 and d["radius"] == 1.25
    # with a friction coefficient below what the rolling needs: slipped (and the summary's line)
    raw = mutated({**SMALL_STUDY, "simulation.model": "ball", "simulation.t_max": 8.0, "ball.friction": 0.05})
    code, out, err = run_cli(["simulate", write_spec(tmp_path, raw, "f.yaml"), "--v-in", "50"])
    assert "outcome: slipped" in out and "largest |F_t|/N" in out and "ball.friction 0.05" in out


def test_explore_and_robustness_take_the_model(tmp_path):
    spec = write_spec(tmp_path, mutated({**SMALL_STUDY, **WIDE}))
    code, out, err = run_cli(["explore", spec, "--vary", "ball.diameter=14,16", "--v-in", "30", "80", "4",
                              "--no-progress", "--json"])
    assert code == 0, err
    d = json.loads(out)
    assert all(not x["safe"] for x in d["designs"])
    code, out, err = run_cli(["robustness", spec, "--v-in", "40", "44", "2", "--sigma-y", "0.05",
                              "--sigma-vy", "0.1", "--samples", "3", "--no-progress", "--json"])
    assert code in (0, 1), err
    d = json.loads(out)
    assert d["model"] == "ball"
    assert "bridged" in json.dumps(d)


MM = ROOT / "tests" / "fixtures" / "ball" / "mm_formula.yaml"
#: the independent implementation (tests/ball_newton_euler.py, scipy DOP853 at rtol 1e-11) on
#: the mm formula (`python benchmarks/ball_reference.py --vc` recomputes both, in about 3 min):
#: v_critical at t_max 8 s by plain bisection to +- 4.0e-5 mm/s; the launch at 232.85 mm/s,
#: inside the two-bounce window 204..262 mm/s: escaped after 2 bounces with this v_out
MM_VC_INDEPENDENT = 408.516790
MM_WINDOW_LAUNCH = (232.85, 2, 75.00250734694175)


def test_sweep_and_simulate_agree_with_the_independent_implementation_in_mm():
    """Another formula, in mm (tests/fixtures/ball/mm_formula.yaml: the paper's surface read
    in mm, the channel's width varying along x), with a 25 mm ball: `fabkit sweep` finds
    v_critical within 1e-4 of the independent implementation's (its samples 1e-6 either side
    of it are classified as that implementation classifies them: they agree to 1e-6; a
    wider bracket costs a ball launch near v_critical a bisection round), and `fabkit simulate`
    inside a two-bounce window gives its bounce count exactly and v_out to 1e-3 (they agree
    to 1e-10)."""
    vc = MM_VC_INDEPENDENT
    code, out, err = run_cli(["sweep", MM, "--v-in", vc * (1 - 1e-6), vc * (1 + 1e-6), "2", "--json",
                              "--no-progress"])
    assert code == 0, err
    sw = json.loads(out)
    assert sw["bounces"] == [1, 1] and sw["outcome"] == ["captured", "escaped"]
    assert sw["v_critical"] == pytest.approx(vc, rel=1e-4)
    assert sw["v_critical"] == pytest.approx(vc, rel=1e-6)     # what they give
    assert sw["v_critical_error"] <= 1e-6 * sw["v_critical"]
    v, bounces, v_out = MM_WINDOW_LAUNCH
    code, out, err = run_cli(["simulate", MM, "--v-in", v, "--json"])
    assert code == 0, err
    sim = json.loads(out)
    assert sim["outcome"] == "escaped" and sim["bounces"] == bounces
    assert sim["v_out"] == pytest.approx(v_out, rel=1e-3)
    assert sim["v_out"] == pytest.approx(v_out, rel=1e-10)    # what they give
