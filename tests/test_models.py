"""The model equations: flat ground, energy balance along the right-hand side, the bracket."""

from __future__ import annotations

import numpy as np
import pytest

from fabkit.expr import compile_surface
from fabkit.physics.models import (Problem, accelerations, dissipated_power, energy, fused, normal_bracket,
                                   problem_from_spec, rhs)
from fabkit.spec import load_spec
from conftest import PAPER

PAPER_H = "eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x)"
PAPER_P = {"a": 0.389, "b": 0.306, "c": 0.0764, "d": 0.306, "eta": 3.27, "eps": 0.25}


def paper(model="full", damping=0.0, nl=0.0):
    return Problem(fns=compile_surface(PAPER_H, PAPER_P), g=980.665, k=0.4, model=model, damping=damping,
                   nonlinear_damping=nl, start=-30.0)


def states(n=7, seed=1):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(-30, 5, n), rng.uniform(-4, 4, n), rng.uniform(-60, 60, n),
                     rng.uniform(-30, 30, n)])


def test_problem_from_spec():
    p = problem_from_spec(load_spec(PAPER), damping=0.0)
    assert p.g_tilde == pytest.approx(980.665 / 1.4, rel=1e-15)
    assert p.start == -30 and p.top == 5 and p.margin == 0.5 and p.damping == 0.0
    assert p.x_range == (-44, 6) and p.model == "full"


def test_flat_surface_no_acceleration():
    p = Problem(fns=compile_surface("1.5 + 0*x", {}), g=980.665, k=0.4)
    d = rhs(p, np.array([[1.0, 2.0], [0.5, -1.0], [3.0, 4.0], [-2.0, 0.0]]))
    assert np.array_equal(d[2:], np.zeros((2, 2)))
    assert np.array_equal(d[:2], [[3.0, 4.0], [-2.0, 0.0]])
    assert np.allclose(normal_bracket(p, 0.0, 0.0, 5.0, 1.0), p.g_tilde)


@pytest.mark.parametrize("model", ["full", "simplified"])
@pytest.mark.parametrize("damping,nl", [(0.0, 0.0), (0.7, 0.0), (0.3, 0.08)])
def test_energy_rate_matches_dissipation(model, damping, nl):
    """dE/dt along the flow (central differences of E along rhs) = -P, and 0 undamped:
    ties rhs (eq. xyODE / xyODE_simp) to the energy written independently."""
    p = paper(model, damping, nl)
    s = states()
    d = rhs(p, s)
    eps = 1e-6
    dE = (energy(p, s + eps * d) - energy(p, s - eps * d)) / (2 * eps)
    x, y, vx, vy = s
    _, hx, hy = p.fns.all(x, y)[:3]
    P = dissipated_power(p, x, y, vx, vy, hx, hy)
    scale = np.abs(energy(p, s)).max()
    assert np.allclose(dE, -P, atol=1e-6 * scale, rtol=0)
    if damping == 0 and nl == 0:
        assert np.allclose(P, 0)


def test_fused_matches_direct_formulas():
    for model in ("full", "simplified"):
        p = paper(model, 0.2, 0.05)
        s = states()
        ax, ay, parts = accelerations(p, *s)
        f = fused(p)(*s)
        assert np.allclose(f[0], ax, rtol=1e-12, atol=1e-9) and np.allclose(f[1], ay, rtol=1e-12, atol=1e-9)
        assert np.allclose(f[5], parts[3], rtol=1e-12)


def test_full_model_explicit_formula():
    """eq. (xyODE) written out by hand for the paper's surface."""
    p = paper("full")
    x, y, vx, vy = 1.3, -0.7, 20.0, 5.0
    a, b, c, d, eta, eps = (PAPER_P[k] for k in "a b c d eta eps".split())
    hx = eta * (a * np.exp(a * x) - b * np.exp(b * x)) + eps * d * y * np.exp(d * x)
    hy = 2 * c * y + eps * np.exp(d * x)
    hxx = eta * (a * a * np.exp(a * x) - b * b * np.exp(b * x)) + eps * d * d * y * np.exp(d * x)
    hxy = eps * d * np.exp(d * x)
    hyy = 2 * c
    gt = 980.665 / 1.4
    B = hxx * vx**2 + 2 * hxy * vx * vy + hyy * vy**2 + gt
    q = B / (1 + hx**2 + hy**2)
    out = rhs(p, np.array([x, y, vx, vy]))
    assert np.allclose(out, [vx, vy, -q * hx, -q * hy], rtol=1e-13)
    ps = paper("simplified")
    assert np.allclose(rhs(ps, np.array([x, y, vx, vy])), [vx, vy, -gt * hx, -gt * hy], rtol=1e-13)
