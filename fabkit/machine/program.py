"""Any grbl or LinuxCNC program, read as its controller runs it: the moves the motion
planner receives (mm, machine coordinates), with the points where the planner's buffer
empties and the dwell time.

This reader is permissive where :func:`fabkit.toolpath.program.reader.read_program` (the
verification's reader of fabkit's own programs) is strict: it takes programs from any
CAM tool or written by hand. Understood:

- G0 G1 G2 G3 (arcs by I J K or R, in the G17/G18/G19 plane, helical with the third
  axis), G4 P (dwell, seconds), G17-G19, G20/G21, G90/G91, G90.1/G91.1 (LinuxCNC's
  arc centre modes; grbl has only G91.1), G53 (machine coordinates, one line),
  G92/G92.1 (offsets), G94, G40, G49, G80, G54 (the work offset, taken as zero),
  G61, G61.1, G64 P Q (LinuxCNC path control), G43 H (LinuxCNC tool length; the
  tip's moves are timed), M0-M9, M30, M48-M53 (no motion), S F T, N line numbers,
  comments in parentheses or after ``;``, ``%`` lines, a leading ``/``.
- grbl 1.1h's arcs exactly as its ``mc_arc`` cuts them into lines:
  ``floor(|theta r / 2| / sqrt(tol (2 r - tol)))`` segments, ``tol`` = $12, the
  end points on the arc; its centre from R as ``gcode.c`` computes it, and its
  errors (error:33 when the end point is off the arc by more than 0.005 mm and
  0.1 % of the radius).
- grbl's buffer syncs (``gcode.c``, ``spindle_control.c``, ``coolant_control.c``):
  a spindle state change (M3/M4/M5 to another state), an S change while the spindle
  runs, a coolant state change (M7/M8/M9), G4, M0/M1/M2/M30. A repeated M3, the
  same S, or M8 when flood is on do not empty the buffer.
  grbl's dwell runs in 50 ms steps: ``ceil(20 P) x 0.05`` s (``delay_sec``).
- LinuxCNC: every spindle, speed and coolant word, G4, M0-M2, M30 and M6 stop the
  motion queue (the task waits for motion before a spindle or coolant command);
  arcs are cut into chords at the profile's arc tolerance for the approximate planner.

G28/G30 move through their axis words to the stored position (machine zero, with the
work offset zero, unless G28.1/G30.1 set it: a warning says so). Anything else (G10,
canned cycles, cutter compensation, inverse time, parameters and expressions, A/B/C
axes, another work offset) is refused naming the word and its line: the time of such a
program is not known.

Positions: the machine starts at the work origin (0, 0, 0) with the work offset zero;
a G53 move therefore assumes the work offset is zero (a warning says so).
"""

from __future__ import annotations

import math
import re
from array import array
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError
from ..units import MM_PER_INCH

RAPID, FEED = 0, 1
#: grbl config.h
N_ARC_CORRECTION = 12
ARC_ANGULAR_TRAVEL_EPSILON = 5e-7
DWELL_TIME_STEP_MS = 50
#: LinuxCNC path control modes per move (``term``)
TERM_STOP, TERM_EXACT, TERM_BLEND = 0, 1, 2

_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)"
_WORD = re.compile(rf"([A-Z])({_NUM})")
_CLEAN = re.compile(rf"(?:[A-Z]{_NUM})*")

#: G words understood (as written by _gname)
_G_OK = {"0", "1", "2", "3", "4", "17", "18", "19", "20", "21", "90", "91", "90.1", "91.1", "53", "92",
         "92.1", "94", "40", "49", "80", "54", "61", "61.1", "64", "43", "28", "30", "28.1", "30.1"}
_G_GRBL = {"0", "1", "2", "3", "4", "17", "18", "19", "20", "21", "90", "91", "91.1", "53", "92", "92.1",
           "94", "40", "49", "80", "54", "61", "28", "30", "28.1", "30.1"}
_M_OK = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 30, 48, 49, 50, 51, 52, 53}
_M_GRBL = {0, 1, 2, 3, 4, 5, 7, 8, 9, 30}
_LETTERS_OK = set("GMXYZIJKRFSTPQHNDL")


@dataclass
class Moves:
    """A program as the controller's planner receives it (mm, mm/min, machine
    coordinates; arcs already cut into lines).

    start: (3,) the position before the first move; points: (n, 3) end points;
    kinds: RAPID | FEED; feed: mm/min (nan for rapids); line: 1-based source line;
    sync: True where the buffer empties before the move; term/tolerance: LinuxCNC's
    path control per move (G61.1 stop, G61 exact, G64 blend with P mm or nan);
    dwell_s: the dwell time in total; syncs: the number of buffer syncs.
    """

    controller: str
    start: np.ndarray
    points: np.ndarray
    kinds: np.ndarray
    feed: np.ndarray
    line: np.ndarray
    sync: np.ndarray
    term: np.ndarray
    tolerance: np.ndarray
    lines: int
    units: str = "mm"
    dwell_s: float = 0.0
    dwells: int = 0
    syncs: int = 0
    arcs: int = 0
    arc_segments: int = 0
    pauses: int = 0
    tool_changes: int = 0
    naivecam: float | None = None     # LinuxCNC G64 Q, mm (None: Q = P)
    warnings: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.points)


_F32 = array("f", [0.0])
MAX_INT_DIGITS = 8          # grbl nuts_bolts.h


def f32(x: float) -> float:
    """``x`` rounded to a 32-bit float (grbl's ``float`` on the ATmega328p)."""
    _F32[0] = x
    return _F32[0]


_F001, _F01, _F10, _F_INCH = f32(0.01), f32(0.1), f32(10.0), f32(MM_PER_INCH)


def grbl_float(text: str) -> float:
    """A number as grbl 1.1h's ``read_float`` reads it on the AVR (where a double is a
    float): at most 8 digits as an integer, then scaled by float multiplications by 0.01,
    0.1 or 10 (not always the correctly rounded float of the decimal)."""
    got = _GRBL_FLOATS.get(text)
    if got is not None:
        return got
    neg = text[0] == "-"
    body = text[1:] if text[0] in "+-" else text
    ip, _, fp = body.partition(".")
    digits = ip + fp
    if len(digits) <= MAX_INT_DIGITS:
        intval = int(digits) if digits else 0
        exp = -len(fp)
    else:
        n_int = len(ip)
        intval = exp = 0
        for i, ch in enumerate(digits):
            if i < MAX_INT_DIGITS:
                if i >= n_int:
                    exp -= 1
                intval = intval * 10 + (ord(ch) - 48)
            elif i < n_int:
                exp += 1            # an integer digit past the eighth: dropped, the value scaled
    f = f32(float(intval))
    if f != 0:
        while exp <= -2:
            f = f32(f * _F001)
            exp += 2
        if exp < 0:
            f = f32(f * _F01)
        while exp > 0:
            f = f32(f * _F10)
            exp -= 1
    f = -f if neg else f
    if len(_GRBL_FLOATS) > 200_000:
        _GRBL_FLOATS.clear()
    _GRBL_FLOATS[text] = f
    return f


_GRBL_FLOATS: dict = {}


def _gname(v: str) -> str:
    f = float(v)
    return str(int(f)) if f.is_integer() else f"{f:g}"


def _bad(line_no: int, what: str, file: str | None) -> SpecError:
    return SpecError(f"line {line_no}: {what}", file=file)


def read_moves(text: str, controller: str = "grbl", arc_tolerance: float = 0.002,
               file: str | None = None) -> Moves:
    """Read ``text`` (a grbl or LinuxCNC program) as ``controller`` runs it. Raises
    SpecError (naming the line and word) on what it does not support."""
    grbl = controller == "grbl"
    g_ok = _G_GRBL if grbl else _G_OK
    m_ok = _M_GRBL if grbl else _M_OK
    pos = [0.0, 0.0, 0.0]           # machine position, mm
    g92 = [0.0, 0.0, 0.0]           # work offset (G92), mm
    motion = 0 if not grbl else 0
    plane = 17
    inch = False
    absolute = True
    arc_abs = False
    feed = math.nan
    spindle = 5
    speed = 0.0
    coolant = 0                      # bit 1 flood, bit 2 mist
    term, tol = TERM_BLEND, math.nan
    pts: list = []
    kinds: list = []
    feeds: list = []
    lines: list = []
    syncs_at: list = []              # indices of moves that start after a sync
    terms: list = []
    tols: list = []
    out = Moves(controller=controller, start=np.zeros(3), points=np.zeros((0, 3)), kinds=np.zeros(0, np.int8),
                feed=np.zeros(0), line=np.zeros(0, int), sync=np.zeros(0, bool), term=np.zeros(0, np.int8),
                tolerance=np.zeros(0), lines=0)
    g53_warned = False
    stored = {28: [0.0, 0.0, 0.0], 30: [0.0, 0.0, 0.0]}      # G28/G30 positions, machine mm
    stored_set: set = set()
    home_warned = False
    src = text.upper().split("\n")
    out.lines = len(src) - (src[-1] == "")       # a final newline ends the last line, it starts none
    for ln, s in enumerate(src, start=1):
        if "(" in s or ";" in s:
            s = _strip_comments(s, grbl, ln, file)
        s = s.replace(" ", "").replace("\t", "").replace("\r", "")
        if not s or s[0] == "%":
            continue
        if s[0] == "/":
            s = s[1:]
        if not _CLEAN.fullmatch(s):
            bad = _CLEAN.match(s).end()
            raise _bad(ln, f"unsupported text {s[bad:bad + 12]!r} (parameters, expressions and O-words "
                           "are not read)", file)
        words = _WORD.findall(s)
        gs = ms = None
        axes = {}
        ijk = {}
        r = None
        p = None
        q_word = None
        f_word = s_word = None
        for letter, v in words:
            if letter == "G":
                name = _gname(v)
                if name not in g_ok:
                    raise _bad(ln, f"G{name} is not supported" + (" by grbl 1.1 (error:20)" if grbl and name in _G_OK
                                                                 else " for timing"), file)
                (gs := gs if gs is not None else []).append(name)
            elif letter == "M":
                m = float(v)
                if not m.is_integer() or int(m) not in m_ok:
                    raise _bad(ln, f"M{_gname(v)} is not supported" + (" by grbl 1.1 (error:20)"
                                                                       if grbl and m.is_integer() and int(m) in _M_OK
                                                                       else " for timing"), file)
                (ms := ms if ms is not None else []).append(int(m))
            elif letter in "XYZ":
                axes["XYZ".index(letter)] = grbl_float(v) if grbl else float(v)
            elif letter in "IJK":
                ijk["IJK".index(letter)] = grbl_float(v) if grbl else float(v)
            elif letter == "F":
                f_word = float(v)
            elif letter == "S":
                s_word = float(v)
            elif letter == "R":
                r = grbl_float(v) if grbl else float(v)
            elif letter == "P":
                p = float(v)
            elif letter == "Q":
                q_word = float(v)
            elif letter not in _LETTERS_OK:
                raise _bad(ln, f"{letter} words are not supported for timing ({letter}{v})", file)
        g53 = False
        dwell = False
        g92_set = False
        go_home = 0
        if gs:
            for name in gs:
                if name in ("0", "1", "2", "3"):
                    motion = int(name)
                elif name == "4":
                    dwell = True
                elif name in ("17", "18", "19"):
                    plane = int(name)
                elif name == "20":
                    inch = True
                elif name == "21":
                    inch = False
                elif name == "90":
                    absolute = True
                elif name == "91":
                    absolute = False
                elif name == "90.1":
                    arc_abs = True
                elif name == "91.1":
                    arc_abs = False
                elif name == "53":
                    g53 = True
                elif name == "92":
                    g92_set = True
                elif name in ("28", "30"):
                    go_home = int(name)
                elif name in ("28.1", "30.1"):
                    stored[int(float(name))] = list(pos)
                    stored_set.add(int(float(name)))
                elif name == "92.1":
                    g92 = [0.0, 0.0, 0.0]
                elif name == "61":
                    term = TERM_EXACT
                elif name == "61.1":
                    term = TERM_STOP
                elif name == "64":
                    term = TERM_BLEND
                    tol = p * (MM_PER_INCH if inch else 1.0) if p is not None else math.nan
                    if q_word is not None:
                        out.naivecam = q_word * (MM_PER_INCH if inch else 1.0)
        k = MM_PER_INCH if inch else 1.0
        sync = False
        # [3] feed, [4] speed, [7] spindle, [8] coolant, [10] dwell: before the motion
        if f_word is not None:
            feed = f_word * k
        if grbl:
            new_spindle = spindle
            new_coolant = coolant
            if ms:
                for m in ms:
                    if m in (3, 4, 5):
                        new_spindle = m
                    elif m == 7:
                        new_coolant |= 2
                    elif m == 8:
                        new_coolant |= 1
                    elif m == 9:
                        new_coolant = 0
            if s_word is not None and s_word != speed:
                if spindle != 5:
                    sync = True
                speed = s_word
            if new_spindle != spindle:
                sync = True
                spindle = new_spindle
            if new_coolant != coolant:
                sync = True
                coolant = new_coolant
        else:
            if s_word is not None:
                sync = True
            if ms and any(m in (3, 4, 5, 6, 7, 8, 9) for m in ms):
                sync = True
                if 6 in ms:
                    out.tool_changes += 1
        if dwell:
            if p is None or p < 0:
                raise _bad(ln, "G4 needs P (seconds, >= 0)", file)
            sync = True
            if grbl:
                out.dwell_s += math.ceil(np.float32(1000 // DWELL_TIME_STEP_MS) * np.float32(p)) \
                    * DWELL_TIME_STEP_MS / 1000.0
            else:
                out.dwell_s += p
            out.dwells += 1
        if sync:
            out.syncs += 1
            syncs_at.append(len(kinds))
        # [19] offsets, G28/G30
        if g92_set:
            for i, v in axes.items():
                g92[i] = pos[i] - v * k
            axes = {}
        if go_home:
            # an intermediate point (the axis words, as a rapid), then the stored position
            # on those axes (all axes without words), both rapids
            dest = list(pos)
            if axes:
                mid = list(pos)
                for i, v in axes.items():
                    mid[i] = v * k + g92[i] if absolute else pos[i] + v * k
                pts.extend(mid)
                kinds.append(RAPID)
                feeds.append(math.nan)
                lines.append(ln)
                terms.append(term)
                tols.append(tol)
                dest = mid
            for i in (axes if axes else range(3)):
                dest = list(dest)
                dest[i] = stored[go_home][i]
            pts.extend(dest)
            kinds.append(RAPID)
            feeds.append(math.nan)
            lines.append(ln)
            terms.append(term)
            tols.append(tol)
            pos = dest
            if go_home not in stored_set and not home_warned:
                out.warnings.append(f"line {ln}: G{go_home}: its stored position is taken as machine zero with the "
                                    "work offset zero (the controller's G28/G30 data are not in the program)")
                home_warned = True
            axes = {}
        # [20] motion
        if axes and not dwell:
            if motion is None:
                raise _bad(ln, "axis words without a motion mode", file)
            target = list(pos)
            if grbl:            # grbl's float arithmetic (gcode.c): the arcs' full-circle test depends on it
                for i, v in axes.items():
                    v = f32(v * _F_INCH) if inch else v
                    target[i] = v if g53 else f32(v + g92[i]) if absolute else f32(pos[i] + v)
            else:
                for i, v in axes.items():
                    if g53:
                        target[i] = v * k
                    elif absolute:
                        target[i] = v * k + g92[i]
                    else:
                        target[i] = pos[i] + v * k
            if g53 and not g53_warned:
                out.warnings.append(f"line {ln}: G53 (machine coordinates): its moves assume the work offset "
                                    "is zero")
                g53_warned = True
            if motion in (0, 1):
                if motion == 1 and not feed > 0:
                    raise _bad(ln, "G1 without a feed (F)", file)
                pts.extend(target)
                kinds.append(motion)
                feeds.append(feed if motion == 1 else math.nan)
                lines.append(ln)
                terms.append(term)
                tols.append(tol)
            else:
                if not feed > 0:
                    raise _bad(ln, f"G{motion} without a feed (F)", file)
                seg = _arc(pos, target, plane, motion == 2, ijk, r, k, arc_abs, g92, grbl, arc_tolerance, ln, file)
                out.arcs += 1
                out.arc_segments += len(seg) // 3
                pts.extend(seg)
                nseg = len(seg) // 3
                kinds.extend([FEED] * nseg)
                feeds.extend([feed] * nseg)
                lines.extend([ln] * nseg)
                terms.extend([term] * nseg)
                tols.extend([tol] * nseg)
            pos = target
        elif (ijk or r is not None) and not dwell:
            raise _bad(ln, "arc words (I J K R) without an arc move", file)
        # [21] program flow: after the motion
        if ms and any(m in (0, 1, 2, 30) for m in ms):
            out.syncs += 1
            syncs_at.append(len(kinds))
            if 0 in ms or 1 in ms:
                out.pauses += 1
            if 2 in ms or 30 in ms:
                motion, plane, absolute, g92_set = 1, 17, True, False
                spindle, coolant = 5, 0
    n = len(kinds)
    out.points = np.array(pts, dtype=float).reshape(n, 3)
    out.kinds = np.asarray(kinds, dtype=np.int8)
    out.feed = np.asarray(feeds, dtype=float)
    out.line = np.asarray(lines, dtype=int)
    out.term = np.asarray(terms, dtype=np.int8)
    out.tolerance = np.asarray(tols, dtype=float)
    out.sync = np.zeros(n, dtype=bool)
    if syncs_at:
        idx = np.asarray(syncs_at)
        out.sync[idx[idx < n]] = True
    out.units = "in" if inch else "mm"
    if out.pauses:
        out.warnings.append(f"{out.pauses} program pause(s) (M0/M1): the time waiting for the operator is not "
                            "counted")
    if out.tool_changes:
        out.warnings.append(f"{out.tool_changes} tool change(s) (M6): the time of the change is not counted")
    return out


def _strip_comments(s: str, grbl: bool, ln: int, file) -> str:
    """The line without its comments, read left to right as the controllers do: ``(...)``
    (a ``;`` inside is part of it) and ``;`` to the end of the line. An unclosed ``(``:
    grbl ignores the rest of the line, LinuxCNC refuses it."""
    out = []
    depth = False
    for ch in s:
        if depth:
            if ch == ")":
                depth = False
        elif ch == "(":
            depth = True
        elif ch == ";":
            break
        else:
            out.append(ch)
    if depth and not grbl:
        raise _bad(ln, "unclosed comment", file)
    return "".join(out)


_PLANES = {17: (0, 1, 2), 18: (2, 0, 1), 19: (1, 2, 0)}


def _arc(pos, target, plane, cw, ijk, r, k, arc_abs, g92, grbl, tol, ln, file) -> list:
    """The end points of the lines an arc is cut into, flat (x, y, z, x, ...) (grbl's
    mc_arc; LinuxCNC: chords at the same tolerance)."""
    a0, a1, al = _PLANES[plane]
    k0 = k
    if grbl and k != 1.0:       # gcode.c: the words times MM_PER_INCH, in floats
        ijk = {i: f32(v * _F_INCH) for i, v in ijk.items()}
        r = None if r is None else f32(r * _F_INCH)
        k = 1.0
    x = target[a0] - pos[a0]
    y = target[a1] - pos[a1]
    if r is not None:
        if ijk:
            pass          # R wins over IJK in LinuxCNC; grbl refuses the mix
        if grbl and ijk:
            raise _bad(ln, "an arc with both R and I/J/K (grbl error:26)", file)
        rr = r * k
        if x == 0 and y == 0:
            raise _bad(ln, "an R arc whose end point is its start (grbl error:33)", file)
        h = 4.0 * rr * rr - x * x - y * y
        if h < 0:
            if grbl or h < -1e-6 * rr * rr:
                raise _bad(ln, f"arc radius R{r / k0:g} is too small for its end point (grbl error:34)", file)
            h = 0.0
        h = -math.sqrt(h) / math.hypot(x, y)
        if not cw:
            h = -h
        if rr < 0:
            h = -h
            rr = -rr
        off0 = 0.5 * (x - y * h)
        off1 = 0.5 * (y + x * h)
        radius = rr
    else:
        axis_letters = "IJK"
        needed = (a0, a1)
        if not any(i in ijk for i in needed):
            raise _bad(ln, f"an arc in G{plane} needs {axis_letters[a0]} or {axis_letters[a1]} (or R) (grbl error:35)", file)
        if arc_abs:
            off0 = ijk.get(a0, 0.0) * k + g92[a0] - pos[a0]
            off1 = ijk.get(a1, 0.0) * k + g92[a1] - pos[a1]
        else:
            off0 = ijk.get(a0, 0.0) * k
            off1 = ijk.get(a1, 0.0) * k
        radius = math.hypot(off0, off1)
        target_r = math.hypot(x - off0, y - off1)
        dr = abs(target_r - radius)
        if dr > 0.005 and (dr > 0.5 or dr > 0.001 * radius):
            raise _bad(ln, f"the arc's end point is {dr:.4g} mm off its circle (grbl error:33; LinuxCNC refuses it too)",
                       file)
    if grbl:            # mc_arc in grbl's floats: a full circle far from the origin may become a sliver
        off0, off1 = f32(off0), f32(off1)
        c0, c1 = f32(pos[a0] + off0), f32(pos[a1] + off1)
        r0, r1 = -off0, -off1
        rt0, rt1 = f32(target[a0] - c0), f32(target[a1] - c1)
        ang = f32(math.atan2(f32(f32(r0 * rt1) - f32(r1 * rt0)), f32(f32(r0 * rt0) + f32(r1 * rt1))))
    else:
        c0, c1 = pos[a0] + off0, pos[a1] + off1
        r0, r1 = -off0, -off1
        rt0, rt1 = target[a0] - c0, target[a1] - c1
        ang = math.atan2(r0 * rt1 - r1 * rt0, r0 * rt0 + r1 * rt1)
    if cw:
        if ang >= -ARC_ANGULAR_TRAVEL_EPSILON:
            ang -= 2 * math.pi
    elif ang <= ARC_ANGULAR_TRAVEL_EPSILON:
        ang += 2 * math.pi
    if radius <= 0:
        return list(target)
    t = tol if tol > 0 else 0.002
    den = math.sqrt(t * (2 * radius - t)) if 2 * radius > t else 0.0
    segments = int(math.floor(abs(0.5 * ang * radius) / den)) if den > 0 else 0
    if grbl:
        segments = min(segments, 65535)       # uint16_t
    out = []
    if segments:
        i = np.arange(1, segments)
        th = ang / segments * i
        c, sn = np.cos(th), np.sin(th)
        p = np.empty((segments - 1, 3))
        p[:, a0] = c0 + r0 * c - r1 * sn
        p[:, a1] = c1 + r0 * sn + r1 * c
        p[:, al] = pos[al] + (target[al] - pos[al]) / segments * i
        out = p.ravel().tolist()
    out.extend(target)
    return out
