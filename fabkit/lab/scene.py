"""The still scene of a video: a sample of its frames, the ArUco markers in it, the background.

The stage between the decoded video (:mod:`fabkit.lab.video`) and the camera's calibration
(:func:`fabkit.lab.camera.calibrate`) and the ball finder (:mod:`fabkit.lab.ballfinder`).
The camera stands still and the ball moves, so what does not move is read from a sample:

1. :func:`sample` - in: a video's path; out: a :class:`Sample` of up to SAMPLE_FRAMES grey
   frames (k, h, w) uint8 spread over the video (its key frames when there are at least
   MIN_KEYFRAMES, else every k-th frame of a full decode);
2. :func:`background` - in: the sample's frames; out: the background (h, w) uint8 (the
   frames' mean where they agree with their median: the ball excluded) and its noise
   (grey levels, 1 sigma);
3. :func:`find_markers` - in: the sample's frames and the background; out: markers 0-3's
   corners, id -> (4, 2) px, found by OpenCV's ArUco detector (the median over the frames)
   and each refined by :func:`refine_square` (the square's four sides fitted as lines);
4. :func:`marker_mask` - in: the calibrated camera and the markers' layout; out: (h, w)
   bool, the markers' paper, which the ball finder never searches.

A video none of whose frames decode, or one without all four markers, is a SpecError
naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import SpecError
from . import camera as cam_mod
from . import video

SAMPLE_FRAMES = 24          # frames of the sample (background, markers)
MIN_KEYFRAMES = 9           # fewer key frames than this: sample a full decode instead


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
