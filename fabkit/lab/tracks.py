"""Readers of tracked trajectories, and the map from video coordinates to the design's.

Formats (detected from the first lines):

* Tracker's text export (physlets.org/tracker, "Export > Data"): line 1 the track's
  name, line 2 tab-separated headers with ``t``, ``x``, ``y`` (other columns ignored),
  then one row a frame; blank cells (frames where the ball was not marked) are skipped.
* CSV with a header holding ``t``, ``x``, ``y`` (comma, semicolon or tab separated;
  other columns ignored; rows with a blank x or y skipped).
* CSV with ``frame``, ``x``, ``y``: t = frame / fps (``fps`` required).
* trackpy's CSV (``frame``, ``x``, ``y``, ``particle``, and trackpy's other columns,
  often a leading unnamed index): the particle with the most frames is kept; t = frame / fps.

Positions are in the spec's design units and frame unless a :class:`VideoMap` maps
them: p_design = scale * R(rotate) * F (p_video - origin), where F flips y when
``flip_y`` (image rows grow downward) and R turns counterclockwise by ``rotate``
degrees. Times are in seconds.

Bad files raise :class:`SpecError` naming the file and the line: ``run3.csv: line 7:
x: not a number: 'abc'`` (exit 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError

MAX_TRACK_BYTES = 64 * 1024 * 1024   # a 10 s video at 1000 frames/s is ~0.5 MB of CSV
MIN_POINTS = 12                      # a track shorter than 0.1 s at 125 frames/s says nothing
#: size guard, stated up front: at most this many rows a track (100 s at 1000 frames/s);
#: longer tracks are refused before they are parsed (cut them to the launch or release)
MAX_POINTS = 100_000
#: the options' ranges (checked like spec keys: one line naming the option, exit 2)
FPS_RANGE = (1.0, 1.0e7)             # frames/s: a phone's slow motion to a 10 MHz camera
SCALE_RANGE = (1.0e-9, 1.0e9)        # design units per video unit
ORIGIN_MAX = 1.0e12                  # |origin|, video units
ROTATE_MAX = 360.0                   # |rotate|, degrees


@dataclass(frozen=True)
class VideoMap:
    """Video coordinates -> design coordinates (see the module doc). ``scale``: design
    units per video unit; ``origin``: the design origin in video coordinates."""

    scale: float = 1.0
    origin: tuple = (0.0, 0.0)
    rotate: float = 0.0
    flip_y: bool = False

    def apply(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = np.asarray(x, dtype=float) - self.origin[0]
        v = np.asarray(y, dtype=float) - self.origin[1]
        if self.flip_y:
            v = -v
        c, s = math.cos(math.radians(self.rotate)), math.sin(math.radians(self.rotate))
        return self.scale * (c * u - s * v), self.scale * (s * u + c * v)

    @property
    def identity(self) -> bool:
        return self == VideoMap()


@dataclass
class Track:
    """One tracked trajectory: t (N,) s increasing, x, y (N,) design units."""

    file: str
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    format: str
    name: str | None = None
    particle: int | None = None
    skipped_rows: int = 0
    notes: list = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def dt(self) -> float:
        """The median frame interval, s."""
        return float(np.median(np.diff(self.t)))


def check_options(fps=None, scale=None, origin=None, rotate=None) -> None:
    """Range checks of the track options (``--fps``, ``--scale``, ``--origin``, ``--rotate``):
    SpecError naming the option (exit 2) before any file is read."""
    def _in(name, v, lo, hi, unit):
        if v is None:
            return
        if not (math.isfinite(v) and lo <= v <= hi):
            raise SpecError(f"must be within {lo:g}..{hi:g} {unit}, got {v:g}", key=name)

    if scale is not None and not (math.isfinite(scale) and scale > 0):
        raise SpecError(f"must be > 0, got {scale:g}", key="--scale")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise SpecError(f"must be > 0, got {fps:g}", key="--fps")
    _in("--fps", fps, *FPS_RANGE, "frames/s")
    _in("--scale", scale, *SCALE_RANGE, "design units per video unit")
    for v in (origin or ()):
        _in("--origin", v, -ORIGIN_MAX, ORIGIN_MAX, "video units")
    _in("--rotate", rotate, -ROTATE_MAX, ROTATE_MAX, "degrees")


def _bad(path, line: int | None, what: str) -> SpecError:
    return SpecError(what, file=str(path), key=f"line {line}" if line else None)


def _read_text(path) -> str:
    from ..io import read_regular

    data = read_regular(path, MAX_TRACK_BYTES, "track export")   # a pipe or device refused, not read
    if len(data) > MAX_TRACK_BYTES:
        raise SpecError(f"larger than {MAX_TRACK_BYTES // 2**20} MB: not a track export", file=str(path))
    if b"\0" in data[:4096]:
        raise SpecError("binary file, not a text export (Tracker text, CSV or trackpy CSV)", file=str(path))
    for enc in ("utf-8-sig", "latin-1"):
        try:
            return data.decode(enc)
        except UnicodeDecodeError:
            continue
    raise SpecError("not a text file", file=str(path))  # pragma: no cover (latin-1 decodes anything)


def _split(line: str, delim: str | None) -> list[str]:
    return [c.strip().strip('"').strip() for c in (line.split(delim) if delim else line.split())]


def _delimiter(header: str) -> str | None:
    for d in ("\t", ",", ";"):
        if d in header:
            return d
    return None


def _col(headers: list[str], *names: str) -> int | None:
    low = [h.lower() for h in headers]
    for n in names:
        if n in low:
            return low.index(n)
    return None


def read_track(path, *, fps: float | None = None, video: VideoMap | None = None) -> Track:
    """Read one track file (any of the module's formats) and map it to design coordinates."""
    text = _read_text(path)
    lines = text.splitlines()
    if len(lines) > MAX_POINTS + 64:
        raise SpecError(f"{len(lines)} lines: more than the {MAX_POINTS} rows a track may have "
                        "(size guard): cut the track to the launch or release", file=str(path))
    first = next((i for i, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise SpecError("empty file", file=str(path))
    name = None
    hline = first
    head = lines[first]
    if "\t" not in head and "," not in head and ";" not in head and first + 1 < len(lines) \
            and "\t" in lines[first + 1]:
        name, hline, fmt = head.strip(), first + 1, "tracker"  # Tracker: name, then headers
        head = lines[hline]
    else:
        fmt = None
    delim = _delimiter(head)
    headers = _split(head, delim)
    it, ix, iy = _col(headers, "t", "time", "t (s)"), _col(headers, "x"), _col(headers, "y")
    iframe, ipart = _col(headers, "frame"), _col(headers, "particle")
    if ix is None or iy is None or (it is None and iframe is None):
        raise _bad(path, hline + 1, f"header {head.strip()[:80]!r}: need columns t, x, y (or frame, x, y; "
                   "trackpy: frame, x, y, particle; Tracker: a name line, then tab-separated t x y)")
    if fmt is None:
        fmt = "trackpy" if (ipart is not None and iframe is not None) else (
            "csv" if it is not None else "frame-csv")
    use_frame = it is None
    if use_frame:
        if fps is None:
            raise _bad(path, hline + 1, "has a frame column and no time column: give --fps")
        check_options(fps=fps)
    want = [iframe if use_frame else it, ix, iy] + ([ipart] if ipart is not None else [])
    names = ["frame" if use_frame else "t", "x", "y", "particle"]
    rows, where, skipped = [], [], 0
    for n, ln in enumerate(lines[hline + 1:], start=hline + 2):
        if not ln.strip():
            continue
        cells = _split(ln, delim)
        vals = []
        blank = False
        for j, c in zip(want, names):
            cell = cells[j] if j < len(cells) else ""
            if cell == "" or cell.lower() in ("nan", "na"):
                blank = True
                continue
            try:
                v = float(cell)
            except ValueError:
                raise _bad(path, n, f"{c}: not a number: {cell[:40]!r}") from None
            if not math.isfinite(v):
                raise _bad(path, n, f"{c}: not finite: {cell[:40]!r}")
            vals.append(v)
        if blank:
            skipped += 1
            continue
        rows.append(vals)
        where.append(n)
    if not rows:
        raise SpecError("no complete rows (t, x, y) after the header", file=str(path))
    a = np.asarray(rows, dtype=float)
    where = np.asarray(where)
    notes = []
    particle = None
    if ipart is not None:
        ids, counts = np.unique(a[:, 3], return_counts=True)
        particle = ids[int(np.argmax(counts))]
        if ids.size > 1:
            notes.append(f"{ids.size} particles; kept particle {particle:g} ({counts.max()} frames)")
        keep = a[:, 3] == particle
        a, where = a[keep], where[keep]
        particle = int(particle) if float(particle).is_integer() else particle
    if fmt == "trackpy":   # trackpy writes frames in any order
        order = np.argsort(a[:, 0], kind="stable")
        a, where = a[order], where[order]
    t = a[:, 0] / fps if use_frame else a[:, 0]
    d = np.diff(t)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        what = "repeats" if d[i] == 0 else "goes back before"
        raise _bad(path, int(where[i + 1]), f"{names[0]} = {a[i + 1, 0]:g} {what} line {where[i]} "
                   f"({names[0]} = {a[i, 0]:g}): times must increase")
    if len(t) < MIN_POINTS:
        raise SpecError(f"only {len(t)} tracked points; at least {MIN_POINTS} are needed", file=str(path))
    if not np.all(np.isfinite(t)):
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise _bad(path, int(where[i]), f"frame {a[i, 0]:g} / --fps {fps:g} is not a finite time")
    with np.errstate(all="ignore"):
        x, y = (video or VideoMap()).apply(a[:, 1], a[:, 2])
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        i = int(np.flatnonzero(~(np.isfinite(x) & np.isfinite(y)))[0])
        raise _bad(path, int(where[i]), f"x, y = {a[i, 1]:g}, {a[i, 2]:g} map to a non-finite position "
                   f"(--scale, --origin)")
    return Track(file=str(path), t=t, x=x, y=y, format=fmt, name=name, particle=particle,
                 skipped_rows=skipped, notes=notes)


def write_csv(track_t, x, y) -> str:
    """A ``t,x,y`` CSV of arrays (the plain format fabkit reads), full precision."""
    out = ["t,x,y"]
    out += [f"{a!r},{b!r},{c!r}" for a, b, c in zip(map(float, track_t), map(float, x), map(float, y))]
    return "\n".join(out) + "\n"
