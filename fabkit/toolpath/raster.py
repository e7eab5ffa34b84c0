"""Raster planning for a ball-end mill, as named stages a test can call one by one:

1. :func:`fabkit.toolpath.guards.estimate` / ``guard``: passes, points, roughing
   levels and planning time from the spec, refused before any work.
2. :func:`fabkit.toolpath.passes.place_passes`: the passes across with the
   slope-aware stepover; each pass carries its exact tip heights
   (:func:`fabkit.toolpath.passes.compensate_passes`, the drop cutter of
   :mod:`fabkit.toolpath.compensate`).
3. :func:`fabkit.toolpath.spacing.space_points`: points along each pass within the
   chord tolerance, air left out.
4. :func:`order_runs`: cut runs in machining order (zigzag or one-way).
5. :func:`fabkit.toolpath.rough.rough_runs`: optional z-level roughing runs.
6. :func:`fabkit.toolpath.links.link_runs`: links, retracts and rapids.
7. :func:`check_depth_limits` and :func:`summarize`.

Work coordinates, mm (see :mod:`fabkit.toolpath.path`); the rules and their
accuracy are in each stage's module and in docs/toolpath.md.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import SpecError
from ..tolerances import DEFAULT, Tolerances
from .compensate import WorkSurface
from .guards import estimate, guard
from .links import link_runs
from .passes import (SCALLOP_SAFETY, Frame, flat_stepover, place_passes, sweep_material,
                     tilted_plane_cusp)
from .path import RAPID, Toolpath
from .rough import rough_runs
from .spacing import CHORD_SAFETY, _runs, space_points

LINK_CLEARANCE = 1.0    # mm above material for short links and approaches (<= safe_height)

__all__ = ["plan_toolpath", "plan_estimate", "order_runs", "check_depth_limits", "summarize",
           "flat_stepover", "tilted_plane_cusp", "sweep_material"]


def plan_estimate(spec, surface, tol: Tolerances = DEFAULT) -> dict:
    """Stage 1: the estimates (passes, points, roughing levels/points, seconds), and
    SpecError (exit 2, naming the key and the estimate) beyond the guards."""
    from .passes import u_grid

    R = 0.5 * float(spec.tool.diameter)
    ws = surface if isinstance(surface, WorkSurface) else WorkSurface(surface)
    fr = Frame(spec.machining.direction, ws.L, ws.W)
    depth = max(0.0, -float(np.min(ws.H(*np.meshgrid(np.linspace(0, ws.L, 101),
                                                      np.linspace(0, ws.W, 101))))))
    if getattr(spec.machining, "stepdown", None):
        from ..surface import Surface
        if isinstance(surface, Surface):
            depth = surface.depth_mm()
    est = estimate(spec, ws, fr, R, SCALLOP_SAFETY * float(spec.machining.scallop),
                   float(spec.machining.tolerance), depth, len(u_grid(fr, R)))
    guard(est, tol, spec.path, float(spec.machining.scallop), float(spec.machining.tolerance))
    return est


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


def check_depth_limits(spec, points) -> float:
    """Stage 7a: refuse a tip deeper than ``stock.depth_limit`` / ``tool.reach``,
    naming where. Returns the deepest tip z (mm, <= 0)."""
    if not len(points):
        return 0.0
    if not np.isfinite(points).all():
        raise ValueError("non-finite program point")       # a planner defect, never input
    i = int(np.argmin(points[:, 2]))
    zmin = float(points[i, 2])
    for key, lim in (("stock.depth_limit", float(spec.stock.depth_limit)),
                     ("tool.reach", float(spec.tool.reach))):
        if -zmin > lim + 1e-9:
            raise SpecError(f"the tool tip goes {-zmin:.3f} mm deep at X={points[i, 0]:.2f}, "
                            f"Y={points[i, 1]:.2f} mm, {-zmin - lim:.3f} mm more than the limit "
                            f"{lim:g} mm", file=spec.path, key=key)
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
    plan = place_passes(ws, fr, R, scallop, depth_lim, tol.max_passes, spec.path,
                        chord=CHORD_SAFETY * tolerance)
    passes = plan.passes
    V = np.array([p.v for p in passes])
    Z = np.vstack([p.Z for p in passes])
    dZ = np.vstack([p.dZ for p in passes])
    keep = np.vstack([p.keep for p in passes])
    sp, su, sz, nodes = space_points(ws, fr, R, V, plan.ug, Z, dZ, keep, tolerance,
                                     tol.max_program_points, spec.path)
    runs = _runs(sp, su, sz, nodes)          # per pass: runs of (k, 2) [u, z]
    passes_cut = [p for p in range(len(V)) if runs[p]]
    finish = order_runs(fr, m, V, runs, passes_cut)
    rough = rough_runs(spec, ws, fr, R, V, runs, passes_cut, depth_lim) \
        if getattr(m, "stepdown", None) else []
    all_runs = rough + [(("f", p), r) for p, r in finish]
    points, kinds = link_runs(ws, R, all_runs, max(4 * R, 4 * plan.s_flat), m.pattern != "zigzag",
                              safe_z, min(LINK_CLEARANCE, safe_z))
    if len(points) > tol.max_program_points:
        raise SpecError(f"{len(points)} program points (limit {tol.max_program_points}); raise "
                        "the tolerance", file=spec.path, key="machining.tolerance")
    zmin = check_depth_limits(spec, points)
    bridged = np.vstack([p.bridged for p in passes])
    info = summarize(fr, plan, V, passes_cut, points, kinds, zmin, len(rough), bridged, keep,
                     scallop, est)
    return Toolpath(points, kinds, tool_radius=R, safe_z=safe_z, passes=len(passes_cut),
                    stepover=info["stepover_max"], stepover_min=info["stepover_min"], info=info)


def summarize(fr, plan, V, passes_cut, points, kinds, zmin, n_rough, bridged, keep, scallop,
              est) -> dict:
    """Stage 7b: ``Toolpath.info`` (figures and warnings)."""
    steps = np.diff(V)
    seglen = np.linalg.norm(np.diff(points, axis=0), axis=1) if len(points) > 1 else np.zeros(0)
    feed = kinds[1:] != RAPID
    nb = int(bridged[keep].sum())
    info = {
        "passes": len(passes_cut),
        "stepover_max": float(steps.max()) if steps.size else 0.0,
        "stepover_min": float(steps.min()) if steps.size else 0.0,
        "stepover_flat": plan.s_flat,
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
