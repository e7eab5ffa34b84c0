"""``fabkit gcode SPEC [-o PATH] [--no-verify] [--json]``: the ball-end raster program,
its setup sheet, and the verified cut.

Reads only the sections surface, stock, tool and machining; never builds the
solid or runs the simulator. The verification reads the WRITTEN TEXT back (not
the planner's arrays), so formatting and rounding are part of what is checked.
Exit 1 (outputs still written, for inspection) when the verified cut is out of
tolerance; exit 2 on bad input (nothing written).
"""

from __future__ import annotations

import os
from datetime import datetime, timezone

from ..errors import DesignError
from ..io import atomic_outputs
from ..spec import load_spec
from ..surface import Surface, check_depth
from ._common import Timer, check_paths, default_output, emit, stage_bar, warn

NEEDS = ("surface", "stock", "tool", "machining")
REPAIR_ROUNDS = 2      # verify, add passes where material is left, verify again (at most twice)


def _generated_at() -> str:
    """UTC time for the setup sheet (SOURCE_DATE_EPOCH honoured for reproducible builds)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    when = datetime.fromtimestamp(int(epoch), timezone.utc) if epoch and epoch.isdigit() \
        else datetime.now(timezone.utc)
    return when.isoformat(timespec="seconds")


def _hm(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60} min" if m >= 60 else f"{m} min"


def failures(check: dict, spec) -> list[str]:
    """The failed acceptance checks of a verification (empty: the cut is good)."""
    m = spec.machining
    bad = []
    if check["max_gouge"] > m.tolerance:
        x, y = check["gouge_at"]
        bad.append(f"gouge {check['max_gouge']:.4f} mm > tolerance {m.tolerance:g} mm at X{x:.3f} Y{y:.3f}")
    if check["max_material_left"] > m.scallop + m.tolerance:
        x, y = check["material_at"]
        bad.append(f"material left {check['max_material_left']:.4f} mm > scallop + tolerance "
                   f"{m.scallop + m.tolerance:g} mm at X{x:.3f} Y{y:.3f}")
    if check["rapid_clearance"] < -m.tolerance:
        x, y = check["rapid_clearance_at"]
        bad.append(f"a rapid passes {-check['rapid_clearance']:.4f} mm into material at X{x:.3f} Y{y:.3f}")
    if not check["depth_ok"]:
        bad.append(f"deepest cut {check['deepest_cut']:.3f} mm exceeds the depth limit or tool reach")
    if not check["first_move_ok"]:
        bad.append("the program does not start with a rapid up to the safe height")
    return bad


def run(args) -> int:
    from ..toolpath.gcode import profile_from_spec, write_program
    from ..toolpath.guards import with_time_budget
    from ..toolpath.raster import plan_estimate, plan_toolpath
    from ..toolpath.setup import sheet_paths

    total = Timer()
    spec = load_spec(args.spec, need=NEEDS, command="gcode")
    spec = with_time_budget(spec, getattr(args, "max_time", None))     # --max-time over machining.max_time
    out = default_output(spec, ".ngc", args.output)
    paths = sheet_paths(out)
    # refuse now, not after minutes of planning
    check_paths(args, {"--output": out, **{f"--output (setup sheet .{k})": p for k, p in paths.items()}})
    surface = Surface.from_spec(spec)
    _machine_precheck(args, spec, surface)     # the machine's travel, spindle, tool changer: before planning
    plan_estimate(spec, surface)        # the guards first: a refusal costs about a second
    check_depth(spec, surface)
    R = spec.tool.diameter / 2.0
    conc = surface.min_concave_radius()
    if conc.z * spec.scale < R and args.no_verify:    # verified: the sheet reports what is left
        warn(f"tool radius {R:g} mm is larger than the smallest concave radius {conc.z * spec.scale:.3g} mm "
             f"(at x={conc.x:.4g}, y={conc.y:.4g}): the tool bridges that valley and leaves material there")

    step, close = stage_bar(3 if args.no_verify else 4, getattr(args, "no_progress", False), "gcode")
    try:
        step("planning the passes")
        t = Timer()
        toolpath = plan_toolpath(spec, surface)
        t_plan = t.seconds
        step("writing the program")
        t = Timer()
        profile = profile_from_spec(spec, surface)
        text = write_program(toolpath, profile)
        t_write = t.seconds
        return _finish(args, spec, surface, toolpath, profile, text, out, paths, R, t_plan, t_write, total,
                       step)
    finally:
        close()


def _machine_precheck(args, spec, surface) -> None:
    """The machine profile (``--machine`` or the spec's section) against the stock,
    spindle and tool call, before any planning (SpecError, exit 2)."""
    from ..machine.limits import precheck
    from ..machine.profile import machine_from_spec

    machine = machine_from_spec(spec, getattr(args, "machine", None))
    if machine is not None:
        precheck(spec, surface, machine).raise_if_refused(machine.source)


def machine_run(args, spec, program, text):
    """(machine, run time, checks) of the program on the machine profile, or (None, None,
    None) without one. Refuses (SpecError, exit 2) travel, spindle or tool change beyond
    the machine; warns of feeds above its rates."""
    from ..machine.limits import check_program
    from ..machine.planner import run_time
    from ..machine.profile import machine_from_spec

    machine = machine_from_spec(spec, getattr(args, "machine", None))
    if machine is None:
        return None, None, None
    run = run_time(text, machine, program, raster_axis=0 if spec.machining.direction == "x" else 1)
    mcheck = check_program(program, text, machine, run)
    mcheck.raise_if_refused(machine.source)
    for w in mcheck.warnings:
        warn(w)
    return machine, run, mcheck


def verified_cut(spec, surface, toolpath, profile, text, program):
    """Verify the program read back from ``text``; where the cut leaves more than
    scallop + tolerance (and nothing else is wrong), add passes there and verify again
    (at most REPAIR_ROUNDS times, kept only if it leaves less). Returns (toolpath, text,
    program, check) of the program to write."""
    from ..toolpath.gcode import write_program
    from ..toolpath.raster import add_passes, scallop_normal
    from ..toolpath.verify import read_program, verify_cut

    m = spec.machining
    cache = {}

    def verify(program):
        return verify_cut(surface, program, spec.tool.diameter / 2.0, m.verify_points,
                          depth_limit=spec.stock.depth_limit, reach=spec.tool.reach,
                          unreachable_min=m.tolerance, normal=scallop_normal(spec),
                          over=m.scallop + m.tolerance, cache=cache)

    check = verify(program)
    for _ in range(REPAIR_ROUNDS):
        bad = failures(check, spec)
        if not bad or not all(b.startswith("material left") for b in bad):
            break
        over = check["over_at"]
        tp2 = add_passes(spec, surface, toolpath, over[:, 1] if m.direction == "x" else over[:, 0])
        if tp2 is None:
            break
        text2 = write_program(tp2, profile)
        program2 = read_program(text2)
        check2 = verify(program2)
        if check2["max_material_left"] >= check["max_material_left"] or \
                check2["max_gouge"] > max(check["max_gouge"], m.tolerance):
            break
        toolpath, text, program, check = tp2, text2, program2, check2
    return toolpath, text, program, check


def _finish(args, spec, surface, toolpath, profile, text, out, paths, R, t_plan, t_write, total, step) -> int:
    """Read the program back, verify it, write the program and its setup sheet, report."""
    from ..toolpath.setup import preview_png, setup_sheet, sheet_json, sheet_markdown
    from ..toolpath.verify import estimate_time, read_program

    t = Timer()
    program = read_program(text)
    check = None
    if not args.no_verify:
        step("verifying the cut")
        toolpath, text, program, check = verified_cut(spec, surface, toolpath, profile, text, program)
    est = estimate_time(program, profile.rapid)
    t_verify = t.seconds
    machine, run, mcheck = machine_run(args, spec, program, text)    # refuses before anything is written

    step("setup sheet")
    t = Timer()
    lines = text.count("\n")
    timings = {"plan": t_plan, "write": t_write, "verify": t_verify}
    sheet = setup_sheet(spec, surface, toolpath, profile, out, check, est, lines, timings=timings,
                        generated_at=_generated_at(), program=program, machine=machine, run=run,
                        machine_check=mcheck)
    L, W = surface.stock_size_mm
    png = preview_png(program, L, W, profile.units)
    md = sheet_markdown(sheet, paths["png"].name)
    with atomic_outputs() as files:
        files.write(out, text)
        files.write(paths["json"], sheet_json(sheet))
        files.write(paths["md"], md)
        files.write(paths["png"], png)
    t_sheet = t.seconds

    bad = failures(check, spec) if check else []
    un = check.get("unreachable") if check else None
    if un:
        x, y = un["at"]
        warn(f"material the ball cannot reach is left (not gouged): up to {un['height']:.3f} mm above "
             f"the design at X{x:.2f} Y{y:.2f}, over about {un['area']:.3g} mm^2 "
             "(material_left_unreachable in the setup sheet)")
    seconds = total.seconds
    so = (f"{toolpath.stepover_min:.2f}-{toolpath.stepover:.2f}" if toolpath.stepover_min < toolpath.stepover
          else f"{toolpath.stepover:.2f}")
    head = f"gcode: {out}, {toolpath.passes} passes, stepover {so} mm, {lines} lines; "
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
    payload = dict(sheet)
    payload.update(program_path=str(out), setup_paths={k: str(v) for k, v in paths.items()},
                   seconds=round(seconds, 3), ok=not bad, failures=bad)
    payload["timings_s"] = {k: round(v, 3) for k, v in {**timings, "sheet": t_sheet, "total": seconds}.items()}
    if check:
        payload["deepest_cut_mm"] = check["deepest_cut"]
        payload["rapids_checked"] = check["rapids_checked"]
    emit(summary, payload, args.json)
    if bad:
        raise DesignError("verification failed: " + "; ".join(bad) +
                          f" (outputs written to {out} and its setup sheet for inspection)")
    return 0
