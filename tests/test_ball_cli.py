"""simulation.model: ball through the commands (simulate, sweep, check, explore, robustness).

A ball wider than the channel's valley (radius 1/(2c) = 6.5 cm on the paper's
surface) bridges at once: the cheap case that still runs every command's ball
path; a 2.5 cm ball on the cheap study spec runs the real dynamics.
"""

from __future__ import annotations

import json

from conftest import SMALL_STUDY, mutated, run_cli, write_spec

WIDE = {"simulation.model": "ball", "ball.diameter": 15.0, "ramp.samples": 6}


def test_check_names_bridging(tmp_path):
    spec = write_spec(tmp_path, mutated(WIDE))
    code, out, err = run_cli(["check", spec, "--no-progress"])
    assert code == 1
    assert "bridged" in err and "bridges" in err and "two points" in err
    code, out, err = run_cli(["check", spec, "--json", "--no-progress"])
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
    code, out, err = run_cli(["simulate", spec, "--v-in", "50"])
    assert "largest |F_t|/N" in out
    # with a friction coefficient below what the rolling needs: slipped
    raw = mutated({**SMALL_STUDY, "simulation.model": "ball", "simulation.t_max": 8.0, "ball.friction": 0.05})
    code, out, err = run_cli(["simulate", write_spec(tmp_path, raw, "f.yaml"), "--v-in", "50", "--json"])
    assert json.loads(out)["outcome"] == "slipped"


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
