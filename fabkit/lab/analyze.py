"""Analysis of tracked launches and releases: events, speeds, and fits with the model.

Pure functions on :class:`tracks.Track` and the spec's :class:`models.Problem`; no
printing, no files. Lengths in design units, times in s.

Noise
-----
The tracking noise sigma of x (and of y) is the robust spread of the residuals of a
local cubic fit over 9 frames (Savitzky-Golay): 1.4826 MAD / sqrt(1 - w0), w0 the
filter's centre weight. Smooth motion leaves a cubic's residual far below the noise
at camera rates.

Bounces: maxima of x, robust to noise
-------------------------------------
Candidates are the maxima of x smoothed by a local cubic fit over 9 frames; one counts
as a bounce only if its prominence (how far x falls on both sides before rising above
it again) exceeds 8 sigma + 0.1 % of the track's x span, so noise wiggles (a few
sigma) never count while a real turn on the wall (centimetres) always does. A slow,
shallow turn (x falls a few sigma over tens of frames after it) is found on a second
scale: the maxima of x smoothed over 25 frames whose prominence exceeds 8 times THAT
smoothing's noise (sigma sqrt(w0), about 2.4 sigma) + 0.1 % of the span. Each bounce
time is then the vertex of a least-squares polynomial through the raw x around the
candidate (re-centred once): a parabola over 9 frames, or, where the turn is so flat
that the parabola falls less than 6 sigma across them, a cubic over a window widened
2 frames at a time (up to 33 frames, within half the way to the neighbouring
bounces) until it does: sub-frame, error about sigma / (|x''| dt^2 sqrt(60)) frames
on a 9-frame window (``bounce_time_errors``: from the fit's covariance).

Entry and exit speeds
---------------------
The model's state at the first frame and the viscous damping are fitted by least
squares to the frames before the first bounce (x0, y0, vx0, vy0, mu; mu starts from the
releases' fitted damping when the same run has releases, else the spec's: a leg of a
second or more pins it well, so a wrong spec damping does not bias the speeds), then
carried along the model to x = start: ``v_in`` = |xd| there (and y, yd there start the side-by-side simulation).
Likewise the state at the last frame from the frames after the last bounce, carried
forward to x = start: ``v_out``. A long leg is fitted by continuation: over the 0.5 s
nearest its anchor frame first, then over twice that, ..., each fit starting from the
last (a slow exit crawling for seconds before the track ends is otherwise out of reach
of a start taken from the last frames alone). Errors: one sigma of the fitted xd. A launch whose
track ends moving toward -x, left of the well, after a bounce, and that the model
carries back to x = start has ``escaped``; one with a point beyond top - margin or
outside the footprint shrunk by the margin ``flew_off``; else ``captured``.

The ball model
--------------
A track is of the ball's centre C = P + r n(P). The ball model's state is the contact
point's (x, y, xd, yd) and its spin u: the fits integrate that state and compare the
model's centre (:func:`fitting.centre_of`) with the track; their start is the contact
point under the seen centre (Newton, :func:`fitting.contact_of`) with u = 0. ``v_in`` and
``v_out`` are the centre's horizontal speed where the contact point crosses x = start,
as the simulator launches the ball.

Budgets and screen
------------------
Every fit is bounded (:mod:`fabkit.lab.fitting`: wall time, model runs, evaluations an
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

from ..errors import SpecError
from ..physics.outcomes import CAPTURED, ESCAPED, FLEW_OFF, OUTCOMES
from . import fitting
from .fitting import (FIT_RTOL, Budget, FitStopped, centre_of, contact_of, covariance_errors,
                      least_squares_bounded, model_solve, state_size)

SG_WINDOW = 9          # frames of the local cubic fits (noise and smoothing)
PROMINENCE_SIGMA = 8.0
EDGE_SECONDS = 0.16    # window of the entry / exit fits
PEAK_HALF = 4          # frames either side of a bounce in its parabola fit
PEAK_HALF_MAX = 16     # ... widened up to this for a flat, slow turn
VERTEX_DROP_SIGMA = 6.0
WIDE_WINDOW = 25       # frames of the second, wider smoothing (shallow turns)
LEG_START = 0.5        # s: first span of a leg's continuation fit (fit_leg)
#: the screen before any fit (:func:`screen_track`)
STILL_SIGMA = 10.0     # a track whose smoothed x and y move less than this many noise
STILL_FRACTION = 1e-4  # sigma + this fraction of the footprint's size never moves
ACCEL_RATIO = (0.2, 5.0)   # the track's accelerations over the model's: outside, refused


# ----------------------------------------------------------------------------
# noise and extrema
# ----------------------------------------------------------------------------
def _savgol(z: np.ndarray, w: int = SG_WINDOW, order: int = 3):
    """Local least-squares polynomial smoothing (Savitzky-Golay) over w frames, the
    ends from the polynomial fitted to the first and last w samples; and the filter's
    centre weight. numpy only (scipy.signal's import alone costs seconds)."""
    z = np.asarray(z, dtype=float)
    n = len(z)
    w = min(w, n - (1 - n % 2))
    if w < order + 2:
        return z.copy(), 1.0
    k = np.arange(w) - w // 2
    A = np.vander(k, order + 1, increasing=True)
    P = np.linalg.pinv(A)                 # rows: coefficients of 1, k, k^2, ... per sample
    out = np.convolve(z, P[0][::-1], mode="same")
    h = w // 2
    for sl, ks in ((slice(0, w), k[:h] if h else k[:0]), (slice(n - w, n), k[-h:] if h else k[:0])):
        c = P @ z[sl]
        vals = np.vander(ks, order + 1, increasing=True) @ c
        if sl.start == 0:
            out[:h] = vals
        else:
            out[n - h:] = vals
    return out, float(P[0][h])


def noise_sigma(z: np.ndarray) -> float:
    """Robust tracking-noise estimate of one coordinate (see the module doc)."""
    sm, w0 = _savgol(z)
    r = np.asarray(z, dtype=float) - sm
    mad = float(np.median(np.abs(r - np.median(r))))
    return 1.4826 * mad / math.sqrt(max(1.0 - w0, 1e-6))


def _smooth(z):
    return _savgol(z)[0]


def _peaks(s: np.ndarray, prominence: float) -> np.ndarray:
    """Indices of the local maxima of s whose topographic prominence (the drop to the
    higher of the two lowest points before s rises above the peak again, on either
    side) is at least ``prominence``."""
    n = len(s)
    cand = np.flatnonzero((s[1:-1] > s[:-2]) & (s[1:-1] >= s[2:])) + 1
    keep = []
    for i in cand:
        v = s[i]
        lo_l = v
        j = i - 1
        while j >= 0 and s[j] <= v:
            lo_l = min(lo_l, s[j])
            j -= 1
        lo_r = v
        j = i + 1
        while j < n and s[j] <= v:
            lo_r = min(lo_r, s[j])
            j += 1
        if v - max(lo_l, lo_r) >= prominence:
            keep.append(i)
    return np.asarray(keep, dtype=int)


def bounce_min_dip(x: np.ndarray, sigma: float) -> float:
    """The smallest dip of x after a turn that :func:`extrema` can count (design units): a
    turn whose x falls back by less cannot be told from the tracking noise and is not
    counted (a captured ball's last, dying turns)."""
    x = np.asarray(x, dtype=float)
    span = float(np.ptp(x)) if len(x) else 0.0
    w0 = _savgol(x, WIDE_WINDOW)[1] if len(x) >= 2 * WIDE_WINDOW else 1.0
    return PROMINENCE_SIGMA * sigma * math.sqrt(w0) + 1e-3 * span


def _near(i: int, idx, gap: int) -> bool:
    return any(abs(int(i) - int(j)) <= gap for j in idx)


def extrema(t: np.ndarray, z: np.ndarray, sigma: float, sign: int = 1, min_prominence: float = 0.0):
    """Maxima (sign=+1) or minima (-1) of a noisy series: (times (K,), values (K,), frames (K,)).

    Two scales (module doc): peaks of the 9-frame smoothing with prominence above
    max(PROMINENCE_SIGMA sigma + 1e-3 span, min_prominence), and peaks of the
    WIDE_WINDOW-frame smoothing with prominence above PROMINENCE_SIGMA times that
    smoothing's own noise (shallow, slow turns); times and values from a polynomial
    through the raw samples around each (:func:`_vertex`)."""
    z = np.asarray(z, dtype=float)
    s = sign * _smooth(z)
    span = float(np.ptp(z)) if len(z) else 0.0
    prom = max(PROMINENCE_SIGMA * sigma + 1e-3 * span, min_prominence, 1e-300)
    idx = [int(i) for i in _peaks(s, prom)]
    if len(z) >= 2 * WIDE_WINDOW:
        sw, w0 = _savgol(z, WIDE_WINDOW)
        prom_w = max(PROMINENCE_SIGMA * sigma * math.sqrt(w0) + 1e-3 * span, min_prominence, 1e-300)
        for i in _peaks(sign * sw, prom_w):
            if not _near(i, idx, WIDE_WINDOW // 2):
                # the narrow smoothing's highest point near the wide one's peak
                a, b = max(0, int(i) - WIDE_WINDOW // 2), min(len(z), int(i) + WIDE_WINDOW // 2 + 1)
                idx.append(a + int(np.argmax(s[a:b])))
    idx.sort()
    times, vals, frames = [], [], []
    for k, i in enumerate(idx):
        # the fit window stays within half the way to the neighbouring peaks
        room = min([i - idx[k - 1] if k else PEAK_HALF_MAX * 2, idx[k + 1] - i if k + 1 < len(idx)
                    else PEAK_HALF_MAX * 2]) // 2
        tv = _vertex(t, sign * z, int(i), sigma, max(PEAK_HALF, min(PEAK_HALF_MAX, room)))
        if tv is None:
            continue
        times.append(tv[0])
        vals.append(sign * tv[1])
        frames.append(int(i))
    return np.array(times), np.array(vals), np.array(frames, dtype=int)


def _fit_half(t, z, i, sigma, half_max):
    """Half-width (frames) of a bounce's vertex fit: PEAK_HALF, widened by 2 frames at a
    time (up to ``half_max``) until the local parabola falls VERTEX_DROP_SIGMA sigma at the
    window's edges, so a flat, slow turn is fitted over enough frames to resolve it."""
    n = len(t)
    h = PEAK_HALF
    while h < half_max:
        a, b = max(0, i - h), min(n, i + h + 1)
        if b - a < 5:
            break
        c2 = np.polyfit(t[a:b] - t[i], z[a:b], 2)[0]
        if -c2 * (h * (t[1] - t[0])) ** 2 >= VERTEX_DROP_SIGMA * sigma:
            break
        h += 2
    return min(h, half_max)


def _vertex(t, z, i, sigma: float = 0.0, half_max: int = PEAK_HALF):
    """Vertex of the least-squares polynomial through z around frame i (re-centred on it
    once): a parabola over 2 PEAK_HALF + 1 frames, a cubic over a window widened for a
    flat turn (:func:`_fit_half`; the cubic keeps an asymmetric turn unbiased)."""
    n = len(t)
    for _ in range(2):
        h = _fit_half(t, z, i, sigma, half_max) if sigma > 0 else PEAK_HALF
        a, b = max(0, i - h), min(n, i + h + 1)
        if b - a < 5:
            return None
        tc = t[i]
        dt = t[a:b] - tc
        c2, c1, c0 = np.polyfit(dt, z[a:b], 2)
        if not c2 < 0:
            return float(t[i]), float(z[i])
        tv = -c1 / (2 * c2)
        if h > PEAK_HALF and b - a >= 9:
            d3, d2, d1, d0 = np.polyfit(dt, z[a:b], 3)
            roots = np.roots([3 * d3, 2 * d2, d1]) if d3 != 0 else np.array([-d1 / (2 * d2)])
            roots = [float(r.real) for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12
                     and 2 * d2 + 6 * d3 * r.real < 0 and dt[0] <= r.real <= dt[-1]]
            if roots:
                tv = min(roots, key=abs)
                val = d0 + d1 * tv + d2 * tv * tv + d3 * tv ** 3
            else:
                val = None
        else:
            val = None
        j = int(np.clip(np.searchsorted(t, tc + tv), a, b - 1))
        if abs(tc + tv - t[j]) > abs(tc + tv - t[max(j - 1, 0)]):
            j = max(j - 1, 0)
        if j == i:
            break
        i = j
    tv = float(np.clip(tv, t[a] - tc, t[b - 1] - tc))
    if val is None:
        val = c0 + c1 * tv + c2 * tv * tv
    return tc + tv, float(val)


def _vertex_errors(t, z, times, sigma, half=PEAK_HALF):
    """One-sigma errors (s) of parabola-vertex times: sigma_c1 / (2 |c2|), c1 and c2 the
    slope and half-curvature of the local fit (the slope vanishes at the vertex), over
    the window the vertex was fitted on."""
    out = []
    for tb in times:
        i = int(np.clip(np.searchsorted(t, tb), 0, len(t) - 1))
        h = _fit_half(t, z, i, sigma, PEAK_HALF_MAX)
        a, b = max(0, i - h), min(len(t), i + h + 1)
        dt = t[a:b] - tb
        c2 = np.polyfit(dt, z[a:b], 2)[0]
        A = np.column_stack([dt * dt, dt, np.ones_like(dt)])
        cov = np.linalg.inv(A.T @ A) * sigma * sigma
        out.append(math.sqrt(cov[1, 1]) / (2 * abs(c2)) if c2 != 0 else math.nan)
    return out


# ----------------------------------------------------------------------------
# states at the ends of a track
# ----------------------------------------------------------------------------
def edge_state(track, end: bool = False, seconds: float = EDGE_SECONDS):
    """(t, x, y, vx, vy) at the first (last) frame from quadratic fits over ``seconds``."""
    t = track.t
    if end:
        sel = np.flatnonzero(t >= t[-1] - seconds)
    else:
        sel = np.flatnonzero(t <= t[0] + seconds)
    if sel.size < 6:
        sel = np.arange(len(t) - 6, len(t)) if end else np.arange(6)
    t0 = t[-1] if end else t[0]
    out = [float(t0)]
    pos, vel = [], []
    for z in (track.x, track.y):
        c = np.polyfit(t[sel] - t0, z[sel], 2)
        pos.append(float(c[2]))
        vel.append(float(c[1]))
    return (out[0], pos[0], pos[1], vel[0], vel[1])


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


def model_to_start(problem, t0: float, state, mu: float, t_limit: float = 30.0, budget: Budget | None = None):
    """Carry a state along the model to x = start, forward or backward in time, whichever
    way its velocity meets that line. Returns (t, x, y, vx, vy) at the crossing, or None
    if it does not get there within ``t_limit`` s. The ball: ``state`` (5,) the contact
    point's, the crossing that of the contact point (where the simulator launches it), and
    (vx, vy) the centre's horizontal velocity there (the simulator's launch velocity)."""
    from scipy.integrate import solve_ivp

    from ..physics.models import rhs

    p = problem.with_(damping=float(mu))  # (one launch: the model's rhs as documented)
    x_s = problem.start
    backward = (state[0] - x_s) * state[2] > 0

    calls = [0]

    def f(t, Y):
        calls[0] += 1
        if calls[0] > fitting.MAX_RHS_CALLS:
            raise FitStopped(f"carrying the state to x = start took more than {fitting.MAX_RHS_CALLS} evaluations")
        if budget is not None and calls[0] % 64 == 0:
            budget.check()
        return rhs(p, np.asarray(Y))

    def hit(t, Y):
        return Y[0] - x_s
    hit.terminal = True
    try:
        with np.errstate(all="ignore"):
            sol = solve_ivp(f, (t0, t0 - t_limit if backward else t0 + t_limit), list(state), method="DOP853",
                            rtol=1e-10, atol=1e-10, events=[hit])
    except FitStopped as exc:
        if budget is not None:
            budget.stopped.append(exc.reason)
        return None
    if sol.t_events is None or not len(sol.t_events[0]):
        return None
    s = sol.y_events[0][0]
    if problem.model == "ball":
        # the launch's velocity is the centre's (the compiled engine's INIT), its x, y the contact point's
        _, _, vx, vy = centre_of(problem, s[0], s[1], s[2], s[3])
        return (float(sol.t_events[0][0]), float(s[0]), float(s[1]), float(vx), float(vy))
    return (float(sol.t_events[0][0]), *map(float, s[:4]))


def well_bottom(problem) -> float:
    """x of the channel's lowest point on y = 0 within the footprint."""
    xs = np.linspace(problem.x_range[0], problem.x_range[1], 4001)
    return float(xs[int(np.argmin(problem.fns.h(xs, np.zeros_like(xs))))])


# ----------------------------------------------------------------------------
# releases
# ----------------------------------------------------------------------------
def logdec(t, y, sigma):
    """The paper's log-decrement estimate from successive extrema of y: dict with
    damping (1/s), omega (rad/s), amplitudes, times; None if fewer than 3 extrema."""
    tmax, vmax, _ = extrema(t, y, sigma, +1)
    tmin, vmin, _ = extrema(t, y, sigma, -1)
    te = np.concatenate([tmax, tmin])
    ve = np.concatenate([vmax, vmin])
    o = np.argsort(te)
    te, ve = te[o], ve[o]
    if te.size < 3:
        return None
    amp = 0.5 * np.abs(np.diff(ve))
    tm = 0.5 * (te[1:] + te[:-1])
    ok = amp > 0
    if ok.sum() < 2:
        return None
    slope, _ = np.polyfit(tm[ok], np.log(amp[ok]), 1)
    omega = math.pi * (te.size - 1) / (te[-1] - te[0])
    return {"damping": float(-2.0 * slope), "omega": float(omega), "extrema": int(te.size),
            "amplitude_first": float(amp[0]), "amplitude_last": float(amp[-1])}


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


# ----------------------------------------------------------------------------
# launches
# ----------------------------------------------------------------------------
def simulate_launch(problem, v_in: float, y0: float, vy0: float, mu: float, t_shift: float,
                    crr: float | None = None) -> dict:
    """The same launch through fabkit's simulator (integrate.launch_batch), times shifted
    to the track's clock (``t_shift`` = the track's time at x = start); ``crr``: the
    rolling resistance (None: the spec's)."""
    from ..physics.integrate import launch_batch
    from ..physics.models import OUTCOMES

    p = problem.with_(damping=float(mu))
    if crr is not None:
        p = p.with_(rolling_resistance=float(crr))
    r = launch_batch(p, [float(v_in)], [float(y0)], [float(vy0)], record=True, workers=1)
    nb = int(r.bounces[0])
    bt = [float(b) + t_shift for b in r.bounce_times[0][: min(nb, r.bounce_times.shape[1])]]
    tr = r.trajectories[0] if r.trajectories else None
    out = {"outcome": OUTCOMES[int(r.outcome[0])], "bounces": nb, "bounce_times": bt,
           "v_out": float(r.v_out[0]) if math.isfinite(r.v_out[0]) else None,
           "damping": float(mu), "v_in": float(v_in), "y0": float(y0), "vy0": float(vy0),
           "seconds": float(r.seconds)}
    if tr is not None:
        from ..plots import hermite_samples  # numpy only; plots imports matplotlib lazily

        d = hermite_samples(tr, n=3000)
        if problem.model == "ball":     # the contact point's: the track shows the centre
            d["x"], d["y"] = centre_of(problem, d["x"], d["y"])
        out["_model"] = {"t": d["t"] + t_shift, "x": d["x"], "y": d["y"]}
    return out


def _sg_derivatives(z, dt: float, w: int):
    """Local cubic fits over w frames (w odd) at the interior frames [w//2, n - w//2):
    (value, first, second derivative), and the second derivative's noise gain
    (its standard deviation per unit noise sigma of z)."""
    k = np.arange(w) - w // 2
    P = np.linalg.pinv(np.vander(k, 4, increasing=True))
    val = np.convolve(z, P[0][::-1], mode="valid")
    d1 = np.convolve(z, P[1][::-1], mode="valid") / dt
    d2 = np.convolve(z, 2.0 * P[2][::-1], mode="valid") / (dt * dt)
    return val, d1, d2, float(np.linalg.norm(2.0 * P[2])) / (dt * dt)


def screen_track(problem, track, sigma: float | None = None) -> dict:
    """What a track can be, before any fit (bounded work: a few array passes).

    * Refused (SpecError naming the file, exit 2): a point farther outside the spec's
      footprint than the footprint's own size (a track in other units, or a wrong
      ``--scale`` / ``--origin``), or accelerations far from the model's at the track's
      own positions and speeds: the ratio lambda = sum(a_track . a_model) / sum(|a_model|^2)
      (a_track from local cubic fits over ~0.1 s) outside ACCEL_RATIO by more than three
      of its standard errors. A track in m for a cm spec reads about 0.01 (the
      positions shrink 100 times, the slopes there do not); a frame rate wrong by a
      factor f reads f^2.
    * ``still``: the ball never moves: x and y smoothed over 25 frames move less than
      STILL_SIGMA noise sigma + STILL_FRACTION of the footprint's size.

    Returns {"kind": "still" | None, "accel_ratio", "accel_ratio_error", "motion"}."""
    t, x, y = track.t, track.x, track.y
    units = problem.units
    (x0, x1), (y0, y1) = problem.x_range, problem.y_range
    sx, sy = x1 - x0, y1 - y0
    for name, z, lo, hi, span in (("x", x, x0, x1, sx), ("y", y, y0, y1, sy)):
        far = (z < lo - span) | (z > hi + span)
        if np.any(far):
            v = float(z[np.flatnonzero(far)[0]])
            raise SpecError(f"{name} = {v:.4g} {units} lies beyond the footprint ({name} from {lo:g} to {hi:g} "
                            f"{units}) by more than its own size: is the track in the spec's unit ({units}) and "
                            "frame? (check the file's units, --scale and --origin)", file=track.file)
    if sigma is None:
        sigma = max(noise_sigma(x), noise_sigma(y))
    w = WIDE_WINDOW if len(t) >= 2 * WIDE_WINDOW else SG_WINDOW
    motion = max(float(np.ptp(_savgol(x, w)[0])), float(np.ptp(_savgol(y, w)[0])))
    size = max(sx, sy)
    out = {"kind": None, "accel_ratio": None, "accel_ratio_error": None, "motion": motion}
    if motion <= STILL_SIGMA * sigma + STILL_FRACTION * size:
        out["kind"] = "still"
        return out
    dt = track.dt
    wa = int(np.clip(round(0.1 / dt), SG_WINDOW, 51)) | 1
    if len(t) < wa + 8:
        return out
    from ..physics.models import accelerations

    xs, vx, ax, gain = _sg_derivatives(x, dt, wa)
    ys, vy, ay, _ = _sg_derivatives(y, dt, wa)
    # the ball is screened with the full point model's accelerations at its centre (the
    # two differ by O(r kappa), far inside the accepted ratio; a wrong unit is a factor 10+)
    pscr = problem.with_(model="full") if problem.model == "ball" else problem
    with np.errstate(all="ignore"):
        mx, my, _ = accelerations(pscr, xs, ys, vx, vy)
    ok = np.isfinite(mx) & np.isfinite(my) & (xs >= x0) & (xs <= x1) & (ys >= y0) & (ys <= y1)
    if ok.sum() < 8:
        return out
    norm2 = float(np.sum(mx[ok] ** 2 + my[ok] ** 2))
    if not norm2 > 0:
        return out
    lam = float(np.sum(ax[ok] * mx[ok] + ay[ok] * my[ok]) / norm2)
    # the fits' noise is correlated over the window: count one independent sample per window
    err = sigma * gain * math.sqrt(wa) / math.sqrt(norm2)
    out["accel_ratio"], out["accel_ratio_error"] = lam, err
    lo, hi = ACCEL_RATIO
    if lam + 3 * err < lo or lam - 3 * err > hi:
        raise SpecError(f"the ball's accelerations are {lam:.3g} times the model's at the track's own positions "
                        f"and speeds (expected near 1): is the track in the spec's unit ({units})? (a track in m "
                        f"for a cm spec reads far below 1, one in mm far above); otherwise check --scale and "
                        f"--fps (a frame rate off by a factor f reads f^2)", file=track.file)
    return out


def classify(track, sigma: float) -> tuple[str, float]:
    """('launch' | 'release', speed at the first frame). A launch enters moving toward
    +x faster than 20 sigma per 0.16 s (far above the speed noise of the fit)."""
    st = edge_state(track)
    speed = math.hypot(st[3], st[4])
    thresh = 20.0 * max(sigma, 1e-9) / EDGE_SECONDS
    return ("launch" if st[3] > thresh else "release"), speed


def outcome_of(problem, track, bounces_t, exit_state):
    """What the track shows: flew_off (a point beyond top - margin or outside the
    footprint shrunk by the margin); escaped (after its last bounce it leaves toward -x,
    left of the well, and the model carries it back through x = start: ``exit_state``
    is that crossing), else captured (still on the surface when the track ends)."""
    m = problem.margin
    with np.errstate(all="ignore"):
        z = problem.fns.h(track.x, track.y)
    if np.any(z > problem.top - m) or np.any(track.x < problem.x_range[0] + m) or \
            np.any(track.x > problem.x_range[1] - m) or np.any(track.y < problem.y_range[0] + m) or \
            np.any(track.y > problem.y_range[1] - m):
        return OUTCOMES[FLEW_OFF], None
    if exit_state is not None and len(bounces_t) and track.x[-1] < well_bottom(problem):
        return OUTCOMES[ESCAPED], abs(exit_state[3])
    return OUTCOMES[CAPTURED], None


def _launch_speeds(problem, track, bt, mu, budget: Budget | None = None) -> dict:
    """v_in, v_out and the outcome of a launch by model fits of its two legs (module doc)."""
    t = track.t
    t_in_end = (bt[0] if bt.size else t[0] + 1.0)
    sel = np.flatnonzero(t <= t_in_end)
    leg = fit_leg(problem, track, sel, False, mu, budget)
    entry = model_to_start(problem, leg["t"], leg["state"], leg["damping"], budget=budget)
    out = {"entry_fit": {"t": leg["t"], "state": leg["state"].tolist(), "error": leg["error"].tolist(),
                         "damping": leg["damping"], "damping_error": leg["damping_error"], "rms": leg["rms"]}}
    v_in = abs(entry[3]) if entry is not None else None
    # v_in's error: the fitted vx's error (the carry to x = start is exact to the model)
    out["v_in"], out["v_in_error"] = v_in, float(leg["error"][2])
    out["_entry"] = entry
    out["t_entry"] = entry[0] if entry is not None else None
    exit_state = None
    if bt.size and t[-1] - bt[-1] > 0.1:
        sel = np.flatnonzero(t >= bt[-1])
        try:
            leg2 = fit_leg(problem, track, sel, True, mu, budget)
        except FitStopped as exc:      # not even the exit leg's first point: no v_out
            if budget is not None:
                budget.stopped.append(f"exit leg: {exc.reason}")
            leg2 = None
    else:
        leg2 = None
    if leg2 is not None:
        if leg2["state"][2] < 0:
            exit_state = model_to_start(problem, leg2["t"], leg2["state"], leg2["damping"], budget=budget)
        out["exit_fit"] = {"t": leg2["t"], "state": leg2["state"].tolist(), "error": leg2["error"].tolist(),
                           "damping": leg2["damping"], "damping_error": leg2["damping_error"], "rms": leg2["rms"]}
        out["v_out_error"] = float(leg2["error"][2])
    outcome, v_out = outcome_of(problem, track, bt, exit_state)
    out["outcome"], out["v_out"] = outcome, v_out
    if v_out is None:
        out.pop("v_out_error", None)
    return out


def _still_row(problem, track, sigma, screen) -> dict:
    """The result of a track whose ball never moves (:func:`screen_track`): nothing fitted."""
    lim = STILL_SIGMA * sigma + STILL_FRACTION * max(np.ptp(problem.x_range), np.ptp(problem.y_range))
    note = (f"the ball never moves: x and y move at most {screen['motion']:.3g} {problem.units} over "
            f"{track.t[-1] - track.t[0]:.4g} s (less than {lim:.3g} {problem.units}, {STILL_SIGMA:g} noise sigma "
            f"+ {STILL_FRACTION:g} of the footprint); no release or launch found, nothing fitted (if the ball "
            f"does move, check the file's units and --scale)")
    return {"file": track.file, "kind": "still", "format": track.format, "frames": len(track),
            "fps": 1.0 / track.dt, "noise_sigma": sigma, "bounces": 0, "bounce_min_dip": None,
            "bounce_times": [], "bounce_time_errors": [], "notes": [*track.notes, note],
            "outcome": None, "v_in": None, "v_out": None, "motion": screen["motion"]}


def analyze_track(problem, track, mu_launch: float | None = None, screen: dict | None = None) -> dict:
    """One track: kind, bounces, speeds; a release is fitted with the model, a launch is
    simulated side by side (with ``mu_launch``, default the spec's damping). The fits
    share one :class:`fitting.Budget`; a track the model cannot follow from its
    first frames is refused (SpecError naming the file)."""
    t0c = time.perf_counter()
    sx, sy = noise_sigma(track.x), noise_sigma(track.y)
    sigma = max(sx, sy)
    if screen is None:
        screen = screen_track(problem, track, sigma)
    if screen.get("kind") == "still":
        out = _still_row(problem, track, sigma, screen)
        out["seconds"] = time.perf_counter() - t0c
        return out
    budget = Budget()
    try:
        out = _analyze_moving(problem, track, mu_launch, sigma, sx, sy, budget)
    except FitStopped as exc:
        raise SpecError(f"the model cannot follow this track from its first frames ({exc.reason}): is it a "
                        f"track of this surface, in the spec's unit ({problem.units})?", file=track.file) from None
    if budget.stopped:
        reasons = list(dict.fromkeys(budget.stopped))
        out["fit_status"] = "; ".join(reasons)
        out["notes"].append(f"fit stopped: {out['fit_status']}; the values are the best point reached, their "
                            "error bars are not computed")
    else:
        out.setdefault("fit_status", "converged")
    out["model_runs"] = budget.runs
    out["accel_ratio"] = screen.get("accel_ratio")
    out["seconds"] = time.perf_counter() - t0c
    return out


def _analyze_moving(problem, track, mu_launch, sigma, sx, sy, budget) -> dict:
    kind, _ = classify(track, sigma)
    bt, bx, _ = extrema(track.t, track.x, sigma, +1)
    out = {"file": track.file, "kind": kind, "format": track.format, "frames": len(track),
           "fps": 1.0 / track.dt, "noise_sigma": sigma, "bounces": int(bt.size),
           "bounce_min_dip": bounce_min_dip(track.x, sigma),
           "bounce_times": [float(b) for b in bt],
           "bounce_time_errors": [float(e) for e in _vertex_errors(track.t, track.x, bt, sigma)],
           "notes": list(track.notes)}
    if track.particle is not None:
        out["particle"] = track.particle
    mu_spec = float(problem.damping)
    if kind == "release":
        fit = fit_release(problem, track, sigma, mu_spec if mu_spec > 0 else 0.1, budget)
        ld = logdec(track.t, track.y, sigma)
        out.update({k: v for k, v in fit.items()})
        out["damping_logdec"] = ld["damping"] if ld else None
        out["omega_logdec"] = ld["omega"] if ld else None
        out["logdec_ratio"] = (fit["model_logdec"] / fit["damping"]) if fit["model_logdec"] and fit["damping"] \
            else None
        if out["logdec_ratio"] is not None:
            A = fit["initial_state"]["y"]
            out["damping_logdec_note"] = (
                f"the log-decrement assumes the linear oscillator y'' + mu y' + w^2 y = 0; at this amplitude "
                f"(|y| up to {abs(A):.3g}) the model's transverse motion is anharmonic (the ball's kinetic energy "
                f"includes (h_y ydot)^2), so the viscous loss per period is a smaller fraction of the energy and "
                f"the maxima decay slower than exp(-mu t/2): on the fitted model itself the log-decrement reads "
                f"{out['logdec_ratio']:.3f} x mu. The model fit has no such bias.")
        out["paper_form"] = (f"y'' + {fit['damping'] / fit['omega']:.4f} y' + y = 0 in a "
                             f"{1.0 / fit['omega']:.4f} s time unit") if fit["omega"] > 0 else None
        if fit["fit_status"] == "converged":
            out.pop("fit_status")
        out["outcome"] = outcome_of(problem, track, bt, None)[0]
        out["v_in"] = None
        out["v_out"] = None
    else:
        mu = mu_spec if mu_launch is None else float(mu_launch)
        out.update(_launch_speeds(problem, track, bt, mu, budget))
        ent = out.get("_entry")
        if ent is not None:
            out["simulation"] = simulate_launch(problem, out["v_in"], ent[2], ent[4], mu, ent[0])
        # transverse maxima between the first two bounces (eq. tn's n)
        if bt.size == 2:
            ty, _, _ = extrema(track.t, track.y, sy, +1)
            out["T_n"] = float(bt[1] - bt[0])
            out["n"] = int(np.sum((ty > bt[0]) & (ty < bt[1])))
    return out


def fit_tn(rows: list[dict]) -> dict | None:
    """Eq. (tn) over two-bounce launches: T_n = T n + delta by least squares (with the
    standard errors of T and delta), or None with fewer than two distinct n."""
    pts = [(r["n"], r["T_n"], r["file"]) for r in rows if r.get("T_n") is not None]
    if len({p[0] for p in pts}) < 2:
        return None
    n = np.array([p[0] for p in pts], dtype=float)
    T = np.array([p[1] for p in pts])
    A = np.column_stack([n, np.ones_like(n)])
    coef, *_ = np.linalg.lstsq(A, T, rcond=None)
    res = T - A @ coef
    out = {"T": float(coef[0]), "delta": float(coef[1]), "n": n.astype(int).tolist(), "T_n": T.tolist(),
           "files": [p[2] for p in pts], "residual_max": float(np.max(np.abs(res)))}
    if len(pts) > 2:
        s2 = float(res @ res) / (len(pts) - 2)
        cov = np.linalg.inv(A.T @ A) * s2
        out["T_error"], out["delta_error"] = float(math.sqrt(cov[0, 0])), float(math.sqrt(cov[1, 1]))
    return out


def screen_tracks(problem, tracks: list) -> list[dict]:
    """:func:`screen_track` of every track (refusals before any fit), with each one's
    ``sigma`` and ``kind`` (still, release or launch)."""
    out = []
    for tr in tracks:
        s = max(noise_sigma(tr.x), noise_sigma(tr.y))
        sc = screen_track(problem, tr, s)
        sc["kind"] = sc["kind"] or classify(tr, s)[0]
        out.append(sc)
    return out


def analyze(problem, tracks: list, screens: list | None = None, compare_losses: bool = True) -> dict:
    """All tracks: releases first (their fitted damping, averaged with inverse-variance
    weights, is then used for the launches' simulations), then launches, then eq. (tn)."""
    t0 = time.perf_counter()
    rows: dict[int, dict] = {}
    # releases need no launch damping; classify first so their damping can serve the launches
    # every track is screened before any fit: a refusal costs no fitting time
    screens = screen_tracks(problem, tracks) if screens is None else screens
    kinds = [sc["kind"] for sc in screens]
    for i, tr in enumerate(tracks):
        if kinds[i] in ("release", "still"):
            rows[i] = analyze_track(problem, tr, screen=screens[i])
    fitted = [(r["damping"], r["damping_error"]) for r in rows.values()
              if r.get("damping") is not None and np.isfinite(r["damping"])
              and r.get("damping_error") is not None and np.isfinite(r["damping_error"]) and r["damping_error"] > 0]
    mu_launch, mu_source = float(problem.damping), "spec"
    if fitted:
        w = np.array([1.0 / e ** 2 for _, e in fitted])
        mu_launch = float(np.sum(w * np.array([d for d, _ in fitted])) / np.sum(w))
        mu_source = "fitted"
    for i, tr in enumerate(tracks):
        if kinds[i] == "launch":
            rows[i] = analyze_track(problem, tr, mu_launch, screen=screens[i])
    ordered = [rows[i] for i in range(len(tracks))]
    losses = None
    if compare_losses:
        from .losses import compare_laws, segments_of

        losses = compare_laws(problem, segments_of(tracks, ordered), mu_launch)
        if losses and losses.get("chosen"):
            # each launch again through the simulator with the law the data support
            c = losses["laws"][losses["chosen"]]["coefficients"]
            if c["damping"] >= 0 and c["rolling_resistance"] >= 0:
                for r in ordered:
                    ent = r.get("_entry")
                    if r.get("kind") == "launch" and ent is not None:
                        sim = simulate_launch(problem, r["v_in"], ent[2], ent[4], c["damping"], ent[0],
                                              crr=c["rolling_resistance"])
                        sim["law"] = losses["chosen"]
                        sim["rolling_resistance"] = c["rolling_resistance"]
                        r["simulation_fitted_losses"] = sim
    return {"tracks": ordered, "tn_fit": fit_tn(ordered), "losses": losses, "launch_damping": mu_launch,
            "launch_damping_source": mu_source, "model": problem.model, "units": problem.units,
            "seconds": time.perf_counter() - t0}
