"""CPU time of ``fabkit time`` on a 100 000-line program, against the import floor.

    python benchmarks/bench_time.py [--lines 100000] [--repeat 3]

The program: a CAM-style mix (modal X Y lines, G1 with Z and F, G2/G3 arcs of a few
segments, rapids, a spindle speed change every 5 000 lines), written to a temporary
folder. For each repeat, in turn: the floor (``python -c "import numpy"``, what any
fabkit command pays) and ``fabkit time PROGRAM --machine grbl-router``. CPU time is
user + sys of the child (``os.wait4``); the best run is reported, with every run and
the load average at it. The target: 2 s of CPU for 100 000 lines.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np

FLOOR = [sys.executable, "-c", "import numpy"]


def program(n: int, seed: int = 1) -> str:
    rng = np.random.default_rng(seed)
    out = ["%", "(benchmark)", "G21 G90 G17 G94", "M3 S12000", "G0 X0 Y0 Z5", "G1 Z-1 F300", "G1 X1 F3000"]
    x = y = 0.0
    while len(out) < n - 3:
        r = rng.random()
        if len(out) % 5000 == 0:
            out.append(f"S{int(rng.integers(8, 20)) * 1000}")
        elif r < 0.05:
            rr = rng.uniform(0.5, 3.0)
            out.append(f"G{2 if r < 0.025 else 3} X{x + 2 * rr:.3f} Y{y:.3f} I{rr:.3f} J0")
            x += 2 * rr
            out.append(f"G1 X{x:.3f}")
        elif r < 0.06:
            out.append(f"G0 Z5\nX{x:.3f} Y{y:.3f}\nG1 Z-1 F300\nG1 X{x + 0.5:.3f} F3000")
            x += 0.5
        else:
            x += rng.uniform(-1, 1)
            y += rng.uniform(-1, 1)
            out.append(f"X{x:.3f} Y{y:.3f}")
    out += ["G0 Z5", "M5", "M30"]
    text = "\n".join(out) + "\n"
    return "\n".join(text.splitlines()[:n]) + "\n"


def cpu(argv, env):
    p = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, ru = os.wait4(p.pid, 0)
    return ru.ru_utime + ru.ru_stime, os.getloadavg()[0], os.waitstatus_to_exitcode(status)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lines", type=int, default=100_000)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    env = dict(os.environ)
    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "bench.nc")
        with open(path, "w") as fh:
            fh.write(program(a.lines))
        cmd = [sys.executable, "-m", "fabkit", "time", path, "--machine", "grbl-router"]
        runs = {"floor": [], "fabkit time": []}
        for _ in range(a.repeat):
            for name, argv in (("floor", FLOOR), ("fabkit time", cmd)):
                t, load, code = cpu(argv, env)
                if code != 0:
                    print(f"{name}: exit {code}")
                    return 1
                runs[name].append((t, load))
    for name, rs in runs.items():
        best = min(rs)
        print(f"{name}: best {best[0]:.2f} s CPU (runs: " + ", ".join(f"{t:.2f} s at load {ld:.2f}" for t, ld in rs)
              + ")")
    ratio = min(runs["fabkit time"])[0] / min(runs["floor"])[0]
    print(f"fabkit time of {a.lines} lines: {min(runs['fabkit time'])[0]:.2f} s CPU, {ratio:.1f}x the import floor")
    return 0


if __name__ == "__main__":
    sys.exit(main())
