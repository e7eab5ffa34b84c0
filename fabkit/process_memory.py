"""How a fabkit command's process takes its memory from the system.

A whole job's check works on grids of a few million nodes (the paper's block: 2001 x
1001 float64, 16 MB an array) and allocates and frees dozens of them. Out of the box
each such array is a fresh mapping from the kernel: glibc's malloc maps blocks over its
(dynamic) threshold and gives them back when freed, and numpy asks for transparent huge
pages on every array over 4 MB, which the kernel zeroes (and, with ``defrag=madvise``,
compacts memory for) on first touch. The same pages are faulted in again and again: in
``fabkit gcode specs/surface_roughing.yaml`` that was 0.4-0.65 s of system time against
0.1 s for its finishing program alone.

:func:`tune` (called once by :func:`fabkit.cli.main`, before a command runs; never on
import, so a program using fabkit as a library keeps its own settings) keeps freed
memory in the process for reuse:

* glibc: ``mallopt(M_MMAP_THRESHOLD, 32 MiB)`` (its largest; the grids' arrays come
  from the heap and are reused), ``M_TRIM_THRESHOLD`` 1 GiB (the heap's top is not
  given back after every free), ``M_TOP_PAD`` 64 MiB (the heap grows in steps);
* numpy: no huge-page advice (``NUMPY_MADVISE_HUGEPAGE=0``'s setting).

Nothing computed changes (the same bytes are written, tests/test_process_memory.py) and
the peak resident memory stays the same (423-427 MB on the paper's job either way); the
job's system time drops to 0.25-0.3 s (``python benchmarks/bench_gcode.py --floor
specs/surface_roughing.yaml specs/surface.yaml``). ``FABKIT_SYSTEM_MEMORY=1`` leaves
the system's settings as they are.
"""

from __future__ import annotations

import os
import sys

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3     # glibc's malloc.h
MMAP_THRESHOLD = 32 << 20       # glibc's largest (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD = 1 << 30
TOP_PAD = 64 << 20

_DONE: dict = {}


def tune() -> dict:
    """Apply the settings once per process; returns what was applied:
    {"malloc": bool, "hugepage_advice_off": bool} (empty when turned off by
    ``FABKIT_SYSTEM_MEMORY=1``). Never raises: a platform without them keeps its own."""
    if _DONE or os.environ.get("FABKIT_SYSTEM_MEMORY") == "1":
        return dict(_DONE)
    done = {"malloc": False, "hugepage_advice_off": False}
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None)
            mallopt = getattr(libc, "mallopt", None)
            gnu = getattr(libc, "gnu_get_libc_version", None)    # glibc only (not musl)
            if mallopt is not None and gnu is not None:
                ok = [mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD), mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD),
                      mallopt(M_TOP_PAD, TOP_PAD)]
                done["malloc"] = all(v == 1 for v in ok)
        except (OSError, AttributeError, TypeError):
            pass
    if "NUMPY_MADVISE_HUGEPAGE" not in os.environ:     # the user's own choice stands
        try:
            try:
                from numpy._core import multiarray
            except ImportError:          # numpy 1.x
                from numpy.core import multiarray
            setter = getattr(multiarray, "_set_madvise_hugepage", None)
            if setter is not None:
                setter(False)
                done["hugepage_advice_off"] = True
        except ImportError:
            pass
    _DONE.update(done)
    return dict(done)
