"""The collective-coordinate model eq. (CCODE) and its separatrix map eq. (themap):
closed forms, a converged bisection reference, and the map read against the ODE."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fabkit.physics import cc

OMEGA = 1.0


def test_separatrix_is_log_1_plus_t2_over_2():
    # X_S(t) = log(1 + t^2/2) lies on E = 0 and solves X'' + U'(X) = 0 (exact derivatives).
    t = np.linspace(-30, 30, 601)
    X = np.log1p(0.5 * t * t)
    Xd = t / (1 + 0.5 * t * t)
    Xdd = (1 - 0.5 * t * t) / (1 + 0.5 * t * t) ** 2
    np.testing.assert_allclose(0.5 * Xd**2 + cc.U(X), 0.0, atol=1e-15)
    np.testing.assert_allclose(Xdd + (-2 * np.exp(-2 * X) + np.exp(-X)), 0.0, atol=1e-15)


@pytest.mark.parametrize("omega", [0.5, 1.0, 2.0])
def test_melnikov_constant_closed_form_matches_quadrature(omega):
    c = 0.3
    exact = c / omega * math.sqrt(2) * math.pi * math.exp(-math.sqrt(2) * omega)
    assert cc.melnikov_C(c, omega) == pytest.approx(exact, rel=1e-15)
    assert cc.melnikov_C_quad(c, omega) == pytest.approx(exact, rel=1e-9)


def test_energy_conserved_by_the_ode():
    r = cc.cc_launch(0.3, 0.2, OMEGA, rtol=1e-11, atol=1e-14)
    assert r["energy_error"] < 1e-8


def test_first_kick_is_minus_i_and_takes_omega2_C2_over_2():
    # eq. (themap) from z = 0: after one collision A ~ C (0 cos + (-1) sin)(omega (t - t1)),
    # i.e. z -> z - i, and the X energy drops by omega^2 C^2 / 2 (leading order in c).
    c = 0.05
    C = cc.melnikov_C(c, OMEGA)
    v = 1.5 * OMEGA * C
    r = cc.cc_launch(v, c, OMEGA, dense=True, rtol=1e-11, atol=1e-14)
    assert r["outcome"] == "escaped" and r["bounces"] == 1
    t1 = r["bounce_times"][0]
    t = np.linspace(t1 + 15, r["t_end"], 2000)
    A = r["solution"](t)[2]
    M = np.column_stack([np.cos(OMEGA * (t - t1)), np.sin(OMEGA * (t - t1))])
    (c1, s1), *_ = np.linalg.lstsq(M, A, rcond=None)
    assert abs(c1 / C) < 0.01
    assert s1 / C == pytest.approx(-1.0, abs=0.02)
    assert r["v_out"] == pytest.approx(math.sqrt(v * v - (OMEGA * C) ** 2), rel=0.02)


def test_time_between_bounces_is_the_morse_period():
    # Between bounces X moves on a bound orbit of energy E_1 < 0 with period
    # pi sqrt(2) / sqrt(-E_1) (so the map's bracket is |z - i|^2 - H > 0).
    c = 0.1
    v = 0.10354
    r = cc.cc_launch(v, c, OMEGA, dense=True, rtol=1e-11, atol=1e-14)
    assert r["bounces"] >= 2
    t1, t2 = r["bounce_times"][:2]
    tm = 0.5 * (t1 + t2)                      # apex of the excursion: coupling negligible
    X, P, A, Q = r["solution"](tm)
    E1 = 0.5 * P * P + cc.U(X) + c * A * math.exp(-X)
    assert E1 < 0
    assert t2 - t1 == pytest.approx(math.pi * math.sqrt(2) / math.sqrt(-E1), rel=0.02)


def test_critical_velocity_against_tight_bisection_reference():
    c = 0.2
    vc = cc.cc_critical_velocity(c, OMEGA, rel_tol=1e-6, rtol=1e-8, atol=1e-11, scan=8)
    ref = cc.cc_critical_velocity(c, OMEGA, rel_tol=1e-7, rtol=1e-12, atol=1e-15, scan=2,
                                  lo=vc * (1 - 2e-5), hi=vc * (1 + 2e-5))
    assert vc == pytest.approx(ref, rel=2e-6)


def test_critical_velocity_tends_to_the_map_formula_as_c_to_0():
    # v_c = sqrt(2) pi c exp(-sqrt(2) omega) + O(c^3): the relative gap falls ~ c^2.
    gaps = []
    for c in (0.2, 0.1, 0.05):
        vc = cc.cc_critical_velocity(c, OMEGA, rel_tol=1e-5, rtol=1e-8, atol=1e-11, scan=6)
        formula = math.sqrt(2) * math.pi * c * math.exp(-math.sqrt(2) * OMEGA)
        assert cc.v_critical_map(c, OMEGA) == pytest.approx(formula, rel=1e-15)
        gaps.append(vc / formula - 1)
    assert all(g > 0 for g in gaps)
    assert gaps[2] < 0.005
    assert gaps[0] / gaps[1] > 3 and gaps[1] / gaps[2] > 3


def test_map_critical_velocity_and_one_bounce_speed_are_exact():
    c = 0.1
    vc = cc.v_critical_map(c, OMEGA)
    b, vo = cc.cc_map(np.array([vc * 1.001, vc * 1.5, vc * 0.999]), c, OMEGA)
    assert b[0] == 1 and b[1] == 1 and b[2] != 1
    np.testing.assert_allclose(vo[:2], np.sqrt(np.array([1.001, 1.5]) ** 2 - 1) * vc, rtol=1e-12)


def test_map_has_two_bounce_windows_with_resonant_maxima():
    # Two-bounce windows accumulate below v_c; at the centre of each, theta_1 = (2m+1) pi
    # and the second kick returns all the energy: v_out -> v_in.
    c = 0.1
    vc = cc.v_critical_map(c, OMEGA)
    v = np.linspace(0.5 * vc, vc, 40001)
    b, vo = cc.cc_map(v, c, OMEGA)
    two = b == 2
    starts = np.flatnonzero(two[1:] & ~two[:-1])
    assert len(starts) >= 5
    # the windows crowd toward v_c
    gaps = np.diff(v[starts])
    assert gaps[-1] < gaps[0]
    ratio = np.where(two, vo / v, 0.0)
    assert ratio.max() == pytest.approx(1.0, abs=1e-4)
    assert np.all(b[v > vc] == 1)
