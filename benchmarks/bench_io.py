"""CPU time of the two pure-Python text stages of ``fabkit gcode``: the verifier's
reader (``verify.read_program``) and the writer's coordinate formatting and move
lines (``gcode._format_array`` / ``gcode._move_lines``), best of N.

    fabkit gcode specs/surface.yaml -o /tmp/x.ngc
    python benchmarks/bench_io.py /tmp/x.ngc [--repeat 5]

The writer's input is rebuilt from the program itself (the points read back in mm,
kinds: G0 -> RAPID, G1 at the first G1's feed -> PLUNGE, other G1 -> CUT), so the
formatting sees the same values and modality as in the command. Prints CPU seconds
(time.process_time) and the load average.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from fabkit.toolpath import gcode, verify
from fabkit.toolpath.path import CUT, PLUNGE, RAPID


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.process_time()
        fn()
        times.append(time.process_time() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("program", type=Path)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--decimals", type=int, default=4)
    a = ap.parse_args()
    text = a.program.read_text()
    prog = verify.read_program(text)
    g1 = prog.kinds == verify.FEED
    plunge = np.nanmin(prog.feed[g1]) if g1.any() else np.nan
    kinds = np.where(~g1, RAPID, np.where(prog.feed == plunge, PLUNGE, CUT))
    pts = prog.points
    txt = gcode._format_array(pts, a.decimals)
    lines = gcode._move_lines(txt, kinds, "5", "2500", "600")
    print(f"program: {a.program} ({prog.lines} lines, {len(pts)} moves, {len(lines)} move lines rebuilt)")
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"read_program:  {best(lambda: verify.read_program(text), a.repeat):.3f} s CPU (best of {a.repeat})")
    print(f"_format_array: {best(lambda: gcode._format_array(pts, a.decimals), a.repeat):.3f} s CPU")
    print(f"_move_lines:   {best(lambda: gcode._move_lines(txt, kinds, '5', '2500', '600'), a.repeat):.3f} s CPU")
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
