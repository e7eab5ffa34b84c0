"""The toolpath's compiled kernels: loading (or building) them for a surface.

The drop cutter's kernel (the template :mod:`.dropcut`) is written once per
installation into the user cache of the simulator's engine
(:func:`fabkit.physics.engine.codegen.cache_dir`, ``FABKIT_CACHE_DIR`` if set), where
numba compiles it with ``cache=True``; the surface's functions (h and its exact first
and second derivatives) are generated from the formula by the engine's own code
generator (:func:`fabkit.physics.engine.codegen.write_surface`, a template of their
own: ``jet``, ``height`` and ``heights``, the last h at an array of points in one
call) and compiled once per formula. Later runs only load both.

``FABKIT_NO_KERNELS=1`` turns the kernels off (the numpy drop cutter runs instead:
the same heights; for comparisons). Surfaces without a formula (no ``fns`` with its
text), a cache that cannot be written and a formula numba cannot compile use the
numpy code.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

_HERE = Path(__file__).resolve().parent
KERNEL_TEMPLATE = "dropcut.py"

_LOCK = threading.RLock()
_MODS: dict = {}            # path -> module
_BY_FNS: dict = {}          # id(fns) -> (fns, Kernel | None)
#: seconds the last cold build took (compile of the kernel and the formula's functions)
last_build_s: float | None = None


def _template():
    from ...physics.engine import codegen

    return codegen.Template(
        "toolpath", KERNEL_TEMPLATE,
        (("jet", ((), ("x",), ("y",), ("x", "x"), ("x", "y"), ("y", "y"))), ("height", ((),))),
        0, (("heights", ((),)),))


class Kernel:
    """The drop cutter's kernel bound to one formula: ``P = (Pa, jet, height, heights)``."""

    def __init__(self, module, surface_module, values):
        import numpy as np

        self.module = module
        self.P = (np.array(values, dtype=float), surface_module.jet, surface_module.height,
                  surface_module.heights)

    def drop(self, *args):
        return self.module.drop_batch(*args)


def enabled() -> bool:
    return os.environ.get("FABKIT_NO_KERNELS", "") in ("", "0")


def _kernel_file() -> Path:
    """Where the kernel's module is (or will be) in the cache."""
    from ...physics.engine import codegen

    src = (_HERE / KERNEL_TEMPLATE).read_text()
    key = codegen._digest(["toolpath-kernel", src, *codegen._versions()])
    return codegen.cache_dir() / f"fk_toolpath_{key}.py"


def _kernel_path() -> Path:
    from ...physics.engine import codegen

    def make():
        from ... import __version__

        return codegen._HEADER.format(version=__version__, what="the toolpath's drop cutter kernel") \
            + "\n\n# ---- " + KERNEL_TEMPLATE + " " + "-" * 60 + "\n" + (_HERE / KERNEL_TEMPLATE).read_text()

    return codegen._write_once(_kernel_file(), make)


def _load(path: Path):
    from ...physics.engine.batch import _import

    mod = _MODS.get(str(path))
    if mod is None:
        mod = _MODS[str(path)] = _import(path)
    return mod


def module():
    """The kernel module alone (formula-free entry points: the swept cut's
    ``lowest_batch_sorted``), or None (numba missing, ``FABKIT_NO_KERNELS``)."""
    if not enabled():
        return None
    with _LOCK:
        try:
            import numba  # noqa: F401
        except ImportError:  # pragma: no cover - numba is a dependency
            return None
        try:
            return _load(_kernel_path())
        except OSError:         # no writable cache: the numpy code runs instead
            return None


def _formula_fns(surface):
    """The surface's compiled functions when the kernels apply to it (kernels on, and a
    formula behind the functions), else None."""
    fns = getattr(surface, "fns", None)
    if fns is None or not enabled():
        return None
    if getattr(fns, "text", None) is None and getattr(fns, "symbolic", None) is None:   # no formula
        return None
    return fns


def kernel_for(surface) -> Kernel | None:
    """The compiled drop cutter for ``surface`` (a Surface with compiled functions
    ``fns`` from a formula), built on first use; None where there is none (no
    formula, numba missing, or ``FABKIT_NO_KERNELS``)."""
    global last_build_s
    fns = _formula_fns(surface)
    if fns is None:
        return None
    hit = _BY_FNS.get(id(fns))
    if hit is not None and hit[0] is fns:
        return hit[1]
    with _LOCK:
        try:
            import numba  # noqa: F401
        except ImportError:  # pragma: no cover - numba is a dependency
            k = None
        else:
            from numba.core.errors import NumbaError

            from ...physics.engine.batch import _formula

            t0 = time.process_time()
            try:
                f, spath = _formula(fns, _template())
                kpath = _kernel_path()
                k = Kernel(_load(kpath), _load(spath), f.values)
                _warm(k)
            except (OSError, NumbaError):
                # no writable cache, or a formula numba cannot compile: the numpy code
                # (the same heights) runs instead
                k = None
            last_build_s = time.process_time() - t0
        if len(_BY_FNS) > 64:
            _BY_FNS.clear()
        _BY_FNS[id(fns)] = (fns, k)
        return k


def _warm(k: Kernel) -> None:
    """Compile (or load from the cache) the kernel's one signature: one position."""
    import numpy as np

    z = np.zeros(1)
    k.drop(z, z, 1.0, np.array([1.0, 0.0, 0.0, 0.0, 1.0, 1.0]), k.P, z, z, z, z,
           np.zeros(1, dtype=np.int64), z, z, 1, 1, np.zeros(1), np.zeros(1), np.zeros(1),
           np.zeros(1, dtype=np.int8), np.zeros(1, dtype=bool), np.zeros(1, dtype=bool), (z,) * 7)


# CPU seconds of a first-time build on the 2-core reference machine, each part measured in
# one process from a fresh clone with an empty cache, in either order (the time guard adds
# them to its estimate when the cache lacks the compiled code; ``python
# benchmarks/bench_first_run.py``; they were 16, 6 and 2.7 s before numba's cached start-up
# and the kernels' split, which over-stated a first run by 1.7x)
BUILD_KERNEL_S = 7.2      # the drop cutter's kernel (dropcut.py: 6.1-6.9 s) and the verification's
                          # lowest-ball batch in it (0.4 s), once per installation
BUILD_FORMULA_S = 1.7     # a new formula's surface functions (jet, height, heights: 0.2 s more than
                          # jet and height alone, benchmarks/notes_gcode_dropcut.md, "Third pass")
BUILD_MATERIAL_S = 2.0    # the material bound's loops (scallop_kernels: 1.8-2.0 s), once per installation
BUILD_SPACING_S = 0.6     # the point spacing's simplification (spacing_kernels: 0.5 s), once per installation


def _static_cached(dispatcher) -> bool:
    """True when numba's cache holds an index for ``dispatcher`` (a ``cache=True``
    function of a package module)."""
    try:
        return os.path.exists(dispatcher._cache._cache_file._index_path)
    except AttributeError:   # pragma: no cover - numba's internals moved: assume a build
        return False


def cold_build_seconds(surface) -> float:
    """CPU seconds (an estimate) of compiling what the toolpath's kernels for
    ``surface`` lack in the cache: 0 when everything loads from it, or when the numpy
    code runs (``FABKIT_NO_KERNELS``, no formula)."""
    fns = _formula_fns(surface)
    if fns is None:
        return 0.0
    hit = _BY_FNS.get(id(fns))
    if hit is not None and hit[0] is fns:
        return 0.0
    from ...physics.engine import codegen
    from ...physics.engine.batch import _cached

    s = 0.0
    try:
        if not _cached(_kernel_file(), "drop_batch"):
            s += BUILD_KERNEL_S
        known = codegen.known_surface(fns, _template())
        if known is None or not _cached(known[1], "jet"):
            s += BUILD_FORMULA_S
    except OSError:
        return 0.0           # no cache: the numpy code runs
    try:
        from . import scallop_kernels, spacing_kernels
    except ImportError:      # pragma: no cover - numba is a dependency
        return s
    if not _static_cached(scallop_kernels.sweep_balls):
        s += BUILD_MATERIAL_S
    if not _static_cached(spacing_kernels.simplify):
        s += BUILD_SPACING_S
    return s

