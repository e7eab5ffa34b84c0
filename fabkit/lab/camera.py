"""The camera: ArUco markers on the top face, calibration from their corners, and the
ray from a pixel to the ball-centre offset surface.

Coordinates. Work coordinates are mm with the origin on the top face at the
footprint's corner of smallest x and y, Z up (:meth:`fabkit.surface.Surface.to_work`).
Image coordinates are pixels with (0, 0) the centre of the top-left pixel, u to the
right, v down (OpenCV's convention).

The camera model: a pinhole with square pixels, its principal point at the image
centre ((w - 1) / 2, (h - 1) / 2), one radial distortion term and a pose:

    p = R (X - C),   x = p_x / p_z,  y = p_y / p_z,   d = 1 + k1 (x^2 + y^2)
    u = f d x + (w - 1) / 2,   v = f d y + (h - 1) / 2

so 8 unknowns (f, k1, the rotation R and the centre C), fitted to the 16 corners of
markers 0-3 by least squares, with ``lab.camera_height`` as a prior on C_Z when
given (a 10 mm standard deviation: the focal length and the height are nearly one
unknown, f / height, when the camera looks straight down).

The markers lie on the top face (Z = 0), printed with their top edge toward +Y. The
corners are matched to the layout by position (after a homography of the four
centres), so a marker stuck down turned by 90 degrees is still read right.

The ball's centre C = P + r n rides on the offset surface of the milled surface
(P = (x, y, min(h, top)), n its upward unit normal, r the ball's radius): a pixel's
ray meets it where P(x, y) + r n(x, y) = O + s d, solved by Newton's method with the
exact Jacobian (h's second derivatives), to 1e-9 design units. The parallax of a
centre below the top face is thus exact, not approximated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import SpecError

DICTIONARY = "DICT_4X4_50"
MARKER_IDS = (0, 1, 2, 3)
MODULES = 6                  # a 4x4 ArUco marker: 4 data modules and a black border module each side
EDGE_GAP_MM = 5.0            # default: the black square this far from the two nearest block edges
HEIGHT_SIGMA_MM = 10.0       # lab.camera_height: a tape measure, good to about 1 cm
CORNER_SIGMA_PX = 0.2        # the weight of a corner in the fit (px); reported errors are measured
K1_PRIOR = 0.3              # without lab.camera_height: k1 ~ N(0, 0.3) ...
LOG_F_PRIOR = 1.0           # ... and log f ~ N(log width, 1): weak, only a degenerate fit leans on them
FLAT_MM = 0.05               # a marker's paper may lie over a cut this shallow (mm)
SMALLER_SIZES_MM = (25.0, 20.0, 15.0, 12.0, 10.0)   # tried in turn when the default size finds no room


# ----------------------------------------------------------------------------
# the marker layout
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class MarkerLayout:
    """Markers 0-3 on the top face: ``size`` the black square's side (mm), ``centres``
    (4, 2) work mm in id order."""

    size: float
    centres: np.ndarray
    notes: tuple = ()

    @property
    def module(self) -> float:
        """The side of one module (one cell of the 6 x 6 marker), mm."""
        return self.size / MODULES

    def corners(self) -> np.ndarray:
        """(4, 4, 3) work mm: each marker's corners in OpenCV's order (top-left, top-right,
        bottom-right, bottom-left of the printed marker, its top toward +Y), Z = 0."""
        h = self.size / 2.0
        off = np.array([[-h, h], [h, h], [h, -h], [-h, -h]])
        xy = self.centres[:, None, :] + off[None]
        return np.concatenate([xy, np.zeros((4, 4, 1))], axis=2)


@dataclass(frozen=True)
class TopFacePlan:
    """Where paper can be stuck on the block's top face, on a grid in work mm.

    ``X`` (nx,), ``Y`` (ny,) the grid; ``depth_mm`` (ny, nx) how far the milled surface
    lies below the top face (top - h, mm; negative where h is above it and the top face
    is uncut); ``cut`` where it is below (h < top); ``blocked`` (ny, nx) the cut grown by
    ``margin_mm`` (the finishing ball-end tool's radius) and one grid step, or under the
    ramp; ``ramp`` the ramp's footprint on the block, [X0, X1, Y0, Y1] work mm, or None
    (a straight ramp's width taken as 3 ball diameters each side)."""

    X: np.ndarray
    Y: np.ndarray
    depth_mm: np.ndarray
    cut: np.ndarray
    blocked: np.ndarray
    margin_mm: float
    ramp: tuple | None
    step_mm: float


#: grid nodes across the block's longer side for :func:`top_face_plan` (at most)
PLAN_NODES = 801


def _ramp_footprint(spec, surface):
    """The ramp's footprint on the block in work mm [X0, X1, Y0, Y1] (the launch point back
    to the block's end, the ramp's width), or None when the spec has no ramp to build."""
    if not all(spec.has(k) for k in ("ramp", "ball", "simulation")):
        return None
    from ..physics.ramp_profile import ramp_profile
    from .ramp import half_width

    try:
        prof = ramp_profile(spec)
        if getattr(spec.ramp, "profile", "fabkit") == "straight":
            hw = min(3.0 * float(spec.ball.diameter), prof.u_end)
            start, y0 = float(spec.simulation.start), float(spec.simulation.y0)
            back = prof.u_end
        else:
            hw, start, y0, back = half_width(spec, prof), prof.start, prof.y0, prof.u_end
    except SpecError:
        return None
    X0, Y0 = surface.to_work(start - back, y0 - hw, surface.top)[:2]
    X1, Y1 = surface.to_work(start, y0 + hw, surface.top)[:2]
    L, W = surface.stock_size_mm
    box = (max(0.0, float(X0)), min(L, float(X1)), max(0.0, float(Y0)), min(W, float(Y1)))
    return box if box[0] < box[1] and box[2] < box[3] else None


def top_face_plan(spec, surface) -> TopFacePlan:
    """The block's top face from above (see :class:`TopFacePlan`): h evaluated on a grid of
    at most PLAN_NODES nodes a side (0.5 mm apart or coarser); a cell is blocked within the
    tool's radius plus one grid step of a cut node, so a marker clear of ``blocked`` is
    clear of the cut by the tool's radius."""
    from scipy.ndimage import distance_transform_edt

    L, W = surface.stock_size_mm
    step = max(0.5, max(L, W) / (PLAN_NODES - 1))
    X = np.linspace(0.0, L, int(math.ceil(L / step)) + 1)
    Y = np.linspace(0.0, W, int(math.ceil(W / step)) + 1)
    dx, dy = X[1] - X[0], Y[1] - Y[0]
    GX, GY = np.meshgrid(X, Y)
    xs, ys = surface.from_work(GX, GY)
    with np.errstate(all="ignore"):
        h = np.broadcast_to(np.asarray(surface.height(xs, ys), dtype=float), GX.shape)
    cut = ~(h >= surface.top)
    margin = 0.5 * float(spec.tool.diameter) if spec.has("tool") else 0.0
    dist = distance_transform_edt(~cut, sampling=(dy, dx)) if cut.any() else np.full(cut.shape, np.inf)
    blocked = dist <= margin + max(dx, dy)
    ramp = _ramp_footprint(spec, surface)
    if ramp is not None:
        g = max(dx, dy)
        blocked |= ((GX >= ramp[0] - g) & (GX <= ramp[1] + g) & (GY >= ramp[2] - g) & (GY <= ramp[3] + g))
    depth = np.where(np.isfinite(h), (surface.top - h) * surface.scale, np.inf)
    return TopFacePlan(X=X, Y=Y, depth_mm=depth, cut=cut, blocked=blocked, margin_mm=margin, ramp=ramp,
                       step_mm=max(dx, dy))


def _default_centres(spec, plan: TopFacePlan, size: float, L: float, W: float) -> np.ndarray:
    """Markers 0-3 at the corners (0, 0), (L, 0), (L, W), (0, W): each black square
    EDGE_GAP_MM from the two nearest edges when all four papers are clear there; else, in
    turn, each at the place nearest its corner where its paper (square and quiet zone,
    inside the block) is clear of the plan's blocked cells and of the markers placed."""
    from scipy.ndimage import maximum_filter

    paper = size + 2.0 * size / MODULES
    dx, dy = plan.X[1] - plan.X[0], plan.Y[1] - plan.Y[0]
    kx, ky = int(math.ceil(0.5 * paper / dx)), int(math.ceil(0.5 * paper / dy))
    free = ~maximum_filter(plan.blocked, size=(2 * ky + 1, 2 * kx + 1), mode="nearest")
    e = 0.5 * paper                   # elsewhere the paper may reach the block's edge
    GX, GY = np.meshgrid(plan.X, plan.Y)
    free &= (GX >= e - 1e-9) & (GX <= L - e + 1e-9) & (GY >= e - 1e-9) & (GY <= W - e + 1e-9)
    c = EDGE_GAP_MM + size / 2.0
    corners = np.array([[0.0, 0.0], [L, 0.0], [L, W], [0.0, W]])
    exact = np.array([[c, c], [L - c, c], [L - c, W - c], [c, W - c]])
    if all(_paper_clear(plan, q, paper) for q in exact):
        return exact
    out = []
    for i, corner in enumerate(corners):
        ok = free.copy()
        for q in out:
            ok &= np.maximum(np.abs(GX - q[0]), np.abs(GY - q[1])) >= paper + 1.0
        if not ok.any():
            raise SpecError(f"no room for marker {i} ({size:g} mm square, {paper:g} mm with its quiet zone) on the "
                            f"block's top face clear of the milled surface (and the tool's radius "
                            f"{plan.margin_mm:g} mm{' and the ramp' if plan.ramp else ''}): give a smaller "
                            "lab.marker_size, or place the markers with lab.markers", file=spec.path,
                            key="lab.marker_size")
        d = np.where(ok, np.hypot(GX - corner[0], GY - corner[1]), np.inf)
        k, j = np.unravel_index(int(np.argmin(d)), d.shape)
        out.append(np.array([float(plan.X[j]), float(plan.Y[k])]))
    return np.array(out)


def _paper_clear(plan: TopFacePlan, centre, paper: float) -> bool:
    """True when no blocked node of the plan lies within the paper's square (half side
    paper / 2 plus one grid step) around ``centre``."""
    h = 0.5 * paper + plan.step_mm
    ix = (plan.X >= centre[0] - h) & (plan.X <= centre[0] + h)
    iy = (plan.Y >= centre[1] - h) & (plan.Y <= centre[1] + h)
    return not plan.blocked[np.ix_(iy, ix)].any()


def _over_cut(surface, centre, paper: float):
    """The deepest point of the milled surface under a paper square (work mm, sampled at most
    0.5 mm apart, 401 nodes a side at most): (depth below the top face mm, X, Y)."""
    L, W = surface.stock_size_mm
    n = int(min(401, max(13, math.ceil(paper / 0.5) + 1)))
    g = np.linspace(-0.5 * paper, 0.5 * paper, n)
    X, Y = np.meshgrid(np.clip(centre[0] + g, 0, L), np.clip(centre[1] + g, 0, W))
    xs, ys = surface.from_work(X, Y)
    with np.errstate(all="ignore"):
        depth = (surface.top - np.broadcast_to(surface.height(xs, ys), X.shape)) * surface.scale
    depth = np.where(np.isnan(depth), np.inf, depth)
    j = int(np.argmax(depth))
    return float(depth.ravel()[j]), float(X.ravel()[j]), float(Y.ravel()[j])


def marker_layout(spec, surface) -> MarkerLayout:
    """The markers' layout from the spec's ``lab`` section (defaults when absent).

    Default: each marker nearest its corner of the block ((0, 0), (L, 0), (L, W), (0, W),
    the black square EDGE_GAP_MM inside the edges) with its paper (square and quiet zone)
    on the top face, clear of the milled surface by the finishing tool's radius and off the
    ramp's footprint (:func:`top_face_plan`); SpecError (``lab.marker_size``) when one
    does not fit. Given (``lab.markers``): a marker off the top face, or whose paper lies
    over the cut (more than FLAT_MM below the top face), is a SpecError naming the marker
    (``lab.markers[i]``); one within the tool's radius of the cut or on the ramp's
    footprint is a note."""
    lab = spec.lab if spec.has("lab") else None
    size = float(lab.marker_size) if lab is not None else 30.0
    paper = size + 2.0 * size / MODULES
    L, W = surface.stock_size_mm
    given = lab is not None and lab.markers is not None
    plan = top_face_plan(spec, surface)
    notes = []
    if given:
        centres = np.array(lab.markers, dtype=float)
    else:
        raw_lab = spec.raw.get("lab") if isinstance(spec.raw, dict) else None
        size_given = isinstance(raw_lab, dict) and "marker_size" in raw_lab
        ladder = [size] if size_given else [size] + [v for v in SMALLER_SIZES_MM if v < size]
        for k, trial in enumerate(ladder):
            try:
                if 2 * (EDGE_GAP_MM + trial / 2.0) > min(L, W) + 1e-9:
                    raise SpecError(f"a {trial:g} mm marker {EDGE_GAP_MM:g} mm inside the edges does not fit on the "
                                    f"block's top face [0, {L:g}] x [0, {W:g}] work mm", file=spec.path,
                                    key="lab.marker_size")
                centres = _default_centres(spec, plan, trial, L, W)
                break
            except SpecError:
                if k == len(ladder) - 1:
                    raise
        if trial != size:
            notes.append(f"{spec.path}: lab.marker_size: {size:g} mm markers do not fit on the top face clear of the "
                         f"cut; {trial:g} mm markers are placed instead (set lab.marker_size, or lab.markers, to "
                         "choose)")
            size, paper = trial, trial + 2.0 * trial / MODULES
    for i, (x, y) in enumerate(centres):
        h = size / 2.0
        if x - h < -1e-9 or x + h > L + 1e-9 or y - h < -1e-9 or y + h > W + 1e-9:
            raise SpecError(f"marker {i} at [{x:g}, {y:g}] ({size:g} mm square) does not lie on the "
                            f"block's top face [0, {L:g}] x [0, {W:g}] work mm", file=spec.path,
                            key=f"lab.markers[{i}]" if given else "lab.marker_size")
    if given:
        for i, (x, y) in enumerate(centres):
            depth, X, Y = _over_cut(surface, (x, y), paper)
            if depth > FLAT_MM:
                raise SpecError(f"marker {i} at [{x:g}, {y:g}] work mm ({paper:g} mm square with its quiet zone) "
                                f"lies over the milled surface (at [{X:.4g}, {Y:.4g}] the surface is {depth:.3g} mm "
                                "below the top face): give its centre on the flat top face (`fabkit markers` "
                                "without lab.markers places all four there)", file=spec.path, key=f"lab.markers[{i}]")
            if not _paper_clear(plan, (x, y), paper):
                what = ("the milled edge by the tool's radius " f"({plan.margin_mm:g} mm)"
                        + (" or on the ramp's footprint" if plan.ramp else ""))
                notes.append(f"{spec.path}: lab.markers[{i}]: marker {i} at [{x:g}, {y:g}] work mm lies within "
                             f"{what}: make sure its paper lies flat and the ramp leaves it in view")
    d = np.hypot(*(centres[:, None, :] - centres[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    if d.min() < size * math.sqrt(2):
        raise SpecError(f"markers overlap (two centres {d.min():.4g} mm apart, each square {size:g} mm)",
                        file=spec.path, key="lab.markers")
    return MarkerLayout(size=size, centres=centres, notes=tuple(notes))


# ----------------------------------------------------------------------------
# the camera model
# ----------------------------------------------------------------------------
def rotation(rvec) -> np.ndarray:
    """Rodrigues: the rotation matrix (3, 3) of the axis-angle vector ``rvec`` (rad)."""
    r = np.asarray(rvec, dtype=float)
    th = float(np.linalg.norm(r))
    if th < 1e-15:
        return np.eye(3)
    k = r / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


@dataclass
class Camera:
    """A calibrated camera (see the module doc): ``f`` px, ``k1``, ``rvec`` (rad) and
    ``tvec`` (mm) with p = R X + t, and the image size in px."""

    f: float
    k1: float
    rvec: np.ndarray
    tvec: np.ndarray
    width: int
    height: int

    @property
    def R(self) -> np.ndarray:
        return rotation(self.rvec)

    @property
    def centre(self) -> np.ndarray:
        """The camera's centre in work mm (3,)."""
        return -self.R.T @ np.asarray(self.tvec, dtype=float)

    @property
    def principal(self) -> tuple[float, float]:
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def project(self, X) -> np.ndarray:
        """Work mm (n, 3) -> pixels (n, 2)."""
        p = np.asarray(X, dtype=float) @ self.R.T + self.tvec
        x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        d = 1.0 + self.k1 * (x * x + y * y)
        cx, cy = self.principal
        return np.stack([self.f * d * x + cx, self.f * d * y + cy], axis=1)

    def undistort(self, uv) -> np.ndarray:
        """Pixels (n, 2) -> normalized, undistorted (x, y) (n, 2): r_d = r (1 + k1 r^2) solved
        for r by Newton's method (to 1e-15)."""
        uv = np.asarray(uv, dtype=float)
        cx, cy = self.principal
        xd, yd = (uv[:, 0] - cx) / self.f, (uv[:, 1] - cy) / self.f
        rd = np.hypot(xd, yd)
        r = rd.copy()
        for _ in range(30):
            g = r * (1.0 + self.k1 * r * r) - rd
            step = g / (1.0 + 3.0 * self.k1 * r * r)
            r -= step
            if np.all(np.abs(step) <= 1e-15 * (1.0 + rd)):
                break
        scale = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        return np.stack([xd * scale, yd * scale], axis=1)

    def rays(self, uv) -> np.ndarray:
        """Pixels (n, 2) -> unit ray directions in work coordinates (n, 3)."""
        xy = self.undistort(uv)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ self.R
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def on_plane(self, uv, Z: float = 0.0) -> np.ndarray:
        """Pixels (n, 2) -> where their rays meet the plane Z (work mm), (n, 3)."""
        d = self.rays(uv)
        O = self.centre
        s = (Z - O[2]) / d[:, 2]
        return O + s[:, None] * d

    def mm_per_px(self, Z: float = 0.0) -> float:
        """The scale at the image centre on the plane Z, mm per px."""
        c = np.array([self.principal])
        p = self.on_plane(np.vstack([c, c + [1.0, 0.0]]), Z)
        return float(np.linalg.norm(p[1] - p[0]))

    def to_json(self) -> dict:
        C = self.centre
        tilt = math.degrees(math.acos(min(1.0, abs(float(self.R[2, 2])))))
        return {"focal_px": self.f, "k1": self.k1, "centre_mm": [float(c) for c in C],
                "height_mm": float(C[2]), "tilt_deg": tilt, "image_size": [self.width, self.height]}


# ----------------------------------------------------------------------------
# calibration
# ----------------------------------------------------------------------------
@dataclass
class Calibration:
    """The fitted camera and how well it reproduces the markers' corners.

    ``rms_px`` / ``max_px``: the reprojection error of the 16 corners in the image;
    ``rms_mm``: the same corners' rays met with the top face against their true places;
    ``height_sigma_mm``: the standard deviation of the camera's height from the fit's
    covariance (scaled by the residual), a measure of how well f and the height separate."""

    camera: Camera
    rms_px: float
    max_px: float
    rms_mm: float
    height_sigma_mm: float
    height_prior: float | None
    corners_px: np.ndarray = field(repr=False)
    layout_corners: np.ndarray = field(repr=False, default=None)     # (4, 4, 3) work mm
    params: np.ndarray = field(repr=False, default=None)             # (log f, k1, rvec, tvec)
    cov: np.ndarray | None = field(repr=False, default=None)         # their covariance (8, 8)
    notes: list = field(default_factory=list)

    def to_json(self) -> dict:
        out = self.camera.to_json()
        out.update({"reprojection_rms_px": self.rms_px, "reprojection_max_px": self.max_px,
                    "reprojection_rms_mm": self.rms_mm, "height_sigma_mm": self.height_sigma_mm,
                    "camera_height_given_mm": self.height_prior})
        return out


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The 3x3 homography taking src (n, 2) to dst (n, 2), n >= 4 (DLT, normalized)."""
    def norm(p):
        m = p.mean(axis=0)
        s = math.sqrt(2) / max(np.sqrt(((p - m) ** 2).sum(axis=1)).mean(), 1e-300)
        return np.array([[s, 0, -s * m[0]], [0, s, -s * m[1]], [0, 0, 1]])
    Ts, Td = norm(src), norm(dst)
    a = np.c_[src, np.ones(len(src))] @ Ts.T
    b = np.c_[dst, np.ones(len(dst))] @ Td.T
    rows = []
    for (x, y, w), (u, v, z) in zip(a, b):
        rows.append([0, 0, 0, -z * x, -z * y, -z * w, v * x, v * y, v * w])
        rows.append([z * x, z * y, z * w, 0, 0, 0, -u * x, -u * y, -u * w])
    H = np.linalg.svd(np.asarray(rows))[2][-1].reshape(3, 3)
    return np.linalg.inv(Td) @ H @ Ts


def _apply_h(H, p):
    q = np.c_[p, np.ones(len(p))] @ H.T
    return q[:, :2] / q[:, 2:3]


def match_corners(detected: dict, layout: MarkerLayout) -> np.ndarray:
    """(4, 4, 2) px: the detected corners of markers 0-3 put in the layout's corner order.

    ``detected``: id -> (4, 2) px corners. The centres' homography predicts where each
    layout corner falls; each is matched to the nearest detected corner of its marker,
    so the marker's turn on the block does not matter."""
    centres_px = np.array([np.asarray(detected[i]).mean(axis=0) for i in MARKER_IDS])
    H = _homography(layout.centres, centres_px)
    want = _apply_h(H, layout.corners()[:, :, :2].reshape(-1, 2)).reshape(4, 4, 2)
    out = np.empty((4, 4, 2))
    for i in MARKER_IDS:
        c = np.asarray(detected[i], dtype=float)
        best = None
        for shift in range(4):              # the four turns of the marker
            cand = np.roll(c, -shift, axis=0)
            for order in (cand, cand[::-1]):
                e = float(np.sum((order - want[i]) ** 2))
                if best is None or e < best[0]:
                    best = (e, order)
        out[i] = best[1]
    return out


def _unpack(p, w, h):
    return Camera(f=float(math.exp(p[0])), k1=float(p[1]), rvec=np.array(p[2:5]), tvec=np.array(p[5:8]),
                  width=w, height=h)


def calibrate(corners_px: np.ndarray, layout: MarkerLayout, size: tuple[int, int],
              camera_height: float | None = None) -> Calibration:
    """Fit the camera to the markers' corners.

    ``corners_px``: (4, 4, 2) px in the layout's order (:func:`match_corners`);
    ``size``: (width, height) px; ``camera_height``: the measured height of the camera
    above the top face, mm, or None. The start: a planar pose (OpenCV's IPPE) for 40
    focal lengths from 0.2 to 20 image widths; the best is refined with all 8 unknowns
    (scipy's least squares, exact to its tolerance 1e-12)."""
    import cv2
    from scipy.optimize import least_squares

    w, h = size
    obj = layout.corners().reshape(-1, 3)
    img = np.asarray(corners_px, dtype=float).reshape(-1, 2)
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0

    def residuals(p):
        cam = _unpack(p, w, h)
        r = ((cam.project(obj) - img) / CORNER_SIGMA_PX).ravel()
        extra = []
        if camera_height is not None:
            extra.append((cam.centre[2] - camera_height) / HEIGHT_SIGMA_MM)
        else:   # weak priors, so that a camera looking straight down stays a camera
            extra.append(p[1] / K1_PRIOR)
            extra.append((p[0] - math.log(w)) / LOG_F_PRIOR)
        return np.concatenate([r, extra])

    best = None
    for f in np.geomspace(0.2 * w, 20 * w, 40):
        K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            continue
        p0 = np.r_[math.log(f), 0.0, rvec.ravel(), tvec.ravel()]
        cost = float(np.sum(residuals(p0) ** 2))
        if best is None or cost < best[0]:
            best = (cost, p0)
    if best is None:  # pragma: no cover (IPPE succeeds on any 4 non-collinear points)
        raise SpecError("the markers' corners give no camera pose")
    fit = least_squares(residuals, best[1], method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=4000)
    cam = _unpack(fit.x, w, h)
    if cam.centre[2] < 0:
        raise SpecError("the markers are seen from below the top face: check lab.markers")
    err = cam.project(obj) - img
    e = np.hypot(err[:, 0], err[:, 1])
    onplane = cam.on_plane(img, 0.0)
    e_mm = np.hypot(*(onplane[:, :2] - obj[:, :2]).T)
    # the height's standard deviation: the covariance of the fit, scaled by the measured corner noise
    J = fit.jac
    dof = max(1, J.shape[0] - J.shape[1])
    s2 = max(float(np.sum(fit.fun[:16 * 2] ** 2)) / dof, 1e-6)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
        eps = 1e-6
        g = np.zeros(8)
        for i in range(8):
            dp = np.zeros(8)
            dp[i] = eps
            g[i] = (_unpack(fit.x + dp, w, h).centre[2] - _unpack(fit.x - dp, w, h).centre[2]) / (2 * eps)
        hs = float(math.sqrt(max(g @ cov @ g, 0.0)))
    except np.linalg.LinAlgError:
        hs, cov = math.inf, None
    notes = []
    if camera_height is not None and abs(cam.centre[2] - camera_height) > 3 * HEIGHT_SIGMA_MM:
        notes.append(f"the fitted camera height {cam.centre[2]:.0f} mm is {cam.centre[2] - camera_height:+.0f} mm "
                     f"from lab.camera_height {camera_height:g} mm")
    return Calibration(camera=cam, rms_px=float(np.sqrt(np.mean(e * e))), max_px=float(e.max()),
                       rms_mm=float(np.sqrt(np.mean(e_mm * e_mm))), height_sigma_mm=hs,
                       height_prior=camera_height, corners_px=np.asarray(corners_px, dtype=float),
                       layout_corners=layout.corners(), params=np.asarray(fit.x, dtype=float), cov=cov,
                       notes=notes)


# ----------------------------------------------------------------------------
# the ray to the ball-centre offset surface
# ----------------------------------------------------------------------------
def _offset_point(surface, radius, x, y):
    """The centre C = P + r n (3, n) of a ball touching the clipped surface at (x, y), and
    dC/dx, dC/dy (3, n) each; design units. On the flat top face n = (0, 0, 1)."""
    h, hx, hy, hxx, hxy, hyy = (np.broadcast_to(np.asarray(a, dtype=float), np.shape(x)).copy()
                                for a in surface.derivatives(x, y))
    top = h >= surface.top
    h = np.where(top, surface.top, h)
    for a in (hx, hy, hxx, hxy, hyy):
        a[top] = 0.0
    w = np.sqrt(1.0 + hx * hx + hy * hy)
    m = np.stack([-hx, -hy, np.ones_like(hx)])
    n = m / w
    wx = (hx * hxx + hy * hxy) / w
    wy = (hx * hxy + hy * hyy) / w
    dmx = np.stack([-hxx, -hxy, np.zeros_like(hx)])
    dmy = np.stack([-hxy, -hyy, np.zeros_like(hx)])
    dnx = dmx / w - m * wx / (w * w)
    dny = dmy / w - m * wy / (w * w)
    one, zero = np.ones_like(hx), np.zeros_like(hx)
    C = np.stack([x, y, h]) + radius * n
    Cx = np.stack([one, zero, hx]) + radius * dnx
    Cy = np.stack([zero, one, hy]) + radius * dny
    return C, Cx, Cy


def _first_crossing(surface, radius, O, d):
    """A start for Newton's method on each ray: the first point Q along it (from the
    camera) where Q_Z - h(Q) <= r sqrt(1 + |grad h|^2) (a centre no higher than a ball
    on the local tangent plane), bracketed on levels r/4 apart from top + r down to the
    surface's lowest point and bisected; returns the contact point's estimate (x, y)
    and the ray parameter s. This picks the visible centre, the nearest to the camera."""
    xs, ys = np.meshgrid(np.linspace(*surface.x_range, 101), np.linspace(*surface.y_range, 101))
    low = float(np.nanmin(np.minimum(surface.height(xs, ys), surface.top)))
    z_hi, z_lo = surface.top + radius, low - radius

    def phi(sv):
        qx, qy, qz = O[0] + sv * d[:, 0], O[1] + sv * d[:, 1], O[2] + sv * d[:, 2]
        h, hx, hy = (np.broadcast_to(np.asarray(a, dtype=float), qx.shape) for a in
                     surface.derivatives(qx, qy)[:3])
        top = h >= surface.top
        h = np.where(top, surface.top, h)
        hx, hy = np.where(top, 0.0, hx), np.where(top, 0.0, hy)
        w = np.sqrt(1.0 + hx * hx + hy * hy)
        return qz - h - radius * w, qx, qy, hx / w, hy / w

    steps = int(min(4000, math.ceil((z_hi - z_lo) / (0.25 * radius))))
    s_hi = (z_hi - O[2]) / d[:, 2]
    s_lo = (z_lo - O[2]) / d[:, 2]
    a = s_hi.copy()
    b = np.full(len(d), np.nan)
    prev = s_hi.copy()
    for k in range(1, steps + 1):
        sv = s_hi + (s_lo - s_hi) * k / steps
        f = phi(sv)[0]
        new = np.isnan(b) & (f <= 0)
        b[new] = sv[new]
        a[new] = prev[new]
        prev = sv
        if not np.isnan(b).any():
            break
    b = np.where(np.isnan(b), s_lo, b)
    for _ in range(20):
        m = 0.5 * (a + b)
        f = phi(m)[0]
        a, b = np.where(f > 0, m, a), np.where(f > 0, b, m)
    _, qx, qy, gx, gy = phi(0.5 * (a + b))
    return qx + radius * gx, qy + radius * gy, 0.5 * (a + b)


def ray_offset_surface(surface, radius: float, origin, dirs, tol: float = 1e-9, start=None):
    """Where rays meet the ball-centre offset surface (see the module doc).

    ``origin`` (3,) and ``dirs`` (n, 3) in design units (the camera's centre and the
    rays' directions); ``radius`` the ball's radius in design units. Returns the centres
    (n, 3) and the contact points' (x, y) (n, 2), design units; rows that do not
    converge (a ray past the block) are nan. ``start``: (x, y, s) to begin Newton's
    method from (a neighbouring ray's solution) instead of the bracketing search."""
    O = np.asarray(origin, dtype=float)
    d = np.asarray(dirs, dtype=float)
    n = len(d)
    x, y, s = _first_crossing(surface, radius, O, d) if start is None else (np.array(a, dtype=float)
                                                                           for a in start)
    x0, x1 = surface.x_range
    y0, y1 = surface.y_range
    span = max(x1 - x0, y1 - y0)
    for _ in range(60):
        C, Cx, Cy = _offset_point(surface, radius, x, y)
        F = C - (O[:, None] + s[None, :] * d.T)
        J = np.stack([Cx, Cy, -d.T], axis=2).transpose(1, 0, 2)        # (n, 3, 3)
        with np.errstate(all="ignore"):
            step = np.linalg.solve(J, -F.T[:, :, None])[:, :, 0]
        bad = ~np.all(np.isfinite(step), axis=1)
        step[bad] = 0.0
        lim = 0.25 * span
        big = np.max(np.abs(step[:, :2]), axis=1)
        step *= np.minimum(1.0, lim / np.maximum(big, 1e-300))[:, None]
        x, y, s = x + step[:, 0], y + step[:, 1], s + step[:, 2]
        x, y = np.clip(x, x0, x1), np.clip(y, y0, y1)
        done = np.max(np.abs(F), axis=0) <= tol * max(1.0, span)
        if done.all():
            break
    C, _, _ = _offset_point(surface, radius, x, y)
    F = C - (O[:, None] + s[None, :] * d.T)
    ok = np.max(np.abs(F), axis=0) <= 1e3 * tol * max(1.0, span)
    Cc = C.T.copy()
    Cc[~ok] = np.nan
    P = np.stack([x, y], axis=1)
    P[~ok] = np.nan
    return Cc, P


def ball_centres(camera: Camera, surface, radius: float, uv, jacobian: bool = False):
    """Pixels (n, 2) of the ball's centre -> its centre (n, 3) in design units, on the
    offset surface (see :func:`ray_offset_surface`). With ``jacobian``, also d(x, y)/du
    and d(x, y)/dv (n, 2) each, design units per px (central differences of 0.25 px,
    each started from the centre's own solution)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    Ow = camera.centre
    O = np.array(surface.from_work(Ow[0], Ow[1], Ow[2]), dtype=float)

    def dirs(p):
        d = camera.rays(p)
        return d / np.linalg.norm(d, axis=1, keepdims=True)      # design units: the same direction

    C, P = ray_offset_surface(surface, radius, O, dirs(uv))
    if not jacobian:
        return C
    start = (P[:, 0], P[:, 1], np.linalg.norm(C - O, axis=1))
    J = []
    for du in ([0.25, 0.0], [0.0, 0.25]):
        Cp = ray_offset_surface(surface, radius, O, dirs(uv + du), start=start)[0]
        Cm = ray_offset_surface(surface, radius, O, dirs(uv - np.asarray(du)), start=start)[0]
        J.append((Cp[:, :2] - Cm[:, :2]) / 0.5)
    return C, J[0], J[1]


def calibration_covariance(cal: Calibration, surface, radius: float, uv, C, P) -> np.ndarray:
    """(n, 2, 2) design units^2: the covariance of the centres' (x, y) that the camera's
    uncertainty alone gives (the fit's covariance of its 8 unknowns, scaled by the corners'
    measured scatter, carried through the ray to the offset surface by central differences
    of half a standard deviation). Zero when the fit has no covariance. The error it
    describes is common to neighbouring frames, not independent from frame to frame."""
    n = len(uv)
    if cal.cov is None or n == 0:
        return np.zeros((n, 2, 2))
    cam0 = cal.camera
    start = (P[:, 0], P[:, 1], None)
    J = np.zeros((n, 2, 8))
    for i in range(8):
        h = 0.5 * math.sqrt(max(float(cal.cov[i, i]), 0.0))
        if not h > 0:
            continue
        out = []
        for sgn in (1.0, -1.0):
            p = cal.params.copy()
            p[i] += sgn * h
            cam = _unpack(p, cam0.width, cam0.height)
            Ow = cam.centre
            O = np.array(surface.from_work(Ow[0], Ow[1], Ow[2]), dtype=float)
            d = cam.rays(uv)
            s0 = np.linalg.norm(C - O, axis=1)
            out.append(ray_offset_surface(surface, radius, O, d, start=(start[0], start[1], s0))[0][:, :2])
        J[:, :, i] = (out[0] - out[1]) / (2 * h)
    J = np.nan_to_num(J)
    return np.einsum("nai,ij,nbj->nab", J, cal.cov, J)
