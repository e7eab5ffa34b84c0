"""``fabkit precision SPEC [--json] [--plot PNG] [--quick]``: work-precision data.

Error against run time for the simulator (fabkit's integrators and scipy's as
peers), and tolerance against verified deviation, size and time for the toolpath
and the mesh. The studies are in :mod:`fabkit.precision`; this module prints and
times. ``--quick`` uses fewer launches and tolerances, and a tile of the
footprint for the toolpath and mesh.
"""

from __future__ import annotations

from ._common import Timer, check_paths, emit, plot_format, prepare_simulator, stage_bar, warn


def run(args) -> int:
    from .. import precision as P
    from ..physics.models import problem_from_spec
    from ..spec import load_spec

    timer = Timer()
    spec = load_spec(args.spec, command="precision")
    check_paths(args, {"--plot": args.plot})
    cfg = P.QUICK if args.quick else P.FULL
    payload: dict = {"spec": str(args.spec), "quick": bool(args.quick)}
    lines: list[str] = []
    has_sim = spec.has("surface") and spec.has("simulation")
    has_tp = all(spec.has(s) for s in ("surface", "stock", "tool", "machining"))
    has_mesh = all(spec.has(s) for s in ("surface", "stock"))
    stages = (2 + len(cfg["methods"]) if has_sim else 0) + int(has_tp) + int(has_mesh)
    say, close = stage_bar(stages, getattr(args, "no_progress", False), "precision")
    try:
        return _studies(args, spec, cfg, P, problem_from_spec, payload, lines, say, timer)
    finally:
        close()


def _studies(args, spec, cfg, P, problem_from_spec, payload, lines, say, timer) -> int:
    sim = None
    if spec.has("surface") and spec.has("simulation"):
        problem = problem_from_spec(spec)
        prepare_simulator(problem)
        cfg = dict(cfg)
        lo, hi = P.ramp_or_default_range(spec, problem)
        t = Timer()
        try:
            sim = P.simulation_study(problem, cfg, progress=say, v_range=(lo, hi))
        except P.NoWellConditionedLaunch as exc:
            sim = None
            payload["simulation"] = []
            payload["simulation_skipped"] = str(exc)
            lines.append(f"precision: simulation study skipped: {exc}")
    if sim is not None:
        u = spec.units
        payload["simulation"] = sim["rows"]
        payload["simulation_info"] = {k: sim[k] for k in ("launches", "reference", "monotone", "problem")}
        payload["simulation_info"]["seconds"] = t.seconds
        lines.append(f"precision: simulation, {sim['problem']} at v_in "
                     + ", ".join(f"{v:.4g}" for v in sim["launches"]["v_in"]) + f" {u}/s; reference scipy "
                     f"DOP853 rtol {P.REFERENCE['rtol']:g} (its error ~{sim['reference']['estimated_error']:.1e})")
        lines.append(f"  {'method':<14} {'rtol':>7} {'error':>9} {'seconds':>9} {'energy drift':>12} "
                     f"{'mismatch':>8}")
        for r in sim["rows"]:
            drift = f"{r['energy_drift']:.1e}" if r["energy_drift"] is not None else "-"
            lines.append(f"  {r['method']:<14} {r['rtol']:>7.0e} {r['error']:>9.1e} {r['seconds']:>9.4f} "
                         f"{drift:>12} {r['mismatched']:>8}")
        bad = [m for m, ok in sim["monotone"].items() if not ok]
        lines.append("precision: error falls as the tolerance tightens for every method" if not bad else
                     f"precision: error does NOT fall monotonically for: {', '.join(bad)}")
    elif not (spec.has("surface") and spec.has("simulation")):
        payload["simulation"] = []

    tp_spec = P.tile_spec(spec, cfg["tile"])
    tile_note = ""
    if cfg["tile"]:
        (x0, x1), (y0, y1) = tp_spec.surface.x, tp_spec.surface.y
        tile_note = f" (tile x {x0:.4g}..{x1:.4g}, y {y0:.4g}..{y1:.4g})"
    if all(spec.has(s) for s in ("surface", "stock", "tool", "machining")):
        say("toolpath")
        payload["toolpath"] = P.toolpath_study(tp_spec, cfg["toolpath"])
        lines.append(f"precision: toolpath{tile_note}, scallop {payload['toolpath'][0]['scallop']:g} mm")
        lines.append(f"  {'tolerance':>9} {'gouge':>9} {'left':>8} {'lines':>8} {'plan+write s':>12} "
                     f"{'verify s':>9}")
        for r in payload["toolpath"]:
            flag = "" if r["within_tolerance"] else "  (gouge above the tolerance)"
            lines.append(f"  {r['tolerance']:>9g} {r['max_deviation']:>9.4f} {r['material_left']:>8.4f} "
                         f"{r['lines']:>8d} {r['seconds']:>12.2f} {r['verify_seconds']:>9.2f}{flag}")
    else:
        payload["toolpath"] = []
    if all(spec.has(s) for s in ("surface", "stock")):
        say("mesh")
        payload["mesh"] = P.mesh_study(tp_spec, cfg["mesh"])
        lines.append(f"precision: mesh{tile_note}")
        lines.append(f"  {'tolerance':>9} {'deviation':>9} {'triangles':>10} {'seconds':>8}")
        for r in payload["mesh"]:
            lines.append(f"  {r['tolerance']:>9g} {r['max_deviation']:>9.4f} {r['triangles']:>10d} "
                         f"{r['seconds']:>8.2f}")
    else:
        payload["mesh"] = []

    if args.plot and sim is not None:
        from ..io import write_atomic
        from ..plots import precision_png

        title = f"{spec.name}: {sim['problem']}"
        write_atomic(args.plot, precision_png(sim["rows"], title=title, floor=sim["reference"]["estimated_error"],
                                              fmt=plot_format(args.plot)))
        payload["plot"] = str(args.plot)
        lines.append(f"wrote {args.plot}")
    elif args.plot and "simulation_skipped" in payload:
        warn(f"--plot {args.plot} not written: the figure is the simulator's work-precision diagram, and the "
             "simulation study was skipped")
    elif args.plot:
        warn(f"--plot {args.plot} not written: the figure is the simulator's work-precision diagram, and the "
             "spec has no surface and simulation sections")
    seconds = timer.seconds
    payload["seconds"] = seconds
    if sim is not None:
        best = min((r for r in sim["rows"] if r["method"] == "fabkit DOP853"), key=lambda r: r["error"])
        lines.append(f"precision: simulation error down to {best['error']:.1e} (fabkit DOP853 at rtol "
                     f"{best['rtol']:g}, measured against the reference), {seconds:.1f} s")
    else:
        lines.append(f"precision: {seconds:.1f} s")
    emit(lines, payload, args.json)
    return 0
