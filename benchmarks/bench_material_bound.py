"""The pass placement's material bound (scallop.sweep_material) alone: its calls
during one planning run of ``fabkit gcode SPEC --no-verify`` are recorded, then
replayed in the same process with the compiled kernels (scallop_kernels) and with
the numpy code (FABKIT_NO_KERNELS's path), and compared bit for bit.

    python benchmarks/bench_material_bound.py [SPEC ...]

Prints, per SPEC, the number of calls, the CPU seconds of each replay (best of two
for the kernels), the kernels' own share and the formula's (``ws.all``), and whether
every result is the same bits. Outputs go to a scratch folder.
"""

from __future__ import annotations

import contextlib
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def replay(spec: str) -> str:
    from fabkit.cli import main
    from fabkit.toolpath.finish import passes, scallop, scallop_kernels
    from fabkit.toolpath.finish.compensate import WorkSurface

    calls = []
    orig = scallop.sweep_material

    def record(*a, **k):
        calls.append((a, k))
        return orig(*a, **k)

    passes.sweep_material = record
    try:
        with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):
            main(["gcode", spec, "-o", str(Path(tmp) / "p.ngc"), "--no-progress", "--no-verify",
                  "--max-time", "600"])
    finally:
        passes.sweep_material = orig

    def run():
        t = time.process_time()
        out = [orig(*a, **k) for a, k in calls]
        return time.process_time() - t, out

    t1, compiled = run()
    t2, _ = run()
    kern = scallop._kernels
    scallop._kernels = lambda: None
    try:
        tn, numpy = run()
    finally:
        scallop._kernels = kern
    same = all(x.shape == y.shape and np.array_equal(np.ascontiguousarray(x).view(np.uint64),
                                                     np.ascontiguousarray(y).view(np.uint64))
               for x, y in zip(compiled, numpy))
    # the compiled run's parts: the kernels and the formula
    acc: dict = {}
    saved = {n: getattr(scallop_kernels, n) for n in ("sweep_balls", "rim_cut")}
    saved_all = WorkSurface.all

    def timed(name, f):
        def g(*a, **k):
            t = time.process_time()
            r = f(*a, **k)
            acc[name] = acc.get(name, 0.0) + time.process_time() - t
            return r
        return g

    for n, f in saved.items():
        setattr(scallop_kernels, n, timed(n, f))
    WorkSurface.all = timed("ws.all", saved_all)
    try:
        t3, _ = run()
    finally:
        for n, f in saved.items():
            setattr(scallop_kernels, n, f)
        WorkSurface.all = saved_all
    tk = min(t1, t2)
    parts = ", ".join(f"{k} {v:.3f}" for k, v in acc.items())
    return (f"{Path(spec).name}: {len(calls)} calls; CPU s: compiled {tk:.3f}, numpy {tn:.3f} ({tn / tk:.1f}x); "
            f"a timed compiled replay {t3:.3f} ({parts}); bit-identical: {same}")


def main() -> int:
    specs = sys.argv[1:] or [str(ROOT / "specs" / "surface.yaml")]
    for s in specs:
        print(replay(str(Path(s).resolve())), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
