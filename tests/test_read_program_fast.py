"""reader.read_program against a model of the programs written inside this test.

Random programs are generated together with what they mean: a small machine model here
(motion, feed, units, tool, offset, tip position, as the reader's docstring states
LinuxCNC does) tracks each line's effect while the line is written in a random shape:
the shapes fabkit writes ([G0|G1] [X] [Y] [Z] [F], single spaces) and others (words in
other orders, lower case, extra spaces, G01, comments, G20 inch units, T / M6 / G43 H /
G49 lines, M3 S, blank lines, M2 with lines after it). The Program read must be the
model's, with the reader's fast path for the common shapes and without it (a pattern
that never matches sends every line down the general word loop), and bad lines are
refused by both with the same message.
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from fabkit.errors import DesignError
from fabkit.toolpath.program import reader as readback
from fabkit.units import MM_PER_INCH

NAN = float("nan")


def _num(rng, v: float) -> str:
    """v written in one of the number shapes G-code allows."""
    s = f"{v:.{int(rng.integers(0, 5))}f}"
    r = rng.random()
    if r < 0.15 and "." in s:
        s = s.rstrip("0")                    # '12.' or '0.5'
    if r > 0.85 and s.startswith("0."):
        s = s[1:]                            # '.5'
    if r > 0.85 and s.startswith("-0."):
        s = "-" + s[2:]                      # '-.5'
    if 0.5 < r < 0.55 and not s.startswith("-"):
        s = "+" + s
    return s


class _Model:
    """The meaning of the lines written so far (lengths in mm)."""

    def __init__(self):
        self.scale, self.units = 1.0, "mm"
        self.motion = None
        self.feed = NAN
        self.pos = [NAN, NAN, NAN]
        self.start = None
        self.selected, self.tool, self.offset = None, -1, -1
        self.pts, self.kinds, self.feeds, self.where = [], [], [], []
        self.tools, self.offsets, self.changes = [], [], []

    def move(self, ln: int, axes: dict) -> None:
        if self.start is None:
            self.start = self.pos
        new = [axes.get(a, p) for a, p in zip("XYZ", self.pos)]
        self.pts.append(new)
        self.kinds.append(self.motion)
        self.feeds.append(self.feed if self.motion == 1 else NAN)
        self.where.append(ln)
        self.tools.append(self.tool)
        self.offsets.append(self.offset)
        self.pos = new


def _write(rng, words: list[str], canonical: bool) -> str:
    """A line of ``words``: as given (fabkit's shape) or shuffled, spaced and cased at random."""
    if canonical:
        return " ".join(words)
    words = list(words)
    if rng.random() < 0.5:
        rng.shuffle(words)
    sep = [" ", "  ", "", "\t"][int(rng.integers(0, 4))]
    line = sep.join(words)
    if rng.random() < 0.3:
        line = line.lower()
    if rng.random() < 0.3:
        line = "  " + line + " "
    if rng.random() < 0.3:
        line = line + " (note)" if rng.random() < 0.5 else "(a) " + line + " ; tail"
    return line


def _program(rng, n: int):
    """(text, model) for a random program of about ``n`` lines."""
    m = _Model()
    lines = ["(header)", "G17 G21 G90 G94 G54", "G64 P0.005"]
    if rng.random() < 0.3:
        lines.append("G20")
        m.scale, m.units = MM_PER_INCH, "in"
    ln = len(lines)
    for _ in range(n):
        ln = len(lines) + 1
        r = rng.random()
        canonical = rng.random() < 0.6
        if r < 0.75:                                          # a move
            words = []
            g = m.motion
            if m.motion is None or rng.random() < 0.3:
                g = int(rng.integers(0, 2))
                words.append(("G0" if g == 0 else "G1") if canonical or rng.random() < 0.7
                             else ("G00" if g == 0 else "G01"))
            axes = {}
            for a in "XYZ":
                if rng.random() < 0.6:
                    s = _num(rng, float(rng.normal(0, 50)))
                    words.append(a + s)
                    axes[a] = float(s) * m.scale
            if not axes:
                s = _num(rng, float(rng.normal(0, 5)))
                words.append("Z" + s)
                axes["Z"] = float(s) * m.scale
            feed = m.feed
            if g == 1 and (not m.feed > 0 or rng.random() < 0.3):
                s = _num(rng, float(rng.uniform(1, 3000)))
                if float(s) <= 0:
                    s = "100"
                words.append("F" + s)
                feed = float(s) * m.scale
            elif rng.random() < 0.05:                         # F with G0: sets the modal feed
                s = str(int(rng.integers(1, 3000)))
                words.append("F" + s)
                feed = float(s) * m.scale
            m.motion, m.feed = g, feed
            m.move(ln, axes)
            lines.append(_write(rng, words, canonical))
        elif r < 0.80:
            lines.append(["", "(a comment)", "; a comment", "   "][int(rng.integers(0, 4))])
        elif r < 0.84:                                        # units
            if rng.random() < 0.5:
                m.scale, m.units = MM_PER_INCH, "in"
                lines.append(_write(rng, ["G20"], canonical))
            else:
                m.scale, m.units = 1.0, "mm"
                lines.append(_write(rng, ["G21"], canonical))
        elif r < 0.90:                                        # a tool change
            t = int(rng.integers(0, 6))
            words = [f"T{t}", "M6"]
            if rng.random() < 0.5:
                words += ["G43", f"H{int(rng.integers(0, 6))}"] if rng.random() < 0.5 else ["G43"]
            m.selected = t
            m.tool = t
            m.changes.append((len(m.pts), t, ln))
            m.pos = [m.pos[0], m.pos[1], NAN]
            if "G43" in words:
                h = int(words[-1][1:]) if words[-1].startswith("H") else m.tool
                if h != m.offset:
                    m.pos = [m.pos[0], m.pos[1], NAN]
                m.offset = h
            lines.append(_write(rng, words, canonical))
        elif r < 0.93:                                        # M6 alone, T on an earlier line
            m.tool = m.selected if m.selected is not None else 0
            m.changes.append((len(m.pts), m.tool, ln))
            m.pos = [m.pos[0], m.pos[1], NAN]
            lines.append("M6")
        elif r < 0.96:                                        # G43 / G49 alone
            if rng.random() < 0.5:
                if m.offset != -1:
                    m.pos = [m.pos[0], m.pos[1], NAN]
                m.offset = -1
                lines.append("G49")
            else:
                h = int(rng.integers(0, 4))
                if h != m.offset:
                    m.pos = [m.pos[0], m.pos[1], NAN]
                m.offset = h
                lines.append(_write(rng, ["G43", f"H{h}"], canonical))
        else:
            lines.append(["M3 S16000", "M5", "G94", "G64 P0.01"][int(rng.integers(0, 4))])
    if rng.random() < 0.3:
        lines.append("M2")
        ln = len(lines)
        lines += ["G91 X1", "this is not read"]             # after the end: ignored
    else:
        ln = len(lines)
    return "\n".join(lines) + "\n", m, ln


def _same(p: readback.Program, m: _Model, n_lines: int) -> None:
    start = m.start if m.start is not None else m.pos
    np.testing.assert_array_equal(p.start, np.array(start, dtype=float))
    np.testing.assert_array_equal(p.points, np.array(m.pts, dtype=float).reshape(-1, 3))
    np.testing.assert_array_equal(p.kinds, np.array(m.kinds, dtype=np.int8))
    assert p.kinds.dtype == np.int8
    np.testing.assert_array_equal(p.feed, np.array(m.feeds, dtype=float))
    np.testing.assert_array_equal(p.line, np.array(m.where, dtype=int))
    np.testing.assert_array_equal(p.tool, np.array(m.tools, dtype=int))
    np.testing.assert_array_equal(p.offset, np.array(m.offsets, dtype=int))
    assert p.units == m.units
    assert p.lines == n_lines
    assert p.tool_changes == m.changes


@pytest.fixture(params=["fast", "general"])
def reader(request, monkeypatch):
    if request.param == "general":
        monkeypatch.setattr(readback, "_FAST", re.compile(r"(?!)"))    # matches nothing
    return readback.read_program


@pytest.mark.parametrize("seed", range(12))
def test_random_programs_read_as_modelled(reader, seed):
    rng = np.random.default_rng(seed)
    text, m, n_lines = _program(rng, int(rng.integers(1, 400)))
    _same(reader(text), m, n_lines)


def test_fabkit_shapes_take_the_fast_path():
    for line in ["X486 Y4.3772", "Z1", "G1 Z0 F600", "X487 Z-0.0057 F2500", "G0 Z1", "G1 X1 Y2 Z3 F10", "X.5"]:
        assert readback._FAST.fullmatch(line), line
    for line in ["x1", " X1", "G01 X1", "Y1 X2", "X1 ; c", "X1 (c)", "G2 X1", "X1  Y2", "X1..2", "T1 M6"]:
        assert not readback._FAST.fullmatch(line), line


BAD = [
    ("G91 X1", "incremental mode G91 is not expected"),
    ("G2 X1 Y1", "unexpected G2"),
    ("X1 Q2", "unexpected word Q2"),
    ("X1..2", "cannot read 'X1..2'"),
    ("X1 (open", "unbalanced or nested comment"),
    ("M8", "unexpected M8"),
    ("T1.5 M6", "T1.5 is not a tool number"),
]


@pytest.mark.parametrize("bad, message", BAD)
@pytest.mark.parametrize("seed", range(3))
def test_bad_lines_refused_with_the_same_message(reader, bad, message, seed):
    rng = np.random.default_rng(100 + seed)
    text, _, _ = _program(rng, 60)
    lines = text.splitlines()
    end = lines.index("M2") if "M2" in lines else len(lines)
    k = int(rng.integers(3, end + 1))                    # after the header, before any M2
    lines.insert(k, bad)
    with pytest.raises(DesignError) as e:
        reader("\n".join(lines))
    assert str(e.value) == f"program line {k + 1}: {message}"


@pytest.mark.parametrize("text, message", [
    ("G21\nX1 Y2\n", "program line 2: axis words before any G0/G1"),
    ("G0 X0\nG1 X1 Y2\n", "program line 2: G1 without a feed rate"),
    ("G1 X1 F0\n", "program line 1: G1 without a feed rate"),
    ("G0 X0\nG1 F-5 X1\n", "program line 2: G1 without a feed rate"),
])
def test_motion_and_feed_refusals(reader, text, message):
    with pytest.raises(DesignError) as e:
        reader(text)
    assert str(e.value) == message
