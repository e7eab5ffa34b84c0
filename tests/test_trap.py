"""The trapping energy and the early end of trapped launches (physics/trap.py)."""

from __future__ import annotations

import numpy as np
import pytest

from fabkit.expr import compile_surface
from fabkit.physics.integrate import launch_batch
from fabkit.physics.models import CAPTURED, Problem, problem_from_spec
from fabkit.physics.trap import trap_energy
from fabkit.spec import load_spec

G = 980.665
K = 0.4
GT = G / (1 + K)


def bowl(c=0.05, **kw):
    """h = c (x^2 + y^2) on [-20, 20]^2, launched at x = -10: D = [-10, 20] x [-20, 20],
    the lowest boundary point is (-10, 0) with h = 100 c; the Hessian is 2c I (no
    negative curvature), top far above."""
    fields = dict(fns=compile_surface("c*(x**2 + y**2)", {"c": c}), g=G, k=K, model="full",
                  start=-10.0, x_range=(-20.0, 20.0), y_range=(-20.0, 20.0), top=1e3, margin=0.0,
                  t_max=60.0)
    fields.update(kw)
    return Problem(**fields)


def test_paraboloid_trapping_energy_is_the_lowest_exit():
    c = 0.05
    e = trap_energy(bowl(c))
    exact = GT * 100 * c
    assert e <= exact
    assert e == pytest.approx(exact, rel=1e-6)


def test_top_and_negative_curvature_lower_it():
    # the top face below the lowest boundary point: E* = g~ (top - margin)
    assert trap_energy(bowl(top=2.0, margin=0.5)) == pytest.approx(GT * 1.5, rel=1e-6)
    # a saddle h = c (x^2 - y^2): kappa = 2c; with h_min on D from the grid, E* <= g~ h_min + g~ / (4 c)
    p = bowl(fns=compile_surface("c*(x**2 - y**2)", {"c": 0.05}))
    e = trap_energy(p)
    h_min = -0.05 * 400 - 0.0            # at y = +-20 (x = 0)
    assert e is None or e <= GT * h_min + GT / (2 * 1.5 * 2 * 0.05)


def test_nonlinear_damping_in_the_full_model_has_no_bound():
    assert trap_energy(bowl(nonlinear_damping=1.0)) is None
    assert trap_energy(bowl(nonlinear_damping=1.0, model="simplified")) is not None


def test_damped_bowl_launch_stops_once_trapped_with_energy_below_the_bound():
    p = bowl(damping=2.0)
    v = np.array([5.0, 20.0, 60.0])
    full = launch_batch(p, v)
    early = launch_batch(p.with_(stop_trapped=True), v)
    assert (full.outcome == CAPTURED).all() and (early.outcome == CAPTURED).all()
    assert np.allclose(full.t_end, 60.0)
    assert (early.status == 4).all() and (early.t_end < 30.0).all()
    # the end state's energy is below E*
    e_star = trap_energy(p)
    x, y, vx, vy = early.x_end, early.y_end, early.vx_end, early.vy_end
    h, hx, hy = 0.05 * (x * x + y * y), 0.1 * x, 0.1 * y
    E = 0.5 * (vx ** 2 + vy ** 2 + (hx * vx + hy * vy) ** 2) + GT * h
    assert (E < e_star).all()
    # dE/dt = -2 mu (E - g~ h) >= -2 mu E (h >= 0): E >= E0 exp(-2 mu t), so a trapped launch cannot stop sooner than
    # the time the damping needs to take its energy from E0 to E*
    E0 = 0.5 * v ** 2 * (1 + 1.0 ** 2) + GT * 5.0
    assert (early.t_end >= np.log(E0 / e_star) / (2 * 2.0)).all()


def test_paper_results_unchanged_but_for_captured_end_times():
    spec = load_spec("specs/surface.yaml")
    p = problem_from_spec(spec)
    v = np.linspace(17.0, 79.0, 48)
    a = launch_batch(p, v)
    b = launch_batch(p.with_(stop_trapped=True), v)
    assert np.array_equal(a.outcome, b.outcome)
    other = a.outcome != CAPTURED
    assert (a.outcome == CAPTURED).any() and other.any()
    for f in ("v_out", "bounce_times", "t_end", "x_end", "y_end", "bounces"):
        assert np.array_equal(getattr(a, f)[other], getattr(b, f)[other], equal_nan=True), f
    assert (b.t_end[~other] < a.t_end[~other]).all()
