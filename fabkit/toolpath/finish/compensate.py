"""Exact ball-end compensation (drop cutter) against the analytic clipped surface.

For a ball-end tool of radius R whose axis stands at (X, Y) (work mm), the tip
height is the lowest z at which the ball touches no material::

    Z(X, Y) = max over p in D(c, R) ∩ F of [ zc(p) + sqrt(R^2 - |p - c|^2) ] - R

with zc = min(H, 0) the clipped design surface in work mm (H = scale * (h - top)),
D the tool's disk and F = [0, L] x [0, W] the stock footprint (outside it there
is no material). The maximum is found EXACTLY, not sampled, from its candidate
points, every one of which is a feasible point (so each is a lower bound, and the
largest is the maximum once the true maximiser is among them):

(i)   interior stationary points on the smooth part: grad H(p) = (p - c) / sqrt(R^2 - |p - c|^2),
      solved by Newton with the exact Hessian, started from the best points of a
      small polar sample of the disk (several starts: concave regions tighter than
      the tool have several local maxima);
(i')  the same from the samples and points of the disk's rim whose tangent plane holds
      the ball highest (a wall's foot beside a floor: the floor's samples are the best,
      the wall's contact lies between the rings or beyond them; see _wall_starts);
(ii)  the flat top (H >= 0): value sqrt(R^2 - dmin^2), dmin = distance from c to the
      top region: 0 if c is in it, else the nearest point of the crease H = 0
      (Lagrange conditions p - c = lambda grad H, H = 0, solved by Newton from several
      seeds, where a sample is near the top or the tangent plane at the highest sample
      reaches it inside the disk: see _candidates);
(iii) the footprint edges where the tool overhangs the stock: 1-D stationary points
      of the smooth part, the flat part and the crease crossings on each edge;
(iv)  the footprint corners;
(v)   a ridge, where the formula has a convex kink (``-abs``, ``min``): no Newton
      converges there (the maximum sits on the kink, where grad H jumps); where no
      start converged, the kink's direction is read from F on a small circle around
      the best point (F peaks where the circle crosses the ridge) and F is maximised
      over a rectangle along the ridge: a golden section along it (F smooth there) of
      the maxima across it (a corner on the kink: the tangents of both sides meet there).

Newton converges quadratically; results are exact to ~1e-9 mm (far below any
machining tolerance). Every step is vectorized over all positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import functools
import math

import numpy as np

# contact kinds reported in CompensationInfo.kind
NONE, SAMPLE, INTERIOR, TOP, CREASE, EDGE, RIDGE = -1, 0, 1, 2, 3, 4, 5
# a crease point found from the extra seeds (the quadrants' highest samples) replaces the
# best only when higher by more than this (mm, the drop cutter's accuracy): the same
# maximum found again from another seed differs in its last bits, or is a tie elsewhere,
# and would move the program by nothing but those bits
SEED_MARGIN = 1e-9
# Newton stops when its steps are below this (mm). At a stationary point the value
# error is second order in the point error (~1e-20 mm); on the crease and edges
# it is first order with a slope <= 1 near the maximum: well below 1e-9 mm.
XTOL = 1e-10


@dataclass
class CompensationInfo:
    """Where the maximum was attained, per position (shapes as the input X).

    contact_x, contact_y: work mm, the contact point (nan where the tool touches no material)
    kind:    int8, NONE | SAMPLE | INTERIOR | TOP | CREASE | EDGE | RIDGE
    bridged: bool, the ball spans a concave region tighter than itself (two or
             more distinct local maxima of the contact problem)
    """

    contact_x: np.ndarray
    contact_y: np.ndarray
    kind: np.ndarray
    bridged: np.ndarray


CHUNK = 16384      # points per vectorized step on large arrays (surface code, Newton)


class WorkSurface:
    """The clipped surface in work mm: H(X, Y) = scale * (h(x, y) - top), with exact
    derivatives (dH/dX = h_x, d2H/dX2 = h_xx / scale)."""

    def __init__(self, surface):
        self.surface = surface
        self.s = float(surface.scale)
        self.x0 = surface.x_range[0]
        self.y0 = surface.y_range[0]
        self.top = surface.top
        self.L, self.W = surface.stock_size_mm
        # the generated functions themselves (fabkit.expr), called directly on float
        # arrays of one shape: the planner evaluates the surface ~100 times per
        # compensation call, mostly on a few hundred points, where the checks of the
        # general wrappers cost more than the arithmetic. Same arithmetic, same values.
        fns = getattr(surface, "fns", None)
        self._raw_h = getattr(fns, "raw_h", None)
        self._raw_all = getattr(fns, "raw_all", None)
        self._kernel = False            # resolved on first use (kernels.kernel_for)

    def kernel(self):
        """The compiled drop cutter of this surface's formula (:mod:`.kernels`), or None."""
        if self._kernel is False:
            from .kernels import kernel_for

            self._kernel = kernel_for(self.surface)
        return self._kernel

    def _xy(self, X, Y):
        return X / self.s + self.x0, Y / self.s + self.y0

    @staticmethod
    def _plain(X, Y):
        return (type(X) is np.ndarray and type(Y) is np.ndarray and X.shape == Y.shape
                and X.dtype == np.float64 and Y.dtype == np.float64)

    def H(self, X, Y):
        """Unclipped height above the top face, mm (negative where cut)."""
        with np.errstate(all="ignore"):
            if self._raw_h is not None and self._plain(X, Y):
                if X.size > 2 * CHUNK:
                    return self._chunked(self._H, X, Y, 1)[0]
                return self._H(X, Y)[0]
            return self.s * (self.surface.height(*self._xy(X, Y)) - self.top)

    def _H(self, X, Y):
        s = self.s
        h = self._raw_h(X / s + self.x0, Y / s + self.y0)[0]
        if type(h) is not np.ndarray or h.shape != X.shape or h.dtype != np.float64:
            h = np.broadcast_to(np.asarray(h, dtype=float), X.shape)
        return [s * (h - self.top)]

    def _all(self, X, Y):
        s = self.s
        shape = X.shape
        out = self._raw_all(X / s + self.x0, Y / s + self.y0)
        for i, v in enumerate(out):
            if type(v) is not np.ndarray or v.shape != shape or v.dtype != np.float64:
                out[i] = np.broadcast_to(np.asarray(v, dtype=float), shape)
        h, hx, hy, hxx, hxy, hyy = out
        return [s * (h - self.top), hx, hy, hxx / s, hxy / s, hyy / s]

    @staticmethod
    def _chunked(fn, X, Y, k):
        """fn on CHUNK points at a time (the temporaries of the generated code stay in
        the cache: twice as fast on large arrays, the same values)."""
        x, y = X.reshape(-1), Y.reshape(-1)
        outs = [np.empty(x.size) for _ in range(k)]
        for i in range(0, x.size, CHUNK):
            for o, v in zip(outs, fn(x[i:i + CHUNK], y[i:i + CHUNK])):
                o[i:i + CHUNK] = v
        return [o.reshape(X.shape) for o in outs]

    def all(self, X, Y):
        """(H, H_X, H_Y, H_XX, H_XY, H_YY), exact."""
        with np.errstate(all="ignore"):
            s = self.s
            shape = np.shape(X)
            if self._raw_all is not None and self._plain(X, Y):
                if X.size > 2 * CHUNK:
                    return self._chunked(self._all, X, Y, 6)
                return self._all(X, Y)
            h, hx, hy, hxx, hxy, hyy = self.surface.derivatives(*self._xy(X, Y))
            out = [s * (h - self.top), hx, hy, hxx / s, hxy / s, hyy / s]
            return [v if np.shape(v) == shape else np.broadcast_to(np.asarray(v, dtype=float), shape)
                    for v in out]

    def inside(self, X, Y):
        return (X >= 0.0) & (X <= self.L) & (Y >= 0.0) & (Y <= self.W)


RING_SLOPES = (0.5, 1.5, 4.0, 12.0)


@functools.lru_cache(maxsize=8)
def _polar(R: float, rings=RING_SLOPES, angles: int = 12) -> np.ndarray:
    """(K, 2) offsets: the centre and one ring of ``angles`` points (staggered) per
    surface slope in ``rings``: the ring where the ball touches a plane of that slope,
    radius R w / sqrt(1 + w^2). Steep contacts lie in a thin band at the disk's rim
    (slope 8: beyond 0.99 R), which rings evenly spaced in radius would miss."""
    pts = [(0.0, 0.0)]
    for j, w in enumerate(rings, start=1):
        r = R * w / math.sqrt(1.0 + w * w)
        ph = np.pi * j / angles + 2 * np.pi * np.arange(angles) / angles
        pts.extend(zip(r * np.cos(ph), r * np.sin(ph)))
    out = np.array(pts)
    out.flags.writeable = False         # cached: shared by every call
    return out


class _Best:
    """Running maximum of F = zc + sqrt(R^2 - d^2) over candidates, per position."""

    def __init__(self, n):
        self.val = np.full(n, -np.inf)
        self.px = np.full(n, np.nan)
        self.py = np.full(n, np.nan)
        self.kind = np.full(n, NONE, dtype=np.int8)

    def offer(self, idx, val, px, py, kind, unique=True):
        """Candidates ``val`` (m,) or (m, k) at points (px, py) for positions ``idx`` (m,).
        ``unique``: no position appears twice in ``idx`` (else a sort groups them)."""
        val = np.where(np.isfinite(val), val, -np.inf)
        if not unique:
            order = np.lexsort((-val, idx))
            idx, val, px, py = idx[order], val[order], px[order], py[order]
            first = np.r_[True, idx[1:] != idx[:-1]]
            idx, val, px, py = idx[first], val[first], px[first], py[first]
        if val.ndim == 2:
            j = np.argmax(val, axis=1)
            r = np.arange(len(idx))
            val, px, py = val[r, j], px[r, j], py[r, j]
        better = val > self.val[idx]
        i = idx[better]
        self.val[i] = val[better]
        self.px[i] = px[better]
        self.py[i] = py[better]
        self.kind[i] = kind


def _top(F, k):
    """Column indices of the k largest values per row of F (finite or -inf), largest
    first, ties in column order: ``np.argsort(-F, axis=1, kind="stable")[:, :k]``
    by k passes of argmax (no sort of the whole row)."""
    key = np.where(np.isfinite(F), F, -np.finfo(float).max)     # -inf below every value
    out = np.empty((F.shape[0], k), dtype=np.intp)
    r = np.arange(F.shape[0])
    for j in range(k):
        out[:, j] = i = np.argmax(key, axis=1)
        key[r, i] = -np.inf                                      # below every other
    return out


def _nan_to_num(a):
    """np.nan_to_num, cheap where there is nothing to replace (nearly always)."""
    return a if np.isfinite(a).all() else np.nan_to_num(a)


def _value(ws, cx, cy, R, px, py, with_H=False):
    """F at feasible points (-inf where p is outside the disk or the footprint);
    with ``with_H`` also H there."""
    d2 = (px - cx) ** 2 + (py - cy) ** 2
    ok = ws.inside(px, py) & (d2 <= R * R)
    H = ws.H(px, py)
    zc = np.minimum(H, 0.0)
    with np.errstate(invalid="ignore"):
        v = zc + np.sqrt(np.maximum(R * R - d2, 0.0))
    v = np.where(ok & np.isfinite(v), v, -np.inf)
    return (v, H) if with_H else v


def _newton_interior(ws, cx, cy, R, px, py, iters):
    """Stationary points of F = H + sqrt(R^2 - |p - c|^2) in the disk, in the slope
    coordinates w = (p - c)/q (q = sqrt(R^2 - |p - c|^2)): p = c + R w / sqrt(1 + |w|^2)
    maps the whole plane onto the open disk, so contacts on steep ground (|w| = the
    surface slope, p near the disk's rim) are as well conditioned as on flat ground.
    Newton (exact Hessian) where the Hessian of F is negative definite, gradient
    ascent elsewhere; every step is backtracked until F does not decrease.
    Returns the final points and a flag: converged to a strict local maximum."""
    n = len(px)
    dx, dy = px - cx, py - cy
    q = np.sqrt(np.maximum(R * R - dx * dx - dy * dy, 1e-6 * R * R))
    wx, wy = dx / q, dy / q
    conv = np.zeros(n, dtype=bool)
    act = np.arange(n)

    def point(i, wx_, wy_):
        s = np.sqrt(1.0 + wx_ * wx_ + wy_ * wy_)
        return cx[i] + R * wx_ / s, cy[i] + R * wy_ / s, s

    for _ in range(iters):
        if act.size == 0:
            break
        ax, ay = wx[act], wy[act]
        x, y, s = point(act, ax, ay)
        H, gx, gy, hxx, hxy, hyy = ws.all(x, y)
        F0 = np.minimum(H, 0.0) + R / s
        Gx, Gy = gx - ax, gy - ay                 # grad_p F
        k = s / R                                  # Jp^-1 = k (I + w w^T)
        a = hxx - k * (1 + ax * ax)
        b = hxy - k * ax * ay
        d = hyy - k * (1 + ay * ay)
        det = a * d - b * b
        negdef = (a < 0) & (det > 0) & np.isfinite(det)
        safe = np.where(negdef, det, 1.0)
        # p-space step: Newton -Hess_F^-1 G, or ascent along G (at most R/4)
        px_n = -(d * Gx - b * Gy) / safe
        py_n = -(-b * Gx + a * Gy) / safe
        gn = np.hypot(Gx, Gy)
        asc = 0.25 * R / np.maximum(1.0, gn) / np.maximum(1.0, k * R)
        sx = np.where(negdef, px_n, Gx * asc)
        sy = np.where(negdef, py_n, Gy * asc)
        sx, sy = _nan_to_num(sx), _nan_to_num(sy)
        # to w: dw = Jp^-1 dp
        wd = ax * sx + ay * sy
        dwx, dwy = k * (sx + ax * wd), k * (sy + ay * wd)
        lim = 0.5 * (1.0 + np.hypot(ax, ay))
        nw = np.hypot(dwx, dwy)
        f = np.where(nw > lim, lim / np.maximum(nw, 1e-300), 1.0)
        dwx, dwy = dwx * f, dwy * f
        step = np.hypot(sx, sy) * f
        # small Newton steps near a strict maximum are accepted as they are; the others
        # are backtracked until F does not decrease
        ok = negdef & (step < 0.02 * R) & (f == 1.0)
        nx_, ny_ = ax.copy(), ay.copy()
        nx_[ok], ny_[ok] = ax[ok] + dwx[ok], ay[ok] + dwy[ok]
        # backtracking: the full step for all, then the halved steps 1/2 .. 1/128 of
        # those that failed at once (one surface call each, not one per halving);
        # the first that does not decrease F is taken, and the reported step is the
        # accepted one halved once more (the stop test below)
        todo = np.nonzero(~ok)[0]
        for halvings in (np.ones(1), 0.5 ** np.arange(1, 8)):
            if todo.size == 0:
                break
            tx = ax[todo, None] + dwx[todo, None] * halvings
            ty = ay[todo, None] + dwy[todo, None] * halvings
            x1, y1, s1 = point(act[todo, None], tx, ty)
            F1 = np.minimum(ws.H(x1, y1), 0.0) + R / s1
            good = np.isfinite(F1) & (F1 >= F0[todo, None] - 1e-13 * R)
            hit = good.any(axis=1)
            first = np.argmax(good, axis=1)[hit]
            j = todo[hit]
            nx_[j], ny_[j] = tx[hit, first], ty[hit, first]
            ok[j] = True
            step[j] *= 0.5 * halvings[first]
            todo = todo[~hit]
        step[todo] *= 0.5 ** 8
        wx[act], wy[act] = nx_, ny_
        done = (negdef & ok & (step < XTOL)) | ~ok
        conv[act[done & negdef & ok]] = True
        act = act[~done]
    x, y, _ = point(np.arange(n), wx, wy)
    return x, y, conv


def _kinked(ws, cx, cy, R, px, py):
    """Whether F has a corner (a ridge) within R/25 of (px, py): its second difference
    along some of 8 directions is negative and does not shrink quadratically with the
    step (R/25, R/100, R/400, R/1600: smooth, ratio 16 from one to the next; a corner within
    the smaller step: about 4; between the two: far more than 16)."""
    a = np.pi * np.arange(8) / 8
    ux, uy = np.cos(a), np.sin(a)
    f0 = _value(ws, cx, cy, R, px, py)[:, None]
    d2 = []
    for d in (R / 25, R / 100, R / 400, R / 1600):
        fp = _value(ws, cx[:, None], cy[:, None], R, px[:, None] + d * ux, py[:, None] + d * uy)
        fm = _value(ws, cx[:, None], cy[:, None], R, px[:, None] - d * ux, py[:, None] - d * uy)
        with np.errstate(invalid="ignore"):
            d2.append(np.where(np.isfinite(fp) & np.isfinite(fm), fp + fm - 2 * f0, 0.0))
    corner = np.zeros(d2[0].shape, dtype=bool)
    with np.errstate(all="ignore"):
        for big, small in zip(d2[:-1], d2[1:]):
            corner |= (d2[0] < -1e-3 * R / 25) & ((big > 10.0 * small) | (big < 26.0 * small))
    return corner.any(axis=1)


def _rises_inward(ws, cx, cy, R, px, py, val):
    """Whether F rises from the edge point (px, py) into the footprint or along the
    edge (7 directions from the inward normal to the edge's tangents, R/64, R/1024 and
    R/16384 away): an
    interior maximum or a ridge crossing the edge, where neither the Newton starts nor
    the edge's 1-D Newton converge, lies beyond the edge candidate."""
    tiny = 1e-9 * max(ws.L, ws.W, 1.0)
    nx = (px <= tiny).astype(float) - (px >= ws.L - tiny)
    ny = (py <= tiny).astype(float) - (py >= ws.W - tiny)
    nn = np.hypot(nx, ny)
    nx, ny = np.where(nn > 0, nx / np.where(nn > 0, nn, 1), 0.0), np.where(nn > 0, ny / np.where(nn > 0, nn, 1), 0.0)
    a = np.radians([-90.0, -60.0, -30.0, 0.0, 30.0, 60.0, 90.0])
    dx = nx[:, None] * np.cos(a) - ny[:, None] * np.sin(a)
    dy = nx[:, None] * np.sin(a) + ny[:, None] * np.cos(a)
    d = R * np.repeat([1 / 64, 1 / 1024, 1 / 16384], a.size)     # a kink may be nearer than R/64
    dx, dy = np.tile(dx, 3) * d, np.tile(dy, 3) * d
    F = _value(ws, cx[:, None], cy[:, None], R, px[:, None] + dx, py[:, None] + dy)
    return (nn > 0) & (F.max(axis=1) > val + 1e-12 * R)


GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
RIDGE_ITERS = 34       # golden-section steps: the bracket shrinks to 0.618^34 = 8e-8 of itself


def _golden_max(fun, lo, hi, iters):
    """Vectorized golden-section search for the maximum of ``fun`` on [lo, hi] (arrays
    (m,)): returns (t, f) of the best point evaluated (f may be -inf)."""
    a, b = lo.copy(), hi.copy()
    c, d = b - GOLDEN * (b - a), a + GOLDEN * (b - a)
    fc, fd = fun(c), fun(d)
    bt, bf = np.where(fc >= fd, c, d), np.maximum(fc, fd)
    for _ in range(iters):
        left = fc >= fd                       # the maximum is in [a, d], else in [c, b]
        a, b = np.where(left, a, c), np.where(left, d, b)
        x = np.where(left, b - GOLDEN * (b - a), a + GOLDEN * (b - a))
        fx = fun(x)
        c, d, fc, fd = (np.where(left, x, d), np.where(left, c, x),
                        np.where(left, fx, fd), np.where(left, fc, fx))
        up = fx > bf
        bt, bf = np.where(up, x, bt), np.where(up, fx, bf)
    return bt, bf


KINK_ITERS = 24


def _kink_max(ws, cx, cy, R, bx, by, nx, ny, T):
    """Maximum of F on the segments b + t n, t in [-T, T] (arrays (m,)): F(t) rises to
    a corner (the ridge) and falls, smooth on each side. The bracket [a, b] keeps
    F'(a) > 0 > F'(b); the next point is where the tangents at a and b meet (exact on
    a corner of two straight pieces, superlinear on curved ones), the midpoint every
    third step and where the tangents do not meet inside. Returns (t, value) of the
    best point evaluated, the segment's ends included (F monotone: the end)."""
    def fd(t):
        x, y = bx + t * nx, by + t * ny
        H, hx, hy = ws.all(x, y)[:3]
        d2 = (x - cx) ** 2 + (y - cy) ** 2
        ok = ws.inside(x, y) & (d2 <= R * R)
        q = np.sqrt(np.maximum(R * R - d2, 0.0))
        top = H >= 0
        v = np.where(top, 0.0, H) + q
        g = np.where(top, 0.0, hx * nx + hy * ny) - ((x - cx) * nx + (y - cy) * ny) / np.maximum(q, 1e-300)
        v = np.where(ok & np.isfinite(v), v, -np.inf)
        return v, np.where(np.isfinite(g), g, 0.0)

    a, b = np.full(bx.size, -T), np.full(bx.size, T)
    fa, ga = fd(a)
    fb, gb = fd(b)
    bt, bf = np.where(fa >= fb, a, b), np.maximum(fa, fb)
    for i in range(KINK_ITERS):
        with np.errstate(all="ignore"):
            tm = (fb - fa + ga * a - gb * b) / (ga - gb)
        mid = 0.5 * (a + b)
        bad = ~np.isfinite(tm) | (tm <= a) | (tm >= b) | ~np.isfinite(fa) | ~np.isfinite(fb) \
            | (ga <= 0) | (gb >= 0) | (i % 3 == 2)
        t = np.where(bad, mid, tm)
        ft, gt = fd(t)
        up = ft > bf
        bt, bf = np.where(up, t, bt), np.where(up, ft, bf)
        right = (gt > 0) & np.isfinite(ft)                  # the peak lies beyond t
        if not np.isfinite(ft).all():                       # outside: towards the better end
            right |= ~np.isfinite(ft) & (fb > fa)
        a, fa, ga = np.where(right, t, a), np.where(right, ft, fa), np.where(right, gt, ga)
        b, fb, gb = np.where(right, b, t), np.where(right, fb, ft), np.where(right, gb, gt)
    return bt, bf


def _ridge(ws, cx, cy, R, px, py):
    """(v) The maximum of F near a convex kink through (or near) the best point
    (px, py) of each position: returns (value, x, y) of the best point found
    (feasible points only; -inf where none)."""
    m = cx.size
    rho = R / 8.0
    ang = 2 * np.pi * np.arange(32) / 32
    qx, qy = px[:, None] + rho * np.cos(ang), py[:, None] + rho * np.sin(ang)
    Fq = _value(ws, cx[:, None], cy[:, None], R, qx, qy)
    i1 = np.argmax(Fq, axis=1)
    far = np.abs((np.arange(32)[None, :] - i1[:, None] + 16) % 32 - 16) >= 8
    i2 = np.argmax(np.where(far, Fq, -np.inf), axis=1)
    r = np.arange(m)
    tx, ty = qx[r, i1] - qx[r, i2], qy[r, i1] - qy[r, i2]
    tn = np.hypot(tx, ty)
    tx, ty = np.where(tn > 0, tx / np.where(tn > 0, tn, 1), 1.0), np.where(tn > 0, ty / np.where(tn > 0, tn, 1), 0.0)
    nx, ny = -ty, tx
    S, T = 0.5 * R, 0.25 * R
    zero = np.zeros(m)
    found = {}

    def across(s):
        bx, by = px + s * tx, py + s * ty

        t, v = _kink_max(ws, cx, cy, R, bx, by, nx, ny, T)
        found[id(s)] = (bx + t * nx, by + t * ny)
        return v

    best = [np.full(m, -np.inf), px.copy(), py.copy()]

    def outer(s):
        v = across(s)
        x, y = found.pop(id(s))
        up = v > best[0]
        best[0] = np.where(up, v, best[0])
        best[1], best[2] = np.where(up, x, best[1]), np.where(up, y, best[2])
        return v

    _golden_max(outer, zero - S, zero + S, RIDGE_ITERS)
    return best[0], best[1], best[2]


def _newton_crease(ws, cx, cy, px, py, iters):
    """Nearest point of the crease H = 0 to c: Newton on the Lagrange conditions
    p - c - lambda grad H = 0, H = 0, after a projection onto H = 0."""
    px, py = px.copy(), py.copy()
    with np.errstate(all="ignore"):
        for _ in range(2):  # project onto H = 0 along the gradient
            H, gx, gy = ws.all(px, py)[:3]
            g2 = gx * gx + gy * gy
            px = px - np.nan_to_num(H * gx / g2)
            py = py - np.nan_to_num(H * gy / g2)
        H, gx, gy = ws.all(px, py)[:3]
        lam = np.nan_to_num(((px - cx) * gx + (py - cy) * gy) / (gx * gx + gy * gy))
        # Newton on the points still moving (a point whose step fell below XTOL, or
        # whose system is singular or not finite, keeps its place)
        act = np.arange(len(px))
        for _ in range(iters):
            if act.size == 0:
                break
            x, y, la = px[act], py[act], lam[act]
            H, gx, gy, hxx, hxy, hyy = ws.all(x, y)
            # the bordered system [[A, B, -gx], [B, D, -gy], [gx, gy, 0]] step = r,
            # solved in closed form (Cramer)
            A, B, D = 1 - la * hxx, -la * hxy, 1 - la * hyy
            r1, r2, r3 = la * gx - (x - cx[act]), la * gy - (y - cy[act]), -H
            det = A * gy * gy - 2.0 * B * gx * gy + D * gx * gx
            ok = np.isfinite(det) & (np.abs(det) > 1e-300) & np.isfinite(r1) & \
                np.isfinite(r2) & np.isfinite(r3)
            det = np.where(ok, det, 1.0)
            sx = np.where(ok, (gy * (r1 * gy - r2 * gx) + r3 * (D * gx - B * gy)) / det, 0.0)
            sy = np.where(ok, (gx * (r2 * gx - r1 * gy) + r3 * (A * gy - B * gx)) / det, 0.0)
            sl = np.where(ok, (A * (D * r3 - r2 * gy) - B * (B * r3 - r2 * gx)
                               + r1 * (B * gy - D * gx)) / det, 0.0)
            px[act], py[act], lam[act] = x + sx, y + sy, la + sl
            act = act[ok & (np.maximum(np.abs(sx), np.abs(sy)) >= XTOL)]
    return px, py


EDGE_SLOPES = (0.5, 1.5, 4.0, 8.0, 12.0, 20.0, 40.0)
_EDGE_OFF = np.array([sg * w / math.sqrt(1.0 + w * w) for w in EDGE_SLOPES for sg in (-1.0, 1.0)])


def _edges(ws, cx, cy, R, best, idx_all, nsamp, iters):
    """Candidates (iii)/(iv) on the four footprint edges within each disk."""
    L, W = ws.L, ws.W
    for axis, level, length in ((1, 0.0, L), (1, W, L), (0, 0.0, W), (0, L, W)):
        # axis 1: edge Y = level, parameter t = X; axis 0: edge X = level, t = Y
        perp = cy if axis == 1 else cx
        tcent = cx if axis == 1 else cy
        dp = np.abs(perp - level)
        sel = np.nonzero(dp < R)[0]
        if sel.size == 0:
            continue
        a = np.sqrt(R * R - dp[sel] ** 2)
        tc = tcent[sel]
        t0, t1 = np.maximum(tc - a, 0.0), np.minimum(tc + a, length)
        keep = t0 <= t1
        sel, a, tc, t0, t1 = sel[keep], a[keep], tc[keep], t0[keep], t1[keep]
        if sel.size == 0:
            continue
        rho2 = (a * a)[:, None]

        def pts(t):
            lv = np.full_like(t, level)
            return (t, lv) if axis == 1 else (lv, t)

        def val(t):
            X, Y = pts(t)
            zc = np.minimum(ws.H(X, Y), 0.0)
            return zc + np.sqrt(np.maximum(rho2 - (t - tc[:, None]) ** 2, 0.0))

        # samples even along the chord, and where the ball touches a line of each slope
        # in EDGE_SLOPES (t - tc = a w / sqrt(1 + w^2)): on a steep wall the contact lies
        # within a few hundredths of R of the chord's end, between two even samples
        # whose values are both far below it
        u = np.linspace(0.0, 1.0, nsamp)
        T = t0[:, None] + (t1 - t0)[:, None] * u[None, :]
        Ts = tc[:, None] + a[:, None] * _EDGE_OFF[None, :]
        T = np.sort(np.concatenate([T, np.clip(Ts, t0[:, None], t1[:, None])], axis=1), axis=1)
        V = val(T)
        idx = idx_all[sel]
        X, Y = pts(T)
        best.offer(idx, V, X, Y, EDGE)
        # flat part: the point of the edge nearest c, if it lies in the top region
        tf = np.clip(tc, t0, t1)[:, None]
        Xf, Yf = pts(tf)
        Vf = np.where(ws.H(Xf, Yf) >= 0, val(tf), -np.inf)
        best.offer(idx, Vf[:, 0], Xf[:, 0], Yf[:, 0], EDGE)
        # smooth part: 1-D Newton in the angle phi (t = tc + a sin phi: no square-root
        # singularity at the disk's rim, where steep ground puts the contact), from the
        # three best local maxima of the samples (a wall's foot and the floor under the
        # ball's centre are separate hills of nearly equal height), each step backtracked
        # until the value does not decrease
        Vf = np.where(np.isfinite(V), V, -np.inf)
        lm = np.ones(V.shape, dtype=bool)
        lm[:, 1:] &= Vf[:, 1:] >= Vf[:, :-1]
        lm[:, :-1] &= Vf[:, :-1] >= Vf[:, 1:]
        k = 3
        start = np.argsort(-np.where(lm, Vf, -np.inf), axis=1, kind="stable")[:, :k]
        t = np.take_along_axis(T, start, axis=1)
        shp = t.shape
        aa = np.broadcast_to(a[:, None], shp).ravel()
        tcc = np.broadcast_to(tc[:, None], shp).ravel()
        lo = np.arcsin(np.clip((np.broadcast_to(t0[:, None], shp).ravel() - tcc) / aa, -1.0, 1.0))
        hi = np.arcsin(np.clip((np.broadcast_to(t1[:, None], shp).ravel() - tcc) / aa, -1.0, 1.0))
        ph = np.clip(np.arcsin(np.clip((t.ravel() - tcc) / aa, -1.0, 1.0)), lo, hi)

        def fval(i, ph_):
            X_, Y_ = pts(tcc[i] + aa[i] * np.sin(ph_))
            return np.minimum(ws.H(X_, Y_), 0.0) + aa[i] * np.cos(ph_)

        act = np.arange(ph.size)
        for _ in range(iters + 4):
            if act.size == 0:
                break
            p_, a_ = ph[act], aa[act]
            sn, cs = np.sin(p_), np.cos(p_)
            X, Y = pts(tcc[act] + a_ * sn)
            H0, gx, gy, hxx, _, hyy = ws.all(X, Y)
            Ht, Htt = (gx, hxx) if axis == 1 else (gy, hyy)
            d1 = a_ * (Ht * cs - sn)
            d2 = a_ * (Htt * a_ * cs * cs - Ht * sn - cs)
            st = np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.1 * np.sign(d1))
            st = np.clip(_nan_to_num(st), -0.5, 0.5)
            f0 = np.minimum(H0, 0.0) + a_ * cs
            moved = np.zeros(act.size, dtype=bool)
            sub = np.arange(act.size)
            # the full step, then the halvings 1/2 .. 1/32 of the failed ones at once
            for halvings in (np.ones(1), 0.5 ** np.arange(1, 6)):
                if sub.size == 0:
                    break
                cand = np.clip(p_[sub, None] + st[sub, None] * halvings,
                               lo[act[sub], None], hi[act[sub], None])
                f1 = fval(act[sub, None], cand)
                good = np.isfinite(f1) & (f1 >= f0[sub, None] - 1e-13 * R)
                hit = good.any(axis=1)
                first = np.argmax(good, axis=1)[hit]
                j = sub[hit]
                p_[j] = cand[hit, first]
                moved[j] = True
                st[j] *= halvings[first]
                sub = sub[~hit]
            st[sub] *= 0.5 ** 6
            ph[act] = p_
            done = ~moved | (np.abs(st) * a_ < XTOL)
            act = act[~done]
        ph = ph.reshape(shp)
        aa, tcc = aa.reshape(shp), tcc.reshape(shp)
        t = tcc + aa * np.sin(ph)
        X, Y = pts(t)
        best.offer(idx, val(t), X, Y, EDGE)
        # crease crossings on the edge: safeguarded Newton inside each sign change
        X, Y = pts(T)
        Hs = ws.H(X, Y)
        sgn = Hs >= 0
        ch = sgn[:, 1:] != sgn[:, :-1]
        r_, j_ = np.nonzero(ch)
        if r_.size:
            a_, b_ = T[r_, j_], T[r_, j_ + 1]
            Ha = Hs[r_, j_]
            tcr = tc[r_][:, None]
            t = 0.5 * (a_ + b_)
            for _ in range(iters + 20):
                X, Y = pts(t)
                H, gx, gy = ws.all(X, Y)[:3]
                Ht = gx if axis == 1 else gy
                same = (H >= 0) == (Ha >= 0)
                a_, b_ = np.where(same, t, a_), np.where(same, b_, t)
                with np.errstate(all="ignore"):
                    tn = t - H / Ht
                bad = ~np.isfinite(tn) | (tn <= np.minimum(a_, b_)) | (tn >= np.maximum(a_, b_))
                t_old, t = t, np.where(bad, 0.5 * (a_ + b_), tn)
                if np.abs(t - t_old).max(initial=0.0) < XTOL:
                    break
            # evaluate on both sides of the root: the top side carries the flat value
            for tt in (t, np.where(Ha >= 0, a_, b_)):
                X, Y = pts(tt)
                zc = np.minimum(ws.H(X, Y), 0.0)
                v = zc + np.sqrt(np.maximum(a[r_] ** 2 - (tt - tcr[:, 0]) ** 2, 0.0))
                best.offer(idx[r_], v, X, Y, CREASE, unique=False)


def compensate(surface, X, Y, R: float, *, return_info: bool = False, rings=RING_SLOPES,
               angles: int = 12, starts: int = 3, iters: int = 12):
    """Exact drop-cutter tip heights for a ball of radius ``R`` mm.

    surface: :class:`fabkit.surface.Surface` (design units; converted with its scale)
    X, Y:    tool axis positions, work mm, any (equal or broadcastable) shapes
    Returns Z, work mm, the shape of the broadcast X, Y: the tip height, exact to
    ~1e-9 mm; -inf where the tool's disk misses the footprint (touches no material).
    With ``return_info`` also a :class:`CompensationInfo`.
    """
    # nothing here may warn: overflowing trial points are rejected as -inf candidates
    with np.errstate(all="ignore"):
        return _compensate(surface, X, Y, R, return_info, rings, angles, starts, iters)


def _compensate(surface, X, Y, R, return_info, rings, angles, starts, iters):
    ws = surface if isinstance(surface, WorkSurface) else WorkSurface(surface)
    X, Y = np.broadcast_arrays(np.asarray(X, dtype=float), np.asarray(Y, dtype=float))
    shape = X.shape
    cx, cy = X.ravel().copy(), Y.ravel().copy()
    n = cx.size
    R = float(R)
    kern = ws.kernel() if n else None
    if kern is not None:
        # candidates (i)-(v) in compiled code (dropcut.py: the same operations per position)
        best = _Best(n)
        bridged = np.zeros(n, dtype=bool)
        converged = np.zeros(n, dtype=bool)
        tab = _tables(R, tuple(rings), angles)
        G = np.array([ws.s, ws.x0, ws.y0, ws.top, ws.L, ws.W], dtype=float)
        _entry(kern)(cx, cy, R, G, kern.P, *tab[:7], int(starts), int(iters), best.val, best.px,
                     best.py, best.kind, bridged, converged, tab[7])
        todo = np.zeros(0, dtype=np.intp)          # (v) and (i')'s offer are done too
        walls = None
    else:
        best, bridged, converged, todo, walls = _candidates(ws, cx, cy, R, rings, angles, starts, iters)

    # (v) a ridge: where no start converged to a strict maximum and the best point is
    # neither on the crease nor the top (the crease is a convex kink too, with its own
    # exact candidate), nor on an edge the tool overhangs with F falling inwards from it
    # (there Newton leaves the footprint and the edge candidates are exact)
    if todo.size:
        kt = best.kind[todo]
        stuck = ~converged[todo] & np.isin(kt, (SAMPLE, INTERIOR))
        si = np.nonzero(stuck)[0]
        if si.size:
            stuck[si] = _kinked(ws, cx[todo[si]], cy[todo[si]], R, best.px[todo[si]],
                                best.py[todo[si]])
        ek = np.nonzero(~converged[todo] & (kt == EDGE))[0]
        if ek.size:
            stuck[ek] = _rises_inward(ws, cx[todo[ek]], cy[todo[ek]], R, best.px[todo[ek]],
                                      best.py[todo[ek]], best.val[todo[ek]])
        if stuck.any():
            g = todo[stuck]
            v, qx, qy = _ridge(ws, cx[g], cy[g], R, best.px[g], best.py[g])
            best.offer(g, v, qx, qy, RIDGE)
    # (i')'s points, last: only where higher than every other candidate
    if walls is not None:
        _offer_walls(best, bridged, *walls)

    Z = (best.val - R).reshape(shape)
    if not return_info:
        return Z
    return Z, CompensationInfo(best.px.reshape(shape), best.py.reshape(shape),
                               best.kind.reshape(shape), bridged.reshape(shape))


_ENTRY: dict = {}


def _entry(kern):
    """The kernel's compiled function itself (numba's entry point of its one
    signature), or ``kern.drop``. Every call passes the same kinds of arguments (float64
    C arrays made here or by :func:`_tables`, Python floats and ints, the kernel's P), the
    types of that signature (compiled by kernels._warm), so the dispatcher's typing of
    them (about 0.1 ms a call, mostly the tuples: 80 ms over the 805 calls of
    specs/surface.yaml) is skipped; the same code runs."""
    hit = _ENTRY.get(id(kern))
    if hit is not None and hit[0] is kern:
        return hit[1]
    fn = kern.drop
    try:
        disp = kern.module.drop_batch
        sigs = list(disp.signatures)
        if len(sigs) == 1:
            fn = disp.overloads[sigs[0]].entry_point
    except (AttributeError, KeyError, TypeError):      # another numba: the dispatcher
        fn = kern.drop
    if len(_ENTRY) > 64:
        _ENTRY.clear()
    _ENTRY[id(kern)] = (kern, fn)
    return fn


@functools.lru_cache(maxsize=8)
def _tables(R, rings, angles):
    """The kernel's fixed tables: the samples' offsets (x, y), their sqrt(R^2 - r^2),
    r^2 and quadrant, the edges' even samples and slope offsets, and those of (v)."""
    off = _polar(R, rings, angles)
    r2 = (off ** 2).sum(axis=1)
    sq = np.sqrt(R * R - r2)
    quad = (np.floor(np.arctan2(off[:, 1], off[:, 0]) / (0.5 * np.pi)).astype(np.int64) + 4) % 4
    out = (np.ascontiguousarray(off[:, 0]), np.ascontiguousarray(off[:, 1]), sq, r2, quad,
           np.linspace(0.0, 1.0, 17), _EDGE_OFF.copy())
    # (v): _kinked's 8 directions, _rises_inward's 7 directions and 3 distances, _ridge's circle
    a = np.pi * np.arange(8) / 8
    b = np.radians([-90.0, -60.0, -30.0, 0.0, 30.0, 60.0, 90.0])
    c = 2 * np.pi * np.arange(32) / 32
    v5 = (np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.repeat([1 / 64, 1 / 1024, 1 / 16384], b.size),
          np.cos(c), np.sin(c))
    out = out + (tuple(np.ascontiguousarray(v, dtype=float) for v in v5),)
    return out           # (writeable: the kernel's one compiled signature takes writeable arrays)


#: more Newton starts per position from the samples with the highest tangent-plane drop (i')
WALL_STARTS = 2
#: ... scored where their own F is within this many R of the best after (i)
WALL_GATE = 0.25
#: ... and started only where the plane's contact point is this many R from the best point
WALL_NEAR = 0.0625
#: points of the disk's rim scored with them of the disk's rim scored with them (a wall steeper than the outer ring's
#: slope whose foot cuts a cap off the disk beyond every sample)
RIM_POINTS = 36


@functools.lru_cache(maxsize=8)
def _rim(R: float) -> np.ndarray:
    ph = 2 * np.pi * np.arange(RIM_POINTS) / RIM_POINTS
    out = np.column_stack([R * np.cos(ph), R * np.sin(ph)])
    out.flags.writeable = False
    return out


def _wall_scores(ws, tx, ty, R, PX, PY, F, vb):
    """T(s): the tip's F on the plane tangent to the surface at each point whose own
    F is within WALL_GATE R of ``vb`` (-inf elsewhere: no point of the disk near it rises
    above the best unless the surface there turns up by that much), and the start of
    Newton it gives: the plane's own contact point c + R g / sqrt(1 + |g|^2)."""
    T = np.full(PX.shape, -np.inf)
    SX, SY = np.full(PX.shape, np.nan), np.full(PX.shape, np.nan)
    ok = F > (vb - WALL_GATE * R)[:, None]
    if ok.any():
        px, py = PX[ok], PY[ok]
        cx, cy = np.broadcast_to(tx[:, None], PX.shape)[ok], np.broadcast_to(ty[:, None], PX.shape)[ok]
        H, gx, gy = ws.all(px, py)[:3]
        m = np.sqrt(1.0 + gx * gx + gy * gy)
        t = H + gx * (cx - px) + gy * (cy - py) + R * m
        T[ok] = np.where((H < 0) & np.isfinite(t), t, -np.inf)
        SX[ok], SY[ok] = cx + R * gx / m, cy + R * gy / m
    return T, SX, SY


def _wall_starts(ws, tx, ty, R, PX, PY, FS, order, vb, bx, by, iters):
    """(i'): Newton from the WALL_STARTS points (samples not already starts, and the
    rim's points) of highest T(s) where T(s) exceeds ``vb`` (the best value after (i)),
    started at the tangent plane's contact point. Returns (rows, value, x, y): the
    best point found per row of the samples (rows into tx); :func:`_offer_walls` offers
    them once every other candidate is in."""
    T, SX, SY = _wall_scores(ws, tx, ty, R, PX, PY, FS, vb)
    np.put_along_axis(T, order, -np.inf, axis=1)            # the best-F starts ran already
    rim = _rim(R)
    RX, RY = tx[:, None] + rim[:, 0], ty[:, None] + rim[:, 1]
    FR = np.where(ws.inside(RX, RY), np.minimum(ws.H(RX, RY), 0.0), -np.inf)    # sqrt(R^2 - R^2) = 0
    Tr, SXr, SYr = _wall_scores(ws, tx, ty, R, RX, RY, FR, vb)
    T, SX, SY = np.hstack([T, Tr]), np.hstack([SX, SXr]), np.hstack([SY, SYr])
    n = T.shape[0]
    r = np.arange(n)
    wv, wx, wy = np.full(n, -np.inf), np.full(n, np.nan), np.full(n, np.nan)
    left = np.full(n, WALL_STARTS)
    while True:
        j = np.argmax(T, axis=1)
        tj = T[r, j]
        live = np.nonzero((left > 0) & (tj > vb + SEED_MARGIN))[0]
        if live.size == 0:
            break
        jl = j[live]
        T[live, jl] = -np.inf
        # a start on the best point's own slope climbs back to it: not run, nor counted
        far = np.hypot(SX[live, jl] - bx[live], SY[live, jl] - by[live]) >= WALL_NEAR * R
        go, jg = live[far], jl[far]
        if go.size == 0:
            continue
        left[go] -= 1
        x, y, _ = _newton_interior(ws, tx[go], ty[go], R, SX[go, jg], SY[go, jg], iters + 8)
        v = _value(ws, tx[go], ty[go], R, x, y)
        up = v > wv[go]
        g = go[up]
        wv[g], wx[g], wy[g] = v[up], x[up], y[up]
    k = np.nonzero(np.isfinite(wv))[0]
    return k, wv[k], wx[k], wy[k]


def _offer_walls(best, bridged, idx, v, x, y):
    """The points of (i') where higher than every other candidate by more than SEED_MARGIN
    (elsewhere the heights are unchanged to the bit); then the contact problem has two
    maxima (bridged)."""
    up = v > best.val[idx] + SEED_MARGIN
    best.offer(idx[up], v[up], x[up], y[up], INTERIOR)
    bridged[idx[up]] = True


def _candidates(ws, cx, cy, R, rings, angles, starts, iters):
    """Candidates (i)-(iv) over all positions in numpy: (best, bridged, converged, todo)."""
    n = cx.size
    best = _Best(n)
    bridged = np.zeros(n, dtype=bool)
    converged = np.zeros(n, dtype=bool)
    walls = None

    # (ii) c on the top face: nothing can be higher
    Hc = ws.H(cx, cy)
    ontop = ws.inside(cx, cy) & (Hc >= 0)
    best.offer(np.nonzero(ontop)[0], np.full(int(ontop.sum()), R), cx[ontop], cy[ontop], TOP)
    todo = np.nonzero(~ontop)[0]
    if todo.size:
        tx, ty = cx[todo], cy[todo]
        off = _polar(R, tuple(rings), angles)
        K = len(off)
        PX, PY = tx[:, None] + off[:, 0], ty[:, None] + off[:, 1]
        inF = ws.inside(PX, PY)
        HS = ws.H(PX, PY)
        sq = np.sqrt(R * R - (off ** 2).sum(axis=1))
        FS = np.where(inF, np.minimum(HS, 0.0) + sq, -np.inf)
        FS = np.where(np.isfinite(FS), FS, -np.inf)
        best.offer(todo, FS, PX, PY, SAMPLE)

        # (i) interior Newton from the best `starts` samples
        k = min(starts, K)
        order = _top(FS, k)
        sx = np.take_along_axis(PX, order, axis=1).ravel()
        sy = np.take_along_axis(PY, order, axis=1).ravel()
        owner = np.repeat(np.arange(todo.size), k)
        ax, ay = tx[owner], ty[owner]
        # in chunks of starts (each start's iteration is its own): the temporaries of
        # a chunk stay in the cache
        parts = [_newton_interior(ws, ax[i:i + CHUNK], ay[i:i + CHUNK], R, sx[i:i + CHUNK],
                                  sy[i:i + CHUNK], iters + 8) for i in range(0, sx.size, CHUNK)]
        px, py, conv = (np.concatenate(c) for c in zip(*parts)) if len(parts) > 1 else parts[0]
        v, Hp = _value(ws, ax, ay, R, px, py, with_H=True)
        best.offer(todo, v.reshape(-1, k), px.reshape(-1, k), py.reshape(-1, k), INTERIOR)
        # (a stationary point outside the footprint, on the surface's continuation, is no candidate)
        converged[todo] = (conv & np.isfinite(v)).reshape(-1, k).any(axis=1)
        # bridged: two converged local maxima in the smooth part, distinct points
        lm = conv & np.isfinite(v) & (Hp < 0)
        if lm.any():
            # per position, the converged maxima against the first of them in (x, y) order
            lm2, qx, qy = lm.reshape(-1, k), px.reshape(-1, k), py.reshape(-1, k)
            fx = np.where(lm2, qx, np.inf).min(axis=1)
            fy = np.where(lm2 & (qx == fx[:, None]), qy, np.inf).min(axis=1)
            far = lm2 & (np.hypot(qx - fx[:, None], qy - fy[:, None]) > 1e-4 * R)
            bridged[todo[far.any(axis=1)]] = True

        # (i') a wall rising into the disk: more starts, from the samples whose tangent plane
        # holds the ball highest. Where the disk holds a floor and the foot of a steep wall,
        # the floor's samples have the best F while the wall's contact (a thin band at the
        # disk's rim, or between the rings) is higher still; the best-F starts all climb to
        # the floor's maximum (a ball of 6 mm beside a wall of slope 15: the tip 0.34 mm low;
        # a 4 mm ball in the concave foot of a slope-5 step: 0.036 mm low). The drop on the
        # plane tangent at s, T(s) = H(s) + grad H(s) . (c - s) + R sqrt(1 + |grad H(s)|^2),
        # is exact for a plane; samples with T above the best value so far start Newton, and
        # what they find replaces the best only when higher by more than SEED_MARGIN (elsewhere
        # the heights are unchanged to the bit)
        wk, wv, wx, wy = _wall_starts(ws, tx, ty, R, PX, PY, FS, order, best.val[todo], best.px[todo],
                                      best.py[todo], iters)
        walls = (todo[wk], wv, wx, wy)

        # (ii) crease: seeds = the nearest top-region sample in each quadrant around c
        # and the best sample. One seed is not enough where the crease itself has a kink
        # (the surface's own crease, 3*abs(x) + 2*abs(y), meeting the top face): Newton
        # stays on its seed's branch, and the nearest point on the other branch was
        # missed (the tip 0.18 mm low, a gouge of 0.12-0.18 mm beside the top face)
        r2 = (off ** 2).sum(axis=1)
        quad = (np.floor(np.arctan2(off[:, 1], off[:, 0]) / (0.5 * np.pi)).astype(int) + 4) % 4
        top_s = inF & (HS >= 0)
        seeds_i, seeds_k = [], []
        for q in range(4):
            tq = top_s & (quad == q)[None, :]
            hq = tq.any(axis=1)
            seeds_i.append(np.nonzero(hq)[0])
            seeds_k.append(np.argmin(np.where(tq, r2[None, :], np.inf), axis=1)[hq])
        has_top = top_s.any(axis=1)
        seeds_i.append(np.arange(todo.size))
        seeds_k.append(order[:, 0])
        # and the highest sample below the top face in each quadrant: a wavy crease has
        # several nearest points, and a tongue of the top face narrower than the rings'
        # spacing holds no sample (8*x + 2*sin(3*y) under a 3 mm ball: the tip 0.11 mm low)
        low_s = inF & (HS < 0)
        first_extra = len(seeds_i)
        for q in range(4):
            lq = low_s & (quad == q)[None, :]
            hq = lq.any(axis=1)
            seeds_i.append(np.nonzero(hq)[0])
            seeds_k.append(np.argmax(np.where(lq, HS, -np.inf), axis=1)[hq])
        # only where the top region is near: a sample on top or within R/4 of it, or
        # the tangent plane at the highest sample rising to within R/4 of it inside the
        # disk (a steep wall whose crease cuts only a thin cap off the disk's rim, between
        # or beyond the samples: slope 8 under a 3 mm ball put the highest sample 0.57 mm
        # below the crease, and the missed crease left the tip 0.057 mm low)
        HSin = np.where(inF, HS, -np.inf)
        nearish = has_top | (HSin.max(axis=1) > -0.25 * R)
        far = np.nonzero(~nearish & np.isfinite(HSin).any(axis=1))[0]
        if far.size:
            jh = np.argmax(HSin[far], axis=1)
            hx_, hy_ = PX[far, jh], PY[far, jh]
            H0, gx0, gy0 = ws.all(hx_, hy_)[:3]
            reach = H0 + gx0 * (tx[far] - hx_) + gy0 * (ty[far] - hy_) + R * np.hypot(gx0, gy0)
            nearish[far] = reach > -0.25 * R
        # both seeds in one Newton call (each point's iteration is its own), offered
        # seed by seed
        groups = [(si[nearish[si]], sk[nearish[si]]) for si, sk in zip(seeds_i, seeds_k)]
        si = np.concatenate([g[0] for g in groups])
        if si.size:
            sk = np.concatenate([g[1] for g in groups])
            qx, qy = _newton_crease(ws, tx[si], ty[si], PX[si, sk], PY[si, sk], iters)
            v = _value(ws, tx[si], ty[si], R, qx, qy)
            a = 0
            for j, (g, _) in enumerate(groups):
                b = a + g.size
                if g.size:
                    vg = v[a:b]
                    if j >= first_extra:    # the quadrants' highest samples: only another maximum
                        vg = np.where(vg > best.val[todo[g]] + SEED_MARGIN, vg, -np.inf)
                    best.offer(todo[g], vg, qx[a:b], qy[a:b], CREASE)
                a = b

    # (iii)/(iv) edges and corners where the disk crosses the footprint boundary
    edge = ~ontop & ((cx < R) | (cy < R) | (cx > ws.L - R) | (cy > ws.W - R))
    ei = np.nonzero(edge)[0]
    if ei.size:
        _edges(ws, cx[ei], cy[ei], R, best, ei, nsamp=17, iters=iters)
    return best, bridged, converged, todo, walls
