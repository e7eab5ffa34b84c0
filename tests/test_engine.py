"""The compiled launch engine: generated surface code, its cache, parameters at run
time, threads, the cold-start message, and the lazy import of numba."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fabkit.expr import compile_surface
from fabkit.physics.engine import batch, codegen
from fabkit.physics.integrate import launch_batch
from fabkit.physics.models import Problem

ROOT = Path(__file__).resolve().parents[1]
G = 980.665
PAPER_H = "eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x)"
PAPER_P = {"a": 0.389, "b": 0.306, "c": 0.0764, "d": 0.306, "eta": 3.27, "eps": 0.25}


def paper(**params):
    return Problem(fns=compile_surface(PAPER_H, dict(PAPER_P, **params)), g=G, k=0.4, start=-30.0,
                   x_range=(-44.0, 6.0), y_range=(-12.5, 12.5), top=5.0, margin=0.5)


def test_generated_surface_shares_exponentials_and_matches_exact_derivatives():
    p = paper()
    f = codegen.formula(p.fns)
    assert f.names == ("a", "b", "c", "d", "eps", "eta")
    src = codegen.generate_surface(f)
    assert src.count("math.exp(") == 3      # exp(a x), exp(b x), exp(d x), each once
    # the launch state's accelerations (the first recorded point), against eq. (xyODE)
    # evaluated with the numpy functions of the exact derivatives
    rng = np.random.default_rng(1)
    n = 16
    v, y0, vy0 = rng.uniform(0, 80, n), rng.uniform(-10, 10, n), rng.uniform(-20, 20, n)
    r = launch_batch(p, v, y0, vy0, record=True, t_max=0.01)
    h, hx, hy, hxx, hxy, hyy = p.fns.all(np.full(n, -30.0), y0)
    gt = G / 1.4
    B = hxx * v * v + 2 * hxy * v * vy0 + hyy * vy0 * vy0 + gt
    q = B / (1 + hx * hx + hy * hy)
    ax = np.array([tr["ax"][0] for tr in r.trajectories])
    ay = np.array([tr["ay"][0] for tr in r.trajectories])
    assert np.allclose(ax, -q * hx, rtol=1e-13, atol=1e-12)
    assert np.allclose(ay, -q * hy, rtol=1e-13, atol=1e-12)


def test_cache_lives_in_the_cache_dir_never_in_the_repository():
    folder = codegen.cache_dir()
    assert folder == Path(os.environ["FABKIT_CACHE_DIR"]) / "engine"
    batch.engine(paper())
    assert any(folder.glob("fk_engine_point_*.py")) and any(folder.glob("fk_surface_point_*.py"))
    assert not list(ROOT.rglob("fk_surface_*")) and not list(ROOT.rglob("fk_engine_*"))


def test_parameters_are_passed_at_run_time():
    """A design study over surface.params compiles nothing new: one surface module,
    and the results follow the parameters (eps = 0: no coupling, one bounce, v_out = v_in)."""
    a, b = paper(), paper(eps=0.0)
    assert batch._formula(a.fns)[1] == batch._formula(b.fns)[1]
    v = np.array([30.0, 60.0])
    rb = launch_batch(b, v)
    assert np.all(rb.bounces == 1) and np.allclose(rb.v_out, v, rtol=1e-8) and np.all(rb.max_abs_y == 0.0)
    ra = launch_batch(a, v)
    assert not np.array_equal(ra.bounce_times, rb.bounce_times)


def test_threads_and_blocks_give_identical_results():
    p = paper()
    v = np.linspace(20.0, 90.0, 37)
    one = launch_batch(p, v)
    for kw in ({"workers": 2}, {"workers": 3}, {"progress": lambda d, n: None}):
        other = launch_batch(p, v, **kw)
        for name in ("outcome", "bounces", "v_out", "bounce_times", "t_end", "x_end", "y_end", "energy_error",
                     "steps", "rejected", "max_z"):
            assert np.array_equal(getattr(one, name), getattr(other, name), equal_nan=True), (kw, name)


def test_ball_identical_for_any_batch_threads_and_parameters():
    """The ball's template: a launch gives the same bits alone, in a batch and on threads;
    its constants are run-time parameters (another radius runs on the same compiled code)."""
    p = paper().with_(model="ball", radius=1.25)
    v = np.linspace(30.0, 75.0, 6)
    y0 = np.array([0.0, 0.3, 0.0, -0.2, 0.0, 0.1])
    one = launch_batch(p, v, y0)
    names = ("outcome", "bounces", "v_out", "bounce_times", "t_end", "x_end", "vx_end", "max_slip",
             "energy_error", "steps", "max_z")
    other = launch_batch(p, v, y0, workers=2)
    for name in names:
        assert np.array_equal(getattr(one, name), getattr(other, name), equal_nan=True), name
    alone = launch_batch(p, v[3:4], y0[3:4])
    for name in names:
        assert np.array_equal(getattr(one, name)[3:4], getattr(alone, name), equal_nan=True), name
    small = launch_batch(p.with_(radius=0.5), v, y0)      # the same compiled engine and surface
    assert not np.array_equal(one.t_end, small.t_end)


def test_new_formula_says_it_compiles_once():
    # a formula never seen before (its literal is new on every run): not in the cache
    import time

    c = 0.004 + (time.time_ns() % 10**9) * 1e-12
    p = Problem(fns=compile_surface(f"0.0173*x**2 + 0.0291*y**2 + {c!r}*x*y", {}), g=G, k=0.4, start=-5.0,
                x_range=(-10, 10), y_range=(-10, 10), top=5.0, margin=0.5, t_max=2.0)
    said = []
    batch.engine(p, notify=said.append)
    assert len(said) == 1 and re.fullmatch(r"compiling the simulator for this surface \(once, about \d+ s\)",
                                            said[0])
    batch._LOADED.clear()          # as a new process would: only the cache is left
    batch._BY_FNS.clear()
    again = []
    batch.engine(p, notify=again.append)
    assert again == []
    r = launch_batch(p, [1.0], t_max=2.0)   # a bowl: the energy is kept
    assert r.outcome[0] == 1 and r.energy_error[0] < 1e-9


def test_rk45_takes_scipys_steps():
    from scipy.integrate import solve_ivp

    from fabkit.physics.models import rhs

    p = paper()
    r = launch_batch(p, [1.0], method="RK45", rtol=1e-6, atol=1e-8, t_max=1.5)
    sol = solve_ivp(lambda t, s: rhs(p, s), (0, 1.5), [-30.0, 0.0, 1.0, 0.0], method="RK45", rtol=1e-6, atol=1e-8)
    assert r.steps[0] == sol.t.size - 1
    assert r.x_end[0] == pytest.approx(sol.y[0, -1], rel=1e-9)


def test_help_does_not_import_numba():
    code = "import sys; from fabkit.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass\n" \
           "print('numba' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip().splitlines()[-1] == "False"


# ----------------------------------------------------------------------------
# escapes inside one step (issue 23, item 6)
# ----------------------------------------------------------------------------
# A damped bowl h = q x^2 + c y^2 (mm), launched on its wall at x = -30 toward +x: the
# ball crosses the bottom, turns on the far wall (one bounce) and comes back. The launch
# speed is chosen so that it turns again DELTA beyond the start line (a few micrometres),
# for a millisecond or two, far shorter than a step: it escapes there. The speeds come
# from independent solutions: the damped oscillator's closed form (simplified), scipy's
# DOP853 on eq. (xyODE) restricted to y = 0 (full), the Newton-Euler ball (ball).
DIP_Q, DIP_XS, DIP_MU, DIP_K = 1.0 / 60.0, -30.0, 0.5, 0.4
GMM = 9806.65


def _bowl(model):
    return Problem(fns=compile_surface("q*x**2 + c*y**2", {"q": DIP_Q, "c": 0.05}), g=GMM, k=DIP_K, model=model,
                   damping=DIP_MU, start=DIP_XS, x_range=(-200.0, 200.0), y_range=(-50.0, 50.0), t_max=1.0,
                   radius=5.0 if model == "ball" else 0.0)


def _oscillator(v):
    """simplified: x'' = -2 g~ q x - mu x' in closed form: (x(t), xd(t)) functions."""
    gt = GMM / (1 + DIP_K)
    wd = math.sqrt(2 * gt * DIP_Q - DIP_MU ** 2 / 4)
    c1, c2 = DIP_XS, (v + DIP_MU / 2 * DIP_XS) / wd

    def x(t):
        return math.exp(-DIP_MU * t / 2) * (c1 * math.cos(wd * t) + c2 * math.sin(wd * t))

    def xd(t):
        return math.exp(-DIP_MU * t / 2) * ((-DIP_MU / 2 * c1 + wd * c2) * math.cos(wd * t)
                                           + (-DIP_MU / 2 * c2 - wd * c1) * math.sin(wd * t))
    return x, xd, wd


def _dip_simplified(v):
    """(x at the second minimum... the first minimum after the bounce, its time, the
    crossing time, |xd| there) from the closed form."""
    from scipy.optimize import brentq

    x, xd, wd = _oscillator(v)
    # xd's zeros: the bounce in (0, pi/wd), the minimum in (pi/wd, 2 pi/wd)
    ts = np.linspace(1e-9, 2 * math.pi / wd, 4001)
    s = np.sign([xd(t) for t in ts])
    z = [brentq(xd, ts[i], ts[i + 1], xtol=1e-15) for i in np.flatnonzero(s[:-1] * s[1:] < 0)]
    tm = z[1]
    return x(tm), tm, x, xd


def _ref_solution(model, v):
    """A dense solution to the minimum of x after the bounce: (x_min, t_min, x(t), |vx|(t))
    with vx the centre's horizontal velocity."""
    from scipy.integrate import solve_ivp

    p = _bowl(model)
    if model == "simplified":
        xm, tm, x, xd = _dip_simplified(v)
        return xm, tm, x, lambda t: abs(xd(t))
    if model == "full":
        gt = GMM / (1 + DIP_K)

        def f(t, s):
            hx, hxx = 2 * DIP_Q * s[0], 2 * DIP_Q
            return [s[1], -(hxx * s[1] ** 2 + gt) * hx / (1 + hx * hx) - DIP_MU * s[1]]

        def turn(t, s):
            return s[1]
        s0, vel = [DIP_XS, v], (lambda s: abs(s[1]))
    else:
        from ball_newton_euler import NewtonEuler

        ne = NewtonEuler(p)
        f = ne.rhs

        def turn(t, s):
            return ne.frame(s)[2]
        s0, vel = ne.initial(v), (lambda s: abs(ne.frame(s)[1][0]))
    turn.terminal, turn.direction = True, 1
    sol = solve_ivp(f, (0.0, 1.0), s0, method="DOP853", rtol=1e-12, atol=1e-12, events=[turn],
                    dense_output=True)
    tm = float(sol.t_events[0][0])
    return float(sol.y_events[0][0][0]), tm, (lambda t: float(sol.sol(t)[0])), (lambda t: vel(sol.sol(t)))


def _speed_for(model, delta, v_guess=217.936):
    """The launch speed whose x turns ``delta`` beyond the start line (secant iterations)."""
    def g(v):
        return _ref_solution(model, v)[0] - (DIP_XS - delta)
    a, b = v_guess, v_guess * (1 + 1e-4)
    ga, gb = g(a), g(b)
    for _ in range(30):
        if abs(gb) < 1e-9 * abs(DIP_XS) or gb == ga:
            break
        a, b, ga = b, b - gb * (b - a) / (gb - ga), gb
        gb = g(b)
    return b


@pytest.mark.parametrize("model", ["simplified", "full", "ball"])
def test_escape_within_one_step_is_found(model):
    """Turns 2 um beyond the start line for about a millisecond: escaped, after one bounce,
    at the reference's crossing time and speed; 2 um short of it: captured."""
    from scipy.optimize import brentq

    p = _bowl(model)
    v_out_of = _speed_for(model, 2e-3)
    v_short = _speed_for(model, -2e-3, v_out_of)
    xm, tm, x, speed = _ref_solution(model, v_out_of)
    t_cross = brentq(lambda t: x(t) - DIP_XS, tm - 0.05, tm, xtol=1e-15)
    assert tm - t_cross < 2e-3                       # the excursion: a fraction of a step
    r = launch_batch(p, [v_out_of, v_short])
    assert r.outcome_names == ["escaped", "captured"]
    assert r.bounces[0] == 1
    assert r.t_end[0] == pytest.approx(t_cross, abs=1e-8)
    # |xd| at the crossing: sqrt(2 a delta) ~ 5 mm/s, so a position error e moves it by a e / v
    assert r.v_out[0] == pytest.approx(speed(t_cross), rel=1e-5)
    assert r.t_end[0] / r.steps[0] > 2 * (tm - t_cross)   # the whole dip is shorter than a mean step
    # the scipy path (reference.solve_launch: the peer launcher and the stiff Radau path) alike
    from fabkit.physics.reference import solve_launch

    for method in ("DOP853",) if model == "ball" else ("DOP853", "Radau"):   # (Radau on the ball: a minute)
        ref = [solve_launch(p, v, method=method, rtol=1e-10, atol=1e-12) for v in (v_out_of, v_short)]
        assert [q["outcome"] for q in ref] == ["escaped", "captured"], method
        assert ref[0]["bounces"] == 1 and ref[0]["t_end"] == pytest.approx(t_cross, abs=1e-7)
        assert ref[0]["v_out"] == pytest.approx(speed(t_cross), rel=1e-3)
