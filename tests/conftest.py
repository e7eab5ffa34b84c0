"""Shared test helpers: the paper's spec, spec mutation, and CLI runs through main(argv)."""

from __future__ import annotations

import contextlib
import copy
import io
import math
import os
import signal
from pathlib import Path

import pytest
import yaml

from fabkit.cli import main


def pytest_configure(config):
    """The compiled simulator's cache (generated and compiled engines) for this test
    session: a fresh folder, unless FABKIT_CACHE_DIR is set already. Each formula
    compiles once per session; subprocesses inherit the folder."""
    import os
    import tempfile

    if not os.environ.get("FABKIT_CACHE_DIR"):
        os.environ["FABKIT_CACHE_DIR"] = tempfile.mkdtemp(prefix="fabkit-test-cache-")


def pytest_collection_finish(session):
    """Compile the simulator for the paper's formula once, before any test that runs
    the simulator, so that command-line tests with a time limit only load it."""
    from fabkit.commands._common import prepare_simulator
    from fabkit.spec import load_spec

    needs = ("simulate", "sweep", "check", "explore", "robust", "integrate", "trap", "stream", "extreme",
             "determinism", "precision", "hardening_cli", "interrupt", "reference", "calibrate")
    if any(any(n in item.module.__name__ for n in needs) for item in session.items
           if getattr(item, "module", None) is not None):
        prepare_simulator(load_spec(PAPER), quiet=True)

ROOT = Path(__file__).resolve().parents[1]
SPECS = ROOT / "specs"
#: the paper's spec on the point model (the shipped specs/surface.yaml runs the finite
#: ball, the default); tests of the ball name SPECS / "surface.yaml"
PAPER = ROOT / "tests" / "fixtures" / "paper_full.yaml"
SHIPPED_PAPER = SPECS / "surface.yaml"


def paper_raw() -> dict:
    return yaml.safe_load(PAPER.read_text())


def write_spec(tmp_path: Path, raw: dict, name: str = "spec.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


def mutated(changes: dict, drop: tuple[str, ...] = ()) -> dict:
    """The paper's spec with dotted keys set (or dropped)."""
    raw = copy.deepcopy(paper_raw())
    for key, value in changes.items():
        node = raw
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    for key in drop:
        node = raw
        parts = key.split(".")
        for p in parts[:-1]:
            node = node[p]
        del node[parts[-1]]
    return raw


@pytest.fixture
def cli(capsys, monkeypatch, tmp_path):
    """Run ``fabkit ARGS`` in-process from a scratch folder; returns (code, stdout, stderr)."""
    monkeypatch.chdir(tmp_path)

    def run(*argv):
        code = main([str(a) for a in argv])
        out, err = capsys.readouterr()
        return code, out, err

    return run


class Hang(BaseException):
    """Raised by :func:`bounded` (a BaseException: code under test cannot swallow it)."""


@contextlib.contextmanager
def bounded(seconds: int = 60):
    """Fail (instead of hanging the suite) if the block runs longer than ``seconds`` on an
    unloaded machine. This detects hangs, it is not a speed target: on a shared machine the
    bound grows with the load average per core (a run at load 9 on 2 cores gets 4.5x), so a
    cold compile under load is not taken for a hang."""
    scale = max(1.0, os.getloadavg()[0] / (os.cpu_count() or 1))
    limit = int(math.ceil(seconds * scale))

    def on_alarm(signum, frame):
        raise Hang(f"still running after {limit} s ({seconds} s x load factor {scale:.2f}): a hang")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(limit)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def run_cli(argv) -> tuple[int, str, str]:
    """``fabkit ARGV`` in-process (no chdir); returns (code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


#: a cheap variant of the paper's apparatus for design studies (loose tolerances, short runs)
SMALL_STUDY = {"name": "small", "simulation.rtol": 1e-6, "simulation.atol": 1e-8, "simulation.t_max": 30.0,
               "ramp.samples": 8}


def small_study_spec():
    from fabkit.spec import validate

    return validate(mutated(SMALL_STUDY), "small.yaml")


def run_study(command: str, spec_path: Path, args: list, plot: str) -> dict:
    """``fabkit COMMAND SPEC ARGS --json --out rows.csv --plot PLOT`` beside the spec; the
    parsed JSON with ``folder`` added (it must succeed)."""
    import json

    folder = spec_path.parent
    code, out, err = run_cli([command, spec_path, *args, "--json", "--out", folder / "rows.csv",
                              "--plot", folder / plot])
    assert code == 0, err
    res = json.loads(out)
    res["folder"] = folder
    return res
