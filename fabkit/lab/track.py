"""From a video of the block to the ball's calibrated trajectory.

The stages, each a function or a small class a test can call:

1. :func:`sample` - a sample of grey frames spread over the video (its key frames
   when there are enough, else every k-th frame of a full decode);
2. :func:`find_markers` - ArUco markers 0-3 in the sample, each corner the median
   over the frames it was found in (the camera stands still);
3. the camera: :func:`fabkit.lab.camera.calibrate`;
4. :class:`BallFinder` - the background (the sample's median: the ball moves) and,
   per frame, the ball: the difference from the background, its peak at the ball's
   scale on a 4x smaller image, then the disc at full resolution: pixels weighted by
   their share of the contrast (clip(|d| / c, 0, 1): a pixel the ball's edge half
   covers counts half), holes (a specular highlight) filled; the weighted centroid is
   the centre, to a fraction of a pixel. Motion blur smears the disc along the path
   symmetrically, so the centroid is the centre at mid-exposure. Its standard
   deviation follows from the background's noise. A frame where no disc of the
   ball's size stands out is a gap;
5. :func:`fabkit.lab.camera.ball_centres` - each centre's ray met with the
   ball-centre offset surface;
6. :class:`VideoTrack` - the result: times from the presentation timestamps, the
   centre's x, y in design units and their standard deviations, with its verdict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError
from . import camera as cam_mod
from . import video

SAMPLE_FRAMES = 24          # frames of the sample (background, markers)
MIN_KEYFRAMES = 9           # fewer key frames than this: sample a full decode instead
DOWN = 4                    # the coarse search's reduction
MIN_CONTRAST = 12.0         # grey levels: a ball that differs less from the surface is not found
AREA_RANGE = (0.35, 4.0)    # the disc's area against pi r^2 (blur lengthens it)
SIGMA_FLOOR_PX = 0.03       # the centre's standard deviation is at least this (the model's own limit)


@dataclass
class Sample:
    """Grey frames (k, h, w) uint8 spread over the video, and its size."""

    frames: np.ndarray
    width: int
    height: int


def sample(path, n: int = SAMPLE_FRAMES) -> Sample:
    """A sample of up to ``n`` grey frames spread over the video (see the module doc)."""
    keys = [g.copy() for _, g in video.frames(path, keyframes_only=True)]
    if len(keys) >= MIN_KEYFRAMES:
        idx = np.unique(np.linspace(0, len(keys) - 1, min(n, len(keys))).round().astype(int))
        frames = [keys[i] for i in idx]
    else:   # every frame decoded; the stride doubles whenever 2n are kept
        frames, stride = [], 1
        for i, (_, g) in enumerate(video.frames(path)):
            if i % stride == 0:
                frames.append(g.copy())
                if len(frames) >= 2 * n:
                    frames, stride = frames[::2], 2 * stride
    if not frames:
        raise SpecError("no frames could be decoded", file=str(path))
    if len(frames) > n:
        frames = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, n).round().astype(int))]
    a = np.stack(frames)
    return Sample(a, a.shape[2], a.shape[1])


def _detector():
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, cam_mod.DICTIONARY))
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    p.cornerRefinementWinSize = 3
    p.cornerRefinementMinAccuracy = 0.01
    p.cornerRefinementMaxIterations = 60
    p.minMarkerPerimeterRate = 0.01
    return cv2.aruco.ArucoDetector(d, p)


def refine_square(img: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """A marker's 4 corners (4, 2) px refined on ``img``: each side of the black square is
    a straight line through the sub-pixel points where the grey crosses halfway from the
    square's black to the quiet zone's white (profiles across the side, its middle 70 %),
    and each corner is where two sides meet. ``corners`` come back unchanged when a side
    cannot be measured."""
    import cv2

    c = np.asarray(corners, dtype=float)
    side = float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))
    if side < 8:
        return c
    centre = c.mean(axis=0)
    reach = max(2.0, side / 6.0)                 # one module: into the black and out into the quiet zone
    img32 = img.astype(np.float32)
    lines = []
    for k in range(4):
        a, b = c[k], c[(k + 1) % 4]
        t = (b - a) / np.linalg.norm(b - a)
        n = np.array([-t[1], t[0]])
        if np.dot(n, centre - (a + b) / 2) > 0:
            n = -n                                # the outward normal
        m = max(8, int(side))
        s = np.linspace(0.15, 0.85, m)
        base = a[None, :] + s[:, None] * (b - a)[None, :]
        off = np.linspace(-reach, reach, int(4 * reach) + 1)
        pts = base[:, None, :] + off[None, :, None] * n[None, None, :]
        prof = cv2.remap(img32, pts[..., 0].astype(np.float32), pts[..., 1].astype(np.float32),
                         cv2.INTER_LINEAR)
        lo, hi = np.median(prof[:, :3]), np.median(prof[:, -3:])
        if not hi - lo > 20:
            return c
        half = 0.5 * (lo + hi)
        found = []
        for row, p0 in zip(prof, base):
            j = np.flatnonzero((row[:-1] < half) & (row[1:] >= half))
            if j.size != 1:
                continue
            j = int(j[0])
            f = (half - row[j]) / (row[j + 1] - row[j])
            found.append(p0 + (off[j] + f * (off[1] - off[0])) * n)
        if len(found) < 5:
            return c
        P = np.asarray(found)
        mu = P.mean(axis=0)
        _, _, vt = np.linalg.svd(P - mu)
        d = vt[0]
        lines.append((mu, d))
    out = np.empty((4, 2))
    for k in range(4):
        (p1, d1), (p2, d2) = lines[(k - 1) % 4], lines[k]
        A = np.array([d1, -d2]).T
        st = np.linalg.solve(A, p2 - p1)
        out[k] = p1 + st[0] * d1
    if np.max(np.linalg.norm(out - c, axis=1)) > 0.25 * side:
        return c
    return out


def find_markers(frames: np.ndarray, path: str = "<video>", image: np.ndarray | None = None) -> dict:
    """id -> (4, 2) px: markers 0-3's corners, found by OpenCV's ArUco detector in the
    sample's frames (the median over the frames) and refined on ``image`` (the sample's
    median image, its noise averaged out) by :func:`refine_square`. SpecError naming
    the file when one is never found."""
    det = _detector()
    found: dict[int, list] = {i: [] for i in cam_mod.MARKER_IDS}
    for g in ([image] if image is not None else []) + list(frames):
        corners, ids, _ = det.detectMarkers(np.ascontiguousarray(g))
        if ids is not None:
            for c, i in zip(corners, ids.ravel()):
                if int(i) in found:
                    found[int(i)].append(np.asarray(c, dtype=float).reshape(4, 2))
        if image is not None and all(found.values()):
            break              # all four on the median image: refined there anyway
    missing = [i for i, v in found.items() if not v]
    if missing:
        which = ", ".join(str(i) for i in missing)
        raise SpecError(f"ArUco marker{'s' if len(missing) > 1 else ''} {which} (DICT_4X4_50) not found in "
                        f"{len(frames)} sampled frames: print them with `fabkit markers` and keep all four "
                        "in view", file=str(path))
    out = {i: np.median(np.stack(v), axis=0) for i, v in found.items()}
    if image is not None:
        out = {i: refine_square(image, c) for i, c in out.items()}
    return out


@dataclass
class Ball:
    """One frame's ball: its centre (u, v) px and standard deviations, the disc's area
    px^2 and its contrast (grey levels)."""

    u: float
    v: float
    su: float
    sv: float
    area: float
    contrast: float


class BallFinder:
    """Finds the ball frame by frame against a background (see the module doc).

    ``background`` (h, w) uint8; ``radius_px`` the ball's expected radius in px;
    ``noise`` the background's noise, grey levels (1 sigma)."""

    def __init__(self, background: np.ndarray, radius_px: float, noise: float, exclude=None):
        import cv2

        self.cv2 = cv2
        self.bg = np.ascontiguousarray(background)
        self.r = float(radius_px)
        self.noise = max(float(noise), 0.5)
        k = max(1, int(round(self.r * 1.2 / DOWN)))
        self.k = k | 1
        self.exclude = None
        self.bg_small = np.ascontiguousarray(self.bg[::DOWN, ::DOWN])
        if exclude is not None:       # (h, w) bool: pixels never searched (the markers' paper)
            self.exclude = np.asarray(exclude, dtype=bool)
            self.exclude_small = np.ascontiguousarray(self.exclude[::DOWN, ::DOWN])
        self.half = int(math.ceil(1.4 * self.r)) + 6
        self.last: list = []          # the last two frames' centres, when both had the ball
        self.threshold = max(MIN_CONTRAST, 6.0 * self.noise)

    def find(self, grey: np.ndarray) -> Ball | None:
        """The ball in this frame, or None. Frames are expected in order: where the last
        two frames had the ball, the search starts in a window around the position they
        predict (the whole frame when it is not there)."""
        b = None
        if len(self.last) == 2:
            (u1, v1), (u2, v2) = self.last
            du, dv = u2 - u1, v2 - v1
            half = int(3 * self.r + 2 * math.hypot(du, dv)) + 8
            b = self._search(grey, (u2 + du, v2 + dv, half))
        if b is None:
            b = self._search(grey, None)
        self.last = (self.last + [(b.u, b.v)])[-2:] if b is not None else []
        return b

    def _search(self, grey: np.ndarray, window) -> Ball | None:
        cv2 = self.cv2
        h, w = grey.shape
        if window is None:
            x0, y0, x1, y1 = 0, 0, w, h
        else:
            u, v, half = window
            x0, y0 = max(0, int(u) - half), max(0, int(v) - half)
            x1, y1 = min(w, int(u) + half + 1), min(h, int(v) + half + 1)
            if x1 - x0 < 2 * DOWN or y1 - y0 < 2 * DOWN:
                return None
        x0, y0 = (x0 // DOWN) * DOWN, (y0 // DOWN) * DOWN      # on the coarse grid
        # the coarse search: every DOWN-th pixel of |grey - bg|, averaged at the ball's scale
        gs = np.ascontiguousarray(grey[y0:y1:DOWN, x0:x1:DOWN])
        small = cv2.absdiff(gs, self.bg_small[y0 // DOWN:y0 // DOWN + gs.shape[0],
                                              x0 // DOWN:x0 // DOWN + gs.shape[1]])
        small = cv2.blur(small, (self.k, self.k))
        if self.exclude is not None:
            small[self.exclude_small[y0 // DOWN:y0 // DOWN + gs.shape[0],
                                     x0 // DOWN:x0 // DOWN + gs.shape[1]]] = 0
        _, peak, _, loc = cv2.minMaxLoc(small)
        if peak < 0.5 * self.threshold:
            return None
        u0, v0 = x0 + loc[0] * DOWN, y0 + loc[1] * DOWN
        # the fine step on a full-resolution crop (room for a long blur's second look)
        reach = 3 * self.half + 4
        cx0, cy0 = max(0, u0 - reach), max(0, v0 - reach)
        cx1, cy1 = min(w, u0 + reach + 1), min(h, v0 + reach + 1)
        g = grey[cy0:cy1, cx0:cx1]
        bg = self.bg[cy0:cy1, cx0:cx1]
        d = cv2.absdiff(g, bg)
        b = self._refine(d, g, bg, u0 - cx0, v0 - cy0, blur_extra=0)
        if b is None:
            return None
        b.u += cx0
        b.v += cy0
        return b

    def _refine(self, d: np.ndarray, grey: np.ndarray, bg: np.ndarray, u0: float, v0: float,
                blur_extra: int) -> Ball | None:
        """The disc around (u0, v0) in the crop ``d`` = |grey - bg| (see the module doc);
        coordinates relative to the crop."""
        cv2 = self.cv2
        h, w = d.shape
        half = self.half + blur_extra
        a0, a1 = max(0, int(u0) - half), min(w, int(u0) + half + 1)
        b0, b1 = max(0, int(v0) - half), min(h, int(v0) + half + 1)
        roi = d[b0:b1, a0:a1]
        if roi.size == 0:
            return None
        _, mask = cv2.threshold(roi, self.threshold, 1, cv2.THRESH_BINARY)
        n, lab, stats, cent = cv2.connectedComponentsWithStats(mask, connectivity=8)
        if n < 2:
            return None
        # the component nearest the peak, among the large ones
        du = cent[1:, 0] + a0 - u0
        dv = cent[1:, 1] + b0 - v0
        score = stats[1:, cv2.CC_STAT_AREA] / (1.0 + (du * du + dv * dv) / (self.r * self.r))
        j = 1 + int(np.argmax(score))
        comp = (lab == j).astype(np.uint8)
        # fill holes (a highlight inside the disc): the background reachable from the border
        inv = 1 - comp
        ff = np.zeros((comp.shape[0] + 2, comp.shape[1] + 2), np.uint8)
        filled = comp.copy()
        outside = inv.copy()
        for y, x in ((0, 0), (0, comp.shape[1] - 1), (comp.shape[0] - 1, 0), (comp.shape[0] - 1, comp.shape[1] - 1)):
            if outside[y, x] == 1:
                cv2.floodFill(outside, ff, (x, y), 2)
        filled[outside == 1] = 1              # holes: not reached from the border
        area = float(filled.sum())
        ra = math.pi * self.r * self.r
        if not AREA_RANGE[0] * ra <= area <= AREA_RANGE[1] * ra:
            return None
        if filled[0, :].any() or filled[-1, :].any() or filled[:, 0].any() or filled[:, -1].any():
            if blur_extra == 0 and (a0 > 0 and b0 > 0 and a1 < w and b1 < h):
                ys, xs = np.nonzero(filled)      # a long blur: look again with a larger window
                return self._refine(d, grey, bg, xs.mean() + a0, ys.mean() + b0, blur_extra=self.half)
            return None
        # from here on, the disc's bounding box and a margin of 4 px (the rim band's reach)
        ys_, xs_ = np.nonzero(filled)
        y0c, y1c = max(0, int(ys_.min()) - 4), min(filled.shape[0], int(ys_.max()) + 5)
        x0c, x1c = max(0, int(xs_.min()) - 4), min(filled.shape[1], int(xs_.max()) + 5)
        filled, comp = filled[y0c:y1c, x0c:x1c].copy(), comp[y0c:y1c, x0c:x1c]
        roi = roi[y0c:y1c, x0c:x1c].astype(np.float32)
        a0, b0 = a0 + x0c, b0 + y0c
        a1, b1 = a0 + (x1c - x0c), b0 + (y1c - y0c)
        core = cv2.erode(filled, np.ones((3, 3), np.uint8))
        c = float(np.median(roi[core == 1])) if core.any() else float(np.median(roi[filled == 1]))
        if c < self.threshold:
            return None
        band = cv2.dilate(filled, np.ones((5, 5), np.uint8))
        inner = cv2.erode(filled, np.ones((5, 5), np.uint8))
        # each rim pixel's share of the ball: g = a b + (1 - a) bg, with b the ball's own grey
        # nearby (the inner disc's grey spread outward: the ball is shaded too)
        g = grey[b0:b1, a0:a1].astype(np.float32)
        gb = bg[b0:b1, a0:a1].astype(np.float32)
        src = inner if inner.sum() >= 6 else core
        k = max(3, int(round(0.6 * self.r)) | 1)
        num = cv2.blur(g * src, (k, k))
        den = cv2.blur(src.astype(np.float32), (k, k))
        for _ in range(3):                       # spread the ball's grey outward to the rim
            grow = den > 1e-6
            bmap = np.where(grow, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)
            if grow[band == 1].all():
                break
            num = cv2.blur(bmap * grow, (k, k))
            den = cv2.blur(grow.astype(np.float32), (k, k))
        contrast = bmap - gb
        sure = np.abs(contrast) > 4.0 * self.noise
        with np.errstate(all="ignore"):
            alpha = np.clip((g - gb) / np.where(sure, contrast, 1.0), 0.0, 1.0)
        wgt = np.where(sure, alpha, np.clip(roi / c, 0.0, 1.0)).astype(np.float32)
        wgt[inner == 1] = 1.0                     # inside: all ball (a highlight too)
        wgt[(filled == 1) & (comp == 0)] = 1.0
        wgt[band == 0] = 0.0
        wgt[(filled == 0) & (roi <= 2.0 * self.noise)] = 0.0
        s = float(wgt.sum())
        xs = np.arange(a0, a1, dtype=np.float64)[None, :]
        ys = np.arange(b0, b1, dtype=np.float64)[:, None]
        u = float((wgt * xs).sum() / s)
        v = float((wgt * ys).sum() / s)
        edge = ((band == 1) & (core == 0)).astype(np.float64)
        sw = self.noise / c
        su = math.sqrt(float((edge * (xs - u) ** 2).sum())) * sw / s
        sv = math.sqrt(float((edge * (ys - v) ** 2).sum())) * sw / s
        return Ball(u, v, max(su, SIGMA_FLOOR_PX), max(sv, SIGMA_FLOOR_PX), area, c)


_MED9 = ((1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 3), (5, 8), (4, 7),
         (3, 6), (1, 4), (2, 5), (4, 7), (4, 2), (6, 4), (4, 2))     # Paeth's median-of-9 network


def _median9(frames) -> np.ndarray:
    """The per-pixel median of 9 uint8 images by a sorting network (19 min/max pairs)."""
    import cv2

    p = list(frames)
    for i, j in _MED9:
        lo, hi = cv2.min(p[i], p[j]), cv2.max(p[i], p[j])
        p[i], p[j] = lo, hi
    return p[4]


def background(frames: np.ndarray) -> tuple[np.ndarray, float]:
    """The background (h, w) uint8 and its noise (grey levels, 1 sigma).

    A first estimate is the per-pixel median of 9 frames spread over the sample (the ball
    moves: it covers a pixel in few of them); the noise is 1.4826 x the median absolute
    deviation about it (every 16th pixel); the background is then the mean, per pixel, of
    the sample's frames within max(6, 4 sigma) grey levels of that median (the ball
    excluded), which averages the noise down with every frame."""
    import cv2

    k = len(frames)
    if k >= 9:
        pick = np.unique(np.linspace(0, k - 1, 9).round().astype(int))
        med = _median9([np.ascontiguousarray(frames[i]) for i in pick]) if pick.size == 9 else \
            np.median(frames, axis=0).astype(np.uint8)
    else:
        med = np.median(frames, axis=0).astype(np.uint8)
    sub = frames[:, ::4, ::4].astype(np.int16)
    noise = max(1.4826 * float(np.median(np.abs(sub - med[::4, ::4].astype(np.int16)))), 0.5)
    tol = max(6.0, 4.0 * noise)
    acc = np.zeros(med.shape, np.float32)
    cnt = np.zeros(med.shape, np.float32)
    for f in frames:
        near = (cv2.absdiff(f, med) <= tol).astype(np.float32)
        acc += near * f
        cnt += near
    bg = np.where(cnt > 0, acc / np.maximum(cnt, 1.0), med)
    return np.clip(np.round(bg), 0, 255).astype(np.uint8), noise


@dataclass
class VideoTrack:
    """One video tracked: per frame t (s), the centre in px (nan: a gap), the ball's
    centre x, y in design units and their standard deviations (nan: a gap)."""

    path: str
    t: np.ndarray
    uv: np.ndarray
    xy: np.ndarray
    sigma: np.ndarray
    calibration: cam_mod.Calibration
    radius_px: float
    units: str
    notes: list = field(default_factory=list)
    sigma_image: np.ndarray | None = field(default=None, repr=False)        # (n, 2) the image noise's share
    sigma_calibration: np.ndarray | None = field(default=None, repr=False)  # (n, 2) the camera's share
    snapshot: np.ndarray | None = field(default=None, repr=False)    # a grey frame with the ball, for figures
    corners_px: dict = field(default_factory=dict, repr=False)      # id -> (4, 2) px as found

    @property
    def frames(self) -> int:
        return int(len(self.t))

    @property
    def tracked(self) -> np.ndarray:
        return np.all(np.isfinite(self.xy), axis=1)

    @property
    def fraction(self) -> float:
        return float(self.tracked.mean()) if len(self.t) else 0.0

    @property
    def ok(self) -> bool:
        return bool(self.tracked.any())

    def to_json(self) -> dict:
        k = self.tracked
        sig = np.hypot(self.sigma[k, 0], self.sigma[k, 1]) if k.any() else np.array([np.nan])
        dt = np.diff(self.t)
        return {"file": self.path, "frames": self.frames, "tracked": int(k.sum()), "fraction_tracked": self.fraction,
                "duration_s": float(self.t[-1] - self.t[0]) if len(self.t) > 1 else 0.0,
                "frame_rate": float(1.0 / np.median(dt)) if dt.size else None,
                "variable_frame_rate": bool(dt.size and (dt.max() - dt.min()) > 1e-3 * np.median(dt)),
                "reprojection_rms_px": self.calibration.rms_px, "reprojection_max_px": self.calibration.max_px,
                "reprojection_rms_mm": self.calibration.rms_mm,
                "position_sigma_median": float(np.median(sig)), "position_sigma_max": float(np.max(sig)),
                "position_sigma_image_median": _med_norm(self.sigma_image, k),
                "position_sigma_calibration_median": _med_norm(self.sigma_calibration, k),
                "position_units": self.units, "ball_radius_px": self.radius_px,
                "camera": self.calibration.to_json(), "notes": self.notes + self.calibration.notes}

    def csv_text(self) -> str:
        """The track as ``t,x,y,sigma_x,sigma_y`` (s and design units); a gap keeps its time
        with the other cells blank, which fabkit's track reader skips."""
        out = ["t,x,y,sigma_x,sigma_y"]
        for t, (x, y), (sx, sy) in zip(self.t, self.xy, self.sigma):
            if math.isfinite(x) and math.isfinite(y):
                out.append(f"{t:.7f},{x:.6f},{y:.6f},{sx:.3g},{sy:.3g}")
            else:
                out.append(f"{t:.7f},,,,")
        return "\n".join(out) + "\n"


def _med_norm(a, keep) -> float | None:
    """The median over the kept rows of |a| (rows of 2), or None."""
    if a is None or not keep.any():
        return None
    return float(np.median(np.hypot(a[keep, 0], a[keep, 1])))


def marker_mask(camera: cam_mod.Camera, layout: cam_mod.MarkerLayout, shape) -> np.ndarray:
    """(h, w) bool: the image of each marker's paper (the square and its quiet zone, plus
    a module more)."""
    import cv2

    m = np.zeros(shape, np.uint8)
    pad = layout.size / 2 + 2 * layout.module
    for c in layout.centres:
        sq = np.array([[c[0] - pad, c[1] - pad, 0], [c[0] + pad, c[1] - pad, 0], [c[0] + pad, c[1] + pad, 0],
                       [c[0] - pad, c[1] + pad, 0]])
        cv2.fillConvexPoly(m, np.round(camera.project(sq)).astype(np.int32), 1)
    return m.astype(bool)


def _contact_points(surface, radius, C) -> np.ndarray:
    """(n, 2): a start near each centre's contact point, (x, y) = C_xy + r grad h / w at C_xy."""
    _, hx, hy = (np.broadcast_to(np.asarray(a, dtype=float), (len(C),)) for a in
                 surface.derivatives(C[:, 0], C[:, 1])[:3])
    w = np.sqrt(1.0 + hx * hx + hy * hy)
    return np.c_[C[:, 0] + radius * hx / w, C[:, 1] + radius * hy / w]


def track_video(spec, surface, path, progress=None) -> VideoTrack:
    """Track the ball in one video (see the module doc). ``progress(done)`` is called
    every few frames. SpecError (exit 2) naming the file: not a video, markers not
    found, or the ball never found."""
    info = video.info(path)
    try:
        return _track(spec, surface, path, info, progress)
    except SpecError as exc:
        if exc.file is None or exc.file == str(path):
            raise exc.with_location(file=str(path)) from None
        raise


def _track(spec, surface, path, info, progress) -> VideoTrack:
    smp = sample(path)
    if len(smp.frames) < 2:
        raise SpecError("a single frame (a still image), not a video", file=str(path))
    bg, noise = background(smp.frames)
    corners = find_markers(smp.frames, str(path), image=bg)
    layout = cam_mod.marker_layout(spec, surface)
    matched = cam_mod.match_corners(corners, layout)
    height = spec.lab.camera_height if spec.has("lab") else None
    calib = cam_mod.calibrate(matched, layout, (smp.width, smp.height), height)
    cam = calib.camera
    radius = float(spec.ball.diameter) / 2.0                      # design units
    r_mm = radius * surface.scale
    # the ball's radius in px where it is seen: about the footprint's middle, half the depth down
    mid = np.array([[surface.length * surface.scale / 2, surface.width * surface.scale / 2, r_mm]])
    dist = float(np.linalg.norm(mid[0] - cam.centre))
    radius_px = cam.f * r_mm / dist
    finder = BallFinder(bg, radius_px, noise, exclude=marker_mask(cam, layout, bg.shape))
    ts, uvs, sig = [], [], []
    snapshot, want = None, max(0, info.frames // 2)
    for i, (t, g) in enumerate(video.frames_ahead(path)):
        b = finder.find(g)
        ts.append(t)
        if b is not None and (snapshot is None or (i >= want and snapshot[0] < want)):
            snapshot = (i, g)
        if b is None:
            uvs.append((math.nan, math.nan))
            sig.append((math.nan, math.nan))
        else:
            uvs.append((b.u, b.v))
            sig.append((b.su, b.sv))
        if progress is not None and i % 16 == 0:
            progress(i)
    if not ts:
        raise SpecError("no frames could be decoded", file=str(path))
    t = np.asarray(ts)
    uv = np.asarray(uvs, dtype=float)
    su = np.asarray(sig, dtype=float)
    ok = np.all(np.isfinite(uv), axis=1)
    if not ok.any():
        raise SpecError(f"the ball was not found in any of {len(t)} frames (a disc of about {radius_px:.0f} px "
                        "radius, darker or lighter than the surface)", file=str(path))
    xy = np.full((len(t), 2), np.nan)
    sxy = np.full((len(t), 2), np.nan)
    idx = np.flatnonzero(ok)
    # the centre, and its standard deviation in design units through the Jacobian px -> centre
    C, Ju, Jv = cam_mod.ball_centres(cam, surface, radius, uv[idx], jacobian=True)
    xy[idx] = C[:, :2]
    s_img = np.sqrt((Ju * su[idx, 0:1]) ** 2 + (Jv * su[idx, 1:2]) ** 2)
    cov = cam_mod.calibration_covariance(calib, surface, radius, uv[idx], C,
                                         _contact_points(surface, radius, C))
    s_cal = np.sqrt(np.maximum(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1), 0.0))
    sxy[idx] = np.hypot(s_img, s_cal)
    sig_img = np.full((len(t), 2), np.nan)
    sig_cal = np.full((len(t), 2), np.nan)
    sig_img[idx], sig_cal[idx] = s_img, s_cal
    lost = ~np.all(np.isfinite(xy), axis=1)
    uv[lost] = np.nan
    notes = list(layout.notes)
    if info.width != smp.width or info.height != smp.height:  # pragma: no cover (a container's odd header)
        notes.append(f"the container says {info.width}x{info.height}, the frames are {smp.width}x{smp.height}")
    return VideoTrack(path=str(path), t=t, uv=uv, xy=xy, sigma=sxy, calibration=calib, radius_px=radius_px,
                      units=spec.units, notes=notes, sigma_image=sig_img, sigma_calibration=sig_cal,
                      snapshot=snapshot[1], corners_px=corners)
