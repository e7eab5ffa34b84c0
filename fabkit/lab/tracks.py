"""The lab stage's tracks in: readers of tracked trajectories, and the map from video
coordinates to the design's.

Formats (detected from the first lines):

* Tracker's text export (physlets.org/tracker, "Export > Data"): line 1 the track's
  name, line 2 tab-separated headers with ``t``, ``x``, ``y`` (other columns ignored),
  then one row a frame; blank cells (frames where the ball was not marked) are skipped.
* CSV with a header holding ``t``, ``x``, ``y`` (comma, semicolon or tab separated;
  other columns ignored; rows with a blank x or y skipped).
* CSV with ``frame``, ``x``, ``y``: t = frame / fps (``fps`` required).
* trackpy's CSV (``frame``, ``x``, ``y``, ``particle``, and trackpy's other columns,
  often a leading unnamed index): the particle with the most frames is kept; t = frame / fps.

Headers may state units, as Logger Pro, PASCO Capstone and Kinovea export them:
``Time (s)``, ``X (m)``, ``x [cm]``, ``t/ms``, ``Latest: Y (m)``, ``X Position (mm) Run #1``.
A data-set prefix (``Latest:``, ``Run 1:``) and a run suffix (``Run #1``) are dropped;
``position x`` / ``x position`` name x. The stated units are converted (:data:`TIME_UNITS`,
:data:`LENGTH_UNITS`): times to s, lengths to the spec's design unit (``units``); a
length in pixels (``px``) is a video unit and keeps ``--scale``. Giving ``--scale``
with positions in a stated length unit is refused (the file says what its numbers are).

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
from ..units import MM_PER_INCH

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
#: the time units a header may state, in s
TIME_UNITS = {"s": 1.0, "sec": 1.0, "ms": 1e-3, "us": 1e-6, "\u00b5s": 1e-6, "\u03bcs": 1e-6, "min": 60.0}
#: the length units a header may state, in mm (None: a video unit, pixels)
LENGTH_UNITS = {"m": 1000.0, "cm": 10.0, "mm": 1.0, "um": 1e-3, "\u00b5m": 1e-3, "\u03bcm": 1e-3,
                "in": MM_PER_INCH, "inch": MM_PER_INCH, "inches": MM_PER_INCH, "ft": 304.8, "px": None, "pixel": None,
                "pixels": None, "pix": None}


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


#: a frame's stated sigma is taken as at least this share of the track's median (a weight
#: at most 10 times the median frame's)
SIGMA_FLOOR = 0.1


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
    #: the tracker's one-sigma of each x and y (design units; ``t,x,y,sigma_x,sigma_y``
    #: files), None when the file has none
    sigma_x: np.ndarray | None = None
    sigma_y: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)

    def weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Relative least-squares weights of x and y: median sigma / sigma per frame (a
        frame's sigma floored at SIGMA_FLOOR of the median, a missing one the median), all
        1 without sigma columns or with a constant sigma (the fits are then unweighted)."""
        out = []
        for s in (self.sigma_x, self.sigma_y):
            if s is None:
                out.append(np.ones(len(self.t)))
                continue
            ok = np.isfinite(s) & (s > 0)
            med = float(np.median(s[ok])) if ok.any() else 1.0
            ss = np.where(ok, np.maximum(s, SIGMA_FLOOR * med), med)
            out.append(med / ss)
        return out[0], out[1]

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


_NAMES = {"t": "t", "time": "t", "x": "x", "y": "y", "frame": "frame", "frame number": "frame",
          "frame #": "frame", "frame no.": "frame", "particle": "particle",
          "x position": "x", "position x": "x", "x-position": "x", "pos x": "x",
          "y position": "y", "position y": "y", "y-position": "y", "pos y": "y"}


def parse_header_cell(cell: str) -> tuple[str, str | None]:
    """(name, unit) of one header cell: ``"Latest: X (m)"`` -> ("x", "m"), ``"t/ms"`` ->
    ("t", "ms"), ``"Time (s) Run #1"`` -> ("t", "s"), ``"x"`` -> ("x", None). The name
    lower-cased and mapped to t, x, y, frame or particle when it is one of them."""
    import re

    c = cell.strip().strip('"').strip()
    c = re.sub(r"\s+run\s*#?\s*\d+\s*$", "", c, flags=re.I)            # PASCO: "... Run #1"
    m = re.match(r"^[^:()\[\]]*:\s*(\S.*)$", c)                           # "Latest: ...", "Run 1: ..."
    if m:
        c = m.group(1)
    unit = None
    m = re.match(r"^(.*?)\s*[(\[]\s*([^()\[\]]*?)\s*[)\]]\s*$", c)      # "X (m)", "x [cm]"
    if m and m.group(1):
        c, unit = m.group(1), m.group(2)
    elif "/" in c:                                                       # "t/s" (ISO 80000)
        a, b = c.rsplit("/", 1)
        if a.strip() and b.strip().lower() in {**TIME_UNITS, **LENGTH_UNITS}:
            c, unit = a, b.strip()
    name = " ".join(c.lower().split())
    return _NAMES.get(name, name), unit


def _col(headers: list[tuple[str, str | None]], name: str) -> int | None:
    for i, (n, _) in enumerate(headers):
        if n == name:
            return i
    return None


def _unit_factors(path, hline, headers, cols, units, video):
    """(time factor to s, x and y factors to design units or None, note) of the header's
    stated units (module doc); SpecError for an unknown unit or a clash with --scale."""
    it, ix, iy = cols
    ft, fl = 1.0, [None, None]
    stated = []
    if it is not None and headers[it][1] is not None:
        u = headers[it][1]
        if u.lower() not in TIME_UNITS:
            raise _bad(path, hline + 1, f"t: unknown time unit {u!r} (known: {', '.join(TIME_UNITS)})")
        ft = TIME_UNITS[u.lower()]
        if ft != 1.0:
            stated.append(f"t in {u}")
    for k, j in enumerate((ix, iy)):
        u = headers[j][1]
        if u is None:
            continue
        key = u.lower() if u.lower() in LENGTH_UNITS else u
        if key not in LENGTH_UNITS:
            raise _bad(path, hline + 1, f"{'xy'[k]}: unknown length unit {u!r} (known: {', '.join(LENGTH_UNITS)})")
        mm = LENGTH_UNITS[key]
        if mm is None:
            continue                                # pixels: video units, --scale maps them
        if units is None:
            raise _bad(path, hline + 1, f"{'xy'[k]} is in {u}: the spec's unit is needed to convert it")
        from ..units import mm_per

        fl[k] = mm / mm_per(units)
        stated.append(f"{'xy'[k]} in {u}")
    if any(f is not None for f in fl) and video is not None and video.scale != 1.0:
        raise SpecError(f"{path} states its positions in a length unit ({', '.join(stated)}), converted to the "
                        "spec's unit: --scale is for video units (pixels), leave it out", key="--scale")
    note = f"units converted: {', '.join(stated)} -> s, {units}" if stated else None
    return ft, fl, note


def read_track(path, *, fps: float | None = None, video: VideoMap | None = None,
               units: str | None = None) -> Track:
    """Read one track file (any of the module's formats) and map it to design coordinates.
    ``units``: the spec's design unit, for a header that states its length unit."""
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
    headers = [parse_header_cell(h) for h in _split(head, delim)]
    it, ix, iy = _col(headers, "t"), _col(headers, "x"), _col(headers, "y")
    iframe, ipart = _col(headers, "frame"), _col(headers, "particle")
    isx, isy = _col(headers, "sigma_x"), _col(headers, "sigma_y")
    has_sigma = isx is not None and isy is not None
    if ix is None or iy is None or (it is None and iframe is None):
        raise _bad(path, hline + 1, f"header {head.strip()[:80]!r}: need columns t, x, y (or frame, x, y; "
                   "units may be stated, as in Time (s), X (m); "
                   "trackpy: frame, x, y, particle; Tracker: a name line, then tab-separated t x y)")
    if fmt is None:
        fmt = "trackpy" if (ipart is not None and iframe is not None) else (
            "csv" if it is not None else "frame-csv")
    use_frame = it is None
    ft, fl, unit_note = _unit_factors(path, hline, headers, (it, ix, iy), units, video)
    if use_frame:
        if fps is None:
            raise _bad(path, hline + 1, "has a frame column and no time column: give --fps")
        check_options(fps=fps)
    want = [iframe if use_frame else it, ix, iy] + ([ipart] if ipart is not None else [])
    names = ["frame" if use_frame else "t", "x", "y", "particle"]
    rows, where, skipped, sig = [], [], 0, []
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
        if has_sigma:       # a blank sigma: the track's median; a negative or non-number one refused
            sv = []
            for j, c in ((isx, "sigma_x"), (isy, "sigma_y")):
                cell = cells[j] if j < len(cells) else ""
                try:
                    v = float(cell) if cell not in ("",) and cell.lower() not in ("nan", "na") else math.nan
                except ValueError:
                    raise _bad(path, n, f"{c}: not a number: {cell[:40]!r}") from None
                if v < 0 or v == math.inf:
                    raise _bad(path, n, f"{c}: {cell[:40]!r} is not a standard deviation (>= 0, finite)")
                sv.append(v)
            sig.append(sv)
        rows.append(vals)
        where.append(n)
    if not rows:
        raise SpecError("no complete rows (t, x, y) after the header", file=str(path))
    a = np.asarray(rows, dtype=float)
    where = np.asarray(where)
    notes = [unit_note] if unit_note else []
    particle = None
    if ipart is not None:
        ids, counts = np.unique(a[:, 3], return_counts=True)
        particle = ids[int(np.argmax(counts))]
        if ids.size > 1:
            notes.append(f"{ids.size} particles; kept particle {particle:g} ({counts.max()} frames)")
        keep = a[:, 3] == particle
        a, where = a[keep], where[keep]
        if sig:
            sig = [v for v, k in zip(sig, keep) if k]
        particle = int(particle) if float(particle).is_integer() else particle
    if fmt == "trackpy":   # trackpy writes frames in any order
        order = np.argsort(a[:, 0], kind="stable")
        a, where = a[order], where[order]
        if sig:
            sig = [sig[i] for i in order]
    t = a[:, 0] / fps if use_frame else a[:, 0] * ft
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
        px = a[:, 1] * fl[0] if fl[0] is not None else a[:, 1]
        py = a[:, 2] * fl[1] if fl[1] is not None else a[:, 2]
        x, y = (video or VideoMap()).apply(px, py)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        i = int(np.flatnonzero(~(np.isfinite(x) & np.isfinite(y)))[0])
        raise _bad(path, int(where[i]), f"x, y = {a[i, 1]:g}, {a[i, 2]:g} map to a non-finite position "
                   f"(--scale, --origin)")
    sx = sy = None
    if has_sigma and sig:
        S = np.asarray(sig, dtype=float)
        # the sigmas in the positions' unit: the header's length factor, then the video map's scale
        vm = video or VideoMap()
        su = S[:, 0] * (fl[0] if fl[0] is not None else 1.0)
        sv = S[:, 1] * (fl[1] if fl[1] is not None else 1.0)
        c, sn = math.cos(math.radians(vm.rotate)), math.sin(math.radians(vm.rotate))
        # independent errors of u and v through the rotation: the variances add
        sx = vm.scale * np.sqrt((c * su) ** 2 + (sn * sv) ** 2)
        sy = vm.scale * np.sqrt((sn * su) ** 2 + (c * sv) ** 2)
    return Track(file=str(path), t=t, x=x, y=y, format=fmt, name=name, particle=particle,
                 skipped_rows=skipped, notes=notes, sigma_x=sx, sigma_y=sy)


def write_csv(track_t, x, y) -> str:
    """A ``t,x,y`` CSV of arrays (the plain format fabkit reads), full precision."""
    out = ["t,x,y"]
    out += [f"{a!r},{b!r},{c!r}" for a, b, c in zip(map(float, track_t), map(float, x), map(float, y))]
    return "\n".join(out) + "\n"
