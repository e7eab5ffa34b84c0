"""Verification of a written program: read the TEXT back, sweep the ball-end tool
along its moves, and compare the cut with the design.

:func:`read_program` is an independent reader of the G-code subset fabkit writes
(it shares no code with the writer): modal G0/G1, G20/G21, G90, F, X/Y/Z.

:func:`verify_cut` computes the material surface left by the program at many
sample points and compares it with the clipped design surface. The swept volume
of a ball of radius R whose centre moves along a straight segment is a capsule;
the lowest point of a capsule on the vertical line through (px, py) is, exactly,
the lowest of (a) the lower surfaces of its two end spheres and (b) the lower
intersection of the line with the capsule's infinite cylinder, when the axial
parameter of that intersection lies in [0, 1] (outside that range the
cylinder's end discs lie inside the end spheres). Closed form, vectorized; a
spatial grid of segments keeps the work O(points x nearby segments). The cut
height at a point is min(0, lowest capsule point over all moves) (0 = the top
face: nothing is above it). Figures are exact at the sample points (floating
point, ~1e-9 mm); between samples the cut is not checked, so the sample count
(``machining.verify_points``) and the jitter set how sharp the check is.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import DesignError, SpecError
from ..tolerances import DEFAULT, Tolerances

RAPID, FEED = 0, 1
from ..units import MM_PER_INCH  # noqa: E402,F401
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
                   tool_changes=changes)


def estimate_time(program: Program, rapid_mm_min: float) -> float:
    """Run time, s: G1 length / its feed, G0 length / ``rapid_mm_min``. Acceleration is
    ignored (a real machine is slower on short segments)."""
    a, b = program.segments()
    seg = np.nan_to_num(np.linalg.norm(b - a, axis=1))
    rate = np.where(program.kinds == RAPID, rapid_mm_min, program.feed)
    return float(np.sum(seg / rate) * 60.0)


# ----------------------------------------------------------------------------
# the swept ball
# ----------------------------------------------------------------------------
def capsule_lower(px, py, a, b, R: float) -> np.ndarray:
    """Lowest point of the volume swept by a ball of radius R whose TIP moves
    from ``a`` to ``b``, on the vertical lines through (px, py).

    px, py: (m,) mm; a, b: (m, 3) tip positions, mm (pairs: point i with segment i).
    Returns (m,) z of the lowest swept point, mm (+inf where the line misses the
    capsule). Exact (closed form; floating point ~1e-12 relative).
    """
    R = float(R)
    ca_z = a[:, 2] + R
    cb_z = b[:, 2] + R
    dxa, dya = px - a[:, 0], py - a[:, 1]
    dxb, dyb = px - b[:, 0], py - b[:, 1]
    R2 = R * R
    with np.errstate(invalid="ignore"):
        za = ca_z - np.sqrt(R2 - dxa * dxa - dya * dya)
        zb = cb_z - np.sqrt(R2 - dxb * dxb - dyb * dyb)
    za = np.where(np.isnan(za), np.inf, za)
    zb = np.where(np.isnan(zb), np.inf, zb)
    z = np.minimum(za, zb)
    # cylinder around the centre line c(t) = ca + t d
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    ok = dd > 0
    inv = np.where(ok, 1.0 / np.where(ok, np.sqrt(dd), 1.0), 0.0)
    ux, uy, uz = d[:, 0] * inv, d[:, 1] * inv, d[:, 2] * inv
    # w(z') = (dxa, dya, z') with z' = z - ca_z; |w|^2 - (w.u)^2 = R^2
    k = dxa * ux + dya * uy
    qa = 1.0 - uz * uz
    beta = k * uz
    c = dxa * dxa + dya * dya - k * k - R2
    disc = beta * beta - qa * c
    cyl = ok & (qa > 1e-12) & (disc >= 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        sd = np.sqrt(np.where(cyl, disc, 0.0))
        # lower root of qa z'^2 - 2 beta z' + c = 0, in the cancellation-free form
        zl = np.where(beta >= 0, c / (beta + sd), (beta - sd) / np.where(cyl, qa, 1.0))
        t = (dxa * d[:, 0] + dya * d[:, 1] + zl * d[:, 2]) / np.where(ok, dd, 1.0)
    cyl &= np.isfinite(zl) & (t >= 0.0) & (t <= 1.0)
    return np.where(cyl, np.minimum(z, ca_z + zl), z)


class SegmentGrid:
    """Segments binned by the cells their XY bounding box (grown by R) touches.

    a, b: (n, 3) segment end points (tip), mm; R: tool radius, mm; cell: cell size, mm.
    """

    def __init__(self, a, b, R, cell, origin, shape, max_pairs):
        self.a, self.b, self.R, self.cell = a, b, R, cell
        self.origin, self.shape = origin, shape
        nx, ny = shape
        lo = np.minimum(a[:, :2], b[:, :2]) - R
        hi = np.maximum(a[:, :2], b[:, :2]) + R
        i0 = np.clip(np.floor((lo - origin) / cell).astype(np.int64), 0, [nx - 1, ny - 1])
        i1 = np.clip(np.floor((hi - origin) / cell).astype(np.int64), 0, [nx - 1, ny - 1])
        cx = i1[:, 0] - i0[:, 0] + 1
        cy = i1[:, 1] - i0[:, 1] + 1
        count = cx * cy
        total = int(count.sum())
        if total > max_pairs:
            raise SpecError(f"verification needs {total} segment-cell entries (limit {max_pairs}); "
                            "use fewer verify points or a coarser program", key="machining.verify_points")
        seg = np.repeat(np.arange(len(a)), count)
        off = np.arange(total) - np.repeat(np.cumsum(count) - count, count)
        ix = i0[seg, 0] + off % cx[seg]
        iy = i0[seg, 1] + off // cx[seg]
        cid = ix * ny + iy
        # within a cell, the segments in ascending order of their lowest tip (the compiled
        # search stops at the first one not below the lowest found: nothing swept is
        # below its segment's lowest tip)
        self.zmin = np.minimum(a[:, 2], b[:, 2])
        order = np.lexsort((self.zmin[seg], cid))
        self.seg = seg[order]
        self.ptr = np.searchsorted(cid[order], np.arange(nx * ny + 1))

    def cell_of(self, px, py):
        nx, ny = self.shape
        ix = np.clip(np.floor((px - self.origin[0]) / self.cell).astype(np.int64), 0, nx - 1)
        iy = np.clip(np.floor((py - self.origin[1]) / self.cell).astype(np.int64), 0, ny - 1)
        return ix * ny + iy

    def lowest(self, px, py, chunk=2_000_000, before=None):
        """(m,) lowest swept z over the binned segments at the points (+inf if none).
        ``before``: (m,) int, only segments with index < before[i] count."""
        out = np.full(len(px), np.inf)
        cid = self.cell_of(px, py)
        from .kernels import module

        kern = module()
        if kern is not None and len(px):
            # compiled: the same closed form per point and segment, no pair arrays
            b = np.zeros(1, dtype=np.int64) if before is None else np.ascontiguousarray(before, dtype=np.int64)
            kern.lowest_batch_sorted(np.ascontiguousarray(px, dtype=float), np.ascontiguousarray(py, dtype=float),
                                     cid.astype(np.int64), self.ptr.astype(np.int64), self.seg.astype(np.int64),
                                     np.ascontiguousarray(self.a, dtype=float),
                                     np.ascontiguousarray(self.b, dtype=float), float(self.R), b,
                                     before is not None, out, np.ascontiguousarray(self.zmin, dtype=float))
            return out
        cnt = self.ptr[cid + 1] - self.ptr[cid]
        pos = 0
        m = len(px)
        while pos < m:
            # as many points as fit in one chunk of pairs
            csum = np.cumsum(cnt[pos:])
            stop = pos + max(1, int(np.searchsorted(csum, chunk, side="right")))
            idx = np.arange(pos, min(stop, m))
            c = cnt[idx]
            total = int(c.sum())
            if total:
                owner = np.repeat(idx, c)
                off = np.arange(total) - np.repeat(np.cumsum(c) - c, c)
                s = self.seg[self.ptr[cid[owner]] + off]
                if before is not None:
                    keep = s < before[owner]
                    owner, s = owner[keep], s[keep]
                z = capsule_lower(px[owner], py[owner], self.a[s], self.b[s], self.R)
                np.minimum.at(out, owner, z)
            pos = idx[-1] + 1
        return out


def sample_points(ws, n: int, seed: int = 0, tol: Tolerances = DEFAULT):
    """At least ``n`` sample points (X, Y), work mm, across the whole footprint
    [0, L] x [0, W]: a regular grid including the edges and corners (about half),
    the same number jittered uniformly (deterministic ``seed``), and points on the
    crease H = 0 where the surface meets the top face (found on the grid rows and
    columns by a few secant/bisection steps)."""
    if n > tol.max_verify_points:
        raise SpecError(f"{n} verification points exceed the limit {tol.max_verify_points}",
                        key="machining.verify_points")
    L, W = ws.L, ws.W
    half = max(n // 2, 4)
    nx = max(2, int(round(np.sqrt(half * L / W))) + 1)
    ny = max(2, int(np.ceil(half / nx)) + 1)
    gx, gy = np.linspace(0.0, L, nx), np.linspace(0.0, W, ny)
    GX, GY = np.meshgrid(gx, gy, indexing="ij")
    rng = np.random.default_rng(seed)
    nj = max(n - GX.size, n // 2)
    jx, jy = rng.uniform(0.0, L, nj), rng.uniform(0.0, W, nj)
    cx, cy = _crease_points(ws, gx, gy)
    X = np.concatenate([GX.ravel(), jx, cx])
    Y = np.concatenate([GY.ravel(), jy, cy])
    return X, Y


def _uniform_count(ws, n: int) -> int:
    """How many of :func:`sample_points` come first and are spread uniformly (grid and
    jitter; the crease points follow): the share of them flagged estimates an area."""
    half = max(n // 2, 4)
    nx = max(2, int(round(np.sqrt(half * ws.L / ws.W))) + 1)
    ny = max(2, int(np.ceil(half / nx)) + 1)
    return nx * ny + max(n - nx * ny, n // 2)


def _crease_points(ws, gx, gy):
    xs, ys = [], []
    for along_x in (True, False):
        A, B = (gx, gy) if along_x else (gy, gx)
        T, C = np.meshgrid(A, B, indexing="ij")  # T varies along the line, C constant per line
        X, Y = (T, C) if along_x else (C, T)
        H = ws.H(X, Y)
        s = H >= 0
        i, j = np.nonzero(s[1:, :] != s[:-1, :])
        if i.size == 0:
            continue
        t0, t1 = A[i], A[i + 1]
        c = B[j]
        h0, h1 = H[i, j], H[i + 1, j]
        for _ in range(30):  # bisection keeps the bracket; 30 steps -> 1e-9 of a cell
            tm = 0.5 * (t0 + t1)
            hm = ws.H(tm, c) if along_x else ws.H(c, tm)
            same = (hm >= 0) == (h0 >= 0)
            t0, h0 = np.where(same, tm, t0), np.where(same, hm, h0)
            t1, h1 = np.where(same, t1, tm), np.where(same, h1, hm)
        tm = 0.5 * (t0 + t1)
        xs.append(tm if along_x else c)
        ys.append(c if along_x else tm)
    if not xs:
        return np.empty(0), np.empty(0)
    return np.concatenate(xs), np.concatenate(ys)


def verify_cut(surface, program: Program, R: float, points: int = 40000, *, seed: int = 0,
               depth_limit: float = np.inf, reach: float = np.inf, tol: Tolerances = DEFAULT,
               detail: bool = False, unreachable_min: float = 1e-3, normal: bool = True,
               over: float | None = None, cache: dict | None = None, along: str | None = None) -> dict:
    """Sweep a ball-end tool of radius ``R`` mm along every move of ``program`` and
    compare the cut with the design (``surface``: a Surface or WorkSurface).

    Returns a dict (lengths mm, work coordinates):
      max_gouge          largest (design - cut) over the sample points (>0: cut below design)
      max_material_left  largest (cut - what the ball can reach): material above the
                         design where the ball reaches it, above the lowest ball surface
                         where it cannot (see :func:`reachable_height`); measured along
                         the design's normal (``normal``, the scallop's usual measure:
                         the vertical height times 1 / sqrt(1 + |grad H|^2)) or vertically
      max_material_left_normal, max_material_left_vertical  the same in both measures
      material_left_measure  'normal' | 'vertical': the measure of max_material_left
      over_at            with ``over`` (mm): (k, 2) X, Y of the points whose material left
                         (as max_material_left) exceeds it
      max_material_above_design  largest (cut - design), unreachable material included
      unreachable        None, or {height, at, area (mm^2), points}: material above the
                         design no ball position removes (more than ``unreachable_min``)
      gouge_at, material_at   (X, Y) where they occur
      checked_points     number of sample points
      rapid_clearance    smallest (material present when the rapid runs - lowest
                         point of the ball during that rapid) over all rapids and
                         points they pass over (>= 0: no rapid touches material)
      rapids_checked     rapids that go below the top face over the stock
      deepest_cut        deepest tip position below the top face, and the limits
      first_move_ok      the first move is a Z-only rapid up to the top face or above
    ``cache``: a dict kept between verifications of programs for the same surface, R,
    points and seed (the reachable height is computed once). ``along``: the raster's
    direction ('x' or 'y'): the reachable height counts balls hanging off the edges up to
    OVERHANG x R across the passes and OVERHANG_ALONG x R along them (None: OVERHANG both).
    With ``detail`` also the arrays ``X``, ``Y``, ``design``, ``cut`` (per sample point).
    """
    from .compensate import WorkSurface

    ws = surface if isinstance(surface, WorkSurface) else WorkSurface(surface)
    L, W = ws.L, ws.W
    R = float(R)
    px, py = sample_points(ws, int(points), seed, tol)
    design = np.minimum(ws.H(px, py), 0.0)
    a, b = program.segments()
    n = len(b)
    # the first move comes from an unknown position: it must be a Z-only rapid
    # up to at or above the top face; after it every move is fully known
    # moves from a partly unknown position (before X, Y, Z were all set) must stay
    # at or above the top face; they are then swept from the known components
    unknown = ~np.isfinite(a).all(axis=1)
    first_ok = bool(n and program.kinds[0] == RAPID and np.all(b[unknown, 2] >= 0)
                    and np.all(a[unknown & np.isfinite(a[:, 2]), 2] >= 0))
    a = np.where(np.isfinite(a), a, b)
    known = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    # moves that can touch material: below the top face somewhere, within R of the footprint
    low = known & (np.minimum(a[:, 2], b[:, 2]) < 0.0)
    lo = np.minimum(a[:, :2], b[:, :2])
    hi = np.maximum(a[:, :2], b[:, :2])
    low &= (hi[:, 0] > -R) & (lo[:, 0] < L + R) & (hi[:, 1] > -R) & (lo[:, 1] < W + R)
    idx = np.nonzero(low)[0]
    cell = max(R, np.sqrt(L * W / max(len(px), 1)) * 2.0)
    shape = (int(np.ceil(L / cell)) + 1, int(np.ceil(W / cell)) + 1)
    grid = SegmentGrid(a[idx], b[idx], R, cell, np.array([0.0, 0.0]), shape,
                       max_pairs=50 * tol.max_program_points)
    cut = np.minimum(grid.lowest(px, py), 0.0)
    gouge = design - cut
    # material the ball cannot reach (a valley tighter than it, a V crease) is
    # separated from the material the program leaves where the ball can reach
    # what the ball can reach depends on the design and the sample points, not on the
    # program: a ``cache`` dict keeps it for the next verification of the same block
    key = ("reach", len(px), float(R), seed, along)
    hang = (OVERHANG_ALONG * R if along == "x" else OVERHANG * R,
            OVERHANG_ALONG * R if along == "y" else OVERHANG * R)
    if cache is not None and key in cache:
        reach_z, scale = cache[key]
    else:
        reach_z, _, scale = reachable_height(ws, px, py, R, overhang=hang, return_scale=True)
        if cache is not None:
            cache[key] = (reach_z, scale)
    unreach = reach_z - design
    above = cut - design
    left_v = cut - np.maximum(design, reach_z)
    left_n = left_v * scale
    left = left_n if normal else left_v
    ig, il = int(np.argmax(gouge)), int(np.argmax(left))
    ilv, iln = int(np.argmax(left_v)), int(np.argmax(left_n))
    ia = int(np.argmax(above))
    un = unreach > unreachable_min
    n_uniform = _uniform_count(ws, int(points))
    iu = int(np.argmax(unreach))

    # rapids below the top face: the ball must stay above the material present at
    # that moment (cut by the moves before it), at the sample points near the rapid
    # and at points along its own path (every R/4)
    rap = np.nonzero(program.kinds[idx] == RAPID)[0]
    clearance = np.inf
    clearance_at = None
    for r in rap:
        ra, rb = a[idx[r]], b[idx[r]]
        ln = np.hypot(*(rb[:2] - ra[:2]))
        t = np.linspace(0.0, 1.0, max(2, int(np.ceil(ln / (R / 4))) + 1))
        qx = np.concatenate([ra[0] + t * (rb[0] - ra[0])])
        qy = np.concatenate([ra[1] + t * (rb[1] - ra[1])])
        # sample points within R of the segment's XY path
        d = _dist_to_segment(px, py, ra[:2], rb[:2])
        near = d < R
        qx = np.concatenate([qx, px[near]])
        qy = np.concatenate([qy, py[near]])
        inside = (qx >= 0) & (qx <= L) & (qy >= 0) & (qy <= W)
        qx, qy = qx[inside], qy[inside]
        if qx.size == 0:
            continue
        before = np.full(qx.size, r)
        material = np.minimum(grid.lowest(qx, qy, before=before), 0.0)
        ball = capsule_lower(qx, qy, np.broadcast_to(ra, (qx.size, 3)), np.broadcast_to(rb, (qx.size, 3)), R)
        gap = ball - material
        j = int(np.argmin(gap))
        if gap[j] < clearance:
            clearance, clearance_at = float(gap[j]), (float(qx[j]), float(qy[j]))

    zmin = float(np.min(b[:, 2])) if n else 0.0
    out = {
        "max_gouge": float(gouge[ig]),
        "gouge_at": (float(px[ig]), float(py[ig])),
        "max_material_left": float(left[il]),
        "material_at": (float(px[il]), float(py[il])),
        "material_left_measure": "normal" if normal else "vertical",
        "max_material_left_normal": float(left_n[iln]),
        "material_left_normal_at": (float(px[iln]), float(py[iln])),
        "max_material_left_vertical": float(left_v[ilv]),
        "material_left_vertical_at": (float(px[ilv]), float(py[ilv])),
        "checked_points": int(len(px)),
        "max_material_above_design": float(above[ia]),
        "material_above_design_at": (float(px[ia]), float(py[ia])),
        "unreachable": ({"height": float(unreach[iu]), "at": (float(px[iu]), float(py[iu])),
                         "area": float(L * W * un[:n_uniform].mean()) if n_uniform else 0.0,
                         "points": int(un.sum())} if un.any() else None),
        "rapid_clearance": clearance,
        "rapid_clearance_at": clearance_at,
        "rapids_checked": int(len(rap)),
        "deepest_cut": max(0.0, -zmin),
        "depth_ok": bool(-zmin <= min(depth_limit, reach) + 1e-9),
        "first_move_ok": first_ok,
        "segments": int(n),
    }
    if over is not None:
        k = left > over
        out["over_at"] = np.column_stack([px[k], py[k]])
    if detail:
        out.update(X=px, Y=py, design=design, cut=cut, reach=reach_z)
    return out


#: where the ball cannot reach the design (a valley, a crease or a wall's foot tighter than
#: it), the floor counts the balls centred up to OVERHANG x R beyond the footprint (the
#: planner's edge passes stand up to 0.999 R out): at such a region's open end on a stock
#: edge a ball hanging off the edge reaches deeper than any ball over the stock (a 45-degree
#: V groove under a 6 mm ball: 0.49 mm deeper 0.1 mm from the edge, 1.19 mm on the edge
#: line). Where the ball reaches the design (its normal position is free, overhanging or
#: not) the design itself is the floor, edges included.
OVERHANG = 0.999
#: along the passes (``along``: their direction) the balls hang off the pass ends up to the
#: planner's last node, 0.99 R out (a ball further out touches the edge with a tip path of
#: nearly vertical tangent, which no chord of the program follows without gouging)
OVERHANG_ALONG = 0.99
REACH_GRID = 1.0 / 8.0                              # x R: the grid of start centres
REACH_SEARCH = 24                                   # compass steps, at most
REACH_DIRS = 8          # compass directions (4 ended up to 0.045 mm higher on 2*sin(x) + 2*sin(y))
REACH_STEP_MIN = 1e-5                               # x R: a point's search stops below this step
REACH_METHOD = "descend"                            # or "compass": the search before the descent
REACH_ITERS = 32                                    # the descent's drops per point, at most
REACH_SHARE_ROUNDS = 3
REACH_SECOND = 0.25                                 # x R: see reachable_height
REACH_ITERS_SECOND = 12                             # the second start's drops, at most
REACH_SHARE_CELL = 1.0 / 64.0                       # x R: one shared ball per cell (the lowest centre)
REACH_LEAD = 1.0 / 8.0                              # x R: one lead point per cell
REACH_POLISH = 1.0 / 128.0                          # x R: the compass's first step after the descent
REACH_PROBE = 1e-3                                  # x R: the step that decides whether it runs
REACH_ITERS_REST = 6                                # the other points' drops, at most


def reachable_height(ws, px, py, R: float, chunk: int = 20000, overhang: float | None = None,
                     return_scale: bool = False):
    """Lowest height a ball of radius R can cut at the points (X, Y) (work mm): the
    design where a ball touching the design there (centre R along its normal) is free
    of the surface; elsewhere (a valley tighter than the ball, a V crease) the lowest
    surface, above the point, of the balls resting on the design (exact drop-cutter
    heights) centred within R of it: g(c) = Z(c) + R - sqrt(R^2 - |c - p|^2), minimised
    over c. Starts: the centre above the point, the normal-offset centre and a grid of
    centres (:data:`REACH_GRID` x R) over the stock. The lowest ball rests on two walls
    (a kink of Z, where g is lowest) or stands at the edge of the allowed centres, so
    the search is a model descent (:func:`_descend`): Z modelled as the larger of two
    linear pieces, the exact heights and slopes of the drops on either side of the kink
    (the slope from the contact point q: dZ/dc = (q - c) / sqrt(R^2 - |q - c|^2)), each
    step the model's lowest ball in closed form. Points share: one lead point per cell
    of :data:`REACH_LEAD` x R, and every point within R of the stock's edges, is searched
    from the grid's best and from the best beyond (or over) the edge, then from the
    other lead points' balls, then by a compass search (8 directions, first step
    :data:`REACH_POLISH` x R, halved to 1e-5 R) where the descent did not settle on a
    kink; the other points start from the lead points' balls and descend at most
    :data:`REACH_ITERS_REST` drops. Every centre kept is a real ball position, so the
    height is an upper bound of the lowest one (the material it calls unreachable is
    never less than there is); on a V crease it is within 1e-6 mm of the closed form
    and on curved creases and at the stock's edges within 2e-5 mm of a brute-force
    search (tests/test_reach.py); on a parabolic valley tighter than the ball within
    3e-4 mm of the centred ball's closed form (tested). :data:`REACH_METHOD` =
    'compass' runs the search this replaced (the compass from the grid's best, first
    step REACH_GRID / 2 x R: 10-20x the drops, and stalled up to 0.33 mm high on a
    crease oblique to its directions or at a stock edge). Centres farther than
    ``overhang`` (mm, default :data:`OVERHANG` x R; a pair: beyond the x and the y edges)
    beyond the footprint are not tried (see :data:`OVERHANG`). Returns (height, reachable), and with ``return_scale`` the
    normal scale of the reachable surface: 1 / sqrt(1 + slope^2) of the design where the
    ball reaches it, and where it cannot, of the lowest ball's surface above the point
    (the surface the ball leaves there is that ball's: d from its centre, the scale is
    sqrt(R^2 - d^2) / R; never below the design's)."""
    from .compensate import compensate

    overhang = OVERHANG * R if overhang is None else overhang
    ox_, oy_ = (overhang, overhang) if np.isscalar(overhang) else (float(overhang[0]), float(overhang[1]))

    def drop(qx, qy):
        shape = qx.shape
        qx, qy = qx.ravel(), qy.ravel()
        z = np.concatenate([compensate(ws, qx[i:i + chunk], qy[i:i + chunk], R)
                            for i in range(0, qx.size, chunk)]) if qx.size else np.zeros(0)
        return z.reshape(shape)

    def drop_info(qx, qy):
        """Tip heights and contact points (1-D)."""
        out = [compensate(ws, qx[i:i + chunk], qy[i:i + chunk], R, return_info=True)
               for i in range(0, qx.size, chunk)]
        if not out:
            return np.zeros(0), np.zeros(0), np.zeros(0)
        return (np.concatenate([z for z, _ in out]), np.concatenate([f.contact_x for _, f in out]),
                np.concatenate([f.contact_y for _, f in out]))

    H, hx, hy = ws.all(px, py)[:3]
    design = np.minimum(H, 0.0)
    with np.errstate(all="ignore"):
        w = np.sqrt(1.0 + hx * hx + hy * hy)
        top = H >= 0
        nx, ny, nz = np.where(top, 0.0, -hx / w), np.where(top, 0.0, -hy / w), np.where(top, 1.0, 1.0 / w)
    scale = np.where(top, 1.0, np.nan_to_num(1.0 / w, nan=1.0))
    cx, cy = px + R * nx, py + R * ny
    tip = design + R * nz - R
    Z = drop(cx, cy)
    ok = top | ~np.isfinite(Z) | (Z <= tip + 1e-7)
    out = design.copy()
    bad = np.nonzero(~ok)[0]
    if bad.size:
        bx, by = px[bad], py[bad]

        def surface_at(ox, oy, idx=slice(None)):
            """g at the points ``idx`` for centre offsets (ox, oy) (arrays (m, k)); +inf
            where the ball misses the point, touches nothing, or stands farther beyond
            the footprint than ``overhang``."""
            qx, qy = bx[idx][:, None] + ox, by[idx][:, None] + oy
            zq = drop(qx, qy)
            with np.errstate(invalid="ignore"):
                low = zq + R - np.sqrt(R * R - ox * ox - oy * oy)
            ex = np.maximum(np.maximum(-qx, qx - ws.L), 0.0)
            ey = np.maximum(np.maximum(-qy, qy - ws.W), 0.0)
            over = (ex > ox_) | (ey > oy_) | (ex * ex + ey * ey > max(ox_, oy_) ** 2)
            return np.where(np.isfinite(low) & (ox * ox + oy * oy <= R * R) & ~over, low, np.inf)

        def allowed(ox, oy):
            qx, qy = bx + ox, by + oy
            ex = np.maximum(np.maximum(-qx, qx - ws.L), 0.0)
            ey = np.maximum(np.maximum(-qy, qy - ws.W), 0.0)
            over = (ex > ox_) | (ey > oy_) | (ex * ex + ey * ey > max(ox_, oy_) ** 2)
            return (ox * ox + oy * oy <= R * R) & ~over

        # starts: the centre above the point, the normal-offset centre (its drop is Z),
        # and the lowest of the balls centred on a grid (REACH_GRID x R) over the stock
        # within R of the point
        nox, noy = (cx - px)[bad], (cy - py)[bad]
        with np.errstate(invalid="ignore"):
            gn = Z[bad] + R - np.sqrt(R * R - nox * nox - noy * noy)
        gn = np.where(np.isfinite(gn) & allowed(nox, noy), gn, np.inf)
        g0 = surface_at(np.zeros((bad.size, 1)), np.zeros((bad.size, 1)))[:, 0]
        lower = gn < g0
        best, bo_x, bo_y = np.where(lower, gn, g0), np.where(lower, nox, 0.0), np.where(lower, noy, 0.0)
        gs, gxs, gys = _grid_starts(ws, bx, by, R, drop, (ox_, oy_), split=True)
        first = np.where(gs[1] < gs[0], 1, 0)
        gb, gx_, gy_ = (np.choose(first, v) for v in (gs, gxs, gys))
        lower = gb < best
        best, bo_x, bo_y = np.where(lower, gb, best), np.where(lower, gx_, bo_x), np.where(lower, gy_, bo_y)
        if REACH_METHOD == "compass":
            _compass(surface_at, best, bo_x, bo_y, R)
        else:
            def probe(ox, oy, idx):
                """One ball per point ``idx``, centred at offset (ox, oy) from it: (g as
                surface_at, the centre's height Zc, dZc/dX, dZc/dY from the contact)."""
                qx, qy = bx[idx] + ox, by[idx] + oy
                Zc, qcx, qcy = drop_info(qx, qy)
                Zc = Zc + R
                with np.errstate(invalid="ignore", divide="ignore"):
                    low = Zc - np.sqrt(R * R - ox * ox - oy * oy)
                    ux, uy = qcx - qx, qcy - qy
                    sq = np.sqrt(np.maximum(R * R - ux * ux - uy * uy, 1e-24 * R * R))
                ex = np.maximum(np.maximum(-qx, qx - ws.L), 0.0)
                ey = np.maximum(np.maximum(-qy, qy - ws.W), 0.0)
                over = (ex > ox_) | (ey > oy_) | (ex * ex + ey * ey > max(ox_, oy_) ** 2)
                g = np.where(np.isfinite(low) & (ox * ox + oy * oy <= R * R) & ~over, low, np.inf)
                return g, Zc, ux / sq, uy / sq

            box = (-ox_ - bx, ws.L + ox_ - bx, -oy_ - by, ws.W + oy_ - by)

            def descend(sel, iters):
                """_descend on the points ``sel`` (in place); the unsettled among them."""
                b_, x_, y_ = best[sel], bo_x[sel], bo_y[sel]
                mv = _descend(lambda ox, oy, idx: probe(ox, oy, sel[idx]), b_, x_, y_, R,
                              tuple(v[sel] for v in box), iters)
                best[sel], bo_x[sel], bo_y[sel] = b_, x_, y_
                return sel[mv]

            def share(src, dst, iters):
                """Neighbouring points share their lowest balls: the points ``dst`` try
                those of ``src`` (real balls: their centre heights are drops) and descend
                again from one lower than their own (another basin)."""
                for _ in range(REACH_SHARE_ROUNDS):
                    moved = _share(bx, by, best, bo_x, bo_y, R, src, dst)
                    if not moved.size:
                        break
                    descend(moved, iters)

            # the lead points (the first in each cell of REACH_LEAD x R) are searched
            # fully: from the grid's best and from the best on the other side of the
            # stock's edge (a ball over the stock, or one hanging off it) when within
            # REACH_SECOND of it (another basin), then from each other's balls, then by the
            # compass where the descent did not settle on a kink. The other points start
            # from the lead points' balls (next to their own lowest: a short descent).
            # (every point within R of the stock's edges is a lead point: balls hanging off
            # an edge make other basins there)
            edge = (bx < R) | (bx > ws.L - R) | (by < R) | (by > ws.W - R)
            lead, rest = _leaders(bx, by, REACH_LEAD * R, edge)
            qx, qy = (bx + bo_x)[lead], (by + bo_y)[lead]
            side = np.where((qx < 0) | (qx > ws.L) | (qy < 0) | (qy > ws.W), 1, 0)
            g2, x2, y2 = (np.choose(1 - side, [v[0][lead], v[1][lead]]) for v in (gs, gxs, gys))
            two = np.nonzero(np.isfinite(g2) & (g2 < best[lead] + REACH_SECOND * R))[0]
            unsettled = np.zeros(bad.size, bool)
            if two.size:
                # the second start's descent, then the first's; the lower kept
                sel = lead[two]
                first_start = best[sel], bo_x[sel], bo_y[sel]
                best[sel], bo_x[sel], bo_y[sel] = g2[two], x2[two], y2[two]
                unsettled[descend(sel, REACH_ITERS_SECOND)] = True
                second = best[sel], bo_x[sel], bo_y[sel]
                best[sel], bo_x[sel], bo_y[sel] = first_start
                mv2 = unsettled[sel]
                unsettled[sel] = False
            unsettled[descend(lead, REACH_ITERS)] = True
            if two.size:
                lo = second[0] < best[sel]
                k = sel[lo]
                best[k], bo_x[k], bo_y[k] = second[0][lo], second[1][lo], second[2][lo]
                unsettled[k] = mv2[lo]
            slow = np.nonzero(unsettled)[0]
            share(lead, lead, REACH_ITERS)
            if slow.size:
                # first one compass step of REACH_PROBE x R: where none lowers the point,
                # it stays (the descent's crawl ended on a ball no nearby one is below)
                dirs = 2 * np.pi * np.arange(REACH_DIRS) / REACH_DIRS
                tx = bo_x[slow, None] + REACH_PROBE * R * np.cos(dirs)
                ty = bo_y[slow, None] + REACH_PROBE * R * np.sin(dirs)
                G = surface_at(tx, ty, slow)
                j = np.argmin(G, axis=1)
                r = np.arange(slow.size)
                up = G[r, j] < best[slow]
                k = slow[up]
                best[k], bo_x[k], bo_y[k] = G[r, j][up], tx[r, j][up], ty[r, j][up]
                slow = k
            if slow.size:
                sb, sx_, sy_ = best[slow], bo_x[slow], bo_y[slow]
                _compass(lambda tx, ty, idx, m=slow: surface_at(tx, ty, m[idx]), sb, sx_, sy_, R,
                         REACH_POLISH)
                best[slow], bo_x[slow], bo_y[slow] = sb, sx_, sy_
            if rest.size:
                _share(bx, by, best, bo_x, bo_y, R, lead, rest)
                descend(rest, REACH_ITERS_REST)
                share(np.arange(bad.size), rest, REACH_ITERS_REST)
        out[bad] = np.maximum(design[bad], np.minimum(best, 0.0))
        d2 = np.minimum(bo_x * bo_x + bo_y * bo_y, R * R)
        fillet = np.where(np.isfinite(best) & (best < 0.0), np.sqrt(R * R - d2) / R, 1.0)
        scale[bad] = np.maximum(scale[bad], fillet)
    return (out, ok, scale) if return_scale else (out, ok)


def _line_min(gx, gy, u0x, u0y, tx, ty, R):
    """Along the line u0 + t (tx, ty) (u0 its point nearest the origin, (tx, ty) a unit
    vector), the point where g . u - sqrt(R^2 - |u|^2) is lowest (closed form; nan
    where the line misses the disk of radius R)."""
    with np.errstate(invalid="ignore"):
        rho = np.sqrt(R * R - u0x * u0x - u0y * u0y)
        sig = gx * tx + gy * ty
        t = -sig * rho / np.sqrt(1.0 + sig * sig)
    return u0x + t * tx, u0y + t * ty


def _model_min(A, B, hb, box, R):
    """The lowest point of the model max(la, lb)(u) - sqrt(R^2 - |u|^2) over the box of
    allowed centre offsets (xlo, xhi, ylo, yhi): la, lb linear (z, gx, gy, ux, uy: the
    value z and slope g at u), lb only where ``hb``. The model is convex: its lowest
    point is the best of the stationary points of each active set (one piece or the
    kink line la = lb; free, on one side of the box, or at a corner). Returns
    (ux, uy, M); M = inf where no candidate is in the box."""
    xlo, xhi, ylo, yhi = box
    zero, one = np.zeros_like(xlo), np.ones_like(xlo)
    cx, cy = [], []
    # one piece: free, and along each side of the box
    for P in (A, B):
        s1 = np.sqrt(1.0 + P[1] * P[1] + P[2] * P[2])
        cx.append(-R * P[1] / s1)
        cy.append(-R * P[2] / s1)
        for c in (xlo, xhi):
            ux, uy = _line_min(P[1], P[2], c, zero, zero, one, R)
            cx.append(ux)
            cy.append(uy)
        for c in (ylo, yhi):
            ux, uy = _line_min(P[1], P[2], zero, c, one, zero, R)
            cx.append(ux)
            cy.append(uy)
    # the kink line la = lb: n . u = d0
    dx, dy = A[1] - B[1], A[2] - B[2]
    dn = np.hypot(dx, dy)
    with np.errstate(invalid="ignore", divide="ignore"):
        rhs = (B[0] - B[1] * B[3] - B[2] * B[4]) - (A[0] - A[1] * A[3] - A[2] * A[4])
        nx, ny, d0 = dx / dn, dy / dn, rhs / dn
        ux, uy = _line_min(A[1], A[2], d0 * nx, d0 * ny, -ny, nx, R)
        cx.append(ux)
        cy.append(uy)
        for c in (xlo, xhi):                  # the kink line across a side
            cx.append(c)
            cy.append((d0 - nx * c) / ny)
        for c in (ylo, yhi):
            cx.append((d0 - ny * c) / nx)
            cy.append(c)
    for a in (xlo, xhi):                      # the corners
        for b in (ylo, yhi):
            cx.append(a)
            cy.append(b)
    UX, UY = np.stack(cx), np.stack(cy)
    with np.errstate(invalid="ignore"):
        la = A[0] + A[1] * (UX - A[3]) + A[2] * (UY - A[4])
        lb = np.where(hb, B[0] + B[1] * (UX - B[3]) + B[2] * (UY - B[4]), -np.inf)
        M = np.maximum(la, lb) - np.sqrt(R * R - UX * UX - UY * UY)
    eps = 1e-12 * R
    feas = (np.isfinite(M) & (UX >= xlo - eps) & (UX <= xhi + eps) & (UY >= ylo - eps) & (UY <= yhi + eps))
    M = np.where(feas, M, np.inf)
    k = np.argmin(M, axis=0)
    r = np.arange(k.size)
    return np.clip(UX[k, r], xlo, xhi), np.clip(UY[k, r], ylo, yhi), M[k, r]


def _descend(probe, best, bo_x, bo_y, R, box, iters=None):
    """Lower each point's best ball (in place) by a model descent: the centre height is
    modelled as the larger of two linear pieces, the drops' exact heights and
    slopes (from their contacts) on either side of the kink where the lowest ball rests
    on two walls; each step drops the model's lowest ball (closed form, within the
    allowed centres ``box``: offsets (xlo, xhi, ylo, yhi) per point) within a trust
    radius. Every value kept is a real drop. Returns the points not settled on a kink
    after REACH_ITERS drops (bool)."""
    n = best.size
    act = np.arange(n)
    g, za, ax, ay = probe(bo_x, bo_y, act)
    ok = np.isfinite(za) & np.isfinite(ax) & np.isfinite(ay)
    uax, uay = bo_x.copy(), bo_y.copy()
    zb, bgx, bgy, ubx, uby = (np.zeros(n) for _ in range(5))
    has_b = np.zeros(n, bool)
    delta = np.full(n, 0.5 * REACH_GRID * R)
    refresh = np.zeros(n, bool)
    fresh = np.zeros(n, bool)                       # the last drop was a refresh
    nref = np.zeros(n)                              # refreshes in a row on the same side
    prev = np.full(n, 0.5 * REACH_GRID * R)        # the last model step's length
    last = np.zeros(n, np.int8)
    act = act[ok & np.isfinite(best)]
    for _ in range(REACH_ITERS if iters is None else iters):
        if not act.size:
            break
        A = (za[act], ax[act], ay[act], uax[act], uay[act])
        B = (zb[act], bgx[act], bgy[act], ubx[act], uby[act])
        hb = has_b[act]
        tx, ty, M = _model_min(A, B, hb, tuple(b[act] for b in box), R)
        none = ~np.isfinite(M)
        sx, sy = tx - bo_x[act], ty - bo_y[act]
        sn = np.hypot(sx, sy)
        f = np.where(sn > delta[act], delta[act] / np.maximum(sn, 1e-300), 1.0)
        sx, sy = np.where(none, 0.0, sx * f), np.where(none, 0.0, sy * f)
        sn = np.hypot(sx, sy)
        # after a step that did not lower the point, the piece not updated by it may be
        # stale (a curved wall): drop a ball just across the kink line on its side instead
        # (or that is stale: linearised farther from the best ball than 8 last steps)
        la0 = last[act] == 0
        ox_, oy_ = np.where(la0, B[3], A[3]), np.where(la0, B[4], A[4])
        bx_, by_ = bo_x[act], bo_y[act]
        sp = np.maximum(prev[act], 1e-7 * R)
        rf = hb & ~fresh[act] & (refresh[act] | (np.hypot(ox_ - bx_, oy_ - by_) > 8.0 * sp))
        ex, ey = np.where(la0, B[1] - A[1], A[1] - B[1]), np.where(la0, B[2] - A[2], A[2] - B[2])
        en = np.maximum(np.hypot(ex, ey), 1e-300)
        # across the model's kink line: twice the model's distance to it, plus the last step
        with np.errstate(invalid="ignore"):
            gap = np.abs((A[0] + A[1] * (bx_ - A[3]) + A[2] * (by_ - A[4]))
                         - (B[0] + B[1] * (bx_ - B[3]) + B[2] * (by_ - B[4]))) / en
        # (4 times farther after each that landed on the same side)
        eps = np.minimum(np.maximum(np.nan_to_num(2.0 * gap), 1e-6 * R) * 4.0 ** nref[act], 0.5 * REACH_GRID * R)
        # (shortened to stay a ball the point allows: within R of it and in the box)
        xlo, xhi, ylo, yhi = (b[act] for b in box)
        for _ in range(8):
            qx, qy = bx_ + eps * ex / en, by_ + eps * ey / en
            out = (qx * qx + qy * qy >= R * R) | (qx < xlo) | (qx > xhi) | (qy < ylo) | (qy > yhi)
            eps = np.where(out, 0.25 * eps, eps)
        sx, sy = np.where(rf, eps * ex / en, sx), np.where(rf, eps * ey / en, sy)
        none &= ~rf
        nx2, ny2 = bo_x[act] + sx, bo_y[act] + sy
        gn, zn, gxn, gyn = probe(nx2, ny2, act)
        up = gn < best[act]
        ia = act[up]
        best[ia], bo_x[ia], bo_y[ia] = gn[up], nx2[up], ny2[up]
        delta[act] = np.where(up, np.minimum(np.maximum(delta[act], 2 * sn), 0.25 * R),
                              np.where(rf, delta[act], 0.5 * sn))
        refresh[act] = ~up & ~rf
        fresh[act] = rf
        prev[act] = np.where(rf, prev[act], sn)
        sn = np.where(rf, eps, sn)
        # the new piece replaces the one whose slope is nearer (the first other slope: b)
        fin = np.isfinite(zn) & np.isfinite(gxn) & np.isfinite(gyn)
        da = np.hypot(gxn - A[1], gyn - A[2])
        near_a = da <= np.hypot(gxn - B[1], gyn - B[2])
        new_b = ~hb & (da > 1e-9)
        to_a = fin & ((hb & near_a) | (~hb & ~new_b))
        to_b = fin & ((hb & ~near_a) | new_b)
        for Pz, Px, Py, Pux, Puy, sel in ((za, ax, ay, uax, uay, to_a), (zb, bgx, bgy, ubx, uby, to_b)):
            i = act[sel]
            Pz[i], Px[i], Py[i], Pux[i], Puy[i] = zn[sel], gxn[sel], gyn[sel], nx2[sel], ny2[sel]
        has_b[act[to_b]] = True
        # a refresh that updated the piece it meant to leave fresh (the same side) counts
        same = rf & np.where(la0, to_a, to_b)
        nref[act] = np.where(same, nref[act] + 1, 0)
        last[act[to_a]] = 0
        last[act[to_b]] = 1
        tol = 1e-4 * R
        near = has_b[act] & (np.hypot(uax[act] - bo_x[act], uay[act] - bo_y[act]) < tol) \
            & (np.hypot(ubx[act] - bo_x[act], uby[act] - bo_y[act]) < tol)
        still = (sn > 1e-9 * R) & (delta[act] > 1e-9 * R)
        act = act[~none & (still | ~near)]
    # settled: both pieces linearised next to the best ball, on either side of its kink
    # (the others, still moving or stopped on a model of one wall, are for the compass)
    tol = 1e-4 * R
    settled = has_b & (np.hypot(uax - bo_x, uay - bo_y) < tol) & (np.hypot(ubx - bo_x, uby - bo_y) < tol) \
        & (np.hypot(ax - bgx, ay - bgy) > 1e-3)
    moving = np.isfinite(best) & ~settled
    moving[act] = True
    return moving


def _share(bx, by, best, bo_x, bo_y, R, src, dst):
    """Offer the points ``dst`` the balls the points ``src`` ended on (in place): per cell
    of REACH_SHARE_CELL x R the ball with the lowest centre, at its exact height. Returns
    the indices of the points it lowered."""
    src = src[np.isfinite(best[src])]
    if not src.size or not dst.size:
        return np.zeros(0, dtype=np.intp)
    cx, cy = bx[src] + bo_x[src], by[src] + bo_y[src]
    zc = best[src] + np.sqrt(np.maximum(R * R - bo_x[src] ** 2 - bo_y[src] ** 2, 0.0))
    h = REACH_SHARE_CELL * R
    key = np.floor(cx / h).astype(np.int64) * 1_000_003 + np.floor(cy / h).astype(np.int64)
    o = np.lexsort((zc, key))
    first = np.r_[True, key[o][1:] != key[o][:-1]]
    cx, cy, zc = cx[o][first], cy[o][first], zc[o][first]
    # bins of size R: a point looks at the 3 x 3 bins around its own
    x0, y0 = cx.min(), cy.min()
    ix, iy = np.floor((cx - x0) / R).astype(np.int64), np.floor((cy - y0) / R).astype(np.int64)
    ny = int(iy.max()) + 3
    cid = (ix + 1) * ny + (iy + 1)
    order = np.argsort(cid, kind="stable")
    cid_s = cid[order]
    px, py = bx[dst], by[dst]
    from .kernels import module

    kern = module()
    if kern is not None:
        m, mx, my = np.empty(dst.size), np.empty(dst.size), np.empty(dst.size)
        ptr = np.searchsorted(cid_s, np.arange(int(cid_s[-1]) + 2))
        kern.reach_share(np.ascontiguousarray(px), np.ascontiguousarray(py), float(x0), float(y0), float(R),
                         int(ny), ptr.astype(np.int64), np.ascontiguousarray(cx[order]),
                         np.ascontiguousarray(cy[order]), np.ascontiguousarray(zc[order]), m, mx, my)
        up = m < best[dst] - 1e-12 * R
        d = dst[up]
        best[d], bo_x[d], bo_y[d] = m[up], mx[up], my[up]
        return d
    px_i = np.floor((px - x0) / R).astype(np.int64) + 1
    py_i = np.floor((py - y0) / R).astype(np.int64) + 1
    m = np.full(dst.size, np.inf)
    mx, my = np.zeros(dst.size), np.zeros(dst.size)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            c = (px_i + di) * ny + (py_i + dj)
            valid = (px_i + di >= 0) & (py_i + dj >= 0) & (py_i + dj < ny)
            lo = np.searchsorted(cid_s, c, "left")
            hi = np.searchsorted(cid_s, c, "right")
            cnt = np.where(valid, hi - lo, 0)
            tot = int(cnt.sum())
            if not tot:
                continue
            own = np.repeat(np.arange(dst.size), cnt)
            off = np.arange(tot) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            k = order[np.repeat(lo, cnt) + off]
            ux, uy = cx[k] - px[own], cy[k] - py[own]
            with np.errstate(invalid="ignore"):
                g = zc[k] - np.sqrt(R * R - ux * ux - uy * uy)
            g = np.where(np.isfinite(g), g, np.inf)
            mm = np.full(dst.size, np.inf)
            np.minimum.at(mm, own, g)
            hit = np.nonzero(g == mm[own])[0]
            j = np.full(dst.size, -1)
            j[own[hit]] = hit
            up = mm < m
            u = np.nonzero(up)[0]
            m[u], mx[u], my[u] = mm[u], ux[j[u]], uy[j[u]]
    up = m < best[dst] - 1e-12 * R
    d = dst[up]
    best[d], bo_x[d], bo_y[d] = m[up], mx[up], my[up]
    return d


def _leaders(bx, by, cell, always):
    """(lead, rest): the first point in each cell of size ``cell`` and the points
    ``always`` (bool), and the others."""
    key = np.floor(bx / cell).astype(np.int64) * 1_000_003 + np.floor(by / cell).astype(np.int64)
    _, first = np.unique(key, return_index=True)
    mask = always.copy()
    mask[first] = True
    return np.nonzero(mask)[0], np.nonzero(~mask)[0]

def _compass(surface_at, best, bo_x, bo_y, R, step0=0.5 * REACH_GRID):
    """The compass search from the best start (in place): 8 directions, first steps
    ``step0`` x R, halved when none lowers the point."""
    r = np.arange(best.size)
    dirs = 2 * np.pi * np.arange(REACH_DIRS) / REACH_DIRS
    dx, dy = np.cos(dirs), np.sin(dirs)
    step = np.full(best.size, step0 * R)
    act = r
    for _ in range(REACH_SEARCH):
        if not act.size:
            break
        tx, ty = bo_x[act, None] + step[act, None] * dx, bo_y[act, None] + step[act, None] * dy
        G = surface_at(tx, ty, act)
        j = np.argmin(G, axis=1)
        ra = np.arange(act.size)
        g = G[ra, j]
        up = g < best[act]
        best[act] = np.where(up, g, best[act])
        bo_x[act] = np.where(up, tx[ra, j], bo_x[act])
        bo_y[act] = np.where(up, ty[ra, j], bo_y[act])
        step[act] = np.where(up, step[act], 0.5 * step[act])
        # a point whose step fell below REACH_STEP_MIN x R stops (the next steps could
        # lower it by less than about that: a few 1e-5 mm)
        act = act[step[act] >= REACH_STEP_MIN * R]


def _grid_starts(ws, bx, by, R, drop, overhang=(0.0, 0.0), split=False):
    """Per point (bx, by), the lowest surface above it of the balls centred on a grid of
    spacing REACH_GRID x R over the stock and up to ``overhang`` (x, y) beyond it (the last
    node of each side at ``overhang``; exact drop-cutter heights; only the nodes within R
    of some point are dropped): (g, centre offset x, y), +inf where none. With ``split``
    the same as two lists, [on the stock, beyond its edges]."""
    h = REACH_GRID * R

    def axis(length, overhang):
        n = int(math.ceil(length / h)) + 1
        g = np.linspace(0.0, length, n)
        st = g[1] - g[0] if n > 1 else h
        k = int(math.ceil(overhang / st - 1e-9)) if overhang > 0 else 0
        out = np.minimum(st * np.arange(1, k + 1), overhang)
        return np.r_[-out[::-1], g, length + out], st, k

    xs, hx, kx = axis(ws.L, overhang[0])
    ys, hy, ky = axis(ws.W, overhang[1])
    nx, ny = xs.size, ys.size
    ix = np.clip(np.rint(bx / hx).astype(int) + kx, 0, nx - 1)
    iy = np.clip(np.rint(by / hy).astype(int) + ky, 0, ny - 1)
    rx, ry = int(math.ceil(R / hx)) + 1, int(math.ceil(R / hy)) + 1
    near = np.zeros((nx, ny), bool)
    near[ix, iy] = True
    # dilated by (rx, ry) nodes: a box sum over a summed-area table
    S = np.zeros((nx + 1, ny + 1))
    S[1:, 1:] = np.cumsum(np.cumsum(near, axis=0), axis=1)
    i0, i1 = np.clip(np.arange(nx) - rx, 0, nx), np.clip(np.arange(nx) + rx + 1, 0, nx)
    j0, j1 = np.clip(np.arange(ny) - ry, 0, ny), np.clip(np.arange(ny) + ry + 1, 0, ny)
    near = (S[i1][:, j1] - S[i0][:, j1] - S[i1][:, j0] + S[i0][:, j0]) > 0
    Z = np.full((nx, ny), np.inf)
    qi, qj = np.nonzero(near)
    z = drop(xs[qi], ys[qj])
    Z[qi, qj] = np.where(np.isfinite(z), z, np.inf)
    from .kernels import module

    kern = module()
    if kern is not None and bx.size:
        B, OX, OY = (np.empty((2, bx.size)) for _ in range(3))
        kern.reach_grid_best(np.ascontiguousarray(bx, dtype=float), np.ascontiguousarray(by, dtype=float),
                             ix.astype(np.int64), iy.astype(np.int64), xs, ys, np.ascontiguousarray(Z),
                             int(kx), int(ky), int(rx), int(ry), float(R), B, OX, OY)
        best, ox, oy = [B[0], B[1]], [OX[0], OX[1]], [OY[0], OY[1]]
        if split:
            return best, ox, oy
        lo = best[1] < best[0]
        return (np.where(lo, best[1], best[0]), np.where(lo, ox[1], ox[0]), np.where(lo, oy[1], oy[0]))
    # the best node on the stock and the best beyond its edges, apart
    best = [np.full(bx.size, np.inf), np.full(bx.size, np.inf)]
    ox, oy = [np.zeros(bx.size), np.zeros(bx.size)], [np.zeros(bx.size), np.zeros(bx.size)]
    R2 = R * R
    for di in range(-rx, rx + 1):
        i = ix + di
        okx = (i >= 0) & (i < nx)
        i = np.clip(i, 0, nx - 1)
        dx = xs[i] - bx
        offx = (i < kx) | (i >= nx - kx)
        dx2 = dx * dx
        for dj in range(-ry, ry + 1):
            jj = iy + dj
            ok = okx & (jj >= 0) & (jj < ny)
            jj = np.clip(jj, 0, ny - 1)
            dy = ys[jj] - by
            d2 = dx2 + dy * dy
            ok &= d2 < R2
            if not ok.any():
                continue
            with np.errstate(invalid="ignore"):
                g = Z[i, jj] + R - np.sqrt(R2 - d2)
            off = offx | (jj < ky) | (jj >= ny - ky)
            for side in (0, 1):
                up = ok & (g < best[side]) & (off == bool(side))
                if up.any():
                    best[side] = np.where(up, g, best[side])
                    ox[side], oy[side] = np.where(up, dx, ox[side]), np.where(up, dy, oy[side])
    if split:
        return best, ox, oy
    lo = best[1] < best[0]
    return (np.where(lo, best[1], best[0]), np.where(lo, ox[1], ox[0]), np.where(lo, oy[1], oy[0]))


def _dist_to_segment(px, py, a, b):
    d = b - a
    dd = float(d @ d)
    if dd == 0:
        return np.hypot(px - a[0], py - a[1])
    t = np.clip(((px - a[0]) * d[0] + (py - a[1]) * d[1]) / dd, 0.0, 1.0)
    return np.hypot(px - a[0] - t * d[0], py - a[1] - t * d[1])


__all__ = ["Program", "read_program", "estimate_time", "capsule_lower", "SegmentGrid", "sample_points",
           "verify_cut", "reachable_height", "RAPID", "FEED"]
