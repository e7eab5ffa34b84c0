"""The machine profile: what the controller that runs a program allows.

A profile is the spec's ``machine`` section, or a YAML file of the same keys
(``--machine FILE``; a spec with a ``machine`` section is also a profile file).
:func:`import_settings` turns a grbl ``$$`` dump or a LinuxCNC INI into one.
Units are fabkit's: lengths mm, rates mm/min, accelerations mm/s^2 (grbl's own
settings are in these units; a LinuxCNC INI's are per second and in its
``LINEAR_UNITS``, converted here).

Shipped profiles (``fabkit/machine/profiles/*.yaml``) are given by name: ``--machine
grbl`` (grbl 1.1h's generic defaults, :func:`grbl_defaults`), ``grbl-router``,
``linuxcnc-mill`` (``fabkit machine list``). A file of that name, when one exists,
comes first.

Hostile files: a repeated key or section is refused naming both lines; a value outside
its physical range (:data:`PHYSICAL`) is refused naming the range and the file's own key
(``$121``, ``[AXIS_Y]MAX_ACCELERATION``); an INI's numbers are read as LinuxCNC reads
them (C's ``sscanf("%lf")``: the longest number at the start, so ``1_000`` is 1); a
UTF-8 byte-order mark is accepted.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from ..errors import SpecError
from ..units import MM_PER_INCH

MAX_PROFILE_BYTES = 1_000_000
AXES = "xyz"

#: grbl $-settings a profile needs (number -> (key, axis index or None))
GRBL_REQUIRED = {11: ("junction_deviation", None),
                 110: ("max_rate", 0), 111: ("max_rate", 1), 112: ("max_rate", 2),
                 120: ("acceleration", 0), 121: ("acceleration", 1), 122: ("acceleration", 2),
                 130: ("travel", 0), 131: ("travel", 1), 132: ("travel", 2)}
GRBL_OPTIONAL = {12: ("arc_tolerance", None), 100: ("steps_per_mm", 0), 101: ("steps_per_mm", 1),
                 102: ("steps_per_mm", 2), 30: ("spindle", 1), 31: ("spindle", 0)}
_GRBL_LINE = re.compile(r"^\s*\$(\d+)\s*=\s*([-+]?(?:\d+\.?\d*|\.\d+))\s*(?:\(.*\))?\s*$")


@dataclass(frozen=True)
class Machine:
    """A validated machine profile (the spec's ``machine`` section's keys).

    max_rate, acceleration, travel, steps_per_mm: (x, y, z) in mm/min, mm/s^2, mm, steps/mm.
    spindle: (min, max) rpm or None (not checked). rapid: mm/min or None (the axis rates).
    """

    controller: str = "grbl"
    max_rate: tuple = (500.0, 500.0, 500.0)
    acceleration: tuple = (10.0, 10.0, 10.0)
    travel: tuple = (200.0, 200.0, 200.0)
    steps_per_mm: tuple = (250.0, 250.0, 250.0)
    junction_deviation: float = 0.01
    arc_tolerance: float = 0.002
    path_tolerance: float | None = None
    max_velocity: float | None = None
    max_acceleration: float | None = None
    rapid: float | None = None
    spindle: tuple | None = None
    tool_changer: bool = False
    name: str | None = None
    source: str | None = None        # the file it was read from

    @classmethod
    def from_section(cls, section, source: str | None = None) -> "Machine":
        v = section.as_dict()
        return cls(**{k: (tuple(x) if isinstance(x, (list, tuple)) else x) for k, x in v.items()},
                   source=source)

    def to_dict(self) -> dict:
        """The profile's keys (JSON/YAML-ready; None-valued keys left out)."""
        out = {}
        for k in ("name", "controller", "max_rate", "acceleration", "travel", "steps_per_mm",
                  "junction_deviation", "arc_tolerance", "path_tolerance", "max_velocity",
                  "max_acceleration", "rapid", "spindle", "tool_changer"):
            v = getattr(self, k)
            if v is None:
                continue
            out[k] = [float(x) for x in v] if isinstance(v, tuple) else v
        return out

    def describe(self) -> str:
        """One line for a summary."""
        r = "/".join(f"{v:g}" for v in self.max_rate)
        a = "/".join(f"{v:g}" for v in self.acceleration)
        extra = f", junction deviation {self.junction_deviation:g} mm" if self.controller == "grbl" else \
            (f", G64 P{self.path_tolerance:g}" if self.path_tolerance is not None else "")
        who = f"{self.name} ({self.controller})" if self.name else self.controller
        return f"{who}: rates X/Y/Z {r} mm/min, acceleration {a} mm/s^2{extra}"


def to_yaml(machine: Machine, comment: str | None = None) -> str:
    """The profile as a YAML file (flow lists, one key a line)."""
    lines = [f"# {c}" for c in (comment or "").splitlines() if c] if comment else []
    for k, v in machine.to_dict().items():
        if isinstance(v, list):
            v = "[" + ", ".join(repr(float(x)) for x in v) + "]"
        elif isinstance(v, bool):
            v = "true" if v else "false"
        elif isinstance(v, str):
            v = json.dumps(v)         # escaped: a YAML double-quoted string for any name
        else:
            v = repr(float(v))
        lines.append(f"{k}: {v}" + (f"  # {YAML_UNITS[k]}" if k in YAML_UNITS else ""))
    return "\n".join(lines) + "\n"


#: the unit of each key, written beside it in the profile's YAML (docs/machine.md)
YAML_UNITS = {"max_rate": "mm/min, X Y Z", "acceleration": "mm/s^2, X Y Z", "travel": "mm, X Y Z",
              "steps_per_mm": "steps/mm, X Y Z", "junction_deviation": "mm", "arc_tolerance": "mm",
              "path_tolerance": "mm", "max_velocity": "mm/min", "max_acceleration": "mm/s^2", "rapid": "mm/min",
              "spindle": "rpm, min max"}


def from_mapping(body, file: str, flat: bool = True) -> Machine:
    """Validate a mapping of profile keys (the spec's ``machine`` schema)."""
    from ..spec import validate

    try:
        spec = validate({"machine": body if body is not None else {}}, file)
    except SpecError as exc:
        key = exc.key
        if flat and key and key.startswith("machine."):
            key = key[len("machine."):]
        raise SpecError(exc.detail, file=exc.file or file, key=key) from None
    m = Machine.from_section(spec.machine, source=file)
    try:
        _physical(m, file)
    except SpecError as exc:
        key = exc.key if flat else f"machine.{exc.key}"
        raise SpecError(exc.detail, file=file, key=key) from None
    return m


def _read_text(path, noun: str) -> str:
    from ..io import read_regular, text_of

    p = str(path)
    text = text_of(read_regular(p, MAX_PROFILE_BYTES, noun), p, MAX_PROFILE_BYTES)
    return text[1:] if text.startswith("\ufeff") else text          # a UTF-8 byte-order mark


#: physical ranges of the profile's values (fabkit's units), refused outside
PHYSICAL = {"max_rate": (1.0, 1e6, "mm/min"), "acceleration": (0.1, 1e5, "mm/s^2"),
            "travel": (0.1, 1e5, "mm"), "steps_per_mm": (1.0, 1e6, "steps/mm"),
            "junction_deviation": (0.0, 10.0, "mm"), "arc_tolerance": (1e-4, 10.0, "mm"),
            "path_tolerance": (0.0, 100.0, "mm"), "max_velocity": (1.0, 1e6, "mm/min"),
            "max_acceleration": (0.1, 1e5, "mm/s^2"), "rapid": (1.0, 1e6, "mm/min"),
            "spindle": (0.0, 1e6, "rpm")}


def _physical(m: "Machine", file: str) -> None:
    """Refuse values outside :data:`PHYSICAL` (key ``max_rate[1]``, ``spindle[0]``...)."""
    for key, (lo, hi, unit) in PHYSICAL.items():
        v = getattr(m, key)
        if v is None:
            continue
        vals = v if isinstance(v, tuple) else (v,)
        for i, x in enumerate(vals):
            if not (lo <= float(x) <= hi):
                k = f"{key}[{i}]" if isinstance(v, tuple) else key
                raise SpecError(f"{float(x):g} {unit} is outside the physical range {lo:g} to {hi:g} {unit}",
                                file=file, key=k)
    if m.spindle is not None:
        if m.spindle[1] <= 0:
            raise SpecError("the spindle's maximum must be > 0 rpm", file=file, key="spindle[1]")
        if m.spindle[0] > m.spindle[1]:
            raise SpecError(f"the spindle's minimum {m.spindle[0]:g} rpm is above its maximum "
                            f"{m.spindle[1]:g} rpm", file=file, key="spindle[0]")


def safe_name(text: str) -> str:
    """A file name as printable text (control characters escaped), for names and summaries."""
    from ..errors import one_line

    return one_line(text, 200)


def shipped_profiles() -> dict:
    """{name: path} of the profiles shipped with fabkit."""
    base = resources.files("fabkit.machine").joinpath("profiles")
    return {Path(e.name).stem: e for e in sorted(base.iterdir(), key=lambda e: e.name) if e.name.endswith(".yaml")}


def resolve_machine(arg: str) -> Machine:
    """``--machine ARG``: a profile file, or the name of a shipped profile."""
    if not os.path.exists(arg):
        shipped = shipped_profiles()
        if arg in shipped:
            with resources.as_file(shipped[arg]) as p:
                m = load_machine(p)
            import dataclasses

            return dataclasses.replace(m, source=f"{arg} (shipped profile)")
        if os.sep not in arg and "." not in arg:
            raise SpecError(f"no such file, and not a shipped profile ({', '.join(shipped)}: `fabkit machine list`)",
                            file=arg)
    return load_machine(arg)


def load_machine(path) -> Machine:
    """A profile file: a YAML mapping of the ``machine`` keys, a spec with a
    ``machine`` section, or the controller's own settings (a grbl ``$$`` dump, a
    LinuxCNC INI). Bad files raise SpecError naming the file and key."""
    from ..spec import parse_yaml

    p = str(path)
    text = _read_text(p, "machine profile")
    native = _native(text, p)
    if native is not None:
        return native
    raw = parse_yaml(text, p)
    if isinstance(raw, dict) and "machine" not in raw and any(k in raw for k in ("surface", "stock", "tool",
                                                                               "machining")):
        raise SpecError("a spec without a machine section: it holds no machine profile (add a machine section, "
                        "or give a profile, a grbl $$ dump or a LinuxCNC INI)", file=p)
    if not isinstance(raw, dict):
        raise SpecError("a machine profile must be a mapping of keys (controller, max_rate, ...); "
                        "`fabkit machine import` writes one from a grbl $$ dump or a LinuxCNC INI", file=p)
    if "machine" in raw:
        return from_mapping(raw["machine"], p, flat=False)
    return from_mapping(raw, p)


def grbl_defaults() -> Machine:
    """grbl 1.1h's generic defaults (the shipped profile ``grbl``)."""
    with resources.as_file(shipped_profiles()["grbl"]) as p:
        return load_machine(p)


def machine_from_spec(spec, machine_file: str | None = None) -> Machine | None:
    """The profile for a command: ``--machine FILE`` if given, else the spec's
    ``machine`` section, else None (no machine known: no planner time, no checks)."""
    if machine_file:
        return resolve_machine(machine_file)
    if spec.has("machine"):
        return Machine.from_section(spec.machine, source=spec.path)
    return None


def dialect_for_machine(spec, machine: Machine | None):
    """The spec with the program's dialect of ``machine`` (grbl for a grbl profile or
    ``$$`` dump, linuxcnc for a LinuxCNC one). A spec whose own ``machining.dialect``
    contradicts the machine is refused naming both."""
    if machine is None:
        return spec
    want = "grbl" if machine.controller == "grbl" else "linuxcnc"
    explicit = (spec.raw.get("machining") or {}).get("dialect") if isinstance(spec.raw, dict) else None
    if explicit is not None and explicit != want:
        who = machine.name or machine.controller
        src = f" ({safe_name(machine.source)})" if machine.source and machine.source != spec.path else ""
        raise SpecError(f"the spec's machining.dialect is {explicit}, the machine {who}{src} runs {want}: remove "
                        f"machining.dialect (the machine sets it) or give a {explicit} machine",
                        file=spec.path, key="machining.dialect")
    if spec.machining.dialect != want:
        return spec.with_overrides({"machining.dialect": want})
    return spec


# ----------------------------------------------------------------------------
# import: grbl $$ and LinuxCNC INI
# ----------------------------------------------------------------------------
def parse_grbl(text: str, file: str = "<grbl>") -> Machine:
    """A grbl ``$$`` dump (``$110=500.000`` lines; ``ok``, ``[...]`` messages, ``<...>``
    status reports and blank lines ignored) -> profile. A setting given twice is refused
    naming both lines; a bad value names its ``$`` setting."""
    if text.startswith("\ufeff"):
        text = text[1:]
    values: dict[int, float] = {}
    where: dict[int, int] = {}
    for ln, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.lower() == "ok" or line[0] in "[<;(" or line.startswith("Grbl"):
            continue
        m = _GRBL_LINE.match(line)
        if not m:
            raise SpecError(f"line {ln}: not a grbl setting ($N=value): {line[:60]!r}", file=file)
        n = int(m.group(1))
        if n in where:
            raise SpecError(f"set twice: line {where[n]} and line {ln}", file=file, key=f"${n}")
        where[n] = ln
        values[n] = float(m.group(2))
    missing = [n for n in GRBL_REQUIRED if n not in values]
    if missing:
        raise SpecError(f"not a complete grbl $$ dump: missing {', '.join(f'${n}' for n in missing)}", file=file)
    body: dict = {"controller": "grbl", "name": f"grbl ({safe_name(Path(file).name)})", "tool_changer": False}
    lists = {"max_rate": [0.0] * 3, "acceleration": [0.0] * 3, "travel": [0.0] * 3,
             "steps_per_mm": [250.0] * 3, "spindle": [0.0, 1000.0]}
    for n, (key, i) in {**GRBL_REQUIRED, **GRBL_OPTIONAL}.items():
        if n not in values:
            continue
        v = values[n]
        if key == "travel":
            v = abs(v)          # grbl stores travel negative internally; $$ shows it positive
        if i is None:
            body[key] = v
        else:
            lists[key][i] = v
    for key, v in lists.items():
        body[key] = v
    try:
        return from_mapping(body, file)
    except SpecError as exc:        # name the $ setting behind a bad value
        num = {f"{k}[{i}]" if i is not None else k: n for n, (k, i) in {**GRBL_REQUIRED, **GRBL_OPTIONAL}.items()}
        num["spindle"] = 30 if lists["spindle"][1] <= 0 or lists["spindle"][1] < lists["spindle"][0] else 31
        n = num.get(exc.key or "")
        raise SpecError(exc.detail, file=file, key=f"${n}" if n is not None else exc.key) from None


#: C's strtod/sscanf("%lf") prefix: what LinuxCNC's IniFile::Find(double*) reads
_C_DOUBLE = re.compile(r"\s*([+-]?(?:0[xX](?:[0-9a-fA-F]+\.?[0-9a-fA-F]*|\.[0-9a-fA-F]+)(?:[pP][+-]?\d+)?"
                       r"|(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|inf(?:inity)?|nan))", re.I)
#: the INI sections fabkit reads (a repeat of these, or of a key in them, is refused)
_INI_READ = re.compile(r"^(TRAJ|AXIS_[XYZ012]|JOINT_\d+|SPINDLE_0|KINS|EMCIO)$")


def c_double(raw: str) -> float | None:
    """``raw`` as LinuxCNC reads a number (``sscanf(raw, "%lf")``): the longest number at
    its start (``1_000`` -> 1, ``0x10`` -> 16, ``2.5 # c`` -> 2.5); None when there is none."""
    m = _C_DOUBLE.match(raw)
    if not m:
        return None
    t = m.group(1)
    body = t.lstrip("+-")
    if body[:2].lower() == "0x":
        v = float.fromhex(t if "p" in t.lower() else t + "p0")
    else:
        v = float(t)
    return v


def _ini_scan(text: str, file: str) -> dict:
    """{SECTION: {KEY: (value, line)}} for the sections fabkit reads, LinuxCNC's way
    (``#``/``;`` comment lines, ``KEY = VALUE``); a repeated section or key is refused
    naming both lines."""
    out: dict = {}
    seen_sec: dict = {}
    cur = None
    for ln, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line[0] == "[":
            end = line.find("]")
            name = line[1:end].strip() if end > 0 else line[1:].strip()
            if _INI_READ.match(name):
                if name in seen_sec:
                    raise SpecError(f"the section appears twice: line {seen_sec[name]} and line {ln}",
                                    file=file, key=f"[{safe_name(name)}]")
                seen_sec[name] = ln
                out[name] = {}
                cur = name
            else:
                cur = None
            continue
        if cur is None or "=" not in line:
            continue
        key, val = line.split("=", 1)
        key = key.strip()
        if key in out[cur]:
            raise SpecError(f"set twice: line {out[cur][key][1]} and line {ln}", file=file,
                            key=f"[{cur}]{safe_name(key)}")
        out[cur][key] = (val.strip(), ln)
    return out


def parse_linuxcnc_ini(text: str, file: str = "<ini>") -> Machine:
    """A LinuxCNC INI -> profile: [TRAJ] LINEAR_UNITS, MAX_LINEAR_VELOCITY,
    MAX_LINEAR_ACCELERATION; [AXIS_X|Y|Z] (or [AXIS_0|1|2]) MAX_VELOCITY,
    MAX_ACCELERATION, MIN_LIMIT, MAX_LIMIT; [JOINT_n] the same limits (the joints of
    each axis by [KINS] KINEMATICS ``coordinates=``, else X Y Z = joints 0 1 2): an
    axis runs at the least of its own and its joints' limits; [SPINDLE_0]
    MIN/MAX_FORWARD_VELOCITY (rpm); [EMCIO] present: M6 is accepted (a tool changer or
    a manual change). Numbers are read as LinuxCNC reads them (:func:`c_double`)."""
    if text.startswith("\ufeff"):
        text = text[1:]
    ini = _ini_scan(text, file)
    src: dict = {}              # profile key -> the INI's key, for the messages

    def num(section, key, required=False, profile_key=None):
        if section not in ini or key not in ini[section]:
            if required:
                raise SpecError("missing key", file=file, key=f"[{section}]{key}")
            return None
        raw, ln = ini[section][key]
        v = c_double(raw)
        if v is None:
            raise SpecError(f"line {ln}: not a number: {safe_name(raw[:40])!r} (LinuxCNC cannot read it)",
                            file=file, key=f"[{section}]{key}")
        if not math.isfinite(v):
            raise SpecError(f"line {ln}: must be finite, got {safe_name(raw[:40])!r}", file=file,
                            key=f"[{section}]{key}")
        if profile_key:
            src[profile_key] = f"[{section}]{key}"
        return v

    units_raw = ini.get("TRAJ", {}).get("LINEAR_UNITS", ("mm", 0))[0]
    units = (units_raw.split() or ["mm"])[0].lower()
    k = {"mm": 1.0, "metric": 1.0, "millimeter": 1.0, "inch": MM_PER_INCH, "in": MM_PER_INCH,
         "imperial": MM_PER_INCH}.get(units)
    if k is None:
        raise SpecError(f"unknown unit {safe_name(units)!r} (mm | inch)", file=file, key="[TRAJ]LINEAR_UNITS")
    coords = "XYZ"
    kins = ini.get("KINS", {}).get("KINEMATICS", ("", 0))[0]
    mc = re.search(r"coordinates\s*=\s*([A-Za-z]+)", kins)
    if mc:
        coords = mc.group(1).upper()
    body: dict = {"controller": "linuxcnc", "name": f"LinuxCNC ({safe_name(Path(file).name)})"}
    rate, acc, travel = [], [], []
    for i, ax in enumerate("XYZ"):
        sec = next((s for s in (f"AXIS_{ax}", f"AXIS_{i}") if s in ini), None)
        joints = [f"JOINT_{j}" for j, c in enumerate(coords) if c == ax and f"JOINT_{j}" in ini]
        if sec is None and not joints:
            raise SpecError(f"no [AXIS_{ax}] section: the profile needs X, Y and Z", file=file)
        vals = {}
        for key, pkey in (("MAX_VELOCITY", f"max_rate[{i}]"), ("MAX_ACCELERATION", f"acceleration[{i}]")):
            cands = []
            for s_ in ([sec] if sec else []) + joints:
                v = num(s_, key)
                if v is not None:
                    cands.append((v, s_))
            if not cands:
                raise SpecError("missing key", file=file, key=f"[{sec or joints[0]}]{key}")
            v, s_ = min(cands)
            src[pkey] = f"[{s_}]{key}"
            vals[key] = v
        lim_sec = sec if sec and "MIN_LIMIT" in ini[sec] and "MAX_LIMIT" in ini[sec] else (joints[0] if joints else sec)
        lo = num(lim_sec, "MIN_LIMIT", required=True)
        hi = num(lim_sec, "MAX_LIMIT", required=True, profile_key=f"travel[{i}]")
        rate.append(vals["MAX_VELOCITY"] * k * 60.0)
        acc.append(vals["MAX_ACCELERATION"] * k)
        travel.append((hi - lo) * k)
    body.update(max_rate=rate, acceleration=acc, travel=travel)
    v = num("TRAJ", "MAX_LINEAR_VELOCITY", profile_key="max_velocity")
    if v is None:
        v = num("TRAJ", "MAX_VELOCITY", profile_key="max_velocity")
    if v is not None:
        body["max_velocity"] = v * k * 60.0
    a = num("TRAJ", "MAX_LINEAR_ACCELERATION", profile_key="max_acceleration")
    if a is None:
        a = num("TRAJ", "MAX_ACCELERATION", profile_key="max_acceleration")
    if a is not None:
        body["max_acceleration"] = a * k
    lo = num("SPINDLE_0", "MIN_FORWARD_VELOCITY", profile_key="spindle[0]")
    hi = num("SPINDLE_0", "MAX_FORWARD_VELOCITY", profile_key="spindle[1]")
    if hi is not None:
        body["spindle"] = [lo or 0.0, hi]
    body["tool_changer"] = "EMCIO" in ini
    try:
        return from_mapping(body, file)
    except SpecError as exc:
        raise SpecError(exc.detail, file=file, key=src.get(exc.key or "", exc.key)) from None


def _native(text: str, p: str) -> Machine | None:
    """The profile of a grbl ``$$`` dump or a LinuxCNC INI; None for other text."""
    if re.search(r"^\s*\$\d+\s*=", text, re.M):
        return parse_grbl(text, p)
    if re.search(r"^\s*\[(TRAJ|AXIS_[XYZ0-9])\]", text, re.M | re.I):
        return parse_linuxcnc_ini(text, p)
    return None


def import_settings(path) -> Machine:
    """A grbl ``$$`` dump or a LinuxCNC INI file -> profile (the format is recognised
    from the text: ``$N=`` lines, or ``[TRAJ]`` / ``[AXIS_..]`` sections)."""
    p = str(path)
    text = _read_text(p, "machine settings")
    native = _native(text, p)
    if native is not None:
        return native
    raise SpecError("not a grbl $$ dump ($110=500.000 lines) or a LinuxCNC INI ([TRAJ], [AXIS_X] sections)",
                    file=p)
