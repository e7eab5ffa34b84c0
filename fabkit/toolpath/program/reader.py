"""Reading a written program back: the TEXT, not the moves that were meant.

:func:`read_program` is an independent reader of the G-code subset fabkit writes
(it shares no code with the writer, :mod:`fabkit.toolpath.program.gcode`): modal G0/G1,
G20/G21, G90, F, X/Y/Z, tool changes. It returns a :class:`Program` (the moves in
work millimetres and their feeds), which the verification of the cut
(:mod:`fabkit.toolpath.cut.verify`), the stock simulation, the run-time estimates
(:func:`estimate_time`) and the machine's planner and limits all start from.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ...errors import DesignError
from ...units import MM_PER_INCH

RAPID, FEED = 0, 1
_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_LINE = re.compile(r"(?:\s*[A-Z]\s*[-+]?(?:\d+\.?\d*|\.\d+))*\s*")
_COMMENT = re.compile(r"\([^()]*\)")
# the line shapes fabkit writes (upper case, no comment): [G0|G1] [X..] [Y..] [Z..] [F..]
# in this order, single spaces; read_program takes these without the general word loop.
# Possessive (no backtracking: faster); a line it misses takes the general path.
_NUM = r"([-+]?+(?:\d++(?:\.\d*+)?+|\.\d++))"
_FAST = re.compile(rf"(?:G([01]) ?)?+(?:X{_NUM} ?)?+(?:Y{_NUM} ?)?+(?:Z{_NUM} ?)?+(?:F{_NUM})?+")


@dataclass
class Program:
    """Moves read from a program.

    start:  (3,) mm, the position before the first move (nan where the program
            never set that axis before moving)
    points: (n, 3) mm, end point of each move, work coordinates
    kinds:  (n,) int8, RAPID (G0) | FEED (G1)
    feed:   (n,) mm/min, the feed of G1 moves (nan for G0)
    line:   (n,) int, 1-based line number of each move
    units:  'mm' | 'in', the program's (last) length unit
    tool:   (n,) int, the tool in the spindle for each move: the T number of the last
            M6 before it (-1 before any tool change)
    offset: (n,) int, the tool length offset in effect: the H number of the last G43
            (G43 without H: the tool in the spindle; -1 before any G43 and after G49)
    tool_changes: [(move index, tool number, line)], one per M6 (the move index is that
            of the first move made with the new tool)
    """

    start: np.ndarray
    points: np.ndarray
    kinds: np.ndarray
    feed: np.ndarray
    line: np.ndarray
    units: str
    lines: int
    tool: np.ndarray | None = None
    offset: np.ndarray | None = None
    tool_changes: list = field(default_factory=list)
    #: the reader's state after the last line read: {"pos": [x, y, z] mm, "tool": the
    #: tool M6 loaded (-1: none), "offset": the G43 H in effect (-1: none), "units"}
    end_state: dict | None = None

    def __post_init__(self):
        n = len(self.points)
        if self.tool is None:
            self.tool = np.full(n, -1, dtype=int)
        if self.offset is None:
            self.offset = np.full(n, -1, dtype=int)

    def segments(self):
        """(a, b): (n, 3) start and end points of every move, mm (a's Z is nan for the
        first move after a tool change, as for the first move of a program)."""
        a = np.vstack([self.start[None, :], self.points[:-1]]) if len(self.points) else self.points
        for i, _, _ in self.tool_changes:
            if 0 < i < len(a):
                a[i, 2] = np.nan      # after a tool change the tip's Z is unknown until set
        return a, self.points

    def __len__(self) -> int:
        return len(self.points)

    def tools(self) -> list[int]:
        """Tool numbers used, in the order of their first move (-1: moves before any M6)."""
        _, first = np.unique(self.tool, return_index=True)
        return [int(self.tool[i]) for i in np.sort(first)]

    def split(self) -> list[tuple[int, "Program"]]:
        """The program cut into runs of consecutive moves made with one tool, in order:
        [(tool number, Program)]. Each run's ``start`` is the position before its first
        move (nan after a tool change: the tip's height then depends on the new tool's
        length, so the run starts from an unknown position like a whole program)."""
        n = len(self.points)
        if n == 0:
            return []
        cuts = [0] + [int(i) for i in np.nonzero(np.diff(self.tool))[0] + 1] + [n]
        changed = {i for i, _, _ in self.tool_changes}
        out = []
        for i0, i1 in zip(cuts[:-1], cuts[1:]):
            if i0 == 0:
                start = self.start
            elif i0 in changed:
                start = np.full(3, np.nan)
            else:
                start = self.points[i0 - 1]
            out.append((int(self.tool[i0]), Program(
                start=np.array(start, dtype=float), points=self.points[i0:i1], kinds=self.kinds[i0:i1],
                feed=self.feed[i0:i1], line=self.line[i0:i1], units=self.units, lines=self.lines,
                tool=self.tool[i0:i1], offset=self.offset[i0:i1],
                tool_changes=[(i - i0, t, ln) for i, t, ln in self.tool_changes if i0 <= i < i1])))
        return out


def read_program(text: str) -> Program:
    """Parse G-code text (the subset fabkit emits) into moves in mm.

    Understood: comments in parentheses or after ';', G0 G1 (modal motion), G17,
    G20/G21 (units, modal), G90 (absolute; G91 is refused), G94, G54, G64 P, T M6 G43 H
    (the tool call: the moves are of the tool tip either way; ``Program.tool`` and
    ``Program.offset`` record, per move, the tool M6 loaded and the G43 H offset in
    effect, so a multi-tool program splits by tool; a T word selects the tool the next
    M6 loads, on the same line or before it (none: T0, as LinuxCNC); after M6, or a G43/G49 that changes the
    offset, the tip's Z is unknown (nan) until a move sets it, as the new tool's length
    moves the program's Z), G49 (offset cancelled), M3 S, M5,
    M2/M30 (end: later lines ignored), F (modal feed), X Y Z. Anything else raises
    DesignError naming the line (a program the reader cannot follow is not verified).
    """
    scale = 1.0
    units = "mm"
    motion = None
    feed = np.nan
    nan = float("nan")
    pos = [nan, nan, nan]     # the tip (plain floats: a line costs no array operations)
    start = None
    pts, kinds, feeds, where = [], [], [], []
    tools, offsets, changes = [], [], []
    selected = None      # T word: the tool the next M6 loads
    spindle_tool = -1    # the tool M6 loaded
    offset = -1          # G43 H in effect
    n_lines = 0
    fast = _FAST.fullmatch
    for ln, raw in enumerate(text.splitlines(), start=1):
        n_lines = ln
        m = fast(raw)
        if m is not None:
            # the common shapes (G0/G1 F X Y Z only): the words the general parse below would find
            g, x, y, z, f = m.groups()
            if g is not None:
                motion = 0 if g == "0" else 1
            if f is not None:
                feed = float(f) * scale
            if x is None and y is None and z is None:
                continue
            axes = {}
            if x is not None:
                axes["X"] = float(x) * scale
            if y is not None:
                axes["Y"] = float(y) * scale
            if z is not None:
                axes["Z"] = float(z) * scale
            end = False
        else:
            line = raw.split(";", 1)[0]
            if "(" in line:
                line = _COMMENT.sub(" ", line)
                if "(" in line or ")" in line:
                    raise DesignError(f"program line {ln}: unbalanced or nested comment")
            line = line.strip().upper()
            if not line:
                continue
            if not _LINE.fullmatch(line):
                raise DesignError(f"program line {ln}: cannot read {raw.strip()!r}")
            words = _WORD.findall(line)
            axes = {}
            end = False
            change = g43 = False
            h_word = None
            for letter, value in words:
                v = float(value)
                if letter == "G":
                    if v in (0, 1):
                        motion = int(v)
                    elif v == 20:
                        scale, units = MM_PER_INCH, "in"
                    elif v == 21:
                        scale, units = 1.0, "mm"
                    elif v == 91:
                        raise DesignError(f"program line {ln}: incremental mode G91 is not expected")
                    elif v == 43:
                        g43 = True
                    elif v == 49:
                        if offset != -1:
                            pos = [pos[0], pos[1], nan]
                        offset = -1
                    elif v not in (17, 90, 94, 54, 64):
                        raise DesignError(f"program line {ln}: unexpected G{value}")
                elif letter == "M":
                    if v in (2, 30):
                        end = True
                    elif v == 6:
                        change = True
                    elif v not in (3, 5):
                        raise DesignError(f"program line {ln}: unexpected M{value}")
                elif letter == "F":
                    feed = v * scale
                elif letter in "XYZ":
                    axes[letter] = v * scale
                elif letter in "TH":
                    if v != int(v) or v < 0:
                        raise DesignError(f"program line {ln}: {letter}{value} is not a tool number")
                    if letter == "T":
                        selected = int(v)
                    else:
                        h_word = int(v)
                elif letter not in "SP":
                    raise DesignError(f"program line {ln}: unexpected word {letter}{value}")
            # the order LinuxCNC executes a line in: T, M6, then G43 (whatever the word order)
            if change:
                # LinuxCNC's selection before any T word is T0 (no tool)
                spindle_tool = selected if selected is not None else 0
                changes.append((len(pts), spindle_tool, ln))
                pos = [pos[0], pos[1], nan]       # the tip's Z now depends on the new tool's length
            if g43:
                new_offset = h_word if h_word is not None else spindle_tool
                if new_offset != offset:
                    pos = [pos[0], pos[1], nan]   # the offset moves the program's Z, not the tool
                offset = new_offset
        if axes:
            if motion is None:
                raise DesignError(f"program line {ln}: axis words before any G0/G1")
            if start is None:
                start = pos
            new = [axes.get("X", pos[0]), axes.get("Y", pos[1]), axes.get("Z", pos[2])]
            if motion == FEED and not feed > 0:
                raise DesignError(f"program line {ln}: G1 without a feed rate")
            pts.append(new)
            kinds.append(motion)
            feeds.append(feed if motion == FEED else np.nan)
            where.append(ln)
            tools.append(spindle_tool)
            offsets.append(offset)
            pos = new
        if end:
            break
    if start is None:
        start = pos
    return Program(start=np.array(start, dtype=float), points=np.array(pts, dtype=float).reshape(-1, 3),
                   kinds=np.array(kinds, dtype=np.int8), feed=np.array(feeds, dtype=float),
                   line=np.array(where, dtype=int), units=units, lines=n_lines,
                   tool=np.array(tools, dtype=int), offset=np.array(offsets, dtype=int),
                   tool_changes=changes,
                   end_state={"pos": list(pos), "tool": spindle_tool, "offset": offset, "units": units})


def estimate_time(program: Program, rapid_mm_min: float) -> float:
    """Run time, s: G1 length / its feed, G0 length / ``rapid_mm_min``. Acceleration is
    ignored (a real machine is slower on short segments)."""
    a, b = program.segments()
    seg = np.nan_to_num(np.linalg.norm(b - a, axis=1))
    rate = np.where(program.kinds == RAPID, rapid_mm_min, program.feed)
    return float(np.sum(seg / rate) * 60.0)


__all__ = ["Program", "read_program", "estimate_time", "RAPID", "FEED"]
