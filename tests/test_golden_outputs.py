"""Same outputs, byte for byte, before and after the toolpath job was written once
(fabkit/toolpath/job.py): the programs, setup sheets (JSON and Markdown) and the
``--json`` summaries of ``fabkit gcode``, and the setup sheet of ``fabkit report``'s
toolpath, over the shipped specs (made cheap: coarser scallop, fewer check points),
small specs of the test suite, a machine profile and the test fixtures.

The reference files in tests/fixtures/golden/ were written ONCE by the code at commit
74ae3d5 (before the refactor), with ``python tests/test_golden_outputs.py --write``.
A golden file is the right reference here, and only here, because the contract is
"unchanged output": the comparison is against what the code produced before the
change, not against its own current output. Removed before comparing: the sheet's
``generated_at`` and every wall time (``timings_s``, ``seconds``), which differ run to
run. A change that alters the programs on purpose (a planner change) regenerates them
with the same command and says so in its commit.
"""

from __future__ import annotations

import contextlib
import copy
import gzip
import hashlib
import io
import json
import os
import sys
from pathlib import Path

import pytest
import yaml
from golden import strip_volatile

HERE = Path(__file__).resolve().parent
GOLDEN = HERE / "fixtures" / "golden"
SPECS = HERE.parent / "specs"
sys.path.insert(0, str(HERE))

GRBL_DUMP = "$11=0.010\n$30=24000\n$31=0\n$110=500\n$111=500\n$112=500\n$120=10.000\n$121=10.000\n" \
            "$122=10.000\n$130=200.000\n$131=200.000\n$132=200.000\n"


def _small(**machining):
    from test_gcode_cli import small_raw

    return small_raw(**machining)


def _shipped(name: str, **machining) -> dict:
    raw = yaml.safe_load((SPECS / f"{name}.yaml").read_text())
    raw["machining"].update(machining)
    return raw


def _fixture(rel: str, **machining) -> dict:
    raw = yaml.safe_load((HERE / "fixtures" / rel).read_text())
    raw["machining"].update(machining)
    return raw


def _crossv() -> dict:
    """Two V creases crossing (tests/test_surface_family.py's crossv): the first verified
    cut leaves 0.12 mm where the crease meets the stock edge; passes are added."""
    from test_surface_family import _raw

    return _raw("3*abs(x) + 2*abs(y) - 20", (-8, 8), (-6, 6), "x", "mm")


#: name -> (spec, extra gcode options); a name starting with "plain_" is planned by the
#: test suite's plain planner cut 0.1 mm too deep (a failed verification, exit 1)
CASES = {
    "crossv_repair": (_crossv, ()),
    "plain_gouge": (lambda: _small(), ()),
    "small_mm": (lambda: _small(), ()),
    "small_in_grbl": (lambda: _small(units="in", dialect="grbl"), ()),
    "small_grbl_machine": (lambda: _small(dialect="grbl"), ("--machine", "grbl.txt")),
    "small_no_verify": (lambda: _small(), ("--no-verify",)),
    "small_vertical": (lambda: _small(scallop_measure="vertical", direction="y"), ()),
    "bowl_coarse": (lambda: _shipped("bowl", scallop=0.25, verify_points=6000), ()),
    "surface_coarse": (lambda: _shipped("surface", scallop=0.3, verify_points=6000), ()),
    "clipped_coarse": (lambda: _fixture("check/clipped_top2.yaml", scallop=0.3, verify_points=6000), ()),
}



def _run(argv: list[str]) -> tuple[int, str, str]:
    from fabkit.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def produce(name: str, folder: Path) -> dict[str, str]:
    """The outputs of case ``name`` run in ``folder``: file name -> text."""
    make, opts = CASES[name]
    raw = copy.deepcopy(make())
    raw["name"] = name
    old = os.getcwd()
    os.chdir(folder)
    undo = None
    if name.startswith("plain_"):
        import fabkit.toolpath.finish.raster as raster
        from test_gcode_cli import simple_plan

        undo = raster.plan_toolpath
        raster.plan_toolpath = lambda spec, surface, *a, **k: simple_plan(
            surface, spec.tool.diameter / 2, spec.machining.scallop, dz=-0.1, safe_z=spec.machining.safe_height)
    try:
        Path("spec.yaml").write_text(yaml.safe_dump(raw, sort_keys=False))
        Path("grbl.txt").write_text(GRBL_DUMP)
        code, out, err = _run(["gcode", "spec.yaml", "--json", "--no-progress", *opts])
        tp = Path("toolpaths")
        files = {f"{name}.ngc": (tp / f"{name}.ngc").read_text(),
                 f"{name}.setup.md": (tp / f"{name}.setup.md").read_text(),
                 f"{name}.setup.json": json.dumps(strip_volatile(json.loads((tp / f"{name}.setup.json").read_text())),
                                                  indent=1) + "\n",
                 f"{name}.summary.json": json.dumps({"exit": code, "stderr": err.strip().splitlines(),
                                                     "payload": strip_volatile(json.loads(out))}, indent=1) + "\n",
                 f"{name}.preview.sha256": hashlib.sha256((tp / f"{name}.preview.png").read_bytes()).hexdigest()
                 + "\n"}
    finally:
        os.chdir(old)
        if undo is not None:
            raster.plan_toolpath = undo
    return files


def golden(fname: str) -> str:
    """A reference file's text (programs are stored gzip-compressed)."""
    if fname.endswith(".ngc"):
        return gzip.decompress((GOLDEN / (fname + ".gz")).read_bytes()).decode()
    return (GOLDEN / fname).read_text()


def _store(fname: str, text: str) -> None:
    if fname.endswith(".ngc"):
        (GOLDEN / (fname + ".gz")).write_bytes(gzip.compress(text.encode(), compresslevel=9, mtime=0))
    else:
        (GOLDEN / fname).write_text(text)


def report_sheet(folder: Path) -> str:
    """The setup sheet and verification of ``fabkit report``'s toolpath (small spec, grbl machine)."""
    from fabkit.commands.report import _toolpath
    from fabkit.machine.profile import load_machine
    from fabkit.spec import load_spec
    from fabkit.surface import Surface

    spec_path = folder / "report_spec.yaml"
    spec_path.write_text(yaml.safe_dump({**_small(dialect="grbl"), "name": "report_small"}, sort_keys=False))
    (folder / "grbl.txt").write_text(GRBL_DUMP)
    old = os.getcwd()
    os.chdir(folder)
    try:
        spec = load_spec("report_spec.yaml")
        tool = _toolpath(spec, Surface.from_spec(spec), load_machine("grbl.txt"))
    finally:
        os.chdir(old)
    doc = {"sheet": strip_volatile(tool["sheet"]), "verify": tool["verify"],
           "preview_sha256": hashlib.sha256(tool["png"]).hexdigest()}
    return json.dumps(doc, indent=1, default=float) + "\n"


SLOW = ("surface_coarse", "clipped_coarse", "bowl_coarse")     # 15-40 s each on a loaded 2-core machine


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW else n
                                  for n in sorted(CASES)])
def test_gcode_outputs_unchanged(name, tmp_path, monkeypatch):
    monkeypatch.delenv("SOURCE_DATE_EPOCH", raising=False)
    got = produce(name, tmp_path)
    for fname, text in got.items():
        ref = golden(fname)
        assert text == ref, f"{fname} differs from the output of the code before the refactor"


def test_report_toolpath_sheet_unchanged(tmp_path):
    assert report_sheet(tmp_path) == (GOLDEN / "report_small.json").read_text()


def test_bad_fixtures_refused_unchanged(tmp_path, monkeypatch):
    """Every bad-input fixture: the same exit code and the same one line, nothing written."""
    with monkeypatch.context() as m:
        m.chdir(HERE.parent)
        got = {}
        for p in sorted((HERE / "fixtures" / "bad").glob("*.yaml")):
            code, out, err = _run(["gcode", str(p.relative_to(HERE.parent)), "-o", str(tmp_path / "x.ngc"),
                                   "--no-progress"])
            got[p.name] = [code, err.strip().replace(str(tmp_path), "TMP")]
    assert not any(tmp_path.iterdir())
    assert json.dumps(got, indent=1) + "\n" == (GOLDEN / "bad_fixtures.json").read_text()


def _write_all(names) -> None:
    import tempfile

    GOLDEN.mkdir(parents=True, exist_ok=True)
    os.environ.pop("SOURCE_DATE_EPOCH", None)
    for name in names:
        with tempfile.TemporaryDirectory() as d:
            for fname, text in produce(name, Path(d)).items():
                _store(fname, text)
        print("wrote", name)
    with tempfile.TemporaryDirectory() as d:
        (GOLDEN / "report_small.json").write_text(report_sheet(Path(d)))
    with tempfile.TemporaryDirectory() as d:
        old = os.getcwd()
        os.chdir(HERE.parent)
        got = {}
        for p in sorted((HERE / "fixtures" / "bad").glob("*.yaml")):
            code, out, err = _run(["gcode", str(p.relative_to(HERE.parent)), "-o", str(Path(d) / "x.ngc"),
                                   "--no-progress"])
            got[p.name] = [code, err.strip().replace(d, "TMP")]
        os.chdir(old)
        (GOLDEN / "bad_fixtures.json").write_text(json.dumps(got, indent=1) + "\n")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--write"]:
        _write_all(sys.argv[2:] or sorted(CASES))
    else:
        print(__doc__)
