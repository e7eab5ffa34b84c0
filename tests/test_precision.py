"""fabkit precision --quick: work-precision rows for the simulator, toolpath and mesh."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fabkit.cli import main
from fabkit.precision import best_time, launch_errors
from conftest import PAPER


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    import contextlib
    import io
    import os

    folder = tmp_path_factory.mktemp("precision")
    png = folder / "precision.png"
    out, err = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["precision", str(PAPER), "--quick", "--json", "--plot", str(png)])
    finally:
        os.chdir(cwd)
    assert code == 0, err.getvalue()
    return json.loads(out.getvalue()), png


def test_simulation_rows(quick):
    data, _ = quick
    rows = data["simulation"]
    methods = {}
    for r in rows:
        assert set(r) >= {"method", "rtol", "error", "seconds"}
        assert math.isfinite(r["error"]) and r["error"] >= 0
        assert math.isfinite(r["seconds"]) and r["seconds"] > 0
        methods.setdefault(r["method"], []).append(r)
    scipy = [m for m in methods if m.startswith("scipy")]
    assert len(methods) >= 3 and len(scipy) >= 2
    for m, rs in methods.items():
        assert len(rs) >= 3, m
        rs = sorted(rs, key=lambda r: -r["rtol"])        # tightening
        errs = [r["error"] for r in rs]
        assert all(r["mismatched"] == 0 for r in rs), m
        # falls as the tolerance tightens (or sits at the reference's floor)
        floor = data["simulation_info"]["reference"]["floor"]
        assert all(b <= a or b <= floor for a, b in zip(errs, errs[1:])), (m, errs)
        assert errs[-1] < errs[0] / 10, (m, errs)
    assert all(data["simulation_info"]["monotone"].values())
    # the errors are measured, not echoed: at rtol 1e-8 fabkit's DOP853 is within 1e-6
    fab = {r["rtol"]: r["error"] for r in methods["fabkit DOP853"]}
    assert fab[1e-8] < 1e-6
    info = data["simulation_info"]
    assert "damping 0" in info["problem"]
    assert set(info["launches"]["kind"]) == {"window", "above"}
    vc = info["launches"]["v_critical"]
    for v, kind in zip(info["launches"]["v_in"], info["launches"]["kind"]):
        assert (v > 1.05 * vc) if kind == "above" else (v < vc)


def test_toolpath_and_mesh_rows(quick):
    data, png = quick
    assert len(data["toolpath"]) >= 3 and len(data["mesh"]) >= 3
    for r in data["toolpath"]:
        assert set(r) >= {"tolerance", "max_deviation", "seconds", "lines"}
        assert 0 <= r["max_deviation"] <= r["tolerance"], r
        assert r["lines"] > 0 and r["seconds"] > 0
    lines = [r["lines"] for r in sorted(data["toolpath"], key=lambda r: -r["tolerance"])]
    assert lines == sorted(lines)                       # tighter: longer programs
    for r in data["mesh"]:
        assert set(r) >= {"tolerance", "max_deviation", "seconds", "triangles"}
        assert 0 <= r["max_deviation"] <= r["tolerance"], r
    tris = [r["triangles"] for r in sorted(data["mesh"], key=lambda r: -r["tolerance"])]
    assert tris == sorted(tris)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert data["seconds"] > 0


def test_launch_errors_counts_mismatches():
    ref = [{"outcome": 0, "bounces": 2, "v_out": 10.0, "bounce_times": np.array([1.0, 2.0])}]
    same = [{"outcome": 0, "bounces": 2, "v_out": 10.001, "bounce_times": np.array([1.0, 2.002])}]
    err, mis = launch_errors(same, ref)
    assert mis == 0 and err == pytest.approx(1e-3)
    other = [{"outcome": 0, "bounces": 3, "v_out": 10.0, "bounce_times": np.array([1.0, 2.0, 3.0])}]
    assert launch_errors(other, ref) == (1.0, 1)


def test_best_time_stops_on_budget():
    calls = []
    t, out = best_time(lambda: calls.append(1) or len(calls), repeats=5, budget=0.0)
    assert len(calls) == 1 and out == 1 and t >= 0
    t, out = best_time(lambda: calls.append(1) or len(calls), repeats=3, budget=10.0)
    assert out == 4
