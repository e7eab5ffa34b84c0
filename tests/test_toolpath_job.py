"""The toolpath job written once (fabkit/toolpath/job.py): ``fabkit precision`` and
``fabkit gcode`` report the same gouge and material left for the same spec and program
(the drift test), the verdict travels with the result, and the typed cut report keeps
verify_cut's keys."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from conftest import SPECS, write_spec


def _bowl_tile_raw() -> tuple[dict, dict]:
    """specs/bowl.yaml as ``fabkit precision --quick`` studies it: its 14 x 8 mm tile around
    the lowest point, scallop 0.2 mm, 4000 check points (the tile precision computes)."""
    from fabkit import precision as P
    from fabkit.spec import load_spec

    raw = yaml.safe_load((SPECS / "bowl.yaml").read_text())
    for section in ("ball", "ramp", "simulation"):     # no simulation study: the toolpath rows only
        raw.pop(section)
    return raw, P.tile_spec(load_spec(SPECS / "bowl.yaml"), P.QUICK["tile"]).raw


def test_precision_and_gcode_report_the_same_cut(cli, tmp_path):
    """The drift test: for every tolerance of ``precision --quick``, ``gcode`` on the same
    spec writes a program whose verified gouge, material left, lines and passes are the
    precision row's (before the job was written once, precision verified with other
    arguments and without the added passes)."""
    raw, tile = _bowl_tile_raw()
    spec = write_spec(tmp_path, raw, "bowl_nosim.yaml")
    code, out, err = cli("precision", spec, "--quick", "--json", "--no-progress")
    assert code == 0, err
    rows = json.loads(out)["toolpath"]
    assert [r["tolerance"] for r in rows] == [0.1, 0.05, 0.02, 0.01]
    for r in rows[2:]:                                 # two tolerances keep the test short
        t = yaml.safe_load(yaml.safe_dump(tile))
        for section in ("ball", "ramp", "simulation"):
            t.pop(section, None)
        t["machining"]["tolerance"] = r["tolerance"]
        one = write_spec(tmp_path, t, f"tile_{r['tolerance']:g}.yaml")
        code, out, err = cli("gcode", one, "-o", tmp_path / f"t{r['tolerance']:g}.ngc", "--json",
                             "--no-progress")
        assert code == 0, err
        g = json.loads(out)
        k = 25.4 if g["units"] == "in" else 1.0        # the sheet is in program units, 9 digits
        assert g["max_gouge"] * k == pytest.approx(r["max_deviation"], rel=1e-8, abs=1e-12)
        assert g["max_material_left"] * k == pytest.approx(r["material_left"], rel=1e-8, abs=1e-12)
        assert (g["lines"], g["passes"], g["verification_points"]) == (r["lines"], r["passes"],
                                                                       r["checked_points"])
        assert g["ok"] is r["ok"]


def _cut(**over):
    from fabkit.toolpath.job import CutReport

    base = dict(max_gouge=0.0, gouge_at=(1.0, 2.0), max_material_left=0.0, material_at=(3.0, 4.0),
                material_left_measure="normal", max_material_left_normal=0.0,
                material_left_normal_at=(3.0, 4.0), max_material_left_vertical=0.0,
                material_left_vertical_at=(3.0, 4.0), checked_points=100, max_material_above_design=0.0,
                material_above_design_at=(0.0, 0.0), unreachable=None, rapid_clearance=np.inf,
                rapid_clearance_at=None, rapids_checked=0, deepest_cut=1.0, depth_ok=True,
                first_move_ok=True, segments=10)
    base.update(over)
    return CutReport(**base)


class M:            # a machining section: tolerance 0.01 mm, scallop 0.05 mm
    tolerance, scallop = 0.01, 0.05


def test_cut_verdict_rules():
    """Each acceptance rule at its threshold: equal passes, just above fails."""
    assert _cut(max_gouge=0.01, max_material_left=0.06, rapid_clearance=-0.01).failures(M) == []
    bad = _cut(max_gouge=0.0125).failures(M)
    assert bad == ["gouge 0.0125 mm > tolerance 0.01 mm at X1.000 Y2.000"]
    bad = _cut(max_material_left=0.0625).failures(M)
    assert bad == ["material left 0.0625 mm > scallop + tolerance 0.06 mm at X3.000 Y4.000"]
    assert _cut(max_material_left=0.0625).only_material_left(M)
    assert not _cut(max_material_left=0.0625, max_gouge=0.02).only_material_left(M)
    bad = _cut(rapid_clearance=-0.5, rapid_clearance_at=(5.0, 6.0)).failures(M)
    assert bad == ["a rapid passes 0.5000 mm into material at X5.000 Y6.000"]
    assert "exceeds the depth limit" in _cut(depth_ok=False).failures(M)[0]
    assert "does not start with a rapid" in _cut(first_move_ok=False).failures(M)[0]


def test_job_result_carries_the_verdict():
    from fabkit.toolpath.job import JobResult

    class Spec:
        machining = M

    def job(cut):
        return JobResult(spec=Spec(), surface=None, toolpath=None, profile=None, text="G0 Z5\nM2\n",
                         program=None, cut=cut, estimate_s=0.0, sheet={}, timings={})

    good, bad, unverified = job(_cut()), job(_cut(max_gouge=0.1)), job(None)
    assert good.ok and good.failures == [] and good.message == "verified: within tolerance"
    assert not bad.ok and bad.message == "verification failed: gouge 0.1000 mm > tolerance 0.01 mm at X1.000 Y2.000"
    assert unverified.ok and not unverified.verified and unverified.message == "not verified"
    assert good.lines == 2


def test_cut_report_keeps_verify_cut_keys():
    """A flat floor 1 mm down cut 0.1 mm too deep by one straight pass: the typed report
    gives verify_cut's keys unchanged, and its gouge is the closed form 0.1 mm."""
    from fabkit.expr import compile_surface
    from fabkit.surface import Surface
    from fabkit.toolpath.job import CutReport
    from fabkit.toolpath.program.reader import read_program
    from fabkit.toolpath.cut.verify import verify_cut

    surface = Surface(compile_surface("-1 + 0*x", {}), (0, 10), (0, 4), 0.0, 1.0)
    R = 1.0
    text = "G21 G90\nG0 Z5\nG0 X-2 Y2\nG1 Z-1.1 F100\nG1 X12 F500\nG0 Z5\nM2\n"
    raw = verify_cut(surface, read_program(text), R, 2000, over=0.05)
    cut = CutReport.from_dict(raw)
    js = cut.to_json()
    assert list(js) == list(raw)
    json.dumps(js)                                     # JSON-ready
    assert 0.1 - 1e-3 < cut.max_gouge <= 0.1 + 1e-9
    assert cut.as_dict()["over_at"] is raw["over_at"]


def test_precision_row_is_the_program_gcode_writes_after_added_passes(cli, tmp_path):
    """Where the first verified cut leaves too much (two V creases crossing: 0.085 mm left
    where the crease meets the stock edge, 0.06 allowed), gcode adds passes; the precision
    row is that program's (before: 40 passes, 1334 lines, 0.0848 mm left, a program gcode
    never writes; now 60 passes, 1996 lines, 0.0459 mm, as gcode's)."""
    from fabkit.precision import toolpath_study
    from fabkit.spec import load_spec
    from test_surface_family import _raw

    spec = write_spec(tmp_path, _raw("3*abs(x) + 2*abs(y) - 20", (-8, 8), (-6, 6), "x", "mm"))
    code, out, err = cli("gcode", spec, "--json", "--no-progress")
    assert code == 0, err
    g = json.loads(out)
    assert g["passes_added_after_verification"] > 0 and g["units"] == "mm"
    (row,) = toolpath_study(load_spec(spec), (g["tolerance"],))
    assert row["max_deviation"] == pytest.approx(g["max_gouge"], rel=1e-8)
    assert row["material_left"] == pytest.approx(g["max_material_left"], rel=1e-8)
    assert row["material_left"] <= g["scallop"] + g["tolerance"]
    assert (row["lines"], row["passes"]) == (g["lines"], g["passes"])
