"""Raster planning for a ball-end mill, as named stages a test can call one by one:

1. :func:`fabkit.toolpath.finish.guards.estimate` / ``guard``: passes, points, roughing
   levels and planning time from the spec, refused before any work.
2. :func:`fabkit.toolpath.finish.passes.place_passes`: the passes across with the
   slope-aware stepover; each pass carries its exact tip heights
   (:func:`fabkit.toolpath.finish.passes.compensate_passes`, the drop cutter of
   :mod:`fabkit.toolpath.finish.compensate`).
3. :func:`fabkit.toolpath.finish.spacing.space_points`: points along each pass within the
   chord tolerance, air left out.
4. :func:`order_runs`: cut runs in machining order (zigzag or one-way).
5. :func:`fabkit.toolpath.rough.ball_levels.rough_runs`: optional z-level roughing runs.
6. :func:`fabkit.toolpath.finish.links.link_runs`: links, retracts and rapids.
7. :func:`check_depth_limits` and :func:`summarize`.

Work coordinates, mm (see :mod:`fabkit.toolpath.path`); the rules and their
accuracy are in each stage's module and in docs/toolpath.md.
"""

from __future__ import annotations

import math

import numpy as np

from ...errors import SpecError
from ...tolerances import DEFAULT, Tolerances
from .compensate import WorkSurface
from .guards import estimate, guard
from .links import link_runs
from .passes import (SCALLOP_SAFETY, Frame, PassPlan, compensate_passes, flat_stepover,
                     place_passes, sweep_material, tilted_plane_cusp)
from ..path import RAPID, Toolpath
from ..rough.ball_levels import rough_runs
from .spacing import AIR_CUT_FRACTION, CHORD_SAFETY, TENT_SHARE, cut_runs, space_points

LINK_CLEARANCE = 1.0    # mm above material for short links and approaches (<= safe_height)

__all__ = ["plan_toolpath", "add_passes", "plan_estimate", "order_runs", "check_depth_limits", "summarize",
           "flat_stepover", "tilted_plane_cusp", "sweep_material"]


def plan_estimate(spec, surface, tol: Tolerances = DEFAULT) -> dict:
    """Stage 1: the estimates (passes, points, roughing levels/points, seconds), and
    SpecError (exit 2, naming the key and the estimate) beyond the guards."""
    from .passes import fine_grid_size, u_grid

    R = 0.5 * float(spec.tool.diameter)
    ws = surface if isinstance(surface, WorkSurface) else WorkSurface(surface)
    fr = Frame(spec.machining.direction, ws.L, ws.W)
    # the depth on a grid (an estimate: the exact lowest point needs an optimizer)
    Hg = ws.H(*np.meshgrid(np.linspace(0, ws.L, 201), np.linspace(0, ws.W, 201)))
    Hg = Hg[np.isfinite(Hg)]
    depth = max(0.0, -float(Hg.min())) if Hg.size else 0.0
    target = SCALLOP_SAFETY * float(spec.machining.scallop)
    ug = u_grid(fr, R)
    uf_n, uf_step = fine_grid_size(ug, R, target)
    est = estimate(spec, ws, fr, R, target, float(spec.machining.tolerance), depth, len(ug),
                   n_fine=uf_n, fine_step=uf_step, normal=scallop_normal(spec))
    guard(est, tol, spec.path, float(spec.machining.scallop), float(spec.machining.tolerance))
    return est


def scallop_normal(spec) -> bool:
    """True where ``machining.scallop_measure`` is ``normal`` (the default)."""
    return getattr(spec.machining, "scallop_measure", "normal") != "vertical"


def _on_readback_grid(spec, ws, R, points, kinds):
    """Stage 6b: feed moves on the grid the controller reads back (:mod:`.snap`) where
    the program's decimals are finer than it (inch programs); elsewhere on the program's
    own grid where the X, Y rounding alone would put the ball more than the tolerance's
    rounding share into the material (the ball's flank at an edge pass)."""
    from .snap import program_grid, snap_points

    step, k, slack = program_grid(spec.machining)
    return snap_points(ws, R, points, kinds, step, k, slack_mm=slack)


def _refine_snapped(spec, ws, R, planned, points, kinds):
    """Stage 6c: where the grid moved a point up by more than the tolerance's rounding
    share (the exact path along the written across coordinate is not the planned one),
    its moves are refined at the written coordinates (:func:`.snap.refine_moves`)."""
    from ...units import ROUNDING_SHARE
    from .snap import program_grid, refine_moves

    m = spec.machining
    step = program_grid(m)[0]
    tol = float(m.tolerance)
    return refine_moves(ws, R, planned, points, kinds, step, tol / ROUNDING_SHARE,
                        CHORD_SAFETY * tol, TENT_SHARE * tol)


def order_runs(fr, m, V, runs, passes_cut):
    """Stage 4: the finishing runs in cutting order, as [(pass, (k, 3) tip points)]."""
    out = []
    forward_climb = fr.direction == "x"     # M3: material on the left of the feed
    for k, p in enumerate(passes_cut):
        rr = runs[p]
        if m.pattern == "zigzag":
            fwd = k % 2 == 0
        else:
            fwd = forward_climb if m.pattern == "climb" else not forward_climb
        if not fwd:
            rr = [r[::-1] for r in rr[::-1]]
        for r in rr:
            X, Y = fr.xy(r[:, 0], np.full(len(r), V[p]))
            out.append((p, np.column_stack([X, Y, r[:, 1]])))
    return out


def _depth_key(spec):
    """(limit mm, key): the binding one of ``stock.depth_limit`` and ``tool.reach``."""
    dl, rc = float(spec.stock.depth_limit), float(spec.tool.reach)
    return (dl, "stock.depth_limit") if dl <= rc else (rc, "tool.reach")


def _where(X, Y) -> str:
    """'X a to b, Y c to d mm' (one value where the range is a point to 0.01 mm)."""
    def rng(v):
        lo, hi = float(np.min(v)), float(np.max(v))
        return f"{lo:.2f}" if hi - lo < 0.005 else f"{lo:.2f} to {hi:.2f}"
    return f"X {rng(X)}, Y {rng(Y)}"


#: ball centres tried around each edge point (x R from it, 16 directions each), and
#: the centre along the surface normal (the exact contact on smooth ground)
EDGE_RING = (0.0, 0.25, 0.5, 0.75, 0.875, 0.95, 0.99)


def edge_depth_needed(ws, R: float, lim: float, allowed: float, step: float | None = None):
    """Where the stock edges can be finished only with the tip deeper than ``lim``.

    A ball finishing the edge point e (footprint boundary, design height H(e)) must
    reach down to H(e) + ``allowed`` there. Every ball touching e has its tip within R
    below H(e), so only edge points with H(e) - R < -lim are examined: for each, ball
    centres on rings around e (:data:`EDGE_RING`) and along the surface normal, at
    their exact drop-cutter tip heights (:func:`compensate`). An edge point is
    flagged when some of these balls reach it but none of them with its tip at or
    above -lim does (material beyond the ball's reach at any depth, a crease at the
    edge, is not a depth matter: the verification reports it). Returns (X, Y, need):
    the flagged edge points (work mm) and the tip depth (mm, > lim) the best of the
    tried balls needs there; the depth is that of a tried centre, an upper bound
    within a few hundredths of a mm of the exact one on smooth ground.
    """
    from .compensate import compensate

    L, W = ws.L, ws.W
    step = step or R / 4
    nx, ny = max(2, int(math.ceil(L / step)) + 1), max(2, int(math.ceil(W / step)) + 1)
    tx, ty = np.linspace(0.0, L, nx), np.linspace(0.0, W, ny)
    ex = np.r_[tx, tx, np.zeros(ny), np.full(ny, L)]
    ey = np.r_[np.zeros(nx), np.full(nx, W), ty, ty]
    H, hx, hy = ws.all(ex, ey)[:3]
    near = np.isfinite(H) & (H - R < -lim)
    empty = np.zeros(0)
    if not near.any():
        return empty, empty, empty
    ex, ey, H, hx, hy = ex[near], ey[near], H[near], hx[near], hy[near]
    ang = 2 * np.pi * np.arange(16) / 16
    ox = np.r_[[f * R * np.cos(a) for f in EDGE_RING[1:] for a in ang]]
    oy = np.r_[[f * R * np.sin(a) for f in EDGE_RING[1:] for a in ang]]
    with np.errstate(all="ignore"):
        w = np.sqrt(1.0 + hx * hx + hy * hy)
    OX = np.column_stack([np.zeros_like(ex), -R * hx / w, np.broadcast_to(ox, (ex.size, ox.size))])
    OY = np.column_stack([np.zeros_like(ex), -R * hy / w, np.broadcast_to(oy, (ex.size, oy.size))])
    OX, OY = np.nan_to_num(OX), np.nan_to_num(OY)
    Z = compensate(ws, ex[:, None] + OX, ey[:, None] + OY, R)
    d2 = np.minimum(OX * OX + OY * OY, R * R)
    with np.errstate(invalid="ignore"):
        low = np.where(np.isfinite(Z), Z + R - np.sqrt(R * R - d2), np.inf)
    hits = low <= (H + allowed)[:, None]
    within = hits & (Z >= -lim - 1e-9)
    bad = hits.any(axis=1) & ~within.any(axis=1)
    need = np.where(hits, -Z, np.inf).min(axis=1)
    return ex[bad], ey[bad], need[bad]


def check_edge_depth(spec, ws, R: float, scallop: float) -> None:
    """Stage 1b, before any pass is planned: refuse (SpecError, exit 2, naming the
    binding key of ``stock.depth_limit`` / ``tool.reach``, the depth needed and the
    X, Y range of the stock edge concerned) a design whose stock edges the ball can
    finish to the scallop only with its tip below the limit (steep ground falling
    towards an edge: the ball finishing the edge overhangs it, its tip lower than
    the surface there). The surface itself deeper than the limits is refused
    earlier (:func:`fabkit.surface.check_depth`)."""
    lim, key = _depth_key(spec)
    X, Y, need = edge_depth_needed(ws, R, lim, scallop)
    if not X.size:
        return
    parts, left = [], np.ones(X.size, bool)
    for sel in (np.isclose(X, 0.0), np.isclose(X, ws.L), np.isclose(Y, 0.0), np.isclose(Y, ws.W)):
        sel &= left
        if sel.any():
            parts.append(_where(X[sel], Y[sel]))
            left &= ~sel
    deepest = float(need.max())
    raise SpecError(f"finishing the stock edge at {'; '.join(parts)} mm (work coordinates) needs the "
                    f"tool tip {deepest:.3f} mm deep, {deepest - lim:.3f} mm below the limit {lim:g} mm "
                    "(steep ground falls towards that edge: the ball finishing it overhangs the edge, "
                    "its tip below the surface); raise the limit or keep the design shallower there",
                    file=spec.path, key=key)


def check_depth_limits(spec, points) -> float:
    """Stage 7a: refuse a tip deeper than ``stock.depth_limit`` / ``tool.reach``,
    naming where (the X, Y range of the tips below the limit). Returns the deepest
    tip z (mm, <= 0)."""
    if not len(points):
        return 0.0
    if not np.isfinite(points).all():
        raise ValueError("non-finite program point")       # a planner defect, never input
    i = int(np.argmin(points[:, 2]))
    zmin = float(points[i, 2])
    lim, key = _depth_key(spec)
    if -zmin > lim + 1e-9:
        deep = points[:, 2] < -lim - 1e-9
        raise SpecError(f"the tool tip goes {-zmin:.3f} mm deep at X={points[i, 0]:.2f}, "
                        f"Y={points[i, 1]:.2f} mm, {-zmin - lim:.3f} mm more than the limit "
                        f"{lim:g} mm (below it over {_where(points[deep, 0], points[deep, 1])}, "
                        "work mm)", file=spec.path, key=key)
    return zmin


def plan_toolpath(spec, surface, tol: Tolerances = DEFAULT) -> Toolpath:
    """Plan the finishing raster (and roughing when ``machining.stepdown`` is set).

    spec:    validated spec (tool, stock, machining sections)
    surface: :class:`fabkit.surface.Surface` of the spec
    Returns a :class:`Toolpath` (tip positions, work mm). Raises SpecError when the
    estimated passes, points, roughing levels or planning time exceed the guards in
    ``tol`` or the tip would go deeper than ``stock.depth_limit`` / ``tool.reach``.
    """
    m = spec.machining
    R = 0.5 * float(spec.tool.diameter)
    scallop, tolerance = float(m.scallop), float(m.tolerance)
    ws = WorkSurface(surface)
    fr = Frame(m.direction, ws.L, ws.W)
    safe_z = float(m.safe_height)
    depth_lim = min(float(spec.stock.depth_limit), float(spec.tool.reach))

    est = plan_estimate(spec, surface, tol)
    check_edge_depth(spec, ws, R, scallop)
    normal = scallop_normal(spec)
    plan = place_passes(ws, fr, R, scallop, depth_lim, tol.max_passes, spec.path,
                        chord=0.0 if normal else CHORD_SAFETY * tolerance, normal=normal)
    return _program(spec, ws, fr, plan, est, tol)


def add_passes(spec, surface, toolpath: Toolpath, v_over, tol: Tolerances = DEFAULT):
    """Stage 8, after the verification: passes added where the verified cut left more
    than ``scallop + tolerance`` (``v_over``: the across coordinates, work mm, of the
    points that did). Each gap between consecutive passes within R of such a point gets
    a pass in its middle (a cusp lies up to R from the passes that cut it: in a valley
    tighter than the ball whose floor slopes across the passes, the balls cut with their
    flanks). The material bound of :func:`place_passes` samples each cross-section at a
    few points between the passes' contact curves; where those curves are not where the
    balls cut (the foot of such a valley at a stock edge), this puts back what it missed.
    Returns the new Toolpath, or None when there is nothing to add."""
    plan = toolpath.plan
    if plan is None or not len(v_over):
        return None
    m = spec.machining
    R = 0.5 * float(spec.tool.diameter)
    ws = WorkSurface(surface)
    fr = Frame(m.direction, ws.L, ws.W)
    V = np.array([p.v for p in plan.passes])
    mid = 0.5 * (V[1:] + V[:-1])
    vo = np.asarray(v_over, float)
    near = (np.abs(mid[:, None] - vo[None, :]) <= R + 0.5 * np.diff(V)[:, None]).any(axis=1)
    near &= np.diff(V) > 1e-3                     # gaps wider than 1 um
    new_v = mid[near]
    if not new_v.size:
        return None
    depth_lim = min(float(spec.stock.depth_limit), float(spec.tool.reach))
    target = SCALLOP_SAFETY * float(m.scallop)
    added = compensate_passes(ws, fr, R, plan.ug, plan.uf, list(new_v), depth_lim, target)
    passes = sorted(plan.passes + added, key=lambda p: p.v)
    if len(passes) > tol.max_passes:
        return None
    plan2 = PassPlan(passes, plan.ug, plan.uf, plan.s_flat, plan.unreachable, plan.relaxed)
    tp = _program(spec, ws, fr, plan2, toolpath.info.get("estimate"), tol)
    tp.info["passes_added_after_verification"] = \
        toolpath.info.get("passes_added_after_verification", 0) + int(new_v.size)
    return tp


def _program(spec, ws, fr, plan, est, tol):
    """Stages 3-7: the program from the placed passes."""
    m = spec.machining
    R = 0.5 * float(spec.tool.diameter)
    scallop, tolerance = float(m.scallop), float(m.tolerance)
    safe_z = float(m.safe_height)
    depth_lim = min(float(spec.stock.depth_limit), float(spec.tool.reach))
    passes = plan.passes
    V = np.array([p.v for p in passes])
    Z = np.vstack([p.Z for p in passes])
    dZ = np.vstack([p.dZ for p in passes])
    keep = np.vstack([p.keep for p in passes])
    slope = np.vstack([p.slope for p in passes])
    sp, su, sz, nodes = space_points(ws, fr, R, V, plan.ug, Z, dZ, keep, tolerance,
                                     tol.max_program_points, spec.path, slope=slope)
    runs = cut_runs(sp, su, sz, nodes, AIR_CUT_FRACTION * tolerance)   # per pass: (k, 2) [u, z]
    passes_cut = [p for p in range(len(V)) if runs[p]]
    finish = order_runs(fr, m, V, runs, passes_cut)
    rough = rough_runs(spec, ws, fr, R, V, runs, passes_cut, depth_lim) \
        if getattr(m, "stepdown", None) else []
    all_runs = rough + [(("f", p), r) for p, r in finish]
    points, kinds = link_runs(ws, R, all_runs, max(4 * R, 4 * plan.s_flat), m.pattern != "zigzag",
                              safe_z, min(LINK_CLEARANCE, safe_z))
    planned = points
    points = _on_readback_grid(spec, ws, R, points, kinds)
    points, kinds = _refine_snapped(spec, ws, R, planned, points, kinds)
    if len(points) > tol.max_program_points:
        raise SpecError(f"{len(points)} program points (limit {tol.max_program_points}); raise "
                        "the tolerance", file=spec.path, key="machining.tolerance")
    zmin = check_depth_limits(spec, points)
    bridged = np.vstack([p.bridged for p in passes])
    info = summarize(fr, plan, V, passes_cut, points, kinds, zmin, len(rough), bridged, keep,
                     scallop, est)
    return Toolpath(points, kinds, tool_radius=R, safe_z=safe_z, passes=len(passes_cut),
                    stepover=info["stepover_max"], stepover_min=info["stepover_min"], info=info,
                    plan=plan)


def pass_gaps(V, Lv: float, eps: float = 1e-6):
    """(stepovers, gaps beyond the edges), mm: the distances between consecutive passes
    both over the stock (0 <= v <= Lv), and those between consecutive passes one of which
    lies beyond a stock edge (the edge passes stand up to R out, and the gap to them is not
    a stepover: on a V groove under a 6 mm ball it was 2.7 mm where flat ground takes 1.09).
    A block whose passes all lie beyond its edges (narrower than the tool) reports every gap
    as a stepover."""
    V = np.asarray(V, float)
    steps = np.diff(V)
    on = (V >= -eps) & (V <= Lv + eps)
    both = on[1:] & on[:-1]
    if not both.any():
        return steps, np.zeros(0)
    return steps[both], steps[~both]


def summarize(fr, plan, V, passes_cut, points, kinds, zmin, n_rough, bridged, keep, scallop,
              est) -> dict:
    """Stage 7b: ``Toolpath.info`` (figures and warnings)."""
    steps, beyond = pass_gaps(V, fr.Lv)
    seglen = np.linalg.norm(np.diff(points, axis=0), axis=1) if len(points) > 1 else np.zeros(0)
    feed = kinds[1:] != RAPID
    nb = int(bridged[keep].sum())
    info = {
        "passes": len(passes_cut),
        "stepover_max": float(steps.max()) if steps.size else 0.0,
        "stepover_min": float(steps.min()) if steps.size else 0.0,
        "stepover_flat": plan.s_flat,
        "edge_pass_gap_max": float(beyond.max()) if beyond.size else 0.0,
        "edge_comb_passes": sum(1 for p in passes_cut if plan.passes[p].comb),
        "points": int(len(points)),
        "cutting_length_mm": float(seglen[feed].sum()),
        "rapid_length_mm": float(seglen[~feed].sum()),
        "deepest_tip_mm": zmin,
        "roughing_runs": n_rough,
        "bridged_positions": nb,
        "pass_positions": [float(v) for v in V[passes_cut]],
        "estimate": {k: (round(float(v), 3) if isinstance(v, float) else v) for k, v in est.items()},
    }
    h, u, v = plan.unreachable
    if h > 0 and math.isfinite(u):
        X, Y = fr.xy(u, v)
        info["unreachable_bound_mm"] = h
        info["unreachable_at"] = (float(X), float(Y))
    if plan.relaxed is not None:
        h, u, v = plan.relaxed
        X, Y = fr.xy(u, v)
        info["scallop_bound_relaxed_mm"] = h
        info["scallop_warning"] = (
            f"near X={float(X):.2f}, Y={float(Y):.2f} mm even passes right beside each other "
            f"leave up to {h:.3f} mm by the planner's conservative bound; the stepover was "
            "relaxed there")
    if nb:
        pi, ji = np.nonzero(bridged & keep)
        X, Y = fr.xy(plan.ug[ji[0]], V[pi[0]])
        info["concave_warning"] = (f"{nb} tool positions span a concave region tighter than the "
                                   f"tool (first at X={float(X):.2f}, Y={float(Y):.2f} mm): the "
                                   "tool cannot reach the bottom there")
    return info
