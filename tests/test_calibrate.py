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


def test_calibration_table_paper(tmp_path):
    """Without losses the table is the closed form; with the paper's damping every row is
    the descent's (entry_speed) and slower."""
    from fabkit.physics.calibrate import entry_speed

    spec = load_spec(write_spec(tmp_path, mutated({"simulation.damping": 0})))
    t = calibration_table(spec)
    assert t["units"] == "cm" and t["k"] == 0.4 and t["g"] == pytest.approx(G_CM, rel=1e-15)
    assert t["heights"][0] == 0.2 and t["heights"][-1] == 4.5
    assert np.allclose(t["v_in"], np.sqrt(10 * G_CM * t["heights"] / 7), rtol=1e-15)
    spec = load_spec(PAPER)
    t = calibration_table(spec)
    np.testing.assert_allclose(t["v_in"][::57], entry_speed(spec, t["heights"][::57]), rtol=1e-9)
    assert np.all(t["v_in"] < np.sqrt(10 * G_CM * t["heights"] / 7))


def test_closed_forms_do_not_overflow_for_finite_heights():
    """v_in = sqrt(2 g / (1 + k)) sqrt(H) stays finite up to the largest double."""
    g, k = 980.665, 0.4
    v = float(v_in_from_height(1e308, g, k))
    assert math.isfinite(v)
    assert v == pytest.approx(math.sqrt(2 * g / (1 + k)) * 1e154, rel=1e-15)


# ----------------------------------------------------------------------------
# the ramp's own losses: an independent integration along the ramp's line
# ----------------------------------------------------------------------------
def _reference_descent(spec, H, mu, c, want_time=False):
    """v_in for release height H on fabkit's ramp, written here from scratch: the line
    z(x) = h(x, y0) + D(start - x) with the smoothstep lift (its closed form below) and
    h's derivatives by sympy; the release point by brentq on the centre's height
    z + r cos(phi); then, in time, the centre's speed V and the contact's x:

        dV/dt = g~ sin(phi) - mu V - c/(1+k) (g cos(phi) + V^2 kappa / (1 - r kappa))
        dx/dt = V / ((1 - r kappa) sqrt(1 + z_x^2))

    (sin(phi) = -z_x / sqrt(1 + z_x^2) downhill toward +x, kappa = z_xx / (1 + z_x^2)^1.5,
    the centre's path is the parallel curve at distance r: its length per unit contact
    length is 1 - r kappa and its curvature kappa / (1 - r kappa)), until x = start."""
    import sympy as sp
    from scipy.integrate import solve_ivp
    from scipy.optimize import brentq

    from fabkit.lab.ramp import design_profile

    prof = design_profile(spec, float(max(spec.ramp.heights)))   # the ramp's size (L, tan)
    L, tan, start, y0 = prof.L, prof.tan, float(spec.simulation.start), float(spec.simulation.y0)
    X = sp.Symbol("x")
    expr = sp.sympify(spec.surface.height, locals={"x": X, "y": sp.Symbol("y")})
    expr = expr.subs({sp.Symbol(k): v for k, v in spec.surface.params.items()}).subs(sp.Symbol("y"), y0)
    U = start - X
    s_ = U / L
    D_in = tan * L * (s_ ** 3 - s_ ** 4 / 2)
    D_out = tan * (L / 2 + U - L)
    z_in, z_out = expr + D_in, expr + D_out
    f_in = [sp.lambdify(X, e) for e in (z_in, sp.diff(z_in, X), sp.diff(z_in, X, 2))]
    f_out = [sp.lambdify(X, e) for e in (z_out, sp.diff(z_out, X), sp.diff(z_out, X, 2))]

    def jet(x):
        fs = f_in if start - x <= L else f_out
        return tuple(float(f(x)) for f in fs)

    r = 0.5 * float(spec.ball.diameter)
    k = 0.4
    g = gravity(spec.units)
    gt = g / (1 + k)

    def centre(x):
        z, zx, _ = jet(x)
        return z + r / math.sqrt(1 + zx * zx)

    x_r = brentq(lambda x: centre(x) - centre(start) - H, start - prof.u_end, start, xtol=1e-14, rtol=1e-15)

    def rhs(t, y):
        x, V = y
        _, zx, zxx = jet(x)
        w = math.sqrt(1 + zx * zx)
        kap = zxx / w ** 3
        N = g / w + V * V * kap / (1 - r * kap)
        dV = gt * (-zx / w) - mu * V - c / (1 + k) * N
        return [V / ((1 - r * kap) * w), dV]

    arrive = lambda t, y: y[0] - start
    arrive.terminal, arrive.direction = True, 1
    sol = solve_ivp(rhs, (0, 300), [x_r, 0.0], method="LSODA" if mu > 5 else "DOP853", rtol=1e-12, atol=1e-13,
                    events=arrive)
    assert sol.status == 1
    if want_time:
        return float(sol.y_events[0][0][1]), float(sol.t_events[0][0])
    return float(sol.y_events[0][0][1])


def test_entry_speed_with_damping_matches_an_independent_descent(tmp_path):
    """The paper's spec (damping 0.127 1/s): calibrate's v_in at the ramp's marks (window
    centres near v_critical and the ends of the ramp) against the reference, 1e-3 asked,
    1e-8 found; and the inverse returns the height."""
    from fabkit.physics.calibrate import entry_speed, release_height

    spec = load_spec(PAPER)
    H = np.array([0.2, 1.2, 2.45, 2.52, 3.3, 4.5])
    v = entry_speed(spec, H)
    ref = np.array([_reference_descent(spec, h, 0.127, 0.0) for h in H])
    np.testing.assert_allclose(v, ref, rtol=1e-8)
    # the losses are real: 1.9-2.8 % slower than the lossless closed form
    loss = 1 - v / np.sqrt(2 * G_CM * H / 1.4)
    assert np.all((loss > 0.018) & (loss < 0.03))
    np.testing.assert_allclose(release_height(spec, v), H, rtol=1e-10)


def test_entry_speed_with_rolling_resistance_and_damping(tmp_path):
    from fabkit.physics.calibrate import entry_speed

    spec = load_spec(write_spec(tmp_path, mutated({"ball.rolling_resistance": 0.01, "simulation.damping": 0.3})))
    H = np.array([0.5, 2.0, 4.0])
    ref = np.array([_reference_descent(spec, h, 0.3, 0.01) for h in H])
    np.testing.assert_allclose(entry_speed(spec, H), ref, rtol=1e-8)


def test_lossless_descent_is_the_closed_form():
    """Without losses entry_speed is the closed form exactly, and the descent's integrator
    itself (run without losses) keeps the energy to 1e-10."""
    from fabkit.lab.ramp import ramp_profile
    from fabkit.physics.calibrate import _descend, entry_speed

    spec = load_spec(write_spec_tmp({"simulation.damping": 0.0}))
    H = np.linspace(0.2, 4.5, 9)
    assert np.array_equal(entry_speed(spec, H), np.sqrt(2 * G_CM / 1.4) * np.sqrt(H))
    e = _descend(ramp_profile(spec), H, G_CM, 0.4, 0.0, 0.0, False, spec)
    np.testing.assert_allclose(e.v_in, np.sqrt(10 * G_CM * H / 7), rtol=1e-10)


def write_spec_tmp(changes):
    import tempfile
    from pathlib import Path

    return write_spec(Path(tempfile.mkdtemp()), mutated(changes))


def _straight_closed_form(H, theta_deg, r, beta, mu, c, k=0.4, g=G_CM):
    """A straight incline: s'' = a - mu s' with a = (g sin - c g cos)/(1+k), from rest:
    s = -V/mu - a/mu^2 ln(1 - mu V / a) (V by brentq), over the centre's run from release
    to the corner (both contacts r tan(kink/2) from the edge); then the kink's impact,
    angular momentum about the new contact kept: V (k + cos kink) / (1 + k)."""
    from scipy.optimize import brentq

    th = math.radians(theta_deg)
    kink = th + beta
    d_star = r * math.tan(kink / 2)
    d_r = (H - r * (math.cos(th) - math.cos(beta))) / math.sin(th)
    s = d_r - d_star
    a = (g * math.sin(th) - c * g * math.cos(th)) / (1 + k)
    if mu == 0:
        V = math.sqrt(2 * a * s)
    else:
        V = brentq(lambda V: -V / mu - a / mu ** 2 * math.log1p(-mu * V / a) - s, 0, a / mu * (1 - 1e-16),
                   xtol=1e-15, rtol=1e-15)
    return V * (k + math.cos(kink)) / (1 + k)


@pytest.mark.parametrize("mu,c", [(0.0, 0.0), (0.127, 0.0), (0.5, 0.02)])
def test_straight_ramp_against_its_closed_form(tmp_path, mu, c):
    from fabkit.physics.calibrate import entry_speed

    spec = load_spec(write_spec(tmp_path, mutated({"ramp.profile": "straight", "ramp.angle": 20,
                                                   "ramp.length": 15, "simulation.damping": mu,
                                                   "ball.rolling_resistance": c})))
    hx = float(spec.surface_functions().grad(-30.0, 0.0)[0])
    H = np.array([0.5, 2.0, 4.5])
    ref = [_straight_closed_form(h, 20.0, 1.25, math.atan(hx), mu, c) for h in H]
    np.testing.assert_allclose(entry_speed(spec, H), ref, rtol=1e-9)
    # a kink of 20 degrees costs 4.3 % of the speed even without losses
    if mu == 0 and c == 0:
        lossless = np.sqrt(2 * G_CM * H / 1.4)
        ratio = entry_speed(spec, H) / lossless
        assert np.all(np.abs(ratio - (0.4 + math.cos(math.radians(20))) / 1.4) < 1e-4)
        assert np.all(np.abs(ratio - 0.957) < 1e-3)


def test_rolling_resistance_stops_the_ball(tmp_path):
    """c above tan(angle) cannot start the ball on a straight ramp; on fabkit's ramp the
    resistance stops a ball released low, on the gentle transition (c = 0.1: the slope
    near the launch point is below 0.1 over the first part of the transition)."""
    from fabkit.physics.calibrate import entry

    spec = load_spec(write_spec(tmp_path, mutated({"ramp.profile": "straight", "ramp.angle": 5,
                                                   "ramp.length": 15, "ball.rolling_resistance": 0.1})))
    e = entry(spec, np.array([0.5, 1.0]))
    assert not e.reached.any() and np.isnan(e.v_in).all() and "stops" in e.why
    spec = load_spec(write_spec(tmp_path, mutated({"ball.rolling_resistance": 0.1}), "b.yaml"))
    e = entry(spec, np.array([0.05, 4.5]))
    assert e.reached.tolist() == [False, True] and "stops" in e.why
    # energy: the resistance's work c N s at least c g cos(phi) per unit path, so v^2 is below the closed form's
    assert e.v_in[1] < math.sqrt(2 * G_CM * 4.5 / 1.4) * 0.99


@pytest.mark.parametrize("changes,key", [
    ({"ramp.length": 10}, "ramp.length"),                                  # fabkit's ramp is sized from heights
    ({"ramp.profile": "straight", "ramp.length": 10}, "ramp.angle"),       # straight needs both
    ({"ramp.profile": "straight", "ramp.angle": 20}, "ramp.length"),
    ({"ramp.profile": "straight", "ramp.angle": 95, "ramp.length": 10}, "ramp.angle"),
    ({"ramp.profile": "curved"}, "ramp.profile"),
])
def test_ramp_keys_refused(cli, tmp_path, changes, key):
    code, out, err = cli("calibrate", write_spec(tmp_path, mutated(changes)))
    assert code == 2 and key in err and err.count("\n") == 1 and out == ""


@pytest.mark.parametrize("units,scale", [("mm", 10.0), ("in", 1 / 2.54)])
def test_entry_speed_is_the_same_in_every_unit(tmp_path, units, scale):
    """The paper's spec written in mm or inches (every design length scaled, damping in 1/s
    unchanged): the same ball on the same ramp, the same speeds in the new unit."""
    from fabkit.physics.calibrate import entry_speed

    raw = mutated({"simulation.damping": 0.127})
    ref = entry_speed(load_spec(write_spec(tmp_path, raw, "cm.yaml")), np.array([0.5, 2.5, 4.5]))
    a, b, c_, d, eta = (raw["surface"]["params"][k] for k in ("a", "b", "c", "d", "eta"))
    raw["units"] = units
    raw["surface"]["params"].update(a=a / scale, b=b / scale, d=d / scale, c=c_ / scale, eta=eta * scale,
                                    eps=raw["surface"]["params"]["eps"])
    raw["surface"]["height"] = "eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x)"
    for key in ("x", "y"):
        raw["surface"][key] = [v * scale for v in raw["surface"][key]]
    raw["surface"]["top"] *= scale
    raw["ball"]["diameter"] *= scale
    raw["ramp"]["heights"] = [h * scale for h in raw["ramp"]["heights"]]
    for key in ("start", "margin"):
        raw["simulation"][key] *= scale
    v = entry_speed(load_spec(write_spec(tmp_path, raw, f"{units}.yaml")), np.array([0.5, 2.5, 4.5]) * scale)
    np.testing.assert_allclose(v, ref * scale, rtol=1e-8)


@pytest.mark.parametrize("mu", [3.0, 10.0])
def test_the_crawl_bound_is_a_lower_bound(tmp_path, mu):
    """The time bound that refuses a crawling ball before integrating (physics/calibrate.py,
    _crawl_bound) stays below the reference descent's time, and the descent's speed agrees."""
    from fabkit.lab.ramp import ramp_profile
    from fabkit.physics.calibrate import _crawl_bound, entry

    spec = load_spec(write_spec(tmp_path, mutated({"simulation.damping": mu})))
    prof = ramp_profile(spec)
    H = np.array([0.5, 4.5])
    gt = G_CM / 1.4
    ug = np.linspace(0.0, float(prof.u_release(H)[-1]), 4001)
    zp = prof.slope(ug)
    w = np.sqrt(1 + zp ** 2)
    kap = prof.curvature(ug) / w ** 3
    A = (1 - 1.25 * kap) * w
    path = np.concatenate([[0.0], np.cumsum(0.5 * (A[1:] + A[:-1]) * np.diff(ug))])
    bound = _crawl_bound(ug, zp / w, path, prof.u_release(H), H, gt, mu)
    e = entry(spec, H)
    for i, h in enumerate(H):
        v, t = _reference_descent(spec, h, mu, 0.0, want_time=True)
        assert 0 <= bound[i] <= t
        assert e.v_in[i] == pytest.approx(v, rel=1e-6)


def test_a_crawling_ball_is_refused_quickly(cli, tmp_path):
    """damping 300 1/s: the bound (at least 60 s down the ramp) refuses it, exit 1, one line."""
    code, out, err = cli("calibrate", write_spec(tmp_path, mutated({"simulation.damping": 300})))
    assert code == 1 and err.count("\n") == 1 and "simulation.t_max" in err and "at least" in err


def test_running_out_of_budget_is_reported(cli, tmp_path, monkeypatch):
    """The descent's evaluation budget (each integrator, each piece) ends in one line, exit 1,
    naming the budget (here shrunk to 40 evaluations, so that the paper's spec runs out)."""
    import fabkit.physics.calibrate as cal

    monkeypatch.setattr(cal, "RAMP_EVAL_BUDGET", 40)
    code, out, err = cli("calibrate", PAPER)
    assert code == 1 and err.count("\n") == 1 and "ran out of its budget (40 evaluations" in err and out == ""


def test_heights_below_the_lines_resolution_are_refused(cli, tmp_path):
    """H is a difference of the centre's heights (~2.5 cm here): below 1e-7 of that rounding
    would decide the release point. --height and ramp.heights name themselves; without losses
    the closed form takes any height."""
    code, out, err = cli("calibrate", PAPER, "--height", "1e-300")
    assert code == 2 and "--height" in err and "resolves" in err and err.count("\n") == 1
    code, out, err = cli("calibrate", write_spec(tmp_path, mutated({"ramp.heights": [1e-9, 1e-6]})))
    assert code == 2 and "ramp.heights" in err and "resolves" in err
    code, out, err = cli("calibrate", write_spec(tmp_path, mutated({"simulation.damping": 0}), "z.yaml"),
                         "--height", "1e-300")
    assert code == 0 and f"{math.sqrt(2 * G_CM * 1e-300 / 1.4):.8g}" in out
