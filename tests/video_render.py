"""A small ray-casting renderer of the apparatus seen from above, for the tracking tests.

Nothing of fabkit is used: the surface is the paper's appendix surface written out
by hand (cm, like tests/lab_sim.py), the camera is its own pinhole with one radial
distortion term, and the ball's path comes from tests/lab_sim.py (the paper's eq.
(xyODE) integrated by scipy's DOP853), its centre put at C = P + r n above the
contact point P.

The scene: the block's top face (Z = 0, work mm, origin at the footprint's corner of
smallest x and y), the milled surface min(h, top) shaded by a Lambertian light, ArUco
markers (OpenCV's DICT_4X4_50, ids 0-3, printed with a one-module white quiet zone)
lying on the top face, the floor around the block, and a dark ball with a specular
highlight, blurred over the exposure (5 sub-frames over half the frame interval,
centred on the frame's time). Each pixel is the mean of 2 x 2 rays; sensor noise
(Gaussian, 1.5 grey levels) is added and the frames are encoded lossily (H.264,
crf 18, or MPEG-4 part 2) with PyAV at the given presentation times (a variable frame
rate when those are uneven).

Lamps (``Renderer(..., lamps=[Lamp(...)])``): point or disc lamps at given places
(work mm) with an ambient share; each surface point's light from a lamp falls off as
1/distance^2 (uneven light) times the cosine, and is multiplied by the share of the
lamp's disc the ball leaves visible from that point (the angular overlap of the lamp's
disc and the ball's disc seen from the point: a penumbra for a wide lamp, a hard edge
for a point lamp). The ball is shaded and has a highlight from each lamp. A hand
(``render_video(..., hand=...)``) is a skin-grey disc over the image in given frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

import lab_sim

SCALE = 10.0                       # mm per cm
X_RANGE, Y_RANGE, TOP = (-44.0, 6.0), (-12.5, 12.5), 5.0
L, W = (X_RANGE[1] - X_RANGE[0]) * SCALE, (Y_RANGE[1] - Y_RANGE[0]) * SCALE
RADIUS = 1.25                      # cm, the ball (diameter 2.5)
LIGHT = np.array([0.35, 0.25, 1.0]) / np.linalg.norm([0.35, 0.25, 1.0])


@dataclass
class Lamp:
    """A lamp: its centre (work mm), the radius of its disc (mm; 0: a point, a hard
    shadow) and its power (the irradiance, relative, it gives at the block's centre
    facing it)."""

    position: tuple
    radius: float = 0.0
    power: float = 0.75

    @classmethod
    def at(cls, elevation_deg, azimuth_deg, distance, radius=0.0, power=0.75):
        """A lamp ``distance`` mm from the block's centre, ``elevation_deg`` above the top
        face's plane, toward ``azimuth_deg`` (from +X toward +Y)."""
        e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
        c = np.array([L / 2, W / 2, 0.0])
        return cls(tuple(c + distance * np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a),
                                                   math.sin(e)])), radius, power)


def disc_overlap(a, b, d):
    """The area of the overlap of two discs of radii a, b with centres d apart (arrays)."""
    a, b, d = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float), np.asarray(d, float))
    out = np.zeros(a.shape)
    inside = d <= np.abs(a - b)
    out[inside] = np.pi * np.minimum(a, b)[inside] ** 2
    part = ~inside & (d < a + b)
    A, B, D = a[part], b[part], d[part]
    with np.errstate(all="ignore"):
        t1 = A * A * np.arccos(np.clip((D * D + A * A - B * B) / (2 * D * A), -1, 1))
        t2 = B * B * np.arccos(np.clip((D * D + B * B - A * A) / (2 * D * B), -1, 1))
        t3 = 0.5 * np.sqrt(np.maximum((-D + A + B) * (D + A - B) * (D - A + B) * (D + A + B), 0))
    out[part] = t1 + t2 - t3
    return out


def lamp_visible(P, C, lamp: Lamp, r):
    """The share (n,) of ``lamp``'s disc seen from surface points P (n, 3) past a ball of
    radius r centred at C (3,), all work mm (angles on the unit sphere, small-angle discs)."""
    Lp = np.asarray(lamp.position, float)
    v = Lp - P
    dl = np.linalg.norm(v, axis=1)
    w = C - P
    dc = np.linalg.norm(w, axis=1)
    aB = np.arcsin(np.clip(r / np.maximum(dc, 1e-9), 0, 1))
    cosang = np.sum(v * w, axis=1) / np.maximum(dl * dc, 1e-12)
    th = np.arccos(np.clip(cosang, -1, 1))
    if lamp.radius <= 0:
        return np.where(th < aB, 0.0, 1.0)
    aL = np.arcsin(np.clip(lamp.radius / dl, 0, 1))
    return 1.0 - disc_overlap(aL, aB, th) / (np.pi * aL * aL)

SPEC_TEXT = """\
name: paper
units: cm
surface:
  height: eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x)
  params: {a: 0.389, b: 0.306, c: 0.0764, d: 0.306, eta: 3.27, eps: 0.25}
  x: [-44, 6]
  y: [-12.5, 12.5]
  top: 5.0
ball:
  diameter: 2.5
simulation:
  model: full
  damping: 0.127
  start: -30
"""


def h_design(x, y):
    """The paper's surface and its gradient, cm (hand-written, independent of fabkit)."""
    p = lab_sim.P
    ea, eb, ed = np.exp(p["a"] * x), np.exp(p["b"] * x), np.exp(p["d"] * x)
    h = p["eta"] * (ea - eb) + p["c"] * y * y + p["eps"] * y * ed
    hx = p["eta"] * (p["a"] * ea - p["b"] * eb) + p["eps"] * p["d"] * y * ed
    hy = 2 * p["c"] * y + p["eps"] * ed
    return h, hx, hy


def surface_work(X, Y):
    """Work mm: the clipped surface's Z and its unit normal (3, ...)."""
    x, y = X / SCALE + X_RANGE[0], Y / SCALE + Y_RANGE[0]
    h, hx, hy = h_design(x, y)
    cut = h < TOP
    Z = np.where(cut, (h - TOP) * SCALE, 0.0)
    hx, hy = np.where(cut, hx, 0.0), np.where(cut, hy, 0.0)
    w = np.sqrt(1 + hx * hx + hy * hy)
    return Z, np.stack([-hx / w, -hy / w, 1 / w])


def centre_work(x, y):
    """The ball's centre (3, n) in work mm for contact points (x, y) in cm."""
    h, hx, hy = h_design(x, y)
    w = np.sqrt(1 + hx * hx + hy * hy)
    C = np.stack([x - hx / w * RADIUS, y - hy / w * RADIUS, h + RADIUS / w])
    return np.stack([(C[0] - X_RANGE[0]) * SCALE, (C[1] - Y_RANGE[0]) * SCALE, (C[2] - TOP) * SCALE])


#: marker centres (work mm) on the paper's block where its top face is flat (the default
#: corner (L, 0) lies over the channel's rising end)
MARKERS = [[20.0, 20.0], [330.0, 20.0], [480.0, 230.0], [20.0, 230.0]]


def default_markers(size=30.0):
    return np.array(MARKERS, dtype=float)


@dataclass
class Cam:
    """Pinhole camera: centre C (mm), rotation R (world -> camera rows), f px, k1, size."""

    C: np.ndarray
    R: np.ndarray
    f: float
    k1: float
    w: int
    h: int

    @classmethod
    def looking_down(cls, height, tilt_deg, azimuth_deg, f, k1, w, h, target=None, roll_deg=0.0):
        T = np.array([L / 2, W / 2, -20.0]) if target is None else np.asarray(target, float)
        a = math.radians(azimuth_deg)
        off = (height - T[2]) * math.tan(math.radians(tilt_deg))
        C = np.array([T[0] + off * math.cos(a), T[1] + off * math.sin(a), height])
        z = (T - C) / np.linalg.norm(T - C)
        x = np.array([1.0, 0.0, 0.0]) - z[0] * z
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        rr = math.radians(roll_deg)
        x, y = math.cos(rr) * x + math.sin(rr) * y, -math.sin(rr) * x + math.cos(rr) * y
        return cls(C, np.stack([x, y, z]), f, k1, w, h)

    def project(self, X):
        p = (np.asarray(X, float) - self.C) @ self.R.T
        x, y = p[..., 0] / p[..., 2], p[..., 1] / p[..., 2]
        d = 1 + self.k1 * (x * x + y * y)
        return np.stack([self.f * d * x + (self.w - 1) / 2, self.f * d * y + (self.h - 1) / 2], axis=-1)

    def rays(self, u, v):
        """Unit world directions (n, 3) of pixels (u, v) (index coordinates)."""
        xd, yd = (u - (self.w - 1) / 2) / self.f, (v - (self.h - 1) / 2) / self.f
        rd = np.hypot(xd, yd)
        r = rd.copy()
        for _ in range(50):            # r (1 + k1 r^2) = rd, by Newton
            r = r - (r + self.k1 * r ** 3 - rd) / (1 + 3 * self.k1 * r * r)
        s = np.where(rd > 0, r / np.maximum(rd, 1e-300), 1.0)
        d = np.stack([xd * s, yd * s, np.ones_like(xd)], axis=-1) @ self.R
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


def marker_texture(X, Y, centres, size):
    """Reflectance at top-face points of the printed markers (nan outside the paper)."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    out = np.full(X.shape, np.nan)
    m = size / 6
    for i, (cx, cy) in enumerate(centres):
        bits = cv2.aruco.generateImageMarker(d, i, 6) > 127          # 6 x 6 modules, True = white
        a = (X - (cx - size / 2)) / m                                   # modules to the right
        b = ((cy + size / 2) - Y) / m                                   # modules down from the top edge
        paper = (a >= -1) & (a < 7) & (b >= -1) & (b < 7)
        inside = (a >= 0) & (a < 6) & (b >= 0) & (b < 6)
        val = np.full(X.shape, 0.92)
        ia, ib = np.clip(a.astype(int), 0, 5), np.clip(b.astype(int), 0, 5)
        val = np.where(inside, np.where(bits[ib, ia], 0.92, 0.08), val)
        out = np.where(paper, val, out)
    return out


def shade(n):
    return 0.25 + 0.75 * np.clip(n @ LIGHT if n.ndim == 2 and n.shape[-1] == 3 else 0, 0, 1)


class Renderer:
    """Renders frames of the scene for one camera; the static part (block, surface,
    markers) is cast once per sub-pixel ray, the ball per frame near its image."""

    SS = 2   # rays per pixel along each axis

    def __init__(self, cam: Cam, markers=None, marker_size=30.0, ball_dark=True, albedo=1.0, lamps=None,
                 ambient=0.25, ball_grey=None):
        """``ball_dark``: a dark ball (else a white one); ``albedo``: the block's
        reflectance (1: white foam; a white ball wants a darker block, e.g. 0.5);
        ``lamps``: a list of :class:`Lamp` (cast shadows; None: the fixed distant light
        LIGHT, no shadow) with ``ambient`` the light that reaches everywhere;
        ``ball_grey``: the ball's reflectance (default 0.12 dark, 0.85 white)."""
        self.cam = cam
        self.albedo = albedo
        self.lamps = list(lamps) if lamps else []
        self.ambient = ambient
        self.ball_grey = ball_grey
        self.markers = default_markers(marker_size) if markers is None else np.asarray(markers, float)
        self.marker_size = marker_size
        self.ball_dark = ball_dark
        ss = self.SS
        off = (np.arange(ss) + 0.5) / ss - 0.5
        v, u = np.mgrid[0:cam.h, 0:cam.w]
        U = (u[:, :, None, None] + off[None, None, None, :]).astype(float)
        V = (v[:, :, None, None] + off[None, None, :, None]).astype(float)
        U, V = np.broadcast_arrays(U, V)
        self.U, self.V = U.reshape(-1), V.reshape(-1)
        self.depth, self.radiance = self._static(self.U, self.V)
        if self.lamps:
            self._lamp_light()
        self.static_img = self.radiance.reshape(cam.h, cam.w, ss * ss).mean(axis=2)

    def _static(self, U, V):
        cam = self.cam
        d = cam.rays(U, V)
        O = cam.C
        s0 = -O[2] / d[:, 2]
        X, Y = O[0] + s0 * d[:, 0], O[1] + s0 * d[:, 1]
        rad = np.full(len(U), 0.35)                    # the floor (and the block's sides)
        self.rho = np.zeros(len(U), np.float32)        # the block's reflectance (0: the floor)
        self.nrm = np.zeros((len(U), 3), np.float32)
        self.nrm[:, 2] = 1.0
        depth = np.full(len(U), np.inf)
        inside = (X >= 0) & (X <= L) & (Y >= 0) & (Y <= W)
        Z, n = surface_work(np.clip(X, 0, L), np.clip(Y, 0, W))
        top = inside & (Z >= 0)
        rad[top] = self.albedo * (0.25 + 0.75 * LIGHT[2])
        depth[top] = s0[top]
        tex = marker_texture(X[top], Y[top], self.markers, self.marker_size)
        r_top = rad[top]
        r_top[~np.isnan(tex)] = (0.25 + 0.75 * LIGHT[2]) * tex[~np.isnan(tex)] / 0.92
        rad[top] = r_top
        rho_top = np.full(int(top.sum()), float(self.albedo))
        rho_top[~np.isnan(tex)] = tex[~np.isnan(tex)] / 0.92
        self.rho[top] = rho_top
        # rays into the cavity: march down in 1.5 mm steps of height, then bisect
        idx = np.flatnonzero(inside & (Z < 0))
        s_lo = s0[idx].copy()
        hit = np.zeros(len(idx), bool)
        s_hi = np.full(len(idx), np.nan)
        active = np.ones(len(idx), bool)
        step = 1.5 / np.abs(d[idx, 2])
        for _ in range(400):
            a = np.flatnonzero(active)
            if a.size == 0:
                break
            s = s_lo[a] + step[a]
            Xs = O[0] + s * d[idx[a], 0]
            Ys = O[1] + s * d[idx[a], 1]
            Zr = O[2] + s * d[idx[a], 2]
            out = (Xs < 0) | (Xs > L) | (Ys < 0) | (Ys > W) | (Zr < -200)
            Zs, _ = surface_work(np.clip(Xs, 0, L), np.clip(Ys, 0, W))
            below = (Zr <= Zs) & ~out
            hit[a[below]] = True
            s_hi[a[below]] = s[below]
            active[a[below | out]] = False
            s_lo[a[~below & ~out]] = s[~below & ~out]
        k = np.flatnonzero(hit)
        lo, hi = s_lo[k], s_hi[k]
        ii = idx[k]
        for _ in range(40):
            m = 0.5 * (lo + hi)
            Xs, Ys, Zr = (O[j] + m * d[ii, j] for j in range(3))
            Zs, _ = surface_work(Xs, Ys)
            b = Zr <= Zs
            hi, lo = np.where(b, m, hi), np.where(b, lo, m)
        m = 0.5 * (lo + hi)
        Xs, Ys = O[0] + m * d[ii, 0], O[1] + m * d[ii, 1]
        _, n = surface_work(Xs, Ys)
        rad[ii] = self.albedo * (0.25 + 0.75 * np.clip(n.T @ LIGHT, 0, 1))
        depth[ii] = m
        self.rho[ii] = self.albedo
        self.nrm[ii] = n.T
        return depth, rad

    def _lamp_light(self):
        """With lamps: each ray's point (work mm), its light from each lamp unshadowed
        (E, n x lamps) and the static image lit so."""
        d = self.cam.rays(self.U, self.V)
        block = np.isfinite(self.depth)
        self.P = np.zeros((len(self.U), 3), np.float32)
        self.P[block] = (self.cam.C + self.depth[block, None] * d[block]).astype(np.float32)
        centre = np.array([L / 2, W / 2, 0.0])
        self.E = np.zeros((len(self.U), len(self.lamps)), np.float32)
        for i, lp in enumerate(self.lamps):
            Lp = np.asarray(lp.position, float)
            v = Lp - self.P[block]
            dl = np.linalg.norm(v, axis=1)
            cosn = np.clip(np.sum(self.nrm[block] * v, axis=1) / dl, 0, 1)
            self.E[block, i] = lp.power * cosn * (np.linalg.norm(Lp - centre) / dl) ** 2
        lit = self.rho * (self.ambient + self.E.sum(axis=1))
        self.radiance = np.where(block, lit, self.radiance)
        self.static_img = self.radiance.reshape(self.cam.h, self.cam.w, self.SS * self.SS).mean(axis=2)

    def frame(self, centres):
        """One grey frame (h, w) float in [0, 1]: the ball at each of ``centres`` (k, 3)
        work mm (sub-frames of the exposure) averaged; None entries: no ball."""
        cam = self.cam
        img = self.static_img.copy()
        pts = [c for c in centres if c is not None]
        if not pts:
            return img
        P = np.array(pts)
        uv = cam.project(P)
        rpx = cam.f * RADIUS * SCALE / np.linalg.norm(P - cam.C, axis=1).min() * 1.3 + 4
        r = RADIUS * SCALE
        for lp in self.lamps:                # the shadows' reach: along the lamp's rays past the ball
            Lp = np.asarray(lp.position, float)
            for c in P:
                e = (c - Lp) / np.linalg.norm(c - Lp)
                reach = (r + 60.0) / max(-e[2], 0.05)
                pen = lp.radius * reach / np.linalg.norm(c - Lp)
                S = c[None, :] + np.linspace(0, reach, 8)[:, None] * e[None, :]
                uvs = cam.project(S)
                grow = (r + pen) * cam.f / np.linalg.norm(c - cam.C) * 1.3 + 4
                uv = np.vstack([uv, uvs - grow, uvs + grow])
        u0 = int(max(0, math.floor(uv[:, 0].min() - rpx)))
        u1 = int(min(cam.w, math.ceil(uv[:, 0].max() + rpx) + 1))
        v0 = int(max(0, math.floor(uv[:, 1].min() - rpx)))
        v1 = int(min(cam.h, math.ceil(uv[:, 1].max() + rpx) + 1))
        if u0 >= u1 or v0 >= v1:
            return img
        ss2 = self.SS * self.SS
        rows = np.arange(v0, v1)[:, None] * cam.w + np.arange(u0, u1)[None, :]
        sub = (rows.reshape(-1)[:, None] * ss2 + np.arange(ss2)[None, :]).reshape(-1)
        d = cam.rays(self.U[sub], self.V[sub])
        acc = np.zeros(len(sub))
        r = RADIUS * SCALE
        for c in centres:
            rad = self.radiance[sub].copy()
            if c is not None and self.lamps:       # the ball's shadow on the surface
                Ps = self.P[sub].astype(float)
                irr = np.full(len(sub), self.ambient)
                for i, lp in enumerate(self.lamps):
                    irr += self.E[sub, i] * lamp_visible(Ps, c, lp, r)
                block = np.isfinite(self.depth[sub])
                rad = np.where(block, self.rho[sub] * irr, rad)
            if c is not None:
                oc = cam.C - c
                b = d @ oc
                disc = b * b - (oc @ oc - r * r)
                s = -b - np.sqrt(np.maximum(disc, 0))
                hit = (disc > 0) & (s > 0) & (s < self.depth[sub])
                p = cam.C + s[hit, None] * d[hit]
                n = (p - c) / r
                lam = np.clip(n @ LIGHT, 0, 1)
                hv = LIGHT - d[hit]
                hv /= np.linalg.norm(hv, axis=1, keepdims=True)
                spec = np.clip(np.sum(n * hv, axis=1), 0, 1) ** 60
                if self.lamps:
                    grey = self.ball_grey if self.ball_grey is not None else (0.12 if self.ball_dark else 0.85)
                    irr = np.full(int(hit.sum()), self.ambient)
                    spec = np.zeros(int(hit.sum()))
                    centre = np.array([L / 2, W / 2, 0.0])
                    for lp in self.lamps:
                        Lp = np.asarray(lp.position, float)
                        lv = Lp - p
                        dl = np.linalg.norm(lv, axis=1)
                        lv /= dl[:, None]
                        fall = (np.linalg.norm(Lp - centre) / dl) ** 2
                        irr += lp.power * fall * np.clip(np.sum(n * lv, axis=1), 0, 1)
                        hv = lv - d[hit]
                        hv /= np.linalg.norm(hv, axis=1, keepdims=True)
                        spec += lp.power * fall * np.clip(np.sum(n * hv, axis=1), 0, 1) ** 60
                    rad[hit] = np.minimum(1.0, grey * irr + 0.9 * spec)
                else:
                    base = (0.05 + 0.12 * lam) if self.ball_dark else (0.7 + 0.3 * lam)
                    rad[hit] = np.minimum(1.0, base + 0.9 * spec)
            acc += rad
        acc /= len(centres)
        img[v0:v1, u0:u1] = acc.reshape(v1 - v0, u1 - u0, ss2).mean(axis=2)
        return img


@dataclass
class Launch:
    """An independently simulated launch (tests/lab_sim.py): contact point (x, y) in cm
    as dense functions of t, from entry at x = -30 cm with speed ``v_in`` cm/s."""

    v_in: float
    vy0: float = 0.0
    mu: float = 0.127
    t_max: float = 6.0
    truth: dict = field(init=False)

    def __post_init__(self):
        self.truth = lab_sim.run((lab_sim.START, 0.0, self.v_in, self.vy0), self.mu, self.t_max)

    def centre(self, t):
        """The ball's centre (n, 3), work mm, at times t (s); nan after the run ended."""
        t = np.atleast_1d(np.asarray(t, float))
        tt = np.clip(t, 0, self.truth["t_end"])
        x, y = self.truth["sol"].sol(tt)[:2]
        C = centre_work(x, y).T
        C[t > self.truth["t_end"]] = np.nan
        return C


class Trajectory:
    """Any dense run of tests/lab_sim.py (``lab_sim.run``'s dict: a launch with a scatter
    in y and vy, rolling resistance, or a release from rest) in ``render_video``'s place
    of a ``Launch``: the ball's centre (n, 3), work mm, at times t (s); nan after the run
    ended."""

    def __init__(self, truth: dict):
        self.truth = truth

    def centre(self, t):
        return Launch.centre(self, t)


def render_video(path, rend: Renderer, launch: Launch, times, *, codec="libx264", crf=18, noise=1.5, seed=0,
                 exposure=0.5, hide=(), t_offset=0.0, gop=None, hand=None, report=None):
    """Render and encode a video with ``rend`` (its camera and scene): frames at
    presentation ``times`` (s, increasing), the ball at launch time t + ``t_offset``;
    ``hide``: frame indices without the ball (taken away: a gap). Returns the frames'
    times (s, as encoded: on the time base's grid) and the true centres (n, 3) work mm
    at those times (nan: no ball).

    ``hand``: {frame index: (u, v, radius px)}, a skin-grey disc (0.55, a little
    texture) drawn over the image in those frames; ``report``: a dict filled with
    ``covered`` (n,), the share of the ball's disc (its true centre's projection and
    radius) the hand covers in each frame."""
    import av

    cam = rend.cam
    rng = np.random.default_rng(seed)
    times = np.asarray(times, float)
    dt = float(np.median(np.diff(times))) if len(times) > 1 else 0.01
    tb = Fraction(1, 90000 if codec == "libx264" else 60000)   # MPEG-4 part 2: a denominator < 2^16
    times = np.round(times / float(tb)) * float(tb)          # each frame's time exactly its timestamp
    out = av.open(str(path), "w")
    if codec == "libx264":
        st = out.add_stream("libx264", rate=max(1, round(1 / dt)))
        st.options = {"crf": str(crf), "preset": "veryfast", "bf": "0"}
    else:
        st = out.add_stream(codec, rate=max(1, round(1 / dt)))
        st.bit_rate = 6_000_000
    st.width, st.height, st.pix_fmt = cam.w, cam.h, "yuv420p"
    if gop is not None:
        st.codec_context.gop_size = int(gop)          # a key frame every gop frames
    st.time_base = tb
    st.codec_context.time_base = tb
    truth = np.full((len(times), 3), np.nan)
    covered = np.zeros(len(times))
    for i, t in enumerate(times):
        tl = t + t_offset
        if i in hide:
            centres = [None]
        else:
            sub = tl + exposure * dt * (np.arange(5) / 4 - 0.5)
            C = launch.centre(sub)
            centres = [None if np.isnan(c).any() else c for c in C]
            truth[i] = launch.centre(tl)[0]
        img = rend.frame(centres)
        if hand is not None and i in hand:
            hu, hv, hr = hand[i]
            yy, xx = np.mgrid[0:cam.h, 0:cam.w]
            inside = np.hypot(xx - hu, yy - hv) <= hr
            img[inside] = 0.55 + 0.04 * np.sin(0.7 * xx[inside]) * np.cos(0.5 * yy[inside])
            if np.isfinite(truth[i]).all():
                cu, cv_ = cam.project(truth[i])
                rb = cam.f * RADIUS * SCALE / np.linalg.norm(truth[i] - cam.C)
                pts = np.mgrid[-1:1:41j, -1:1:41j].reshape(2, -1)
                pts = pts[:, np.hypot(*pts) <= 1]
                covered[i] = np.mean(np.hypot(cu + rb * pts[0] - hu, cv_ + rb * pts[1] - hv) <= hr)
        img = np.clip(img * 255 + rng.normal(0, noise, img.shape), 0, 255).astype(np.uint8)
        yuv = np.concatenate([img, np.full((cam.h // 2, cam.w), 128, np.uint8)], axis=0)
        fr = av.VideoFrame.from_ndarray(yuv, format="yuv420p")
        fr.pts = int(round(t / tb))
        fr.time_base = tb
        for pkt in st.encode(fr):
            out.mux(pkt)
    for pkt in st.encode():
        out.mux(pkt)
    out.close()
    if report is not None:
        report["covered"] = covered
    return times, truth
