"""Verification of a written program: sweep the ball-end tool along the moves READ BACK
from its text (:func:`fabkit.toolpath.program.reader.read_program`) and compare the cut with the
design.

:func:`verify_cut` computes the material surface left by the program at many
sample points and compares it with the clipped design surface. The swept volume
of a ball of radius R whose centre moves along a straight segment is a capsule;
the lowest point of a capsule on the vertical line through (px, py) is, exactly,
the lowest of (a) the lower surfaces of its two end spheres and (b) the lower
intersection of the line with the capsule's infinite cylinder, when the axial
parameter of that intersection lies in [0, 1] (outside that range the
cylinder's end discs lie inside the end spheres). Closed form, vectorized; a
spatial grid of segments keeps the work O(points x nearby segments). The cut
height at a point is min(0, lowest capsule point over all moves) (0 = the top
face: nothing is above it). Figures are exact at the sample points (floating
point, ~1e-9 mm); between samples the cut is not checked, so the sample count
(``machining.verify_points``) and the jitter set how sharp the check is. Material
the ball cannot reach (:mod:`fabkit.toolpath.cut.reach`) is told apart from material the
program leaves.
"""

from __future__ import annotations

import numpy as np

from ...errors import SpecError
from ...tolerances import DEFAULT, Tolerances
from .reach import OVERHANG, OVERHANG_ALONG, reachable_height
from ..program.reader import RAPID, Program


# ----------------------------------------------------------------------------
# the swept ball
# ----------------------------------------------------------------------------
def capsule_lower(px, py, a, b, R: float) -> np.ndarray:
    """Lowest point of the volume swept by a ball of radius R whose TIP moves
    from ``a`` to ``b``, on the vertical lines through (px, py).

    px, py: (m,) mm; a, b: (m, 3) tip positions, mm (pairs: point i with segment i).
    Returns (m,) z of the lowest swept point, mm (+inf where the line misses the
    capsule). Exact (closed form; floating point ~1e-12 relative).
    """
    R = float(R)
    ca_z = a[:, 2] + R
    cb_z = b[:, 2] + R
    dxa, dya = px - a[:, 0], py - a[:, 1]
    dxb, dyb = px - b[:, 0], py - b[:, 1]
    R2 = R * R
    with np.errstate(invalid="ignore"):
        za = ca_z - np.sqrt(R2 - dxa * dxa - dya * dya)
        zb = cb_z - np.sqrt(R2 - dxb * dxb - dyb * dyb)
    za = np.where(np.isnan(za), np.inf, za)
    zb = np.where(np.isnan(zb), np.inf, zb)
    z = np.minimum(za, zb)
    # cylinder around the centre line c(t) = ca + t d
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    ok = dd > 0
    inv = np.where(ok, 1.0 / np.where(ok, np.sqrt(dd), 1.0), 0.0)
    ux, uy, uz = d[:, 0] * inv, d[:, 1] * inv, d[:, 2] * inv
    # w(z') = (dxa, dya, z') with z' = z - ca_z; |w|^2 - (w.u)^2 = R^2
    k = dxa * ux + dya * uy
    qa = 1.0 - uz * uz
    beta = k * uz
    c = dxa * dxa + dya * dya - k * k - R2
    disc = beta * beta - qa * c
    cyl = ok & (qa > 1e-12) & (disc >= 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.sqrt(np.where(cyl, disc, 0.0))
        # lower root of qa z'^2 - 2 beta z' + c = 0, in the cancellation-free form
        zl = np.where(beta >= 0, c / (beta + sd), (beta - sd) / np.where(cyl, qa, 1.0))
        t = (dxa * d[:, 0] + dya * d[:, 1] + zl * d[:, 2]) / np.where(ok, dd, 1.0)
    cyl &= np.isfinite(zl) & (t >= 0.0) & (t <= 1.0)
    return np.where(cyl, np.minimum(z, ca_z + zl), z)


class SegmentGrid:
    """Segments binned by the cells their XY bounding box (grown by R) touches.

    a, b: (n, 3) segment end points (tip), mm; R: tool radius, mm; cell: cell size, mm.
    """

    def __init__(self, a, b, R, cell, origin, shape, max_pairs):
        self.a, self.b, self.R, self.cell = a, b, R, cell
        self.origin, self.shape = origin, shape
        nx, ny = shape
        lo = np.minimum(a[:, :2], b[:, :2]) - R
        hi = np.maximum(a[:, :2], b[:, :2]) + R
        i0 = np.clip(np.floor((lo - origin) / cell).astype(np.int64), 0, [nx - 1, ny - 1])
        i1 = np.clip(np.floor((hi - origin) / cell).astype(np.int64), 0, [nx - 1, ny - 1])
        cx = i1[:, 0] - i0[:, 0] + 1
        cy = i1[:, 1] - i0[:, 1] + 1
        count = cx * cy
        total = int(count.sum())
        if total > max_pairs:
            raise SpecError(f"verification needs {total} segment-cell entries (limit {max_pairs}); "
                            "use fewer verify points or a coarser program", key="machining.verify_points")
        seg = np.repeat(np.arange(len(a)), count)
        off = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        ix = i0[seg, 0] + off % cx[seg]
        iy = i0[seg, 1] + off // cx[seg]
        cid = ix * ny + iy
        # within a cell, the segments in ascending order of their lowest tip (the compiled
        # search stops at the first one not below the lowest found: nothing swept is
        # below its segment's lowest tip)
        self.zmin = np.minimum(a[:, 2], b[:, 2])
        order = np.lexsort((self.zmin[seg], cid))
        self.seg = seg[order]
        self.ptr = np.searchsorted(cid[order], np.arange(nx * ny + 1))

    def cell_of(self, px, py):
        nx, ny = self.shape
        ix = np.clip(np.floor((px - self.origin[0]) / self.cell).astype(np.int64), 0, nx - 1)
        iy = np.clip(np.floor((py - self.origin[1]) / self.cell).astype(np.int64), 0, ny - 1)
        return ix * ny + iy

    def lowest(self, px, py, chunk=2_000_000, before=None):
        """(m,) lowest swept z over the binned segments at the points (+inf if none).
        ``before``: (m,) int, only segments with index < before[i] count."""
        out = np.full(len(px), np.inf)
        cid = self.cell_of(px, py)
        from ..finish.kernels import module

        kern = module()
        if kern is not None and len(px):
            # compiled: the same closed form per point and segment, no pair arrays
            b = np.zeros(1, dtype=np.int64) if before is None else np.ascontiguousarray(before, dtype=np.int64)
            kern.lowest_batch_sorted(np.ascontiguousarray(px, dtype=float), np.ascontiguousarray(py, dtype=float),
                                     cid.astype(np.int64), self.ptr.astype(np.int64), self.seg.astype(np.int64),
                                     np.ascontiguousarray(self.a, dtype=float),
                                     np.ascontiguousarray(self.b, dtype=float), float(self.R), b,
                                     before is not None, out, np.ascontiguousarray(self.zmin, dtype=float))
            return out
        cnt = self.ptr[cid + 1] - self.ptr[cid]
        pos = 0
        m = len(px)
        while pos < m:
            # as many points as fit in one chunk of pairs
            csum = np.cumsum(cnt[pos:])
            stop = pos + max(1, int(np.searchsorted(csum, chunk, side="right")))
            idx = np.arange(pos, min(stop, m))
            c = cnt[idx]
            total = int(c.sum())
            if total:
                owner = np.repeat(idx, c)
                off = np.arange(total) - np.repeat(np.cumsum(c) - c, c)
                s = self.seg[self.ptr[cid[owner]] + off]
                if before is not None:
                    keep = s < before[owner]
                    owner, s = owner[keep], s[keep]
                z = capsule_lower(px[owner], py[owner], self.a[s], self.b[s], self.R)
                np.minimum.at(out, owner, z)
            pos = idx[-1] + 1
        return out


def sample_points(ws, n: int, seed: int = 0, tol: Tolerances = DEFAULT):
    """At least ``n`` sample points (X, Y), work mm, across the whole footprint
    [0, L] x [0, W]: a regular grid including the edges and corners (about half),
    the same number jittered uniformly (deterministic ``seed``), and points on the
    crease H = 0 where the surface meets the top face (found on the grid rows and
    columns by a few secant/bisection steps)."""
    if n > tol.max_verify_points:
        raise SpecError(f"{n} verification points exceed the limit {tol.max_verify_points}",
                        key="machining.verify_points")
    L, W = ws.L, ws.W
    half = max(n // 2, 4)
    nx = max(2, int(round(np.sqrt(half * L / W))) + 1)
    ny = max(2, int(np.ceil(half / nx)) + 1)
    gx, gy = np.linspace(0.0, L, nx), np.linspace(0.0, W, ny)
    GX, GY = np.meshgrid(gx, gy, indexing="ij")
    rng = np.random.default_rng(seed)
    nj = max(n - GX.size, n // 2)
    jx, jy = rng.uniform(0.0, L, nj), rng.uniform(0.0, W, nj)
    cx, cy = _crease_points(ws, gx, gy)
    X = np.concatenate([GX.ravel(), jx, cx])
    Y = np.concatenate([GY.ravel(), jy, cy])
    return X, Y


def _uniform_count(ws, n: int) -> int:
    """How many of :func:`sample_points` come first and are spread uniformly (grid and
    jitter; the crease points follow): the share of them flagged estimates an area."""
    half = max(n // 2, 4)
    nx = max(2, int(round(np.sqrt(half * ws.L / ws.W))) + 1)
    ny = max(2, int(np.ceil(half / nx)) + 1)
    return nx * ny + max(n - nx * ny, n // 2)


def _crease_points(ws, gx, gy):
    xs, ys = [], []
    for along_x in (True, False):
        A, B = (gx, gy) if along_x else (gy, gx)
        T, C = np.meshgrid(A, B, indexing="ij")  # T varies along the line, C constant per line
        X, Y = (T, C) if along_x else (C, T)
        H = ws.H(X, Y)
        s = H >= 0
        i, j = np.nonzero(s[1:, :] != s[:-1, :])
        if i.size == 0:
            continue
        t0, t1 = A[i], A[i + 1]
        c = B[j]
        h0, h1 = H[i, j], H[i + 1, j]
        for _ in range(30):  # bisection keeps the bracket; 30 steps -> 1e-9 of a cell
            tm = 0.5 * (t0 + t1)
            hm = ws.H(tm, c) if along_x else ws.H(c, tm)
            same = (hm >= 0) == (h0 >= 0)
            t0, h0 = np.where(same, tm, t0), np.where(same, hm, h0)
            t1, h1 = np.where(same, t1, tm), np.where(same, h1, hm)
        tm = 0.5 * (t0 + t1)
        xs.append(tm if along_x else c)
        ys.append(c if along_x else tm)
    if not xs:
        return np.empty(0), np.empty(0)
    return np.concatenate(xs), np.concatenate(ys)


def verify_cut(surface, program: Program, R: float, points: int = 40000, *, seed: int = 0,
               depth_limit: float = np.inf, reach: float = np.inf, tol: Tolerances = DEFAULT,
               detail: bool = False, unreachable_min: float = 1e-3, normal: bool = True,
               over: float | None = None, cache: dict | None = None, along: str | None = None) -> dict:
    """Sweep a ball-end tool of radius ``R`` mm along every move of ``program`` and
    compare the cut with the design (``surface``: a Surface or WorkSurface).

    Returns a dict (lengths mm, work coordinates):
      max_gouge          largest (design - cut) over the sample points (>0: cut below design)
      max_material_left  largest (cut - what the ball can reach): material above the
                         design where the ball reaches it, above the lowest ball surface
                         where it cannot (see :func:`reachable_height`); measured along
                         the design's normal (``normal``, the scallop's usual measure:
                         the vertical height times 1 / sqrt(1 + |grad H|^2)) or vertically
      max_material_left_normal, max_material_left_vertical  the same in both measures
      material_left_measure  'normal' | 'vertical': the measure of max_material_left
      over_at            with ``over`` (mm): (k, 2) X, Y of the points whose material left
                         (as max_material_left) exceeds it
      max_material_above_design  largest (cut - design), unreachable material included
      unreachable        None, or {height, at, area (mm^2), points}: material above the
                         design no ball position removes (more than ``unreachable_min``)
      gouge_at, material_at   (X, Y) where they occur
      checked_points     number of sample points
      rapid_clearance    smallest (material present when the rapid runs - lowest
                         point of the ball during that rapid) over all rapids and
                         points they pass over (>= 0: no rapid touches material)
      rapids_checked     rapids that go below the top face over the stock
      deepest_cut        deepest tip position below the top face, and the limits
      first_move_ok      the first move is a Z-only rapid up to the top face or above
    ``cache``: a dict kept between verifications of programs for the same surface, R,
    points and seed (the reachable height is computed once). ``along``: the raster's
    direction ('x' or 'y'): the reachable height counts balls hanging off the edges up to
    OVERHANG x R across the passes and OVERHANG_ALONG x R along them (None: OVERHANG both).
    With ``detail`` also the arrays ``X``, ``Y``, ``design``, ``cut`` (per sample point).
    """
    from ..finish.compensate import WorkSurface

    ws = surface if isinstance(surface, WorkSurface) else WorkSurface(surface)
    L, W = ws.L, ws.W
    R = float(R)
    px, py = sample_points(ws, int(points), seed, tol)
    design = np.minimum(ws.H(px, py), 0.0)
    a, b = program.segments()
    n = len(b)
    # the first move comes from an unknown position: it must be a Z-only rapid
    # up to at or above the top face; after it every move is fully known
    # moves from a partly unknown position (before X, Y, Z were all set) must stay
    # at or above the top face; they are then swept from the known components
    unknown = ~np.isfinite(a).all(axis=1)
    first_ok = bool(n and program.kinds[0] == RAPID and np.all(b[unknown, 2] >= 0)
                    and np.all(a[unknown & np.isfinite(a[:, 2]), 2] >= 0))
    a = np.where(np.isfinite(a), a, b)
    known = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    # moves that can touch material: below the top face somewhere, within R of the footprint
    low = known & (np.minimum(a[:, 2], b[:, 2]) < 0.0)
    lo = np.minimum(a[:, :2], b[:, :2])
    hi = np.maximum(a[:, :2], b[:, :2])
    low &= (hi[:, 0] > -R) & (lo[:, 0] < L + R) & (hi[:, 1] > -R) & (lo[:, 1] < W + R)
    idx = np.nonzero(low)[0]
    cell = max(R, np.sqrt(L * W / max(len(px), 1)) * 2.0)
    shape = (int(np.ceil(L / cell)) + 1, int(np.ceil(W / cell)) + 1)
    grid = SegmentGrid(a[idx], b[idx], R, cell, np.array([0.0, 0.0]), shape,
                       max_pairs=50 * tol.max_program_points)
    cut = np.minimum(grid.lowest(px, py), 0.0)
    gouge = design - cut
    # material the ball cannot reach (a valley tighter than it, a V crease) is
    # separated from the material the program leaves where the ball can reach
    # what the ball can reach depends on the design and the sample points, not on the
    # program: a ``cache`` dict keeps it for the next verification of the same block
    key = ("reach", len(px), float(R), seed, along)
    hang = (OVERHANG_ALONG * R if along == "x" else OVERHANG * R,
            OVERHANG_ALONG * R if along == "y" else OVERHANG * R)
    if cache is not None and key in cache:
        reach_z, scale = cache[key]
    else:
        reach_z, _, scale = reachable_height(ws, px, py, R, overhang=hang, return_scale=True)
        if cache is not None:
            cache[key] = (reach_z, scale)
    unreach = reach_z - design
    above = cut - design
    left_v = cut - np.maximum(design, reach_z)
    left_n = left_v * scale
    left = left_n if normal else left_v
    ig, il = int(np.argmax(gouge)), int(np.argmax(left))
    ilv, iln = int(np.argmax(left_v)), int(np.argmax(left_n))
    ia = int(np.argmax(above))
    un = unreach > unreachable_min
    n_uniform = _uniform_count(ws, int(points))
    iu = int(np.argmax(unreach))

    # rapids below the top face: the ball must stay above the material present at
    # that moment (cut by the moves before it), at the sample points near the rapid
    # and at points along its own path (every R/4)
    rap = np.nonzero(program.kinds[idx] == RAPID)[0]
    clearance = np.inf
    clearance_at = None
    for r in rap:
        ra, rb = a[idx[r]], b[idx[r]]
        ln = np.hypot(*(rb[:2] - ra[:2]))
        t = np.linspace(0.0, 1.0, max(2, int(np.ceil(ln / (R / 4))) + 1))
        qx = np.concatenate([ra[0] + t * (rb[0] - ra[0])])
        qy = np.concatenate([ra[1] + t * (rb[1] - ra[1])])
        # sample points within R of the segment's XY path
        d = _dist_to_segment(px, py, ra[:2], rb[:2])
        near = d < R
        qx = np.concatenate([qx, px[near]])
        qy = np.concatenate([qy, py[near]])
        inside = (qx >= 0) & (qx <= L) & (qy >= 0) & (qy <= W)
        qx, qy = qx[inside], qy[inside]
        if qx.size == 0:
            continue
        before = np.full(qx.size, r)
        material = np.minimum(grid.lowest(qx, qy, before=before), 0.0)
        ball = capsule_lower(qx, qy, np.broadcast_to(ra, (qx.size, 3)), np.broadcast_to(rb, (qx.size, 3)), R)
        gap = ball - material
        j = int(np.argmin(gap))
        if gap[j] < clearance:
            clearance, clearance_at = float(gap[j]), (float(qx[j]), float(qy[j]))

    zmin = float(np.min(b[:, 2])) if n else 0.0
    out = {
        "max_gouge": float(gouge[ig]),
        "gouge_at": (float(px[ig]), float(py[ig])),
        "max_material_left": float(left[il]),
        "material_at": (float(px[il]), float(py[il])),
        "material_left_measure": "normal" if normal else "vertical",
        "max_material_left_normal": float(left_n[iln]),
        "material_left_normal_at": (float(px[iln]), float(py[iln])),
        "max_material_left_vertical": float(left_v[ilv]),
        "material_left_vertical_at": (float(px[ilv]), float(py[ilv])),
        "checked_points": int(len(px)),
        "max_material_above_design": float(above[ia]),
        "material_above_design_at": (float(px[ia]), float(py[ia])),
        "unreachable": ({"height": float(unreach[iu]), "at": (float(px[iu]), float(py[iu])),
                         "area": float(L * W * un[:n_uniform].mean()) if n_uniform else 0.0,
                         "points": int(un.sum())} if un.any() else None),
        "rapid_clearance": clearance,
        "rapid_clearance_at": clearance_at,
        "rapids_checked": int(len(rap)),
        "deepest_cut": max(0.0, -zmin),
        "depth_ok": bool(-zmin <= min(depth_limit, reach) + 1e-9),
        "first_move_ok": first_ok,
        "segments": int(n),
    }
    if over is not None:
        k = left > over
        out["over_at"] = np.column_stack([px[k], py[k]])
    if detail:
        out.update(X=px, Y=py, design=design, cut=cut, reach=reach_z)
    return out


def _dist_to_segment(px, py, a, b):
    d = b - a
    dd = float(d @ d)
    if dd == 0:
        return np.hypot(px - a[0], py - a[1])
    t = np.clip(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / dd, 0.0, 1.0)
    return np.hypot(px - a[0] - t * d[0], py - a[1] - t * d[1])


__all__ = ["Program", "read_program", "estimate_time", "capsule_lower", "SegmentGrid", "sample_points",
           "verify_cut", "reachable_height", "RAPID", "FEED"]
