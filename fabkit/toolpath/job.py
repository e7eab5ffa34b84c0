"""The toolpath job, written once: plan the passes, write the program, read the
written text back, verify the cut (adding passes where material is left, at most
``REPAIR_ROUNDS`` times), estimate the run time (length / feed, and the machine's
planner when a machine profile is given) and build the setup sheet.

``fabkit gcode``, ``fabkit report`` and ``fabkit precision`` call :func:`run_job`; they
only format and write what it returns. Its :class:`JobResult` carries the verdict
(:attr:`JobResult.failures`, :attr:`JobResult.ok`, :attr:`JobResult.message`), so no
command judges a cut on its own. Nothing here prints, writes files or exits.

The verification reads the WRITTEN TEXT back (not the planner's arrays), so the
program's formatting and rounding are part of what is checked. Lengths are work mm
(the program's own units appear only in the text and the sheet).

With a ``roughing`` section the finish above is planned, verified and repaired the
same way; then the roughing planner (:mod:`fabkit.toolpath.rough.roughing`) adds its rough
and rest operations, :func:`fabkit.toolpath.program.gcode.write_job` writes every program, each
is read back, and the stock model (:mod:`fabkit.toolpath.cut.stock`, when present)
replays the whole job from the text.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from typing import Callable

import numpy as np

__all__ = ["REPAIR_ROUNDS", "CutReport", "JobResult", "OperationFigures", "run_job", "verify_program", "repair",
           "generated_at", "has_roughing", "plan_job_operations", "job_figures"]

REPAIR_ROUNDS = 2      # verify, add passes where material is left, verify again (at most twice)


def generated_at() -> str:
    """UTC time for the setup sheet (SOURCE_DATE_EPOCH honoured for reproducible builds)."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    when = datetime.fromtimestamp(int(epoch), timezone.utc) if epoch and epoch.isdigit() \
        else datetime.now(timezone.utc)
    return when.isoformat(timespec="seconds")


# ----------------------------------------------------------------------------
# the verified cut
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class CutReport:
    """The verified cut of one program (work mm, work X, Y): what
    :func:`fabkit.toolpath.cut.verify.verify_cut` measures, typed. ``to_json()`` gives the
    keys of verify_cut's dict unchanged (``over_at`` as [[X, Y], ...] when asked for);
    keys verify_cut may add later are kept in ``extra`` and passed through."""

    max_gouge: float
    gouge_at: tuple
    max_material_left: float
    material_at: tuple
    material_left_measure: str
    max_material_left_normal: float
    material_left_normal_at: tuple
    max_material_left_vertical: float
    material_left_vertical_at: tuple
    checked_points: int
    max_material_above_design: float
    material_above_design_at: tuple
    unreachable: dict | None
    rapid_clearance: float
    rapid_clearance_at: tuple | None
    rapids_checked: int
    deepest_cut: float
    depth_ok: bool
    first_move_ok: bool
    segments: int
    over_at: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, check: dict) -> "CutReport":
        names = {f.name for f in fields(cls)} - {"extra"}
        return cls(**{k: v for k, v in check.items() if k in names},
                   extra={k: v for k, v in check.items() if k not in names})

    def as_dict(self) -> dict:
        """verify_cut's dict (arrays kept as arrays)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("over_at", "extra")}
        if self.over_at is not None:
            out["over_at"] = self.over_at
        out.update(self.extra)
        return out

    def to_json(self) -> dict:
        """verify_cut's keys, JSON-ready (tuples as lists, ``over_at`` as [[X, Y], ...])."""
        def plain(v):
            if isinstance(v, np.ndarray):
                return v.tolist()
            if isinstance(v, tuple):
                return [plain(x) for x in v]
            if isinstance(v, dict):
                return {k: plain(x) for k, x in v.items()}
            return v
        return {k: plain(v) for k, v in self.as_dict().items()}

    def failures(self, machining) -> list[str]:
        """The failed acceptance checks against the spec's ``machining`` section
        (tolerance, scallop; mm): empty when the cut is good."""
        m = machining
        bad = []
        if self.max_gouge > m.tolerance:
            x, y = self.gouge_at
            bad.append(f"gouge {self.max_gouge:.4f} mm > tolerance {m.tolerance:g} mm at X{x:.3f} Y{y:.3f}")
        if self.max_material_left > m.scallop + m.tolerance:
            x, y = self.material_at
            bad.append(f"material left {self.max_material_left:.4f} mm > scallop + tolerance "
                       f"{m.scallop + m.tolerance:g} mm at X{x:.3f} Y{y:.3f}")
        if self.rapid_clearance < -m.tolerance:
            x, y = self.rapid_clearance_at
            bad.append(f"a rapid passes {-self.rapid_clearance:.4f} mm into material at X{x:.3f} Y{y:.3f}")
        if not self.depth_ok:
            bad.append(f"deepest cut {self.deepest_cut:.3f} mm exceeds the depth limit or tool reach")
        if not self.first_move_ok:
            bad.append("the program does not start with a rapid up to the safe height")
        return bad

    def only_material_left(self, machining) -> bool:
        """Every failure is material left (what added passes can repair)."""
        bad = self.failures(machining)
        return bool(bad) and all(b.startswith("material left") for b in bad)


def verify_program(spec, surface, program, cache: dict | None = None) -> CutReport:
    """The one verification of a program read back for ``spec`` (the arguments every
    command uses: the spec's check points, depth limit, reach, scallop measure; the
    points above scallop + tolerance kept for the repair)."""
    from .finish.raster import scallop_normal
    from .cut.verify import verify_cut

    m = spec.machining
    return CutReport.from_dict(verify_cut(surface, program, spec.tool.diameter / 2.0, m.verify_points,
                                          depth_limit=spec.stock.depth_limit, reach=spec.tool.reach,
                                          unreachable_min=m.tolerance, normal=scallop_normal(spec),
                                          over=m.scallop + m.tolerance, cache=cache, along=m.direction))


def repair(spec, surface, toolpath, profile, text, program, cut: CutReport, cache: dict | None = None):
    """Where the cut leaves more than scallop + tolerance (and nothing else is wrong),
    add passes there and verify again (at most REPAIR_ROUNDS times, kept only if it
    leaves less and gouges no more). Returns (toolpath, text, program, cut) to write."""
    from .program.gcode import write_program
    from .finish.raster import add_passes
    from .program.reader import read_program

    m = spec.machining
    cache = {} if cache is None else cache
    for _ in range(REPAIR_ROUNDS):
        if not cut.only_material_left(m):
            break
        over = cut.over_at
        tp2 = add_passes(spec, surface, toolpath, over[:, 1] if m.direction == "x" else over[:, 0])
        if tp2 is None:
            break
        text2 = write_program(tp2, profile)
        program2 = read_program(text2)
        cut2 = verify_program(spec, surface, program2, cache)
        if cut2.max_material_left >= cut.max_material_left or \
                cut2.max_gouge > max(cut.max_gouge, m.tolerance):
            break
        toolpath, text, program, cut = tp2, text2, program2, cut2
    return toolpath, text, program, cut


# ----------------------------------------------------------------------------
# the job
# ----------------------------------------------------------------------------
@dataclass
class JobResult:
    """One toolpath job's outcome. ``cut`` is None when not verified. ``estimate_s``:
    length / feed (rapids at the assumed rate, no acceleration); ``run``, ``machine_check``:
    the machine planner's run time and the checks before cutting (None without a machine
    profile). ``timings``: wall seconds of plan, write, verify, sheet.

    A job with roughing (a ``roughing`` section) also has ``operations`` (rough, rest,
    finish: :class:`~fabkit.toolpath.operations.Operation`), ``figures`` (one
    :class:`OperationFigures` each), ``programs`` ([(suffix, text)] as written:
    :func:`fabkit.toolpath.program.gcode.write_job`), ``job_check`` (the whole job simulated on
    the stock, None without the stock model or unverified) and ``stock_pictures``
    ({'rough'|'finish': PNG bytes}). Then ``toolpath``, ``program`` and ``cut`` are the
    finish's (verified as without roughing), ``text`` the program holding the finish,
    ``estimate_s`` and ``lines`` the whole job's. Without roughing these are empty and
    everything is as before."""

    spec: object
    surface: object
    toolpath: object
    profile: object
    text: str
    program: object
    cut: CutReport | None
    estimate_s: float
    sheet: dict
    timings: dict
    machine: object = None
    run: object = None
    machine_check: object = None
    operations: list = field(default_factory=list)
    figures: list = field(default_factory=list)
    programs: list = field(default_factory=list)
    job_check: object = None
    stock_pictures: dict = field(default_factory=dict)

    @property
    def lines(self) -> int:
        """Lines of every program of the job (today's one program: its lines)."""
        if self.programs:
            return sum(text.count("\n") for _, text in self.programs)
        return self.text.count("\n")

    @property
    def verified(self) -> bool:
        return self.cut is not None

    @property
    def failures(self) -> list[str]:
        """The failed acceptance checks (empty: the cut is good, or it was not verified):
        the finishing cut's and, for a job with roughing, the whole job's (every tool's
        gouge, the allowance after roughing, the finishing ball's depth of cut)."""
        bad = self.cut.failures(self.spec.machining) if self.cut is not None else []
        if self.job_check is not None:
            bad += [f"whole job: {b}" for b in self.job_check.failures]
        return bad

    @property
    def ok(self) -> bool:
        return not self.failures

    @property
    def message(self) -> str:
        """One line: the verdict and, when it failed, why."""
        if self.cut is None:
            return "not verified"
        bad = self.failures
        return "verification failed: " + "; ".join(bad) if bad else "verified: within tolerance"

    def preview_png(self) -> bytes:
        """The top view of the passes coloured by depth (the sheet's preview)."""
        from .program.setup_sheet import preview_png

        L, W = self.surface.stock_size_mm
        return preview_png(self.program, L, W, self.profile.units)


# ----------------------------------------------------------------------------
# a job of several operations (roughing, rest machining, finishing)
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class OperationFigures:
    """What the summary, the sheet and the report give for one operation (work mm, s).

    ``program``: the suffix of its program file on the program's stem ("" : the program
    itself); ``lines``: its lines (in a one-program job, those from its tool change to
    the next); ``estimate_s``: length / feed at its tool's feeds; ``run_s``: the machine
    planner's time of its moves (None without a machine profile). Both from the program
    text: ``estimate_s`` is :func:`fabkit.toolpath.program.reader.estimate_time` of its moves read
    back (today's estimator; in a one-program job the moves from the previous
    operation's last position, so the operations' figures add up to the program's)."""

    kind: str
    tool: object
    levels: int
    passes: int
    leave: float
    program: str
    lines: int
    estimate_s: float
    run_s: float | None = None
    feed: float = 0.0
    plunge: float = 0.0
    spindle: float = 0.0

    @property
    def time_s(self) -> float:
        """The best time there is: the machine's when known, else length / feed."""
        return self.run_s if self.run_s is not None else self.estimate_s

    @property
    def estimator(self) -> str:
        return "machine planner" if self.run_s is not None else "length/feed"

    def to_json(self, k: float = 1.0) -> dict:
        """JSON keys; lengths in program units (``k``: program units per mm)."""
        t = self.tool
        return {"kind": self.kind, "tool": {"number": t.number, "shape": t.shape, "diameter": _rk(t.diameter, k),
                                            "corner_radius": _rk(t.corner_radius, k)},
                "levels": int(self.levels), "passes": int(self.passes), "leave": _rk(self.leave, k),
                "program": self.program, "lines": int(self.lines),
                "time_s": round(float(self.time_s), 1), "estimator": self.estimator,
                "length_over_feed_s": round(float(self.estimate_s), 1),
                "machine_s": round(float(self.run_s), 1) if self.run_s is not None else None,
                "feed": _rk(self.feed, k), "plunge": _rk(self.plunge, k), "spindle_rpm": _rk(self.spindle, 1.0)}


def _rk(v: float, k: float):
    v = float(v) * k
    return float(f"{v:.9g}") if np.isfinite(v) else None


def has_roughing(spec) -> bool:
    """The spec asks for roughing with its own tool (a ``roughing`` section)."""
    return bool(getattr(spec, "has", lambda name: False)("roughing"))


def _op_line_ranges(text: str, n: int, lines: list | None = None) -> list[tuple[int, int]]:
    """[(first line, last line)] (1-based) of each operation in a one-program job: from its
    ``(operation: i of n, ...)`` comment (:func:`fabkit.toolpath.program.gcode.write_job`) to the
    line before the next one (the first from line 1, the last to the end). ``lines``:
    ``text.splitlines()`` when already split."""
    lines = text.splitlines() if lines is None else lines
    starts = [i + 1 for i, ln in enumerate(lines) if ln.startswith("(operation: ")]
    if len(starts) != n:
        raise ValueError(f"{len(starts)} operation comments in a program of {n} operations")
    starts[0] = 1
    return [(a, b - 1) for a, b in zip(starts, starts[1:] + [len(lines) + 1])]


def _section(program, lo: int, hi: int):
    """The moves of ``program`` on lines lo..hi, as a Program starting where the one
    before left off."""
    from .program.reader import Program

    keep = (program.line >= lo) & (program.line <= hi)
    idx = np.nonzero(keep)[0]
    start = program.start if not len(idx) or idx[0] == 0 else program.points[idx[0] - 1]
    return Program(start=np.array(start, dtype=float), points=program.points[keep], kinds=program.kinds[keep],
                   feed=program.feed[keep], line=program.line[keep], units=program.units, lines=program.lines)


def plan_job_operations(spec, surface, finish_toolpath) -> list:
    """The job's operations: the roughing planner's (rough, then rest) and the finish
    with the spec's finishing tool. Without a ``roughing`` section: the finish alone."""
    from .operations import Operation

    if not has_roughing(spec):
        from .tools import Tool

        t = spec.tool
        tool = Tool(t.shape, t.diameter, 0.5 * t.diameter if t.shape == "ball" else 0.0,
                    reach=t.reach, number=t.number)
        return [Operation("finish", tool, finish_toolpath, passes=int(finish_toolpath.passes))]
    from .rough import roughing

    ops = list(roughing.plan_operations(spec, surface, finish_toolpath))
    ops.append(Operation("finish", roughing.finish_tool(spec), finish_toolpath,
                         passes=int(finish_toolpath.passes)))
    return ops


def _read_with_finish(lines: list, first: int, finish):
    """The Program of a one-program job's text (``lines``), its last operation (from line
    ``first``) being ``finish`` = (text, Program) as written and read alone: its lines
    from its first move on must be the job's last lines, one for one, with no tool,
    offset or unit change among them; then only the lines before them are read, and the
    finish's moves are taken as read alone (its leading axes never set taken from where
    the job's lines before left the tool, its tool and offset theirs, its line numbers
    the job's). None where that does not hold (the caller reads the whole text).
    tests/test_job_operations.py: field for field the whole text's read."""
    from .program.reader import Program, read_program

    text_f, fin = finish
    if not len(fin.points):
        return None
    flines = text_f.splitlines()
    l0 = int(fin.line[0])                    # the finish's first move, 1-based, in its own text
    body = flines[l0 - 1:]
    k = len(lines) - len(body)               # where the same lines start in the job (0-based)
    if k < first or lines[k:] != body:
        return None
    if any(("G2" in ln) or ("G4" in ln) or ("G9" in ln) or ("M6" in ln) or ("T" in ln.split("(")[0])
           for ln in body):
        return None                          # a units, offset, mode or tool word: read it all
    pre = read_program("\n".join(lines[:k]) + "\n")
    st = pre.end_state
    if st["units"] != fin.units:
        return None
    pts = np.array(fin.points, dtype=float)
    for a in range(3):                       # the axes the finish had not set: where the job left them
        unset = ~np.isfinite(pts[:, a])
        lead = int(np.argmin(unset)) if not unset.all() else len(unset)
        pts[:lead, a] = st["pos"][a]
    m = len(pts)
    return Program(start=pre.start if len(pre.points) else np.array(st["pos"], dtype=float),
                   points=np.vstack([pre.points, pts]), kinds=np.concatenate([pre.kinds, fin.kinds]),
                   feed=np.concatenate([pre.feed, fin.feed]),
                   line=np.concatenate([pre.line, fin.line + (k - (l0 - 1))]), units=fin.units, lines=len(lines),
                   tool=np.concatenate([pre.tool, np.full(m, st["tool"], dtype=int)]),
                   offset=np.concatenate([pre.offset, np.full(m, st["offset"], dtype=int)]),
                   tool_changes=list(pre.tool_changes),
                   end_state={**fin.end_state, "tool": st["tool"], "offset": st["offset"]})


def job_figures(operations, programs, profile, machine=None, raster_axis: int | None = None,
                parsed: list | None = None, finish=None) -> tuple:
    """Per operation :class:`OperationFigures` and the programs read back.

    ``programs``: :func:`fabkit.toolpath.program.gcode.write_job`'s [(suffix, text)]: one per
    operation, or one for all. Returns (figures, readback) with ``readback`` one
    Program per operation (its moves read back from the written text). ``parsed``: a
    list given is filled with the reader's parse of each program's text, in order (one
    per program: for a one-program job, the whole before it is split). ``finish``: (text,
    Program) of the last operation written and read alone (:func:`_read_with_finish`)."""
    from .program.gcode import operation_profile, write_program
    from .program.reader import estimate_time, read_program

    n = len(operations)
    if len(programs) == n:
        parts = [(suffix, text, read_program(text)) for suffix, text in programs]
        readback = [p for _, _, p in parts]
        lines = [text.count("\n") for _, text, _ in parts]
        names = [suffix for suffix, _, _ in parts]
        if parsed is not None:
            parsed.extend(readback)
    else:
        (suffix, text), = programs
        text_lines = text.splitlines()
        ranges = _op_line_ranges(text, n, text_lines)
        whole = _read_with_finish(text_lines, ranges[-1][0], finish) if finish is not None else None
        if whole is None:
            whole = read_program(text)
        if parsed is not None:
            parsed.append(whole)
        readback = [_section(whole, lo, hi) for lo, hi in ranges]
        lines = [hi - lo + 1 for lo, hi in ranges]
        names = [suffix] * n
    figures = []
    for i, op in enumerate(operations):
        run_s = None
        p = operation_profile(profile, op.tool)
        if machine is not None:
            from ..machine.planner import run_time

            text_i = programs[i][1] if len(programs) == n else write_program(op.toolpath, p)
            run_s = float(run_time(text_i, machine, None if len(programs) != n else readback[i],
                                   raster_axis=raster_axis if op.kind == "finish" else None).total_s)
        figures.append(OperationFigures(kind=op.kind, tool=op.tool, levels=int(op.levels), passes=int(op.passes),
                                        leave=float(op.leave), program=names[i], lines=int(lines[i]),
                                        estimate_s=estimate_time(readback[i], profile.rapid), run_s=run_s,
                                        feed=p.feed, plunge=p.plunge, spindle=p.spindle))
    return figures, readback


#: the operations a picture "after roughing" follows: the last of these before the finish
_ROUGHING_KINDS = ("rough", "rest")
def _stock_verification(spec, surface, operations, readback):
    """The whole job simulated on the stock, each operation's moves AS READ BACK from the
    written text, each with its own tool (:func:`fabkit.toolpath.cut.stock.verify_job`), and
    the shaded pictures of the stock after roughing and after finishing
    (:func:`fabkit.toolpath.cut.stock.stock_png`): (check, {'rough'|'finish': png}). The one place that knows the stock module's interface."""
    from .cut import stock
    from .operations import Operation
    from .path import Toolpath

    m = spec.machining
    replay = []
    for op, prog in zip(operations, readback):
        tp = Toolpath(prog.points, prog.kinds, op.tool.radius, safe_z=op.toolpath.safe_z)
        tp.info["start"] = prog.start
        tp.info["line"] = prog.line
        replay.append(Operation(op.kind, op.tool, tp, leave=op.leave, levels=op.levels, passes=op.passes,
                                info={**op.info, "start": prog.start}))
    doc = getattr(spec.tool, "depth_of_cut", None)     # the finishing tool's allowed depth of cut
    check = stock.verify_job(surface, replay, m.tolerance, scallop=m.scallop,
                             depth_of_cut={"finish": doc} if doc else None,
                             measure=getattr(m, "scallop_measure", "normal"))
    pictures = {}
    snaps = check.snapshots
    if len(snaps) == len(replay):
        rough = [i for i, op in enumerate(replay) if op.kind in _ROUGHING_KINDS]
        for after, i in (("rough", rough[-1] if rough else None), ("finish", len(replay) - 1)):
            if i is not None:
                title = "stock after " + ("roughing" if after == "rough" else "finishing")
                pictures[after] = stock.stock_png(snaps[i], check.design, title=title, tolerance=m.tolerance)
    return check, pictures


def run_job(spec, surface, *, machine=None, verify: bool = True,
            progress: Callable[[str], None] | None = None, program_path=None,
            generated: str | None = None) -> JobResult:
    """Plan, write, read back, verify and repair, estimate and sheet the toolpath of
    ``spec`` on ``surface`` (see the module docstring).

    ``machine``: a machine profile (:mod:`fabkit.machine.profile`) or None; with it the
    result carries the controller's run time and the checks (shown, not raised: the
    caller decides whether a refusal stops it). ``progress``: optional callable(str)
    told the stage that runs next. ``program_path``: the program's file name for the
    sheet (default ``<name>.ngc``). ``generated``: the sheet's ``generated_at``
    (default: now, or SOURCE_DATE_EPOCH)."""
    from .program.gcode import profile_from_spec, write_program
    from .finish.raster import plan_toolpath
    from .program.setup_sheet import setup_sheet
    from .program.reader import estimate_time, read_program

    say = progress or (lambda stage: None)
    say("planning the passes")
    t0 = time.perf_counter()
    toolpath = plan_toolpath(spec, surface)
    t_plan = time.perf_counter() - t0
    say("writing the program")
    t0 = time.perf_counter()
    profile = profile_from_spec(spec, surface)
    text = write_program(toolpath, profile)
    t_write = time.perf_counter() - t0
    t0 = time.perf_counter()
    program = read_program(text)
    cut = None
    if verify:
        say("verifying the cut")
        cache: dict = {}
        cut = verify_program(spec, surface, program, cache)
        toolpath, text, program, cut = repair(spec, surface, toolpath, profile, text, program, cut, cache)
    est = estimate_time(program, profile.rapid)
    t_verify = time.perf_counter() - t0
    run = mcheck = None
    axis = 0 if spec.machining.direction == "x" else 1
    if machine is not None:
        from ..machine.limits import check_program
        from ..machine.planner import run_time

        run = run_time(text, machine, program, raster_axis=axis)
        mcheck = check_program(program, text, machine, run)
    extra: dict = {}
    if has_roughing(spec):
        extra = _operations(spec, surface, toolpath, profile, text, program, machine, verify, axis, say)
        est = sum(f.estimate_s for f in extra["figures"])
        if machine is not None:
            mcheck = _machine_checks(extra["programs"], extra["parsed_programs"], machine, mcheck)
        t_plan += extra.pop("plan_seconds")         # the rough and rest operations' planning
        t_verify += extra.pop("seconds")            # writing, reading back, the whole job simulated

    say("setup sheet")
    t0 = time.perf_counter()
    timings = {"plan": t_plan, "write": t_write, "verify": t_verify}
    lines = sum(t.count("\n") for _, t in extra["programs"]) if extra else text.count("\n")
    sheet_program = job_path = program_path if program_path is not None else f"{spec.name}.ngc"
    if extra and len(extra["programs"]) > 1:        # grbl: the finishing program's own file
        from .program.setup_sheet import job_program_path

        sheet_program = job_program_path(sheet_program, extra["programs"][-1][0])
    needs = program if not extra else _merged(extra["readback_programs"])
    sheet = setup_sheet(spec, surface, toolpath, profile, sheet_program,
                        cut.as_dict() if cut is not None else None, est, lines,
                        timings=timings, generated_at=generated if generated is not None else generated_at(),
                        program=needs, machine=machine, run=run, machine_check=mcheck,
                        operations=extra.get("figures"), job_check=extra.get("job_check"), job_path=job_path)
    timings["sheet"] = time.perf_counter() - t0
    if extra:
        job_text = extra["programs"][-1][1]      # the program holding the finish
        return JobResult(spec=spec, surface=surface, toolpath=toolpath, profile=profile, text=job_text,
                         program=program, cut=cut, estimate_s=est, sheet=sheet, timings=timings, machine=machine,
                         run=run, machine_check=mcheck, operations=extra["operations"], figures=extra["figures"],
                         programs=extra["programs"], job_check=extra.get("job_check"),
                         stock_pictures=extra.get("stock_pictures", {}))
    return JobResult(spec=spec, surface=surface, toolpath=toolpath, profile=profile, text=text, program=program,
                     cut=cut, estimate_s=est, sheet=sheet, timings=timings, machine=machine, run=run,
                     machine_check=mcheck)


def _operations(spec, surface, toolpath, profile, text, program, machine, verify, axis, say) -> dict:
    """The roughing part of :func:`run_job`: plan the rough and rest operations against
    the (verified, repaired) finish, write every program, read each back, check that
    the finish's moves read back are the ones verified, figure each operation and, when
    the stock simulation is there, verify the whole job."""
    from ..errors import DesignError, SpecError
    from .program.gcode import write_job

    say("planning the roughing")
    t0 = time.perf_counter()
    ops = plan_job_operations(spec, surface, toolpath)
    t_plan = time.perf_counter() - t0
    if profile.d.tool_change is not None:
        missing = [op.kind for op in ops if op.tool.number is None]
        if missing:
            raise SpecError(f"a {profile.dialect} job with roughing changes tools with M6: every tool needs a "
                            f"number (none for the {', '.join(missing)} tool)", file=spec.path, key="tools")
    # the finish as written and read alone: its lines and its moves are the job's last
    # operation's (write_job and job_figures take them as they are where they are the same)
    programs = write_job(ops, profile, finish=(toolpath, text))
    parsed: list = []
    figures, readback = job_figures(ops, programs, profile, machine, raster_axis=axis, parsed=parsed,
                                    finish=(text, program))
    fin = readback[-1]
    # from the rapid across on: the first move (G0 Z<safe>) starts where the tool change left the tool
    if not (np.array_equal(fin.points[1:], program.points[1:], equal_nan=True)
            and np.array_equal(fin.kinds, program.kinds)):
        # the finish written into the job is not the program verified: never pass it off as verified
        raise DesignError("the finishing moves written into the job differ from the verified program")
    job_check, pictures = (None, {})
    if verify:
        say("verifying the whole job")
        job_check, pictures = _stock_verification(spec, surface, ops, readback)
    return {"operations": ops, "programs": programs, "figures": figures, "readback_programs": readback,
            "parsed_programs": parsed, "job_check": job_check, "stock_pictures": pictures, "plan_seconds": t_plan,
            "seconds": time.perf_counter() - t0 - t_plan}


def _merged(programs):
    """Every operation's moves read back, in order, as one Program (what the whole job
    asks of the machine)."""
    from .program.reader import Program

    return Program(start=programs[0].start, points=np.vstack([p.points for p in programs]),
                   kinds=np.concatenate([p.kinds for p in programs]),
                   feed=np.concatenate([p.feed for p in programs]),
                   line=np.concatenate([p.line for p in programs]), units=programs[0].units,
                   lines=sum(p.lines for p in programs))


def _machine_checks(programs, parsed, machine, finish_check):
    """The machine's checks over every program of the job, merged into one verdict.

    ``parsed``: :func:`job_figures`' parse of each program's very text (its ``parsed``),
    used as it is, not parsed again (read here when not one per program)."""
    from ..machine.limits import MachineCheck, check_program
    from .program.reader import read_program

    merged = MachineCheck(machine=finish_check.machine, travel=dict(finish_check.travel))
    known = parsed is not None and len(parsed) == len(programs)
    for i, (suffix, text) in enumerate(programs):
        prog = parsed[i] if known else read_program(text)
        chk = check_program(prog, text, machine, name=suffix if len(programs) > 1 else None)
        merged.refusals += [r for r in chk.refusals if r not in merged.refusals]
        merged.warnings += [w for w in chk.warnings if w not in merged.warnings]
        for ax, (span, avail) in chk.travel.items():
            if span > merged.travel.get(ax, (0.0, avail))[0]:
                merged.travel[ax] = (span, avail)
    return merged
