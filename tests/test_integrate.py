"""The batched integrator against closed forms and a converged scipy reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fabkit.errors import SpecError
from fabkit.expr import compile_surface
from fabkit.physics.integrate import launch_batch, simulate_one
from fabkit.physics.models import CAPTURED, ESCAPED, FLEW_OFF, LOST_CONTACT, OUTCOMES, Problem
from fabkit.tolerances import Tolerances

G = 980.665
PAPER_H = "eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x)"
PAPER_P = {"a": 0.389, "b": 0.306, "c": 0.0764, "d": 0.306, "eta": 3.27, "eps": 0.25}


def paper(model="full", damping=0.0, eps=0.25, **kw):
    params = dict(PAPER_P, eps=eps)
    base = dict(fns=compile_surface(PAPER_H, params), g=G, k=0.4, model=model, damping=damping, start=-30.0,
                x_range=(-44.0, 6.0), y_range=(-12.5, 12.5), top=5.0, margin=0.5, t_max=60.0)
    base.update(kw)
    return Problem(**base)


def flat(**kw):
    base = dict(fns=compile_surface("0.5 + 0*x", {}), g=G, k=0.4, start=-30.0, x_range=(-44.0, 6.0),
                y_range=(-12.5, 12.5), top=5.0, margin=0.5, t_max=60.0)
    base.update(kw)
    return Problem(**base)


def finite_summary(r):
    for name in ("t_end", "x_end", "y_end", "vx_end", "vy_end", "max_z", "max_abs_y"):
        assert np.all(np.isfinite(getattr(r, name))), name


@pytest.mark.parametrize("model", ["full", "simplified"])
def test_flat_free_rolling_flies_off_at_predicted_time(model):
    v = np.array([3.0, 17.0, 40.0])
    r = launch_batch(flat(model=model), v)
    assert np.all(r.outcome == FLEW_OFF) and np.all(r.bounces == 0)
    x_hi = 6.0 - 0.5
    assert np.allclose(r.t_end, (x_hi - (-30.0)) / v, rtol=1e-13)
    assert np.allclose(r.x_end, x_hi, rtol=0, atol=1e-12)
    assert np.allclose(r.vx_end, v, rtol=1e-14)


def test_flat_free_rolling_exact_until_t_max():
    v = np.array([0.5, 1.0])
    r = launch_batch(flat(), v, t_max=20.0)  # 10 and 20 units: stays on the block
    assert np.all(r.outcome == CAPTURED) and np.all(r.bounces == 0)
    assert np.allclose(r.t_end, 20.0, rtol=1e-15)
    assert np.allclose(r.x_end, -30.0 + v * 20.0, rtol=1e-13)


def test_viscous_damping_flat_exponential():
    mu, v0, T = 1.7, 12.0, 1.5
    r = launch_batch(flat(damping=mu, model="simplified"), [v0], t_max=T)
    assert OUTCOMES[r.outcome[0]] == "captured"
    assert r.vx_end[0] == pytest.approx(v0 * math.exp(-mu * T), rel=1e-9)
    assert r.x_end[0] == pytest.approx(-30.0 + v0 * (1 - math.exp(-mu * T)) / mu, rel=1e-9)
    assert r.energy_error[0] < 1e-8  # energy balance: E(T) + dissipated = E(0)


def test_eps_zero_one_bounce_v_out_equals_v_in():
    v = np.array([30.0, 45.0, 60.0, 75.0])
    for model in ("full", "simplified"):
        r = launch_batch(paper(model, eps=0.0), v)
        assert np.all(r.outcome == ESCAPED) and np.all(r.bounces == 1), model
        assert np.allclose(r.v_out, v, rtol=1e-8), model
        assert np.all(r.max_abs_y == 0.0)


def test_small_transverse_oscillation_frequency():
    """Channel h = c y^2, flat along x: y = y0 cos(sqrt(2 g~ c) t) (simplified, exact);
    the full model's frequency approaches it for small amplitude."""
    c, y0 = 0.0764, 1e-3
    fns = compile_surface("c*y**2", {"c": c})
    w = math.sqrt(2 * G / 1.4 * c)
    T = 7.3
    base = dict(fns=fns, g=G, k=0.4, start=0.0, x_range=(-1e3, 1e3), y_range=(-10, 10), top=5.0, margin=0.5)
    r = launch_batch(Problem(model="simplified", **base), [0.0], y0=y0, t_max=T, rtol=1e-11, atol=1e-14)
    assert r.y_end[0] == pytest.approx(y0 * math.cos(w * T), abs=1e-9 * y0 * w * T * 10)
    assert r.vy_end[0] == pytest.approx(-y0 * w * math.sin(w * T), abs=1e-8 * y0 * w)
    # full model: relative frequency shift O((c y0)^2): phase error after T is tiny
    r = launch_batch(Problem(model="full", **base), [0.0], y0=y0, t_max=T, rtol=1e-11, atol=1e-14)
    assert r.y_end[0] == pytest.approx(y0 * math.cos(w * T), abs=1e-7 * y0)
    # and at a large amplitude it is measurably slower
    r = launch_batch(Problem(model="full", **base), [0.0], y0=3.0, t_max=T, rtol=1e-11, atol=1e-12)
    assert abs(r.y_end[0] - 3.0 * math.cos(w * T)) > 1e-3


def test_energy_conserved_undamped():
    v = np.array([35.0, 40.0, 47.0, 60.0, 85.0])
    for model in ("full", "simplified"):
        r = launch_batch(paper(model), v, rtol=1e-10, atol=1e-12)
        assert np.all(r.energy_error < 1e-8), (model, r.energy_error)


def test_damped_energy_balance():
    r = launch_batch(paper("full", damping=0.127), [40.0, 60.0], rtol=1e-10, atol=1e-12)
    assert np.all(r.energy_error < 1e-8)


@pytest.mark.parametrize("model", ["full", "simplified"])
def test_agrees_with_converged_scipy_reference(model):
    from fabkit.physics.reference import solve_launch

    p = paper(model)
    v = np.array([40.0, 47.5, 70.0])
    r = launch_batch(p, v)
    for i, vi in enumerate(v):
        ref = solve_launch(p, float(vi), rtol=1e-12, atol=1e-14)
        assert OUTCOMES[r.outcome[i]] == ref["outcome"]
        assert r.bounces[i] == ref["bounces"]
        if ref["outcome"] == "escaped":
            assert r.v_out[i] == pytest.approx(ref["v_out"], rel=1e-7)
        nb = ref["bounces"]
        assert np.allclose(r.bounce_times[i, :nb], ref["bounce_times"], rtol=1e-7, atol=1e-9)
        assert np.all(np.isnan(r.bounce_times[i, nb:]))


def test_deterministic_across_chunks():
    p = paper("full")
    v = np.linspace(30.0, 90.0, 23)
    a = launch_batch(p, v, chunk=1000)
    b = launch_batch(p, v, chunk=4)
    c = launch_batch(p, v[7:12])
    d = launch_batch(p, v, chunk=6, workers=2)  # forked worker processes where available
    for name in ("outcome", "bounces", "v_out", "bounce_times", "t_end", "x_end", "energy_error", "steps"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
        assert np.array_equal(getattr(a, name)[7:12], getattr(c, name), equal_nan=True), name
        assert np.array_equal(getattr(a, name), getattr(d, name), equal_nan=True), name


@pytest.mark.parametrize("mu", [3e3, 2e4])
def test_heavy_damping_ends_with_named_outcome(mu):
    r = launch_batch(paper("full", damping=mu), [40.0], t_max=60.0)
    assert OUTCOMES[r.outcome[0]] == "captured" and r.status[0] == 2  # the implicit path
    finite_summary(r)
    # overdamped: the entry speed carries the ball v/mu, then it creeps down the slope
    # (|h_x| < 1e-4 there) at g~ |h_x| / mu at most
    assert 0 < r.x_end[0] - (-30.0) < (40.0 + G / 1.4 * 1e-4 * 60.0) / mu


def test_very_fast_launch_leaves_the_surface():
    r = launch_batch(paper("simplified"), [900.0])   # ~20 v_critical
    assert r.outcome[0] == FLEW_OFF and r.bounces[0] == 0
    r = launch_batch(paper("full"), [900.0])
    assert r.outcome[0] in (FLEW_OFF, LOST_CONTACT)
    finite_summary(r)


def test_very_slow_launch_ends_at_t_max():
    r = launch_batch(paper("full"), [1e-6], t_max=30.0)
    assert r.outcome[0] == CAPTURED and r.t_end[0] == pytest.approx(30.0, rel=1e-15)
    finite_summary(r)
    assert np.isfinite(r.energy_error[0]) and r.energy_error[0] < 1e-6


def test_simulate_one_record():
    out = simulate_one(paper("full"), 40.0, record=True)
    tr = out["trajectory"]
    assert out["outcome"] == "escaped" and out["bounces"] == len(out["bounce_times"]) == 2
    assert tr["t"][0] == 0 and tr["t"][-1] == pytest.approx(out["t_end"])
    assert tr["x"][-1] == pytest.approx(-30.0, abs=1e-9)


def test_guards():
    with pytest.raises(SpecError, match="too many launches"):
        launch_batch(paper(), np.ones(11), tol=Tolerances(max_launches=10))
    with pytest.raises(SpecError):
        launch_batch(paper(), [-1.0])
    r = launch_batch(paper(), [40.0], tol=Tolerances(max_sim_steps=20))
    assert r.status[0] == 1 and r.outcome[0] == CAPTURED


def test_a_stiff_batch_over_its_budget_is_refused_after_its_first_launch(tmp_path, monkeypatch):
    """simulation.nonlinear_damping 1e9 (the hostile round's hang: 400 implicit launches of
    about 5 s each): the batch is refused after its first launch, with the evaluations it
    would take, naming the keys that make it stiff, instead of running for half an hour."""
    from conftest import mutated, write_spec
    from fabkit.errors import DesignError
    from fabkit.physics import integrate
    from fabkit.physics.models import problem_from_spec
    from fabkit.spec import load_spec

    spec = load_spec(write_spec(tmp_path, mutated({"simulation.nonlinear_damping": 1e9, "simulation.t_max": 2.0})))
    problem = problem_from_spec(spec)
    assert integrate.is_stiff(problem, problem.t_max)
    first = integrate.launch_batch(problem, [40.0])          # one launch is never refused
    budget = int(first.steps[0]) * 3                           # room for three such launches, not four
    monkeypatch.setattr(integrate, "STIFF_EVALUATIONS", budget)
    with pytest.raises(DesignError) as e:
        integrate.launch_batch(problem, [40.0, 41.0, 42.0, 43.0])
    msg = str(e.value)
    assert "simulation.nonlinear_damping 1e+09" in msg and f"took {int(first.steps[0])} evaluations" in msg
    assert integrate.launch_batch(problem, [40.0, 41.0, 42.0]).outcome.shape == (3,)
