"""``fabkit stl`` through main(argv): output file, summary, JSON, formats,
refusals with nothing written, byte-identical reruns."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import SPECS, mutated, write_spec

BOWL = SPECS / "bowl.yaml"


def stl_volume(data: bytes) -> float:
    """Signed volume of a binary STL read with numpy (independent of fabkit's writer)."""
    n = int(np.frombuffer(data, "<u4", 1, 80)[0])
    rec = np.frombuffer(data, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), n, 84)
    v = rec["v"].astype(float)
    assert len(data) == 84 + 50 * n
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6)


def test_writes_default_path_and_summary(cli, tmp_path):
    code, out, err = cli("stl", BOWL, "--tolerance", "0.05")
    assert code == 0, err
    path = tmp_path / "toolpaths" / "bowl.stl"
    assert path.exists()
    assert out.startswith("stl: toolpaths/bowl.stl, ")
    for word in ("triangles", "volume", "mm^3", "largest deviation", "tolerance 0.05", "checked at", " s"):
        assert word in out
    data = path.read_bytes()
    n = int(np.frombuffer(data, "<u4", 1, 80)[0])
    assert f"{n} triangles" in out
    # the stock box minus the cut: the STL's own volume is below the box and close to the report
    assert 0 < stl_volume(data) < 160 * 100 * 50


def test_json_keys_and_values(cli, tmp_path):
    code, out, err = cli("stl", BOWL, "--tolerance", "0.05", "--json", "-o", "m.stl")
    assert code == 0, err
    d = json.loads(out)
    assert set(d) == {"path", "triangles", "volume_mm3", "max_deviation_mm", "tolerance_mm", "checked_points",
                      "seconds", "watertight"}
    assert d["path"] == "m.stl" and d["watertight"] is True
    assert 0 < d["max_deviation_mm"] <= d["tolerance_mm"] == 0.05
    assert d["volume_mm3"] == pytest.approx(stl_volume((tmp_path / "m.stl").read_bytes()), rel=1e-6)


@pytest.mark.parametrize("ext", ["ply", "obj", "glb"])
def test_other_formats_by_extension(cli, tmp_path, ext):
    import trimesh

    code, out, err = cli("stl", BOWL, "--tolerance", "0.1", "-o", f"block.{ext}", "--json")
    assert code == 0, err
    d = json.loads(out)
    mesh = trimesh.load(tmp_path / f"block.{ext}", force="mesh")
    assert len(mesh.faces) == d["triangles"]
    assert mesh.volume == pytest.approx(d["volume_mm3"], rel=1e-6)


def test_two_runs_byte_identical(cli, tmp_path):
    assert cli("stl", BOWL, "--tolerance", "0.05", "-o", "a.stl")[0] == 0
    assert cli("stl", BOWL, "--tolerance", "0.05", "-o", "b.stl")[0] == 0
    assert (tmp_path / "a.stl").read_bytes() == (tmp_path / "b.stl").read_bytes()


def test_needs_only_surface_and_stock(cli, tmp_path):
    raw = mutated({}, drop=("tool", "machining", "ball", "ramp", "simulation"))
    spec = write_spec(tmp_path, raw)
    code, out, err = cli("stl", spec, "--tolerance", "0.1")
    assert code == 0, err
    assert (tmp_path / "toolpaths" / "surface.stl").exists()


def test_missing_stock_refused(cli, tmp_path):
    spec = write_spec(tmp_path, mutated({}, drop=("stock",)))
    code, out, err = cli("stl", spec)
    assert code == 2 and "stock" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "toolpaths").exists()


@pytest.mark.parametrize("bad", ["0", "-0.01", "nan", "inf", "1e-9"])
def test_bad_tolerance_exit_2_nothing_written(cli, tmp_path, bad):
    code, out, err = cli("stl", BOWL, "--tolerance", bad)
    assert code == 2
    assert "--tolerance" in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert out == ""
    assert not (tmp_path / "toolpaths").exists()


@pytest.mark.parametrize("key,value", [("stock.depth_limit", 10), ("tool.reach", 20)])
def test_depth_over_limit_exit_2_nothing_written(cli, tmp_path, key, value):
    spec = write_spec(tmp_path, mutated({key: value}))
    code, out, err = cli("stl", spec)
    assert code == 2
    assert key in err and "deep" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "toolpaths").exists()


def test_existing_output_kept_on_refusal(cli, tmp_path):
    target = tmp_path / "keep.stl"
    target.write_bytes(b"previous")
    code, _, err = cli("stl", BOWL, "--tolerance", "-1", "-o", target)
    assert code == 2
    assert target.read_bytes() == b"previous"


def test_unknown_extension_refused(cli, tmp_path):
    code, out, err = cli("stl", BOWL, "-o", "block.xyz2")
    assert code == 2 and "--output" in err
    assert not (tmp_path / "block.xyz2").exists()


def test_volume_matches_paraboloid_closed_form(cli, tmp_path):
    raw = {"name": "dish", "units": "mm",
           "surface": {"height": "(x**2 + y**2)/(2*R)", "params": {"R": 40}, "x": [-30, 30], "y": [-25, 25],
                       "top": 5},
           "stock": {"thickness": 50}}
    spec = write_spec(tmp_path, raw)
    code, out, err = cli("stl", spec, "--json")
    assert code == 0, err
    exact = 60 * 50 * 50 - math.pi * 40 * 25
    assert json.loads(out)["volume_mm3"] == pytest.approx(exact, rel=1e-4)
    assert stl_volume((tmp_path / "toolpaths" / "dish.stl").read_bytes()) == pytest.approx(exact, rel=1e-4)
