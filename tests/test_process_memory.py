"""fabkit/process_memory.py: a command's process keeps freed memory for reuse (glibc's
malloc thresholds, no huge-page advice from numpy) and computes the same bytes.

Each run is its own process (the settings hold for the process they are made in)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from conftest import ROOT
from golden import strip_volatile

PROBE = """
import json, sys
from fabkit import process_memory
first = process_memory.tune()
again = process_memory.tune()
print(json.dumps({"first": first, "again": again}))
"""


def _probe(**env):
    e = {k: v for k, v in os.environ.items() if k not in ("FABKIT_SYSTEM_MEMORY", "NUMPY_MADVISE_HUGEPAGE")}
    e.update(PYTHONPATH=str(ROOT), **env)
    out = subprocess.run([sys.executable, "-c", PROBE], env=e, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def _glibc() -> bool:
    import ctypes

    try:
        return sys.platform.startswith("linux") and hasattr(ctypes.CDLL(None), "gnu_get_libc_version")
    except OSError:
        return False


def test_tune_applies_once_and_reports_what_it_did():
    got = _probe()
    assert got["first"]["hugepage_advice_off"] is True
    assert got["first"]["malloc"] is _glibc()
    assert got["again"] == got["first"]


def test_tune_leaves_the_system_settings_when_asked():
    assert _probe(FABKIT_SYSTEM_MEMORY="1")["first"] == {}
    # numpy's own switch, set by the user, stands
    got = _probe(NUMPY_MADVISE_HUGEPAGE="1")
    assert got["first"]["hugepage_advice_off"] is False


def test_cli_applies_the_settings_before_a_command():
    code = ("import sys; from fabkit import cli, process_memory; cli.main(['--version']); "
            "print('SET', bool(process_memory._DONE)); cli.main(['stl', '/nonexistent.yaml']); "
            "print('SET', process_memory._DONE.get('hugepage_advice_off'))")
    e = {k: v for k, v in os.environ.items() if k != "FABKIT_SYSTEM_MEMORY"}
    out = subprocess.run([sys.executable, "-c", code], env=dict(e, PYTHONPATH=str(ROOT)), capture_output=True,
                         text=True, timeout=120)
    # --version exits before any command: nothing set; a command (even one refusing its input) sets them
    said = [ln.split()[1] for ln in out.stdout.splitlines() if ln.startswith("SET ")]
    assert said == ["False", "True"], out.stdout + out.stderr


def test_a_roughing_job_writes_the_same_bytes_either_way(tmp_path):
    """The whole job (rough, rest, finish, the stock pictures and the sheet) with and without
    the settings: every file the same bytes but the sheet's timings (SOURCE_DATE_EPOCH fixes
    its date)."""
    spec = ROOT / "benchmarks" / "specs" / "vee45.yaml"
    runs = {}
    for system in ("0", "1"):
        e = {k: v for k, v in os.environ.items() if k != "FABKIT_SYSTEM_MEMORY"}
        e.update(PYTHONPATH=str(ROOT), SOURCE_DATE_EPOCH="1700000000", FABKIT_SYSTEM_MEMORY=system)
        out = tmp_path / system
        proc = subprocess.run([sys.executable, "-m", "fabkit", "gcode", str(spec), "-o", str(out / "vee45"),
                               "--no-progress"], env=e, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr
        runs[system] = {p.name: p.read_bytes() for p in out.iterdir()}
    assert "vee45.stock-finish.png" in runs["0"] and "vee45.setup.json" in runs["0"]
    assert sorted(runs["0"]) == sorted(runs["1"])
    for name, a in runs["0"].items():
        b = runs["1"][name]
        if name.endswith(".json"):
            a, b = strip_volatile(json.loads(a)), strip_volatile(json.loads(b))
        elif name.endswith(".md"):
            a, b = _no_timing_lines(a), _no_timing_lines(b)
        assert a == b, name


def _no_timing_lines(raw: bytes):
    return [ln for ln in raw.decode().splitlines() if not ln.lstrip("-* ").lower().startswith("timings")]
