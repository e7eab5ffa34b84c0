"""fabkit's launch integrator: the public API (``launch_batch``, ``launch_stream``).

The point models (``full``, ``simplified``) run on the compiled engine
(:mod:`fabkit.physics.engine`: the same method, step control and events as
described below, one launch wholly in compiled code); the ball model runs on the
batched numpy loop of this module until it is ported onto the engine as a template
of its own. What follows describes the numpy loop; the engine's docs are in
``engine/dop853.py``.

fabkit's batched integrator: many launches advanced at once, each with its own step.

Method
------
The Runge-Kutta kernel (tableaux, step, error norm, initial step) is in
:mod:`fabkit.physics.rk`, the event location in :mod:`fabkit.physics.events`;
this module holds the chunk loop, the stiff path and the public API.

An embedded explicit Runge-Kutta pair (default Dormand-Prince 8(5,3), the method
of scipy's ``DOP853``; ``method='RK45'`` gives Dormand-Prince 5(4)) applied to
all lanes (launches) of a batch with numpy: every lane has its own time, step
size, accept/reject decision and events. The arithmetic is elementwise over
lanes in a fixed order (no reductions across lanes, no BLAS), so a lane's
result does not depend on which other lanes share its batch: results are
bit-identical for any batch size, chunking or thread count. Lanes that finish
are compacted away; launches are processed in chunks of at most ``CHUNK`` lanes
and only per-lane summaries are kept (memory bounded for any number of launches).

State per lane: (x, y, xd, yd, W) with W the energy dissipated by damping
(only integrated when there is damping; it gives the energy-balance error).
Step-size control and error norm are scipy's (so tolerances mean the same).

Events (checked on every accepted step, from its start and end states):

    bounce        xd crosses from + to -: a maximum of x(t). Located by Henon's trick:
                  one extra RK step from the step's start with xd as the independent
                  variable, to xd = 0 exactly. Not terminal; the first K times are kept.
    escaped       x crosses ``start`` moving toward -x. Henon step with x as the
                  independent variable to x = start exactly; v_out = |xd| there.
    flew_off      h(x, y) reaches top - margin (Henon step in z), or x or y leaves the
                  footprint shrunk by the margin (Henon step in x or y).
    lost_contact  (full model) the normal-force bracket B of eq. (xyODE) falls to 0 or
                  below; located by secant iterations on re-taken RK steps.
    captured      still on the surface at ``t_max`` (including launches too slow to
                  arrive anywhere, and runs stopped by the step guard, ``status`` 1).

The event location is as accurate as a step (Henon's step has the step's own
local error), so bounce times and v_out carry the integrator's tolerance. Nothing
in the step loop depends on where exactly an event lies, so events are located in
batches: bounces are queued and located many at once; a lane whose step crosses a
terminal event retires at once and its event (the earliest, if several; a bounce in
the same step counts only if it comes first) is located at the end of the chunk.

Stiff cases: where the damping rate times ``t_max`` is so large that the explicit
method would need more than ``STIFF_STEPS`` stability-bound steps (mu above about
200 1/s at t_max = 60 s), the lanes go to scipy's implicit Radau method (one launch
at a time, about a second each, same events), ``status`` 2.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError
from ..tolerances import DEFAULT
from .events import _KINDS, PENDING, _flush_bounces, _flush_terminal, _locate, _secant
from .models import BRIDGED, CAPTURED, ESCAPED, FLEW_OFF, LOST_CONTACT, OUTCOMES
from .rk import _error_norm, _error_norm_scaled, _initial_step, _pow2, _rk_step, system, tableau
from .trap import region, trap_energy

CHUNK = 16384         # lanes per chunk (memory bound; the arithmetic does not depend on it)
K_BOUNCES = 16        # bounce times kept per lane
QUEUE = 1024          # bounces located together
STIFF_STEPS = 2_000   # stability-bound explicit steps beyond which a damped problem goes to Radau
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0
BETA = 0.0            # PI step control exponent (0: scipy's controller)


# ----------------------------------------------------------------------------
# results
# ----------------------------------------------------------------------------
@dataclass
class LaunchResult:
    """Per-launch summaries, arrays of shape (N,) unless stated.

    outcome       int8, index into ``models.OUTCOMES``
    bounces       int, maxima of x(t) before the end
    v_out         |xd| at the escape crossing, design units/s (nan unless escaped)
    bounce_times  (N, K) the first K bounce times, s (nan padded)
    t_end, x_end, y_end, vx_end, vy_end   the final state (at the event that ended the run)
    max_z, max_abs_y   the largest height and |y| over the step points
    energy_error  |E(t_end) + W(t_end) - E(0)| / (E_kin(0) + g~ (z_max - z_min)): the
                  relative energy drift (undamped) or energy-balance error (damped, W =
                  dissipated energy); the scale is the largest kinetic energy the run can reach
    steps, rejected   accepted and rejected steps per launch
    status        0 normal, 1 stopped by the step guard (outcome captured), 2 stiff: run by Radau,
                  3 derivatives overflow at the launch (flew_off), 4 captured before t_max: its
                  energy fell below the trapping energy (``problem.stop_trapped``, see trap.py)
    trajectories  with record=True: per launch a dict of arrays t, x, y, vx, vy, ax, ay
    """

    v_in: np.ndarray
    outcome: np.ndarray
    bounces: np.ndarray
    v_out: np.ndarray
    bounce_times: np.ndarray
    t_end: np.ndarray
    x_end: np.ndarray
    y_end: np.ndarray
    vx_end: np.ndarray
    vy_end: np.ndarray
    max_z: np.ndarray
    max_abs_y: np.ndarray
    energy_error: np.ndarray
    max_slip: np.ndarray
    steps: np.ndarray
    rejected: np.ndarray
    status: np.ndarray
    method: str = "DOP853"
    rtol: float = 1e-10
    atol: float = 1e-12
    seconds: float = 0.0
    trajectories: list | None = field(default=None, repr=False)

    @property
    def outcome_names(self) -> list[str]:
        return [OUTCOMES[i] for i in self.outcome]

    def __len__(self) -> int:
        return len(self.v_in)


_FIELDS = ("outcome", "bounces", "v_out", "bounce_times", "t_end", "x_end", "y_end", "vx_end", "vy_end",
           "max_z", "max_abs_y", "energy_error", "max_slip", "steps", "rejected", "status")


def _empty(n: int, k: int) -> dict:
    nan = np.full(n, np.nan)
    return {
        "outcome": np.full(n, CAPTURED, dtype=np.int8), "bounces": np.zeros(n, dtype=np.int64),
        "v_out": nan.copy(), "bounce_times": np.full((n, k), np.nan), "t_end": nan.copy(),
        "x_end": nan.copy(), "y_end": nan.copy(), "vx_end": nan.copy(), "vy_end": nan.copy(),
        "max_z": nan.copy(), "max_abs_y": nan.copy(), "energy_error": nan.copy(), "max_slip": nan.copy(),
        "steps": np.zeros(n, dtype=np.int64), "rejected": np.zeros(n, dtype=np.int64),
        "status": np.zeros(n, dtype=np.int8),
    }


# ----------------------------------------------------------------------------
# the chunk loop
# ----------------------------------------------------------------------------
TRAP_EVERY = 8   # steps between trapping-energy checks (problem.stop_trapped)


def _keep(keep, *arrays):
    """The lanes ``keep`` (m,) bool of per-lane arrays (lanes on the last axis)."""
    return tuple(a[..., keep] for a in arrays)


def _run_chunk(*args, **kw):
    """Integrate one chunk of lanes; returns the per-lane summary dict (and trajectories)."""
    with np.errstate(all="ignore"):
        return _run_chunk_body(*args, **kw)


def _run_chunk_body(problem, v_in, y0, vy0, rtol, atol, t_max, max_steps, tab, record, k_keep, tick=None):
    sys = system(problem)
    ne = sys.ne
    n = len(v_in)
    out = _empty(n, k_keep)
    x_lo, x_hi = problem.x_range[0] + problem.margin, problem.x_range[1] - problem.margin
    y_lo, y_hi = problem.y_range[0] + problem.margin, problem.y_range[1] - problem.margin
    z_lim = problem.top - problem.margin
    start = problem.start
    e_star = trap_energy(problem, 100.0 * rtol) if problem.stop_trapped else None
    tx0, tx1, ty0, ty1 = region(problem)
    it = 0

    Y = sys.initial(start, y0, v_in, vy0)
    F, aux = sys(Y)
    # energies are kept per lane times inv^2 (inv a power of two, 1 for any ordinary speed)
    inv = np.where(np.maximum(np.abs(Y[2]), np.abs(Y[3])) > 1e100,
                   1.0 / _pow2(np.maximum(np.abs(Y[2]), np.abs(Y[3]))), 1.0)
    E0 = sys.energy(Y, aux, inv)
    kin0 = sys.kinetic(Y, aux, inv)
    t = np.zeros(n)
    h = _initial_step(sys, tab, Y, F, rtol, atol, t_max)
    idx = np.arange(n)
    zmax = aux[0].copy()
    zmin = aux[0].copy()
    ymax = np.abs(Y[1])
    smax = aux[4].copy() if len(aux) > 4 else np.full(n, np.nan)   # largest slip ratio (ball)
    steps = np.zeros(n, dtype=np.int64)
    rej = np.zeros(n, dtype=np.int64)
    nb = np.zeros(n, dtype=np.int64)
    was_rejected = np.zeros(n, dtype=bool)
    err_prev = np.ones(n)
    expo = -1.0 / (tab.order + 1)
    traj = [[(0.0, *Y[:4, i], *F[2:4, i])] for i in range(n)] if record else None
    # derivatives that overflow at the launch (|v| beyond ~1e150 design units/s on a curved
    # surface: h_xx v^2 is not a float): no step can be taken, and no surface holds such a
    # ball. The lane ends at once as flew_off, status 3, instead of shrinking its step forever.
    over = ~np.isfinite(F[:ne]).all(axis=0)
    # the ball launched where its guard is already down (bridged at the start, say): it ends there
    bad0 = (aux[3] <= 0) & ~over if sys.guarded else np.zeros(n, dtype=bool)
    if bad0.any():
        sel = np.flatnonzero(bad0)
        out["outcome"][sel] = sys.guard_outcome(Y[:, sel])
        out["t_end"][sel] = 0.0
        out["x_end"][sel], out["y_end"][sel] = Y[0, sel], Y[1, sel]
        out["vx_end"][sel], out["vy_end"][sel] = sys.velocity(Y[:, sel])
        out["max_z"][sel] = aux[0][sel]
        out["max_abs_y"][sel] = np.abs(Y[1, sel])
        out["energy_error"][sel] = 0.0
        out["max_slip"][sel] = smax[sel]
        over = over | bad0
    if over.any():
        sel = np.flatnonzero(over)
        out["outcome"][sel] = FLEW_OFF
        out["t_end"][sel] = 0.0
        out["x_end"][sel], out["y_end"][sel] = Y[0, sel], Y[1, sel]
        out["vx_end"][sel], out["vy_end"][sel] = Y[2, sel], Y[3, sel]
        out["max_z"][sel] = aux[0][sel]
        out["max_abs_y"][sel] = np.abs(Y[1, sel])
        out["energy_error"][sel] = 0.0
        out["status"][sel] = 3
        out["outcome"][np.flatnonzero(bad0)] = sys.guard_outcome(Y[:, bad0])
        out["status"][np.flatnonzero(bad0)] = 0
        idx, Y, F, t, h, zmax, zmin, ymax, smax, steps, rej, nb, was_rejected, err_prev = _keep(
            ~over, idx, Y, F, t, h, zmax, zmin, ymax, smax, steps, rej, nb, was_rejected, err_prev)
        aux = _keep(~over, *aux)

    queue, queued, pending = [], [0], []
    while idx.size:
        m = idx.size
        it += 1
        hstep = np.minimum(h, t_max - t)
        last = hstep >= t_max - t
        K = np.empty((tab.n_stages + 1, sys.nv, m))
        Ynew = _rk_step(sys, tab, Y, F, hstep, K)
        Fnew, auxn = sys(Ynew, out=K[tab.n_stages])
        scale = atol + np.maximum(np.abs(Y[:ne]), np.abs(Ynew[:ne])) * rtol
        err = _error_norm(tab, K, hstep, scale)
        # (the dissipated work W may overflow at absurd speeds; it only feeds the energy check)
        okK = np.isfinite(Ynew[:ne]).all(axis=0) & np.isfinite(Fnew[:ne]).all(axis=0)
        over = ~np.isfinite(err) & okK
        if over.any():  # the squares overflowed (huge speeds): the same norm, rescaled
            sel = np.flatnonzero(over)
            err[sel] = _error_norm_scaled(tab, K[:, :, sel], hstep[sel], scale[:, sel])
        finite = np.isfinite(err) & okK
        acc = finite & (err <= 1.0)
        fac = np.where(err == 0, MAX_FACTOR, SAFETY * np.power(np.where(finite, err, 1.0), expo))
        fac_acc = fac
        if BETA:  # PI control (Gustafsson): damp the step growth by the previous error
            fac_acc = fac * np.power(np.maximum(err, 1e-4), 0.75 * BETA) * np.power(err_prev, BETA)
        fac_acc = np.minimum(MAX_FACTOR, fac_acc)
        fac_acc = np.where(was_rejected, np.minimum(1.0, fac_acc), fac_acc)
        err_prev = np.where(acc, np.maximum(err, 1e-4), err_prev)
        fac_rej = np.where(finite, np.maximum(MIN_FACTOR, fac), MIN_FACTOR)
        rej += ~acc
        steps += acc
        was_rejected = ~acc
        h = np.where(acc, hstep * fac_acc, hstep * fac_rej)

        # ---- events on accepted steps ----
        done = np.zeros(m, dtype=bool)
        code = np.full(m, -1, dtype=np.int8)
        t_ev = np.full(m, np.inf)
        Y_ev = np.empty((sys.nv, m))
        tnew = t + hstep

        # candidates (lane, kind, target, outcome), located together in one Henon step
        cand = []

        def propose(mask, kind, target, outcome):
            sel = np.flatnonzero(mask)
            if sel.size:
                cand.append((sel, np.full(sel.size, _KINDS.get(kind, -1)), np.broadcast_to(
                    np.asarray(target, dtype=float), (m,))[sel], outcome))

        xo, xn = Y[0], Ynew[0]
        propose(acc & (xo > start) & (xn <= start) & (Ynew[2] < 0), "x", start, ESCAPED)
        propose(acc & (auxn[0] >= z_lim) & (aux[0] < z_lim), "z", z_lim, FLEW_OFF)
        propose(acc & (xn >= x_hi) & (xo < x_hi), "x", x_hi, FLEW_OFF)
        propose(acc & (xn <= x_lo) & (xo > x_lo), "x", x_lo, FLEW_OFF)
        propose(acc & (Ynew[1] >= y_hi) & (Y[1] < y_hi), "y", y_hi, FLEW_OFF)
        propose(acc & (Ynew[1] <= y_lo) & (Y[1] > y_lo), "y", y_lo, FLEW_OFF)
        bmask = acc & (Y[2] > 0) & (Ynew[2] <= 0)   # bounce: xd from + to - (not terminal)
        if bmask.any():
            # bounces in steps without a terminal event are located later, many at once
            # (nothing in the step loop depends on their times); the others right now
            tany = np.zeros(m, dtype=bool)
            for c in cand:
                tany[c[0]] = True
            later = np.flatnonzero(bmask & ~tany)
            if later.size:
                queue.append((Y[:, later].copy(), t[later].copy(), idx[later], nb[later].copy(),
                              hstep[later].copy()))
                nb[later] += 1
                queued[0] += later.size
                if queued[0] >= QUEUE:
                    _flush_bounces(sys, tab, queue, out, k_keep)
                    queued[0] = 0
            propose(bmask & tany, "vx", 0.0, -2)
        lm = (acc & (auxn[3] <= 0) & (aux[3] > 0)) if sys.guarded else None
        if cand:
            sel = np.concatenate([c[0] for c in cand])
            kinds = np.concatenate([c[1] for c in cand])
            targ = np.concatenate([c[2] for c in cand])
            outc = np.concatenate([np.full(c[0].size, c[3]) for c in cand])
            if not record:
                # lanes ending in this step (without a loss of contact) retire now with a
                # placeholder; their events are located together at the end of the chunk
                later = ~lm[sel] if lm is not None else np.ones(sel.size, dtype=bool)
                if later.any():
                    ls = sel[later]
                    lanes = np.unique(ls)
                    pending.append({
                        "lane": idx[ls], "Y": Y[:, ls].copy(), "t": t[ls].copy(), "h": hstep[ls].copy(),
                        "Yfb": Ynew[:, ls].copy(), "kind": kinds[later], "target": targ[later],
                        "outcome": outc[later], "E0": E0[idx[ls]], "kin0": kin0[idx[ls]], "inv": inv[idx[ls]],
                        "zmax": zmax[ls].copy(), "zmin": zmin[ls].copy(), "ymax": ymax[ls].copy(),
                        "smax": smax[ls].copy(), "nb": nb[ls].copy()})
                    code[lanes] = PENDING
                    t_ev[lanes] = tnew[lanes]
                    Y_ev[:, lanes] = Ynew[:, lanes]
                    sel, kinds, targ, outc = sel[~later], kinds[~later], targ[~later], outc[~later]
        if cand and sel.size:
            te, Ye, ok = _locate(sys, tab, Y[:, sel], t[sel], hstep[sel], kinds, targ)
            te = np.where(ok, te, tnew[sel])
            Ye = np.where(ok, Ye, Ynew[:, sel])
            isb = outc == -2
            if isb.any():
                bs, tb = sel[isb], te[isb]
                gl = idx[bs]
                cnt = nb[bs]
                keep = cnt < k_keep
                out["bounce_times"][gl[keep], cnt[keep]] = tb[keep]
                nb[bs] += 1
            for j in np.flatnonzero(~isb):  # terminal candidates: the earliest wins
                i = sel[j]
                if te[j] < t_ev[i]:
                    t_ev[i] = te[j]
                    Y_ev[:, i] = Ye[:, j]
                    code[i] = outc[j]
        if sys.guarded:
            if lm.any():
                sel = np.flatnonzero(lm)
                te, Ye = _secant(sys, tab, Y[:, sel], F[:, sel], t[sel], hstep[sel], aux[3][sel],
                                 auxn[3][sel], iters=sys.guard_iters)
                better = te < t_ev[sel]
                b = sel[better]
                t_ev[b] = te[better]
                Y_ev[:, b] = Ye[:, better]
                code[b] = sys.guard_outcome(Ye[:, better])
        # already outside at the start of the run (start outside the shrunk footprint): ignore
        term = code >= 0
        # a bounce located after the terminal event does not count
        if term.any() and bmask.any():
            late = term & bmask & (nb > 0)
            sel = np.flatnonzero(late)
            if sel.size:
                gl = idx[sel]
                cnt = nb[sel] - 1
                tb_rec = np.where(cnt < k_keep, out["bounce_times"][gl, np.minimum(cnt, k_keep - 1)], -np.inf)
                drop = tb_rec > t_ev[sel]
                nb[sel[drop]] -= 1
                keepc = drop & (cnt < k_keep)
                out["bounce_times"][gl[keepc], cnt[keepc]] = np.nan

        # ---- advance accepted lanes ----
        Y = np.where(acc, Ynew, Y)
        F = np.where(acc, Fnew, F)
        aux = tuple(np.where(acc, a1, a0) for a0, a1 in zip(aux, auxn))
        t = np.where(acc, tnew, t)
        zmax = np.where(acc, np.maximum(zmax, aux[0]), zmax)
        zmin = np.where(acc, np.minimum(zmin, aux[0]), zmin)
        ymax = np.where(acc, np.maximum(ymax, np.abs(Y[1])), ymax)
        if len(aux) > 4:
            smax = np.where(acc & ~term, np.fmax(smax, aux[4]), smax)
        if record:
            for i in np.flatnonzero(acc & ~term):
                traj[idx[i]].append((t[i], *Y[:4, i], *F[2:4, i]))

        captured = acc & last & ~term
        trapped = np.zeros(m, dtype=bool)
        if e_star is not None and it % TRAP_EVERY == 0:
            # energy below every exit (trap.py): captured for good, stop now
            cand_t = acc & ~term & ~last & (inv[idx] == 1.0) & (Y[0] > tx0) & (Y[0] < tx1) & \
                (Y[1] > ty0) & (Y[1] < ty1)
            if cand_t.any():
                trapped = cand_t & (sys.energy(Y, aux) < e_star)
                captured = captured | trapped
        guard = (steps + rej >= max_steps) & ~term & ~captured
        # step-size underflow: the next step would not move t (scipy's criterion); relative
        # to t, not absolute, so a huge speed (steps ~ size / speed) can still be followed
        tiny = ~acc & (h <= 10.0 * np.spacing(np.abs(t)))
        guard |= tiny & ~term & ~captured
        done = term | captured | guard
        if done.any():
            sel = np.flatnonzero(done)
            gl = idx[sel]
            Yend = np.where(term[sel], Y_ev[:, sel], Y[:, sel])
            tend = np.where(term[sel], t_ev[sel], t[sel])
            oc = np.where(term[sel], code[sel], CAPTURED).astype(np.int8)
            out["outcome"][gl] = oc
            out["t_end"][gl] = tend
            out["x_end"][gl], out["y_end"][gl] = Yend[0], Yend[1]
            vxe, vye = sys.velocity(Yend)
            out["vx_end"][gl], out["vy_end"][gl] = vxe, vye
            out["v_out"][gl] = np.where(oc == ESCAPED, np.abs(vxe), np.nan)
            F_end, aux_end = sys(Yend)
            if len(aux_end) > 4:
                # the slip ratio at the end counts, except where contact is lost or bridged
                out["max_slip"][gl] = np.where((oc == LOST_CONTACT) | (oc == BRIDGED), smax[sel],
                                               np.fmax(smax[sel], aux_end[4]))
            i2 = inv[gl] * inv[gl]
            E = sys.energy(Yend, aux_end, inv[gl])
            W = Yend[sys.iw] * i2 if sys.damped else 0.0
            # scale: the largest kinetic energy the run can have had (launch + height lost)
            escale = kin0[gl] + sys.gt * (np.maximum(zmax[sel], aux_end[0]) - np.minimum(zmin[sel], aux_end[0])) * i2
            out["energy_error"][gl] = np.abs(E + W - E0[gl]) / np.maximum(escale, 1e-300)
            out["max_z"][gl] = np.maximum(zmax[sel], aux_end[0])
            out["max_abs_y"][gl] = np.maximum(ymax[sel], np.abs(Yend[1]))
            out["bounces"][gl] = nb[sel]
            out["steps"][gl] = steps[sel]
            out["rejected"][gl] = rej[sel]
            out["status"][gl] = np.where(guard[sel], 1, np.where(trapped[sel], 4, 0))
            if record:
                for j, i in enumerate(sel):
                    if term[i]:
                        traj[idx[i]].append((tend[j], *Yend[:4, j], *F_end[2:4, j]))
            keep = ~done
            if tick is not None:
                tick(n - int(keep.sum()))
            idx, Y, F, t, h, zmax, zmin, ymax, smax, steps, rej, nb, was_rejected, err_prev = _keep(
                keep, idx, Y, F, t, h, zmax, zmin, ymax, smax, steps, rej, nb, was_rejected, err_prev)
            aux = _keep(keep, *aux)
    _flush_bounces(sys, tab, queue, out, k_keep)
    _flush_terminal(sys, tab, pending, out, k_keep)
    if record:
        trajs = []
        for rows in traj:
            a = np.array(rows, dtype=float)
            trajs.append({"t": a[:, 0], "x": a[:, 1], "y": a[:, 2], "vx": a[:, 3], "vy": a[:, 4],
                          "ax": a[:, 5], "ay": a[:, 6]})
        out["_traj"] = trajs
    return out


# ----------------------------------------------------------------------------
# stiff path
# ----------------------------------------------------------------------------
def stiffness_rate(problem) -> float:
    """An upper estimate of the damping rate (1/s) that limits an explicit step."""
    rate = float(problem.damping)
    if problem.nonlinear_damping:
        xs = np.linspace(problem.x_range[0], problem.x_range[1], 401) if np.all(
            np.isfinite(problem.x_range)) else np.linspace(-10, 10, 401)
        F = problem.fns.grad(xs, np.zeros_like(xs))[1]
        ym = max(abs(problem.y_range[0]), abs(problem.y_range[1])) if np.all(
            np.isfinite(problem.y_range)) else 10.0
        rate += float(problem.nonlinear_damping) * float(np.nanmax(F * F)) * ym * ym
    return rate


def is_stiff(problem, t_max: float) -> bool:
    """True when the explicit method's step is bounded by stability against the damping
    (|h mu| <= ~6 for DOP853) for more than STIFF_STEPS steps: then scipy's implicit
    Radau is cheaper per launch. Measured for one launch at mu = 3000 1/s, t_max = 60 s:
    explicit 18 s, Radau 0.7 s. The choice depends on the problem only (not on the batch
    size), so results stay identical for any batching."""
    return stiffness_rate(problem) * t_max / 6.0 > STIFF_STEPS


def _run_stiff(problem, v_in, y0, vy0, rtol, atol, t_max, k_keep):
    from .reference import solve_launch

    n = len(v_in)
    out = _empty(n, k_keep)
    for i in range(n):
        r = solve_launch(problem, float(v_in[i]), float(y0[i]), float(vy0[i]), method="Radau",
                         rtol=max(rtol, 1e-10), atol=max(atol, 1e-12), t_max=t_max)
        out["outcome"][i] = OUTCOMES.index(r["outcome"])
        out["bounces"][i] = r["bounces"]
        tb = np.asarray(r["bounce_times"])[:k_keep]
        out["bounce_times"][i, :len(tb)] = tb
        out["v_out"][i] = r["v_out"]
        out["t_end"][i] = r["t_end"]
        out["x_end"][i], out["y_end"][i] = r["x_end"], r["y_end"]
        out["vx_end"][i], out["vy_end"][i] = r["xdot_end"], r["ydot_end"]
        out["max_z"][i], out["max_abs_y"][i] = r["max_z"], r["max_abs_y"]
        out["energy_error"][i] = np.nan  # the Radau path does not track the dissipated work
        out["max_slip"][i] = r.get("max_slip", np.nan)
        out["steps"][i] = r["nfev"]
        out["status"][i] = 2
    return out


# ----------------------------------------------------------------------------
# public entry points
# ----------------------------------------------------------------------------
def _lanes(values, n, name):
    if values is None:
        return None
    a = np.asarray(values, dtype=float)
    a = np.broadcast_to(a, (n,)) if a.ndim == 0 or a.shape == (1,) else a
    if a.shape != (n,):
        raise SpecError(f"must be a number or one value per launch ({n}), got shape {a.shape}", key=name)
    if not np.all(np.isfinite(a)):
        raise SpecError("must be finite", key=name)
    return np.ascontiguousarray(a, dtype=float)


def _prepare(problem, v_in, y0, vy0, rtol, atol, t_max, tol):
    """Validated lanes and tolerances: (v (N,), y0 (N,), vy0 (N,), rtol, atol, t_max)."""
    v = np.atleast_1d(np.asarray(v_in, dtype=float)).ravel()
    n = v.size
    if n > tol.max_launches:
        raise SpecError(f"too many launches: {n} (limit {tol.max_launches})", key="v_in")
    if not np.all(np.isfinite(v)) or np.any(v < 0):
        raise SpecError("entry speeds must be finite and >= 0", key="v_in")
    y0a = _lanes(problem.y0 if y0 is None else y0, n, "y0")
    vy0a = _lanes(problem.vy0 if vy0 is None else vy0, n, "vy0")
    rtol = float(problem.rtol if rtol is None else rtol)
    atol = float(problem.atol if atol is None else atol)
    t_max = float(problem.t_max if t_max is None else t_max)
    if not (rtol > 0 and atol > 0 and t_max > 0):
        raise SpecError("rtol, atol and t_max must be > 0", key="simulation")
    return v, y0a, vy0a, rtol, atol, t_max


def launch_stream(problem, v_in, y0=None, vy0=None, *, rtol: float | None = None, atol: float | None = None,
                  t_max: float | None = None, max_bounces: int = K_BOUNCES, method: str = "DOP853",
                  chunk: int = CHUNK, tol=DEFAULT):
    """Like :func:`launch_batch`, but yields one :class:`LaunchResult` per chunk of at
    most ``chunk`` launches, in order, as each finishes.

    For studies of any size: memory is bounded by one chunk (plus the N input
    speeds), whatever N; a caller writes or reduces each chunk and lets it go. Each
    launch's result is bit-identical to :func:`launch_batch` (lanes do not interact).
    """
    v, y0a, vy0a, rtol, atol, t_max = _prepare(problem, v_in, y0, vy0, rtol, atol, t_max, tol)
    chunk = max(1, int(chunk))
    for a in range(0, v.size, chunk):
        b = min(a + chunk, v.size)
        yield launch_batch(problem, v[a:b], y0a[a:b], vy0a[a:b], rtol=rtol, atol=atol, t_max=t_max,
                           max_bounces=max_bounces, method=method, workers=1, chunk=chunk, tol=tol)


_JOB = None


def _run_job(ab):
    return _JOB(ab)


def _fork_pool(workers: int):
    """A process pool by fork (None where fork is unavailable)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    import threading

    # fork only from a single-threaded main program (forking a threaded process, e.g. a
    # Dask worker, can deadlock): elsewhere the chunks run serially
    if "fork" not in mp.get_all_start_methods() or threading.active_count() > 1 \
            or threading.current_thread() is not threading.main_thread():
        return None
    try:
        return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork"))
    except (OSError, ValueError):
        return None


def launch_batch(problem, v_in, y0=None, vy0=None, *, rtol: float | None = None, atol: float | None = None,
                 t_max: float | None = None, max_bounces: int = K_BOUNCES, record: bool = False,
                 progress=None, method: str = "DOP853", workers: int | None = None,
                 chunk: int = CHUNK, tol=DEFAULT) -> LaunchResult:
    """Launch N balls at x = ``problem.start`` with xd = ``v_in`` (N,), y = ``y0``, yd = ``vy0``.

    Parameters
    ----------
    problem : models.Problem
    v_in : (N,) entry speeds, design units/s (>= 0)
    y0, vy0 : scalars or (N,): transverse offset and speed (default problem.y0, problem.vy0)
    rtol, atol : tolerances (default problem.rtol, problem.atol: 1e-10, 1e-12)
    t_max : time limit, s (default problem.t_max)
    max_bounces : K, bounce times kept per launch (>= 8)
    record : keep each launch's step points (for plots; only for small N)
    progress : callable(done, total) called as launches finish (at most 5 times a second,
               and once at the end of each chunk)
    method : 'DOP853' (default) or 'RK45'
    workers : processes over chunks (default 1; forked, and only from a single-threaded
              main program, else serial); results do not depend on it
    chunk : lanes per chunk (results do not depend on it)

    Returns a :class:`LaunchResult`. Accuracy: each launch is integrated to the
    given tolerances; events are located to the same accuracy (see the module doc).
    """
    t0 = time.perf_counter()
    v, y0a, vy0a, rtol, atol, t_max = _prepare(problem, v_in, y0, vy0, rtol, atol, t_max, tol)
    n = v.size
    k_keep = max(8, int(max_bounces))
    tab = tableau(method)
    max_steps = int(tol.max_sim_steps)
    if record and n > 64:
        raise SpecError(f"record=True keeps every step: at most 64 launches, got {n}", key="v_in")
    stiff = is_stiff(problem, t_max)
    if not stiff and problem.model in ENGINE_MODELS:
        # the point models run on the compiled engine (fabkit/physics/engine)
        out = _run_engine(problem, v, y0a, vy0a, rtol, atol, t_max, max_steps, method, record, k_keep,
                          progress, 1 if workers is None else int(workers))
        trajs = out.pop("_traj", None)
        return LaunchResult(v_in=v, **out, method=method, rtol=rtol, atol=atol,
                            seconds=time.perf_counter() - t0, trajectories=trajs)

    chunk = max(1, int(chunk))
    if workers is None:
        # measured on the 2-core machine (docs/simulator.md): two processes were not
        # reliably faster than one, so one is the default; pass workers=2 to try
        workers = 1
    n_chunks = max(1, math.ceil(n / chunk))
    if workers > 1 and n >= 256 and not stiff:  # equal chunks, a multiple of the workers
        n_chunks = workers * math.ceil(n_chunks / workers)
    bounds = np.linspace(0, n, n_chunks + 1).round().astype(int)
    pieces = [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]

    def job(ab, tick=None):
        a, b = ab
        if stiff:
            return _run_stiff(problem, v[a:b], y0a[a:b], vy0a[a:b], rtol, atol, t_max, k_keep)
        return _run_chunk(problem, v[a:b], y0a[a:b], vy0a[a:b], rtol, atol, t_max, max_steps, tab,
                          record, k_keep, tick)

    results = []
    done = 0
    pool = None
    if workers > 1 and len(pieces) > 1 and not record:
        pool = _fork_pool(workers)
    if pool is not None:
        # Processes, not threads: the per-step Python work holds the GIL. Forked
        # workers inherit the problem (its compiled functions do not pickle); only
        # the per-lane summaries come back. Same arithmetic per lane, same results.
        global _JOB
        _JOB = job
        try:
            with pool:
                for (a, b), r in zip(pieces, pool.map(_run_job, pieces)):
                    results.append(r)
                    done += b - a
                    if progress is not None:
                        progress(done, n)
        finally:
            _JOB = None
    else:
        last = [time.perf_counter()]

        def ticker(base):
            def tick(finished):  # progress within a chunk, at most 5 times a second
                now = time.perf_counter()
                if now - last[0] >= 0.2:
                    last[0] = now
                    progress(base + finished, n)
            return tick

        for a, b in pieces:
            results.append(job((a, b), ticker(done) if progress is not None else None))
            done += b - a
            if progress is not None:
                progress(done, n)

    if not results:
        merged = _empty(0, k_keep)
    else:
        merged = {f: np.concatenate([r[f] for r in results]) for f in _FIELDS}
    trajs = None
    if record:
        trajs = [tr for r in results for tr in r.get("_traj", [])]
    return LaunchResult(v_in=v, **merged, method="Radau" if stiff else method, rtol=rtol, atol=atol,
                        seconds=time.perf_counter() - t0, trajectories=trajs)


ENGINE_MODELS = ("full", "simplified")   # models the compiled engine serves (the ball: the numpy loop)


def _run_engine(problem, v, y0, vy0, rtol, atol, t_max, max_steps, method, record, k_keep, progress,
                threads):
    """All the launches on the compiled engine (engine/): the per-launch summary dict."""
    from .engine import batch

    n = v.size
    eng = batch.engine(problem)
    e_star = trap_energy(problem, 100.0 * rtol) if problem.stop_trapped else None
    last = [0.0]

    def tick(done):  # at most 5 times a second, and at the end
        now = time.perf_counter()
        if now - last[0] >= 0.2 or done >= n:
            last[0] = now
            progress(done, n)

    FO, IO, BT, trajs = batch.run(eng, problem, v, y0, vy0, rtol=rtol, atol=atol, t_max=t_max,
                                  max_steps=max_steps, k_keep=k_keep, method=method, record=record,
                                  e_star=e_star, threads=max(1, threads),
                                  progress=tick if progress is not None else None)
    if progress is not None and n == 0:
        progress(0, 0)
    out = {
        "outcome": IO[:, 0].astype(np.int8), "bounces": IO[:, 1].copy(), "v_out": FO[:, 0].copy(),
        "bounce_times": BT, "t_end": FO[:, 1].copy(), "x_end": FO[:, 2].copy(), "y_end": FO[:, 3].copy(),
        "vx_end": FO[:, 4].copy(), "vy_end": FO[:, 5].copy(), "max_z": FO[:, 6].copy(),
        "max_abs_y": FO[:, 7].copy(), "energy_error": FO[:, 8].copy(), "max_slip": np.full(n, np.nan),
        "steps": IO[:, 2].copy(), "rejected": IO[:, 3].copy(), "status": IO[:, 4].astype(np.int8),
    }
    if record:
        out["_traj"] = trajs
    return out


def simulate_one(problem, v_in: float, record: bool = True, **kw) -> dict:
    """One launch as a dict of plain values (and its trajectory when ``record``)."""
    r = launch_batch(problem, [float(v_in)], record=record, workers=1, **kw)
    nb = int(r.bounces[0])
    bt = r.bounce_times[0]
    out = {
        "outcome": OUTCOMES[int(r.outcome[0])],
        "bounces": nb,
        "bounce_times": [float(b) for b in bt[: min(nb, bt.size)]],
        "v_out": float(r.v_out[0]),
        "t_end": float(r.t_end[0]),
        "x_end": float(r.x_end[0]), "y_end": float(r.y_end[0]),
        "vx_end": float(r.vx_end[0]), "vy_end": float(r.vy_end[0]),
        "max_height": float(r.max_z[0]),
        "max_abs_y": float(r.max_abs_y[0]),
        "energy_error": float(r.energy_error[0]),
        "max_slip": float(r.max_slip[0]),
        "steps": int(r.steps[0]), "rejected": int(r.rejected[0]), "status": int(r.status[0]),
        "method": r.method, "rtol": r.rtol, "atol": r.atol,
    }
    if record and r.trajectories:
        out["trajectory"] = r.trajectories[0]
    return out
