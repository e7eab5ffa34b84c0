"""The ball finder: the ball's centre in each frame from its silhouette, or the reason it is a gap.

The stage between the still scene (:mod:`fabkit.lab.scene`: the background and its noise)
and the track (:mod:`fabkit.lab.track`, which meets each centre's ray with the ball-centre
offset surface). In: the background (h, w) uint8, its noise, the ball's image everywhere
(:class:`Shape`, from the calibrated camera, the offset surface and the diameter), and the
grey frames in order; out, per frame: a :class:`Ball` (the centre (u, v) px, the projection
of the sphere's centre, with its standard deviations) or None with a :class:`Miss` (one of
GAP_REASONS). :class:`BallFinder` reads the ball's SILHOUETTE, never the changed pixels (a
lamp's cast shadow changes pixels too):

* :class:`Shape` - the ball's image anywhere in the frame from the calibrated camera,
  the offset surface and the diameter: the cone tangent to the sphere projected (with
  the distortion), an ellipse (semi-axes, angle) and its centre's offset from the
  projected sphere centre, on a grid, interpolated;
* the coarse peak of |frame - background| at the ball's scale on a 4x smaller image
  (near the track's prediction first), then a Hough vote of the edges of
  frame - background for circles of the expected radius there: the strongest
  (HYPOTHESES) are the ball, its shadow, a hand...;
* for each, rays across the expected edge: the edge on a ray is where the profile's
  share of the ball (the area between the inside's grey and the outside's, the
  outside taken as the background times the ray's own ratio, so a shadow's darkening
  and the surface's shading do not move it) puts it, blur-symmetric; a ray is
  "covered" when inside and outside both differ from the ball and the background,
  "low" when it has no contrast, "shadow" when the outside is darker than the
  background;
* the expected ellipse fitted to the rays' edge points (:func:`fit_silhouette`:
  Gauss-Newton, Huber weights, the size with a 3 % prior), its inliers, residual and
  size checked;
* among the hypotheses: a silhouette darker than the surface all over, no darker than
  a shadow can be, with something lighter beside it (a light ball, a highlight), is
  that ball's shadow; a shadow's inside keeps an even ratio to the background; of two
  overlapping silhouettes the ball is in front, so its edge toward the other is whole;
  one far from the track's prediction is doubtful;
* the centre's sigma: the fit's covariance scaled by its residual, plus a floor, a
  share of the residual and a term for the share of the edge left out (calibrated
  against rendered truth: benchmarks/lab_accuracy.py track).

A frame where no silhouette is accepted is a gap with its reason (GAP_REASONS): not
found, partly hidden, merges with the surface, in its shadow, fits badly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError
from . import camera as cam_mod

DOWN = 4                    # the coarse search's reduction
MIN_CONTRAST = 12.0         # grey levels: a ball that differs less from the surface is not found
AREA_RANGE = (0.35, 4.0)    # the disc's area against pi r^2 (blur lengthens it)
SIGMA_FLOOR_PX = 0.03       # the centre's standard deviation is at least this (the model's own limit)
SIGMA_GAIN = 1.0            # the fit's covariance scaled by this (calibrated against rendered truth)
SIGMA_PARTIAL_PX = 1.0      # added (times the share of rays left out) when a side of the edge is not used
SIGMA_RESIDUAL = 0.3        # the share of the edge's rms residual added to the centre's sigma
SCALE_SIGMA = 0.03          # the prior on the silhouette's size against the camera's prediction
SCALE_RANGE = (0.93, 1.035)  # the fitted size against the prediction outside this: the fit is bad (a dark
                            # ball's fits: within 2 %; a light ball's limb, darker than its middle, reads
                            # 2-4 % small; a shadow beside the edge reads large)
SHADOW_RATIO = 0.04         # outside the edge, darker than the background by this share: a shadow
HIDDEN_RAYS = 0.08          # more than this share of the edge's rays covered: the ball is partly hidden
HIDDEN_DIFF = 0.15          # ... its inside unlike the ball's by this share of the background's grey at least
MAX_RAMP = 0.08             # the outside's change past the edge against the edge's contrast: more, no edge
MAX_SOFT_SHARE = 0.3        # more of the edge than this beside such a ramp: the ball is not told from its shadow
MIN_BALL_CONTRAST = 0.25    # the ball's edge (inside) against the surface, a share of the surface's grey
MIN_RAYS = 0.35             # fewer usable rays than this share: no fit
MAX_ARC_GAP = math.radians(90)    # the used rays leave no wider gap around the centre
CHECK_RAYS = 0.25           # the edge beside the plain background, fitted alone when this share of rays ...
CHECK_ARC_GAP = math.radians(200)   # ... leaves no wider gap: the two fits' distance is added to the sigma
MAX_SHIFT_PX = 0.6          # ... and more than this is a gap ("in its shadow")
MIN_INLIERS = 0.6           # the fit's inliers among the used rays
MAX_RESIDUAL_PX = 0.4       # the inliers' rms distance from the fitted silhouette
SHADOW_EVEN = 0.12          # a shadow's inside: the ratio to the background varies less than this (relative)
SHADOW_RATIO_MIN = 0.15     # ... and is at least this (the ambient light's share: a dark ball is darker)
MAX_LOW_SHARE = 0.2         # a silhouette with more of its edge than this without contrast: unseparable
MIN_FACING = 0.6            # overlapping silhouettes: the ball's edge toward the others is this intact
PREDICT_TOL = 0.5           # a centre further than this (times the radius) from the track's prediction: doubtful
SHAPE_STEP = 4              # px between the entries of the ball's shape table
HYPOTHESES = 3              # the edge's strongest circles tried (the ball, its shadow, ...)
GAP_REASONS = ("not found", "partly hidden", "merges with the surface", "in its shadow", "fits badly")


@dataclass
class Ball:
    """One frame's ball: its centre (u, v) px (the projection of the sphere's centre) and
    standard deviations, the silhouette's fitted scale against the expected one, the
    median contrast (grey levels) of its edge, and how the edge's rays were used."""

    u: float
    v: float
    su: float
    sv: float
    area: float
    contrast: float
    scale: float = 1.0
    residual_px: float = 0.0
    rays_used: int = 0
    rays: int = 0
    fit: dict | None = field(default=None, repr=False)    # the silhouette for a review sheet
    score: float = 0.0                                     # the hypothesis's support (rays that fit)
    shadowlike: bool = False                               # its inside looks like a shadow (a lower rank)
    facing: float = 1.0                                    # its edge's share intact toward an overlapping one
    low_share: float = 0.0                                 # the share of its edge's rays without contrast
    dark: bool = False                                     # nothing inside is lighter than the surface


@dataclass
class Miss:
    """A frame without a reported ball: the reason (one of GAP_REASONS) and, when a ball
    was seen, where (px) and its silhouette."""

    reason: str
    u: float = math.nan
    v: float = math.nan
    fit: dict | None = field(default=None, repr=False)


class Shape:
    """The ball's silhouette anywhere in the image: on a grid of image points q (each
    taken as the projection of the sphere's centre, its ray met with the ball-centre
    offset surface), the cone of rays tangent to the sphere projected through the camera
    (with its distortion) and fitted by an ellipse: semi-axes a >= b px, the major axis's
    angle, and the ellipse's centre's offset from q (the perspective shift of a sphere's
    image, up to a tenth of a pixel). Interpolated bilinearly between grid points."""

    def __init__(self, camera, surface, radius, size, n=13):
        import cv2

        w, h = size
        us, vs = np.linspace(0, w - 1, n), np.linspace(0, h - 1, n)
        U, V = np.meshgrid(us, vs)
        q = np.c_[U.ravel(), V.ravel()]
        C = cam_mod.ball_centres(camera, surface, radius, q)
        Cw = np.stack(surface.to_work(C[:, 0], C[:, 1], C[:, 2]), axis=1)
        r_mm = radius * surface.scale
        O = camera.centre
        out = np.full((len(q), 5), np.nan)
        t = np.linspace(0, 2 * math.pi, 48, endpoint=False)
        for i, c in enumerate(Cw):
            if not np.all(np.isfinite(c)):
                continue
            z = c - O
            d = float(np.linalg.norm(z))
            if d <= r_mm:
                continue
            z /= d
            e1 = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(z, e1)
            rho = r_mm * math.sqrt(1 - (r_mm / d) ** 2)      # the tangent circle's radius
            ring = c - (r_mm * r_mm / d) * z + rho * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
            p = camera.project(ring)
            (eu, ev), (A, B), ang = cv2.fitEllipse(p.astype(np.float32))
            qc = camera.project(c[None, :])[0]
            a2, b2, th = A / 2, B / 2, math.radians(ang)
            if a2 < b2:                                      # the major axis first
                a2, b2, th = b2, a2, th + math.pi / 2
            out[i] = (a2, b2, th, eu - qc[0], ev - qc[1])
        bad = ~np.all(np.isfinite(out), axis=1)
        if bad.all():
            raise SpecError("the ball's image could not be computed: the camera does not see the block")
        if bad.any():                                       # rays past the block: the nearest grid point
            good = np.flatnonzero(~bad)
            for i in np.flatnonzero(bad):
                j = good[np.argmin(np.hypot(*(q[good] - q[i]).T))]
                out[i] = out[j]
        self.grid = out.reshape(n, n, 5)
        self.us, self.vs = us, vs
        self.n = n
        # a dense table every SHAPE_STEP px (bilinear from the grid), read by the nearest entry
        g = self.grid
        planes = np.stack([g[..., 0], g[..., 1], np.cos(2 * g[..., 2]), np.sin(2 * g[..., 2]), g[..., 3], g[..., 4]],
                          axis=-1).astype(np.float32)
        tw, th = w // SHAPE_STEP + 2, h // SHAPE_STEP + 2
        xs = np.arange(tw) * SHAPE_STEP / us[-1] * (n - 1)
        ys = np.arange(th) * SHAPE_STEP / vs[-1] * (n - 1)
        X, Y = np.meshgrid(xs.astype(np.float32), ys.astype(np.float32))
        tab = np.stack([cv2.remap(planes[..., k], X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                        for k in range(6)], axis=-1).astype(float)
        self.table = np.stack([tab[..., 0], tab[..., 1], 0.5 * np.arctan2(tab[..., 3], tab[..., 2]),
                               tab[..., 4], tab[..., 5]], axis=-1)
        self.tw, self.th = tw, th

    def at(self, u: float, v: float):
        """(a, b, angle, du, dv) at image point (u, v) (the table's nearest entry, SHAPE_STEP
        px apart: the ellipse changes by well under a thousandth of a pixel between them)."""
        i = min(max(int(v / SHAPE_STEP + 0.5), 0), self.th - 1)
        j = min(max(int(u / SHAPE_STEP + 0.5), 0), self.tw - 1)
        return self.table[i, j]

    def at_exact(self, u: float, v: float):
        """(a, b, angle, du, dv) at image point (u, v), bilinear on the grid."""
        n = self.n
        fu = min(max(u / self.us[-1] * (n - 1), 0.0), n - 1 - 1e-9)
        fv = min(max(v / self.vs[-1] * (n - 1), 0.0), n - 1 - 1e-9)
        i, j = int(fv), int(fu)
        s, t = fv - i, fu - j
        g = self.grid
        a, b, c, d = g[i, j], g[i, j + 1], g[i + 1, j], g[i + 1, j + 1]
        out = (1 - s) * ((1 - t) * a + t * b) + s * ((1 - t) * c + t * d)
        # the angle: averaged as a direction of period pi
        ang = [a[2], b[2], c[2], d[2]]
        wts = [(1 - s) * (1 - t), (1 - s) * t, s * (1 - t), s * t]
        cx = sum(wt * math.cos(2 * x) for wt, x in zip(wts, ang))
        sx = sum(wt * math.sin(2 * x) for wt, x in zip(wts, ang))
        out[2] = 0.5 * math.atan2(sx, cx)
        return out

    @property
    def median_radius(self) -> float:
        return float(np.median(0.5 * (self.grid[..., 0] + self.grid[..., 1])))


def _ellipse_radius(theta, a, b, phi):
    """The radius of an ellipse (semi-axes a, b, major axis at angle phi) toward theta."""
    c, s = np.cos(theta - phi), np.sin(theta - phi)
    return a * b / np.sqrt((b * c) ** 2 + (a * s) ** 2)


def fit_silhouette(pts, wts, start, a, b, phi, scale_sigma=SCALE_SIGMA, iters=12):
    """The centre (2,) and scale of the ellipse (a s, b s, angle phi) through the edge
    points ``pts`` (n, 2) px with weights ``wts`` (n,), robustly (Huber's weights on the
    residuals' own scale, a prior N(1, scale_sigma) on s), by Gauss-Newton with the exact
    derivatives of the radial residual |p - c| - s rho(theta). Returns (centre, scale,
    residuals (n,), robust weights (n,), covariance (3, 3) of (u, v, s) per unit residual
    variance)."""
    c = np.asarray(start, dtype=float).copy()
    s = 1.0
    w_rob = np.ones(len(pts))
    cov = np.full((3, 3), np.nan)
    r = np.zeros(len(pts))
    for it in range(iters):
        dx, dy = pts[:, 0] - c[0], pts[:, 1] - c[1]
        rr = np.hypot(dx, dy)
        rr = np.maximum(rr, 1e-9)
        th = np.arctan2(dy, dx)
        cs, sn = np.cos(th - phi), np.sin(th - phi)
        q = np.sqrt((b * cs) ** 2 + (a * sn) ** 2)
        rho = a * b / q
        r = rr - s * rho
        # d rho / d theta, and d theta / d c
        drho = -a * b * (a * a - b * b) * sn * cs / q ** 3
        dth_du, dth_dv = dy / rr ** 2, -dx / rr ** 2
        J = np.stack([-dx / rr - s * drho * dth_du, -dy / rr - s * drho * dth_dv, -rho], axis=1)
        if it >= 1:
            if it in (1, 3):            # the residuals' own scale (their median absolute value)
                ar = np.abs(r[wts > 0]) if (wts > 0).any() else np.ones(1)
                scale_r = max(1.4826 * float(np.partition(ar, ar.size // 2)[ar.size // 2]), 0.05)
            k = 1.5 * scale_r
            w_rob = np.where(np.abs(r) <= k, 1.0, k / np.maximum(np.abs(r), 1e-12))
        W = wts * w_rob
        A = J.T @ (W[:, None] * J)
        g = J.T @ (W * r)
        A[2, 2] += 1.0 / scale_sigma ** 2
        g[2] += (s - 1.0) / scale_sigma ** 2
        try:
            step = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            return None
        c += step[:2]
        s += step[2]
        if abs(step[0]) + abs(step[1]) + 10.0 * abs(step[2]) < 2e-4 and it >= 2:
            break
    try:
        cov = np.linalg.inv(A)
    except np.linalg.LinAlgError:
        return None
    return c, s, r, w_rob, cov


class BallFinder:
    """Finds the ball frame by frame against a background (see the module doc).

    ``background`` (h, w) uint8; ``shape`` a :class:`Shape` (or a number: one radius in
    px everywhere, a circle); ``noise`` the background's noise, grey levels (1 sigma)."""

    def __init__(self, background: np.ndarray, shape, noise: float, exclude=None):
        import cv2

        self.cv2 = cv2
        self.bg = np.ascontiguousarray(background)
        self.bgf = self.bg.astype(np.float32)
        if not isinstance(shape, Shape):
            shape = _FixedShape(float(shape))
        self.shape = shape
        self.r = shape.median_radius
        self.noise = max(float(noise), 0.5)
        k = max(1, int(round(self.r * 1.2 / DOWN)))
        self.k = k | 1
        self.exclude = None
        self.bg_small = np.ascontiguousarray(self.bg[::DOWN, ::DOWN])
        if exclude is not None:       # (h, w) bool: pixels never searched (the markers' paper)
            self.exclude = np.asarray(exclude, dtype=bool)
            self.exclude_small = np.ascontiguousarray(self.exclude[::DOWN, ::DOWN])
        self.last: list = []          # the last two frames' centres, when both had the ball
        self.threshold = max(MIN_CONTRAST, 6.0 * self.noise)
        self.nrays = int(min(128, max(48, 4 * round(1.5 * self.r))))
        self.theta = np.linspace(0, 2 * math.pi, self.nrays, endpoint=False)
        self.miss: Miss | None = None
        self.predicted = None

    def find(self, grey: np.ndarray) -> Ball | None:
        """The ball in this frame, or None (then ``self.miss`` says why). Frames are
        expected in order: where the last two frames had the ball, the search starts in a
        window around the position they predict (the whole frame when it is not there)."""
        b = None
        self.miss = None
        self.predicted = None
        if len(self.last) == 2:
            (u1, v1), (u2, v2) = self.last
            du, dv = u2 - u1, v2 - v1
            self.predicted = (u2 + du, v2 + dv)
            # the silhouette straight at the prediction: no search when it fits there
            pu, pv = self.predicted
            h, w = grey.shape
            if 0 <= pu < w and 0 <= pv < h:
                got = self._fit_at(grey, np.array([pu, pv]))
                if not isinstance(got, Miss) and self._early_ok(got):
                    self.last = (self.last + [(got.u, got.v)])[-2:]
                    return got
            half = int(3 * self.r + 2 * math.hypot(du, dv)) + 8
            b = self._search(grey, (u2 + du, v2 + dv, half))
        if b is None and (self.miss is None or self.miss.reason == "not found"):
            self.predicted = None
            b = self._search(grey, None)
        if b is None and self.miss is None:
            self.miss = Miss("not found")
        self.last = (self.last + [(b.u, b.v)])[-2:] if b is not None else []
        return b

    def _early_ok(self, got) -> bool:
        """A silhouette found where the track predicts it, whole enough and not a shadow."""
        R = 0.5 * (got.fit["a"] + got.fit["b"])
        return (not got.shadowlike and got.low_share <= MAX_LOW_SHARE
                and math.hypot(got.fit["centre"][0] - self.predicted[0], got.fit["centre"][1] - self.predicted[1])
                <= max(PREDICT_TOL * R, 3.0))

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
        return self._silhouette(grey, u0, v0)

    def _hough(self, d: np.ndarray, R: float):
        """The centre (crop px) of the circle of radius R best supported by the edges of
        ``d`` (frame - background, float32): each edge pixel votes R along its gradient,
        both ways (the ball may be darker on one side and lighter on the other), weighted
        by the gradient's size."""
        cv2 = self.cv2
        gx = cv2.Sobel(d, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(d, cv2.CV_32F, 0, 1, ksize=3)
        mag = cv2.magnitude(gx, gy)
        thr = max(8.0 * self.noise, 0.08 * float(mag.max()))
        ys, xs = np.nonzero(mag > thr)
        if xs.size < 8:
            return None
        m = mag[ys, xs]
        ux, uy = gx[ys, xs] / m, gy[ys, xs] / m
        hh, ww = d.shape
        acc = np.zeros(hh * ww, np.float32)
        wt = np.sqrt(m)
        for sgn in (1.0, -1.0):
            cx = np.rint(xs + sgn * R * ux).astype(np.int64)
            cy = np.rint(ys + sgn * R * uy).astype(np.int64)
            ok = (cx >= 0) & (cx < ww) & (cy >= 0) & (cy < hh)
            acc += np.bincount(cy[ok] * ww + cx[ok], weights=wt[ok], minlength=hh * ww).astype(np.float32)
        sb = max(1.0, 0.08 * R)
        kb = 2 * int(math.ceil(2.0 * sb)) + 1
        acc = cv2.GaussianBlur(acc.reshape(hh, ww), (kb, kb), sb)
        out = []
        for _ in range(HYPOTHESES):         # the strongest peaks, each at least 0.7 R from the others
            _, val, _, loc = cv2.minMaxLoc(acc)
            if val <= 0 or (out and val < 0.15 * out[0][2]):
                break
            out.append((float(loc[0]), float(loc[1]), float(val)))
            cv2.circle(acc, loc, int(math.ceil(0.7 * R)), 0.0, -1)
        return out

    def _silhouette(self, grey: np.ndarray, u0: float, v0: float) -> Ball | None:
        """The silhouette fit around the coarse peak (u0, v0) (see the module doc)."""
        cv2 = self.cv2
        h, w = grey.shape
        a, b, phi, _, _ = self.shape.at(u0, v0)
        R = 0.5 * (a + b)
        reach = int(math.ceil(3.2 * R)) + 6
        cx0, cy0 = max(0, int(u0) - reach), max(0, int(v0) - reach)
        cx1, cy1 = min(w, int(u0) + reach + 1), min(h, int(v0) + reach + 1)
        g = grey[cy0:cy1, cx0:cx1].astype(np.float32)
        bg = self.bgf[cy0:cy1, cx0:cx1]
        d = g - bg
        if self.exclude is not None:
            d[self.exclude[cy0:cy1, cx0:cx1]] = 0.0
        peaks = self._hough(d, R)
        if not peaks:
            self.miss = Miss("not found")
            return None
        best, miss = None, None
        balls, covered = [], []
        if self.predicted is not None:      # the track so far: first the peak it predicts
            pu, pv = self.predicted[0] - cx0, self.predicted[1] - cy0
            j = int(np.argmin([math.hypot(p_[0] - pu, p_[1] - pv) for p_ in peaks]))
            if math.hypot(peaks[j][0] - pu, peaks[j][1] - pv) <= max(PREDICT_TOL * R, 3.0):
                got = self._fit_at(grey, np.array([peaks[j][0] + cx0, peaks[j][1] + cy0]))
                if not isinstance(got, Miss) and self._early_ok(got):
                    return got
        for hu, hv, _ in peaks:
            got = self._fit_at(grey, np.array([hu + cx0, hv + cy0]))
            if not isinstance(got, Miss):
                balls.append(got)
            else:
                if got.reason == "partly hidden":
                    covered.append(got)
                miss = miss or got
        # two silhouettes overlapping (the ball and its shadow): the ball is in front, so its
        # edge facing the other is whole, while the shadow's edge there is behind the ball
        for A in balls:
            for B in balls:
                if A is B:
                    continue
                dv = np.array([B.fit["centre"][0] - A.fit["centre"][0], B.fit["centre"][1] - A.fit["centre"][1]])
                dist = float(np.hypot(*dv))
                if dist < 0.3 * R or dist > 2.3 * R:
                    continue
                face = np.cos(self.theta - math.atan2(dv[1], dv[0])) > math.cos(math.radians(50))
                A.facing = min(A.facing, float(np.mean(A.fit["inlier"][face])))
        # a silhouette darker than the surface all over, no darker than a shadow can be, next to
        # something lighter than the surface (a light ball, a highlight): the light ball's shadow
        lit = (d > np.maximum(6.0 * self.noise, 0.08 * bg)) & (bg > 0)
        if lit.any():
            ly, lx = np.nonzero(lit)
            for b_ in balls:
                if b_.dark and not b_.shadowlike:
                    cu, cv_ = b_.fit["centre"][0] - cx0, b_.fit["centre"][1] - cy0
                    rr2 = (lx - cu) ** 2 + (ly - cv_) ** 2
                    if np.count_nonzero((rr2 > (1.1 * R) ** 2) & (rr2 < (2.3 * R) ** 2)) >= 3:
                        b_.shadowlike = True
        ok = [b_ for b_ in balls if not b_.shadowlike and b_.low_share <= MAX_LOW_SHARE]
        if self.predicted is not None:          # the track so far: a ball moves smoothly
            pu, pv = self.predicted
            near = [b_ for b_ in ok if math.hypot(b_.fit["centre"][0] - pu, b_.fit["centre"][1] - pv)
                    <= max(PREDICT_TOL * R, 3.0)]
            if ok and not near:
                self.miss = Miss("fits badly", ok[0].fit["centre"][0], ok[0].fit["centre"][1], ok[0].fit)
                return None
            ok = near
        if ok:
            ok.sort(key=lambda b_: (-round(b_.facing, 1), -b_.score))
            best = ok[0]
            for m_ in covered:          # something covers a disc next to it: which is the ball is unsure
                if math.hypot(m_.u - best.fit["centre"][0], m_.v - best.fit["centre"][1]) < 2.3 * R:
                    self.miss = Miss("partly hidden", m_.u, m_.v, m_.fit)
                    return None
            if best.facing < MIN_FACING or (len(ok) > 1 and ok[1].facing > 0.6 and best.facing - ok[1].facing < 0.3):
                self.miss = Miss("in its shadow", best.fit["centre"][0], best.fit["centre"][1], best.fit)
                return None
        elif balls and miss is None:
            why = "in its shadow" if any(b_.shadowlike for b_ in balls) else "merges with the surface"
            miss = Miss(why, balls[0].fit["centre"][0], balls[0].fit["centre"][1], balls[0].fit)
        if best is None:
            self.miss = miss
        return best

    def _fit_at(self, grey, c0):
        """The ball's silhouette fitted from rays around ``c0`` (px): a Ball, or a Miss."""
        cv2 = self.cv2
        h, w = grey.shape
        a, b, phi, _, _ = self.shape.at(*c0)
        R = 0.5 * (a + b)
        # the rays: profiles across the expected edge, from m inside to m outside
        m = max(3.0, 0.3 * R)
        st = np.arange(-m, m + 1e-9, 0.25)
        rho0 = _ellipse_radius(self.theta, a, b, phi)
        dist = rho0[:, None] + st[None, :]
        cth, sth = np.cos(self.theta)[:, None], np.sin(self.theta)[:, None]
        X = (c0[0] + dist * cth).astype(np.float32)
        Y = (c0[1] + dist * sth).astype(np.float32)
        inside_img = (X.min(axis=1) >= 0) & (X.max(axis=1) <= w - 1) & (Y.min(axis=1) >= 0) & \
            (Y.max(axis=1) <= h - 1)
        # the profiles, sampled (bilinear) on a float crop around the rays
        px0, py0 = max(0, int(X.min()) - 1), max(0, int(Y.min()) - 1)
        px1, py1 = min(w, int(X.max()) + 3), min(h, int(Y.max()) + 3)
        Xc, Yc = X - px0, Y - py0
        f = cv2.remap(grey[py0:py1, px0:px1].astype(np.float32), Xc, Yc, cv2.INTER_LINEAR,
                      borderMode=cv2.BORDER_REPLICATE)
        gb = cv2.remap(self.bgf[py0:py1, px0:px1], Xc, Yc, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        n_st = len(st)
        q = max(2, n_st // 4)
        # inside the ball near the edge, outside, and the background there (medians)
        I, O, B = np.median(np.stack([f[:, :q], f[:, -q:], gb[:, -q:]]), axis=2)
        sig = self.noise
        contrast = I - O
        ratio = O / np.maximum(B, 1.0)
        I_med = _med(I[inside_img]) if inside_img.any() else _med(I)
        B_med = _med(B)
        ball_vs_bg = I_med - B_med
        # the rays' verdicts
        low = np.abs(contrast) < max(6.0 * sig, MIN_CONTRAST)
        changed = np.abs(O - B) > np.maximum(4.0 * sig, SHADOW_RATIO * B)
        shadow = changed & (O < B)                      # darker than the background: a shadow ...
        other = changed & (O >= B)                      # lighter: something else
        # covered: inside unlike the ball, outside unlike the background, and the two alike
        hidden = (np.abs(I - I_med) > max(8.0 * sig, 0.5 * abs(ball_vs_bg), HIDDEN_DIFF * B_med)) & \
            (np.sign(I - I_med) != np.sign(ball_vs_bg)) & (np.abs(I - O) < 0.5 * abs(ball_vs_bg)) & \
            (np.abs(O - B) > HIDDEN_DIFF * B)
        hidden |= ~inside_img
        # the edge on each ray: the area of the profile's share of the ball (blur-symmetric)
        # the outside as the background times the ray's own ratio (a shadow scales the
        # background), so the surface's shading across the edge does not move it
        Os = ratio[:, None] * gb
        den = I[:, None] - Os
        with np.errstate(all="ignore"):
            alpha = np.clip((f - Os) / np.where(np.abs(den) < 1e-3, 1e-3, den), 0.0, 1.0)
        # the edge's offset from rho0: the share's integral (trapezoid, 0.25 px steps)
        e = -m + (alpha.sum(axis=1) - 0.5 * (alpha[:, 0] + alpha[:, -1])) * 0.25
        # monotone: the profile crosses halfway once
        half = (f - 0.5 * (I + O)[:, None]) * np.sign(contrast)[:, None]
        crossings = np.sum((half[:, :-1] > 0) & (half[:, 1:] <= 0), axis=1)
        # the outside must be flat past the edge (a penumbra's ramp beside a faint edge moves it)
        h2 = max(1, q // 2)
        q1 = f[:, -q:-h2].mean(axis=1) / np.maximum(gb[:, -q:-h2].mean(axis=1), 1.0)
        q2 = f[:, -h2:].mean(axis=1) / np.maximum(gb[:, -h2:].mean(axis=1), 1.0)
        ramp = np.abs(q1 - q2) * B / np.maximum(np.abs(contrast), 1.0)      # over m / 4 px
        soft = ramp > MAX_RAMP
        clean = ~low & ~soft & ~changed & ~hidden & (crossings == 1)
        usable = ~low & ~soft & ~hidden & (crossings == 1)
        n = self.nrays
        nh = int(hidden.sum())
        reasons = {"hidden": nh, "low": int((low & ~hidden).sum()), "shadow": int((shadow & ~hidden).sum()),
                   "other": int((other & ~hidden).sum())}
        pts = np.c_[c0[0] + (rho0 + e) * np.cos(self.theta), c0[1] + (rho0 + e) * np.sin(self.theta)]
        fitinfo = {"centre0": c0, "points": pts, "clean": clean, "shadow": (shadow | soft) & ~hidden, "hidden": hidden,
                   "low": low & ~hidden, "a": a, "b": b, "phi": phi}
        if nh > HIDDEN_RAYS * n:
            return Miss("partly hidden", c0[0], c0[1], fitinfo)
        use = usable
        if abs(ball_vs_bg) < MIN_BALL_CONTRAST * B_med:    # the ball's edge about as light as the surface
            return Miss("merges with the surface", c0[0], c0[1], fitinfo)
        if soft.mean() > MAX_SOFT_SHARE:     # most of the edge beside a shadow's ramp: not separable
            return Miss("in its shadow", c0[0], c0[1], fitinfo)
        if use.sum() < MIN_RAYS * n or not _arc_ok(self.theta[use]):
            why = "merges with the surface" if reasons["low"] >= reasons["shadow"] else "in its shadow"
            return Miss(why, c0[0], c0[1], fitinfo)
        res = fit_silhouette(pts[use], np.ones(int(use.sum())), c0, a, b, phi)
        if res is None:
            return Miss("fits badly", c0[0], c0[1], fitinfo)
        c, s, r, w_rob, cov = res
        # the inliers: within 3 robust sigma of the silhouette (0.3 px at least)
        inl = np.abs(r) <= max(3.0 * 1.4826 * _med(np.abs(r)), 0.3)
        sr = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.sum() > 3 else float("inf")
        inlier = np.zeros(n, bool)
        inlier[np.flatnonzero(use)[inl]] = True
        fitinfo.update(centre=c, scale=s, used=use, residual=sr, inlier=inlier)
        bad = not (SCALE_RANGE[0] <= s <= SCALE_RANGE[1]) or inl.mean() < MIN_INLIERS or sr > MAX_RESIDUAL_PX
        if bad:
            return Miss("fits badly", c[0], c[1], fitinfo)
        # the edge beside the background alone (no shadow, nothing changed outside) fitted on
        # its own: where it says otherwise, the shadow's side moved the fit
        shift = 0.0
        sub = clean & use
        if 0 < int((use & ~sub).sum()) and sub.sum() >= CHECK_RAYS * n and _arc_ok(self.theta[sub], CHECK_ARC_GAP):
            res2 = fit_silhouette(pts[sub], np.ones(int(sub.sum())), c, a, b, phi, iters=5)
            if res2 is not None:
                shift = float(np.hypot(*(res2[0] - c)))
                if shift > MAX_SHIFT_PX:
                    return Miss("in its shadow", c[0], c[1], fitinfo)
        k = int(inl.sum())
        s2 = max(sr * sr * k / max(k - 3, 1), (0.5 * sig / max(_med(np.abs(contrast[use])), 1.0)) ** 2)
        cov_px = cov[:2, :2] * s2
        _, _, _, du, dv = self.shape.at(*c)
        su = math.sqrt(SIGMA_GAIN ** 2 * max(cov_px[0, 0], 0.0) + SIGMA_FLOOR_PX ** 2)
        sv = math.sqrt(SIGMA_GAIN ** 2 * max(cov_px[1, 1], 0.0) + SIGMA_FLOOR_PX ** 2)
        # the model's own error, which does not average down over the rays: a share of the
        # edge's residual, and more when a side of the edge is left out (the blur and the
        # shading are then not averaged out)
        frac = 1.0 - float(use.mean())
        extra = math.hypot(math.hypot(SIGMA_PARTIAL_PX * frac, SIGMA_RESIDUAL * sr), shift)
        su, sv = math.hypot(su, extra), math.hypot(sv, extra)
        ball = Ball(float(c[0] - du), float(c[1] - dv), su, sv, math.pi * a * b * s * s,
                    _med(np.abs(contrast[use])), float(s), sr, int(use.sum()), n, fitinfo)
        ball.low_share = float((low & ~hidden).mean())
        ball.score = float(usable.sum()) + 0.5 * float(inl.sum()) / max(1.0, 4.0 * sr)
        # a shadow only darkens the surface it falls on, by a smooth ratio: the disc's inside
        # that never rises above the background and keeps its ratio even is no ball
        rr = 0.75 * min(a, b) * s
        k0 = max(0, int(c[0] - rr)), max(0, int(c[1] - rr))
        k1 = min(w, int(c[0] + rr) + 2), min(h, int(c[1] + rr) + 2)
        gin = grey[k0[1]:k1[1], k0[0]:k1[0]].astype(np.float32)
        bin_ = self.bgf[k0[1]:k1[1], k0[0]:k1[0]]
        yy = np.arange(k0[1], k1[1], dtype=np.float32)[:, None]
        xx = np.arange(k0[0], k1[0], dtype=np.float32)[None, :]
        disc = (xx - c[0]) ** 2 + (yy - c[1]) ** 2 <= rr * rr
        if disc.sum() >= 5:
            gi, bi = gin[disc], bin_[disc]
            brighter = float(np.mean(gi > bi + np.maximum(4.0 * sig, 0.05 * bi)))
            q = gi / np.maximum(bi, 1.0)
            even = float(np.std(q)) / max(float(np.mean(q)), 1e-3)
            ball.shadowlike = brighter < 0.02 and even < SHADOW_EVEN and float(np.mean(q)) > SHADOW_RATIO_MIN
            ball.dark = not np.any(gi > bi + np.maximum(6.0 * sig, 0.08 * bi)) and float(np.mean(q)) > SHADOW_RATIO_MIN
        fitinfo["shadowlike"] = ball.shadowlike
        return ball


def _med(x) -> float:
    """The median of a 1-d array (the upper one of an even count: a robust level, not an average)."""
    x = np.asarray(x).ravel()
    if x.size == 0:
        return float("nan")
    k = x.size // 2
    return float(np.partition(x, k)[k])


def _arc_ok(theta, widest=None) -> bool:
    """The used rays surround the centre: no gap between neighbours wider than ``widest``
    (MAX_ARC_GAP)."""
    if theta.size < 3:
        return False
    t = np.sort(theta)
    gaps = np.diff(np.r_[t, t[0] + 2 * math.pi])
    return float(gaps.max()) <= (MAX_ARC_GAP if widest is None else widest)


class _FixedShape:
    """One circle of radius r px everywhere (no camera known)."""

    def __init__(self, r):
        self.r = r
        self.median_radius = r

    def at(self, u, v):
        return np.array([self.r, self.r, 0.0, 0.0, 0.0])
