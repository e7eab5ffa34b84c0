"""The package's house, read from its imports (docs/architecture.py, the AST; nothing is
imported): no import cycle, no module over 1000 lines, every folder says its phase.

Two graphs (docs/architecture.py says how each import counts): the imports that run at
module level, where a cycle is an import-order hazard, must have none; the imports inside
functions (deferred to the first call) are counted in a second graph, where a cycle still
says two modules need each other. The parts still waiting for work on other branches are
marked xfail (not strict) with their reason, beside a test that nothing NEW joins them.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "docs"))
import architecture as A  # noqa: E402

#: waiting for another branch: the cycle and the long modules known when this was written
KNOWN_CYCLES: set = set()   # none left: the ramp's profile lives in physics (fabkit.physics.ramp_profile)
KNOWN_LONG: set = set()     # none left: roughing split (roughing_loops, roughing_rest), lab/track.py by concern


@pytest.fixture(scope="module")
def graphs():
    return A.graph(), A.graph(deferred=True)


def test_the_reader_sees_cycles_and_reexports(tmp_path):
    """The graph on a package made here: a module-level cycle, a cycle through a function's
    import only, and a name re-exported by a module it does not live in."""
    pkg = tmp_path / "fabkit"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text('"""top"""\n')
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from . import b\n")
    (pkg / "b.py").write_text("from .a import x\n")
    (pkg / "c.py").write_text("def f():\n    from .sub import d\n")
    (pkg / "sub" / "d.py").write_text("from ..c import f\nfrom ..e import thing  # re-exported\n")
    (pkg / "e.py").write_text("thing = 1\n")
    (pkg / "g.py").write_text("from .sub.d import thing\nfrom typing import TYPE_CHECKING\n"
                              "if TYPE_CHECKING:\n    from . import a\n")
    g, g_all = A.graph(tmp_path), A.graph(tmp_path, deferred=True)
    assert A.cycles(g) == [["fabkit.a", "fabkit.b", "fabkit.a"]]
    assert A.cycles(g_all) == [["fabkit.a", "fabkit.b", "fabkit.a"], ["fabkit.c", "fabkit.sub.d", "fabkit.c"]]
    assert g["fabkit.g"] == {"fabkit.sub.d", "fabkit.e"}          # TYPE_CHECKING left out
    assert A.stage_docs(tmp_path) == {"fabkit": "top", "fabkit.sub": ""}
    assert A.long_modules(tmp_path, limit=1) == {"fabkit.c": 2, "fabkit.sub.d": 2, "fabkit.g": 4}


def test_no_import_cycle_at_module_level(graphs):
    assert A.cycles(graphs[0]) == []


def test_no_new_cycle_through_function_imports(graphs):
    found = {tuple(sorted(set(c))) for c in A.cycles(graphs[1])}
    assert found <= KNOWN_CYCLES, found - KNOWN_CYCLES


def test_no_import_cycle_counting_function_imports(graphs):
    assert A.cycles(graphs[1]) == []


def test_no_new_module_over_1000_lines():
    assert set(A.long_modules()) <= KNOWN_LONG, set(A.long_modules()) - KNOWN_LONG


def test_no_module_over_1000_lines():
    assert A.long_modules() == {}


def test_every_folder_names_its_phase():
    assert {m: d for m, d in A.stage_docs().items() if not d} == {}
