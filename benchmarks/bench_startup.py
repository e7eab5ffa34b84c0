"""CPU time of fabkit commands against the import floor, old code and new alternated.

    python benchmarks/bench_startup.py [--base DIR] [--repeat 3] "fabkit gcode SPEC -o OUT" ...

For each command, in turn and ``--repeat`` times: the floor (``python -c "import numpy,
scipy.integrate, sympy"``), the command with ``PYTHONPATH=DIR`` (a checkout of the old
code, e.g. ``git archive COMMIT | tar -x -C DIR``; left out without ``--base``), then the
command with this checkout. CPU time is user + sys of the child (``os.wait4``), never
wall time; the best of the runs is reported with every run and the load average at it.
Warm the cache (``FABKIT_CACHE_DIR``) with one run of each code first.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

FLOOR = [sys.executable, "-c", "import numpy, scipy.integrate, sympy"]


def cpu(argv, env):
    p = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, ru = os.wait4(p.pid, 0)
    return ru.ru_utime + ru.ru_stime, os.getloadavg()[0], os.waitstatus_to_exitcode(status)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", nargs="+", help="a command line, quoted")
    ap.add_argument("--base", default=None, help="a checkout of the old code (put on PYTHONPATH)")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    new_env = dict(os.environ)
    new_env.pop("PYTHONPATH", None)
    codes = [("floor", None, new_env)]
    if a.base:
        codes.append(("before", None, {**os.environ, "PYTHONPATH": a.base}))
    codes.append(("after", None, new_env))
    res: dict = {}
    for _ in range(a.repeat):
        for c in a.command:
            for name, _, env in codes:
                argv = FLOOR if name == "floor" else c.split()
                res.setdefault((c, name), []).append(cpu(argv, env))
    for c in a.command:
        floor = min(t for t, _, _ in res[(c, "floor")])
        print(f"{c}\n   floor {floor:.2f} s (runs {', '.join(f'{t:.2f}' for t, _, _ in res[(c, 'floor')])})")
        for name, _, _ in codes[1:]:
            r = res[(c, name)]
            best = min(t for t, _, _ in r)
            print(f"   {name} {best:.2f} s = {best / floor:.2f}x the floor (runs {', '.join(f'{t:.2f}' for t, _, _ in r)};"
                  f" load {', '.join(f'{ld:.1f}' for _, ld, _ in r)}; exit {sorted({s for _, _, s in r})})")


if __name__ == "__main__":
    main()
