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


# ----------------------------------------------------------------------------
# the first run: every kernel the shipped commands need for a spec, compiled once
# ----------------------------------------------------------------------------
def _toolpath_signatures():
    """The argument types the toolpath's formula-free kernels are called with by ``fabkit
    gcode`` and ``fabkit report`` (the material bound, its rim search, the point spacing's
    simplification, the verification's swept cut): compiling them ahead needs no job."""
    from numba import types as T

    f8, i8, b1 = T.float64, T.int64, T.boolean

    def A(dt, nd, readonly=False):
        return T.Array(dt, nd, "C", readonly=readonly)

    from .toolpath import kernels, scallop_kernels, spacing_kernels

    out = [(scallop_kernels.sweep_balls, (A(f8, 1), A(f8, 1, True), A(f8, 2), A(f8, 2), A(f8, 1), f8, i8,
                                          A(f8, 2), A(f8, 2), f8)),
           (scallop_kernels.rim_cut, (A(f8, 1), A(f8, 2), A(f8, 1, True), A(f8, 2), A(f8, 2), A(b1, 2),
                                      A(f8, 1), A(f8, 1), A(f8, 1), f8, A(f8, 1), f8, f8, i8)),
           (spacing_kernels.simplify, (A(i8, 1), A(f8, 1), A(f8, 1), A(b1, 1), A(b1, 1), f8, i8))]
    mod = kernels.module()
    if mod is not None:
        out.append((mod.lowest_batch_sorted, (A(f8, 1), A(f8, 1), A(i8, 1), A(i8, 1), A(i8, 1), A(f8, 2),
                                              A(f8, 2), f8, A(i8, 1), b1, A(f8, 1), A(f8, 1))))
    return out


def cold_kernels(spec) -> dict:
    """What a first run of ``fabkit gcode``, ``check`` or ``report`` on ``spec`` would compile,
    in seconds of CPU (estimates measured on the 2-core reference machine): ``simulator``
    (the launch engine of the spec's model and its surface functions; 0 without the
    sections that simulate, or when cached), ``toolpath`` (the drop cutter for the formula
    and the formula-free kernels; 0 without stock and tool, or when cached), and whether
    the part compiled once per installation is among them (``simulator_install``: the
    engine; ``toolpath_install``: the drop cutter's kernel or the formula-free ones)."""
    out = {"simulator": 0.0, "toolpath": 0.0, "simulator_install": False, "toolpath_install": False}
    if spec.has("simulation") and spec.has("surface"):
        from .physics.integrate import ENGINE_MODELS, is_stiff
        from .physics.models import problem_from_spec

        problem = problem_from_spec(spec)
        if problem.model in ENGINE_MODELS and not is_stiff(problem, problem.t_max):
            from .physics.engine import batch

            if not batch.is_compiled(problem):
                tpl = batch.codegen.template_of(problem.model)
                cold_engine = not batch._cached(batch.codegen.write_engine(tpl), "run_batch")
                out["simulator"] = batch.compile_estimate() + 2.0 if cold_engine else 2.0
                out["simulator_install"] = cold_engine
    if spec.has("tool") and spec.has("stock"):
        from .surface import Surface
        from .toolpath import kernels

        out["toolpath"] = kernels.cold_build_seconds(Surface.from_spec(spec))
        out["toolpath_install"] = out["toolpath"] > kernels.BUILD_FORMULA_S + 1e-9
    return out


def prepare(spec, say=None, *, need=("simulator", "toolpath"), quiet: bool = False) -> dict:
    """Compile ahead what ``fabkit gcode``, ``check`` and ``report`` need for ``spec`` and
    the caches lack, and say so first with the total to expect: ``compiling fabkit's
    kernels for this surface (once, about N s of CPU in all: the simulator A s, the
    toolpath's kernels B s; then gcode, check and report load them)``, through
    ``say(message)`` (a stage bar's stage) or, on a terminal, stderr.

    ``need``: the parts the calling command uses (gcode: the toolpath; check and sweep:
    the simulator; report: both), compiled whenever cold. The other part is compiled
    too when its once-per-installation kernels are cold (the first run after installing:
    the next command then loads everything); a new formula later costs each part a
    second or two, in the command that needs it. Returns :func:`cold_kernels`' estimate
    of what was compiled (0: nothing). A kernel that cannot be compiled (no writable
    cache) is left to the code that needs it (the numpy path)."""
    import sys

    cold = cold_kernels(spec)
    do = {part: cold[part] > 0 and (part in need or cold[f"{part}_install"]) for part in ("simulator", "toolpath")}
    total = sum(cold[p] for p in do if do[p])
    if total <= 0:
        return {"simulator": 0.0, "toolpath": 0.0}
    parts = [f"{name} about {round(cold[p])} s" for p, name in (("simulator", "the simulator"),
                                                                ("toolpath", "the toolpath's kernels")) if do[p]]
    msg = (f"compiling fabkit's kernels for this surface (once, about {max(1, round(total))} s of CPU in all: "
           f"{', '.join(parts)}; then gcode, check and report load them)")
    if say is not None:
        say(msg)
    elif not quiet and sys.stderr.isatty():
        sys.stderr.write(msg + "\n")
        sys.stderr.flush()
    if do["simulator"]:
        from .physics.engine.batch import engine
        from .physics.models import problem_from_spec

        engine(problem_from_spec(spec))
    if do["toolpath"]:
        from .surface import Surface
        from .toolpath import kernels

        kernels.kernel_for(Surface.from_spec(spec))
        if kernels.enabled():
            for disp, sig in _toolpath_signatures():
                try:
                    disp.compile(sig)
                except Exception:   # pragma: no cover - a kernel numba cannot build: the numpy code runs
                    pass
    return {p: (cold[p] if do[p] else 0.0) for p in do}
