"""The scipy reference path and the batched integrator against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fabkit.expr import compile_surface
from fabkit.physics import models
from fabkit.physics.integrate import launch_batch
from fabkit.physics.reference import solve_launch
from fabkit.spec import validate

from conftest import mutated


def _problem(height, params=None, **kw):
    base = dict(fns=compile_surface(height, params or {}), g=980.665, k=0.4, start=-30.0,
                x_range=(-44.0, 6.0), y_range=(-12.5, 12.5), top=5.0, margin=0.5, t_max=20.0)
    base.update(kw)
    return models.Problem(**base)


@pytest.mark.parametrize("model", ["full", "simplified"])
def test_flat_surface_rolls_freely_off_the_far_end(model):
    p = _problem("0*x + 0*y", model=model)
    v = 25.0
    t_exact = (6.0 - 0.5 - (-30.0)) / v
    r = solve_launch(p, v)
    assert r["outcome"] == "flew_off" and r["bounces"] == 0
    assert r["t_end"] == pytest.approx(t_exact, rel=1e-10)
    b = launch_batch(p, [v])
    assert models.OUTCOMES[b.outcome[0]] == "flew_off"
    assert b.t_end[0] == pytest.approx(t_exact, rel=1e-8)


@pytest.mark.parametrize("model", ["full", "simplified"])
def test_eps_zero_one_bounce_returns_with_the_entry_speed(model):
    spec = validate(mutated({"surface.params.eps": 0.0, "simulation.damping": 0.0}), "eps0.yaml")
    p = models.problem_from_spec(spec, model=model)
    for v in (30.0, 60.0):
        r = solve_launch(p, v)
        assert r["outcome"] == "escaped" and r["bounces"] == 1
        assert r["v_out"] == pytest.approx(v, rel=1e-9)
        assert r["max_abs_y"] == 0.0
        assert r["energy_error"] < 1e-9
    b = launch_batch(p, [30.0, 60.0])
    assert list(b.bounces) == [1, 1]
    np.testing.assert_allclose(b.v_out, [30.0, 60.0], rtol=1e-7)


def test_small_transverse_oscillation_has_frequency_sqrt_2_gt_c():
    c = 0.0764
    p = _problem("c*y**2", {"c": c}, model="simplified", y0=0.0, t_max=5.0, start=-30.0,
                 x_range=(-1e3, 1e3), top=1e3)
    r = launch_batch(p, [1e-9], y0=0.3, record=True)
    tr = r.trajectories[0]
    t, y = np.asarray(tr["t"]), np.asarray(tr["y"])
    s = np.flatnonzero((y[:-1] > 0) & (y[1:] <= 0))          # downward zero crossings
    tz = t[s] - y[s] * (t[s + 1] - t[s]) / (y[s + 1] - y[s])
    period = np.mean(np.diff(tz))
    omega = math.sqrt(2 * p.g_tilde * c)
    assert period == pytest.approx(2 * math.pi / omega, rel=2e-3)   # linear interpolation of crossings


def test_methods_agree_and_report_cost():
    spec = validate(mutated({"simulation.damping": 0.0}), "p.yaml")
    p = models.problem_from_spec(spec)
    ref = solve_launch(p, 32.0)
    assert ref["bounces"] == 2 and ref["outcome"] == "escaped"
    for method in ("RK45", "Radau", "LSODA"):
        r = solve_launch(p, 32.0, method=method, rtol=1e-9, atol=1e-11)
        assert r["bounces"] == 2
        assert r["v_out"] == pytest.approx(ref["v_out"], rel=1e-5)
        assert r["nfev"] > 0 and r["seconds"] > 0
