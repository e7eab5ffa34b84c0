"""Estimates of a raster's size and planning time from the spec alone, before
anything is allocated or planned, and the guards that refuse what would exceed
the limits in :class:`fabkit.tolerances.Tolerances`.

The estimates come from the surface's exact slopes and curvatures on a grid (no
drop cutter): passes from the stepover the steepest slope across each strip
needs (closed form of the tilted-plane cusp), program points from the chord
spacing the curvature along the passes needs, roughing levels from the depth and
``machining.stepdown``, and the planning time from those counts with per-unit
costs measured on the 2-core reference machine (a conservative model, not a
measurement: about x2 either way).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import SpecError

# measured per-unit costs of the planner on the 2-core reference machine, seconds
SEC_PER_PASS_NODE = 1.2e-4     # pass placement: exact tip heights and material bounds, per node
SEC_PER_POINT = 2.0e-4         # point spacing, links and roughing, per program point
SEC_FIXED = 1.0


def stepover_on_slope(R: float, target: float, slope) -> np.ndarray:
    """Largest stepover (horizontal, mm) whose vertical cusp on a plane of the given
    slope across the passes is ``target`` (inverse of the tilted-plane cusp)."""
    c = 1.0 / np.sqrt(1.0 + np.asarray(slope, float) ** 2)
    t = np.minimum(target * c, R)
    return 2.0 * c * np.sqrt(np.maximum(2.0 * R * t - t * t, 0.0))


def estimate(spec, ws, fr, R: float, target: float, tolerance: float, depth_mm: float,
             n_nodes: int, n_grid: int = 201) -> dict:
    """Passes, program points, roughing levels and points, and planning seconds."""
    Lu, Lv = fr.Lu, fr.Lv
    u = np.linspace(0.0, Lu, n_grid)
    v = np.linspace(0.0, Lv, n_grid)
    UU, VV = np.meshgrid(u, v)                         # rows: v (across), columns: u (along)
    X, Y = fr.xy(UU, VV)
    H, hx, hy, hxx, hxy, hyy = ws.all(X, Y)
    Hu, Hv, Huu = (hx, hy, hxx) if fr.direction == "x" else (hy, hx, hyy)
    cut = np.isfinite(H) & (H < 0)
    fin = lambda a: np.where(np.isfinite(a), a, 0.0)   # noqa: E731
    # passes: per strip across, the stepover its steepest cut slope across allows
    slope_v = np.where(cut, np.abs(fin(Hv)), 0.0).max(axis=1)
    s_flat = float(stepover_on_slope(R, target, 0.0))
    s_row = np.maximum(stepover_on_slope(R, target, slope_v), 1e-3 * s_flat)
    passes = float(np.trapezoid(1.0 / s_row, v)) + 2.0
    # points per pass: chord spacing sqrt(8 e / k) along the arc, k the curvature along
    # the pass (at most 1/R: the tip path is an offset of the surface by R)
    e = 0.5 * tolerance
    w = np.sqrt(1.0 + fin(Hu) ** 2)
    k = np.minimum(np.abs(fin(Huu)) / w ** 3, 1.0 / R)
    dens = np.where(cut, np.sqrt(k / (8.0 * e)) * w, 0.0)
    per_pass = float(np.trapezoid(dens, u, axis=1).mean()) + 8.0
    points = passes * per_pass
    out = {"passes": passes, "points": points, "nodes": passes * n_nodes,
           "roughing_levels": 0, "roughing_points": 0.0}
    step = getattr(spec.machining, "stepdown", None)
    if step:
        leave = float(spec.machining.leave)
        levels = max(0, math.ceil((depth_mm - leave) / float(step)))
        mean_depth = float(np.where(cut, -fin(H), 0.0).mean())
        rough_passes = Lv / R + 2.0
        out["roughing_levels"] = levels
        out["roughing_points"] = rough_passes * per_pass * (mean_depth / float(step) + 1.0) \
            if levels else 0.0
    out["seconds"] = SEC_FIXED + SEC_PER_PASS_NODE * out["nodes"] + \
        SEC_PER_POINT * (points + out["roughing_points"])
    return out


MIN_LENGTH_MM = 1e-4   # scallop and tolerance below this are below any machine's resolution


def guard(est: dict, tol, spec_path=None, scallop=None, tolerance=None) -> None:
    """Refuse (SpecError, exit 2, naming the key and the estimate) beyond the guards."""
    for key, val in (("machining.scallop", scallop), ("machining.tolerance", tolerance)):
        if val is not None and val < MIN_LENGTH_MM:
            raise SpecError(f"must be >= {MIN_LENGTH_MM:g} mm, got {val:g} mm: finer than any machine "
                            "resolves (the program has at most 6 decimals)", file=spec_path, key=key)
    if est["passes"] > tol.max_passes:
        raise SpecError(f"needs about {est['passes']:.3g} passes (limit {tol.max_passes}); "
                        "raise the scallop", file=spec_path, key="machining.scallop")
    if est["roughing_levels"] > tol.max_roughing_levels:
        raise SpecError(f"needs {est['roughing_levels']} roughing levels (limit "
                        f"{tol.max_roughing_levels}); raise the stepdown", file=spec_path,
                        key="machining.stepdown")
    if est["points"] > tol.max_program_points:
        raise SpecError(f"needs about {est['points']:.3g} program points (limit "
                        f"{tol.max_program_points}); raise the tolerance or the scallop",
                        file=spec_path, key="machining.tolerance")
    if est["points"] + est["roughing_points"] > tol.max_program_points:
        raise SpecError(f"roughing needs about {est['roughing_points']:.3g} program points "
                        f"(limit {tol.max_program_points} in all); raise the stepdown",
                        file=spec_path, key="machining.stepdown")
    if est["seconds"] > tol.max_plan_seconds:
        key = "machining.scallop" if SEC_PER_PASS_NODE * est["nodes"] >= \
            SEC_PER_POINT * (est["points"] + est["roughing_points"]) else \
            ("machining.stepdown" if est["roughing_points"] > est["points"] else "machining.tolerance")
        raise SpecError(f"planning would take about {est['seconds']:.0f} s ({est['passes']:.3g} "
                        f"passes, {est['points'] + est['roughing_points']:.3g} program points; "
                        f"limit {tol.max_plan_seconds:g} s); raise {key.split('.')[1]}",
                        file=spec_path, key=key)
