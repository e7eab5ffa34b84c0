"""The parametric surface z = h(x, y), clipped at the stock's top face.

Pure array functions over the compiled expression (:mod:`fabkit.expr`): h and
its exact first and second derivatives, the clipped height min(h, top), the
lowest point of the footprint, principal curvatures and the smallest concave
radius, and the design -> work coordinate transform.

Design coordinates are in the spec's design unit; work coordinates are mm,
origin on the top face at the footprint corner of smallest x and y:
``work = scale * (design - (x0, y0, top))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import SpecError
from .tolerances import DEFAULT, Tolerances


#: share of the check grid on which an undefined (0/0) derivative is taken for a kink
KINK_SHARE = 0.02
KINK_MAX_SLOPE = 1e3     # |grad h| beside such a point: beyond it, a vertical tangent (refused)


@dataclass(frozen=True)
class Extremum:
    x: float
    y: float
    z: float


class Surface:
    """h(x, y) on the footprint ``x_range`` x ``y_range``, clipped at ``top``.

    Parameters are in design units; ``scale`` is mm per design unit.
    """

    def __init__(self, fns, x_range, y_range, top: float, scale: float = 1.0,
                 tol: Tolerances = DEFAULT, source: str = "<spec>"):
        self.fns = fns
        self.x_range = (float(x_range[0]), float(x_range[1]))
        self.y_range = (float(y_range[0]), float(y_range[1]))
        self.top = float(top)
        self.scale = float(scale)
        self.tol = tol
        self.source = source

    @classmethod
    def from_spec(cls, spec, tol: Tolerances = DEFAULT) -> "Surface":
        spec.require("surface")
        s = spec.surface
        surf = cls(spec.surface_functions(), s.x, s.y, s.top, spec.scale, tol, source=spec.path)
        surf.check_finite()
        return surf

    # -- evaluation ---------------------------------------------------------
    def height(self, x, y) -> np.ndarray:
        """h(x, y), any broadcastable shapes."""
        return self.fns.h(x, y)

    def clipped(self, x, y) -> np.ndarray:
        """min(h, top): the milled surface (flat top face where h >= top)."""
        return np.minimum(self.fns.h(x, y), self.top)

    def gradient(self, x, y):
        """(h_x, h_y), exact."""
        return self.fns.grad(x, y)

    def hessian(self, x, y):
        """(h_xx, h_xy, h_yy), exact."""
        return self.fns.hess(x, y)

    def derivatives(self, x, y):
        """(h, h_x, h_y, h_xx, h_xy, h_yy), exact, sharing subexpressions."""
        return self.fns.all(x, y)

    # -- footprint ----------------------------------------------------------
    @property
    def length(self) -> float:
        return self.x_range[1] - self.x_range[0]

    @property
    def width(self) -> float:
        return self.y_range[1] - self.y_range[0]

    def grid(self, n: int | None = None):
        """An n x n grid over the footprint, (X, Y) of shape (n, n) (indexing='xy')."""
        n = n or self.tol.grid_samples
        xs = np.linspace(*self.x_range, n)
        ys = np.linspace(*self.y_range, n)
        return np.meshgrid(xs, ys)

    def check_finite(self) -> None:
        """Raise SpecError if h or its derivatives are not finite on the footprint.

        A derivative that is undefined (0/0: nan) where h is finite is a kink of the
        formula, like abs at 0: the apex of a cone sqrt(x^2 + y^2), a crease written
        sqrt(x^2). Those are accepted on a few grid points (at most KINK_SHARE of them);
        an infinite derivative (a vertical tangent, sqrt(x) at 0) is refused, and so is
        a footprint reaching a singular point of asin, acos or atan2 (expr.check_domain)."""
        from .expr import check_domain

        try:
            check_domain(self.fns, self.x_range, self.y_range)
        except SpecError as exc:
            raise exc.with_location(file=self.source) from None
        X, Y = self.grid(201)
        vals = self.derivatives(X, Y)
        kink = self._kinks(X, Y, vals)
        for name, v in zip(("h", "h_x", "h_y", "h_xx", "h_xy", "h_yy"), vals):
            bad = ~np.isfinite(v)
            if name != "h":
                bad &= ~kink
            if bad.any():
                i = np.argmax(bad.ravel())
                raise SpecError(
                    f"{name} is not finite at x={X.ravel()[i]:.6g}, y={Y.ravel()[i]:.6g} "
                    "(check the formula and the footprint)", file=self.source, key="surface.height")
        h = vals[0]
        if np.abs(h).max() > 1e9:
            raise SpecError("height exceeds 1e9 design units on the footprint", file=self.source,
                            key="surface.height")

    def _kinks(self, X, Y, vals):
        """Grid points where a derivative is undefined (nan) but h is finite and the
        slope stays bounded around the point: at 8 points 1e-9 of the footprint away,
        h_x and h_y finite and |grad h| <= KINK_MAX_SLOPE (a cone's apex: its slope; a
        vertical tangent such as (x^2 + y^2)^(1/4) at 0: about 4000). All False when more
        than KINK_SHARE of the grid is flagged."""
        h = vals[0]
        cand = np.isfinite(h) & np.any([np.isnan(v) for v in vals[1:]], axis=0)
        if not cand.any() or cand.mean() > KINK_SHARE:
            return np.zeros_like(cand)
        px, py = X[cand], Y[cand]
        d = 1e-9 * max(self.length, self.width)
        a = 2 * np.pi * np.arange(8) / 8 + 0.3
        qx, qy = px[:, None] + d * np.cos(a), py[:, None] + d * np.sin(a)
        with np.errstate(all="ignore"):
            _, gx, gy = self.derivatives(qx, qy)[:3]
            g = np.hypot(gx, gy)
        ok = np.all(np.isfinite(g) & (g <= KINK_MAX_SLOPE), axis=1)
        out = np.zeros_like(cand)
        out[cand] = ok
        return out

    def lowest(self) -> Extremum:
        """The lowest point of h on the footprint (exact to ~1e-12 relative:
        grid search, then bounded quasi-Newton with the exact gradient)."""
        from scipy.optimize import minimize

        X, Y = self.grid()
        H = self.height(X, Y)
        order = np.argsort(H.ravel())[:5]
        best = Extremum(float(X.ravel()[order[0]]), float(Y.ravel()[order[0]]), float(H.ravel()[order[0]]))
        bounds = [self.x_range, self.y_range]
        for i in order:
            p0 = np.array([X.ravel()[i], Y.ravel()[i]])
            res = minimize(lambda p: float(self.height(p[0], p[1])), p0, method="L-BFGS-B",
                           jac=lambda p: np.array([float(g) for g in self.gradient(p[0], p[1])]),
                           bounds=bounds, options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 200})
            if np.isfinite(res.fun) and res.fun < best.z:
                best = Extremum(float(res.x[0]), float(res.x[1]), float(res.fun))
        return best

    def depth_mm(self) -> float:
        """Deepest cut below the top face, mm (0 if the surface never dips below top)."""
        return max(0.0, (self.top - self.lowest().z) * self.scale)

    # -- curvature ----------------------------------------------------------
    def principal_curvatures(self, x, y):
        """(k1, k2), k1 >= k2, of the graph z = h with the upward normal, in
        1/design unit. Positive: concave up (a valley a ball-end tool must fit)."""
        return principal_curvatures(*self.derivatives(x, y)[1:6])

    def min_concave_radius(self) -> Extremum:
        """Smallest radius of concave curvature where the surface is cut (h < top),
        design units, with its location (``z`` holds the radius; inf if none).
        Sampled on the grid and refined locally (accurate to ~1e-6 relative)."""
        from scipy.optimize import minimize

        X, Y = self.grid()
        k1, _ = self.principal_curvatures(X, Y)
        cut = self.height(X, Y) < self.top
        k1 = np.where(cut & np.isfinite(k1), k1, -np.inf)
        i = int(np.argmax(k1))
        if not k1.ravel()[i] > 0:
            return Extremum(math.nan, math.nan, math.inf)
        x0, y0 = float(X.ravel()[i]), float(Y.ravel()[i])

        def neg(p):
            if self.height(p[0], p[1]) >= self.top:
                return 0.0
            return -float(self.principal_curvatures(p[0], p[1])[0])

        res = minimize(neg, [x0, y0], method="Nelder-Mead", bounds=[self.x_range, self.y_range],
                       options={"xatol": 1e-9 * max(self.length, self.width), "fatol": 1e-14})
        kbest = max(float(k1.ravel()[i]), -float(res.fun))
        px, py = (res.x if -res.fun >= k1.ravel()[i] else (x0, y0))
        return Extremum(float(px), float(py), 1.0 / kbest)

    # -- coordinates --------------------------------------------------------
    def to_work(self, x, y, z):
        """Design (x, y, z) -> work (X, Y, Z) in mm."""
        s = self.scale
        return ((np.asarray(x) - self.x_range[0]) * s, (np.asarray(y) - self.y_range[0]) * s,
                (np.asarray(z) - self.top) * s)

    def from_work(self, X, Y, Z=None):
        s = self.scale
        x = np.asarray(X) / s + self.x_range[0]
        y = np.asarray(Y) / s + self.y_range[0]
        if Z is None:
            return x, y
        return x, y, np.asarray(Z) / s + self.top

    @property
    def stock_size_mm(self):
        """(L, W): the stock's length and width in mm."""
        return self.length * self.scale, self.width * self.scale


#: within this of a depth limit (mm), :func:`check_depth` decides by :meth:`Surface.lowest`
DEPTH_MARGIN_MM = 1e-6


def lowest_local(surface: Surface) -> Extremum:
    """The lowest point of h on the footprint without scipy: the grid of
    :meth:`Surface.lowest`, then from its 5 best points a projected Newton descent
    with the exact gradient and Hessian (a gradient step where the Hessian is not
    positive definite; bounds by projection, an Armijo backtracking line search).

    Its z is the height of a point of the footprint, so it is never below the true
    least; from the same starts it reaches the same local minima as
    :meth:`Surface.lowest` (to about 1e-12 relative), not bit for bit."""
    X, Y = surface.grid()
    H = surface.height(X, Y)
    order = np.argsort(H.ravel())[:5]
    best = Extremum(float(X.ravel()[order[0]]), float(Y.ravel()[order[0]]), float(H.ravel()[order[0]]))
    lo = np.array([surface.x_range[0], surface.y_range[0]])
    hi = np.array([surface.x_range[1], surface.y_range[1]])
    size = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-300))
    for i in order:
        p = np.array([X.ravel()[i], Y.ravel()[i]], dtype=float)
        z = _descend(surface, p, lo, hi, size)
        if z[2] < best.z:
            best = Extremum(*z)
    return best


def _descend(surface: Surface, p, lo, hi, size: float, iters: int = 200):
    """(x, y, h) where a projected Newton descent from ``p`` stops (see lowest_local)."""
    def height(q):
        return float(surface.height(q[0], q[1]))

    f = height(p)
    if not math.isfinite(f):
        return float(p[0]), float(p[1]), math.inf
    with np.errstate(all="ignore"):
        for _ in range(iters):
            g = np.array([float(v) for v in surface.gradient(p[0], p[1])])
            hxx, hxy, hyy = (float(v) for v in surface.hessian(p[0], p[1]))
            if not np.all(np.isfinite(g)):
                break
            free = ~(((p <= lo) & (g > 0)) | ((p >= hi) & (g < 0)))
            if not free.any() or not np.any(g[free]):
                break
            d = np.zeros(2)
            Hm = np.array([[hxx, hxy], [hxy, hyy]])[np.ix_(free, free)]
            gf = g[free]
            step = None
            if np.all(np.isfinite(Hm)):
                try:
                    c = np.linalg.cholesky(Hm)
                    step = -np.linalg.solve(c.T, np.linalg.solve(c, gf))
                except np.linalg.LinAlgError:
                    step = None
            if step is None or not np.all(np.isfinite(step)) or float(step @ gf) >= 0:
                step = -gf * (0.1 * size / float(np.linalg.norm(gf)))
            d[free] = step
            t, moved = 1.0, False
            while t > 1e-30:
                q = np.clip(p + t * d, lo, hi)
                fq = height(q)
                if fq < f - 1e-4 * float(g @ (p - q)) or (fq < f and t < 1e-12):
                    moved = True
                    break
                t *= 0.5
            if not moved:
                break
            done = float(np.max(np.abs(q - p))) <= 1e-15 * size
            p, f = q, fq
            if done:
                break
    return float(p[0]), float(p[1]), f


def check_depth(spec, surface: Surface) -> float:
    """Refuse (SpecError, exit 2) a cut deeper than the stock, ``stock.depth_limit``
    or ``tool.reach`` allow. Returns the depth in mm.

    The depth comes from :func:`lowest_local` (no scipy); within DEPTH_MARGIN_MM of a
    limit, or over one, from :meth:`Surface.depth_mm` (scipy's L-BFGS-B, what ``fabkit
    check`` reports), so the verdict and the message are those of that search."""
    limits = []
    if spec.has("stock"):
        limits.append(("stock.depth_limit", spec.stock.depth_limit))
        limits.append(("stock.thickness", spec.stock.thickness))
    if spec.has("tool"):
        limits.append(("tool.reach", spec.tool.reach))
    depth = max(0.0, (surface.top - lowest_local(surface).z) * surface.scale)
    if any(depth > limit - DEPTH_MARGIN_MM for _, limit in limits):
        depth = surface.depth_mm()
    for key, limit in limits:
        if depth > limit:
            low = surface.lowest()
            raise SpecError(
                f"the surface is {depth:.3f} mm deep (lowest at x={low.x:.4g}, y={low.y:.4g}; "
                f"deeper than the limit over {_deep_region(surface, limit)}), "
                f"{depth - limit:.3f} mm more than the limit {limit:g} mm", file=spec.path, key=key)
    return depth


def _deep_region(surface: Surface, limit_mm: float) -> str:
    """'x a to b, y c to d' (design units): the range of the footprint where the
    surface is deeper than ``limit_mm`` (a 401 x 401 grid, the lowest point included)."""
    X, Y = surface.grid(401)
    deep = (surface.top - surface.height(X, Y)) * surface.scale > limit_mm
    low = surface.lowest()
    xs, ys = np.r_[X[deep], low.x], np.r_[Y[deep], low.y]

    def rng(v):
        lo, hi = float(v.min()), float(v.max())
        return f"{lo:.4g}" if hi - lo <= 1e-9 * max(1.0, abs(hi)) else f"{lo:.4g} to {hi:.4g}"
    return f"x {rng(xs)}, y {rng(ys)}"


def principal_curvatures(hx, hy, hxx, hxy, hyy):
    """(k1, k2), k1 >= k2, of the graph z = h with the upward normal, from its first
    and second derivatives (arrays of one shape; 1/length). Positive: concave up."""
    w = np.sqrt(1.0 + hx * hx + hy * hy)
    E, F, G = 1.0 + hx * hx, hx * hy, 1.0 + hy * hy
    L, M, N = hxx / w, hxy / w, hyy / w
    det = E * G - F * F
    K = (L * N - M * M) / det
    H = (E * N - 2.0 * F * M + G * L) / (2.0 * det)
    disc = np.sqrt(np.maximum(H * H - K, 0.0))
    return H + disc, H - disc
