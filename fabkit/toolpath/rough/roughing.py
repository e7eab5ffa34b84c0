"""Roughing with its own tool, then rest passes: the operations before the finish.

The ``roughing`` section of the spec (fabkit/spec.py) names a tool from ``tools``
(flat end mill, bull nose or ball). :func:`plan_operations` returns the rough
operation and the rest operation(s); the job adds the finish.

Roughing (:func:`plan_rough`) cuts Z levels every ``roughing.stepdown`` below the
top face. At a level z the tool TIP may stand at c only if it leaves the allowance::

    D(q) <= z + lift(|q - c|)   for every q of the stock under the tool,

D = the design clipped at the top face (``surface.top``: above it the stock is not
cut) plus ``roughing.leave``, on the footprint F = [0, L] x [0, W] (no material
beyond it; the finishing planner's convention). With K(z) = {q in F : D(q) > z}
the forbidden centres are exactly the union over rho of K(z + lift(rho)) dilated
by rho. A flat end mill (lift 0) is K(z) dilated by R, exactly; a bull nose or a
ball uses a ladder of lifts 0 = h_0 < ... < h_n = corner radius (equal steps
Delta): the union of K(z + h_j) dilated by rho(h_{j+1}), conservative, the tool
at most Delta higher than it could stand (``Operation.info['allowance_excess_mm']``).

K(z) is the filled contour (contourpy, linear on the grid's edges) of the design on
a grid of step h, at the level lowered by the interpolation bound
e = h^2 / 8 (max|H_xx| + max|H_yy|) (second differences over the band of heights
the levels cut): the polygon contains the true K(z). Dilations use circumscribed
polygons (radius / cos(pi / 4 QUAD_SEGS)), so they contain the true discs. The
allowance is therefore never violated by the geometry, and the tool stands at
most e + Delta + the dilation's chord error (x the local slope) higher than it
could (``allowance_error_mm``: grid h is chosen for e <= machining.tolerance).

Per level the allowed centres A_k (inside the footprint grown by R - stepover/2)
fall into pockets; each pocket is cleared by contour-parallel loops (its boundary
eroded by i x stepover, shapely) or by rows at the stepover. A pocket reaching
beyond the stock is entered from outside (its centre over air, no helix) and cut
outside-in; a closed pocket is entered by a helix (or ramp, or plunge as asked) at
the pole of each innermost loop and cut inside-out. Within a level moves stay in
the pocket; between pockets and levels the tool lifts to 1 mm above the level
above when the straight link's tool disc lies in what that level cleared, else to
the safe height. The region a level cleared is the union of the tool's discs along
its moves (shapely), so the next level cuts only where the level above left
material (no air above material already removed).

Levels stop at the roughing tool's reach and stock.depth_limit: material below is
left to the rest passes and the finish (which refuse depths beyond their own limits).

Rest passes: :mod:`fabkit.toolpath.rough.roughing_rest`; the loops and moves of a level:
:mod:`fabkit.toolpath.rough.roughing_loops`.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..finish.compensate import WorkSurface
from ..operations import Operation
from ..path import CUT, PLUNGE, RAPID, Toolpath
from .roughing_loops import (HELIX_FRACTION, HELIX_SEGS, LINK_CLEARANCE, QUAD_SEGS, _cut_inside_out,  # noqa: F401
                             _cut_outside_in, _erosion_tree, _figures, _go, _Node, _parts, _Path, _polys,
                             _post_order, _pre_order, _raster_pocket, _ring_from, _ring_region, _rings, _walk)
from .roughing_rest import drop_on_grid, drop_on_levels, plan_rest, stock_after  # noqa: F401
from ..tools import Tool, depth_of_cut, feeds_of, finish_tool, spec_tools  # noqa: F401

__all__ = ["spec_tools", "finish_tool", "depth_of_cut", "plan_operations", "plan_rough", "plan_rest",
           "LevelSets", "allowed_region", "ENTRY_ANGLE_DEG", "stock_after"]

ENTRY_ANGLE_DEG = 5.0       # helix and ramp descent angle (foam and wood: 3-10 degrees)
LADDER_MAX = 24             # lift steps of a bull nose / ball allowance
GRID_MAX_NODES = 1_500_000  # the design grid of the level sets
LOOP_INSET = 1.0            # x machining.tolerance: loops eroded by it and simplified within it
LEVEL_BLOCK = 1 << 16       # LevelSets: grid nodes evaluated at a time


# ----------------------------------------------------------------------------
# level sets of the design
# ----------------------------------------------------------------------------
def _dilate(g, r: float):
    """g dilated by r, containing the exact dilation (circumscribed arcs)."""
    if r <= 0:
        return g
    return g.buffer(r / math.cos(math.pi / (4 * QUAD_SEGS)), quad_segs=QUAD_SEGS)


def _ladder(tool: Tool, n_max: int = LADDER_MAX):
    """[(lift h_j, radius rho_{j+1})]: the forbidden region is the union of
    K(z + h_j) dilated by rho_{j+1}; Delta = the lift step (0 for a flat end mill)."""
    R, r, f = tool.radius, tool.corner_radius, tool.flat_radius
    if r <= 0:
        return [(0.0, R)], 0.0
    n = n_max
    h = np.linspace(0.0, r, n + 1)
    rho = f + np.sqrt(np.clip(r * r - (r - h) ** 2, 0.0, None))
    return [(float(h[j]), float(rho[j + 1])) for j in range(n)], r / n


class LevelSets:
    """The design on a grid over the footprint and its level sets K(z) as polygons.

    H: unclipped design height above the top face, mm (work coordinates), on the grid
    x (nx), y (ny). ``err``: the interpolation bound (mm, vertical) by which every
    level is lowered, so that the polygon of {H > t - err} contains {H > t}."""

    def __init__(self, ws: WorkSurface, step: float, band: tuple[float, float]):
        import contourpy

        L, W = ws.L, ws.W
        nx, ny = max(3, int(math.ceil(L / step)) + 1), max(3, int(math.ceil(W / step)) + 1)
        self.x, self.y = np.linspace(0.0, L, nx), np.linspace(0.0, W, ny)
        self.hx, self.hy = self.x[1] - self.x[0], self.y[1] - self.y[0]
        # the design and its second differences in blocks of rows (the same values as on
        # the whole grid at once, without its full-size temporaries)
        H = np.empty((ny, nx))
        rows = max(3, LEVEL_BLOCK // nx)
        for a in range(0, ny, rows):
            X, Y = np.meshgrid(self.x, self.y[a:a + rows])
            H[a:a + rows] = ws.H(X, Y)
        H[~np.isfinite(H)] = 1e9                     # unreadable: kept (material)
        self.H = H
        lo, hi = band
        from ..cut.stock_kernels import curvature_bounds

        # the largest second differences where H lies within 1 mm of the band: one compiled
        # pass, the array expressions' operations (tests/test_roughing.py: the same to the bit)
        cxx, cyy, cxy = (max(float(c), 0.0) for c in curvature_bounds(
            H, lo - 1.0, hi + 1.0, self.hx ** 2, self.hy ** 2, self.hx * self.hy))
        # the contour's vertices (linear on the cell edges) err by <= h^2/8 max|H''| along an
        # edge, its chords across a cell by <= d^2/8 max|H_dd| more (d the cell diagonal,
        # |H_dd| <= |H_xx| + 2|H_xy| + |H_yy|): the polygon is within err of the level set
        C = cxx + cyy + 2.0 * cxy
        self.curv = C
        self.err = (max(self.hx, self.hy) ** 2 + self.hx ** 2 + self.hy ** 2) / 8.0 * C
        self.top = float(H.max()) + 1.0
        self._gen = contourpy.contour_generator(self.x, self.y, H, fill_type=contourpy.FillType.OuterOffset)
        self._cache = {}

    def above(self, t: float):
        """Polygon containing {q in F : H(q) > t}."""
        from shapely.geometry import Polygon
        from shapely.ops import unary_union

        key = round(t, 9)
        if key in self._cache:
            return self._cache[key]
        lev = t - self.err
        if lev >= self.top:
            g = Polygon()
        else:
            pts, offs = self._gen.filled(lev, self.top)
            polys = []
            for p, o in zip(pts, offs):
                rings = [p[o[i]:o[i + 1]] for i in range(len(o) - 1)]
                rings = [r for r in rings if len(r) >= 4]
                if not rings:
                    continue
                poly = Polygon(rings[0], rings[1:])
                if not poly.is_valid:
                    poly = poly.buffer(0)
                polys.append(poly)
            g = unary_union(polys) if polys else Polygon()
        self._cache[key] = g
        return g


def grid_step(ws: WorkSurface, R: float, tolerance: float, band) -> float:
    """The grid step for an interpolation bound within ``tolerance`` (a coarse grid's
    curvature estimate), at most R/4 and 1 mm, at least what GRID_MAX_NODES allows."""
    coarse = LevelSets(ws, min(1.0, R / 4), band)
    c = coarse.curv
    # the level set lowered by err and the polygon within err of it: the tool stands at
    # most 2 err too high; 2 err = 6 h^2 C / 8 <= tolerance
    h = min(1.0, R / 4, math.sqrt(8 * tolerance / (6 * c)) if c > 0 else 1.0)
    hmin = math.sqrt(ws.L * ws.W / GRID_MAX_NODES)
    return max(h, hmin), coarse


def allowed_region(sets: LevelSets, tool: Tool, z: float, leave: float, outer):
    """Tip positions at level z (work mm) that leave ``leave`` above the design:
    ``outer`` minus the forbidden region (module docstring). Returns (geometry, Delta)."""
    from shapely.ops import unary_union

    ladder, delta = _ladder(tool)
    parts = []
    for h, rho in ladder:
        K = sets.above(z + h - leave)
        if not K.is_empty:
            parts.append(_dilate(K, rho))
    if not parts:
        return outer, delta
    forb = unary_union(parts)
    return outer.difference(forb), delta


# ----------------------------------------------------------------------------
# roughing
# ----------------------------------------------------------------------------
def _cleared_radius(tool: Tool, height: float) -> float:
    """The distance from a cut's path within which the tool leaves material at most
    ``height`` above its tip: R for a flat end mill, less on a corner radius."""
    r, f = tool.corner_radius, tool.flat_radius
    if r <= 0:
        return tool.radius
    h = min(height, r)
    return f + math.sqrt(max(r * r - (r - h) ** 2, 0.0))


class _Level:
    """What one level cleared: the cut lines' discs (∪ the air beyond the footprint).

    ``cleared``: the material there is at most the level + ``tolerance`` (a bull nose's
    or ball's discs shrink to where the corner stands within it; between loops further
    apart the cusps count as uncut: rest passes are then conservative); ``free`` (links
    1 mm above the level): within half the link clearance.

    ``pockets``: [(Q, lines)] per pocket cleared by loops or rows at most ``s`` apart
    (:func:`_ring_region`: Q the region its outermost loops bound); where s + 4 simp <=
    the disc's radius rho every point of Q lies within rho of a cut line (consecutive
    loops are at most s + 2 simp apart, the innermost encloses no disc of radius s), so
    the discs' union is Q dilated by rho with the discs of the lines leaving Q: the same
    region as every line's disc, in time linear in the lines (their discs overlap about
    rho / s deep otherwise)."""

    def __init__(self, z, lines, tool, outside, tolerance, clr, pockets=(), s=math.inf, simp=0.0):
        from shapely.geometry import Point
        from shapely.ops import unary_union
        import shapely

        self.z = z
        empty = Point(0, 0).buffer(0)

        def swept(rho):
            parts = []
            loose = [ln for ln in lines if len(ln) >= 2]
            for Q, plines in pockets:
                if Q is not None and s + 4.0 * simp <= rho:
                    shapely.prepare(Q)
                    out = [ln for ln in plines if len(ln) >= 2
                           and not Q.covers(shapely.linestrings(ln))]
                    parts.append(Q.buffer(rho, quad_segs=QUAD_SEGS))
                    loose += out
                else:
                    loose += [ln for ln in plines if len(ln) >= 2]
            if loose:
                # inscribed polygons: contained in the true swept discs
                parts.append(shapely.multilinestrings([shapely.linestrings(ln) for ln in loose])
                             .buffer(rho, quad_segs=QUAD_SEGS))
            return unary_union(parts) if parts else empty

        rho = _cleared_radius(tool, tolerance)
        self.cleared = swept(rho)
        low = self.cleared if tool.corner_radius <= 0 else swept(_cleared_radius(tool, 0.5 * clr))
        self.free = unary_union([low, outside])
        shapely.prepare(self.free)


def plan_rough(spec, surface, tool: Tool | None = None, *, ws=None, sets=None, timings=None) -> Operation:
    """The roughing operation (module docstring). ``tool``: default the spec's roughing tool."""
    import shapely
    from shapely.geometry import LineString, Point, box
    from shapely.ops import polylabel

    t0 = time.process_time()
    m, rg = spec.machining, spec.roughing
    tool = tool or spec_tools(spec)[int(rg.tool)]
    ws = ws or WorkSurface(surface)
    L, W = ws.L, ws.W
    R = tool.radius
    step, s, leave = float(rg.stepdown), float(rg.stepover), float(rg.leave)
    tolerance = float(m.tolerance)
    safe_z = float(m.safe_height)
    clr = min(LINK_CLEARANCE, safe_z)
    lim = min(float(spec.stock.depth_limit), float(tool.reach))
    if sets is None:
        sets = design_sets(ws, R, tolerance, leave, lim)
    bottom = float(sets.H.min()) + leave          # the lowest allowance on the grid
    # the allowance bound held strictly: the tool stands at most 2 e + Delta (vertical)
    # and the dilations' chord + twice the loops' inset (horizontal, x the slope m) higher
    # than it could; the inset shrinks (down to a tenth of the tolerance) until that stays
    # within the tolerance on the steepest wall the levels cut, and what it cannot bring
    # within comes off the level step (leave + step + that error <= leave + stepdown + tol)
    m_max = _band_slope(sets, -lim - leave - 1.0)
    chord = R * (1.0 / math.cos(math.pi / (4 * QUAD_SEGS)) - 1.0)
    delta0 = _ladder(tool)[1]
    room = tolerance - 2 * sets.err - delta0 - chord * m_max
    simp = LOOP_INSET * tolerance if m_max <= 0 else \
        min(LOOP_INSET * tolerance, max(0.1 * tolerance, room / (2.0 * m_max)))
    excess = 2 * sets.err + delta0 + (chord + 2 * simp) * m_max
    step_eff = step - max(0.0, excess - tolerance - 1e-12)
    if step_eff < 0.5 * step:
        step_eff = 0.5 * step     # (a wall steeper than the guards' slope cap: the check states the rest)
    # a bull nose's or ball's corner standing beyond the stock's edge (its flat clear of
    # it) cuts the edge's allowance from a tip up to the corner radius below the lowest
    # allowance: a groove or basin running out through the edge is reached only so. The
    # levels go on to there (the last within a step of it), so that wherever the tool
    # reaches, a level lies within a step above the tip that reaches (a 10 mm bull nose,
    # corner 2, left a groove's end 0.2 mm above leave + stepdown when they stopped at the
    # lowest allowance); below the lowest allowance the allowed centres lie beyond the edge
    low = bottom - float(tool.corner_radius)
    levels = []
    k = 1
    while True:
        z = -k * step_eff
        if z <= low - 1e-9 or z < -lim - 1e-9:
            z = max(z, -lim)
            if z <= low + 1e-9 or (levels and z >= levels[-1] - 1e-9):
                break
            levels.append(z)
            break
        levels.append(z)
        k += 1
    e_out = max(0.0, R - 0.5 * s)
    F = box(0.0, 0.0, L, W)
    # centres whose disc meets the stock: up to R beyond its edges a tool still cuts them
    # (the whole job's check takes its reach so; within R - s/2 a wall meeting the edge was
    # left up to a stepdown and more above its bound there); beyond its corners only as far
    e_reach = max(0.0, R - simp)
    outer = box(0.0, 0.0, L, W).buffer(e_reach, quad_segs=QUAD_SEGS) if e_reach > 0 else box(0.0, 0.0, L, W)
    big = box(-10 * R - L, -10 * R - W, 2 * L + 10 * R, 2 * W + 10 * R)
    outside = big.difference(F)
    path = _Path()
    above = None              # the level above (_Level); None: the top face
    fig = {"loops": 0, "pockets": 0, "helix": 0, "ramp": 0, "plunge_entries": 0, "from_outside": 0,
           "from_cleared": 0, "lifts_low": 0, "lifts_safe": 0}
    cleared_levels = []
    delta = 0.0
    t_geom = 0.0
    angle = math.tan(math.radians(ENTRY_ANGLE_DEG))

    def link_to(b_xy, z_level, z_above):
        """Rapid from the current point to above b, ready to enter at z_above + clr."""
        a = path.at
        z_low = z_above + clr
        if a is None:
            path.add((b_xy[0], b_xy[1], safe_z), RAPID)
            path.add((b_xy[0], b_xy[1], max(clr, z_low)), RAPID)
            if z_low < clr:
                _descend_to(b_xy, z_low)
            return
        seg = LineString([(a[0], a[1]), (b_xy[0], b_xy[1])]) if math.hypot(a[0] - b_xy[0], a[1] - b_xy[1]) > 1e-9 \
            else Point(a[0], a[1])
        low_ok = above is None or above.free.covers(seg.buffer(R, quad_segs=8))
        if low_ok and z_low <= safe_z:
            fig["lifts_low"] += 1
            path.add((a[0], a[1], max(z_low, a[2])), RAPID)
            path.add((b_xy[0], b_xy[1], max(z_low, a[2])), RAPID)
            path.add((b_xy[0], b_xy[1], z_low), RAPID)
        else:
            fig["lifts_safe"] += 1
            path.add((a[0], a[1], safe_z), RAPID)
            path.add((b_xy[0], b_xy[1], safe_z), RAPID)
            path.add((b_xy[0], b_xy[1], max(clr, z_low)), RAPID)
            if z_low < clr:
                _descend_to(b_xy, z_low)

    def _descend_to(b_xy, z_low):
        # below the top face: rapid only where the level above cleared the tool's disc
        if above is not None and above.free.covers(Point(b_xy[0], b_xy[1]).buffer(R, quad_segs=8)):
            path.add((b_xy[0], b_xy[1], z_low), RAPID)
        else:
            path.add((b_xy[0], b_xy[1], z_low), PLUNGE)

    def enter(ring_xy, closed, z, z_above, how, pole=None, r_h=0.0):
        """Enter at ring_xy[0] from z_above + clr down to z."""
        z0 = z_above + clr
        drop = z0 - z
        if how == "helix" and pole is not None and r_h > 0:
            fig["helix"] += 1
            c = np.asarray(pole, float)
            d = ring_xy[0] - c
            nd = float(np.hypot(*d))
            a0 = math.atan2(d[1], d[0]) if nd > 1e-12 else 0.0
            start = c + r_h * np.array([math.cos(a0), math.sin(a0)])
            link_to(start, z, z_above)
            turns = drop / (2 * math.pi * r_h * angle)
            nt = max(1, int(math.ceil(turns * HELIX_SEGS)))
            th = a0 + np.linspace(0.0, 2 * math.pi * turns, nt + 1)[1:]
            zz = z0 - drop * np.arange(1, nt + 1) / nt
            for ti, zi in zip(th, zz):
                path.add((c[0] + r_h * math.cos(ti), c[1] + r_h * math.sin(ti), zi), PLUNGE)
            th = th[-1] + np.linspace(0.0, 2 * math.pi, HELIX_SEGS + 1)[1:]
            circ = np.column_stack([c[0] + r_h * np.cos(th), c[1] + r_h * np.sin(th)])
            path.cut_xy(circ, z)
            path.cut_xy(np.vstack([circ[-1], ring_xy[0]]), z)
            return
        link_to(ring_xy[0], z, z_above)
        if how == "ramp":
            fig["ramp"] += 1
            w = _walk(ring_xy, drop / angle, closed)
            for x, y, sl in w[1:]:
                path.add((x, y, z0 - drop * sl / w[-1, 2]), PLUNGE)
            if closed:
                return          # the caller cuts the loop from here: a whole lap at the level
            for x, y, _ in w[::-1]:
                path.add((x, y, z), CUT)
            return
        fig["plunge_entries"] += 1
        path.add((ring_xy[0][0], ring_xy[0][1], z), PLUNGE)

    for k, z in enumerate(levels):
        tg = time.process_time()
        A, delta = allowed_region(sets, tool, z, leave, outer)
        pockets = [p for p in _polys(A) if p.area > 1e-6]
        t_geom += time.process_time() - tg
        z_above = 0.0 if above is None else above.z
        path.level_lines = []
        # pockets in order of their lowest x, y (a stable, short tour)
        pockets.sort(key=lambda p: (round(p.bounds[0], 3), round(p.bounds[1], 3)))
        done = []                 # per pocket: (the region its loops bound, its cut lines)
        for P in pockets:
            shapely.prepare(P)
            fig["pockets"] += 1
            n0 = len(path.level_lines)
            open_ = not P.difference(F.buffer(0.25 * e_out, join_style=2)).is_empty if e_out > 0 else False
            inset = None
            if rg.strategy == "raster":
                _raster_pocket(P, z, z_above, s, R, spec, path, enter, link_to, fig, F, open_, simp)
            else:
                tree = _erosion_tree(P, s, simp)
                inset = tree.inset         # P eroded and simplified: its loops' region too
                if open_:
                    _cut_outside_in(tree, P, z, z_above, path, enter, link_to, fig, F, R, e_out)
                else:
                    _cut_inside_out(tree, P, z, z_above, path, enter, link_to, fig, R, rg.entry, polylabel, s)
            done.append((_ring_region(P, simp, inset), path.level_lines[n0:]))
            del path.level_lines[n0:]
        tg = time.process_time()
        above = _Level(z, path.level_lines, tool, outside, tolerance, clr, done, s, simp)
        cleared_levels.append(above)
        t_geom += time.process_time() - tg
    if path.pts:
        a = path.at
        path.add((a[0], a[1], safe_z), RAPID)
    pts = np.array(path.pts, float).reshape(-1, 3)
    kinds = np.array(path.kinds, np.int8)
    tp = Toolpath(pts, kinds, tool_radius=R, safe_z=safe_z)
    feed, plunge = feeds_of(spec, tool)
    info = _figures(pts, kinds, feed, plunge)
    cusp = step_eff + _stepover_cusp(tool, s)
    info.update({
        "tool": tool.describe(), "levels": len(levels), "level_z_mm": [round(v, 4) for v in levels],
        "loops": fig["loops"], "pockets": fig["pockets"], "stepdown_mm": step, "stepover_mm": s,
        "leave_mm": leave, "cusp_mm": cusp, "strategy": rg.strategy, "entry": rg.entry,
        "entries": {k2: fig[k2] for k2 in ("helix", "ramp", "plunge_entries", "from_outside", "from_cleared")},
        "links": {"low": fig["lifts_low"], "safe_height": fig["lifts_safe"]},
        "grid_step_mm": float(max(sets.hx, sets.hy)), "level_set_error_mm": 2 * sets.err,
        "allowance_excess_mm": 2 * sets.err + delta, "loop_inset_mm": 2 * simp,
        # horizontal: the dilations' circumscribed polygons and the loops' inset keep the
        # tool up to this much farther from the level set than it could stand; on a wall of
        # slope m the material left grows by m times it (the stock check adds it)
        "allowance_offset_mm": chord + 2 * simp, "depth_limit_mm": lim,
        "level_step_mm": step_eff, "steepest_slope": m_max,
        "stopped_at_limit": bool(levels and levels[-1] <= -lim + 1e-9 and bottom < -lim),
        "plan_seconds": time.process_time() - t0,
    })
    if timings is not None:
        timings["rough_geometry_s"] = t_geom
    tp.info = info
    op = Operation("rough", tool, tp, leave=leave, levels=len(levels), passes=fig["loops"], info=info)
    op.cleared = cleared_levels      # per level: z and the cleared region (for the rest passes)
    op.sets = sets
    return op


def _band_slope(sets, low: float) -> float:
    """The steepest slope of the design (grid differences) where it lies between ``low``
    and the top face: the walls the levels cut. At most 20 (beyond, a wall is cut by its rim)."""
    H = np.ascontiguousarray(sets.H, dtype=float)
    if min(H.shape) < 2:
        return 0.0
    from ..cut.stock_kernels import band_max_slope

    # numpy.gradient's differences, one pass (tests/test_roughing.py: the same to the bit)
    best = float(band_max_slope(H, float(sets.hy), float(sets.hx), float(low), 0.0))
    return 0.0 if best < 0.0 else float(min(20.0, best))


def design_sets(ws, R, tolerance, leave, lim):
    band = (-lim - leave - 1.0, 0.0)
    # 2 e within half the tolerance: the other half for the dilations' chords and the loops'
    # inset on the walls (plan_rough), so that the levels keep their step where they can
    h, coarse = grid_step(ws, R, 0.5 * tolerance, band)
    if abs(h - min(1.0, R / 4)) < 1e-12:
        return coarse
    return LevelSets(ws, h, band)


def _stepover_cusp(tool: Tool, s: float) -> float:
    """Material a floor keeps between loops s apart: 0 for a flat end mill (s <= D)."""
    r, f = tool.corner_radius, tool.flat_radius
    half = 0.5 * s - f
    if r <= 0 or half <= 0:
        return 0.0
    half = min(half, r)
    return r - math.sqrt(r * r - half * half)


def plan_operations(spec, surface, finish: Toolpath) -> list[Operation]:
    """The operations before the finish: [rough, rest...] (empty without a
    ``roughing`` section; an operation with nothing to cut is left out). ``finish``:
    the finishing toolpath (its pass plan gives the rest passes' geometry).

    The rough operation also carries ``cleared`` (per level: ``z`` and the ``cleared``
    region, shapely) and ``sets`` (the design grid); :func:`stock_after` gives the
    stock's height field after it."""
    if not spec.has("roughing"):
        return []
    ws = WorkSurface(surface)
    rough = plan_rough(spec, surface, ws=ws)
    rest = plan_rest(spec, surface, rough, finish, ws=ws)
    # an operation with nothing to cut (a design shallower than leave + one stepdown) is left out
    return ([rough] if rough.levels else []) + rest
