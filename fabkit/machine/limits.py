"""Checks before cutting: the program (read back from its text) against the machine.

Refused (exit 2, nothing written): travel beyond the machine's on an axis, a spindle
speed outside the machine's range, a tool change on a machine without one. Warned:
a feed above what the axis rates allow along a move (the controller clips it; the
warning gives the time it costs, from the planner's run time).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError

#: relative slack on comparisons (rounding of the program's numbers)
SLACK = 1e-9
_S_WORD = re.compile(r"S\s*([-+]?(?:\d+\.?\d*|\.\d+))")
#: the G and M words grbl 1.1 accepts (doc/markdown/commands.md); others are error:20
GRBL_WORDS = frozenset({"G0", "G1", "G2", "G3", "G4", "G10", "G17", "G18", "G19", "G20", "G21", "G28", "G30",
                        "G38.2", "G38.3", "G38.4", "G38.5", "G40", "G43.1", "G49", "G53", "G54", "G55", "G56",
                        "G57", "G58", "G59", "G61", "G80", "G90", "G91", "G91.1", "G92", "G92.1", "G93", "G94",
                        "M0", "M1", "M2", "M3", "M4", "M5", "M7", "M8", "M9", "M30", "M56"})
_GM_WORD = re.compile(r"([GM])\s*([0-9]+(?:\.[0-9]*)?)")
_COMMENTS = re.compile(r"\([^()\n]*\)|;[^\n]*")


def _num(v: str) -> str:
    """'01' -> '1', '38.20' -> '38.2' (as used_words names them)."""
    f = float(v)
    return str(int(f)) if f.is_integer() else f"{f:g}"


@dataclass
class MachineCheck:
    """The verdict of the checks: ``refusals`` make the command exit 2; ``warnings`` are printed."""

    machine: str
    refusals: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    travel: dict = field(default_factory=dict)          # axis -> [program span, machine travel] mm

    @property
    def ok(self) -> bool:
        return not self.refusals

    def to_json(self) -> dict:
        return {"machine": self.machine, "ok": self.ok, "refusals": list(self.refusals),
                "warnings": list(self.warnings),
                "travel_mm": {ax: [round(a, 4), round(b, 4)] for ax, (a, b) in self.travel.items()}}

    def summary(self) -> str:
        """One line: the travel used against the machine's, and the warnings' count."""
        t = ", ".join(f"{ax.upper()} {a:.4g}/{b:g}" for ax, (a, b) in self.travel.items())
        w = f"; {len(self.warnings)} warning(s)" if self.warnings else ""
        return f"checked against {self.machine}: travel used/available {t} mm" + \
            ("" if self.ok else "; REFUSED") + w

    def raise_if_refused(self, file: str | None = None) -> None:
        if self.refusals:
            raise SpecError("the machine cannot run this program: " + "; ".join(self.refusals), file=file,
                            key="machine")


def travel_refusals(span: dict, machine) -> list[str]:
    """Axes whose program span (mm) exceeds the machine's travel."""
    out = []
    for i, ax in enumerate("xyz"):
        need = span.get(ax)
        have = float(machine.travel[i])
        if need is not None and need > have * (1 + SLACK) + 1e-9:
            out.append(f"{ax.upper()} travel: the program spans {need:.4g} mm, the machine travels {have:g} mm")
    return out


def spindle_refusals(rpm: float | None, machine) -> list[str]:
    if rpm is None or machine.spindle is None or rpm <= 0:
        return []
    lo, hi = machine.spindle
    if rpm > hi * (1 + SLACK) or rpm < lo * (1 - SLACK):
        return [f"spindle {rpm:g} rpm is outside the machine's range {lo:g}-{hi:g} rpm"]
    return []


def precheck(spec, surface, machine) -> MachineCheck:
    """What is known before planning: the stock footprint against X and Y travel, the
    spindle speed, and a tool call on a machine without a tool changer."""
    chk = MachineCheck(machine=machine.name or machine.controller)
    L, W = surface.stock_size_mm
    chk.refusals += [r.replace("the program spans", "the block spans") for r in travel_refusals({"x": L, "y": W}, machine)]
    chk.refusals += spindle_refusals(spec.machining.spindle, machine)
    if machine.controller == "grbl" and spec.machining.dialect != "grbl":
        chk.refusals.append(f"machining.dialect is {spec.machining.dialect}, the machine runs grbl (it rejects "
                            "G64, G43 and M6): set machining.dialect: grbl")
    if spec.tool.number is not None and spec.machining.dialect == "linuxcnc" and not machine.tool_changer:
        chk.refusals.append(f"the program changes to tool T{spec.tool.number} (M6), the machine has no tool changer "
                            "(remove tool.number or set machine.tool_changer: true for a manual change)")
    return chk


def check_program(program, text: str, machine, run=None, name: str | None = None) -> MachineCheck:
    """The program read back (``program``, mm) and its ``text`` against ``machine``;
    ``run``: its :class:`fabkit.machine.planner.RunTime` (for the cost of clipped feeds:
    planned here when not given); ``name``: the program's name in a multi-program job,
    for the warnings."""
    chk = MachineCheck(machine=machine.name or machine.controller)
    pts = np.vstack([program.start[None, :], program.points]) if len(program) else program.start[None, :]
    span = {}
    for i, ax in enumerate("xyz"):
        col = pts[:, i][np.isfinite(pts[:, i])]
        span[ax] = float(col.max() - col.min()) if col.size else 0.0
        chk.travel[ax] = (span[ax], float(machine.travel[i]))
    chk.refusals += travel_refusals(span, machine)
    clean = _COMMENTS.sub(" ", text.upper())
    words = {f"{g}{_num(v)}" for g, v in _GM_WORD.findall(clean)}
    for rpm in sorted({float(v) for v in _S_WORD.findall(clean)}):
        chk.refusals += spindle_refusals(rpm, machine)
    if not machine.tool_changer and "M6" in words:
        chk.refusals.append("the program calls M6 (tool change), the machine has no tool changer")
    if machine.controller == "grbl":
        foreign = sorted(w for w in words if w not in GRBL_WORDS and w != "M6")
        if foreign:
            chk.refusals.append(f"the program uses {', '.join(foreign)}, which grbl 1.1 does not accept "
                                "(error:20): write it with machining.dialect: grbl")
    feeds = program.kinds == 1
    if feeds.any():
        a, b = program.segments()
        d = np.nan_to_num(b[feeds] - a[feeds])
        length = np.linalg.norm(d, axis=1)
        moving = length > 0
        u = d[moving] / length[moving, None]
        rate = np.asarray(machine.max_rate, dtype=float)
        with np.errstate(divide="ignore"):
            cap = np.min(np.where(u != 0, rate[None, :] / np.abs(u), np.inf), axis=1)
        if getattr(machine, "max_velocity", None):
            cap = np.minimum(cap, machine.max_velocity)
        f = program.feed[feeds][moving]
        over = f > cap * (1 + SLACK)
        if over.any():
            share = float(length[moving][over].sum() / length[moving].sum())
            if run is None:
                from .planner import run_time

                try:
                    run = run_time(text, machine)
                except SpecError:           # words the controller refuses: refused above, no time
                    run = None
            cost = (f" (+{run.lost_rate_s:.0f} s of run time: the planner with these rates and with the rates "
                    "raised to the programmed feed)") if run is not None else ""
            who = f"the {name.lstrip('.')} program: " if name else ""
            chk.warnings.append(f"{who}feed up to F{f[over].max():g} mm/min is above the machine's rates along "
                                f"{100 * share:.0f} % of the cut length (axis rates X/Y/Z "
                                f"{'/'.join(f'{v:g}' for v in machine.max_rate)} mm/min): the controller runs "
                                f"those moves slower{cost}")
    return chk
