"""``fabkit simulate SPEC --v-in V [--json] [--plot PNG]``: one launch of the rolling ball."""

from __future__ import annotations

import math

from ..errors import SpecError
from ..spec import load_spec
from ._common import Timer, check_paths, emit, plot_format, prepare_simulator


def _bounce_lines(n: int, times: list) -> list[str]:
    """'bounces: N at t = ...' with every bounce time, ten to a line."""
    if not times:
        return [f"bounces: {n}"]
    head = f"bounces: {n} at t =" + ("" if len(times) == n else f" (the first {len(times)} recorded)")
    rows = [", ".join(f"{t:.6f}" for t in times[i:i + 10]) for i in range(0, len(times), 10)]
    if len(rows) == 1:
        return [f"{head} {rows[0]} s"]
    return [head] + [f"  {row}" + (" s" if i == len(rows) - 1 else ",") for i, row in enumerate(rows)]


def run(args) -> int:
    from ..physics.check import end_reason
    from ..physics.integrate import simulate_one
    from ..physics.models import OUTCOMES, problem_from_spec

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "simulation"), command="simulate")
    check_paths(args, {"--plot": args.plot})
    v = float(args.v_in)
    if not math.isfinite(v) or v < 0:
        raise SpecError(f"must be finite and >= 0, got {v:g}", key="--v-in")
    problem = problem_from_spec(spec)
    prepare_simulator(problem)
    rtol, atol = problem.rtol, problem.atol
    r = simulate_one(problem, v, record=bool(args.plot))
    if r["bounces"] > len(r["bounce_times"]):
        # the integrator keeps the first K bounce times: run again keeping every one (the same steps)
        r = simulate_one(problem, v, record=bool(args.plot), max_bounces=r["bounces"])
    seconds = timer.seconds
    # error estimate: the same launch at ten times tighter tolerances
    tight = simulate_one(problem, v, record=False, rtol=rtol / 10, atol=atol / 10,
                         max_bounces=max(r["bounces"], 8))
    est = {"rtol": rtol, "rtol_ref": rtol / 10, "same_outcome": tight["outcome"] == r["outcome"]
           and tight["bounces"] == r["bounces"]}
    if est["same_outcome"] and r["outcome"] == "escaped":
        est["v_out_abs"] = abs(tight["v_out"] - r["v_out"])
    if est["same_outcome"] and r["bounces"]:
        est["bounce_time_abs"] = max(abs(a - b) for a, b in zip(r["bounce_times"], tight["bounce_times"]))
    traj = r.pop("trajectory", None)
    r["end_reason"] = end_reason(problem, OUTCOMES.index(r["outcome"]), r["x_end"], r["y_end"], r["status"])
    payload = {k: r[k] for k in ("outcome", "bounces", "bounce_times", "v_out", "max_height", "max_abs_y",
                                 "energy_error", "t_end", "x_end", "y_end", "vx_end", "vy_end", "end_reason", "steps", "rejected",
                                 "status", "method")}
    if problem.model == "ball":
        payload.update({"max_slip": r["max_slip"], "radius": problem.radius,
                        "friction": problem.friction if math.isfinite(problem.friction) else None})
    payload.update({"v_in": v, "model": problem.model, "damping": problem.damping, "rtol": rtol,
                    "atol": atol, "seconds": seconds, "error_estimate": est})
    u = spec.units
    lines = [
        f"simulate: {problem.model} model, v_in = {v:g} {u}/s, damping {problem.damping:g} 1/s, "
        f"start x = {problem.start:g} {u}",
        f"outcome: {r['outcome']}" + (f", v_out = {r['v_out']:.10g} {u}/s" if r["outcome"] == "escaped" else
                                      f" at x = {r['x_end']:.6g} {u}, y = {r['y_end']:.6g} {u}, "
                                      f"t = {r['t_end']:.6g} s: {r['end_reason']}"),
        *_bounce_lines(r["bounces"], r["bounce_times"]),
        f"max height {r['max_height']:.6g} {u} (top - margin = {problem.top - problem.margin:g}), "
        f"max |y| {r['max_abs_y']:.6g} {u}, ended at t = {r['t_end']:.6g} s",
        (f"energy error {r['energy_error']:.2e} (relative)" if math.isfinite(r["energy_error"]) else
         "energy error not tracked" + (" (implicit Radau path)" if r["status"] == 2 else ""))
        + f", {r['steps']} steps ({r['rejected']} rejected), rtol {rtol:g}"
        + (f", method {r['method']}" if r["method"] != "DOP853" else ""),
    ]
    if problem.model == "ball":
        ms = r["max_slip"]
        lines.append(f"ball: radius {problem.radius:g} {u}; largest |F_t|/N {ms:.4g} (the static friction the "
                     f"rolling needs)" + (f", ball.friction {problem.friction:g}" if math.isfinite(problem.friction)
                                          else ", no ball.friction given"))
    if "v_out_abs" in est:
        err_txt = f"v_out error < {est['v_out_abs']:.1e} {u}/s (estimated at rtol {rtol / 10:g})"
    elif "bounce_time_abs" in est:
        err_txt = f"bounce time error < {est['bounce_time_abs']:.1e} s (estimated at rtol {rtol / 10:g})"
    elif not est["same_outcome"]:
        err_txt = f"outcome or bounce count changes at rtol {rtol / 10:g} (ill-conditioned launch)"
    elif math.isfinite(r["energy_error"]):
        err_txt = f"energy error {r['energy_error']:.1e}, same outcome at rtol {rtol / 10:g}"
    else:
        err_txt = f"same outcome at rtol {rtol / 10:g}"
    lines.append(f"simulate: {err_txt}, {seconds:.3f} s")
    if args.plot:
        from ..io import write_atomic
        from ..plots import trajectory_png

        png = trajectory_png(traj, r, title=f"{spec.name}: {problem.model} model, v_in = {v:g} {u}/s",
                             units=u, fmt=plot_format(args.plot))
        write_atomic(args.plot, png)
        payload["plot"] = str(args.plot)
        lines.append(f"wrote {args.plot}")
    emit(lines, payload, args.json)
    return 0
