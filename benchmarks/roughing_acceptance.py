"""The rough-then-finish job checked by an independent cut of LinuxCNC's reading of it.

    fabkit gcode specs/surface_roughing.yaml -o /tmp/rj/job.ngc --no-progress
    python benchmarks/roughing_acceptance.py specs/surface_roughing.yaml /tmp/rj/job.ngc [--h 0.5] [--step 0.25]
    [--gvalidate PATH] [--json]

``rs274 -g`` (the LinuxCNC interpreter) reads the program, M6 included (with a tool
table of the spec's tools, length offsets 0); its canonical moves are replayed by brute
force with each tool's own shape (the functions of tests/test_roughing_job.py: every tool
placed every ``--step`` mm along each feed move, lowering a height field of nodes ``--h``
mm apart; nothing of fabkit.toolpath.cut.stock). The design is the spec's surface
(fabkit.surface), clipped at the top face, in work mm.

A grbl job is one program per tool (``<stem>.1-rough.nc`` ...): give the ``-o`` path;
each program is read by rs274 in turn (its tool from its header, the stock carried over)
and, with ``--gvalidate`` (or the environment's GVALIDATE: grbl-sim's validator, built
from the gnea/grbl sources), by grbl 1.1's own parser, which must answer ``ok`` to every
line. A G20 program's moves are scaled to mm (rs274 prints 4 decimals of an inch: the
moves are known to 0.0013 mm).

Printed per operation: the deepest gouge; after a rest operation, the deepest cut into
the allowance; after roughing, the material left above T = min(design + leave, 0) (its
range, and where the roughing tool reaches T within the tolerance, the largest); after
rest and finishing, the largest thickness the finish removes at a node (its engagement,
against the finishing tool's depth of cut); after finishing, the material left normal to
the design where the ball reaches it; the deepest rapid into the stock its operation
leaves. Sampling a move leaves at most step^2 / (8 R) more material than the envelope
(0.0025 mm for the 1/4 in ball at 0.25 mm). Then the verdict of each acceptance bound
(docs/toolpath.md), ``ACCEPT`` or ``FAIL``, and with ``--json`` the figures as one line.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

_MOVE = re.compile(r"(STRAIGHT_FEED|STRAIGHT_TRAVERSE)\(([-0-9.]+), ([-0-9.]+), ([-0-9.]+)"
                   r"|SELECT_TOOL\((\d+)\)|COMMENT\(\"operation: \d+ of \d+, (\w+), T\d+\"\)"
                   r"|COMMENT\(\"operation \d+ of \d+: (\w+), T(\d+) "
                   r"|USE_LENGTH_UNITS\(CANON_UNITS_(MM|INCHES)\)")


def programs_of(path: Path) -> list[Path]:
    """The programs of a job: the one given, or a grbl job's ``<stem>.K-kind.nc`` in order."""
    if path.exists():
        return [path]
    found = []
    for suffix in dict.fromkeys((path.suffix, ".nc")):      # grbl's programs are written .nc
        found = found or sorted(path.parent.glob(f"{path.stem}.[0-9]*-*{suffix}"),
                                key=lambda p: int(p.name[len(path.stem) + 1:].split("-")[0]))
    if not found:
        raise SystemExit(f"{path}: no such program (nor {path.stem}.1-rough{path.suffix} ...)")
    return found


def rs274_moves(programs, tools, grbl):
    """Every program as LinuxCNC's interpreter executes it, in mm: [(kind, tool number,
    points (n, 3), feed flags (n,), start point)] per operation, in order; the tool
    changes; and per program rs274's exit code and error text."""
    rs = T.RS274
    ops, changes, runs = [], [], []
    with tempfile.TemporaryDirectory() as d:
        tbl = Path(d) / "tools.tbl"
        tbl.write_text("".join(f"T{n} P{n} Z0 D{2 * r:.4f} ;\n" for n, (_, r) in tools.items()))
        at = None
        for prog in programs:
            run = subprocess.run([rs, "-t", str(tbl), "-g", str(prog)], stdin=subprocess.DEVNULL,
                                 capture_output=True, text=True, timeout=600)
            err = run.stderr.strip()
            runs.append((prog.name, run.returncode, "" if err in ("", "executing") else err[-300:]))
            tool, k = None, 1.0
            for m in _MOVE.finditer(run.stdout):
                if m.group(9):
                    k = 25.4 if m.group(9) == "INCHES" else 1.0
                elif m.group(5):
                    # SELECT_TOOL(tool number), then M6's CHANGE_TOOL(its pocket index): fabkit
                    # writes T<n> M6 on one line, so the tool selected is the one loaded
                    tool = int(m.group(5))
                    changes.append(m.group(5))
                elif m.group(6) or (grbl and m.group(7)):
                    if m.group(7):
                        tool = int(m.group(8))       # grbl: one tool a program, named in its header
                    ops.append([m.group(6) or m.group(7), None, [], [], at])
                elif m.group(7):
                    continue                          # LinuxCNC: the header's list of operations
                else:
                    p = (k * float(m.group(2)), k * float(m.group(3)), k * float(m.group(4)))
                    if ops:
                        op = ops[-1]
                        op[1] = tool if op[1] is None else op[1]
                        assert op[1] == tool, "a tool change inside an operation"
                        if op[4] is None:
                            op[4] = at if at is not None else p
                        op[2].append(p)
                        op[3].append(m.group(1) == "STRAIGHT_FEED")
                    at = p
    out = [(kd, t, np.array(p, float), np.array(f, bool), np.array(s, float)) for kd, t, p, f, s in ops]
    return out, changes, runs


def reach(Tt, h, shape, R, zmin=-np.inf):
    """The lowest surface the tool's underside reaches over the target Tt, its tip never
    below ``zmin`` (the tool's reach, the stock's depth limit): the grey-scale closing of Tt
    by the tool (tests/test_roughing_job.py reach), the tips clamped before the erosion;
    the tool may stand beyond the stock (no material there)."""
    import math

    from scipy.ndimage import grey_dilation, grey_erosion

    k = int(math.ceil(R / h))
    di, dj = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    rho = np.hypot(di, dj) * h
    inside = rho <= R
    st = np.where(inside, -T.lift(shape, R, np.minimum(rho, R)), 0.0)
    pad = np.pad(Tt, k, constant_values=-1e6)
    tip = np.maximum(grey_dilation(pad, footprint=inside, structure=st, mode="nearest"), zmin)
    low = grey_erosion(tip, footprint=inside, structure=st, mode="nearest")
    return low[k:-k, k:-k]


#: nodes over the material-left bound whose reach is confirmed on a fine local grid (worst first)
RECHECK = 2000


def reach_fine(ws, x, y, shape, R, tol):
    """Whether the tool reaches the design at (x, y) within ``tol``: :func:`reach` on a local
    grid of spacing R / 16 over the square of half side 2 R about the point (every tip
    within R of it sees all the material it must clear), the stock's outside empty. The
    whole-block grid (--h) samples a groove narrower than the ball too coarsely to tell:
    at h = 0.25 a 2 mm ball over a groove of curvature radius 0.25 was called reaching a
    point it stays 0.13 mm above at best (R / 16: 0.128, the exact bound 0.1298; the grid's
    own error, tips only at its nodes, is about hf^2 / (8 R) = R / 2048, below the tolerance)."""
    hf = R / 16.0
    n = 32
    g = np.arange(-n, n + 1) * hf
    PX, PY = np.meshgrid(x + g, y + g, indexing="ij")
    Df = np.where(ws.inside(PX, PY), np.minimum(ws.H(PX, PY), 0.0), -1e6)
    low = reach(Df, hf, shape, R)
    return bool(low[n, n] <= Df[n, n] + tol)


def gvalidate(programs, exe):
    """grbl 1.1's parser (grbl-sim's validator) on every line: [(name, lines, ok answers, first error)]."""
    out = []
    for prog in programs:
        with tempfile.TemporaryDirectory() as d:       # it writes an EEPROM.DAT where it runs
            run = subprocess.run([exe, str(prog.resolve())], capture_output=True, text=True, cwd=d, timeout=600)
        lines = [ln for ln in prog.read_text().splitlines() if ln.strip()]
        answers = run.stdout.split()
        err = next((a for a in answers if a.startswith("error")), None)
        out.append((prog.name, len(lines), answers.count("ok"), err if err or run.returncode == 0
                    else f"exit {run.returncode}"))
    return out


def main(argv=None):
    global T
    ap = argparse.ArgumentParser()
    ap.add_argument("spec")
    ap.add_argument("program", help="the program (LinuxCNC), or the -o path of a grbl job")
    ap.add_argument("--h", type=float, default=0.5, help="mm between nodes")
    ap.add_argument("--step", type=float, default=0.25, help="mm between tool placements along a move")
    ap.add_argument("--gvalidate", default=os.environ.get("GVALIDATE"),
                    help="grbl-sim's validator (gvalidate.exe): grbl 1.1's parser reads every line of a grbl job")
    ap.add_argument("--json", action="store_true", help="the figures and verdicts as one JSON line at the end")
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
    step = float(spec.roughing.stepdown)
    grbl = spec.machining.dialect == "grbl"
    t0 = time.process_time()
    progs = programs_of(Path(a.program))
    ops, changes, runs = rs274_moves(progs, T.TOOLS, grbl)
    t_read = time.process_time() - t0
    fig = {"spec": Path(a.spec).name, "dialect": spec.machining.dialect, "units": spec.machining.units,
           "rs274": all(rc == 0 and not err for _, rc, err in runs), "checks": {}}
    for name, rc, err in runs:
        print(f"rs274 -g {name}: exit {rc}{', ' + err if err else ''}")
    if grbl:
        if a.gvalidate:
            g = gvalidate(progs, a.gvalidate)
            for name, n, ok, err in g:
                print(f"grbl 1.1 parser (gvalidate) {name}: {ok} ok of {n} lines{', ' + err if err else ''}")
            fig["gvalidate"] = all(ok == n and not err for _, n, ok, err in g)
        else:
            print("grbl 1.1 parser: not run (no --gvalidate / GVALIDATE)")
            fig["gvalidate"] = None
    print(f"rs274: {sum(len(o[2]) for o in ops)} moves, tool changes {changes}, "
          f"operations {[(o[0], o[1]) for o in ops]} ({t_read:.1f} s)")
    x, y = np.arange(0.0, ws.L + 1e-9, a.h), np.arange(0.0, ws.W + 1e-9, a.h)
    X, Y = np.meshgrid(x, y, indexing="ij")
    Hraw = ws.H(X, Y)
    D = np.minimum(Hraw, 0.0)
    e = 1e-4
    gx = (ws.H(X + e, Y) - ws.H(X - e, Y)) / (2 * e)
    gy = (ws.H(X, Y + e) - ws.H(X, Y - e)) / (2 * e)
    slope = np.where(Hraw < 0.0, np.hypot(gx, gy), 0.0)
    S = np.zeros_like(D)
    print(f"grid {X.shape[0]} x {X.shape[1]} nodes, h = {a.h} mm, tool placed every {a.step} mm")
    T.STEP = a.step
    before = {}
    checks = fig["checks"]
    gouges, rapids = [], []
    for op in ops:
        kind, num = op[0], op[1]
        t1 = time.process_time()
        prev = S.copy()
        rapid = T.replay(S, a.h, op)
        gouge = float(max(0.0, np.max(D - S)))
        gouges.append(gouge)
        rapids.append(rapid)
        print(f"{kind} (T{num} {T.TOOLS[num][0]} {2 * T.TOOLS[num][1]:g} mm): gouge {gouge:.4f} mm, "
              f"deepest rapid into the stock it leaves {rapid:.4f} mm, "
              f"largest removed at a node {float(np.max(prev - S)):.3f} mm ({time.process_time() - t1:.1f} s)")
        before[kind] = prev
        if kind == "rest":
            into = float(max(0.0, np.max(np.minimum(D + leave, 0.0) - S)))
            fig.setdefault("rest_into_allowance", []).append(round(into, 4))
            print(f"  deepest cut into the allowance (design + {leave:g}): {into:.4f} mm")
        if kind == "rough":
            Tt = np.minimum(D + leave, 0.0)
            left = S - Tt
            shape, R = T.TOOLS[num]
            t1 = time.process_time()
            lim = min(float(spec.stock.depth_limit), float(tools[num].reach))
            reach_ = reach(Tt, a.h, shape, R, -lim)
            there = reach_ <= Tt + tol
            over = S - np.maximum(Tt, reach_)
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
            lo, hi = leave + float(left.min()), leave + float(left[there].max()) if there.any() else leave
            fig["allowance"] = [round(lo, 4), round(hi, 4)]
            fig["allowance_bound"] = [leave - tol, leave + step + tol]
            fig["rough_reaches_pct"] = round(100 * float(there.mean()), 1)
            fig["over_own_reach"] = round(float(np.max(over - step - tol)), 4)
            checks["allowance"] = bool(lo >= leave - tol - 1e-9 and hi <= leave + step + tol + 1e-9)
        if kind == "finish":
            removed = before["finish"] - S
            print(f"  finish engagement: largest thickness removed at a node {removed.max():.3f} mm "
                  f"(depth of cut {doc:g} mm)")
            fig["finish_doc"] = [round(float(removed.max()), 4), doc]
            checks["finish_depth_of_cut"] = bool(removed.max() <= doc + tol)
            shape, R = T.TOOLS[num]
            t1 = time.process_time()
            there = reach(D, a.h, shape, R) <= D + tol
            nl = (S - D) / np.sqrt(1.0 + slope ** 2)
            # the nodes over the bound: their reach confirmed on a fine local grid
            over = np.argwhere(there & (nl > scallop + tol))
            over = over[np.argsort(-nl[tuple(over.T)], kind="stable")][:RECHECK]
            unreached = [(i, j) for i, j in over if not reach_fine(ws, X[i, j], Y[i, j], shape, R, tol)]
            for i, j in unreached:
                there[i, j] = False
            if over.size:
                print(f"  reach confirmed on a fine grid (R/16) at the {len(over)} worst nodes over the bound: "
                      f"{len(unreached)} not reached")
            fig["reach_rechecked"] = [int(len(over)), len(unreached)]
            print(f"  after finishing: where the ball reaches the design ({100 * there.mean():.1f} % of the "
                  f"nodes) material left normal to it {float(nl[there].min()):+.4f} .. "
                  f"{float(nl[there].max()):.4f} mm (scallop {scallop:g} + tolerance {tol:g}); vertical "
                  f"{float((S - D)[there].max()):.4f} mm; elsewhere up to {float((S - D).max()):.3f} mm "
                  f"({time.process_time() - t1:.1f} s reach)")
            j = np.unravel_index(np.argmax(np.where(there, nl, -np.inf)), nl.shape)
            print(f"    largest at X{X[j]:.2f} Y{Y[j]:.2f}, slope {slope[j]:.2f}")
            fig["material_left"] = round(float(nl[there].max()), 4)
            fig["ball_reaches_pct"] = round(100 * float(there.mean()), 1)
            checks["material_left"] = bool(nl[there].max() <= scallop + tol)
    fig["gouge"] = round(max(gouges), 4) if gouges else None
    fig["gouge_by_op"] = [round(g, 4) for g in gouges]
    fig["rapid_into_stock"] = round(max(rapids), 4) if rapids else None
    checks["gouge"] = bool(gouges and max(gouges) <= tol)
    checks["rapids"] = bool(rapids and max(rapids) <= tol)
    checks["rs274"] = fig["rs274"]
    if grbl and fig["gvalidate"] is not None:
        checks["gvalidate"] = fig["gvalidate"]
    if "rest_into_allowance" in fig:
        checks["rest_allowance"] = max(fig["rest_into_allowance"]) <= tol
    for want in ("allowance", "finish_depth_of_cut", "material_left"):
        checks.setdefault(want, False)
    fig["accept"] = all(checks.values())
    print("verdict: " + ", ".join(f"{k} {'ok' if v else 'FAIL'}" for k, v in checks.items())
          + f" -> {'ACCEPT' if fig['accept'] else 'FAIL'}")
    print(f"total {time.process_time() - t0:.1f} s CPU")
    if a.json:
        print(json.dumps(fig))
    return 0 if fig["accept"] else 1


if __name__ == "__main__":
    sys.exit(main())
