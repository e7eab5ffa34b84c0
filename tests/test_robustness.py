"""fabkit robustness (issue 7): Monte Carlo over the launch's transverse offset and velocity.

Checked against independent answers: zero scatter gives the nominal bounce count
with probability 1; the probabilities of a row sum to 1 and equal a recount of
the same draws launched directly by ``launch_batch``; the draws depend only on
the seed; the Dask run equals the in-process run bit for bit.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from conftest import SMALL_STUDY, mutated, run_cli, run_study, small_study_spec, write_spec
from fabkit.errors import SpecError
from fabkit.explore import Engine, check_scatter, draw_scatter, robustness
from fabkit.physics.integrate import launch_batch
from fabkit.physics.models import OUTCOMES, problem_from_spec

SMALL = SMALL_STUDY
# across the edge of a two-bounce window of the small spec (nominal 2 bounces from 36 to 42 cm/s)
ARGS = ["--v-in", "40", "44", "5", "--sigma-y", "0.05", "--sigma-vy", "0.3", "--samples", "12", "--no-progress"]


small_spec = small_study_spec


@pytest.fixture(scope="module")
def small_path(tmp_path_factory):
    return write_spec(tmp_path_factory.mktemp("robustness"), mutated(SMALL), "small.yaml")


@pytest.fixture(scope="module")
def inprocess(small_path):
    return run_study("robustness", small_path, ARGS, "p.png")


def test_zero_scatter_gives_the_nominal_count_with_probability_one():
    with Engine() as eng:
        res = robustness(small_spec(), np.linspace(30, 60, 7), sigma_y=0.0, sigma_vy=0.0, samples=3, engine=eng)
    for row in res["rows"]:
        assert row["p_nominal"] == 1.0 and row["most_likely_is_nominal"]
        if row["nominal_outcome"] == "escaped":
            assert row["p_bounces"] == {str(row["nominal_bounces"]): 1.0}
        else:
            assert row["p_outcome"][row["nominal_outcome"]] == 1.0
        assert row["standard_error"] == 0.0
    assert res["summary"]["mean_p_nominal"] == 1.0 and res["summary"]["most_likely_differs"] == 0


def test_probabilities_sum_to_one_and_equal_a_direct_recount(inprocess):
    problem = problem_from_spec(small_spec())
    v = np.linspace(40, 44, 5)
    Y, VY = draw_scatter(5, 12, 0.05, 0.3, problem.y0, problem.vy0, seed=0)
    r = launch_batch(problem, np.repeat(v, 12), Y.ravel(), VY.ravel())
    nominal = launch_batch(problem, v)
    assert inprocess["v_in"] == list(v)
    saw_scatter = False
    for i, row in enumerate(inprocess["rows"]):
        total = sum(row["p_bounces"].values()) + sum(p for o, p in row["p_outcome"].items() if o != "escaped")
        assert total == pytest.approx(1.0, abs=1e-12)
        assert sum(row["p_bounces"].values()) == pytest.approx(row["p_outcome"]["escaped"], abs=1e-12)
        o, b = r.outcome[12 * i: 12 * i + 12], r.bounces[12 * i: 12 * i + 12]
        for n, p in row["p_bounces"].items():
            assert p == np.count_nonzero((o == 0) & (b == int(n))) / 12
        for j, name in enumerate(OUTCOMES):
            assert row["p_outcome"][name] == np.count_nonzero(o == j) / 12
        assert row["nominal_bounces"] == nominal.bounces[i]
        assert row["nominal_outcome"] == OUTCOMES[nominal.outcome[i]]
        saw_scatter |= 0 < row["p_nominal"] < 1
    assert saw_scatter, "the scatter should change the bounce count somewhere near the window's edge"


def test_draws_depend_only_on_the_seed():
    a = draw_scatter(4, 10, 0.1, 0.2, 0.0, 0.0, seed=7)
    b = draw_scatter(4, 10, 0.1, 0.2, 0.0, 0.0, seed=7)
    c = draw_scatter(4, 10, 0.1, 0.2, 0.0, 0.0, seed=8)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    z = np.random.default_rng(7).standard_normal((2, 4, 10))
    np.testing.assert_array_equal(a[0], 0.1 * z[0])
    assert abs(np.std(draw_scatter(1, 20000, 0.1, 0.2, 0.0, 0.0)[1]) - 0.2) < 0.01


def test_out_rows_plot_and_summary(inprocess, small_path):
    folder = inprocess["folder"]
    rows = list(csv.DictReader((folder / "rows.csv").open()))
    assert len(rows) == 5 * 12
    assert set(rows[0]) == {"v_in", "sample", "y0", "vy0", "outcome", "bounces", "v_out"}
    Y, VY = draw_scatter(5, 12, 0.05, 0.3, 0.0, 0.0, seed=0)
    assert [float(r["y0"]) for r in rows] == list(Y.ravel())             # written exactly
    assert (folder / "p.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    s = inprocess["summary"]
    assert 0 <= s["min_p_nominal"] <= s["mean_p_nominal"] <= 1
    assert s["max_standard_error"] <= s["bound_standard_error"] == pytest.approx(0.5 / np.sqrt(12))
    code, out, err = run_cli(["robustness", small_path, *ARGS])
    assert code == 0, err
    assert "nominal 2 bounce(s)" in out and "standard error" in out and " s" in out.splitlines()[-1]


def test_same_seed_same_json_other_seed_differs(small_path, inprocess):
    code, out, err = run_cli(["robustness", small_path, *ARGS, "--json", "--seed", "1"])
    assert code == 0, err
    other = json.loads(out)
    assert other["seed"] == 1 and other["rows"] != inprocess["rows"]


@pytest.mark.parametrize("extra,needle", [
    (["--sigma-y", "-1"], "--sigma-y"),
    (["--sigma-y", "nan"], "--sigma-y"),
    (["--sigma-vy", "inf"], "--sigma-vy"),
    (["--samples", "0"], "--samples"),
    (["--samples", "3000000"], "--samples"),          # 5 x 3000001 launches: over the guard
    (["--v-in", "40", "44", "1.5"], "--v-in"),
    (["--out", "rows.json"], "--out"),
    (["--chunk", "0"], "--chunk"),
])
def test_bad_input_exit_2_one_line_nothing_written(cli, tmp_path, extra, needle):
    spec = write_spec(tmp_path, mutated(SMALL))
    argv = ["robustness", spec, *ARGS, "--plot", "p.png", *extra]
    if "--out" not in extra:
        argv += ["--out", "rows.csv"]
    code, out, err = cli(*argv)
    assert code == 2 and needle in err and err.count("\n") == 1 and out == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.yaml"]


def test_check_scatter_guard():
    check_scatter(0.0, 0.0, 1, 2)
    with pytest.raises(SpecError) as e:
        check_scatter(0.1, 0.1, 10**7, 2)
    assert e.value.key == "--samples" and "limit" in str(e.value)


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=":0") as c:
        yield c


@pytest.mark.dask
def test_dask_run_is_identical(cluster, small_path, inprocess):
    code, out, err = run_cli(["robustness", small_path, *ARGS, "--json", "--scheduler", cluster.scheduler_address,
                              "--chunk", "16"])
    assert code == 0, err
    remote = json.loads(out)
    assert remote["rows"] == inprocess["rows"] and remote["summary"] == inprocess["summary"]
    eng = remote["engine"]
    assert eng["tasks"] == 5 and eng["launches"] == 5 * 13 and len(eng["workers"]) >= 1
