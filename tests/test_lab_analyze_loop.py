"""The lab loop end to end, small: two launches from release heights on the paper's block
(with a launch scatter) and a short release, simulated by the independent model
(tests/lab_sim.py) with viscous damping AND rolling resistance the spec does not know,
filmed into ``t,x,y,sigma_x,sigma_y`` tracks (0.3 mm noise); ``fabkit analyze`` finds
each launch's bounces, outcome and v_in within its stated errors, the ``both`` law with
each coefficient within 3 sigma and 10 %, and the launches again through the simulator
with those losses bounce as the truth did. benchmarks/lab_loop.py is the full version
(eight heights, the two-bounce windows)."""

from __future__ import annotations

import json

import numpy as np

import lab_sim as L
from conftest import PAPER

MU, CRR = 0.11, 0.0015
FPS = 125.0


def test_launches_from_release_heights_and_a_release_through_analyze(cli, tmp_path):
    launches = L.scattered_launches([1.1, 1.35], MU, CRR, seed=7)
    files = []
    for i, (_, _, _, _, truth) in enumerate(launches):
        assert truth["escaped"]            # the test's premise: both escape (2 and 3 bounces)
        files.append(tmp_path / f"launch{i}.csv")
        files[-1].write_text(L.track_csv(truth, fps=FPS, seed=40 + i))
    rel = L.run((-27.5, 5.0, 0.0, 0.0), MU, 2.0, escape=False, crr=CRR)
    files.append(tmp_path / "release.csv")
    files[-1].write_text(L.track_csv(rel, fps=FPS, seed=39, t_end=2.0))
    code, out, err = cli("analyze", PAPER, *files, "--json", "-o", "fitted.yaml")
    assert code == 0, err
    res = json.loads(out)
    lo = res["losses"]
    assert lo["chosen"] == "both" and min(lo["delta_bic"]["viscous"], lo["delta_bic"]["rolling"]) > 10
    c, e = lo["laws"]["both"]["coefficients"], lo["laws"]["both"]["errors"]
    for k, truth in (("damping", MU), ("rolling_resistance", CRR)):
        assert abs(c[k] - truth) <= 3 * e[k] and abs(c[k] / truth - 1) <= 0.10, (k, c[k], e[k])
    for r, (_, v, _, _, truth) in zip(res["tracks"], launches):
        bt = np.asarray(truth["bounce_times"])
        assert r["kind"] == "launch" and r["outcome"] == "escaped" and r["bounces"] == bt.size
        assert np.all(np.abs(np.asarray(r["bounce_times"]) - bt) < 2.0 / FPS)
        assert abs(r["v_in"] - v) <= 3 * r["v_in_error"]
        assert abs(r["v_out"] / truth["v_out"] - 1) < 0.02
        sim = r["simulation_fitted_losses"]
        assert sim["law"] == "both" and sim["outcome"] == "escaped" and sim["bounces"] == bt.size
    assert (tmp_path / "fitted.yaml").exists()
