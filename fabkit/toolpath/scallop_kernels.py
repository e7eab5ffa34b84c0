"""Compiled loops of the material bound (:func:`fabkit.toolpath.scallop.sweep_material`).

Two kernels, each the numpy code's arithmetic transcribed operation by operation per
sample point (the same floating-point expressions in the same order; the minima over
balls and passes are exact whatever their order), so the bounds are the same bits:

* :func:`ball_cut` (stages 1 and 2): the lowest of the balls of several passes at
  given offsets of the fine grid along the pass, over each sample point;
* :func:`rim_cut` (stage 3): per pass, the lowest ball between the fine positions,
  found by 65 samples within R and a golden-section search of 24 steps around the
  lowest, the balls following the pass's Hermite tip profile
  (:func:`fabkit.toolpath.scallop.hermite_profile`).

The formula-dependent parts (the design's height and slopes, the normal's scale, the
steep-along test) stay in numpy outside. Minima propagate NaN as numpy's do. Compiled
with ``cache=True`` like :mod:`fabkit.toolpath.stock_kernels` (numba's cache next to
this module, or NUMBA_CACHE_DIR).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

jit = njit(cache=True, nogil=True, error_model="numpy")


@jit
def _nanmin(cur, x):
    """min(cur, x) propagating NaN (np.minimum; NaN stays once there)."""
    if x < cur or x != x:
        return x
    return cur


@jit
def ball_cut(uq, uf, j0, vs, fine, pv, R, cols, offsets):
    """(m, len(cols)): at each sample point (uq[c], vs[i, c]) of the columns ``cols``,
    the lowest of the balls (radius R) of the passes p (across at pv[p], tip heights
    fine[p] on the fine grid uf; +inf where not machined) centred at the fine
    positions j0[c] + offsets (clipped to the grid); +inf where none covers it."""
    nf = uf.shape[0]
    m = vs.shape[0]
    P = pv.shape[0]
    nc = cols.shape[0]
    RR = R * R
    out = np.empty((m, nc))
    for ci in range(nc):
        c = cols[ci]
        for i in range(m):
            out[i, ci] = np.inf
        for k in range(offsets.shape[0]):
            J = j0[c] + offsets[k]
            if J < 0:
                J = 0
            elif J > nf - 1:
                J = nf - 1
            du = uq[c] - uf[J]
            rr = RR - du * du
            if rr < 0.0:           # r2 = rr - dv2 < 0 for every pass and row
                continue
            for p in range(P):
                f = fine[p, J]
                if f == np.inf:    # an unmachined position: +inf, lowers nothing
                    continue
                fR = f + R
                vp = pv[p]
                for i in range(m):
                    dv = vs[i, c] - vp
                    r2 = rr - dv * dv
                    if r2 >= 0.0:
                        out[i, ci] = _nanmin(out[i, ci], fR - math.sqrt(r2))
    return out


@jit
def _hermite(ug, Z, dZ, kink, p, u):
    """The Hermite tip profile of pass p at u (as scallop.hermite_profile, one point)."""
    n = ug.shape[0]
    lo, hi = 0, n                 # searchsorted(ug, u, side="right"): count of ug <= u
    while lo < hi:
        mid = (lo + hi) >> 1
        if ug[mid] <= u:
            lo = mid + 1
        else:
            hi = mid
    i = lo - 1
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
def _ball(oo, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p):
    """Lowest point above u0 of pass p's ball at u0 + oo (scallop.sweep_material's ``ball``)."""
    r2 = RR - oo * oo - dv2
    if not (r2 >= 0.0):
        return np.inf
    u = u0 + oo
    if not (u >= lo[p] and u <= hi[p]):
        return np.inf
    return _hermite(ug, Z, dZ, kink, p, u) + R - math.sqrt(r2)


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
    out = np.empty((m, nh))
    for c in range(nh):
        u0 = u0s[c]
        for i in range(m):
            out[i, c] = np.inf
        for p in range(P):
            # every ball of the search lies within R + 2h of u0 along the pass
            if hi[p] < u0 - R - 2 * h or lo[p] > u0 + R + 2 * h:
                continue
            for k in range(no):
                u = u0 + o[k]
                if u >= lo[p] and u <= hi[p]:
                    zR[k] = _hermite(ug, Z, dZ, kink, p, u) + R
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
                a = o[jb] - h
                b = a + 2 * h
                cc = b - gr * (b - a)
                d = a + gr * (b - a)
                gc = _ball(cc, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p)
                gd = _ball(d, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p)
                for _ in range(steps):
                    if gc <= gd:
                        b = d
                        d = cc
                        cc = b - gr * (b - a)
                        gn = _ball(cc, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p)
                        gd = gc
                        gc = gn
                    else:
                        a = cc
                        cc = d
                        d = a + gr * (b - a)
                        gn = _ball(d, u0, dv2, RR, R, ug, Z, dZ, kink, lo, hi, p)
                        gc = gd
                        gd = gn
                out[i, c] = _nanmin(out[i, c], _nanmin(gmin, _nanmin(gc, gd)))
    return out
