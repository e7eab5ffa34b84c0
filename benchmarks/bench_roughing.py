"""The rough-then-finish job against today's single-ball stepdown job, at the same
allowance, on the paper's spec (specs/surface.yaml: the block 53.75 mm deep, the
1/4 in ball).

    python benchmarks/bench_roughing.py [SPEC] [--stepdown-ball 6.35] [--leave 0.5]
        [--rough-diameter 12.7] [--rough-stepdown 12.7] [--rough-stepover 5.5]
        [--rough-feed 4000] [--rough-plunge 1000] [--machine FILE] [--no-verify]

Rows:
- ``ball stepdown``: today's job, ``machining.stepdown`` (the ball roughs in Z levels along
  the finishing passes) with ``machining.leave``;
- ``rough + finish``: a ``roughing`` section with a flat end mill (T2, its own feeds),
  the same ``leave``, then the same ball (T1) finishing.

Both jobs are planned by :func:`fabkit.toolpath.job.run_job` and written by its writer;
every column comes from the programs' TEXT read back: lines, and the time by ONE
estimator for both (:func:`fabkit.toolpath.program.reader.estimate_time`: G1 length / F, G0 at
5000 mm/min, no acceleration), plus the machine planner's time with ``--machine``. The
planning wall time is printed too (by hand, not a test). Needs fabkit/toolpath/rough/roughing.py.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _hm(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60:02d} min"


def specs(raw: dict, a) -> dict:
    """{row name: raw spec} for the two jobs."""
    today = copy.deepcopy(raw)
    today["machining"].update(stepdown=a.stepdown_ball, leave=a.leave)
    rough = copy.deepcopy(raw)
    rough["tool"]["number"] = 1
    rough["tools"] = [{"number": 2, "shape": "flat", "diameter": a.rough_diameter, "reach": a.rough_reach,
                       "feed": a.rough_feed, "plunge": a.rough_plunge, "spindle": a.rough_spindle}]
    rough["roughing"] = {"tool": 2, "stepdown": a.rough_stepdown, "stepover": a.rough_stepover,
                         "leave": a.leave}
    return {"ball stepdown": today, "rough + finish": rough}


def measure(raw: dict, name: str, machine_file, verify: bool) -> dict:
    from fabkit.machine.profile import dialect_for_machine, machine_from_spec
    from fabkit.spec import validate
    from fabkit.surface import Surface
    from fabkit.toolpath.job import run_job
    from fabkit.toolpath.program.reader import estimate_time, read_program

    spec = validate(raw, f"{name}.yaml")
    surface = Surface.from_spec(spec)
    machine = machine_from_spec(spec, machine_file) if machine_file else None
    if machine is not None:
        spec = dialect_for_machine(spec, machine)      # as `fabkit gcode --machine`: its dialect
    t0 = time.perf_counter()
    job = run_job(spec, surface, machine=machine, verify=verify)
    wall = time.perf_counter() - t0
    programs = job.programs or [("", job.text)]
    est = sum(estimate_time(read_program(text), job.profile.rapid) for _, text in programs)
    row = {"job": name, "operations": ", ".join(f.kind for f in job.figures) or "finish (+ ball roughing)",
           "programs": len(programs), "lines": sum(t.count("\n") for _, t in programs), "length_feed_s": est,
           "machine_s": None, "plan_s": wall, "verdict": job.message}
    if machine is not None:
        from fabkit.machine.planner import run_time

        row["machine_s"] = sum(run_time(text, machine).total_s for _, text in programs)
        row["per_operation"] = [(f.kind, f.lines, f.estimate_s, f.run_s) for f in job.figures]
    return row


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("spec", nargs="?", default=str(ROOT / "specs" / "surface.yaml"))
    p.add_argument("--stepdown-ball", type=float, default=6.35, help="mm: today's machining.stepdown")
    p.add_argument("--leave", type=float, default=0.5, help="mm: the allowance of both jobs")
    p.add_argument("--rough-diameter", type=float, default=12.7, help="mm: the flat end mill (1/2 in)")
    p.add_argument("--rough-reach", type=float, default=76.0, help="mm: its flute length")
    p.add_argument("--rough-stepdown", type=float, default=12.7, help="mm: 1 x D, foam")
    p.add_argument("--rough-stepover", type=float, default=5.5, help="mm: about 0.43 x D")
    p.add_argument("--rough-feed", type=float, default=4000.0, help="mm/min")
    p.add_argument("--rough-plunge", type=float, default=1000.0, help="mm/min")
    p.add_argument("--rough-spindle", type=float, default=16000.0, help="rpm")
    p.add_argument("--machine", default=None, help="machine profile: add the controller's planner time")
    p.add_argument("--no-verify", action="store_true")
    p.add_argument("--only", choices=("ball stepdown", "rough + finish"), default=None, help="run one row")
    a = p.parse_args(argv)
    raw = yaml.safe_load(Path(a.spec).read_text())
    from fabkit.errors import FabkitError

    rows, missing = [], []
    for name, r in specs(raw, a).items():
        if a.only and name != a.only:
            continue
        try:
            rows.append(measure(r, name, a.machine, not a.no_verify))
        except (FabkitError, ImportError) as exc:     # e.g. a fabkit without the roughing planner
            missing.append(f"{name}: not run ({exc})")
    print(f"{Path(a.spec).name}: same allowance leave {a.leave:g} mm; time by one estimator "
          "(program text read back: G1 length / F, G0 at 5000 mm/min, no acceleration)")
    print()
    head = "| job | operations | programs | lines | time (length/feed) |" + \
        (" time (machine planner) |" if a.machine else "") + " planned in |"
    print(head)
    print("|" + "---|" * (head.count("|") - 1))
    for r in rows:
        print(f"| {r['job']} | {r['operations']} | {r['programs']} | {r['lines']:,} | "
              f"{_hm(r['length_feed_s'])} ({r['length_feed_s']:.0f} s) |"
              + (f" {_hm(r['machine_s'])} |" if a.machine else "") + f" {r['plan_s']:.1f} s |")
    print()
    for r in rows:
        print(f"{r['job']}: {r['verdict']}")
        for kind, lines, lf, ms in r.get("per_operation") or ():
            print(f"  {kind}: {lines:,} lines, length/feed {lf / 60:.1f} min"
                  + (f", machine planner {ms / 60:.1f} min" if ms is not None else ""))
    for m in missing:
        print(m)
    if len(rows) == 2:
        a0, b0 = rows
        print(f"\nrough + finish / ball stepdown: time x{b0['length_feed_s'] / a0['length_feed_s']:.2f}, "
              f"lines x{b0['lines'] / a0['lines']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
