"""The lab stage's loss laws: which one the tracks support, viscous damping, rolling
resistance, or both.

Pure functions on tracks and the spec's :class:`models.Problem`; no printing, no files.

The laws (the spec's model, ``full``, ``simplified`` or ``ball``, with; the module docs of
models.py and ball.py):

* ``viscous``: - mu [xd, yd] (``simulation.damping`` = mu, 1/s);
* ``rolling``: a force c_rr N opposing v (``ball.rolling_resistance`` = c_rr);
* ``both``: the two together.

Each law is fitted by least squares (scipy's trust region reflective, every coefficient
bounded at zero; Jacobian by central differences between lanes of one integration on
the compiled engine, :mod:`fabkit.lab.fitting`) to every segment at once: each release
track whole, and each launch's legs before its first bounce and after its last (the
segments :func:`fabkit.lab.analyze.analyze` fitted), each segment with its own state
(x, y, xd, yd; the ball's adds its spin u) at its anchor frame and the law's coefficients shared by all;
each frame weighted by the tracker's sigma relative to its track's median (1 without
sigma columns). The laws
are compared by the Bayesian information criterion of Gaussian residuals of unknown
variance,

    BIC = N ln(RSS / N) + p ln N,

N the residuals (x and y of every frame used), p the fitted parameters (4 a segment +
the law's coefficients); the law with the least BIC is the one the data support, and
the difference to the next (Kass & Raftery: above 10 very strong, 6-10 strong, 2-6
positive, below 2 not worth more than a mention) says how strongly. AIC (N ln(RSS/N)
+ 2 p) is reported beside it. Errors: one standard deviation from the fit's covariance
(J^T J)^-1 RSS / (N - p).

Only a law whose fit converged (with finite error bars) is fitted: a law that ran out of
its budget (model runs, never seconds) or whose covariance is singular is reported with
its status and no coefficients, never ranked, never written by ``analyze -o``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

LAWS = {"viscous": ("damping",), "rolling": ("rolling_resistance",), "both": ("damping", "rolling_resistance")}
#: the information criterion that chooses the law
CRITERION = "BIC"
#: Kass & Raftery's scale for a BIC difference
EVIDENCE = ((10.0, "very strong"), (6.0, "strong"), (2.0, "positive"), (0.0, "not worth more than a mention"))
FIT_MAX_NFEV = 100
#: the evidence when every other law's fit did not converge (nothing to compare with)
ONLY_LAW = "the only law fitted"


@dataclass
class Segment:
    """Frames of one track the model follows without a break: ``idx`` frame indices in
    integration order (from the anchor), ``state`` (4,) the start at the anchor."""

    file: str
    what: str           # "release", "entry leg", "exit leg"
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    state: np.ndarray
    wx: np.ndarray | None = None     # the frames' weights (Track.weights), None: 1
    wy: np.ndarray | None = None

    def weights(self) -> np.ndarray:
        """The residuals' weights, x then y."""
        n = self.t.size
        return np.concatenate([np.ones(n) if self.wx is None else self.wx, np.ones(n) if self.wy is None else self.wy])

    @property
    def t0(self) -> float:
        return float(self.t[0])


@dataclass
class LawFit:
    """One law fitted to every segment: coefficients and their one-sigma errors."""

    law: str
    coefficients: dict
    errors: dict
    rss: float
    n: int
    p: int
    status: str
    rms: float
    segment_rms: list = field(default_factory=list)
    states: np.ndarray | None = None      # (segments, state size): the fitted starts

    @property
    def fitted(self) -> bool:
        """The fit converged with finite error bars: only such a law is ranked or written."""
        return self.status == "converged"

    @property
    def bic(self) -> float:
        return self.n * math.log(self.rss / self.n) + self.p * math.log(self.n)

    @property
    def aic(self) -> float:
        return self.n * math.log(self.rss / self.n) + 2.0 * self.p

    def to_json(self) -> dict:
        """The law's result; a law not fitted has no coefficients, errors or criteria (None)."""
        ok = self.fitted
        return {"coefficients": self.coefficients if ok else None, "errors": self.errors if ok else None,
                "rss": self.rss, "residuals": self.n, "parameters": self.p, "residual_rms": self.rms,
                "bic": self.bic if ok else None, "aic": self.aic if ok else None,
                "fit_status": self.status, "segment_rms": self.segment_rms}


def segments_of(tracks, rows) -> list[Segment]:
    """The segments of analyzed tracks (``rows`` from :func:`fabkit.lab.analyze.analyze`):
    releases whole from their fitted initial state, launches' legs from their fitted
    states (the exit leg backward from its last frame); only fits that converged."""
    out = []
    for tr, r in zip(tracks, rows):
        if r.get("kind") == "release" and r.get("initial_state"):
            s = r["initial_state"]
            st = np.array([s[k] for k in ("x", "y", "vx", "vy", "u") if k in s], dtype=float)
            if np.all(np.isfinite(st)):
                wx, wy = tr.weights()
                out.append(Segment(tr.file, "release", tr.t, tr.x, tr.y, st, wx, wy))
        elif r.get("kind") == "launch":
            bt = r.get("bounce_times") or []
            for key, what in (("entry_fit", "entry leg"), ("exit_fit", "exit leg")):
                leg = r.get(key)
                if not leg or leg.get("fit_status", "converged") != "converged" or leg["state"] is None \
                        or not np.all(np.isfinite(leg["state"])):
                    continue
                if what == "entry leg":
                    sel = tr.t <= (bt[0] if bt else tr.t[0] + 1.0)
                    sl = np.flatnonzero(sel)
                else:
                    sl = np.flatnonzero(tr.t >= bt[-1])[::-1]
                if sl.size < 8:
                    continue
                wx, wy = tr.weights()
                out.append(Segment(tr.file, what, tr.t[sl], tr.x[sl], tr.y[sl], np.asarray(leg["state"], float),
                                   wx[sl], wy[sl]))
    return out


def _law_vectors(law: str, q: np.ndarray, m: int):
    """(mu (m,), crr (m,)) of a law's coefficient vector ``q`` for m lanes; q (m, n_law)."""
    names = LAWS[law]
    mu = q[:, names.index("damping")] if "damping" in names else np.zeros(m)
    crr = q[:, names.index("rolling_resistance")] if "rolling_resistance" in names else np.zeros(m)
    return mu, crr


def fit_law(problem, segments: list[Segment], law: str, q0, budget=None, states=None) -> LawFit:
    """Least squares of every segment's state and the law's shared coefficients, each
    coefficient bounded at zero (module doc); ``states`` (segments, state size): the
    starts (default: each segment's own fitted state)."""
    from .fitting import (COEF_FLOOR, COEF_STEP, FIT_RTOL, STATE_STEP, central_jacobian, covariance_errors,
                          least_squares_bounded, model_solve, state_size)

    names = LAWS[law]
    nl = len(names)
    ns = state_size(problem)
    S = len(segments)
    W = [s.weights() for s in segments]
    data = np.concatenate([np.concatenate([s.x, s.y]) * w for s, w in zip(segments, W)])
    st0 = np.concatenate([s.state for s in segments]) if states is None else np.ravel(states)
    p0 = np.concatenate([st0, np.asarray(q0, dtype=float)])
    lower = np.concatenate([np.full(ns * S, -np.inf), np.zeros(nl)])

    def lanes(seg_i, P):
        """x, y of segment seg_i for each row of P (lanes, ns + nl): (lanes, 2 n)."""
        seg = segments[seg_i]
        mu, crr = _law_vectors(law, P[:, ns:], P.shape[0])
        Y = model_solve(problem, P[:, :ns].T, mu, seg.t0, seg.t, rtol=FIT_RTOL, crr=crr)
        return np.concatenate([Y[0], Y[1]], axis=1) * W[seg_i]

    def split(p):
        return p[:ns * S].reshape(S, ns), p[ns * S:]

    def fun(p):
        st, q = split(p)
        return np.concatenate([lanes(i, np.concatenate([st[i], q])[None, :])[0] for i in range(S)]) - data

    def jac(p):
        st, q = split(p)
        J = np.zeros((data.size, p.size))
        row = 0
        for i, seg in enumerate(segments):
            base = np.concatenate([st[i], q])
            h = STATE_STEP * np.maximum(1.0, np.abs(base))
            for j, nm in enumerate(names):
                h[ns + j] = COEF_STEP * max(abs(float(base[ns + j])), COEF_FLOOR[nm])
            D = central_jacobian(lambda P: lanes(i, P), base, h)     # (2 n, ns + nl)
            n2 = D.shape[0]
            J[row:row + n2, ns * i:ns * i + ns] = D[:, :ns]
            J[row:row + n2, ns * S:] = D[:, ns:]
            row += n2
        return J

    x, r, J, nfev, status = least_squares_bounded(fun, jac, p0, budget, lower=lower, xtol=1e-10,
                                                  max_nfev=FIT_MAX_NFEV)
    err = covariance_errors(J, r, p0.size)
    q = x[ns * S:]
    coef = {"damping": 0.0, "rolling_resistance": 0.0}
    errs = {"damping": 0.0, "rolling_resistance": 0.0}
    for j, nm in enumerate(names):
        coef[nm] = float(q[j])
        errs[nm] = float(err[ns * S + j])
    if status == "converged" and not all(math.isfinite(errs[nm]) for nm in names):
        status = "the fit's covariance is singular (no error bars)"
    seg_rms, row = [], 0
    for seg in segments:
        n2 = 2 * seg.t.size
        seg_rms.append({"file": seg.file, "segment": seg.what,
                        "rms": float(math.sqrt(float(r[row:row + n2] @ r[row:row + n2]) / n2))})
        row += n2
    rss = float(r @ r)
    return LawFit(law, coef, errs, rss, int(r.size), int(p0.size), status, math.sqrt(rss / r.size), seg_rms,
                  x[:ns * S].reshape(S, ns))


def compare_laws(problem, segments: list[Segment], mu0: float, budget_factory=None) -> dict | None:
    """Every law of :data:`LAWS` fitted to the segments and compared by BIC (module
    doc): {"criterion", "chosen", "evidence", "delta_bic", "laws": {law: LawFit.to_json()}};
    None without segments. ``mu0``: the viscous damping's start (the releases' fit or the
    spec's). The viscous law is fitted first; the rolling law starts from its fitted
    states with the c_rr that removes the same power at the segments' median speed
    (c_rr = mu v_median / g~), ``both`` from the viscous optimum and from the rolling
    one, keeping the lower cost (each start is deterministic: the same tracks, the same
    fits)."""
    from .fitting import Budget, FitStopped

    if not segments:
        return None
    v = np.concatenate([np.hypot(np.gradient(s.x, s.t), np.gradient(s.y, s.t)) for s in segments])
    vmean = float(np.median(v)) if v.size else 10.0
    mu0 = float(mu0) if math.isfinite(mu0) and mu0 > 1e-3 else 0.1
    vmean = vmean if math.isfinite(vmean) and vmean > 0 else 10.0
    gt = problem.g_tilde
    fits: dict[str, LawFit] = {}
    stopped = {}

    def fit(law, q0, states=None):
        budget = budget_factory() if budget_factory else Budget()
        try:
            return fit_law(problem, segments, law, q0, budget, states)
        except FitStopped as exc:
            stopped[law] = exc.reason
            return None

    # viscous first, from the segments' own fits; the other laws start from its fitted
    # states, with the rolling resistance that removes the same power at the median speed
    # (c_rr = mu v / g~), and `both` from the better of the two single laws' optima
    v = fit("viscous", [mu0])
    if v is not None:
        fits["viscous"] = v
    ok_v = v is not None and v.fitted
    mu_v = v.coefficients["damping"] if ok_v else mu0
    st_v = v.states if ok_v else None
    c0 = max(mu_v, 1e-3) * vmean / gt
    r = fit("rolling", [c0], st_v)
    if r is not None:
        fits["rolling"] = r
    ok_r = r is not None and r.fitted
    starts = [([mu_v, 1e-3 * c0], st_v)]
    if ok_r:
        starts.append(([1e-3 * max(mu_v, 1e-3), r.coefficients["rolling_resistance"]], r.states))
    if not ok_v and not ok_r:
        starts = [([0.5 * mu0, 0.5 * c0], None)]
    best = None
    for q0, st in starts:
        b = fit("both", q0, st)
        if b is not None and (best is None or (b.fitted, -b.rss) > (best.fitted, -best.rss)):
            best = b
    if best is not None:
        fits["both"] = best
        if best.fitted:
            stopped.pop("both", None)
            # a single law whose fit did not converge from its start (a launch fitted whole,
            # through its bounces, is far from its track from another law's states) again
            # from the `both` optimum: its states and the law's own coefficient
            for law, (nm,) in (("viscous", ("damping",)), ("rolling", ("rolling_resistance",))):
                if law not in fits or not fits[law].fitted:
                    again = fit(law, [max(best.coefficients[nm], 1e-6)], best.states)
                    if again is not None and (law not in fits or again.fitted):
                        fits[law] = again
                        if again.fitted:
                            stopped.pop(law, None)
    if not fits:
        return {"criterion": CRITERION, "chosen": None, "laws": {}, "stopped": stopped,
                "segments": [f"{s.file}: {s.what}" for s in segments]}
    for law, f in fits.items():
        if not f.fitted:
            stopped.setdefault(law, f.status)
    order = sorted((k for k in fits if fits[k].fitted), key=lambda k: fits[k].bic)
    if not order:
        return {"criterion": CRITERION, "chosen": None, "evidence": None, "delta_bic": {},
                "laws": {k: fits[k].to_json() for k in fits}, "stopped": stopped,
                "segments": [f"{s.file}: {s.what}" for s in segments]}
    best = order[0]
    delta = {k: fits[k].bic - fits[best].bic for k in order}
    if len(order) > 1:
        gap = delta[order[1]]
        strength = next(name for lim, name in EVIDENCE if gap >= lim)
    else:
        strength = ONLY_LAW
    return {"criterion": CRITERION, "chosen": best, "evidence": strength, "delta_bic": delta,
            "laws": {k: fits[k].to_json() for k in fits}, "stopped": stopped,
            "segments": [f"{s.file}: {s.what}" for s in segments]}
