"""The on-disk cache of compiled surface formulas: what sympy computes once per formula.

:func:`fabkit.expr.compile_surface` differentiates h(x, y) exactly with sympy and
generates numpy source for h and its derivatives (``sympy.lambdify``, common
subexpressions shared). Importing sympy and differentiating cost about a second of
CPU on every run; the generated source depends only on the formula, so it is kept
here and a later run of the same formula builds its functions from the stored source
without importing sympy. The functions are built from the source in the first run
too, so the first run and every later one evaluate the same code: the same numbers,
bit for bit, as ``lambdify``'s own functions (the same source, the same numpy
functions by identity).

Entry: ``cache_dir()/formulas/fk_formula_<key>.json`` (the simulator's cache folder,
:func:`fabkit.cache.cache_dir`), the key a hash of this format's
number, the formula's text, its parameters (names and exact values: the source has
the values in it), the expression limits of the tolerances, the fabkit, sympy, numpy
and Python versions and the source of ``expr.py`` and of this module. It holds the
generated functions' source, where each free name of that source comes from
(``numpy``'s attribute, a builtin or a module) and the formula's derivative sizes
(:func:`fabkit.expr.derivative_size`, orders 2 and 3), with a checksum. Written atomically
(a temporary file renamed over it); an entry that cannot be read or parsed, or whose
key, text or checksum does not match, is a miss and is rebuilt; a cache that cannot be
written is skipped (the formula is compiled on every run, as before). Deleting the
folder is always safe.
"""

from __future__ import annotations

import ast
import builtins
import hashlib
import json
import sys
from pathlib import Path

from .cache import cache_dir, replace_quietly

#: bump on any change of the entry's layout or of what the functions are built from
FORMAT = 1
#: the generated functions of a formula, as compile_surface names them
FUNCTIONS = ("all", "h", "grad", "hess", "accel")
#: the modules a generated source may name (lambdify's numpy printer uses numpy only)
MODULES = frozenset({"numpy", "math"})
_FUNC_NAME = "_lambdifygenerated"
_HERE = Path(__file__).resolve().parent


def folder() -> Path:
    return cache_dir() / "formulas"


def _sympy_version() -> str:
    """sympy's version, read from its release file (importing sympy is what this cache
    avoids); its folder's path and the file's size and time stamp where it cannot be read."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("sympy")
        origin = Path(spec.origin).parent / "release.py"
        for line in origin.read_text().splitlines():
            if line.startswith("__version__"):
                return line.split("=", 1)[1].strip().strip("\"'")
        st = origin.stat()
        return f"{origin}:{st.st_size}:{st.st_mtime_ns}"
    except (AttributeError, OSError, TypeError, ValueError):
        return "unknown"


def key(text: str, params: tuple, tol) -> str:
    """The entry's key: ``params`` as ((name, float value), ...) in the given order."""
    import numpy as np

    from . import __version__

    limits = (tol.expr_max_chars, tol.expr_max_nodes, tol.expr_max_depth, tol.expr_max_exponent,
              tol.expr_max_number, tol.expr_max_compiled_nodes)
    parts = [f"fabkit-formula-{FORMAT}", text, repr(tuple((str(k), repr(float(v))) for k, v in params)),
             repr(limits), __version__, _sympy_version(), np.__version__,
             f"{sys.version_info[0]}.{sys.version_info[1]}",
             (_HERE / "expr.py").read_text(), (_HERE / "expr_cache.py").read_text()]
    m = hashlib.sha256()
    for p in parts:
        m.update(p.encode())
        m.update(b"\0")
    return m.hexdigest()[:32]


def _path(k: str, part: str = "") -> Path:
    return folder() / (f"fk_formula_{k}_{part}.json" if part else f"fk_formula_{k}.json")


def _checksum(body: dict) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def free_names(source: str) -> set[str]:
    """The names a generated function's source reads that it does not bind itself
    (its arguments and assignments excluded): numpy's functions and constants."""
    tree = ast.parse(source)
    bound, read = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.arg):
            bound.add(node.arg)
        elif isinstance(node, ast.Name):
            (read if isinstance(node.ctx, ast.Load) else bound).add(node.id)
        elif isinstance(node, ast.FunctionDef):
            bound.add(node.name)
    return read - bound


def rebuilt(fns: dict, sources: dict) -> tuple[dict, dict] | None:
    """``fns`` (name -> lambdify's function) rebuilt from ``sources`` (name -> its
    source) with the names they read told (:func:`origins`), and those names; None
    where one cannot be told."""
    names: dict = {}
    for name, fn in fns.items():
        got = origins(fn, sources[name])
        if got is None:
            return None
        names.update(got)
    return {name: build(sources[name], names, name) for name in fns}, names


def origins(fn, source: str) -> dict | None:
    """Where each free name of ``source`` comes from in the globals of ``fn``
    (lambdify's namespace): ``["numpy", attr]``, ``["builtins", name]`` or
    ``["module", name]``, each checked by identity; None when one cannot be told
    (the formula is then not cached)."""
    import numpy as np

    g = fn.__globals__
    out = {}
    for name in sorted(free_names(source)):
        if name in g:
            obj = g[name]
        elif hasattr(builtins, name):
            obj = getattr(builtins, name)
        else:
            return None
        if type(obj) is type(np) and getattr(obj, "__name__", None) in MODULES:
            out[name] = ["module", obj.__name__]
        elif getattr(np, name, _MISSING) is obj:
            out[name] = ["numpy", name]
        elif getattr(builtins, name, _MISSING) is obj:
            out[name] = ["builtins", name]
        else:
            return None
    return out


_MISSING = object()


def build(source: str, names: dict, label: str):
    """The function defined by ``source`` with its free names bound as ``names`` says
    (:func:`origins`). Raises ValueError on anything unexpected."""
    import importlib

    import numpy as np

    ns: dict = {"__builtins__": builtins}
    for name, (kind, attr) in names.items():
        if kind == "numpy":
            ns[name] = getattr(np, attr)
        elif kind == "builtins":
            ns[name] = getattr(builtins, attr)
        elif kind == "module" and attr in MODULES:
            ns[name] = importlib.import_module(attr)
        else:
            raise ValueError(f"unknown origin {kind!r} of {name!r}")
    missing = free_names(source) - set(ns)
    if missing:
        raise ValueError(f"unbound names {sorted(missing)}")
    code = compile(source, f"<fabkit formula {label}>", "exec")
    exec(code, ns)  # noqa: S102 - source generated by sympy from a vetted formula (fabkit.expr)
    fn = ns.get(_FUNC_NAME)
    if not callable(fn):
        raise ValueError("no generated function in the source")
    return fn


def load(k: str, text: str, part: str = "", functions: tuple = FUNCTIONS) -> tuple[dict, dict] | None:
    """The functions of entry ``k`` (name -> function) and its derivative sizes ({order:
    estimate}, :func:`fabkit.expr.derivative_size`), or None: missing, unreadable,
    corrupt or not this formula's. ``part``: a further entry of the formula (``jet3``:
    :func:`fabkit.expr.jet_raw`) with its own ``functions``."""
    try:
        data = json.loads(_path(k, part).read_text())
        body = data["body"]
        if data.get("sha256") != _checksum(body) or body.get("format") != FORMAT or body.get("key") != k \
                or body.get("text") != text:
            return None
        names = body["names"]
        sizes = {int(order): int(n) for order, n in body["sizes"].items()}
        return {f: build(body["source"][f], names, f) for f in functions}, sizes
    except (OSError, ValueError, KeyError, TypeError, AttributeError, SyntaxError, UnicodeDecodeError):
        return None


def store(k: str, text: str, sources: dict, names: dict, sizes: dict, part: str = "") -> bool:
    """Write entry ``k`` (or its ``part``) atomically; False (nothing written) where the
    cache cannot be."""
    body = {"format": FORMAT, "key": k, "text": text, "source": dict(sources),
            "names": names, "sizes": {str(order): int(n) for order, n in sizes.items()}}
    return replace_quietly(_path(k, part), json.dumps({"body": body, "sha256": _checksum(body)}, sort_keys=True))
