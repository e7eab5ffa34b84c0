"""CPU time of the two pure-Python text stages of ``fabkit gcode``: the verifier's
reader (``reader.read_program``) and the writer's coordinate formatting and move
lines (``gcode._format_array`` / ``gcode._move_lines``), best of N.

    fabkit gcode specs/surface.yaml -o /tmp/x.ngc
    python benchmarks/bench_io.py /tmp/x.ngc [--repeat 5] [--against DIR]

The writer's input is rebuilt from the program itself (the points read back in mm,
kinds: G0 -> RAPID, G1 at the first G1's feed -> PLUNGE, other G1 -> CUT), so the
formatting sees the same values and modality as in the command. Prints CPU seconds
(time.process_time) and the load average. ``--against DIR``: also time the
reader.py (verify.py before it) and gcode.py of another checkout (e.g. ``git archive REV fabkit | tar -x -C DIR``),
the two versions' runs interleaved (the same load for both), and check that they
give the same Program and the same lines.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from pathlib import Path

import numpy as np

from fabkit.toolpath.program import gcode, reader
from fabkit.toolpath.path import CUT, PLUNGE, RAPID


def load(path: Path, name: str):
    """A module of another checkout's fabkit/toolpath, beside the installed one."""
    spec = importlib.util.spec_from_file_location(f"fabkit.toolpath.{name}", path)
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "fabkit.toolpath"
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("program", type=Path)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--decimals", type=int, default=4)
    ap.add_argument("--against", type=Path, help="a checkout's root (its fabkit/toolpath is compared)")
    a = ap.parse_args()
    text = a.program.read_text()
    prog = reader.read_program(text)
    g1 = prog.kinds == reader.FEED
    plunge = np.nanmin(prog.feed[g1]) if g1.any() else np.nan
    kinds = np.where(~g1, RAPID, np.where(prog.feed == plunge, PLUNGE, CUT))
    pts = prog.points
    txt = gcode._format_array(pts, a.decimals)
    lines = gcode._move_lines(txt, kinds, "5", "2500", "600")
    print(f"program: {a.program} ({prog.lines} lines, {len(pts)} moves, {len(lines)} move lines rebuilt)")
    versions = [("", reader, gcode)]
    if a.against:
        d = a.against / "fabkit" / "toolpath"
        older = d / "reader.py" if (d / "reader.py").is_file() else d / "verify.py"
        versions.insert(0, (" (against)", load(older, "_against_reader"),
                            load(d / "gcode.py", "_against_gcode")))
        _, v0, g0 = versions[0]
        p0 = v0.read_program(text)
        for f in ("start", "points", "kinds", "feed", "line", "tool", "offset"):
            np.testing.assert_array_equal(getattr(p0, f), getattr(prog, f))
        assert (p0.units, p0.lines, p0.tool_changes) == (prog.units, prog.lines, prog.tool_changes)
        assert (g0._format_array(pts, a.decimals) == txt).all()
        assert g0._move_lines(txt, kinds, "5", "2500", "600") == lines
        print("same Program and lines from both versions")
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    stages = {
        "read_program": lambda v, g: v.read_program(text),
        "_format_array": lambda v, g: g._format_array(pts, a.decimals),
        "_move_lines": lambda v, g: g._move_lines(txt, kinds, "5", "2500", "600"),
    }
    best_s = {}
    for _ in range(a.repeat):                      # interleaved: each version sees the same load
        for stage, fn in stages.items():
            for tag, v, g in versions:
                t = time.process_time()
                fn(v, g)
                dt = time.process_time() - t
                best_s[stage, tag] = min(best_s.get((stage, tag), dt), dt)
    for stage in stages:
        for tag, _, _ in versions:
            print(f"{stage + tag + ':':<28} {best_s[stage, tag]:.3f} s CPU (best of {a.repeat})")
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")

if __name__ == "__main__":
    main()
