"""The lab stage (tracks -> events -> fits -> outcomes -> loss laws): the analysis of
tracked launches and releases, run here over the modules of each concern.

Pure functions on :class:`tracks.Track` and the spec's :class:`models.Problem`; no
printing, no files. Lengths in design units, times in s.

The stages, one module each (this one runs them):

    tracks.py       tracks in: CSV and trackpy files, units, the video's frame
    events.py       segmentation and events: noise, bounces, transverse extrema, the
                    states at a track's ends, release or launch, the screen before any fit
    track_fits.py   the fits of each track: a release whole, a launch's legs
    fitting.py      the model's lanes integrated on the compiled engine, the bounded
                    least squares and its budget (model runs)
    outcome.py      the outcome of each launch (escaped, captured, flew_off), v_in, v_out,
                    the launch through the simulator
    losses.py       which loss law the tracks support (viscous, rolling, both), by BIC
    summary.py      the summary a person reads, and the spec with the fitted losses

Eq. (tn): T_n = T n + delta over the two-bounce launches (:func:`fit_tn`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..errors import SpecError
from .events import (  # noqa: F401  (the stage's public names, re-exported)
    ACCEL_RATIO, EDGE_SECONDS, PEAK_HALF, PEAK_HALF_MAX, PROMINENCE_SIGMA, SG_WINDOW, STILL_FRACTION,
    STILL_SIGMA, VERTEX_DROP_SIGMA, WIDE_WINDOW, bounce_min_dip, classify, edge_state, extrema, logdec,
    noise_sigma, screen_track)
from .events import _savgol, _vertex_errors  # noqa: F401
from .fitting import Budget, FitStopped
from .outcome import model_to_start, outcome_of, simulate_launch, well_bottom  # noqa: F401
from .outcome import _launch_speeds, whole_usable
from .track_fits import LEG_START, fit_leg, fit_release, start_state  # noqa: F401


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
        out["notes"].append(f"fit stopped: {out['fit_status']}; what did not converge is not fitted (no "
                            "values, no error bars)")
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
                             f"{1.0 / fit['omega']:.4f} s time unit") \
            if fit["omega"] is not None and fit["omega"] > 0 else None
        if fit["fit_status"] == "converged":
            out.pop("fit_status")
        out["outcome"] = outcome_of(problem, track, bt)
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


def law_segments(tracks, rows) -> list:
    """The segments the loss laws are fitted to (:mod:`.losses`): each release whole;
    each launch whole (one state, through its bounces: :func:`.track_fits.fit_whole`)
    where that fit is usable (:func:`.outcome.whole_usable`),
    else its legs (before the first bounce, between bounces, after the last)."""
    from .losses import Segment, segments_of

    whole = {}
    for tr, r in zip(tracks, rows):
        w = r.get("whole_fit") if r.get("kind") == "launch" else None
        if whole_usable(w, tr):
            wx, wy = tr.weights()
            whole[tr.file] = Segment(tr.file, "launch", tr.t, tr.x, tr.y, np.asarray(w["state"], float), wx, wy)
    segs = [s for s in segments_of(tracks, rows) if s.file not in whole or s.what == "release"]
    segs += [s for s in between_segments(tracks, rows) if s.file not in whole]
    return segs + list(whole.values())


def _whole_damping(rows) -> float | None:
    """The launches' whole fits' damping (inverse-variance mean), None without any: the
    loss laws start from it, the damping their whole-launch states were fitted with (a
    launch of seconds through its bounces from another damping is far from its track)."""
    d = [(w["damping"], w["damping_error"]) for w in (r.get("whole_fit") for r in rows if r.get("kind") == "launch")
         if w and w.get("fit_status") == "converged" and w.get("damping") is not None
         and w.get("damping_error") and math.isfinite(w["damping_error"]) and w["damping_error"] > 0]
    if not d:
        return None
    wts = np.array([1.0 / e ** 2 for _, e in d])
    return float(np.sum(wts * np.array([v for v, _ in d])) / np.sum(wts))


def _compare_laws(problem, tracks, rows, mu_launch) -> dict | None:
    """The loss laws fitted to :func:`law_segments` (launches whole where they could be
    fitted whole); if a law's fit does not converge there, the laws again on the legs
    (:func:`.losses.segments_of` and :func:`between_segments`), that result kept if
    every law converged on it."""
    from .losses import compare_laws, segments_of

    segs = law_segments(tracks, rows)
    legs = segments_of(tracks, rows) + between_segments(tracks, rows)
    whole = len(segs) != len(legs) or any(s.what == "launch" for s in segs)
    mu0 = _whole_damping(rows) if whole else None
    res = compare_laws(problem, segs, mu_launch if mu0 is None else mu0)
    if not whole or res is None or not res.get("stopped"):
        return res
    alt = compare_laws(problem, legs, mu_launch)
    if alt is not None and not alt.get("stopped") and alt.get("chosen"):
        return alt
    return res


def between_segments(tracks, rows) -> list:
    """The loss-law fits' segments of the legs between a launch's bounces
    (:func:`.outcome.fit_between`, only those that converged), each from its fitted state
    at its first frame, its frames weighted as the whole track's (:meth:`Track.weights`).
    With the release and the entry and exit legs (:func:`.losses.segments_of`) they span
    the launch's whole range of speeds, which is what tells a loss ~ v (viscous) from a
    constant one (rolling)."""
    from .losses import Segment

    out = []
    for tr, r in zip(tracks, rows):
        if r.get("kind") != "launch":
            continue
        wx, wy = tr.weights()
        for leg in r.get("between_fits") or []:
            if leg.get("fit_status") != "converged" or leg.get("state") is None \
                    or not np.all(np.isfinite(leg["state"])):
                continue
            sl = np.flatnonzero((tr.t >= leg["t_first"]) & (tr.t <= leg["t_last"]))
            out.append(Segment(tr.file, "leg between bounces", tr.t[sl], tr.x[sl], tr.y[sl],
                               np.asarray(leg["state"], float), wx[sl], wy[sl]))
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
        mu_launch = float(fitted[0][0]) if len(fitted) == 1 else \
            float(np.sum(w * np.array([d for d, _ in fitted])) / np.sum(w))
        mu_source = "fitted"
    for i, tr in enumerate(tracks):
        if kinds[i] == "launch":
            rows[i] = analyze_track(problem, tr, mu_launch, screen=screens[i])
    ordered = [rows[i] for i in range(len(tracks))]
    losses = None
    if compare_losses:
        from .losses import compare_laws, segments_of

        losses = _compare_laws(problem, tracks, ordered, mu_launch)
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
