"""Event location for the batched integrator (integrate.py).

Bounces (maxima of x(t)), escapes and fly-offs are located by Henon's trick: one
RK step from the start of the step that crossed the event, with the event's
quantity as the independent variable, landing on it exactly (so an event carries
the step's own local error). Loss of contact is located by secant iterations on
re-taken RK steps. Events are located in batches: bounces queued during the step
loop and the terminal events of retired lanes are flushed together.
"""

from __future__ import annotations

import numpy as np

from .models import ESCAPED
from .rk import _combine, _rk_step

# ----------------------------------------------------------------------------
# event location
# ----------------------------------------------------------------------------
_KINDS = {"x": 0, "y": 1, "vx": 2, "z": 3}


def _henon(sys, tab, Y, t, kind, target):
    """Henon's trick: one RK step from Y (nv, m) at times t (m,) with a quantity of the
    state as the independent variable, to ``target`` (m,).

    ``kind``: 'x' | 'y' | 'vx' | 'z', or an int array (m,) of codes 0..3 (one per lane).
    Returns (t_event (m,), Y_event (nv, m)); accurate to the RK step's local error.
    """
    nv, m = Y.shape
    code = np.broadcast_to(np.asarray(_KINDS[kind] if isinstance(kind, str) else kind), (m,))
    Z = np.empty((nv + 1, m))
    Z[:nv] = Y
    Z[nv] = t
    aux0 = sys(Y)[1]

    def rate(Yc, Fc, auxc):
        zd = auxc[1] * Yc[2] + auxc[2] * Yc[3]  # dz/dt = h_x xd + h_y yd
        return np.choose(code, (Fc[0], Fc[1], Fc[2], zd))

    def g(Zc):
        Fc, auxc = sys(Zc[:nv])
        r = rate(Zc, Fc, auxc)
        G = np.empty_like(Zc)
        G[:nv] = Fc / r
        G[nv] = 1.0 / r
        return G

    s0 = np.choose(code, (Y[0], Y[1], Y[2], aux0[0]))
    ds = target - s0
    K = np.empty((tab.n_stages + 1, nv + 1, m))
    K[0] = g(Z)
    Zs = np.empty_like(Z)
    for s in range(1, tab.n_stages):
        _combine(Z, ds, K, tab.A[s], Zs)
        K[s] = g(Zs)
    Znew = np.empty_like(Z)
    _combine(Z, ds, K, tab.B, Znew)
    for c in range(3):  # the independent variable lands on its target exactly
        Znew[c] = np.where(code == c, target, Znew[c])
    return Znew[nv], Znew[:nv]


def _secant(sys, tab, Y, F0, t, h, b0, b1, iters: int = 4):
    """Time and state where the bracket B crosses 0 inside steps of size h from Y,
    by secant iterations on re-taken RK steps (each as accurate as the step)."""
    nv, m = Y.shape
    lo, hi = np.zeros(m), np.ones(m)
    blo, bhi = b0.copy(), b1.copy()
    K = np.empty((tab.n_stages + 1, nv, m))
    Yt = Y.copy()
    th = np.ones(m)
    if iters <= 4:   # the point models: a fixed number of secant steps
        for _ in range(iters):
            th = lo + (hi - lo) * blo / (blo - bhi)
            th = np.where(np.isfinite(th), np.clip(th, lo, hi), 0.5 * (lo + hi))
            Yt = _rk_step(sys, tab, Y, F0, h * th, K)
            b = sys(Yt)[1][3]
            pos = b > 0
            lo = np.where(pos, th, lo)
            blo = np.where(pos, b, blo)
            hi = np.where(pos, hi, th)
            bhi = np.where(pos, bhi, b)
        return t + h * th, Yt
    # longer runs (the ball's guard): Illinois steps, each lane until its bracket is at rounding
    side = np.zeros(m)
    act = np.ones(m, dtype=bool)
    for _ in range(iters):
        tn = lo + (hi - lo) * blo / (blo - bhi)
        tn = np.where(np.isfinite(tn), np.clip(tn, lo, hi), 0.5 * (lo + hi))
        Yn = _rk_step(sys, tab, Y, F0, h * tn, K)
        b = sys(Yn)[1][3]
        th = np.where(act, tn, th)
        Yt = np.where(act, Yn, Yt)
        pos = b > 0
        up_lo, up_hi = act & pos, act & ~pos
        blo_new = np.where(up_lo, b, np.where(up_hi & (side == -1), 0.5 * blo, blo))
        bhi_new = np.where(up_hi, b, np.where(up_lo & (side == 1), 0.5 * bhi, bhi))
        lo, hi = np.where(up_lo, tn, lo), np.where(up_hi, tn, hi)
        blo, bhi = blo_new, bhi_new
        side = np.where(act, np.where(pos, 1, -1), side)
        act = act & ~((hi - lo <= 4 * np.spacing(1.0)) | (b == 0) | (np.abs(b) <= 1e-15))
        if not act.any():
            break
    return t + h * th, Yt


def _quantity(sys, Y, code):
    """The event quantity of states Y (nv, m) per lane code (0 x, 1 y, 2 xd, 3 z = h)."""
    h = sys(Y)[1][0]
    return np.choose(code, (Y[0], Y[1], Y[2], h))


def _bracketed(sys, tab, Y, t, h, kind, target, iters: int = 60):
    """Fallback where Henon's step fails (the event's quantity turns inside the step, e.g.
    a bounce and the escape in one long step, where x is not monotonic): the event's
    time by Illinois regula falsi on re-taken RK steps from Y (nv, m) over fractions of
    the step h (m,). The quantity changes sign over the step by construction. Each
    iterate is as accurate as a step; iterations stop when the bracket is at rounding."""
    nv, m = Y.shape
    code = np.broadcast_to(np.asarray(_KINDS[kind] if isinstance(kind, str) else kind), (m,))
    F0 = sys(Y)[0]
    K = np.empty((tab.n_stages + 1, nv, m))
    lo, hi = np.zeros(m), np.ones(m)
    glo = _quantity(sys, Y, code) - target
    Y1 = _rk_step(sys, tab, Y, F0, h, K)
    ghi = _quantity(sys, Y1, code) - target
    Yt, th = Y1, np.ones(m)
    side = np.zeros(m)
    act = np.ones(m, dtype=bool)     # lanes still iterating: each lane's sequence is its own
    for _ in range(iters):
        tn = (lo * ghi - hi * glo) / (ghi - glo)
        tn = np.where(np.isfinite(tn) & (tn > lo) & (tn < hi), tn, 0.5 * (lo + hi))
        Yn = _rk_step(sys, tab, Y, F0, h * tn, K)
        gn = _quantity(sys, Yn, code) - target
        th = np.where(act, tn, th)
        Yt = np.where(act, Yn, Yt)
        same = np.sign(gn) == np.sign(glo)
        up_lo, up_hi = act & same, act & ~same
        # Illinois: halve the stale end's value when the same end is kept twice
        glo_new = np.where(up_lo, gn, np.where(up_hi & (side == -1), 0.5 * glo, glo))
        ghi_new = np.where(up_hi, gn, np.where(up_lo & (side == 1), 0.5 * ghi, ghi))
        lo, hi = np.where(up_lo, tn, lo), np.where(up_hi, tn, hi)
        glo, ghi = glo_new, ghi_new
        side = np.where(act, np.where(same, 1, -1), side)
        act = act & ~((hi - lo <= 4 * np.spacing(1.0)) | (gn == 0))
        if not act.any():
            break
    for c in range(3):
        Yt[c] = np.where(code == c, target, Yt[c])
    return t + h * th, Yt


def _locate(sys, tab, Y, t, h, kind, target):
    """Henon's step, and for the lanes where it fails (result outside the step or not
    finite) the bracketed fallback. Returns (t_event, Y_event, ok)."""
    te, Ye = _henon(sys, tab, Y, t, kind, target)
    ok = np.isfinite(te) & (te >= t) & (te <= t + h + 1e-9 * h) & np.isfinite(Ye[:sys.ne]).all(axis=0)
    if not ok.all():
        bad = np.flatnonzero(~ok)
        kd = kind if isinstance(kind, str) else np.asarray(kind)[bad]
        tg = np.broadcast_to(np.asarray(target, dtype=float), t.shape)[bad]
        tb, Yb = _bracketed(sys, tab, Y[:, bad], t[bad], h[bad], kd, tg)
        okb = np.isfinite(tb) & np.isfinite(Yb[:sys.ne]).all(axis=0)
        te[bad] = np.where(okb, tb, te[bad])
        Ye[:, bad] = np.where(okb, Yb, Ye[:, bad])
        ok[bad] = okb
    return te, Ye, ok


def _flush_bounces(sys, tab, queue, out, k_keep):
    """Locate the queued bounces (one Henon step in xd for all) and store their times."""
    if not queue:
        return
    Y = np.concatenate([q[0] for q in queue], axis=1)
    t = np.concatenate([q[1] for q in queue])
    lane = np.concatenate([q[2] for q in queue])
    order = np.concatenate([q[3] for q in queue])
    h = np.concatenate([q[4] for q in queue])
    queue.clear()
    keep = order < k_keep
    if not keep.any():
        return
    Y, t, lane, order, h = Y[:, keep], t[keep], lane[keep], order[keep], h[keep]
    te, _, ok = _locate(sys, tab, Y, t, h, "vx", np.zeros(t.size))
    ok = ok & (te <= t + h)
    out["bounce_times"][lane, order] = np.where(ok, te, t + h)


PENDING = 100  # placeholder outcome of a lane whose terminal event is located later


def _flush_terminal(sys, tab, pending, out, k_keep):
    """Locate the terminal events (and bounces in the same steps) of lanes retired with
    a placeholder: one Henon step for all; per lane the earliest terminal event wins;
    a bounce counts if it comes before it. Writes the lanes' final summaries."""
    if not pending:
        return
    cat = {k: np.concatenate([p[k] for p in pending], axis=-1) for k in pending[0]}
    pending.clear()
    te, Ye, ok = _locate(sys, tab, cat["Y"], cat["t"], cat["h"], cat["kind"], cat["target"])
    t_hi = cat["t"] + cat["h"]
    te = np.where(ok, te, t_hi)
    Ye = np.where(ok, Ye, cat["Yfb"])
    lane, oc = cat["lane"], cat["outcome"]
    term = np.flatnonzero(oc >= 0)
    order = term[np.lexsort((te[term], lane[term]))]
    first = order[np.r_[True, lane[order][1:] != lane[order][:-1]]]  # earliest per lane
    gl = lane[first]
    Yend, tend = Ye[:, first], te[first]
    out["outcome"][gl] = oc[first]
    out["t_end"][gl] = tend
    out["x_end"][gl], out["y_end"][gl] = Yend[0], Yend[1]
    vxe, vye = sys.velocity(Yend)
    out["vx_end"][gl], out["vy_end"][gl] = vxe, vye
    out["v_out"][gl] = np.where(oc[first] == ESCAPED, np.abs(vxe), np.nan)
    aux_end = sys(Yend)[1]
    if len(aux_end) > 4:   # (terminal events here are escapes and fly-offs: the end counts)
        out["max_slip"][gl] = np.fmax(cat["smax"][first], aux_end[4])
    inv = cat["inv"][first]
    E = sys.energy(Yend, aux_end, inv)
    W = Yend[sys.iw] * (inv * inv) if sys.damped else 0.0
    zmax = np.maximum(cat["zmax"][first], aux_end[0])
    zmin = np.minimum(cat["zmin"][first], aux_end[0])
    escale = cat["kin0"][first] + sys.gt * (zmax - zmin) * (inv * inv)
    out["energy_error"][gl] = np.abs(E + W - cat["E0"][first]) / np.maximum(escale, 1e-300)
    out["max_z"][gl] = zmax
    out["max_abs_y"][gl] = np.maximum(cat["ymax"][first], np.abs(Yend[1]))
    out["bounces"][gl] = cat["nb"][first]
    b = np.flatnonzero(oc == -2)
    if b.size:
        t_end = np.full(out["t_end"].shape, np.inf)
        t_end[gl] = tend
        counts = te[b] <= t_end[lane[b]]
        b = b[counts]
        out["bounces"][lane[b]] = cat["nb"][b] + 1
        keep = cat["nb"][b] < k_keep
        out["bounce_times"][lane[b][keep], cat["nb"][b][keep]] = te[b][keep]
