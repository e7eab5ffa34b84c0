"""fabkit calibrate and fabkit simulate through main(argv)."""

from __future__ import annotations

import json
import math

import numpy as np

from conftest import PAPER, mutated, write_spec

G_CM = 980.665


def test_calibrate_json(cli, tmp_path):
    # without losses: the closed form (with the paper's damping: tests/test_calibrate.py)
    code, out, err = cli("calibrate", write_spec(tmp_path, mutated({"simulation.damping": 0})), "--json",
                         "--v-in", "50", "80")
    assert code == 0, err
    d = json.loads(out)
    H = np.array(d["heights"])
    assert d["units"] == "cm" and d["k"] == 0.4 and len(H) == 400
    assert np.allclose(d["v_in"], np.sqrt(10 * G_CM * H / 7), rtol=1e-14)
    assert np.allclose(d["inverse"]["heights"], 0.7 * np.array([50.0, 80.0]) ** 2 / G_CM, rtol=1e-14)
    assert "entry_level" in d


def test_calibrate_heights_table(cli, tmp_path):
    raw = mutated({"ball.inertia": "hollow"}, drop=("surface", "simulation", "stock", "tool", "machining"))
    code, out, err = cli("calibrate", write_spec(tmp_path, raw), "--height", "2")
    assert code == 0, err
    assert f"{math.sqrt(2 * G_CM * 2 / (1 + 2 / 3)):.8g}" in out


def test_calibrate_missing_ramp_and_bad_height(cli, tmp_path):
    code, out, err = cli("calibrate", write_spec(tmp_path, mutated({}, drop=("ramp",))))
    assert code == 2 and "ramp" in err and err.count("\n") == 1
    code, out, err = cli("calibrate", PAPER, "--height", "-1")
    assert code == 2 and "--height" in err


def test_simulate_json_and_plot(cli, tmp_path):
    png = tmp_path / "t.png"
    code, out, err = cli("simulate", PAPER, "--v-in", "40", "--json", "--plot", png)
    assert code == 0, err
    d = json.loads(out)
    for key in ("outcome", "bounces", "bounce_times", "v_out", "max_height", "max_abs_y", "energy_error",
                "seconds", "error_estimate"):
        assert key in d
    assert d["outcome"] == "escaped" and d["bounces"] == len(d["bounce_times"]) >= 1
    assert d["energy_error"] < 1e-8 and d["v_out"] < 40
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*.tmp"))


def test_simulate_text_and_bad_input(cli, tmp_path):
    code, out, err = cli("simulate", PAPER, "--v-in", "900")
    assert code == 0 and ("flew_off" in out or "lost_contact" in out)
    code, out, err = cli("simulate", PAPER, "--v-in", "-3")
    assert code == 2 and "--v-in" in err
    code, out, err = cli("simulate", write_spec(tmp_path, mutated({}, drop=("simulation",))), "--v-in", "40")
    assert code == 2 and "simulation" in err
