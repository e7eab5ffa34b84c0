"""``fabkit compare SPEC [--plot PNG] [--json]``: the seed paper's Fig. 1 for this apparatus.

Four panels of v_out against v_in, both over each panel's v_critical: the phi^4 PDE,
the CC ODE and the separatrix map (c = 1/4, omega = 1), and the spec's apparatus
through the simulator's sweep. Coloured by collisions: one black, two blue, three
green, four red (fabkit/waves/compare.py). All four panels share the x range
v_in / v_critical = 0.65..1.25. The summary and the JSON (``paper``) set the lab's
published T_n fit beside the apparatus's (docs/paper.md).
"""

from __future__ import annotations

from ..errors import SpecError
from ._common import Timer, check_paths, emit, plot_format, progress_bar

MAX_SAMPLES = 20_000


def _count(value, default: int, flag: str) -> int:
    if value is None:
        return default
    if not 8 <= value <= MAX_SAMPLES:
        raise SpecError(f"must be in [8, {MAX_SAMPLES}], got {value}", key=flag)
    return int(value)


def _paper_lines(paper: dict) -> list[str]:
    """The summary's T_n lines: the lab's published fit, fabkit's, and both at the lab's n."""
    lab, fab = paper["lab"], paper["fabkit"]
    out = [f"compare: T_n, the lab (published): {lab['T']:g} n + {lab['delta']:g} s, n = "
           f"{lab['n'][0]}..{lab['n'][-1]}"]
    if fab["T"] is None:
        out.append(f"compare: T_n, fabkit ({fab['model']} model, lengths in {fab['length_unit']}): no fit "
                   f"({len(fab['n'])} two-bounce window(s))")
        return out
    out.append(f"compare: T_n, fabkit ({fab['model']} model, lengths in {fab['length_unit']}): "
               f"{fab['T']:.3f} n + {fab['delta']:.3f} s over n = {','.join(str(n) for n in fab['n'])} "
               f"(T_shape {fab['T_shape']:.3f} s)")
    lo, hi = min(fab["n"]), max(fab["n"])
    cells = ", ".join(f"n={r['n']}: {r['fabkit']:.3f} vs {r['lab']:.3f} ({100 * r['rel_diff']:+.1f} %"
                      + ("" if lo <= r["n"] <= hi else ", extrapolated") + ")" for r in paper["by_n"])
    out.append(f"  fabkit's line vs the lab's: {cells}")
    return out


def run(args) -> int:
    from ..spec import load_spec
    from ..waves import compare as cmp
    from .sweep import speeds

    timer = Timer()
    n_pde = _count(args.pde_samples, 400, "--pde-samples")
    n_ode = _count(args.ode_samples, 300, "--ode-samples")
    check_paths(args, {"--plot": args.plot})                # a bad path or extension fails before the work
    fmt = plot_format(args.plot) if args.plot else None
    spec = load_spec(args.spec, need=("surface", "simulation", "ball", "ramp"), command="compare")
    v_app = speeds(spec, None)
    quiet = getattr(args, "no_progress", False)
    panels = []
    cb, close = progress_bar(n_pde, quiet, "compare: phi^4")
    try:
        panels.append(cmp.pde_panel(n_pde, progress=cb))
    finally:
        close()
    panels.append(cmp.ode_panel(n_ode))
    panels.append(cmp.map_panel(max(n_ode, 2000)))
    cb, close = progress_bar(len(v_app), quiet, "compare: apparatus")
    try:
        panels.append(cmp.apparatus_panel(spec, v_app, progress=cb))
    finally:
        close()
    seconds = timer.seconds
    rows = cmp.summary_rows(panels)
    lines = []
    for p, r in zip(panels, rows):
        vc = p["v_critical"]
        c = r["counts"]
        vc_txt = f"v_critical {vc:.6g} {p['units']}".rstrip() + f" ({p['v_critical_note']})" if vc is not None \
            else f"v_critical: none ({p['v_critical_note']})"
        lines.append(f"compare: {p['name']}: {vc_txt}; escapes after 1/2/3/4 collisions "
                     f"{c['1']}/{c['2']}/{c['3']}/{c['4']}, other {c['other']}, {p['seconds']:.1f} s")
        lines.append(f"  {p['params']}")
    app = panels[-1]
    paper = cmp.lab_tn_comparison(app["tn_fit"], model=app["model"], length_unit=app["length_unit"])
    lines += _paper_lines(paper)
    if args.plot:
        from ..io import write_atomic
        from ..plots import compare_figure

        png = compare_figure(panels, title=f"v_out against v_in, over each panel's v_critical: "
                                           f"phi^4, CC ODE, map and {spec.name} ({app['model']} model)",
                             span=cmp.SPAN, fmt=fmt)
        write_atomic(args.plot, png)
        lines.append(f"wrote {args.plot}")
    lines.append(f"compare: {seconds:.1f} s")
    payload = {"panels": [{k: p[k] for k in ("name", "params", "v_in", "v_out", "bounces", "outcome", "v_critical",
                                             "v_critical_note", "units", "launches", "seconds")} for p in panels],
               "summary": rows, "paper": paper, "x_range": list(cmp.SPAN), "seconds": seconds}
    payload["panels"][-1].update(model=app["model"], windows=app["windows"], tn_fit=app["tn_fit"])
    if args.plot:
        payload["plot"] = str(args.plot)
    emit(lines, payload, args.json)
    return 0
