"""The finite rolling ball (simulation.model: ball) against closed forms.

Closed forms (docs/ball.md): a ball on an inclined plane accelerates at
g sin(theta) / (1 + k) and needs the friction ratio k/(1+k) tan(theta); small
oscillations in a spherical bowl of radius Rb have angular frequency
sqrt(g / ((1 + k)(Rb - r))); on a flat floor with damping mu the speed decays as
exp(-mu t); a ball rolling along a valley bridges where r times the valley's
curvature reaches 1. Each to 1e-6 relative or better.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fabkit.expr import compile_surface
from fabkit.physics import ball as B
from fabkit.physics.integrate import launch_batch
from fabkit.physics.models import OUTCOMES, Problem, ball_quantities, problem_from_spec
from fabkit.physics.reference import solve_launch
from fabkit.spec import load_spec

from conftest import PAPER

G = 980.665
K = 0.4


def problem(text, params=None, **kw):
    fns = compile_surface(text, params or {})
    base = dict(fns=fns, g=G, k=K, model="ball", radius=1.25, start=0.0, x_range=(-50.0, 50.0),
                y_range=(-50.0, 50.0), top=1e6, margin=0.0, t_max=5.0, units="cm")
    base.update(kw)
    return Problem(**base)


def test_jet_matches_sympy_third_derivatives():
    p = problem("eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x) + 0.01*x**2*y**2",
                dict(a=0.389, b=0.306, c=0.0764, d=0.306, eta=3.27, eps=0.25))
    import sympy as sp

    h = p.fns.symbolic
    x, y = sorted(h.free_symbols, key=lambda s: s.name)
    j = B.jet_function(p.fns)(np.array([-3.0, 1.5]), np.array([0.7, -2.0]))
    for idx, (a, b) in enumerate([(3, 0), (2, 1), (1, 2), (0, 3)]):
        e = sp.diff(h, x, a, y, b) if b else sp.diff(h, x, a)
        for i, (xv, yv) in enumerate([(-3.0, 0.7), (1.5, -2.0)]):
            assert j[6 + idx][i] == pytest.approx(float(e.subs({x: xv, y: yv})), rel=1e-12, abs=1e-14)


def test_geometry_against_finite_differences_of_the_centre():
    """C_x, C_xx ... from the closed formulas against central differences of C = P + r n."""
    p = problem("0.3*sin(0.7*x)*cos(0.4*y) + 0.05*x*y**2", radius=0.8)
    jet = B.jet_function(p.fns)

    def C(x, y):
        g = B.geometry(jet(x, y), 0.8)
        return np.array([x + 0.8 * g["n"][0], y + 0.8 * g["n"][1], g["h"] + 0.8 * g["n"][2]])

    x0, y0, d = 0.37, -0.61, 1e-4
    g = B.geometry(jet(x0, y0), 0.8)
    Cx = (C(x0 + d, y0) - C(x0 - d, y0)) / (2 * d)
    Cyy = (C(x0, y0 + d) - 2 * C(x0, y0) + C(x0, y0 - d)) / d ** 2
    Cxy = (C(x0 + d, y0 + d) - C(x0 + d, y0 - d) - C(x0 - d, y0 + d) + C(x0 - d, y0 - d)) / (4 * d * d)
    np.testing.assert_allclose(np.array(g["Cx"], dtype=float), Cx, rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.array(g["Cyy"], dtype=float), Cyy, rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.array(g["Cxy"], dtype=float), Cxy, rtol=0, atol=1e-5)


@pytest.mark.parametrize("theta_deg", [5.0, 20.0])
def test_inclined_plane(theta_deg):
    """Up the plane z = x tan(theta) and back: the horizontal deceleration is
    g sin cos / (1 + k), the bounce at v_in / that, v_out = v_in, u stays 0 (also with a
    sideways launch), and |F_t|/N = k/(1+k) tan(theta)."""
    th = math.radians(theta_deg)
    p = problem(f"x*{math.tan(th)!r}", t_max=20.0)
    a_h = G * math.sin(th) * math.cos(th) / (1 + K)
    v_in = 30.0
    r = launch_batch(p, [v_in, v_in], y0=[0.0, 0.0], vy0=[0.0, 7.0])
    assert [OUTCOMES[o] for o in r.outcome] == ["escaped", "escaped"]
    assert np.all(r.bounces == 1)
    np.testing.assert_allclose(r.bounce_times[:, 0], v_in / a_h, rtol=1e-9)
    np.testing.assert_allclose(r.t_end, 2 * v_in / a_h, rtol=1e-9)
    np.testing.assert_allclose(r.v_out, v_in, rtol=1e-9)
    np.testing.assert_allclose(r.max_slip, K / (1 + K) * math.tan(th), rtol=1e-9)
    # the event fallback (regula falsi where a long step holds the bounce and the escape)
    # is per lane: a launch alone gives the same bits as in a batch
    alone = launch_batch(p, [v_in], y0=[0.0], vy0=[7.0])
    assert alone.t_end[0] == r.t_end[1] and alone.v_out[0] == r.v_out[1]
    # along the slope: g sin(theta) / (1 + k), u = 0
    q = ball_quantities(p, np.array([0.0, 0.0, 12.0, 5.0, 0.0]))
    a_slope = q["xdd"] / math.cos(th)          # the centre moves as the contact point on a plane
    assert a_slope == pytest.approx(-G * math.sin(th) / (1 + K), rel=1e-12)
    assert q["ydd"] == pytest.approx(0.0, abs=1e-12) and q["ud"] == pytest.approx(0.0, abs=1e-12)


def test_spherical_bowl_small_oscillations():
    """Contact point at the bottom of a bowl of radius Rb: the first maximum of x is a
    quarter period of omega = sqrt(g / ((1 + k)(Rb - r))), for two ball radii."""
    Rb = 10.0
    for r in (1.25, 4.0):
        p = problem(f"{Rb} - sqrt({Rb}**2 - x**2 - y**2)", radius=r, x_range=(-9.0, 9.0), y_range=(-9.0, 9.0))
        omega = math.sqrt(G / ((1 + K) * (Rb - r)))
        amp = 1e-5 * Rb
        v_in = amp * omega * (Rb - r) / Rb            # the centre moves on a sphere of radius Rb - r
        res = launch_batch(p, [v_in])
        assert OUTCOMES[res.outcome[0]] == "escaped" and res.bounces[0] == 1
        assert res.bounce_times[0, 0] == pytest.approx(0.5 * math.pi / omega, rel=1e-7)
        assert res.t_end[0] == pytest.approx(math.pi / omega, rel=1e-7)


def test_no_transverse_motion_keeps_u_zero_and_small_radius_gives_full():
    spec = load_spec(PAPER)
    base = problem_from_spec(spec, damping=0.0).with_(fns=compile_surface(
        "eta*(exp(a*x) - exp(b*x)) + c*y**2", dict(a=0.389, b=0.306, c=0.0764, eta=3.27)))
    v = np.array([25.0, 45.0, 70.0])
    full = launch_batch(base.with_(model="full"), v)
    for r in (1e-7, 1e-8):
        ball = launch_batch(base.with_(model="ball", radius=r), v, record=True)
        assert np.array_equal(ball.outcome, full.outcome) and np.array_equal(ball.bounces, full.bounces)
        np.testing.assert_allclose(ball.v_out, full.v_out, rtol=1e-6)
        np.testing.assert_allclose(ball.t_end, full.t_end, rtol=1e-6)
    # u stays 0 exactly along the channel's axis
    ref = solve_launch(base.with_(model="ball"), 45.0, rtol=1e-10, atol=1e-12)
    assert ref["outcome"] == "escaped"
    p = base.with_(model="ball")
    s0 = np.array([p.start, 0.0, 45.0, 0.0, 0.0])
    assert float(ball_quantities(p, s0)["ud"]) == 0.0


def test_energy_conserved_on_the_paper_surface():
    spec = load_spec(PAPER)
    p = problem_from_spec(spec, model="ball", damping=0.0)
    r = launch_batch(p, [30.0, 55.0, 75.0], y0=[0.0, 0.3, -0.2], vy0=[0.0, 2.0, 1.0], t_max=8.0)
    assert np.all(r.energy_error < 1e-9), r.energy_error
    # with damping: the energy balance E + W - E0 closes to the same accuracy
    r = launch_batch(p.with_(damping=0.127, rolling_resistance=0.002), [55.0], t_max=8.0)
    assert r.energy_error[0] < 1e-9


def test_flat_floor_damping_decay_rate():
    """damping mu: the speed decays as exp(-mu t) (the point models' rate); the friction
    the rolling needs is k mu v (the ball's spin must slow with it)."""
    mu, v_in, T = 0.5, 20.0, 3.0
    p = problem("0*x", damping=mu, t_max=T)
    r = launch_batch(p, [v_in])
    assert OUTCOMES[r.outcome[0]] == "captured"
    assert r.vx_end[0] == pytest.approx(v_in * math.exp(-mu * T), rel=1e-9)
    assert r.x_end[0] == pytest.approx(v_in * (1 - math.exp(-mu * T)) / mu, rel=1e-9)
    assert r.max_slip[0] == pytest.approx(K * mu * v_in / G, rel=1e-9)


def test_rolling_resistance_on_a_flat_floor():
    """c_rr N opposing v: uniform deceleration c g / (1 + k) until the ball stops."""
    c, v_in, T = 0.01, 5.0, 0.5
    p = problem("0*x", rolling_resistance=c, t_max=T)
    r = launch_batch(p, [v_in])
    a = c * G / (1 + K)
    # the smoothing below v_s = 1e-2 sqrt(g r) changes the force by (v_s / v)^2 / 2 <= 2e-3
    # exact for the smoothed force a v / sqrt(v^2 + v_s^2): a t = [w - v_s ln((v_s + w) / v)]
    # between v_end and v_in, w = sqrt(v^2 + v_s^2)
    from scipy.optimize import brentq

    v_s = 1e-3 * math.sqrt(G * 1.25)

    def F(v):
        w = math.sqrt(v * v + v_s * v_s)
        return w - v_s * math.log((v_s + w) / v)

    v_end = brentq(lambda v: F(v_in) - F(v) - a * T, 1e-6, v_in, xtol=1e-14)
    assert r.vx_end[0] == pytest.approx(v_end, rel=1e-9)
    assert v_end == pytest.approx(v_in - a * T, rel=1e-3)   # the smoothing is small
    # it comes to rest and stays (no chattering: the launch finishes in a few hundred steps)
    r = launch_batch(p.with_(t_max=2.0), [v_in])
    assert abs(r.vx_end[0]) < 1e-6 and r.steps[0] < 2000


def test_valley_narrower_than_the_ball_bridges():
    """Rolling down a slope into a valley whose radius shrinks along x: bridged exactly
    where r times the valley's curvature 2 c exp(x / 5) reaches 1."""
    c, r = 0.1, 2.0
    p = problem(f"-0.2*x + {c}*exp(x/5)*y**2", radius=r, t_max=10.0)
    res = launch_batch(p, [10.0])
    assert OUTCOMES[res.outcome[0]] == "bridged"
    # on y = 0 the principal curvature across is h_yy / sqrt(1 + h_x^2), h_x = -0.2
    x_star = 5.0 * math.log(math.sqrt(1.04) / (2 * c * r))
    assert res.x_end[0] == pytest.approx(x_star, rel=1e-6)
    ref = solve_launch(p, 10.0, rtol=1e-11, atol=1e-13)
    assert ref["outcome"] == "bridged" and ref["x_end"] == pytest.approx(x_star, rel=1e-6)
    # a ball larger than the valley everywhere bridges at the launch
    res = launch_batch(problem(f"{c}*y**2", radius=1.0 / (2 * c) + 0.1), [10.0])
    assert OUTCOMES[res.outcome[0]] == "bridged" and res.t_end[0] == 0.0


def test_friction_slipped_on_a_steep_plane():
    th = math.radians(30.0)
    need = K / (1 + K) * math.tan(th)
    p = problem(f"x*{math.tan(th)!r}", t_max=2.0)
    r = launch_batch(p.with_(friction=0.99 * need), [30.0])
    assert OUTCOMES[r.outcome[0]] == "slipped" and r.t_end[0] == 0.0
    r = launch_batch(p.with_(friction=1.01 * need), [30.0])
    assert OUTCOMES[r.outcome[0]] == "escaped"


def test_lost_contact_over_a_circular_crest():
    """Over the crest z = sqrt(R^2 - x^2) the centre moves on a circle of radius
    rho = R + r; from the top at speed v0 contact is lost where
    cos(theta) = ((1 + k) v0^2 + 2 g rho) / ((3 + k) g rho) (10/17 from rest for a solid
    ball): N = 0 with the energy of the rolling ball."""
    R, r, v0 = 20.0, 1.0, 10.0
    p = problem(f"sqrt({R}**2 - x**2) - {R}", radius=r, x_range=(-19.9, 19.9), t_max=3.0)
    rho = R + r
    cos_t = ((1 + K) * v0 ** 2 + 2 * G * rho) / ((3 + K) * G * rho)
    res = launch_batch(p, [v0])
    assert OUTCOMES[res.outcome[0]] == "lost_contact"
    assert res.x_end[0] == pytest.approx(R * math.sqrt(1 - cos_t ** 2), rel=1e-8)
    ref = solve_launch(p, v0, rtol=1e-11, atol=1e-13)
    assert ref["outcome"] == "lost_contact" and ref["x_end"] == pytest.approx(res.x_end[0], rel=1e-8)


def test_agrees_with_the_independent_newton_euler_implementation():
    """fabkit's reduced equations against 3-D Newton-Euler in omega with the contact force
    solved from the constraint (tests/ball_newton_euler.py: no third derivatives, no
    spin variable), on the paper's surface with its damping: same outcome and bounce
    count, v_out and bounce times to 1e-7 (benchmarks/ball_reference.py compares more)."""
    from ball_newton_euler import NewtonEuler

    spec = load_spec(PAPER)
    p = problem_from_spec(spec, model="ball").with_(t_max=6.0)
    r = launch_batch(p, [50.0])
    ref = NewtonEuler(p).launch(50.0)
    assert OUTCOMES[r.outcome[0]] == ref["outcome"] == "escaped"
    assert r.bounces[0] == ref["bounces"] == 2     # a two-bounce escape of the real ball
    assert r.v_out[0] == pytest.approx(ref["v_out"], rel=1e-7)
    np.testing.assert_allclose(r.bounce_times[0, :2], ref["bounce_times"], rtol=1e-7)
    assert abs(ref["spin"]) > 1e-3    # the spin about the normal is not zero: u matters


def test_trapping_energy_of_the_ball():
    """E* lies above the lowest centre height (the ball can be trapped) and below the
    energy of the slowest ramp launch that escapes; none with a friction coefficient."""
    from fabkit.physics.trap import trap_energy

    spec = load_spec(PAPER)
    p = problem_from_spec(spec, model="ball")
    e = trap_energy(p, 1e-8)
    q = ball_quantities(p, np.array([p.start, 0.0, 16.7, 0.0, 0.0]))
    assert e is not None and e < float(q["energy"])          # a launch from the ramp starts above E*
    assert e > p.g_tilde * (-1.8 + p.radius * 0.9)          # above the channel's bottom (h ~ -1.7 cm)
    assert trap_energy(p.with_(friction=0.5), 1e-8) is None
