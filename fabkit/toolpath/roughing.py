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

Rest passes (:func:`plan_rest`): the stock after roughing is a height field on the
grid (each level's cleared region at its Z; conservatively the highest of a cell's
neighbours). A rest ball's passes follow the finishing passes (their exact
drop-cutter heights; another ball's own, :func:`compensate`), at most R apart, in
Z levels of its depth of cut less the cusp between its passes, tip at
max(level, design contact + leave), only where its drop onto the roughed stock
stands more than min(stepdown, finish depth_of_cut - leave) + tolerance above the
allowance (a grid bound, then the exact drop onto the levels' polygons; one node
either side), and, either side of a finishing pass between two rest passes, where that
pass would engage more than the finishing depth of cut: the valleys and corners the
roughing tool could not reach, and staircases deeper than the finish may cut. A ball's
engagement is the stock's thickness it cuts through, max over q under it of
S(q) - (tip + lift(|q - c|)): elsewhere the finishing ball's is at most leave + that
threshold <= its depth of cut; where the rest passes ran, leave + their cusp.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..errors import SpecError
from .compensate import WorkSurface, compensate
from .operations import Operation
from .passes import AIR_EPS, Frame
from .path import CUT, PLUNGE, RAPID, Toolpath
from .tools import Tool

__all__ = ["spec_tools", "finish_tool", "depth_of_cut", "plan_operations", "plan_rough", "plan_rest",
           "LevelSets", "allowed_region", "ENTRY_ANGLE_DEG"]

ENTRY_ANGLE_DEG = 5.0       # helix and ramp descent angle (foam and wood: 3-10 degrees)
HELIX_FRACTION = 0.5        # helix radius: at most this x the tool radius
QUAD_SEGS = 32              # polygon segments per quarter circle in the dilations
LADDER_MAX = 24             # lift steps of a bull nose / ball allowance
GRID_MAX_NODES = 1_500_000  # the design grid of the level sets
LINK_CLEARANCE = 1.0        # mm above the level above for links and the start of entries
HELIX_SEGS = 24             # points per helix turn
LOOP_INSET = 1.0            # x machining.tolerance: loops eroded by it and simplified within it


# ----------------------------------------------------------------------------
# tools of the spec
# ----------------------------------------------------------------------------
def finish_tool(spec) -> Tool:
    """The finishing ball of the ``tool`` section."""
    t = spec.tool
    return Tool.ball(float(t.diameter), reach=float(t.reach), number=t.number)


def spec_tools(spec) -> dict[int, Tool]:
    """Every numbered tool of the spec: the ``tools`` list and the finishing ``tool``
    (when it has a number), by tool number. Feeds None mean the machining section's."""
    out = {}
    if spec.has("tool") and spec.tool.number is not None:
        out[int(spec.tool.number)] = finish_tool(spec)
    for t in (spec.tools if spec.has("tools") else ()):
        out[int(t.number)] = Tool(t.shape, float(t.diameter),
                                  float(t.corner_radius or 0.0), reach=float(t.reach), number=int(t.number),
                                  feed=t.feed, plunge=t.plunge, spindle=t.spindle)
    return out


def depth_of_cut(spec, number) -> float:
    """The axial depth of cut (mm) of tool ``number`` (None: the finishing tool)."""
    if number is None or (spec.tool.number is not None and number == spec.tool.number):
        return float(spec.tool.depth_of_cut)
    for t in spec.tools:
        if t.number == number:
            return float(t.depth_of_cut)
    raise KeyError(number)


def _feeds(spec, tool: Tool) -> tuple[float, float]:
    m = spec.machining
    return float(tool.feed or m.feed), float(tool.plunge or m.plunge)


# ----------------------------------------------------------------------------
# geometry helpers (shapely)
# ----------------------------------------------------------------------------
def _parts(g, kind: str):
    """The non-empty parts of type ``kind`` ('Polygon', 'LineString') of a geometry
    (single, multi-part or collection, at any depth)."""
    if g is None or g.is_empty:
        return []
    if g.geom_type == kind:
        return [g]
    if hasattr(g, "geoms"):
        return [p for sub in g.geoms for p in _parts(sub, kind)]
    return []


def _polys(g):
    """The polygons of a geometry (Polygon, MultiPolygon, collection), non-empty."""
    return _parts(g, "Polygon")


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
        X, Y = np.meshgrid(self.x, self.y)
        H = ws.H(X, Y)
        H = np.where(np.isfinite(H), H, 1e9)          # unreadable: kept (material)
        self.H = H
        lo, hi = band
        rel = (H >= lo - 1.0) & (H <= hi + 1.0)
        hxx = np.abs(H[:, 2:] - 2 * H[:, 1:-1] + H[:, :-2]) / self.hx ** 2
        hyy = np.abs(H[2:, :] - 2 * H[1:-1, :] + H[:-2, :]) / self.hy ** 2
        hxy = np.abs(H[1:, 1:] - H[1:, :-1] - H[:-1, 1:] + H[:-1, :-1]) / (self.hx * self.hy)
        cxx = float(hxx[rel[:, 1:-1]].max()) if rel[:, 1:-1].any() else 0.0
        cyy = float(hyy[rel[1:-1, :]].max()) if rel[1:-1, :].any() else 0.0
        cxy = float(hxy[rel[1:, 1:]].max()) if rel[1:, 1:].any() else 0.0
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
# moves
# ----------------------------------------------------------------------------
class _Path:
    """Points and move kinds being built, with the cut lines of the current level."""

    def __init__(self):
        self.pts: list = []
        self.kinds: list = []
        self.level_lines: list = []

    @property
    def at(self):
        return self.pts[-1] if self.pts else None

    def add(self, p, kind):
        p = (float(p[0]), float(p[1]), float(p[2]))
        if self.pts and max(abs(a - b) for a, b in zip(p, self.pts[-1])) < 1e-9:
            return
        self.pts.append(p)
        self.kinds.append(kind)

    def cut_xy(self, xy, z):
        for q in xy:
            self.add((q[0], q[1], z), CUT)
        if len(xy) >= 2:
            self.level_lines.append(np.asarray(xy, float))


def _ring_from(ring: np.ndarray, p) -> np.ndarray:
    """The closed ring (k, 2) rotated to start (and end) at its point nearest p."""
    from shapely.geometry import LineString, Point

    ls = LineString(ring)
    d = ls.project(Point(p[0], p[1]))
    q = ls.interpolate(d)
    seg = np.cumsum(np.r_[0.0, np.hypot(*np.diff(ring, axis=0).T)])
    i = int(np.searchsorted(seg, d, side="right"))
    i = min(max(i, 1), len(ring) - 1)
    start = np.array([q.x, q.y])
    body = np.vstack([ring[i:-1], ring[:i]]) if i < len(ring) - 1 else ring[:-1]
    out = np.vstack([start, body, start])
    keep = np.r_[True, np.hypot(*np.diff(out, axis=0).T) > 1e-9]
    return out[keep]


def _walk(path: np.ndarray, length: float, closed: bool) -> np.ndarray:
    """Points along ``path`` (k, 2) over ``length`` mm from its start (cyclically if
    closed, back and forth if open), with their arc lengths: (m, 3) [x, y, s]."""
    seg = np.hypot(*np.diff(path, axis=0).T)
    per = float(seg.sum())
    if per <= 1e-9:
        return np.array([[path[0, 0], path[0, 1], 0.0], [path[0, 0], path[0, 1], length]])
    out, s = [(path[0, 0], path[0, 1], 0.0)], 0.0
    fwd = True
    while s < length - 1e-12:
        idx = range(1, len(path)) if (closed or fwd) else range(len(path) - 2, -1, -1)
        prev = path[0] if (closed or fwd) else path[-1]
        for i in idx:
            q = path[i]
            d = float(math.hypot(q[0] - prev[0], q[1] - prev[1]))
            if s + d >= length:
                t = (length - s) / d if d > 0 else 1.0
                out.append((prev[0] + t * (q[0] - prev[0]), prev[1] + t * (q[1] - prev[1]), length))
                s = length
                break
            s += d
            out.append((q[0], q[1], s))
            prev = q
        if not closed:
            fwd = not fwd
    return np.array(out)


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


def _ring_region(poly, simp=0.0):
    """The region the loops of :func:`_rings` (poly, simp) bound: their polygons."""
    from shapely.ops import unary_union

    if simp > 0:
        out = []
        for q in _polys(poly.buffer(-simp, quad_segs=QUAD_SEGS)):
            q = q.simplify(0.99 * simp, preserve_topology=True)
            if len(q.exterior.coords) >= 4:
                out.append(q)
        if out:
            return unary_union(out)
    return poly


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
    levels = []
    k = 1
    while True:
        z = -k * step
        if z <= bottom - 1e-9 or z < -lim - 1e-9:
            z = max(z, -lim)
            if z <= bottom + 1e-9 or (levels and z >= levels[-1] - 1e-9):
                break
            levels.append(z)
            break
        levels.append(z)
        k += 1
    e_out = max(0.0, R - 0.5 * s)
    simp = LOOP_INSET * tolerance     # loops eroded by it and simplified within it (_rings)
    F = box(0.0, 0.0, L, W)
    outer = box(-e_out, -e_out, L + e_out, W + e_out)
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
            if rg.strategy == "raster":
                _raster_pocket(P, z, z_above, s, R, spec, path, enter, link_to, fig, F, open_, simp)
            else:
                tree = _erosion_tree(P, s, simp)
                if open_:
                    _cut_outside_in(tree, P, z, z_above, path, enter, link_to, fig, F, R, e_out)
                else:
                    _cut_inside_out(tree, P, z, z_above, path, enter, link_to, fig, R, rg.entry, polylabel, s)
            done.append((_ring_region(P, simp), path.level_lines[n0:]))
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
    feed, plunge = _feeds(spec, tool)
    info = _figures(pts, kinds, feed, plunge)
    cusp = step + _stepover_cusp(tool, s)
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
        "allowance_offset_mm": R * (1.0 / math.cos(math.pi / (4 * QUAD_SEGS)) - 1.0) + 2 * simp, "depth_limit_mm": lim,
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


def design_sets(ws, R, tolerance, leave, lim):
    band = (-lim - leave - 1.0, 0.0)
    h, coarse = grid_step(ws, R, tolerance, band)
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


def _figures(pts, kinds, feed, plunge) -> dict:
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1) if len(pts) > 1 else np.zeros(0)
    k = kinds[1:] if len(kinds) > 1 else np.zeros(0, np.int8)
    cut, plg, rap = float(seg[k == CUT].sum()), float(seg[k == PLUNGE].sum()), float(seg[k == RAPID].sum())
    return {"points": int(len(pts)), "cutting_length_mm": cut + plg, "plunge_length_mm": plg,
            "rapid_length_mm": rap,
            "time_by_length_feed_s": 60.0 * (cut / feed + plg / plunge),
            "time_model": "cutting length / feed + plunge length / plunge feed (rapids not counted)"}


class _Node:
    __slots__ = ("poly", "depth", "children", "rings")

    def __init__(self, poly, depth, simp=0.0):
        self.poly, self.depth, self.children = poly, depth, []
        self.rings = _rings(poly, simp)


def _erosion_tree(P, s, simp=0.0):
    """P's components eroded by i x s, as a tree (children inside their parent)."""
    root = _Node(P, 0, simp)
    stack = [root]
    while stack:
        node = stack.pop()
        E = node.poly.buffer(-s, quad_segs=QUAD_SEGS)
        for q in _polys(E):
            if q.area <= 1e-6:
                continue
            ch = _Node(q, node.depth + 1, simp)
            node.children.append(ch)
            stack.append(ch)
    return root


def _rings(poly, simp=0.0):
    """The loops of a polygon (exterior first). ``simp`` > 0: of the polygon eroded by
    ``simp`` and simplified within it (Douglas-Peucker, 0.99 simp): inside the polygon,
    at most 2 simp inside its boundary, with far fewer points than the contour's grid."""
    if simp > 0:
        out = []
        for q in _polys(poly.buffer(-simp, quad_segs=QUAD_SEGS)):
            q = q.simplify(0.99 * simp, preserve_topology=True)
            out += [np.asarray(q.exterior.coords)] + [np.asarray(r.coords) for r in q.interiors]
        out = [r for r in out if len(r) >= 4]
        if out:
            return out
    out = [np.asarray(poly.exterior.coords)]
    out += [np.asarray(r.coords) for r in poly.interiors]
    return [r for r in out if len(r) >= 3]


def _go(path, P, b_xy, z, z_above, link_to, enter, fig):
    """From the current point to b at level z: a straight feed inside P, else a lift."""
    from shapely.geometry import LineString

    a = path.at
    if a is not None and abs(a[2] - z) < 1e-9:
        if math.hypot(a[0] - b_xy[0], a[1] - b_xy[1]) < 1e-9:
            return
        seg = LineString([(a[0], a[1]), (b_xy[0], b_xy[1])])
        if P.buffer(1e-7).covers(seg):
            path.cut_xy(np.array([[a[0], a[1]], [b_xy[0], b_xy[1]]]), z)
            return
    # lift and come down over ground this level cleared (the tool's centre within R of its cuts)
    link_to(b_xy, z, z_above)
    fig["from_cleared"] += 1
    path.add((b_xy[0], b_xy[1], z), PLUNGE)


def _post_order(root):
    """The tree's nodes, children (in order) before their parent: no recursion (a tree
    as deep as the pocket's inradius / stepover)."""
    out, stack = [], [(root, False)]
    while stack:
        node, seen = stack.pop()
        if seen:
            out.append(node)
            continue
        stack.append((node, True))
        stack.extend((ch, False) for ch in reversed(node.children))
    return out


def _pre_order(root):
    """The tree's nodes, each before its children (in order): no recursion."""
    out, stack = [], [root]
    while stack:
        node = stack.pop()
        out.append(node)
        stack.extend(reversed(node.children))
    return out


def _cut_inside_out(tree, P, z, z_above, path, enter, link_to, fig, R, how, polylabel, s):
    for node in _post_order(tree):
        for j, ring in enumerate(node.rings):
            if not node.children and j == 0:
                # an innermost loop: material all round it at this level
                pole = polylabel(node.poly, tolerance=max(1e-3, 0.01 * R))
                d = node.poly.exterior.distance(pole) if node.poly.interiors == [] else node.poly.boundary.distance(pole)
                r_h = min(HELIX_FRACTION * R, d + node.depth * s - 1e-6)
                ring = _ring_from(ring, _nearest_on(node.poly.exterior, pole))
                use = how
                if how == "helix" and r_h < 0.1 * R:
                    use = "ramp"
                enter(ring, True, z, z_above, use, (pole.x, pole.y), max(r_h, 0.0))
                ring = _ring_from(ring, path.at[:2])
                fig["loops"] += 1
                path.cut_xy(ring, z)
                continue
            a = path.at
            ring = _ring_from(ring, a[:2])
            _go(path, P, ring[0], z, z_above, link_to, enter, fig)
            fig["loops"] += 1
            path.cut_xy(ring, z)


def _nearest_on(line, pt):
    q = line.interpolate(line.project(pt))
    return (q.x, q.y)


def _cut_outside_in(tree, P, z, z_above, path, enter, link_to, fig, F, R, e_out):
    """A pocket reaching beyond the stock: enter from outside it (the tool's centre
    over air), loops from the outermost in."""
    first = True
    for node in _pre_order(tree):
        for j, ring in enumerate(node.rings):
            if first:
                # the ring point farthest outside the footprint
                dx = np.maximum(np.maximum(-ring[:, 0], ring[:, 0] - F.bounds[2]), 0.0)
                dy = np.maximum(np.maximum(-ring[:, 1], ring[:, 1] - F.bounds[3]), 0.0)
                i = int(np.argmax(np.hypot(dx, dy)))
                ring = _ring_from(ring, ring[i])
                link_to(ring[0], z, z_above)
                path.add((ring[0][0], ring[0][1], z), PLUNGE)
                fig["from_outside"] += 1
                first = False
            else:
                ring = _ring_from(ring, path.at[:2])
                _go(path, P, ring[0], z, z_above, link_to, enter, fig)
            fig["loops"] += 1
            path.cut_xy(ring, z)


def _raster_pocket(P, z, z_above, s, R, spec, path, enter, link_to, fig, F, open_, simp=0.0):
    """Rows along machining.direction, s apart, then the pocket's boundary loops. A
    row whose start is not within 0.95 R of this level's cuts is entered as asked (a
    helix has no room at a row's end: a ramp along the row)."""
    from shapely.geometry import LineString, MultiLineString, Point

    x0, y0, x1, y1 = P.bounds
    along_x = spec.machining.direction == "x"
    lo, hi = (y0, y1) if along_x else (x0, x1)
    n = max(1, int(math.ceil((hi - lo) / s)))
    vs = lo + (np.arange(n + 1) if n > 0 else np.array([0.5])) * (hi - lo) / n
    rows = []
    for i, v in enumerate(vs):
        ln = LineString([(x0 - 1, v), (x1 + 1, v)] if along_x else [(v, y0 - 1), (v, y1 + 1)])
        segs = [np.asarray(g.coords) for g in _parts(ln.intersection(P), "LineString")]
        segs.sort(key=lambda a: a[:, 0 if along_x else 1].min())
        if i % 2:
            segs = [a[::-1] for a in segs[::-1]]
        rows.extend(segs)
    cut_lines = []
    how = spec.roughing.entry
    for seg in rows:
        if len(seg) < 2:
            continue
        a = path.at
        # the centre over ground this level cleared (the disc of an earlier row covers it
        # with 5 % of R to spare: an end mill does not cut at its very centre)
        near = cut_lines and MultiLineString([c.tolist() for c in cut_lines]).distance(Point(seg[0])) <= 0.95 * R
        if a is not None and abs(a[2] - z) < 1e-9 and near:
            _go(path, P, seg[0], z, z_above, link_to, enter, fig)
        elif open_ and (seg[0][0] < 0 or seg[0][1] < 0 or seg[0][0] > F.bounds[2] or seg[0][1] > F.bounds[3]):
            link_to(seg[0], z, z_above)
            path.add((seg[0][0], seg[0][1], z), PLUNGE)
            fig["from_outside"] += 1
        else:
            enter(seg, False, z, z_above, "plunge" if how == "plunge" else "ramp")
        fig["loops"] += 1
        path.cut_xy(seg, z)
        cut_lines.append(seg)
    for ring in _rings(P, simp):
        ring = _ring_from(ring, path.at[:2])
        _go(path, P, ring[0], z, z_above, link_to, enter, fig)
        fig["loops"] += 1
        path.cut_xy(ring, z)


# ----------------------------------------------------------------------------
# the stock after roughing, and rest passes
# ----------------------------------------------------------------------------
def stock_after(rough: Operation) -> np.ndarray:
    """The stock's top (work mm, <= 0) after roughing on the design grid
    (``rough.sets.x``, ``.y``): each level's cleared region at its Z (cv2 fills
    the polygons' pixels), then the highest of each node's neighbours: an upper
    bound of the material a cell holds."""
    import cv2
    from scipy.ndimage import maximum_filter

    sets = rough.sets
    ny, nx = len(sets.y), len(sets.x)
    S = np.zeros((ny, nx))
    shift = 4
    scale = np.array([1.0 / sets.hx, 1.0 / sets.hy]) * (1 << shift)
    for lev in rough.cleared:
        mask = np.zeros((ny, nx), np.uint8)
        for poly in _polys(lev.cleared):
            rings = [np.round(np.asarray(r.coords)[:, :2] * scale).astype(np.int32)
                     for r in [poly.exterior, *poly.interiors]]
            cv2.fillPoly(mask, rings[:1], 1, lineType=cv2.LINE_8, shift=shift)
            if len(rings) > 1:
                cv2.fillPoly(mask, rings[1:], 0, lineType=cv2.LINE_8, shift=shift)
        S = np.where(mask.astype(bool), np.minimum(S, lev.z), S)
    return maximum_filter(S, size=3, mode="nearest")


def drop_on_grid(S, x, y, X, Y, tool: Tool, slack: float = 0.0) -> np.ndarray:
    """The tip height at which ``tool`` standing at (X, Y) first touches the stock
    height field S (grid x, y; no material beyond it): max over grid nodes q within
    the tool's radius + one cell diagonal of S(q) - lift(|q - c| - diagonal), an
    upper bound of the exact drop (the node stands for its cell). -inf: no material.
    ``slack`` (mm): the bound holds for every centre within it of (X, Y) too."""
    hx, hy = x[1] - x[0], y[1] - y[0]
    diag = math.hypot(hx, hy) + slack
    R = tool.radius
    ni, nj = int(math.ceil((R + diag) / hy)), int(math.ceil((R + diag) / hx))
    di, dj = np.meshgrid(np.arange(-ni, ni + 1), np.arange(-nj, nj + 1), indexing="ij")
    rho = np.hypot(di * hy, dj * hx)
    ok = rho - diag <= R
    di, dj = di[ok], dj[ok]
    lift = tool.lift(np.clip(rho[ok] - diag, 0.0, R))
    X, Y = np.asarray(X, float), np.asarray(Y, float)
    i0 = np.rint(Y / hy).astype(np.int64)
    j0 = np.rint(X / hx).astype(np.int64)
    out = np.full(X.shape, -np.inf)
    ny, nx = S.shape
    for a in range(0, X.size, 4096):
        ii = i0.ravel()[a:a + 4096, None] + di[None, :]
        jj = j0.ravel()[a:a + 4096, None] + dj[None, :]
        inside = (ii >= 0) & (ii < ny) & (jj >= 0) & (jj < nx)
        v = np.where(inside, S[np.clip(ii, 0, ny - 1), np.clip(jj, 0, nx - 1)] - lift[None, :], -np.inf)
        out.ravel()[a:a + 4096] = v.max(axis=1)
    return out


def drop_on_levels(rough: Operation, ws, X, Y, tool: Tool, need=None) -> np.ndarray:
    """The tip height at which ``tool`` at (X, Y) first touches the stock the roughing
    left: the levels' cleared regions C_k are nested, material stands at or above
    z_{k-1} on F minus C_k, so the drop is max over k of z_{k-1} - lift(distance to
    F minus C_k), and z_n - lift(distance to F) (the last level's floor). Exact for
    the polygons (C_k inscribed in the swept discs: an upper bound). ``need``: a
    level is skipped where its term cannot exceed it (only whether the drop exceeds
    ``need`` is asked)."""
    import shapely
    from shapely.geometry import box

    F = box(0.0, 0.0, ws.L, ws.W)
    pts = shapely.points(X, Y)
    out = tool.lift(np.asarray(shapely.distance(pts, F), float))
    out = np.where(np.isfinite(out), (rough.cleared[-1].z if rough.cleared else 0.0) - out, -np.inf)
    z_prev = 0.0
    for lev in rough.cleared:
        sel = np.ones(len(pts), bool) if need is None else (z_prev > need)
        if sel.any():
            U = F.difference(lev.cleared)
            if U.is_empty:
                z_prev = lev.z
                continue
            shapely.prepare(U)
            d = np.full(len(pts), np.inf)
            d[sel] = shapely.distance(pts[sel], U)
            with np.errstate(invalid="ignore"):
                term = z_prev - tool.lift(np.minimum(d, 1e9))
            out = np.maximum(out, np.where(np.isfinite(term), term, -np.inf))
        z_prev = lev.z
    return out


def plan_rest(spec, surface, rough: Operation, finish: Toolpath, *, ws=None) -> list[Operation]:
    """Rest operations, one per rest tool (``roughing.rest``, default the finishing
    ball), module docstring. Operations with nothing to cut are left out."""
    m, rg = spec.machining, spec.roughing
    ws = ws or WorkSurface(surface)
    plan = finish.plan
    if plan is None:
        raise ValueError("the finishing toolpath carries no pass plan")
    fr = Frame(m.direction, ws.L, ws.W)
    tools = spec_tools(spec)
    fin = finish_tool(spec)
    numbers = rg.rest if rg.rest else (fin.number,)
    leave = float(rg.leave)
    tolerance = float(m.tolerance)
    step_rough = float(rg.stepdown)
    doc_f = float(spec.tool.depth_of_cut)
    threshold = min(step_rough, doc_f - leave) + tolerance
    S = stock_after(rough)
    x, y = rough.sets.x, rough.sets.y
    safe_z = float(m.safe_height)
    clr = min(LINK_CLEARANCE, safe_z)
    ops = []
    for n in numbers:
        t0 = time.process_time()
        tool = fin if (n is None or n == fin.number) else tools[int(n)]
        is_fin = tool is fin
        Rr = tool.radius
        doc = depth_of_cut(spec, n)
        lim = min(float(spec.stock.depth_limit), float(tool.reach))
        # passes at most Rr apart
        V = np.array([p.v for p in plan.passes])
        sel = [0]
        while sel[-1] < len(V) - 1:
            i = sel[-1]
            j = int(np.searchsorted(V, V[i] + Rr, side="right")) - 1
            sel.append(max(j, i + 1))
        spacing = float(np.diff(V[sel]).max()) if len(sel) > 1 else 0.0
        cusp = Rr - math.sqrt(max(Rr * Rr - 0.25 * spacing * spacing, 0.0))
        step_r = doc - cusp
        if step_r <= 0:
            raise SpecError(f"rest passes {spacing:.3g} mm apart leave {cusp:.3g} mm cusps, more than the tool's "
                            "depth_of_cut", file=spec.path, key="roughing.rest")
        ug = plan.ug
        U = np.broadcast_to(ug, (len(sel), len(ug)))
        Vv = np.broadcast_to(V[sel][:, None], U.shape)
        X, Y = fr.xy(U, Vv)
        X, Y = np.ascontiguousarray(X, float), np.ascontiguousarray(Y, float)
        if is_fin:
            Z = np.vstack([plan.passes[i].Z for i in sel])
        else:
            Z = compensate(ws, X, Y, Rr)
        keep = np.vstack([plan.passes[i].keep for i in sel]) if is_fin else np.isfinite(Z)
        Sb = drop_on_grid(S, x, y, X, Y, tool)
        floor = np.maximum(Z + leave, -lim)
        with np.errstate(invalid="ignore"):
            zone = keep & np.isfinite(Z) & np.isfinite(Sb) & (Sb - (Z + leave) > threshold)
        # the grid's bound is loose beside the levels' walls: where it asks for rest
        # passes, the drop onto the levels' polygons instead (exact to their chords)
        # (the drop onto the levels skips the levels that cannot lift it above the zone's
        # threshold: below the threshold it is no bound; there the grid's bound stays, as
        # the links and the descent to a run's start need an upper bound of the stock)
        if zone.any():
            d = drop_on_levels(rough, ws, X[zone], Y[zone], tool, (Z + leave + threshold)[zone])
            with np.errstate(invalid="ignore"):
                hit = d - (Z + leave)[zone] > threshold
            Sb[zone] = np.where(hit, d, Sb[zone])
            zone[zone] = hit
        if is_fin and len(sel) < len(V):
            # the passes between: where the finishing ball would engage more than its depth of cut
            zone |= keep & np.isfinite(Z) & np.isfinite(Sb) & _between_zone(
                plan, fr, sel, V, ug, S, x, y, tool, rough, ws, leave, doc_f - leave)
        # one node more on either side: the finish's own points lie between the nodes
        # (1 mm apart), and across a groove the material it meets changes within one
        ok = keep & np.isfinite(Z) & np.isfinite(Sb)
        zone = ok & (zone | np.c_[zone[:, 1:], np.zeros((len(zone), 1), bool)]
                     | np.c_[np.zeros((len(zone), 1), bool), zone[:, :-1]])
        runs = []
        levels_cut = set()
        if zone.any():
            low = float(floor[zone].min())
            nlev = int(math.ceil(-low / step_r)) if low < 0 else 0
            for j in range(1, nlev + 1):
                zj, zp = -j * step_r, (-(j - 1) * step_r if j > 1 else math.inf)
                tip = np.maximum(zj, floor)
                prev = np.maximum(zp, floor)
                act = zone & (tip < np.minimum(Sb, prev) - AIR_EPS)
                for r in range(len(sel)):
                    a = act[r]
                    if not a.any():
                        continue
                    near = a | np.r_[a[1:], False] | np.r_[False, a[:-1]]
                    near &= zone[r]
                    edges = np.diff(np.r_[0, near.astype(np.int8), 0])
                    pieces = []
                    spans = []
                    for i0, i1 in zip(np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]):
                        if i1 - i0 < 2:
                            continue
                        # runs of a pass at most 4 R apart are joined along the nodes between at
                        # their tips: there the ball touches nothing (air above the roughed stock,
                        # or ground the level above took lower) and never the allowance
                        if spans and ug[i0] - ug[spans[-1][1] - 1] <= 4 * Rr \
                                and np.isfinite(tip[r, spans[-1][1]:i0]).all() and keep[r, spans[-1][1]:i0].all():
                            spans[-1] = (spans[-1][0], i1)
                        else:
                            spans.append((i0, i1))
                    for i0, i1 in spans:
                        pieces.append((np.column_stack([X[r, i0:i1], Y[r, i0:i1], tip[r, i0:i1]]),
                                       Sb[r, i0:i1]))
                    if r % 2:
                        pieces = [(q[::-1], sb[::-1]) for q, sb in pieces[::-1]]
                    runs.extend(pieces)
                    if pieces:
                        levels_cut.add(j)
        if not runs:
            continue
        runs = _refine_runs(ws, runs, Rr, leave, lim, 0.5 * tolerance)
        fig_low = 0
        zlink = _link_heights(S, x, y, runs, tool, clr)
        path = _Path()
        for n, (q, sb) in enumerate(runs):
            start = q[0]
            above = min(max(float(sb[0]), float(start[2])) + clr, safe_z)
            zl = zlink[n]
            if path.at is not None and zl is not None and zl < safe_z:
                fig_low += 1
                path.add((path.at[0], path.at[1], max(zl, path.at[2])), RAPID)
                path.add((start[0], start[1], max(zl, path.at[2])), RAPID)
            else:
                if path.at is not None:
                    path.add((path.at[0], path.at[1], safe_z), RAPID)
                path.add((start[0], start[1], safe_z), RAPID)
            path.add((start[0], start[1], above), RAPID)
            path.add(tuple(start), PLUNGE)
            for p in q[1:]:
                path.add(tuple(p), CUT)
        path.add((path.at[0], path.at[1], safe_z), RAPID)
        pts = np.array(path.pts, float)
        kinds = np.array(path.kinds, np.int8)
        tp = Toolpath(pts, kinds, tool_radius=Rr, safe_z=safe_z)
        feed, plunge = _feeds(spec, tool)
        info = _figures(pts, kinds, feed, plunge)
        levels_cut = len(levels_cut)
        info.update({
            "tool": tool.describe(), "levels": levels_cut, "stepdown_mm": step_r, "stepover_mm": spacing,
            "leave_mm": leave, "cusp_mm": cusp, "runs": len(runs),
            "passes": len({(round(float(q[0, 0]), 6), round(float(q[0, 1]), 6)) for q, _ in runs}),
            "entry": "plunge (into ground the rest ball's drop shows clear above the cut)",
            "links": {"low": fig_low, "safe_height": len(runs) - 1 - fig_low},
            "zone_threshold_mm": threshold, "zone_positions": int(zone.sum()),
            "depth_of_cut_mm": doc, "finish_depth_of_cut_mm": doc_f, "stock_grid_step_mm": float(max(x[1] - x[0], y[1] - y[0])),
            "plan_seconds": time.process_time() - t0,
        })
        tp.info = info
        ops.append(Operation("rest", tool, tp, leave=leave, levels=levels_cut, passes=len(runs), info=info))
    return ops


def _between_zone(plan, fr, sel, V, ug, S, x, y, tool, rough, ws, leave, threshold):
    """The zone asked by the finishing passes between the selected ones (sel): the
    finishing ball's drop at a position is not continuous across a steep wall, so a pass
    between two rest passes can meet more than the threshold where neither of them does
    (``threshold``: finish depth_of_cut - leave, the ball's engagement past its depth of
    cut; with roughing.stepdown 12.7 mm on the paper, 7.0 mm without this).
    Such a node marks the rest passes either side of its pass (at the same node of the
    common pass grid ``ug``). Returns a (len(sel), len(ug)) mask."""
    others = np.setdiff1d(np.arange(len(V)), np.asarray(sel))
    out = np.zeros((len(sel), len(ug)), bool)
    if not len(others):
        return out
    U = np.broadcast_to(ug, (len(others), len(ug)))
    X, Y = fr.xy(U, np.broadcast_to(V[others][:, None], U.shape))
    X, Y = np.ascontiguousarray(X, float), np.ascontiguousarray(Y, float)
    Z = np.vstack([plan.passes[i].Z for i in others])
    keep = np.vstack([plan.passes[i].keep for i in others])
    Sb = drop_on_grid(S, x, y, X, Y, tool)
    with np.errstate(invalid="ignore"):
        z = keep & np.isfinite(Z) & np.isfinite(Sb) & (Sb - (Z + leave) > threshold)
    if z.any():
        d = drop_on_levels(rough, ws, X[z], Y[z], tool, (Z + leave + threshold)[z])
        with np.errstate(invalid="ignore"):
            z[z] = d - (Z + leave)[z] > threshold
    hi = np.searchsorted(np.asarray(sel), others)           # the selected pass after each
    for row in np.nonzero(z.any(axis=1))[0]:
        h = int(hi[row])
        for r in (h - 1, h):
            if 0 <= r < len(sel):
                out[r] |= z[row]
    return out


def _refine_runs(ws, runs, Rr, leave, lim, tolerance, rounds=8):
    """Midpoints inserted where a run's chord passes more than ``tolerance`` below
    the tip the exact drop cutter asks there (max(level, Z + leave)): the nodes are
    up to 1 mm apart and a valley narrower than the ball bends the path sharply."""
    for _ in range(rounds):
        mids = []
        for q, _ in runs:
            if len(q) < 2:
                continue
            mids.append(0.5 * (q[1:] + q[:-1]))
        if not mids:
            break
        M = np.vstack(mids)
        # the level a segment is cut at: its two tips' lower value bounds it from below
        lev = np.concatenate([np.minimum(q[1:, 2], q[:-1, 2]) for q, _ in runs if len(q) >= 2])
        Zm = compensate(ws, M[:, 0].copy(), M[:, 1].copy(), Rr)
        need = np.maximum(np.maximum(lev, Zm + leave), -lim)
        bad = need > M[:, 2] + tolerance
        if not bad.any():
            break
        new_runs = []
        k = 0
        for n, (q, sb) in enumerate(runs):
            if len(q) < 2:
                new_runs.append((q, sb))
                continue
            b = bad[k:k + len(q) - 1]
            mz = need[k:k + len(q) - 1]
            if b.any():
                rows, srows = [q[0]], [sb[0]]
                for i in range(len(q) - 1):
                    if b[i]:
                        m = M[k + i].copy()
                        m[2] = mz[i]
                        rows.append(m)
                        srows.append(max(sb[i], sb[i + 1]))
                    rows.append(q[i + 1])
                    srows.append(sb[i + 1])
                new_runs.append((np.array(rows), np.array(srows)))
            else:
                new_runs.append((q, sb))
            k += len(q) - 1
        runs = new_runs
    return runs


def _link_heights(S, x, y, runs, tool, clr, step=1.0):
    """Per run, the height of the straight link from the run before: ``clr`` above the
    highest of the two ends and the tool's drop onto the roughed stock along the link
    (grid bound, every ``step`` mm; the rest only lowers the stock). None for the first."""
    out = [None] * len(runs)
    XS, YS, own = [], [], []
    for n in range(1, len(runs)):
        a, b = runs[n - 1][0][-1], runs[n][0][0]
        d = math.hypot(b[0] - a[0], b[1] - a[1])
        k = max(2, int(math.ceil(d / step)) + 1)
        t = np.linspace(0.0, 1.0, k)
        XS.append(a[0] + t * (b[0] - a[0]))
        YS.append(a[1] + t * (b[1] - a[1]))
        own.append(np.full(k, n))
    if not XS:
        return out
    # samples at most ``step`` apart: every centre of the link within step/2 of one
    drop = drop_on_grid(S, x, y, np.concatenate(XS), np.concatenate(YS), tool, slack=0.5 * step)
    high = np.full(len(runs), -np.inf)
    np.maximum.at(high, np.concatenate(own), drop)
    for n in range(1, len(runs)):
        a, b = runs[n - 1][0][-1], runs[n][0][0]
        out[n] = max(float(high[n]), float(a[2]), float(b[2]), float(runs[n][1][0])) + clr
    return out


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
