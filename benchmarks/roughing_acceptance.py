"""The rough-then-finish job checked by an independent cut of LinuxCNC's reading of it.

    fabkit gcode specs/surface_roughing.yaml -o /tmp/rj/job.ngc --no-progress
    python benchmarks/roughing_acceptance.py specs/surface_roughing.yaml /tmp/rj/job.ngc [--h 0.5] [--step 0.25]

``rs274 -g`` (the LinuxCNC interpreter) reads the program, M6 included; its canonical
moves are replayed by brute force with each tool's own shape (the functions of
tests/test_roughing_job.py: every tool placed every ``--step`` mm along each feed move,
lowering a height field of nodes ``--h`` mm apart; nothing of fabkit.toolpath.cut.stock).
The design is the spec's surface (fabkit.surface), clipped at the top face, in work mm.

Printed per operation: the deepest gouge; after roughing, the material left above
T = min(design + leave, 0) (its range, and where the end mill reaches T within the
tolerance, the largest); after rest and finishing, the largest thickness the finish
removes at a node (its engagement, against the finishing tool's depth of cut); after
finishing, the material left normal to the design where the ball reaches it; the
deepest rapid into the stock its operation leaves. Sampling a move leaves at most
step^2 / (8 R) more material than the envelope (0.0025 mm for the 1/4 in ball at 0.25 mm).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("spec")
    ap.add_argument("program")
    ap.add_argument("--h", type=float, default=0.5, help="mm between nodes")
    ap.add_argument("--step", type=float, default=0.25, help="mm between tool placements along a move")
    a = ap.parse_args(argv)

    import test_roughing_job as T
    from fabkit.spec import load_spec
    from fabkit.surface import Surface
    from fabkit.toolpath.finish.compensate import WorkSurface
    from fabkit.toolpath.rough.roughing import spec_tools

    spec = load_spec(a.spec)
    ws = WorkSurface(Surface.from_spec(spec))
    tools = spec_tools(spec)
    T.TOOLS = {n: ("ball" if t.corner_radius >= t.radius - 1e-12 else "flat" if t.corner_radius <= 0
                   else f"bull{t.corner_radius!r}", t.radius) for n, t in tools.items()}
    tol, leave = float(spec.machining.tolerance), float(spec.roughing.leave)
    scallop = float(spec.machining.scallop)
    doc = float(spec.tool.depth_of_cut)
    t0 = time.process_time()
    ops, changes = T.rs274_operations(a.program)
    t_read = time.process_time() - t0
    x, y = np.arange(0.0, ws.L + 1e-9, a.h), np.arange(0.0, ws.W + 1e-9, a.h)
    X, Y = np.meshgrid(x, y, indexing="ij")
    Hraw = ws.H(X, Y)
    D = np.minimum(Hraw, 0.0)
    e = 1e-4
    gx = (ws.H(X + e, Y) - ws.H(X - e, Y)) / (2 * e)
    gy = (ws.H(X, Y + e) - ws.H(X, Y - e)) / (2 * e)
    slope = np.where(Hraw < 0.0, np.hypot(gx, gy), 0.0)
    S = np.zeros_like(D)
    print(f"rs274 -g {a.program}: {sum(len(o[2]) for o in ops)} moves, tool changes {changes}, "
          f"operations {[o[0] for o in ops]} ({t_read:.1f} s)")
    print(f"grid {X.shape[0]} x {X.shape[1]} nodes, h = {a.h} mm, tool placed every {a.step} mm")
    T.STEP = a.step
    before = {}
    for op in ops:
        kind, num = op[0], op[1]
        t1 = time.process_time()
        prev = S.copy()
        rapid = T.replay(S, a.h, op)
        gouge = float(max(0.0, np.max(D - S)))
        print(f"{kind} (T{num} {T.TOOLS[num][0]} {2 * T.TOOLS[num][1]:g} mm): gouge {gouge:.4f} mm, "
              f"deepest rapid into the stock it leaves {rapid:.4f} mm, "
              f"largest removed at a node {float(np.max(prev - S)):.3f} mm ({time.process_time() - t1:.1f} s)")
        before[kind] = prev
        if kind == "rough":
            Tt = np.minimum(D + leave, 0.0)
            left = S - Tt
            shape, R = T.TOOLS[num]
            t1 = time.process_time()
            reach = T.reach(Tt, a.h, shape, R)
            there = reach <= Tt + tol
            step = float(spec.roughing.stepdown)
            over = S - np.maximum(Tt, reach)
            print(f"  after roughing: material left above design + leave {left.min():+.4f} .. {left.max():.4f} mm "
                  f"(allowance {leave} mm: left above the design {leave + left.min():.4f} .. "
                  f"{leave + left.max():.4f} mm)")
            print(f"  where the roughing tool reaches T ({100 * there.mean():.1f} % of the nodes): largest "
                  f"{leave + float(left[there].max()):.4f} mm above the design (bound leave + stepdown = "
                  f"{leave + step:g} mm, + tolerance {tol:g}); above its own reach elsewhere: largest "
                  f"{leave + float(over.max()):.4f} mm; largest excess over leave + stepdown + tol "
                  f"{float(np.max(over - step - tol)):+.4f} mm ({time.process_time() - t1:.1f} s reach)")
            i = np.unravel_index(np.argmax(over - step), over.shape)
            print(f"    at X{X[i]:.2f} Y{Y[i]:.2f}, slope {slope[i]:.2f}")
        if kind == "finish":
            removed = before["finish"] - S
            print(f"  finish engagement: largest thickness removed at a node {removed.max():.3f} mm "
                  f"(depth of cut {doc:g} mm)")
            shape, R = T.TOOLS[num]
            t1 = time.process_time()
            reach = T.reach(D, a.h, shape, R)
            there = reach <= D + tol
            nl = (S - D) / np.sqrt(1.0 + slope ** 2)
            print(f"  after finishing: where the ball reaches the design ({100 * there.mean():.1f} % of the "
                  f"nodes) material left normal to it {float(nl[there].min()):+.4f} .. "
                  f"{float(nl[there].max()):.4f} mm (scallop {scallop:g} + tolerance {tol:g}); vertical "
                  f"{float((S - D)[there].max()):.4f} mm; elsewhere up to {float((S - D).max()):.3f} mm "
                  f"({time.process_time() - t1:.1f} s reach)")
    print(f"total {time.process_time() - t0:.1f} s CPU")


if __name__ == "__main__":
    main()
