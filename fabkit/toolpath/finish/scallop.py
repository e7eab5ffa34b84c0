"""The scallop bound: how much material two ball-end passes leave between them.

Work coordinates, mm; a pass runs along ``u`` at a fixed ``v`` across (see
:class:`fabkit.toolpath.finish.passes.Frame`). The closed forms first: the flat-ground
stepover (:func:`flat_stepover`) and the cusp on a tilted plane
(:func:`tilted_plane_cusp`). Then the bound the pass placement
(:mod:`fabkit.toolpath.finish.passes`) spaces every pass by, on any ground
(:func:`sweep_material`): an upper bound of the material left above the design at
sample points, from the actual ball centres of the passes, measured along the
design's normal (:func:`slope_scale`) or vertically.

The next pass is the farthest (never beyond the
flat-ground stepover) for which the material left between the two balls, in each
cross-section u = const, stays <= 0.95 * scallop, measured along the design's
normal (``machining.scallop_measure: normal``, the default: the vertical height
times 1 / sqrt(1 + |grad H|^2)) or vertically. The bound is computed from the
actual ball centres of both passes on a grid along u (1 mm or R/2) at 9 points
between their contact lines (refined around the largest), balls within R along the
pass included, so it holds on steep walls (on a plane of slope angle theta across
the passes the cusp is R - sqrt(R^2 - (s / (2 cos theta))^2) along the normal,
1 / cos theta times that vertically) and on slopes along the pass (the contact
lies up to R ahead of the ball; the flat stepover holds for the normal measure).
"""

from __future__ import annotations

import math

import numpy as np

from .kernels import enabled

SCALLOP_SAFETY = 0.95   # stepover keeps the cross-section bound below this fraction of the scallop
STEEP_ALONG = 1.5       # the material bound's stage 3 runs where the slope along the pass exceeds this
EDGE_NODES = (0.95, 0.99)   # extra nodes along the passes beyond the edges, x R out (passes.u_grid)
GOLDEN_STEPS = 24       # stage 3: golden-section steps around the lowest of 65 balls within R


_KERNELS: list = []     # the compiled module once imported (or None: numba missing)


def _kernels():
    """The compiled loops (:mod:`fabkit.toolpath.finish.scallop_kernels`), or None
    (``FABKIT_NO_KERNELS=1``, numba missing): the numpy code below, the same bits."""
    if not enabled():
        return None
    if not _KERNELS:
        try:
            from . import scallop_kernels
        except ImportError:  # pragma: no cover - numba is a dependency
            scallop_kernels = None
        _KERNELS.append(scallop_kernels)
    return _KERNELS[0]


def flat_stepover(R: float, scallop: float) -> float:
    """Stepover leaving cusps of height ``scallop`` on flat ground, mm (exact)."""
    if scallop >= R:
        return 2.0 * R
    return 2.0 * math.sqrt(2.0 * R * scallop - scallop * scallop)


def tilted_plane_cusp(R: float, s: float, theta: float, normal: bool = False) -> float:
    """Cusp height between two balls of radius R on a plane of slope angle ``theta``
    across passes ``s`` apart horizontally, mm (closed form): along the plane's normal
    (``normal``) or vertically (1 / cos theta times that)."""
    half = s / (2.0 * math.cos(theta))
    cusp = R - math.sqrt(R * R - half * half)
    return cusp if normal else cusp / math.cos(theta)


def hermite_profile(ug, Z, dZ, uf, kink=None, rows=None):
    """Cubic Hermite interpolation of the pass profile (exact values and slopes at
    the nodes ug) at uf; +inf outside the finite nodes.

    ``kink`` (bool per node): the tip path has a kink there (the ball bridges a V
    crease or a valley tighter than itself: two contacts, the slope of either one
    side's); on the segments beside such a node the profile is not below the chord
    (the Hermite cubic with the other side's slope dips below the true path, by
    ~ h |dZ_left - dZ_right| / 7: 0.5 mm on a V crease of slope 3, and the material
    bounds would take the balls for lower than they are).

    ``rows``: Z, dZ, kink are stacked profiles (P, n) and ``rows`` (broadcastable to
    uf) picks each position's profile: several passes in one call.

    On a fixed pair of grids (both read-only arrays: the pass placement's nodes and fine
    grid) the segments and the cubic's weights are computed once (:func:`hermite_weights`);
    the same products and sums follow, so the same bits."""
    if rows is None:
        i, t, w0, w1, w2, w3 = hermite_weights(ug, uf)
        ix, ix1 = i, i + 1
        with np.errstate(invalid="ignore"):
            z = w0 * Z[ix] + w1 * dZ[ix] + w2 * Z[ix1] + w3 * dZ[ix1]
            if kink is not None:
                k = kink[ix] | kink[ix1]
                z = np.where(k, np.fmax(z, Z[ix] + t * (Z[ix1] - Z[ix])), z)
        return np.where(np.isfinite(z), z, np.inf)
    i = np.clip(np.searchsorted(ug, uf, side="right") - 1, 0, len(ug) - 2)
    h = ug[i + 1] - ug[i]
    t = (uf - ug[i]) / h
    t2, t3 = t * t, t * t * t
    ix, ix1 = (rows, i), (rows, i + 1)
    with np.errstate(invalid="ignore"):
        z = ((2 * t3 - 3 * t2 + 1) * Z[ix] + (t3 - 2 * t2 + t) * h * dZ[ix]
             + (-2 * t3 + 3 * t2) * Z[ix1] + (t3 - t2) * h * dZ[ix1])
        if kink is not None:
            k = kink[ix] | kink[ix1]
            z = np.where(k, np.fmax(z, Z[ix] + t * (Z[ix1] - Z[ix])), z)
    return np.where(np.isfinite(z), z, np.inf)


_GRID_MEMO: dict = {}


def grid_memo(tag, arrays, make):
    """``make()``, kept per ``tag`` and the identity of ``arrays`` when they are all
    read-only numpy arrays (the pass placement's grids, fixed for its run: a kept value
    cannot go stale); computed on every call otherwise."""
    frozen = all(isinstance(a, np.ndarray) and not a.flags.writeable for a in arrays)
    if not frozen:
        return make()
    key = (tag, *map(id, arrays))
    hit = _GRID_MEMO.get(key)
    if hit is not None and all(x is a for x, a in zip(hit[0], arrays)):
        return hit[1]
    val = make()
    if len(_GRID_MEMO) > 32:
        _GRID_MEMO.clear()
    _GRID_MEMO[key] = (tuple(arrays), val)
    return val


def hermite_weights(ug, uf):
    """(i, t, w0, w1, w2, w3) of :func:`hermite_profile` at uf between the nodes ug: the
    segment i of each point, its parameter t and the weights of Z[i], dZ[i], Z[i + 1] and
    dZ[i + 1] (those of h * dZ computed as the profile multiplies them, (w * h) * dZ).
    Kept per pair of read-only grids (:func:`grid_memo`)."""
    def make():
        i = np.clip(np.searchsorted(ug, uf, side="right") - 1, 0, len(ug) - 2)
        h = ug[i + 1] - ug[i]
        t = (uf - ug[i]) / h
        t2, t3 = t * t, t * t * t
        with np.errstate(invalid="ignore"):
            return (i, t, 2 * t3 - 3 * t2 + 1, (t3 - 2 * t2 + t) * h, -2 * t3 + 3 * t2, (t3 - t2) * h)

    return grid_memo("hermite", (ug, uf), make)


def node_index(ug, uf):
    """Per point of uf, the index of the node of ug equal to it, else -1 (so that
    ``np.isin(uf, ug[m])`` is ``(j >= 0) & m[max(j, 0)]``: the nodes are distinct).
    Kept per pair of read-only grids (:func:`grid_memo`)."""
    def make():
        if not len(ug):
            return np.full(uf.shape, -1)
        j = np.clip(np.searchsorted(ug, uf), 0, len(ug) - 1)
        return np.where(ug[j] == uf, j, -1)

    return grid_memo("nodes", (ug, uf), make)


def stack_profiles(cutters):
    """(Z, dZ, lo, hi, kink) of several passes stacked along a leading axis."""
    return (np.vstack([p.Z for p in cutters]), np.vstack([p.dZ for p in cutters]),
            np.array([p._lo for p in cutters]), np.array([p._hi for p in cutters]),
            np.vstack([p.bridged for p in cutters]))


def slope_scale(ws, X, Y, normal: bool = True):
    """(design clipped at the top face, scale): the factor that turns material measured
    vertically above the design at (X, Y) into material measured along the design's
    normal, 1 / sqrt(1 + |grad H|^2) (1 on the top face and where ``normal`` is False).
    Exact for a cut surface parallel to the design (a cusp's crest above a plane), to
    first order elsewhere."""
    if not normal:
        H = ws.H(X, Y)
        return np.minimum(H, 0.0), np.ones_like(H)
    H, hx, hy = ws.all(X, Y)[:3]
    with np.errstate(all="ignore"):
        g = np.where(np.isfinite(H) & (H < 0), hx * hx + hy * hy, 0.0)
        scale = 1.0 / np.sqrt(1.0 + np.where(g < np.inf, g, 0.0))     # g >= 0: NaN, inf -> 0
    return np.minimum(H, 0.0), scale


def sweep_material(ws, fr, R, uq, vs, cutters, uf, threshold=0.0, chord=0.0, normal=False):
    """Upper bound of the material left above the design at the points (uq, vs)
    (``normal``: measured along the design's normal, else vertically; mm; vs (m, nq)
    across, uq (nq,) along) after the passes ``cutters``
    (list of :class:`fabkit.toolpath.finish.passes._Pass`). Each point is cut by the lowest of the balls at the
    fine positions uf of those passes: a discrete subset of the continuous sweep,
    so the bound is conservative (by at most (du/4)^2 / (8 R) along steep slopes).
    Where a first bound from the balls at the same u alone is <= ``threshold`` it
    is returned as is (the caller needs no better). On ground steep along the pass the
    lowest ball between the fine positions is found (stage 3); that bound follows the
    exact path, so the chords of the program (within ``chord`` mm of it) are added to
    it. Returns (m, nq) mm."""
    df = float(np.diff(uf).max())   # the even spacing (nodes beyond the edges added between)
    K = int(math.ceil(R / df)) + len(EDGE_NODES) + 1    # and the edge nodes between
    X, Y = fr.xy(np.broadcast_to(uq, vs.shape), vs)
    design, scale = slope_scale(ws, X, Y, normal)
    kern = _kernels()
    if kern is not None:
        # stages 1 and 2 compiled (scallop_kernels.sweep_balls: the same arithmetic)
        pv = np.array([p.v for p in cutters], dtype=float)
        ml = kern.sweep_balls(np.ascontiguousarray(uq, dtype=float), uf, np.ascontiguousarray(vs, dtype=float),
                              np.vstack([p.fine for p in cutters]), pv, float(R), K,
                              np.ascontiguousarray(design, dtype=float), np.ascontiguousarray(scale, dtype=float),
                              float(threshold))
    else:
        ml = _sweep_balls(R, uq, vs, cutters, uf, K, design, scale, threshold)
    return _rim_stage(ws, fr, R, uq, vs, cutters, threshold, chord, design, scale, ml, kern)


def _sweep_balls(R, uq, vs, cutters, uf, K, design, scale, threshold):
    """Stages 1 and 2 of :func:`sweep_material` in numpy (FABKIT_NO_KERNELS=1)."""
    j0 = np.clip(np.searchsorted(uf, uq), 0, len(uf) - 1)

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
        return (np.minimum(cut, 0.0) - design[:, cols]) * scale[:, cols]

    # stage 1: balls at the same u only (fewer balls: a higher, still valid bound)
    all_cols = np.arange(len(uq))
    ml = bound(all_cols, np.zeros(1, int))
    # stage 2: the whole sweep within R along the pass, where stage 1 is not enough
    hot = np.nonzero((ml > threshold).any(axis=0))[0]
    if hot.size:
        ml[:, hot] = bound(hot, np.arange(-K, K + 1))
    return ml


def _rim_stage(ws, fr, R, uq, vs, cutters, threshold, chord, design, scale, ml, kern):
    """Stage 3 of :func:`sweep_material` (compiled with ``kern``, else numpy): ml lowered
    where the ball's rim cuts on ground steep along the pass."""
    # stage 3: on ground steep along the pass the ball cuts a cross-section with its rim
    # (slope 8: 0.99 R ahead), where a step du between balls leaves ~ du^2 / (2 R cos^3)
    # (1.6 mm at the fine grid's 0.1 mm): the lowest ball between the fine positions,
    # per pass, by golden-section search along the pass
    hot = np.nonzero((ml > threshold + chord).any(axis=0))[0]
    if hot.size:
        # only where the design is steep along the pass (slope > STEEP_ALONG) near the
        # column: elsewhere the fine grid's error, <= df^2 (1 + slope^2)^1.5 / (8 R), is small
        uu = uq[hot][None, :] + np.array([-1.0, -0.5, 0.0, 0.5, 1.0])[:, None] * R
        Xs, Ys = fr.xy(uu, np.broadcast_to(vs[vs.shape[0] // 2, hot], uu.shape))
        d = ws.all(Xs, Ys)
        # (|slope| > STEEP_ALONG below the top face somewhere; NaN slopes count as 0)
        hot = hot[((np.abs(d[1] if fr.direction == "x" else d[2]) > STEEP_ALONG) & (d[0] < 0)).any(axis=0)]
    if hot.size and kern is not None:
        o = np.linspace(-R, R, 65)
        Zs, dZs, lo, hi, kink = stack_profiles(cutters)
        pv = np.array([p.v for p in cutters], dtype=float)
        cut = kern.rim_cut(np.ascontiguousarray(uq[hot], dtype=float), np.ascontiguousarray(vs[:, hot], dtype=float),
                           cutters[0]._ug, Zs, dZs, kink, lo.astype(float), hi.astype(float), pv, float(R), o,
                           float(o[1] - o[0]), 0.5 * (math.sqrt(5.0) - 1.0), GOLDEN_STEPS)
        ml[:, hot] = np.minimum(ml[:, hot],
                                (np.minimum(cut, 0.0) - design[:, hot] + chord) * scale[:, hot])
    elif hot.size:
        v = vs[:, hot][:, :, None]
        u0 = uq[hot][None, :, None]
        uf_nodes = cutters[0]._ug
        o = np.linspace(-R, R, 65)
        h = o[1] - o[0]
        # all cutters at once (leading axis): the same search per cutter, one array call
        Zs, dZs, lo, hi, kink = stack_profiles(cutters)
        cv = np.array([p.v for p in cutters])[:, None, None, None]
        dv2 = (v[None] - cv) ** 2
        pi = np.arange(len(cutters))[:, None, None, None]

        def ball(oo):
            """Lowest point above u0 of each cutter's ball at u0 + oo: the pass's tip
            profile (Hermite), +inf where it is not machined or beyond 7/8 R out."""
            r2 = R * R - oo * oo - dv2
            u = u0 + oo
            with np.errstate(invalid="ignore"):
                z = hermite_profile(uf_nodes, Zs, dZs, u, kink, rows=pi)
                z = np.where((u >= lo[pi]) & (u <= hi[pi]), z, np.inf)
                b = z + R - np.sqrt(r2)
            return np.where(r2 >= 0, b, np.inf)

        g = ball(o + 0 * dv2)
        j = np.argmin(g, axis=3)[..., None]
        a = np.take_along_axis(np.broadcast_to(o, g.shape), j, axis=3) - h
        b = a + 2 * h
        gr = 0.5 * (math.sqrt(5.0) - 1.0)
        c, d = b - gr * (b - a), a + gr * (b - a)
        gc, gd = ball(c), ball(d)
        for _ in range(GOLDEN_STEPS):
            lt = gc <= gd
            a, b = np.where(lt, a, c), np.where(lt, d, b)
            c, d = np.where(lt, b - gr * (b - a), d), np.where(lt, c, a + gr * (b - a))
            gn = ball(np.where(lt, c, d))
            gc, gd = np.where(lt, gn, gd), np.where(lt, gc, gn)
        best = np.minimum(np.min(g, axis=3), np.minimum(gc, gd)[..., 0])
        cut = best.min(axis=0)
        ml[:, hot] = np.minimum(ml[:, hot],
                                (np.minimum(cut, 0.0) - design[:, hot] + chord) * scale[:, hot])
    return ml


def between_rows(lo, hi, Lv, n=9):
    """(n, nq) sample points across from lo to hi per position, clipped to [0, Lv]."""
    a, b = np.minimum(lo, hi), np.maximum(lo, hi)
    a, b = np.clip(a, 0.0, Lv), np.clip(b, 0.0, Lv)
    w = np.linspace(0.0, 1.0, n)[:, None]
    return a[None, :] + (b - a)[None, :] * w
