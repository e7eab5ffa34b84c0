"""The setup sheet written beside a program: ``<stem>.setup.json`` (machine-readable),
``<stem>.setup.md`` (for the operator) and ``<stem>.preview.png`` (top view of the
passes coloured by depth).

ALL lengths in the sheet are in the PROGRAM's units (mm or inch); times in
seconds. The transform maps design coordinates to the program's coordinates::

    work = scale * design + offset      (per axis)
    scale  = [s, s, s],  s = design-unit length in program units
    offset = [-x0 * s, -y0 * s, -top * s]

The only timestamp fabkit writes anywhere is ``generated_at`` here (programs and
meshes carry none, so they are byte-identical run to run).
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import numpy as np

from ... import __version__

from ...units import MM_PER_INCH

#: grbl 1.1's default settings, for comparison on the sheet: $110-$112 max rate
#: (mm/min), $30 max spindle speed (rpm), $130-$132 max travel (mm)
GRBL_DEFAULTS = {"max_rate_mm_min": 500.0, "spindle_max_rpm": 1000.0, "max_travel_mm": 200.0}


def machine_needs(program, spindle_rpm: float) -> dict:
    """What ``program`` (read back from its text, work mm) asks of the machine, in mm:
    ``feed_max`` (largest programmed F), ``plunge_max`` (largest F of a straight-down
    G1; None when there is none), ``axis_rate_max`` {x, y, z} (largest speed along
    each axis in a G1 move, F * |d_axis| / length: what the axis rates $110-$112 or
    MAX_VELOCITY must allow), ``travel`` {x, y, z} (max - min over every position the
    program visits, rapids and park included), ``extent`` {x, y, z: [min, max]},
    ``spindle_rpm``. Rapids run at the machine's own rate, so they set no need here."""
    a, b = program.segments()
    feed = program.kinds == 1
    out: dict = {"feed_max": None, "plunge_max": None, "axis_rate_max": {"x": None, "y": None, "z": None}}
    if feed.any():
        d = np.abs(np.nan_to_num(b[feed] - a[feed]))
        length = np.linalg.norm(d, axis=1)
        f = program.feed[feed]
        moving = length > 0
        out["feed_max"] = float(np.max(f))
        down = moving & (d[:, 0] + d[:, 1] <= 1e-12) & ((b[feed] - a[feed])[:, 2] < 0)
        out["plunge_max"] = float(np.max(f[down])) if down.any() else None
        if moving.any():
            rate = f[moving, None] * d[moving] / length[moving, None]
            out["axis_rate_max"] = {ax: float(rate[:, i].max()) for i, ax in enumerate("xyz")}
    pts = np.vstack([program.start[None, :], program.points]) if len(program.points) else program.start[None, :]
    ext, travel = {}, {}
    for i, ax in enumerate("xyz"):
        col = pts[:, i][np.isfinite(pts[:, i])]
        ext[ax] = [float(col.min()), float(col.max())] if col.size else None
        travel[ax] = float(col.max() - col.min()) if col.size else 0.0
    out.update(travel=travel, extent=ext, spindle_rpm=float(spindle_rpm))
    return out


def sheet_paths(program_path) -> dict:
    """{'json', 'md', 'png'}: the setup files beside ``program_path`` (same stem)."""
    p = Path(program_path)
    stem = p.with_suffix("") if p.suffix else p
    return {"json": Path(f"{stem}.setup.json"), "md": Path(f"{stem}.setup.md"),
            "png": Path(f"{stem}.preview.png")}


def job_program_path(program_path, suffix: str) -> Path:
    """The file of one program of a job: ``program_path`` itself for suffix "", else the
    stem with the suffix (``<stem>.1-rough.nc``)."""
    p = Path(program_path)
    if not suffix:
        return p
    stem = p.with_suffix("") if p.suffix else p
    return Path(f"{stem}{suffix}")


def job_program_paths_possible(program_path, dialect: str) -> list[Path]:
    """Every program file besides ``program_path`` a job with roughing may write for
    ``dialect`` (to check them before planning): none with a tool change (one program),
    else (grbl) one per operation."""
    from .gcode import DIALECTS
    from ..operations import OPERATION_KINDS

    if DIALECTS[dialect].tool_change is not None:
        return []
    return [job_program_path(program_path, f".{i}-{kind}.nc")
            for i in range(1, 6) for kind in OPERATION_KINDS]


def stock_paths(program_path) -> dict:
    """{'rough', 'finish'}: the shaded stock pictures beside ``program_path``."""
    p = Path(program_path)
    stem = p.with_suffix("") if p.suffix else p
    return {after: Path(f"{stem}.stock-{after}.png") for after in ("rough", "finish")}


def _operations_keys(figures, program_path, dialect: str, k: float, job_check) -> dict:
    """The sheet's keys of a job with roughing: ``operations`` (one per operation: tool,
    levels, passes, leave, program file, lines, time and its estimator), ``programs``
    (the files in the order they run), ``steps`` (what the operator does, per tool) and
    ``job_verification`` (the whole job simulated on the stock, when there is one)."""
    ops = []
    for f in figures:
        d = f.to_json(k)
        d["program"] = job_program_path(program_path, f.program).name
        ops.append(d)
    files = list(dict.fromkeys(o["program"] for o in ops))
    steps = []
    loaded = None
    # per tool, in the order the job loads it: its number, the operations and programs it
    # cuts, how its length is known (LinuxCNC: the tool table's offset H<n> applied by G43
    # after T<n> M6; grbl, no tool table: touched off Z0 on the top face by hand)
    tools: dict = {}
    for o in ops:
        t = o["tool"]
        key = t["number"] if t["number"] is not None else (t["shape"], t["diameter"])
        if key not in tools:
            n = t["number"]
            tools[key] = {"number": n, "shape": t["shape"], "diameter": t["diameter"],
                          "operations": [], "programs": [],
                          "tool_call": (f"T{n} M6 G43 H{n}" if dialect == "linuxcnc" and n is not None else None),
                          "length_offset": (f"H{n}" if dialect == "linuxcnc" and n is not None else None),
                          "touch_off": ("measure its length into the tool table (tool "
                                        f"{n}, offset H{n}) from the same top face (Z0)" if dialect == "linuxcnc"
                                        else "touch off Z0 on the same top face after loading it by hand "
                                             "(grbl has no tool table: the touch-off is its length)")}
        tools[key]["operations"].append(o["kind"])
        if o["program"] not in tools[key]["programs"]:
            tools[key]["programs"].append(o["program"])
    for i, o in enumerate(ops, start=1):
        t = o["tool"]
        tool = (f"T{t['number']} " if t["number"] is not None else "") + _TOOL_NAMES[t["shape"]] + \
            f" {t['diameter']:g}"
        same, loaded = t["number"] is not None and t["number"] == loaded, t["number"]
        if same:
            steps.append(f"{o['kind']}: keep {tool} (no change)"
                         + (f", run {o['program']}" if len(files) > 1 else ""))
        elif len(files) == 1:
            n = t["number"]
            steps.append(f"{o['kind']}: {tool}: measure its length into the tool table as tool {n} (offset "
                         f"H{n}) from the same top face (Z0); the program loads it with T{n} M6 and applies "
                         f"its length with G43 H{n}")
        else:
            steps.append(f"{o['kind']}: load {tool} by hand, touch off Z0 on the same top face, run "
                         f"{o['program']}")
    if len(files) == 1:
        steps.append(f"run {files[0]}: it stops for each tool change (M6)")
    out = {"operations": ops, "programs": files, "steps": steps, "tools_loaded": list(tools.values())}
    if job_check is not None:
        to_json = getattr(job_check, "to_json", None)
        jv = to_json() if callable(to_json) else None
        if isinstance(jv, dict):
            jv = {key: v for key, v in jv.items() if key != "seconds"}     # wall time: in timings_s
        out["job_verification"] = _plain(jv)
        out["left_for_next"] = _left_for_next(ops, jv, k)
    return out


def _left_for_next(ops: list, jv, k: float) -> list:
    """Where an operation left material above its allowance's bound, from the whole
    job's stock check (``jv``: its JSON): where its tool could not reach (the next
    operation takes what is left) and where it reaches but did not hold the bound (out of
    bounds). One entry per such operation: ``operation``, ``tool`` (its number),
    ``kind`` (``unreachable`` | ``over``), ``area`` (program units^2), ``largest`` (above
    the bound, program units), ``at`` ([x, y] of the largest, program units, work zero),
    ``taken_by`` (the next operation's kind and tool number, None after the last)."""
    if not isinstance(jv, dict):
        return []
    cut = jv.get("operations") or []
    out = []
    for i, (o, c) in enumerate(zip(ops, cut)):
        nxt = ops[i + 1] if i + 1 < len(ops) else None
        for kind, area, largest, at in (("unreachable", "unreachable_area", "unreachable", "unreachable_at"),
                                        ("over", "over_area", "over_reachable", "over_at")):
            a = c.get(area) or 0.0
            if a <= 0.0 or c.get(at) is None:
                continue
            out.append({"operation": o["kind"], "tool": o["tool"]["number"], "kind": kind,
                        "area": _r(float(a) * k * k, 6), "largest": _r(float(c[largest]) * k, 6),
                        "at": [_r(float(v) * k, 6) for v in c[at]],
                        "taken_by": ({"operation": nxt["kind"], "tool": nxt["tool"]["number"]}
                                     if nxt is not None else None)})
    return out


_TOOL_NAMES = {"flat": "flat end mill", "bull": "bull nose", "ball": "ball-end mill"}


def _plain(v):
    """JSON-ready (the sheet is written with allow_nan=False): numpy to Python, tuples to
    lists, non-finite floats to None."""
    if isinstance(v, dict):
        return {str(key): _plain(x) for key, x in v.items()}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def _r(v, nd=9):
    """Round for the sheet (floats to ``nd`` significant digits); None for non-finite."""
    if v is None:
        return None
    v = float(v)
    if not math.isfinite(v):
        return None
    return float(f"{v:.{nd}g}") if v != 0 else 0.0


def setup_sheet(spec, surface, toolpath, profile, program_path, check: dict | None,
                estimated_time_s: float, lines: int, timings: dict | None = None,
                generated_at: str | None = None, program=None, machine=None, run=None,
                machine_check=None, operations=None, job_check=None, job_path=None) -> dict:
    """The setup sheet as a dict (JSON-ready). ``check``: the result of
    :func:`fabkit.toolpath.cut.verify.verify_cut` (work mm) or None when not verified.
    ``program``: the program read back (:func:`fabkit.toolpath.program.reader.read_program`);
    with it the sheet states what the program needs from the machine
    (``machine_needs``, program units; ``grbl_defaults`` in mm for comparison)."""
    k = 1.0 / (MM_PER_INCH if profile.units == "in" else 1.0)   # mm -> program units
    s = spec.scale * k                                           # design unit -> program units
    x0, y0, top = surface.x_range[0], surface.y_range[0], surface.top
    L, W = surface.stock_size_mm
    T = spec.stock.thickness
    m = spec.machining
    sheet = {
        "program": Path(program_path).name,
        "units": profile.units,
        "dialect": profile.dialect,
        "spec": spec.path,
        "name": spec.name,
        "fabkit_version": __version__,
        "work_zero": "X0 Y0 at the footprint corner of smallest x, y; Z0 on the stock top face",
        "stock": {"min": [0.0, 0.0, _r(-T * k)], "max": [_r(L * k), _r(W * k), 0.0]},
        "tool": {"shape": spec.tool.shape, "diameter": _r(spec.tool.diameter * k),
                 "reach": _r(spec.tool.reach * k)},
        "design_to_work": {"design_units": spec.units, "scale": [_r(s, 12)] * 3,
                           "offset": [_r(-x0 * s, 12), _r(-y0 * s, 12), _r(-top * s, 12)]},
        "passes": int(toolpath.passes),
        "passes_added_after_verification": int(toolpath.info.get("passes_added_after_verification", 0)),
        "stepover": _r(toolpath.stepover * k),
        "stepover_min": _r(toolpath.stepover_min * k),
        "edge_pass_gap": _r(toolpath.info.get("edge_pass_gap_max", 0.0) * k),
        "direction": m.direction,
        "scallop": _r(m.scallop * k),
        "scallop_measure": getattr(m, "scallop_measure", "normal"),
        "tolerance": _r(m.tolerance * k),
        "feed": _r(profile.feed * k),
        "plunge": _r(profile.plunge * k),
        "spindle_rpm": _r(profile.spindle),
        "safe_z": _r(profile.safe_z * k),
        "rapid_rate_assumed": _r(profile.rapid * k),
        "depth": _r(check["deepest_cut"] * k) if check else None,
        "depth_limit": _r(spec.stock.depth_limit * k),
        "estimated_time_s": round(float(estimated_time_s), 1),
        "lines": int(lines),
        "verified": check is not None,
        "max_gouge": _r(check["max_gouge"] * k) if check else None,
        "max_material_left": _r(check["max_material_left"] * k) if check else None,
        "verification_points": int(check["checked_points"]) if check else 0,
    }
    if check:
        sheet["gouge_at"] = [_r(v * k) for v in check["gouge_at"]]
        sheet["material_left_at"] = [_r(v * k) for v in check["material_at"]]
        for meas in ("normal", "vertical"):
            if f"max_material_left_{meas}" in check:
                sheet[f"max_material_left_{meas}"] = _r(check[f"max_material_left_{meas}"] * k)
        sheet["rapid_clearance"] = _r(check["rapid_clearance"] * k)
        if "max_material_above_design" in check:
            sheet["max_material_above_design"] = _r(check["max_material_above_design"] * k)
        un = check.get("unreachable")
        sheet["material_left_unreachable"] = None if not un else {
            "height": _r(un["height"] * k), "at": [_r(v * k) for v in un["at"]],
            "area": _r(un["area"] * k * k)}
    if program is not None:
        rpm = max([profile.spindle] + [f.spindle for f in operations or []])
        need = machine_needs(program, rpm)
        axes = need["axis_rate_max"]
        sheet["tool_number"] = getattr(spec.tool, "number", None)
        sheet["park"] = [_r(v * k) for v in profile.park]
        sheet["machine_needs"] = {
            "feed_max": _r(need["feed_max"] * k) if need["feed_max"] is not None else None,
            "plunge_max": _r(need["plunge_max"] * k) if need["plunge_max"] is not None else None,
            "axis_rate_max": {ax: _r(v * k) if v is not None else None for ax, v in axes.items()},
            "travel": {ax: _r(v * k) for ax, v in need["travel"].items()},
            "extent": {ax: [_r(v * k) for v in e] if e else None for ax, e in need["extent"].items()},
            "spindle_rpm": _r(need["spindle_rpm"]),
        }
        sheet["grbl_defaults"] = dict(GRBL_DEFAULTS)
    if machine is not None:
        sheet.update(_machine_keys(machine, run, machine_check, k))
        if sheet.get("machine_needs"):
            sheet["machine_comparison"] = machine_comparison(sheet["machine_needs"], sheet["machine"], k)
    if operations:
        sheet.update(_operations_keys(operations, job_path if job_path is not None else program_path,
                                      profile.dialect, k, job_check))
    if timings:
        sheet["timings_s"] = {key: round(float(v), 3) for key, v in timings.items()}
    if generated_at:
        sheet["generated_at"] = generated_at
    return sheet


def _machine_keys(machine, run, machine_check, k: float) -> dict:
    """The sheet's keys for a machine profile: ``machine`` (the profile, in its own
    units: mm, mm/min, mm/s^2), ``run_time`` (the controller's planner simulated:
    seconds; feeds and positions in program units) and ``machine_check``."""
    out = {"machine": {**machine.to_dict(), "source": machine.source}}
    if run is not None:
        rt = run.to_json()
        for r in rt["capped_regions"]:
            r["at"] = [_r(v * k) for v in r["at"]]
            r["feed"], r["mean_speed"] = _r(r["feed"] * k), _r(r["mean_speed"] * k)
        out["run_time"] = rt
    if machine_check is not None:
        out["machine_check"] = machine_check.to_json()
    return out


def _run_markdown(sheet: dict) -> list[str]:
    """The 'Run time on this machine' section (empty without a machine profile)."""
    rt = sheet.get("run_time")
    if not rt:
        return []
    u = sheet["units"]
    lines = ["## Run time on this machine", "",
             f"- Machine: {rt['machine']} ({rt['controller']}; {rt['model']})",
             f"- Run time {_hms(rt['total_s'])} ({rt['total_s']:g} s): feeds {rt['feed_s']:g} s, "
             f"plunges {rt['plunge_s']:g} s, rapids {rt['rapid_s']:g} s",
             f"- Length/feed estimate of the same moves (no acceleration): {_hms(rt['length_over_feed_s'])} "
             f"({rt['length_over_feed_s']:g} s)"]
    if sheet.get("operations"):
        lines.insert(3, "- These figures are the finishing program's; every operation's time is in the "
                        "Operations table")
    pp = rt.get("per_pass")
    if pp:
        lines.append(f"- {pp['passes']} passes: {pp['median_s']:g} s each (median; {pp['min_s']:g} to {pp['max_s']:g} s, "
                     f"the longest at lines {pp['slowest_lines'][0]}-{pp['slowest_lines'][1]}); "
                     f"length/feed {pp['median_length_over_feed_s']:g} s")
    if rt["feed_capped_fraction"] > 0:
        lines.append(f"- The controller keeps the feed below F on {100 * rt['feed_capped_fraction']:.0f} % of the "
                     f"cut length: the axis rates on {100 * rt['feed_capped_by_rates_fraction']:.0f} % "
                     f"(+{rt['time_lost_to_axis_rates_s']:g} s), acceleration (look-ahead, corners) on "
                     f"{100 * rt['feed_capped_by_acceleration_fraction']:.0f} % "
                     f"(+{rt['time_lost_to_acceleration_s']:g} s); where acceleration costs most:")
        for r in rt["capped_regions"]:
            lines.append(f"  - lines {r['lines'][0]}-{r['lines'][1]} from X{r['at'][0]:g} Y{r['at'][1]:g}: "
                         f"F{r['feed']:g} runs at {r['mean_speed']:g} {u}/min on average "
                         f"(+{r['time_lost_s']:g} s)")
    for w in sheet.get("machine_check", {}).get("warnings", []):
        lines.append(f"- Warning: {w}")
    return lines + [""]


def sheet_json(sheet: dict) -> str:
    return json.dumps(sheet, indent=2, allow_nan=False) + "\n"


def _hms(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60:02d} min" if m >= 60 else f"{m} min"


def _needs_markdown(sheet: dict) -> list[str]:
    """The 'What the machine must do' section (empty without ``machine_needs``)."""
    need = sheet.get("machine_needs")
    if not need:
        return []
    u = sheet["units"]
    k = MM_PER_INCH if u == "in" else 1.0     # program units -> mm, for the comparison
    g = sheet.get("grbl_defaults", GRBL_DEFAULTS)
    mach = sheet.get("machine")
    if mach:
        return _needs_vs_machine(sheet, need, mach, u, k)

    def cmp(v_mm, limit_mm):
        return " (above grbl's default)" if v_mm is not None and v_mm > limit_mm * (1 + 1e-9) else ""

    def f(v, per=""):
        """A need in program units, with its mm figure for an inch program."""
        if v is None:
            return "none"
        return f"{v:g} {u}{per}" + (f" ({v * k:.4g} mm{per})" if u != "mm" else "")

    rates, travel = need["axis_rate_max"], need["travel"]
    top_rate = max((v for v in rates.values() if v is not None), default=None)
    lines = ["## What the machine must do", "",
             "Compare with the machine's settings before running (grbl: `$$`; LinuxCNC: the INI's "
             "MAX_VELOCITY and axis limits).", "",
             f"- Largest feed F {f(need['feed_max'], '/min')}"
             f"{cmp(need['feed_max'] and need['feed_max'] * k, g['max_rate_mm_min'])}; "
             f"largest plunge F {f(need['plunge_max'], '/min')}",
             f"- Largest axis speed in a feed move: X {f(rates['x'], '/min')}, Y {f(rates['y'], '/min')}, "
             f"Z {f(rates['z'], '/min')}{cmp(top_rate and top_rate * k, g['max_rate_mm_min'])}",
             f"- Travel: X {f(travel['x'])}, Y {f(travel['y'])}, Z {f(travel['z'])}"
             + cmp(max(travel.values()) * k, g["max_travel_mm"]),
             f"- Spindle {need['spindle_rpm']:g} rpm{cmp(need['spindle_rpm'], g['spindle_max_rpm'])}",
             f"- Program ends parked at X{sheet['park'][0]:g} Y{sheet['park'][1]:g} at the safe height",
             "",
             f"grbl 1.1's defaults for comparison: max rates $110-$112 {g['max_rate_mm_min']:g} mm/min, "
             f"max spindle $30 {g['spindle_max_rpm']:g} rpm, max travel $130-$132 {g['max_travel_mm']:g} mm.",
             ""]
    lines[4:4] = _tool_lines(sheet)
    return lines


def machine_comparison(need: dict, machine: dict, k: float) -> dict:
    """Every need of the program (program units; ``k`` mm per unit) against the machine
    given (its profile in mm): ``{item: {"need", "machine", "ok"}}`` in mm (rpm for the
    spindle). Feeds above the axis rates are not refused (the controller runs them
    slower): ``ok`` false there means slower than programmed."""
    rates = machine["max_rate"]
    out: dict = {}
    feed = need.get("feed_max")
    vmax = machine.get("max_velocity")
    if feed is not None:
        lim = min(rates[:2]) if vmax is None else min(min(rates[:2]), vmax)
        out["feed"] = {"need": _r(feed * k), "machine": _r(lim), "ok": feed * k <= lim * (1 + 1e-9)}
    for i, ax in enumerate("xyz"):
        v = need["axis_rate_max"].get(ax)
        if v is not None:
            out[f"axis_rate_{ax}"] = {"need": _r(v * k), "machine": _r(rates[i]), "ok": v * k <= rates[i] * (1 + 1e-9)}
    for i, ax in enumerate("xyz"):
        t = need["travel"][ax] * k
        have = machine["travel"][i]
        out[f"travel_{ax}"] = {"need": _r(t), "machine": _r(have), "ok": t <= have * (1 + 1e-9) + 1e-9}
    sp = machine.get("spindle")
    rpm = need.get("spindle_rpm")
    if sp is not None and rpm:
        out["spindle"] = {"need": _r(rpm), "machine": [_r(sp[0]), _r(sp[1])],
                          "ok": sp[0] * (1 - 1e-9) <= rpm <= sp[1] * (1 + 1e-9)}
    return out


def _needs_vs_machine(sheet: dict, need: dict, mach: dict, u: str, k: float) -> list[str]:
    """'What the machine must do', each need against the machine given (in mm)."""
    cmpd = sheet.get("machine_comparison") or machine_comparison(need, mach, k)
    name = mach.get("name") or mach.get("controller")

    def row(label, key, unit, note_bad):
        c = cmpd.get(key)
        if c is None:
            return None
        have = c["machine"]
        have_s = f"{have[0]:g}-{have[1]:g}" if isinstance(have, list) else f"{have:g}"
        verdict = "ok" if c["ok"] else note_bad
        return f"| {label} | {c['need']:g} {unit} | {have_s} {unit} | {verdict} |"

    rows = [row("Largest feed F", "feed", "mm/min", "above the axis rates: runs slower (see the run time)")]
    rows += [row(f"{ax.upper()} axis speed in a feed move", f"axis_rate_{ax}", "mm/min", "above the axis rate: runs "
                 "slower") for ax in "xyz"]
    rows += [row(f"{ax.upper()} travel used / available", f"travel_{ax}", "mm", "REFUSED: beyond the travel")
             for ax in "xyz"]
    rows.append(row("Spindle", "spindle", "rpm", "REFUSED: outside the range"))
    lines = ["## What the machine must do", "",
             f"Each need against the machine given: {name} ({mach.get('controller')}"
             + (f", from {mach['source']}" if mach.get("source") else "") + "), in mm.", "",
             "| need | program | machine | verdict |", "|---|---|---|---|"]
    lines += [r for r in rows if r]
    lines += ["", "- Largest plunge F " + (f"{need['plunge_max']:g} {u}/min" if need["plunge_max"] is not None
                                             else "none"),
              f"- Program ends parked at X{sheet['park'][0]:g} Y{sheet['park'][1]:g} at the safe height", ""]
    lines[4:4] = _tool_lines(sheet)
    return lines


def _tool_lines(sheet: dict) -> list[str]:
    """The needs' lines on the tools: one per tool the job loads, or the single tool's call."""
    if sheet.get("tools_loaded"):
        return [_tool_line(t, sheet["dialect"]) for t in sheet["tools_loaded"]]
    n = sheet.get("tool_number")
    if n is None:
        return []
    return [f"- Tool T{n}" + (f": the program calls T{n} M6 G43 H{n} (tool change and length offset)"
                              if sheet["dialect"] == "linuxcnc" else ": load it by hand before the start (grbl has no M6)")]


def _tool_line(t: dict, dialect: str) -> str:
    """One tool of a job with several: which programs it cuts and how it is loaded."""
    name = (f"T{t['number']} " if t["number"] is not None else "") + f"{_TOOL_NAMES[t['shape']]} {t['diameter']:g}"
    what = f"{', '.join(t['operations'])} ({', '.join(t['programs'])})"
    if t.get("tool_call"):
        return f"- Tool {name}, {what}: the program calls {t['tool_call']} (tool change and length offset)"
    return f"- Tool {name}, {what}: {t['touch_off']}, before running {t['programs'][0]}"


def _duration(seconds: float) -> str:
    """h min, or seconds below a minute."""
    return _hms(seconds) if seconds >= 59.5 else f"{seconds:.0f} s"


def _operations_markdown(sheet: dict) -> list[str]:
    """The 'Operations' section of a job with roughing: the steps per tool and a table
    per operation (empty for today's one-tool job)."""
    ops = sheet.get("operations")
    if not ops:
        return []
    u = sheet["units"]
    total = sum(o["time_s"] for o in ops)
    est = sorted({o["estimator"] for o in ops})
    lines = ["## Operations", "", "Steps, in this order:", ""]
    lines += [f"{i}. {s}" for i, s in enumerate(sheet["steps"], start=1)]
    lines += ["", "| # | operation | tool | feeds | levels | passes | leaves | program | lines | time |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for i, o in enumerate(ops, start=1):
        t = o["tool"]
        tool = (f"T{t['number']} " if t["number"] is not None else "") + f"{_TOOL_NAMES[t['shape']]} " \
            f"{t['diameter']:g} {u}" + (f" (corner {t['corner_radius']:g})" if t["shape"] == "bull" else "")
        lines.append(f"| {i} | {o['kind']} | {tool} | F{o['feed']:g}, plunge F{o['plunge']:g} {u}/min, "
                     f"S{o['spindle_rpm']:g} | {o['levels'] or '-'} | {o['passes']} | "
                     f"{o['leave']:g} {u} | `{o['program']}` | {o['lines']} | "
                     f"{_duration(o['time_s'])} ({o['estimator']}) |")
    lines += ["", f"Total {_duration(total)} ({' and '.join(est)}; a tool change's own time not counted), "
                  f"{sheet['lines']} program lines."]
    jv = sheet.get("job_verification")
    if jv and isinstance(jv, dict):
        ok = jv.get("ok")
        lines.append("")
        lines.append("Whole job simulated on the stock, each tool with its own shape: "
                     + ("within its bounds." if ok else "see `job_verification` in the JSON sheet."
                        if ok is None else "OUT OF BOUNDS: see `job_verification` in the JSON sheet."))
    if sheet.get("left_for_next"):
        lines += ["", "Where a tool left material above its allowance's bound (the same simulation):", ""]
    for e in sheet.get("left_for_next") or ():
        tool = f" (T{e['tool']})" if e["tool"] is not None else ""
        where = (f"{e['area']:g} {u}^2, up to {e['largest']:g} {u} above its bound (largest at "
                 f"X{e['at'][0]:g} Y{e['at'][1]:g})")
        if e["kind"] == "unreachable":
            nxt = e["taken_by"]
            then = (f"the {nxt['operation']}" + (f" (T{nxt['tool']})" if nxt["tool"] is not None else "")
                    + " takes what is left" if nxt is not None else "nothing after it takes it")
            lines.append(f"- The {e['operation']}{tool} cannot reach its allowance over {where}: {then}.")
        else:
            lines.append(f"- The {e['operation']}{tool} left material above its bound where it reaches, "
                         f"over {where}.")
    return lines + [""]


def sheet_markdown(sheet: dict, png_name: str | None, stock_pngs: dict | None = None) -> str:
    """The operator's sheet (Markdown). ``stock_pngs``: {'rough'|'finish': file name} of
    the shaded stock pictures beside it (a job with roughing)."""
    u = sheet["units"]
    st = sheet["stock"]
    files = sheet.get("programs") or []
    title = sheet["program"] if len(files) <= 1 else \
        f"{sheet['name']} job, {len(files)} programs ({', '.join(files)})"
    lines = [
        f"# Setup sheet: {title}",
        "",
        f"Generated by fabkit {sheet['fabkit_version']} from `{sheet['spec']}` ({sheet['dialect']} dialect). "
        f"All lengths in **{u}**.",
        "",
        "## Stock and work zero",
        "",
        f"- Stock: X 0 to {st['max'][0]:g}, Y 0 to {st['max'][1]:g}, Z {st['min'][2]:g} to 0 {u}",
        f"- Work zero: {sheet['work_zero']}.",
        f"- Design to work: work = {sheet['design_to_work']['scale'][0]:g} * design + "
        f"({', '.join(f'{v:g}' for v in sheet['design_to_work']['offset'])}) "
        f"(design units: {sheet['design_to_work']['design_units']}).",
        "",
        "## Tool and feeds" if not sheet.get("operations") else "## Finishing tool and feeds",
        "",
        f"- Tool: {sheet['tool']['shape']}-end mill, diameter {sheet['tool']['diameter']:g} {u}"
        + (f", reach {sheet['tool']['reach']:g} {u}" if sheet["tool"]["reach"] is not None else ""),
        f"- Feed {sheet['feed']:g} {u}/min, plunge {sheet['plunge']:g} {u}/min, spindle {sheet['spindle_rpm']:g} rpm",
        f"- Safe height Z{sheet['safe_z']:g}; deepest cut {sheet['depth']:g} {u} (limit {sheet['depth_limit']:g})"
        if sheet["depth"] is not None else f"- Safe height Z{sheet['safe_z']:g}",
        "",
        *_operations_markdown(sheet),
        *_needs_markdown(sheet),
        *_run_markdown(sheet),
        "## Passes" if not sheet.get("operations") else "## Finishing passes",
        "",
        f"- {sheet['passes']} raster passes along {sheet['direction']}, stepover "
        f"{sheet['stepover_min']:g} to {sheet['stepover']:g} {u} between passes over the stock"
        + (f" (up to {sheet['edge_pass_gap']:g} {u} from them to the passes beyond its edges)"
           if (sheet.get("edge_pass_gap") or 0) > sheet["stepover"] else "")
        + (f" ({sheet['passes_added_after_verification']} of them added where the first verified "
           "cut left more than scallop + tolerance)" if sheet.get("passes_added_after_verification") else ""),
        f"- Scallop {sheet['scallop']:g} {u} (measured {_MEASURE[sheet.get('scallop_measure', 'normal')]}), "
        f"tolerance {sheet['tolerance']:g} {u}",
        f"- {sheet['lines']} program lines; estimated run time {_hms(sheet['estimated_time_s'])} "
        f"(rapids at {sheet['rapid_rate_assumed']:g} {u}/min, acceleration ignored)",
        "",
        "## Verification",
        "",
    ]
    if sheet["verified"]:
        lines += [f"- Largest gouge {sheet['max_gouge']:.4g} {u} (allowed {sheet['tolerance']:g})",
                  f"- Largest material left {sheet['max_material_left']:.4g} {u} "
                  f"{_MEASURE[sheet.get('scallop_measure', 'normal')]} "
                  f"(allowed {sheet['scallop'] + sheet['tolerance']:.4g})"
                  + (f"; {sheet['max_material_left_vertical']:.4g} {u} measured vertically"
                     if sheet.get("scallop_measure", "normal") == "normal"
                     and "max_material_left_vertical" in sheet else ""),
                  *([f"- Material the ball cannot reach (a valley tighter than the tool, a crease): up to "
                     f"{sheet['material_left_unreachable']['height']:.4g} {u} above the design at "
                     f"X{sheet['material_left_unreachable']['at'][0]:g} Y{sheet['material_left_unreachable']['at'][1]:g}, "
                     f"over about {sheet['material_left_unreachable']['area']:.4g} {u}^2 (left, not gouged)"]
                    if sheet.get("material_left_unreachable") else []),
                  f"- Checked at {sheet['verification_points']} points across the whole stock, edges and "
                  "crease included, by sweeping the ball along every move read back from the program."]
    else:
        lines += ["- Not verified (--no-verify)."]
    if png_name:
        lines += ["", "## Preview", "", f"![toolpath preview]({png_name})"]
    for after, name in (stock_pngs or {}).items():
        lines += ["", f"## Simulated stock after {'roughing' if after == 'rough' else 'finishing'}", "",
                  f"![stock after {after}]({name})"]
    return "\n".join(lines) + "\n"


_MEASURE = {"normal": "normal to the surface", "vertical": "vertically"}


PREVIEW_MAX_ASPECT = 2.0     # the preview's plot height over width, at most (equal scales kept)
# viridis at 0, 1/8, ..., 1 (matplotlib's table), interpolated linearly between
_VIRIDIS = np.array([[68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
                     [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37]], float)


def _viridis(t: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 colours of t in [0, 1]."""
    x = np.clip(t, 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(x.astype(int), len(_VIRIDIS) - 2)
    f = (x - i)[:, None]
    return np.rint(_VIRIDIS[i] * (1.0 - f) + _VIRIDIS[i + 1] * f).astype(np.uint8)


def preview_png(program, L: float, W: float, units: str = "mm", max_segments: int = 400_000) -> bytes:
    """Top view of the feed moves coloured by tip depth (work mm shown in program
    units), stock outline dashed, with a colour bar. Returns PNG bytes, drawn with
    numpy and Pillow (no plotting library: the preview costs a few hundredths of a
    second, not the second matplotlib's import and render took)."""
    from PIL import Image, ImageDraw, ImageFont

    k = 1.0 / (MM_PER_INCH if units == "in" else 1.0)
    a, b = program.segments()
    feed = (program.kinds == 1) & np.isfinite(a).all(axis=1)
    a, b = a[feed] * k, b[feed] * k
    if len(a) > max_segments:
        step = int(math.ceil(len(a) / max_segments))
        a, b = a[::step], b[::step]
    Lk, Wk = L * k, W * k
    left, right, top, bottom, pw = 70, 130, 40, 50, 700      # margins and plot width, pixels
    s = pw / (1.06 * Lk)                                       # pixels per program unit
    ph = int(round(min(1.06 * Wk * s, PREVIEW_MAX_ASPECT * pw, max(0.3 * pw, 1.06 * Wk * s))))
    s = min(s, ph / (1.06 * Wk)) if Wk > 0 else s
    img = np.full((top + ph + bottom, left + pw + right, 3), 255, np.uint8)
    ox, oy = left + 0.5 * (pw - Lk * s), top + 0.5 * (ph + Wk * s)   # pixel of work (0, 0)

    def px(x, y):
        return ox + x * s, oy - y * s

    if len(a):
        z = 0.5 * (a[:, 2] + b[:, 2])
        zlo, zhi = float(z.min()), float(z.max())
        col = _viridis((z - zlo) / (zhi - zlo) if zhi > zlo else np.zeros_like(z))
        (x0, y0), (x1, y1) = px(a[:, 0], a[:, 1]), px(b[:, 0], b[:, 1])
        n = np.ceil(np.maximum(np.abs(x1 - x0), np.abs(y1 - y0))).astype(np.int64) + 1
        seg = np.repeat(np.arange(len(n)), n)
        t = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) / np.maximum(np.repeat(n, n) - 1, 1)
        xi = np.rint(x0[seg] + t * (x1 - x0)[seg]).astype(np.int64)
        yi = np.rint(y0[seg] + t * (y1 - y0)[seg]).astype(np.int64)
        ok = (xi > left) & (xi < left + pw) & (yi > top) & (yi < top + ph)     # inside the plot
        img[yi[ok], xi[ok]] = col[seg[ok]]
    else:
        zlo = zhi = 0.0
    bar = np.linspace(1.0, 0.0, ph)                           # the colour bar, top = highest
    bx = left + pw + 30
    img[top:top + ph, bx:bx + 18] = _viridis(bar)[:, None, :]
    im = Image.fromarray(img)
    d = ImageDraw.Draw(im)
    font = ImageFont.load_default()
    (sx0, sy0), (sx1, sy1) = px(0.0, 0.0), px(Lk, Wk)
    for (u0, v0), (u1, v1) in (((sx0, sy0), (sx1, sy0)), ((sx1, sy0), (sx1, sy1)),
                               ((sx1, sy1), (sx0, sy1)), ((sx0, sy1), (sx0, sy0))):
        m = max(1, int(math.hypot(u1 - u0, v1 - v0) // 12))
        for i in range(m):                                     # dashed stock outline
            f0, f1 = i / m, (i + 0.5) / m
            d.line([(u0 + f0 * (u1 - u0), v0 + f0 * (v1 - v0)), (u0 + f1 * (u1 - u0), v0 + f1 * (v1 - v0))],
                   fill=(0, 0, 0), width=1)
    d.rectangle([left, top, left + pw, top + ph], outline=(0, 0, 0))
    d.text((left, 12), "toolpath, top view (feed moves coloured by tip Z)", fill=(0, 0, 0), font=font)
    d.text((left + pw // 2 - 20, top + ph + 28), f"X ({units})", fill=(0, 0, 0), font=font)
    d.text((8, top + ph // 2), f"Y ({units})", fill=(0, 0, 0), font=font)
    for val, (u, v) in ((0.0, (sx0, top + ph + 6)), (Lk, (sx1 - 20, top + ph + 6))):
        d.text((u, v), f"{val:.4g}", fill=(0, 0, 0), font=font)
    for val, (u, v) in ((0.0, (left - 40, sy0 - 6)), (Wk, (left - 40, sy1 - 6))):
        d.text((u, v), f"{val:.4g}", fill=(0, 0, 0), font=font)
    d.text((bx + 22, top - 4), f"{zhi:.4g}", fill=(0, 0, 0), font=font)
    d.text((bx + 22, top + ph - 8), f"{zlo:.4g}", fill=(0, 0, 0), font=font)
    d.text((bx - 6, top + ph + 8), f"tip Z ({units})", fill=(0, 0, 0), font=font)
    buf = io.BytesIO()
    im.save(buf, format="PNG", optimize=False)
    return buf.getvalue()


__all__ = ["sheet_paths", "setup_sheet", "sheet_json", "sheet_markdown", "preview_png", "job_program_path",
           "stock_paths"]
