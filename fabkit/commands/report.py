"""``fabkit report SPEC [-o PATH]``: the whole design on one self-contained HTML page.

Computes the results (check, sweep, toolpath with its verified cut and setup sheet,
calibration, the surface's samples, the ramp's marks) and hands them to
:func:`fabkit.report.render`, which only lays them out. Exit 0 whatever the verdict
(the page states it; ``fabkit check`` is the gate that exits 1).
"""

from __future__ import annotations

import numpy as np

from ..errors import SpecError
from ..spec import load_spec
from ._common import Timer, check_paths, default_output, emit, prepare_simulator, stage_bar

NEEDS = ("surface", "stock", "tool", "machining", "ball", "ramp", "simulation")
SURFACE_SAMPLES = (90, 46)   # the 3-D view's grid (x, y)
ERROR_SAMPLES = 24           # escaped launches re-run tighter for the sweep's v_out error
OBSERVABLE_MM = 1.0          # an observable window's least width in release height (fabkit design's default)


def _mark_observable(marks: list, windows: list, min_width: float) -> list:
    """Each window's mark (at its centre in v_in, :func:`fabkit.lab.ramp.mark_targets`)
    with ``observable``: the window at least ``min_width`` wide in release height (design
    units); v_critical's mark is a boundary, always shown."""
    centre = {0.5 * (w["lo"] + w["hi"]): w for w in windows}
    out = []
    for m in marks:
        w = centre.get(m["v_in"])
        out.append(dict(m, observable=True) if w is None else
                   dict(m, observable=bool(w["height_hi"] - w["height_lo"] >= min_width * (1 - 1e-12)),
                        width=w["height_hi"] - w["height_lo"]))
    return out


def _toolpath(spec, surface, machine=None):
    """The toolpath job (as ``fabkit gcode``'s: the same verification and added passes); the
    machine's run time and checks are shown in the sheet, not refused."""
    from ..toolpath.job import run_job

    job = run_job(spec, surface, machine=machine)
    ver = job.cut.to_json()
    return {"png": job.preview_png(), "sheet": job.sheet,
            "seconds": {k: job.timings[k] for k in ("plan", "write", "verify")},
            "verify": {k: ver[k] for k in ("max_gouge", "max_material_left", "checked_points") if k in ver},
            **({"stock_png": dict(job.stock_pictures)} if job.stock_pictures else {})}


class _SharedLaunches:
    """One problem's launches in this process (the compiled engine), shared between the
    check and the sweep: :meth:`full` is the check's launcher (full results, as its own),
    :meth:`replay` the sweep's, answering from what was launched where it can. Each
    launch's outcome, bounces, v_out and bounce times are kept by entry speed (a launch
    depends on its speed alone, not on its batch)."""

    def __init__(self, problem):
        from ..physics.check import _in_process

        self._run = _in_process(problem)
        self._memo: dict = {}

    def _record(self, v, r):
        from ..physics.check import _as_launches

        lr = _as_launches(r)
        for i, x in enumerate(v):
            self._memo[x] = (lr.outcome[i], lr.bounces[i], lr.v_out[i], lr.bounce_times[i])

    def full(self, v):
        r = self._run(v)
        self._record(np.asarray(v, dtype=float).tolist(), r)
        return r

    def replay(self, v):
        from ..physics.sweep import Launches

        v = np.asarray(v, dtype=float)
        miss = [x for x in v.tolist() if x not in self._memo]
        if miss:
            self._record(miss, self._run(np.asarray(miss)))
        rows = [self._memo[x] for x in v.tolist()]
        width = max((np.size(r[3]) for r in rows), default=0)
        bt = np.full((len(rows), width), np.nan)
        for i, r in enumerate(rows):
            bt[i, :np.size(r[3])] = r[3]
        return Launches(v, np.array([r[0] for r in rows], dtype=np.int8), np.array([r[1] for r in rows], dtype=int),
                        np.array([r[2] for r in rows], dtype=float), bt)


def _sweep(spec, cal, problem, shared: _SharedLaunches) -> dict:
    """The sweep over the ramp's entry speeds and its figure, for the page: v_critical and
    the two-bounce windows to the check's tolerances, on the check's problem, so that its
    bisections are the check's own launches, replayed (``shared``)."""
    from ..physics.check import TOLERANCES
    from ..physics.sweep import estimate_error, sweep
    from ..plots import sweep_figure

    t = Timer()
    v = np.unique(np.asarray(cal["v_in"], dtype=float))
    v = v[np.isfinite(v)]                 # nan: heights from which the ball does not reach the block
    replay = shared.replay
    sw = sweep(problem, v, launcher=replay, error_samples=0, tn=False,
               rel_tol=TOLERANCES["v_rel_tol"], edge_rel_tol=TOLERANCES["edge_rel_tol"],
               gap_rel_tol=TOLERANCES["gap_rel_tol"], bounces=(2,))
    # the integration error of v_out: 24 escaped launches re-run with rtol and atol ten times tighter
    v_sorted = np.sort(v)
    sw["error_estimate"] = estimate_error(problem, v_sorted, replay(v_sorted), method="fabkit", rtol=None,
                                          atol=None, samples=ERROR_SAMPLES)
    sw_png = sweep_figure(sw, f"{spec.name}: {problem.model} model, damping {problem.damping:g} 1/s",
                          units=spec.units)
    return {"png": sw_png, "v_critical": sw["v_critical"], "v_critical_error": sw["v_critical_error"],
            "v_critical_reason": sw.get("v_critical_reason"),
            "windows": sw["windows"], "error_estimate": sw["error_estimate"], "launches": sw["launches"],
            "seconds": t.seconds}


def run(args) -> int:
    from .. import __version__
    from ..io import write_atomic
    from ..lab.ramp import mark_targets
    from ..physics.calibrate import calibration_table
    from ..physics.check import check
    from ..physics.models import problem_from_spec
    from ..report import render
    from ..surface import Surface, check_depth
    from ..toolpath.finish.guards import with_time_budget
    from ..toolpath.job import generated_at as _generated_at

    total = Timer()
    spec = load_spec(args.spec, need=NEEDS, command="report")
    spec = with_time_budget(spec, getattr(args, "max_time", None))     # --max-time over machining.max_time
    path = default_output(spec, ".report.html", args.output)
    check_paths(args, {"--output": path})
    if path.suffix.lower() not in ("", ".html", ".htm", ".xhtml"):
        raise SpecError(f"the report is an HTML page: name it .html, not '{path.suffix}'", key="--output")
    surface = Surface.from_spec(spec)
    check_depth(spec, surface)
    from ..machine.profile import dialect_for_machine, machine_from_spec

    machine = machine_from_spec(spec, getattr(args, "machine", None))    # a bad profile: exit 2 now
    spec = dialect_for_machine(spec, machine)        # the toolpath in the machine's dialect

    from ..first_run import cold_kernels, prepare

    # a first run compiles every kernel the page needs (the simulator, the toolpath's) at once, and
    # says so; a job the time guard refuses is refused before that (the guard runs again in the job)
    cold = cold_kernels(spec)
    if cold["simulator"] > 0 or cold["toolpath"] > 0:
        from ..toolpath.finish.raster import plan_estimate

        plan_estimate(spec, surface)
        prepare(spec, quiet=getattr(args, "no_progress", False))
    step, close = stage_bar(5, getattr(args, "no_progress", False), "report")
    try:
        step("calibrating the ramp")
        t = Timer()
        cal = calibration_table(spec)
        cal["seconds"] = t.seconds

        step("compiling or loading the simulator")
        prepare_simulator(spec)
        step("checking")
        # the check's own problem (stop_trapped, as check builds it) and its launches
        # recorded for the sweep
        problem = problem_from_spec(spec).with_(stop_trapped=True)
        shared = _SharedLaunches(problem)
        chk = check(spec, problem=problem, launcher=shared.full).to_json()
        step("sweeping")
        sw_part = _sweep(spec, cal, problem, shared)
        step("planning and verifying the toolpath")
        tool = _toolpath(spec, surface, machine)
    finally:
        close()
    sweep_res = sw_part


    nx, ny = SURFACE_SAMPLES
    xs = np.linspace(surface.x_range[0], surface.x_range[1], nx)
    ys = np.linspace(surface.y_range[0], surface.y_range[1], ny)
    GX, GY = np.meshgrid(xs, ys, indexing="ij")
    surf = {"x": xs, "y": ys, "z": surface.clipped(GX, GY), "top": surface.top,
            "start": float(spec.simulation.start), "y0": float(spec.simulation.y0)}

    min_width = OBSERVABLE_MM / float(spec.scale)
    marks = _mark_observable(mark_targets(chk, cal["g"], cal["k"], spec=spec), chk.get("reachable_windows") or [],
                             min_width)
    results = {"name": spec.name, "units": spec.units, "spec_path": str(args.spec), "version": __version__,
               "generated_at": _generated_at(), "check": chk, "surface": surf, "sweep": sweep_res,
               "toolpath": tool, "calibration": cal, "ramp_marks": marks, "scale": float(spec.scale),
               "min_width": min_width}
    results["seconds"] = total.seconds
    page = render(results)
    write_atomic(path, page)
    verdict = "SAFE" if chk["safe"] else "UNSAFE"
    payload = {"path": str(path), "verdict": verdict, "safe": chk["safe"], "model": chk["model"], "bytes": len(page.encode()),
               "seconds": total.seconds,
               "seconds_by_part": {"check": chk["seconds"], "sweep": sweep_res["seconds"],
                                   **{f"toolpath_{k}": v for k, v in tool["seconds"].items()}}}
    emit([f"report: {path} ({len(page.encode()) / 1e6:.2f} MB, self-contained), verdict {verdict} "
          f"({chk['model']} model), "
          f"{total.seconds:.1f} s (check {chk['seconds']:.1f}, sweep {sweep_res['seconds']:.1f}, toolpath "
          f"{sum(tool['seconds'].values()):.1f})"], payload, args.json)
    return 0
