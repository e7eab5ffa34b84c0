"""``fabkit design SPEC --vary KEY=LO:HI [--vary ...] [--budget N] [--seed S]
[--min-width W] [--sigma-y S] [--sigma-vy S] [--samples M] [--top K]
[--scheduler ADDR] [--json] [--plot PNG] [-o OUT.yaml] [--no-progress]``.

Searches the named keys for the design with the most observable two-bounce
windows that passes the pre-fabrication check (fabkit/design.py), prints the
baseline (the spec as it is) and the best verified designs, and writes the
winner as a complete spec (default ``toolpaths/<name>.design.yaml``).
"""

from __future__ import annotations

from ..errors import DesignError
from ._common import Timer, check_paths, default_output, emit, plot_format, progress_bar


def _values(bounds, values) -> str:
    return ", ".join(f"{b.key.removeprefix('surface.params.')}={v:g}" if v is not None
                     else f"{b.key}=unset" for b, v in zip(bounds, values))


def _window(w: dict, u: str, scale: float) -> str:
    txt = f"{w['height_lo']:.4f}..{w['height_hi']:.4f} {u} ({w['width'] * scale:.2f} mm"
    if w["p_two"] is not None:
        txt += f", P2 {w['p_two']:.2f}"
    return txt + (") *" if w["observable"] else ")")


def _row(label: str, ev: dict, bounds, u: str, scale: float) -> list[str]:
    vc = ev.get("v_critical")
    vc_txt = f"v_critical {vc:.4f} {u}/s" if vc is not None else "v_critical -"
    wins = ev.get("windows") or []
    wtxt = "; ".join(_window(w, u, scale) for w in wins[:8])
    if len(wins) > 8:
        wtxt += f"; ... {len(wins) - 8} more"
    depth = f"depth {ev['depth_mm']:.2f} mm" if ev.get("depth_mm") is not None else "depth -"
    verdict = {"pass": "check passes", "fail": "check FAILS", None: "not checked"}[ev.get("check")]
    status = "feasible" if ev["feasible"] else f"INFEASIBLE: {ev['reason']}"
    lines = [f"  {label}: {_values(bounds, ev['values'])}: {ev['observable']} observable "
             f"({ev['observable_width'] * scale:.2f} mm), {vc_txt}, {depth}, {verdict}, {status}"]
    if wins:
        lines.append(f"      two-bounce windows (release height, width; * observable): {wtxt}")
    if "screen" in ev:
        lines.append(f"      (the screen said {ev['screen']['observable']} observable)")
    return lines


def _public(ev: dict | None, bounds) -> dict | None:
    if ev is None:
        return None
    out = {kk: vv for kk, vv in ev.items() if kk not in ("sweep", "values")}
    out["params"] = {b.key: v for b, v in zip(bounds, ev["values"])}
    return out


def run(args) -> int:
    from ..design import (DEFAULT_SAMPLES, Options, Runner, check_request, check_tolerances, parse_bound, search,
                          winner_yaml)
    from ..io import atomic_outputs
    from ..spec import load_spec

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "ball", "ramp", "simulation"), command="design")
    bounds = [parse_bound(t, spec) for t in args.vary]
    u = spec.units
    min_width = args.min_width if args.min_width is not None else 1.0 / spec.scale    # 1 mm
    opts = Options(min_width=float(min_width), sigma_y=float(args.sigma_y), sigma_vy=float(args.sigma_vy),
                   samples=int(args.samples if args.samples is not None else DEFAULT_SAMPLES),
                   seed=int(args.seed))
    check_request(spec, bounds, opts, budget=args.budget, top=args.top)
    output = default_output(spec, ".design.yaml", args.output)
    check_paths(args, {"-o": str(output), "--plot": args.plot})
    total = 1 + args.budget + args.top
    cb, close = progress_bar(total, getattr(args, "no_progress", False), "design", unit="design")
    try:
        with Runner(args.scheduler, progress=cb) as runner:
            res = search(spec, bounds, opts, runner=runner, budget=args.budget, top=args.top)
            engine = runner.info()
    finally:
        close()
    res["seconds"] = timer.seconds
    w = res["winner"]
    with atomic_outputs() as out:
        if w is not None:
            out.write(output, winner_yaml(res, spec, bounds, args.spec))
        if args.plot:
            from ..plots import design_figure

            out.write(args.plot, design_figure(res, bounds, title=f"{spec.name}: design, {spec.simulation.model} model", units=u,
                                                 fmt=plot_format(args.plot)))

    opt = res["optimizer"]
    where = (f"on {engine['scheduler']} ({engine['tasks']} tasks on {len(engine['workers'])} workers)"
             if engine["scheduler"] else "in-process")
    lines = [f"design: {len(bounds)} keys, " + ", ".join(f"{b.key}={b.lo:g}:{b.hi:g}" for b in bounds)
             + f"; differential evolution, population {opt['population']}, {opt['generations']} generations, "
             f"seed {opt['seed']}: {opt['evaluations']} screened ({res['screened']} distinct) {where}, "
             f"{spec.simulation.model} model (screen and check)",
             f"design: observable = reachable two-bounce window >= {opts.min_width:g} {u} wide in release height"
             + (f", P(2 bounces) >= 0.8 at its centre over {opts.samples} launches (sigma_y {opts.sigma_y:g} {u}, "
                f"sigma_vy {opts.sigma_vy:g} {u}/s)" if opts.sigma_y > 0 or opts.sigma_vy > 0
                else ", the nominal launch at its centre bounces twice")
             + "; the top of the ramp launches >= 1.05 v_critical",
             "design: baseline (the spec as it is), checked:"]
    lines += _row("baseline", res["baseline"], bounds, u, spec.scale)
    lines.append(f"design: best designs of the search, checked ({len(res['finalists'])}):")
    for i, ev in enumerate(res["finalists"], 1):
        lines += _row(f"#{i}", ev, bounds, u, spec.scale)
    if w is None:
        lines.append("design: no design satisfies the constraints; nothing written")
    else:
        lines.append(f"design: winner {'(the spec as it is) ' if w is res['baseline'] else ''}"
                     f"{_values(bounds, w['values'])}: {w['observable']} observable two-bounce windows "
                     f"(baseline {res['baseline']['observable']}) -> {output}")
    tols = {kk: vv for kk, vv in check_tolerances().items() if kk.endswith("rel_tol")}
    lines.append(f"design: window edges to {tols['edge_rel_tol']:g} relative in v_in, v_critical to "
                 f"{tols['v_rel_tol']:g} (fabkit check), P(2 bounces) from "
                 f"{opts.samples if opts.sigma_y > 0 or opts.sigma_vy > 0 else 1} launches; {res['seconds']:.1f} s"
                 + (f"; plot in {args.plot}" if args.plot else ""))
    payload = {"baseline": _public(res["baseline"], bounds),
               "designs": [_public(ev, bounds) for ev in res["finalists"]],
               "winner": _public(w, bounds), "output": str(output) if w is not None else None,
               "history": res["history"], "optimizer": opt, "options": res["options"],
               "bounds": [{"key": b.key, "lo": b.lo, "hi": b.hi, "step": b.step} for b in bounds],
               "engine": engine, "check_tolerances": tols, "model": spec.simulation.model, "units": u, "seconds": res["seconds"]}
    emit(lines, payload, args.json)
    if w is None:
        raise DesignError("no design within the bounds passes the constraints (see the table)")
    return 0
