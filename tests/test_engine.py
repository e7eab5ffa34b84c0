"""The compiled launch engine: generated surface code, its cache, parameters at run
time, threads, the cold-start message, and the lazy import of numba."""

from __future__ import annotations

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
