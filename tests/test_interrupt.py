"""Interrupted runs (issue 8, item 2): Ctrl-C or a crash while writing leaves any
existing output intact and no temporary file behind.

Three levels: :func:`fabkit.io.atomic_outputs` directly; the CLI in-process with
the writer patched to raise KeyboardInterrupt between staging and renaming
(exit 130); and a real SIGINT sent to ``python -m fabkit stl`` and ``gcode``
while they work.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

import fabkit.io
from fabkit.errors import SpecError
from fabkit.io import atomic_outputs, write_atomic

from conftest import ROOT, paper_raw

OLD = b"previous output: must survive\n"


def tiny_raw() -> dict:
    """The paper's formula on a small footprint with coarse machining: each run is short."""
    raw = paper_raw()
    raw["name"] = "tiny"
    raw["surface"].update(x=[-10, 4], y=[-4, 4])
    raw["machining"].update(scallop=0.5, tolerance=0.1, verify_points=2000)
    raw["ramp"] = {"heights": [0.2, 1.0], "samples": 4}
    raw["simulation"].update(start=-8, t_max=5.0, rtol=1e-6, atol=1e-8)
    return raw


def temporaries(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob(".*.tmp"))


# ----------------------------------------------------------------------------
# atomic_outputs directly
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("exc", [KeyboardInterrupt, RuntimeError, SystemExit])
def test_interrupt_inside_block_keeps_both_old_files(tmp_path, exc):
    a, b = tmp_path / "out" / "a.ngc", tmp_path / "out" / "a.setup.json"
    a.parent.mkdir()
    a.write_bytes(OLD)
    b.write_bytes(OLD + b"2")
    with pytest.raises(exc):
        with atomic_outputs() as out:
            out.write(a, "new program")
            raise exc()
    assert a.read_bytes() == OLD and b.read_bytes() == OLD + b"2"
    assert temporaries(tmp_path) == []


def test_interrupt_during_a_write_leaves_no_temporary(tmp_path, monkeypatch):
    a, b = tmp_path / "a.ngc", tmp_path / "b.ngc"
    a.write_bytes(OLD)

    def interrupted_fsync(fd):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        with atomic_outputs() as out:
            out.write(b, "staged first")
            monkeypatch.setattr(os, "fsync", interrupted_fsync)
            out.write(a, "new")
    assert a.read_bytes() == OLD and not b.exists()
    assert temporaries(tmp_path) == []


def test_refused_second_output_discards_the_first(tmp_path):
    a = tmp_path / "a.ngc"
    a.write_bytes(OLD)
    (tmp_path / "folder.json").mkdir()
    with pytest.raises(SpecError, match="folder"):
        with atomic_outputs() as out:
            out.write(a, "new")
            out.write(tmp_path / "folder.json", "{}")
    assert a.read_bytes() == OLD and temporaries(tmp_path) == []


def test_clean_exit_replaces_all_and_leaves_no_temporary(tmp_path):
    a, b = tmp_path / "a.ngc", tmp_path / "sub" / "b.json"
    a.write_bytes(OLD)
    with atomic_outputs() as out:
        out.write(a, "new program\n")
        out.write(b, b"{}")
    assert a.read_bytes() == b"new program\n" and b.read_bytes() == b"{}"
    write_atomic(a, "again")
    assert a.read_text() == "again" and temporaries(tmp_path) == []


# ----------------------------------------------------------------------------
# through the CLI, in-process: interrupted between staging and renaming
# ----------------------------------------------------------------------------
def _interrupt_after_staging(monkeypatch, after: int):
    """Make the ``after``-th staged write raise KeyboardInterrupt once its data is on disk."""
    original = fabkit.io._Outputs.write
    calls = {"n": 0}

    def write(self, path, data):
        result = original(self, path, data)
        calls["n"] += 1
        if calls["n"] >= after:
            raise KeyboardInterrupt
        return result

    monkeypatch.setattr(fabkit.io._Outputs, "write", write)
    return calls


@pytest.mark.parametrize("command,outputs,extra", [
    ("stl", ["tiny.stl"], ["--tolerance", "0.05"]),
    ("gcode", ["tiny.ngc", "tiny.setup.json"], ["--no-verify"]),
])
def test_cli_interrupted_while_writing(cli, tmp_path, monkeypatch, command, outputs, extra):
    spec = tmp_path / "tiny.yaml"
    spec.write_text(yaml.safe_dump(tiny_raw(), sort_keys=False))
    out_dir = tmp_path / "toolpaths"
    out_dir.mkdir()
    for name in outputs:
        (out_dir / name).write_bytes(OLD + name.encode())
    calls = _interrupt_after_staging(monkeypatch, after=len(outputs))
    code, out, err = cli(command, spec, *extra)
    assert code == 130, err
    assert calls["n"] == len(outputs)            # every output was staged, none renamed
    assert err.count("\n") == 1 and "interrupted" in err and "Traceback" not in err
    for name in outputs:
        assert (out_dir / name).read_bytes() == OLD + name.encode()
    assert temporaries(tmp_path) == []


def test_cli_gcode_interrupted_during_verification(cli, tmp_path, monkeypatch):
    import fabkit.toolpath.cut.verify as verify

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(verify, "verify_cut", interrupted)
    spec = tmp_path / "tiny.yaml"
    spec.write_text(yaml.safe_dump(tiny_raw(), sort_keys=False))
    old = tmp_path / "prev.ngc"
    old.write_bytes(OLD)
    code, out, err = cli("gcode", spec, "-o", old)
    assert code == 130 and old.read_bytes() == OLD
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prev.ngc", "tiny.yaml"]


# ----------------------------------------------------------------------------
# a real SIGINT to a running process
# ----------------------------------------------------------------------------
def _ctrl_c_reaches_children() -> None:
    """In the child before exec: SIGINT to its default, so that Python installs its
    KeyboardInterrupt handler there. A shell without job control starts background
    commands with SIGINT ignored, and an ignored signal stays ignored across exec: a
    suite started that way would otherwise send Ctrl-C into the void."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def python_ctrl_c():
    """SIGINT raising KeyboardInterrupt in this process for the test (as in a terminal),
    whatever the suite was started with; the previous handler restored after."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _cpu_seconds(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return -1.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
@pytest.mark.parametrize("command,busy_cpu_s", [("stl", 0.9), ("stl", 1.2), ("gcode", 1.5)])
def test_sigint_to_running_command(tmp_path, command, busy_cpu_s):
    """Ctrl-C once the process has used ``busy_cpu_s`` of CPU (past start-up,
    inside surface compilation, the mesh build or the planning): exit 130, one
    line, the previous output byte-identical, no temporary file. About 0.9 s
    lands in scipy's import, where CPython used to turn a caught Ctrl-C into a
    SIGINT death (-2) at exit (see ``fabkit.cli.entry``)."""
    spec = tmp_path / "tiny.yaml"
    raw = tiny_raw()
    raw["surface"].update(x=[-44, 6], y=[-12.5, 12.5])        # the paper's block: a few seconds of work
    spec.write_text(yaml.safe_dump(raw, sort_keys=False))
    target = tmp_path / "out" / f"block.{'stl' if command == 'stl' else 'ngc'}"
    target.parent.mkdir()
    target.write_bytes(OLD)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "fabkit", command, str(spec), "-o", str(target)],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=_ctrl_c_reaches_children)
    deadline = time.monotonic() + 60
    while proc.poll() is None and _cpu_seconds(proc.pid) < busy_cpu_s and time.monotonic() < deadline:
        time.sleep(0.02)
    sent = proc.poll() is None
    if sent:
        proc.send_signal(signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"fabkit {command} did not stop within 60 s of SIGINT")
    err = err.decode("utf-8", "replace")
    if not sent:
        pytest.skip(f"the run finished before SIGINT could be sent (exit {proc.returncode})")
    if proc.returncode in (0, 4):
        # the signal landed after the outputs were committed: the exit code must say so
        # (0: the command had returned; 4: interrupted after writing), the output complete
        assert target.read_bytes() != OLD and temporaries(tmp_path) == [], err
        pytest.skip(f"SIGINT landed after the outputs were written (exit {proc.returncode}, output complete)")
    assert proc.returncode == 130, err
    assert "Traceback" not in err and len(err.splitlines()) == 1 and "interrupted" in err
    assert target.read_bytes() == OLD
    assert temporaries(tmp_path) == []


def test_ctrl_c_during_the_renames_leaves_a_consistent_pair(tmp_path, monkeypatch, python_ctrl_c):
    """SIGINT arriving between renaming the program and its sheet is held until
    both are in place: never a new program beside an old sheet."""
    a, b = tmp_path / "a.ngc", tmp_path / "a.setup.json"
    a.write_bytes(OLD)
    b.write_bytes(OLD)
    real_replace = os.replace
    calls = []

    def replace_then_ctrl_c(src, dst):
        real_replace(src, dst)
        calls.append(dst)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(os, "replace", replace_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        with atomic_outputs() as out:
            out.write(a, "new program")
            out.write(b, "new sheet")
        time.sleep(0.1)                       # (unreached: the held SIGINT fires as the block ends)
    assert len(calls) == 2
    assert a.read_text() == "new program" and b.read_text() == "new sheet"
    assert temporaries(tmp_path) == []



# ----------------------------------------------------------------------------
# Ctrl-C at the edges of a run: real SIGINT at known points (FABKIT_PAUSE_AT)
# ----------------------------------------------------------------------------
GRBL_DUMP = "".join(f"${k}={v}\n" for k, v in [(11, 0.02), (12, 0.002), (30, 24000), (31, 1000), (100, 800),
                                                 (101, 800), (102, 400), (110, 5000), (111, 4000), (112, 1000),
                                                 (120, 500), (121, 400), (122, 100), (130, 300), (131, 180),
                                                 (132, 80)])


def _sigint_at(tmp_path, point: str, *args: str):
    """Run ``python -m fabkit ARGS`` with FABKIT_PAUSE_AT=point; once it says it has paused
    there (a line on stderr, read before anything is sent: no timing), send SIGINT."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), FABKIT_PAUSE_AT=point)
    env.pop("FABKIT_DEBUG", None)
    proc = subprocess.Popen([sys.executable, "-m", "fabkit", *args], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=_ctrl_c_reaches_children)
    first = proc.stderr.readline().decode()
    if first == f"fabkit: paused at {point}\n":
        proc.send_signal(signal.SIGINT)
    try:
        out, err = proc.communicate(timeout=90)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"fabkit did not stop after SIGINT at {point}")
    assert first == f"fabkit: paused at {point}\n", first + err.decode()
    return proc.returncode, out.decode(), err.decode()


@pytest.mark.parametrize("point,code,words", [
    ("start", 130, "interrupted while starting; nothing written"),
    ("written", 4, "interrupted after writing"),
    ("exit", 0, None),
])
def test_sigint_at_the_edges_of_a_run(tmp_path, point, code, words):
    """Ctrl-C from the first instruction to the last: at start-up (before the command's
    imports) 130 and nothing written; right after the output is renamed into place 4,
    naming it, and it is complete; after the command returned, its own code."""
    dump = tmp_path / "dump.txt"
    dump.write_text(GRBL_DUMP)
    target = tmp_path / "profile.yaml"
    target.write_bytes(OLD)
    rc, out, err = _sigint_at(tmp_path, point, "machine", "import", str(dump), "-o", str(target))
    assert "Traceback" not in err
    lines = err.splitlines()
    assert rc == code, err
    if words is None:
        assert lines == [] and "machine:" in out          # the summary, whole
    else:
        assert len(lines) == 1 and words in lines[0], err
    if point == "start":
        assert target.read_bytes() == OLD
    else:                                                 # written, whole: the profile it would always write
        text = target.read_text()
        assert text.startswith("# fabkit machine profile") and "max_rate: [5000.0, 4000.0, 1000.0]  # mm/min" in text
        assert point != "written" or str(target) in lines[0]
    assert temporaries(tmp_path) == []


@pytest.mark.parametrize("command", ["stl", "gcode"])
def test_sigint_when_the_outputs_are_made_but_not_renamed(tmp_path, command):
    """Ctrl-C after all the work, in the last instant before the renames (every output staged):
    130, one line, the previous output byte-identical, no temporary file left. The same as a
    Ctrl-C anywhere during the work, at a point reached on any machine at any speed."""
    spec = tmp_path / "tiny.yaml"
    raw = tiny_raw()
    raw["surface"].update(x=[-44, 6], y=[-12.5, 12.5])
    spec.write_text(yaml.safe_dump(raw, sort_keys=False))
    target = tmp_path / "out" / f"block.{'stl' if command == 'stl' else 'ngc'}"
    target.parent.mkdir()
    target.write_bytes(OLD)
    rc, out, err = _sigint_at(tmp_path, "staged", command, str(spec), "-o", str(target))
    assert rc == 130, err
    assert "Traceback" not in err and len(err.splitlines()) == 1 and "interrupted" in err, err
    assert target.read_bytes() == OLD
    assert temporaries(tmp_path) == []


def test_cli_interrupted_after_the_renames_says_written(cli, tmp_path, monkeypatch):
    """In-process: a KeyboardInterrupt once the outputs are renamed (a held SIGINT delivered
    as the renames end) reports them written, exit 4, not "left intact"."""
    dump = tmp_path / "dump.txt"
    dump.write_text(GRBL_DUMP)
    target = tmp_path / "profile.yaml"
    original = fabkit.io._Outputs._commit

    def commit_then_ctrl_c(self):
        original(self)
        raise KeyboardInterrupt

    monkeypatch.setattr(fabkit.io._Outputs, "_commit", commit_then_ctrl_c)
    code, out, err = cli("machine", "import", dump, "-o", target)
    assert code == 4 and err.count("\n") == 1 and "interrupted after writing" in err and str(target) in err
    assert target.read_text().startswith("# fabkit machine profile")


def test_ctrl_c_inside_an_import_is_an_interrupt(cli, tmp_path, monkeypatch):
    """numpy re-raises a KeyboardInterrupt that lands in its import as an ImportError: still
    exit 130 and the interrupt's line, not an internal error."""
    import importlib

    real = importlib.import_module

    def interrupted_import(name, *a, **k):
        if name.startswith("fabkit.commands."):
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt:
                raise ImportError("IMPORTANT: PLEASE READ THIS FOR ADVICE") from None
        return real(name, *a, **k)

    monkeypatch.setattr(importlib, "import_module", interrupted_import)
    code, out, err = cli("stl", tmp_path / "x.yaml")
    assert code == 130 and "interrupted" in err and "internal error" not in err
