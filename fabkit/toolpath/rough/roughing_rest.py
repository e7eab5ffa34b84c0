"""Rest passes after roughing with its own tool (the ``roughing`` section,
:mod:`fabkit.toolpath.rough.roughing`): the stock the roughing left, and the rest tools' passes.

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

from ...errors import SpecError
from ..finish.compensate import WorkSurface, compensate
from ..finish.snap import program_grid
from ..operations import Operation
from ..finish.passes import AIR_EPS, Frame
from ..path import CUT, PLUNGE, RAPID, Toolpath
from .roughing_loops import LINK_CLEARANCE, _figures, _Path, _polys
from ..tools import Tool, depth_of_cut, feeds_of, finish_tool, spec_tools

__all__ = ["stock_after", "drop_on_grid", "drop_on_levels", "plan_rest"]


def stock_after(rough: Operation) -> np.ndarray:
    """The stock's top (work mm, <= 0) after roughing on the design grid
    (``rough.sets.x``, ``.y``): each level's cleared region at its Z (cv2 fills
    the polygons' pixels), then the highest of each node's neighbours: an upper
    bound of the material a cell holds."""
    import cv2

    from ..cut.stock_kernels import window_max

    sets = rough.sets
    ny, nx = len(sets.y), len(sets.x)
    S = np.zeros((ny, nx))
    shift = 4
    scale = np.array([1.0 / sets.hx, 1.0 / sets.hy]) * (1 << shift)
    mask = np.empty((ny, nx), np.uint8)
    for lev in rough.cleared:
        mask.fill(0)
        for poly in _polys(lev.cleared):
            rings = [np.round(np.asarray(r.coords)[:, :2] * scale).astype(np.int32)
                     for r in [poly.exterior, *poly.interiors]]
            cv2.fillPoly(mask, rings[:1], 1, lineType=cv2.LINE_8, shift=shift)
            if len(rings) > 1:
                cv2.fillPoly(mask, rings[1:], 0, lineType=cv2.LINE_8, shift=shift)
        np.minimum(S, lev.z, out=S, where=mask.view(np.bool_))      # 0 / 1: a valid bool view
    return window_max(S, (3, 3))


def drop_on_grid(S, x, y, X, Y, tool: Tool, slack: float = 0.0) -> np.ndarray:
    """The tip height at which ``tool`` standing at (X, Y) first touches the stock
    height field S (grid x, y; no material beyond it): max over grid nodes q within
    the tool's radius + one cell diagonal of S(q) - lift(|q - c| - diagonal), an
    upper bound of the exact drop (the node stands for its cell). -inf: no material.
    ``slack`` (mm): the bound holds for every centre within it of (X, Y) too.

    On a grid finer than R / DROP_CELLS_PER_R (a design grid refined for a steep wall),
    S is first pooled by k x k: each k-th node takes the highest of the nodes within k of
    it, and stands for them (the diagonal grows by one original cell): the offsets within
    R stay about pi DROP_CELLS_PER_R^2 per position, in chunks of bounded memory."""
    hx, hy = x[1] - x[0], y[1] - y[0]
    R = tool.radius
    k = int(R / DROP_CELLS_PER_R / max(hx, hy))
    if k >= 2:
        from ..cut.stock_kernels import window_max

        Sp = window_max(S, (2 * k + 1, 2 * k + 1))[::k, ::k]
        return drop_on_grid(Sp, x[::k], y[::k], X, Y, tool, slack + math.hypot(hx, hy))
    diag = math.hypot(hx, hy) + slack
    ni, nj = int(math.ceil((R + diag) / hy)), int(math.ceil((R + diag) / hx))
    di, dj = np.meshgrid(np.arange(-ni, ni + 1), np.arange(-nj, nj + 1), indexing="ij")
    rho = np.hypot(di * hy, dj * hx)
    ok = rho - diag <= R
    di, dj = di[ok], dj[ok]
    lift = tool.lift(np.clip(rho[ok] - diag, 0.0, R))
    from ..cut.stock_kernels import block_max, drop_grid

    X, Y = np.asarray(X, float), np.asarray(Y, float)
    Xf, Yf = np.ascontiguousarray(X.ravel()), np.ascontiguousarray(Y.ravel())
    out = np.full(Xf.size, -np.inf)
    Sc = np.ascontiguousarray(S, dtype=float)
    # the offsets by rising lift, and the highest node of each block of ni x ni nodes: a
    # position's search stops at the first offset whose lift puts its blocks' highest node
    # no higher than the best so far (the same maximum: the rest cannot exceed it)
    # (a flat bottom lifts nothing within its radius: no order helps, every offset is searched)
    bs = max(1, ni)
    if len(lift) and float(np.max(lift)) > float(np.min(lift)):
        order = np.argsort(lift, kind="stable")
        di, dj, lift = di[order], dj[order], lift[order]
        bmax = block_max(Sc, bs)          # nan nodes, which never win, left out
    else:
        bmax = _NO_BLOCKS
    di, dj = np.ascontiguousarray(di, np.int64), np.ascontiguousarray(dj, np.int64)
    lift = np.ascontiguousarray(lift, float)
    # compiled, in chunks of about DROP_CHUNK_PAIRS position-offset pairs (Ctrl-C between them)
    c = max(1, int(DROP_CHUNK_PAIRS / max(len(di), 1)))
    for a in range(0, Xf.size, c):
        drop_grid(Sc, hx, hy, Xf[a:a + c], Yf[a:a + c], di, dj, lift, out[a:a + c], bmax, bs, ni, nj)
    return out.reshape(X.shape)


#: drop_grid without the blocks' bound (every offset searched)
_NO_BLOCKS = np.empty((0, 0))
#: drop_on_grid: grid cells per tool radius at most (finer grids are pooled), and
#: position-offset pairs per call of its compiled kernel
DROP_CELLS_PER_R = 12
DROP_CHUNK_PAIRS = 50_000_000


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
            d[sel] = _distance_near(U, X[sel], Y[sel], tool.radius + WITHIN_MARGIN)
            with np.errstate(invalid="ignore"):
                term = z_prev - tool.lift(np.minimum(d, 1e9))
            out = np.maximum(out, np.where(np.isfinite(term), term, -np.inf))
        z_prev = lev.z
    return out


#: :func:`_distance_near`'s margin beyond the tool's radius (mm): a point this little
#: farther has its distance too (its term is -inf either way)
WITHIN_MARGIN = 1e-6


def _distance_near(U, X, Y, cap: float) -> np.ndarray:
    """shapely.distance of the points (X, Y) to the polygon(s) U, to the bit, where it is
    at most ``cap``; +inf beyond (the drop's term is -inf there either way): 0 inside or
    on U, else the nearest edge's distance by the compiled kernel (GEOS's point-to-segment
    distance over the edges near the point, :mod:`~fabkit.toolpath.rough.distance_kernels`)."""
    import shapely

    from .distance_kernels import edge_distance

    X = np.ascontiguousarray(X, dtype=float)
    Y = np.ascontiguousarray(Y, dtype=float)
    A, B = [], []
    for poly in _polys(U):
        for ring in (poly.exterior, *poly.interiors):
            c = np.asarray(ring.coords)[:, :2]
            if len(c) >= 2:
                A.append(c[:-1])
                B.append(c[1:])
    out = np.empty(X.size)
    if not X.size:
        return out
    A = np.ascontiguousarray(np.concatenate(A) if A else np.empty((0, 2)))
    B = np.ascontiguousarray(np.concatenate(B) if B else np.empty((0, 2)))
    edge_distance(X, Y, A, B, float(cap), out)
    out[shapely.intersects_xy(U, X, Y)] = 0.0
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
    S_nodes = _stock_at_nodes(rough, S, leave, threshold)
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
        # passes at most Rr apart (a flat end mill or bull nose: Rr / 2; beside a steep
        # wall the pass nearer it stands high on the wall, and a node between two passes
        # Rr apart lies beyond the other's reach: a 4 mm bull nose left 0.8 mm above its
        # bound at a slot's end)
        ball = tool.corner_radius >= Rr - 1e-12
        apart = Rr if ball else 0.5 * Rr
        V = np.array([p.v for p in plan.passes])
        sel = (_ball_passes(plan, fr, ws, V, Rr, apart, leave, doc_f - 2.0 * tolerance, rough, S) if is_fin
               else _passes_apart(V, apart))
        spacing = float(np.diff(V[sel]).max()) if len(sel) > 1 else 0.0
        if ball:
            cusp = Rr - math.sqrt(max(Rr * Rr - 0.25 * spacing * spacing, 0.0))
        else:
            # a flat bottom or a bull nose: the cusp of its corners (none within twice its flat)
            half = min(max(0.5 * spacing - tool.flat_radius, 0.0), tool.corner_radius)
            r_c = tool.corner_radius
            cusp = r_c - math.sqrt(max(r_c * r_c - half * half, 0.0)) if r_c > 0 else 0.0
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
            Z = _tool_on_design(rough, X, Y, tool) if not ball else compensate(ws, X, Y, Rr)
        keep = np.vstack([plan.passes[i].keep for i in sel]) if is_fin else np.isfinite(Z)
        if not ball:
            # beside the nodes left over the threshold the design grid's bound stands the
            # tool up to the slope x two cells' diagonals too high (4 mm on a slope-4 wall):
            # there, the bound from a fine lattice with the design's exact gradient
            near = np.isfinite(drop_on_grid(S_nodes, x, y, X, Y, tool)) & np.isfinite(Z)
            fine = _FineDesign(rough, ws, X[near], Y[near], tool) if near.any() else None
            if fine is not None:
                Z[near] = np.minimum(Z[near], fine(X[near], Y[near]))
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
        # the nodes the roughing (and the rest tools before) left more than the threshold
        # above the allowance: wherever this tool, standing at its own target, cuts into
        # one of them, it runs (its drop at the same centre can be within the threshold
        # while a node beside it, which it reaches from another centre, is not: a flat or
        # bull nose between an island and a wall left 5.2 mm where the check asks 3.01)
        zone |= keep & np.isfinite(Z) & _over_zone(rough, S_nodes, X, Y, tool, floor, leave, threshold, tolerance)
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
        runs = _refine_runs(ws, runs, Rr, leave, lim, 0.5 * tolerance,
                            drop=None if ball else (fine if fine is not None else
                                                    (lambda px, py, t=tool: _tool_on_design(rough, px, py, t))),
                            grid=program_grid(m))
        fig_low = 0
        zlink = _link_heights(S, x, y, runs, tool, clr)
        fed = _feed_links(ws, runs, tool, leave, lim, S, x, y, doc, tolerance,
                          drop=(lambda px, py: compensate(ws, px, py, Rr)) if ball else
                          (fine if fine is not None else (lambda px, py, t=tool: _tool_on_design(rough, px, py, t))))
        path = _Path()
        for n, (q, sb) in enumerate(runs):
            start = q[0]
            above = min(max(float(sb[0]), float(start[2])) + clr, safe_z)
            zl = zlink[n]
            if fed[n]:
                # the tool stays down: the straight link is proven clear of the allowance and
                # within the tool's depth of cut of the roughed stock (_feed_links)
                path.add(tuple(start), CUT)
                for p in q[1:]:
                    path.add(tuple(p), CUT)
                continue
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
        feed, plunge = feeds_of(spec, tool)
        info = _figures(pts, kinds, feed, plunge)
        levels_cut = len(levels_cut)
        info.update({
            "tool": tool.describe(), "levels": levels_cut, "stepdown_mm": step_r, "stepover_mm": spacing,
            "leave_mm": leave, "cusp_mm": cusp, "runs": len(runs) - int(sum(fed)), "runs_linked": int(sum(fed)),
            "passes": len({(round(float(q[0, 0]), 6), round(float(q[0, 1]), 6)) for q, _ in runs}),
            "entry": "plunge (into ground the rest ball's drop shows clear above the cut)",
            "links": {"fed": int(sum(fed)), "low": fig_low, "safe_height": len(runs) - 1 - fig_low - int(sum(fed))},
            "zone_threshold_mm": threshold, "zone_positions": int(zone.sum()),
            "depth_of_cut_mm": doc, "finish_depth_of_cut_mm": doc_f, "stock_grid_step_mm": float(max(x[1] - x[0], y[1] - y[0])),
            "plan_seconds": time.process_time() - t0,
        })
        tp.info = info
        ops.append(Operation("rest", tool, tp, leave=leave, levels=levels_cut, passes=info["runs"], info=info))
    return ops


def _stock_at_nodes(rough: Operation, S: np.ndarray, leave: float, threshold: float) -> np.ndarray:
    """The stock the roughing left at the design grid's nodes where it stands more than
    ``threshold`` above the allowance min(design + leave, 0), -inf elsewhere: candidates
    from the grid's upper bound S (:func:`stock_after`), then each candidate's height from
    the levels' polygons (the lowest level whose cleared region holds it)."""
    import shapely

    sets = rough.sets
    T = np.minimum(np.minimum(sets.H, 0.0) + leave, 0.0)
    out = np.full(S.shape, -np.inf)
    cand = S - T > threshold
    if not cand.any():
        return out
    iy, ix = np.nonzero(cand)
    px, py = sets.x[ix], sets.y[iy]
    z = np.zeros(len(ix))
    for lev in rough.cleared:
        if lev.cleared.is_empty:
            continue
        shapely.prepare(lev.cleared)
        z = np.where(shapely.contains_xy(lev.cleared, px, py), np.minimum(z, lev.z), z)
    over = z - T[iy, ix] > threshold
    out[iy[over], ix[over]] = z[over]
    return out


def _over_zone(rough, S_nodes, X, Y, tool: Tool, floor, leave, threshold, tolerance) -> np.ndarray:
    """Where ``tool`` with its tip at ``floor`` (its target) would cut more than the
    tolerance into a node left over the threshold (``S_nodes``, :func:`_stock_at_nodes`):
    its drop onto those nodes alone (:func:`drop_on_grid`, an upper bound) above its tip."""
    if not np.isfinite(S_nodes).any():
        return np.zeros(np.shape(X), bool)
    sets = rough.sets
    d = drop_on_grid(S_nodes, sets.x, sets.y, X, Y, tool)
    with np.errstate(invalid="ignore"):
        return np.isfinite(d) & np.isfinite(floor) & (d > floor + tolerance)


def _ball_passes(plan, fr, ws, V, R: float, apart: float, leave: float, limit: float, rough, S) -> list[int]:
    """The finishing passes a rest ball runs on: each next one the farthest within ``apart``
    (its radius) whose rib with the last leaves the finish at most ``limit`` to remove.
    Across a steep wall parallel to the passes two balls ``apart`` on flat ground stand
    far apart along the wall, and the rib between them is left for the finish (a moat's
    wall with rest passes 1.59 mm apart: the finish removed 3.28 mm at a node, its depth
    of cut 3 mm). Per node of the passes' common grid and per finishing pass from one
    radius before the last chosen pass to the candidate (and the midpoints between them):
    the rest-cut stock there is at most the lowest cross-section through its centre (each
    ball sweeps through that section) of the chosen passes, the candidate and every later
    finishing pass within a radius (their best case: a later choice checks again), lifted by
    ``leave``, and at most the roughed stock ``S`` (an upper bound,
    :func:`stock_after`, at the nearest node of its grid); the finish cuts it to the design
    (exact, clipped at the top face). Passes where the roughed stock stands within the
    limit of the design everywhere constrain nothing (the paper's job: none)."""
    sets = rough.sets
    x, y = sets.x, sets.y
    hx, hy = float(x[1] - x[0]), float(y[1] - y[0])
    ug = plan.ug

    def sample(v):
        """(stock bound S, design clipped at the top face) at (ug, v) for each v."""
        v = np.atleast_1d(np.asarray(v, float))
        U = np.broadcast_to(ug, (len(v), len(ug)))
        X, Y = fr.xy(U, np.broadcast_to(v[:, None], U.shape))
        X, Y = np.ascontiguousarray(X, float), np.ascontiguousarray(Y, float)
        ix = np.clip(np.rint((X - x[0]) / hx).astype(np.int64), 0, len(x) - 1)
        iy = np.clip(np.rint((Y - y[0]) / hy).astype(np.int64), 0, len(y) - 1)
        return S[iy, ix], np.minimum(ws.H(X, Y), 0.0)

    Sk, Dk = sample(V)
    with np.errstate(invalid="ignore"):
        tall2 = np.nan_to_num(Sk - Dk, nan=0.0, posinf=0.0, neginf=0.0) > limit
    tall = tall2.any(axis=1)
    Zs = np.vstack([np.where(p.keep & np.isfinite(p.Z), p.Z, np.inf) for p in plan.passes])

    def ok(sel: list[int], j: int) -> bool:
        """The rib at the finishing passes (and their midpoints) from one radius before the
        last chosen pass to the candidate j, under the sections of the chosen passes, j, and
        every finishing pass after j (those a later choice can still take: their best case;
        the nodes beyond one radius before j are checked again at the next choice)."""
        i = sel[-1]
        lo = int(np.searchsorted(V, V[i] - R, side="left"))
        if not tall[lo:j + 1].any():
            return True
        cols = tall2[lo:j + 1].any(axis=0)
        vs = np.union1d(V[lo:j + 1], 0.5 * (V[lo:j] + V[lo + 1:j + 1]))
        vs = vs[vs < V[j]]
        if not len(vs):
            return True
        hi = int(np.searchsorted(V, V[j] + R, side="right"))
        balls = np.array([e for e in sel if V[e] > V[lo] - R] + [j] + list(range(j + 1, hi)), dtype=np.int64)
        Sv, Dv = sample(vs)
        Sv, Dv = Sv[:, cols], Dv[:, cols]
        cap = np.full(Sv.shape, np.inf)
        Zb = Zs[balls][:, cols]
        for e, ze in zip(balls, Zb):
            d = np.abs(vs - V[e])
            near = d < R
            if not near.any():
                continue
            low = ze[None, :] + (R - np.sqrt(np.maximum(R * R - d[near] * d[near], 0.0)))[:, None] + leave
            cap[near] = np.minimum(cap[near], low)
        with np.errstate(invalid="ignore"):
            rib = np.minimum(cap, Sv) - Dv
        return not np.any(np.isfinite(rib) & (rib > limit))

    return _passes_apart(V, apart, ok)


def _passes_apart(V, apart: float, ok=None) -> list[int]:
    """Indices of the passes at offsets ``V`` (ascending) a rest tool runs on: from the
    first, each next the farthest within ``apart`` of the last that ``ok(sel, j)`` accepts
    (always the very next one if none)."""
    sel = [0]
    while sel[-1] < len(V) - 1:
        i = sel[-1]
        j = max(int(np.searchsorted(V, V[i] + apart, side="right")) - 1, i + 1)
        while ok is not None and j > i + 1 and not ok(sel, j):
            j -= 1
        sel.append(j)
    return sel


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


def _tool_on_design(rough: Operation, X, Y, tool: Tool) -> np.ndarray:
    """The tip height at which a flat end mill or bull nose at (X, Y) first touches the
    design clipped at the top face: :func:`drop_on_grid` onto the level sets' design grid,
    each node raised to the highest of its neighbours plus the grid's interpolation bound
    (an upper bound of the design over its cell), so an upper bound of the exact drop: the
    tool never enters the allowance; it stands at most the slope x a cell's diagonal + 2 e
    higher than it could."""
    from ..cut.stock_kernels import window_max

    sets = rough.sets
    key = "_design_upper"
    S = getattr(sets, key, None)
    if S is None:
        S = window_max(np.minimum(sets.H, 0.0), (3, 3)) + sets.err
        setattr(sets, key, S)
    return drop_on_grid(S, sets.x, sets.y, X, Y, tool)


#: _tool_on_design_fine: lattice nodes, and position-offset pairs, at most
FINE_NODES = 4_000_000
FINE_PAIRS = 200_000_000


class _FineDesign:
    """An upper bound of the tip height at which a flat end mill or bull nose at (X, Y)
    first touches the design clipped at the top face, tighter than :func:`_tool_on_design`
    on steep walls, over the box round the positions it is made for (elsewhere that bound):
    on a lattice of step d (as fine as FINE_NODES and FINE_PAIRS allow, at most the design
    grid's) each node q stands for the points within half its cell's diagonal c of it, with
    min(H(q) + |grad H(q)| c + C c^2 / 2, 0) (the exact gradient; C the larger of the level
    sets' curvature bound and the node's own), and the tool's lift taken one diagonal nearer
    its axis (the position lies within half a diagonal of its nearest node): max over the
    nodes within R + diagonal of that minus lift. Within about (slope + the lift's slope at
    the contact) x d of the exact drop."""

    def __init__(self, rough: Operation, ws, X, Y, tool: Tool):
        sets = rough.sets
        self.rough, self.tool = rough, tool
        X, Y = np.asarray(X, float).ravel(), np.asarray(Y, float).ravel()
        R = tool.radius
        pad = R + 2.0
        x0, x1 = max(0.0, float(X.min()) - pad), min(ws.L, float(X.max()) + pad)
        y0, y1 = max(0.0, float(Y.min()) - pad), min(ws.W, float(Y.max()) + pad)
        self.box = (float(X.min()) - 1.0, float(X.max()) + 1.0, float(Y.min()) - 1.0, float(Y.max()) + 1.0)
        h0 = max(sets.hx, sets.hy)
        # the positions asked: these and about 3 x as many midpoints (the runs' refinement)
        d = max(math.sqrt(max(x1 - x0, 1e-9) * max(y1 - y0, 1e-9) / FINE_NODES),
                (R + 2.0 * h0) * math.sqrt(math.pi * 4 * X.size / FINE_PAIRS), 0.02)
        d = min(d, h0)
        nx, ny = max(2, int(math.ceil((x1 - x0) / d)) + 1), max(2, int(math.ceil((y1 - y0) / d)) + 1)
        gx, gy = np.linspace(x0, x1, nx), np.linspace(y0, y1, ny)
        hx, hy = gx[1] - gx[0], gy[1] - gy[0]
        GX, GY = np.meshgrid(gx, gy)
        H, Hx, Hy, Hxx, Hxy, Hyy = ws.all(GX, GY)
        c = 0.5 * math.hypot(hx, hy)
        C = np.maximum(np.abs(Hxx) + 2.0 * np.abs(Hxy) + np.abs(Hyy), sets.curv)
        with np.errstate(invalid="ignore"):
            U = np.minimum(H + np.hypot(Hx, Hy) * c + 0.5 * C * c * c, 0.0)
        self.U = np.ascontiguousarray(np.where(np.isfinite(U), U, 0.0), float)   # unreadable: material
        diag = 2.0 * c
        ni, nj = int(math.ceil((R + diag) / hy)), int(math.ceil((R + diag) / hx))
        di, dj = np.meshgrid(np.arange(-ni, ni + 1), np.arange(-nj, nj + 1), indexing="ij")
        rho = np.hypot(di * hy, dj * hx)
        ok = rho - diag <= R
        self.lift = np.ascontiguousarray(tool.lift(np.clip(rho[ok] - diag, 0.0, R)), float)
        self.di, self.dj = np.ascontiguousarray(di[ok], np.int64), np.ascontiguousarray(dj[ok], np.int64)
        self.x0, self.y0, self.hx, self.hy, self.step = x0, y0, hx, hy, d

    def __call__(self, X, Y) -> np.ndarray:
        """The bound at (X, Y): this lattice's inside the box, :func:`_tool_on_design` everywhere."""
        from ..cut.stock_kernels import drop_grid

        X, Y = np.asarray(X, float), np.asarray(Y, float)
        out = _tool_on_design(self.rough, X, Y, self.tool).ravel()
        xs, ys = X.ravel(), Y.ravel()
        bx0, bx1, by0, by1 = self.box
        inb = (xs >= bx0) & (xs <= bx1) & (ys >= by0) & (ys <= by1)
        if inb.any():
            Xs, Ys = np.ascontiguousarray(xs[inb] - self.x0), np.ascontiguousarray(ys[inb] - self.y0)
            fine = np.full(Xs.size, -np.inf)
            step = max(1, int(DROP_CHUNK_PAIRS / max(len(self.di), 1)))
            for a in range(0, Xs.size, step):
                drop_grid(self.U, self.hx, self.hy, Xs[a:a + step], Ys[a:a + step], self.di, self.dj, self.lift,
                          fine[a:a + step], _NO_BLOCKS, 1, 0, 0)
            out[inb] = np.minimum(out[inb], fine)
        return out.reshape(X.shape)


def _refine_runs(ws, runs, Rr, leave, lim, tolerance, rounds=10, drop=None, grid=None):
    """Midpoints inserted where a run's chord passes more than ``tolerance`` below
    the tip the exact drop cutter asks there (max(level, Z + leave)), asked at the
    eighths of each chord: the nodes are up to 1 mm apart, a valley narrower than the
    ball bends the path sharply, and over a steep wall's convex rim the chord dips
    between its midpoint and its ends.

    ``grid``: :func:`fabkit.toolpath.finish.snap.program_grid`'s (step, units_mm, slack):
    before each round the runs' points are put where the program writes them, as the
    finish's are (:func:`~fabkit.toolpath.finish.snap.snap_points` with the rest's ask,
    max(drop + leave, -lim), for height): beside a steep wall at the stock's edge, the
    ball touching it with its rim only, rounding Y by 4.5e-5 mm raised the ask by 0.0124
    mm (vee45: a rest pass at Y-1.49604502 written Y-1.496)."""
    fr = np.arange(1, 8) / 8.0

    def ask(px, py):
        z = compensate(ws, px, py, Rr) if drop is None else drop(px, py)
        return np.maximum(np.asarray(z, float) + leave, -lim)

    def on_grid(runs, fresh):
        """The fresh points put on the program's grid (the others are already: putting a
        point there again leaves it as it is)."""
        if grid is None or not runs:
            return runs
        from ..finish.snap import snap_points

        f = np.concatenate(fresh)
        if not f.any():
            return runs
        step, k, slack = grid
        Q = np.vstack([q for q, _ in runs])
        Qf = Q[f]
        Q2 = snap_points(ws, Rr, Qf, np.ones(len(Qf), np.int8), step, k, slack_mm=slack, height=ask)
        moved = np.zeros(len(Q), bool)
        moved[f] = np.any(Q2 != Qf, axis=1)
        if not moved.any():
            return runs
        Q[f] = Q2
        out, a = [], 0
        for q, sb in runs:
            out.append((Q[a:a + len(q)] if moved[a:a + len(q)].any() else q, sb))
            a += len(q)
        return out

    # per run, its points not yet put on the grid nor their chords checked: a chord between
    # two points neither new nor moved was checked in an earlier round and passed
    fresh = [np.ones(len(q), bool) for q, _ in runs]
    for _ in range(rounds):
        runs = on_grid(runs, fresh)
        segs = [(q[:-1], q[1:], fr_[:-1] | fr_[1:]) for (q, _), fr_ in zip(runs, fresh) if len(q) >= 2]
        if not segs:
            break
        A = np.vstack([a for a, _, _ in segs])
        B = np.vstack([b for _, b, _ in segs])
        ask_seg = np.concatenate([c for _, _, c in segs])
        bad = np.zeros(len(A), bool)
        M = np.zeros((len(A), 3))
        need = np.zeros(len(A))
        if ask_seg.any():
            Aa, Ba = A[ask_seg], B[ask_seg]
            P = Aa[None, :, :] + fr[:, None, None] * (Ba - Aa)[None, :, :]        # (7, n, 3)
            # the level a segment is cut at: its two tips' lower value bounds it from below
            lev = np.minimum(Aa[:, 2], Ba[:, 2])
            px, py = np.ascontiguousarray(P[..., 0].ravel()), np.ascontiguousarray(P[..., 1].ravel())
            Zp = (compensate(ws, px, py, Rr) if drop is None else drop(px, py)).reshape(P.shape[:2])
            needs = np.maximum(np.maximum(lev[None, :], Zp + leave), -lim)
            bad[ask_seg] = (needs > P[..., 2] + tolerance).any(axis=0)
            M[ask_seg] = P[3]
            need[ask_seg] = needs[3]
        if not bad.any():
            break
        new_runs, new_fresh = [], []
        k = 0
        for n, (q, sb) in enumerate(runs):
            if len(q) < 2:
                new_runs.append((q, sb))
                new_fresh.append(np.zeros(len(q), bool))
                continue
            b = bad[k:k + len(q) - 1]
            mz = need[k:k + len(q) - 1]
            if b.any():
                rows, srows, frows = [q[0]], [sb[0]], [False]
                for i in range(len(q) - 1):
                    if b[i]:
                        m = M[k + i].copy()
                        m[2] = mz[i]
                        rows.append(m)
                        srows.append(max(sb[i], sb[i + 1]))
                        frows.append(True)
                    rows.append(q[i + 1])
                    srows.append(sb[i + 1])
                    frows.append(False)
                new_runs.append((np.array(rows), np.array(srows)))
                new_fresh.append(np.array(frows, bool))
            else:
                new_runs.append((q, sb))
                new_fresh.append(np.zeros(len(q), bool))
            k += len(q) - 1
        runs, fresh = new_runs, new_fresh
    return on_grid(runs, fresh)


#: _feed_links: runs at most this many tool radii apart are linked by a feed when clear,
#: and the link is proven at points at most FEED_LINK_STEP mm apart
FEED_LINK_RADII = 2.0
FEED_LINK_STEP = 0.05


def _feed_links(ws, runs, tool: Tool, leave, lim, S, x, y, doc, tolerance, drop) -> list[bool]:
    """Per run, whether the tool feeds straight from the end of the run before to its
    start, staying down (the runs merged into one pass): the runs are at most
    FEED_LINK_RADII x R apart and along the straight link, at points FEED_LINK_STEP mm
    apart, the tip (linear between the two ends) stands at or above the tool's drop onto
    the design (``drop``: the exact ball's, or a flat end mill's or bull nose's upper
    bound) + ``leave`` and above the reach limit ``lim``, and at most the tool's depth of
    cut less the tolerance below its drop onto the roughed stock S (an upper bound of
    the stock there: the rest passes only lower it). Else False: lift, across, plunge."""
    out = [False] * len(runs)
    R = tool.radius
    cand, XS, YS, ZS, own = [], [], [], [], []
    for n in range(1, len(runs)):
        a, b = runs[n - 1][0][-1], runs[n][0][0]
        d = math.hypot(b[0] - a[0], b[1] - a[1])
        if d > FEED_LINK_RADII * R:
            continue
        k = max(2, int(math.ceil(d / FEED_LINK_STEP)) + 1)
        t = np.linspace(0.0, 1.0, k)
        XS.append(a[0] + t * (b[0] - a[0]))
        YS.append(a[1] + t * (b[1] - a[1]))
        ZS.append(a[2] + t * (b[2] - a[2]))
        own.append(np.full(k, len(cand)))
        cand.append(n)
    if not cand:
        return out
    X, Y, Z, own = (np.ascontiguousarray(np.concatenate(v)) for v in (XS, YS, ZS, own))
    with np.errstate(invalid="ignore"):
        need = np.maximum(np.asarray(drop(X, Y), float) + leave, -lim)
        stock = drop_on_grid(S, x, y, X, Y, tool)
        bad = ~np.isfinite(need) | (Z < need - 1e-9) | (np.isfinite(stock) & (stock - Z > doc - tolerance))
    worst = np.zeros(len(cand), bool)
    np.logical_or.at(worst, own, bad)
    for j, n in enumerate(cand):
        out[n] = not worst[j]
    return out


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
