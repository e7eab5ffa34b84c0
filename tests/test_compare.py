"""``fabkit compare``: the lab's published T_n fit beside the apparatus's (checked against an
independent numpy fit of the windows the sweep reports), and the four panels' shared x range."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
G_CM = 980.665          # standard gravity, cm/s^2


def _spec(tmp_path, model: str) -> Path:
    text = (ROOT / "specs" / "surface.yaml").read_text()
    assert "  model: ball " in text
    p = tmp_path / f"surface_{model}.yaml"
    p.write_text(text.replace("  model: ball ", f"  model: {model} "))
    return p


def _no_pde(monkeypatch):
    # the phi^4 panel costs minutes on a loaded machine and is not what these tests check:
    # a separatrix-map panel stands in for it
    from fabkit.waves import compare as cmp

    monkeypatch.setattr(cmp, "pde_panel", lambda n, **kw: cmp.map_panel(200))


def test_compare_json_sets_the_labs_published_fit_beside_the_sweeps_own(cli, tmp_path, monkeypatch):
    _no_pde(monkeypatch)
    spec = _spec(tmp_path, "full")
    code, out, err = cli("compare", spec, "--pde-samples", "8", "--ode-samples", "8", "--json", "--no-progress")
    assert code == 0, err
    r = json.loads(out)
    paper = r["paper"]
    # the lab's coefficients exactly as published (Goodman et al., T_n = 0.961 n + 0.755, n = 2..6)
    assert paper["lab"]["T"] == 0.961 and paper["lab"]["delta"] == 0.755
    assert paper["lab"]["n"] == [2, 3, 4, 5, 6]
    for row in paper["by_n"]:
        assert row["lab"] == pytest.approx(0.961 * row["n"] + 0.755, rel=1e-15)
    app = r["panels"][-1]
    assert app["model"] == "full" and "full model" in app["name"] and paper["fabkit"]["model"] == "full"
    assert paper["fabkit"]["length_unit"] == "cm"
    # the two-bounce windows the sweep reports, each with the T_n at its v_out maximum (inside it)
    wins = [w for w in app["windows"] if w["bounces"] == 2 and w.get("T_n") is not None]
    assert len(wins) >= 3
    for w in wins:
        assert w["lo"] - w["edge_error"] <= w["v_in_max"] <= w["hi"] + w["edge_error"]
    t = np.array([w["T_n"] for w in sorted(wins, key=lambda w: w["lo"])])
    # n numbered independently: T_shape from the closed form 2 pi / sqrt(2 c g / (1 + 2/5)) (c y^2
    # channel, solid ball rolling), n_0 = floor(T_0 / T_shape), then consecutive differences
    t_shape = 2 * math.pi / math.sqrt(2 * 0.0764 * G_CM / 1.4)
    assert paper["fabkit"]["T_shape"] == pytest.approx(t_shape, rel=1e-6)
    n = [math.floor(t[0] / t_shape)]
    for a, b in zip(t[:-1], t[1:]):
        n.append(n[-1] + max(1, round((b - a) / t_shape)))
    T, delta = np.polyfit(n, t, 1)
    assert paper["fabkit"]["n"] == n
    assert paper["fabkit"]["T"] == pytest.approx(T, rel=1e-9)
    assert paper["fabkit"]["delta"] == pytest.approx(delta, rel=1e-9)
    assert app["tn_fit"]["T"] == paper["fabkit"]["T"]
    for row in paper["by_n"]:
        assert row["fabkit"] == pytest.approx(T * row["n"] + delta, rel=1e-9)
        assert row["rel_diff"] == pytest.approx((T * row["n"] + delta) / row["lab"] - 1, rel=1e-9)
    # the summary names the model and prints both lines
    code, out, err = cli("compare", spec, "--pde-samples", "8", "--ode-samples", "8", "--no-progress")
    assert code == 0, err
    assert "T_n, the lab (published): 0.961 n + 0.755 s, n = 2..6" in out
    assert f"T_n, fabkit (full model, lengths in cm): {T:.3f} n + {delta:.3f} s" in out
    # the lab's n = 2 lies below fabkit's first window (n = 3): its line is extrapolated there
    assert n[0] == 3 and f"n=2: {T * 2 + delta:.3f} vs 2.677 (" in out and "%, extrapolated), n=3:" in out


def test_lab_comparison_fits_the_labs_n_alone():
    from fabkit.waves.compare import lab_tn_comparison

    ns, tn = [3, 4, 5, 6, 7, 9], [3.6, 4.65, 5.69, 6.72, 7.74, 9.74]
    c = lab_tn_comparison({"T": 1.0, "delta": 0.6, "n": ns, "T_n": tn, "T_shape": 0.97}, model="ball",
                          length_unit="in")
    T, delta = np.polyfit(ns[:4], tn[:4], 1)
    assert c["fabkit_over_lab_n"]["n"] == [3, 4, 5, 6]
    assert c["fabkit_over_lab_n"]["T"] == pytest.approx(T, rel=1e-12)
    assert c["fabkit_over_lab_n"]["delta"] == pytest.approx(delta, rel=1e-12)
    assert [r["fabkit_window"] for r in c["by_n"]] == [None, 3.6, 4.65, 5.69, 6.72]
    # the largest difference over the lab's n that the windows cover (3..6), not n = 2
    assert c["max_rel_diff"] == pytest.approx(max(abs((n + 0.6) / (0.961 * n + 0.755) - 1) for n in (3, 4, 5, 6)))
    none = lab_tn_comparison({"T": None, "delta": None, "n": [3], "T_n": [3.6], "T_shape": 0.97}, model="full",
                             length_unit="cm")
    assert none["fabkit"]["T"] is None and none["max_rel_diff"] is None


def test_compare_panels_share_the_x_range_and_name_the_apparatus_model():
    from fabkit.plots import compare_axes, compare_figure
    from fabkit.waves.compare import SPAN, map_panel

    m = map_panel(300)
    wide = map_panel(300, span=(0.3, 1.5))     # an apparatus samples its ramp's wider range
    app = dict(wide, name="the apparatus (surface, ball model)", params="ball model, damping 0.127 1/s",
               units="cm/s")
    plt, fig = compare_axes([m, m, m, app], span=SPAN)
    axes = fig.axes
    assert len(axes) == 4
    for ax in axes:
        assert ax.get_xlim() == pytest.approx(SPAN, abs=1e-12)
        assert ax.get_xlabel() == "v_in / v_critical"
    title = axes[3].get_title()
    assert "ball model" in title
    # the wider panel says how much of it is shown: the map's own samples in 0.65..1.25 (+-1 % pad)
    v = np.asarray(wide["v_in"]) / wide["v_critical"]
    k = int(((v >= SPAN[0] - 0.006) & (v <= SPAN[1] + 0.006)).sum())
    assert f"{k} of 300 launches in this range" in title
    # nothing drawn outside the shared range
    for line in axes[3].get_lines():
        x = np.asarray(line.get_xdata(), dtype=float)
        if x.size > 1 or (x.size == 1 and x[0] != 1.0):
            assert x.min() >= SPAN[0] - 0.006 and x.max() <= SPAN[1] + 0.006
    plt.close(fig)
    png = compare_figure([m, m, m, app])
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
