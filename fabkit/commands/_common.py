"""Helpers shared by the command modules (edge code: printing, paths, timing)."""

from __future__ import annotations

import json
import threading
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

DEFAULT_OUTPUT_DIR = Path("toolpaths")


def default_output(spec, suffix: str, given: str | None) -> Path:
    """``given`` or ``toolpaths/<name><suffix>``."""
    return Path(given) if given else DEFAULT_OUTPUT_DIR / f"{spec.name}{suffix}"


#: figure formats by extension (matplotlib's Agg writes each); no extension: png
PLOT_FORMATS = {".png": "png", ".pdf": "pdf", ".svg": "svg", ".jpg": "jpg", ".jpeg": "jpg", ".tif": "tiff",
                ".tiff": "tiff", ".webp": "webp", ".eps": "eps", ".ps": "ps"}


def plot_format(path, key: str = "--plot") -> str:
    """The figure format ``path``'s extension names; SpecError (exit 2) for one fabkit cannot write."""
    from ..errors import SpecError

    suffix = Path(path).suffix.lower()
    if not suffix:
        return "png"
    if suffix not in PLOT_FORMATS:
        raise SpecError(f"cannot write a figure as '{suffix}' (use one of: {', '.join(PLOT_FORMATS)})", key=key)
    return PLOT_FORMATS[suffix]


def check_paths(args, outputs: dict) -> None:
    """Refuse bad outputs before any work: :func:`fabkit.io.check_outputs` with the
    spec as the input, and the figure format of ``--plot``."""
    from ..io import check_outputs

    machine = getattr(args, "machine", None)          # --machine FILE is an input too
    check_outputs(outputs, inputs=[getattr(args, "spec", None)] + ([machine] if machine and os.path.exists(machine)
                                                                   else []))
    if outputs.get("--plot") is not None:
        plot_format(outputs["--plot"])


class Timer:
    def __init__(self) -> None:
        self.t0 = time.perf_counter()

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.t0


def _clean(obj):
    """JSON-safe: numpy scalars/arrays to Python, non-finite floats to None."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [_clean(v) for v in obj.tolist()]
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        return f if math.isfinite(f) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def to_json(obj, indent: int | None = 2) -> str:
    return json.dumps(_clean(obj), indent=indent, sort_keys=False)


def emit(summary_lines: list[str] | str, payload: dict | None, as_json: bool) -> None:
    """Print either the JSON payload or the human summary to stdout."""
    if as_json:
        sys.stdout.write(to_json(payload) + "\n")
    else:
        if isinstance(summary_lines, str):
            summary_lines = [summary_lines]
        for line in summary_lines:
            sys.stdout.write(line + "\n")
    sys.stdout.flush()


def warn(message: str) -> None:
    sys.stderr.write(f"warning: {message}\n")


#: seconds a command runs before its stage bar is shown
BAR_DELAY_S = 2.0


def stage_bar(total: int, disabled: bool, desc: str, delay: float | None = None):
    """A tqdm bar of named stages on stderr, for commands whose work is a few long steps
    (gcode, precision); returns (step(name), close). Each ``step`` call completes the
    previous stage and names the one that starts (``step(name, advance=False)`` renames the
    running one). Shown on a terminal only, once the command has run ``delay`` s (default
    :data:`BAR_DELAY_S`), then redrawn every second (the clock keeps moving through a long
    stage)."""
    if disabled or not sys.stderr.isatty():
        return (lambda _name, advance=True: None), (lambda: None)
    delay = BAR_DELAY_S if delay is None else delay
    from tqdm import tqdm

    bar = tqdm(total=max(1, int(total)), desc=desc, unit="stage", file=sys.stderr, delay=delay, leave=False,
               bar_format="{desc}: {n_fmt}/{total_fmt} stages |{bar}| {elapsed}{postfix}")
    t0 = time.monotonic()
    started = [False]
    done = threading.Event()

    def shown() -> bool:
        return time.monotonic() - t0 >= delay

    def step(name: str, advance: bool = True) -> None:
        """Start stage ``name`` (``advance`` False: rename the running stage, e.g. with a count)."""
        if advance and started[0] and bar.n < bar.total:
            bar.update(1)            # tqdm itself draws nothing before its delay
        started[0] = True
        bar.set_postfix_str(str(name), refresh=shown())

    def tick() -> None:
        if done.wait(delay):
            return
        while not done.is_set():
            bar.refresh()
            done.wait(1.0)

    ticker = threading.Thread(target=tick, daemon=True, name="fabkit-stage-bar")
    ticker.start()

    def close() -> None:
        done.set()
        ticker.join(timeout=2.0)
        if shown():
            # the bar was drawn by refresh(), which tqdm does not count as printed: without
            # this, close() leaves it on the line and the summary is written after it
            bar.last_print_t = max(bar.last_print_t, bar.start_t + bar.delay)
        bar.close()

    return step, close


def quiet(args) -> bool:
    """No progress bar: ``--no-progress`` or ``--json`` (stderr off a terminal is silent anyway)."""
    return bool(getattr(args, "no_progress", False) or getattr(args, "json", False))


def launch_stages(stages: int, disabled: bool, desc: str):
    """A :func:`stage_bar` for commands that launch a batch and then refine it (sweep,
    check): returns (stage(name), launches(name, total), close). ``launches`` starts the
    stage ``name`` and returns the launch callback ``cb(done, total=None)`` that keeps
    the count of its launches in the stage's name (``name: done/total``), so the bar
    never stands still at a full count while the refinement runs."""
    step, close = stage_bar(stages, disabled, desc)

    def launches(name: str, total: int):
        step(name)
        lock = threading.Lock()

        def cb(done, _total=None):
            with lock:
                step(f"{name}: {int(done)}/{int(total)}", advance=False)

        return cb

    return step, launches, close


def progress_bar(total: int, disabled: bool, desc: str, unit: str = "launch"):
    """A tqdm bar of launches on stderr, shown only on a terminal and after 2 s; returns
    (callback(done, total=None), close), or (None, no-op) when disabled. The total grows
    when refinement launches more than estimated; callbacks may come from threads."""
    if disabled or not sys.stderr.isatty():
        return None, lambda: None
    from tqdm import tqdm

    bar = tqdm(total=max(1, int(total)), desc=desc, unit=unit, file=sys.stderr, delay=BAR_DELAY_S, leave=False)
    lock = threading.Lock()

    def cb(done, _total=None):
        with lock:
            done = int(done)
            if done >= bar.total:
                # more launches than estimated: the refinement runs. The bar must not sit at
                # 100 % while work goes on, so the total moves ahead of the count and the bar
                # names the stage (the true total is unknown until the refinement ends)
                bar.total = max(done + 1, int(done * 1.25))
                bar.set_description_str(f"{desc}: refining", refresh=False)
            bar.update(max(0, done - bar.n))

    return cb, bar.close


def prepare_simulator(problem_or_spec, quiet: bool = False, say=None) -> None:
    """Load the compiled simulator for a problem (or a spec's problem) before its
    launches. The first run of a new formula compiles it (fabkit/physics/engine) and
    says so on stderr when it is a terminal: ``compiling the simulator for this
    surface (once, about N s)``; later runs only load it from the cache. ``say``: where
    that line goes instead (a stage bar's running stage)."""
    from ..physics.integrate import is_stiff

    problem = problem_or_spec
    if not hasattr(problem, "fns"):
        from ..physics.models import problem_from_spec

        problem = problem_from_spec(problem_or_spec)
    from ..physics.integrate import ENGINE_MODELS

    if is_stiff(problem, problem.t_max) or problem.model not in ENGINE_MODELS:
        return   # the implicit Radau path: nothing to compile
    from ..physics.engine.batch import engine

    def notify(message: str) -> None:
        if say is not None:
            say(message)
        elif not quiet and sys.stderr.isatty():
            sys.stderr.write(message + "\n")
            sys.stderr.flush()

    engine(problem, notify=notify)
