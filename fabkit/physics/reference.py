"""Single-launch reference path: scipy ``solve_ivp`` with the simulator's events.

One launch at a time, with scipy's RK45, DOP853, Radau or LSODA. It solves the
same equations as the batched integrator (eq. xyODE for ``model='full'``,
eq. xyODE_simp for ``model='simplified'``, through :mod:`fabkit.physics.models`)
and detects the same events, written as plain callables with ``terminal`` and
``direction`` in the ``solve_ivp`` pattern:

    bounce        xdot crosses 0 from + to -        (a maximum of x(t); recorded, not terminal)
    escaped       x crosses ``start`` moving toward -x, t > 0     (terminal; v_out = |xdot| there)
    flew_off      h(x, y) reaches top - margin, or the ball leaves the footprint
                  shrunk by the margin                            (terminal)
    lost_contact  the normal-force bracket of eq. (xyODE) falls to 0 (full model; terminal)
    captured      none of these before ``t_max``

At ``rtol=1e-12`` (the default) it is the converged reference against which the
fast path is tested; at looser tolerances it is the scipy peer of the
work-precision study. Results carry ``nfev`` and the wall time.
"""

from __future__ import annotations

import math
import time

import numpy as np

METHODS = ("RK45", "DOP853", "Radau", "LSODA")


def _models():
    from . import models

    return models


def _state_rhs(problem):
    """f(t, s) for solve_ivp, s = (x, y, xdot, ydot) of shape (4,), or for the ball
    (x, y, xdot, ydot, u) of shape (5,) (contact point, its velocity, the spin)."""
    m = _models()
    if problem.model == "ball":
        def f(t, s):
            return np.asarray(m.ball_rhs(problem, s), dtype=float).reshape(5)

        return f

    def f(t, s):
        return np.asarray(m.rhs(problem, s), dtype=float).reshape(4)

    return f


def _ball(problem, s, key) -> float:
    return float(np.asarray(_models().ball_quantities(problem, s)[key]).reshape(()))


def _energy(problem, s) -> float:
    if problem.model == "ball":
        return _ball(problem, s, "energy")
    return float(np.asarray(_models().energy(problem, s)).reshape(()))


def _bracket(problem, s) -> float:
    return float(np.asarray(_models().normal_bracket(problem, s)).reshape(()))


def _event(fn, terminal: bool, direction: int):
    fn.terminal = terminal
    fn.direction = direction
    return fn


def _events(problem):
    """The event callables, in a fixed order, with their outcome names."""
    h = problem.fns.h
    x0, x1 = problem.x_range
    y0, y1 = problem.y_range
    mg = float(problem.margin)
    start = float(problem.start)
    z_lim = float(problem.top) - mg
    ev = [
        ("bounce", _event(lambda t, s: s[2], False, -1)),
        # only while moving toward -x: at a huge speed the first steps can leave x == start
        # in floating point, which must not count as a return
        ("escaped", _event(lambda t, s: (s[0] - start) if (t > 0 and s[2] < 0) else 1.0, True, -1)),
        # minima of x: one at or beyond the start line inside a step is an escape too (solve_launch)
        ("x_min", _event(lambda t, s: s[2], False, 1)),
        ("flew_off:top", _event(lambda t, s: float(h(s[0], s[1])) - z_lim, True, 1)),
        ("flew_off:x_max", _event(lambda t, s: s[0] - (x1 - mg), True, 1)),
        ("flew_off:x_min", _event(lambda t, s: (x0 + mg) - s[0], True, 1)),
        ("flew_off:y_max", _event(lambda t, s: s[1] - (y1 - mg), True, 1)),
        ("flew_off:y_min", _event(lambda t, s: (y0 + mg) - s[1], True, 1)),
    ]
    if problem.model == "full":
        ev.append(("lost_contact", _event(lambda t, s: _bracket(problem, s), True, -1)))
    if problem.model == "ball":
        r = float(problem.radius)
        ev.append(("lost_contact", _event(lambda t, s: _ball(problem, s, "N"), True, -1)))
        ev.append(("bridged", _event(lambda t, s: 1.0 - r * _ball(problem, s, "kappa"), True, -1)))
        if math.isfinite(problem.friction):
            fr = float(problem.friction)
            ev.append(("slipped", _event(lambda t, s: fr - min(_ball(problem, s, "slip"), 1e300), True, -1)))
    return ev


_REASONS = {
    "flew_off:top": "z reaches top - margin",
    "flew_off:x_max": "x reaches the footprint's far end (minus the margin)",
    "flew_off:x_min": "x reaches the footprint's near end (plus the margin)",
    "flew_off:y_max": "y reaches the footprint's side (minus the margin)",
    "flew_off:y_min": "y reaches the footprint's side (plus the margin)",
    "lost_contact": "the normal force falls to zero",
    "bridged": "the ball touches the surface at two points (r times the concave curvature reaches 1)",
    "slipped": "the friction the rolling needs exceeds ball.friction",
}


def solve_launch(problem, v_in: float, y0: float = 0.0, vy0: float = 0.0, *, method: str = "DOP853",
                 rtol: float = 1e-12, atol: float = 1e-14, t_max: float | None = None) -> dict:
    """One launch at x = ``problem.start``, y = ``y0``, xdot = ``v_in``, ydot = ``vy0``.

    Parameters
    ----------
    problem : models.Problem
    v_in : float, design units/s (> 0 moves toward +x)
    y0, vy0 : transverse offset (design units) and velocity (design units/s)
    method : 'RK45' | 'DOP853' | 'Radau' | 'LSODA' (scipy)
    rtol, atol : solve_ivp tolerances (atol in design units)
    t_max : time limit, s (default ``problem.t_max``)

    Returns
    -------
    dict with
        outcome        one of models.OUTCOMES
        reason         for flew_off / lost_contact: why (e.g. 'z reaches top - margin'), else ''
        bounces        int, maxima of x(t) before the end
        bounce_times   (bounces,) float, s (event-located, accurate to ~rtol)
        v_out          |xdot| at the escape crossing (nan unless escaped), design units/s
        t_end, x_end, y_end, xdot_end, ydot_end   the final state
        max_z, max_abs_y   over the step points (design units)
        energy_error   max |E(t) - E(0)| / (v_in^2 / 2) over the step points (meaningful
                       undamped; with damping it includes the dissipated energy)
        nfev, seconds, status, message   from solve_ivp and the wall clock
    """
    from scipy.integrate import solve_ivp

    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    t_max = float(problem.t_max if t_max is None else t_max)
    s0 = np.array([float(problem.start), float(y0), float(v_in), float(vy0)])
    ball = problem.model == "ball"
    if ball:  # the centre's horizontal velocity (v_in, vy0): the contact point's velocity, u = 0
        from .ball import contact_velocity, geometry, jet_function

        geo = geometry(jet_function(problem.fns)(s0[0], s0[1]), float(problem.radius))
        xd, yd = contact_velocity(geo, s0[2], s0[3])
        s0 = np.array([s0[0], s0[1], float(xd), float(yd), 0.0])
    events = _events(problem)
    fun = _state_rhs(problem)
    t0 = time.perf_counter()
    try:
        with np.errstate(all="ignore"):
            sol = solve_ivp(fun, (0.0, t_max), s0, method=method, rtol=rtol, atol=atol,
                            events=[e for _, e in events], dense_output=True)
    except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
        # scipy's norms and Jacobians overflow at absurd speeds (beyond ~1e100 design units/s)
        return _failed(problem, s0, f"integration failed ({type(exc).__name__}: {exc})",
                       time.perf_counter() - t0)
    seconds = time.perf_counter() - t0

    names = [n for n, _ in events]
    outcome, reason = "captured", ""
    end = sol.y[:, -1]
    t_end = float(sol.t[-1])
    if sol.status == 1:  # a terminal event fired: the earliest one is where solve_ivp stopped
        best = None
        for i, n in enumerate(names):
            if n in ("bounce", "x_min") or len(sol.t_events[i]) == 0:
                continue
            te = float(sol.t_events[i][0])
            if best is None or te < best[0]:
                best = (te, n, sol.y_events[i][0])
        if best is not None:
            t_end, name, end = best[0], best[1], best[2]
            outcome = name.split(":")[0]
            reason = _REASONS.get(name, "")
    elif sol.status < 0:
        outcome, reason = "captured", f"integration failed: {sol.message}"
    dip = _dip(sol, names.index("x_min"), float(problem.start), t_end)
    if dip is not None:   # the start line crossed and crossed back inside a step: escaped there
        t_end, end = dip
        outcome, reason = "escaped", ""

    Ys = sol.y[:, sol.t <= t_end] if dip is not None else sol.y     # the step points up to the end
    tb = np.asarray(sol.t_events[0], dtype=float)
    tb = tb[tb <= t_end]
    vx_end, vy_end = float(end[2]), float(end[3])
    max_slip = math.nan
    if ball:   # the centre's velocity; the largest slip ratio over the steps and the end
        q = _models().ball_quantities(problem, end)
        vx_end, vy_end = float(q["vx"]), float(q["vy"])
        sl = np.append(_models().ball_quantities(problem, Ys)["slip"][:-1], q["slip"])
        if outcome in ("lost_contact", "bridged") and sl.size > 1:
            sl = sl[:-1]   # the ratio is unbounded where contact is lost
        max_slip = float(np.nanmax(sl))
    v_out = abs(vx_end) if outcome == "escaped" else math.nan

    xs, ys = Ys[0], Ys[1]
    z = np.asarray(problem.fns.h(xs, ys), dtype=float)
    with np.errstate(all="ignore"):
        e = np.array([_energy(problem, Ys[:, j]) for j in range(Ys.shape[1])])
        e0 = _energy(problem, s0)
        scale = max(0.5 * float(v_in) * float(v_in), 1e-300)
        drift = float(np.max(np.abs(e - e0)) / scale)
    return {
        "outcome": outcome,
        "reason": reason,
        "bounces": int(len(tb)),
        "bounce_times": tb,
        "v_out": v_out,
        "t_end": t_end,
        "x_end": float(end[0]),
        "y_end": float(end[1]),
        "xdot_end": vx_end,
        "ydot_end": vy_end,
        "max_slip": max_slip,
        "max_z": float(np.max(z)),
        "max_abs_y": float(np.max(np.abs(ys))),
        "energy_error": drift,
        "nfev": int(sol.nfev),
        "seconds": seconds,
        "status": int(sol.status),
        "message": str(sol.message),
    }


def _dip(sol, i_min: int, start: float, t_end: float):
    """The first minimum of x before ``t_end`` at or beyond the start line (x <= start),
    which the escape event (a sign change at the step ends) misses when x returns above
    the line within the step: (t, state) of the crossing before it, from the dense
    output (brentq to rounding), or None."""
    from scipy.optimize import brentq

    tm = np.asarray(sol.t_events[i_min], dtype=float)
    ym = sol.y_events[i_min]
    for k in range(len(tm)):
        if tm[k] > t_end:
            break
        if not ym[k][0] <= start:
            continue
        # the crossing: between the last step point before the minimum with x above the line
        # and the minimum
        above = np.flatnonzero((sol.t < tm[k]) & (sol.y[0] > start))
        if len(above) == 0:
            return None
        ta = float(sol.t[above[-1]])
        te = brentq(lambda t: float(sol.sol(t)[0]) - start, ta, float(tm[k]), xtol=1e-15, rtol=1e-15)
        if te >= t_end:
            return None
        y = np.array(sol.sol(te), dtype=float)
        y[0] = start
        return float(te), y
    return None


def _failed(problem, s0, reason: str, seconds: float) -> dict:
    """The result of a solve that raised: still at the launch state, outcome captured
    (with the reason), finite figures."""
    return {
        "outcome": "captured", "reason": reason, "bounces": 0, "bounce_times": np.zeros(0),
        "v_out": math.nan, "t_end": 0.0, "x_end": float(s0[0]), "y_end": float(s0[1]),
        "xdot_end": float(s0[2]), "ydot_end": float(s0[3]),
        "max_z": float(problem.fns.h(s0[0], s0[1])), "max_abs_y": abs(float(s0[1])),
        "energy_error": 0.0, "nfev": 0, "seconds": seconds, "status": -1, "message": reason,
    }
