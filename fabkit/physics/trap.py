"""The trapping energy: below it a launch can end in no way but ``captured``.

With no energy input (viscous damping, or the nonlinear damping in the
simplified model, only ever remove energy), the energy per unit (1 + k) m

    E = 1/2 (xd^2 + yd^2 + zd^2) + g~ h      (full model; zd = 0 in the simplified one)

never increases, and the ball stays in the sublevel set g~ h(x, y) <= E. Every
terminal event lies on the boundary of the region

    D = [max(start, x0 + margin), x1 - margin] x [y0 + margin, y1 - margin]

(``escaped`` at x = start, ``flew_off`` on the shrunk footprint) or above the
level top - margin (``flew_off`` in z), or needs the normal-force bracket of eq.
(xyODE) to vanish (``lost_contact``, full model). So once a ball inside D has

    E < E* = min( g~ min_{boundary of D} h,  g~ (top - margin),
                  g~ h_min(D) + g~ / (2 kappa) )                     (full model)

none of these can happen any more: it is captured for good, and the simulator
may stop it at once instead of integrating to ``t_max``. The third term bounds
the bracket: B = v^T Hess(h) v + g~ >= g~ - kappa |v|^2 with kappa the largest
negative curvature (-min eigenvalue of the Hessian) on D, and |v|^2 <= 2 (E - g~
h_min). Only the ``captured`` launches are affected (their end time, bounce
count and end state become those at the moment they were found trapped); every
escaped, flew_off and lost_contact result is unchanged.

Accuracy: the minima over the boundary and over D are lower bounds from dense
samples less twice the largest sampled second derivative times the sampling
error bound (spacing^2 / 8); kappa is the sampled maximum times 1.5. E* is then
lowered by max(1e-9, 100 rtol) of the energy scale, more than the integrator's own
energy error.
"""

from __future__ import annotations

import numpy as np

from ..surface import principal_curvatures

EDGE_SAMPLES = 4097     # points per boundary edge
GRID = 257              # points per axis over D (h_min, kappa)


def _edge_min(fns, xa, ya, xb, yb, n=EDGE_SAMPLES) -> float:
    """Lower bound of h on the segment (xa, ya)-(xb, yb)."""
    s = np.linspace(0.0, 1.0, n)
    x, y = xa + (xb - xa) * s, ya + (yb - ya) * s
    dx, dy = xb - xa, yb - ya
    with np.errstate(all="ignore"):     # a surface that overflows here gives -inf below
        h, _, _, hxx, hxy, hyy = fns.all(x, y)
        htt = hxx * dx * dx + 2 * hxy * dx * dy + hyy * dy * dy      # d2h/ds2 (s in [0, 1])
    if not (np.isfinite(h).all() and np.isfinite(htt).all()):
        return -np.inf
    step = 1.0 / (n - 1)
    return float(h.min() - 2.0 * np.abs(htt).max() * step * step / 8.0)


def trap_energy(problem, rel_margin: float = 1e-9) -> float | None:
    """E* (design units^2/s^2, per unit (1 + k) m) for ``problem``, or None when the
    bound does not apply (nonlinear damping in the full model can feed energy in,
    an empty region D, or a surface that is not finite on D). ``rel_margin``: E* is
    lowered by this fraction of the energy scale (the integrator passes 100 rtol, so
    its own energy error cannot carry a lane across)."""
    if problem.model == "full" and float(problem.nonlinear_damping) > 0:
        return None
    if problem.model == "ball":
        return _ball_trap_energy(problem, rel_margin)
    m = float(problem.margin)
    x0, x1, y0, y1 = region(problem)
    if not (np.isfinite([x0, x1, y0, y1]).all() and x1 > x0 and y1 > y0):
        return None
    fns, gt = problem.fns, problem.g_tilde
    m_b = min(_edge_min(fns, x0, y0, x1, y0), _edge_min(fns, x0, y1, x1, y1),
              _edge_min(fns, x0, y0, x0, y1), _edge_min(fns, x1, y0, x1, y1))
    bounds = [gt * m_b, gt * (float(problem.top) - m)]
    xs, ys = np.linspace(x0, x1, GRID), np.linspace(y0, y1, GRID)
    X, Y = np.meshgrid(xs, ys)
    with np.errstate(all="ignore"):
        h, _, _, hxx, hxy, hyy = fns.all(X, Y)
    if not all(np.isfinite(a).all() for a in (h, hxx, hxy, hyy)):
        return None
    dx, dy = xs[1] - xs[0], ys[1] - ys[0]
    curv = np.maximum(np.abs(hxx), np.abs(hyy)).max() + np.abs(hxy).max()
    h_min = float(h.min() - 2.0 * curv * (dx * dx + dy * dy) / 8.0)
    if problem.model == "full":
        # smallest eigenvalue of [[hxx, hxy], [hxy, hyy]]
        lam = 0.5 * (hxx + hyy) - np.sqrt(0.25 * (hxx - hyy) ** 2 + hxy ** 2)
        kappa = 1.5 * max(0.0, float(-lam.min()))
        if kappa > 0:
            bounds.append(gt * h_min + gt / (2.0 * kappa))
    e_star = min(bounds)
    if not np.isfinite(e_star):
        return None
    e_star -= max(1e-9, float(rel_margin)) * max(abs(e_star), gt * (abs(h_min) + abs(m_b) + 1.0))
    if e_star <= gt * h_min:
        return None          # no state inside D is below it
    return float(e_star)


def region(problem) -> tuple[float, float, float, float]:
    """D as (x0, x1, y0, y1)."""
    m = float(problem.margin)
    return (max(float(problem.start), float(problem.x_range[0]) + m), float(problem.x_range[1]) - m,
            float(problem.y_range[0]) + m, float(problem.y_range[1]) - m)


def _ball_trap_energy(problem, rel_margin: float) -> float | None:
    """E* for the finite ball (per unit (1 + k) m: E = 1/2 |v|^2 + k/(2 (1 + k)) u^2 + g~ z_C,
    z_C = h + r n_z the centre's height). None with ``ball.friction`` (slip is not bounded
    by the energy: a ball at rest on a slope can need more friction than given).

    Exits and their bounds, E >= 1/2 |v|^2 + g~ z_C:
    * the contact point on the boundary of D: E >= g~ min over the boundary of z_C;
    * the contact point at top - margin: E >= g~ (top - margin + r min n_z);
    * bridging (r kappa_1 >= 1): E >= g~ min of z_C where r kappa_1 >= 0.9 (sampled);
    * loss of contact: N/m = g n_z - v . n' and, in principal directions, v . n' =
      -sum kappa_i / (1 - r kappa_i) w_i^2 (w = v's components), so N > 0 while
      |v|^2 < g n_z / lambda, lambda = max over convex directions of |kappa| / (1 + r |kappa|):
      E >= g~ min z_C + g min n_z / (2 lambda).
    Sampled minima are lowered by the sampling error bound as in :func:`trap_energy`;
    lambda is the sampled maximum times 1.5."""
    from . import ball as B

    if np.isfinite(float(problem.friction)):
        return None
    m = float(problem.margin)
    x0, x1, y0, y1 = region(problem)
    if not (np.isfinite([x0, x1, y0, y1]).all() and x1 > x0 and y1 > y0):
        return None
    r, gt, g = float(problem.radius), problem.g_tilde, float(problem.g)
    jet = B.jet_function(problem.fns)

    def zc_kappa(x, y):
        with np.errstate(all="ignore"):
            j = jet(x, y)
            geo = B.geometry(j, r)
            zc = j[0] + r * geo["n"][2]
            k1 = B.max_concave_curvature(j)
            hxx, hxy, hyy = j[3], j[4], j[5]
            spread = np.maximum(np.abs(hxx), np.abs(hyy)) + np.abs(hxy)
        return zc, k1, geo["n"][2], spread, j

    edges = []
    s = np.linspace(0.0, 1.0, EDGE_SAMPLES)
    for xa, ya, xb, yb in ((x0, y0, x1, y0), (x0, y1, x1, y1), (x0, y0, x0, y1), (x1, y0, x1, y1)):
        zc, _, _, spread, _ = zc_kappa(xa + (xb - xa) * s, ya + (yb - ya) * s)
        if not (np.isfinite(zc).all() and np.isfinite(spread).all()):
            return None
        step = max(abs(xb - xa), abs(yb - ya)) / (EDGE_SAMPLES - 1)
        # z_C's second derivative along the edge is bounded by about h's (r n_z adds r |h''|^2 terms)
        edges.append(float(zc.min() - 2.0 * spread.max() * (1.0 + r * spread.max()) * step * step / 8.0))
    xs, ys = np.linspace(x0, x1, GRID), np.linspace(y0, y1, GRID)
    X, Y = np.meshgrid(xs, ys)
    zc, k1, nz, spread, j = zc_kappa(X, Y)
    if not all(np.isfinite(a).all() for a in (zc, k1, nz, spread)):
        return None
    dx, dy = xs[1] - xs[0], ys[1] - ys[0]
    err = 2.0 * spread.max() * (1.0 + r * spread.max()) * (dx * dx + dy * dy) / 8.0
    zc_min = float(zc.min() - err)
    bounds = [gt * min(edges), gt * (float(problem.top) - m + r * float(nz.min()))]
    near = r * k1 >= 0.9
    if near.any():
        bounds.append(gt * (float(zc[near].min()) - err))
    # the most convex curvature: the smaller principal curvature (negative where convex)
    _, k2 = principal_curvatures(*j[1:6])
    convex = np.maximum(-k2, 0.0)
    lam = 1.5 * float((convex / (1.0 + r * convex)).max())
    if lam > 0:
        bounds.append(gt * zc_min + g * float(nz.min()) / (2.0 * lam))
    e_star = min(bounds)
    if not np.isfinite(e_star):
        return None
    e_star -= max(1e-9, float(rel_margin)) * max(abs(e_star), gt * (abs(zc_min) + abs(min(edges)) + 1.0))
    if e_star <= gt * zc_min:
        return None
    return float(e_star)
