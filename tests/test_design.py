"""fabkit design (issue 17): the search for the most observable two-bounce windows.

The optimizer is checked on closed-form objectives; the constraints against the
pre-fabrication check itself (a design the search refuses really fails ``fabkit
check``, or the check reports the same violation); the whole search for
determinism (same seed, same bytes) and on a real two-worker Dask cluster (the
same result as in-process). The designs are the cheap variant of the paper's
apparatus used by the explore tests (loose tolerances, eight ramp heights).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from conftest import SMALL_STUDY, mutated, run_cli, write_spec
from fabkit.design import (Options, objective, optimize, parse_bound, rank_key, scatter_draws, screen,
                           screen_heights)
from fabkit.errors import SpecError
from fabkit.spec import load_spec, validate

TINY = ["--vary", "surface.params.eps=0.22:0.28", "--budget", "5", "--top", "1", "--min-width", "0.2",
        "--seed", "3", "--no-progress"]


def small(changes: dict | None = None):
    return validate(mutated({**SMALL_STUDY, **(changes or {})}), "small.yaml")


# ----------------------------------------------------------------------------
# the optimizer on closed-form objectives
# ----------------------------------------------------------------------------
def test_optimizer_finds_the_minimum_of_a_quadratic():
    centre = np.array([0.3, -0.2, 0.55])

    def fn(X):
        return np.sum((X - centre) ** 2, axis=1)

    r = optimize(fn, [-1, -1, -1], [1, 1, 1], budget=360, seed=4)
    assert np.max(np.abs(r["x"] - centre)) < 0.02
    assert r["fun"] == pytest.approx(float(np.sum((r["x"] - centre) ** 2)))
    assert len(r["calls"]) <= 360


def test_optimizer_finds_the_plateau_of_a_count_objective():
    """A piecewise-constant objective like the design's: minus the number of discs
    (radius 0.15) containing x, plus a small tie term. Three discs overlap only in a
    lens around (0.6, 0.5); the closed-form optimum is any point of that lens."""
    discs = np.array([[0.5, 0.5], [0.7, 0.5], [0.6, 0.62], [-0.6, -0.6]])

    def count(X):
        return np.sum(np.linalg.norm(X[:, None, :] - discs[None], axis=2) <= 0.15, axis=1)

    def fn(X):
        return -(count(X) + 0.01 * np.exp(-np.sum(X ** 2, axis=1)))

    r = optimize(fn, [-1, -1], [1, 1], budget=240, seed=1)
    assert count(r["x"][None])[0] == 3
    assert np.all(np.linalg.norm(discs[:3] - r["x"], axis=1) <= 0.15)


def test_optimizer_is_deterministic_for_a_seed():
    def fn(X):
        return np.cos(7 * X[:, 0]) + (X[:, 1] - 0.1) ** 2

    a = optimize(fn, [0, 0], [1, 1], budget=50, seed=7)
    b = optimize(fn, [0, 0], [1, 1], budget=50, seed=7)
    c = optimize(fn, [0, 0], [1, 1], budget=50, seed=8)
    assert a["calls"] == b["calls"] and np.array_equal(a["x"], b["x"])
    assert a["calls"] != c["calls"]
    assert len(a["calls"]) == 50 and a["population"] == 10          # 5 generations of 10
    # the first member of the first population is the given x0
    d = optimize(fn, [0, 0], [1, 1], budget=10, seed=7, x0=[0.25, 0.75])
    assert d["calls"][0][0] == [0.25, 0.75]


def test_objective_orders_as_the_rank_key():
    """Count first, then observable width, then all two-bounce width; infeasible last."""
    def ev(feasible, n, w_obs, w_all, viol=0.0):
        return {"feasible": feasible, "observable": n, "observable_width": w_obs, "two_width": w_all,
                "violation": viol}

    evs = [ev(True, 2, 0.1, 0.5), ev(True, 1, 4.0, 4.2), ev(True, 2, 0.3, 0.3), ev(True, 0, 0.0, 2.0),
           ev(True, 0, 0.0, 0.0), ev(False, 5, 3.0, 3.0, 0.2), ev(False, 0, 0.0, 0.0, 3.0)]
    span = 4.3
    by_key = sorted(range(len(evs)), key=lambda i: rank_key(evs[i]), reverse=True)
    by_obj = sorted(range(len(evs)), key=lambda i: objective(evs[i], span))
    assert by_key == by_obj == [2, 0, 1, 3, 4, 5, 6]
    assert all(objective(e, span) > 0 for e in evs if not e["feasible"])


# ----------------------------------------------------------------------------
# bounds and options
# ----------------------------------------------------------------------------
def test_bounds_parse_and_snap():
    spec = small()
    b = parse_bound("surface.params.eps=0.1:0.4", spec)
    assert (b.key, b.lo, b.hi, b.integer, b.step) == ("surface.params.eps", 0.1, 0.4, False, 1e-4)
    assert b.snap(0.123456) == 0.1235 and b.snap(0.05) == 0.1 and b.snap(0.9) == 0.4
    assert parse_bound("surface.y.hi=8:12.5", spec).step == 1e-3
    n = parse_bound("ramp.samples=5.5:9.2", spec)
    assert n.integer and n.snap(7.6) == 8 and n.snap(1) == 6 and n.snap(20) == 9
    assert parse_bound("stock.depth_limit=40:60", spec).lo == 40.0


@pytest.mark.parametrize("text,needle", [
    ("surface.params.eps", "expected KEY=LO:HI"),
    ("surface.params.epz=0.1:0.4", "did you mean 'surface.params.eps'"),
    ("simulation.dampng=0:1", "did you mean 'simulation.damping'"),
    ("surface.params.eps=0.4:0.1", "LO < HI"),
    ("surface.params.eps=0.1:0.4:4", "expected LO:HI"),
    ("surface.params.eps=a:0.4", "LO must be a number"),
    ("surface.params.eps=0.1:inf", "HI must be finite"),
    ("simulation.model=0:1", "not a number key"),
    ("surface.x.mid=0:1", "unknown key"),
    ("ramp.samples=5.2:5.8", "no whole number"),
])
def test_bad_bounds_are_refused(text, needle):
    with pytest.raises(SpecError) as exc:
        parse_bound(text, small())
    assert needle in str(exc.value) and "--vary" in str(exc.value)


@pytest.mark.parametrize("extra,needle", [
    ([], "--vary: give at least one"),
    (["--vary", "surface.top=4:5", "--vary", "surface.top=3:6"], "varied twice"),
    (["--vary", "surface.top=4:5", "--budget", "3"], "--budget"),
    (["--vary", "surface.top=4:5", "--sigma-y", "-1"], "--sigma-y"),
    (["--vary", "surface.top=4:5", "--min-width", "9"], "--min-width"),
    (["--vary", "surface.top=4:5", "--samples", "0"], "--samples"),
    (["--vary", "surface.top=4:5", "--top", "0"], "--top"),
])
def test_bad_input_is_one_line_exit_2_nothing_written(tmp_path, extra, needle):
    path = write_spec(tmp_path, mutated(SMALL_STUDY))
    out = tmp_path / "w.yaml"
    code, stdout, err = run_cli(["design", path, *extra, "-o", out, "--no-progress"])
    assert code == 2, err
    assert needle in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists() and stdout == ""


def test_screen_heights_hold_two_samples_of_every_minimum_window():
    spec = small({"ramp.samples": 400})
    H = screen_heights(spec, 0.1)
    assert np.max(np.diff(H)) <= 0.1 / 3 + 1e-12 and H[0] == 0.2 and H[-1] == 4.5
    assert np.array_equal(screen_heights(small(), 0.1), np.linspace(0.2, 4.5, 8))   # never more than the check


def test_scatter_draws_are_the_seeds_normal_draws():
    y, vy = scatter_draws(Options(0.1, sigma_y=0.2, sigma_vy=0.5, samples=5, seed=9), 0.1, -0.3)
    z = np.random.default_rng(9).standard_normal((2, 5))
    assert np.array_equal(y, 0.1 + 0.2 * z[0]) and np.array_equal(vy, -0.3 + 0.5 * z[1])
    y, vy = scatter_draws(Options(0.1, samples=5), 0.1, -0.3)                          # no scatter: nominal
    assert y.tolist() == [0.1] and vy.tolist() == [-0.3]


# ----------------------------------------------------------------------------
# constraints: what the search refuses, the check refuses too
# ----------------------------------------------------------------------------
def _check_cli(tmp_path, changes, name):
    path = write_spec(tmp_path, mutated({**SMALL_STUDY, **changes}), name)
    return run_cli(["check", path, "--json", "--no-progress"])


def test_a_design_that_flies_off_is_refused_and_fails_the_check(tmp_path):
    ev = screen(small({"surface.top": 2.0}), Options(0.2))
    assert not ev["feasible"] and "flew off" in ev["reason"] and ev["launches"] == 8
    code, out, err = _check_cli(tmp_path, {"surface.top": 2.0}, "top2.yaml")
    assert code == 1 and "UNSAFE" in err and json.loads(out)["safe"] is False


def test_a_cut_too_deep_is_refused_without_launches_and_fails_the_check(tmp_path):
    ev = screen(small({"stock.depth_limit": 40}), Options(0.2))
    assert not ev["feasible"] and ev["launches"] == 0 and "stock.depth_limit" in ev["reason"]
    assert ev["violation"] == pytest.approx((ev["depth_mm"] - 40) / 40)
    code, out, err = _check_cli(tmp_path, {"stock.depth_limit": 40}, "deep.yaml")
    assert code == 1 and "UNMACHINABLE" in err and "stock.depth_limit" in err


def test_a_tool_larger_than_the_concave_radius_is_refused_as_the_check_reports():
    from fabkit.physics.check import machining

    spec = small({"tool.diameter": 30})                 # radius 15 mm > the paper's 10.6 mm
    ev = screen(spec, Options(0.2))
    m = machining(spec)                                 # what fabkit check prints (TOOL TOO LARGE)
    assert m["radius_ok"] is False and not ev["feasible"] and ev["launches"] == 0
    assert ev["violation"] == pytest.approx(15.0 / m["min_concave_radius_mm"] - 1)


def test_v_critical_without_margin_is_refused_as_the_check_reports():
    """The paper's v_critical (51.74 cm/s, release height 1.991 cm with the ramp's own damping,
    1.911 cm without): a ramp up to 2.03 cm reaches it, but its top launches only 1 % above
    it (< 5 %)."""
    from fabkit.physics.check import check, entry_speeds

    spec = small({"ramp.heights": [0.2, 2.03], "ramp.samples": 16})
    ev = screen(spec, Options(0.1))
    assert not ev["feasible"] and "v_critical" in ev["reason"]
    r = check(spec)
    top = float(entry_speeds(spec, 2.03))
    assert r.v_critical is not None and top < 1.05 * r.v_critical and r.v_critical < top
    assert ev["violation"] == pytest.approx((1.05 * ev["v_critical"] - top) / ev["v_critical"])


def test_an_invalid_combination_is_an_infeasible_design(tmp_path):
    from fabkit.design import evaluate

    raw = mutated({**SMALL_STUDY, "surface.x": [-20, 6]})       # simulation.start -30 outside
    ev = evaluate("screen", raw, "small.yaml", Options(0.2))
    assert not ev["feasible"] and "simulation.start" in ev["reason"] and ev["violation"] > 1


# ----------------------------------------------------------------------------
# the whole search: outputs, determinism, Dask
# ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = tmp_path_factory.mktemp("design")
    # no stock or tool: the machining constraints are tested above; here the search itself
    path = write_spec(folder, mutated(SMALL_STUDY, drop=("stock", "tool", "machining")), "small.yaml")
    code, out, err = run_cli(["design", path, *TINY, "--json", "-o", folder / "w.yaml", "--plot",
                              folder / "d.png"])
    assert code == 0, err
    return {"path": path, "folder": folder, "json": json.loads(out), "yaml": (folder / "w.yaml").read_bytes()}


def test_the_winner_is_a_complete_spec_the_other_commands_take(tiny):
    res = tiny["json"]
    w = res["winner"]
    spec = load_spec(tiny["folder"] / "w.yaml")
    assert spec.name == "small.design"
    assert spec.surface.params["eps"] == w["params"]["surface.params.eps"]
    raw = dict(spec.raw)
    raw.pop("name")
    want = mutated({**SMALL_STUDY, "surface.params.eps": w["params"]["surface.params.eps"]},
                   drop=("stock", "tool", "machining"))
    want.pop("name")
    assert raw == want                                  # the original with the searched key replaced
    # the baseline is the spec as it is, evaluated by the full check
    assert res["baseline"]["params"] == {"surface.params.eps": 0.25} and res["baseline"]["stage"] == "check"
    assert w["check"] == "pass" and w["feasible"]
    assert all(d["stage"] == "check" for d in res["designs"])
    assert res["optimizer"]["evaluations"] == 5 and len(res["history"]) == 5
    assert (tiny["folder"] / "d.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the winner is at least as good as the baseline, by the rank key
    assert (w["observable"], w["observable_width"]) >= (res["baseline"]["observable"],
                                                       res["baseline"]["observable_width"]) or \
        w["params"] == res["baseline"]["params"]


def test_windows_agree_with_the_check_of_the_written_spec(tiny):
    """The winner's windows are the check's reachable windows of the written spec, the
    observable ones at least min_width wide with the centre launch bouncing twice."""
    from fabkit.physics.check import check

    w = tiny["json"]["winner"]
    r = check(load_spec(tiny["folder"] / "w.yaml"))
    assert [(x["height_lo"], x["height_hi"]) for x in r.reachable_windows] == \
        [(x["height_lo"], x["height_hi"]) for x in w["windows"]]
    for x in w["windows"]:
        assert x["observable"] == (x["width"] >= 0.2 and x["p_two"] == 1.0)
    assert w["observable"] == sum(x["observable"] for x in w["windows"])


def test_stated_accuracy_is_the_checks(tiny):
    """The accuracy the command states is the one the check ran with, and the winner's
    brackets (v_critical, every window edge) are that narrow."""
    from fabkit.physics.check import TOLERANCES

    res = tiny["json"]
    tols = res["check_tolerances"]
    assert tols == {kk: vv for kk, vv in TOLERANCES.items() if kk.endswith("rel_tol")}
    w = res["winner"]
    assert 0 < w["v_critical_error"] <= 0.5 * tols["v_rel_tol"] * w["v_critical"]
    assert w["windows"]
    for x in w["windows"]:
        assert 0 < x["edge_error"] <= 0.5 * tols["edge_rel_tol"] * x["hi"]


def test_same_seed_same_design(tiny):
    folder = tiny["folder"]
    code, out, err = run_cli(["design", tiny["path"], *TINY, "--json", "-o", folder / "again.yaml"])
    assert code == 0, err
    again = json.loads(out)
    assert (folder / "again.yaml").read_bytes() == tiny["yaml"]
    assert again["history"] == tiny["json"]["history"]
    assert again["winner"]["params"] == tiny["json"]["winner"]["params"]


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, host="127.0.0.1",
                                  dashboard_address=":0") as c:
        yield c


@pytest.mark.dask
def test_dask_run_equals_the_in_process_run(cluster, tiny):
    from distributed import Client

    folder = tiny["folder"]
    code, out, err = run_cli(["design", tiny["path"], *TINY, "--json", "-o", folder / "dask.yaml",
                              "--scheduler", cluster.scheduler_address])
    assert code == 0, err
    remote, local = json.loads(out), tiny["json"]
    assert (folder / "dask.yaml").read_bytes() == tiny["yaml"]
    assert remote["history"] == local["history"]
    for key in ("baseline", "winner"):
        a, b = dict(local[key]), dict(remote[key])
        a.pop("seconds"), b.pop("seconds")
        assert a == b, key
    eng = remote["engine"]
    assert eng["scheduler"] == cluster.scheduler_address and eng["tasks"] == 1 + 5 + len(remote["designs"])
    with Client(cluster) as client:
        workers = set(client.scheduler_info()["workers"])
        prefixes = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.task_prefixes))
    assert set(eng["workers"]) == workers and len(workers) == 2
    assert "fabkit-design" in prefixes


def test_scatter_probability_is_the_fraction_of_two_bounce_launches():
    """P(2 bounces) at a window's centre is the fraction of the seed's scatter launches
    that escape after two bounces (recounted by launching the same draws directly); a
    scatter far wider than the channel leaves no window observable."""
    from fabkit.design import _centres, _problem
    from fabkit.physics.calibrate import v_in_from_height
    from fabkit.physics.integrate import launch_batch

    spec = small()
    problem = _problem(spec)
    win = {"lo": 0.0, "hi": 0.0, "height_lo": 0.8071, "height_hi": 1.3536}     # the paper's widest window
    opts = Options(0.1, sigma_y=0.1, sigma_vy=0.5, samples=16, seed=2)
    (w,) = _centres(spec, problem, [win], opts)
    y, vy = scatter_draws(opts, problem.y0, problem.vy0)
    v = np.full(16, float(v_in_from_height(0.5 * (0.8071 + 1.3536), 980.665, 0.4)))
    r = launch_batch(problem, v, y, vy)
    two = (np.asarray(r.outcome) == 0) & (np.asarray(r.bounces) == 2)
    assert w["p_two"] == two.mean() and w["observable"] == (two.mean() >= 0.8)
    assert w["width"] == pytest.approx(1.3536 - 0.8071) and w["centre"] == pytest.approx(1.08035)
    (wide,) = _centres(spec, problem, [win], Options(0.1, sigma_y=100.0, samples=16, seed=2))
    assert wide["p_two"] < 0.8 and not wide["observable"]
    (narrow,) = _centres(spec, problem, [win], Options(0.6, sigma_y=0.1, samples=16, seed=2))
    assert narrow["p_two"] is None and not narrow["observable"]                  # narrower than min_width


def test_outputs_are_refused_before_any_work(tmp_path):
    path = write_spec(tmp_path, mutated(SMALL_STUDY))
    code, out, err = run_cli(["design", path, "--vary", "surface.top=4:5", "-o", path, "--no-progress"])
    assert code == 2 and "-o" in err and "is the input" in err
    code, out, err = run_cli(["design", path, "--vary", "surface.top=4:5", "-o", tmp_path / "w.yaml",
                              "--plot", tmp_path / "d.gif", "--no-progress"])
    assert code == 2 and "--plot" in err and ".gif" in err and not (tmp_path / "w.yaml").exists()


def test_v_critical_outside_the_ramp_cannot_be_measured():
    from fabkit.design import _vc_violation

    assert _vc_violation(50.0, 52.5, "")[0] == 0.0                           # exactly 5 % above
    assert _vc_violation(50.0, 52.0, "")[0] == pytest.approx(0.01)
    for reason in ("no one-bounce escape at the top of the range (v_in up to 79.4): v_critical is above it",
                   "every launch escapes after one bounce: v_critical is below the range (v_in from 16.7)"):
        viol, why = _vc_violation(None, 79.4, reason)
        assert viol == 1.0 and "cannot be measured" in why
