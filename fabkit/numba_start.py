"""numba's start-up when fabkit's compiled code loads from the cache.

Before loading anything from its cache, numba's loader
(``numba.core.caching.Cache.load_overload``) calls the CPU target's ``refresh()``:
it imports and installs every lowering registry numba has (its array math, whose
BLAS check imports all of scipy.linalg, linear algebra, random generators,
polynomials, typed containers, datetimes, ...). That is what *compiling* needs, and
it costs 0.55-0.7 s of CPU once per process on the 2-core reference machine: a
quarter of a small ``fabkit gcode`` run (benchmarks/notes_gcode_startup.md). Loading
compiled code needs none of it: the cached object code is linked against symbols
numba registers when it is imported (its C helpers, the exceptions, the math
library) and against its runtime (NRT), which this module initialises.

:func:`install` (run on import of this module, which every fabkit module using numba
imports first) makes the loader take that short path for fabkit's own functions
(those defined in the fabkit package or in its cache of generated modules,
:func:`fabkit.physics.engine.codegen.cache_dir`):

* it initialises numba's runtime and imports numba's first-class function types (so
  the drop cutter's formula callbacks type as they did when they were compiled, and
  the cache's index finds them);
* it loads the cached code; on a miss, or any error, it runs the full ``refresh()``
  and numba's own loader, and numba compiles as before (its compiler refreshes the
  contexts itself too).

Anything else (another package's cached functions in the same process) goes
through numba's own loader unchanged. ``FABKIT_NUMBA_FULL_START=1`` turns the short
path off. The same compiled code runs either way: tests/test_numba_start.py checks
programs byte for byte and that a warm run imports none of the registries.
"""

from __future__ import annotations

import os
import threading

_LOCK = threading.Lock()
_STATE = {"installed": False, "full": False, "light_loads": 0}


def _fabkit_roots() -> tuple[str, ...]:
    here = os.path.dirname(os.path.abspath(__file__))
    roots = [here + os.sep]
    try:
        from .physics.engine import codegen

        roots.append(str(codegen.cache_dir().resolve()) + os.sep)
    except Exception:  # pragma: no cover - a cache folder that cannot be named
        pass
    return tuple(roots)


def _ours(cache, roots) -> bool:
    fn = getattr(cache, "_py_func", None)
    code = getattr(fn, "__code__", None)
    path = getattr(code, "co_filename", None)
    if not path:
        return False
    path = os.path.realpath(path)
    return path.startswith(roots)


def install() -> bool:
    """Make numba's cache loader take the short path for fabkit's functions (once per
    process). False where it cannot (``FABKIT_NUMBA_FULL_START``, or a numba whose
    loader this does not know: numba's own start-up runs)."""
    with _LOCK:
        if _STATE["installed"]:
            return True
        if os.environ.get("FABKIT_NUMBA_FULL_START", "") not in ("", "0"):
            return False
        try:
            from numba.core import caching
            from numba.core.runtime import rtsys
            from numba.experimental import function_type  # noqa: F401  (first-class function types)
        except ImportError:  # pragma: no cover - numba missing, or moved its internals
            return False
        orig = getattr(caching.Cache, "load_overload", None)
        if orig is None or not hasattr(caching.Cache, "_load_overload"):  # pragma: no cover
            return False
        roots = _fabkit_roots()

        def load_overload(self, sig, target_context):
            if _STATE["full"] or not _ours(self, roots):
                return orig(self, sig, target_context)
            try:
                rtsys.initialize(target_context)
                cres = self._load_overload(sig, target_context)
            except Exception:
                cres = None
            if cres is not None:
                _STATE["light_loads"] += 1
                return cres
            # a miss (numba compiles next) or a load that failed: numba's own way
            _STATE["full"] = True
            return orig(self, sig, target_context)

        load_overload.__doc__ = orig.__doc__
        caching.Cache.load_overload = load_overload
        _STATE["installed"] = True
        return True


def light_loads() -> int:
    """How many functions this process loaded by the short path."""
    return _STATE["light_loads"]


install()
