"""Generated surface code for the compiled engine, and the cache it lives in.

From the exact symbolic h(x, y) of the spec (:mod:`fabkit.expr`), this module
prints plain ``math`` source for h and its derivatives with common
subexpressions shared (each exponential of the surface is evaluated once), puts
it in front of a model template (:mod:`.point`; a model of its own, such as the
finite-radius ball, brings its template and the derivative orders it needs) and
the step loop (:mod:`.dop853`), and writes the module ONCE per formula to the
user cache, where numba compiles it with ``cache=True``: later runs only load it.

Key: a hash of the formula with its parameters as symbols (the values are passed
at run time, so a design study over ``surface.params`` compiles once), the names
of the parameters, the template's name and source, the step loop's source, and
the fabkit and numba versions.

Cache directory: :func:`fabkit.cache.cache_dir` (``FABKIT_CACHE_DIR`` if set, else the
user cache); deleting it is always safe. This module depends on the formula layer
(:mod:`fabkit.expr`, :mod:`fabkit.expr_cache`), never the other way.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

from ...cache import cache_dir, replace_quietly  # noqa: F401  (the engine's cache, named here too)

_HERE = Path(__file__).resolve().parent

#: the step loop, common to every model (a template: included, not imported)
ENGINE_TEMPLATE = "dop853.py"


@dataclass(frozen=True)
class Template:
    """A model for the engine: its template file (defining NV, NE, W, rhs, energy,
    kinetic, FULL, GT: see dop853.py) and the surface functions it calls, as
    ``name -> derivative list`` with each derivative a tuple of variables
    (``()`` is h, ``("x",)`` is h_x, ``("x", "y")`` is h_xy ...), plus ``"F"`` for
    F(x) = h_y(x, 0), the coupling of the nonlinear damping. ``batched``: functions
    of the same form over arrays of points, ``name(n, X, Y, OUT, P)`` (C pointers:
    OUT[m i + k] is the k-th of the m derivatives at (X[i], Y[i]), i < n), each point
    computed by the same source as the scalar function's, so to the same bits."""

    name: str
    source: str                 # file name next to this module
    functions: tuple = field(default_factory=tuple)   # ((fname, (derivs...)), ...)
    n_model_params: int = 4     # P[:n] are the model's, P[n:] the surface's
    batched: tuple = field(default_factory=tuple)     # ((fname, (derivs...)), ...)


POINT = Template(
    "point", "point.py",
    (("surface", ((), ("x",), ("y",), ("x", "x"), ("x", "y"), ("y", "y"), "F")),),
    4)

BALL = Template(
    "ball", "ball.py",
    (("jet", ((), ("x",), ("y",), ("x", "x"), ("x", "y"), ("y", "y"),
              ("x", "x", "x"), ("x", "x", "y"), ("x", "y", "y"), ("y", "y", "y"))),),
    8)

TEMPLATES = {"point": POINT, "ball": BALL}


def template_of(model: str) -> Template:
    """The template that runs ``simulation.model``: the finite ball's, or the point's
    (``full``, ``simplified``)."""
    return BALL if model == "ball" else POINT


@dataclass(frozen=True)
class Formula:
    """The surface as the engine sees it: h with its parameters as symbols."""

    h: object                 # sympy expression
    x: object
    y: object
    names: tuple              # parameter names, in the order of P[n_model_params:]
    values: tuple             # their values
    symbols: tuple            # their sympy symbols


def formula(fns) -> Formula:
    """The :class:`Formula` of compiled surface functions (``expr.SurfaceFunctions``).

    With the text and parameters at hand the parameters become symbols; otherwise
    (surface functions built some other way) the numeric expression is used as is.
    """
    import sympy as sp

    from ...expr import to_sympy

    params = dict(getattr(fns, "params", ()) or ())
    text = getattr(fns, "text", None)
    if text is not None and (params or not fns.symbolic.free_symbols - _xy(fns.symbolic)):
        h, x, y = to_sympy(text, params, symbolic=True)
        used = sorted((s for s in h.free_symbols if s.name.startswith("p_")), key=lambda s: s.name)
        names = tuple(s.name[2:] for s in used)
        return Formula(h, x, y, names, tuple(float(params[n]) for n in names), tuple(used))
    h = fns.symbolic
    syms = {s.name: s for s in h.free_symbols}
    x = syms.get("x", sp.Symbol("x", real=True))
    y = syms.get("y", sp.Symbol("y", real=True))
    return Formula(h, x, y, (), (), ())


class KnownFormula:
    """A formula whose surface module the cache already holds, found by its text
    (:func:`known_surface`): the parameters' names and values now; the sympy
    expression (``h``, ``x``, ``y``, ``symbols``: :func:`formula`) only when asked for."""

    def __init__(self, fns, names: tuple, values: tuple):
        self._fns = fns
        self._full = None
        self.names = names
        self.values = values

    def __getattr__(self, name):
        if name in ("h", "x", "y", "symbols"):
            if self._full is None:
                self._full = formula(self._fns)
            return getattr(self._full, name)
        raise AttributeError(name)


def _alias_path(fns, template: Template) -> Path | None:
    """Where the surface module of ``fns`` (a formula's text and parameter names) under
    ``template`` is recorded, or None for functions not made by expr.compile_surface."""
    from ... import expr_cache
    from ...expr import SurfaceFunctions

    if not isinstance(fns, SurfaceFunctions) or not isinstance(fns.text, str):
        return None
    names = ",".join(sorted(str(k) for k, _ in fns.params))
    k = _digest(["surface-by-text", fns.text, names, template.name, _functions_key(template), *_versions(),
                 expr_cache._sympy_version(), (_HERE.parent.parent / "expr.py").read_text()])
    return cache_dir() / "formulas" / f"fk_surface_{template.name}_{k}.json"


def known_surface(fns, template: Template = POINT):
    """(KnownFormula, surface module path) of ``fns`` under ``template`` when the cache
    has them (recorded by :func:`remember_surface`), without sympy; None otherwise (a
    missing, unreadable or inconsistent record, or a removed module: the caller builds
    them)."""
    import json

    try:
        alias = _alias_path(fns, template)
        if alias is None:
            return None
        data = json.loads(alias.read_text())
        module = cache_dir() / data["module"]
        names = tuple(data["names"])
        params = dict(fns.params)
        if Path(data["module"]).name != data["module"] or not module.is_file() \
                or not all(isinstance(n, str) and n in params for n in names):
            return None
        return KnownFormula(fns, names, tuple(float(params[n]) for n in names)), module
    except (OSError, ValueError, KeyError, TypeError):
        return None


def remember_surface(fns, template: Template, f: Formula, path: Path) -> None:
    """Record (atomically) that ``fns``' formula under ``template`` is the surface module
    ``path`` with parameters ``f.names``; a cache that cannot be written is skipped."""
    import json

    try:
        alias = _alias_path(fns, template)
    except OSError:
        return
    if alias is None:
        return
    replace_quietly(alias, json.dumps({"module": path.name, "names": list(f.names)}))


def _xy(h):
    return {s for s in h.free_symbols if s.name in ("x", "y")}


def _source(name: str) -> str:
    return (_HERE / name).read_text()


@functools.lru_cache(maxsize=1)
def _versions() -> tuple[str, ...]:
    """What every cache key depends on (fabkit, numba, Python, this generator's source):
    fixed for the process, so read once."""
    from ... import __version__

    try:
        import numba
        nv = numba.__version__
    except ImportError:  # pragma: no cover - numba is a dependency
        nv = "none"
    return (__version__, nv, f"{sys.version_info[0]}.{sys.version_info[1]}", _source("codegen.py"))


def _digest(parts) -> str:
    m = hashlib.sha256()
    for part in parts:
        m.update(part.encode())
        m.update(b"\0")
    return m.hexdigest()[:24]


def engine_key(template: Template = POINT) -> str:
    """The cache key of the engine of a model template (its source, the step loop's,
    the fabkit, numba and Python versions): the engine compiles once per install."""
    return _digest([template.name, _source(template.source), _source(ENGINE_TEMPLATE), *_versions()])


def key(f: Formula, template: Template = POINT) -> str:
    """The cache key of a formula's surface functions under a model template: the
    formula with its parameters as symbols (so their values do not count), the
    parameters' names, the template and the versions."""
    import sympy as sp

    return _digest([sp.srepr(f.h), ",".join(f.names), template.name, _functions_key(template), *_versions()])


def _functions_key(template: Template) -> str:
    """The template's surface functions, as they enter the cache keys."""
    if not template.batched:
        return repr(template.functions)
    return repr(template.functions) + " batched " + repr(template.batched)


# ----------------------------------------------------------------------------
# printing
# ----------------------------------------------------------------------------
def derivatives(f: Formula, wanted) -> list:
    """The exact derivatives ``wanted`` (tuples of 'x'/'y', or 'F') of h."""
    import sympy as sp

    var = {"x": f.x, "y": f.y}
    cache: dict = {(): f.h}

    def d(spec):
        spec = tuple(sorted(spec))
        if spec not in cache:
            cache[spec] = sp.diff(d(spec[:-1]), var[spec[-1]])
        return cache[spec]

    out = []
    for w in wanted:
        e = d(("y",)).subs(f.y, 0) if w == "F" else d(w)
        # d/dx |u| = sign(u) u'; its derivative's DiracDelta is zero almost everywhere
        out.append(e.replace(sp.DiracDelta, lambda *a: sp.Integer(0)))
    return out


def print_function(name: str, f: Formula, exprs: list, n_model_params: int) -> str:
    """Plain ``math`` source of ``name(x, y, P) -> tuple(exprs)``, common
    subexpressions shared; parameters read from P[n_model_params + i]."""
    params, subs, outs = _printed(f, exprs, n_model_params)
    lines = [f"@jit\ndef {name}(x, y, P):", *params, *subs]
    outs = ", ".join(outs)
    lines.append(f"    return ({outs},)" if len(exprs) == 1 else f"    return {outs}")
    return "\n".join(lines) + "\n"


def print_batched(name: str, f: Formula, exprs: list, n_model_params: int) -> str:
    """Plain ``math`` source of ``name(n, X, Y, OUT, P)``: OUT[m i + k] = exprs[k] at
    (X[i], Y[i]) for i < n (m = len(exprs)), each point by the very lines of
    :func:`print_function` (the same operations: the same bits); the parameters are
    read once."""
    params, subs, outs = _printed(f, exprs, n_model_params)
    m = len(exprs)
    lines = [f"@jit\ndef {name}(n, X, Y, OUT, P):", *params, "    for i in range(n):",
             "        x = X[i]", "        y = Y[i]"]
    lines += ["    " + line for line in subs]
    for k, e in enumerate(outs):
        lines.append(f"        OUT[{m} * i + {k}] = {e}" if m > 1 else f"        OUT[i] = {e}")
    return "\n".join(lines) + "\n"


def _printed(f: Formula, exprs: list, n_model_params: int):
    """The lines of a surface function: (the parameters' reads, the common
    subexpressions, the printed ``float(...)`` of each of ``exprs``)."""
    import sympy as sp
    from sympy.printing.pycode import PythonCodePrinter

    printer = PythonCodePrinter({"fully_qualified_modules": True, "standard": "python3"})
    temps = sp.numbered_symbols("_t")
    # unevaluated, as expr.cse_unevaluated: evaluating the rebuilt tree asks sympy's
    # assumptions about nested functions of the cse symbols (exponential in the nesting)
    with sp.evaluate(False):
        subs, reduced = sp.cse(exprs, symbols=temps)
    used = set()
    for e in [e for _, e in subs] + list(reduced):
        used |= e.free_symbols
    params = [f"    {s.name} = P[{n_model_params + i}]" for i, s in enumerate(f.symbols) if s in used]
    lines = [f"    {s.name} = {printer.doprint(e)}" for s, e in subs]
    return params, lines, [f"float({printer.doprint(e)})" for e in reduced]


_HEADER = """# Generated by fabkit {version}: {what}.
# Do not edit: delete this folder to rebuild (fabkit/physics/engine/codegen.py).
import math

import numpy as np
from numba import cfunc, njit, types

jit = njit(cache=True, nogil=True, error_model="numpy")
"""


def generate_surface(f: Formula, template: Template = POINT) -> str:
    """The surface module's source: one compiled C callback per surface function of
    the template, ``name(x, y, P) -> (values...)`` with P a pointer to the run-time
    parameters, and one per batched function, ``name(n, X, Y, OUT, P)``."""
    from ... import __version__

    text = " ".join(f"h(x, y) = {f.h}".split())[:2000]
    parts = [_HEADER.format(version=__version__, what=f"surface functions ({template.name} template) of "
                            f"{text}; parameters passed at run time: {', '.join(f.names) or '(none)'}")]
    for fname, wanted in template.functions:
        parts.append(f"_sig_{fname} = types.UniTuple(types.float64, {len(wanted)})("
                     "types.float64, types.float64, types.CPointer(types.float64))")
        src = print_function(fname, f, derivatives(f, wanted), template.n_model_params)
        parts.append(src.replace("@jit\n", f'@cfunc(_sig_{fname}, cache=True, error_model="numpy")\n', 1))
    for fname, wanted in template.batched:
        parts.append(f"_sig_{fname} = types.void(types.intp, types.CPointer(types.float64), "
                     "types.CPointer(types.float64), types.CPointer(types.float64), "
                     "types.CPointer(types.float64))")
        src = print_batched(fname, f, derivatives(f, wanted), template.n_model_params)
        parts.append(src.replace("@jit\n", f'@cfunc(_sig_{fname}, cache=True, error_model="numpy")\n', 1))
    return "\n\n".join(parts)


def generate_engine(template: Template = POINT) -> str:
    """The engine module's source: the model template, then the step loop."""
    from ... import __version__

    parts = [_HEADER.format(version=__version__, what=f"the launch engine, {template.name} template")]
    for src in (template.source, ENGINE_TEMPLATE):
        parts.append(f"# ---- {src} " + "-" * 60 + "\n" + _source(src))
    return "\n\n".join(parts)


def _write_once(path: Path, make) -> Path:
    """Write ``make()`` to ``path`` atomically unless it exists. An existing file is
    never rewritten: numba's cache is keyed on its time stamp."""
    if path.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.parent / f".{path.name}.{os.getpid()}.tmp"
    tmp.write_text(make())
    if not path.exists():
        os.replace(tmp, path)
    else:
        tmp.unlink(missing_ok=True)
    return path


def write_engine(template: Template = POINT) -> Path:
    """The engine module of ``template`` in the cache (written if missing)."""
    return _write_once(cache_dir() / f"fk_engine_{template.name}_{engine_key(template)}.py",
                       lambda: generate_engine(template))


def write_surface(f: Formula, template: Template = POINT) -> Path:
    """The surface module of formula ``f`` in the cache (written if missing)."""
    return _write_once(cache_dir() / f"fk_surface_{template.name}_{key(f, template)}.py",
                       lambda: generate_surface(f, template))
