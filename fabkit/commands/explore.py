"""``fabkit explore SPEC --vary KEY=LO:HI:N [--vary ...] [--v-in LO HI N]
[--scheduler ADDRESS] [--out FILE] [--json] [--plot PNG] [--no-progress]``.

A grid of designs over spec keys; per design v_critical, the n-bounce windows,
the highest safe release height, depth feasibility and ``safe``. In-process, or
on a Dask cluster with ``--scheduler`` (the same results either way). Per-launch
rows of the grid launches go to ``--out`` (.csv, or .parquet with pyarrow).
"""

from __future__ import annotations


import numpy as np

from ..errors import SpecError
from ._common import Timer, check_paths, emit, plot_format, prepare_simulator, progress_bar, warn


def _fmt(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _models(designs: list[dict], spec) -> str:
    """Which model made the designs' results: the spec's, or those the grid varies."""
    names = list(dict.fromkeys(d["model"] for d in designs if d.get("model")) or [spec.simulation.model])
    return f"{names[0]} model" if len(names) == 1 else f"models {', '.join(names)}"


def run(args) -> int:
    from ..explore import explore
    from ..launches import Engine
    from ..tables import table_bytes, table_format
    from ..vary import design_grid, parse_vary
    from ..io import atomic_outputs
    from ..physics.calibrate import ramp_heights
    from ..spec import load_spec
    from .sweep import speeds

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "simulation"), command="explore")
    if args.v_in is None:
        spec.require("ball", "ramp", command="explore (without --v-in)")
    varies = [parse_vary(t, spec) for t in args.vary]
    grid = design_grid(varies)
    v = speeds(spec, args.v_in) if args.v_in is not None else None
    check_paths(args, {"--out": args.out, "--plot": args.plot})
    fmt = table_format(args.out)
    per = (len(v) if v is not None else 0) + (len(ramp_heights(spec)) if spec.has("ramp") else 0)
    if not args.scheduler:
        prepare_simulator(spec)
    cb, close = progress_bar(len(grid) * per, getattr(args, "no_progress", False), "explore")
    try:
        with Engine(args.scheduler, chunk=getattr(args, "chunk", None), progress=cb) as engine:
            res = explore(spec, varies, v, engine=engine)
    finally:
        close()
    designs = res["designs"]
    bad = [d for d in designs if "error" in d]
    if len(bad) == len(designs):
        raise SpecError(f"no valid design: {bad[0]['error']}", key="--vary" if args.vary else None)

    u = spec.units
    good = [d for d in designs if "error" not in d]
    if good and all(d["v_critical"] is None for d in good):
        reasons = sorted({str(d.get("v_critical_reason") or "unknown") for d in good})
        warn("no design of the grid has a v_critical"
             + (" (its panel in the figure is empty)" if args.plot else "") + ": "
             + "; ".join(reasons[:3]) + (f"; and {len(reasons) - 3} other reasons" if len(reasons) > 3 else "")
             + ". Widen --v-in (or the ramp's heights) so that the speeds straddle v_critical: launches "
               "below it that do not escape after one bounce, launches above it that do")
    rows: dict = {}
    for i, d in enumerate(designs):
        g = d.pop("grid", None)
        if g is None:
            continue
        n = len(g["v_in"])
        rows.setdefault("design", []).extend([i] * n)
        for key in grid[0]:
            rows.setdefault(key, []).extend([d["params"][key]] * n)
        rows.setdefault("v_in", []).extend(np.asarray(g["v_in"], dtype=float).tolist())
        rows.setdefault("outcome", []).extend(g["outcome"])
        rows.setdefault("bounces", []).extend(np.asarray(g["bounces"]).tolist())
        rows.setdefault("v_out", []).extend(np.asarray(g["v_out"], dtype=float).tolist())
    res["seconds"] = timer.seconds
    with atomic_outputs() as out:
        if args.out:
            out.write(args.out, table_bytes(rows, fmt))
        if args.plot:
            from ..plots import explore_figure

            out.write(args.plot, explore_figure(res, [vv.key for vv in varies], title=f"{spec.name}: explore, {_models(designs, spec)}",
                                                units=u, fmt=plot_format(args.plot)))

    eng = res["engine"]
    where = (f"on {eng['scheduler']} ({eng['tasks']} tasks on {len(eng['workers'])} workers)"
             if eng["scheduler"] else "in-process")
    lines = [f"explore: {len(designs)} designs ({len(bad)} invalid), "
             + (f"v_in {v[0]:.4g}..{v[-1]:.4g} {u}/s x {len(v)}" if v is not None else "the ramp's speeds")
             + f", {_models(designs, spec)}, {res['launches']} launches {where}"]
    for d in designs:
        name = ", ".join(f"{kk}={_fmt(vv)}" for kk, vv in d["params"].items()) or "the spec as is"
        if "error" in d:
            lines.append(f"  {name}: INVALID: {d['error']}")
            continue
        vc = d["v_critical"]
        vc_txt = (f"v_critical {vc:.6f} ± {d['v_critical_error']:.1e} {u}/s" if vc is not None
                  else f"v_critical none ({d['v_critical_reason']})")
        two = sum(1 for w in d["windows"] if w["bounces"] == 2)
        hs = d["highest_safe_height"]
        hs_txt = (f"highest safe height {hs:.4f} {u}" if hs is not None
                  else ("highest safe height none" if d["safe_over"] == "ramp" else "no ramp"))
        depth = (f", depth {d['depth_mm']:.2f} mm {'ok' if d['depth_ok'] else 'TOO DEEP'}"
                 if d["depth_mm"] is not None else "")
        lines.append(f"  {name}: {vc_txt}, {len(d['windows'])} windows ({two} two-bounce), {hs_txt}{depth}: "
                     + ("SAFE" if d["safe"] else "UNSAFE"))
    lines.append(f"explore: v_critical to 1e-6 relative (± is its bracket half-width), highest safe height "
                 f"to 1e-4 relative; {res['seconds']:.1f} s" + (f"; rows in {args.out}" if args.out else ""))
    payload = {"designs": designs, "model": spec.simulation.model, "units": u, "v_in": v, "launches": res["launches"], "engine": eng,
               "seconds": res["seconds"]}
    emit(lines, payload, args.json)
    return 0
