"""``--vary KEY=LO:HI:N`` and ``KEY=V1,V2,...``: the spec keys a design study may vary,
their values checked by the spec's own rules, and the grid of their combinations.

Used by ``fabkit explore`` (:func:`parse_vary`, :func:`design_grid`) and ``fabkit
design`` (its ``KEY=LO:HI`` bounds reuse :func:`check_interval` and :func:`refuse_key`).
Pure: no printing, no files; bad input is a SpecError naming the option.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from .errors import SpecError
from .spec import suggest

MAX_DESIGNS = 10_000   # designs in one grid


@dataclass(frozen=True)
class Vary:
    """One axis of a design grid: a dotted spec key and its values."""

    key: str
    values: tuple


def variable_keys(spec) -> list[str]:
    """The dotted keys a grid may vary in ``spec``: every number or choice field
    of the sections the spec has, and ``surface.params.<name>`` for its params."""
    from .spec import SCHEMA, Choice, Inertia, Num

    keys = []
    for sec, fields in SCHEMA.items():
        if not spec.has(sec):
            continue
        for name, f in fields.items():
            if isinstance(f, (Num, Choice, Inertia)):
                keys.append(f"{sec}.{name}")
        if sec == "surface":
            keys.extend(f"surface.params.{p}" for p in spec.surface.params)
    return keys


def all_keys() -> list[str]:
    from .spec import SCHEMA

    return [f"{sec}.{name}" for sec, fields in SCHEMA.items() for name in fields]


def parse_number(text: str, what: str, flag: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise SpecError(f"{what} must be a number, got {text.strip()!r}", key=flag) from None
    if not math.isfinite(x):
        raise SpecError(f"{what} must be finite, got {text.strip()!r}", key=flag)
    return x


#: the narrowest searchable or sampled interval LO:HI, relative to its ends' magnitude (the
#: values must stay distinct floats, and a search's step, 1/1000 of the interval, too)
MIN_SPAN_REL = 1e-9
#: and in absolute terms (a step far above the smallest normal float)
MIN_SPAN_ABS = 1e-100


def check_value(key: str, value, spec, flag: str, what: str = "a value"):
    """The value ``value`` of ``key`` (one end of a ``--vary`` interval or one listed value)
    checked by the spec's own rules for that key (range, whole number, choice), as if it
    were written in the spec; returns it as the spec would read it. SpecError naming
    ``flag`` and the key."""
    from .spec import SCHEMA, Params, read_field

    sec, _, rest = key.partition(".")
    try:
        if key.startswith("surface.params."):
            return read_field(Params(), {rest.split(".", 1)[1]: value}, "surface.params", "", spec.units)[
                rest.split(".", 1)[1]]
        if rest.count(".") == 1:          # an end of a footprint interval (surface.x.lo)
            if not abs(value) <= 1e9:
                raise SpecError(f"out of range (|value| <= 1e9), got {value:g}")
            return value
        return read_field(SCHEMA[sec][rest], value, key, "", spec.units)
    except SpecError as exc:
        raise SpecError(f"{key}: {what}: {exc.detail}", key=flag) from None


def check_interval(key: str, lo: float, hi: float, spec, flag: str) -> None:
    """Both ends of ``key=LO:HI`` inside the key's range (:func:`check_value`), LO < HI,
    and the interval wide enough to be divided (:data:`MIN_SPAN_REL`, :data:`MIN_SPAN_ABS`)
    and not so wide that HI - LO overflows. SpecError naming ``flag``."""
    from .spec import SCHEMA

    sec, _, rest = key.partition(".")
    if getattr(SCHEMA.get(sec, {}).get(rest), "integer", False):     # whole-number key: its whole numbers
        first, last = math.ceil(lo), math.floor(hi)
        if last < first:
            raise SpecError(f"{key}: no whole number in {lo:g}:{hi:g}", key=flag)
        check_value(key, float(first), spec, flag, "LO")
        check_value(key, float(last), spec, flag, "HI")
        return
    check_value(key, lo, spec, flag, "LO")
    check_value(key, hi, spec, flag, "HI")
    if not hi > lo:
        raise SpecError(f"{key}: need LO < HI, got {lo:g}:{hi:g}", key=flag)
    span = hi - lo
    if not math.isfinite(span):
        raise SpecError(f"{key}: the interval {lo:g}:{hi:g} is too wide (HI - LO overflows)", key=flag)
    need = max(MIN_SPAN_ABS, MIN_SPAN_REL * max(abs(lo), abs(hi)))
    if span < need:
        raise SpecError(f"{key}: the interval {lo:.17g}:{hi:.17g} is too narrow to divide (HI - LO = {span:g}, "
                        f"need >= {need:g})", key=flag)


def refuse_key(key: str, allowed, spec, flag: str, not_variable: str):
    """Raise the SpecError for a ``--vary`` key outside ``allowed``: a section the
    spec lacks, a key that exists but cannot be varied (``not_variable`` says why),
    an unknown surface parameter or an unknown key, with a did-you-mean."""
    section = key.split(".")[0]
    if key in all_keys() and not spec.has(section):
        raise SpecError(f"{key}: the spec has no {section} section", key=flag)
    if key in all_keys():
        raise SpecError(f"{key}: {not_variable}", key=flag)
    if key.startswith("surface.params."):
        names = list(spec.surface.params) if spec.has("surface") else []
        raise SpecError(f"{key}: no such parameter in surface.params"
                        f"{suggest(key, [f'surface.params.{n}' for n in names])}", key=flag)
    raise SpecError(f"unknown key {key!r}{suggest(key, allowed)}", key=flag)


def split_key(text, spec, flag: str, form: str, allowed, not_variable: str) -> tuple[str, str]:
    """``KEY=REST`` -> (key, rest), the key one of ``allowed`` (else :func:`refuse_key`'s
    error naming ``flag``); ``form`` is the expected shape, for the error."""
    text = str(text)
    if "=" not in text:
        raise SpecError(f"expected {form}, got {text!r}", key=flag)
    key, _, rhs = text.partition("=")
    key, rhs = key.strip(), rhs.strip()
    if key not in allowed:
        refuse_key(key, allowed, spec, flag, not_variable)
    return key, rhs


def parse_vary(text: str, spec, flag: str = "--vary") -> Vary:
    """``KEY=LO:HI:N`` (N evenly spaced values, both ends included) or
    ``KEY=V1,V2,...`` (values as given; words for choice keys such as
    ``simulation.model=full,simplified``). The key must be a number or choice
    key of a section the spec has (did-you-mean otherwise); values of whole-number
    keys must be whole. Raises SpecError naming ``--vary``."""
    from .spec import SCHEMA, Choice, Inertia, Num

    key, rhs = split_key(text, spec, flag, "KEY=LO:HI:N (or KEY=V1,V2,...)", variable_keys(spec),
                         "not a number or choice key (it cannot be varied on a grid)")
    field = None
    if not key.startswith("surface.params."):
        sec, name = key.split(".")
        field = SCHEMA[sec][name]
    if not rhs:
        raise SpecError(f"{key}: no values (expected {key}=LO:HI:N)", key=flag)
    if ":" in rhs:
        parts = rhs.split(":")
        if len(parts) != 3:
            raise SpecError(f"{key}: expected LO:HI:N, got {rhs!r}", key=flag)
        lo, hi = parse_number(parts[0], "LO", flag), parse_number(parts[1], "HI", flag)
        n = parse_number(parts[2], "N", flag)
        if n != int(n) or n < 1:
            raise SpecError(f"{key}: N must be a whole number >= 1, got {parts[2].strip()}", key=flag)
        if n > MAX_DESIGNS:
            raise SpecError(f"{key}: N = {n:.6g} exceeds the limit of {MAX_DESIGNS} designs", key=flag)
        if n == 1 and lo != hi:
            raise SpecError(f"{key}: N = 1 needs LO = HI, got {lo:g}:{hi:g}", key=flag)
        if isinstance(field, Choice):
            raise SpecError(f"{key}: a choice key takes a list of words, e.g. {key}="
                            f"{','.join(field.options)}", key=flag)
        if n >= 2:
            check_interval(key, lo, hi, spec, flag)
        values = [float(x) for x in np.linspace(lo, hi, int(n))]
        if n >= 2 and len(set(values)) != len(values):
            raise SpecError(f"{key}: {int(n)} values between {lo:g} and {hi:g} are not distinct numbers "
                            "(a smaller N or a wider interval)", key=flag)
    else:
        values = []
        for item in rhs.split(","):
            item = item.strip()
            if not item:
                raise SpecError(f"{key}: empty value in {rhs!r}", key=flag)
            if isinstance(field, Choice) or (isinstance(field, Inertia) and item in ("solid", "hollow")):
                values.append(item)
            else:
                values.append(parse_number(item, "a value", flag))
        if len(values) > MAX_DESIGNS:
            raise SpecError(f"{key}: {len(values)} values exceed the limit of {MAX_DESIGNS} designs", key=flag)
    if isinstance(field, Num) and field.integer:
        for x in values:
            if x != int(x):
                raise SpecError(f"{key}: must be a whole number, got {x:g}", key=flag)
        values = [int(x) for x in values]
    if len(set(map(repr, values))) != len(values):
        raise SpecError(f"{key}: repeated values", key=flag)
    for x in values:
        check_value(key, x, spec, flag, f"the value {x:g}" if isinstance(x, float) else f"the value {x}")
    return Vary(key, tuple(values))


def design_grid(varies: list[Vary]) -> list[dict]:
    """Every combination of the axes' values as ``{key: value}``, in the order of
    the axes (the last axis varies fastest). One empty design for no axes."""
    keys = [v.key for v in varies]
    if len(set(keys)) != len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise SpecError(f"{dup} is varied twice", key="--vary")
    n = 1
    for v in varies:
        n *= len(v.values)
    if n > MAX_DESIGNS:
        raise SpecError(f"the grid has {n} designs (limit {MAX_DESIGNS})", key="--vary")
    return [dict(zip(keys, combo)) for combo in itertools.product(*(v.values for v in varies))]
