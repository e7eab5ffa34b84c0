"""Stock simulation of the paper's finishing program (by hand; not a test).

    fabkit gcode specs/surface.yaml -o /tmp/x
    python benchmarks/bench_stock.py /tmp/x [--spacing 0.25] [--png /tmp/x.stock.png]
    python benchmarks/bench_stock.py /tmp/x --rough 12.7 --png /tmp/x.stock.png

With ``--rough D`` a D mm flat end mill first roughs the block in Z levels
(``--stepdown``, ``--stepover``) along raster lines, its tip at max(level, the drop
height of the flat end mill on design + leave at centres every mm): a stand-in for the
roughing planner, enough to exercise the whole-job check and draw both pictures
(``<png>`` after finishing, ``<png stem>.rough.png`` after roughing).

Reads the written program back (verify.read_program), replays it with the spec's ball
on a height-field stock (fabkit.toolpath.cut.stock) and prints the grid, the seconds of
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
    ap.add_argument("--rough", type=float, default=None, help="flat end mill diameter, mm")
    ap.add_argument("--stepdown", type=float, default=8.0)
    ap.add_argument("--stepover", type=float, default=7.5)
    ap.add_argument("--leave", type=float, default=0.5)
    args = ap.parse_args()

    from fabkit.spec import load_spec
    from fabkit.surface import Surface
    from fabkit.toolpath.cut import stock as st
    from fabkit.toolpath.finish.compensate import WorkSurface
    from fabkit.toolpath.tools import Tool
    from fabkit.toolpath.program.reader import read_program

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
    if args.rough:
        t = time.perf_counter()
        rough = rough_op(stock, design, Tool("flat", args.rough, number=1), args.stepdown, args.stepover,
                         args.leave)
        print(f"stand-in roughing: {len(rough.toolpath)} moves, {rough.levels} levels, planned in "
              f"{time.perf_counter() - t:.2f} s")
        ops = [rough] + ops
    t = time.perf_counter()
    job = st.verify_job(ws, ops, tol, spacing=h, design=design)
    t_job = time.perf_counter() - t
    print(f"verify_job {t_job:.2f} s (design given): ok={job.ok}")
    for o in job.operations:
        print(f"  {o.kind} ({o.tool}): gouge {o.max_gouge:.4f} mm at {o.gouge_at}; material left "
              f"{o.min_left:.4f} .. {o.max_left:.4f} mm, max at {o.left_at} (bounds {o.bounds[0]:.3f} .. "
              f"{o.bounds[1]:.3f}); unreachable {o.unreachable:.3f} mm over {o.unreachable_area:.0f} mm^2; "
              f"above bound where reachable {o.over_reachable:.4f} mm over {o.over_area:.1f} mm^2; "
              f"removed up to {o.max_removed:.2f} mm (one move {o.max_engagement:.2f} mm)")
    for f in job.failures:
        print("  failure:", f)
    if args.png:
        t = time.perf_counter()
        pics = job.pictures()
        Path(args.png).write_bytes(pics["finish"])
        if "rough" in pics:
            Path(args.png).with_suffix(".rough.png").write_bytes(pics["rough"])
        print(f"pictures {time.perf_counter() - t:.2f} s -> {args.png}")


def rough_op(stock, design, tool, stepdown, stepover, leave):
    """Z-level raster roughing (a stand-in, see the module): returns an Operation."""
    from fabkit.toolpath.operations import Operation
    from fabkit.toolpath.path import CUT, PLUNGE, RAPID, Toolpath

    R = tool.radius
    target = np.minimum(design + leave, 0.0)
    nx, ny = target.shape
    hx, hy = stock.hx, stock.hy
    xs = np.arange(-R + 0.5, stock.L + R - 0.5 + 1e-9, 1.0)
    n_y = int(np.ceil((stock.W + 2 * R) / stepover))
    ys = np.linspace(-R + 0.5, stock.W + R - 0.5, n_y + 1)
    # drop height of the flat end mill at the centres: the highest target node under its disk
    CX, CY = np.meshgrid(xs, ys, indexing="ij")
    drop = np.full(CX.shape, -np.inf)
    ri, rj = int(np.ceil(R / hx)), int(np.ceil(R / hy))
    ci, cj = np.rint(CX / hx).astype(int), np.rint(CY / hy).astype(int)
    for di in range(-ri - 1, ri + 2):
        for dj in range(-rj - 1, rj + 2):
            qi, qj = ci + di, cj + dj
            ok = (qi >= 0) & (qi < nx) & (qj >= 0) & (qj < ny)
            qi, qj = np.clip(qi, 0, nx - 1), np.clip(qj, 0, ny - 1)
            inside = ok & (np.hypot(qi * hx - CX, qj * hy - CY) <= R)
            drop = np.where(inside, np.maximum(drop, target[qi, qj]), drop)
    drop = np.where(np.isfinite(drop), drop, 0.0)   # a disk over no node: stay on the top face
    # a chord between two centres stays above both drops (the drop between them is not
    # linear): each centre takes the highest drop of itself and its neighbours along x
    drop = np.maximum(drop, np.maximum(np.vstack([drop[1:], drop[-1:]]), np.vstack([drop[:1], drop[:-1]])))
    deepest = float(np.min(drop))
    levels = -stepdown * np.arange(1, int(np.ceil(-deepest / stepdown - 1e-9)) + 1)
    levels[-1] = max(levels[-1], deepest)
    pts, kinds = [], []
    safe = 5.0
    for z in levels:
        for j in range(len(ys)):
            zz = np.maximum(z, drop[:, j])
            cutting = zz < 0.0
            if not cutting.any():
                continue
            i0, i1 = np.nonzero(cutting)[0][[0, -1]]
            seg = np.column_stack([xs[i0:i1 + 1], np.full(i1 - i0 + 1, ys[j]), zz[i0:i1 + 1]])
            pts += [[seg[0, 0], seg[0, 1], safe], [seg[0, 0], seg[0, 1], 1.0], seg[0]]
            kinds += [RAPID, RAPID, PLUNGE]
            pts += seg[1:].tolist()
            kinds += [CUT] * (len(seg) - 1)
            pts.append([seg[-1, 0], seg[-1, 1], safe])
            kinds.append(RAPID)
    tp = Toolpath(np.array(pts), np.array(kinds), R, safe)
    return Operation("rough", tool, tp, leave=leave, levels=len(levels), passes=0,
                     info={"cusp_mm": stepdown, "stepdown_mm": stepdown})


if __name__ == "__main__":
    main()
