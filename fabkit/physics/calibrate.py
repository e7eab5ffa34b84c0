"""Ramp calibration: release height <-> entry speed, with the ramp's own losses.

H, the release height, is the drop of the ball's centre: from the ball at rest on the
ramp to the ball resting on the block with its contact at the launch point
(x = simulation.start on the launch line y = simulation.y0). It is the one definition
used by the calibration table, the ramp's marks and the check.

Without losses (energy balance, rolling without slipping; the centre's speed is
omega r on any profile, so the kinetic energy is 1/2 m V^2 (1 + k) exactly):

    m g H = 1/2 m V^2 (1 + k),     k = I / (m r^2)

so ``v_in = sqrt(2 g H / (1 + k))`` and ``H = (1 + k) v_in^2 / (2 g)`` on fabkit's
ramp, whatever its shape. For a solid sphere k = 2/5 (the paper's 7/5 factor), hollow
k = 2/3, or a number from ``ball.inertia``; ``g`` is standard gravity in design
units/s^2 (:func:`fabkit.units.gravity`).

With losses (``simulation.damping`` mu, 1/s; ``ball.rolling_resistance`` c) the ball is
integrated down the ramp's running line (the profile ``fabkit ramp`` builds, or the
user's straight incline, ``ramp.profile``). With s the distance its centre travels,
phi the slope angle of the line at the contact and kappa the line's curvature
(> 0 concave), the centre runs on the parallel curve at distance r, whose slope is phi
and whose curvature is kappa_c = kappa / (1 - r kappa), and

    (1 + k) s'' = g sin(phi) - (1 + k) mu s' - c N / m,    N / m = g cos(phi) + kappa_c s'^2

(the same laws as the block's ball model: the viscous force (1 + k) m mu v on the
centre, which decays a free roll as exp(-mu t), and the rolling resistance c N against
the motion). The paper's localized damping acts on the transverse motion only, which the
launch line has none of: it does not act on the ramp. The line is the ramp's section
along y = y0 (its cross slope is neglected: on the paper's spec it is below 3e-5).
The integration is in the kinetic energy E = s'^2 / 2 along the path (all heights at
once, DOP853, rtol 1e-11), so the ramp's length bounds it; a ball whose speed falls to
zero stops on the ramp and does not reach the block. A straight ramp ends in a kink
that costs a factor (k + cos kink) / (1 + k) in speed (``physics/ramp_profile.py``,
:class:`StraightRamp`); fabkit's ramp is curvature-continuous and has none.

:func:`entry_speed` and :func:`release_height` are the two public directions; every
command calls them. ``v_in_from_height`` and ``height_from_v_in`` are the lossless
closed forms.

>>> round(float(v_in_from_height(4.5, 980.665, 0.4)), 3)     # cm, cm/s
79.28
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import DesignError, SpecError
from ..units import gravity
from .ramp_profile import ramp_heights, ramp_profile

#: relative tolerance of the descent's integration (DOP853); the entry speeds it gives
#: agree with an independent integration to ~1e-10 relative (tests/test_calibrate.py)
RAMP_RTOL = 1e-11
#: right-hand-side evaluations allowed to each piece of one descent (all heights together),
#: to each of the explicit and the stiff integrator
RAMP_EVAL_BUDGET = 20_000
#: secant steps allowed to the inverse (release_height)
INVERSE_ITERATIONS = 60


def v_in_from_height(H, g: float, k: float):
    """Entry speed (design units/s) for release height(s) ``H`` (design units, >= 0).

    H: scalar or array; g: gravity in design units/s^2; k = I/(m r^2).
    Returns an array of H's shape (a float for a scalar H).
    """
    H = np.asarray(H, dtype=float)
    # sqrt(2 g / (1 + k)) sqrt(H): no overflow for any finite H
    return np.sqrt(2.0 * g / (1.0 + k)) * np.sqrt(H)


def height_from_v_in(v, g: float, k: float):
    """Release height (design units) that gives entry speed(s) ``v`` (design units/s)."""
    v = np.asarray(v, dtype=float)
    with np.errstate(over="ignore"):
        return (1.0 + k) / (2.0 * g) * v * v


def ball_k(spec) -> float:
    """k = I/(m r^2) of the spec's ball (0.4 solid, 2/3 hollow, or the number given)."""
    return float(spec.ball.inertia) if spec.has("ball") else 0.4


def ramp_losses(spec) -> tuple[float, float]:
    """(mu, c): the viscous coefficient (1/s, ``simulation.damping``) and the rolling
    resistance coefficient (``ball.rolling_resistance``) the ball meets on the ramp."""
    mu = float(spec.simulation.damping) if spec.has("simulation") else 0.0
    c = float(getattr(spec.ball, "rolling_resistance", 0.0) or 0.0) if spec.has("ball") else 0.0
    return mu, c


@dataclass(frozen=True)
class Entry:
    """Entry speeds for release heights on the spec's ramp (design units, /s).

    ``v_in`` is nan where the ball does not reach the launch point (``reached`` False;
    ``why`` says why). ``closed_form``: lossless fabkit ramp, v_in exact. ``error``: the
    relative accuracy of v_in."""

    heights: np.ndarray
    v_in: np.ndarray
    reached: np.ndarray
    g: float
    k: float
    mu: float
    c: float
    profile: str
    closed_form: bool
    error: float
    top: float
    why: str | None = None
    method: str = field(default="")

    @property
    def lossless(self) -> np.ndarray:
        """The closed form's entry speeds at the same heights."""
        return v_in_from_height(np.maximum(self.heights, 0.0), self.g, self.k)


def entry(spec, heights) -> Entry:
    """Entry speeds (design units/s) of a ball released at rest at ``heights`` (design units,
    the drop of its centre, see the module doc) on the spec's ramp, with the ramp's losses.

    Raises :class:`SpecError` for a negative or non-finite height and :class:`DesignError`
    if the descent cannot be integrated within its budget."""
    spec.require("ball", "ramp")
    H = np.atleast_1d(np.asarray(heights, dtype=float))
    if not np.all(np.isfinite(H)) or np.any(H < 0):
        raise SpecError("release heights must be finite and >= 0", file=spec.path, key="ramp.heights")
    g, k = gravity(spec.units), ball_k(spec)
    mu, c = ramp_losses(spec)
    straight = getattr(spec.ramp, "profile", "fabkit") == "straight"
    if not straight and mu == 0 and c == 0:
        v = v_in_from_height(H, g, k)
        return Entry(H, v, np.ones(H.shape, bool), g, k, mu, c, "fabkit", True, 1e-16, math.inf,
                     method="closed form sqrt(2 g H / (1 + k))")
    if not straight and not (spec.has("surface") and spec.has("simulation")):
        spec.require("surface", "simulation")
    prof = ramp_profile(spec)
    res = float(prof.resolution)
    if np.any((H > 0) & (H < res)):
        raise SpecError(f"a release height of {float(np.min(H[H > 0])):.3g} {spec.units} is below what the ramp's "
                        f"line resolves ({res:.3g} {spec.units}: the centre's drop is a difference of heights)",
                        file=spec.path, key="ramp.heights")
    return _descend(prof, H, g, k, mu, c, straight, spec)


def height_resolution(spec) -> float:
    """The smallest release height (design units) :func:`entry` accepts on the spec's ramp
    (0 when the closed form applies)."""
    mu, c = ramp_losses(spec)
    if getattr(spec.ramp, "profile", "fabkit") != "straight" and mu == 0 and c == 0:
        return 0.0
    return float(ramp_profile(spec).resolution)


def entry_speed(spec, heights) -> np.ndarray:
    """v_in (design units/s) for release heights ``heights`` (design units, the centre's
    drop) on the spec's ramp with its losses; nan where the ball does not reach the block.
    Shape of ``heights`` (a 0-d array for a scalar)."""
    return entry(spec, heights).v_in.reshape(np.shape(heights))


def release_height(spec, v_in) -> np.ndarray:
    """The inverse of :func:`entry_speed`: release heights (design units) that give the
    entry speeds ``v_in`` (design units/s) on the spec's ramp, to 1e-10 relative; nan for a
    speed beyond the ramp's top. Shape of ``v_in``."""
    v = np.atleast_1d(np.asarray(v_in, dtype=float))
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise SpecError("entry speeds must be finite and >= 0", file=spec.path, key="v_in")
    g, k = gravity(spec.units), ball_k(spec)
    first = entry(spec, np.zeros(1))
    if first.closed_form:
        return height_from_v_in(v, g, k).reshape(np.shape(v_in))
    top = entry(spec, np.array([first.top]))
    vtop = float(top.v_in[0]) if top.reached[0] else 0.0
    out = np.full(v.shape, np.nan)
    todo = (v <= vtop) & (v > 0)
    out[v == 0] = 0.0
    if not todo.any():
        return out.reshape(np.shape(v_in))
    # secant on f(H) = v(H)^2 - v^2 (v^2 is nearly linear in H: 2 g H / (1 + k) less the
    # work of the losses), bracketed in [0, top]
    vt = v[todo]
    lo, hi = np.zeros(vt.shape), np.full(vt.shape, first.top)
    flo, fhi = -vt ** 2, np.full(vt.shape, vtop ** 2) - vt ** 2
    Hc = np.clip(height_from_v_in(vt, g, k), 0.0, first.top)
    Hp = fp = None
    for _ in range(INVERSE_ITERATIONS):
        e = entry(spec, Hc)
        f = np.where(e.reached, np.nan_to_num(e.v_in) ** 2, 0.0) - vt ** 2
        below = f < 0
        lo, flo = np.where(below, Hc, lo), np.where(below, f, flo)
        hi, fhi = np.where(below, hi, Hc), np.where(below, fhi, f)
        done = np.abs(f) <= 1e-13 * vt ** 2
        if np.all(done | (hi - lo <= 1e-14 * first.top)):
            break
        # secant through the last two iterates (the first step: v^2 is nearly 2 g H / (1 + k),
        # less the losses' work), kept inside the bracket
        with np.errstate(all="ignore"):
            slope = (2.0 * g / (1.0 + k)) if Hp is None else (f - fp) / (Hc - Hp)
            Hn = Hc - f / slope
        Hn = np.where((Hn > lo) & (Hn < hi) & np.isfinite(Hn), Hn, 0.5 * (lo + hi))
        Hp, fp = Hc, f
        Hc = np.where(done, Hc, Hn)
    else:
        raise DesignError(f"the ramp's release heights did not converge in {INVERSE_ITERATIONS} steps "
                          f"(speeds {', '.join(f'{x:g}' for x in vt)})")
    out[todo] = Hc
    return out.reshape(np.shape(v_in))


def _descend(prof, H, g, k, mu, c, straight, spec) -> Entry:
    """Integrate the descent from every release point at once (see the module doc)."""
    from scipy.integrate import solve_ivp

    r = float(prof.radius)
    gt = g / (1.0 + k)
    cp = c / (1.0 + k)
    top = float(prof.top)
    name = "straight" if straight else "fabkit"
    ur = prof.u_release(H)
    reached = np.isfinite(ur)
    why = None if reached.all() else (f"release heights above the ramp's top ({top:.6g}) are not on the ramp")
    v = np.full(H.shape, np.nan)
    u0 = float(prof.u_stop)
    live = reached & (ur > u0)
    v[reached & ~live] = 0.0
    kink = (k + math.cos(prof.kink_angle)) / (1.0 + k)
    method = (f"descent integrated along the {name} ramp's line (DOP853, rtol {RAMP_RTOL:g}), "
              f"damping {mu:g} 1/s, rolling resistance {c:g}" + (f", kink factor {kink:.6f}" if straight else ""))

    t_max = float(spec.simulation.t_max) if spec.has("simulation") else 60.0

    def geo(u):
        zp = prof.slope(u)
        zpp = prof.curvature(u)
        w = np.sqrt(1.0 + zp * zp)
        kap = zpp / w ** 3
        return zp / w, 1.0 / w, kap, w

    if live.any():
        # a quick bound before integrating: from rest the speed never exceeds g~ max sin(phi) / mu,
        # so a ball whose centre's path is longer than that speed times simulation.t_max does not
        # reach the block within it
        ug = np.linspace(u0, float(np.nanmax(ur[live])), 4001)
        sn, cs, kap, w = geo(ug)
        if np.any(1.0 - r * kap <= 0):
            raise SpecError(f"the ramp's line is tighter than the ball (radius {r:g}): it would touch at two "
                            "points (a steeper ramp has a tighter transition)", file=spec.path, key="ramp.angle")
        A = (1.0 - r * kap) * w
        path = np.concatenate([[0.0], np.cumsum(0.5 * (A[1:] + A[:-1]) * np.diff(ug))])
        vmax = gt * float(np.max(np.abs(sn))) / mu if mu > 0 else math.inf
        t_lb = np.zeros(H.shape)
        if mu > 0:
            t_lb[live] = np.maximum(np.interp(ur[live], ug, path) / vmax,
                                    _crawl_bound(ug, sn, path, ur[live], H[live], gt, mu))
        slow = t_lb > t_max
        if slow.any():
            why = ((why + "; ") if why else "") + (
                f"the ball does not reach the block within simulation.t_max = {t_max:g} s from release heights "
                f"{_ranges(H[slow])}: with simulation.damping = {mu:g} 1/s it rolls at most {vmax:.3g} "
                f"{spec.units}/s on the ramp and takes at least {float(np.min(t_lb[slow])):.3g} s to come down")
            reached &= ~slow
            live &= ~slow
        if not live.any():
            return Entry(H, v, reached, g, k, mu, c, name, False, 0.0, top, why, method)
        idx = np.flatnonzero(live)
        # the line's curvature has a kink at each of prof.breaks (the lift's third derivative
        # jumps at the end of its transition): the descent is integrated piecewise between them,
        # every lane crossing a break at the end of a piece, so each piece is smooth
        cuts = sorted({u0, *[float(b) for b in getattr(prof, "breaks", ()) if b > u0]}, reverse=True)
        uri = ur[idx]
        n = len(idx)
        E, T = np.zeros(n), np.zeros(n)
        stopped = np.zeros(n, bool)
        lifted = np.zeros(n, bool)
        stiff = [False]
        for j, lo_u in enumerate(cuts):
            hi_u = cuts[j - 1] if j > 0 else math.inf
            on = uri > lo_u
            if not on.any():
                continue
            a = np.minimum(uri[on], hi_u)
            span = a - lo_u
            sol = _piece(geo, a, span, E[on], T[on], g, gt, mu, cp, r, t_max, H[idx][on], stiff, spec, c)
            # the normal force and the speed along the way (sampled): a ball whose speed falls to
            # zero stops on the ramp; one whose normal force falls to zero leaves it
            sig = np.linspace(0.0, 1.0, 201)
            Es = np.atleast_2d(sol.sol(sig))[: int(on.sum())]          # (lanes, 201)
            u = a[:, None] - span[:, None] * sig[None, :] ** 2
            sn, cs, kap, w = geo(u)
            N = g * cs + 2.0 * np.maximum(Es, 0.0) * kap / (1.0 - r * kap)
            stopped[on] |= np.any(Es[:, 1:] <= 0, axis=1)
            lifted[on] |= np.any(N < 0, axis=1)
            m = int(on.sum())
            E[on], T[on] = sol.y[:m, -1], sol.y[m:, -1]
        stopped |= E <= 0
        late = ~stopped & ~lifted & (T > t_max)
        ok = ~stopped & ~lifted & ~late
        v[idx] = np.where(ok, np.sqrt(2.0 * np.maximum(E, 0.0)) * kink, np.nan)
        reached[idx] = ok
        notes = [why] if why else []
        if stopped.any():
            notes.append(f"the ball stops on the ramp (simulation.damping {mu:g} 1/s, ball.rolling_resistance "
                         f"{c:g}) from release heights {_ranges(H[idx][stopped])}")
        if lifted.any():
            notes.append(f"the ball leaves the ramp's surface (its normal force falls to zero) from release "
                         f"heights {_ranges(H[idx][lifted])}")
        if late.any():
            notes.append(f"the ball takes longer than simulation.t_max = {t_max:g} s to roll down the ramp "
                         f"(simulation.damping {mu:g} 1/s, ball.rolling_resistance {c:g}) from release heights "
                         f"{_ranges(H[idx][late])}")
        why = "; ".join(notes) or None
        if stiff[0]:
            method = method.replace("DOP853", "LSODA: stiff")
    return Entry(H, v, reached, g, k, mu, c, name, False, 1e-9, top, why, method)


class _Budget(Exception):
    pass


def _crawl_bound(ug, sn, path, ur, H, gt, mu) -> np.ndarray:
    """A lower bound on each lane's time down the ramp (s), rigorous for viscous damping mu
    (rolling resistance only slows the ball more). Over the last stretch of the line,
    u in [u0, u1] (centre path l1, largest slope sine s1 there), dV/dt <= g~ s1 - mu V, so
    V(t) <= V1 exp(-mu t) + g~ s1 / mu and the stretch takes at least (l1 - V1 / mu) mu / (g~ s1),
    V1 the speed on arriving at u1: at most the lossless sqrt(2 g~ H) and at most g~ s / mu with
    s the largest slope sine above u1 (the speed from rest never exceeds it). The best u1 per lane.
    ``ug`` ascending from the launch point, ``sn``, ``path`` on it; ``ur``, ``H`` per lane."""
    s_below = np.maximum(np.maximum.accumulate(sn), 1e-300)            # max over [u0, u1]
    on = ug[None, :] <= ur[:, None]                                     # (lanes, nodes) below the release
    s_above = np.maximum.accumulate(np.where(on, sn[None, :], -np.inf)[:, ::-1], axis=1)[:, ::-1]
    v1 = np.minimum(np.sqrt(2.0 * gt * np.maximum(H, 0.0))[:, None], gt * np.maximum(s_above, 0.0) / mu)
    t = (path[None, :] - v1 / mu) * mu / (gt * s_below[None, :])
    return np.maximum(np.max(np.where(on, t, 0.0), axis=1), 0.0)


def _piece(geo, a, span, E0, T0, g, gt, mu, cp, r, t_max, H, stiff, spec, c):
    """One smooth piece of the descent for the lanes released at or passing through ``a``
    (design units) down to ``a - span``: state (E, t) per lane, E the kinetic energy per
    unit (1 + k) m, t the time (s), against sigma in [0, 1] with u = a - span sigma^2
    (where a lane starts from rest E grows like the distance, sqrt(E) like sigma: smooth in
    sigma; dt/dsigma stays finite). A lane past t_max is frozen (it does not reach in time).
    DOP853 within a budget of evaluations; a problem too stiff for it (large damping) goes
    to LSODA, whose Jacobian is banded (the state interleaved per lane)."""
    from scipy.integrate import solve_ivp

    m = len(a)
    count = [0]
    budget = [RAMP_EVAL_BUDGET]

    def rhs(sig, y):
        count[0] += 1
        if count[0] > budget[0]:
            raise _Budget
        E, t = y[:m], y[m:]
        u = a - span * sig * sig
        sn, cs, kap, w = geo(u)
        Ep = np.maximum(E, 0.0)
        N = g * cs + 2.0 * Ep * kap / (1.0 - r * kap)
        f = gt * sn - mu * np.sqrt(2.0 * Ep) - cp * np.maximum(N, 0.0)
        dSu = span * (1.0 - r * kap) * w                 # centre path per unit sigma, over 2 sigma
        dE = 2.0 * sig * dSu * f
        with np.errstate(divide="ignore", invalid="ignore"):
            # dt/dsigma = dS/dsigma / V; from rest (E = 0, sigma = 0) its limit sqrt(2 dSu / f)
            dt = np.where(Ep > 0, 2.0 * sig * dSu / np.sqrt(2.0 * Ep), np.sqrt(2.0 * dSu / np.maximum(f, 1e-300)))
        dead = ((E <= 0) & (f <= 0)) | (t > t_max)
        return np.concatenate([np.where(dead, 0.0, dE), np.where(dead, 0.0, dt)])

    y0 = np.concatenate([E0, T0])
    # E's absolute tolerance per lane from its own scale g~ H (a tiny height keeps its digits)
    # (floored at 1e-150: the error norm squares err / atol)
    atol = np.concatenate([np.maximum(1e-16 * gt * H, 1e-150), np.full(m, 1e-6 * t_max)])        # t decides only "within t_max"
    try:
        sol = solve_ivp(rhs, (0.0, 1.0), y0, method="DOP853", rtol=RAMP_RTOL, atol=atol, dense_output=True)
    except _Budget:
        # stiff: LSODA on the state interleaved per lane (E_i, t_i), whose Jacobian is then
        # banded (lower bandwidth 1: t depends on E, nothing across lanes)
        stiff[0] = True
        count[0], budget[0] = 0, RAMP_EVAL_BUDGET
        perm = np.arange(2 * m).reshape(2, m).T.ravel()          # interleaved -> [E..., t...] order
        inv = np.argsort(perm)

        def rhs_i(sig, yi):
            return rhs(sig, yi[inv])[perm]

        try:
            sol = solve_ivp(rhs_i, (0.0, 1.0), y0[perm], method="LSODA", rtol=max(RAMP_RTOL, 1e-9),
                            atol=atol[perm], dense_output=True, lband=1, uband=0)
        except _Budget:
            raise DesignError(f"{spec.path}: the ball's descent of the ramp ran out of its budget "
                              f"({RAMP_EVAL_BUDGET} evaluations of the explicit and of the stiff integrator): "
                              f"simulation.damping = {mu:g} 1/s makes it crawl (its decay time 1/mu is "
                              f"{1 / mu if mu else math.inf:.3g} s); lower it") from None
        if sol.success:
            dense = sol.sol
            sol.y = sol.y[inv]
            sol.sol = lambda s_, dense=dense: dense(s_)[inv]
    if not sol.success:
        raise DesignError(f"{spec.path}: the descent of the ramp failed: {sol.message}")
    return sol


def _ranges(h) -> str:
    h = np.asarray(h, dtype=float)
    return f"{float(h.min()):.6g}" if len(h) == 1 else f"{float(h.min()):.6g} .. {float(h.max()):.6g}"


def calibration_table(spec) -> dict:
    """Heights and entry speeds for the spec's ramp (:func:`entry`).

    Returns ``{"heights": (M,), "v_in": (M,), "g": float, "k": float, "units": str,
    "entry": Entry}`` (heights in design units, v_in in design units/s, nan where the ball
    does not reach the block; g in design units/s^2).
    """
    spec.require("ball", "ramp", command="calibrate")
    H = ramp_heights(spec)
    e = entry(spec, H)
    return {"heights": H, "v_in": e.v_in, "g": e.g, "k": e.k, "units": spec.units, "entry": e}
