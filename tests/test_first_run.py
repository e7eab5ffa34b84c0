"""The first run: one command compiles every kernel the shipped commands need for a spec
(fabkit/first_run.py, :func:`prepare`) and says so with the total to expect; the part a
command does not use is compiled ahead only when its once-per-installation kernels are
cold. The compilers are replaced here by recorders (a real first run costs tens of seconds
of CPU: README, "Performance", measures it from a fresh clone)."""

from __future__ import annotations

import pytest

from conftest import PAPER
from fabkit import first_run


@pytest.fixture
def recorded(monkeypatch):
    calls = []
    import fabkit.physics.engine.batch as batch
    import fabkit.toolpath.finish.kernels as kernels

    monkeypatch.setattr(batch, "engine", lambda problem, notify=None: calls.append(("simulator", problem.model)))
    monkeypatch.setattr(kernels, "kernel_for", lambda surface: calls.append(("toolpath", "drop cutter")))
    monkeypatch.setattr(first_run, "_toolpath_signatures", lambda: [])
    return calls


def _cold(monkeypatch, **kw):
    cold = {"simulator": 0.0, "toolpath": 0.0, "simulator_install": False, "toolpath_install": False, **kw}
    monkeypatch.setattr(first_run, "cold_kernels", lambda spec: dict(cold))


@pytest.mark.parametrize("need", [("simulator",), ("toolpath",), ("simulator", "toolpath")])
def test_the_first_run_compiles_everything_once_and_says_the_total(monkeypatch, recorded, need):
    from fabkit.spec import load_spec

    _cold(monkeypatch, simulator=22.0, toolpath=27.4, simulator_install=True, toolpath_install=True)
    said = []
    got = first_run.prepare(load_spec(PAPER), say=said.append, need=need)
    assert got == {"simulator": 22.0, "toolpath": 27.4}
    assert [c[0] for c in recorded] == ["simulator", "toolpath"]          # both, whichever command runs first
    assert said == ["compiling fabkit's kernels for this surface (once, about 49 s of CPU in all: the simulator "
                    "about 22 s, the toolpath's kernels about 27 s; then gcode, check and report load them)"]


def test_a_new_formula_compiles_only_what_the_command_uses(monkeypatch, recorded):
    from fabkit.spec import load_spec

    # the installation's kernels are built; a new formula's functions are not
    _cold(monkeypatch, simulator=2.0, toolpath=1.7)
    said = []
    assert first_run.prepare(load_spec(PAPER), say=said.append, need=("toolpath",)) == \
        {"simulator": 0.0, "toolpath": 1.7}
    assert recorded == [("toolpath", "drop cutter")] and "about 2 s of CPU in all: the toolpath's" in said[0]
    recorded.clear()
    said.clear()
    _cold(monkeypatch)                               # everything cached: nothing said, nothing compiled
    assert first_run.prepare(load_spec(PAPER), say=said.append) == {"simulator": 0.0, "toolpath": 0.0}
    assert recorded == [] and said == []


def test_cold_kernels_reads_the_caches():
    """On the tests' session cache the paper's simulator is compiled (conftest) and every
    estimate is a whole part's: the engine's measured compile plus its formula, or 2 s."""
    from fabkit.spec import load_spec
    from fabkit.toolpath.finish import kernels

    c = first_run.cold_kernels(load_spec(PAPER))
    assert set(c) == {"simulator", "toolpath", "simulator_install", "toolpath_install"}
    assert c["simulator"] in (0.0, 2.0) or c["simulator_install"]
    assert c["toolpath"] >= 0 and c["toolpath_install"] == (c["toolpath"] > kernels.BUILD_FORMULA_S + 1e-9)
