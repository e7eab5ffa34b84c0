"""Sweeps against the converged scipy reference (rtol 1e-12) for the paper's apparatus,
damping 0, start -30 cm, both models (issue: accuracy)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import mutated
from fabkit.physics import models
from fabkit.physics.integrate import launch_batch
from fabkit.physics.reference import solve_launch
from fabkit.physics.sweep import Launches, critical_bracket, find_runs, fit_tn, sweep
from fabkit.spec import validate


def _paper(model):
    spec = validate(mutated({"simulation.damping": 0.0, "simulation.start": -30}), "paper.yaml")
    return models.problem_from_spec(spec, model=model)


def _one_bounce(p, v):
    r = solve_launch(p, v)
    return r["outcome"] == "escaped" and r["bounces"] == 1


@pytest.mark.slow
@pytest.mark.parametrize("model,lo,hi", [("full", 43.9, 44.4), ("simplified", 48.6, 49.1)])
def test_v_critical_agrees_with_converged_reference(model, lo, hi):
    p = _paper(model)
    res = sweep(p, np.linspace(lo, hi, 6), error_samples=0, tn=False, k=128, k_edge=32)
    vc = res["v_critical"]
    assert vc is not None and res["v_critical_error"] <= 1e-6 * vc
    # the rtol-1e-12 reference brackets its own v_critical within 3e-5 of vc: at vc (1 - 3e-5) it
    # does not escape after one bounce, at vc (1 + 3e-5) it does (bisecting that bracket further
    # would only narrow what the two launches already show: vc agrees with it to 3e-5 < 1e-4)
    assert not _one_bounce(p, vc * (1 - 3e-5)) and _one_bounce(p, vc * (1 + 3e-5))
    # every sample above v_critical escapes after one bounce
    v = res["v_in"]
    above = v > vc
    assert all(o == "escaped" for o, a in zip(res["outcome"], above) if a)
    assert all(b == 1 for b, a in zip(res["bounces"], above) if a)


@pytest.mark.parametrize("model,speeds", [("full", [28.0, 39.2]), ("simplified", [28.0, 43.3])])
def test_v_out_inside_wide_two_bounce_windows(model, speeds):
    p = _paper(model)
    fast = launch_batch(p, speeds)
    for i, v in enumerate(speeds):
        ref = solve_launch(p, v)
        assert ref["outcome"] == "escaped" and ref["bounces"] == 2
        assert fast.bounces[i] == 2
        assert fast.v_out[i] == pytest.approx(ref["v_out"], rel=1e-3)
        assert fast.v_out[i] == pytest.approx(ref["v_out"], rel=1e-6)   # what the fast path actually gives
        np.testing.assert_allclose(fast.bounce_times[i, :2], ref["bounce_times"][:2], rtol=1e-6)


def test_eps_zero_sweep_is_one_bounce_with_v_out_equal_v_in():
    spec = validate(mutated({"surface.params.eps": 0.0, "simulation.damping": 0.0}), "eps0.yaml")
    p = models.problem_from_spec(spec)
    v = np.linspace(20, 70, 11)
    res = sweep(p, v, error_samples=0)
    assert list(res["bounces"]) == [1] * 11 and res["windows"] == []
    np.testing.assert_allclose(res["v_out"], v, rtol=1e-7)
    assert res["v_critical"] is None and "below the range" in res["v_critical_reason"]


def _fake(outcomes, bounces):
    n = len(outcomes)
    return Launches(np.arange(1.0, n + 1), np.array(outcomes, dtype=np.int8), np.array(bounces),
                    np.full(n, 1.0), np.full((n, 8), np.nan))


def test_bracket_and_runs_logic():
    # samples: captured, 2, 2, 3, 2, 1, 1, flew_off, flew_off
    r = _fake([1, 0, 0, 0, 0, 0, 0, 2, 2], [3, 2, 2, 3, 2, 1, 1, 0, 0])
    lo, hi, why = critical_bracket(r.v_in, r)
    assert (lo, hi) == (5.0, 6.0) and why == ""
    assert find_runs(r) == [(2, 1, 2), (3, 3, 3), (2, 4, 4)]
    r2 = _fake([0, 0, 1], [1, 1, 4])
    assert critical_bracket(r2.v_in, r2)[0] is None


def _structured_launcher(windows, vc):
    """Launches with a known structure: two-bounce inside ``windows`` [(lo, hi)], one
    bounce above ``vc`` and on one-bounce islands (the windows' gaps' midpoints +- 1e-3
    are captured), captured elsewhere."""
    def launch(v):
        v = np.asarray(v, dtype=float)
        two = np.zeros(len(v), dtype=bool)
        for lo, hi in windows:
            two |= (v >= lo) & (v < hi)
        one = (v >= vc) | ((v > 50.6) & (v < 50.61))       # an island of one-bounce escapes below v_c
        outcome = np.where(two | one, models.ESCAPED, models.CAPTURED).astype(np.int8)
        return Launches(v, outcome, np.where(two, 2, np.where(one, 1, 5)), np.where(two | one, 1.0, np.nan),
                        np.zeros((len(v), 8)))
    return launch


def test_edges_and_v_critical_follow_the_connected_run_where_windows_crowd():
    # two-bounce windows separated by gaps far narrower than the samples' spacing (as near
    # v_critical): a plain bisection of [48, 52] could end on any of their 2 x 6 edges
    wins = [(45.0, 48.5)] + [(48.5 + 0.2 * i + 0.01, 48.5 + 0.2 * (i + 1)) for i in range(6)]
    res = sweep(_paper("full"), [44.0, 46.0, 48.0, 52.0], launcher=_structured_launcher(wins, 51.25),
                error_samples=0, tn=False)
    w = res["windows"][0]
    assert w["lo"] == pytest.approx(45.0, rel=1e-6) and w["hi"] == pytest.approx(48.5, rel=1e-6)
    assert res["v_critical"] == pytest.approx(51.25, rel=1e-6) and res["v_critical_error"] <= 0.5e-6 * 51.25


def test_check_edge_next_to_v_critical_agrees_with_the_converged_reference():
    # the paper's apparatus (damping 0.127, start -30): above v_in 51.2695 the two-bounce
    # launches run on in windows about 0.02 cm/s wide, separated by gaps of 0.017, up to
    # v_critical. Converged references (scipy DOP853, rtol 1e-12, atol 1e-14, bisection to
    # 1e-7 relative): this window ends at 51.2904780, v_critical 51.742718 (+- 3e-6).
    # A 24-point k-section (51.513) and a plain bisection of the bracket (51.428) both
    # missed it.
    spec = validate(mutated({"simulation.t_max": 20}), "paper.yaml")
    p = models.problem_from_spec(spec).with_(stop_trapped=True)
    res = sweep(p, [46.02224, 51.26950, 51.76, 52.25577], error_samples=0, tn=False)
    # the two samples 46.02 and 51.27 both escape after two bounces, in different windows
    # (resolved at 1e-4): the one that holds 51.2695
    w = next(w for w in res["windows"] if w["lo"] <= 51.2695 <= w["hi"])
    assert w["bounces"] == 2 and w["edge_error"] <= 0.5e-6 * 51.3
    assert w["hi"] == pytest.approx(51.2904780, rel=1e-6)
    assert res["v_critical"] == pytest.approx(51.742718, rel=1e-6)


def test_tn_fit_recovers_a_line_with_gaps():
    T, delta, Ts = 0.67, 0.25, 0.607
    n = [3, 4, 5, 6, 8, 9, 12]
    fit = fit_tn([T * k + delta for k in n], list(range(len(n))), Ts)
    assert fit["n"] == n
    assert fit["T"] == pytest.approx(T, rel=1e-12) and fit["delta"] == pytest.approx(delta, rel=1e-10)


@pytest.mark.slow
def test_simplified_windows_follow_eq_tn_with_the_transverse_period():
    # eq. (xyODE_simp) on c y^2: the transverse mode has period 2 pi / sqrt(2 g~ c) exactly
    p = _paper("simplified")
    res = sweep(p, np.linspace(41.0, 47.5, 27), error_samples=8)
    fit = res["tn_fit"]
    T_shape = 2 * math.pi / math.sqrt(2 * p.g_tilde * 0.0764)
    assert fit["T_shape"] == pytest.approx(T_shape, rel=1e-9)
    assert len(fit["n"]) >= 3 and np.all(np.diff(fit["n"]) >= 1)
    assert fit["T"] == pytest.approx(T_shape, rel=0.01)
    assert res["error_estimate"]["v_out_rel"] < 1e-6
    # at the v_out maximum of each two-bounce window the reference agrees
    for w in [w for w in res["windows"] if w["bounces"] == 2 and "v_in_max" in w][:2]:
        ref = solve_launch(p, w["v_in_max"])
        assert ref["bounces"] == 2 and ref["outcome"] == "escaped"
        assert w["v_out_max"] == pytest.approx(ref["v_out"], rel=1e-6)


def test_sweep_cli_json_and_plot(cli, tmp_path):
    import json

    from conftest import write_spec

    spec = write_spec(tmp_path, mutated({"surface.params.eps": 0.0, "simulation.damping": 0.0}))
    code, out, err = cli("sweep", spec, "--v-in", "20", "70", "6", "--json", "--plot", "fig.png", "--no-progress")
    assert code == 0, err
    r = json.loads(out)
    for key in ("v_in", "v_out", "bounces", "outcome", "v_critical", "windows", "tn_fit", "seconds",
                "error_estimate"):
        assert key in r
    np.testing.assert_allclose(r["v_out"], r["v_in"], rtol=1e-7)       # eps = 0: v_out = v_in
    assert (tmp_path / "fig.png").read_bytes()[:4] == b"\x89PNG"
    code, out, err = cli("sweep", spec, "--v-in", "70", "20", "6")
    assert code == 2 and "--v-in" in err


# ----------------------------------------------------------------------------
# resolved windows (issue 23, item 5)
# ----------------------------------------------------------------------------
# A synthetic outcome function with known windows: two-bounce on [10, 20.005) and
# [20.01, 22.5) but captured in the gap [14.5, 14.503) (2e-4 relative: far narrower than the
# samples' spacing of 1), three-bounce on [25, 30) but two-bounce on [27, 27.01),
# one bounce from 40 up, captured elsewhere. v_out peaks at each window's centre.
SYN_TWO = [(10.0, 14.5), (14.503, 20.005), (20.01, 22.5), (27.0, 27.01)]
SYN_THREE = [(25.0, 27.0), (27.01, 30.0)]
SYN_NARROW = (33.0, 33.001)     # two-bounce, 3e-5 relative wide, holding the sample at 33


def _synthetic(v):
    v = np.asarray(v, dtype=float)
    n = np.full(len(v), 5)
    out = np.full(len(v), models.CAPTURED)
    vout = np.full(len(v), np.nan)
    bt = np.full((len(v), 8), np.nan)
    for wins, nb in ((SYN_TWO, 2), (SYN_THREE, 3)):
        for lo, hi in wins:
            m = (v >= lo) & (v < hi)
            n[m], out[m] = nb, models.ESCAPED
            vout[m] = 1.0 - ((v[m] - 0.5 * (lo + hi)) / (hi - lo)) ** 2
            bt[m, 0], bt[m, 1] = 0.0, lo          # T_n: the window's own lower edge
    narrow = (v >= SYN_NARROW[0]) & (v < SYN_NARROW[1])
    n[narrow], out[narrow], vout[narrow] = 2, models.ESCAPED, 1.0
    one = v >= 40.0
    n[one], out[one], vout[one] = 1, models.ESCAPED, 1.0
    return Launches(v, out.astype(np.int8), n, vout, bt)


def test_resolve_windows_splits_at_gaps_narrower_than_the_sampling():
    from fabkit.physics.sweep import resolve_windows

    v = np.arange(5.0, 46.0, 1.0)
    calls = []

    def launch(x):
        calls.append(len(x))
        return _synthetic(x)

    wins = resolve_windows(launch, v, _synthetic(v), resolution=1e-4, edge_rel_tol=1e-6, tn=True)
    expect = sorted([(2, lo, hi) for lo, hi in SYN_TWO] + [(3, lo, hi) for lo, hi in SYN_THREE], key=lambda w: w[1])
    assert [(w["bounces"], pytest.approx(w["lo"], rel=1e-6), pytest.approx(w["hi"], rel=1e-6)) for w in wins] == \
        expect                                   # the sample at 27 lies in [27, 27.01): three windows there
    for w in wins:
        assert 0 < w["edge_error"] <= 0.5e-6 * w["hi"]
        # the inside ends of the brackets carry the window's outcome
        r = _synthetic([w["lo_in"], w["hi_in"]])
        assert list(r.bounces) == [w["bounces"]] * 2 and list(r.outcome) == [models.ESCAPED] * 2
    for w in [w for w in wins if w["bounces"] == 2]:     # v_out maximized inside the window, at its centre
        vb, vo, tn = w["best"]
        assert w["lo"] <= vb <= w["hi"]
        assert vb == pytest.approx(0.5 * (w["lo"] + w["hi"]), abs=1e-3 * (w["hi"] - w["lo"]))
        assert tn in [lo for lo, hi in SYN_TWO] and tn == pytest.approx(w["lo"], abs=w["edge_error"])
    # the probes: at most 1e-4 relative apart over the runs' spans (10..22 and 25..29), plus the edges
    assert sum(calls) < 1.05 * (12 / 10 + 4 / 25) / 1e-4 + 2000
    # the narrow window is narrower than the resolution: not a window, listed apart
    sw = sweep(_paper("full"), v, launcher=launch, error_samples=0, tn=False)
    assert [(w["bounces"], w["lo"], w["hi"]) for w in sw["windows"]] == [(w["bounces"], w["lo"], w["hi"]) for w in wins]
    assert sw["resolution"] == 1e-4 and len(sw["unresolved_windows"]) == 1
    u = sw["unresolved_windows"][0]
    assert u["bounces"] == 2 and u["lo"] == pytest.approx(33.0, abs=1e-4) and u["hi"] == pytest.approx(33.001, abs=1e-4)
    # a coarser resolution than the gap leaves it unseen: it says what it resolves
    coarse = resolve_windows(_synthetic, v, _synthetic(v), resolution=1e-2, edge_rel_tol=1e-6)
    assert [(w["bounces"], round(w["lo"], 4), round(w["hi"], 4)) for w in coarse][0] == (2, 10.0, 22.5)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["full", "simplified", "ball"])
def test_no_merged_windows_on_the_papers_spec(model):
    """Acceptance (issue 23): five launches spread across every window of specs/surface.yaml
    (the ramp's speeds, the spec's damping) all end with that window's outcome. The windows
    are the sweep's as ``check`` computes them (trapped launches stopped early: the same
    outcomes, so the same windows as ``fabkit sweep``; ``check`` reports the two-bounce ones
    inside the ramp's range). Before resolution, the full model's window 50.484..50.930
    cm/s held two capture gaps."""
    from fabkit.commands.sweep import speeds
    from fabkit.physics.sweep import make_launcher

    spec = validate(mutated({"simulation.model": model}), "surface.yaml")
    p = models.problem_from_spec(spec).with_(stop_trapped=True)
    v = speeds(spec, None)
    res = sweep(p, v, error_samples=0, tn=False)
    wins = res["windows"]
    assert res["resolution"] == 1e-4 and len(wins) >= 10 and sum(w["bounces"] == 2 for w in wins) >= 7
    frac = (np.arange(5) + 0.5) / 5
    probe = np.concatenate([w["lo"] + (w["hi"] - w["lo"]) * frac for w in wins])
    r = make_launcher(p)(probe)        # the compiled engine's batch launcher
    want = np.repeat([w["bounces"] for w in wins], 5)
    bad = [(float(x), int(o), int(b), int(n)) for x, o, b, n in zip(probe, r.outcome, r.bounces, want)
           if not (o == models.ESCAPED and b == n)]
    assert not bad
    for a, b in zip(wins[:-1], wins[1:]):         # windows in order, disjoint
        assert a["lo"] <= a["hi"] <= b["lo"] <= b["hi"]


# ----------------------------------------------------------------------------
# the typed report of `fabkit sweep`
# ----------------------------------------------------------------------------
def test_sweep_report_carries_its_verdict_and_the_json_keys():
    from fabkit.physics.sweep import SWEEP_JSON_KEYS, SweepReport

    base = dict(v_in=np.array([20.0, 70.0]), v_out=np.array([1.0, 2.0]), bounces=np.array([3, 1]),
                outcome=["escaped", "escaped"], v_critical=50.0, v_critical_error=1e-5, v_critical_reason="",
                resolution=1e-4, unresolved_windows=[], tn_fit={}, error_estimate=None, launches=2, seconds=0.1,
                model="full", damping=0.0, units="mm")
    three = SweepReport(windows=[{"bounces": 3, "lo": 20.0, "hi": 21.0}], **base)
    assert not three.resonant and three.reason == "no two-bounce window in v_in 20..70 mm/s"
    two = SweepReport(windows=[{"bounces": 3, "lo": 20.0, "hi": 21.0}, {"bounces": 2, "lo": 22.0, "hi": 23.0}],
                      **base)
    assert two.resonant and two.reason == "" and two.two_bounce_windows == [{"bounces": 2, "lo": 22.0, "hi": 23.0}]
    none = SweepReport(windows=[], **{**base, "v_critical": None, "v_critical_reason": "every launch escapes"})
    assert none.reason.endswith("no v_critical (every launch escapes)")
    # the JSON keys of earlier versions, in their order
    assert list(two.to_json()) == ["v_in", "v_out", "bounces", "outcome", "v_critical", "windows", "tn_fit",
                                   "seconds", "error_estimate", "v_critical_error", "v_critical_reason",
                                   "launches", "resolution", "unresolved_windows", "model", "units",
                                   "window_completeness"]
    assert tuple(two.to_json()) == SWEEP_JSON_KEYS and two.outcome_counts == {"escaped": 2}


# ----------------------------------------------------------------------------
# which windows the samples can miss (issue 39)
# ----------------------------------------------------------------------------
#: the n-bounce ... windows of a resonance crowding toward v_critical = 60: window n
#: (n = 3..12) from 60 - 20 * 0.72^n, 2.4 * 0.62^n wide (0.55 .. 0.0079), T_n = 0.6 n + 0.4 s
ACC = [(n, 60.0 - 20.0 * 0.72 ** n, 60.0 - 20.0 * 0.72 ** n + 2.4 * 0.62 ** n) for n in range(3, 13)]


def _accumulating(v):
    v = np.asarray(v, dtype=float)
    n = np.full(len(v), 5)
    out = np.full(len(v), models.CAPTURED)
    bt = np.full((len(v), 8), np.nan)
    for k, lo, hi in ACC:
        m = (v >= lo) & (v < hi)
        n[m], out[m] = 2, models.ESCAPED
        bt[m, 0], bt[m, 1] = 1.0, 1.0 + 0.6 * k + 0.4
    one = v >= 60.0
    n[one], out[one] = 1, models.ESCAPED
    vout = np.where(out == models.ESCAPED, 1.0, np.nan)
    return Launches(v, out.astype(np.int8), n, vout, bt)


@pytest.mark.parametrize("offset", [0.0, 0.11, 0.23, 0.31])
def test_windows_wider_than_the_stated_width_are_found_and_the_fit_names_the_missed(offset):
    from fabkit.commands.sweep import summary
    from fabkit.physics.sweep import SweepReport

    p = _paper("full")
    v = np.linspace(40.0, 64.0, 61) + offset          # 0.4 apart: windows n >= 6 are narrower
    res = sweep(p, v, launcher=_accumulating, error_samples=0)
    c = res["window_completeness"]
    assert c["certain_width"] == pytest.approx(0.4, rel=1e-9) and c["spacing_near_critical"] == pytest.approx(0.4)
    found = {k for k, lo, hi in ACC
             if any(w["lo"] == pytest.approx(lo, rel=1e-6) and w["hi"] == pytest.approx(hi, rel=1e-6)
                    for w in res["windows"])}
    assert len(found) == len(res["windows"])              # no window that is not one of ACC
    for k, lo, hi in ACC:
        if hi - lo > c["certain_width"]:
            assert k in found                             # the statement holds
        held = bool(np.any((v >= lo) & (v < hi)))
        assert (k in found) == held                       # found exactly when a sample falls in it
    fit = res["tn_fit"]
    assert fit["n"] == sorted(found)                      # numbered by T_n (0.6 s apart), gaps kept
    assert fit["missing_n"] == [k for k in range(min(found), max(found) + 1) if k not in found]
    assert fit["T"] == pytest.approx(0.6, rel=1e-9) and fit["delta"] == pytest.approx(0.4, rel=1e-9)
    text = "\n".join(summary(SweepReport.of(res, p, "cm")))
    assert (f"every window wider than 0.4 cm/s (the samples' largest spacing, from v_in "
            f"{c['certain_width_at']:.4g}) is found") in text
    if fit["missing_n"]:
        assert "none found for n = " in text


def test_completeness_of_the_ramps_speeds():
    # the ramp's heights are evenly spaced; v = sqrt(2 g~ H) spreads them widest at the bottom
    from fabkit.physics.sweep import completeness

    H = np.linspace(0.2, 4.5, 400)
    v = np.sqrt(2 * 981.0 * H / 1.4)
    c = completeness(v[::-1], v_critical=float(v[250]) + 1e-9)
    assert c["certain_width"] == pytest.approx(v[1] - v[0], rel=1e-12) and c["certain_width_at"] == v[0]
    assert c["spacing_near_critical"] == pytest.approx(v[251] - v[250], rel=1e-12)
    assert completeness([3.0])["certain_width"] is None
