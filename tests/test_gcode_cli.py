"""``fabkit gcode`` end to end: exit codes, nothing written on bad input, atomic
outputs, determinism, the setup sheet's transform, and full runs of the shipped
specs read by LinuxCNC's interpreter."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from fabkit.expr import compile_surface
from fabkit.surface import Surface
from fabkit.toolpath.finish.compensate import compensate
from fabkit.toolpath.path import CUT, PLUNGE, RAPID, Toolpath
from fabkit.toolpath.program.reader import read_program

from conftest import SPECS, write_spec

RS274 = shutil.which("rs274")

# a 60 x 40 mm elliptic bowl in mm design units: h = x^2/80 + y^2/60 - 8, top 0
BOWL = {"height": "x**2/(2*rx) + y**2/(2*ry) - d", "params": {"rx": 40.0, "ry": 30.0, "d": 8.0},
        "x": [-30, 30], "y": [-20, 20], "top": 0.0}


def small_raw(**machining):
    m = {"scallop": 0.1, "tolerance": 0.02, "verify_points": 4000, "feed": 1200, "plunge": 300,
         "safe_height": 3}
    m.update(machining)
    return {"name": "small", "units": "mm", "surface": dict(BOWL),
            "stock": {"thickness": 20, "depth_limit": 15},
            "tool": {"shape": "ball", "diameter": 6, "reach": 25}, "machining": m}


def bowl_surface():
    return Surface(compile_surface(BOWL["height"], BOWL["params"]), BOWL["x"], BOWL["y"], BOWL["top"], 1.0)


def simple_plan(surface, R, scallop, spacing=0.25, dz=0.0, safe_z=3.0):
    """A deliberately plain planner for tests: rows along x every 0.6 x the flat-ground
    stepover, exact drop-cutter heights every ``spacing`` mm, rows joined along the
    edges on the compensated surface (one continuous cut). ``dz`` shifts every cut."""
    L, W = surface.stock_size_mm
    s = 0.6 * 2 * np.sqrt(2 * R * scallop - scallop ** 2)
    ys = np.linspace(0, W, int(np.ceil(W / s)) + 1)
    xs = np.linspace(0, L, int(np.ceil(L / spacing)) + 1)
    rows = []
    for i, y in enumerate(ys):
        row = np.column_stack([xs, np.full_like(xs, y)])
        if i % 2:
            row = row[::-1]
        if i:
            xe = rows[-1][-1, 0]
            yl = np.linspace(ys[i - 1], y, max(2, int(np.ceil((y - ys[i - 1]) / spacing)) + 1))[1:-1]
            rows.append(np.column_stack([np.full_like(yl, xe), yl]))
        rows.append(row)
    xy = np.vstack(rows)
    z = compensate(surface, xy[:, 0], xy[:, 1], R) + dz
    pts = np.vstack([[xy[0, 0], xy[0, 1], z[0] + 1.0], np.column_stack([xy, z]),
                     [xy[-1, 0], xy[-1, 1], safe_z]])
    kinds = np.r_[RAPID, PLUNGE, np.full(len(xy) - 1, CUT), RAPID]
    return Toolpath(pts, kinds, tool_radius=R, safe_z=safe_z, passes=len(ys), stepover=float(ys[1] - ys[0]),
                    stepover_min=float(ys[1] - ys[0]))


@pytest.fixture
def plain_planner(monkeypatch):
    """Replace the production planner by :func:`simple_plan` (``dz`` settable)."""
    import fabkit.toolpath.finish.raster as raster

    opts = {"dz": 0.0}

    def plan(spec, surface, *a, **k):
        return simple_plan(surface, spec.tool.diameter / 2, spec.machining.scallop, dz=opts["dz"],
                           safe_z=spec.machining.safe_height)

    monkeypatch.setattr(raster, "plan_toolpath", plan)
    return opts


def test_writes_program_and_sheet_with_exit_0(cli, tmp_path, plain_planner):
    spec = write_spec(tmp_path, small_raw(units="in", dialect="grbl"))
    code, out, err = cli("gcode", spec, "--json")
    assert code == 0, err
    summary = json.loads(out)
    prog = tmp_path / "toolpaths" / "small.ngc"
    sheet = json.loads((tmp_path / "toolpaths" / "small.setup.json").read_text())
    assert (tmp_path / "toolpaths" / "small.setup.md").exists()
    assert (tmp_path / "toolpaths" / "small.preview.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for key in ("units", "stock", "tool", "design_to_work", "passes", "stepover", "estimated_time_s",
                "max_gouge", "max_material_left"):
        assert key in sheet and key in summary
    assert sheet["units"] == "in"
    # stock box in inches
    np.testing.assert_allclose(sheet["stock"]["min"], [0, 0, -20 / 25.4], rtol=1e-6)
    np.testing.assert_allclose(sheet["stock"]["max"], [60 / 25.4, 40 / 25.4, 0], rtol=1e-6)
    assert sheet["tool"] == {"shape": "ball", "diameter": pytest.approx(6 / 25.4, rel=1e-6),
                             "reach": pytest.approx(25 / 25.4, rel=1e-6)}
    # the transform takes the design's lowest point (0, 0, -8) to the program's
    # deepest tip position (the bowl is wider than the tool: the tip touches there)
    sc, off = np.array(sheet["design_to_work"]["scale"]), np.array(sheet["design_to_work"]["offset"])
    low = sc * np.array([0.0, 0.0, -8.0]) + off
    text = prog.read_text()
    p = read_program(text)
    feed = p.points[p.kinds == 1] / 25.4
    k = np.argmin(feed[:, 2])
    assert feed[k, 2] == pytest.approx(low[2], abs=(0.02 + 2e-4) / 25.4)
    assert abs(feed[k, 0] - low[0]) < 0.3 / 25.4 and abs(feed[k, 1] - low[1]) < 1.0 / 25.4
    # corners of the footprint map onto the stock box
    np.testing.assert_allclose(sc * np.array([-30, -20, 0]) + off, [0, 0, 0], atol=1e-9)
    np.testing.assert_allclose(sc * np.array([30, 20, 0]) + off, sheet["stock"]["max"], rtol=1e-6)
    assert sheet["max_gouge"] <= 0.02 / 25.4 and sheet["max_material_left"] <= 0.12 / 25.4
    assert summary["ok"] is True and summary["verification_points"] >= 4000


def test_verification_failure_exits_1_and_keeps_outputs(cli, tmp_path, plain_planner):
    plain_planner["dz"] = -0.1
    spec = write_spec(tmp_path, small_raw())
    code, out, err = cli("gcode", spec)
    assert code == 1
    assert "gouge 0.1" in err and "for inspection" in err
    assert (tmp_path / "toolpaths" / "small.ngc").exists()
    assert "largest gouge 0.1" in out


@pytest.mark.parametrize("raw, key", [
    ({k: v for k, v in small_raw().items() if k != "machining"}, "machining"),
    ({**small_raw(), "tool": {"diameter": -3}}, "tool.diameter"),
    ({**small_raw(), "stock": {"thickness": 20, "depth_limit": 5}}, "stock.depth_limit"),
    ({**small_raw(), "tool": {"diameter": 6, "reach": 4}}, "tool.reach"),
])
def test_bad_input_exits_2_and_writes_nothing(cli, tmp_path, raw, key, plain_planner):
    spec = write_spec(tmp_path, raw)
    code, out, err = cli("gcode", spec)
    assert code == 2
    assert key in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "toolpaths").exists()


def test_interrupted_run_leaves_previous_program_intact(cli, tmp_path, plain_planner, monkeypatch):
    import fabkit.toolpath.cut.verify as verify

    spec = write_spec(tmp_path, small_raw())
    old = tmp_path / "keep.ngc"
    old.write_text("(previous program)\nM2\n")

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(verify, "verify_cut", boom)
    code, out, err = cli("gcode", spec, "-o", old)
    assert code == 130
    assert old.read_text() == "(previous program)\nM2\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.ngc", "spec.yaml"]


def test_output_path_is_a_folder(cli, tmp_path, plain_planner):
    spec = write_spec(tmp_path, small_raw())
    (tmp_path / "dir.ngc").mkdir()
    code, out, err = cli("gcode", spec, "-o", tmp_path / "dir.ngc")
    assert code == 2 and "folder" in err
    assert list((tmp_path / "dir.ngc").iterdir()) == []


# ----------------------------------------------------------------------------
# with the production planner
# ----------------------------------------------------------------------------
def _rs274_ok(path):
    run = subprocess.run([RS274, "-g", str(path)], stdin=subprocess.DEVNULL, capture_output=True,
                         text=True, timeout=300)
    return run.returncode, run.stderr.strip()


def test_same_spec_gives_identical_program(cli, tmp_path):
    spec = write_spec(tmp_path, small_raw())
    assert cli("gcode", spec, "-o", "a.ngc", "--no-verify")[0] == 0
    assert cli("gcode", spec, "-o", "b.ngc", "--no-verify")[0] == 0
    assert (tmp_path / "a.ngc").read_bytes() == (tmp_path / "b.ngc").read_bytes()


@pytest.mark.parametrize("name", ["surface", "bowl"])
def test_shipped_specs_full_run(cli, tmp_path, name):
    code, out, err = cli("gcode", SPECS / f"{name}.yaml", "--json")
    assert code == 0, err
    s = json.loads(out)
    prog = tmp_path / "toolpaths" / f"{name}.ngc"
    k = 25.4 if s["units"] == "in" else 1.0
    assert s["max_gouge"] * k <= 0.01 and s["max_material_left"] * k <= 0.06
    assert s["verification_points"] >= 40000
    # null: no rapid goes below the top face; else the smallest clearance over material
    assert s["rapid_clearance"] is None or s["rapid_clearance"] >= -0.01 / k
    assert s["depth"] * k <= min(s["depth_limit"] * k, s["tool"]["reach"] * k) + 1e-9
    if RS274:
        rc, err = _rs274_ok(prog)
        assert rc == 0 and err in ("", "executing"), err
