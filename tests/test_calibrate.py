"""Ramp calibration against the energy balance m g H = 1/2 m v^2 (1 + k)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import PAPER, mutated, write_spec
from fabkit.errors import SpecError
from fabkit.physics.calibrate import (calibration_table, height_from_v_in, ramp_heights,
                                      v_in_from_height)
from fabkit.spec import load_spec
from fabkit.units import gravity

G_CM = 980.665


def test_solid_ball_seven_fifths():
    # m g H = (7/5) (1/2) m v^2 for a solid ball: v = sqrt(10 g H / 7)
    H = np.array([0.0, 0.2, 1.0, 4.5])
    assert np.allclose(v_in_from_height(H, G_CM, 0.4), np.sqrt(10 * G_CM * H / 7), rtol=1e-15, atol=0)


def test_hollow_and_number():
    assert math.isclose(float(v_in_from_height(2.0, G_CM, 2 / 3)), math.sqrt(2 * G_CM * 2.0 * 3 / 5), rel_tol=1e-15)
    assert math.isclose(float(v_in_from_height(2.0, G_CM, 0.0)), math.sqrt(2 * G_CM * 2.0), rel_tol=1e-15)


@pytest.mark.parametrize("k", [0.0, 0.4, 2 / 3, 3.0])
def test_round_trip(k):
    H = np.linspace(0, 10, 11)
    assert np.allclose(height_from_v_in(v_in_from_height(H, G_CM, k), G_CM, k), H, rtol=1e-14, atol=1e-14)


def test_gravity_units():
    assert gravity("cm") == pytest.approx(980.665, rel=1e-15)
    assert gravity("mm") == pytest.approx(9806.65, rel=1e-15)
    assert gravity("in") == pytest.approx(9.80665 / 0.0254, rel=1e-15)


def test_ramp_heights_range_and_list(tmp_path):
    spec = load_spec(write_spec(tmp_path, mutated({"ramp.heights": [0.2, 4.5], "ramp.samples": 5})))
    assert np.allclose(ramp_heights(spec), [0.2, 1.275, 2.35, 3.425, 4.5], rtol=1e-15)
    spec = load_spec(write_spec(tmp_path, mutated({"ramp.heights": [1.0, 0.5, 3.0]}), "b.yaml"))
    assert ramp_heights(spec).tolist() == [1.0, 0.5, 3.0]
    with pytest.raises(SpecError, match="ramp.heights"):
        load_spec(write_spec(tmp_path, mutated({"ramp.heights": [3.0, 1.0]}), "c.yaml"))


def test_calibration_table_paper():
    spec = load_spec(PAPER)
    t = calibration_table(spec)
    assert t["units"] == "cm" and t["k"] == 0.4 and t["g"] == pytest.approx(G_CM, rel=1e-15)
    assert t["heights"][0] == 0.2 and t["heights"][-1] == 4.5
    assert np.allclose(t["v_in"], np.sqrt(10 * G_CM * t["heights"] / 7), rtol=1e-15)


def test_closed_forms_do_not_overflow_for_finite_heights():
    """v_in = sqrt(2 g / (1 + k)) sqrt(H) stays finite up to the largest double."""
    g, k = 980.665, 0.4
    v = float(v_in_from_height(1e308, g, k))
    assert math.isfinite(v)
    assert v == pytest.approx(math.sqrt(2 * g / (1 + k)) * 1e154, rel=1e-15)
