"""Command line: ``fabkit <command> SPEC [options]``.

A thin ``main(argv) -> int``. The parser is defined here; each command's work
lives in ``fabkit.commands.<name>.run(args) -> int``, imported only when that
command runs (so ``fabkit --help`` imports nothing heavy). Exceptions become
exit codes here and nowhere else:

    0  ok
    1  a check failed (design unsafe, verified cut out of tolerance)
    2  bad input (file, YAML, key, value, expression, depth over a limit, size guard), or an
       output that cannot be written (full disk, read-only folder: an I/O error line)
    3  internal error (a bug: please report it; FABKIT_DEBUG=1 shows the traceback)
    4  interrupted (Ctrl-C) after outputs were written: each one named is complete
  130  interrupted (Ctrl-C) before any output was written; existing outputs are left intact
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys

from . import __version__
from .errors import (EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_INTERRUPTED_WRITTEN, RUN, FabkitError, interrupted_line,
                     one_line, pause_at)


class _Parser(argparse.ArgumentParser):
    """argparse that raises instead of exiting, so main() owns the exit code."""

    def error(self, message):
        raise _UsageError(f"{self.prog}: {message}")


class _UsageError(Exception):
    pass


EXIT_CODES = """exit codes:
    0  ok
    1  a check failed: design unsafe, verified cut out of tolerance (outputs still written for inspection)
    2  bad input: file, YAML, key, value, option or output path, or an output that cannot
       be written (full disk): one line naming it; nothing written
    3  internal error: a bug, please report it (FABKIT_DEBUG=1 shows the traceback)
    4  interrupted (Ctrl-C) after the outputs were written: the outputs named are complete
  130  interrupted (Ctrl-C) before any output was written: existing outputs left intact

units: speeds are in the spec's design units per second (units: mm | cm | in), heights and
lengths of the surface, ball, ramp and simulation in design units, machining lengths in mm.
`fabkit COMMAND --help` describes each command's options."""

PLOT = ("write the figure to FILE; the format follows the extension (.png, .pdf, .svg, .jpg, .tif, .webp, "
        ".eps, .ps; none: png)")


def _float_list(n):
    return {"nargs": n, "type": float}


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="fabkit", description="From a surface formula to a milled block: STL, verified "
                "ball-end G-code, ramp calibration and a rolling-ball simulator.",
                epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"fabkit {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)

    def cmd(name, help_):
        c = sub.add_parser(name, help=help_, description=help_)
        c.add_argument("spec", metavar="SPEC", help="the YAML spec, e.g. specs/surface.yaml")
        return c

    c = cmd("stl", "build the milled block as a watertight solid and export it (binary STL by default)")
    c.add_argument("-o", "--output", metavar="PATH", help="output file (default toolpaths/<name>.stl; "
                   "other formats by extension)")
    c.add_argument("--tolerance", type=float, metavar="MM", help="chordal tolerance in mm (default 0.01)")
    c.add_argument("--json", action="store_true", help="print the summary as JSON")

    c = cmd("gcode", "write the ball-end raster program, its setup sheet, and verify the cut")
    c.add_argument("-o", "--output", metavar="PATH", help="output program (default toolpaths/<name>.ngc)")
    c.add_argument("--no-verify", action="store_true", help="skip the built-in cut verification")
    c.add_argument("--json", action="store_true", help="print the summary as JSON")
    c.add_argument("--machine", metavar="FILE", help="machine profile (YAML, grbl $$ dump, LinuxCNC INI, or a "
                   "shipped name: `fabkit machine list`): the program's dialect, the controller's run time and the checks before cutting (default: the spec's machine section)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.add_argument("--max-time", type=float, default=None, metavar="SECONDS", dest="max_time",
                   help="CPU seconds the toolpath job may take, estimated before planning (default: the spec's "
                   "machining.max_time, else 60); a longer job is refused")

    c = cmd("calibrate", "map ramp release height to entry speed v_in (rolling, energy)")
    c.add_argument("--height", type=float, nargs="+", metavar="H", help="heights to convert (design units)")
    c.add_argument("--v-in", type=float, nargs="+", metavar="V", dest="v_in",
                   help="entry speeds to convert back to heights (design units/s)")
    c.add_argument("--all", action="store_true", help="print every row of the table (default: a few rows and "
                   "the range; --json always has every row)")
    c.add_argument("--json", action="store_true", help="print JSON")

    c = cmd("simulate", "simulate one launch")
    c.add_argument("--v-in", type=float, required=True, metavar="V", dest="v_in",
                   help="entry speed of the ball, design units/s (the spec's units per second)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="x(t), y(t) with the bounces marked: " + PLOT)

    c = cmd("sweep", "v_out against v_in, v_critical, two-bounce windows (the paper's Fig. 1)")
    c.add_argument("--v-in", metavar=("LO", "HI", "N"), dest="v_in", **_float_list(3),
                   help="N entry speeds from LO to HI, design units/s (default: the ramp's heights calibrated)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="v_out against v_in by outcome, v_critical marked: " + PLOT)
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("check", "pre-fabrication check: the ball stays on the milled surface for every ramp height")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("precision", "work-precision data: error against run time for simulator, toolpath and mesh")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="simulator error against wall time, log-log: " + PLOT)
    c.add_argument("--quick", action="store_true", help="fewer tolerances and launches")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("explore", "a grid of designs over spec keys: v_critical, windows, safety per design")
    c.add_argument("--vary", action="append", default=[], metavar="KEY=LO:HI:N",
                   help="a spec key and its grid, e.g. surface.params.eps=0.1:0.4:4 (repeatable)")
    c.add_argument("--v-in", metavar=("LO", "HI", "N"), dest="v_in", **_float_list(3),
                   help="N entry speeds from LO to HI per design, design units/s (default: the ramp's "
                   "heights calibrated)")
    c.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address, e.g. tcp://127.0.0.1:8786 "
                   "(default: run in this process)")
    c.add_argument("--out", metavar="FILE", help="write one row per launch (design, keys, v_in, outcome, "
                   "bounces, v_out) to FILE: .csv, or .parquet with pyarrow")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="v_critical and two-bounce windows against the first "
                   "varied key: " + PLOT)
    c.add_argument("--chunk", type=int, default=None, metavar="N",
                   help="launches per Dask task (default: each batch split over the cluster's "
                   "threads; results do not depend on it)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("robustness", "Monte Carlo over the launch's transverse offset and velocity")
    c.add_argument("--v-in", metavar=("LO", "HI", "N"), dest="v_in", required=True, **_float_list(3),
                   help="N entry speeds from LO to HI, design units/s")
    c.add_argument("--sigma-y", type=float, required=True, metavar="S", dest="sigma_y",
                   help="standard deviation of the launch's transverse offset y0, design units (0: none)")
    c.add_argument("--sigma-vy", type=float, required=True, metavar="S", dest="sigma_vy",
                   help="standard deviation of the launch's transverse velocity vy0, design units/s (0: none)")
    c.add_argument("--samples", type=int, required=True, metavar="M",
                   help="random launches per entry speed (a count; the nominal launch is added)")
    c.add_argument("--seed", type=int, default=0, help="random seed (default 0: results are reproducible)")
    c.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address, e.g. tcp://127.0.0.1:8786 "
                   "(default: run in this process)")
    c.add_argument("--out", metavar="FILE", help="write one row per launch (v_in, sample, y0, vy0, outcome, bounces, "
                   "v_out) to FILE: .csv, or .parquet with pyarrow")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="probability of each outcome against v_in: " + PLOT)
    c.add_argument("--chunk", type=int, default=None, metavar="N",
                   help="launches per Dask task (default: each batch split over the cluster's "
                   "threads; results do not depend on it)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    # ---- the lab: tracked launches, the ramp, the design report ----
    c = cmd("analyze", "tracked launches and releases: bounces, speeds, the damping fitted with the model")
    c.add_argument("tracks", nargs="+", metavar="TRACK",
                   help="Tracker text export, CSV t,x,y or frame,x,y (with --fps), or trackpy CSV")
    c.add_argument("--fps", type=float, metavar="F",
                   help="frames per second, 1/s (for frame columns: t = frame / F)")
    c.add_argument("--scale", type=float, metavar="S", help="design units per video unit, e.g. cm per pixel "
                   "(default 1: the track is already in design units)")
    c.add_argument("--origin", type=float, nargs=2, metavar=("X", "Y"),
                   help="the design origin in video coordinates, video units (default 0 0)")
    c.add_argument("--rotate", type=float, metavar="DEG",
                   help="turn the video frame counterclockwise by DEG degrees (default 0)")
    c.add_argument("--flip-y", action="store_true", dest="flip_y", help="video y grows downward")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="track and model overlaid, x(t) and y(t): " + PLOT)
    c.add_argument("-o", "--output", metavar="PATH", help="write the spec with the losses of the law the tracks "
                   "support (simulation.damping, ball.rolling_resistance) to PATH (YAML)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("markers", "the ArUco markers for `fabkit track`, at true size, with where each goes on the block")
    c.add_argument("-o", "--output", metavar="PATH", help="the page to print (default toolpaths/<name>.markers.pdf; "
                   ".pdf, .svg or .png at 600 dpi)")
    c.add_argument("--json", action="store_true", help="print JSON")

    c = cmd("track", "videos of the block -> the ball centre's calibrated trajectory per video (for analyze)")
    c.add_argument("videos", nargs="+", metavar="VIDEO", help="mp4, mov, avi, mkv, ... (PyAV); times from each "
                   "frame's presentation timestamp")
    c.add_argument("-o", "--output", metavar="OUT", help="the track file for one video (t,x,y,sigma_x,sigma_y: "
                   "s and design units)")
    c.add_argument("--out-dir", metavar="DIR", dest="out_dir",
                   help="folder for the tracks, <video name>.track.csv each (default toolpaths)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="the first video's frame with the track and the markers "
                   "overlaid: " + PLOT)
    c.add_argument("--review", metavar="PNG", help="a contact sheet of the first video: crops around the ball "
                   "for a spread of frames, the fitted silhouette, the rejected shadow and the gaps with their reason")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("ramp", "the launch ramp as a watertight solid, with release marks at calibrated heights")
    c.add_argument("-o", "--output", metavar="PATH", help="output file (default toolpaths/<name>.ramp.stl; "
                   "other mesh formats by extension)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("report", "the whole design on one self-contained HTML page (verdict, surface, toolpath, sweep, ...)")
    c.add_argument("-o", "--output", metavar="PATH", help="output page (default toolpaths/<name>.report.html)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.add_argument("--machine", metavar="FILE", help="machine profile: the setup sheet shows the controller's run "
                   "time and the checks (default: the spec's machine section)")
    c.add_argument("--max-time", type=float, default=None, metavar="SECONDS", dest="max_time",
                   help="CPU seconds the toolpath job may take, estimated before planning (default: the spec's "
                   "machining.max_time, else 60); a longer job is refused")

    h = "machine profiles: `import FILE` reads a grbl $$ dump or a LinuxCNC INI into a profile (YAML)"
    c = sub.add_parser("machine", help=h, description=h)
    c.add_argument("action", choices=["import", "list"], help="import: settings file -> profile; list: the "
                   "shipped profiles (by name: --machine grbl)")
    c.add_argument("file", metavar="FILE", nargs="?", help="grbl $$ dump (text) or LinuxCNC .ini")
    c.add_argument("-o", "--output", metavar="OUT.yaml", help="write the profile here (default: print it)")
    c.add_argument("--json", action="store_true", help="print JSON")

    h = "the controller's run time of any grbl or LinuxCNC program (its planner simulated)"
    c = sub.add_parser("time", help=h, description=h)
    c.add_argument("program", metavar="PROGRAM", help="a G-code program (.nc, .ngc, .gcode, ...)")
    c.add_argument("--machine", metavar="PROFILE", help="machine profile: a file (YAML, grbl $$ dump, LinuxCNC "
                   "INI) or a shipped profile's name (`fabkit machine list`; default: grbl)")
    c.add_argument("--json", action="store_true", help="print JSON")

    # the solitary-wave side: phi^4 collisions and the seed paper's Fig. 1
    h = "kink-antikink collisions of phi^4 (phi_tt - phi_xx - phi + phi^3 = 0), one speed or a sweep"
    c = sub.add_parser("phi4", help=h, description=h)
    c.add_argument("--v-in", type=float, nargs="+", required=True, metavar="V", dest="v_in",
                   help="one speed V, or LO HI N for a sweep; each kink's speed in units of c, the "
                   "speed of light (dimensionless, not design units/s)")
    c.add_argument("--t-max", type=float, dest="t_max", metavar="T",
                   help="end of each run, in the PDE's time unit (default 800); not escaped by then: captured")
    c.add_argument("--dx", type=float, metavar="DX", help="grid spacing, in kink length units (default 0.25)")
    c.add_argument("--dt", type=float, metavar="DT", help="ETDRK4 time step, in the PDE's time unit (default 0.05)")
    c.add_argument("--x0", type=float, metavar="X0",
                   help="initial half-separation of the kinks, in kink length units (as --dx), >= 10 (default 10)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="one speed: X(t) and A(t) (the paper's Fig. 3); a sweep: "
                   "v_out against v_in. " + PLOT)
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("compare", "the seed paper's Fig. 1 for this apparatus: PDE, CC ODE, map and the apparatus")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="the four panels of v_out against v_in: " + PLOT)
    c.add_argument("--pde-samples", type=int, default=None, dest="pde_samples", metavar="N",
                   help="phi^4 collisions in the PDE panel (default 400)")
    c.add_argument("--ode-samples", type=int, default=None, dest="ode_samples", metavar="N",
                   help="CC ODE launches (default 300)")
    c.add_argument("--no-progress", action="store_true", help="no progress bar")

    c = cmd("design", "search spec keys for the design with the most observable two-bounce windows")
    c.add_argument("--vary", action="append", default=[], metavar="KEY=LO:HI",
                   help="a spec key and its bounds, e.g. surface.params.eps=0.1:0.4 (repeatable)")
    c.add_argument("--budget", type=int, default=48, metavar="N",
                   help="designs screened by the search (default 48)")
    c.add_argument("--seed", type=int, default=0, metavar="S",
                   help="random seed of the search and the scatter draws (default 0; same seed, same design)")
    c.add_argument("--min-width", type=float, default=None, metavar="W", dest="min_width",
                   help="narrowest observable window, release height in design units (default 1 mm)")
    c.add_argument("--sigma-y", type=float, default=0.0, metavar="S", dest="sigma_y",
                   help="standard deviation of the launch's transverse offset y0, design units (default 0: none)")
    c.add_argument("--sigma-vy", type=float, default=0.0, metavar="S", dest="sigma_vy",
                   help="standard deviation of the launch's transverse velocity vy0, design units/s (default 0: none)")
    c.add_argument("--samples", type=int, default=None, metavar="M",
                   help="random launches per entry speed tried, the centre of each window (a count, default 64; "
                   "without scatter the nominal launch alone)")
    c.add_argument("--top", type=int, default=3, metavar="K", help="best designs verified by the full check (default 3)")
    c.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address, e.g. tcp://127.0.0.1:8786 "
                   "(default: run in this process)")
    c.add_argument("-o", "--output", metavar="OUT.yaml", help="the winner's spec (default toolpaths/<name>.design.yaml)")
    c.add_argument("--json", action="store_true", help="print JSON")
    c.add_argument("--plot", metavar="FILE", help="the objective over the search and the winner's v_out against "
                   "release height: " + PLOT)
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def _non_finite_option(parser: argparse.ArgumentParser, args) -> str | None:
    """The error line for a numeric option given nan or inf (argparse's float()
    accepts both), naming the option; None when every number is finite."""
    import math

    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for action in sub.choices[args.command]._actions:
        value = getattr(args, action.dest, None)
        values = value if isinstance(value, list) else [value]
        if any(isinstance(v, float) and not math.isfinite(v) for v in values):
            shown = " ".join(f"{v:g}" for v in values)
            return f"{action.option_strings[-1] if action.option_strings else action.dest}: numbers must be " \
                   f"finite, got {shown}"
    return None


def _from_interrupt(exc: BaseException) -> bool:
    """True when ``exc`` was raised while handling a KeyboardInterrupt (its cause or context)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def main(argv: list[str] | None = None) -> int:
    """Run fabkit; returns the exit code (never raises, never exits)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    RUN.reset()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except _UsageError as exc:
        print(one_line(exc, 4000), file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help, --version
        return int(exc.code or 0)
    if not args.command:
        parser.print_help()
        return 2
    bad = _non_finite_option(parser, args)
    if bad:
        print(f"fabkit {args.command}: {bad}", file=sys.stderr)
        return 2
    RUN.command, RUN.phase = args.command, "run"
    try:
        from . import process_memory

        process_memory.tune()           # freed memory kept for reuse (fabkit/process_memory.py)
        module = importlib.import_module(f"fabkit.commands.{args.command}")
        return int(module.run(args))
    except FabkitError as exc:
        where = "" if getattr(exc, "file", None) else f"fabkit {args.command}: "
        print(f"{where}{one_line(exc, 4000)}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        line, code = interrupted_line()
        print(line, file=sys.stderr)
        return code
    except MemoryError:
        print(f"fabkit {args.command}: out of memory: the request is too large for this machine", file=sys.stderr)
        return 2
    except BrokenPipeError:
        return 0
    except OSError as exc:  # a file fabkit reads or writes outside io.py: an I/O error, not a bug
        if os.environ.get("FABKIT_DEBUG"):
            raise
        where = f"{one_line(exc.filename, 300)}: " if getattr(exc, "filename", None) else ""
        print(f"fabkit {args.command}: {where}I/O error: {one_line(exc.strerror or exc, 300)}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: one line, traceback only on request
        # numpy turns a Ctrl-C during its import into an ImportError; one raised inside a ctypes
        # callback (numba's compiler) is swallowed there and the compiler then fails: either way
        # this error is the interrupt's doing
        if _from_interrupt(exc) or RUN.interrupted:
            line, code = interrupted_line()
            print(line, file=sys.stderr)
            return code
        if os.environ.get("FABKIT_DEBUG"):
            raise
        print(f"fabkit {args.command}: internal error ({type(exc).__name__}: {one_line(exc, 300)}); "
              "please report it (FABKIT_DEBUG=1 shows the traceback)", file=sys.stderr)
        return EXIT_INTERNAL


def _on_sigint(signum, frame):
    """Ctrl-C, from the entry point's first instruction to the process's end (see :func:`entry`)."""
    RUN.interrupted = True
    if RUN.phase == "run" and not RUN.written:
        raise KeyboardInterrupt          # main() discards the staged outputs and says so
    if RUN.phase == "exit":
        _exit(RUN.code)                  # the command is done: its code already says what was written
    line, code = interrupted_line()      # starting: nothing written; or after writing: which outputs
    _exit(code, line)


def _exit(code: int, line: str | None = None) -> None:
    """End the process now with ``code``: the streams flushed (a flush the signal
    interrupted is skipped), ``line`` written straight to stderr."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    if line:
        with contextlib.suppress(OSError):
            os.write(2, (line + "\n").encode("utf-8", "replace"))
    os._exit(code)


def _quiet_interrupts(unraisable) -> None:
    """sys.unraisablehook: a KeyboardInterrupt that Python cannot raise (it came inside a
    ctypes callback or a finalizer) is not printed as a traceback; the run reports the
    interrupt in its one line. Anything else goes to Python's own hook."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        RUN.interrupted = True
        return
    sys.__unraisablehook__(unraisable)


def entry() -> int:
    """The console entry point: :func:`main`, then the process exit.

    Its first instruction installs the Ctrl-C handler (before any heavy import), so the
    exit code says what was written whenever SIGINT comes: while starting, 130 and
    "nothing written"; during the command's work, KeyboardInterrupt, which main() turns
    into 130 with the staged outputs discarded; once outputs are renamed into place
    (:mod:`fabkit.io` records them), 4 and the outputs named; after the command returned,
    its own code; in the interpreter's last teardown (after the exit functions), ignored.
    (Before this function runs, Python's own start-up and the import of this module take
    a few tens of milliseconds in which Python's default applies.) A SIGINT ignored by
    the parent (a background job) stays ignored.

    After Ctrl-C the process ends with ``os._exit`` once the streams are flushed. A
    normal exit is not used there: CPython (3.11) marks a KeyboardInterrupt raised
    inside code run by ``exec`` of a string (scipy does so while it is imported) as
    unhandled even when it is caught, and then kills the process with SIGINT at exit,
    so the shell would see -2 instead of 130. Outputs are already discarded (or
    complete) by then; nothing else needs the shutdown.
    """
    import signal

    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, _on_sigint)
        # registered before the command's imports, so run after their exit functions: from
        # then on the interpreter's own teardown would put back SIGINT's default (death by
        # signal, no message), so Ctrl-C is ignored for those last milliseconds
        import atexit

        atexit.register(signal.signal, signal.SIGINT, signal.SIG_IGN)
    sys.unraisablehook = _quiet_interrupts
    RUN.reset()
    pause_at("start")
    code = main()
    RUN.phase, RUN.code = "exit", code
    if code in (EXIT_INTERRUPTED, EXIT_INTERRUPTED_WRITTEN):
        _exit(code)
    pause_at("exit")
    return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(entry())
