"""gcode._format_array and gcode._move_lines against plain per-value / per-row
versions written here (the programs' bytes depend on them: shortest fixed-point
strings, '-0' written '0'; modal G, X, Y, Z and F words omitted)."""

from __future__ import annotations

import numpy as np
import pytest

from fabkit.toolpath.program import gcode
from fabkit.toolpath.path import CUT, PLUNGE, RAPID


def _one(v: float, dec: int) -> str:
    t = f"{v:.{dec}f}"
    if dec > 0:
        t = t.rstrip("0").rstrip(".")
    return "0" if t in ("-0", "") else t


def _lines(txt, kinds, safe, feed_s, plunge_s):
    out, last, g, f = [], [txt[0][0], txt[0][1], safe], "G0", None
    for row, k in zip(txt, kinds):
        row = list(row)
        if row == last:
            continue
        words = []
        gk = "G0" if k == RAPID else "G1"
        if gk != g:
            words.append(gk)
        words += [a + s for a, s, p in zip("XYZ", row, last) if s != p]
        if k != RAPID:
            fk = plunge_s if k == PLUNGE else feed_s
            if fk != f:
                words.append("F" + fk)
            f = fk
        out.append(" ".join(words))
        last, g = row, gk
    return out


def _values(rng, n):
    a = np.round(rng.normal(0, rng.choice([1e-5, 1e-3, 1.0, 100.0, 1e4]), (n, 3)), int(rng.integers(0, 7)))
    for v, share in ((0.0, 0.2), (-0.0, 0.1), (-1e-5, 0.1), (0.00005, 0.05), (-2.5e-5, 0.05)):
        a[rng.random((n, 3)) < share] = v
    if n:
        a[rng.random((n, 3)) < 0.3] = a[0, 0]          # repeated values
        a[:, 0] = np.where(rng.random(n) < 0.3, np.roll(a[:, 0], 1), a[:, 0])
    return a


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("dec", [0, 1, 3, 4, 5])
def test_format_array_matches_per_value_format(seed, dec):
    rng = np.random.default_rng(seed)
    a = _values(rng, int(rng.integers(0, 80)))
    got = gcode._format_array(a, dec)
    assert got.shape == a.shape and got.dtype == object
    assert got.tolist() == [[_one(v, dec) for v in row] for row in a.tolist()]


def test_format_array_odd_values():
    a = np.array([[0.0, -0.0, -0.00004], [0.00005, 1e6, -123.45678], [np.inf, -np.inf, np.nan], [np.nan, 2.5, 2.5]])
    for dec in (0, 2, 4):
        assert gcode._format_array(a, dec).tolist() == [[_one(v, dec) for v in row] for row in a.tolist()]


@pytest.mark.parametrize("seed", range(20))
def test_move_lines_match_per_row_writer(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 80))
    txt = gcode._format_array(_values(rng, n), 4)
    kinds = rng.choice([RAPID, PLUNGE, CUT], n) if rng.random() < 0.7 else np.full(n, int(rng.integers(0, 3)))
    for feed_s, plunge_s in (("2500", "600"), ("100", "100")):
        want = _lines(txt.tolist(), kinds, "5", feed_s, plunge_s)
        assert gcode._move_lines(txt, kinds, "5", feed_s, plunge_s) == want
