"""The loops and moves of one roughing level (:mod:`fabkit.toolpath.rough.roughing`): a
pocket's contour-parallel loops (its boundary eroded by i x stepover, as a tree walked
without recursion) or rows, entries (helix, ramp, plunge), links within the pocket,
and the path being built. Geometry by shapely.
"""

from __future__ import annotations

import math

import numpy as np

from ..path import CUT, PLUNGE, RAPID

__all__ = ["QUAD_SEGS", "HELIX_FRACTION", "HELIX_SEGS", "LINK_CLEARANCE"]

HELIX_FRACTION = 0.5        # helix radius: at most this x the tool radius
QUAD_SEGS = 32              # polygon segments per quarter circle in the dilations
LINK_CLEARANCE = 1.0        # mm above the level above for links and the start of entries
HELIX_SEGS = 24             # points per helix turn


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
        P = np.asarray(xy, float)
        if P.ndim == 2 and len(P) and P.shape[1] >= 2:
            P = np.column_stack([P[:, 0], P[:, 1], np.full(len(P), float(z))])
            prev = np.vstack([self.pts[-1] if self.pts else P[0] + 1.0, P[:-1]])
            close = np.max(np.abs(P - prev), axis=1) < 1e-9
            if np.isfinite(P).all() and np.isfinite(prev).all() and not close[1:].any():
                # no point repeats the one before it: :meth:`add` would keep each (the first
                # unless it repeats the current point)
                P = P[1:] if close[0] else P
                self.pts.extend(map(tuple, P.tolist()))
                self.kinds.extend([CUT] * len(P))
            else:
                for q in xy:
                    self.add((q[0], q[1], z), CUT)
        else:
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


def _figures(pts, kinds, feed, plunge) -> dict:
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1) if len(pts) > 1 else np.zeros(0)
    k = kinds[1:] if len(kinds) > 1 else np.zeros(0, np.int8)
    cut, plg, rap = float(seg[k == CUT].sum()), float(seg[k == PLUNGE].sum()), float(seg[k == RAPID].sum())
    return {"points": int(len(pts)), "cutting_length_mm": cut + plg, "plunge_length_mm": plg,
            "rapid_length_mm": rap,
            "time_by_length_feed_s": 60.0 * (cut / feed + plg / plunge),
            "time_model": "cutting length / feed + plunge length / plunge feed (rapids not counted)"}


class _Node:
    __slots__ = ("poly", "depth", "children", "rings", "inset")

    def __init__(self, poly, depth, simp=0.0):
        self.poly, self.depth, self.children = poly, depth, []
        self.inset = _inset(poly, simp)
        self.rings = _rings(poly, simp, self.inset)


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


def _inset(poly, simp=0.0):
    """The polygon eroded by ``simp`` and simplified within it (Douglas-Peucker, 0.99
    simp), as a list of polygons (None for ``simp`` <= 0): what :func:`_rings` and
    :func:`_ring_region` are made of, computed once per polygon."""
    if simp <= 0:
        return None
    return [_simplify(q, 0.99 * simp) for q in _polys(poly.buffer(-simp, quad_segs=QUAD_SEGS))]


def _simplify(q, tol: float):
    """Polygon ``q`` simplified within ``tol`` (Douglas-Peucker). GEOS's plain simplifier
    (about ten times faster than its topology-preserving one: 0.015 against 0.15 s of CPU
    on the paper's 83 loops) is kept where its result is a valid polygon with every ring
    of ``q``; each ring then starts where the topology-preserving simplifier starts it (at
    the ring's first point when kept, else at the last point kept before it), so that both
    give the same loops to the bit where neither has to repair a crossing (the paper's 83
    polygons, tests/test_roughing.py). Otherwise (a ring lost, a crossing, a split) the
    topology-preserving simplification."""
    import shapely
    from shapely.geometry import Polygon

    b = q.simplify(tol, preserve_topology=False)
    if b.geom_type != "Polygon" or b.is_empty or len(b.interiors) != len(q.interiors) or not b.is_valid:
        return q.simplify(tol, preserve_topology=True)
    rings = []
    for rb, rq in zip([b.exterior, *b.interiors], [q.exterior, *q.interiors]):
        c = shapely.get_coordinates(rb)[:-1]
        if len(c) < 3:
            return q.simplify(tol, preserve_topology=True)
        k = np.nonzero((c == shapely.get_coordinates(rq)[0]).all(axis=1))[0]
        # GEOS's plain simplifier starts a ring whose first point it dropped at the next kept
        c = np.roll(c, -int(k[0]), axis=0) if len(k) else np.roll(c, 1, axis=0)
        rings.append(np.vstack([c, c[:1]]))
    return Polygon(rings[0], rings[1:])


def _rings(poly, simp=0.0, inset=None):
    """The loops of a polygon (exterior first). ``simp`` > 0: of the polygon eroded by
    ``simp`` and simplified within it (Douglas-Peucker, 0.99 simp): inside the polygon,
    at most 2 simp inside its boundary, with far fewer points than the contour's grid.
    ``inset``: :func:`_inset` (poly, simp) when known."""
    if simp > 0:
        out = []
        for q in (_inset(poly, simp) if inset is None else inset):
            out += [np.asarray(q.exterior.coords)] + [np.asarray(r.coords) for r in q.interiors]
        out = [r for r in out if len(r) >= 4]
        if out:
            return out
    out = [np.asarray(poly.exterior.coords)]
    out += [np.asarray(r.coords) for r in poly.interiors]
    return [r for r in out if len(r) >= 3]


def _ring_region(poly, simp=0.0, inset=None):
    """The region the loops of :func:`_rings` (poly, simp) bound: their polygons.
    ``inset``: :func:`_inset` (poly, simp) when known."""
    from shapely.ops import unary_union

    if simp > 0:
        out = []
        for q in (_inset(poly, simp) if inset is None else inset):
            if len(q.exterior.coords) >= 4:
                out.append(q)
        if out:
            return unary_union(out)
    return poly


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
