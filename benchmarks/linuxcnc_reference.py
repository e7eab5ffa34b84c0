"""fabkit's LinuxCNC run time against LinuxCNC's own trajectory planner.

The reference is LinuxCNC's `src/emc/tp` (the isolated build of the sittner/linuxcnc
fork, `isolated-tp`), built outside this repository with a small driver that reads
rs274's canonical moves (`rs274 -g`), applies emccanon.cc's per-axis velocity and
acceleration limits and its naive-CAM collinear merge (G64 Q), sets the term condition
from SET_MOTION_CONTROL_MODE, drains the queue before dwell, spindle, coolant and tool
commands, and runs `tpRunCycle` every 1 ms servo period (look-ahead depth 50, arc
blends on). Set LCNCTIME to that driver (arguments: VX VY VZ AX AY AZ VLIMIT in mm/s and
mm/s^2; canonical moves on stdin; prints seconds).

    LCNCTIME=/path/to/lcnctime python benchmarks/linuxcnc_reference.py PROGRAM.ngc ... [--seed N]

Programs: the ones given (fabkit's, e.g. for three specs) and generated ones: a dense
raster (0.1 mm points), long moves, two random walks; each at G64 P0.01 and P0.1, on a
slow mill and a router.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys

import numpy as np

from fabkit.machine.planner import run_time
from fabkit.machine.profile import Machine

MACHINES = {
    "slow mill": dict(max_rate=(1500.0, 1500.0, 750.0), acceleration=(100.0, 100.0, 50.0)),
    "router": dict(max_rate=(6000.0, 6000.0, 3000.0), acceleration=(1000.0, 1000.0, 500.0)),
}


def raster(step=0.1, rows=12, length=60.0, feed=2000) -> str:
    out = ["G21 G90 G17 G64 P0.01", "G0 Z5", "G0 X0 Y0", "M3 S10000", f"G1 Z0 F{feed}"]
    for r in range(rows):
        xs = np.arange(0, length + 1e-9, step)
        if r % 2:
            xs = xs[::-1]
        for x in xs:
            out.append(f"G1 X{x:.3f} Y{r * 1.0:.3f} Z{-0.5 * np.sin(x / 7.0) - 0.2 * np.cos(r):.4f}")
    out += ["G0 Z5", "M5", "M2"]
    return "\n".join(out) + "\n"


def long_moves() -> str:
    out = ["G21 G90 G17 G64 P0.01", "M3 S10000"]
    for i in range(30):
        out += [f"G0 X{(i % 3) * 10:.1f} Y{i * 3:.1f} Z5", "G1 Z-1 F300", f"G1 X{150 + (i % 3) * 10:.1f} F3000",
                f"G1 Y{i * 3 + 2:.1f}", "G1 X0 F2500", "G0 Z5"]
    out += ["M5", "M2"]
    return "\n".join(out) + "\n"


def random_walk(seed: int, n: int = 3000) -> str:
    rng = np.random.default_rng(seed)
    out = ["G21 G90 G17 G64 P0.01", "M3 S10000"]
    p = np.zeros(3)
    for i in range(n):
        d = rng.normal(size=3)
        d[2] *= 0.2
        p = p + d / np.linalg.norm(d) * rng.uniform(0.05, 20)
        if rng.random() < 0.05:
            out.append(f"G0 X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f}")
        else:
            out.append(f"G1 X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f} F{rng.uniform(200, 8000):.0f}")
        if rng.random() < 0.003:
            out += ["M5", "M3 S10000"]
    out += ["M5", "M2"]
    return "\n".join(out) + "\n"


def with_p(text: str, p: float) -> str:
    text = re.sub(r"G64 ?P[0-9.]+", f"G64 P{p:g}", text)
    return text if "G64" in text else f"G64 P{p:g}\n" + text


def reference(exe: str, text: str, m: dict) -> float:
    with open("/tmp/_lcnc_ref.ngc", "w") as fh:
        fh.write(text)
    canon = subprocess.run(["rs274", "-g", "/tmp/_lcnc_ref.ngc"], capture_output=True, text=True, check=True).stdout
    args = [f"{v / 60:.6g}" for v in m["max_rate"]] + [f"{v:.6g}" for v in m["acceleration"]] + ["0"]
    r = subprocess.run([exe] + args, input=canon, capture_output=True, text=True, check=True)
    return float(r.stdout.split()[0])


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("programs", nargs="*")
    ap.add_argument("--seed", type=int, default=11)
    a = ap.parse_args()
    exe = os.environ.get("LCNCTIME")
    if not exe or not os.path.exists(exe):
        print("set LCNCTIME to the LinuxCNC planner driver (see the docstring)")
        return 2
    cases = [(os.path.basename(p), open(p).read()) for p in a.programs]
    cases += [("dense raster (0.1 mm)", raster()), ("long moves", long_moves()),
              ("random walk A", random_walk(a.seed)), ("random walk B", random_walk(a.seed + 1))]
    print("| program | G64 P | machine | LinuxCNC (s) | fabkit (s) | error |\n|---|---|---|---|---|---|")
    worst = 0.0
    for name, text in cases:
        for p in (0.01, 0.1):
            t = with_p(text, p)
            for mname, m in MACHINES.items():
                ref = reference(exe, t, m)
                ours = run_time(t, Machine(controller="linuxcnc", name=mname, **m)).total_s
                err = 100 * (ours / ref - 1)
                worst = max(worst, abs(err))
                print(f"| {name} | {p:g} | {mname} | {ref:.1f} | {ours:.1f} | {err:+.2f} % |", flush=True)
    print(f"\nworst |error| {worst:.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
