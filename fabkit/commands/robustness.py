"""``fabkit robustness SPEC --v-in LO HI N --sigma-y S --sigma-vy S --samples M
[--seed K] [--scheduler ADDRESS] [--out FILE] [--json] [--plot PNG] [--no-progress]``.

Monte Carlo over the launch's transverse offset y0 and velocity vy0 (normal,
around the spec's simulation.y0 / vy0): for each v_in the probability of each
bounce count and outcome, against the nominal (zero-scatter) launch. Answers
whether launch scatter explains disorder in the two-bounce windows.
"""

from __future__ import annotations

import numpy as np

from ._common import Timer, check_paths, emit, plot_format, prepare_simulator


def run(args) -> int:
    from ..launches import Engine
    from ..robustness import check_scatter, check_scatter_size, robustness
    from ..tables import table_bytes, table_format
    from ..io import atomic_outputs
    from ..spec import load_spec
    from ._common import progress_bar
    from .sweep import speeds

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "simulation"), command="robustness")
    v = speeds(spec, args.v_in)
    check_scatter(args.sigma_y, args.sigma_vy, args.samples, len(v), seed=args.seed)
    check_scatter_size(spec, args.sigma_y, args.sigma_vy)
    check_paths(args, {"--out": args.out, "--plot": args.plot})
    fmt = table_format(args.out)
    if not args.scheduler:
        prepare_simulator(spec)
    cb, close = progress_bar(len(v) * (args.samples + 1), getattr(args, "no_progress", False), "robustness")
    try:
        with Engine(args.scheduler, chunk=getattr(args, "chunk", None), progress=cb) as engine:
            res = robustness(spec, v, sigma_y=args.sigma_y, sigma_vy=args.sigma_vy, samples=args.samples,
                             seed=args.seed, engine=engine)
    finally:
        close()
    res["seconds"] = timer.seconds
    table = res.pop("launches")
    u = spec.units
    with atomic_outputs() as out:
        if args.out:
            out.write(args.out, table_bytes(table, fmt))
        if args.plot:
            from ..plots import robustness_figure

            out.write(args.plot, robustness_figure(res, title=f"{spec.name}: robustness, {res['model']} model", units=u,
                                                   fmt=plot_format(args.plot)))

    s = res["summary"]
    eng = res["engine"]
    where = (f"on {eng['scheduler']} ({eng['tasks']} tasks on {len(eng['workers'])} workers)"
             if eng["scheduler"] else "in-process")
    lines = [f"robustness: {len(v)} speeds {v[0]:.4g}..{v[-1]:.4g} {u}/s x {args.samples} samples "
             f"(sigma_y {args.sigma_y:g} {u}, sigma_vy {args.sigma_vy:g} {u}/s, seed {args.seed}), "
             f"{res['model']} model, {res['launch_count']} launches {where}"]
    step = 1 if len(res["rows"]) <= 40 else int(np.ceil(len(res["rows"]) / 40))
    shown = res["rows"][::step]
    if step > 1:
        lines.append(f"robustness: one speed in {step} listed ({len(shown)} of {len(res['rows'])}; all in --json"
                     + (f" and {args.out}" if args.out else "") + ")")
    for row in shown:
        nom = (f"{row['nominal_bounces']} bounce(s)" if row["nominal_outcome"] == "escaped"
               else row["nominal_outcome"])
        probs = ", ".join([f"P({b})={p:.3f}" for b, p in row["p_bounces"].items()]
                          + [f"P({o})={p:.3f}" for o, p in row["p_outcome"].items() if o != "escaped" and p > 0])
        lines.append(f"  v_in {row['v_in']:.4f}: nominal {nom}; {probs}")
    lines.append(f"robustness: P(nominal outcome) mean {s['mean_p_nominal']:.3f}, min {s['min_p_nominal']:.3f} "
                 f"(at v_in {s['v_in_min_p_nominal']:.4f}); most likely outcome differs from the nominal at "
                 f"{s['most_likely_differs']} of {len(v)} speeds")
    if s["mean_p_two_where_nominal_two"] is not None:
        lines.append(f"robustness: P(2 bounces) mean {s['mean_p_two_where_nominal_two']:.3f} where the nominal "
                     f"launch bounces twice ({s['nominal_two_bounce']} speeds)"
                     + (f", {s['mean_p_two_elsewhere']:.3f} elsewhere" if s["mean_p_two_elsewhere"] is not None
                        else ""))
    lines.append(f"robustness: standard error of each probability <= {s['max_standard_error']:.3f} "
                 f"(binomial sqrt(p (1 - p) / {args.samples}) at the measured p; at most "
                 f"{s['bound_standard_error']:.3f} = 0.5 / sqrt({args.samples}) whatever p); {res['seconds']:.1f} s"
                 + (f"; rows in {args.out}" if args.out else ""))
    payload = {kk: res[kk] for kk in ("v_in", "rows", "summary", "sigma_y", "sigma_vy", "samples", "seed", "y0",
                                      "vy0", "model", "damping", "launch_count", "engine", "seconds")}
    payload["units"] = u
    emit(lines, payload, args.json)
    return 0
