"""Micro-benchmark of the drop cutter on the positions of one ``fabkit gcode`` run.

    python benchmarks/bench_dropcut.py [SPEC] [--repeat 3] [--save CALLS.pkl] [--calls CALLS.pkl]

Runs ``fabkit gcode SPEC`` once in-process (outputs to a scratch folder) recording
every call of :func:`fabkit.toolpath.finish.compensate.compensate` (its positions, R, caller),
then replays the calls and prints, best of ``--repeat``, the CPU seconds per caller
(passes.compensate_passes, spacing.space_points, the verification, ...), the positions
per call, the microseconds per position, the compiled kernel's share (``drop_batch``
called directly on the same positions) and the wrapper's per-call overhead.
``--save`` keeps the recorded calls, ``--calls`` replays saved ones (no gcode run);
``--check REF.npz`` / ``--write REF.npz`` compare the tip heights and contact
information bit for bit with (or write) a reference from another version of the code.
``--versus OLD_DROPCUT.py`` runs another version of the kernel's template (for example
``git show REV:fabkit/toolpath/finish/dropcut.py > old.py``) and this one in the same process,
alternated call by call (the machine's load then weighs on both alike), and prints the
best and median CPU seconds of each over ``--repeat`` rounds and whether every output
(heights, contacts, kinds, flags) is the same bits.
CPU time (time.process_time), not wall time. Warm the kernels' cache first
(``FABKIT_CACHE_DIR``): the first run compiles.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def record(spec: str) -> list:
    """The compensate calls of one `fabkit gcode SPEC` run: (X, Y, R, return_info, caller)."""
    from fabkit.cli import main
    from fabkit.toolpath.finish import compensate as C

    calls = []
    orig = C._compensate

    def rec(surface, X, Y, R, return_info, *rest):
        f = sys._getframe(2)
        who = f"{Path(f.f_code.co_filename).name}:{f.f_code.co_name}"
        Xa, Ya = np.broadcast_arrays(np.asarray(X, float), np.asarray(Y, float))
        calls.append((Xa.copy(), Ya.copy(), float(R), bool(return_info), who))
        return orig(surface, X, Y, R, return_info, *rest)

    C._compensate = rec
    try:
        with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):
            main(["gcode", spec, "-o", str(Path(tmp) / "out.ngc"), "--no-progress", "--max-time", "1000"])
    finally:
        C._compensate = orig
    return calls


def _flat(r):
    if isinstance(r, tuple):
        Z, ci = r
        return [Z, ci.contact_x, ci.contact_y, ci.kind, ci.bridged]
    return [r]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec", nargs="?", default=str(ROOT / "specs" / "surface.yaml"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--save")
    ap.add_argument("--calls")
    ap.add_argument("--check")
    ap.add_argument("--write")
    ap.add_argument("--versus")
    a = ap.parse_args()

    from fabkit.spec import load_spec
    from fabkit.surface import Surface
    from fabkit.toolpath.finish import compensate as C

    if a.calls:
        calls = pickle.loads(Path(a.calls).read_bytes())
    else:
        calls = record(a.spec)
    if a.save:
        Path(a.save).write_bytes(pickle.dumps(calls))
    surface = Surface.from_spec(load_spec(a.spec))
    ws = C.WorkSurface(surface)
    kern = ws.kernel()
    n_all = sum(c[0].size for c in calls)
    if a.versus:
        return versus(calls, ws, kern, Path(a.versus), a.repeat)
    best: dict = {}
    kbest = wbest = float("inf")
    outs = []
    for _ in range(a.repeat):
        per: dict = {}
        tk = 0.0
        outs = []
        for X, Y, R, ri, who in calls:
            t0 = time.process_time()
            outs.append(C.compensate(ws, X, Y, R, return_info=ri))
            per[who] = per.get(who, 0.0) + time.process_time() - t0
            if kern is not None:
                cx, cy = X.ravel().copy(), Y.ravel().copy()
                n = cx.size
                b = C._Best(n)
                br, cv = np.zeros(n, bool), np.zeros(n, bool)
                tab = C._tables(R, tuple(C.RING_SLOPES), 12)
                G = np.array([ws.s, ws.x0, ws.y0, ws.top, ws.L, ws.W], dtype=float)
                t0 = time.process_time()
                call = C._entry(kern) if hasattr(C, "_entry") else kern.drop     # older code
                call(cx, cy, R, G, kern.P, *tab[:7], 3, 12, b.val, b.px, b.py, b.kind, br,
                               cv, tab[7])
                tk += time.process_time() - t0
        for k, v in per.items():
            best[k] = min(best.get(k, float("inf")), v)
        tot = sum(per.values())
        kbest = min(kbest, tk)
        wbest = min(wbest, tot)
    print(f"{a.spec}: {len(calls)} calls, {n_all} positions ({'kernel' if kern else 'numpy'})")
    for who in sorted(best, key=lambda k: -best[k]):
        n = sum(c[0].size for c in calls if c[4] == who)
        m = sum(1 for c in calls if c[4] == who)
        print(f"  {who:44s} {best[who]:7.3f} s  {m:5d} calls  {n:8d} positions  "
              f"{1e6 * best[who] / max(n, 1):6.2f} us/position")
    print(f"  compensate total {wbest:.3f} s ({1e6 * wbest / max(n_all, 1):.2f} us/position)")
    if kern is not None:
        print(f"  kernel alone {kbest:.3f} s; wrapper {wbest - kbest:.3f} s "
              f"({1e6 * (wbest - kbest) / len(calls):.0f} us/call)")
    if a.write or a.check:
        flat = {f"{i}_{j}": v for i, r in enumerate(outs) for j, v in enumerate(_flat(r))}
        if a.write:
            np.savez(a.write, **flat)
        else:
            ref = np.load(a.check)
            nbit = nz = 0
            worst = 0.0
            for key, v in flat.items():
                r = ref[key]
                same = (v == r) | (np.isnan(v.astype(float)) & np.isnan(r.astype(float)))
                if key.endswith("_0"):
                    nz += int((~same).sum())
                    fin = np.isfinite(r) & np.isfinite(v)
                    if fin.any():
                        worst = max(worst, float(np.abs(v[fin] - r[fin]).max()))
                else:
                    nbit += int((~same).sum())
            print(f"  against {a.check}: tip heights differ at {nz} positions (max {worst:.3e} mm); "
                  f"contact information at {nbit}")
    return 0


def versus(calls, ws, kern, old_template: Path, rounds: int) -> int:
    """The kernel of ``old_template`` against this one, alternated call by call."""
    import hashlib

    from fabkit.physics.engine import codegen
    from fabkit.physics.engine.batch import _import
    from fabkit.toolpath.finish import compensate as C
    from fabkit.toolpath.finish import kernels

    if kern is None:
        print("no compiled kernel (FABKIT_NO_KERNELS, or no formula)")
        return 1
    src = old_template.read_text()
    path = codegen.cache_dir() / f"fk_bench_dropcut_{hashlib.sha256(src.encode()).hexdigest()[:16]}.py"
    if not path.exists():
        codegen.replace_quietly(path, src)
    versions = {"old": (_import(path), kern.P if "P[3]" in src else kern.P[:3]), "new": (kern.module, kern.P)}
    G = np.array([ws.s, ws.x0, ws.y0, ws.top, ws.L, ws.W], dtype=float)
    entry = {}
    for k, (mod, P) in versions.items():
        kernels._warm(type("K", (), {"drop": staticmethod(mod.drop_batch), "P": P})())
        disp = mod.drop_batch
        entry[k] = (disp.overloads[disp.signatures[0]].entry_point, P)
    times = {k: [] for k in entry}
    outs = {k: [] for k in entry}
    for r in range(rounds + 1):            # round 0 warms up (and keeps the outputs)
        acc = {k: 0.0 for k in entry}
        for X, Y, R, _ri, _who in calls:
            cx, cy = X.ravel().copy(), Y.ravel().copy()
            n = cx.size
            tab = C._tables(R, tuple(C.RING_SLOPES), 12)
            for k in (list(entry) if r % 2 else list(entry)[::-1]):
                fn, P = entry[k]
                b = C._Best(n)
                br, cv = np.zeros(n, bool), np.zeros(n, bool)
                t0 = time.process_time()
                fn(cx, cy, R, G, P, *tab[:7], 3, 12, b.val, b.px, b.py, b.kind, br, cv, tab[7])
                acc[k] += time.process_time() - t0
                if r == 0:
                    outs[k].append((b.val, b.px, b.py, b.kind, br, cv))
        if r:
            for k in entry:
                times[k].append(acc[k])
    same = all(np.array_equal(u, v, equal_nan=u.dtype.kind == "f")
               for o, q in zip(outs["old"], outs["new"]) for u, v in zip(o, q))
    n_all = sum(c[0].size for c in calls)
    for k in entry:
        t = times[k]
        print(f"  kernel {k}: best {min(t):.3f} s ({1e6 * min(t) / n_all:.2f} us/position), "
              f"median {np.median(t):.3f} s over {rounds} rounds")
    print(f"  new / old: best {min(times['new']) / min(times['old']):.3f}, "
          f"median {np.median(times['new']) / np.median(times['old']):.3f}; outputs the same bits: {same}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
