"""Stock simulation of the paper's finishing program (by hand; not a test).

    fabkit gcode specs/surface.yaml -o /tmp/x
    python benchmarks/bench_stock.py /tmp/x [--spacing 0.25] [--png /tmp/x.stock.png]

Reads the written program back (verify.read_program), replays it with the spec's ball
on a height-field stock (fabkit.toolpath.stock) and prints the grid, the seconds of
each stage and the whole-job check (verify_job) with its figures. The first run
compiles the kernels (numba cache): the figures below are from a second run.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("program")
    ap.add_argument("--spec", default="specs/surface.yaml")
    ap.add_argument("--spacing", type=float, default=None)
    ap.add_argument("--png", default=None)
    args = ap.parse_args()

    from fabkit.spec import load_spec
    from fabkit.surface import Surface
    from fabkit.toolpath import stock as st
    from fabkit.toolpath.compensate import WorkSurface
    from fabkit.toolpath.tools import Tool
    from fabkit.toolpath.verify import read_program

    spec = load_spec(args.spec)
    surface = Surface.from_spec(spec)
    ws = WorkSurface(surface)
    tool = Tool.ball(float(spec.tool.diameter))
    tol = float(spec.machining.tolerance)
    scallop = float(spec.machining.scallop)

    t = time.perf_counter()
    prog = read_program(Path(args.program).read_text())
    t_read = time.perf_counter() - t
    h = args.spacing if args.spacing else st.grid_spacing([tool], tol)

    # warm the kernels (compile or load the cache) on a small block
    s0 = st.make_stock(10, 10, 1.0)
    st.cut(s0, tool, np.array([[1.0, 1.0, -1.0], [9.0, 9.0, -1.0]]), np.array([1, 2]))

    stock = st.make_stock(ws.L, ws.W, h)
    t = time.perf_counter()
    res = st.cut(stock, tool, prog.points, prog.kinds, start=prog.start)
    t_cut = time.perf_counter() - t
    t = time.perf_counter()
    design = st.design_heights(ws, stock)
    t_design = time.perf_counter() - t
    print(f"program: {len(prog)} moves ({res.feeds} feeds); grid {stock.shape[0]} x {stock.shape[1]} "
          f"= {stock.z.size} nodes at {stock.hx:.4f} x {stock.hy:.4f} mm")
    print(f"read {t_read:.2f} s; cut {t_cut:.2f} s; design at the nodes {t_design:.2f} s")
    print(f"rapids into stock {res.rapids_into_stock}; largest single-move engagement {res.max_engagement:.3f} mm")

    ops = st.operations_from_program(prog, {-1: tool}, kinds={-1: "finish"}, info={-1: {"scallop": scallop}})
    t = time.perf_counter()
    job = st.verify_job(ws, ops, tol, spacing=h, design=design)
    t_job = time.perf_counter() - t
    o = job.operations[0]
    print(f"verify_job {t_job:.2f} s (design given): ok={job.ok}")
    print(f"  gouge {o.max_gouge:.4f} mm at {o.gouge_at}; material left {o.max_left:.4f} mm at {o.left_at} "
          f"(bound {o.bounds[1]:.3f}); unreachable {o.unreachable:.3f} mm over {o.unreachable_area:.0f} mm^2; "
          f"above bound where reachable {o.over_reachable:.4f} mm over {o.over_area:.1f} mm^2; "
          f"removed {o.max_removed:.2f} mm")
    for f in job.failures:
        print("  failure:", f)
    if args.png:
        t = time.perf_counter()
        png = st.stock_png(job.snapshots[-1], design, title="after finishing", tolerance=tol)
        Path(args.png).write_bytes(png)
        print(f"picture {time.perf_counter() - t:.2f} s -> {args.png}")


if __name__ == "__main__":
    main()
