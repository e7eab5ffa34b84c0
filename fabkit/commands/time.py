"""``fabkit time PROGRAM [--machine PROFILE] [--json]``: the run time the controller
really takes for any grbl or LinuxCNC program (from fabkit or from another CAM tool,
or written by hand), its motion planner simulated on the program as the controller
reads it (:mod:`fabkit.machine.program`, :mod:`fabkit.machine.planner`).

The summary and ``--json`` give the total, the breakdown (feeds, plunges, rapids,
dwells), the length/feed figure, where the feed is capped (by the axis rates, with the
cap's cost from the planner, and by acceleration, with the runs of lines that lose the
most) and the buffer syncs. Without ``--machine`` the shipped ``grbl`` profile (grbl
1.1h's defaults) is used and the summary says so. Exit 2 (one line naming the file and
line) on a word the reader does not support or a bad profile.
"""

from __future__ import annotations

from ._common import emit, warn

#: the largest program read (bytes)
MAX_PROGRAM_BYTES = 512 * 1024 * 1024


def run(args) -> int:
    from ..errors import SpecError
    from ..io import read_regular, text_of
    from ..machine.planner import _hm, run_time
    from ..machine.profile import grbl_defaults, resolve_machine, safe_name
    from ..machine.program import read_moves

    machine = resolve_machine(args.machine) if args.machine else grbl_defaults()
    p = str(args.program)
    text = text_of(read_regular(p, MAX_PROGRAM_BYTES, "program"), p, MAX_PROGRAM_BYTES)
    if text.startswith("\ufeff"):
        text = text[1:]
    try:
        moves = read_moves(text, machine.controller, machine.arc_tolerance, file=p)
    except SpecError as exc:
        if args.machine or "grbl 1.1" not in exc.detail:
            raise
        raise SpecError(exc.detail + "; without --machine the program is timed on grbl 1.1h's defaults: for a "
                        "LinuxCNC program give its INI or --machine linuxcnc-mill", file=exc.file) from None
    rt = run_time(None, machine, moves=moves)
    who = machine.name or machine.controller
    default = "" if args.machine else " (no --machine: grbl 1.1h's defaults)"
    total = f"{_hm(rt.total_s)} ({rt.total_s:.1f} s)" if rt.total_s >= 60 else f"{rt.total_s:.1f} s"
    lines = [f"time: {safe_name(p)} on {who}{default}: {total}",
             rt.summary(),
             f"program: {moves.lines} lines, {len(moves)} moves ({rt.blocks} planner blocks), "
             f"{moves.arcs} arcs ({moves.arc_segments} lines), {moves.dwells} dwells ({moves.dwell_s:.2f} s), "
             f"{moves.syncs} buffer syncs; units {moves.units}"]
    for r in rt.regions[:3]:
        lines.append(f"  slowest by acceleration: lines {r.first_line}-{r.last_line} at X{r.at[0]:.2f} "
                     f"Y{r.at[1]:.2f}: feed {r.feed:.0f} mm/min, mean {r.speed:.0f} mm/min, +{r.lost_s:.1f} s")
    lines.append(f"model: {rt.model}")
    for w in moves.warnings:
        warn(f"{safe_name(p)}: {w}")
    payload = {"program": p, "machine": {**machine.to_dict(), "source": machine.source},
               "lines": moves.lines, "moves": len(moves), "units": moves.units, "arcs": moves.arcs,
               "dwells": moves.dwells, "warnings": list(moves.warnings), **rt.to_json()}
    payload["machine_name"] = who
    emit(lines, payload, args.json)
    return 0
