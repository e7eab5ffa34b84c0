"""Time ``fabkit gcode SPEC`` in-process (best of N) and print the plan / write /
verify split, program lines and the verified gouge and material left.

    python benchmarks/bench_gcode.py [SPEC] [--repeat 3]
    python benchmarks/bench_gcode.py --floor [SPEC ...] [--repeat 3] [--max-time S] [--numpy]

Outputs go to a scratch folder. Target: specs/surface.yaml in under 20 s on the
2-core reference machine.

``--floor``: each SPEC (default specs/surface.yaml) is run as ``fabkit gcode SPEC
--no-progress --json`` in a fresh process, alternated with the import floor
(``python -c "import numpy, scipy.integrate, sympy"``) in the same run, and each is
reported as CPU time (user + sys of the child, resource.getrusage: not wall time,
which a loaded machine inflates), peak resident memory, the ratio to the floor's
CPU time (best of --repeat each), the load average at each run, and the stages'
CPU seconds (the command's timers read time.process_time in the child) beside
the time guard's estimate (toolpath.finish.guards; its ratio measured / estimated).
``--numpy`` adds a run of each SPEC without the compiled kernels (``FABKIT_NO_KERNELS=1``,
the numpy code they transcribe) right after it, and checks the programs are the same
bytes. With two SPECs or more the first's CPU time is also given as a ratio to the
second's (``--floor specs/surface_roughing.yaml specs/surface.yaml``: the paper's whole
job against its finishing program alone, README). The kernels' cache is ``FABKIT_CACHE_DIR`` (warm it with one run first: the
cold build is not what this measures).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


FLOOR = "import numpy, scipy.integrate, sympy"
# the child: fabkit's stage timers read CPU time; prints the guard's estimate on stderr
CHILD = """
import json, sys, time
time.perf_counter = time.process_time
from fabkit.toolpath.finish import guards
_estimate = guards.estimate
def estimate(*a, **k):
    est = _estimate(*a, **k)
    print("ESTIMATE " + json.dumps({k: v for k, v in est.items() if isinstance(v, (int, float))}), file=sys.stderr)
    return est
guards.estimate = estimate
from fabkit.toolpath.finish import raster
raster.estimate = estimate
from fabkit.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _env(extra=None) -> dict:
    """The children's environment: as a user's shell, bytecode written and read (a
    PYTHONDONTWRITEBYTECODE left set would recompile every module on every run)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return {**env, **(extra or {})}


def _compile_bytecode() -> None:
    """Write fabkit's bytecode once, as its first run on a user's machine does."""
    import compileall

    compileall.compile_dir(str(ROOT / "fabkit"), quiet=1)


def _child(argv, cwd, env=None) -> dict:
    """CPU seconds (user + sys), peak RSS (MB), load average, stdout/stderr of one child
    (its own rusage, from os.wait4)."""
    import subprocess

    load = os.getloadavg()[0]
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        p = subprocess.Popen([sys.executable, *argv], cwd=cwd, stdout=fo, stderr=fe, text=True,
                             env=_env(env))
        _, status, ru = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        out, err = fo.read(), fe.read()
    return {"cpu": ru.ru_utime + ru.ru_stime, "rss_mb": ru.ru_maxrss / 1024.0, "load": load,
            "code": p.returncode, "out": out, "err": err}


def floor_main(a) -> int:
    """The --floor mode: CPU-time ratios to the import floor, measured in the same run."""
    _compile_bytecode()
    specs = [str(Path(s).resolve()) for s in (a.spec or [str(ROOT / "specs" / "surface.yaml")])]
    extra = ["--max-time", str(a.max_time)] if a.max_time else []
    floors = []
    modes = [("", {})] + ([(" (numpy)", {"FABKIT_NO_KERNELS": "1"})] if a.numpy else [])
    rows = {s + tag: [] for s in specs for tag, _ in modes}
    same = {}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(a.repeat):
            floors.append(_child(["-c", FLOOR], tmp))
            for s in specs:
                progs = []
                for tag, env in modes:       # alternated: kernels, then the numpy drop cutter
                    out = Path(tmp) / (Path(s).stem + tag.strip(" ()") + ".ngc")
                    r = _child(["-c", CHILD, "gcode", s, "--no-progress", "--json", "-o", str(out), *extra],
                               tmp, {"SOURCE_DATE_EPOCH": "1700000000", **env})
                    if r["code"] not in (0, 1):
                        print(f"{s}: exit {r['code']}: {r['err'].strip().splitlines()[-1:]}", file=sys.stderr)
                        return r["code"]
                    rows[s + tag].append(r)
                    progs.append(out.read_bytes())
                if len(progs) > 1:
                    same[s] = same.get(s, True) and progs[0] == progs[1]
    floor = min(f["cpu"] for f in floors)
    fl = ", ".join(f"{f['cpu']:.2f}" for f in floors)
    ld = ", ".join(f"{f['load']:.1f}" for f in floors)
    print(f"import floor ({FLOOR}): {floor:.2f} s CPU (best of {a.repeat}; {fl}; load {ld})")
    for s in rows:
        best = min(rows[s], key=lambda r: r["cpu"])
        j = json.loads(best["out"])
        t = j["timings_s"]
        est = next((json.loads(line[9:]) for line in best["err"].splitlines() if line.startswith("ESTIMATE ")), {})
        runs = ", ".join(f"{r['cpu']:.2f}" for r in rows[s])
        print(f"{Path(s).name}: {best['cpu']:.2f} s CPU = {best['cpu'] / floor:.2f}x the floor, peak "
              f"{best['rss_mb']:.0f} MB, load {best['load']:.1f} (runs {runs} s); stages CPU: plan "
              f"{t['plan']:.2f}, write {t['write']:.2f}, verify {t['verify']:.2f}, sheet {t['sheet']:.2f}; "
              f"{j['passes']} passes, {j['lines']} lines")
        if est:
            print(f"    guard's estimate {est['seconds']:.2f} s, {est['bytes'] / 1e6:.0f} MB: measured / estimated "
                  f"{best['cpu'] / est['seconds']:.2f} (time), {best['rss_mb'] * 1e6 / est['bytes']:.2f} (memory)")
    for s, ok in same.items():
        print(f"{Path(s).name}: programs with and without the kernels {'byte-identical' if ok else 'DIFFER'}")
    if len(specs) >= 2:
        # the first spec against the second (e.g. the paper's whole job against its finishing program)
        a0, b0 = (min(r["cpu"] for r in rows[s]) for s in specs[:2])
        loads = [r["load"] for s in specs[:2] for r in rows[s]]
        print(f"{Path(specs[0]).name} / {Path(specs[1]).name}: {a0 / b0:.2f}x CPU (best of {a.repeat} each, "
              f"alternated; load {min(loads):.1f}-{max(loads):.1f})")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec", nargs="*" if "--floor" in sys.argv else "?",
                    default=None if "--floor" in sys.argv else str(ROOT / "specs" / "surface.yaml"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--floor", action="store_true", help="CPU-time ratios to the import floor, in subprocesses")
    ap.add_argument("--max-time", type=float, default=None, help="passed to fabkit gcode (--floor)")
    ap.add_argument("--numpy", action="store_true",
                    help="--floor: also run each spec with FABKIT_NO_KERNELS=1 (the numpy drop cutter and "
                         "swept cut), alternated, and compare the programs")
    a = ap.parse_args()
    if a.floor:
        return floor_main(a)
    from fabkit.cli import main as fabkit

    spec = str(Path(a.spec).resolve())
    best = None
    with tempfile.TemporaryDirectory() as tmp:
        old = os.getcwd()
        os.chdir(tmp)
        try:
            for i in range(a.repeat):
                buf = io.StringIO()
                t0 = time.perf_counter()
                with contextlib.redirect_stdout(buf):
                    code = fabkit(["gcode", spec, "--json"])
                wall = time.perf_counter() - t0
                if code not in (0, 1):
                    print(f"run {i + 1}: exit {code}", file=sys.stderr)
                    return code
                s = json.loads(buf.getvalue())
                if code == 1:
                    print(f"run {i + 1}: verification FAILED: {'; '.join(s['failures'])}")
                print(f"run {i + 1}: {wall:.2f} s (plan {s['timings_s']['plan']:.2f}, write "
                      f"{s['timings_s']['write']:.2f}, verify {s['timings_s']['verify']:.2f}, sheet "
                      f"{s['timings_s']['sheet']:.2f})")
                if best is None or wall < best[0]:
                    best = (wall, s)
        finally:
            os.chdir(old)
    wall, s = best
    u = s["units"]
    t = s["timings_s"]
    print(f"best of {a.repeat}: {wall:.2f} s  (plan {t['plan']:.2f}, write {t['write']:.2f}, "
          f"verify {t['verify']:.2f}, sheet {t['sheet']:.2f})")
    print(f"program: {s['lines']} lines, {s['passes']} passes, stepover {s['stepover_min']:.4g}-{s['stepover']:.4g} {u}, "
          f"est. machining {s['estimated_time_s'] / 60:.0f} min")
    print(f"verified at {s['verification_points']} points: largest gouge {s['max_gouge']:.5f} {u}, "
          f"material left {s['max_material_left']:.5f} {u} (scallop {s['scallop']:g}, tolerance {s['tolerance']:g})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
