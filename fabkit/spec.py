"""The spec: YAML -> validated, typed, unit-converted objects.

Validated once, on load. Every problem is one :class:`SpecError` naming the
file and the dotted key (``specs/x.yaml: tool.diameter: must be > 0, got -3``).
Unknown keys are errors with a did-you-mean. After loading, the rest of fabkit
trusts these objects.

Units: ``units`` (mm | cm | in) is the design unit of the ``surface``,
``ball``, ``ramp`` and ``simulation`` sections; ``stock``, ``tool`` and
``machining`` lengths are millimetres. Any length may also be written as a
string with its unit, ``"1/8 in"`` or ``"3.175 mm"``; it is converted.

Sections a command does not need may be omitted; :meth:`Spec.require` makes a
missing one a clear error for the commands that do need it. Defaults are
listed in ``SCHEMA`` and in the README.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import SpecError
from .units import MM_PER, PROGRAM_UNITS, finest_tolerance, program_rounding

MAX_SPEC_BYTES = 1_000_000
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
IDENT_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,31}$")
REQUIRED = object()


# ----------------------------------------------------------------------------
# field kinds
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Num:
    """A real number. ``length`` is None (plain number), 'design' or 'mm'."""

    default: Any = REQUIRED
    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None
    length: str | None = None
    integer: bool = False
    doc: str = ""
    hint: str = ""      # appended to a range error: why the bound is there


@dataclass(frozen=True)
class Choice:
    options: tuple[str, ...]
    default: Any = REQUIRED
    doc: str = ""


@dataclass(frozen=True)
class Text:
    default: Any = REQUIRED
    doc: str = ""


@dataclass(frozen=True)
class Pair:
    """An interval [lo, hi] with lo < hi."""

    default: Any = REQUIRED
    length: str | None = None
    doc: str = ""


@dataclass(frozen=True)
class NumList:
    """A list of numbers (at least ``min_len``)."""

    default: Any = REQUIRED
    ge: float | None = None
    gt: float | None = None
    min_len: int = 1
    max_len: int = 100_000
    length: str | None = None
    doc: str = ""
    hint: str = ""


@dataclass(frozen=True)
class Flag:
    """true | false."""

    default: Any = REQUIRED
    doc: str = ""


@dataclass(frozen=True)
class Points:
    """A list of [X, Y] points (exactly ``count`` of them when given)."""

    default: Any = REQUIRED
    count: int | None = None
    length: str | None = None
    doc: str = ""


@dataclass(frozen=True)
class Params:
    default: Any = dataclasses.field(default_factory=dict)
    doc: str = ""


@dataclass(frozen=True)
class Inertia:
    default: Any = "solid"
    doc: str = ""


SCHEMA: dict[str, dict[str, Any]] = {
    "surface": {
        "height": Text(doc="expression in x, y and the params"),
        "params": Params(doc="name: number"),
        "x": Pair(length="design", doc="footprint along the channel"),
        "y": Pair(length="design", doc="footprint across"),
        "top": Num(length="design", ge=-1e9, le=1e9,
                   doc="height of the stock's top face; the surface is clipped here"),
    },
    "stock": {
        "thickness": Num(gt=0, le=10_000, length="mm"),
        "depth_limit": Num(default=None, gt=0, le=10_000, length="mm", doc="default: the thickness"),
    },
    "tool": {
        "shape": Choice(("ball",), default="ball"),
        "diameter": Num(gt=0, le=200, length="mm"),
        "reach": Num(default=None, gt=0, le=10_000, length="mm", doc="default: unlimited"),
        "number": Num(default=None, ge=1, le=99_999, integer=True,
                      doc="tool-table number: LinuxCNC gets T<n> M6 G43 H<n>; grbl (no M6) a comment. "
                          "Default: no tool call"),
        "depth_of_cut": Num(default=None, gt=0, le=1000, length="mm",
                            doc="mm the tool may engage axially (rest passes keep the finish within it); "
                                "default: its diameter"),
    },
    # further tools (a list of mappings, each with these keys): roughing and rest tools
    "tools": {
        "number": Num(ge=1, le=99_999, integer=True, doc="tool-table number, unique, not tool.number"),
        "shape": Choice(("flat", "bull", "ball"), doc="flat end mill | bull nose | ball-end mill"),
        "diameter": Num(gt=0, le=200, length="mm"),
        "corner_radius": Num(default=None, gt=0, le=100, length="mm",
                             doc="bull nose only: 0 < r <= diameter/2"),
        "reach": Num(default=None, gt=0, le=10_000, length="mm",
                     doc="flute length / usable length: no level deeper; default: unlimited"),
        "depth_of_cut": Num(default=None, gt=0, le=1000, length="mm", doc="default: the diameter"),
        "feed": Num(default=None, gt=0, le=1e6, doc="mm/min; default: machining.feed"),
        "plunge": Num(default=None, gt=0, le=1e6, doc="mm/min; default: machining.plunge"),
        "spindle": Num(default=None, gt=0, le=1e6, doc="rpm; default: machining.spindle"),
    },
    # roughing with its own tool, then rest passes, then the finish (fabkit/toolpath/rough/roughing.py)
    "roughing": {
        "tool": Num(ge=1, le=99_999, integer=True, doc="the roughing tool: a number from `tools`"),
        "stepdown": Num(gt=0, le=1000, length="mm", doc="mm between Z levels (<= the tool's depth_of_cut)"),
        "stepover": Num(default=None, gt=0, le=1000, length="mm",
                        doc="mm between offsets / rows; default 0.45 x the tool's diameter"),
        "leave": Num(default=0.5, ge=0, le=100, length="mm", doc="mm left above the design for the finish"),
        "strategy": Choice(("offset", "raster"), default="offset",
                           doc="offset: contour-parallel loops per level; raster: rows per level"),
        "entry": Choice(("helix", "ramp", "plunge"), default="helix",
                        doc="how the tool enters a closed pocket at a new level"),
        "rest": NumList(default=None, ge=1, min_len=0, max_len=20,
                        doc="tool numbers for rest passes, in order; default: the finishing tool"),
    },
    "machining": {
        "scallop": Num(default=0.05, gt=0, le=100, length="mm"),
        "scallop_measure": Choice(("normal", "vertical"), default="normal",
                                  doc="how material left is measured: normal to the surface (the "
                                      "usual scallop height) or vertically (stricter on steep ground)"),
        "tolerance": Num(default=0.01, gt=0, le=100, length="mm"),
        "direction": Choice(("x", "y"), default="x"),
        "pattern": Choice(("zigzag", "climb", "conventional"), default="zigzag"),
        "feed": Num(default=2500, gt=0, le=1e6, doc="mm/min"),
        "plunge": Num(default=600, gt=0, le=1e6, doc="mm/min"),
        "spindle": Num(default=16000, gt=0, le=1e6, doc="rpm"),
        "safe_height": Num(default=5, ge=0.5, le=1000, length="mm",
                           doc="mm above the top face for rapids; at least 0.5 mm",
                           hint="mm above the top face: rapids need a real clearance over stock that is "
                                "never perfectly flat or zeroed"),
        "dialect": Choice(("linuxcnc", "grbl"), default="linuxcnc"),
        "units": Choice(("mm", "in"), default="mm"),
        "stepdown": Num(default=None, gt=0, le=1000, length="mm", doc="roughing z-step; default: no roughing"),
        "leave": Num(default=0.5, ge=0, le=100, length="mm", doc="stock left by roughing for the finish pass"),
        "verify_points": Num(default=40000, ge=100, le=2_000_000, integer=True,
                             doc="points at which the cut is verified"),
        "park": NumList(default=(0.0, 0.0), min_len=2, max_len=2, length="mm",
                        doc="[X, Y] work mm where the program ends, at the safe height"),
        "max_time": Num(default=None, gt=0, le=1e6,
                        doc="seconds of CPU time the toolpath job may take (planning, verification, "
                            "setup sheet), estimated before planning; a longer job is refused. Default: "
                            "fabkit.tolerances max_plan_seconds (60); `--max-time` overrides it"),
    },
    # the machine that runs the program (fabkit/machine): also a profile file of the same
    # keys (`--machine FILE`, `fabkit machine import`). Rates mm/min, accelerations mm/s^2.
    "machine": {
        "name": Text(default=None, doc="what the profile describes"),
        "controller": Choice(("grbl", "linuxcnc"), default="grbl"),
        "max_rate": NumList(default=(500.0, 500.0, 500.0), gt=0, min_len=3, max_len=3,
                            doc="mm/min per axis X Y Z (grbl $110-$112, LinuxCNC [AXIS_n] MAX_VELOCITY)"),
        "acceleration": NumList(default=(10.0, 10.0, 10.0), gt=0, min_len=3, max_len=3,
                                doc="mm/s^2 per axis X Y Z (grbl $120-$122, [AXIS_n] MAX_ACCELERATION)"),
        "travel": NumList(default=(200.0, 200.0, 200.0), gt=0, min_len=3, max_len=3, length="mm",
                          doc="mm per axis X Y Z (grbl $130-$132, [AXIS_n] MAX_LIMIT - MIN_LIMIT)"),
        "steps_per_mm": NumList(default=(250.0, 250.0, 250.0), gt=0, min_len=3, max_len=3,
                                doc="grbl $100-$102: positions are whole steps (not used for linuxcnc)"),
        "junction_deviation": Num(default=0.01, ge=0, le=10, length="mm", doc="grbl $11"),
        "arc_tolerance": Num(default=0.002, gt=0, le=10, length="mm", doc="grbl $12"),
        "path_tolerance": Num(default=None, ge=0, le=100, length="mm",
                              doc="LinuxCNC G64 P; default: the program's G64 P"),
        "max_velocity": Num(default=None, gt=0, le=1e7,
                            doc="mm/min, LinuxCNC [TRAJ] MAX_LINEAR_VELOCITY; default: no limit beyond the axes"),
        "max_acceleration": Num(default=None, gt=0, le=1e7,
                                doc="mm/s^2, LinuxCNC [TRAJ] MAX_LINEAR_ACCELERATION"),
        "rapid": Num(default=None, gt=0, le=1e7, doc="mm/min; default: the axis rates"),
        "spindle": Pair(default=None, doc="[min, max] rpm (grbl $31, $30); default: not checked"),
        "tool_changer": Flag(default=False, doc="true: M6 changes the tool (LinuxCNC); false: one tool"),
    },
    "ball": {
        "diameter": Num(default=2.5, gt=0, le=1e6, length="design"),
        "inertia": Inertia(doc="solid | hollow | k = I/(m r^2)"),
        "friction": Num(default=None, ge=0, le=1e6,
                        doc="static friction coefficient (model ball: slipped where |F_t|/N exceeds it)"),
        "rolling_resistance": Num(default=0.0, ge=0, le=10,
                                  doc="rolling resistance coefficient (every model): a force c N opposing v"),
    },
    "ramp": {
        "heights": NumList(gt=0, min_len=1, length="design",
                           doc="[min, max] (sampled densely) or a list of 3 or more heights, each > 0",
                           hint="a release height of 0 gives the ball no entry speed"),
        "samples": Num(default=400, ge=2, le=10_000, integer=True,
                       doc="heights sampled in [min, max] (each is a full simulation: at most 10000)"),
        "profile": Choice(("fabkit", "straight"), default="fabkit",
                          doc="fabkit: the curvature-continuous ramp `fabkit ramp` builds; straight: your own "
                              "incline, described by ramp.angle and ramp.length"),
        "angle": Num(default=None, ge=1, le=80,
                     doc="the incline's angle to the horizontal, degrees (fabkit's ramp: 30 unless given)"),
        "length": Num(default=None, gt=0, le=1e6, length="design",
                      doc="a straight ramp's length along its surface, from its edge on the block"),
    },
    "simulation": {
        "model": Choice(("full", "simplified", "ball"), default="ball"),
        "damping": Num(default=0.0, ge=0, le=1e9, doc="viscous coefficient, 1/s"),
        "nonlinear_damping": Num(default=0.0, ge=0, le=1e9,
                                 doc="the paper's localized damping, coefficient of F(x)^2 y^2 ydot"),
        "start": Num(length="design", doc="x where the ball enters at y = 0 moving toward +x"),
        "margin": Num(default=0.5, ge=0, le=1e6, length="design"),
        "y0": Num(default=0.0, length="design", doc="transverse launch offset"),
        "vy0": Num(default=0.0, ge=-1e6, le=1e6, doc="transverse launch velocity, design units/s"),
        "t_max": Num(default=60.0, gt=0, le=3600, doc="time limit, s: still trapped then = captured"),
        "rtol": Num(default=1e-10, ge=1e-13, le=0.1,
                    doc="integrator relative tolerance (below 1e-13 double precision cannot follow)"),
        "atol": Num(default=1e-12, gt=0, le=1.0, doc="integrator absolute tolerance (design units)"),
        "method": Choice(("fabkit", "DOP853", "RK45", "Radau", "LSODA"), default="fabkit"),
    },
    "lab": {
        "marker_size": Num(default=30.0, gt=0, le=1000, length="mm",
                           doc="side of each ArUco marker's black square, mm (printed with a white quiet "
                               "zone one module wide)"),
        "markers": Points(default=None, count=4, length="mm",
                          doc="[[X, Y], ...] work mm: the centres of markers 0-3 on the top face, in id "
                              "order (default: each square 5 mm from the two nearest block edges, at the "
                              "corners (0, 0), (L, 0), (L, W), (0, W))"),
        "camera_height": Num(default=None, gt=0, le=100_000, length="mm",
                             doc="the camera's height above the top face, mm (a tape measure; optional)"),
    },
}
TOP_KEYS = {"name": Text(default=None), "units": Choice(("mm", "cm", "in"), default="mm")}
#: sections written as a list of mappings (each item validated against the section's fields);
#: ``spec.tools`` is then a tuple of :class:`Section`, one per item
LIST_SECTIONS = ("tools",)
#: the most tools a spec may list
MAX_TOOLS = 20


# ----------------------------------------------------------------------------
# typed spec
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Section:
    """A validated section: attribute access to its (converted) values."""

    _name: str
    _values: dict

    def __getattr__(self, key: str) -> Any:
        if key.startswith("_"):
            raise AttributeError(key)
        try:
            return self._values[key]
        except KeyError:
            raise AttributeError(f"{self._name}.{key}") from None

    def as_dict(self) -> dict:
        return dict(self._values)


@dataclass(frozen=True)
class Spec:
    """A validated spec. Lengths: design units in surface/ball/ramp/simulation,
    mm in stock/tool/machining. ``scale`` is mm per design unit."""

    path: str
    name: str
    units: str
    sections: dict = field(default_factory=dict)
    raw: dict = field(default_factory=dict, repr=False)

    @property
    def scale(self) -> float:
        return MM_PER[self.units]

    def has(self, section: str) -> bool:
        return section in self.sections

    def require(self, *names: str, command: str | None = None) -> None:
        for n in names:
            if n not in self.sections:
                who = f" (needed by {command})" if command else ""
                raise SpecError(f"missing section{who}", file=self.path, key=n)

    def __getattr__(self, key: str) -> Section:
        if key.startswith("_"):
            raise AttributeError(key)
        sections = object.__getattribute__(self, "sections")
        if key in sections:
            return sections[key]
        if key in SCHEMA:
            raise SpecError("missing section", file=object.__getattribute__(self, "path"), key=key)
        raise AttributeError(key)

    def surface_functions(self):
        """The compiled surface functions (cached per spec)."""
        cache = self.__dict__.setdefault("_cache", {})
        if "fns" not in cache:
            from .expr import compile_surface

            try:
                cache["fns"] = compile_surface(self.surface.height, self.surface.params)
            except SpecError as exc:
                raise exc.with_location(file=self.path) from None
        return cache["fns"]

    def with_overrides(self, overrides: dict[str, Any]) -> "Spec":
        """A new, fully validated spec with dotted keys replaced (``surface.params.eps``)."""
        import copy

        raw = copy.deepcopy(self.raw)
        for key, value in overrides.items():
            parts = key.split(".")
            node = raw
            if parts[0] in LIST_SECTIONS:
                raise SpecError("a key of a list section cannot be set or varied (edit the spec)",
                                file=self.path, key=key)
            for p in parts[:-1]:
                if not isinstance(node.get(p), dict):
                    node[p] = {}
                node = node[p]
            node[parts[-1]] = value
        return validate(raw, self.path)


# ----------------------------------------------------------------------------
# loading and validation
# ----------------------------------------------------------------------------
def parse_yaml(text: str, path: str):
    """``text`` parsed as safe YAML (no tags, no aliases bombs: :class:`_SafeLoader`);
    SpecError naming ``path`` and the line for a syntax error or an unreadable value."""
    import yaml

    try:
        return yaml.load(text, Loader=_SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise SpecError(f"YAML error: {where}{problem}", file=path) from None
    except RecursionError:
        raise SpecError("YAML nested too deeply", file=path) from None
    except (ValueError, OverflowError) as exc:  # e.g. a 5000-digit integer, a date 2001-02-30
        raise SpecError(f"YAML error: unreadable value ({str(exc).split(':')[0]})", file=path) from None


def load_spec(path: str | Path, need: tuple[str, ...] = (), command: str | None = None) -> Spec:
    """Read, parse and validate a spec file. ``need``: sections the caller requires."""
    from .io import text_of

    p = str(path)
    text = text_of(_read_spec_bytes(p), p, MAX_SPEC_BYTES)
    raw = parse_yaml(text, p)
    spec = validate(raw, p)
    spec.require(*need, command=command)
    return spec


def _read_spec_bytes(p: str) -> bytes:
    """The first MAX_SPEC_BYTES + 1 bytes of the regular file ``p`` (a pipe, device or
    socket refused: :func:`fabkit.io.read_regular`)."""
    from .io import read_regular

    return read_regular(p, MAX_SPEC_BYTES, "spec")


# Plain scalars resolved as numbers the way people (and YAML 1.2) write them.
# YAML 1.1 (PyYAML's default) reads 1e-10 and 1.5e3 as text (its floats need a
# dot and a signed exponent), 010 as octal 8 and 1:00:00 as base-60 3600. Here:
# decimal integers (leading zeros allowed, '_' separators), 0x / 0o integers,
# floats with or without a dot or exponent sign, .inf and .nan (refused later);
# sexagesimal stays text and the number check names it.
_INT_RE = re.compile(r"^[-+]?(?:[0-9][0-9_]*|0x[0-9a-fA-F_]+|0o[0-7_]+)$")
_FLOAT_RE = re.compile(r"^(?:[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)?"
                       r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$")
_SEXAGESIMAL_RE = re.compile(r"^\s*[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+(?:\.[0-9_]*)?\s*$")


def _construct_int(loader, node):
    text = loader.construct_scalar(node).replace("_", "")
    sign = -1 if text.startswith("-") else 1
    text = text.lstrip("+-")
    if text[:2] in ("0x", "0X"):
        return sign * int(text[2:], 16)
    if text[:2] in ("0o", "0O"):
        return sign * int(text[2:], 8)
    return sign * int(text, 10)


def _construct_float(loader, node):
    text = loader.construct_scalar(node).replace("_", "")
    low = text.lower()
    if low.endswith(".inf"):
        return -math.inf if low.startswith("-") else math.inf
    if low == ".nan":
        return math.nan
    return float(text)


def _make_loader():
    import yaml

    class Loader(yaml.SafeLoader):
        """SafeLoader that refuses aliases (no alias bombs) and duplicate keys."""

        def compose_node(self, parent, index):  # noqa: D401
            if self.check_event(yaml.events.AliasEvent):
                event = self.peek_event()
                raise yaml.constructor.ConstructorError(
                    None, None, "aliases (*name) are not allowed in a spec", event.start_mark)
            return super().compose_node(parent, index)

        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=deep)
                try:
                    hash(key)
                except TypeError:
                    raise yaml.constructor.ConstructorError(
                        None, None, "a key must be a plain value", key_node.start_mark) from None
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {key!r}", key_node.start_mark)
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    Loader.yaml_implicit_resolvers = {
        first: [(tag, rx) for tag, rx in resolvers if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float")]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
    Loader.add_implicit_resolver("tag:yaml.org,2002:int", _INT_RE, list("-+0123456789"))
    Loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_RE, list("-+.0123456789"))
    Loader.add_constructor("tag:yaml.org,2002:int", _construct_int)
    Loader.add_constructor("tag:yaml.org,2002:float", _construct_float)
    return Loader


class _LazyLoader:
    _cls = None

    def __call__(self, stream):
        if _LazyLoader._cls is None:
            _LazyLoader._cls = _make_loader()
        return _LazyLoader._cls(stream)


_SafeLoader = _LazyLoader()


def suggest(word: str, options) -> str:
    close = difflib.get_close_matches(str(word), list(options), n=1, cutoff=0.5)
    return f" (did you mean {close[0]!r}?)" if close else ""


_suggest = suggest      # the name this module's checks use


_LEN_RE = re.compile(r"^\s*([-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)(?:\s*/\s*(\d+(?:\.\d*)?))?\s*(mm|cm|in)\s*$")


def _number(value: Any, key: str, file: str, length: str | None, design_unit: str) -> float:
    """A finite float from a YAML value; length strings like '1/8 in' converted."""
    if isinstance(value, bool) or value is None:
        raise SpecError(f"must be a number, got {_show(value)}", file=file, key=key)
    if isinstance(value, str):
        m = _LEN_RE.match(value) if length else None
        if not m:
            hint = " (a number, or a length with its unit such as '3.175 mm' or '1/8 in')" if length else ""
            if _SEXAGESIMAL_RE.match(value):
                hint = " (base-60 numbers such as 1:00:00 are not read: write the number itself)"
            raise SpecError(f"must be a number{hint}, got {_show(value)}", file=file, key=key)
        num = float(m.group(1))
        if m.group(2):
            den = float(m.group(2))
            if den == 0:
                raise SpecError(f"division by zero in {value!r}", file=file, key=key)
            num /= den
        target = "mm" if length == "mm" else design_unit
        value = num * MM_PER[m.group(3)] / MM_PER[target]
    if isinstance(value, int):
        if abs(value) > 10**15:
            raise SpecError(f"out of range, got {value}", file=file, key=key)
        value = float(value)
    if not isinstance(value, float):
        raise SpecError(f"must be a number, got {_show(value)}", file=file, key=key)
    if not math.isfinite(value):
        raise SpecError(f"must be finite, got {value}", file=file, key=key)
    return value


def _show(value: Any) -> str:
    if isinstance(value, (dict, list)):
        return type(value).__name__
    s = repr(value)
    return s if len(s) <= 40 else s[:37] + "..."


def _check_range(v: float, f: Num, key: str, file: str) -> None:
    def bad(rel, bound):
        why = f" ({f.hint})" if f.hint else ""
        return SpecError(f"must be {rel} {bound:g}, got {v:g}{why}", file=file, key=key)

    if f.gt is not None and not v > f.gt:
        raise bad(">", f.gt)
    if f.ge is not None and not v >= f.ge:
        raise bad(">=", f.ge)
    if f.lt is not None and not v < f.lt:
        raise bad("<", f.lt)
    if f.le is not None and not v <= f.le:
        raise bad("<=", f.le)
    if f.integer and v != int(v):
        raise SpecError(f"must be a whole number, got {v:g}", file=file, key=key)


def read_field(f: Any, value: Any, key: str, file: str, unit: str) -> Any:
    if isinstance(f, Num):
        if value is None and f.default is None:
            return None
        v = _number(value, key, file, f.length, unit)
        _check_range(v, f, key, file)
        return int(v) if f.integer else v
    if isinstance(f, Choice):
        if not isinstance(value, str) or value not in f.options:
            raise SpecError(f"must be one of {' | '.join(f.options)}, got {_show(value)}"
                            f"{_suggest(value, f.options) if isinstance(value, str) else ''}",
                            file=file, key=key)
        return value
    if isinstance(f, Text):
        if not isinstance(value, str):
            raise SpecError(f"must be a string, got {_show(value)}", file=file, key=key)
        return value
    if isinstance(f, Pair):
        if not isinstance(value, (list, tuple)) or len(value) != 2:
            raise SpecError(f"must be a pair [lo, hi], got {_show(value)}", file=file, key=key)
        lo = _number(value[0], key, file, f.length, unit)
        hi = _number(value[1], key, file, f.length, unit)
        if not lo < hi:
            raise SpecError(f"must have lo < hi, got [{lo:g}, {hi:g}]", file=file, key=key)
        if abs(lo) > 1e9 or abs(hi) > 1e9:
            raise SpecError("out of range (|value| <= 1e9)", file=file, key=key)
        return (lo, hi)
    if isinstance(f, NumList):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise SpecError(f"must be a list of numbers, got {_show(value)}", file=file, key=key)
        if not f.min_len <= len(value) <= f.max_len:
            raise SpecError(f"must have {f.min_len} to {f.max_len} entries, got {len(value)}", file=file, key=key)
        out = []
        for i, item in enumerate(value):
            v = _number(item, f"{key}[{i}]", file, f.length, unit)
            if f.ge is not None and v < f.ge:
                raise SpecError(f"must be >= {f.ge:g}, got {v:g}", file=file, key=f"{key}[{i}]")
            if f.gt is not None and not v > f.gt:
                why = f" ({f.hint})" if f.hint else ""
                raise SpecError(f"must be > {f.gt:g}, got {v:g}{why}", file=file, key=f"{key}[{i}]")
            if abs(v) > 1e9:
                raise SpecError(f"out of range, got {v:g}", file=file, key=f"{key}[{i}]")
            out.append(v)
        return tuple(out)
    if isinstance(f, Flag):
        if not isinstance(value, bool):
            raise SpecError(f"must be true | false, got {_show(value)}", file=file, key=key)
        return value
    if isinstance(f, Points):
        if value is None and f.default is None:
            return None
        if not isinstance(value, (list, tuple)) or (f.count is not None and len(value) != f.count):
            n = f"{f.count} " if f.count is not None else ""
            raise SpecError(f"must be a list of {n}points [X, Y], got {_show(value)}"
                            + (f" of {len(value)}" if isinstance(value, (list, tuple)) else ""), file=file, key=key)
        pts = []
        for i, item in enumerate(value):
            if not isinstance(item, (list, tuple)) or len(item) != 2:
                raise SpecError(f"must be a point [X, Y], got {_show(item)}", file=file, key=f"{key}[{i}]")
            pt = tuple(_number(c, f"{key}[{i}]", file, f.length, unit) for c in item)
            if max(abs(c) for c in pt) > 1e9:
                raise SpecError("out of range (|value| <= 1e9)", file=file, key=f"{key}[{i}]")
            pts.append(pt)
        return tuple(pts)
    if isinstance(f, Params):
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise SpecError(f"must be a mapping name: number, got {_show(value)}", file=file, key=key)
        if len(value) > 64:
            raise SpecError("too many parameters (limit 64)", file=file, key=key)
        out = {}
        from .expr import RESERVED

        for name, v in value.items():
            k = f"{key}.{name}"
            if not isinstance(name, str) or not IDENT_RE.match(name):
                raise SpecError("parameter names must be identifiers", file=file, key=k)
            if name.startswith("__"):
                raise SpecError("names starting with '__' are not allowed", file=file, key=k)
            if name in RESERVED:
                raise SpecError(f"{name!r} is reserved (x, y, pi and the function names)", file=file, key=k)
            fv = _number(v, k, file, None, unit)
            if abs(fv) > 1e12:
                raise SpecError(f"out of range (|value| <= 1e12), got {fv:g}", file=file, key=k)
            out[name] = fv
        return out
    if isinstance(f, Inertia):
        if value in ("solid", "hollow"):
            return {"solid": 0.4, "hollow": 2.0 / 3.0}[value]
        if isinstance(value, str):
            raise SpecError(f"must be solid | hollow | a number k = I/(m r^2), got {_show(value)}"
                            f"{_suggest(value, ('solid', 'hollow'))}", file=file, key=key)
        v = _number(value, key, file, None, unit)
        if not 0 <= v <= 10:
            raise SpecError(f"k = I/(m r^2) must be in [0, 10], got {v:g}", file=file, key=key)
        return v
    raise AssertionError(f)  # pragma: no cover


_field = read_field      # the name this module's checks use


def _default(f: Any) -> Any:
    if isinstance(f, Params):
        return {}
    if isinstance(f, Inertia):
        return 0.4
    return f.default


def validate(raw: Any, file: str = "<spec>") -> Spec:
    """Validate a parsed YAML document into a :class:`Spec`."""
    if raw is None:
        raise SpecError("empty spec", file=file)
    if not isinstance(raw, dict):
        raise SpecError(f"top level must be a mapping of sections, got {type(raw).__name__}", file=file)
    for key in raw:
        if not isinstance(key, str):
            raise SpecError(f"keys must be strings, got {_show(key)}", file=file)
        if key not in SCHEMA and key not in TOP_KEYS:
            raise SpecError(f"unknown key{_suggest(key, list(SCHEMA) + list(TOP_KEYS))}", file=file, key=key)
    units = _field(TOP_KEYS["units"], raw.get("units", "mm"), "units", file, "mm")
    name = raw.get("name")
    if name is None:
        name = Path(file).stem if file and not file.startswith("<") else "fabkit"
        if not NAME_RE.match(name):
            name = "fabkit"
    elif not isinstance(name, str) or not NAME_RE.match(name):
        raise SpecError("must be 1-64 characters of letters, digits, '_', '.', '-' (it names the output files), "
                        f"got {_show(name)}", file=file, key="name")
    sections: dict[str, Section] = {}
    for sec, fields in SCHEMA.items():
        if sec not in raw:
            continue
        body = raw[sec]
        if sec in LIST_SECTIONS:
            sections[sec] = _list_section(sec, fields, body, file, units)
            continue
        if body is None:
            body = {}
        if not isinstance(body, dict):
            raise SpecError(f"must be a mapping, got {_show(body)}", file=file, key=sec)
        sections[sec] = _section(sec, sec, fields, body, file, units)
    _cross_checks(sections, file, units)
    return Spec(path=file, name=name, units=units, sections=sections, raw=raw)


def _section(name: str, where: str, fields: dict, body: dict, file: str, units: str) -> Section:
    """One mapping validated against ``fields``; ``where`` prefixes its keys in errors."""
    values = {}
    for key in body:
        if not isinstance(key, str) or key not in fields:
            raise SpecError(f"unknown key{_suggest(key, fields)}", file=file, key=f"{where}.{key}")
    for key, f in fields.items():
        dotted = f"{where}.{key}"
        if key in body:
            values[key] = _field(f, body[key], dotted, file, units)
        else:
            d = _default(f)
            if d is REQUIRED:
                raise SpecError("missing key", file=file, key=dotted)
            values[key] = d
    return Section(name, values)


def _list_section(sec: str, fields: dict, body: Any, file: str, units: str) -> tuple:
    """A list of mappings (``tools``): a tuple of Sections, errors naming ``tools[i].key``."""
    if not isinstance(body, list) or not body:
        raise SpecError(f"must be a non-empty list of mappings, got {_show(body)}", file=file, key=sec)
    if len(body) > MAX_TOOLS:
        raise SpecError(f"at most {MAX_TOOLS} entries, got {len(body)}", file=file, key=sec)
    out = []
    for i, item in enumerate(body):
        where = f"{sec}[{i}]"
        if not isinstance(item, dict):
            raise SpecError(f"must be a mapping, got {_show(item)}", file=file, key=where)
        out.append(_section(sec, where, fields, item, file, units))
    return tuple(out)


def _tool_checks(s: dict, file: str) -> None:
    """tool / tools / roughing together: unique numbers, bull corner radii, depths of
    cut, the roughing tool and rest tools known, roughing not with machining.stepdown."""
    if "tool" in s and s["tool"].depth_of_cut is None:
        s["tool"]._values["depth_of_cut"] = s["tool"].diameter
    numbers: dict[int, str] = {}
    if "tool" in s and s["tool"].number is not None:
        numbers[s["tool"].number] = "tool.number"
    for i, t in enumerate(s.get("tools", ())):
        w = f"tools[{i}]"
        if t.number in numbers:
            raise SpecError(f"tool number {t.number} is already {numbers[t.number]}", file=file, key=f"{w}.number")
        numbers[t.number] = f"{w}.number"
        R = 0.5 * t.diameter
        if t.shape == "bull":
            if t.corner_radius is None:
                raise SpecError("a bull nose needs its corner_radius (0 < r <= diameter/2)", file=file,
                                key=f"{w}.corner_radius")
            if not t.corner_radius <= R:
                raise SpecError(f"must be <= diameter/2 ({R:g} mm), got {t.corner_radius:g}", file=file,
                                key=f"{w}.corner_radius")
        elif t.corner_radius is not None:
            raise SpecError(f"only a bull nose has a corner_radius (this tool is {t.shape})", file=file,
                            key=f"{w}.corner_radius")
        if t.reach is None:
            t._values["reach"] = math.inf
        if t.depth_of_cut is None:
            t._values["depth_of_cut"] = t.diameter
    if "roughing" not in s:
        return
    r = s["roughing"]
    if "machining" in s and s["machining"].stepdown is not None:
        raise SpecError("roughing with its own tool (the roughing section) and machining.stepdown (roughing with "
                        "the finishing ball) are exclusive: remove one", file=file, key="roughing")
    listed = {t.number: (i, t) for i, t in enumerate(s.get("tools", ()))}
    if r.tool not in listed:
        where = "tool.number, the finishing tool" if r.tool in numbers else "not in `tools`"
        raise SpecError(f"tool {r.tool}: {where}; roughing.tool must be a number from `tools` "
                        f"({', '.join(str(n) for n in listed) or 'none listed'})", file=file, key="roughing.tool")
    i, t = listed[r.tool]
    if r.stepdown > t.depth_of_cut:
        raise SpecError(f"must be <= the roughing tool's depth_of_cut ({t.depth_of_cut:g} mm, tools[{i}]), got "
                        f"{r.stepdown:g}", file=file, key="roughing.stepdown")
    if r.stepover is None:
        r._values["stepover"] = 0.45 * t.diameter
    elif r.stepover > t.diameter:
        raise SpecError(f"must be <= the roughing tool's diameter ({t.diameter:g} mm), got {r.stepover:g}",
                        file=file, key="roughing.stepover")
    if "stock" in s:
        from .tolerances import DEFAULT

        levels = s["stock"].thickness / r.stepdown
        if levels > DEFAULT.max_rough_levels:
            raise SpecError(f"{r.stepdown:g} mm would rough up to {levels:.3g} levels, more than the limit "
                            f"{DEFAULT.max_rough_levels}; raise the stepdown", file=file, key="roughing.stepdown")
    if "tool" in s and r.leave >= s["tool"].depth_of_cut:
        raise SpecError(f"must be < the finishing tool's depth_of_cut ({s['tool'].depth_of_cut:g} mm): the finish "
                        f"would cut {r.leave:g} mm or more everywhere, got {r.leave:g}", file=file, key="roughing.leave")
    if "stock" in s:
        deep = s["stock"].depth_limit if s["stock"].depth_limit is not None else s["stock"].thickness
        if r.leave >= deep:
            raise SpecError(f"must be < the stock's depth ({deep:g} mm, stock.depth_limit): nothing would be "
                            f"roughed, got {r.leave:g}", file=file, key="roughing.leave")
    finish_no = s["tool"].number if "tool" in s else None
    rest = r.rest
    if rest is None:
        rest = ()
        r._values["rest"] = None
    out = []
    for j, n in enumerate(rest):
        key = f"roughing.rest[{j}]"
        if n != int(n):
            raise SpecError(f"must be a tool number, got {n:g}", file=file, key=key)
        n = int(n)
        if n == r.tool:
            raise SpecError(f"tool {n} is the roughing tool; rest passes need a smaller tool", file=file, key=key)
        if n not in listed and n != finish_no:
            raise SpecError(f"tool {n} is not in `tools` (nor tool.number)", file=file, key=key)
        out.append(n)
    if out and out[-1] != finish_no and "tool" in s:
        last = listed[out[-1]][1] if out[-1] in listed else None
        if last is not None and last.diameter > s["tool"].diameter:
            raise SpecError(f"the last rest tool (T{out[-1]}, {last.diameter:g} mm) is larger than the finishing "
                            f"tool ({s['tool'].diameter:g} mm): the finish would meet what it cannot reach; end "
                            f"with the finishing tool"
                            + (f" ({finish_no})" if finish_no is not None else "") + " or a smaller one",
                            file=file, key=f"roughing.rest[{len(out) - 1}]")
    r._values["rest"] = tuple(out) if r.rest is not None else None


def _cross_checks(s: dict[str, Section], file: str, units: str = "mm") -> None:
    _tool_checks(s, file)
    if "surface" in s:
        from .expr import check_syntax

        try:
            check_syntax(s["surface"].height, frozenset(s["surface"].params))
        except SpecError as exc:
            raise exc.with_location(file=file) from None
    if "surface" in s:
        _footprint_checks(s["surface"], file, MM_PER[units])
        if "tool" in s:
            d = s["tool"].diameter
            for ax in ("x", "y"):
                lo, hi = getattr(s["surface"], ax)
                width_mm = (hi - lo) * MM_PER[units]
                if width_mm < d:
                    raise SpecError(f"the footprint is {width_mm:.4g} mm wide, narrower than the tool "
                                    f"(tool.diameter {d:g} mm): the ball-end mill cannot shape it",
                                    file=file, key=f"surface.{ax}")
    if "machining" in s:
        _machining_checks(s, file)
    if "stock" in s:
        st = s["stock"]
        if st.depth_limit is None:
            st._values["depth_limit"] = st.thickness
        elif st.depth_limit > st.thickness:
            raise SpecError(f"must be <= stock.thickness ({st.thickness:g} mm), got {st.depth_limit:g}",
                            file=file, key="stock.depth_limit")
    if "tool" in s and s["tool"].reach is None:
        s["tool"]._values["reach"] = math.inf
    if "ramp" in s:
        h = s["ramp"].heights
        if len(h) == 2 and not h[0] < h[1]:
            raise SpecError(f"a range [min, max] needs min < max, got [{h[0]:g}, {h[1]:g}]",
                            file=file, key="ramp.heights")
        rp = s["ramp"]
        if rp.profile == "straight":
            for key in ("angle", "length"):
                if getattr(rp, key) is None:
                    raise SpecError("a straight ramp needs ramp.angle (degrees) and ramp.length (along its "
                                    "surface)", file=file, key=f"ramp.{key}")
        elif rp.length is not None:
            raise SpecError("describes a straight ramp: fabkit's own ramp is sized from ramp.heights (set "
                            "ramp.profile: straight for your own incline)", file=file, key="ramp.length")
    if "simulation" in s and "surface" in s:
        sim, sur = s["simulation"], s["surface"]
        x0, x1 = sur.x
        if not x0 <= sim.start <= x1:
            raise SpecError(f"must lie in surface.x [{x0:g}, {x1:g}], got {sim.start:g}",
                            file=file, key="simulation.start")
        y0, y1 = sur.y
        if not y0 < sim.y0 < y1:
            raise SpecError(f"must lie inside surface.y [{y0:g}, {y1:g}], got {sim.y0:g}",
                            file=file, key="simulation.y0")
        for ax, (lo, hi) in (("x", sur.x), ("y", sur.y)):
            if not 2 * sim.margin < hi - lo:
                raise SpecError(f"{sim.margin:g} leaves no room in surface.{ax} [{lo:g}, {hi:g}] (the ball must "
                                f"stay this far inside the footprint: need 2 x margin < {hi - lo:g})",
                                file=file, key="simulation.margin")


#: the narrowest footprint, mm: below it the block can be neither milled nor simulated
MIN_FOOTPRINT_MM = 0.1


def _footprint_checks(sur: Section, file: str, scale: float) -> None:
    """surface.x / surface.y must be real widths: at least MIN_FOOTPRINT_MM (``scale``:
    mm per design unit), and wide against their own magnitude (else the grids
    collapse onto a few doubles)."""
    for ax in ("x", "y"):
        lo, hi = getattr(sur, ax)
        width_mm = (hi - lo) * scale
        if not width_mm >= MIN_FOOTPRINT_MM or not (hi - lo) >= 1e-9 * max(abs(lo), abs(hi)):
            raise SpecError(f"the footprint is {width_mm:.3g} mm wide: at least {MIN_FOOTPRINT_MM:g} mm "
                            f"(and more than 1e-9 of its coordinates) is needed to mill or simulate it",
                            file=file, key=f"surface.{ax}")


def _machining_checks(s: dict[str, Section], file: str) -> None:
    """Numbers the program writes must survive its rounding (to 1 %): a spindle of
    0.4 rpm would be written S0, a feed of 0.0001 mm/min F0; tolerance and
    stepdown must be representable in the program's decimals, and the roughing
    levels bounded."""
    from .tolerances import DEFAULT

    m = s["machining"]
    inch = m.units == "in"
    per = PROGRAM_UNITS[m.units].mm_per_unit
    fdec = PROGRAM_UNITS[m.units].feed_decimals
    unit = "in/min" if inch else "mm/min"
    # the machining section's rates and each tool's own (tools[i].feed, .plunge, .spindle)
    owners = [("machining", m)] + [(f"tools[{i}]", t) for i, t in enumerate(s.get("tools", ()))]
    for where, sec in owners:
        for key, word, dec, u in (("feed", "F", fdec, unit), ("plunge", "F", fdec, unit),
                                  ("spindle", "S", 0, "rpm")):
            val = getattr(sec, key)
            if val is None:
                continue
            v = val / (per if u != "rpm" else 1.0)
            r = program_rounding(v, dec)
            if r == 0 or abs(r - v) > 0.01 * v:
                least = 50 * 10.0 ** -dec
                step = f"{10.0 ** -dec:g} {u}" if dec else f"whole {u}"
                raise SpecError(f"{v:g} {u} would be written {word}{r:.{dec}f} (the program writes {step}): "
                                f"give at least {least:g} {u}", file=file, key=f"{where}.{key}")
    # coordinates get at most 6 decimals in program units; the rounding (half a unit in the
    # last place) must stay within tolerance / 20 (gcode.MachineProfile.decimals)
    finest = finest_tolerance(m.units)
    if m.tolerance < finest:
        raise SpecError(f"{m.tolerance:g} mm is finer than the program can carry (limit {finest:g} mm: "
                        f"coordinates have at most 6 decimals in {m.units})", file=file, key="machining.tolerance")
    if "roughing" in s:
        rg = s["roughing"]
        for key in ("stepdown", "stepover"):
            v = getattr(rg, key)
            if v is not None and v < finest:
                raise SpecError(f"{v:g} mm is finer than the program can carry (limit {finest:g} mm)",
                                file=file, key=f"roughing.{key}")
        if m.dialect == "linuxcnc" and "tool" in s and s["tool"].number is None:
            raise SpecError("a linuxcnc job with roughing changes tools with M6 (T<n> M6 G43 H<n>): the "
                            "finishing tool needs its number too", file=file, key="tool.number")
    if m.stepdown is not None:
        if m.stepdown < finest:
            raise SpecError(f"{m.stepdown:g} mm is finer than the program can carry (limit {finest:g} mm)",
                            file=file, key="machining.stepdown")
        if "stock" in s:
            depth = s["stock"].depth_limit if s["stock"].depth_limit is not None else s["stock"].thickness
            levels = depth / m.stepdown
            if levels > DEFAULT.max_rough_levels:
                raise SpecError(f"{m.stepdown:g} mm would rough up to {levels:.3g} levels down to stock.depth_limit "
                                f"({depth:g} mm), more than the limit {DEFAULT.max_rough_levels}; raise the stepdown",
                                file=file, key="machining.stepdown")
