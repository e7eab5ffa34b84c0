"""Rerun every figure and every command output the docs quote, so that a change reruns them.

    python docs/regenerate.py              # every job (tens of minutes on 2 cores)
    python docs/regenerate.py --list       # the jobs, the doc that quotes each, and its command
    python docs/regenerate.py compare ramp # only these jobs

Each job runs one documented ``fabkit`` command from the repository root, exactly as a user
types it, writes the figure the doc shows (under docs/), and records the command, its
summary (stdout), its wall time and the load average before and after it in
``docs/outputs/<job>.txt``. A doc quotes those files; when a figure or a figure's number in
a doc disagrees with its output file, the doc is stale. (One job runs a benchmark script,
``benchmarks/ball_compare.py``: the three models' checks side by side.)

A passage of README.md or docs/*.md that quotes an output is marked
``<!-- numbers: JOB[, JOB] -->`` ... ``<!-- /numbers -->``; tests/test_doc_numbers.py checks
every decimal number inside it against those outputs (to the digits quoted), and every whole
number (a count) against the whole numbers they print, so a number
that drifts from what the command prints fails the suite. A time or load inside such a
passage depends on the machine and is named in the mark, ``<!-- numbers: JOB; timings: 65.4 0.7 -->``,
and not checked; so is a spec's input or a year the passage names, ``; inputs: 25``. Every
other number of those pages sits in a passage marked with its kind, ``<!-- figures: benchmark
benchmarks/X.py -->``, ``history``, ``reference``, ``input``, ``derived NAME from JOB`` (a figure
computed from the outputs, recomputed by the test) ...: tests/test_doc_figures.py fails on a
number outside every mark, and on an output whose last line ("quoted by") does not name exactly
the docs that quote it. Jobs
run in this order: ``time-router``, ``time-defaults``, ``time-fast`` and ``time-unequal`` time the
program ``gcode-router`` writes, ``time-bowl-*`` the one ``gcode-bowl`` writes. The ``error-*`` jobs
give a command bad input (docs/errors.md): their output records the one line on stderr and exit 2.
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "outputs"


@dataclass(frozen=True)
class Job:
    name: str
    doc: str
    argv: tuple[str, ...]
    script: str | None = None     # a benchmark script run with these arguments, in place of fabkit

    @property
    def shown(self) -> str:
        """The command as the output file's first line gives it."""
        return ((f"python {self.script} " if self.script else "fabkit ") + shlex.join(self.argv)).rstrip()


JOBS = (
    Job("check", "README.md, docs/ball.md, docs/design.md, docs/sweep_check.md", ("check", "specs/surface.yaml")),
    Job("check-as-built", "README.md", ("check", "specs/surface_as_built.yaml")),
    Job("check-clipped-top2", "docs/sweep_check.md", ("check", "tests/fixtures/check/clipped_top2.yaml")),
    Job("ball-compare", "README.md, docs/ball.md, docs/sweep_check.md, docs/lab.md, docs/simulator.md, docs/numerics.md", (), script="benchmarks/ball_compare.py"),
    Job("calibrate", "docs/simulator.md, README.md, docs/ball.md, docs/lab.md", ("calibrate", "specs/surface.yaml", "--height", "1", "4.5",
                                           "--v-in", "50")),
    Job("calibrate-range", "README.md, docs/simulator.md", ("calibrate", "specs/surface.yaml", "--height", "0.2", "4.5")),
    Job("sweep", "docs/sweep_check.md, docs/explore.md, docs/paper.md, README.md",
        ("sweep", "specs/surface.yaml", "--plot", "docs/sweep.png")),
    # the paper's spec undamped on the two point models (docs/sweep_check.md's table; about 10 s each)
    Job("sweep-undamped-full", "docs/sweep_check.md", ("sweep", "tests/fixtures/sweep/undamped_full.yaml")),
    Job("sweep-undamped-simplified", "docs/sweep_check.md",
        ("sweep", "tests/fixtures/sweep/undamped_simplified.yaml")),
    # docs/paper.md's table: the point model in cm, and both models in inches (about 10 s each)
    Job("sweep-full", "docs/paper.md, docs/sweep_check.md", ("sweep", "tests/fixtures/paper_full.yaml")),
    Job("sweep-full-in", "docs/paper.md", ("sweep", "tests/fixtures/sweep/paper_full_in.yaml")),
    Job("sweep-ball-in", "docs/paper.md", ("sweep", "tests/fixtures/sweep/paper_ball_in.yaml")),
    Job("sweep-ball-in-2p5cm", "docs/paper.md", ("sweep", "tests/fixtures/sweep/paper_ball_in_2p5cm.yaml")),
    # and the point model with every height 2.54 times lower, lengths in cm (docs/paper.md's last part)
    # the inch spec's check: UNMACHINABLE on the cm stock (about 3 s)
    Job("check-full-in", "docs/paper.md", ("check", "tests/fixtures/sweep/paper_full_in.yaml")),
    # specs/bowl.yaml with top 0: no v_critical in the range, and the sweep says why (about 2 s)
    Job("sweep-bowl-top0", "docs/sweep_check.md", ("sweep", "tests/fixtures/sweep/bowl_top0.yaml")),
    Job("sweep-full-flat", "docs/paper.md", ("sweep", "tests/fixtures/sweep/paper_full_flat.yaml")),
    # docs/ball.md's formula in mm with a 25 mm ball (tests/fixtures/ball/mm_formula.yaml; about 5 s of CPU)
    Job("sweep-ball-mm", "docs/ball.md", ("sweep", "tests/fixtures/ball/mm_formula.yaml")),
    Job("stl", "docs/stl.md, README.md", ("stl", "specs/surface.yaml")),
    Job("gcode-surface", "docs/gcode.md, README.md, docs/toolpath.md",
        ("gcode", "specs/surface.yaml", "--no-progress")),
    Job("gcode-bowl", "docs/gcode.md", ("gcode", "specs/bowl.yaml", "--no-progress")),
    # two V creases crossing (tests/fixtures/precision/crossing_v.yaml): gcode adds passes after verifying
    Job("gcode-crossing-v", "docs/gcode.md", ("gcode", "tests/fixtures/precision/crossing_v.yaml", "-o",
                                              "toolpaths/crossing_v.ngc", "--no-progress", "--json")),
    # grooves tighter than the ball running off the stock edges across the passes: the comb of passes
    # hanging off the edges (tests/fixtures/toolpath/; docs/toolpath.md)
        # (the V's program is in inches: its summary gives mm; the groove's JSON gives the passes added)
    Job("gcode-v-groove", "docs/toolpath.md", ("gcode", "tests/fixtures/toolpath/v_groove.yaml", "-o",
                                               "toolpaths/v_groove.ngc", "--no-progress")),
    Job("gcode-groove-2mm", "docs/toolpath.md", ("gcode", "tests/fixtures/toolpath/groove_2mm.yaml", "-o",
                                                 "toolpaths/groove_2mm.ngc", "--no-progress", "--json")),
    # the steep wall meeting the top face the drop cutter once missed (benchmarks/specs/steep.yaml)
    Job("gcode-steep", "README.md", ("gcode", "benchmarks/specs/steep.yaml", "-o", "toolpaths/steep.ngc",
                                     "--no-progress")),
    Job("gcode-router", "docs/machine.md, README.md", ("gcode", "specs/surface.yaml", "--machine", "grbl-router", "-o",
                                             "toolpaths/surface_grbl.ngc", "--no-progress")),
    # README.md's roughing table, as JSON (each operation's seconds): the roughing job and the single-ball
    # stepdown job, each alone (length/feed) and written for and timed on two shipped machines
        *(Job(f"gcode-{name}{suffix}", "README.md" + (", docs/toolpath.md" if (name, suffix) == ("roughing", "") else ""),
          ("gcode", spec, *machine, "-o", f"toolpaths/{name}{suffix}.ngc", "--no-progress", "--json"))
      for name, spec in (("roughing", "specs/surface_roughing.yaml"),
                         ("ball-stepdown", "tests/fixtures/roughing/ball_stepdown.yaml"))
      for suffix, machine in (("", ()), ("-router", ("--machine", "grbl-router")),
                              ("-mill", ("--machine", "linuxcnc-mill")))),
    # the program gcode-router writes, timed on two profiles (cheap: under 1 s each)
    Job("time-router", "docs/machine.md", ("time", "toolpaths/surface_grbl.ngc", "--machine", "grbl-router")),
    Job("time-defaults", "docs/machine.md, README.md", ("time", "toolpaths/surface_grbl.ngc", "--machine", "grbl")),
    # and on the two other profiles of benchmarks/time_reference.py, as grbl $$ dumps (not shipped)
    Job("time-fast", "docs/machine.md", ("time", "toolpaths/surface_grbl.ngc", "--machine",
                                         "tests/fixtures/machine/router.grbl.txt")),
    Job("time-unequal", "docs/machine.md", ("time", "toolpaths/surface_grbl.ngc", "--machine",
                                            "tests/fixtures/machine/unequal.grbl.txt")),
    # the same three as JSON: the feed cap's cost to 0.1 s (the summary gives whole seconds)
    *(Job(f"{name}-json", "docs/machine.md", ("time", "toolpaths/surface_grbl.ngc", "--machine", profile, "--json"))
      for name, profile in (("time-defaults", "grbl"), ("time-router", "grbl-router"),
                            ("time-fast", "tests/fixtures/machine/router.grbl.txt"),
                            ("time-unequal", "tests/fixtures/machine/unequal.grbl.txt"))),
        # the bowl's program (gcode-bowl writes it, in inches, grbl dialect) timed on grbl's defaults and the router
    *(Job(f"time-bowl-{name}-json", "docs/machine.md", ("time", "toolpaths/bowl.ngc", "--machine", profile, "--json"))
      for name, profile in (("defaults", "grbl"), ("router", "grbl-router"))),
    Job("ramp", "docs/lab.md, docs/ball.md", ("ramp", "specs/surface.yaml")),
    # where the markers go on the paper's block, and a marker given over the milled surface refused
    Job("markers", "docs/track.md", ("markers", "specs/surface.yaml", "-o", "toolpaths/surface.markers.pdf")),
    Job("error-marker", "docs/track.md", ("markers", "tests/fixtures/errors/marker_over_cut.yaml", "-o",
                                          "toolpaths/marker_over_cut.markers.pdf")),
    Job("precision", "docs/numerics.md, docs/simulator.md", ("precision", "specs/surface.yaml", "--plot", "docs/precision.png",
                                          "--no-progress")),
    Job("phi4", "docs/phi4.md, README.md", ("phi4", "--v-in", "0.2236", "--plot", "docs/phi4_three_bounce.png")),
    # docs/phi4.md's table of the paper's Fig. 3 speeds: each at the default step (its error by step
    # halving) and at dt = 1/80 (the converged column), and the sweep over the one-bounce threshold
    # (about a minute of CPU)
    *(Job(f"phi4-{v}", "docs/phi4.md", ("phi4", "--v-in", v)) for v in ("0.184", "0.1988", "0.2269", "0.27")),
    *(Job(f"phi4-{v}-dt80", "docs/phi4.md" + (", README.md, docs/numerics.md" if v == "0.2236" else ""),
          ("phi4", "--v-in", v, "--dt", "0.0125"))
      for v in ("0.1988", "0.2236", "0.2269", "0.27")),
    Job("phi4-sweep", "docs/phi4.md", ("phi4", "--v-in", "0.25", "0.27", "21")),
    Job("compare", "docs/phi4.md, docs/paper.md", ("compare", "specs/surface.yaml", "--plot", "docs/compare.png",
                                    "--no-progress")),
    Job("explore", "docs/explore.md", ("explore", "specs/surface.yaml", "--vary", "surface.params.eps=0.2:0.25:2",
                                       "--v-in", "20", "90", "200", "--no-progress")),
    Job("robustness", "docs/explore.md", ("robustness", "specs/surface.yaml", "--v-in", "43", "52", "46",
                                          "--sigma-y", "0.1", "--sigma-vy", "0.5", "--samples", "50",
                                          "--no-progress")),
    Job("design", "docs/design.md, README.md",
        ("design", "specs/surface_eps015.yaml", "--vary", "surface.params.eps=0.1:0.4",
         "--vary", "surface.params.c=0.04:0.12", "--vary", "surface.params.eta=2:5",
         "--seed", "1", "--plot", "docs/design.png", "-o",
         "toolpaths/surface_eps015.design.yaml", "--no-progress")),
    # docs/errors.md's examples: each a bad input (a fixture, a shipped spec with a bad option) given to
    # the command, which refuses it with one line on stderr and exit 2 (the output records both)
    *(Job(f"error-{name}", "docs/errors.md" + (", docs/toolpath.md" if name == "edge-too-deep" else ""), argv)
      for name, argv in (
        ("diameter", ("check", "tests/fixtures/bad/negative_tool_diameter.yaml")),
        ("footprint", ("check", "tests/fixtures/bad/reversed_footprint.yaml")),
        ("exponent", ("check", "tests/fixtures/errors/big_exponent.yaml")),
        ("not-finite", ("check", "tests/fixtures/errors/not_finite.yaml")),
        ("too-deep", ("gcode", "tests/fixtures/errors/too_deep.yaml", "-o", "toolpaths/too_deep.ngc",
                      "--no-progress")),
        ("edge-too-deep", ("gcode", "tests/fixtures/errors/edge_too_deep.yaml", "-o",
                           "toolpaths/edge_too_deep.ngc", "--no-progress")),
        ("scallop", ("gcode", "tests/fixtures/errors/scallop_1e-4.yaml", "-o", "toolpaths/scallop_1e-4.ngc",
                     "--no-progress")),
        ("tolerance", ("stl", "specs/surface.yaml", "--tolerance", "1e-9", "-o", "toolpaths/tolerance.stl")),
        ("alias", ("check", "tests/fixtures/bad/yaml_alias.yaml")),
        ("base60", ("check", "tests/fixtures/errors/base60_thickness.yaml")),
        ("spindle", ("check", "tests/fixtures/errors/spindle_0p4.yaml")),
        ("ramp-height", ("check", "tests/fixtures/bad/negative_ramp_height.yaml")),
        ("not-text", ("check", "tests/fixtures/bad/binary_junk.yaml")),
        ("launches", ("sweep", "specs/surface.yaml", "--v-in", "40", "50", "1000000000")),
        ("nan", ("sweep", "specs/surface.yaml", "--v-in", "40", "50", "nan")),
        ("scheduler", ("robustness", "specs/surface.yaml", "--v-in", "43", "52", "2", "--sigma-y", "0.1",
                       "--sigma-vy", "0.5", "--samples", "2", "--scheduler", "tcp://127.0.0.1:1", "--no-progress")),
        ("arguments", ("sweep", "specs/surface.yaml", "--v-in", "40")),
    )),
)


def _fabkit() -> list[str]:
    """The fabkit of this checkout, run as a module so the docs quote this code."""
    return [sys.executable, "-m", "fabkit"]


def command(job: Job) -> list[str]:
    """The argv that runs ``job`` from the repository root."""
    return ([sys.executable, job.script] if job.script else _fabkit()) + list(job.argv)


def body(job: Job, stdout: str) -> str:
    """What the output file holds before its last line (the exit, wall time and load)."""
    return f"$ {job.shown}\n{stdout}"


JOBS_BY_NAME = {j.name: j for j in JOBS}


def run(job: Job) -> int:
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.run(command(job), cwd=ROOT, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    load1 = os.getloadavg()[0]
    OUT.mkdir(parents=True, exist_ok=True)
    text = (body(job, proc.stdout)
            + (f"[stderr]\n{proc.stderr}" if proc.returncode else "")
            + f"[exit {proc.returncode}; {seconds:.1f} s wall; load average {load0:.2f} before, {load1:.2f} after; "
              f"quoted by {job.doc}]\n")
    tmp = OUT / f".{job.name}.txt.tmp"
    tmp.write_text(text)
    tmp.replace(OUT / f"{job.name}.txt")
    print(f"{job.name}: exit {proc.returncode}, {seconds:.1f} s (load {load0:.2f})", flush=True)
    return proc.returncode


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("jobs", nargs="*", help="job names (default: all)")
    ap.add_argument("--list", action="store_true", help="list the jobs and exit")
    args = ap.parse_args(argv)
    if args.list:
        for j in JOBS:
            print(f"{j.name:16s} {j.doc:22s} {j.shown}")
        return 0
    names = {j.name for j in JOBS}
    unknown = [n for n in args.jobs if n not in names]
    if unknown:
        print(f"unknown job(s): {', '.join(unknown)} (see --list)", file=sys.stderr)
        return 2
    worst = 0
    for j in JOBS:
        if not args.jobs or j.name in args.jobs:
            rc = run(j)
            worst = max(worst, 0 if rc in (0, 1) else rc)   # exit 1 is a verdict (an unsafe check), not a failure
    return worst


if __name__ == "__main__":
    sys.exit(main())
