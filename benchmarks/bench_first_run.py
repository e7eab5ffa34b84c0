"""The first run's compile, part by part, against the estimate fabkit states.

Clones this repository's HEAD (commit first) into a temporary folder (no numba cache in the tree), points
``FABKIT_CACHE_DIR`` at an empty folder, and in a fresh process compiles what a first
``fabkit gcode`` / ``check`` / ``report`` compiles (:func:`fabkit.first_run.prepare`'s parts),
printing each part's CPU seconds next to :func:`fabkit.first_run.cold_kernels`' estimate.
Each order is run in its own clone (the simulator first, then the toolpath; and the reverse),
since the first compile of a process also starts LLVM. Then a cold ``fabkit gcode`` whole,
its CPU against the total it announces.

    python benchmarks/bench_first_run.py [SPEC]      # default specs/surface.yaml

CPU is user + sys of the child (``os.wait4``); the load average is printed with each run.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PARTS = r'''
import sys, resource
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF); return r.ru_utime + r.ru_stime
from fabkit.spec import load_spec
from fabkit import first_run
from fabkit.physics.engine.batch import engine
from fabkit.physics.models import problem_from_spec
from fabkit.surface import Surface
from fabkit.toolpath.finish import kernels
sp = load_spec(sys.argv[1])
est = first_run.cold_kernels(sp)
print(f"estimate: simulator {est['simulator']:.1f} s, toolpath {est['toolpath']:.1f} s")
def sim():
    t = cpu(); engine(problem_from_spec(sp)); return cpu() - t
def tp():
    t = cpu(); kernels.kernel_for(Surface.from_spec(sp)); out = {"drop cutter + formula": cpu() - t}
    for disp, sig in first_run._toolpath_signatures():
        t = cpu(); disp.compile(sig); out[disp.py_func.__name__] = cpu() - t
    return out
order = sys.argv[2].split(",")
for part in order:
    if part == "simulator":
        print(f"measured: simulator {sim():.2f} s")
    else:
        d = tp()
        print(f"measured: toolpath {sum(d.values()):.2f} s (" + ", ".join(f"{k} {v:.2f}" for k, v in d.items()) + ")")
'''


def _fresh_clone(base: Path) -> Path:
    dst = base / "clone"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(dst)], check=True)
    return dst


def _run(cmd, env, cwd):
    # cwd: the clone (``python -c`` puts the working folder first on sys.path)
    p = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    _, status, ru = os.wait4(p.pid, 0)
    out = p.stdout.read()
    return out, ru.ru_utime + ru.ru_stime, os.waitstatus_to_exitcode(status)


def main(argv=None) -> int:
    spec = (argv or sys.argv[1:] or ["specs/surface.yaml"])[0]
    for order in ("simulator,toolpath", "toolpath,simulator"):
        with tempfile.TemporaryDirectory() as d:
            clone = _fresh_clone(Path(d))
            env = dict(os.environ, PYTHONPATH=str(clone), FABKIT_CACHE_DIR=str(Path(d) / "cache"))
            out, cpu, rc = _run([sys.executable, "-c", PARTS, str(ROOT / spec), order], env, clone)
            print(f"-- parts in the order {order} (load {os.getloadavg()[0]:.2f}; process {cpu:.1f} s CPU, exit {rc})")
            print(out.rstrip())
    with tempfile.TemporaryDirectory() as d:
        clone = _fresh_clone(Path(d))
        env = dict(os.environ, PYTHONPATH=str(clone), FABKIT_CACHE_DIR=str(Path(d) / "cache"))
        cmd = [sys.executable, "-m", "fabkit.cli", "gcode", str(ROOT / spec), "-o", str(Path(d) / "a.ngc")]
        # the announcement goes to a stage bar or a terminal; --json keeps it out of the way,
        # so print the estimate for this cache first, from the same clone
        est, _, _ = _run([sys.executable, "-c", PARTS.split("order =")[0], str(ROOT / spec)], env, clone)
        out, cpu, rc = _run(cmd + ["--no-progress"], env, clone)
        print(f"-- a cold `fabkit gcode {spec}` (load {os.getloadavg()[0]:.2f}): {cpu:.1f} s CPU, exit {rc}; "
              f"{est.strip()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
