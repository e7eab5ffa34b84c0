"""The machine profile: what the controller that runs a program allows.

A profile is the spec's ``machine`` section, or a YAML file of the same keys
(``--machine FILE``; a spec with a ``machine`` section is also a profile file).
:func:`import_settings` turns a grbl ``$$`` dump or a LinuxCNC INI into one.
Units are fabkit's: lengths mm, rates mm/min, accelerations mm/s^2 (grbl's own
settings are in these units; a LinuxCNC INI's are per second and in its
``LINEAR_UNITS``, converted here).

grbl 1.1's generic defaults ship as ``grbl_defaults.yaml`` (:func:`grbl_defaults`).
"""

from __future__ import annotations

import configparser
import math
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
            v = '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
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
    return Machine.from_section(spec.machine, source=file)


def _read_text(path, noun: str) -> str:
    from ..io import read_regular, text_of

    p = str(path)
    return text_of(read_regular(p, MAX_PROFILE_BYTES, noun), p, MAX_PROFILE_BYTES)


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
    if not isinstance(raw, dict):
        raise SpecError("a machine profile must be a mapping of keys (controller, max_rate, ...); "
                        "`fabkit machine import` writes one from a grbl $$ dump or a LinuxCNC INI", file=p)
    if "machine" in raw:
        return from_mapping(raw["machine"], p, flat=False)
    return from_mapping(raw, p)


def grbl_defaults() -> Machine:
    """grbl 1.1h's generic defaults (the shipped profile)."""
    ref = resources.files("fabkit.machine").joinpath("grbl_defaults.yaml")
    with resources.as_file(ref) as p:
        return load_machine(p)


def machine_from_spec(spec, machine_file: str | None = None) -> Machine | None:
    """The profile for a command: ``--machine FILE`` if given, else the spec's
    ``machine`` section, else None (no machine known: no planner time, no checks)."""
    if machine_file:
        return load_machine(machine_file)
    if spec.has("machine"):
        return Machine.from_section(spec.machine, source=spec.path)
    return None


# ----------------------------------------------------------------------------
# import: grbl $$ and LinuxCNC INI
# ----------------------------------------------------------------------------
def parse_grbl(text: str, file: str = "<grbl>") -> Machine:
    """A grbl ``$$`` dump (``$110=500.000`` lines; ``ok``, ``[...]`` messages, ``<...>``
    status reports and blank lines ignored) -> profile."""
    values: dict[int, float] = {}
    for ln, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.lower() == "ok" or line[0] in "[<;(" or line.startswith("Grbl"):
            continue
        m = _GRBL_LINE.match(line)
        if not m:
            raise SpecError(f"line {ln}: not a grbl setting ($N=value): {line[:60]!r}", file=file)
        values[int(m.group(1))] = float(m.group(2))
    missing = [n for n in GRBL_REQUIRED if n not in values]
    if missing:
        raise SpecError(f"not a complete grbl $$ dump: missing {', '.join(f'${n}' for n in missing)}", file=file)
    body: dict = {"controller": "grbl", "name": f"grbl ({Path(file).name})", "tool_changer": False}
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
        n = num.get(exc.key or "")
        raise SpecError(exc.detail, file=file, key=f"${n}" if n is not None else exc.key) from None


def _ini_float(cp, section: str, key: str, file: str) -> float | None:
    if not cp.has_option(section, key):
        return None
    raw = cp.get(section, key).strip()
    try:
        v = float(raw)
    except ValueError:
        raise SpecError(f"must be a number, got {raw[:40]!r}", file=file, key=f"[{section}]{key}") from None
    if not math.isfinite(v):
        raise SpecError(f"must be finite, got {raw[:40]!r}", file=file, key=f"[{section}]{key}")
    return v


def parse_linuxcnc_ini(text: str, file: str = "<ini>") -> Machine:
    """A LinuxCNC INI -> profile: [TRAJ] LINEAR_UNITS, MAX_LINEAR_VELOCITY,
    MAX_LINEAR_ACCELERATION; [AXIS_X|Y|Z] (or [AXIS_0|1|2]) MAX_VELOCITY,
    MAX_ACCELERATION, MIN_LIMIT, MAX_LIMIT; [SPINDLE_0] MIN/MAX_FORWARD_VELOCITY
    (rpm); [EMCIO] present: M6 is accepted (a tool changer or a manual change)."""
    cp = configparser.ConfigParser(strict=False, interpolation=None, inline_comment_prefixes=("#", ";"),
                                   comment_prefixes=("#", ";"))
    cp.optionxform = str.upper
    try:
        cp.read_string(text, source=file)
    except configparser.Error as exc:
        first = str(exc).splitlines()[0]
        raise SpecError(f"not a readable INI file: {first[:120]}", file=file) from None
    units = cp.get("TRAJ", "LINEAR_UNITS", fallback="mm").strip().lower()
    k = {"mm": 1.0, "metric": 1.0, "millimeter": 1.0, "inch": MM_PER_INCH, "in": MM_PER_INCH,
         "imperial": MM_PER_INCH}.get(units)
    if k is None:
        raise SpecError(f"unknown unit {units!r} (mm | inch)", file=file, key="[TRAJ]LINEAR_UNITS")
    body: dict = {"controller": "linuxcnc", "name": f"LinuxCNC ({Path(file).name})"}
    rate, acc, travel = [], [], []
    for i, ax in enumerate("XYZ"):
        sec = next((s for s in (f"AXIS_{ax}", f"AXIS_{i}") if cp.has_section(s)), None)
        if sec is None:
            raise SpecError(f"no [AXIS_{ax}] section: the profile needs X, Y and Z", file=file)
        vals = {key: _ini_float(cp, sec, key, file) for key in ("MAX_VELOCITY", "MAX_ACCELERATION",
                                                                "MIN_LIMIT", "MAX_LIMIT")}
        for key, v in vals.items():
            if v is None:
                raise SpecError("missing key", file=file, key=f"[{sec}]{key}")
        rate.append(vals["MAX_VELOCITY"] * k * 60.0)
        acc.append(vals["MAX_ACCELERATION"] * k)
        travel.append((vals["MAX_LIMIT"] - vals["MIN_LIMIT"]) * k)
    body.update(max_rate=rate, acceleration=acc, travel=travel)
    v = _ini_float(cp, "TRAJ", "MAX_LINEAR_VELOCITY", file) or _ini_float(cp, "TRAJ", "MAX_VELOCITY", file)
    if v is not None:
        body["max_velocity"] = v * k * 60.0
    a = _ini_float(cp, "TRAJ", "MAX_LINEAR_ACCELERATION", file) or _ini_float(cp, "TRAJ", "MAX_ACCELERATION", file)
    if a is not None:
        body["max_acceleration"] = a * k
    lo = _ini_float(cp, "SPINDLE_0", "MIN_FORWARD_VELOCITY", file)
    hi = _ini_float(cp, "SPINDLE_0", "MAX_FORWARD_VELOCITY", file)
    if hi is not None:
        body["spindle"] = [lo or 0.0, hi]
    body["tool_changer"] = cp.has_section("EMCIO")
    try:
        return from_mapping(body, file)
    except SpecError as exc:
        raise SpecError(exc.detail, file=file, key=exc.key) from None


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
