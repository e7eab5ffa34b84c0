"""Hardening of every command (issue 8, items 1 and the acceptance).

* Property-based runs of ``fabkit.cli.main(argv)`` in-process: random values for
  random keys of a tiny version of the paper's spec, for each command. Every run
  ends with exit 0, 1 or 2, at most one line on stderr besides ``warning:``
  lines, never a traceback or "internal error", and writes nothing on exit 2.
* Guards on sizes derived from user numbers (scallop 1e-9 mm, tolerance 1e-12
  mm, ``--tolerance 1e-9``, ramp.samples 1e6, t_max 1e6 with rtol 1e-14): refused
  with a message naming the key and the limit, or a bounded run.
* The acceptance of issue 8: forty mutated versions of ``specs/surface.yaml`` and
  junk files, each run through ``python -m fabkit stl`` and ``check`` in a
  subprocess with a 30 s timeout.

Property runs of a command whose module ``fabkit.commands.<cmd>`` does not exist
are skipped.
"""

from __future__ import annotations

import contextlib
import copy
import importlib.util
import io
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fabkit.cli import main

from conftest import PAPER, ROOT, bounded, paper_raw, run_cli


def has_command(name: str) -> bool:
    return importlib.util.find_spec(f"fabkit.commands.{name}") is not None


def needs(name: str):
    return pytest.mark.skipif(not has_command(name), reason=f"fabkit {name} not implemented yet")


def tiny_raw() -> dict:
    """The paper's formula on a 14 x 8 cm footprint, coarse machining, few ramp
    samples, short time limit: every command runs in about a second."""
    raw = paper_raw()
    raw["name"] = "tiny"
    raw["surface"].update(x=[-10, 4], y=[-4, 4])
    raw["machining"].update(scallop=0.5, tolerance=0.1, verify_points=2000)
    raw["ramp"] = {"heights": [0.2, 1.0], "samples": 4}
    raw["simulation"].update(start=-8, t_max=5.0, rtol=1e-6, atol=1e-8)
    return raw


ARGS = {
    "stl": ["--tolerance", "0.05"],
    "gcode": [],
    "calibrate": [],
    "simulate": ["--v-in", "40"],
    "sweep": ["--v-in", "20", "60", "4", "--no-progress"],
    "check": ["--no-progress"],
}


def run_inprocess(argv: list[str], cwd: Path, seconds: int = 120) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    old = os.getcwd()
    os.chdir(cwd)
    try:
        with bounded(seconds), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main([str(a) for a in argv])
    finally:
        os.chdir(old)
    return code, out.getvalue(), err.getvalue()


def assert_clean_exit(code: int, err: str, expect=(0, 1, 2), out: str = "") -> None:
    """Exit 0/1/2 as expected; at most one non-warning line on stderr; no traceback.
    (``fabkit`` with no command prints its help on stdout and exits 2.)"""
    assert "Traceback" not in err and "internal error" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("warning:")]
    assert len(lines) <= 1, err
    assert code in expect, f"exit {code}, expected {expect}: {err}"
    if code == 2 and not out.startswith("usage:"):
        assert len(lines) == 1, "exit 2 must say why in one line"


def written(folder: Path, spec_name: str) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.name != spec_name)


# ----------------------------------------------------------------------------
# property-based CLI runs
# ----------------------------------------------------------------------------
def _leaves(raw: dict, prefix: str = "") -> list[str]:
    out = []
    for k, v in raw.items():
        if isinstance(v, dict) and k != "params":
            out.extend(_leaves(v, f"{prefix}{k}."))
        else:
            out.append(f"{prefix}{k}")
    return out


TINY = tiny_raw()
KEYS = _leaves(TINY) + [k for k, v in TINY.items() if isinstance(v, dict)] + [
    "surface.params.eps", "machining.stepdown", "machining.pattern", "simulation.y0", "simulation.vy0",
    "simulation.nonlinear_damping", "simulation.method", "ramp.samples", "tool.reach"]
cli_values = st.one_of(
    st.none(), st.booleans(),
    st.sampled_from([0, -1, 1, 2, -0.0, 1e-300, 1e-12, 1e-9, 1e-6, 0.5, 3, 7.5, 100, 1e6, 1e9, 1e12, 1e300,
                     float("nan"), float("inf"), -float("inf"), 10**16, "1/8 in", "2 mm", "-1 cm", "0 mm",
                     "grbl", "y", "climb", "simplified", "hollow", "Radau", [0.2, 4.5], [1, 2, 3], [-1, 2],
                     [], {}, "x" * 5000, "ü", "exp(exp(x))", "x**x**x", "sqrt(x)", "1/y", "0*x"]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10**20), max_value=10**20),
    st.text(max_size=20),
)


def _set(raw: dict, key: str, value) -> dict:
    raw = copy.deepcopy(raw)
    node = raw
    parts = key.split(".")
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value
    return raw


def _cli_property(command: str, key: str, value) -> None:
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        spec = folder / "tiny.yaml"
        spec.write_text(yaml.safe_dump(_set(TINY, key, value), sort_keys=False, allow_unicode=True))
        code, out, err = run_inprocess([command, spec.name, *ARGS[command]], folder)
        assert_clean_exit(code, err)
        if code == 2:
            assert written(folder, spec.name) == [], err


def _property_test(command: str, examples: int):
    @needs(command)
    @settings(max_examples=examples, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow])
    @given(key=st.sampled_from(KEYS), value=cli_values)
    def test(key, value):
        _cli_property(command, key, value)

    test.__name__ = f"test_random_spec_values_{command}"
    test.__doc__ = f"fabkit {command} on the tiny spec with one key set to a random value."
    return test


test_random_spec_values_stl = _property_test("stl", 25)
test_random_spec_values_gcode = _property_test("gcode", 15)
test_random_spec_values_calibrate = _property_test("calibrate", 30)
test_random_spec_values_simulate = _property_test("simulate", 20)
test_random_spec_values_sweep = _property_test("sweep", 12)
test_random_spec_values_check = _property_test("check", 12)


@settings(max_examples=30, deadline=None, derandomize=True, database=None)
@given(argv=st.lists(st.one_of(
    st.sampled_from(["stl", "gcode", "calibrate", "simulate", "sweep", "check", "precision", "explore",
                     "robustness", "--json", "-o", "--tolerance", "--v-in", "--height", "--plot", "--vary",
                     "nan", "inf", "-1", "1e308", "0", "--", "-", "--help-me", "specs/surface.yaml"]),
    st.text(max_size=12)), max_size=6))
def test_random_argv(argv):
    """Random argument lists: usage errors exit 2 with one line; nothing crashes."""
    argv = [a for a in argv if a not in ("-h", "--help", "--version")]
    cmd = next((a for a in argv if a in ARGS or a in ("precision", "explore", "robustness")), None)
    if cmd is not None and not has_command(cmd):
        argv = [a for a in argv if a != cmd]
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "specs").mkdir()
        (Path(d) / "specs" / "surface.yaml").write_text(yaml.safe_dump(TINY))
        code, out, err = run_inprocess(argv, Path(d))
    assert_clean_exit(code, err, out=out)


@pytest.mark.parametrize("argv", [
    [], ["nosuch"], ["stl"], ["stl", "a.yaml", "b.yaml"], ["stl", "a.yaml", "--tolerance", "x"],
    ["simulate", "a.yaml"], ["sweep", "a.yaml", "--v-in", "1", "2"], ["stl", "\n\u2028"], ["\x00"],
])
def test_usage_errors_are_one_line(argv, tmp_path):
    code, out, err = run_inprocess(argv, tmp_path)
    assert_clean_exit(code, err, (2,), out=out)


# ----------------------------------------------------------------------------
# guards on sizes derived from user numbers
# ----------------------------------------------------------------------------
GUARDS = [
    # (command, extra argv, key set in the tiny spec, value, key the refusal must name)
    ("gcode", [], "machining.scallop", 1e-9, "machining.scallop"),
    ("gcode", [], "machining.tolerance", 1e-12, "machining.tolerance"),
    ("stl", ["--tolerance", "1e-9"], None, None, "--tolerance"),
    ("check", ["--no-progress"], "ramp.samples", 1_000_000, "ramp.samples"),
    ("simulate", ["--v-in", "40"], "simulation.t_max", 1e6, "simulation.t_max"),
    ("simulate", ["--v-in", "40"], "simulation.rtol", 1e-14, "simulation.rtol"),
    ("sweep", ["--no-progress"], "ramp.samples", 10**7, "ramp.samples"),
    ("sweep", ["--v-in", "1", "60", "1e9", "--no-progress"], None, None, "v-in"),
]


@pytest.mark.parametrize("command,extra,key,value,names", GUARDS, ids=[f"{g[0]}-{g[2] or g[1][0]}" for g in GUARDS])
def test_guards_refuse_or_bound(tmp_path, command, extra, key, value, names):
    """Refused quickly (exit 2, one line naming the key and a limit), or a bounded
    run (the subprocess timeout is a hang guard, not a speed assertion)."""
    if not has_command(command):
        pytest.skip(f"fabkit {command} not implemented yet")
    raw = copy.deepcopy(TINY)
    if key:
        raw = _set(raw, key, value)
    if key == "simulation.t_max":
        raw["simulation"]["rtol"] = 1e-14
    spec = tmp_path / "tiny.yaml"
    spec.write_text(yaml.safe_dump(raw, sort_keys=False))
    code, out, err = run_subprocess([command, spec.name, *extra], tmp_path, timeout=120)
    assert_clean_exit(code, err)
    if code == 2:
        assert names in err and ("limit" in err or "<=" in err or ">=" in err), err
        assert written(tmp_path, spec.name) == []


# ----------------------------------------------------------------------------
# acceptance: forty mutated paper specs and junk files through stl and check
# ----------------------------------------------------------------------------
def _cpu_seconds(pid: int) -> float:
    """CPU time (user + system, all threads) of a running process, from /proc."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_subprocess(argv: list[str], cwd: Path, timeout: float = 30, fail: bool = True):
    """(exit code, stdout, stderr) of ``python -m fabkit ARGV``. A run that uses more
    than ``timeout`` seconds of CPU (a hang or a runaway loop; CPU, not wall time, so
    that a loaded machine does not fail the test), or sleeps past ten times that,
    fails the test (or, with ``fail=False``, gives exit code None)."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore")
    env.pop("FABKIT_DEBUG", None)
    proc = subprocess.Popen([sys.executable, "-m", "fabkit", *map(str, argv)], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    wall_limit = time.monotonic() + 10 * timeout
    while True:
        try:
            out, err = proc.communicate(timeout=0.25)
            break
        except subprocess.TimeoutExpired:
            if _cpu_seconds(proc.pid) > timeout or time.monotonic() > wall_limit:
                proc.kill()
                proc.communicate()
                if fail:
                    pytest.fail(f"fabkit {' '.join(map(str, argv))} still running after {timeout} s of CPU")
                return None, "", f"still running after {timeout} s of CPU"
    return proc.returncode, out.decode("utf-8", "replace"), err.decode("utf-8", "replace")


def _m(**changes):
    """A mutation: dotted key -> value (``None`` deletes the key)."""
    def apply(raw):
        for key, value in changes.items():
            parts = key.split(".")
            node = raw
            for p in parts[:-1]:
                node = node[p]
            if value is None:
                node.pop(parts[-1], None)
            else:
                node[parts[-1]] = value
        return raw
    return apply


def _swap_sections(a, b):
    def apply(raw):
        raw[a], raw[b] = raw[b], raw[a]
        return raw
    return apply


def _swap_height_params(raw):
    raw["surface"]["height"], raw["surface"]["params"] = raw["surface"]["params"], raw["surface"]["height"]
    return raw


# BAD: exit 2, nothing written. OK: valid input, exit 0 or 1 (a full run; these set ramp.samples 40
# instead of 400 so that check's full run stays a few seconds).
BAD, OK = "bad", "ok"
MUTATIONS = {
    # deleted keys and sections
    "drop_height": (_m(**{"surface.height": None}), BAD),
    "drop_surface": (_m(surface=None), BAD),
    "drop_thickness": (_m(**{"stock.thickness": None}), BAD),
    "drop_start": (_m(**{"simulation.start": None}), BAD),
    "drop_ramp_heights": (_m(**{"ramp.heights": None}), BAD),
    # wrong types
    "diameter_word": (_m(**{"tool.diameter": "big"}), BAD),
    "x_scalar": (_m(**{"surface.x": 5}), BAD),
    "params_list": (_m(**{"surface.params": [1, 2]}), BAD),
    "stock_string": (_m(stock="foam"), BAD),
    "scallop_bool": (_m(**{"machining.scallop": True}), BAD),
    "inertia_word": (_m(**{"ball.inertia": "lead"}), BAD),
    "heights_mapping": (_m(**{"ramp.heights": {"a": 1}}), BAD),
    "model_number": (_m(**{"simulation.model": 3}), BAD),
    # out-of-range numbers
    "diameter_negative": (_m(**{"tool.diameter": -3}), BAD),
    "thickness_zero": (_m(**{"stock.thickness": 0}), BAD),
    "top_nan": (_m(**{"surface.top": float("nan")}), BAD),
    "damping_negative": (_m(**{"simulation.damping": -1}), BAD),
    "depth_limit_huge": (_m(**{"stock.depth_limit": 1e9}), BAD),
    "top_1e300": (_m(**{"surface.top": 1e300}), BAD),
    "eta_1e12": (_m(**{"surface.params.eta": 1e12}), BAD),
    "eps_inf": (_m(**{"surface.params.eps": float("inf")}), BAD),
    # typos
    "typo_diamter": (_m(**{"tool.diamter": 6.35, "tool.diameter": None}), BAD),
    "typo_section": (lambda raw: {("surfac" if k == "surface" else k): v for k, v in raw.items()}, BAD),
    "typo_modle": (_m(**{"simulation.modle": "full", "simulation.model": None}), BAD),
    "typo_dialect": (_m(**{"machining.dialect": "linuxcn"}), BAD),
    "units_word": (_m(units="centimeters"), BAD),
    # swapped pairs
    "x_swapped": (_m(**{"surface.x": [6, -44]}), BAD),
    "y_swapped": (_m(**{"surface.y": [12.5, -12.5]}), BAD),
    "height_params_swapped": (_swap_height_params, BAD),
    "tool_stock_swapped": (_swap_sections("tool", "stock"), BAD),
    # hostile expressions
    "expr_import": (_m(**{"surface.height": "__import__('os').system('touch PWNED')"}), BAD),
    "expr_tower": (_m(**{"surface.height": "9**9**9*x"}), BAD),
    "expr_overflow": (_m(**{"surface.height": "exp(exp(exp(x)))"}), BAD),
    "expr_long": (_m(**{"surface.height": "x+" * 3000 + "x"}), BAD),
    "expr_log_negative": (_m(**{"surface.height": "log(x)"}), BAD),
    # unit changes
    # 135 mm deep: over the limit. stl refuses (exit 2); check reports it unmachinable (exit 1)
    "units_inch": (_m(units="in", **{"ramp.samples": 40}), {"stl": (2,), "check": (1, 2)}),
    "units_mm": (_m(units="mm", **{"ramp.samples": 40}), OK),
    "tool_inch_string": (_m(**{"tool.diameter": "1/8 in", "stock.thickness": "3 in", "ramp.samples": 40}), OK),
    # other edits a user makes
    "name_path": (_m(name="../../etc/evil"), BAD),
    "grbl_inch_y": (_m(**{"machining.dialect": "grbl", "machining.units": "in",
                          "machining.direction": "y", "name": "edited", "ramp.samples": 40}), OK),
}
assert len(MUTATIONS) == 40


def _junk_file(name: str, data: bytes | None):
    def make(folder: Path) -> str:
        if data is None:
            (folder / name).mkdir()
        else:
            (folder / name).write_bytes(data)
        return name
    return make


JUNK = {
    "binary": _junk_file("junk.yaml", bytes(range(256)) * 64),
    "empty": _junk_file("empty.yaml", b""),
    "huge_line": _junk_file("line.yaml", b"name: " + b"x" * 2_000_000),
    "directory": _junk_file("folder.yaml", None),
    "missing": lambda folder: "does-not-exist.yaml",
    "yaml_bomb": _junk_file("bomb.yaml", (ROOT / "tests" / "fixtures" / "junk" / "billion_laughs.yaml").read_bytes()),
}


ACCEPTANCE_COMMANDS = ["stl", "check"]
CASES = [(cmd, kind, name) for cmd in ACCEPTANCE_COMMANDS
         for kind, names in (("mutation", MUTATIONS), ("junk", JUNK)) for name in names]


def _run_case(cmd: str, kind: str, name: str, root: Path) -> dict:
    folder = root / f"{cmd}-{kind}-{name}"
    folder.mkdir()
    if kind == "mutation":
        mutate, expect = MUTATIONS[name]
        raw = mutate(paper_raw())
        (folder / "spec.yaml").write_text(yaml.safe_dump(raw, sort_keys=False, allow_unicode=True))
        spec = "spec.yaml"
    else:
        spec, expect = JUNK[name](folder), BAD
    before = set(folder.rglob("*"))
    extra = ["--no-progress"] if cmd == "check" else []
    if expect == BAD:
        # refused input: in this process (the refusal is the spec parser's, before any work),
        # from the case's folder, bounded like the subprocess runs
        # Python warnings (numpy's RuntimeWarning) reach a user's terminal as stderr lines:
        # recorded here and added to stderr, so the one-line rule sees them
        import warnings

        home = os.getcwd()
        os.chdir(folder)
        try:
            with bounded(30), warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                code, out, err = run_cli([cmd, spec, *extra])
        finally:
            os.chdir(home)
        err += "".join(f"{w.category.__name__}: {w.message}\n" for w in caught)
    else:
        code, out, err = run_subprocess([cmd, spec, *extra], folder, timeout=30, fail=False)
    after = set(folder.rglob("*"))
    return {"code": code, "out": out, "err": err, "expect": expect, "new": sorted(map(str, after - before)),
            "pwned": (folder / "PWNED").exists()}


@pytest.fixture(scope="module")
def acceptance(tmp_path_factory):
    """Run every (command, case) once, two at a time (the machine has two cores)."""
    root = tmp_path_factory.mktemp("acceptance")
    refused = [c for c in CASES if c[1] == "junk" or MUTATIONS[c[2]][1] == BAD]
    full = [c for c in CASES if c not in refused]
    results = {c: _run_case(*c, root) for c in refused}      # in-process, one at a time (chdir)
    with ThreadPoolExecutor(max_workers=2) as pool:           # full runs: subprocesses, two at a time
        results.update(zip(full, pool.map(lambda c: _run_case(*c, root), full)))
    return results


SLOW: dict = {}   # (command, kind, case) -> an xfail mark for a case known to be over the limit


@pytest.mark.parametrize("cmd,kind,name", [
    pytest.param(*c, marks=[SLOW[c]] if c in SLOW else []) for c in CASES],
    ids=[f"{c[0]}-{c[2]}" for c in CASES])
def test_acceptance_mutations_and_junk(acceptance, cmd, kind, name):
    r = acceptance[(cmd, kind, name)]
    assert not r["pwned"]
    assert r["code"] is not None, f"fabkit {cmd} {name}: {r['err']} (limit 30 s of CPU)"
    if isinstance(r["expect"], dict):
        assert_clean_exit(r["code"], r["err"], r["expect"][cmd])
        if r["code"] == 2:
            assert r["new"] == [], f"exit 2 but wrote {r['new']}"
    elif r["expect"] == BAD:
        assert_clean_exit(r["code"], r["err"], (2,))
        assert r["new"] == [], f"exit 2 but wrote {r['new']}"
    else:
        assert_clean_exit(r["code"], r["err"], (0, 1))
        if cmd == "stl":
            assert r["code"] == 0 and any(p.endswith(".stl") for p in r["new"]), r


# ----------------------------------------------------------------------------
# known bugs in the commands, kept visible
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("argv", [["simulate", "tiny.yaml", "--v-in", "1e100"],
                                  ["sweep", "tiny.yaml", "--v-in", "1", "1e308", "3", "--no-progress"]],
                         ids=["simulate", "sweep"])
def test_huge_entry_speed_ends(tmp_path, argv):
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(TINY, sort_keys=False))
    code, out, err = run_subprocess(argv, tmp_path, timeout=10, fail=False)
    assert code is not None, err
    assert_clean_exit(code, err)


def test_absurd_entry_speed_flies_off(tmp_path):
    """At 1e20 cm/s the ball leaves the 14 x 8 cm footprint at once: flew_off (or a refusal)."""
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(TINY, sort_keys=False))
    code, out, err = run_inprocess(["simulate", "tiny.yaml", "--v-in", "1e20", "--json"], tmp_path, seconds=60)
    assert_clean_exit(code, err, (0, 2))
    if code == 0:
        import json
        assert json.loads(out)["outcome"] == "flew_off"


def test_calibrate_huge_height(tmp_path):
    (tmp_path / "tiny.yaml").write_text(yaml.safe_dump(TINY, sort_keys=False))
    code, out, err = run_subprocess(["calibrate", "tiny.yaml", "--height", "1e308"], tmp_path, timeout=60)
    assert_clean_exit(code, err)
    assert code == 2 or "inf" not in out


# ----------------------------------------------------------------------------
# issue 11: exit 3 for bad input, I/O errors, Dask addresses, truthful messages
# ----------------------------------------------------------------------------
def _tiny_file(tmp_path: Path, changes: dict | None = None) -> Path:
    raw = tiny_raw()
    for key, value in (changes or {}).items():
        node = raw
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path


def _one_line_exit2(code: int, err: str, named: str) -> None:
    lines = [ln for ln in err.splitlines() if ln and not ln.startswith("warning:")]
    assert code == 2, err
    assert len(lines) == 1 and named in lines[0], err
    assert "internal error" not in err and "Traceback" not in err


@pytest.mark.parametrize("argv,named", [
    (["sweep", "{spec}", "--v-in", "40", "50", "nan"], "--v-in"),
    (["sweep", "{spec}", "--v-in", "40", "50", "inf"], "--v-in"),
    (["sweep", "{spec}", "--v-in", "nan", "50", "3"], "--v-in"),
    (["explore", "{spec}", "--v-in", "40", "50", "inf"], "--v-in"),
    (["robustness", "{spec}", "--v-in", "40", "50", "nan", "--sigma-y", "0.1", "--sigma-vy", "0.1",
      "--samples", "2"], "--v-in"),
    (["robustness", "{spec}", "--v-in", "40", "50", "3", "--sigma-y", "inf", "--sigma-vy", "0.1",
      "--samples", "2"], "--sigma-y"),
    (["robustness", "{spec}", "--v-in", "40", "50", "3", "--sigma-y", "0.1", "--sigma-vy", "0.1",
      "--samples", "2", "--seed", "-1"], "--seed"),
    (["simulate", "{spec}", "--v-in", "inf"], "--v-in"),
    (["calibrate", "{spec}", "--height", "nan"], "--height"),
    (["stl", "{spec}", "--tolerance", "inf"], "--tolerance"),
])
def test_bad_numbers_on_the_command_line(tmp_path, argv, named):
    spec = _tiny_file(tmp_path)
    with bounded(60):
        code, out, err = _run([a.format(spec=spec) for a in argv])
    _one_line_exit2(code, err, named)


def _run(argv):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


def test_full_disk_is_an_io_error_line(tmp_path, monkeypatch):
    """ENOSPC while writing the output: one line naming the output, exit 2, no file
    and no temporary left (a real full disk behaves the same: a 64 kB tmpfs was
    tried by hand)."""
    import errno

    import fabkit.io as fio

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(fio.os, "fsync", full)
    spec = _tiny_file(tmp_path)
    target = tmp_path / "out" / "x.png"
    with bounded(60):
        code, out, err = _run(["simulate", spec, "--v-in", "30", "--plot", target])
    _one_line_exit2(code, err, "No space left on device")
    assert str(target) in err
    assert not any(p.is_file() for p in (tmp_path / "out").iterdir())


def test_stray_os_error_is_not_an_internal_error(tmp_path, monkeypatch):
    import errno

    import fabkit.commands.calibrate as cal

    def broken(args):
        raise OSError(errno.EIO, os.strerror(errno.EIO), "/some/file")

    monkeypatch.setattr(cal, "run", broken)
    code, out, err = _run(["calibrate", _tiny_file(tmp_path)])
    _one_line_exit2(code, err, "I/O error")
    assert "/some/file" in err


@pytest.mark.parametrize("address,why", [
    ("garbage://x", "unknown scheme"),
    ("tcp://127.0.0.1:1", "cannot connect"),
    ("tcp://host.invalid:8786", "unknown host"),
    ("127.0.0.1", "host:port"),
])
def test_bad_dask_address_is_one_line(tmp_path, address, why):
    import gc

    spec = _tiny_file(tmp_path)
    out, err = io.StringIO(), io.StringIO()
    with bounded(20), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["robustness", str(spec), "--v-in", "30", "40", "2", "--sigma-y", "0.1", "--sigma-vy", "0.1",
                     "--samples", "2", "--scheduler", address, "--no-progress"])
        gc.collect()   # a half-built distributed.Client used to print a traceback here, 20 s later
    _one_line_exit2(code, err.getvalue(), "--scheduler")
    assert why in err.getvalue() and "Exception ignored" not in err.getvalue()


def test_zero_ramp_height_names_file_and_key(tmp_path):
    spec = _tiny_file(tmp_path, {"ramp.heights": [0, 1.0]})
    code, out, err = _run(["check", spec, "--no-progress"])
    _one_line_exit2(code, err, f"{spec}: ramp.heights[0]:")


@pytest.mark.parametrize("key,value", [("machining.spindle", 0.4), ("machining.feed", 0.0001),
                                       ("machining.safe_height", 1e-300)])
def test_gcode_refuses_values_that_round_away(tmp_path, key, value):
    spec = _tiny_file(tmp_path, {key: value})
    code, out, err = _run(["gcode", spec, "-o", tmp_path / "x.ngc"])
    _one_line_exit2(code, err, key)
    assert not (tmp_path / "x.ngc").exists()


def test_named_pipe_spec_does_not_block(tmp_path):
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    with bounded(20):
        code, out, err = _run(["calibrate", fifo])
    _one_line_exit2(code, err, "named pipe")


def _launches(outcomes, bounces):
    import numpy as np

    from fabkit.physics.sweep import Launches

    n = len(outcomes)
    return Launches(np.arange(1.0, n + 1), np.array(outcomes, dtype=np.int8), np.array(bounces),
                    np.zeros(n), np.full((n, 2), np.nan))


@pytest.mark.parametrize("outcomes,bounces,says,never", [
    # specs/bowl.yaml: the slow launches escape after one bounce, the fast ones fly off
    ([0, 0, 0, 2, 2, 2], [1, 1, 1, 0, 0, 0],
     "the 3 launches from v_in 1 to 3 escape after one bounce and the 3 launches from v_in 4 up fly off",
     "every launch escapes"),
    ([0, 0, 0, 0, 0, 3], [1, 1, 1, 1, 1, 0], "and the launch at v_in 6 loses contact", "every launch escapes"),
    ([0] * 6, [1] * 6, "every launch escapes after one bounce: v_critical is below the range", "fly off"),
    ([2, 3, 2, 2, 2, 2], [0] * 6, "every launch in the range (6, v_in 1 to 6) flies off or loses contact", "escape"),
    ([1, 2, 2, 2, 2, 2], [0] * 6, "no one-bounce escape at v_in 1", "every launch escapes"),
])
def test_v_critical_reason_counts_what_the_launches_did(outcomes, bounces, says, never):
    import numpy as np

    from fabkit.physics.sweep import critical_bracket

    lo, hi, reason = critical_bracket(np.arange(1.0, len(outcomes) + 1), _launches(outcomes, bounces))
    assert lo is None and says in reason and never not in reason, reason


def test_bowl_sweep_reason_in_every_output(tmp_path):
    """specs/bowl.yaml with top 0, as first shipped, said 'every launch escapes after one bounce'
    with 335 of 400 launches flying off."""
    import json

    raw = yaml.safe_load((ROOT / "specs" / "bowl.yaml").read_text())
    raw["surface"]["top"] = 0          # as first shipped: the channel is cut off at x = 0
    bowl = tmp_path / "bowl.yaml"
    bowl.write_text(yaml.safe_dump(raw))
    with bounded(120):
        code, out, err = _run(["sweep", bowl, "--v-in", "118", "335", "24", "--json", "--no-progress"])
    assert code == 0, err
    res = json.loads(out)
    n_off = res["outcome"].count("flew_off")
    assert n_off and res["v_critical"] is None
    assert f"the {n_off} launches from v_in" in res["v_critical_reason"] and "fly off" in res["v_critical_reason"]
    assert "every launch escapes" not in res["v_critical_reason"]


def test_simulate_says_where_and_why_contact_is_lost():
    """v_in 400 cm/s on the paper's surface: the ball loses contact. The line gives
    x, y, t and the reason; at that point the normal-force bracket of eq. (xyODE),
    B = h_xx xd^2 + 2 h_xy xd yd + h_yy yd^2 + g~, is zero."""
    import json

    from fabkit import units
    from fabkit.physics.calibrate import ball_k
    from fabkit.spec import load_spec

    with bounded(120):
        code, out, err = _run(["simulate", PAPER, "--v-in", "400", "--json"])
    assert code == 0, err
    r = json.loads(out)
    assert r["outcome"] == "lost_contact" and "normal force falls to zero" in r["end_reason"]
    spec = load_spec(PAPER)
    f = spec.surface_functions()
    hxx, hxy, hyy = (float(a) for a in f.hess(r["x_end"], r["y_end"]))
    g = units.gravity(spec.units) / (1 + ball_k(spec))
    xd, yd = r["vx_end"], r["vy_end"]
    B = hxx * xd ** 2 + 2 * hxy * xd * yd + hyy * yd ** 2 + g
    assert abs(B) < 1e-5 * g          # B falls from g~ at the launch to zero (event located to ~1e-6)
    code, out, err = _run(["simulate", PAPER, "--v-in", "400"])
    line = next(ln for ln in out.splitlines() if ln.startswith("outcome:"))
    assert f"x = {r['x_end']:.6g} cm" in line and f"t = {r['t_end']:.6g} s" in line and "normal force" in line


def test_simulate_keeps_every_bounce_time(tmp_path):
    """A captured launch bouncing 20-odd times in 30 s: every bounce time is printed
    and in the JSON (the integrator keeps 16 unless asked), the first 16 equal the
    default run's (the same steps)."""
    import json

    import numpy as np

    from fabkit.physics.integrate import simulate_one
    from fabkit.physics.models import problem_from_spec
    from fabkit.spec import load_spec

    spec = _tiny_file(tmp_path, {"simulation.t_max": 25.0})
    with bounded(120):
        code, out, err = _run(["simulate", spec, "--v-in", "10", "--json"])
    assert code == 0, err
    r = json.loads(out)
    assert r["bounces"] > 16 and len(r["bounce_times"]) == r["bounces"]
    assert np.all(np.diff(r["bounce_times"]) > 0)
    first = simulate_one(problem_from_spec(load_spec(spec)), 10.0, record=False)["bounce_times"]
    assert len(first) == 16 and first == r["bounce_times"][:16]
    from fabkit.commands.simulate import _bounce_lines

    lines = _bounce_lines(r["bounces"], r["bounce_times"])
    printed = [float(t) for ln in lines[1:] for t in ln.replace(" s", "").split(",") if t.strip()]
    assert lines[0] == f"bounces: {r['bounces']} at t =" and len(printed) == r["bounces"]
    np.testing.assert_allclose(printed, r["bounce_times"], atol=5e-7)


def test_check_lists_every_window_or_says_how_many(tmp_path, monkeypatch):
    """The summary layer: 7 windows are all listed; 30 are listed to 24 with a note;
    the JSON holds all 30."""
    import json

    import numpy as np

    import fabkit.physics.check as pc

    def fake(n):
        def check(spec, *, progress=None, **kw):
            wins = [{"lo": 10 + i, "hi": 10.5 + i, "height_lo": 1 + i / 100, "height_hi": 1.004 + i / 100,
                     "v_out_max": 1.0} for i in range(n)]
            return pc.CheckReport(
                model="full", damping=0.1, units="cm", heights=np.array([0.2, 1.0]), v_in=np.array([16.0, 40.0]),
                outcome=np.array([0, 0], dtype=np.int8), bounces=np.array([1, 1]), v_out=np.array([1.0, 1.0]),
                first_failure=None, highest_safe_height=1.0, v_critical=50.0, v_critical_error=1e-5,
                v_critical_reason="", critical_height=1.9, windows=wins, reachable_windows=wins, machining=None,
                ball=None, grid=None, tolerances=dict(pc.TOLERANCES))
        return check

    spec = _tiny_file(tmp_path)
    for n, listed, note in ((7, 7, False), (30, 24, True)):
        monkeypatch.setattr(pc, "check", fake(n))
        code, out, err = _run(["check", spec, "--no-progress"])
        assert code == 0, err
        assert sum(ln.startswith("  release height") for ln in out.splitlines()) == listed
        assert (f"{n} two-bounce windows reachable from the ramp (the first 24 listed; all in --json)" in out) == note
        code, out, err = _run(["check", spec, "--no-progress", "--json"])
        assert len(json.loads(out)["reachable_windows"]) == n


def test_robustness_says_how_many_speeds_it_lists(tmp_path):
    import json

    spec = _tiny_file(tmp_path)
    argv = ["robustness", spec, "--v-in", "20", "40", "81", "--sigma-y", "0", "--sigma-vy", "0", "--samples", "1",
            "--no-progress"]
    with bounded(120):
        code, out, err = _run(argv)
    assert code == 0, err
    rows = [ln for ln in out.splitlines() if ln.startswith("  v_in")]
    assert "one speed in 3 listed (27 of 81; all in --json)" in out and len(rows) == 27
    code, out, err = _run(argv + ["--json"])
    assert len(json.loads(out)["rows"]) == 81


def test_precision_without_launches_still_studies_toolpath_and_mesh(tmp_path, monkeypatch):
    """A tilted plane: every launch flies off, so the simulation study cannot run.
    Exit 0 (not 1: nothing is unsafe), one line saying why, no doubled prefix, the
    toolpath and mesh rows present, --plot not written (a warning says so)."""
    import json

    from fabkit import precision as P

    monkeypatch.setitem(P.QUICK, "toolpath", (0.1,))
    monkeypatch.setitem(P.QUICK, "mesh", (0.1,))
    spec = _tiny_file(tmp_path, {"surface.height": "-0.05*x + c*y**2", "surface.params": {"c": 0.0764}})
    with bounded(120):
        code, out, err = _run(["precision", spec, "--quick", "--json", "--plot", tmp_path / "p.png"])
    assert code == 0, err
    res = json.loads(out)
    assert res["simulation"] == [] and "no well-conditioned launch" in res["simulation_skipped"]
    assert "flew_off" in res["simulation_skipped"]
    assert len(res["toolpath"]) == 1 and len(res["mesh"]) == 1
    assert not (tmp_path / "p.png").exists() and "not written" in err
    code, out, err = _run(["precision", spec, "--quick"])
    assert code == 0 and "precision: simulation study skipped: no well-conditioned" in out
    assert "precision: precision:" not in out + err


# ----------------------------------------------------------------------------
# issue 29: --vary values get the spec key's own range checks (design and explore)
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("command,vary,says", [
    ("design", "surface.params.eps=-1e308:1e308", "out of range"),         # was OverflowError (exit 3)
    ("design", "surface.params.eps=0:5e-324", "too narrow"),               # was an optimizer error (exit 3)
    ("design", "surface.params.eps=1:1.0000000000000002", "too narrow"),
    ("design", "simulation.start=-1e308:1e308", "too wide"),                # no range of its own: HI - LO overflows
    ("design", "ball.diameter=0:3", "must be > 0"),                        # the key's own range
    ("design", "simulation.damping=-1:1", "must be >= 0"),
    ("design", "ramp.samples=2:1e300", "must be <= 10000"),
    ("design", "surface.x.lo=-1e10:0", "out of range"),
    ("design", "ramp.samples=2.5:2.7", "no whole number"),
    ("explore", "surface.params.eps=-1e308:1e308:3", "out of range"),
    ("explore", "surface.params.eps=0:5e-324:2", "too narrow"),
    ("explore", "surface.params.eps=1e308,2", "out of range"),
    ("explore", "tool.diameter=0:1:2", "must be > 0"),
    ("explore", "simulation.model=full,bogus", "must be one of"),
    ("explore", "ball.inertia=solid,-1", "must be in [0, 10]"),
    ("explore", "surface.params.eps=1:1.000000000001:1000", "too narrow"),
])
def test_vary_values_get_the_keys_range_checks(tmp_path, command, vary, says):
    spec = _tiny_file(tmp_path)
    before = set(tmp_path.rglob("*"))
    with bounded(60):
        code, out, err = _run([command, spec, "--vary", vary, "--no-progress"])
    _one_line_exit2(code, err, "--vary")
    assert says in err and vary.split("=")[0] in err, err
    assert set(tmp_path.rglob("*")) == before


def test_vary_parsing_keeps_good_values():
    """What passes the checks is exactly the grid asked for (values against linspace's
    closed form lo + i (hi - lo) / (n - 1)), whole numbers for whole-number keys."""
    from fabkit.design import parse_bound
    from fabkit.explore import parse_vary
    from fabkit.spec import load_spec

    spec = load_spec(PAPER)
    v = parse_vary("surface.params.eps=0.1:0.4:4", spec)
    assert v.values == pytest.approx([0.1 + i * 0.1 for i in range(4)], rel=1e-15)
    assert parse_vary("ramp.samples=2:4:3", spec).values == (2, 3, 4)
    assert parse_vary("ball.inertia=solid,0.5", spec).values == ("solid", 0.5)
    b = parse_bound("ramp.samples=1.5:3", spec)
    assert (b.lo, b.hi, b.integer) == (1.5, 3.0, True)
    b = parse_bound("surface.params.eps=-1e12:1e12", spec)
    assert (b.lo, b.hi) == (-1e12, 1e12) and b.step == 1e9


# ----------------------------------------------------------------------------
# issue 29: every option tried with huge, tiny (subnormal), negative and junk numbers
# ends with one line naming the option, exit 2 (they were exit 3, numpy warnings)
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("argv,named,says", [
    (["phi4", "--v-in", "0.27", "--dx", "1e-320"], "--dx", "grid intervals exceed"),      # was OverflowError
    (["phi4", "--v-in", "0.27", "--dx", "5e-324"], "--dx", "grid intervals exceed"),
    (["stl", "{spec}", "--tolerance", "1e-320"], "--tolerance", ">= 1e-06 mm"),       # was a numpy warning
    (["stl", "{spec}", "--tolerance", "5e-324"], "--tolerance", ">= 1e-06 mm"),
    (["design", "{spec}", "--vary", "surface.params.c=0.05:0.1", "--min-width", "5e-324"], "--min-width",
     "below 1e-9"),                                                                          # was OverflowError
    (["design", "{spec}", "--vary", "surface.params.c=0.05:0.1", "--sigma-y", "1e308"], "--sigma-y",
     "wider than the footprint"),                                                            # was a numpy warning
    (["design", "{spec}", "--vary", "surface.params.c=0.05:0.1", "--sigma-vy", "1e308"], "--sigma-vy",
     "at most 1e+06"),
    (["robustness", "{spec}", "--v-in", "40", "50", "3", "--sigma-y", "1e308", "--sigma-vy", "0",
      "--samples", "2"], "--sigma-y", "wider than the footprint"),
    (["robustness", "{spec}", "--v-in", "40", "50", "3", "--sigma-y", "0", "--sigma-vy", "1e300",
      "--samples", "2"], "--sigma-vy", "at most 1e+06"),
    (["sweep", "{spec}", "--v-in", "40", "50", "1e308"], "--v-in", "N = 1e+308 exceeds"),    # was 309 digits
])
def test_hostile_option_values_are_one_line(tmp_path, argv, named, says):
    spec = _tiny_file(tmp_path)
    before = set(tmp_path.rglob("*"))
    with bounded(120):
        code, out, err = _run([a.format(spec=spec) for a in argv])
    _one_line_exit2(code, err, named)
    assert says in err and len(err) < 300, err
    assert "Warning" not in err
    assert set(tmp_path.rglob("*")) == before
