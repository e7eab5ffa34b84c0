"""The lab stage's fits of each track: the model's start and viscous damping fitted by
least squares to a release whole, or to a launch's legs (before its first bounce, after
its last).

Pure functions on :class:`tracks.Track` and the spec's :class:`models.Problem`; no
printing, no files. In: a track and its events (:mod:`.events`); out: the fitted
state at the anchor frame, the damping, one-sigma errors from the fit's covariance,
the fit's status (converged, or why not). The integration and the bounded least
squares are :mod:`.fitting`'s.


Entry and exit speeds
---------------------
The model's state at the first frame and the viscous damping are fitted by least
squares to the frames before the first bounce (x0, y0, vx0, vy0, mu; mu starts from the
releases' fitted damping when the same run has releases, else the spec's: a leg of a
second or more pins it well, so a wrong spec damping does not bias the speeds), then
carried along the model to x = start: ``v_in`` = |xd| there (and y, yd there start the side-by-side simulation).
Likewise the state at the last frame from the frames after the last bounce, carried
forward to x = start: ``v_out``. A long leg is fitted by continuation: over the 0.5 s
(:func:`fit_leg`).

carries back to x = start has ``escaped``; one with a point beyond top - margin or
outside the footprint shrunk by the margin ``flew_off``; else ``captured``.

The ball model
--------------
A track is of the ball's centre C = P + r n(P). The ball model's state is the contact
point's (x, y, xd, yd) and its spin u: the fits integrate that state and compare the
model's centre (:func:`fitting.centre_of`) with the track; their start is the contact

integration; running out is reported); :func:`screen_track` refuses, before any fit, a
track that cannot be of this surface in the spec's unit, and finds a ball that never
moves. The loss laws are compared in :mod:`fabkit.lab.losses`.

Releases: the damping fitted with the model
-------------------------------------------
The spec's model (models.fused, eq. xyODE or xyODE_simp, with the spec's nonlinear
damping) with viscous damping mu is integrated from the first frame (scipy DOP853,
rtol 1e-8) and x(t), y(t) at the frame times are fitted to the track by least
squares over (x0, y0, vx0, vy0, mu) (Jacobian by finite differences, all perturbed
lanes in one integration so they share their steps). ``omega``: pi / (mean spacing
of successive extrema of the fitted y(t)). Errors: one standard deviation from the
fit's covariance. ``damping_logdec``: the paper's estimate, from the half
peak-to-peak amplitudes A_k of successive extrema of the track's y: ln A_k = c -
mu t_k / 2 by least squares; it assumes the linear oscillator y'' + mu y' + w^2 y = 0.
In the full model the ball's kinetic energy includes zdot^2 = (h_y ydot)^2, so at
large amplitude the transverse oscillation is anharmonic: it spends more of each
period near its turning points, the mean kinetic energy (the part viscous damping
removes) is below half the energy, and the amplitude decays slower than
e^{-mu t/2}. ``logdec_ratio`` measures that bias on the fitted model's own noise-free
trajectory (log-decrement of the model / fitted mu).
"""

from __future__ import annotations

import math
import time

import numpy as np

from .events import edge_state
from .fitting import (FIT_RTOL, Budget, FitStopped, centre_of, contact_of, covariance_errors,
                      least_squares_bounded, model_solve, state_size)

LEG_START = 0.5        # s: first span of a leg's continuation fit (fit_leg)


def start_state(problem, st) -> list:
    """The model's starting state from an edge state (t, X, Y, VX, VY) of the track: the
    point models' (x, y, xd, yd) are the track's; the ball's contact point and its
    velocity under the seen centre (:func:`fitting.contact_of`) and u = 0."""
    if problem.model != "ball":
        return list(st[1:5])
    try:
        x, y, xd, yd = contact_of(problem, *st[1:5])
    except ValueError as exc:
        raise FitStopped(str(exc)) from None
    return [float(x), float(y), float(xd), float(yd), 0.0]


def fit_leg(problem, track, sel: np.ndarray, end: bool, mu: float, budget: Budget | None = None) -> dict:
    """The model's state at the first (``end``: last) frame and the viscous damping, fitted
    by least squares to the frames ``sel`` (a leg of a launch: before its first bounce, or
    after its last); ``mu`` is the damping's starting value. Returns {"t", "state" (4,),
    "error" (4,) one sigma, "damping", "damping_error", "rms"}."""
    t = track.t
    anchor = len(t) - 1 if end else 0
    idx = np.unique(np.concatenate([[anchor], sel]))
    if end:
        idx = idx[::-1]
    st = edge_state(track, end=end)
    p = np.array([*start_state(problem, st), max(float(mu), 1e-3)])
    t0 = float(t[anchor])
    # continuation: a long leg is fitted over LEG_START s from the anchor first, then over
    # twice that, ... each from the last fit, so the start (the edge state, a few percent
    # off) never meets seconds of model motion at once (a slow, long exit leg)
    reach = np.abs(t[idx] - t0)
    span = LEG_START
    while span < reach[-1]:
        step = _fit_leg_once(problem, track, idx[reach <= span], t0, p, budget)
        p = step["p"]
        if step["status"] not in ("converged", "evaluations"):
            return step          # out of budget: the best so far, reported
        span *= 2.0
    return _fit_leg_once(problem, track, idx, t0, p, budget)


def _fit_leg_once(problem, track, idx, t0: float, p0, budget: Budget | None = None) -> dict:
    """One least-squares fit of (state at t0, mu) to the frames ``idx`` (:func:`fit_leg`)."""
    te = track.t[idx]
    data = np.concatenate([track.x[idx], track.y[idx]])
    ns = state_size(problem)
    npar = ns + 1

    def run(P):
        Y, _ = model_solve(problem, P[:, :ns].T.copy(), P[:, ns], t0, te, rtol=FIT_RTOL, budget=budget)
        return Y

    def fun(p):
        Y = run(p[None, :])
        return np.concatenate([Y[0, 0], Y[1, 0]]) - data

    def jac(p):
        h = 1e-5 * np.maximum(1.0, np.abs(p))
        P = np.vstack([p] + [p + np.eye(npar)[j] * h[j] for j in range(npar)])
        Y = run(P)
        base = np.concatenate([Y[0, 0], Y[1, 0]])
        return np.column_stack([(np.concatenate([Y[0, j + 1], Y[1, j + 1]]) - base) / h[j]
                                for j in range(npar)])

    x, r, J, nfev, status = least_squares_bounded(fun, jac, p0, budget, xtol=1e-10, max_nfev=40)
    err = covariance_errors(J, r, npar)
    return {"t": t0, "state": x[:ns], "error": err[:ns], "damping": float(x[ns]),
            "damping_error": float(err[ns]), "rms": float(math.sqrt(float(r @ r) / r.size)), "p": x,
            "status": status, "nfev": int(nfev)}


def _dense_extrema(sol, lane: int, m: int, t0: float, t1: float, n: int = 20000):
    """Times of the extrema of y of one lane of a dense model solution (roots of vy)."""
    from scipy.optimize import brentq

    ts = np.linspace(t0, t1, n)
    ns = sol.y.shape[0] // m
    Y = sol.sol(ts).reshape(ns, m, n)
    vy = Y[3, lane]
    out, vals = [], []
    for i in np.flatnonzero(np.sign(vy[:-1]) * np.sign(vy[1:]) < 0):
        r = brentq(lambda s: sol.sol(s).reshape(ns, m)[3, lane], ts[i], ts[i + 1], xtol=1e-12)
        out.append(r)
        vals.append(float(sol.sol(r).reshape(ns, m)[1, lane]))
    return np.array(out), np.array(vals)


def fit_release(problem, track, sigma: float, mu0: float, budget: Budget | None = None) -> dict:
    """Least-squares fit of (x0, y0, vx0, vy0, mu) to a release track (module doc)."""
    t = track.t
    st = edge_state(track)
    ns = state_size(problem)
    npar = ns + 1
    p0 = np.array([*start_state(problem, st), max(mu0, 1e-3)])
    t0 = float(t[0])
    data = np.concatenate([track.x, track.y])
    steps = np.full(npar, 1e-5)
    cache = {}

    def run(P):
        S0 = np.array(P[:, :ns]).T
        Y, _ = model_solve(problem, S0, P[:, ns], t0, t, budget=budget)
        return Y

    def fun(p):
        key = p.tobytes()
        if key not in cache:
            Y = run(p[None, :])
            cache.clear()
            cache[key] = np.concatenate([Y[0, 0], Y[1, 0]]) - data
        return cache[key]

    def jac(p):
        h = steps * np.maximum(1.0, np.abs(p))
        P = np.vstack([p] + [p + np.eye(npar)[j] * h[j] for j in range(npar)])
        Y = run(P)
        base = np.concatenate([Y[0, 0], Y[1, 0]])
        J = np.empty((base.size, npar))
        for j in range(npar):
            J[:, j] = (np.concatenate([Y[0, j + 1], Y[1, j + 1]]) - base) / h[j]
        return J

    t_start = time.perf_counter()
    p, r, J, nfev, status = least_squares_bounded(fun, jac, p0, budget, xtol=1e-10, ftol=1e-12, max_nfev=60)
    err = covariance_errors(J, r, npar)
    # omega and the model's own log-decrement on the fitted noise-free trajectory
    try:
        _, sol = model_solve(problem, p[:ns, None], p[ns:ns + 1], t0, t, dense=True)
    except FitStopped as exc:  # the best point of a stopped fit is not followed to the end
        status = status if status != "converged" else exc.reason
        sol = None
    if sol is not None:
        te, ve = _dense_extrema(sol, 0, 1, t0, float(t[-1]))
    else:
        te, ve = np.zeros(0), np.zeros(0)
    # the release itself is a turning point (at rest): whether the fitted yd puts it just
    # inside the track or not, turning points within two frames of either end are left out
    inner = (te > t0 + 2 * track.dt) & (te < t[-1] - 2 * track.dt)
    te, ve = te[inner], ve[inner]
    omega = math.pi * (te.size - 1) / (te[-1] - te[0]) if te.size >= 2 else math.nan
    model_ld = None
    if te.size >= 3:
        amp = 0.5 * np.abs(np.diff(ve))
        tm = 0.5 * (te[1:] + te[:-1])
        model_ld = float(-2.0 * np.polyfit(tm, np.log(amp), 1)[0])
    # omega's error: the extrema spacing moves with the fitted state; propagate by the
    # fit's covariance through a finite difference of omega in mu and y0 (the dominant terms)
    ys = sol.sol(t) if sol is not None else np.full((ns, t.size), np.nan)
    if ns == 5:       # the ball: the centre, what the track shows
        ys = np.stack(centre_of(problem, ys[0], ys[1]))
    keys = ("x", "y", "vx", "vy", "u")[:ns]
    return {
        "damping": float(p[ns]), "damping_error": float(err[ns]),
        "omega": float(omega),
        "initial_state": {"t": t0, **{k: float(v) for k, v in zip(keys, p[:ns])}},
        "initial_state_error": {k: float(e) for k, e in zip(keys, err[:ns])},
        "residual_rms": float(math.sqrt(float(r @ r) / r.size)),
        "noise_sigma": float(sigma),
        "iterations": int(nfev), "fit_seconds": time.perf_counter() - t_start, "fit_status": status,
        "model_logdec": model_ld,
        "_model": {"t": t, "x": ys[0], "y": ys[1]},
    }


