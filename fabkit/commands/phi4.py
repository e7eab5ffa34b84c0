"""``fabkit phi4 --v-in V | --v-in LO HI N [--json] [--plot PNG]``: kink-antikink
collisions of the phi^4 equation (fabkit/waves/phi4.py; docs/numerics.md, "phi^4").

One speed: outcome, bounces, bounce times, v_out, and with ``--plot`` X(t) and the
shape-mode amplitude A(t) (the seed paper's Fig. 3). Three numbers: a sweep of N
speeds with v_critical refined by bisection and the n-bounce windows (``--plot``:
v_out against v_in coloured by bounces). Speeds are in units of the speed of light.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import SpecError
from ._common import Timer, check_paths, emit, plot_format, progress_bar

# guards on the user's numbers: memory (N x grid) and run time
MAX_SPEEDS = 20_000
MAX_STEPS = 200_000
MAX_GRID = 20_000


def config_from_args(args):
    from ..waves.phi4 import DEFAULT_CONFIG

    cfg = DEFAULT_CONFIG
    checks = (("t_max", "--t-max", 0.0, 1e5), ("dx", "--dx", 0.0, 1.0), ("dt", "--dt", 0.0, 0.5),
              ("x0", "--x0", 10.0, 1e3))
    for attr, flag, lo, hi in checks:
        val = getattr(args, attr, None)
        if val is None:
            continue
        ok = math.isfinite(val) and (val >= lo if attr == "x0" else val > lo) and val <= hi
        if not ok:
            rng = f"in [{lo:g}, {hi:g}]" if attr == "x0" else f"in ({lo:g}, {hi:g}]"
            raise SpecError(f"must be {rng}, got {val:g}", key=flag)
        cfg = cfg.with_(**{attr: float(val)})
    if cfg.t_max / cfg.dt > MAX_STEPS:
        key = "--dt" if getattr(args, "dt", None) is not None else "--t-max"
        raise SpecError(f"t_max / dt = {cfg.t_max:g} / {cfg.dt:g} = {cfg.t_max / cfg.dt:.3g} steps exceeds the "
                        f"limit {MAX_STEPS}: a larger --dt or a smaller --t-max", key=key)
    if not cfg.length / cfg.dx <= MAX_GRID:          # in floats: a subnormal dx overflows an integer count
        raise SpecError(f"{cfg.length / cfg.dx:.3g} grid intervals exceed the limit {MAX_GRID}", key="--dx")
    return cfg


def speeds(v_arg) -> tuple[np.ndarray, bool]:
    """(v (N,), is_sweep) from ``--v-in V`` or ``--v-in LO HI N``."""
    if len(v_arg) == 1:
        v = float(v_arg[0])
        if not (math.isfinite(v) and 0 < v < 1):
            raise SpecError(f"must be in (0, 1) (units of c), got {v:g}", key="--v-in")
        return np.array([v]), False
    if len(v_arg) != 3:
        raise SpecError(f"give one speed V or LO HI N, got {len(v_arg)} numbers", key="--v-in")
    lo, hi, n = v_arg
    if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi < 1):
        raise SpecError(f"need 0 < LO < HI < 1, got {lo:g} {hi:g}", key="--v-in")
    if not (n == int(n) and 2 <= n <= MAX_SPEEDS):
        raise SpecError(f"N must be a whole number in [2, {MAX_SPEEDS}], got {n:g}", key="--v-in")
    return np.linspace(lo, hi, int(n)), True


def run(args) -> int:
    from ..waves.phi4 import check_resolution

    v, is_sweep = speeds(args.v_in)
    cfg = config_from_args(args)
    check_paths(args, {"--plot": args.plot})                # a bad path or extension fails before the work
    fmt = plot_format(args.plot) if args.plot else None
    reason = check_resolution(v, cfg.dx)
    if reason:
        raise SpecError(reason, key="--v-in")
    if is_sweep:
        return _sweep(args, v, cfg, fmt)
    return _one(args, float(v[0]), cfg, fmt)


def _one(args, v: float, cfg, fmt) -> int:
    from ..waves.phi4 import OUTCOMES, collide
    from ..waves.sweep import config_dict

    timer = Timer()
    r = collide([v], cfg, record=bool(args.plot))
    out = OUTCOMES[int(r.outcome[0])]
    nb = int(r.bounces[0])
    bt = [float(t) for t in r.bounce_times[0, :nb] if np.isfinite(t)]
    v_out = float(r.v_out[0])
    # the error of this result, by step halving: the same collision at dt/2 (ETDRK4 is fourth
    # order, so |v_out(dt) - v_out(dt/2)| is about 15/16 of v_out(dt)'s error)
    half = cfg.with_(dt=0.5 * cfg.dt)
    check = collide([v], half) if half.t_max / half.dt <= MAX_STEPS else None
    error, error_note = None, None
    if check is None:
        error_note = f"not estimated: dt/2 would exceed {MAX_STEPS} steps"
    elif OUTCOMES[int(check.outcome[0])] != out or (out == "escaped" and int(check.bounces[0]) != nb):
        # (a capture's count of bounces by t_max is not converged at any step: not compared)
        half_out = OUTCOMES[int(check.outcome[0])]
        error_note = (f"the outcome changes at dt/2 = {half.dt:g} ({half_out}, {int(check.bounces[0])} bounces): "
                      f"the step does not resolve this collision; use --dt {0.25 * cfg.dt:g} or smaller")
    elif out == "escaped":
        error = abs(v_out - float(check.v_out[0]))
    seconds = timer.seconds
    payload = {"v_in": v, "outcome": out, "bounces": nb, "bounce_times": bt,
               "v_out": v_out if out == "escaped" else None,
               "v_out_error": error, "v_out_error_method": "step halving: |v_out(dt) - v_out(dt/2)|",
               "error_note": error_note, "t_end": float(r.t_end[0]),
               "seconds": seconds, "config": config_dict(cfg)}
    if out != "escaped":
        err_txt = "no v_out" if error_note is None else error_note
    elif error is not None:
        err_txt = f"v_out error {error:.1e} c (step halving, dt/2 = {half.dt:g})"
    else:
        err_txt = error_note
    lines = [f"phi4: v_in = {v:g} c, X0 = {cfg.x0:g}, dx = {cfg.dx:g}, dt = {cfg.dt:g}, t_max = {cfg.t_max:g}",
             f"outcome: {out}" + (f", v_out = {v_out:.6f} c" if out == "escaped" else f" (at t = {cfg.t_max:g})"),
             f"bounces: {nb}" + (f" at t = {', '.join(f'{t:.2f}' for t in bt[:8])}" if bt else "")
             + (f", ... (the first 8 of {len(bt)}; all in --json)" if len(bt) > 8 else ""),
             f"phi4: {err_txt}; {seconds:.1f} s with the check at dt/2"]
    if args.plot:
        from ..io import write_atomic
        from ..plots import phi4_trajectory_png

        write_atomic(args.plot, phi4_trajectory_png(r.record, payload, fmt=fmt))
        payload["plot"] = str(args.plot)
        lines.append(f"wrote {args.plot}")
    emit(lines, payload, args.json)
    return 0


def _sweep(args, v: np.ndarray, cfg, fmt) -> int:
    from ..waves.sweep import phi4_sweep

    timer = Timer()
    cb, close = progress_bar(len(v), getattr(args, "no_progress", False), "phi4")
    try:
        res = phi4_sweep(v, cfg, progress=cb)
    finally:
        close()
    res["seconds"] = timer.seconds
    if args.plot:
        from ..io import write_atomic
        from ..plots import sweep_figure

        write_atomic(args.plot, sweep_figure(res, "phi^4 kink-antikink collisions", fmt=fmt,
                                             speed_units="units of c"))
    counts: dict = {}
    for o, b in zip(res["outcome"], res["bounces"]):
        key = f"{o} after {b}" if o == "escaped" else o
        counts[key] = counts.get(key, 0) + 1
    vc = res["v_critical"]
    lines = [f"phi4: {len(v)} collisions, v_in {v[0]:.4g}..{v[-1]:.4g} c: "
             + ", ".join(f"{k} {n}" for k, n in sorted(counts.items()))]
    for w in res["windows"]:
        if w["bounces"] == 2:
            lines.append(f"  2-bounce window {w['lo']:.5f} .. {w['hi']:.5f} c")
    if vc is not None:
        txt = f"v_critical {vc:.5f} c ± {res['v_critical_error']:.1e} (escape: X back at X0 = {cfg.x0:g} " \
              f"by t_max = {cfg.t_max:g})"
        if res["v_critical_extrapolated"] is not None:
            txt += f"; v_out -> 0 extrapolation {res['v_critical_extrapolated']:.5f} c"
    else:
        txt = f"v_critical: none ({res['v_critical_reason']})"
    lines.append(f"phi4: {txt}")
    lines.append(f"phi4: {res['launches']} collisions in {res['seconds']:.1f} s "
                 f"({1e3 * res['seconds_per_collision']:.0f} ms each); at dx = 1/4, dt = 1/20 v_out error ~3e-6 c, "
                 f"up to 3e-4 c inside narrow windows, v_critical ~1e-5 c (docs/numerics.md, phi^4; "
                 f"one speed gives its own step-halving estimate)")
    payload = {k: res[k] for k in ("v_in", "v_out", "bounces", "outcome", "v_critical", "windows",
                                   "v_critical_error", "v_critical_reason", "v_critical_extrapolated",
                                   "t_max_bias", "launches", "seconds", "seconds_per_collision", "config")}
    emit(lines, payload, args.json)
    return 0
