"""Compiled distance from points to polygons' edges, near them only (the rest passes'
drop onto the roughing levels, :func:`fabkit.toolpath.rough.roughing_rest.drop_on_levels`).

:func:`edge_distance` gives, for each point, its distance to the nearest edge of a set
of rings when that distance is at most ``cap``, else +inf. The edges are binned in a
grid of cells at least ``cap`` wide (each edge in every cell its bounding box meets),
so a point looks at the edges of its own and the 8 neighbouring cells only: an edge
within ``cap`` of the point has a point within ``cap`` of it, in one of those cells.
The distance to an edge is GEOS's (``geos::algorithm::Distance::pointToSegment``, the
same operations in the same order), so the result equals ``shapely.distance`` to the
bit wherever the point lies outside the polygons and within ``cap`` of them (checked
in tests/test_roughing.py); points inside are the caller's (distance 0).

Compiled with ``cache=True`` like the stock kernels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ... import numba_start  # noqa: F401  (numba's short start-up for cached code)

jit = njit(cache=True, nogil=True, error_model="numpy")


@jit
def _point_to_segment(x, y, ax, ay, bx, by):
    """GEOS's Distance::pointToSegment: the distance of (x, y) to the segment a-b."""
    if ax == bx and ay == by:
        ex, ey = x - ax, y - ay
        return math.sqrt(ex * ex + ey * ey)
    len2 = (bx - ax) * (bx - ax) + (by - ay) * (by - ay)
    r = ((x - ax) * (bx - ax) + (y - ay) * (by - ay)) / len2
    if r <= 0.0:
        ex, ey = x - ax, y - ay
        return math.sqrt(ex * ex + ey * ey)
    if r >= 1.0:
        ex, ey = x - bx, y - by
        return math.sqrt(ex * ex + ey * ey)
    s = ((ay - y) * (bx - ax) - (ax - x) * (by - ay)) / len2
    return abs(s) * math.sqrt(len2)


@jit
def _cells_of(A, B, e, x0, y0, cell, nxc, nyc):
    """The cells (i0..i1, j0..j1) the bounding box of edge A[e] -> B[e] meets."""
    i0 = max(0, min(nxc - 1, int(math.floor((min(A[e, 0], B[e, 0]) - x0) / cell))))
    i1 = max(0, min(nxc - 1, int(math.floor((max(A[e, 0], B[e, 0]) - x0) / cell))))
    j0 = max(0, min(nyc - 1, int(math.floor((min(A[e, 1], B[e, 1]) - y0) / cell))))
    j1 = max(0, min(nyc - 1, int(math.floor((max(A[e, 1], B[e, 1]) - y0) / cell))))
    return i0, i1, j0, j1


@jit
def _bins(A, B, x0, y0, cell, nxc, nyc):
    """CSR of the edges (A[e] -> B[e]) per cell: (start (nxc * nyc + 1), edges)."""
    count = np.empty(nxc * nyc + 1, np.int64)
    for c in range(nxc * nyc + 1):
        count[c] = 0
    for e in range(A.shape[0]):
        i0, i1, j0, j1 = _cells_of(A, B, e, x0, y0, cell, nxc, nyc)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                count[i * nyc + j + 1] += 1
    start = np.empty(nxc * nyc + 1, np.int64)     # running sums (loops: no array-math import)
    fill = np.empty(nxc * nyc, np.int64)
    acc = 0
    for c in range(nxc * nyc + 1):
        acc += count[c]
        start[c] = acc
        if c < nxc * nyc:
            fill[c] = acc
    edges = np.empty(acc, np.int64)
    for e in range(A.shape[0]):
        i0, i1, j0, j1 = _cells_of(A, B, e, x0, y0, cell, nxc, nyc)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                c = i * nyc + j
                edges[fill[c]] = e
                fill[c] += 1
    return start, edges


@jit
def edge_distance(px, py, A, B, cap, out):
    """out[k] = the distance of (px[k], py[k]) to the nearest edge A[e] -> B[e] when at
    most ``cap`` (else +inf); see the module."""
    n = px.size
    if A.shape[0] == 0:
        for k in range(n):
            out[k] = np.inf
        return
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    for e in range(A.shape[0]):
        x0 = min(x0, A[e, 0], B[e, 0])
        y0 = min(y0, A[e, 1], B[e, 1])
        x1 = max(x1, A[e, 0], B[e, 0])
        y1 = max(y1, A[e, 1], B[e, 1])
    x0, y0, x1, y1 = x0 - cap, y0 - cap, x1 + cap, y1 + cap
    # cells at least cap wide, at most ~4 million of them
    cell = max(cap, math.sqrt((x1 - x0) * (y1 - y0) / 4e6), 1e-9)
    nxc = max(1, int(math.ceil((x1 - x0) / cell)))
    nyc = max(1, int(math.ceil((y1 - y0) / cell)))
    start, edges = _bins(A, B, x0, y0, cell, nxc, nyc)
    for k in range(n):
        x, y = px[k], py[k]
        best = np.inf
        ci = int(math.floor((x - x0) / cell)) if x == x else -2
        cj = int(math.floor((y - y0) / cell)) if y == y else -2
        for i in range(max(ci - 1, 0), min(ci + 1, nxc - 1) + 1):
            for j in range(max(cj - 1, 0), min(cj + 1, nyc - 1) + 1):
                c = i * nyc + j
                for q in range(start[c], start[c + 1]):
                    e = edges[q]
                    d = _point_to_segment(x, y, A[e, 0], A[e, 1], B[e, 0], B[e, 1])
                    if d < best:
                        best = d
        out[k] = best if best <= cap else np.inf
