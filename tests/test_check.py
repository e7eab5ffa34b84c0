"""fabkit check: the acceptance cases (paper's design passes, the wall clipped at 2 cm fails)."""

from __future__ import annotations

import json

import pytest

from conftest import PAPER, ROOT, mutated, write_spec

CLIPPED = ROOT / "tests" / "fixtures" / "check" / "clipped_top2.yaml"


@pytest.mark.slow
def test_paper_design_passes(cli, tmp_path):
    # specs/surface.yaml as is, but 60 ramp samples instead of 400 (test time)
    code, out, err = cli("check", write_spec(tmp_path, mutated({"ramp.samples": 60})), "--json", "--no-progress")
    assert code == 0, err
    r = json.loads(out)
    assert r["safe"] is True
    assert r["first_failure"] is None
    assert r["highest_safe_height"] == pytest.approx(4.5)
    # energy bound: z never exceeds the release height, and top - margin = 4.5 = the highest height
    assert set(r["outcomes"]) <= {"escaped", "captured"}
    assert r["machining"]["depth_ok"] and r["machining"]["radius_ok"]
    assert 40 < r["v_critical"] < 60
    # sweep and check on the same spec report the same windows, and the same width from which
    # every window is found: the ramp's largest spacing (60 heights 0.2..4.5 cm, so 4.3 / 59 cm
    # in release height; in v_in the lowest spacing, v = sqrt(2 g H / (1 + k)) less the ramp's losses)
    code, out2, err = cli("sweep", write_spec(tmp_path, mutated({"ramp.samples": 60})), "--json", "--no-progress")
    assert code == 0, err
    s = json.loads(out2)
    two = [(w["lo"], w["hi"]) for w in s["windows"] if w["bounces"] == 2
           and r["v_in"][0] < w["lo"] and w["hi"] < r["v_in"][-1]]
    assert two and two == [(w["lo"], w["hi"]) for w in r["reachable_windows"]]
    c, cs = r["window_completeness"], s["window_completeness"]
    assert c["certain_height_width"] == pytest.approx(4.3 / 59, rel=1e-9)
    assert c["certain_width"] == cs["certain_width"] == pytest.approx(r["v_in"][1] - r["v_in"][0], rel=1e-12)
    assert c["spacing_near_critical"] == cs["spacing_near_critical"] < c["certain_width"]


def test_wall_clipped_at_2cm_fails_naming_the_first_height(cli, tmp_path):
    raw = mutated({"surface.top": 2, "ramp.samples": 40})
    spec = write_spec(tmp_path, raw)
    code, out, err = cli("check", spec, "--no-progress")
    assert code == 1
    assert err.count("\n") == 1 and "UNSAFE: release height" in err and "top - margin" in err
    # undamped energy bound: a launch from H can reach at most z = H, so every height
    # <= top - margin = 1.5 cm is safe; the first failure lies above it.
    h = float(err.split("release height ")[1].split()[0])
    assert h > 1.5
    assert "check: highest safe release height" in out


def test_clipped_fixture_is_the_paper_with_top_2():
    import yaml

    a = yaml.safe_load(CLIPPED.read_text())
    b = yaml.safe_load(PAPER.read_text())
    assert a["surface"]["top"] == 2
    a["surface"]["top"] = b["surface"]["top"]
    a["name"] = b["name"]
    assert a == b


def test_bad_input_exit_2(cli, tmp_path):
    raw = mutated({}, drop=("ramp",))
    code, out, err = cli("check", write_spec(tmp_path, raw), "--no-progress")
    assert code == 2 and "ramp" in err and out == ""


def test_point_model_fixture_is_the_shipped_paper_spec_on_the_full_model():
    """tests/fixtures/paper_full.yaml (the tests' paper spec) is specs/surface.yaml but for
    simulation.model: full (the shipped spec runs the finite ball)."""
    import yaml

    from conftest import SHIPPED_PAPER

    a = yaml.safe_load(PAPER.read_text())
    b = yaml.safe_load(SHIPPED_PAPER.read_text())
    assert a["simulation"]["model"] == "full" and b["simulation"]["model"] == "ball"
    a["simulation"]["model"] = "ball"
    assert a == b


def test_outcome_codes_are_defined_once():
    """The compiled engine's outcome numbers (module constants numba needs) are those of
    models.OUTCOMES, the one definition the check, explore and design read."""
    from fabkit.physics import models
    from fabkit.physics.engine import ball, dop853

    assert models.OUTCOMES == ("escaped", "captured", "flew_off", "lost_contact", "bridged", "slipped")
    assert (dop853.ESCAPED, dop853.CAPTURED, dop853.FLEW_OFF, dop853.LOST_CONTACT, dop853.BRIDGED) == \
        (models.ESCAPED, models.CAPTURED, models.FLEW_OFF, models.LOST_CONTACT, models.BRIDGED)
    assert (ball._LOST_CONTACT, ball._BRIDGED, ball._SLIPPED) == (models.LOST_CONTACT, models.BRIDGED,
                                                                  models.SLIPPED)


AS_BUILT = ROOT / "specs" / "surface_as_built.yaml"


def test_as_built_spec_is_the_paper_spec_with_the_wall_at_2cm():
    import yaml

    from conftest import SHIPPED_PAPER

    a = yaml.safe_load(AS_BUILT.read_text())
    b = yaml.safe_load(SHIPPED_PAPER.read_text())
    assert a["surface"]["top"] == 2.0 and b["surface"]["top"] == 5.0 and a["simulation"]["model"] == "ball"
    a["surface"]["top"], a["name"] = b["surface"]["top"], b["name"]
    assert a == b


@pytest.mark.slow
def test_as_built_block_fails_the_check_below_v_critical(cli):
    """The paper's block as built (the wall 2 cm above the entry level) fails: fast balls fly
    off the part before v_critical, so it cannot be measured (the paper's report). Energy
    bound: the damped ball's centre never rises more than H above its entry height (its
    contact point more only by r (1 - n_z) on a slope), so the heights up to top - margin
    = 1.5 cm stay safe; the first failure lies above them, and below the release height of
    v_critical on the full-depth block (2.50 cm for the 2.5 cm ball)."""
    code, out, err = cli("check", AS_BUILT, "--json", "--no-progress")
    assert code == 1
    assert err.count("\n") == 1 and "UNSAFE: release height" in err and "flew off" in err
    r = json.loads(out)
    assert r["safe"] is False and r["model"] == "ball" and r["first_failure"]["outcome"] == "flew_off"
    assert r["v_critical"] is None and "fly off" in r["v_critical_reason"]
    assert 1.5 <= r["highest_safe_height"] < r["first_failure"]["height"] < 2.50
    # the boundary bisected between the last safe and the first failing sample
    assert r["first_failure"]["height"] - r["highest_safe_height"] <= (4.5 - 0.2) / 399


def test_check_takes_a_launcher_and_heights():
    """check(spec, launcher=..., heights=...): a launcher that keeps no end states (the
    sweep's Launches, as explore's engine returns) gives the report of the default one,
    the failing launch's end state found again in-process; the heights given are the
    heights launched; the report's verdict is the command's (exit 1, the same reason)."""
    import numpy as np

    from fabkit.physics.check import check, entry_speeds
    from fabkit.physics.models import problem_from_spec
    from fabkit.physics.sweep import make_launcher
    from fabkit.spec import load_spec

    spec = load_spec(CLIPPED).with_overrides({"ramp.samples": 12, "simulation.rtol": 1e-6,
                                              "simulation.atol": 1e-8})
    base = make_launcher(problem_from_spec(spec).with_(stop_trapped=True))
    seen = []

    def launch(v):
        seen.append(np.asarray(v, dtype=float).copy())
        return base(v)

    a = check(spec)
    b = check(spec, launcher=launch)
    assert not a.safe and a.reason.startswith("UNSAFE: release height") and a.reason == b.reason
    assert a.first_failure == b.first_failure and a.highest_safe_height == b.highest_safe_height
    assert a.v_critical == b.v_critical and a.reachable_windows == b.reachable_windows
    assert b.launches == sum(len(x) for x in seen) and np.array_equal(seen[0], b.v_in)
    H = np.array([0.5, 1.0, 1.4])
    c = check(spec, heights=H[::-1])
    assert np.array_equal(c.heights, H) and np.array_equal(c.v_in, entry_speeds(spec, H))
    assert c.ramp_safe and c.first_failure is None and c.highest_safe_height == 1.4   # below top - margin
    assert c.to_json()["safe"] is c.safe and c.to_json()["model"] == "full"
