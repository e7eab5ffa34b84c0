"""``fabkit sweep SPEC [--v-in LO HI N] [--json] [--plot PNG] [--no-progress]``.

v_out against v_in (the paper's Fig. 1 for the apparatus), v_critical, the
n-bounce windows and the eq. (tn) fit. Default speeds: the ramp's heights
calibrated to v_in (``ramp.samples`` points). The summary states the estimated
v_out error and the run time.
"""

from __future__ import annotations


import numpy as np

from ..errors import SpecError
from ._common import Timer, check_paths, emit, launch_stages, plot_format, prepare_simulator, quiet


#: two-bounce windows listed in the summary (--json lists every one)
SHOW = 24


def speeds(spec, v_in_arg, tol=None) -> np.ndarray:
    """The sweep's v_in (N,): ``--v-in LO HI N`` or the ramp's calibrated range."""
    from ..tolerances import DEFAULT

    tol = tol or DEFAULT
    if v_in_arg is not None:
        lo, hi, n = v_in_arg
        if not (np.isfinite(lo) and np.isfinite(hi) and lo > 0 and hi > lo):
            raise SpecError(f"need 0 < LO < HI, got {lo:g} {hi:g}", key="--v-in")
        if not (np.isfinite(n) and n == int(n) and n >= 2):
            raise SpecError(f"N must be a whole number >= 2, got {n:g}", key="--v-in")
        if n > tol.max_launches:
            raise SpecError(f"N = {n:.6g} exceeds the limit {tol.max_launches}", key="--v-in")
        return np.linspace(lo, hi, int(n))
    spec.require("ramp", "ball", command="sweep (without --v-in)")
    from ..physics.calibrate import ramp_heights
    from ..physics.check import entry_speeds

    H = ramp_heights(spec)
    if len(H) > tol.max_launches:
        raise SpecError(f"{len(H)} heights exceed the limit {tol.max_launches}", file=spec.path,
                        key="ramp.samples")
    return np.unique(entry_speeds(spec, H))


def run(args) -> int:
    from ..io import write_atomic
    from ..physics.models import problem_from_spec
    from ..physics.sweep import SweepReport, sweep
    from ..spec import load_spec

    timer = Timer()
    spec = load_spec(args.spec, need=("surface", "simulation"), command="sweep")
    if args.v_in is None:
        spec.require("ball", "ramp", command="sweep (without --v-in)")
    check_paths(args, {"--plot": args.plot})
    v = speeds(spec, args.v_in)
    problem = problem_from_spec(spec)
    # stages: the simulator, the launches, the refinement, the error estimate (, the figure)
    stage, launches, close = launch_stages(4 + bool(args.plot), quiet(args), "sweep")
    try:
        stage("compiling or loading the simulator")
        say = None if quiet(args) else (lambda m: stage(m, advance=False))
        if args.v_in is None:       # the ramp's spec: a first run compiles what gcode, check, report need
            from ..first_run import prepare

            prepare(spec, need=("simulator",), say=say, quiet=quiet(args))
        prepare_simulator(problem, say=say)
        res = sweep(problem, v, progress=launches(f"launching {len(v)} speeds", len(v)), stage=stage)
        rep = SweepReport.of(res, problem, spec.units, seconds=timer.seconds)
        if args.plot:
            from ..plots import sweep_figure

            stage("drawing the figure")
            write_atomic(args.plot, sweep_figure(rep.as_result(), f"{spec.name}: {rep.model} model, damping "
                                                                  f"{rep.damping:g} 1/s", units=spec.units,
                                                 fmt=plot_format(args.plot)))
    finally:
        close()
    emit(summary(rep), rep.to_json(), args.json)
    return 0


def summary(rep) -> list[str]:
    """The human summary of a :class:`~fabkit.physics.sweep.SweepReport`."""
    u, v = rep.units, rep.v_in
    vc = rep.v_critical
    err = rep.error_estimate
    err_txt = f"v_out error < {err['v_out_abs']:.1e} {u}/s (estimated)" if err else "v_out error: not estimated"
    vc_txt = (f"v_critical {vc:.6f} {u}/s ± {rep.v_critical_error:.1e}" if vc is not None
              else f"v_critical: none ({rep.v_critical_reason})")
    lines = [f"sweep: {len(v)} launches, v_in {v[0]:.4g}..{v[-1]:.4g} {u}/s, {rep.model} model, "
             f"damping {rep.damping:g} 1/s: " + ", ".join(f"{kk} {n}" for kk, n in sorted(rep.outcome_counts.items()))]
    two = rep.two_bounce_windows
    shown = two if len(two) <= SHOW else two[:SHOW]
    lines.append(f"sweep: {len(rep.windows)} windows of 2+ bounces, {len(two)} of two bounces"
                 + (f", resolved to {rep.resolution:g} relative" if rep.resolution else "")
                 + (f" (the first {SHOW} listed; all in --json)" if len(shown) < len(two) else ""))
    for w in shown:
        lines.append(f"  2-bounce window {w['lo']:.6f} .. {w['hi']:.6f} {u}/s"
                     + (f", T_n {w['T_n']:.4f} s" if "T_n" in w else ""))
    fit = rep.tn_fit
    if fit.get("T") is not None:
        lines.append(f"sweep: T_n = {fit['T']:.4f} n + {fit['delta']:.4f} s (eq. tn, {len(fit['n'])} windows); "
                     f"2 pi/omega_y = {fit['T_shape']:.4f} s")
        if fit.get("missing_n"):
            lines.append(f"sweep: the fit numbers the windows n = {fit['n'][0]}..{fit['n'][-1]}: none found for "
                         f"n = {_ranges(fit['missing_n'])} (windows narrower than the samples' spacing, missed; "
                         f"fitted on the {len(fit['n'])} found)")
    c = completeness_line("sweep", rep.window_completeness, u)
    if c:
        lines.append(c)
    lines.append(f"sweep: {err_txt}, {vc_txt}, {rep.seconds:.1f} s")
    return lines


def _ranges(ns) -> str:
    """Whole numbers as runs: [10, 11, 12, 14] -> '10-12, 14'."""
    out, ns = [], sorted(int(n) for n in ns)
    i = 0
    while i < len(ns):
        j = i
        while j + 1 < len(ns) and ns[j + 1] == ns[j] + 1:
            j += 1
        out.append(str(ns[i]) if j == i else f"{ns[i]}-{ns[j]}")
        i = j + 1
    return ", ".join(out)


def completeness_line(who: str, c: dict | None, units: str) -> str:
    """The summary's statement of which windows are certain to be found
    (:func:`fabkit.physics.sweep.completeness`), one line ('' without samples)."""
    if not c or c.get("certain_width") is None:
        return ""
    near, dh = c.get("spacing_near_critical"), c.get("certain_height_width")
    wide = (f"{dh:.4g} {units} in release height (the ramp's spacing; {c['certain_width']:.4g} {units}/s in v_in "
            f"at most, from v_in {c['certain_width_at']:.4g})" if dh is not None else
            f"{c['certain_width']:.4g} {units}/s (the samples' largest spacing, from v_in "
            f"{c['certain_width_at']:.4g})")
    return (f"{who}: every window wider than {wide} is found; a narrower one only if a sample falls in it"
            + (f" (samples {near:.4g} {units}/s apart at v_critical, where the windows narrow)"
               if near is not None else ""))
