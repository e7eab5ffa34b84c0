"""The milled block as one watertight solid, triangulated to a chordal tolerance.

Pipeline (pure array functions; nothing here writes files or prints):

1. **Top skin.** The clipped surface min(h, top) over the footprint is
   triangulated adaptively in design coordinates: a coarse grid of right
   triangles, then rounds of conforming longest-edge bisection of every triangle
   whose measured vertical error exceeds a fraction of the tolerance (flat ground
   keeps its coarse triangles; only new triangles are measured again).
2. **Crease.** The curve h = top where the cut meets the stock's top face is
   placed exactly: every triangle edge whose endpoints straddle ``top`` gets its
   crossing point by a safeguarded Newton iteration on h(p(t)) - top with the
   exact derivative (|h - top| <= 1e-12 relative), computed once per unique edge
   so neighbouring triangles share it, and each straddling triangle is split into
   a surface part and a flat part. The error is measured on these final pieces.
3. **Walls and bottom.** Each side wall is the polygon of the top skin's
   boundary vertices along that side plus the two bottom corners, triangulated
   by ``manifold3d.triangulate`` without new vertices; the bottom is 2 triangles.
4. **Check.** The mesh is handed to ``manifold3d`` (status must be NoError), which
   gives the volume, the number of bodies (must be 1) and the genus (must be 0).

Work coordinates (mm): design (x, y, z) -> ((x - x0) s, (y - y0) s, (z - top) s);
the stock is [0, L] x [0, W] x [-thickness, 0].
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .errors import DesignError, SpecError
from .tolerances import DEFAULT, Tolerances

__all__ = ["SolidMesh", "build_solid", "top_skin", "estimate_triangles", "stl_bytes", "export_bytes",
           "mesh_precision", "barycentric_grid", "EXPORT_FORMATS"]

#: refine until every sampled error is below this fraction of the tolerance
SAFETY = 0.7
#: barycentric sampling level per triangle while refining and for the report
SAMPLE_LEVEL = 6
#: initial grid: cells along the footprint's longer side
INITIAL_CELLS = 16
#: first-round probe lattice: steps per initial grid cell (the samples give ~6)
PROBES_PER_CELL = 16
MAX_ROUNDS = 80
STL_HEADER = b"fabkit binary STL: milled block, work coordinates, mm".ljust(80, b" ")
EXPORT_FORMATS = ("stl", "ply", "obj", "off", "glb", "gltf", "3mf", "dae")


@dataclass
class SolidMesh:
    """The milled block.

    vertices : (n, 3) float, work coordinates in mm
    faces : (m, 3) int, vertex indices, counter-clockwise seen from outside
    volume_mm3 : the solid's volume (manifold3d; exact for the mesh)
    max_deviation_mm : largest measured |mesh - min(h, top)| * s on the top skin,
        sampled at ``checked_points`` points (vertical, mm)
    surface_triangles : triangles of the top skin (cut and flat parts)
    crease : (k, 2) float, design (x, y) of the crease vertices (h = top there to ~1e-12)
    """

    vertices: np.ndarray
    faces: np.ndarray
    volume_mm3: float
    max_deviation_mm: float
    checked_points: int
    surface_triangles: int
    crease: np.ndarray
    tolerance_mm: float
    bodies: int = 1
    watertight: bool = True
    rounds: int = 0

    @property
    def triangles(self) -> int:
        return int(len(self.faces))


# ----------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------
def barycentric_grid(level: int, interior_only: bool = False) -> np.ndarray:
    """Barycentric points (i/k, j/k, (k-i-j)/k), shape (p, 3), without the three
    vertices (where the piecewise-linear error is zero by construction)."""
    k = level
    pts = [(i / k, j / k, (k - i - j) / k) for i in range(k + 1) for j in range(k + 1 - i)]
    pts = [p for p in pts if max(p) < 1.0]
    if interior_only:
        pts = [p for p in pts if min(p) > 0.0]
    return np.array(pts, dtype=float)


def _crossings(h, a: np.ndarray, b: np.ndarray, top: float, grad, xtol: float) -> np.ndarray:
    """Points on segments a -> b (shapes (k, 2)) where h = top, given h(a) <= top < h(b).

    Safeguarded Newton (bracket kept, bisection when a step leaves it) with the
    exact derivative grad(p) . (b - a); converges to |h - top| <= 1e-12 (1 + |top|)
    or a bracket of 1e-15, whichever first. Returns (k, 2)."""
    d = b - a
    lo = np.zeros(len(a))
    hi = np.ones(len(a))
    fa = h(a[:, 0], a[:, 1]) - top
    fb = h(b[:, 0], b[:, 1]) - top
    with np.errstate(all="ignore"):
        t = np.clip(-fa / (fb - fa), 0.0, 1.0)
    t = np.where(np.isfinite(t), t, 0.5)
    ftol = xtol * (1.0 + abs(top))
    active = np.ones(len(a), bool)
    for _ in range(100):
        idx = np.nonzero(active)[0]
        if idx.size == 0:
            break
        ti = t[idx]
        p = a[idx] + ti[:, None] * d[idx]
        f = h(p[:, 0], p[:, 1]) - top
        gx, gy = grad(p[:, 0], p[:, 1])
        g = gx * d[idx, 0] + gy * d[idx, 1]
        neg = f <= 0
        lo[idx] = np.where(neg, ti, lo[idx])
        hi[idx] = np.where(neg, hi[idx], ti)
        with np.errstate(all="ignore"):
            tn = ti - f / g
        bad = ~np.isfinite(tn) | (tn <= lo[idx]) | (tn >= hi[idx])
        tn = np.where(bad, 0.5 * (lo[idx] + hi[idx]), tn)
        done = (np.abs(f) <= ftol) | (hi[idx] - lo[idx] <= 1e-15)
        t[idx] = np.where(done, ti, tn)
        active[idx[done]] = False
    return a + t[:, None] * d


def _split(points: np.ndarray, tris: np.ndarray, h, grad, top: float, xtol: float):
    """Split the triangulation along the crease h = top.

    points : (n, 2) design (x, y); tris : (m, 3) counter-clockwise.
    Returns (P, Z, pieces, parent, crease_index):
    P (n + k, 2) points incl. the k crease points; Z (n + k,) = min(h, top) there
    (exactly top on the crease); pieces (q, 3) counter-clockwise; parent (q,) the
    triangle each piece came from; crease_index (k,) indices into P.
    """
    n = len(points)
    hv = h(points[:, 0], points[:, 1])
    above = hv > top                     # uncut (flat top face); h <= top is cut
    nab = above[tris].sum(axis=1)
    straddle = (nab == 1) | (nab == 2)

    # the odd vertex first (rotation keeps orientation): the single below vertex
    # when one is below, the single above vertex when two are below
    ab = above[tris]
    odd = np.where(nab == 1, np.argmax(ab, axis=1), np.argmin(ab, axis=1))
    st = np.nonzero(straddle)[0]
    r = odd[st]
    rot = np.stack([tris[st, r], tris[st, (r + 1) % 3], tris[st, (r + 2) % 3]], axis=1)
    o, p, q = rot[:, 0], rot[:, 1], rot[:, 2]

    # one crossing per unique straddling edge (shared by both neighbours)
    uniq, inv = _unique_pairs(np.concatenate([np.stack([o, p], 1), np.stack([o, q], 1)]))
    lo_is_below = ~above[uniq[:, 0]]
    below_end = np.where(lo_is_below, uniq[:, 0], uniq[:, 1])
    above_end = np.where(lo_is_below, uniq[:, 1], uniq[:, 0])
    cpts = _crossings(h, points[below_end], points[above_end], top, grad, xtol)
    # a crossing at the cut end itself (h == top there) reuses that vertex
    at_end = np.all(cpts == points[below_end], axis=1)
    cidx = np.empty(len(uniq), np.int64)
    cidx[at_end] = below_end[at_end]
    cidx[~at_end] = n + np.arange(np.count_nonzero(~at_end))
    c1 = cidx[inv[: len(st)]]            # on edge o-p
    c2 = cidx[inv[len(st):]]             # on edge o-q

    P = np.concatenate([points, cpts[~at_end]])
    Z = np.concatenate([np.minimum(hv, top), np.full(np.count_nonzero(~at_end), top)])

    keep = np.nonzero(~straddle)[0]
    # each straddling triangle -> triangle (o, c1, c2) + quad (c1, p, q, c2) as 2 triangles
    pieces = np.concatenate([tris[keep],
                             np.stack([o, c1, c2], 1),
                             np.stack([c1, p, q], 1),
                             np.stack([c1, q, c2], 1)])
    parent = np.concatenate([keep, st, st, st])
    # pieces collapsed by a reused vertex have zero area: drop them
    good = (pieces[:, 0] != pieces[:, 1]) & (pieces[:, 1] != pieces[:, 2]) & (pieces[:, 2] != pieces[:, 0])
    return P, Z, pieces[good], parent[good], np.unique(cidx)


def _piece_errors(P, Z, pieces, clipped, bary, source="<spec>") -> np.ndarray:
    """Largest |linear interpolation - min(h, top)| per piece at barycentric points
    ``bary`` (s, 3); design units, shape (q,). Raises SpecError (key
    ``surface.height``) where h is not finite."""
    A, B, C = P[pieces[:, 0]], P[pieces[:, 1]], P[pieces[:, 2]]
    x = bary[:, 0] * A[:, None, 0] + bary[:, 1] * B[:, None, 0] + bary[:, 2] * C[:, None, 0]
    y = bary[:, 0] * A[:, None, 1] + bary[:, 1] * B[:, None, 1] + bary[:, 2] * C[:, None, 1]
    zc = clipped(x, y)
    bad = ~np.isfinite(zc)
    if bad.any() or not np.isfinite(Z).all():
        if bad.any():
            i = np.argmax(bad.ravel())
            px, py = x.ravel()[i], y.ravel()[i]
        else:
            j = np.argmax(~np.isfinite(Z))
            px, py = P[j]
        raise SpecError(f"h is not finite at x={px:.6g}, y={py:.6g} (check the formula and the footprint)",
                        file=source, key="surface.height")
    zl = bary @ Z[pieces].T
    return np.abs(zl.T - zc).max(axis=1, initial=0.0)


def estimate_triangles(surface, tolerance_mm: float) -> float:
    """Triangles the adaptive skin will need, from the exact Hessian on a 101 x 101
    grid: a triangle of size d has chordal error ~ |lambda_max| d^2 / 8, so the
    cut area needs about 2 s |lambda_max| / (8 SAFETY tol) triangles per unit area.
    An order-of-magnitude estimate, used only for the size guard."""
    X, Y = surface.grid(101)
    hxx, hxy, hyy = surface.hessian(X, Y)
    lam = 0.5 * np.abs(hxx + hyy) + np.sqrt(0.25 * (hxx - hyy) ** 2 + hxy ** 2)
    lam = np.where(np.isfinite(lam), lam, 0.0)
    cut = surface.height(X, Y) < surface.top
    cell = surface.length * surface.width / (100 * 100)
    return float(2.0 * cell * surface.scale * np.sum(lam * cut) / (8 * SAFETY * tolerance_mm))


def _edges(tris):
    """Unique edges (e, 2) sorted per row, and the edge id of each triangle's
    edges (v0 v1, v1 v2, v2 v0), shape (m, 3)."""
    e = np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], axis=1).reshape(-1, 2)
    uniq, inv = _unique_pairs(e)
    return uniq, inv.reshape(-1, 3)


def _unique_pairs(e):
    """Unique unordered index pairs of (k, 2) ``e``: (u, 2) rows sorted (lo, hi) and in
    lexicographic order, and the (k,) inverse. An int64 key sorts far faster than
    ``np.unique(axis=0)``."""
    lo, hi = np.minimum(e[:, 0], e[:, 1]).astype(np.int64), np.maximum(e[:, 0], e[:, 1]).astype(np.int64)
    base = int(hi.max(initial=0)) + 1
    keys, inv = np.unique(lo * base + hi, return_inverse=True)
    return np.stack([keys // base, keys % base], axis=1), inv.ravel()


def _bisect(points, tris, terr, fail_all, fail_long):
    """Conforming longest-edge refinement of a triangulation.

    fail_all : triangles to split into 4 (all edges marked); fail_long : triangles
    whose longest edge is marked. The closure marks the longest edge of every
    triangle with a marked edge, so each triangle splits into 2, 3 or 4 (no
    hanging vertices). Midpoints are computed from the edge's lower vertex index,
    so both neighbours of an edge share one exact vertex. Returns (points, tris, terr):
    ``terr`` (m,) the measured error of each kept triangle carried over, NaN
    (not measured yet) for the new ones.
    """
    edges, te = _edges(tris)
    m = len(tris)
    ar = np.arange(m)
    P = points[tris]
    L = np.stack([np.hypot(*(P[:, 1] - P[:, 0]).T), np.hypot(*(P[:, 2] - P[:, 1]).T),
                  np.hypot(*(P[:, 0] - P[:, 2]).T)], axis=1)
    lng = np.argmax(L, axis=1)
    long_edge = te[ar, lng]
    marked = np.zeros(len(edges), bool)
    marked[te[fail_all].ravel()] = True
    marked[long_edge[fail_long]] = True
    while True:   # closure: a triangle with any marked edge has its longest edge marked
        need = marked[te].any(axis=1) & ~marked[long_edge]
        if not need.any():
            break
        marked[long_edge[need]] = True
    mid_id = np.full(len(edges), -1, np.int64)
    me = np.nonzero(marked)[0]
    mid_id[me] = len(points) + np.arange(len(me))
    lo, hi = points[edges[me, 0]], points[edges[me, 1]]
    points = np.concatenate([points, lo + 0.5 * (hi - lo)])

    split = np.nonzero(marked[long_edge])[0]
    keep = np.nonzero(~marked[long_edge])[0]
    k = lng[split]
    r0, r1, r2 = tris[split, k], tris[split, (k + 1) % 3], tris[split, (k + 2) % 3]
    e12, e20 = te[split, (k + 1) % 3], te[split, (k + 2) % 3]
    mm = mid_id[long_edge[split]]
    m12, m20 = mid_id[e12], mid_id[e20]
    s12, s20 = m12 >= 0, m20 >= 0
    parts = [tris[keep]]
    # right half (m, r1, r2), split at m12 when marked
    parts.append(np.stack([mm, r1, r2], 1)[~s12])
    parts.append(np.stack([mm, r1, m12], 1)[s12])
    parts.append(np.stack([mm, m12, r2], 1)[s12])
    # left half (r0, m, r2), split at m20 when marked
    parts.append(np.stack([r0, mm, r2], 1)[~s20])
    parts.append(np.stack([r0, mm, m20], 1)[s20])
    parts.append(np.stack([mm, r2, m20], 1)[s20])
    new_tris = np.concatenate(parts)
    new_err = np.concatenate([terr[keep], np.full(len(new_tris) - len(keep), np.nan)])
    return points, new_tris, new_err


def _initial_mesh(surface):
    """A grid of the footprint, about INITIAL_CELLS cells along its longer side,
    each cell cut into 2 counter-clockwise triangles. Returns (points, tris, (nx, ny))."""
    (x0, x1), (y0, y1) = surface.x_range, surface.y_range
    big = max(x1 - x0, y1 - y0)
    nx = max(2, int(math.ceil(INITIAL_CELLS * (x1 - x0) / big)))
    ny = max(2, int(math.ceil(INITIAL_CELLS * (y1 - y0) / big)))
    X, Y = np.meshgrid(np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1))
    points = np.column_stack([X.ravel(), Y.ravel()])
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    a = (j * (nx + 1) + i).ravel()
    b, c, d = a + 1, a + nx + 2, a + nx + 1          # (i+1, j), (i+1, j+1), (i, j+1)
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return points, tris, (nx, ny)


def _grid_probes(surface, nx: int, ny: int, per_cell: int = PROBES_PER_CELL):
    """Probe points on a lattice ``per_cell`` times finer than the initial grid,
    with the initial triangle containing each: (k, 2) design points, (k,) ids
    (cell (i, j) holds triangles j nx + i (below its diagonal) and nx ny + j nx + i)."""
    (x0, x1), (y0, y1) = surface.x_range, surface.y_range
    I, J = np.meshgrid(np.arange(nx * per_cell + 1), np.arange(ny * per_cell + 1))
    I, J = I.ravel(), J.ravel()
    i, j = np.minimum(I // per_cell, nx - 1), np.minimum(J // per_cell, ny - 1)
    u, v = I - i * per_cell, J - j * per_cell          # lattice steps inside the cell
    tri = np.where(u >= v, j * nx + i, nx * ny + j * nx + i)
    xy = np.column_stack([x0 + (x1 - x0) * I / (nx * per_cell), y0 + (y1 - y0) * J / (ny * per_cell)])
    return xy, tri


def _probe_errors(P, Z, pieces, parent, m, xy, tri, clipped):
    """|mesh - min(h, top)| at probe points ``xy`` (k, 2) lying in triangles ``tri``
    (k,) of a triangulation with ``m`` triangles whose crease pieces are ``pieces``
    with ``parent``; design units, shape (k,)."""
    order = np.argsort(parent, kind="stable")
    count = np.bincount(parent, minlength=m)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    best = np.full(len(xy), -np.inf)
    zmesh = np.zeros(len(xy))
    for k in range(3):
        has = count[tri] > k
        pid = order[np.minimum(start[tri] + k, len(order) - 1)]
        A, B, C = P[pieces[pid, 0]], P[pieces[pid, 1]], P[pieces[pid, 2]]
        det = (B[:, 0] - A[:, 0]) * (C[:, 1] - A[:, 1]) - (B[:, 1] - A[:, 1]) * (C[:, 0] - A[:, 0])
        with np.errstate(all="ignore"):
            wb = ((xy[:, 0] - A[:, 0]) * (C[:, 1] - A[:, 1]) - (xy[:, 1] - A[:, 1]) * (C[:, 0] - A[:, 0])) / det
            wc = ((B[:, 0] - A[:, 0]) * (xy[:, 1] - A[:, 1]) - (B[:, 1] - A[:, 1]) * (xy[:, 0] - A[:, 0])) / det
        wa = 1 - wb - wc
        inside = np.where(has & np.isfinite(wa), np.minimum(np.minimum(wa, wb), wc), -np.inf)
        take = inside > best
        best = np.where(take, inside, best)
        z = wa * Z[pieces[pid, 0]] + wb * Z[pieces[pid, 1]] + wc * Z[pieces[pid, 2]]
        zmesh = np.where(take, z, zmesh)
    return np.abs(zmesh - clipped(xy[:, 0], xy[:, 1]))


def top_skin(surface, tolerance_mm: float, tol: Tolerances = DEFAULT, key: str = "--tolerance"):
    """Adaptive triangulation of min(h, top) over the footprint, crease exact.

    Returns (P, Z, pieces, crease_index, max_dev_mm, checked_points, rounds):
    P (n, 2) design (x, y); Z (n,) design z; pieces (q, 3) counter-clockwise in
    (x, y); max_dev_mm the largest vertical deviation measured at
    ``checked_points`` sample points (mm); every sample is within
    ``SAFETY * tolerance_mm`` when this returns.
    """
    h, grad = surface.fns.h, surface.fns.grad
    top, s = surface.top, surface.scale
    clipped = surface.clipped
    limit = tol.max_mesh_triangles
    est = estimate_triangles(surface, tolerance_mm)
    if not est <= limit:
        raise SpecError(f"a tolerance of {tolerance_mm:g} mm needs about {est:.2g} triangles, more than the "
                        f"limit {limit}; use a larger tolerance", file=surface.source, key=key)
    points, tris, (nx, ny) = _initial_mesh(surface)
    probe_xy, probe_tri = _grid_probes(surface, nx, ny)
    terr = np.full(len(tris), np.nan)     # largest sampled error of each triangle's pieces
    target = SAFETY * tolerance_mm / s          # design units
    bary = barycentric_grid(SAMPLE_LEVEL)
    for rounds in range(1, MAX_ROUNDS + 1):
        sub = np.nonzero(np.isnan(terr))[0]
        if sub.size == 0:
            break
        P, Z, pieces, parent, _ = _split(points, tris[sub], h, grad, top, tol.root_xtol)
        err = _piece_errors(P, Z, pieces, clipped, bary, surface.source)
        ratio = np.zeros(len(sub))
        np.maximum.at(ratio, parent, err / target)
        if rounds == 1:
            # a lattice of probes finer than the samples, so that a feature smaller
            # than the initial triangles is seen before the first split
            perr = _probe_errors(P, Z, pieces, parent, len(tris), probe_xy, probe_tri, clipped)
            np.maximum.at(ratio, probe_tri, perr / target)
        terr[sub] = ratio * target
        fail = terr > target
        if not fail.any():
            break
        # a failing triangle needs about `ratio` triangles (error ~ size^2 on smooth
        # ground, ~ size along a kink): refuse early instead of refining to the limit
        need = np.count_nonzero(~fail) + np.sum(terr[fail] / target)
        if need > limit:
            raise SpecError(f"a tolerance of {tolerance_mm:g} mm needs about {need:.2g} triangles on this "
                            f"surface, more than the limit {limit}; use a larger tolerance",
                            file=surface.source, key=key)
        fail_all = sub[ratio > 2.0]
        fail_long = sub[(ratio > 1.0) & (ratio <= 2.0)]
        points, tris, terr = _bisect(points, tris, terr, fail_all, fail_long)
        if len(tris) > limit:
            raise SpecError(f"a tolerance of {tolerance_mm:g} mm needs more than the limit of {limit} "
                            "triangles on this surface; use a larger tolerance", file=surface.source, key=key)
    else:
        raise DesignError(f"the mesh did not reach the tolerance {tolerance_mm:g} mm in {MAX_ROUNDS} "
                          "refinement rounds (is the surface smooth?)")
    # The output: the crease split of the whole mesh. A triangle's pieces depend on
    # its own vertices only (crossings are per edge, elementwise), so they are the
    # very pieces measured when the triangle was made: their errors carry over.
    P, Z, pieces, _, cidx = _split(points, tris, h, grad, top, tol.root_xtol)
    return P, Z, pieces, cidx, float(terr.max(initial=0.0) * s), int(len(pieces) * len(bary)), rounds


# ----------------------------------------------------------------------------
# the solid
# ----------------------------------------------------------------------------
def _wall(chain_u, chain_z, idx_chain, u_lo, u_hi, z_bot, i_bl, i_br):
    """Triangles of one side wall: polygon of the top chain (sorted by u) and the
    two bottom corners; returns (k, 3) global indices (orientation fixed later)."""
    import manifold3d

    poly = np.concatenate([np.column_stack([chain_u, chain_z]), [[u_hi, z_bot], [u_lo, z_bot]]])
    ids = np.concatenate([idx_chain, [i_br, i_bl]])
    # make counter-clockwise for the triangulator
    area2 = np.sum(poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1])
    if area2 < 0:
        poly, ids = poly[::-1].copy(), ids[::-1].copy()
    t = np.asarray(manifold3d.triangulate([poly]), dtype=np.int64)
    return ids[t]


def _orient(V, faces, outward):
    """Flip ``faces`` (k, 3) if their summed area vector points against ``outward``."""
    a, b, c = V[faces[:, 0]], V[faces[:, 1]], V[faces[:, 2]]
    if np.cross(b - a, c - a).sum(axis=0) @ outward < 0:
        return faces[:, [0, 2, 1]]
    return faces


def build_solid(surface, thickness_mm: float, tolerance_mm: float = DEFAULT.mesh_tolerance_mm,
                tol: Tolerances = DEFAULT, key: str = "--tolerance") -> SolidMesh:
    """The milled block as a watertight mesh in work coordinates (mm).

    surface : :class:`fabkit.surface.Surface`; thickness_mm : stock thickness;
    tolerance_mm : chordal (vertical) tolerance of the top skin, mm.
    Raises SpecError (naming ``key``) when the tolerance needs more triangles than
    ``tol.max_mesh_triangles``; RuntimeError if manifold3d rejects the mesh (a bug).
    """
    import manifold3d

    if not (math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise SpecError(f"must be a finite number > 0, got {tolerance_mm!r}", key=key)
    P, Z, pieces, cidx, dev, checked, rounds = top_skin(surface, tolerance_mm, tol, key)
    (x0, x1), (y0, y1) = surface.x_range, surface.y_range
    s, top = surface.scale, surface.top
    n = len(P)
    V = np.empty((n + 4, 3))
    V[:n, 0] = (P[:, 0] - x0) * s
    V[:n, 1] = (P[:, 1] - y0) * s
    V[:n, 2] = (Z - top) * s
    Lw, Ww = (x1 - x0) * s, (y1 - y0) * s
    zb = -float(thickness_mm)
    # bottom corners: 00, 10, 11, 01
    V[n:] = [[0, 0, zb], [Lw, 0, zb], [Lw, Ww, zb], [0, Ww, zb]]
    b00, b10, b11, b01 = n, n + 1, n + 2, n + 3

    faces = [pieces]
    sides = [  # (mask, u column, u range in work, bottom corners at u_lo/u_hi, outward)
        (P[:, 1] == y0, 0, (0.0, Lw), (b00, b10), (0, -1, 0)),
        (P[:, 1] == y1, 0, (0.0, Lw), (b01, b11), (0, 1, 0)),
        (P[:, 0] == x0, 1, (0.0, Ww), (b00, b01), (-1, 0, 0)),
        (P[:, 0] == x1, 1, (0.0, Ww), (b10, b11), (1, 0, 0)),
    ]
    for mask, col, (ulo, uhi), (ilo, ihi), out in sides:
        idx = np.nonzero(mask)[0]
        idx = idx[np.argsort(V[idx, col], kind="stable")]
        w = _wall(V[idx, col], V[idx, 2], idx, ulo, uhi, zb, ilo, ihi)
        faces.append(_orient(V, w, np.array(out, float)))
    faces.append(np.array([[b00, b11, b10], [b00, b01, b11]]))   # normal -z
    F = np.concatenate(faces).astype(np.int64)

    m = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.ascontiguousarray(V),
                                              tri_verts=np.ascontiguousarray(F, dtype=np.uint64)))
    status = m.status()
    if status != manifold3d.Error.NoError:
        raise RuntimeError(f"manifold3d rejected the block mesh: {status.name}")
    bodies = len(m.decompose())
    volume = float(m.volume())
    if bodies != 1 or m.genus() != 0:
        raise RuntimeError(f"the block mesh has {bodies} bodies and genus {m.genus()}, expected 1 and 0")
    return SolidMesh(vertices=V, faces=F, volume_mm3=volume, max_deviation_mm=dev, checked_points=checked,
                     surface_triangles=int(len(pieces)), crease=P[cidx], tolerance_mm=float(tolerance_mm),
                     bodies=bodies, watertight=True, rounds=rounds)


# ----------------------------------------------------------------------------
# export (bytes only; the command writes them atomically)
# ----------------------------------------------------------------------------
def stl_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """Binary STL of (n, 3) vertices (mm) and (m, 3) faces: fixed 80-byte header,
    float32 unit normals and coordinates, no timestamps (byte-identical per input)."""
    tri = vertices[faces]                                   # (m, 3, 3)
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.divide(nrm, ln, out=np.zeros_like(nrm), where=ln > 0)
    rec = np.zeros(len(faces), dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]))
    rec["n"] = nrm
    rec["v"] = tri
    return STL_HEADER + np.uint32(len(faces)).astype("<u4").tobytes() + rec.tobytes()


def export_bytes(vertices: np.ndarray, faces: np.ndarray, fmt: str) -> bytes:
    """The mesh in format ``fmt`` (a file extension without the dot): binary STL by
    fabkit's own writer, others through trimesh. Raises SpecError for unknown formats."""
    fmt = fmt.lower()
    if fmt == "stl":
        return stl_bytes(vertices, faces)
    if fmt not in EXPORT_FORMATS:
        raise SpecError(f"unknown mesh format '.{fmt}' (use one of: {', '.join('.' + f for f in EXPORT_FORMATS)})",
                        key="--output")
    import trimesh

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    data = mesh.export(file_type=fmt)
    return data.encode("utf-8") if isinstance(data, str) else bytes(data)


# ----------------------------------------------------------------------------
# work-precision
# ----------------------------------------------------------------------------
def mesh_precision(spec, tolerances=(0.1, 0.03, 0.01, 0.003), tol: Tolerances = DEFAULT) -> list[dict]:
    """Work-precision rows for the solid: for each chordal tolerance (mm), the
    measured largest deviation (mm), triangle count, volume and wall time (s,
    best of one run after a warm-up build)."""
    from .surface import Surface

    surface = Surface.from_spec(spec, tol)
    thickness = spec.stock.thickness
    build_solid(surface, thickness, max(tolerances), tol)          # warm-up (imports, compilation)
    rows = []
    for t in tolerances:
        t0 = time.perf_counter()
        m = build_solid(surface, thickness, t, tol)
        rows.append({"tolerance": float(t), "max_deviation": m.max_deviation_mm, "triangles": m.triangles,
                     "volume_mm3": m.volume_mm3, "checked_points": m.checked_points,
                     "seconds": time.perf_counter() - t0})
    return rows
