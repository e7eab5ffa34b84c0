"""The toolpath job's time guard is a budget: ``machining.max_time`` in the spec,
``--max-time SECONDS`` on gcode and report (the option wins). A job estimated
beyond it is refused before planning (exit 2, one line naming both ways to raise
it, nothing written); a raised budget lets the same job run."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import write_spec

from fabkit.tolerances import DEFAULT

# a cheap job: a 6 x 10 mm plane of slope 0.5, 6 mm ball, coarse scallop (a few passes)
RAW = {"name": "tiny", "units": "mm",
       "surface": {"height": "0.5*x", "x": [0, 6], "y": [0, 10], "top": 3.0},
       "stock": {"thickness": 20, "depth_limit": 10},
       "tool": {"shape": "ball", "diameter": 6, "reach": 30},
       "machining": {"scallop": 0.2, "tolerance": 0.02, "direction": "x"}}


def _spec(tmp_path, **machining):
    raw = {**RAW, "machining": {**RAW["machining"], **machining}}
    return write_spec(tmp_path, raw)


def _refused(code, err, tmp_path):
    assert code == 2
    assert "--max-time" in err and "machining.max_time" in err
    assert "limit 0.001 s" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not list(tmp_path.glob("p*")), "nothing is written on a refusal"


def test_the_option_refuses_beyond_a_tiny_budget_and_names_both_ways(cli, tmp_path):
    code, out, err = cli("gcode", _spec(tmp_path), "--no-verify", "-o", tmp_path / "p.ngc",
                         "--max-time", "0.001")
    _refused(code, err, tmp_path)


def test_the_spec_key_refuses_and_the_option_overrides_it(cli, tmp_path):
    spec = _spec(tmp_path, max_time=0.001)
    code, out, err = cli("gcode", spec, "--no-verify", "-o", tmp_path / "p.ngc")
    _refused(code, err, tmp_path)
    # the same job with the budget raised on the command line runs and writes its program
    code, out, err = cli("gcode", spec, "--no-verify", "-o", tmp_path / "p.ngc", "--max-time", "1e5")
    assert code == 0, err
    text = (tmp_path / "p.ngc").read_text()
    assert "G1" in text and text.rstrip().endswith(("M30", "M2"))


def test_a_raised_spec_key_lets_the_job_run(cli, tmp_path):
    code, out, err = cli("gcode", _spec(tmp_path, max_time=1e5), "--no-verify", "-o", tmp_path / "p.ngc")
    assert code == 0, err
    assert (tmp_path / "p.ngc").exists()


@pytest.mark.parametrize("value", ["0", "-3"])
def test_a_budget_not_above_zero_is_refused_naming_the_option(cli, tmp_path, value):
    code, out, err = cli("gcode", _spec(tmp_path), "-o", tmp_path / "p.ngc", f"--max-time={value}")
    assert code == 2 and "--max-time" in err and "> 0" in err
    assert not (tmp_path / "p.ngc").exists()


def test_the_spec_key_is_validated_and_defaults_to_the_tolerance(tmp_path):
    from fabkit.errors import SpecError
    from fabkit.spec import load_spec

    assert load_spec(_spec(tmp_path)).machining.max_time is None     # the guard uses DEFAULT's 60 s
    assert DEFAULT.max_plan_seconds == 60.0
    with pytest.raises(SpecError) as e:
        load_spec(_spec(tmp_path, max_time=-1))
    assert "machining.max_time" in str(e.value)


def test_report_takes_the_option(tmp_path):
    from fabkit.cli import build_parser

    args = build_parser().parse_args(["report", "s.yaml", "--max-time", "300"])
    assert args.max_time == 300.0


# ----------------------------------------------------------------------------
# the estimate's share of the footprint where the verification's compass search runs
# ----------------------------------------------------------------------------
def _fraction(slope_u, R, L=10.0, W=20.0, n=201):
    from fabkit.toolpath.finish.guards import _tight_fraction

    u, v = np.linspace(-L / 2, L / 2, n), np.linspace(0.0, W, n)
    UU, _ = np.meshgrid(u, v)
    Hu = slope_u(UU)
    return _tight_fraction(None, R, Hu, np.zeros_like(Hu), np.ones_like(Hu, bool), u, v), u[1] - u[0]


def test_tight_fraction_of_a_v_crease_is_the_band_within_r():
    """3|x| on 10 mm: concave only at the crease, so the band within R of it: 2R / L
    (to a few grid cells)."""
    R = 1.5875
    f, du = _fraction(lambda x: 3.0 * np.sign(x), R)
    assert abs(f - 2 * R / 10.0) <= 4 * du / 10.0


def test_tight_fraction_of_a_parabolic_valley():
    """c x^2: curvature 2c / (1 + 4c^2 x^2)^1.5 exceeds 1/R for |x| < x0 =
    sqrt((2cR)^(2/3) - 1) / (2c); the band is that, widened by R each side. A wide
    valley (2c < 1/R) and a plane have none."""
    R, c = 1.5875, 1.0
    x0 = math.sqrt((2 * c * R) ** (2 / 3) - 1) / (2 * c)
    f, du = _fraction(lambda x: 2 * c * x, R)
    assert abs(f - 2 * (x0 + R) / 10.0) <= 4 * du / 10.0
    assert _fraction(lambda x: 2 * 0.02 * x, R)[0] == 0.0
    assert _fraction(lambda x: 4.0 + 0 * x, R)[0] == 0.0


def _creases(m, R=2.0, L=12.0, W=12.0, n=201, k=2.0):
    """guards._creases of the V crease k |y - m x| on [0, L] x [-W/2, W/2], passes along x."""
    from fabkit.toolpath.finish.guards import _creases

    u, v = np.linspace(0.0, L, n), np.linspace(-W / 2, W / 2, n)
    UU, VV = np.meshgrid(u, v)
    sgn = np.sign(VV - m * UU)
    Hu, Hv = -k * m * sgn, k * sgn            # the exact slopes along (x) and across (y)
    tight, oblique, rows = _creases(None, R, Hu, Hv, np.ones_like(Hu, bool), u, v)
    return tight, oblique, rows, v


def test_a_crease_along_or_across_the_passes_is_not_oblique():
    """k |y| (along the passes) and k |x - 6| (across them): no oblique crease, no
    crowded rows, whatever the ball."""
    for R in (1.5875, 3.0):
        tight, oblique, rows, _ = _creases(0.0, R)
        assert tight > 0 and oblique == 0.0 and not rows.any()
    from fabkit.toolpath.finish.guards import _creases as creases

    u, v = np.linspace(0.0, 12.0, 201), np.linspace(-6.0, 6.0, 201)
    UU, _ = np.meshgrid(u, v)
    Hu = 2.0 * np.sign(UU - 6.0)
    tight, oblique, rows = creases(None, 2.0, Hu, np.zeros_like(Hu), np.ones_like(Hu, bool), u, v)
    assert tight > 0 and oblique == 0.0 and not rows.any()


def test_an_oblique_crease_crowds_the_rows_it_crosses():
    """k |y - m x| over x in [0, 12]: the crease crosses the rows y in [0, 12 m] (clipped
    to the block), and those within R of them are the crowded ones (to a grid cell); the
    obliqueness grows with the angle (the slope jumps along and across are in the ratio
    m = tan(angle))."""
    R = 2.0
    last = 0.0
    for m in (0.3, 0.577, 1.0):
        tight, oblique, rows, v = _creases(m, R)
        dv = v[1] - v[0]
        lo, hi = -R, min(12.0 * m, 6.0) + R
        inside = (v >= lo + 1.5 * dv) & (v <= hi - 1.5 * dv)
        outside = (v < lo - 1.5 * dv) | (v > hi + 1.5 * dv)
        assert rows[inside].all() and not rows[outside].any()
        assert oblique > last
        last = oblique


def test_preview_draws_each_feed_move_at_its_place_in_its_colour():
    """Two feed moves across a 10 x 10 mm block, at Y = 2 (Z -1) and Y = 8 (Z -3): the
    deeper is drawn in the colour map's lowest colour (viridis 0: 68, 1, 84), the other
    in its highest (253, 231, 37), each a horizontal line 8 mm long at the plot's scale,
    the deeper above the other (Y up) by 6 mm."""
    import io

    from PIL import Image

    from fabkit.toolpath.program.setup_sheet import preview_png
    from fabkit.toolpath.program.reader import read_program

    text = ("G21 G90\nG0 Z5\nG0 X1 Y2\nG0 Z-1\nG1 X9 Y2 F100\nG0 Z5\nG0 X1 Y8\nG0 Z-3\n"
            "G1 X9 Y8\nG0 Z5\nM2\n")
    img = np.asarray(Image.open(io.BytesIO(preview_png(read_program(text), 10.0, 10.0))).convert("RGB"))
    plot = img[:, :780]                                       # left of the colour bar
    dark = np.argwhere((plot == (68, 1, 84)).all(axis=2))
    light = np.argwhere((plot == (253, 231, 37)).all(axis=2))
    assert len(dark) and len(light)
    # the moves: one row each
    assert np.ptp(dark[:, 0]) == 0 and np.ptp(light[:, 0]) == 0
    assert dark[0, 0] < light[0, 0]                          # Y = 8 above Y = 2
    # the plot is 700 px wide for 1.06 x the stock's length (equal scales): 66.04 px/mm;
    # each move is 8 mm long, and they are 6 mm apart
    px_mm = 700 / (1.06 * 10.0)
    assert abs(np.ptp(dark[:, 1]) - 8 * px_mm) <= 2 and abs(np.ptp(light[:, 1]) - 8 * px_mm) <= 2
    assert abs((light[0, 0] - dark[0, 0]) - 6 * px_mm) <= 2


def test_the_estimate_counts_a_first_compile_only_when_the_cache_lacks_it(tmp_path, monkeypatch):
    """An empty kernel cache: the estimate adds the drop cutter's and the formula's build
    (kernels.BUILD_KERNEL_S + BUILD_FORMULA_S) and says so when it refuses; the numpy code
    (FABKIT_NO_KERNELS=1) compiles nothing; once the kernels are loaded nothing is added."""
    from fabkit.errors import SpecError
    from fabkit.spec import load_spec
    from fabkit.surface import Surface
    from fabkit.toolpath.finish import kernels
    from fabkit.toolpath.finish.raster import plan_estimate

    spec = load_spec(_spec(tmp_path))
    surface = Surface.from_spec(spec)
    warm = plan_estimate(spec, surface)
    kernels.kernel_for(surface)                      # built or loaded in the session's cache
    assert kernels.cold_build_seconds(surface) == 0.0
    monkeypatch.setenv("FABKIT_CACHE_DIR", str(tmp_path / "empty"))
    monkeypatch.setattr(kernels, "_BY_FNS", {})      # as a new process with that cache
    fresh = Surface.from_spec(spec)
    cold = plan_estimate(spec, fresh)
    want = kernels.BUILD_KERNEL_S + kernels.BUILD_FORMULA_S
    assert cold["build_seconds"] == pytest.approx(want)
    assert cold["seconds"] == pytest.approx(warm["seconds"] - warm["build_seconds"] + want)
    with pytest.raises(SpecError, match="compiling the kernels, once"):
        plan_estimate(load_spec(_spec(tmp_path, max_time=cold["seconds"] - 1.0)), fresh)
    monkeypatch.setenv("FABKIT_NO_KERNELS", "1")
    assert plan_estimate(spec, fresh)["build_seconds"] == 0.0
