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
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from typing import Callable

import numpy as np

__all__ = ["REPAIR_ROUNDS", "CutReport", "JobResult", "run_job", "verify_program", "repair", "generated_at"]

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
    :func:`fabkit.toolpath.verify.verify_cut` measures, typed. ``to_json()`` gives the
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
    from .raster import scallop_normal
    from .verify import verify_cut

    m = spec.machining
    return CutReport.from_dict(verify_cut(surface, program, spec.tool.diameter / 2.0, m.verify_points,
                                          depth_limit=spec.stock.depth_limit, reach=spec.tool.reach,
                                          unreachable_min=m.tolerance, normal=scallop_normal(spec),
                                          over=m.scallop + m.tolerance, cache=cache, along=m.direction))


def repair(spec, surface, toolpath, profile, text, program, cut: CutReport, cache: dict | None = None):
    """Where the cut leaves more than scallop + tolerance (and nothing else is wrong),
    add passes there and verify again (at most REPAIR_ROUNDS times, kept only if it
    leaves less and gouges no more). Returns (toolpath, text, program, cut) to write."""
    from .gcode import write_program
    from .raster import add_passes
    from .verify import read_program

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
    profile). ``timings``: wall seconds of plan, write, verify, sheet."""

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

    @property
    def lines(self) -> int:
        return self.text.count("\n")

    @property
    def verified(self) -> bool:
        return self.cut is not None

    @property
    def failures(self) -> list[str]:
        """The failed acceptance checks (empty: the cut is good, or it was not verified)."""
        return self.cut.failures(self.spec.machining) if self.cut is not None else []

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
        from .setup import preview_png

        L, W = self.surface.stock_size_mm
        return preview_png(self.program, L, W, self.profile.units)


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
    from .gcode import profile_from_spec, write_program
    from .raster import plan_toolpath
    from .setup import setup_sheet
    from .verify import estimate_time, read_program

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
    if machine is not None:
        from ..machine.limits import check_program
        from ..machine.planner import run_time

        run = run_time(text, machine, program, raster_axis=0 if spec.machining.direction == "x" else 1)
        mcheck = check_program(program, text, machine, run)

    say("setup sheet")
    t0 = time.perf_counter()
    timings = {"plan": t_plan, "write": t_write, "verify": t_verify}
    sheet = setup_sheet(spec, surface, toolpath, profile,
                        program_path if program_path is not None else f"{spec.name}.ngc",
                        cut.as_dict() if cut is not None else None, est, text.count("\n"),
                        timings=timings, generated_at=generated if generated is not None else generated_at(),
                        program=program, machine=machine, run=run, machine_check=mcheck)
    timings["sheet"] = time.perf_counter() - t0
    return JobResult(spec=spec, surface=surface, toolpath=toolpath, profile=profile, text=text, program=program,
                     cut=cut, estimate_s=est, sheet=sheet, timings=timings, machine=machine, run=run,
                     machine_check=mcheck)
