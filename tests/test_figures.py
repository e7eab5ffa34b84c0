"""Figures say what they show: units on every axis and value, every outcome its own
marker, empty panels explained, labels that do not overlap. Read from the SVG text
(fonts kept as text) rather than from pixels."""

from __future__ import annotations

import re

import matplotlib
import pytest

from fabkit import plots


@pytest.fixture
def svg_text():
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        yield lambda data: data.decode("utf-8")


def sweep_result():
    # one launch of each outcome, escaped ones with 1, 2 and 3 bounces
    return {"v_in": [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0],
            "v_out": [None, 3.0, 4.0, None, None, 6.0, 8.0],
            "bounces": [2, 2, 3, 1, 0, 1, 1],
            "outcome": ["captured", "escaped", "escaped", "flew_off", "lost_contact", "escaped", "escaped"],
            "v_critical": 55.5, "v_critical_error": 1e-5}


def test_sweep_figure_units_and_one_marker_per_outcome(svg_text):
    svg = svg_text(plots.sweep_figure(sweep_result(), "t", units="cm", fmt="svg"))
    for text in ("v_in, entry speed (cm/s)", "v_out, exit speed (cm/s)", "v_critical = 55.5 ± 1.0e-05 cm/s",
                 "escaped after 1 bounce", "escaped after 2 bounces", "escaped after 3 bounces",
                 "captured (1 launches", "flew off (1 launches", "lost contact (1 launches"):
        assert text in svg, text
    # each outcome without a v_out is drawn with its own marker and colour
    styles = {(m, c) for m, c in plots.OUTCOME_STYLE.values()}
    assert len(styles) == len(plots.OUTCOME_STYLE) >= 3


def test_explore_figure_explains_empty_panels(svg_text):
    design = {"params": {"surface.params.eps": 0.1}, "v_critical": None, "v_critical_error": None,
              "v_critical_reason": "no launch at the top of the range escapes", "windows": [], "safe": True}
    svg = svg_text(plots.explore_figure({"designs": [design, {**design, "params": {"surface.params.eps": 0.2}}]},
                                        ["surface.params.eps"], units="cm", fmt="svg"))
    assert "no v_critical in this grid" in svg and "no launch at the top of the range escapes" in svg
    assert "no two-bounce window in this grid" in svg and "v_critical (cm/s)" in svg


def test_robustness_title_gives_the_units_of_sigma(svg_text):
    rows = [{"v_in": v, "p_bounces": {"2": 0.5, "11": 0.25}, "p_outcome": {"captured": 0.25},
             "nominal_outcome": "escaped", "nominal_bounces": 2} for v in (40.0, 41.0)]
    svg = svg_text(plots.robustness_figure({"rows": rows, "sigma_y": 0.1, "sigma_vy": 0.5, "samples": 4},
                                           units="cm", fmt="svg"))
    assert "sigma_y 0.1 cm, sigma_vy 0.5 cm/s" in svg and "v_in (cm/s)" in svg
    assert "escaped, 5+ bounces" in svg


def test_outcome_colours_are_the_same_in_every_figure(svg_text):
    """One bounce is black and captured grey in the sweep, in robustness and in compare:
    the colour of a count or an outcome means one thing across figures."""
    from matplotlib.colors import to_hex

    black, grey = to_hex(plots.BOUNCE_COLOURS[1]), to_hex(plots.OUTCOME_STYLE["captured"][1])
    assert black != grey
    sweep = svg_text(plots.sweep_figure(sweep_result(), "t", units="cm", fmt="svg")).lower()
    rows = [{"v_in": v, "p_bounces": {"1": 0.5}, "p_outcome": {"captured": 0.5},
             "nominal_outcome": "escaped", "nominal_bounces": 1} for v in (40.0, 41.0)]
    rob = svg_text(plots.robustness_figure({"rows": rows, "sigma_y": 0.1, "sigma_vy": 0.5, "samples": 4},
                                           units="cm", fmt="svg")).lower()
    for svg in (sweep, rob):
        assert black in svg and grey in svg


def test_explore_figure_choice_key_is_categorical(svg_text):
    """--vary simulation.model=full,simplified,ball: one tick named after each model, and no
    line joining the models as if they were points on a numeric axis."""
    designs = [{"params": {"simulation.model": m}, "v_critical": vc, "v_critical_error": 1e-5, "windows": [],
                "safe": True} for m, vc in (("full", 51.7), ("simplified", 56.1), ("ball", 59.2))]
    with matplotlib.rc_context({"svg.fonttype": "none"}):
        svg = plots.explore_figure({"designs": designs}, ["simulation.model"], units="cm", fmt="svg").decode()
    for m in ("full", "simplified", "ball"):
        assert f">{m}<" in svg, m
    # the joining line would be one path through the three points; markers only here
    assert not re.search(r'<path d="M [^"]*L [^"]*L [^"]*"[^>]*style="fill: none; stroke: #1f77b4', svg)


def test_precision_labels_do_not_overlap():
    """Eight points on top of each other: the labels placed never overlap one another."""
    plt, fig = plots._figure(figsize=(4, 3))
    ax = fig.add_subplot(1, 1, 1)
    ax.loglog([1, 1.01], [1e-4, 1.02e-4], "o")
    items = [(1.0, 1e-4, f"rtol 1e-{k:02d}", "C0") for k in range(8)]
    plots._place_labels(fig, ax, items)
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_window_extent(renderer) for t in ax.texts]
    assert 1 <= len(boxes) < len(items)           # some left out rather than stacked
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
    plt.close(fig)


def test_precision_figure_has_units_on_both_axes(svg_text):
    rows = [{"method": m, "rtol": r, "error": r * 10, "seconds": s * (2 if m.startswith("scipy") else 1)}
            for m in ("fabkit DOP853", "scipy DOP853") for r, s in ((1e-4, 0.2), (1e-6, 0.4), (1e-8, 0.8))]
    svg = svg_text(plots.precision_png(rows, title="t", fmt="svg"))
    assert "wall time for the launch set (s)" in svg and "relative, dimensionless" in svg
    assert re.search(r"rtol 1e-0[468]", svg)


def test_stock_picture_says_where_its_scale_is_clipped_and_shows_the_top_faces_grey():
    """The stock picture (fabkit.toolpath.cut.stock.stock_png): a scale clipped at its material
    end draws an arrow past the bar in the end's colour and marks the bound '>='; the flat
    top face on the design is the grey of the legend's swatch (pixels read back)."""
    from io import BytesIO

    import numpy as np
    from PIL import Image

    from fabkit.toolpath.cut.stock import _LEFT, make_stock, stock_png

    s = make_stock(40.0, 20.0, 0.25)
    design = np.zeros(s.z.shape)
    s.z[:] = 0.0
    s.z[40:120, 20:60] = 0.05          # material left, within the scale
    s.z[60:70, 30:40] = 0.4            # more than the scale shows: clipped

    def pixels(**kw):
        return np.asarray(Image.open(BytesIO(stock_png(s, design, envelope=0.0, **kw))).convert("RGB")).astype(int)

    clipped, whole = pixels(left_max=0.1), pixels(left_max=0.4)
    h, w = clipped.shape[:2]
    pw = w - 90                         # the picture's margins: left 60, right 30, top 34, bottom 86
    bw = max(60, min(pw - 152, 520))
    bar_end, by0 = 60 + (pw - bw) // 2 + bw, h - 52
    tip = clipped[by0 + 7, bar_end + 4]
    assert np.abs(tip - _LEFT).max() <= 1                     # the arrow, in the end's colour
    assert np.abs(whole[by0 + 7, bar_end + 4] - 255).max() == 0   # none when nothing is clipped
    swatch = clipped[h - 14, 66]
    top_face = clipped[34 + 5, 60 + 5]                          # a corner of the stock: flat, on the design
    assert np.abs(top_face - swatch).max() <= 1 and swatch.max() < 247   # grey, not the scale's white
