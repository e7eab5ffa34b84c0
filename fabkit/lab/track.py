"""From a video of the block to the ball's calibrated trajectory: the track.

The stage after the video's decoding (:mod:`fabkit.lab.video`) and before the analysis
(:mod:`fabkit.lab.analyze`). In: the spec, its surface and a video's path; out: a
:class:`VideoTrack` (per frame the time, the ball's centre x, y in design units and their
standard deviations, or a gap with its reason), written as CSV (:meth:`VideoTrack.csv_text`)
and summarised as JSON (:meth:`VideoTrack.to_json`), and on request a review sheet of crops
(:func:`review_sheet`). :func:`track_video` runs the stages, each a function or a small
class a test can call:

1. :func:`fabkit.lab.scene.sample` - a sample of grey frames spread over the video (its
   key frames when there are enough, else every k-th frame of a full decode);
2. :func:`fabkit.lab.scene.background` - the background (the sample's median: the ball
   moves) and its noise; :func:`fabkit.lab.scene.find_markers` - ArUco markers 0-3 in the
   sample, each corner the median over the frames it was found in (the camera stands
   still), refined on the background;
3. the camera: :func:`fabkit.lab.camera.calibrate`;
4. :class:`fabkit.lab.ballfinder.BallFinder` - per frame, the ball's SILHOUETTE fitted on
   rays across its expected edge (never the changed pixels: a lamp's cast shadow changes
   pixels too), its shadow rejected, the centre's sigma; a frame where no silhouette is
   accepted is a gap with its reason (GAP_REASONS): not found, partly hidden, merges with
   the surface, in its shadow, fits badly (and runs of fewer than MIN_RUN tracked frames
   between doubtful gaps are gaps too);
5. :func:`fabkit.lab.camera.ball_centres` - each centre's ray met with the
   ball-centre offset surface, its sigma through the Jacobian and the calibration's
   covariance;
6. :class:`VideoTrack` - the result: times from the presentation timestamps, the
   centre's x, y in design units and their standard deviations, with its verdict.

The names of the scene and the ball finder are importable from here as well.
"""

from __future__ import annotations

import math
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError
from . import camera as cam_mod
from . import video
from .ballfinder import (AREA_RANGE, CHECK_ARC_GAP, CHECK_RAYS, DOWN, GAP_REASONS, HIDDEN_DIFF,
                         HIDDEN_RAYS, HYPOTHESES, MAX_ARC_GAP, MAX_LOW_SHARE, MAX_RAMP, MAX_RESIDUAL_PX,
                         MAX_SHIFT_PX, MAX_SOFT_SHARE, MIN_BALL_CONTRAST, MIN_CONTRAST, MIN_FACING, MIN_INLIERS,
                         MIN_RAYS, PREDICT_TOL, SCALE_RANGE, SCALE_SIGMA, SHADOW_EVEN, SHADOW_RATIO,
                         SHADOW_RATIO_MIN, SHAPE_STEP, SIGMA_FLOOR_PX, SIGMA_GAIN, SIGMA_PARTIAL_PX, SIGMA_RESIDUAL,
                         Ball, BallFinder, Miss, Shape, fit_silhouette)
from .scene import (MIN_KEYFRAMES, SAMPLE_FRAMES, Sample, background, find_markers, marker_mask,
                    refine_square, sample)

#: the track's own names, and those of the scene and the ball finder it runs (importable from here)
__all__ = [
    # the track
    "DOUBTFUL_SHARE", "REVIEW_CROPS", "MIN_RUN", "REVIEW_TILE", "REVIEW_COLUMNS",
    "VideoTrack", "ReviewCrop", "track_video", "review_sheet", "review_png",
    # the scene (fabkit.lab.scene)
    "SAMPLE_FRAMES", "MIN_KEYFRAMES", "Sample", "sample", "refine_square", "find_markers", "background",
    "marker_mask",
    # the ball finder (fabkit.lab.ballfinder)
    "DOWN", "MIN_CONTRAST", "AREA_RANGE", "SIGMA_FLOOR_PX", "SIGMA_GAIN", "SIGMA_PARTIAL_PX", "SIGMA_RESIDUAL",
    "SCALE_SIGMA", "SCALE_RANGE", "SHADOW_RATIO", "HIDDEN_RAYS", "HIDDEN_DIFF", "MAX_RAMP", "MAX_SOFT_SHARE",
    "MIN_BALL_CONTRAST", "MIN_RAYS", "MAX_ARC_GAP", "CHECK_RAYS", "CHECK_ARC_GAP", "MAX_SHIFT_PX", "MIN_INLIERS",
    "MAX_RESIDUAL_PX", "SHADOW_EVEN", "SHADOW_RATIO_MIN", "MAX_LOW_SHARE", "MIN_FACING", "PREDICT_TOL",
    "SHAPE_STEP", "HYPOTHESES", "GAP_REASONS", "Ball", "Miss", "Shape", "fit_silhouette", "BallFinder",
]

DOUBTFUL_SHARE = 0.05      # more than this share of the frames doubtful (seen, not reported): a warning
REVIEW_CROPS = 24           # crops kept for a review sheet
MIN_RUN = 3                 # fewer tracked frames in a row than this, beside doubtful gaps: gaps too


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
    gap_reason: list = field(default_factory=list, repr=False)      # per frame: "" (tracked) or why not
    review: list = field(default_factory=list, repr=False)          # ReviewCrop's for a contact sheet

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

    def gaps(self) -> dict:
        """reason -> the number of frames left out for it (reasons in GAP_REASONS order)."""
        out = {r: 0 for r in GAP_REASONS}
        for r in self.gap_reason:
            if r:
                out[r] = out.get(r, 0) + 1
        if not self.gap_reason:
            out["not found"] = int((~self.tracked).sum())
        return out

    @property
    def doubtful(self) -> int:
        """Frames where a ball was seen but not reported (every gap but "not found")."""
        g = self.gaps()
        return int(sum(v for k, v in g.items() if k != "not found"))

    def to_json(self) -> dict:
        k = self.tracked
        sig = np.hypot(self.sigma[k, 0], self.sigma[k, 1]) if k.any() else np.array([np.nan])
        dt = np.diff(self.t)
        gaps = self.gaps()
        n = max(1, self.frames)
        return {"gaps": gaps, "left_out": int((~k).sum()), "doubtful": self.doubtful,
                "doubtful_fraction": self.doubtful / n, "doubtful_warning": self.doubtful / n > DOUBTFUL_SHARE,
                "doubtful_share_limit": DOUBTFUL_SHARE, "timestamps": "monotone",
                "camera_height_constrained": self.calibration.height_prior is not None
                or _height_constrained(self.calibration),
                **self._json_base(k, sig, dt)}

    def _json_base(self, k, sig, dt) -> dict:
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


def _height_constrained(cal) -> bool:
    """The markers alone fix the camera's height (to 5 %)."""
    h = float(cal.camera.centre[2])
    return bool(np.isfinite(cal.height_sigma_mm) and cal.height_sigma_mm < 0.05 * abs(h))


def _med_norm(a, keep) -> float | None:
    """The median over the kept rows of |a| (rows of 2), or None."""
    if a is None or not keep.any():
        return None
    return float(np.median(np.hypot(a[keep, 0], a[keep, 1])))


def _contact_points(surface, radius, C) -> np.ndarray:
    """(n, 2): a start near each centre's contact point, (x, y) = C_xy + r grad h / w at C_xy."""
    _, hx, hy = (np.broadcast_to(np.asarray(a, dtype=float), (len(C),)) for a in
                 surface.derivatives(C[:, 0], C[:, 1])[:3])
    w = np.sqrt(1.0 + hx * hx + hy * hy)
    return np.c_[C[:, 0] + radius * hx / w, C[:, 1] + radius * hy / w]


def track_video(spec, surface, path, progress=None, review: bool = False) -> VideoTrack:
    """Track the ball in one video (see the module doc). ``progress(done)`` is called
    every few frames. SpecError (exit 2) naming the file: not a video, markers not
    found, or the ball never found."""
    info = video.info(path)
    try:
        return _track(spec, surface, path, info, progress, review)
    except SpecError as exc:
        if exc.file is None or exc.file == str(path):
            raise exc.with_location(file=str(path)) from None
        raise


def _drop_short_runs(uvs, sig, why) -> None:
    """Runs of fewer than MIN_RUN tracked frames between doubtful gaps (a ball seen but
    not separated on both sides) become gaps themselves ("fits badly"): a ball that is
    separable in one frame and not in its neighbours is more likely a chance fit."""
    n = len(why)
    i = 0
    while i < n:
        if why[i]:
            i += 1
            continue
        j = i
        while j < n and not why[j]:
            j += 1
        before = why[i - 1] if i > 0 else "not found"
        after = why[j] if j < n else "not found"
        doubtful = (before not in ("", "not found")) or (after not in ("", "not found"))
        if j - i < MIN_RUN and doubtful and (i > 0 or j < n):
            for k in range(i, j):
                uvs[k] = (math.nan, math.nan)
                sig[k] = (math.nan, math.nan)
                why[k] = "fits badly"
        i = j


def _review_crop(i, t, g, bg, at, half, ball, miss) -> "ReviewCrop":
    u, v = at
    h, w = g.shape
    x0, y0 = max(0, int(round(u)) - half), max(0, int(round(v)) - half)
    x1, y1 = min(w, int(round(u)) + half + 1), min(h, int(round(v)) + half + 1)
    fit = ball.fit if ball is not None else (miss.fit if miss is not None else None)
    return ReviewCrop(index=i, t=float(t), origin=(x0, y0), image=g[y0:y1, x0:x1].copy(),
                      background=bg[y0:y1, x0:x1].copy(), fit=fit,
                      reason="" if ball is not None else (miss.reason if miss is not None else "not found"),
                      centre=(ball.u, ball.v) if ball is not None else None)


@dataclass
class ReviewCrop:
    """A frame's crop around the ball for a review sheet: the frame's index and time, the
    crop's top-left (px), the grey crop and the background's, the silhouette fit (points,
    the rays' verdicts, the ellipse) and the gap's reason ("" when tracked)."""

    index: int
    t: float
    origin: tuple
    image: np.ndarray
    background: np.ndarray
    fit: dict | None
    reason: str
    centre: tuple | None


def _track(spec, surface, path, info, progress, review=False) -> VideoTrack:
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
    shape = Shape(cam, surface, radius, (smp.width, smp.height))
    radius_px = shape.median_radius
    finder = BallFinder(bg, shape, noise, exclude=marker_mask(cam, layout, bg.shape))
    ts, uvs, sig, why = [], [], [], []
    snapshot, want = None, max(0, info.frames // 2)
    n_est = max(info.frames, 1)
    targets = set(np.linspace(0, n_est - 1, REVIEW_CROPS).round().astype(int).tolist()) if review else set()
    kept_misses: dict = {}
    crops = []
    half = int(math.ceil(3.0 * radius_px)) + 4
    last_seen = None
    for i, (t, g) in enumerate(video.frames_ahead(path)):
        b = finder.find(g)
        ts.append(t)
        if b is not None and (snapshot is None or (i >= want and snapshot[0] < want)):
            snapshot = (i, g)
        if b is None:
            uvs.append((math.nan, math.nan))
            sig.append((math.nan, math.nan))
            why.append(finder.miss.reason if finder.miss is not None else "not found")
        else:
            uvs.append((b.u, b.v))
            sig.append((b.su, b.sv))
            why.append("")
        if review:
            m = finder.miss
            at = (b.u, b.v) if b is not None else ((m.u, m.v) if m is not None and math.isfinite(m.u) else last_seen)
            keep = i in targets
            if b is None and m is not None and m.reason != "not found" and kept_misses.get(m.reason, 0) < 3:
                kept_misses[m.reason] = kept_misses.get(m.reason, 0) + 1
                keep = True
            if keep and at is not None:
                crops.append(_review_crop(i, t, g, bg, at, half, b, m))
            if b is not None:
                last_seen = (b.u, b.v)
        if progress is not None and i % 16 == 0:
            progress(i)
    if not ts:
        raise SpecError("no frames could be decoded", file=str(path))
    _drop_short_runs(uvs, sig, why)
    for c in crops:                 # the sheet says what the track says
        if why[c.index] and not c.reason:
            c.reason = why[c.index]
    t = np.asarray(ts)
    uv = np.asarray(uvs, dtype=float)
    su = np.asarray(sig, dtype=float)
    ok = np.all(np.isfinite(uv), axis=1)
    if not ok.any() and not any(w and w != "not found" for w in why):
        raise SpecError(f"the ball was not found in any of {len(t)} frames (a disc of about {radius_px:.0f} px "
                        "radius, darker or lighter than the surface)", file=str(path))
    xy = np.full((len(t), 2), np.nan)
    sxy = np.full((len(t), 2), np.nan)
    idx = np.flatnonzero(ok)
    if idx.size == 0:       # seen in places, never separated: every frame a gap, said so
        notes = list(layout.notes) + ["the ball was seen but never separated from the surface, its shadow or what "
                                      "covered it: no position is reported (see the gaps' reasons, --review)"]
        return VideoTrack(path=str(path), t=t, uv=uv, xy=xy, sigma=sxy, calibration=calib, radius_px=radius_px,
                          units=spec.units, notes=notes, sigma_image=xy.copy(), sigma_calibration=xy.copy(),
                          snapshot=(snapshot or (0, g))[1], corners_px=corners,
                          gap_reason=[w or "not found" for w in why], review=crops)
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
                      snapshot=snapshot[1], corners_px=corners,
                      gap_reason=[(w or "not found") if not k else "" for w, k in zip(why, np.all(np.isfinite(xy), axis=1))],
                      review=crops)


# ----------------------------------------------------------------------------
# the review sheet
# ----------------------------------------------------------------------------
REVIEW_TILE = 200           # px, a crop's side on the sheet
REVIEW_COLUMNS = 6


def review_sheet(result: VideoTrack) -> np.ndarray:
    """A contact sheet (h, w, 3) uint8 BGR of ``result.review``'s crops (see
    :func:`track_video` with ``review=True``): each crop enlarged, the pixels darker than
    the background outside the ball (its shadow, rejected) tinted blue, the fitted
    silhouette drawn green with its centre, the edge's points coloured by their use
    (green: fitted; blue: next to the shadow; red: covered; yellow: no contrast), and a
    gap framed red with its reason."""
    import cv2

    crops = sorted(result.review, key=lambda c: c.index)
    n = max(1, len(crops))
    cols = min(REVIEW_COLUMNS, n)
    rows = (n + cols - 1) // cols
    T = REVIEW_TILE
    head = 34
    sheet = np.full((head + rows * (T + 22), cols * T, 3), 255, np.uint8)
    j = result.to_json()
    gaps = ", ".join(f"{k} {v}" for k, v in j["gaps"].items() if v)
    title = f"{Path(result.path).name}: {j['tracked']}/{j['frames']} frames tracked" + (f"; gaps: {gaps}" if gaps else "")
    cv2.putText(sheet, title[:150], (6, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for k, c in enumerate(crops):
        r_, c_ = divmod(k, cols)
        y0, x0 = head + r_ * (T + 22), c_ * T
        img = c.image.astype(np.float32)
        bgc = c.background.astype(np.float32)
        h, w = img.shape
        s = T / max(h, w)
        big = cv2.resize(c.image, (int(round(w * s)), int(round(h * s))), interpolation=cv2.INTER_NEAREST)
        tile = cv2.cvtColor(big, cv2.COLOR_GRAY2BGR)
        ox, oy = c.origin
        fit = c.fit
        # the shadow: darker than the background by a ratio, outside the fitted silhouette
        dark = img < bgc * (1.0 - SHADOW_RATIO) - 3.0
        if fit is not None:         # not the ball itself (where it was fitted, or first looked for)
            yy, xx = np.mgrid[0:h, 0:w]
            cen, sc = (fit["centre"], fit["scale"]) if "centre" in fit else (fit["centre0"], 1.0)
            cu, cv_ = cen[0] - ox, cen[1] - oy
            a, b, phi = fit["a"] * sc, fit["b"] * sc, fit["phi"]
            ca, sa = math.cos(phi), math.sin(phi)
            xr, yr = (xx - cu) * ca + (yy - cv_) * sa, -(xx - cu) * sa + (yy - cv_) * ca
            dark &= (xr / (a + 1.0)) ** 2 + (yr / (b + 1.0)) ** 2 > 1.0
        m = cv2.resize(dark.astype(np.uint8), (tile.shape[1], tile.shape[0]), interpolation=cv2.INTER_NEAREST) > 0
        tile[m] = (0.55 * tile[m] + 0.45 * np.array([255, 120, 0])).astype(np.uint8)
        if fit is not None:
            pts = fit["points"]
            colours = ((fit["hidden"], (0, 0, 230)), (fit["low"], (0, 200, 230)), (fit["shadow"], (255, 80, 0)),
                       (fit.get("used", fit["clean"]), (0, 170, 0)))
            for mask, col in colours:
                for (pu, pv) in pts[np.asarray(mask, bool)]:
                    cv2.circle(tile, (int(round((pu - ox + 0.5) * s)), int(round((pv - oy + 0.5) * s))), 2, col, -1,
                               cv2.LINE_AA)
            if "centre" in fit:
                col = (0, 200, 0) if not c.reason else (0, 0, 230)
                cen = (int(round((fit["centre"][0] - ox + 0.5) * s * 16)), int(round((fit["centre"][1] - oy + 0.5) * s * 16)))
                axes = (int(round(fit["a"] * fit["scale"] * s * 16)), int(round(fit["b"] * fit["scale"] * s * 16)))
                cv2.ellipse(tile, cen, axes, math.degrees(fit["phi"]), 0, 360, col, 1, cv2.LINE_AA, shift=4)
                cv2.drawMarker(tile, (cen[0] >> 4, cen[1] >> 4), col, cv2.MARKER_CROSS, 9, 1)
        sheet[y0 + 20:y0 + 20 + tile.shape[0], x0:x0 + tile.shape[1]] = tile
        label = f"#{c.index} t {c.t:.3f} s" + (f"  GAP: {c.reason}" if c.reason else "")
        cv2.putText(sheet, label, (x0 + 3, y0 + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                    (0, 0, 200) if c.reason else (0, 0, 0), 1, cv2.LINE_AA)
        if c.reason:
            cv2.rectangle(sheet, (x0 + 1, y0 + 20), (x0 + tile.shape[1] - 2, y0 + 19 + tile.shape[0]), (0, 0, 230), 2)
    return sheet


def review_png(result: VideoTrack) -> bytes:
    """:func:`review_sheet` encoded as PNG."""
    import cv2

    ok, buf = cv2.imencode(".png", review_sheet(result))
    if not ok:  # pragma: no cover
        raise SpecError("the review sheet could not be encoded as PNG")
    return buf.tobytes()
