"""G-code writer: a pure function from a :class:`~fabkit.toolpath.path.Toolpath` and a
:class:`MachineProfile` to program text.

The differences between controllers are DATA (:data:`DIALECTS`): the words a
dialect accepts, its preamble, program end, comment style and line length. The
writer has no per-dialect branches.

Every program is: a header comment block (lengths in the program's units), the
modal preamble (G17 plane, G21 mm or G20 inch, G90 absolute, G94 feed per minute,
G54 work offset; LinuxCNC also G64 P: path blending held to half the machining
tolerance), the tool call when ``tool.number`` is given (LinuxCNC ``T1 M6 G43 H1``:
change and apply the tool's length offset; grbl has no tool changer and no M6 by
default, so the tool is named in a comment and changed by hand before the start),
a rapid to the safe height, spindle on (M3 S), the moves (G0 and G1 only), a rapid
back to the safe height, spindle off (M5), a rapid at the safe height to the park
position (``machining.park``, default X0 Y0) and the program end (M2 or M30). Modal words are not repeated:
G0/G1, F and unchanged axis words are written only when they change. Coordinates
have fixed decimals (4 in mm, 5 in inch, more if the tolerance needs them) so the
rounding error (half a unit in the last place, per axis) stays below 1/20 of the
tolerance; :mod:`fabkit.toolpath.cut.verify` reads the TEXT back, so whatever rounding
remains is part of the verified figures. Same toolpath and profile -> same text.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ...units import PROGRAM_UNITS as UNITS, ProgramUnits as Units, MM_PER_INCH, coordinate_decimals  # noqa: F401
from ..path import CUT, PLUNGE, RAPID, Toolpath

#: rapid rate assumed for time estimates, mm/min (G0 speed is set by the machine,
#: not the program; 5000 mm/min is a typical hobby router/mill figure)
DEFAULT_RAPID_MM_MIN = 5000.0


@dataclass(frozen=True)
class Dialect:
    """What one controller accepts. Data, not code."""

    name: str
    words: frozenset            # G and M words the writer may emit
    preamble: tuple             # modal words on the first line, in order ({units} is G20/G21)
    program_end: str
    comment_open: str = "("
    comment_close: str = ")"
    max_line: int = 70          # characters per line, comment lines included
    path_blending: bool = False  # G64 P<tolerance/2> (LinuxCNC trajectory blending)
    tool_change: str | None = None   # the tool call ({n}: tool.number); None: a comment only


DIALECTS: dict[str, Dialect] = {
    "linuxcnc": Dialect(
        name="linuxcnc",
        words=frozenset({"G0", "G1", "G17", "G20", "G21", "G90", "G94", "G54", "G64", "G43", "M3", "M5", "M6",
                         "M2"}),
        preamble=("G17", "{units}", "G90", "G94", "G54"),
        program_end="M2",
        max_line=250,
        path_blending=True,
        tool_change="T{n} M6 G43 H{n}",
    ),
    # grbl 1.1: no %, no O or N words needed, no tool change (M6 is not in its
    # default build), comments in plain parentheses; 80-character line buffer, so
    # lines are kept to 70.
    "grbl": Dialect(
        name="grbl",
        words=frozenset({"G0", "G1", "G17", "G20", "G21", "G90", "G94", "G54", "M3", "M5", "M30"}),
        preamble=("G17", "{units}", "G90", "G94", "G54"),
        program_end="M30",
        max_line=70,
    ),
}


@dataclass(frozen=True)
class MachineProfile:
    """Everything the writer needs besides the moves. Lengths mm, feeds mm/min.

    header: (key, value) pairs written as comments after the standard ones
    tool_number: the tool's number in the machine's tool table (None: no tool call)
    park: (X, Y) work mm where the program ends, at the safe height
    """

    dialect: str = "linuxcnc"
    units: str = "mm"
    feed: float = 2500.0
    plunge: float = 600.0
    spindle: float = 16000.0
    safe_z: float = 5.0
    tolerance: float = 0.01
    scallop: float = 0.05
    rapid: float = DEFAULT_RAPID_MM_MIN
    header: tuple = field(default_factory=tuple)
    tool_number: int | None = None
    park: tuple = (0.0, 0.0)

    @property
    def d(self) -> Dialect:
        return DIALECTS[self.dialect]

    @property
    def u(self) -> Units:
        return UNITS[self.units]

    @property
    def decimals(self) -> int:
        """Coordinate decimals: the unit's default, raised until half a unit in the
        last place is at most tolerance/20 (capped at 6)."""
        return coordinate_decimals(self.units, self.tolerance)

    @property
    def rounding_mm(self) -> float:
        """Largest rounding error of one coordinate, mm (half a unit in the last place)."""
        return 0.5 * 10.0 ** -self.decimals * self.u.mm_per_unit


def profile_from_spec(spec, surface=None) -> MachineProfile:
    """The machine profile of a spec (sections tool, stock, machining; surface for
    the stock size). Header lines describe the job for the operator, in the program's units."""
    m, t, st = spec.machining, spec.tool, spec.stock
    u = UNITS[m.units]
    # the spec's file name, not the path as typed: `gcode a.yaml` and `gcode /abs/a.yaml`
    # give the same program (the setup sheet records the full path)
    header = [("spec", Path(spec.path).name), ("name", spec.name),
              ("tool", (f"T{t.number} " if t.number is not None else "")
               + f"{t.shape}-end mill, diameter {_length(t.diameter, u)}")]
    if surface is not None:
        L, W = surface.stock_size_mm
        k = 1.0 / u.mm_per_unit
        header.append(("stock", f"{L * k:.6g} x {W * k:.6g} x {st.thickness * k:.6g} {u.name} (X x Y x Z)"))
    return MachineProfile(dialect=m.dialect, units=m.units, feed=m.feed, plunge=m.plunge,
                          spindle=m.spindle, safe_z=m.safe_height, tolerance=m.tolerance,
                          scallop=m.scallop, header=tuple(header), tool_number=t.number,
                          park=tuple(float(v) for v in m.park))


def _length(mm: float, u: Units) -> str:
    """A length for a comment, in the program's units (6 significant digits)."""
    return f"{mm / u.mm_per_unit:.6g} {u.name}"


def _ascii_comment(text: str) -> str:
    """Comment-safe text: ASCII printable, no parentheses or semicolons."""
    out = []
    for ch in text:
        o = ord(ch)
        if ch in "()":
            ch = "[" if ch == "(" else "]"
        elif ch == ";" or o < 32 or o > 126:
            ch = "?"
        out.append(ch)
    return "".join(out)


def _comment_lines(key: str, value: str, d: Dialect) -> list[str]:
    """One header item as comment lines within the dialect's line length. Every
    comment starts with a lower-case word or '-' (LinuxCNC treats comments starting
    with MSG, DEBUG, PRINT, LOG, PROBE... specially; these never match)."""
    body = _ascii_comment(f"{key}: {value}" if key else f"  {value}")
    room = d.max_line - len(d.comment_open) - len(d.comment_close)
    lines = []
    while len(body) > room:
        cut = body.rfind(" ", 0, room)
        cut = cut if cut > room // 2 else room
        lines.append(body[:cut])
        body = "  " + body[cut:].lstrip()
    lines.append(body)
    return [f"{d.comment_open}{s}{d.comment_close}" for s in lines]


def _fmt_duration(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60} min" if m >= 60 else f"{max(m, 0)} min" if m else f"{seconds:.0f} s"


def estimate_seconds(points: np.ndarray, kinds: np.ndarray, start: np.ndarray, profile: MachineProfile) -> float:
    """Run time, s, from move lengths: G1 at the plunge or cutting feed, G0 at
    ``profile.rapid``. Acceleration is ignored, so short segments run slower than
    this on a real machine (typically 5-30 % on dense finishing programs)."""
    pts = np.vstack([start[None, :], points])
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    seg = np.nan_to_num(seg)
    rate = np.where(kinds == RAPID, profile.rapid, np.where(kinds == PLUNGE, profile.plunge, profile.feed))
    return float(np.sum(seg / rate) * 60.0)


_TRAILING_ZEROS = re.compile(r"0+\n")   # every string has a '.' when dec > 0: only decimals go
_MINUS_ZERO = re.compile(r"^-0$", re.MULTILINE)


def _format_array(values: np.ndarray, dec: int) -> np.ndarray:
    """(n, 3) floats -> (n, 3) shortest fixed-point strings with at most ``dec``
    decimals ('12.5', '-0.0312', '0'; never '-0'). Each distinct value is formatted
    once (a toolpath repeats its X and Y values), all by one '%' operation (the same
    rounding as '%.{dec}f' % v per value); the trailing zeros, a bare '.' and '-0' go
    by text substitutions over the result. (-0.0 and 0.0 are one value to np.unique;
    both are written '0'.)"""
    flat = values.ravel()
    if not flat.size:
        return np.empty(values.shape, dtype=object)
    distinct, inverse = np.unique(flat, return_inverse=True)
    text = (f"%.{dec}f\n" * len(distinct)) % tuple(distinct.tolist())
    if dec > 0:
        text = _TRAILING_ZEROS.sub("\n", text).replace(".\n", "\n")
    text = _MINUS_ZERO.sub("0", text)
    strings = np.empty(len(distinct), dtype=object)
    strings[:] = text.split("\n")[:-1]
    return strings[inverse.reshape(-1)].reshape(values.shape)


def _move_lines(txt: np.ndarray, kinds: np.ndarray, safe: str, feed_s: str, plunge_s: str) -> list[str]:
    """Program lines for the moves, modal words omitted. ``txt``: (n, 3) coordinate
    strings; the position before the first move is (txt[0, 0], txt[0, 1], safe) in G0.
    Vectorized: a move whose three strings equal its predecessor's is dropped (so the
    predecessor of a kept move is always the last written position). Each word carries
    its trailing space ('' when omitted): a line is its words joined, the last space cut."""
    prev = np.vstack([[txt[0, 0], txt[0, 1], safe], txt[:-1]])
    changed = txt != prev
    keep = changed.any(axis=1)
    txt, changed, kinds = txt[keep], changed[keep], kinds[keep]
    rapid = kinds == RAPID
    g_new = np.empty(len(kinds), dtype=bool)
    g_new[:1] = ~rapid[:1]                   # G0 is modal before the first move
    g_new[1:] = rapid[1:] != rapid[:-1]
    g_word = np.where(g_new, np.where(rapid, "G0 ", "G1 "), "").tolist()
    feed = np.where(rapid, "", np.where(kinds == PLUNGE, plunge_s + " ", feed_s + " "))
    fi = np.nonzero(~rapid)[0]
    f_word = [""] * len(kinds)
    if fi.size:
        fv = feed[fi]
        new = np.concatenate([[True], fv[1:] != fv[:-1]])
        for i, v in zip(fi[new].tolist(), fv[new].tolist()):
            f_word[i] = "F" + v
    words = []
    for a, name in enumerate("XYZ"):
        col = txt[:, a].tolist()
        words.append([name + t + " " if c else "" for t, c in zip(col, changed[:, a].tolist())])
    return [line[:-1] for line in map("".join, zip(g_word, *words, f_word))]


def _num(v: float, nd: int) -> str:
    """A number with at most ``nd`` decimals, trailing zeros dropped ('12.5', '0', never '-0')."""
    s = f"{v:.{nd}f}"
    if "." in s:
        s = s.rstrip("0").rstrip(".")
    if s in ("-0", ""):
        s = "0"
    return s


def _start(toolpath: Toolpath, profile: MachineProfile) -> np.ndarray:
    """The position before the first move: above the first point at the safe height."""
    if len(toolpath.points):
        return np.array([toolpath.points[0, 0], toolpath.points[0, 1], profile.safe_z])
    return np.array([np.nan, np.nan, profile.safe_z])


def _moves(toolpath: Toolpath, profile: MachineProfile, add) -> tuple:
    """The rapid across to above the first point and the moves of ``toolpath`` (G0 is
    modal from the "G0 Z<safe>" before). Returns (txt, kinds, last_z) for the retract."""
    k = 1.0 / profile.u.mm_per_unit
    dec, fdec = profile.decimals, profile.u.feed_decimals
    pts = np.asarray(toolpath.points, dtype=float) * k
    kinds = np.asarray(toolpath.kinds)
    # format every coordinate once; the same strings are compared (modality) and written
    txt = _format_array(pts, dec)
    safe = _num(profile.safe_z * k, dec)
    if not len(pts):
        return txt, kinds, safe
    add(f"X{txt[0, 0]} Y{txt[0, 1]}")
    for line in _move_lines(txt, kinds, safe, _num(profile.feed * k, fdec), _num(profile.plunge * k, fdec)):
        add(line)
    return txt, kinds, txt[-1, 2]


def _retract(txt, kinds, last_z: str, safe: str, add) -> None:
    """Back up to the safe height after the moves (G0 named when the last move was G1)."""
    if last_z != safe:
        add(("G0 " if len(txt) and kinds[-1] != RAPID else "") + f"Z{safe}")


def _feeds_item(profile: MachineProfile) -> str:
    u, k, fdec = profile.u, 1.0 / profile.u.mm_per_unit, profile.u.feed_decimals
    return (f"cut {_num(profile.feed * k, fdec)}, plunge {_num(profile.plunge * k, fdec)} "
            f"{u.name}/min, spindle {profile.spindle:.0f} rpm")


def write_program(toolpath: Toolpath, profile: MachineProfile, *, title: str | None = None,
                  operation: tuple | None = None) -> str:
    """The program text for ``toolpath`` (tip positions, work mm) on ``profile``.

    Pure and deterministic: no timestamps, no I/O. Coordinates are rounded to
    ``profile.decimals`` in program units (error <= ``profile.rounding_mm`` per axis).
    Moves that round to the previous position are dropped.

    ``title``: the first header comment (default: the ball-end finishing program);
    ``operation``: (key, value) header items of one operation of a job written one
    program per tool (grbl), in place of the finishing passes' ``passes`` and ``stepover``.
    """
    d, u = profile.d, profile.u
    k = 1.0 / u.mm_per_unit
    dec, fdec = profile.decimals, u.feed_decimals
    units_word = u.gword
    num = _num
    kinds = np.asarray(toolpath.kinds)

    safe = num(profile.safe_z * k, dec)
    park = [num(v * k, dec) for v in profile.park]
    est = estimate_seconds(toolpath.points, kinds, _start(toolpath, profile), profile)

    out: list[str] = []
    add = out.append
    items = [("fabkit", title or f"ball-end raster finishing program, {d.name} dialect")]
    items += list(profile.header)
    items += [("work zero (G54)", "X0 Y0 at the footprint corner of smallest x, y,"),
              ("", "Z0 on the stock top face"),
              ("scallop", _length(profile.scallop, u)), ("tolerance", _length(profile.tolerance, u))]
    gap = float(toolpath.info.get("edge_pass_gap_max", 0.0))
    if operation is not None:
        items += list(operation)
    else:
        items += [("passes", f"{toolpath.passes}"),
                  ("stepover", (f"{toolpath.stepover_min * k:.4g}-" if toolpath.stepover_min < toolpath.stepover
                                else "") + f"{toolpath.stepover * k:.4g} {u.name}"),
                  *([("edge pass gap", f"up to {gap * k:.4g} {u.name} from the passes over the stock "
                                       "to those beyond its edges")]
                    if gap > toolpath.stepover else [])]
    items += [("units", f"{u.name} ({units_word}), feeds {u.name}/min, absolute (G90)"),
              ("feeds", _feeds_item(profile)),
              ("safe height", f"Z{safe} {u.name}"),
              ("park", f"X{park[0]} Y{park[1]} at the safe height"),
              ("estimated time", f"{_fmt_duration(est)} (rapids at {num(profile.rapid * k, fdec)} "
                                 f"{u.name}/min, no acceleration)")]
    if profile.tool_number is not None and d.tool_change is None:
        items.append(("tool change", f"load T{profile.tool_number} by hand before the start "
                                     f"and set Z0 with it ({d.name} has no M6)"))
    for key, value in items:
        out.extend(_comment_lines(key, str(value), d))
    pre = [w.format(units=units_word) for w in d.preamble]
    add(" ".join(pre))
    if d.path_blending:
        add(f"G64 P{num(profile.tolerance * 0.5 * k, dec)}")
    if profile.tool_number is not None and d.tool_change is not None:
        add(d.tool_change.format(n=int(profile.tool_number)))
    add(f"G0 Z{safe}")
    add(f"M3 S{profile.spindle:.0f}")

    txt, kinds, last_z = _moves(toolpath, profile, add)
    _retract(txt, kinds, last_z, safe, add)
    _park(txt, kinds, last_z, safe, park, add)
    add("M5")
    add(d.program_end)
    return "\n".join(out) + "\n"


def _park(txt, kinds, last_z: str, safe: str, park: list, add) -> None:
    """The rapid at the safe height to the park position (axes already there omitted)."""
    n = len(txt)
    last_xy = (txt[-1, 0], txt[-1, 1]) if n else (None, None)
    if (last_xy[0], last_xy[1]) != (park[0], park[1]):
        g0 = "G0 " if n and kinds[-1] != RAPID and last_z == safe else ""
        add(g0 + " ".join(f"{a}{v}" for a, v, was in (("X", park[0], last_xy[0]), ("Y", park[1], last_xy[1]))
                          if v != was))


# ----------------------------------------------------------------------------
# a job of several operations (each with its own tool)
# ----------------------------------------------------------------------------
def operation_profile(profile: MachineProfile, tool) -> MachineProfile:
    """``profile`` with the tool's own feed, plunge, spindle speed and number (the
    profile's feeds and speed where the tool gives none)."""
    return replace(profile,
                   feed=float(tool.feed) if getattr(tool, "feed", None) is not None else profile.feed,
                   plunge=float(tool.plunge) if getattr(tool, "plunge", None) is not None else profile.plunge,
                   spindle=float(tool.spindle) if getattr(tool, "spindle", None) is not None else profile.spindle,
                   tool_number=tool.number)


def operation_seconds(op, profile: MachineProfile) -> float:
    """Length / feed run time of one operation, s, at its tool's feeds (rapids at
    ``profile.rapid``, no acceleration), from the safe height above its first point."""
    p = operation_profile(profile, op.tool)
    return estimate_seconds(op.toolpath.points, np.asarray(op.toolpath.kinds), _start(op.toolpath, p), p)


def job_suffixes(operations, dialect: str) -> list[str]:
    """The program files of a job, as suffixes of the program's stem: ``[""]`` (the
    program path itself) for one program; for a dialect without a tool change (grbl)
    and more than one operation, ``.1-rough.nc``, ``.2-rest.nc``, ``.3-finish.nc``...
    numbered in the order they run."""
    if len(operations) <= 1 or DIALECTS[dialect].tool_change is not None:
        return [""]
    return [f".{i}-{op.kind}.nc" for i, op in enumerate(operations, start=1)]


def _op_items(op, i: int, n: int, profile: MachineProfile, u: Units, full: bool = True) -> list[tuple]:
    """Header items describing operation ``i`` of ``n`` (``full``: with its feeds and time)."""
    p = operation_profile(profile, op.tool)
    k = 1.0 / u.mm_per_unit
    tool = (f"T{op.tool.number} " if op.tool.number is not None else "") + _tool_words(op.tool, u)
    what = [f"{op.levels} level" + ("s" if op.levels != 1 else "")] if op.levels else []
    what.append(f"{op.passes} pass" + ("es" if op.passes != 1 else ""))
    if op.leave > 0:
        what.append(f"leaves {op.leave * k:.4g} {u.name}")
    items = [(f"operation {i} of {n}", f"{op.kind}, {tool}"), ("", ", ".join(what))]
    if full:
        items += [("", f"feeds {_feeds_item(p)}"),
                  ("", f"estimated {_fmt_duration(operation_seconds(op, profile))} (length/feed)")]
    return items


def _tool_words(tool, u: Units) -> str:
    name = {"flat": "flat end mill", "ball": "ball-end mill", "bull": "bull nose"}[tool.shape]
    extra = f", corner radius {_length(tool.corner_radius, u)}" if tool.shape == "bull" else ""
    return f"{name}, diameter {_length(tool.diameter, u)}{extra}"


def write_job(operations, profile: MachineProfile, finish=None) -> list[tuple[str, str]]:
    """The programs of a job of ``operations`` (:class:`~fabkit.toolpath.operations.Operation`,
    in the order they run) on ``profile`` (the finishing tool's, as :func:`profile_from_spec`
    gives it). Returns [(suffix, text)], suffixes as :func:`job_suffixes`.

    - One operation: :func:`write_program` of its toolpath on ``profile``, unchanged
      (today's single program, byte for byte).
    - A dialect with a tool change (LinuxCNC): ONE program; each operation starts with a
      comment ``(operation: i of n, kind, Tn)``, then (when its tool is not the one in the
      spindle) spindle off (M5, from the second on; the tool is already retracted to the
      safe height) and the tool call ``Tn M6 G43 Hn``, a rapid to the safe height (the new
      length offset applies) and its own spindle speed, then its moves at its tool's
      feeds. The header lists every operation. Every tool needs a number.
    - Without one (grbl): one complete program per operation (preamble, spindle, its
      moves, end), each naming its tool and its place in the job.

    ``finish``: (toolpath, text) of the last operation written alone, ``write_program``
    (toolpath, profile): in the one program of a dialect with a tool change, its lines
    from its first ``G0 Z<safe>`` on are the last operation's, line for line, when that
    operation runs the same toolpath with moves at the same feeds and speed; they are
    taken as they are, not written again (tests/test_job_operations.py checks the two).

    Pure and deterministic, like :func:`write_program`.
    """
    ops = list(operations)
    if not ops:
        raise ValueError("a job needs at least one operation")
    if len(ops) == 1:
        return [("", write_program(ops[0].toolpath, profile))]
    d, u = profile.d, profile.u
    n = len(ops)
    header = [(key, value) for key, value in profile.header if key != "tool"]
    kinds = " then ".join(op.kind for op in ops)
    if d.tool_change is None:
        out = []
        for i, (op, suffix) in enumerate(zip(ops, job_suffixes(ops, d.name)), start=1):
            p = replace(operation_profile(profile, op.tool), header=tuple(header))
            items = _op_items(op, i, n, profile, u, full=False)
            items.append(("job", f"{kinds}: run the programs in this order, touching off Z0 on the "
                                 "same top face after each tool change"))
            out.append((suffix, write_program(op.toolpath, p, operation=items,
                                              title=f"{op.kind} program {i} of {n}, {d.name} dialect")))
        return out
    missing = [op.kind for op in ops if op.tool.number is None]
    if missing:
        raise ValueError(f"every tool of a {d.name} job needs a number for its tool change "
                         f"(none for: {', '.join(missing)})")
    return [("", _write_changes(ops, profile, header, finish))]


def _finish_lines(op, p: MachineProfile, profile: MachineProfile, finish, safe: str):
    """The lines of ``finish``'s text (toolpath, text) from its first ``G0 Z<safe>`` to its
    end, when ``op`` (the job's last operation, written with ``p``) would write them the
    same: its toolpath is that one, with moves, and ``p`` writes moves as ``profile``
    (:func:`write_job`); else None."""
    if finish is None:
        return None
    toolpath, text = finish
    same = (op.toolpath is toolpath and len(toolpath.points) > 0
            and (p.feed, p.plunge, p.spindle) == (profile.feed, profile.plunge, profile.spindle))
    if not same:
        return None
    lines = text.splitlines()
    try:
        k = lines.index(f"G0 Z{safe}")
    except ValueError:
        return None
    return lines[k:]


def _write_changes(ops, profile: MachineProfile, header: list, finish=None) -> str:
    """One program with a tool change before each operation (see :func:`write_job`)."""
    d, u = profile.d, profile.u
    k = 1.0 / u.mm_per_unit
    dec, fdec = profile.decimals, u.feed_decimals
    safe = _num(profile.safe_z * k, dec)
    park = [_num(v * k, dec) for v in profile.park]
    n = len(ops)
    total = sum(operation_seconds(op, profile) for op in ops)
    n_tools = len({op.tool.number for op in ops})
    items = [("fabkit", f"{', '.join(op.kind for op in ops)} program, {n_tools} tools, {d.name} dialect")]
    items += header
    items += [("work zero (G54)", "X0 Y0 at the footprint corner of smallest x, y,"),
              ("", "Z0 on the stock top face, every tool's length offset from the tool table (G43)"),
              ("scallop", _length(profile.scallop, u)), ("tolerance", _length(profile.tolerance, u))]
    for i, op in enumerate(ops, start=1):
        items += _op_items(op, i, n, profile, u)
    items += [("units", f"{u.name} ({u.gword}), feeds {u.name}/min, absolute (G90)"),
              ("safe height", f"Z{safe} {u.name}"),
              ("park", f"X{park[0]} Y{park[1]} at the safe height"),
              ("estimated time", f"{_fmt_duration(total)} (length/feed, rapids at "
                                 f"{_num(profile.rapid * k, fdec)} {u.name}/min, no acceleration)")]
    out: list[str] = []
    add = out.append
    for key, value in items:
        out.extend(_comment_lines(key, str(value), d))
    add(" ".join(w.format(units=u.gword) for w in d.preamble))
    if d.path_blending:
        add(f"G64 P{_num(profile.tolerance * 0.5 * k, dec)}")
    loaded = None
    for i, op in enumerate(ops, start=1):
        p = operation_profile(profile, op.tool)
        out.extend(_comment_lines("operation", f"{i} of {n}, {op.kind}, T{op.tool.number}", d))
        if op.tool.number != loaded:          # the same tool again (rest then finish with one ball): no change
            if loaded is not None:
                add("M5")
            add(d.tool_change.format(n=int(op.tool.number)))
            loaded = op.tool.number
        tail = _finish_lines(op, p, profile, finish, safe) if i == n else None
        if tail is not None:
            out.extend(tail)            # the last operation's lines, park and end as written alone
            return "\n".join(out) + "\n"
        add(f"G0 Z{safe}")
        add(f"M3 S{p.spindle:.0f}")
        txt, kinds, last_z = _moves(op.toolpath, p, add)
        _retract(txt, kinds, last_z, safe, add)
    if len(txt):
        _park(txt, kinds, last_z, safe, park, add)
    else:
        add(f"G0 X{park[0]} Y{park[1]}")
    add("M5")
    add(d.program_end)
    return "\n".join(out) + "\n"


def used_words(text: str) -> set[str]:
    """The G and M words (and other letter words) of a program, comments removed:
    {'G0', 'G1', 'X', 'F', ...}: G/M with their number, other letters alone."""
    import re

    words = set()
    for line in text.splitlines():
        line = re.sub(r"\([^)]*\)", "", line).split(";")[0]
        for letter, value in re.findall(r"([A-Za-z])\s*([-+]?[0-9.]*)", line):
            letter = letter.upper()
            if letter in "GM":
                words.add(f"{letter}{int(float(value))}" if float(value).is_integer() else f"{letter}{value}")
            else:
                words.add(letter)
    return words


__all__ = ["Dialect", "DIALECTS", "UNITS", "MachineProfile", "profile_from_spec", "write_program", "write_job",
           "job_suffixes", "operation_profile", "operation_seconds",
           "estimate_seconds", "used_words", "DEFAULT_RAPID_MM_MIN", "MM_PER_INCH"]
