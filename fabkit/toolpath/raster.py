"""Raster planning for a ball-end mill: passes, slope-aware stepover, adaptive
point spacing, air skipping, links, optional z-level roughing.

Work coordinates, mm (see :mod:`fabkit.toolpath.path`). A pass runs along ``u``
(X for ``direction: x``, Y for ``direction: y``) at a fixed ``v`` across; tip
heights come from the exact drop cutter (:func:`compensate`).

Rules (accuracy in brackets):

* Stepover, pass by pass: the next pass is the farthest (never beyond the
  flat-ground stepover) for which the material left between the two balls,
  measured VERTICALLY above the design in each cross-section u = const, stays
  <= 0.95 * scallop. The bound is computed from the actual ball centres of both
  passes on a grid along u (1 mm or R/2) at the exact cusp and 7 points between
  the passes, so it holds on steep walls (on a plane of slope angle theta across
  the passes the vertical cusp is (R - sqrt(R^2 - (s / (2 cos theta))^2)) / cos theta).
  It ignores the extra material removed by neighbouring ball positions along the
  pass, so it is an upper bound of the material left.
* Spacing along a pass: segments are halved until the exact path at each
  segment's midpoint is within tolerance/2 of the chord; then nodes are dropped
  while every evaluated point between the surviving nodes stays within
  tolerance/2 of the chord.
* Air: portions where the tip is at or above the top face (touching nothing) are
  left out; passes that cut nothing are dropped. Along u a pass reaches beyond the
  stock to mill the edge from the side, at most 7/8 R out (at R the tip height
  has a vertical tangent that no chord follows within the tolerance); positions
  beyond the stock whose ball touches only the top face mill nothing and are
  dropped. Across, the first and
  last passes run along the footprint edges v = 0 and v = W.
* Links: between runs less than max(4 R, 4 stepover) apart: up to a local
  clearance (1 mm above the highest material along the straight link, checked
  with :func:`compensate`), across, plunge (feed moves); otherwise retract to
  safe_z, rapid, rapid down to the clearance above the top face, plunge.
  Rapids only move vertically out of a drop-cutter position, at safe_z, or above
  the top face.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import SpecError
from ..tolerances import DEFAULT, Tolerances
from .compensate import WorkSurface, compensate
from .path import CUT, PLUNGE, RAPID, Toolpath

AIR_EPS = 1e-7          # mm: a tip this close below the top face touches nothing worth a move
SCALLOP_SAFETY = 0.95   # stepover keeps the cross-section bound below this fraction of the scallop
CHORD_SAFETY = 0.5      # evaluated chord errors kept below this fraction of the tolerance
LINK_CLEARANCE = 1.0    # mm above material for short links and approaches (<= safe_height)


def flat_stepover(R: float, scallop: float) -> float:
    """Stepover leaving cusps of height ``scallop`` on flat ground, mm (exact)."""
    if scallop >= R:
        return 2.0 * R
    return 2.0 * math.sqrt(2.0 * R * scallop - scallop * scallop)


def tilted_plane_cusp(R: float, s: float, theta: float) -> float:
    """Vertical cusp height between two balls of radius R on a plane of slope angle
    ``theta`` across passes ``s`` apart horizontally, mm (closed form)."""
    half = s / (2.0 * math.cos(theta))
    return (R - math.sqrt(R * R - half * half)) / math.cos(theta)


class _Frame:
    """Pass coordinates (u along, v across) <-> work (X, Y)."""

    def __init__(self, direction: str, L: float, W: float):
        self.direction = direction
        self.Lu, self.Lv = (L, W) if direction == "x" else (W, L)

    def xy(self, u, v):
        return (u, v) if self.direction == "x" else (v, u)


def _profile(ws, fr, R, u, v, info=False):
    X, Y = fr.xy(*np.broadcast_arrays(np.asarray(u, float), np.asarray(v, float)))
    return compensate(ws, X, Y, R, return_info=info)


def _hermite(ug, Z, dZ, uf):
    """Cubic Hermite interpolation of the pass profile (exact values and slopes at
    the nodes ug) at uf; +inf outside the finite nodes."""
    i = np.clip(np.searchsorted(ug, uf, side="right") - 1, 0, len(ug) - 2)
    h = ug[i + 1] - ug[i]
    t = (uf - ug[i]) / h
    t2, t3 = t * t, t * t * t
    with np.errstate(invalid="ignore"):
        z = ((2 * t3 - 3 * t2 + 1) * Z[i] + (t3 - 2 * t2 + t) * h * dZ[i]
             + (-2 * t3 + 3 * t2) * Z[i + 1] + (t3 - t2) * h * dZ[i + 1])
    return np.where(np.isfinite(z), z, np.inf)


class _Pass:
    """One pass: v, exact tip heights Z and slopes dZ/du at the grid ug, the nodes
    kept, and the profile on a fine grid uf (Hermite; +inf where not machined)."""

    def __init__(self, fr, R, ug, uf, v, X, Y, Z, ci, depth_lim=math.inf, contact_top=None):
        pu = ci.contact_x if fr.direction == "x" else ci.contact_y
        d2 = (ci.contact_x - X) ** 2 + (ci.contact_y - Y) ** 2
        with np.errstate(all="ignore"):
            dZ = np.clip(np.nan_to_num((pu - ug) / np.sqrt(np.maximum(R * R - d2, 0.0))), -20, 20)
        self.v, self.Z, self.dZ, self.bridged = v, Z, dZ, ci.bridged
        # the contact curve where it crosses each cross-section u (contacts lie up to
        # R along the pass from their ball's centre on steep ground)
        cv = ci.contact_y if fr.direction == "x" else ci.contact_x
        ok = np.isfinite(pu) & np.isfinite(cv)
        if ok.any():
            o = np.argsort(pu[ok], kind="stable")
            self.cv = np.interp(ug, pu[ok][o], cv[ok][o])
        else:
            self.cv = np.full_like(ug, v)
        self.keep = _trim_outside(ug, Z, fr.Lu, depth_lim, contact_top)
        k = np.nonzero(self.keep)[0]
        f = _hermite(ug, Z, dZ, uf)
        self.fine = np.where((uf >= ug[k[0]]) & (uf <= ug[k[-1]]), f, np.inf) if k.size \
            else np.full_like(uf, np.inf)


def _passes(ws, fr, R, ug, uf, vlist, depth_lim):
    """Several passes at once (one vectorized compensation call)."""
    vv = np.asarray(vlist, float)[:, None] + 0 * ug[None, :]
    uu = np.broadcast_to(ug, vv.shape)
    X, Y = fr.xy(uu, vv)
    Z, ci = compensate(ws, X, Y, R, return_info=True)
    # the ball touches the stock only on its top face (contact at or above it)
    top = ws.H(np.nan_to_num(ci.contact_x), np.nan_to_num(ci.contact_y)) >= -AIR_EPS
    top &= np.isfinite(ci.contact_x)
    out = []
    for k, v in enumerate(vlist):
        row = type(ci)(ci.contact_x[k], ci.contact_y[k], ci.kind[k], ci.bridged[k])
        out.append(_Pass(fr, R, ug, uf, float(v), X[k], Y[k], Z[k], row, depth_lim, top[k]))
    return out


def sweep_material(ws, fr, R, uq, vs, cutters, uf, threshold=0.0):
    """Upper bound of the material left vertically above the design at the points
    (uq, vs) (mm; vs (m, nq) across, uq (nq,) along) after the passes ``cutters``
    (list of :class:`_Pass`). Each point is cut by the lowest of the balls at the
    fine positions uf of those passes: a discrete subset of the continuous sweep,
    so the bound is conservative (by at most (du/4)^2 / (8 R) along steep slopes).
    Where a first bound from the balls at the same u alone is <= ``threshold`` it
    is returned as is (the caller needs no better). Returns (m, nq) mm."""
    df = uf[1] - uf[0]
    K = int(math.ceil(R / df))
    j0 = np.clip(np.rint((uq - uf[0]) / df).astype(int), 0, len(uf) - 1)
    X, Y = fr.xy(np.broadcast_to(uq, vs.shape), vs)
    design = np.minimum(ws.H(X, Y), 0.0)

    def bound(cols, offsets):
        """Material at the columns ``cols`` using the balls at fine offsets."""
        J = np.clip(j0[cols, None] + offsets[None, :], 0, len(uf) - 1)
        du2 = (uq[cols, None] - uf[J]) ** 2
        v = vs[:, cols]
        cut = np.full(v.shape, np.inf)
        for p in cutters:
            dv2 = (v - p.v) ** 2
            r2 = R * R - du2[None, :, :] - dv2[:, :, None]
            with np.errstate(invalid="ignore"):
                b = (p.fine[J] + R)[None, :, :] - np.sqrt(r2)
            cut = np.minimum(cut, np.where(r2 >= 0, b, np.inf).min(axis=2))
        return np.minimum(cut, 0.0) - design[:, cols]

    # stage 1: balls at the same u only (fewer balls: a higher, still valid bound)
    all_cols = np.arange(len(uq))
    ml = bound(all_cols, np.zeros(1, int))
    # stage 2: the whole sweep within R along the pass, where stage 1 is not enough
    hot = np.nonzero((ml > threshold).any(axis=0))[0]
    if hot.size:
        ml[:, hot] = bound(hot, np.arange(-K, K + 1))
    return ml


def _between(lo, hi, Lv, n=9):
    """(n, nq) sample points across from lo to hi per position, clipped to [0, Lv]."""
    a, b = np.minimum(lo, hi), np.maximum(lo, hi)
    a, b = np.clip(a, 0.0, Lv), np.clip(b, 0.0, Lv)
    w = np.linspace(0.0, 1.0, n)[:, None]
    return a[None, :] + (b - a)[None, :] * w


def _u_grid(fr, R):
    du = min(1.0, R / 2.0)
    n_in = max(2, int(math.ceil(fr.Lu / du)) + 1)
    side = np.linspace(0.0, R, 9)
    return np.concatenate([-side[:0:-1], np.linspace(0.0, fr.Lu, n_in), fr.Lu + side[1:]])


def _trim_outside(ug, Z, Lu, depth_lim, contact_top=None):
    """Nodes kept along u: all inside the footprint; outside, while the ball still
    overlaps the stock (within R of the edge: it mills the edge from the side) and
    the tip stays within the depth limit. ``contact_top`` (bool per node): the ball
    touches the stock only on its top face; such nodes beyond the stock mill nothing,
    and they are dropped from the outer end inward (the kept nodes stay contiguous)."""
    inside = (ug >= 0) & (ug <= Lu)
    # not the nodes a whole radius out: there the ball touches the edge with its equator
    # and the tip height has a vertical tangent (Z = H_edge + sqrt(R^2 - u^2) - R) that no
    # chord of the program's resolution follows within the tolerance (it gouged the edge
    # by 6-7 um); the next node in, 7/8 R out, has a slope below 2
    reach = np.maximum(-ug, ug - Lu) < (1.0 - 1e-9) * np.max(np.maximum(-ug, ug - Lu))
    keep = inside | (reach & np.isfinite(Z) & (Z >= -depth_lim))
    if contact_top is not None:
        n = len(ug)
        i = 0
        while i < n and not inside[i] and (contact_top[i] or not keep[i]):
            keep[i] = False
            i += 1
        i = n - 1
        while i >= 0 and not inside[i] and (contact_top[i] or not keep[i]):
            keep[i] = False
            i -= 1
    return keep


def plan_toolpath(spec, surface, tol: Tolerances = DEFAULT) -> Toolpath:
    """Plan the finishing raster (and roughing when ``machining.stepdown`` is set).

    spec:    validated spec (tool, stock, machining sections)
    surface: :class:`fabkit.surface.Surface` of the spec
    Returns a :class:`Toolpath` (tip positions, work mm). Raises SpecError when the
    pass or point count would exceed the guards in ``tol`` or the tip would go
    deeper than ``stock.depth_limit`` / ``tool.reach``.
    """
    m = spec.machining
    R = 0.5 * float(spec.tool.diameter)
    scallop, tolerance = float(m.scallop), float(m.tolerance)
    ws = WorkSurface(surface)
    fr = _Frame(m.direction, ws.L, ws.W)
    safe_z = float(m.safe_height)
    clr = min(LINK_CLEARANCE, safe_z)
    s_flat = flat_stepover(R, SCALLOP_SAFETY * scallop)

    # -- guards before allocating ---------------------------------------------
    n_pass_est = int(math.ceil(fr.Lv / s_flat)) + 1
    if n_pass_est > tol.max_passes:
        raise SpecError(f"needs about {n_pass_est} passes (limit {tol.max_passes}); "
                        "raise the scallop", file=spec.path, key="machining.scallop")
    ug = _u_grid(fr, R)
    bend = math.sqrt(8.0 * CHORD_SAFETY * tolerance * R)   # spacing on an arc of radius R
    n_pts_est = n_pass_est * max(len(ug), (fr.Lu + 2 * R) / bend)
    if n_pts_est > tol.max_program_points:
        raise SpecError(f"needs about {n_pts_est:.3g} program points (limit "
                        f"{tol.max_program_points}); raise the tolerance or the scallop",
                        file=spec.path, key="machining.tolerance")

    # -- passes across, pass by pass (slope-aware stepover) -------------------
    inside_u = (ug >= 0) & (ug <= fr.Lu)
    uq = ug[inside_u]
    uf = np.linspace(ug[0], ug[-1], 4 * (len(ug) - 1) + 1)
    target = SCALLOP_SAFETY * scallop
    Lv = fr.Lv
    dl = min(float(spec.stock.depth_limit), float(spec.tool.reach))

    def material(pa, pb, older):
        """Per u, worst material between the contact lines of pa and pb (the region
        those two passes finish), cut by pa, pb and the passes before."""
        vs = _between(pa.cv[inside_u], pb.cv[inside_u], Lv)
        ml = sweep_material(ws, fr, R, uq, vs, [pb, pa] + older, uf, 0.5 * target)
        return np.nan_to_num(ml, nan=np.inf).max(axis=0)

    def edge_material(p, older, edge):
        vs = _between(p.cv[inside_u], np.full(uq.shape, edge), Lv)
        return np.nan_to_num(sweep_material(ws, fr, R, uq, vs, [p] + older, uf, 0.5 * target),
                             nan=np.inf).max(axis=0)

    def make(vlist):
        return _passes(ws, fr, R, ug, uf, vlist, dl)

    # first pass: on the edge v = 0, or beyond it until the edge is milled
    v0 = 0.0
    while True:
        p0 = make([v0])[0]
        if edge_material(p0, [], 0.0).max(initial=0.0) <= target or v0 <= -R:
            break
        v0 = max(v0 - R / 8, -R)
    passes = [p0]
    s_next = s_flat
    unreachable = (0.0, 0.0, 0.0)        # (mm above the design, u, v): material no stepover removes
    ahead = []                           # passes computed speculatively at the same stepover
    while True:
        pa = passes[-1]
        older = passes[-2:-1]
        if pa.v >= Lv and edge_material(pa, older, Lv).max(initial=0.0) <= target:
            break
        if pa.v >= Lv + R:
            break
        vmax = Lv if pa.v < Lv else Lv + R
        allowed = np.full(uq.shape, target)

        def check(pb):
            mlu = material(pa, pb, older)
            if pb.v >= Lv:
                mlu = np.maximum(mlu, edge_material(pb, [pa] + older, Lv))
            return float((mlu / allowed).max(initial=0.0))

        pb = None
        if ahead and ahead[0].v > pa.v:
            cand = ahead.pop(0)
            ratio = check(cand)
            if ratio <= 1.0:
                pb = cand
        if pb is None:
            ahead = []
            s = min(s_next, s_flat)
            # this stepover and two more passes at it, in one call (cheap: the cost
            # of a compensation call is mostly fixed)
            vl = sorted({min(pa.v + k * s, vmax) for k in (1, 2, 3)})
            cands = make(vl)
            ratio = check(cands[0])
            if ratio <= 1.0:
                pb, ahead = cands[0], cands[1:]
        floor_done = False
        tries = 0
        while pb is None:
            tries += 1
            if tries > 30:
                raise SpecError("cannot reach the scallop with any stepover (surface too steep "
                                "or the tool too large)", file=spec.path, key="machining.scallop")
            if ratio > 1.0 and not floor_done:
                # material a pass right beside this one leaves too (the ball cannot
                # reach it: a concave region tighter than the tool); no stepover
                # removes it, so allow it (reported)
                floor_done = True
                pt = make([pa.v + 0.02 * s_flat])[0]
                floor = material(pa, pt, older)
                allowed = np.maximum(target, floor + 0.1 * target)
                if floor.max() > unreachable[0]:
                    i = int(np.argmax(floor))
                    unreachable = (float(floor[i]), float(uq[i]), pa.v)
                if (floor > target).any():
                    ratio = check(cands[0])
                    if ratio <= 1.0:
                        pb = cands[0]
                        break
            s0 = cands[0].v - pa.v
            f = min(0.97, max(0.3, 0.99 / math.sqrt(ratio)))
            trial = [pa.v + s0 * f * g for g in (1.0, 0.85, 0.7, 0.55)]
            cands = make(trial)
            for c in cands:
                r = check(c)
                if r <= 1.0:
                    pb, ratio = c, r
                    break
            else:
                cands, ratio = cands[-1:], r
        passes.append(pb)
        if len(passes) > tol.max_passes:
            raise SpecError(f"needs more than {tol.max_passes} passes; raise the scallop",
                            file=spec.path, key="machining.scallop")
        # predict the next stepover from this one's margin (cusp ~ s^2)
        s_next = max(pb.v - pa.v, 0.05 * s_flat) * min(1.15, 0.97 / math.sqrt(max(ratio, 1e-12)))
    V = np.array([p.v for p in passes])
    Z = np.vstack([p.Z for p in passes])
    bridged = np.vstack([p.bridged for p in passes])
    keep = np.vstack([p.keep for p in passes])

    # -- refinement along each pass (all passes at once) -----------------------
    etol = CHORD_SAFETY * tolerance
    P = len(V)
    pid0, j0 = np.nonzero(keep)
    dZ = np.vstack([p.dZ for p in passes])
    node_p, node_u, node_z, node_d = pid0, ug[j0], Z[pid0, j0], dZ[pid0, j0]
    # segments between consecutive kept nodes of the same pass
    same = node_p[1:] == node_p[:-1]
    sp, sa, sb = node_p[:-1][same], np.nonzero(same)[0], np.nonzero(same)[0] + 1
    seg = (sp, node_u[sa], node_z[sa], node_d[sa], node_u[sb], node_z[sb], node_d[sb])
    samp_p, samp_u, samp_z, samp_node = [node_p], [node_u], [node_z], [np.ones(len(node_p), bool)]
    total = len(node_p)
    th = np.array([0.1, 0.25, 0.75, 0.9])
    for _ in range(40):
        p, ua, za, da, ub, zb, db = seg
        if p.size == 0:
            break
        um = 0.5 * (ua + ub)
        X, Y = fr.xy(um, V[p])
        zm, ci = compensate(ws, X, Y, R, return_info=True)
        pu = ci.contact_x if fr.direction == "x" else ci.contact_y
        with np.errstate(all="ignore"):
            q = np.sqrt(np.maximum(R * R - (ci.contact_x - X) ** 2 - (ci.contact_y - Y) ** 2, 0.0))
            dm = np.clip(np.nan_to_num((pu - um) / q), -20, 20)
        err = np.abs(zm - 0.5 * (za + zb))
        # and the deviation of the Hermite cubic (exact end values and slopes) from the
        # chord: catches a sharp rise between a midpoint and an end
        h = (ub - ua)[:, None]
        t = th[None, :]
        herm = ((2 * t**3 - 3 * t**2 + 1) * za[:, None] + (t**3 - 2 * t**2 + t) * h * da[:, None]
                + (-2 * t**3 + 3 * t**2) * zb[:, None] + (t**3 - t**2) * h * db[:, None])
        chord = za[:, None] + t * (zb - za)[:, None]
        err = np.maximum(err, np.nan_to_num(np.abs(herm - chord), nan=np.inf).max(axis=1))
        both_air = (za >= -AIR_EPS) & (zb >= -AIR_EPS) & (zm >= -AIR_EPS)
        bad = (err > etol) & (ub - ua > 1e-4) & ~both_air
        samp_p.append(p)
        samp_u.append(um)
        samp_z.append(zm)
        samp_node.append(bad)
        total += p.size
        if total > 4 * tol.max_program_points:
            raise SpecError("too many program points; raise the tolerance", file=spec.path,
                            key="machining.tolerance")
        b = bad
        seg = (np.concatenate([p[b], p[b]]), np.concatenate([ua[b], um[b]]),
               np.concatenate([za[b], zm[b]]), np.concatenate([da[b], dm[b]]),
               np.concatenate([um[b], ub[b]]), np.concatenate([zm[b], zb[b]]),
               np.concatenate([dm[b], db[b]]))
    sp_ = np.concatenate(samp_p)
    su = np.concatenate(samp_u)
    sz = np.concatenate(samp_z)
    sn = np.concatenate(samp_node)
    order = np.lexsort((su, sp_))
    sp_, su, sz, sn = sp_[order], su[order], sz[order], sn[order]
    nodes = _simplify(sp_, su, sz, sn, etol)

    # -- runs of cut segments per pass ----------------------------------------
    runs = _runs(sp_, su, sz, nodes)          # list per pass of lists of (k, 2) [u, z] arrays
    passes_cut = [p for p in range(P) if runs[p]]
    Vc = V[passes_cut]
    steps = np.diff(V)
    depth_lim = min(float(spec.stock.depth_limit), float(spec.tool.reach))

    # -- roughing (optional) then finishing, ordered, with links ---------------
    pts, kinds = [], []
    order_runs = []
    forward_climb = fr.direction == "x"     # M3: material on the left of the feed
    for k, p in enumerate(passes_cut):
        rr = runs[p]
        if m.pattern == "zigzag":
            fwd = k % 2 == 0
        else:
            fwd = forward_climb if m.pattern == "climb" else not forward_climb
        if not fwd:
            rr = [r[::-1] for r in rr[::-1]]
        for r in rr:
            X, Y = fr.xy(r[:, 0], np.full(len(r), V[p]))
            order_runs.append((p, np.column_stack([X, Y, r[:, 1]])))
    rough = _roughing(spec, ws, fr, R, V, runs, passes_cut, depth_lim) \
        if getattr(m, "stepdown", None) else []
    all_runs = rough + [(("f", p), r) for p, r in order_runs]
    link_max = max(4 * R, 4 * s_flat)
    one_way = m.pattern != "zigzag"
    # local link heights, all links at once: 1 mm above the highest material along
    # the straight link (drop cutter every R/4), None where a full retract is needed
    zlink = [None] * len(all_runs)
    idx, TX, TY, owner = [], [], [], []
    for i in range(1, len(all_runs)):
        (pkey, pr), (key, r) = all_runs[i - 1], all_runs[i]
        a, b = pr[-1], r[0]
        d = math.hypot(b[0] - a[0], b[1] - a[1])
        if d <= link_max and not (one_way and pkey != key) and pkey[0] == key[0] == "f":
            n = max(2, int(math.ceil(d / (R / 4))) + 1)
            t = np.linspace(0.0, 1.0, n)
            TX.append(a[0] + t * (b[0] - a[0]))
            TY.append(a[1] + t * (b[1] - a[1]))
            owner.append(np.full(n, len(idx)))
            idx.append(i)
    if idx:
        zc = compensate(ws, np.concatenate(TX), np.concatenate(TY), R)
        high = np.full(len(idx), -np.inf)
        np.maximum.at(high, np.concatenate(owner), zc)
        for j, i in enumerate(idx):
            a, b = all_runs[i - 1][1][-1], all_runs[i][1][0]
            zl = max(a[2], b[2], float(high[j])) + clr
            zlink[i] = zl if zl <= safe_z else None
    prev = None
    for i, (key, r) in enumerate(all_runs):
        if prev is None:
            _approach(pts, kinds, r[0], safe_z, clr, first=True)
        else:
            a, b = prev[1], r[0]
            zl = zlink[i]
            if zl is not None:
                pts += [(a[0], a[1], zl), (b[0], b[1], zl), tuple(b)]
                kinds += [CUT, CUT, PLUNGE]
            else:
                pts += [(a[0], a[1], safe_z)]
                kinds += [RAPID]
                _approach(pts, kinds, b, safe_z, clr)
        pts += [tuple(q) for q in r[1:]]
        kinds += [CUT] * (len(r) - 1)
        prev = (key, r[-1])
    if prev is not None:
        a = prev[1]
        pts.append((a[0], a[1], safe_z))
        kinds.append(RAPID)
    points = np.array(pts, float).reshape(-1, 3)
    kinds = np.array(kinds, np.int8)
    if len(points) > tol.max_program_points:
        raise SpecError(f"{len(points)} program points (limit {tol.max_program_points}); raise "
                        "the tolerance", file=spec.path, key="machining.tolerance")
    zmin = float(points[:, 2].min()) if len(points) else 0.0
    for key, lim in (("stock.depth_limit", float(spec.stock.depth_limit)),
                     ("tool.reach", float(spec.tool.reach))):
        if -zmin > lim + 1e-9:
            raise SpecError(f"the tool tip goes {-zmin:.3f} mm deep, {-zmin - lim:.3f} mm more "
                            f"than the limit {lim:g} mm", file=spec.path, key=key)

    seglen = np.linalg.norm(np.diff(points, axis=0), axis=1) if len(points) > 1 else np.zeros(0)
    feed = kinds[1:] != RAPID
    nb = int(bridged[keep].sum())
    info = {
        "passes": len(passes_cut),
        "stepover_max": float(steps.max()) if steps.size else 0.0,
        "stepover_min": float(steps.min()) if steps.size else 0.0,
        "stepover_flat": s_flat,
        "points": int(len(points)),
        "cutting_length_mm": float(seglen[feed].sum()),
        "rapid_length_mm": float(seglen[~feed].sum()),
        "deepest_tip_mm": zmin,
        "roughing_runs": len(rough),
        "bridged_positions": nb,
        "pass_positions": [float(v) for v in Vc],
    }
    if unreachable[0] > scallop:
        X, Y = fr.xy(unreachable[1], unreachable[2])
        info["scallop_bound_relaxed_mm"] = unreachable[0]
        info["scallop_warning"] = (
            f"near X={float(X):.2f}, Y={float(Y):.2f} mm even passes right beside each other "
            f"leave up to {unreachable[0]:.3f} mm by the planner's conservative bound (a design "
            "narrower than the tool, or a loose bound there); the stepover was relaxed there")
    if nb:
        pi, ji = np.nonzero(bridged & keep)
        X, Y = fr.xy(ug[ji[0]], V[pi[0]])
        info["concave_warning"] = (f"{nb} tool positions span a concave region tighter than the "
                                   f"tool (first at X={float(X):.2f}, Y={float(Y):.2f} mm): the "
                                   "tool cannot reach the bottom there")
    return Toolpath(points, kinds, tool_radius=R, safe_z=safe_z, passes=len(passes_cut),
                    stepover=info["stepover_max"], stepover_min=info["stepover_min"], info=info)


def _approach(pts, kinds, b, safe_z, clr, first=False):
    """Rapid above b at safe_z, rapid down to clr above the top face, plunge to b."""
    pts += [(b[0], b[1], safe_z), (b[0], b[1], max(clr, b[2]))]
    kinds += [RAPID, RAPID]
    if b[2] < max(clr, b[2]):
        pts.append(tuple(b))
        kinds.append(PLUNGE)


def _simplify(sp, su, sz, sn, etol, rounds=64):
    """Drop nodes (sn) while every sample between the surviving neighbours stays
    within etol of their chord. Nodes flanked by air (tip at/above the top face)
    or at pass ends stay. Returns the boolean node mask over the samples."""
    nodes = sn.copy()
    air = sz >= -AIR_EPS
    idle = 0
    for r in range(rounds):
        ni = np.nonzero(nodes)[0]
        if ni.size < 3:
            break
        npass = sp[ni]
        interior = np.zeros(ni.size, bool)
        interior[1:-1] = (npass[1:-1] == npass[:-2]) & (npass[1:-1] == npass[2:])
        # node k removable if the chord (k-1, k+1) covers all samples in between
        seg_of = np.searchsorted(ni, np.arange(len(su)), side="right") - 1   # node at left
        seg_of = np.clip(seg_of, 0, ni.size - 1)
        k_left = np.clip(seg_of - 1, 0, ni.size - 1)
        k_right = np.clip(seg_of + 1, 0, ni.size - 1)
        # samples in segment j (between node j and j+1), chord of candidate j (j-1 .. j+1)
        # and of candidate j+1 (j .. j+2)
        errA = _chord_err(su, sz, su[ni[k_left]], sz[ni[k_left]], su[ni[k_right]], sz[ni[k_right]])
        k_r2 = np.clip(seg_of + 2, 0, ni.size - 1)
        errB = _chord_err(su, sz, su[ni[seg_of]], sz[ni[seg_of]], su[ni[k_r2]], sz[ni[k_r2]])
        # a sample at node j (itself) belongs to segment j and to candidate j's range only
        isn = nodes
        errB = np.where(isn, 0.0, errB)
        worst = np.zeros(ni.size)
        np.maximum.at(worst, seg_of, errA)                       # candidate j: its segment j
        np.maximum.at(worst, np.clip(seg_of + 1, 0, ni.size - 1), errB)  # candidate j+1
        airseg = np.zeros(ni.size, bool)                         # segment j touches air
        np.logical_or.at(airseg, seg_of, air)
        airseg |= np.r_[air[ni][1:], True]
        ok = interior & (worst <= etol)
        ok[1:] &= ~airseg[:-1]
        ok &= ~airseg
        ok &= np.arange(ni.size) % 2 == r % 2
        if ok.any():
            nodes[ni[ok]] = False
            idle = 0
        else:
            idle += 1
            if idle >= 2:
                break
    return nodes


def _chord_err(u, z, ua, za, ub, zb):
    with np.errstate(all="ignore"):
        t = np.where(ub > ua, (u - ua) / (ub - ua), 0.0)
    return np.abs(z - (za + t * (zb - za)))


def _runs(sp, su, sz, nodes):
    """Per pass, the runs of consecutive cut segments as (k, 2) arrays of [u, z]."""
    P = int(sp.max()) + 1 if sp.size else 0
    out = [[] for _ in range(P)]
    ni = np.nonzero(nodes)[0]
    air = sz >= -AIR_EPS
    # a segment (node j .. j+1, same pass) cuts if any sample in [j, j+1] is below the top
    seg_of = np.clip(np.searchsorted(ni, np.arange(len(su)), side="right") - 1, 0, max(ni.size - 1, 0))
    cuts = np.zeros(ni.size, bool)
    np.logical_or.at(cuts, seg_of, ~air)
    cuts[:-1] |= ~air[ni[1:]]
    samepass = np.r_[sp[ni][1:] == sp[ni][:-1], False]
    cuts &= samepass
    j = 0
    while j < ni.size:
        if not cuts[j]:
            j += 1
            continue
        k = j
        while k < ni.size and cuts[k]:
            k += 1
        idx = ni[j:k + 1]
        out[int(sp[idx[0]])].append(np.column_stack([su[idx], sz[idx]]))
        j = k + 1
    return out


def _roughing(spec, ws, fr, R, V, runs, passes_cut, depth_lim):
    """Z-level roughing runs: levels every ``machining.stepdown`` below the top face,
    on finishing passes at most R apart, tip at max(level, finish + leave) (never
    below the finish path plus the stock to leave: the finish path's chord error is
    within the tolerance, and the max of a level and a chord only lies higher).
    Only where the level removes material the level above left. Links between
    roughing runs retract to safe_z. Returns [(key, (k, 3) points)] in cutting order."""
    m = spec.machining
    step, leave = float(m.stepdown), float(m.leave)
    zmin = min((float(r[:, 1].min()) for p in passes_cut for r in runs[p]), default=0.0)
    bottom = zmin + leave
    if bottom >= 0:
        return []
    nlev = int(math.ceil(-bottom / step))
    # finishing passes at most R apart
    sel, last = [], -math.inf
    for p in passes_cut:
        if V[p] - last >= R or p == passes_cut[-1]:
            sel.append(p)
            last = V[p]
    out = []
    for k in range(1, nlev + 1):
        level, prev = max(-k * step, bottom), -(k - 1) * step
        for n, p in enumerate(sel):
            pieces = []
            for r in runs[p]:
                z = np.maximum(level, r[:, 1] + leave)
                act = z < prev - AIR_EPS
                # keep nodes that are active or next to an active one
                near = act | np.r_[act[1:], False] | np.r_[False, act[:-1]]
                i = 0
                while i < len(r):
                    if not near[i]:
                        i += 1
                        continue
                    j = i
                    while j < len(r) and near[j]:
                        j += 1
                    if j - i >= 2:
                        X, Y = fr.xy(r[i:j, 0], np.full(j - i, V[p]))
                        pieces.append(np.column_stack([X, Y, z[i:j]]))
                    i = j
            if n % 2:
                pieces = [q[::-1] for q in pieces[::-1]]
            out += [(("r", k, p), q) for q in pieces]
    return out
