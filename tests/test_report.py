"""fabkit report: the page renders in headless Chromium, states the verdict and why, draws
its 3-D view, and loads nothing from the network. The renderer takes results and
computes nothing, so it is fed results here (the command's run is checked by hand:
README); the command's bad-input path runs through main()."""

from __future__ import annotations

import io
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from conftest import PAPER, mutated, write_spec
from fabkit.report import render

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _png(color):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(2, 1))
    fig.patch.set_facecolor(color)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


#: a real setup sheet (fabkit gcode specs/bowl.yaml, an inch program), generated_at removed
SHEET = json.loads((Path(__file__).parent / "fixtures" / "report" / "bowl.setup.json").read_text())


def _results(safe: bool):
    x = np.linspace(-44, 6, 30)
    y = np.linspace(-12.5, 12.5, 16)
    X, Y = np.meshgrid(x, y, indexing="ij")
    z = np.minimum(3.27 * (np.exp(0.389 * X) - np.exp(0.306 * X)) + 0.0764 * Y ** 2 + 0.25 * Y * np.exp(0.306 * X), 5)
    ff = None if safe else {"height": 2.1722, "v_in": 55.16, "outcome": "flew_off", "reason": "z reaches top - margin",
                            "x": -7.653, "y": 4.49, "t": 1.16}
    chk = {"safe": safe, "highest_safe_height": 4.5 if safe else 2.1625, "first_failure": ff, "v_critical": 51.742707,
           "critical_height": 1.911, "reachable_windows": [{"lo": 33.58, "hi": 43.55, "height_lo": 0.8048,
                                                             "height_hi": 1.3537, "v_out_max": None},
                                                            {"lo": 51.5011, "hi": 51.5063, "height_lo": 1.89141,
                                                             "height_hi": 1.89145, "v_out_max": None}],
           "window_completeness": {"certain_width": 0.4366, "certain_width_at": 16.28,
                                   "spacing_near_critical": 0.1227, "certain_height_width": 0.01078},
           "machining": {"depth_mm": 53.3, "depth_ok": True, "radius_ok": True}, "heights": np.linspace(0.2, 4.5, 5),
           "model": "full", "damping": 0.127, "seconds": 6.1}
    return {"name": "surface", "units": "cm", "spec_path": "specs/surface.yaml", "version": "t", "generated_at": "now",
            "seconds": 60.0, "check": chk,
            "surface": {"x": x, "y": y, "z": z, "top": 5.0, "start": -30.0, "y0": 0.0},
            "sweep": {"png": _png("#ff00ff"), "v_critical": 51.742707, "v_critical_error": 1.7e-5, "windows": [],
                      "error_estimate": {"v_out_abs": 5e-9, "rtol_ref": 1e-11}, "launches": 400, "seconds": 40.0},
            "toolpath": {"png": _png("#00ffff"), "sheet": SHEET,
                         "seconds": {"plan": 9.3, "write": 0.2, "verify": 1.0},
                         "verify": {"max_gouge": 0.0052, "max_material_left": 0.0504, "checked_points": 40000}},
            "calibration": {"heights": np.linspace(0.2, 4.5, 50), "v_in": np.sqrt(np.linspace(0.2, 4.5, 50)) * 37.43,
                            "g": 980.665, "k": 0.4, "units": "cm", "seconds": 1e-4},
            "ramp_marks": [{"height": 1.911, "v_in": 51.742707, "label": "v_critical"},
                           {"height": 1.0569, "v_in": 38.565, "label": "2-bounce window 1 centre (33.58..43.55)",
                            "observable": True},
                           {"height": 1.89143, "v_in": 51.5037, "label": "2-bounce window 2 centre (51.50..51.51)",
                            "observable": False}],
            "scale": 10.0, "min_width": 0.1}


def test_setup_sheet_is_the_operators_sheet_with_units():
    """The page's setup sheet reads as setup.md does: each figure with its unit, no raw
    dump of Python values (``verified True``, ``tool_number None``, a bare ``feed 59.055``)."""
    page = render(_results(True))
    sheet = page[page.index('<div id="setup-sheet">'):]
    sheet = sheet[:sheet.index("</section>")]
    text = re.sub(r"<[^>]+>", " ", sheet)
    assert f"Feed {SHEET['feed']:g} in/min" in text and f"spindle {SHEET['spindle_rpm']:g} rpm" in text
    assert f"Largest gouge {SHEET['max_gouge']:.4g} in" in text
    assert f"{SHEET['passes']} raster passes" in text and "All lengths in  in" in text
    assert not re.search(r"\b(True|False|None)\b", text)


def test_accuracy_lines_come_from_the_checks_tolerances():
    """The page states the tolerances the check ran with, not fixed strings."""
    res = _results(True)
    res["check"]["tolerances"] = {"rel_tol": 3e-3, "v_rel_tol": 2e-7, "edge_rel_tol": 5e-8, "gap_rel_tol": 1e-4}
    page = render(res)
    assert "highest safe height to 3e-03 relative" in page
    assert "to 2e-07 relative)" in page and "edges to 5e-08 relative in v_in" in page


def test_self_contained():
    page = render(_results(True))
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", page)
    assert "<script src" not in page and "@import" not in page and "url(http" not in page
    assert 'id="verdict" class="verdict safe">SAFE<' in page


def test_no_v_critical_says_why():
    """specs/bowl.yaml: every launch escapes after one bounce; the page says so instead of
    printing an empty value with a unit."""
    res = _results(True)
    why = "every launch escapes after one bounce: v_critical is below the range (v_in from 118.362)"
    res["check"].update(v_critical=None, critical_height=None, v_critical_reason=why)
    res["sweep"].update(v_critical=None, v_critical_error=None, v_critical_reason=why)
    page = render(res)
    assert page.count(f"no v_critical over the ramp's speeds ({why})") == 1
    assert page.count(f"no v_critical ({why})") == 1
    assert "— cm/s" not in page and "± —" not in page


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
@pytest.mark.parametrize("safe", [True, False])
def test_renders_in_headless_chromium(tmp_path, safe):
    page = tmp_path / "r.html"
    page.write_text(render(_results(safe)))
    base = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
            f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run(base + ["--virtual-time-budget=3000", "--dump-dom", page.as_uri()], capture_output=True,
                         text=True, timeout=90).stdout
    word = "SAFE" if safe else "UNSAFE"
    assert re.search(rf'id="verdict" class="verdict {word.lower()}">{word}<', dom)
    if not safe:
        assert "release height 2.1722 cm" in dom and "z reaches top - margin" in dom
    _units_on_every_numeric_column(dom)
    _one_heading_per_section(dom)
    # the observable window is marked, the one 0.0004 cm (0.004 mm) wide set apart, its mark too
    assert "1 of 2 windows are observable" in dom
    assert re.search(r'<tr class="narrow"><td>2</td>', dom) and 'id="marks-narrow"' in dom
    assert "window 2 centre" in dom.split('id="marks-narrow"')[1] and "window 2 centre" not in \
        dom.split('id="marks-narrow"')[0].split('id="marks"')[1]
    m = re.search(r'id="surface3d"[^>]*data-rendered="(\d+)"', dom)
    assert m and int(m.group(1)) == 29 * 15          # every quad of the grid drawn by the script
    shot = tmp_path / "shot.png"
    subprocess.run(base + ["--window-size=1200,1800", f"--screenshot={shot}", page.as_uri()], capture_output=True,
                   timeout=90)
    import matplotlib.image as mpimg

    img = (mpimg.imread(shot)[..., :3] * 255).round()
    box = np.array([223, 243, 227] if safe else [251, 227, 225])   # the verdict's background
    assert np.sum(np.all(np.abs(img - box) <= 2, axis=-1)) > 500
    assert np.sum(np.all(np.abs(img - [255, 0, 255]) <= 2, axis=-1)) > 500   # the sweep figure is shown
    # the 3-D view painted the surface (sand and blue shades, not the empty background)
    sand = np.all(np.abs(img - [225, 196, 140]) <= 40, axis=-1) & (img[..., 0] > img[..., 2] + 40)
    assert sand.sum() > 2000


class _Tables:
    """The tables of an HTML page (the browser's DOM): per table, its rows as [(tag, text)]."""

    def __init__(self, page: str):
        from html.parser import HTMLParser

        tables, stack = [], []

        class P(HTMLParser):
            def handle_starttag(self, tag, attrs):
                if tag == "table":
                    stack.append([])
                elif tag == "tr" and stack:
                    stack[-1].append([])
                elif tag in ("td", "th") and stack and stack[-1]:
                    stack[-1][-1].append([tag, ""])

            def handle_endtag(self, tag):
                if tag == "table" and stack:
                    tables.append(stack.pop())

            def handle_data(self, data):
                if stack and stack[-1] and stack[-1][-1]:
                    stack[-1][-1][-1][1] += data

        P().feed(page)
        self.tables = tables


NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
UNIT = re.compile(r"\(([^)]*[A-Za-zµ°%/²][^)]*)\)")


def _units_on_every_numeric_column(page: str) -> None:
    """Every column of every table whose cells are all numbers, not all whole (a measured
    quantity, not a count or an ordinal), names its unit in its header: 'H (cm)'."""
    tables = _Tables(page).tables
    assert tables
    seen = 0
    for rows in tables:
        head = next((r for r in rows if r and all(t == "th" for t, _ in r)), None)
        body = [r for r in rows if r and all(t == "td" for t, _ in r)]
        if head is None or not body:
            continue
        for j, (_, name) in enumerate(head):
            cells = [r[j][1].strip() for r in body if j < len(r) and r[j][1].strip() not in ("", "—", "-")]
            if not cells or not all(NUMBER.match(c) for c in cells):
                continue
            if all(float(c) == int(float(c)) and "." not in c and "e" not in c.lower() for c in cells):
                continue                              # counts and ordinals
            seen += 1
            assert UNIT.search(name), f"column '{name.strip()}' ({cells[:3]}...) has no unit"
    assert seen >= 6                                  # windows, calibration and marks tables


def _one_heading_per_section(page: str) -> None:
    for sec in re.findall(r"<section>(.*?)</section>", page, flags=re.S):
        assert len(re.findall(r"<h2[ >]", sec)) == 1, sec[:200]
    heads = re.findall(r"<h[23][^>]*>(.*?)</h[23]>", page)
    assert len(heads) == len(set(heads)), heads


def test_windows_table_and_marks_carry_units_and_the_observable_ones():
    """Without a browser: the rendered page's tables (windows, calibration, marks) put a
    unit on every numeric column, each section has one heading, the setup sheet's title
    is its section's heading; the window narrower than min_width (0.1 cm = 1 mm) is set apart."""
    page = render(_results(True))
    _units_on_every_numeric_column(page)
    _one_heading_per_section(page)
    assert page.count("Setup sheet") == 1 and "<h2>Setup sheet: " in page
    assert "1 of 2 windows are observable: at least 0.1 cm (1 mm) wide in release height" in page
    assert "Every window wider than 0.01078 cm in release height" in page
    # a page given no minimum width says nothing about observability (an older caller)
    res = _results(True)
    del res["min_width"], res["scale"]
    assert "observable" not in render(res).split("Ramp calibration")[0]


def test_bad_spec_exit_2_nothing_written(cli, tmp_path):
    spec = write_spec(tmp_path, mutated({}, drop=("tool",)))
    code, out, err = cli("report", spec, "-o", "r.html")
    assert code == 2 and "tool: missing section (needed by report)" in err
    assert not (tmp_path / "r.html").exists()


def test_calibration_caption_says_how_the_speeds_were_made():
    """With the ramp's losses the page names the descent and its accuracy, not the closed
    form; without them it gives the closed form."""
    from types import SimpleNamespace

    res = _results(True)
    assert "Exact closed form" in render(res)
    res["calibration"]["entry"] = SimpleNamespace(closed_form=False, method="descent along the ramp, damping 0.127 1/s",
                                                  profile="fabkit", mu=0.127, c=0.0, error=1e-9)
    page = render(res)
    assert "descent of the ramp with its losses (descent along the ramp, damping 0.127 1/s)" in page
    assert "to ~1e-09 relative" in page and "Exact closed form" not in page
