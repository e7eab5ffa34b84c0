"""The lab stage's outcome of each launch: where its entry and exit legs' fitted states
carry along the model to x = start (``v_in``, ``v_out``), and what the track shows it
did (escaped, captured or flew_off); and the same launch through the simulator.

Pure functions on a track, its events (:mod:`.events`) and its legs' fits
(:mod:`.track_fits`); no printing, no files.

The outcome is the track's, never a fit's: a launch with a point beyond top - margin or
outside the footprint shrunk by the margin ``flew_off``; one whose track ends, after a
bounce, left of the well moving toward -x, with the model carrying the track's own last
state (a quadratic over its last 0.16 s) back through x = start, ``escaped``; else
``captured``. Whether a fit converged changes no outcome.

``v_in``: the entry leg's fitted state carried along the model to x = start, |xd| there
(and y, yd there start the side-by-side simulation). ``v_out``: likewise the exit leg's,
for an escaped launch. Errors: one sigma of the fitted xd (the carry is exact to the
model). A leg whose fit did not converge is not fitted: its speed is None. The carries
integrate the model (scipy DOP853, rtol 1e-10, an event at x = start), bounded by
MAX_CARRY_CALLS evaluations.
"""

from __future__ import annotations

import math

import numpy as np

from ..physics.outcomes import Outcome
from .events import edge_state
from .fitting import Budget, FitStopped, centre_of
from .track_fits import fit_leg, fit_whole, start_state


#: evaluations of the model carrying one state to x = start (a bound on the work, not on time)
MAX_CARRY_CALLS = 200_000


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
        if calls[0] > MAX_CARRY_CALLS:
            raise FitStopped(f"carrying the state to x = start took more than {MAX_CARRY_CALLS} evaluations")
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


def outcome_of(problem, track, bounces_t, mu: float | None = None):
    """What the track shows, whatever any fit did: flew_off (a point beyond top - margin
    or outside the footprint shrunk by the margin); escaped (after a bounce the track
    ends left of the well moving toward -x, and the model with damping ``mu`` carries the
    track's own last state (:func:`.events.edge_state`, no fit) back through x =
    start); else captured (still on the surface when the track ends)."""
    m = problem.margin
    with np.errstate(all="ignore"):
        z = problem.fns.h(track.x, track.y)
    if np.any(z > problem.top - m) or np.any(track.x < problem.x_range[0] + m) or \
            np.any(track.x > problem.x_range[1] - m) or np.any(track.y < problem.y_range[0] + m) or \
            np.any(track.y > problem.y_range[1] - m):
        return Outcome.FLEW_OFF.value
    if mu is None or not len(bounces_t) or not track.x[-1] < well_bottom(problem):
        return Outcome.CAPTURED.value
    st = edge_state(track, end=True)
    if not st[3] < 0:
        return Outcome.CAPTURED.value
    if track.x[-1] <= problem.start:
        return Outcome.ESCAPED.value
    try:
        s0 = start_state(problem, st)
    except FitStopped:
        return Outcome.CAPTURED.value
    return Outcome.ESCAPED.value if model_to_start(problem, st[0], s0, mu) is not None else Outcome.CAPTURED.value


def _leg_json(leg) -> dict:
    """A leg's fit for the result: its values only where it converged (not fitted: null)."""
    if not _fitted(leg):
        return {"t": leg["t"], "state": None, "error": None, "damping": None, "damping_error": None,
                "rms": leg["rms"], "fit_status": leg["status"] if leg["status"] != "converged"
                else "the fit's covariance is singular (no error bars)"}
    return {"t": leg["t"], "state": leg["state"].tolist(), "error": leg["error"].tolist(),
            "damping": leg["damping"], "damping_error": leg["damping_error"], "rms": leg["rms"],
            "fit_status": leg["status"]}


def _fitted(leg) -> bool:
    """A leg's fit converged with finite error bars."""
    return leg is not None and leg["status"] == "converged" and bool(np.all(np.isfinite(leg["error"]))) \
        and math.isfinite(leg["damping_error"])


def _singular(leg, what: str, budget) -> None:
    """A leg whose fit converged without error bars is not fitted either: said in the
    track's ``fit_status``."""
    if budget is not None and leg["status"] == "converged" and not _fitted(leg):
        budget.stopped.append(f"{what}: the fit's covariance is singular (no error bars)")


def _launch_speeds(problem, track, bt, mu, budget: Budget | None = None) -> dict:
    """v_in, v_out and the outcome of a launch (module doc). The outcome is the track's
    (:func:`outcome_of`); v_in and v_out are the fitted legs' crossings of x = start, None
    where a leg's fit did not converge (not fitted)."""
    t = track.t
    t_in_end = (bt[0] if bt.size else t[0] + 1.0)
    sel = np.flatnonzero(t <= t_in_end)
    leg = fit_leg(problem, track, sel, False, mu, budget)
    out = {"entry_fit": _leg_json(leg)}
    _singular(leg, "entry leg", budget)
    entry = None
    if _fitted(leg):
        entry = model_to_start(problem, leg["t"], leg["state"], leg["damping"], budget=budget)
    v_in = abs(entry[3]) if entry is not None else None
    # v_in's error: the fitted vx's error (the carry to x = start is exact to the model)
    out["v_in"], out["v_in_error"] = v_in, (float(leg["error"][2]) if v_in is not None else None)
    out["_entry"] = entry
    out["t_entry"] = entry[0] if entry is not None else None
    outcome = outcome_of(problem, track, bt, mu)
    leg2 = None
    if bt.size and t[-1] - bt[-1] > 0.1:
        sel = np.flatnonzero(t >= bt[-1])
        try:
            leg2 = fit_leg(problem, track, sel, True, mu, budget)
        except FitStopped as exc:      # not even the exit leg's first point: no v_out
            if budget is not None:
                budget.stopped.append(f"exit leg: {exc.reason}")
    v_out = None
    if leg2 is not None:
        out["exit_fit"] = _leg_json(leg2)
        _singular(leg2, "exit leg", budget)
        if outcome == Outcome.ESCAPED and _fitted(leg2) and leg2["state"][2] < 0:
            ex = model_to_start(problem, leg2["t"], leg2["state"], leg2["damping"], budget=budget)
            if ex is not None:
                v_out = abs(ex[3])
                out["v_out_error"] = float(leg2["error"][2])
    out["outcome"], out["v_out"] = outcome, v_out
    out["whole_fit"] = None
    if bt.size and _fitted(leg):
        span = float(t_in_end - t[0])
        try:
            whole = fit_whole(problem, track, {**leg, "span": span}, Budget())
            out["whole_fit"] = _leg_json(whole)
        except FitStopped as exc:
            out["whole_fit"] = {"t": float(t[0]), "state": None, "error": None, "damping": None,
                                "damping_error": None, "rms": None, "fit_status": exc.reason}
    # the legs between bounces only where the whole launch is not fitted (the loss laws
    # then use the legs, :func:`.analyze.law_segments`)
    out["between_fits"] = [] if whole_usable(out["whole_fit"], track) else fit_between(problem, track, bt, mu)
    return out


#: a launch's whole fit stands for its legs in the loss-law fits when its residual rms is
#: within this factor of the track's noise sigma (else: a wrong minimum; the legs)
WHOLE_RMS_FACTOR = 2.0


def whole_usable(whole: dict | None, track) -> bool:
    """A launch's whole fit converged, with finite values, its rms within WHOLE_RMS_FACTOR
    of the track's noise sigma (:func:`.events.noise_sigma`)."""
    from .events import noise_sigma

    if not whole or whole.get("fit_status") != "converged" or whole.get("state") is None \
            or not np.all(np.isfinite(whole["state"])):
        return False
    return whole["rms"] <= WHOLE_RMS_FACTOR * max(noise_sigma(track.x), noise_sigma(track.y))


#: a leg between two bounces is fitted when it has at least this many frames
BETWEEN_MIN_FRAMES = 16


def fit_between(problem, track, bt, mu) -> list[dict]:
    """The legs between successive bounces, each fitted like the entry leg (its state at
    its first frame after the bounce and the viscous damping, :func:`.track_fits.fit_leg`)
    on a budget of its own: these legs only add the speeds of the middle of a launch to
    the loss-law fits (:mod:`.losses`), so one that does not converge is left out of them
    (its ``fit_status`` says why) and changes nothing else of the track. Each leg:
    {"t_first", "t_last", "frames", and the leg's fit as the entry leg's}."""
    from dataclasses import replace

    out = []
    t = track.t
    for a, b in zip(bt[:-1], bt[1:]):
        sel = np.flatnonzero((t >= a) & (t <= b))
        if sel.size < BETWEEN_MIN_FRAMES:
            continue
        sub = replace(track, t=t[sel], x=track.x[sel], y=track.y[sel],
                      sigma_x=None if track.sigma_x is None else track.sigma_x[sel],
                      sigma_y=None if track.sigma_y is None else track.sigma_y[sel], notes=[])
        try:
            leg = fit_leg(problem, sub, np.arange(sel.size), False, mu, Budget())
        except FitStopped as exc:
            out.append({"t_first": float(t[sel[0]]), "t_last": float(t[sel[-1]]), "frames": int(sel.size),
                        "t": float(t[sel[0]]), "state": None, "error": None, "damping": None,
                        "damping_error": None, "rms": None, "fit_status": exc.reason})
            continue
        out.append({"t_first": float(t[sel[0]]), "t_last": float(t[sel[-1]]), "frames": int(sel.size),
                    **_leg_json(leg)})
    return out


def simulate_launch(problem, v_in: float, y0: float, vy0: float, mu: float, t_shift: float,
                    crr: float | None = None) -> dict:
    """The same launch through fabkit's simulator (integrate.launch_batch), times shifted
    to the track's clock (``t_shift`` = the track's time at x = start); ``crr``: the
    rolling resistance (None: the spec's)."""
    from ..physics.integrate import launch_batch

    p = problem.with_(damping=float(mu))
    if crr is not None:
        p = p.with_(rolling_resistance=float(crr))
    r = launch_batch(p, [float(v_in)], [float(y0)], [float(vy0)], record=True, workers=1)
    nb = int(r.bounces[0])
    bt = [float(b) + t_shift for b in r.bounce_times[0][: min(nb, r.bounce_times.shape[1])]]
    tr = r.trajectories[0] if r.trajectories else None
    out = {"outcome": Outcome.of(r.outcome[0]).value, "bounces": nb, "bounce_times": bt,
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


