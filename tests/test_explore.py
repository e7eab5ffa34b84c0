"""fabkit explore (issue 7): design grids over spec keys, in-process and on a Dask cluster.

The designs are the paper's formula with loose integrator tolerances, a 30 s
time limit and eight ramp heights, so a design takes a second or two. Answers
are checked against independent computations: a direct ``sweep`` of the
overridden spec, ``check`` for the highest safe height, and the in-process run
for the Dask run (bit for bit).
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys

import numpy as np
import pytest

from conftest import SMALL_STUDY, mutated, run_cli, run_study, small_study_spec, write_spec
from fabkit.errors import SpecError
from fabkit.explore import (Engine, design_grid, design_of, parse_vary, problem_of, run_chunk, table_bytes,
                            table_format)
from fabkit.physics.integrate import launch_batch
from fabkit.physics.models import problem_from_spec
from fabkit.physics.sweep import sweep
from fabkit.spec import validate

SMALL = SMALL_STUDY
EPS = ["--vary", "surface.params.eps=0.24:0.26:2", "--v-in", "30", "80", "16", "--no-progress"]


small_spec = small_study_spec


@pytest.fixture(scope="module")
def small_path(tmp_path_factory):
    return write_spec(tmp_path_factory.mktemp("explore"), mutated(SMALL), "small.yaml")


@pytest.fixture(scope="module")
def inprocess(small_path):
    """The in-process run, with its per-launch rows and plot (read by the tests below)."""
    return run_study("explore", small_path, EPS, "grid.png")


# ----------------------------------------------------------------------------
# --vary
# ----------------------------------------------------------------------------
def test_parse_vary_forms():
    spec = small_spec()
    assert parse_vary("surface.params.eps=0.1:0.4:4", spec).values == pytest.approx((0.1, 0.2, 0.3, 0.4))
    assert parse_vary(" surface.top = 5:5:1", spec).values == (5.0,)
    assert parse_vary("simulation.damping=0,0.127", spec).values == (0.0, 0.127)
    assert parse_vary("simulation.model=full,simplified", spec).values == ("full", "simplified")
    assert parse_vary("ramp.samples=10:30:3", spec).values == (10, 20, 30)
    grid = design_grid([parse_vary("surface.top=4,5", spec), parse_vary("simulation.damping=0,1", spec)])
    assert grid == [{"surface.top": 4.0, "simulation.damping": 0.0}, {"surface.top": 4.0, "simulation.damping": 1.0},
                    {"surface.top": 5.0, "simulation.damping": 0.0}, {"surface.top": 5.0, "simulation.damping": 1.0}]
    assert design_grid([]) == [{}]


@pytest.mark.parametrize("text,needle", [
    ("surface.params.eps", "expected KEY=LO:HI:N"),
    ("surface.parms.eps=1:2:2", "unknown key"),
    ("simulation.dampng=0:1:2", "did you mean 'simulation.damping'"),
    ("surface.params.epz=0:1:2", "did you mean 'surface.params.eps'"),
    ("surface.params.eps=0.1:0.4:2.5", "N must be a whole number"),
    ("surface.params.eps=0.1:0.4:0", "N must be a whole number"),
    ("surface.params.eps=0.4:0.1:3", "LO < HI"),
    ("surface.params.eps=0.1:0.4", "expected LO:HI:N"),
    ("surface.params.eps=a:0.4:3", "LO must be a number"),
    ("surface.params.eps=nan:0.4:3", "LO must be finite"),
    ("surface.params.eps=0.1:0.4:1", "N = 1 needs LO = HI"),
    ("surface.params.eps=", "no values"),
    ("surface.x=0:1:2", "not a number or choice key"),
    ("ramp.samples=10:20:4", "whole number"),
    ("simulation.model=0:1:2", "choice key takes a list"),
    ("surface.top=4,4", "repeated values"),
])
def test_parse_vary_errors_name_the_flag(text, needle):
    with pytest.raises(SpecError) as e:
        parse_vary(text, small_spec())
    assert e.value.key == "--vary" and needle in str(e.value)


def test_vary_in_a_missing_section():
    spec = validate(mutated(SMALL, drop=("stock",)), "nostock.yaml")
    with pytest.raises(SpecError, match="no stock section"):
        parse_vary("stock.thickness=50,60", spec)


def test_duplicate_key_and_grid_guard():
    spec = small_spec()
    v = parse_vary("surface.top=4,5", spec)
    with pytest.raises(SpecError, match="varied twice"):
        design_grid([v, v])
    big = [parse_vary(f"{k}=1:2:101", spec) for k in ("surface.top", "simulation.damping")]
    with pytest.raises(SpecError, match="limit"):
        design_grid(big)


@pytest.mark.parametrize("extra,needle", [
    (["--vary", "surface.params.epz=0:1:2"], "did you mean"),
    (["--vary", "surface.params.eps=0:1:x"], "N must be a number"),
    (["--vary", "simulation.y0=20,30"], "no valid design"),                # every design invalid
    (["--vary", "surface.params.eps=0.2,0.3", "--out", "rows.txt"], "--out"),
    (["--vary", "surface.params.eps=0.2,0.3", "--scheduler", "not an address"], "--scheduler"),
    (["--vary", "surface.params.eps=0.2,0.3", "--v-in", "80", "30", "4"], "--v-in"),
])
def test_bad_input_exit_2_one_line_nothing_written(cli, tmp_path, extra, needle):
    spec = write_spec(tmp_path, mutated(SMALL))
    argv = ["explore", spec, "--v-in", "30", "80", "4", "--no-progress", *extra, "--plot", "p.png"]
    if "--out" not in extra:
        argv += ["--out", "rows.csv"]
    code, out, err = cli(*argv)
    assert code == 2 and needle in err and err.count("\n") == 1 and out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]


def test_parquet_without_pyarrow_names_out(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyarrow", None)          # as if not installed
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    with pytest.raises(SpecError) as e:
        table_format("rows.parquet")
    assert e.value.key == "--out" and "pyarrow" in str(e.value)


def test_parquet_rows_round_trip():
    pq = pytest.importorskip("pyarrow.parquet")
    assert table_format("rows.parquet") == "parquet"
    t = pq.read_table(io.BytesIO(table_bytes({"a": [1.5, float("nan")], "b": ["x", "y"]}, "parquet")))
    assert t.column("b").to_pylist() == ["x", "y"]
    a = t.column("a").to_pylist()
    assert a[0] == 1.5 and (a[1] is None or math.isnan(a[1]))


# ----------------------------------------------------------------------------
# answers
# ----------------------------------------------------------------------------
def test_two_designs_match_direct_sweeps(inprocess):
    designs = inprocess["designs"]
    assert [d["params"] for d in designs] == [{"surface.params.eps": 0.24}, {"surface.params.eps": 0.26}]
    assert designs[0]["v_critical"] != designs[1]["v_critical"]
    for d in designs:
        spec = small_spec().with_overrides(d["params"])
        ref = sweep(problem_from_spec(spec), np.linspace(30, 80, 16), error_samples=0, tn=False)  # bisection, as explore
        assert d["v_critical"] == ref["v_critical"]      # the same launches, so exactly
        assert d["v_critical_error"] == ref["v_critical_error"] <= 1e-6 * d["v_critical"]
        assert [(w["bounces"], w["lo"], w["hi"]) for w in d["windows"]] == \
            [(w["bounces"], w["lo"], w["hi"]) for w in ref["windows"]]
        assert d["safe"] is True and d["highest_safe_height"] == 4.5 and d["depth_ok"] is True
        assert d["safe_over"] == "ramp"


def test_highest_safe_height_matches_check_and_invalid_design_is_reported(cli, tmp_path):
    from fabkit import units
    from fabkit.physics.calibrate import ball_k, ramp_heights, v_in_from_height
    from fabkit.physics.check import check

    spec = write_spec(tmp_path, mutated(SMALL))
    # --v-in above v_critical: no refinement, so the run is about the ramp and the grid's errors
    code, out, err = cli("explore", spec, "--vary", "surface.top=2,5", "--vary", "simulation.y0=0,20",
                         "--v-in", "60", "80", "3", "--json", "--no-progress")
    assert code == 0, err
    designs = json.loads(out)["designs"]
    assert len(designs) == 4
    bad = [d for d in designs if "error" in d]
    assert [d["params"]["simulation.y0"] for d in bad] == [20.0, 20.0]
    assert all("simulation.y0" in d["error"] and d["safe"] is None and d["v_critical"] is None for d in bad)
    clipped, paper = [d for d in designs if "error" not in d]
    # the check's own path: the ramp launched by launch_batch, the boundary by fabkit check
    s2 = small_spec().with_overrides({"surface.top": 2.0})
    p2 = problem_from_spec(s2)
    g, k = units.gravity(s2.units), ball_k(s2)
    H = np.sort(ramp_heights(s2))
    r = launch_batch(p2, v_in_from_height(H, g, k))
    i = int(np.flatnonzero(r.outcome == 2)[0])                     # flew_off
    assert clipped["safe"] is False and clipped["first_failure"]["height"] == H[i]
    assert clipped["first_failure"]["outcome"] == "flew_off"
    assert clipped["highest_safe_height"] == check(s2).highest_safe_height
    assert 1.5 <= clipped["highest_safe_height"] < H[i]             # undamped energy bound: top - margin
    assert paper["safe"] is True and paper["highest_safe_height"] == 4.5


def test_unmachinable_design_is_unsafe(cli, tmp_path):
    spec = write_spec(tmp_path, mutated(SMALL))
    code, out, err = cli("explore", spec, "--vary", "stock.depth_limit=40,60", "--v-in", "60", "80", "3",
                         "--json", "--no-progress")
    assert code == 0, err
    shallow, deep = json.loads(out)["designs"]
    assert shallow["depth_ok"] is False and shallow["safe"] is False
    assert deep["depth_ok"] is True and deep["safe"] is True
    assert shallow["depth_mm"] == pytest.approx(deep["depth_mm"]) and 40 < deep["depth_mm"] < 60


def test_out_csv_rows_and_plot(inprocess, small_path):
    folder = inprocess["folder"]
    rows = list(csv.DictReader((folder / "rows.csv").open()))
    assert len(rows) == 2 * 16
    assert set(rows[0]) == {"design", "surface.params.eps", "v_in", "outcome", "bounces", "v_out"}
    assert [float(r["v_in"]) for r in rows[:16]] == list(np.linspace(30, 80, 16))
    assert [r["design"] for r in rows] == ["0"] * 16 + ["1"] * 16
    assert [float(r["surface.params.eps"]) for r in rows[::16]] == [0.24, 0.26]
    escaped = [r for r in rows if r["outcome"] == "escaped"]
    assert escaped and all(float(r["v_out"]) > 0 for r in escaped)
    assert all(r["v_out"] == "" for r in rows if r["outcome"] != "escaped")
    assert (folder / "grid.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_summary_states_time_and_accuracy(cli, tmp_path):
    spec = write_spec(tmp_path, mutated(SMALL))
    # above v_critical every launch escapes after one bounce: no refinement, a fast run
    code, out, err = cli("explore", spec, "--vary", "surface.params.eps=0.25", "--v-in", "60", "80", "3",
                         "--no-progress")
    assert code == 0, err
    assert "1 designs (0 invalid)" in out and "in-process" in out and "1e-6 relative" in out
    assert "v_critical none (every launch escapes after one bounce" in out and " s\n" in out


def test_chunked_launches_are_bitwise_equal_to_one_batch():
    """What the cluster relies on: a launch's result does not depend on its chunk."""
    spec = small_spec()
    d = design_of(spec)
    rng = np.random.default_rng(3)
    v = np.linspace(30, 80, 40)
    y0, vy0 = 0.05 * rng.standard_normal(40), 0.2 * rng.standard_normal(40)
    whole = launch_batch(problem_of(d), v, y0, vy0, workers=1)
    parts = [run_chunk(d, v[a:b], y0[a:b], vy0[a:b]) for a, b in ((0, 7), (7, 8), (8, 33), (33, 40))]
    for f in ("outcome", "bounces", "v_out"):
        np.testing.assert_array_equal(np.concatenate([p[f] for p in parts]), getattr(whole, f))
    bt = np.concatenate([p["bounce_times"] for p in parts])
    np.testing.assert_array_equal(bt, whole.bounce_times)
    assert parts[0]["worker"] is None
    with Engine() as eng:
        r = eng.launch(d, v, y0, vy0)
    np.testing.assert_array_equal(r.v_out, whole.v_out)
    assert eng.info()["scheduler"] is None and eng.launches == 40


# ----------------------------------------------------------------------------
# on a Dask cluster
# ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=":0") as c:
        yield c


@pytest.mark.dask
def test_dask_run_is_identical_and_ran_on_the_cluster(cluster, small_path, inprocess):
    from distributed import Client

    # small chunks: every refinement round becomes several tasks, spread over both workers
    code, out, err = run_cli(["explore", small_path, *EPS, "--json", "--scheduler", cluster.scheduler_address,
                              "--chunk", "40"])
    assert code == 0, err
    remote = json.loads(out)
    a, b = inprocess["designs"], remote["designs"]
    assert len(b) == 2 and b[0]["v_critical"] != b[1]["v_critical"]
    for x, y in zip(a, b):
        assert abs(x["v_critical"] - y["v_critical"]) <= 1e-9
        assert x["v_critical"] == y["v_critical"]                          # in fact bit for bit
        for key in ("v_critical_error", "windows", "highest_safe_height", "safe", "outcomes", "launches"):
            assert x[key] == y[key], key
    eng = remote["engine"]
    assert eng["scheduler"] == cluster.scheduler_address and eng["tasks"] > 0
    with Client(cluster) as client:
        workers = set(client.scheduler_info()["workers"])
        prefixes = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
    assert set(eng["workers"]) == workers and len(workers) == 2    # both workers ran chunks
    assert "fabkit-launch" in prefixes
    assert sum(eng["workers"].values()) == eng["tasks"]


def test_unreachable_scheduler_and_bad_chunk_are_bad_input():
    with pytest.raises(SpecError) as e:
        Engine("tcp://127.0.0.1:9", timeout=1)
    assert e.value.key == "--scheduler" and "cannot connect" in str(e.value)
    for bad in (0, -3, 10**9):
        with pytest.raises(SpecError) as e:
            Engine(None, chunk=bad)
        assert e.value.key == "--chunk"


def test_automatic_chunks_split_a_batch_over_the_free_threads():
    eng = Engine()
    eng.threads = 4
    assert eng.chunk_for(1000) == 250          # one stream: a chunk per thread
    eng.streams = 2
    assert eng.chunk_for(1000) == 500          # two designs side by side: two threads each
    eng.streams = 8
    assert eng.chunk_for(1000) == 1000         # more designs than threads: a batch per task
    assert eng.chunk_for(10) == 64 and eng.chunk_for(10**6) == 16384
    assert Engine(chunk=40).chunk_for(1000) == 40
