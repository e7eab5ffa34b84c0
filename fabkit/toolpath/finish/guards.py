"""Estimates of a raster's size and planning time from the spec alone, before
anything is allocated or planned, and the guards that refuse what would exceed
the limits in :class:`fabkit.tolerances.Tolerances`.

The estimates come from the surface's exact slopes and curvatures on a grid (no
drop cutter): passes from the stepover the worst point of each strip across
needs (slopes along and across the passes and convex curvature across: closed
form of the cusp between two passes' swept cylinders), program points from the chord
spacing the curvature along the passes needs, roughing levels from the depth and
``machining.stepdown``, and the CPU time of the whole job (planning, verification,
setup sheet, start-up) from those counts, the verify points and the share of the
footprint near a concave crease tighter than the ball, with per-unit costs measured
on the 2-core reference machine (a model, not a measurement: with the compiled
kernels the measured CPU time was 0.8-1.25 of it on the jobs it was fitted to, see
the constants). The time guard is
a budget: ``machining.max_time`` or ``--max-time`` (default
:attr:`fabkit.tolerances.Tolerances.max_plan_seconds`).
"""

from __future__ import annotations

import math

import numpy as np

from ...errors import SpecError

# per-unit CPU costs of the whole `fabkit gcode` job on the 2-core reference machine,
# seconds. The planner's per-pass terms were fitted to the stage times of place_passes
# and space_points on a near-flat bowl (three sizes, scallops 0.002-0.05 mm), planes of
# slope 4 and 8 in both raster directions, a V crease in both directions, an exponential
# wall, a valley and the paper's surface, then rescaled (x0.6 but the steep terms, and
# 1.6e-4 s per program point for planning, writing and the setup sheet), with the fixed
# cost (process, imports, spec, the surface's compiled derivatives, the depth search,
# the sheet's figure) and the verification, to the measured CPU time (user + sys) of the
# whole command on seven jobs at load 6-12: specs/surface.yaml, specs/bowl.yaml, the
# paper's surface with a 1/8 in ball at scallop 0.02 mm, a 5 x 40 mm plane of slope 4
# and a 10 x 20 mm block of 3*abs(x) (bowl's tool), a 3 x 30 mm plane of slope 8 along
# the passes and an oblique V crease: measured / estimated 0.76-1.43 there, except the
# plane steep along the passes in a second run (2.28: its CPU time varied 10.1-14.9 s
# between runs, and its per-pass cost is not explained by these terms; see
# benchmarks/notes_gcode_profile.md)
#: with the compiled drop cutter and swept cut (toolpath/finish/dropcut.py) every planning term
#: was scaled by PLAN_SCALE, the fixed cost and the verification refitted, to the measured
#: CPU time of the whole command on plane, block, steep, vee, tiny, bowl, surface, the
#: paper's surface at scallop 0.02 mm and four dishes (benchmarks/notes_gcode_profile.md,
#: "With the compiled kernels"): measured / estimated 0.8-1.25 there
PLAN_SCALE = 0.72
#: refitted again (issue 28's second pass: the material bound, the point spacing and the
#: crease search compiled, the formula's derivatives cached) by a minimax fit of each
#: group's factor to the CPU time of the whole command on plane, tiny, block, steep, vee,
#: bowl, surface, surface_eps015 and the paper's surface at scallop 0.02 mm (load 1.0):
#: measured / estimated 0.74-1.34 there (benchmarks/notes_gcode_profile.md, "Second pass")
#: and again (issue 28's third pass: numba's short start-up on cached code, the drop
#: cutter's batched samples): the pass and steep factors x 0.75, the points' x 0.7, the
#: tight points' 1.0 -> 0.8 and the fixed cost 1.7 -> 1.1 s, fitted over plane, tiny,
#: block, steep, vee, bowl, surface, surface_eps015, the 1/8 in ball job and the roughing
#: job, two runs each (load 1.1): measured / estimated 0.60-1.49 there. The extremes were
#: the two creases: a crease oblique to the passes crowds them where it crosses them (the
#: V at 17 degrees: 123 passes against 34 estimated; at 45 degrees 214 against 25, 3x
#: under) and costs more per tight point to verify. Hence OBLIQUE_*: the rows an oblique
#: crease crosses at 0.08 of the flat stepover, and its tight points' verification by
#: obliqueness and ball; on V creases at 0, 17, 30, 35 and 45 degrees, along and across
#: the passes, 3.2-6 mm balls: 0.66-1.23 (benchmarks/notes_gcode_profile.md, "Third pass")
FIT_PASS, FIT_BALL, FIT_STEEP, FIT_POINT, FIT_VERIFY, FIT_TIGHT = 0.15, 0.33, 0.2775, 0.273, 0.5, 0.8
SEC_PER_PASS = 4.8e-3 * PLAN_SCALE * FIT_PASS       # pass placement, per pass: fixed cost (two bounds, a few calls)
SEC_PER_PASS_NODE = 1.2e-5 * PLAN_SCALE * FIT_PASS  # per node along a pass: exact tip heights (incl. trial passes)
SEC_PER_BALL = 9e-7 * PLAN_SCALE * FIT_BALL         # per column and fine ball position within R along the pass
SEC_STEEP_PASS = 3e-2 * PLAN_SCALE * FIT_STEEP      # passes over ground steep along the pass: the bound's stage 3
SEC_STEEP_COLUMN = 1e-4 * PLAN_SCALE * FIT_STEEP    # and per steep column
SEC_PER_POINT = 1.75e-4 * PLAN_SCALE * FIT_POINT    # point spacing, links, roughing, writing, the sheet, per program point
SEC_FIXED = 1.1                # start-up (imports, loading the compiled kernels), spec, derivatives, depth,
                               # the planner's and the sheet's fixed costs (1.7 before numba's short start-up; 3.0 before the formula's
                               # derivatives were cached and the depth search left scipy: 1.2-1.5 s less
                               # on the tiny and plane jobs, benchmarks/notes_gcode_profile.md)
SEC_PER_VERIFY_POINT = 1.4e-5 * FIT_VERIFY  # verification per verify point: swept cut and reachable height
SEC_PER_TIGHT_POINT = 2.0e-4 * FIT_TIGHT    # per verify point within R of a concave crease or valley tighter
                               # than the ball: the reachable height's search (the model descent:
                               # 7.8e-5 on the 3*abs(x) block, 2.8e-4 on the oblique V; it was
                               # 7.6e-4 and 7.0e-4 with the compass search)
OBLIQUE_STEP = 0.08            # stepover over strips an oblique tight crease crosses, share of the flat one
OBLIQUE_MIN = 0.15             # a crease counts as oblique beyond this tan(angle to the passes)
OBLIQUE_VERIFY = 4.0           # a tight point's verification costs (1 + this x obliqueness x (R / OBLIQUE_R)^2)
OBLIQUE_R = 2.0                # times more (mm)
STEEP_ALONG = 1.5              # as fabkit.toolpath.finish.passes.STEEP_ALONG
# memory (peak resident, bytes): the process with the verification and the setup sheet
# (measured 470-810 MB end to end on the jobs above, programs of 900-91 000 lines;
# the small blocks' peak is the verification's chunk of segment-point pairs), what the
# planner holds per pass (fine profile and nodes) and per program point (~6 evaluated
# samples per point at the peak of the point spacing's batched drop cutter): measured /
# estimated 0.72-1.44 on those jobs (1.15 GB measured, 0.95 GB estimated on the 1/8 in
# ball at scallop 0.02 mm)
BYTES_BASE = 175e6             # 560e6 before the kernels, 230e6 before the second pass
BYTES_PER_POINT = 2500.0       # (and the per-pass bytes x MEM_SCALE): measured / estimated 0.83-1.01
MEM_SCALE = 0.5                # on plane, bowl, surface and the 1/8 in ball job (peak 179-374 MB)
# roughing with its own tool, per node of the stock's grid (toolpath/cut/stock.py): the paper's
# rough + rest + finish job (2001 x 1001 nodes) measured 12.6-16.0 s CPU and 617-694 MB
SEC_PER_STOCK_NODE = 3.2e-6
BYTES_PER_STOCK_NODE = 180.0
MAX_BYTES = 1.8e9              # refused beyond this (the process stays under 2 GB)
MAX_SLOPE = 20.0               # slopes beyond this count as this (the wall is cut by the rim)


def stepover_on_slope(R: float, target: float, slope, slope_along=0.0, curvature=0.0,
                      normal: bool = False) -> np.ndarray:
    """Largest stepover (horizontal, mm) whose cusp between two passes is ``target``
    (along the plane's normal with ``normal``, else vertically) on a plane of the given
    slope across the passes and ``slope_along`` along them, with a convex ``curvature``
    across (1/mm, >= 0): the passes' swept cylinders (axes along the plane's slope along
    the pass) are d = s sqrt(G / (1 + a^2)) apart (G = 1 + a^2 + b^2, a along, b across),
    their cusp normal to the plane is R' - sqrt(R'^2 - d^2 / 4) (1/R' = 1/R + curvature),
    and vertically sqrt(G) times that. Closed form; a = 0, no curvature: the tilted-plane
    cusp across."""
    a = np.minimum(np.abs(np.asarray(slope_along, float)), MAX_SLOPE)
    b = np.minimum(np.abs(np.asarray(slope, float)), MAX_SLOPE)
    G = 1.0 + a * a + b * b
    Re = 1.0 / (1.0 / R + np.maximum(np.asarray(curvature, float), 0.0))
    hn = np.minimum(target if normal else target / np.sqrt(G), Re)
    d = 2.0 * np.sqrt(np.maximum(2.0 * Re * hn - hn * hn, 0.0))
    return d * np.sqrt((1.0 + a * a) / G)


def estimate(spec, ws, fr, R: float, target: float, tolerance: float, depth_mm: float,
             n_nodes: int, n_grid: int = 201, n_fine: int | None = None,
             fine_step: float | None = None, normal: bool = False) -> dict:
    """Passes, program points, roughing levels and points, planning seconds and memory
    (bytes), from the surface's exact slopes and curvatures on an n_grid^2 grid.

    n_nodes: nodes along a pass (:func:`fabkit.toolpath.finish.passes.u_grid`); n_fine and
    fine_step: the material bounds' fine grid along a pass (size, step mm)."""
    Lu, Lv = fr.Lu, fr.Lv
    u = np.linspace(0.0, Lu, n_grid)
    v = np.linspace(0.0, Lv, n_grid)
    UU, VV = np.meshgrid(u, v)                         # rows: v (across), columns: u (along)
    X, Y = fr.xy(UU, VV)
    H, hx, hy, hxx, hxy, hyy = ws.all(X, Y)
    Hu, Hv, Huu, Hvv = (hx, hy, hxx, hyy) if fr.direction == "x" else (hy, hx, hyy, hxx)
    cut = np.isfinite(H) & (H < 0)
    fin = lambda a: np.where(np.isfinite(a), a, 0.0)   # noqa: E731
    # passes: per strip across, the stepover its worst cut point allows (slopes along
    # and across, convex curvature across up to 1/R)
    kv = np.minimum(np.maximum(-fin(Hvv), 0.0) / (1.0 + fin(Hv) ** 2) ** 1.5, 1.0 / R)
    s_pt = stepover_on_slope(R, target, fin(Hv), fin(Hu), kv, normal)
    s_flat = float(stepover_on_slope(R, target, 0.0))
    s_row = np.where(cut, s_pt, s_flat).min(axis=1)
    s_row = np.maximum(s_row, 0.02 * s_flat)
    # a crease (or a valley) tighter than the ball running obliquely across the passes:
    # the placement crowds the passes over the strips it crosses (measured 0.07-0.09 of the
    # flat stepover on V creases at 17, 30 and 45 degrees to the passes)
    tight, oblique, oblique_rows = _creases(fr, R, Hu, Hv, cut, u, v)
    s_row = np.where(oblique_rows, np.minimum(s_row, OBLIQUE_STEP * s_flat), s_row)
    passes = float(np.trapezoid(1.0 / s_row, v)) + 2.0
    # points per pass: chord spacing sqrt(8 e / k) along the arc, k the curvature along
    # the pass (at most 1/R: the tip path is an offset of the surface by R), x1.6 for the
    # simplification's leftovers, and ~20 for the ends (the ball leaving the stock over
    # its edges), the links and the crease with the top face
    e = 0.5 * tolerance
    w = np.sqrt(1.0 + fin(Hu) ** 2)
    k = np.minimum(np.abs(fin(Huu)) / w ** 3, 1.0 / R)
    dens = np.where(cut, np.sqrt(k / (8.0 * e)) * w, 0.0)
    per_pass = 1.6 * float(np.trapezoid(dens, u, axis=1).mean()) + 20.0
    points = passes * per_pass
    out = {"passes": passes, "points": points, "nodes": passes * n_nodes,
           "roughing_levels": 0, "roughing_points": 0.0,
           "max_time": getattr(spec.machining, "max_time", None)}
    step = getattr(spec.machining, "stepdown", None)
    if step:
        leave = float(spec.machining.leave)
        levels = max(0, math.ceil((depth_mm - leave) / float(step)))
        mean_depth = float(np.where(cut, -fin(H), 0.0).mean())
        rough_passes = Lv / R + 2.0
        out["roughing_levels"] = levels
        out["roughing_points"] = rough_passes * per_pass * (mean_depth / float(step) + 1.0) \
            if levels else 0.0
    # planning time: per pass, the exact tip heights (nodes), the material bounds (the
    # balls within R along the pass at each column, and the rim search where the ground
    # is steep along the pass), then per program point
    n_fine = n_fine or 4 * n_nodes
    fine_step = fine_step or Lu / max(n_fine - 1, 1)
    cols = n_nodes * Lu / (Lu + 2.0 * R)
    balls = 2.0 * (math.ceil(R / fine_step) + 3) + 1.0
    steep_cols = float(((np.abs(fin(Hu)) * cut).max(axis=0) > STEEP_ALONG).mean()) * cols
    per_pass_s = SEC_PER_PASS + SEC_PER_PASS_NODE * n_nodes + SEC_PER_BALL * cols * balls + \
        ((SEC_STEEP_PASS + SEC_STEEP_COLUMN * steep_cols) if steep_cols else 0.0)
    out["place_seconds"] = passes * per_pass_s
    out["plan_seconds"] = out["place_seconds"] + SEC_PER_POINT * (points + out["roughing_points"])
    # the verification: the swept cut and the reachable height at each verify point (one
    # drop cutter), and where a ball touching the design there is not free (a V crease,
    # a valley tighter than the ball: within R of where the concave curvature exceeds
    # 1/R) the reachable height's search (tens of drop cutters per point)
    vp = float(getattr(spec.machining, "verify_points", 40000))
    out["tight_fraction"] = tight
    out["oblique"] = oblique
    # (an oblique crease's points cost more, the more so the larger the ball: measured on V
    # creases at 0-45 degrees to the passes under 3.2-6 mm balls)
    out["verify_seconds"] = vp * (SEC_PER_VERIFY_POINT + SEC_PER_TIGHT_POINT * tight
                                  * (1.0 + OBLIQUE_VERIFY * oblique * (R / OBLIQUE_R) ** 2))
    # roughing with its own tool (the spec's `roughing` section): its levels, the rest
    # passes and the whole job's stock simulation, per node of the stock's grid
    out["roughing_seconds"] = out["roughing_bytes"] = 0.0
    if hasattr(spec, "has") and spec.has("roughing"):
        from ..rough.roughing import spec_tools
        from ..cut.stock import grid_spacing

        h = grid_spacing(list(spec_tools(spec).values()), tolerance)
        nodes = (ws.L / h + 1.0) * (ws.W / h + 1.0)
        rough = roughing_estimate(spec, ws, H, hx, hy, hxx, hxy, hyy, depth_mm, tolerance, h)
        out.update(rough)
        out["roughing_seconds"] = SEC_PER_STOCK_NODE * nodes + rough["rough_seconds"]
        out["roughing_bytes"] = BYTES_PER_STOCK_NODE * nodes + rough["rough_bytes"]
    out["plan_seconds"] += out["roughing_seconds"]
    # a first run compiles the kernels it lacks (once per installation, or per formula)
    from .kernels import cold_build_seconds

    out["build_seconds"] = cold_build_seconds(ws.surface) if hasattr(ws, "surface") else 0.0
    out["seconds"] = SEC_FIXED + out["plan_seconds"] + out["verify_seconds"] + out["build_seconds"]
    out["bytes"] = BYTES_BASE + MEM_SCALE * passes * (16.0 * n_fine + 80.0 * n_nodes) + \
        BYTES_PER_POINT * (points + out["roughing_points"]) + out["roughing_bytes"]
    return out


# roughing with its own tool (toolpath/rough/roughing.py), before planning: the levels' loops or
# rows (their length: each level's area / stepover), the program points on them, and the
# whole-job check's reach search (stock.reach_height: per stock-grid centre within R of a
# node asked, the tool's offsets within R). The loops are offsets of contours on the design
# grid of step hg (roughing.grid_step): their vertices per mm grow as 1 / hg. Measured
# (tolerance 0.01 mm, load ~2): the paper's job (1/2 in flat, hg 0.29 mm, stepover 0.25-6
# mm, 10 levels) planned in 3.3-4.9 us per mm of loop, 0.125 program points per mm, 270
# bytes per mm; a 27 x 40 mm block (1 mm flat, hg 0.125 mm, stepover 0.1-0.2 mm) 25 us,
# 0.30 points and 870 bytes per mm: seconds per mm 4.1e-7 / hg^2, points 0.036 / hg, bytes
# 100 / hg (hg in mm). The reach kernel: 1.5-2.8 ns per centre-offset pair (flat 6.35-40 mm
# on a 0.25 mm grid)
SEC_ROUGH_MM_HG2 = 4.1e-7
ROUGH_POINTS_MM_HG = 0.036
BYTES_ROUGH_MM_HG = 100.0
SEC_PER_REACH_PAIR = 3.0e-9
ROUGH_GRID_MAX_NODES = 1_500_000    # as roughing.GRID_MAX_NODES


def roughing_estimate(spec, ws, H, hx, hy, hxx, hxy, hyy, depth_mm: float, tolerance: float, h: float) -> dict:
    """The roughing's work before planning, from the design H on the grid X, Y (work mm):
    its levels (every ``roughing.stepdown`` down to the allowance's lowest point or the
    tool's reach and stock.depth_limit), the length of its loops or rows (per level the
    area where the design + leave lies below the level, with the band beyond the stock's
    edges the tool may stand in, over the stepover), their program points, the planning
    seconds and bytes, and the worst case of the whole-job check's reach search (every
    stock node asked, ``stock_grid_mm`` h). Also the depth the roughing tool must reach
    (``rough_depth_mm``) against its ``reach``."""
    from ..rough.roughing import spec_tools

    fin = lambda a: np.where(np.isfinite(a), a, 0.0)   # noqa: E731
    rg = spec.roughing
    tools = spec_tools(spec)
    tool = tools[int(rg.tool)]
    R, step, s, leave = tool.radius, float(rg.stepdown), float(rg.stepover), float(rg.leave)
    lim = min(float(spec.stock.depth_limit), float(tool.reach))
    Hf = np.where(np.isfinite(H), H, np.inf)
    e = max(0.0, R - 0.5 * s)
    area_cell = ws.L * ws.W / Hf.size
    # the edge nodes (for the band beyond the stock): spacing along each edge
    edge = np.r_[Hf[0, :], Hf[-1, :], Hf[:, 0], Hf[:, -1]]
    edge_len = 2.0 * (ws.L + ws.W) / max(len(edge), 1)
    corners = np.array([Hf[0, 0], Hf[0, -1], Hf[-1, 0], Hf[-1, -1]])
    bottom = float(np.min(Hf)) + leave if np.isfinite(np.min(Hf)) else 0.0
    zs, k = [], 1                      # the planner's levels (roughing.plan_rough)
    while True:
        z = -k * step
        if z <= bottom - 1e-9 or z < -lim - 1e-9:
            z = max(z, -lim)
            if not (z <= bottom + 1e-9 or (zs and z >= zs[-1] - 1e-9)):
                zs.append(z)
            break
        zs.append(z)
        k += 1
    length = 0.0
    for z in zs:
        band = e * edge_len * float(np.sum(edge + leave < z)) + math.pi * e * e * float(np.sum(corners + leave < z)) / 4
        length += (float(np.sum(Hf + leave < z)) * area_cell + band) / s
    levels = len(zs)
    # the design grid's step (roughing.grid_step, from the exact curvatures here: the planner's
    # coarse second differences see no more, so this step is at most the planner's)
    band = np.isfinite(H) & (H >= -lim - leave - 1.0) & (H <= 0.0)
    C = float(np.max((np.abs(fin(hxx)) + np.abs(fin(hyy)) + 2.0 * np.abs(fin(hxy)))[band])) if band.any() else 0.0
    hg = min(1.0, R / 4.0, math.sqrt(8.0 * 0.5 * tolerance / (6.0 * C)) if C > 0 else 1.0)
    hg = max(hg, math.sqrt(ws.L * ws.W / ROUGH_GRID_MAX_NODES))
    # the loops' inset shrinks on steep walls (roughing.plan_rough: down to a tenth of the
    # tolerance); the points grow as the square root of tolerance / inset (paper: 3.2x at 0.1)
    slope = np.hypot(fin(hx), fin(hy))[band] if band.any() else np.zeros(1)
    m = float(min(20.0, slope.max())) if slope.size else 0.0
    chord = R * (1.0 / math.cos(math.pi / 128) - 1.0)
    inset = tolerance if m <= 0 else min(tolerance, max(0.1 * tolerance, (0.5 * tolerance - chord * m) / (2 * m)))
    pts = length * ROUGH_POINTS_MM_HG / hg * math.sqrt(tolerance / inset)
    # the reach search's worst case, per tool of the job: centres (the stock grid grown by R)
    # times the tool's offsets within R
    reach_pairs, reach_key, worst = 0.0, None, 0.0
    listed = {int(t.number): i for i, t in enumerate(spec.tools)}
    for n, t in tools.items():
        cen = (ws.L / h + 1.0 + 2.0 * t.radius / h) * (ws.W / h + 1.0 + 2.0 * t.radius / h)
        pairs = cen * math.pi * (t.radius / h + 1.0) ** 2
        reach_pairs += pairs
        if pairs > worst:
            worst, reach_key = pairs, (f"tools[{listed[n]}].diameter" if n in listed else "tool.diameter")
    depth_need = min(depth_mm, float(spec.stock.depth_limit)) - leave
    return {"rough_levels": levels, "rough_length_mm": length, "rough_points": pts,
            "rough_seconds": SEC_ROUGH_MM_HG2 * length / (hg * hg) + SEC_PER_POINT * pts,
            "rough_bytes": BYTES_ROUGH_MM_HG * length / hg + BYTES_PER_POINT * pts, "rough_grid_mm": hg,
            "rough_reach_pairs": reach_pairs, "rough_reach_seconds": SEC_PER_REACH_PAIR * reach_pairs,
            "rough_reach_key": reach_key, "rough_depth_mm": depth_need,
            "rough_tool_reach_mm": float(tool.reach), "rough_stepdown_mm": step,
            "rough_tool_key": f"tools[{listed[int(rg.tool)]}]", "stock_grid_mm": h}


def roughing_guard(est: dict, tol, spec_path=None) -> None:
    """Refuse (SpecError, exit 2, naming the key and the estimate) a roughing beyond the
    guards: a tool that cannot reach within one stepdown of the allowance's bottom, loops
    whose points, memory or time exceed the limits, a reach search beyond the time budget."""
    if "rough_levels" not in est:
        return
    budget = est.get("max_time") or tol.max_plan_seconds
    key = est["rough_tool_key"]
    need = est["rough_depth_mm"] - est["rough_stepdown_mm"]
    if est["rough_tool_reach_mm"] < need:
        raise SpecError(f"{est['rough_tool_reach_mm']:g} mm: the roughing must reach {est['rough_depth_mm']:.3g} mm "
                        f"below the top face (the design's depth less roughing.leave, within stock.depth_limit), "
                        f"within one stepdown; give the roughing tool at least {need:.3g} mm of reach",
                        file=spec_path, key=f"{key}.reach")
    if est["rough_points"] > tol.max_program_points:
        raise SpecError(f"roughing needs about {est['rough_points']:.3g} program points ({est['rough_length_mm']:.3g} "
                        f"mm of loops over {est['rough_levels']} levels; limit {tol.max_program_points}); raise "
                        "the stepover", file=spec_path, key="roughing.stepover")
    if est["rough_bytes"] > MAX_BYTES:
        raise SpecError(f"roughing would need about {est['rough_bytes'] / 1e9:.2g} GB of memory "
                        f"({est['rough_length_mm']:.3g} mm of loops over {est['rough_levels']} levels; limit "
                        f"{MAX_BYTES / 1e9:g} GB); raise the stepover", file=spec_path, key="roughing.stepover")
    if est["rough_seconds"] > budget:
        raise SpecError(f"roughing would take about {est['rough_seconds']:.0f} s of CPU time "
                        f"({est['rough_length_mm']:.3g} mm of loops over {est['rough_levels']} levels; limit "
                        f"{budget:g} s): raise the stepover, or the limit with --max-time SECONDS or "
                        "machining.max_time", file=spec_path, key="roughing.stepover")
    if est["rough_reach_seconds"] > budget:
        raise SpecError(f"the whole job's check would search each tool's reach over up to "
                        f"{est['rough_reach_pairs']:.3g} centre-offset pairs of the {est['stock_grid_mm']:.3g} mm "
                        f"stock grid (about {est['rough_reach_seconds']:.0f} s of CPU time; limit {budget:g} s): the "
                        "tool is too large for the block and the grid the finishing tool needs",
                        file=spec_path, key=est["rough_reach_key"])


def _dilate(mask: np.ndarray, r: int, axis: int) -> np.ndarray:
    """True within r cells of a True cell along ``axis`` (a moving-window count)."""
    if r <= 0:
        return mask
    m = np.moveaxis(mask, axis, -1).astype(np.int64)
    c = np.concatenate([np.zeros(m.shape[:-1] + (1,), np.int64), np.cumsum(m, axis=-1)], axis=-1)
    n = m.shape[-1]
    i = np.arange(n)
    hi, lo = np.minimum(i + r + 1, n), np.maximum(i - r, 0)
    return np.moveaxis((c[..., hi] - c[..., lo]) > 0, -1, axis)


def _creases(fr, R: float, Hu, Hv, cut, u, v):
    """(:func:`_tight_fraction`, how oblique to the passes the tight creases run, the rows
    across (v) they cross obliquely). At each point concave tighter than the ball the
    jumps of the slope along and across the passes, over one grid cell, are in the ratio
    tan(angle between the crease and the passes): ``oblique`` is the mean over those
    points of min/max of the two (0 along or across the passes, 1 at 45 degrees); a row
    within R of a point whose ratio exceeds OBLIQUE_MIN is crossed obliquely."""
    du, dv, ku, kv, at = _concave(R, Hu, Hv, cut, u, v)
    tight = _tight_band(R, at, cut, du, dv)
    rows = np.zeros(len(v), dtype=bool)
    if tight == 0.0 or len(u) < 2 or len(v) < 2:
        return tight, 0.0, rows
    with np.errstate(all="ignore"):
        a, b = np.maximum(ku, 0.0) * du, np.maximum(kv, 0.0) * dv
        ratio = np.where(at, np.minimum(a, b) / np.maximum(np.maximum(a, b), 1e-300), 0.0)
    oblique = float(ratio[at].mean())
    crossed = (at & (ratio > OBLIQUE_MIN)).any(axis=1)
    rows = _dilate(crossed, int(math.ceil(R / dv)), 0)
    return tight, oblique, rows


def _concave(R: float, Hu, Hv, cut, u, v):
    """(du, dv, curvature along u, across v, the cut points concave tighter than the
    ball), the curvatures from differences of the exact slopes on the grid, so that a V
    crease counts too."""
    with np.errstate(all="ignore"):
        du = u[1] - u[0] if len(u) > 1 else 1.0
        dv = v[1] - v[0] if len(v) > 1 else 1.0
        su = np.where(np.isfinite(Hu), Hu, 0.0)
        sv = np.where(np.isfinite(Hv), Hv, 0.0)
        ku = np.gradient(su, du, axis=1) / (1.0 + su * su) ** 1.5
        kv = np.gradient(sv, dv, axis=0) / (1.0 + sv * sv) ** 1.5
        tight = cut & ((ku > 1.0 / R) | (kv > 1.0 / R))
    return du, dv, ku, kv, tight


def _tight_band(R: float, tight, cut, du, dv) -> float:
    """The share of the footprint cut within R of the points ``tight``."""
    if not tight.any():
        return 0.0
    near = _dilate(_dilate(tight, int(math.ceil(R / du)), 1), int(math.ceil(R / dv)), 0)
    return float((near & cut).mean())


def _tight_fraction(fr, R: float, Hu, Hv, cut, u, v) -> float:
    """Fraction of the footprint within R of where the surface is concave tighter than
    the ball (curvature along u or v above 1/R, :func:`_concave`): where the
    verification's reachable height needs its search."""
    du, dv, _, _, tight = _concave(R, Hu, Hv, cut, u, v)
    return _tight_band(R, tight, cut, du, dv)


MIN_LENGTH_MM = 1e-4   # scallop and tolerance below this are below any machine's resolution


def guard(est: dict, tol, spec_path=None, scallop=None, tolerance=None) -> None:
    """Refuse (SpecError, exit 2, naming the key and the estimate) beyond the guards."""
    roughing_guard(est, tol, spec_path)
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
    if est.get("bytes", 0.0) > MAX_BYTES:
        key = "roughing.stepover" if est.get("rough_bytes", 0.0) >= 0.5 * est["bytes"] else \
            "machining.stepdown" if est["roughing_points"] > est["points"] else \
            ("machining.scallop" if est["points"] < 40.0 * est["passes"] else "machining.tolerance")
        raise SpecError(f"planning would need about {est['bytes'] / 1e9:.2g} GB of memory "
                        f"({est['passes']:.3g} passes, {est['points'] + est['roughing_points']:.3g} "
                        f"program points" + (f", {est['rough_length_mm']:.3g} mm of roughing loops"
                                             if "rough_length_mm" in est else "") + f"; limit {MAX_BYTES / 1e9:g} GB); raise {key.split('.')[1]}",
                        file=spec_path, key=key)
    budget = est.get("max_time") or tol.max_plan_seconds
    if est["seconds"] > budget:
        key = "roughing.stepover" if est.get("rough_seconds", 0.0) >= 0.5 * est["seconds"] else \
            "machining.scallop" if est["place_seconds"] >= \
            SEC_PER_POINT * (est["points"] + est["roughing_points"]) else \
            ("machining.stepdown" if est["roughing_points"] > est["points"] else "machining.tolerance")
        build = est.get("build_seconds", 0.0)
        raise SpecError(f"the job would take about {est['seconds']:.0f} s of CPU time ({est['passes']:.3g} "
                        f"passes, {est['points'] + est['roughing_points']:.3g} program points"
                        + (f", {build:.0f} s of it compiling the kernels, once" if build > 0 else "") + "; "
                        f"limit {budget:g} s): raise the limit with --max-time SECONDS or the spec key "
                        f"machining.max_time, or raise {key.split('.')[1]}",
                        file=spec_path, key=key)


def with_time_budget(spec, seconds):
    """The spec with ``machining.max_time`` set to ``seconds`` (the ``--max-time``
    option; None: the spec unchanged). SpecError naming the option when not > 0."""
    if seconds is None:
        return spec
    if not seconds > 0:
        raise SpecError(f"must be > 0 seconds, got {seconds:g}", key="--max-time")
    return spec.with_overrides({"machining.max_time": float(seconds)})
