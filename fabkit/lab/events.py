"""The lab stage's segmentation and events: what a track shows before any model fit.

Pure functions on :class:`tracks.Track` arrays; no printing, no files, no model
integration. Lengths in design units, times in s. In: a track (t, x, y); out: its
noise sigma, its bounces (maxima of x with their times and errors), the transverse
extrema, the states at its ends (local quadratic fits), whether it is a release or a
launch, and the screen that refuses a track of another unit before any fit.

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
on a 9-frame window (``bounce_time_errors``: from a cubic's covariance over the same
window, which covers the parabola's bias on an asymmetric turn; :func:`_vertex_errors`).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import SpecError

SG_WINDOW = 9          # frames of the local cubic fits (noise and smoothing)
PROMINENCE_SIGMA = 8.0
EDGE_SECONDS = 0.16    # window of the entry / exit fits
PEAK_HALF = 4          # frames either side of a bounce in its parabola fit
PEAK_HALF_MAX = 16     # ... widened up to this for a flat, slow turn
VERTEX_DROP_SIGMA = 6.0
WIDE_WINDOW = 25       # frames of the second, wider smoothing (shallow turns)
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
    """One-sigma errors (s) of the bounce times: sigma_d1 / (2 |d2|), d1 and d2 the slope
    and half-curvature of a least-squares CUBIC through the window the vertex was fitted
    on, centred on the vertex (the slope vanishes there). The parabola's own statistical
    error is about half of this, but an asymmetric turn (a third derivative of x) biases
    a parabola's vertex by as much: on 118 bounces of independent launches (0.3 mm noise,
    125 frames/s) the parabola's sigma was exceeded 3-fold by 14 % of them, this one by
    0.8 % (median |error| / sigma 0.53)."""
    out = []
    for tb in times:
        i = int(np.clip(np.searchsorted(t, tb), 0, len(t) - 1))
        h = _fit_half(t, z, i, sigma, PEAK_HALF_MAX)
        a, b = max(0, i - h), min(len(t), i + h + 1)
        dt = t[a:b] - tb
        d2 = np.polyfit(dt, z[a:b], 3)[1]
        A = np.column_stack([dt ** 3, dt * dt, dt, np.ones_like(dt)])
        cov = np.linalg.inv(A.T @ A) * sigma * sigma
        out.append(math.sqrt(cov[2, 2]) / (2 * abs(d2)) if d2 != 0 else math.nan)
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


# ----------------------------------------------------------------------------
# the paper's log-decrement of a release
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


# ----------------------------------------------------------------------------
# the screen before any fit, and the kind of a track
# ----------------------------------------------------------------------------
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
