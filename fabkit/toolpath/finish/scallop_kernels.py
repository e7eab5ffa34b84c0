"""Compiled loops of the material bound (:func:`fabkit.toolpath.finish.scallop.sweep_material`).

Two kernels, each the numpy code's arithmetic transcribed operation by operation per
sample point (the same floating-point expressions in the same order; the minima over
balls and passes are exact whatever their order), so the bounds are the same bits:

* :func:`ball_cut` (stages 1 and 2): the lowest of the balls of several passes at
  given offsets of the fine grid along the pass, over each sample point;
* :func:`rim_cut` (stage 3): per pass, the lowest ball between the fine positions,
  found by 65 samples within R and a golden-section search of 24 steps around the
  lowest, the balls following the pass's Hermite tip profile
  (:func:`fabkit.toolpath.finish.scallop.hermite_profile`).

The formula-dependent parts (the design's height and slopes, the normal's scale, the
steep-along test) stay in numpy outside. Minima propagate NaN as numpy's do. Compiled
with ``cache=True`` like :mod:`fabkit.toolpath.cut.stock_kernels` (numba's cache next to
this module, or NUMBA_CACHE_DIR).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ... import numba_start  # noqa: F401  (numba's short start-up for cached code)

jit = njit(cache=True, nogil=True, error_model="numpy")


@jit
def _nanmin(cur, x):
    """min(cur, x) propagating NaN (np.minimum; NaN stays once there)."""
    if x < cur or x != x:
        return x
    return cur


@jit
def _balls_into(col, dv2, fine, R, Js, rrs, n):
    """Lower col (one column's cut, m points) to the balls of every pass at the fine
    positions Js[:n] (R^2 - du^2 in rrs, non-increasing; dv2[p, i] the points' squared
    distances across from pass p): a ball whose height (+ R) is not below that of an
    earlier ball of the same pass is skipped, being nowhere lower (a larger circle in
    the cross-section, centred no higher: monotone rounding keeps that true in floating
    point, so the minimum is the same bits)."""
    m = col.shape[0]
    for p in range(dv2.shape[0]):
        fmin = np.inf
        for k in range(n):
            rr = rrs[k]
            if rr < 0.0:               # r2 = rr - dv2 < 0 here and at every later ball
                break
            f = fine[p, Js[k]]
            if f == np.inf:            # an unmachined position: +inf, lowers nothing
                continue
            fR = f + R
            if fR >= fmin:
                continue
            if fR < fmin:
                fmin = fR
            for i in range(m):
                r2 = rr - dv2[p, i]
                if r2 >= 0.0:
                    b = fR - math.sqrt(r2)
                    if b < col[i] or b != b:
                        col[i] = b


@jit
def _material(ml, c, col, design, scale):
    """ml[:, c] = (np.minimum(col, 0) - design[:, c]) * scale[:, c]."""
    for i in range(col.shape[0]):
        x = col[i]
        if x >= 0.0:
            x = 0.0
        ml[i, c] = (x - design[i, c]) * scale[i, c]


@jit
def sweep_balls(uq, uf, vs, fine, pv, R, K, design, scale, threshold):
    """Stages 1 and 2 of the material bound: (m, nq) material (min(cut, 0) - design) x
    scale at the sample points (uq[c], vs[i, c]), cut by the lowest ball of the passes p
    (across at pv[p], tip heights fine[p] on the fine grid uf, +inf where not machined)
    at the fine position j0 = searchsorted(uf, uq[c]) (stage 1), and, in the columns
    where that leaves more than ``threshold`` somewhere, at the positions j0 - K .. j0 + K
    (stage 2)."""
    nf = uf.shape[0]
    m, nq = vs.shape
    P = pv.shape[0]
    RR = R * R
    ml = np.empty((m, nq))
    col = np.empty(m)
    dv2 = np.empty((P, m))
    Js = np.empty(2 * K + 2, dtype=np.int64)
    rrs = np.empty(2 * K + 2)
    for c in range(nq):
        u = uq[c]
        lo, hi = 0, nf                 # searchsorted(uf, u, side="left")
        while lo < hi:
            mid = (lo + hi) >> 1
            if uf[mid] < u:
                lo = mid + 1
            else:
                hi = mid
        j0 = lo if lo < nf else nf - 1
        for i in range(m):
            col[i] = np.inf
        for p in range(P):
            for i in range(m):
                dv = vs[i, c] - pv[p]
                dv2[p, i] = dv * dv
        du = u - uf[j0]
        Js[0] = j0
        rrs[0] = RR - du * du
        _balls_into(col, dv2, fine, R, Js, rrs, 1)
        _material(ml, c, col, design, scale)
        hot = False
        for i in range(m):
            if ml[i, c] > threshold:
                hot = True
        if not hot:
            continue
        # stage 2: the positions j0 - K .. j0 + K (clipped), nearest along u first
        a = j0 - K if j0 - K > 0 else 0
        b = j0 + K if j0 + K < nf - 1 else nf - 1
        left, right, n = j0 - 1, j0, 0
        while left >= a or right <= b:
            if right > b:
                J = left
                left -= 1
            elif left < a:
                J = right
                right += 1
            else:
                dl = u - uf[left]
                dr = u - uf[right]
                if dl * dl <= dr * dr:
                    J = left
                    left -= 1
                else:
                    J = right
                    right += 1
            du = u - uf[J]
            Js[n] = J
            rrs[n] = RR - du * du
            n += 1
        _balls_into(col, dv2, fine, R, Js, rrs, n)
        _material(ml, c, col, design, scale)
    return ml


@jit
def _search(ug, u):
    """searchsorted(ug, u, side="right") - 1, by bisection."""
    lo, hi = 0, ug.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if ug[mid] <= u:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


@jit
def _segment(ug, u, r):
    """searchsorted(ug, u, side="right") - 1 (the count of nodes <= u, less one),
    walked from the guess r (a neighbour's: a step or two)."""
    n = ug.shape[0]
    if u != u:                    # NaN sorts last
        return n - 1
    if r < -1:
        r = -1
    elif r > n - 1:
        r = n - 1
    while r + 1 < n and ug[r + 1] <= u:
        r += 1
    while r >= 0 and ug[r] > u:
        r -= 1
    return r


@jit
def _hermite(ug, Z, dZ, kink, p, u, r):
    """The Hermite tip profile of pass p at u (as scallop.hermite_profile, one point),
    u in the segment r = searchsorted(ug, u, side="right") - 1 (clipped here)."""
    n = ug.shape[0]
    i = r
    if i < 0:
        i = 0
    elif i > n - 2:
        i = n - 2
    h = ug[i + 1] - ug[i]
    t = (u - ug[i]) / h
    t2 = t * t
    t3 = t * t * t
    Z0 = Z[p, i]
    Z1 = Z[p, i + 1]
    z = ((2 * t3 - 3 * t2 + 1) * Z0 + (t3 - 2 * t2 + t) * h * dZ[p, i]
         + (-2 * t3 + 3 * t2) * Z1 + (t3 - t2) * h * dZ[p, i + 1])
    if kink[p, i] or kink[p, i + 1]:
        lin = Z0 + t * (Z1 - Z0)
        if z != z or lin > z:          # np.fmax
            z = lin
    if not math.isfinite(z):
        return np.inf
    return z


@jit
def _ball(oo, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p, r):
    """Lowest point above u0 of pass p's ball at u0 + oo (scallop.sweep_material's
    ``ball``); r: a guess of the segment of u0 + oo."""
    r2 = RR - oo * oo - dv2
    if not (r2 >= 0.0):
        return np.inf
    u = u0 + oo
    if not (u >= lo[p] and u <= hi[p]):
        return np.inf
    return _hermite(ug, Z, dZ, kink, p, u, _segment(ug, u, r)) + R - math.sqrt(r2)


@jit
def rim_cut(u0s, vs, ug, Z, dZ, kink, lo, hi, pv, R, o, h, gr, steps):
    """(m, nh): at each sample point (u0s[c], vs[i, c]) the lowest, over the passes p,
    of the lowest ball of pass p centred within R along the pass: the samples at
    offsets ``o`` (spacing ``h``), then ``steps`` golden-section steps (ratio ``gr``)
    in the two sample intervals around the lowest sample. The passes' tip profiles:
    nodes ug, heights Z[p], slopes dZ[p], kinks kink[p], machined on [lo[p], hi[p]].

    The samples' tip heights (+ R) are computed once per column and pass (they do not
    depend on the point across); a pass whose balls reach neither the point across
    (|v - pv| > R) nor its machined span along is skipped (its balls are all +inf)."""
    m, nh = vs.shape
    P = pv.shape[0]
    no = o.shape[0]
    RR = R * R
    RRo = np.empty(no)          # R^2 - o^2 per sample offset
    for k in range(no):
        RRo[k] = RR - o[k] * o[k]
    zR = np.empty(no)           # the samples' tip height + R (+inf: not machined)
    seg = np.empty(no, dtype=np.int64)      # the samples' segments of ug
    out = np.empty((m, nh))
    for c in range(nh):
        u0 = u0s[c]
        for i in range(m):
            out[i, c] = np.inf
        for p in range(P):
            # every ball of the search lies within R + 2h of u0 along the pass
            if hi[p] < u0 - R - 2 * h or lo[p] > u0 + R + 2 * h:
                continue
            r = _search(ug, u0 + o[0])
            for k in range(no):
                u = u0 + o[k]
                r = _segment(ug, u, r)
                seg[k] = r
                if u >= lo[p] and u <= hi[p]:
                    zR[k] = _hermite(ug, Z, dZ, kink, p, u, r) + R
                else:
                    zR[k] = np.inf
            for i in range(m):
                dv = vs[i, c] - pv[p]
                dv2 = dv * dv
                if RR - dv2 < 0.0:      # r2 <= RR - dv2 < 0 at every offset
                    continue
                # the samples: their minimum and its first index (np.argmin: the first NaN)
                gmin = np.inf
                jb = -1
                gb = 0.0
                for k in range(no):
                    r2 = RRo[k] - dv2
                    g = zR[k] - math.sqrt(r2) if r2 >= 0.0 else np.inf
                    gmin = _nanmin(gmin, g)
                    if jb < 0:
                        jb, gb = k, g
                    elif gb == gb and (g < gb or g != g):
                        jb, gb = k, g
                r = seg[jb]
                a = o[jb] - h
                b = a + 2 * h
                cc = b - gr * (b - a)
                d = a + gr * (b - a)
                gc = _ball(cc, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p, r)
                gd = _ball(d, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p, r)
                for _ in range(steps):
                    if gc <= gd:
                        b = d
                        d = cc
                        cc = b - gr * (b - a)
                        gn = _ball(cc, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p, r)
                        gd = gc
                        gc = gn
                    else:
                        a = cc
                        cc = d
                        d = a + gr * (b - a)
                        gn = _ball(d, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p, r)
                        gc = gd
                        gd = gn
                out[i, c] = _nanmin(out[i, c], _nanmin(gmin, _nanmin(gc, gd)))
    return out
