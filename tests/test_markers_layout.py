"""`fabkit markers`: the default layout lies on the uncut top face, clear of the milled
region by the tool's radius and off the ramp; a layout over the cut is refused; the page
draws the milled region; a large page is not rasterised at full resolution.

The milled region is checked against the surface itself, not fabkit's grid: for the
paper's family h = eta (e^{ax} - e^{bx}) + c y^2 + eps y e^{dx}, h < top is, at each x,
the open interval between the two roots in y of c y^2 + eps e^{dx} y + eta (e^{ax} - e^{bx})
- top (closed form); for the other specs, h on a 0.1 mm lattice."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import ROOT, write_spec

SPECS = sorted((ROOT / "specs").glob("*.yaml"))
PAPER_FAMILY = "eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x)"


def _variants():
    raw = yaml.safe_load((ROOT / "specs" / "surface.yaml").read_text())
    k = 2.54
    inch = copy.deepcopy(raw)                   # the same block in inches
    inch["name"], inch["units"] = "inch", "in"
    p = inch["surface"]["params"]
    p.update(a=p["a"] * k, b=p["b"] * k, c=p["c"] * k, d=p["d"] * k, eta=p["eta"] / k)
    inch["surface"].update(x=[-44 / k, 6 / k], y=[-12.5 / k, 12.5 / k], top=5 / k)
    inch["ball"]["diameter"] = 2.5 / k
    inch["ramp"]["heights"] = [0.2 / k, 4.5 / k]
    inch["simulation"].update(start=-30 / k, margin=0.5 / k)
    flip = copy.deepcopy(raw)                   # the channel the other way: rising toward -x, deeper eps
    flip["name"] = "flip"
    flip["surface"]["params"].update(a=-0.389, b=-0.306, d=-0.306, eps=0.4)
    flip["surface"]["x"] = [-6, 44]
    for key in ("ramp", "simulation"):
        flip.pop(key)
    return [("inch", inch), ("flip", flip)]


def _cut_intervals(spec, X):
    """Work X (n,) -> the cut's work Y interval at each (lo, hi; nan where none): closed form."""
    p = spec.surface.params
    s, x0, y0, top = spec.scale, float(spec.surface.x[0]), float(spec.surface.y[0]), float(spec.surface.top)
    x = X / s + x0
    A = p["c"]
    B = p["eps"] * np.exp(p["d"] * x)
    C = p["eta"] * (np.exp(p["a"] * x) - np.exp(p["b"] * x)) - top
    disc = B * B - 4 * A * C
    r = np.sqrt(np.where(disc > 0, disc, np.nan))
    lo, hi = (-B - r) / (2 * A), (-B + r) / (2 * A)
    return (lo - y0) * s, (hi - y0) * s


def _clearance_ok(spec, centre, paper, margin):
    """True when no point of the cut lies within ``margin`` of the paper's square."""
    L, W = (float(spec.surface.x[1]) - float(spec.surface.x[0])) * spec.scale, \
        (float(spec.surface.y[1]) - float(spec.surface.y[0])) * spec.scale
    cx, cy = centre
    X = np.arange(cx - paper / 2 - margin, cx + paper / 2 + margin + 1e-9, 0.05)
    X = X[(X >= 0) & (X <= L)]
    out = np.maximum(np.abs(X - cx) - paper / 2, 0.0)              # x distance outside the square
    reach = np.sqrt(np.maximum(margin * margin - out * out, 0.0))   # the disc's half chord there
    if spec.surface.height.replace(" ", "") == PAPER_FAMILY.replace(" ", ""):
        lo, hi = _cut_intervals(spec, X)
        lo, hi = np.maximum(lo, 0.0), np.minimum(hi, W)
        ok = np.isnan(lo) | (hi <= lo) | (hi <= cy - paper / 2 - reach) | (lo >= cy + paper / 2 + reach)
        return bool(np.all(ok))
    fns = spec.surface_functions()
    Y = np.arange(max(0.0, cy - paper / 2 - margin), min(W, cy + paper / 2 + margin) + 1e-9, 0.1)
    GX, GY = np.meshgrid(X, Y)
    h = fns.h(GX / spec.scale + float(spec.surface.x[0]), GY / spec.scale + float(spec.surface.y[0]))
    d = np.hypot(np.maximum(np.abs(GX - cx) - paper / 2, 0), np.maximum(np.abs(GY - cy) - paper / 2, 0))
    return not np.any((h < float(spec.surface.top)) & (d < margin))


@pytest.mark.parametrize("case", [p.name for p in SPECS] + [v[0] for v in _variants()])
def test_default_layout_on_the_uncut_top_face(tmp_path, case):
    from fabkit.lab.camera import MODULES, marker_layout
    from fabkit.spec import load_spec
    from fabkit.surface import Surface

    variants = dict(_variants())
    path = write_spec(tmp_path, variants[case]) if case in variants else ROOT / "specs" / case
    spec = load_spec(path)
    lay = marker_layout(spec, Surface.from_spec(spec))
    paper = lay.size * (1 + 2 / MODULES)
    margin = 0.5 * float(spec.tool.diameter)
    L = (float(spec.surface.x[1]) - float(spec.surface.x[0])) * spec.scale
    W = (float(spec.surface.y[1]) - float(spec.surface.y[0])) * spec.scale
    for i, c in enumerate(lay.centres):
        assert paper / 2 - 1e-9 <= c[0] <= L - paper / 2 + 1e-9 and paper / 2 - 1e-9 <= c[1] <= W - paper / 2 + 1e-9
        assert _clearance_ok(spec, c, paper, margin), (case, i, c)
        if spec.has("ramp"):
            # the ramp: from the block's end to the launch point, at most 3 ball diameters across
            s = spec.scale
            X1 = (float(spec.simulation.start) - float(spec.surface.x[0])) * s
            yc = (float(spec.simulation.y0) - float(spec.surface.y[0])) * s
            hw = 3.0 * float(spec.ball.diameter) * s
            apart = c[0] - paper / 2 >= X1 or abs(c[1] - yc) >= hw + paper / 2
            assert apart, (case, i, c)
    # the four papers do not overlap
    for i in range(4):
        for j in range(i + 1, 4):
            assert np.max(np.abs(lay.centres[i] - lay.centres[j])) >= paper


def test_a_layout_over_the_cut_is_refused(cli, tmp_path):
    """The paper's old default corner (480, 20) lies over the channel's rising end: exit 2,
    one line naming the marker and its key, nothing written."""
    raw = yaml.safe_load((ROOT / "specs" / "surface.yaml").read_text())
    raw["lab"] = {"markers": [[20, 20], [480, 20], [480, 230], [20, 230]]}
    spec = write_spec(tmp_path, raw)
    out = tmp_path / "m.pdf"
    code, _, err = cli("markers", spec, "-o", out)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err
    assert "lab.markers[1]" in err and "marker 1 at [480, 20]" in err and "milled surface" in err
    assert not out.exists()
    # the closed form agrees: the surface is below the top face under that paper
    from fabkit.spec import load_spec

    assert not _clearance_ok(load_spec(spec), (480.0, 20.0), 40.0, 0.0)


def test_the_page_draws_the_milled_region_and_the_ramp(cli, tmp_path):
    """The plan on the page (SVG, vector): the milled region as a filled contour in the
    page's grey, its edge, the ramp hatched, every marker's paper outlined."""
    out = tmp_path / "m.svg"
    code, text, err = cli("markers", ROOT / "specs" / "surface.yaml", "-o", out, "--json")
    assert code == 0, err
    svg = out.read_text()
    assert "#d1d1d1" in svg                 # 0.82 grey: the milled region's fill
    assert "<image" not in svg              # nothing rasterised
    assert "hatch" in svg.lower() or "pattern" in svg.lower()
    import json

    rec = json.loads(text)
    assert rec["ramp_footprint_mm"] is not None and rec["tool_margin_mm"] == pytest.approx(3.175)


def test_a_large_page_is_not_rasterised_at_full_resolution():
    """300 mm markers need an 854 x 1016 mm page: 470 Mpx at 600 dpi (about 1.9 GB while
    drawn). The PNG is rendered at the dpi that keeps it within MAX_PNG_PIXELS; A4 keeps
    600 dpi (true size)."""
    from fabkit.commands.markers import A4, MAX_PNG_PIXELS, PNG_DPI, page_size, png_dpi
    from fabkit.lab.camera import MarkerLayout

    assert png_dpi(A4) == PNG_DPI
    for size in (30.0, 300.0, 1000.0):
        w, h = page_size(MarkerLayout(size, np.zeros((4, 2))))
        dpi = png_dpi((w, h))
        assert (w / 25.4 * dpi) * (h / 25.4 * dpi) <= MAX_PNG_PIXELS
        assert dpi == PNG_DPI or (w / 25.4 * (dpi + 1)) * (h / 25.4 * (dpi + 1)) > MAX_PNG_PIXELS
