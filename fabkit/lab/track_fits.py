"""The lab stage's fits of each track: the model's start and viscous damping fitted by
least squares to a release whole, or to a launch's legs (before its first bounce, after
its last).

Pure functions on :class:`tracks.Track` and the spec's :class:`models.Problem`; no
printing, no files. Each frame is weighted by the tracker's sigma relative to the
track's median (``Track.weights``: all 1 without sigma columns, or with a constant
sigma). In: a track and its events (:mod:`.events`); out: the fitted state
at the anchor frame, the damping, their one-sigma errors from the fit's covariance, the
fit's status ("converged", or why not: a fit that did not converge is not fitted, its
values and errors are None). The integration on the compiled engine, the bounded least
squares (damping >= 0) and the budget (model runs, never seconds) are :mod:`.fitting`'s.

Releases: the damping fitted with the model
-------------------------------------------
The spec's model (eq. xyODE or xyODE_simp, or the ball, with the spec's nonlinear
damping and rolling resistance) with viscous damping mu is integrated from the first
frame (DOP853, rtol 1e-8) and x(t), y(t) at the frame times are fitted to the track by
least squares over (x0, y0, vx0, vy0, mu) (the ball's: its contact point, velocity and
spin u). ``omega``: pi / (mean spacing of successive extrema of the fitted y(t), found
on the model sampled every 1/20000 of the track, refined by cubic Hermite
interpolation). Errors: one standard deviation from the fit's covariance.
``damping_logdec``: the paper's estimate (:func:`.events.logdec`), which assumes the
linear oscillator y'' + mu y' + w^2 y = 0. In the full model the ball's kinetic energy
includes zdot^2 = (h_y ydot)^2, so at large amplitude the transverse oscillation is
anharmonic: it spends more of each period near its turning points, the mean kinetic
energy (the part viscous damping removes) is below half the energy, and the amplitude
decays slower than e^{-mu t/2}. ``logdec_ratio`` measures that bias on the fitted
model's own noise-free trajectory (log-decrement of the model / fitted mu).

Launch legs
-----------
The state at the first frame and mu are fitted to the frames before the first bounce
(mu starts from the releases' fitted damping when the same run has releases, else the
spec's: a leg of a second or more pins it well, so a wrong spec damping does not bias
the speeds); likewise the state at the last frame to the frames after the last bounce,
integrated backward. A long leg is fitted by continuation: over the LEG_START s nearest
its anchor frame first, then over twice that, ..., each fit starting from the last (a
slow exit crawling for seconds before the track ends is otherwise out of reach of a
start taken from the last frames alone).

A launch whole
--------------
The state at the first frame and mu fitted to every frame of a launch, through its
bounces (:func:`fit_whole`: continuation from the entry leg's fit, twice its span, four
times, ...). The loss laws use it in place of the legs where it converged with a residual
rms within 2 noise sigma (:func:`.outcome.whole_usable`); the legs between bounces are
fitted only where it did not (:func:`.outcome.fit_between`).

The ball model
--------------
A track is of the ball's centre C = P + r n(P). The ball model's state is the contact
point's (x, y, xd, yd) and its spin u: the fits integrate that state and compare the
model's centre (:func:`fitting.centre_of`) with the track; their start is the contact
point under the seen centre (Newton, :func:`fitting.contact_of`) with u = 0.
"""

from __future__ import annotations

import math
import time

import numpy as np

from .events import edge_state
from .fitting import (COEF_FLOOR, COEF_STEP, FIT_RTOL, STATE_STEP, Budget, FitStopped, central_jacobian,
                      centre_of, contact_of, covariance_errors, least_squares_bounded, model_solve, state_size)

LEG_START = 0.5        # s: first span of a leg's continuation fit (fit_leg)
#: evaluations of one least-squares fit (a leg's step, a release)
LEG_MAX_NFEV = 100
RELEASE_MAX_NFEV = 100
#: samples of the fitted model over a release, for its extrema (omega, the model's logdec)
DENSE_SAMPLES = 20000


def _steps(p, ns) -> np.ndarray:
    """The Jacobian's central-difference steps (:mod:`.fitting`): the state's, then mu's."""
    h = STATE_STEP * np.maximum(1.0, np.abs(p))
    h[ns] = COEF_STEP * max(abs(float(p[ns])), COEF_FLOOR["damping"])
    return h


def _lower(ns) -> np.ndarray:
    """Bounds of (state, mu): the state free, mu >= 0."""
    lo = np.full(ns + 1, -np.inf)
    lo[ns] = 0.0
    return lo


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


def fit_whole(problem, track, leg: dict, budget: Budget | None = None) -> dict:
    """The model's state at the first frame and the viscous damping fitted to the WHOLE
    track, through its bounces (the model rolls up the wall and back: nothing breaks
    there), from the entry leg's fit ``leg`` (:func:`fit_leg`): by continuation, over
    twice the leg's span, then four times, ... each fit from the last. One state for the
    whole launch ties the speeds before, between and after the bounces to one
    trajectory, which is what separates a loss ~ v (viscous) from a constant one
    (rolling) (:mod:`.losses`). Returns as :func:`fit_leg`."""
    t = track.t
    idx = np.arange(len(t))
    t0 = float(t[0])
    p = np.array([*np.asarray(leg["state"], dtype=float), max(float(leg["damping"]), 1e-3)])
    reach = t - t0
    span = 2.0 * max(float(leg.get("span", LEG_START)), LEG_START)
    while span < reach[-1]:
        step = _fit_leg_once(problem, track, idx[reach <= span], t0, p, budget)
        p = step["p"]
        if step["status"] not in ("converged", "evaluations"):
            return step
        span *= 2.0
    return _fit_leg_once(problem, track, idx, t0, p, budget)


def _fit_leg_once(problem, track, idx, t0: float, p0, budget: Budget | None = None) -> dict:
    """One least-squares fit of (state at t0, mu) to the frames ``idx`` (:func:`fit_leg`)."""
    te = track.t[idx]
    wx, wy = track.weights()
    w = np.concatenate([wx[idx], wy[idx]])
    data = np.concatenate([track.x[idx], track.y[idx]]) * w
    ns = state_size(problem)
    npar = ns + 1

    def run(P):
        Y = model_solve(problem, P[:, :ns].T, P[:, ns], t0, te, rtol=FIT_RTOL)
        return np.concatenate([Y[0], Y[1]], axis=1) * w

    def fun(p):
        return run(p[None, :])[0] - data

    def jac(p):
        return central_jacobian(run, p, _steps(p, ns))

    x, r, J, nfev, status = least_squares_bounded(fun, jac, p0, budget, lower=_lower(ns), xtol=1e-10,
                                                  max_nfev=LEG_MAX_NFEV)
    err = covariance_errors(J, r, npar)
    return {"t": t0, "state": x[:ns], "error": err[:ns], "damping": float(x[ns]),
            "damping_error": float(err[ns]), "rms": float(math.sqrt(float(r @ r) / r.size)), "p": x,
            "status": status, "nfev": int(nfev)}


def _dense_extrema(problem, p, ns: int, t0: float, t1: float, n: int = DENSE_SAMPLES):
    """Times and values of the extrema of y of the model from the fitted start ``p``
    (roots of yd; the ball's: its contact point's) on [t0, t1]: the model sampled at n
    times, each root refined by the cubic Hermite interpolant of yd (with ydd), its
    value by that of y (with yd)."""
    ts = np.linspace(t0, t1, n)
    _, Y, dY = model_solve(problem, p[:ns, None], p[ns:ns + 1], t0, ts, derivatives=True)
    y, vy, ay = Y[0, :, 1], Y[0, :, 3], dY[0, :, 3]
    out, vals = [], []
    for i in np.flatnonzero(np.sign(vy[:-1]) * np.sign(vy[1:]) < 0):
        h = ts[i + 1] - ts[i]
        # Hermite cubic of vy on [0, 1]: roots by a few Newton steps from the linear guess
        a0, a1, m0, m1 = vy[i], vy[i + 1], ay[i] * h, ay[i + 1] * h
        s = a0 / (a0 - a1)
        for _ in range(8):
            h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
            f = h00 * a0 + h10 * m0 + h01 * a1 + h11 * m1
            df = (6 * s**2 - 6 * s) * a0 + (3 * s**2 - 4 * s + 1) * m0 + (-6 * s**2 + 6 * s) * a1 \
                + (3 * s**2 - 2 * s) * m1
            if df == 0:
                break
            s = min(1.0, max(0.0, s - f / df))
        h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
        out.append(ts[i] + s * h)
        vals.append(float(h00 * y[i] + h10 * vy[i] * h + h01 * y[i + 1] + h11 * vy[i + 1] * h))
    return np.array(out), np.array(vals)


def fit_release(problem, track, sigma: float, mu0: float, budget: Budget | None = None) -> dict:
    """Least-squares fit of (x0, y0, vx0, vy0, mu) to a release track (module doc). A fit
    that did not converge is not fitted: its values and errors are None, ``fit_status``
    says why."""
    t = track.t
    st = edge_state(track)
    ns = state_size(problem)
    npar = ns + 1
    p0 = np.array([*start_state(problem, st), max(mu0, 1e-3)])
    t0 = float(t[0])
    w = np.concatenate(track.weights())
    data = np.concatenate([track.x, track.y]) * w

    def run(P):
        Y = model_solve(problem, P[:, :ns].T, P[:, ns], t0, t)
        return np.concatenate([Y[0], Y[1]], axis=1) * w

    def fun(p):
        return run(p[None, :])[0] - data

    def jac(p):
        return central_jacobian(run, p, _steps(p, ns))

    t_start = time.perf_counter()
    p, r, J, nfev, status = least_squares_bounded(fun, jac, p0, budget, lower=_lower(ns), xtol=1e-10,
                                                  max_nfev=RELEASE_MAX_NFEV)
    err = covariance_errors(J, r, npar)
    keys = ("x", "y", "vx", "vy", "u")[:ns]
    out = {"damping": None, "damping_error": None, "omega": None, "initial_state": None,
           "initial_state_error": None, "residual_rms": float(math.sqrt(float(r @ r) / r.size)),
           "noise_sigma": float(sigma), "iterations": int(nfev), "fit_seconds": None, "fit_status": status,
           "model_logdec": None}
    if status == "converged" and not np.all(np.isfinite(err)):
        status = out["fit_status"] = "the fit's covariance is singular (no error bars)"
    if status != "converged":
        out["fit_seconds"] = time.perf_counter() - t_start
        return out
    # omega and the model's own log-decrement on the fitted noise-free trajectory
    try:
        te, ve = _dense_extrema(problem, p, ns, t0, float(t[-1]))
        ys = model_solve(problem, p[:ns, None], p[ns:ns + 1], t0, t)[:2, 0]
    except FitStopped:  # the fitted model followed the frames: its samples between them too
        te, ve = np.zeros(0), np.zeros(0)
        ys = np.full((2, t.size), np.nan)
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
    out.update({
        "damping": float(p[ns]), "damping_error": float(err[ns]),
        "omega": float(omega),
        "initial_state": {"t": t0, **{k: float(v) for k, v in zip(keys, p[:ns])}},
        "initial_state_error": {k: float(e) for k, e in zip(keys, err[:ns])},
        "fit_seconds": time.perf_counter() - t_start,
        "model_logdec": model_ld,
        "_model": {"t": t, "x": ys[0], "y": ys[1]},
    })
    return out
