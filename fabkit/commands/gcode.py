"""``fabkit gcode SPEC [-o PATH] [--no-verify] [--json]``: the ball-end raster program,
its setup sheet, and the verified cut.

With a ``roughing`` section (its tools in ``tools``) the job is rough, rest and
finish operations: LinuxCNC gets one program with a tool change per tool, grbl one
program per operation (``<stem>.1-rough.nc``, ...); the summary and ``--json``
(``operations``) give each operation's tool, levels, passes, lines and time.

Reads only the sections surface, stock, tool and machining; never builds the
solid or runs the simulator. The verification reads the WRITTEN TEXT back (not
the planner's arrays), so formatting and rounding are part of what is checked.
Exit 1 (outputs still written, for inspection) when the verified cut is out of
tolerance; exit 2 on bad input (nothing written).
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DesignError
from ..io import atomic_outputs
from ..spec import load_spec
from ..surface import Surface, check_depth
from ..toolpath.job import REPAIR_ROUNDS, generated_at as _generated_at  # noqa: F401  (kept names)
from ._common import Timer, check_paths, default_output, emit, stage_bar, warn

NEEDS = ("surface", "stock", "tool", "machining")


def _hm(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60} min" if m >= 60 else f"{m} min"


def run(args) -> int:
    from ..machine.profile import dialect_for_machine, machine_from_spec
    from ..toolpath.finish.guards import with_time_budget
    from ..toolpath.job import run_job
    from ..toolpath.finish.raster import plan_estimate
    from ..toolpath.program.setup_sheet import sheet_paths

    total = Timer()
    spec = load_spec(args.spec, need=NEEDS, command="gcode")
    spec = with_time_budget(spec, getattr(args, "max_time", None))     # --max-time over machining.max_time
    machine = machine_from_spec(spec, getattr(args, "machine", None))    # a bad profile: exit 2 now
    spec = dialect_for_machine(spec, machine)        # the program for the machine given
    out = default_output(spec, ".ngc", args.output)
    paths = sheet_paths(out)
    # refuse now, not after minutes of planning
    check_paths(args, {"--output": out, **{f"--output (setup sheet .{k})": p for k, p in paths.items()},
                       **_job_paths(spec, out)})
    surface = Surface.from_spec(spec)
    _machine_precheck(spec, surface, machine)  # the machine's travel, spindle, tool changer: before planning
    plan_estimate(spec, surface)  # the guards first: a refusal costs about a second
    # a first run compiles every kernel gcode, check and report need for this surface, and says so
    from ..first_run import prepare

    prepare(spec, need=("toolpath",), quiet=getattr(args, "no_progress", False))
    check_depth(spec, surface)
    R = spec.tool.diameter / 2.0
    # verified, the sheet reports what is left; unverified, the smallest concave radius
    # warns (its search, scipy's Nelder-Mead, only then)
    conc = surface.min_concave_radius() if args.no_verify else None
    if conc is not None and conc.z * spec.scale < R:
        warn(f"tool radius {R:g} mm is larger than the smallest concave radius {conc.z * spec.scale:.3g} mm "
             f"(at x={conc.x:.4g}, y={conc.y:.4g}): the tool bridges that valley and leaves material there")

    step, close = stage_bar(3 if args.no_verify else 4, getattr(args, "no_progress", False), "gcode")
    try:
        job = run_job(spec, surface, machine=machine, verify=not args.no_verify, progress=step, program_path=out)
    finally:
        close()          # the bar is gone before any warning or the summary: each starts on its own line
    return _finish(args, job, out, paths, total)


def _job_paths(spec, out) -> dict:
    """A job with roughing: the files it may write besides ``out`` (grbl's programs per
    operation, the stock pictures), to refuse before planning."""
    from ..toolpath.job import has_roughing
    from ..toolpath.program.setup_sheet import job_program_paths_possible, stock_paths

    if not has_roughing(spec):
        return {}
    paths = {f"--output (stock picture, {k})": p for k, p in stock_paths(out).items()}
    for p in job_program_paths_possible(out, spec.machining.dialect):
        paths[f"--output (program {p.name})"] = p
    return paths


def _machine_precheck(spec, surface, machine) -> None:
    """The machine profile (``--machine`` or the spec's section) against the stock,
    spindle and tool call, before any planning (SpecError, exit 2)."""
    from ..machine.limits import precheck

    if machine is not None:
        precheck(spec, surface, machine).raise_if_refused(machine.source)


def _machine_verdict(job) -> None:
    """Refuse (SpecError, exit 2, nothing written) travel, spindle or tool change beyond
    the machine; warn of feeds above its rates."""
    if job.machine_check is None:
        return
    job.machine_check.raise_if_refused(job.machine.source)
    for w in job.machine_check.warnings:
        warn(w)


def _finish(args, job, out, paths, total) -> int:
    """Write the program and its setup sheet (atomically, all or nothing), report."""
    from ..toolpath.program.setup_sheet import sheet_json, sheet_markdown

    _machine_verdict(job)          # refuses before anything is written
    t = Timer()
    toolpath, profile, sheet, run, mcheck = (job.toolpath, job.profile, job.sheet, job.run,
                                                    job.machine_check)
    check = job.cut.as_dict() if job.cut is not None else None
    est, lines = job.estimate_s, job.lines
    t_plan, t_write, t_verify = job.timings["plan"], job.timings["write"], job.timings["verify"]
    timings = {"plan": t_plan, "write": t_write, "verify": t_verify}
    png = job.preview_png()
    pictures = _stock_pictures(job, out)
    md = sheet_markdown(sheet, paths["png"].name, {k: p.name for k, (p, _) in pictures.items()} or None)
    programs = _program_files(job, out)
    with atomic_outputs() as files:         # every program, sheet and picture, or none
        for path, body in programs:
            files.write(path, body)
        files.write(paths["json"], sheet_json(sheet))
        files.write(paths["md"], md)
        files.write(paths["png"], png)
        for path, body in pictures.values():
            files.write(path, body)
    t_sheet = job.timings["sheet"] + t.seconds

    bad = job.failures
    un = check.get("unreachable") if check else None
    if un:
        x, y = un["at"]
        warn(f"material the ball cannot reach is left (not gouged): up to {un['height']:.3f} mm above "
             f"the design at X{x:.2f} Y{y:.2f}, over about {un['area']:.3g} mm^2 "
             "(material_left_unreachable in the setup sheet)")
    seconds = total.seconds
    so = (f"{toolpath.stepover_min:.2f}-{toolpath.stepover:.2f}" if toolpath.stepover_min < toolpath.stepover
          else f"{toolpath.stepover:.2f}")
    gap = toolpath.info.get("edge_pass_gap_max", 0.0)
    so += f" (edge pass gap {gap:.2f})" if gap > toolpath.stepover else ""
    shown = programs[-1][0]       # the program (grbl with roughing: the finishing one, the last)
    if len(programs) > 1:         # grbl with roughing: every program, the finish's passes
        head = f"gcode: {len(programs)} programs {programs[0][0]} .. {Path(programs[-1][0]).name} ({lines} " \
               f"lines in all), finish: {toolpath.passes} passes, stepover {so} mm; "
    else:
        head = f"gcode: {shown}, {toolpath.passes} passes, stepover {so} mm, {lines} lines; "
    if check:
        meas = "normal to the surface" if check.get("material_left_measure", "normal") == "normal" else "vertically"
        head += (f"largest gouge {check['max_gouge']:.4f} mm, material left {check['max_material_left']:.4f} mm {meas} "
                 f"(checked at {check['checked_points']} points); ")
    else:
        head += "not verified (--no-verify); "
    head += (f"est. machining {_hm(est)}; {seconds:.1f} s (plan {t_plan:.1f}, write {t_write:.1f}, "
             f"verify {t_verify:.1f}, sheet {t_sheet:.1f})")
    need, u = sheet["machine_needs"], profile.units
    summary = [head, f"machine: feed up to F{need['feed_max']:g} {u}/min, spindle {need['spindle_rpm']:g} rpm, "
               f"travel X {need['travel']['x']:g}, Y {need['travel']['y']:g}, Z {need['travel']['z']:g} {u} "
               f"(compare with the machine's limits; see the setup sheet)" if need["feed_max"] is not None else
               f"machine: spindle {need['spindle_rpm']:g} rpm (no feed moves)",
               f"setup sheet: {paths['json']}, {paths['md']}, {paths['png']}"]
    if run is not None:
        summary.insert(2, run.summary())
        summary.insert(3, mcheck.summary())
    if job.figures:
        summary[1:1] = _operations_summary(job, out)
        if len(programs) > 1:
            summary.append("programs (run in this order): " + ", ".join(str(p) for p, _ in programs))
        if pictures:
            summary.append("stock pictures: " + ", ".join(str(p) for p, _ in pictures.values()))
    payload = dict(sheet)
    payload.update(program_path=str(shown), setup_paths={k: str(v) for k, v in paths.items()},
                   seconds=round(seconds, 3), ok=not bad, failures=bad)
    payload["timings_s"] = {k: round(v, 3) for k, v in {**timings, "sheet": t_sheet, "total": seconds}.items()}
    if check:
        payload["deepest_cut_mm"] = check["deepest_cut"]
        payload["rapids_checked"] = check["rapids_checked"]
    if job.figures:
        payload["program_paths"] = [str(p) for p, _ in programs]
        if pictures:
            payload["stock_paths"] = {k: str(p) for k, (p, _) in pictures.items()}
    emit(summary, payload, args.json)
    if not job.ok:
        raise DesignError(job.message + f" (outputs written to {shown} and its setup sheet for inspection)")
    return 0


def _program_files(job, out) -> list:
    """[(path, text)]: the job's programs (today's one program at ``out``)."""
    from ..toolpath.program.setup_sheet import job_program_path

    if not job.programs:
        return [(out, job.text)]
    return [(job_program_path(out, suffix), text) for suffix, text in job.programs]


def _stock_pictures(job, out) -> dict:
    """{'rough'|'finish': (path, png)}: the shaded stock pictures the job made."""
    from ..toolpath.program.setup_sheet import stock_paths

    paths = stock_paths(out)
    return {k: (paths[k], png) for k, png in (job.stock_pictures or {}).items() if k in paths}


def _operations_summary(job, out) -> list[str]:
    """One line per operation: tool, levels, passes, lines, time and its estimator; then
    the total and the whole job's verdict."""
    from ..toolpath.program.setup_sheet import job_program_path

    lines = []
    for i, f in enumerate(job.figures, start=1):
        t = f.tool
        tool = (f"T{t.number} " if t.number is not None else "") + f"{t.shape} {t.diameter:g} mm"
        lines.append(f"  {i}. {f.kind}: {tool}, " + (f"{f.levels} level{'s' * (f.levels != 1)}, " if f.levels else "")
                     + f"{f.passes} pass{'es' * (f.passes != 1)}, leaves {f.leave:g} mm, {f.lines} lines, "
                     f"{_hm(f.time_s)} ({f.estimator}), {job_program_path(out, f.program).name}")
    est = " and ".join(sorted({f.estimator for f in job.figures}))
    total = sum(f.time_s for f in job.figures)
    verdict = ("whole job not simulated (--no-verify)" if not job.verified else
               "whole job not simulated (no stock model)" if job.job_check is None else
               "whole job simulated on the stock: " + ("FAILED" if job.job_check.failures else "within bounds"))
    return [f"operations: {len(job.figures)}, {job.lines} lines, {_hm(total)} ({est}); {verdict}"] + lines
