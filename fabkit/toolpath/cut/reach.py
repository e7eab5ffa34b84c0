"""The reachable height: the lowest a ball of radius R can cut at a point.

Where a ball touching the design (centre R along its normal) is free of the surface,
the design itself; elsewhere (a valley tighter than the ball, a V crease, a wall's
foot) the lowest surface of the balls resting on the design, from the exact drop
cutter heights (:mod:`fabkit.toolpath.finish.compensate`). The verification of the cut
(:func:`fabkit.toolpath.cut.verify.verify_cut`) separates the material a program leaves
where the ball reaches it from the material no ball position removes by it.
"""

from __future__ import annotations

import math

import numpy as np



#: where the ball cannot reach the design (a valley, a crease or a wall's foot tighter than
#: it), the floor counts the balls centred up to OVERHANG x R beyond the footprint (the
#: planner's edge passes stand up to 0.999 R out): at such a region's open end on a stock
#: edge a ball hanging off the edge reaches deeper than any ball over the stock (a 45-degree
#: V groove under a 6 mm ball: 0.49 mm deeper 0.1 mm from the edge, 1.19 mm on the edge
#: line). Where the ball reaches the design (its normal position is free, overhanging or
#: not) the design itself is the floor, edges included.
OVERHANG = 0.999
#: along the passes (``along``: their direction) the balls hang off the pass ends up to the
#: planner's last node, 0.99 R out (a ball further out touches the edge with a tip path of
#: nearly vertical tangent, which no chord of the program follows without gouging)
OVERHANG_ALONG = 0.99
REACH_GRID = 1.0 / 8.0                              # x R: the grid of start centres
REACH_SEARCH = 24                                   # compass steps, at most
REACH_DIRS = 8          # compass directions (4 ended up to 0.045 mm higher on 2*sin(x) + 2*sin(y))
REACH_STEP_MIN = 1e-5                               # x R: a point's search stops below this step
REACH_METHOD = "descend"                            # or "compass": the search before the descent
REACH_ITERS = 32                                    # the descent's drops per point, at most
REACH_SHARE_ROUNDS = 3
REACH_SECOND = 0.25                                 # x R: see reachable_height
REACH_ITERS_SECOND = 12                             # the second start's drops, at most
REACH_SHARE_CELL = 1.0 / 64.0                       # x R: one shared ball per cell (the lowest centre)
REACH_LEAD = 1.0 / 8.0                              # x R: one lead point per cell
REACH_POLISH = 1.0 / 128.0                          # x R: the compass's first step after the descent
REACH_PROBE = 1e-3                                  # x R: the step that decides whether it runs
REACH_ITERS_REST = 6                                # the other points' drops, at most


def reachable_height(ws, px, py, R: float, chunk: int = 20000, overhang: float | None = None,
                     return_scale: bool = False):
    """Lowest height a ball of radius R can cut at the points (X, Y) (work mm): the
    design where a ball touching the design there (centre R along its normal) is free
    of the surface; elsewhere (a valley tighter than the ball, a V crease) the lowest
    surface, above the point, of the balls resting on the design (exact drop-cutter
    heights) centred within R of it: g(c) = Z(c) + R - sqrt(R^2 - |c - p|^2), minimised
    over c. Starts: the centre above the point, the normal-offset centre and a grid of
    centres (:data:`REACH_GRID` x R) over the stock. The lowest ball rests on two walls
    (a kink of Z, where g is lowest) or stands at the edge of the allowed centres, so
    the search is a model descent (:func:`_descend`): Z modelled as the larger of two
    linear pieces, the exact heights and slopes of the drops on either side of the kink
    (the slope from the contact point q: dZ/dc = (q - c) / sqrt(R^2 - |q - c|^2)), each
    step the model's lowest ball in closed form. Points share: one lead point per cell
    of :data:`REACH_LEAD` x R, and every point within R of the stock's edges, is searched
    from the grid's best and from the best beyond (or over) the edge, then from the
    other lead points' balls, then by a compass search (8 directions, first step
    :data:`REACH_POLISH` x R, halved to 1e-5 R) where the descent did not settle on a
    kink; the other points start from the lead points' balls and descend at most
    :data:`REACH_ITERS_REST` drops. Every centre kept is a real ball position, so the
    height is an upper bound of the lowest one (the material it calls unreachable is
    never less than there is); on a V crease it is within 1e-6 mm of the closed form
    and on curved creases and at the stock's edges within 2e-5 mm of a brute-force
    search (tests/test_reach.py); on a parabolic valley tighter than the ball within
    3e-4 mm of the centred ball's closed form (tested). :data:`REACH_METHOD` =
    'compass' runs the search this replaced (the compass from the grid's best, first
    step REACH_GRID / 2 x R: 10-20x the drops, and stalled up to 0.33 mm high on a
    crease oblique to its directions or at a stock edge). Centres farther than
    ``overhang`` (mm, default :data:`OVERHANG` x R; a pair: beyond the x and the y edges)
    beyond the footprint are not tried (see :data:`OVERHANG`). Returns (height, reachable), and with ``return_scale`` the
    normal scale of the reachable surface: 1 / sqrt(1 + slope^2) of the design where the
    ball reaches it, and where it cannot, of the lowest ball's surface above the point
    (the surface the ball leaves there is that ball's: d from its centre, the scale is
    sqrt(R^2 - d^2) / R; never below the design's)."""
    from ..finish.compensate import compensate

    overhang = OVERHANG * R if overhang is None else overhang
    ox_, oy_ = (overhang, overhang) if np.isscalar(overhang) else (float(overhang[0]), float(overhang[1]))

    def drop(qx, qy):
        shape = qx.shape
        qx, qy = qx.ravel(), qy.ravel()
        z = np.concatenate([compensate(ws, qx[i:i + chunk], qy[i:i + chunk], R)
                            for i in range(0, qx.size, chunk)]) if qx.size else np.zeros(0)
        return z.reshape(shape)

    def drop_info(qx, qy):
        """Tip heights and contact points (1-D)."""
        out = [compensate(ws, qx[i:i + chunk], qy[i:i + chunk], R, return_info=True)
               for i in range(0, qx.size, chunk)]
        if not out:
            return np.zeros(0), np.zeros(0), np.zeros(0)
        return (np.concatenate([z for z, _ in out]), np.concatenate([f.contact_x for _, f in out]),
                np.concatenate([f.contact_y for _, f in out]))

    H, hx, hy = ws.all(px, py)[:3]
    design = np.minimum(H, 0.0)
    with np.errstate(all="ignore"):
        w = np.sqrt(1.0 + hx * hx + hy * hy)
        top = H >= 0
        nx, ny, nz = np.where(top, 0.0, -hx / w), np.where(top, 0.0, -hy / w), np.where(top, 1.0, 1.0 / w)
    scale = np.where(top, 1.0, np.nan_to_num(1.0 / w, nan=1.0))
    cx, cy = px + R * nx, py + R * ny
    tip = design + R * nz - R
    Z = drop(cx, cy)
    ok = top | ~np.isfinite(Z) | (Z <= tip + 1e-7)
    out = design.copy()
    bad = np.nonzero(~ok)[0]
    if bad.size:
        bx, by = px[bad], py[bad]

        def surface_at(ox, oy, idx=slice(None)):
            """g at the points ``idx`` for centre offsets (ox, oy) (arrays (m, k)); +inf
            where the ball misses the point, touches nothing, or stands farther beyond
            the footprint than ``overhang``."""
            qx, qy = bx[idx][:, None] + ox, by[idx][:, None] + oy
            zq = drop(qx, qy)
            with np.errstate(invalid="ignore"):
                low = zq + R - np.sqrt(R * R - ox * ox - oy * oy)
            ex = np.maximum(np.maximum(-qx, qx - ws.L), 0.0)
            ey = np.maximum(np.maximum(-qy, qy - ws.W), 0.0)
            over = (ex > ox_) | (ey > oy_) | (ex * ex + ey * ey > max(ox_, oy_) ** 2)
            return np.where(np.isfinite(low) & (ox * ox + oy * oy <= R * R) & ~over, low, np.inf)

        def allowed(ox, oy):
            qx, qy = bx + ox, by + oy
            ex = np.maximum(np.maximum(-qx, qx - ws.L), 0.0)
            ey = np.maximum(np.maximum(-qy, qy - ws.W), 0.0)
            over = (ex > ox_) | (ey > oy_) | (ex * ex + ey * ey > max(ox_, oy_) ** 2)
            return (ox * ox + oy * oy <= R * R) & ~over

        # starts: the centre above the point, the normal-offset centre (its drop is Z),
        # and the lowest of the balls centred on a grid (REACH_GRID x R) over the stock
        # within R of the point
        nox, noy = (cx - px)[bad], (cy - py)[bad]
        with np.errstate(invalid="ignore"):
            gn = Z[bad] + R - np.sqrt(R * R - nox * nox - noy * noy)
        gn = np.where(np.isfinite(gn) & allowed(nox, noy), gn, np.inf)
        g0 = surface_at(np.zeros((bad.size, 1)), np.zeros((bad.size, 1)))[:, 0]
        lower = gn < g0
        best, bo_x, bo_y = np.where(lower, gn, g0), np.where(lower, nox, 0.0), np.where(lower, noy, 0.0)
        gs, gxs, gys = _grid_starts(ws, bx, by, R, drop, (ox_, oy_), split=True)
        first = np.where(gs[1] < gs[0], 1, 0)
        gb, gx_, gy_ = (np.choose(first, v) for v in (gs, gxs, gys))
        lower = gb < best
        best, bo_x, bo_y = np.where(lower, gb, best), np.where(lower, gx_, bo_x), np.where(lower, gy_, bo_y)
        if REACH_METHOD == "compass":
            _compass(surface_at, best, bo_x, bo_y, R)
        else:
            def probe(ox, oy, idx):
                """One ball per point ``idx``, centred at offset (ox, oy) from it: (g as
                surface_at, the centre's height Zc, dZc/dX, dZc/dY from the contact)."""
                qx, qy = bx[idx] + ox, by[idx] + oy
                Zc, qcx, qcy = drop_info(qx, qy)
                Zc = Zc + R
                with np.errstate(invalid="ignore", divide="ignore"):
                    low = Zc - np.sqrt(R * R - ox * ox - oy * oy)
                    ux, uy = qcx - qx, qcy - qy
                    sq = np.sqrt(np.maximum(R * R - ux * ux - uy * uy, 1e-24 * R * R))
                ex = np.maximum(np.maximum(-qx, qx - ws.L), 0.0)
                ey = np.maximum(np.maximum(-qy, qy - ws.W), 0.0)
                over = (ex > ox_) | (ey > oy_) | (ex * ex + ey * ey > max(ox_, oy_) ** 2)
                g = np.where(np.isfinite(low) & (ox * ox + oy * oy <= R * R) & ~over, low, np.inf)
                return g, Zc, ux / sq, uy / sq

            box = (-ox_ - bx, ws.L + ox_ - bx, -oy_ - by, ws.W + oy_ - by)

            def descend(sel, iters):
                """_descend on the points ``sel`` (in place); the unsettled among them."""
                b_, x_, y_ = best[sel], bo_x[sel], bo_y[sel]
                mv = _descend(lambda ox, oy, idx: probe(ox, oy, sel[idx]), b_, x_, y_, R,
                              tuple(v[sel] for v in box), iters)
                best[sel], bo_x[sel], bo_y[sel] = b_, x_, y_
                return sel[mv]

            def share(src, dst, iters):
                """Neighbouring points share their lowest balls: the points ``dst`` try
                those of ``src`` (real balls: their centre heights are drops) and descend
                again from one lower than their own (another basin)."""
                for _ in range(REACH_SHARE_ROUNDS):
                    moved = _share(bx, by, best, bo_x, bo_y, R, src, dst)
                    if not moved.size:
                        break
                    descend(moved, iters)

            # the lead points (the first in each cell of REACH_LEAD x R) are searched
            # fully: from the grid's best and from the best on the other side of the
            # stock's edge (a ball over the stock, or one hanging off it) when within
            # REACH_SECOND of it (another basin), then from each other's balls, then by the
            # compass where the descent did not settle on a kink. The other points start
            # from the lead points' balls (next to their own lowest: a short descent).
            # (every point within R of the stock's edges is a lead point: balls hanging off
            # an edge make other basins there)
            edge = (bx < R) | (bx > ws.L - R) | (by < R) | (by > ws.W - R)
            lead, rest = _leaders(bx, by, REACH_LEAD * R, edge)
            qx, qy = (bx + bo_x)[lead], (by + bo_y)[lead]
            side = np.where((qx < 0) | (qx > ws.L) | (qy < 0) | (qy > ws.W), 1, 0)
            g2, x2, y2 = (np.choose(1 - side, [v[0][lead], v[1][lead]]) for v in (gs, gxs, gys))
            two = np.nonzero(np.isfinite(g2) & (g2 < best[lead] + REACH_SECOND * R))[0]
            unsettled = np.zeros(bad.size, bool)
            if two.size:
                # the second start's descent, then the first's; the lower kept
                sel = lead[two]
                first_start = best[sel], bo_x[sel], bo_y[sel]
                best[sel], bo_x[sel], bo_y[sel] = g2[two], x2[two], y2[two]
                unsettled[descend(sel, REACH_ITERS_SECOND)] = True
                second = best[sel], bo_x[sel], bo_y[sel]
                best[sel], bo_x[sel], bo_y[sel] = first_start
                mv2 = unsettled[sel]
                unsettled[sel] = False
            unsettled[descend(lead, REACH_ITERS)] = True
            if two.size:
                lo = second[0] < best[sel]
                k = sel[lo]
                best[k], bo_x[k], bo_y[k] = second[0][lo], second[1][lo], second[2][lo]
                unsettled[k] = mv2[lo]
            slow = np.nonzero(unsettled)[0]
            share(lead, lead, REACH_ITERS)
            if slow.size:
                # first one compass step of REACH_PROBE x R: where none lowers the point,
                # it stays (the descent's crawl ended on a ball no nearby one is below)
                dirs = 2 * np.pi * np.arange(REACH_DIRS) / REACH_DIRS
                tx = bo_x[slow, None] + REACH_PROBE * R * np.cos(dirs)
                ty = bo_y[slow, None] + REACH_PROBE * R * np.sin(dirs)
                G = surface_at(tx, ty, slow)
                j = np.argmin(G, axis=1)
                r = np.arange(slow.size)
                up = G[r, j] < best[slow]
                k = slow[up]
                best[k], bo_x[k], bo_y[k] = G[r, j][up], tx[r, j][up], ty[r, j][up]
                slow = k
            if slow.size:
                sb, sx_, sy_ = best[slow], bo_x[slow], bo_y[slow]
                _compass(lambda tx, ty, idx, m=slow: surface_at(tx, ty, m[idx]), sb, sx_, sy_, R,
                         REACH_POLISH)
                best[slow], bo_x[slow], bo_y[slow] = sb, sx_, sy_
            if rest.size:
                _share(bx, by, best, bo_x, bo_y, R, lead, rest)
                descend(rest, REACH_ITERS_REST)
                share(np.arange(bad.size), rest, REACH_ITERS_REST)
        out[bad] = np.maximum(design[bad], np.minimum(best, 0.0))
        d2 = np.minimum(bo_x * bo_x + bo_y * bo_y, R * R)
        fillet = np.where(np.isfinite(best) & (best < 0.0), np.sqrt(R * R - d2) / R, 1.0)
        scale[bad] = np.maximum(scale[bad], fillet)
    return (out, ok, scale) if return_scale else (out, ok)


def _line_min(gx, gy, u0x, u0y, tx, ty, R):
    """Along the line u0 + t (tx, ty) (u0 its point nearest the origin, (tx, ty) a unit
    vector), the point where g . u - sqrt(R^2 - |u|^2) is lowest (closed form; nan
    where the line misses the disk of radius R)."""
    with np.errstate(invalid="ignore"):
        rho = np.sqrt(R * R - u0x * u0x - u0y * u0y)
        sig = gx * tx + gy * ty
        t = -sig * rho / np.sqrt(1.0 + sig * sig)
    return u0x + t * tx, u0y + t * ty


def _model_min(A, B, hb, box, R):
    """The lowest point of the model max(la, lb)(u) - sqrt(R^2 - |u|^2) over the box of
    allowed centre offsets (xlo, xhi, ylo, yhi): la, lb linear (z, gx, gy, ux, uy: the
    value z and slope g at u), lb only where ``hb``. The model is convex: its lowest
    point is the best of the stationary points of each active set (one piece or the
    kink line la = lb; free, on one side of the box, or at a corner). Returns
    (ux, uy, M); M = inf where no candidate is in the box."""
    xlo, xhi, ylo, yhi = box
    zero, one = np.zeros_like(xlo), np.ones_like(xlo)
    cx, cy = [], []
    # one piece: free, and along each side of the box
    for P in (A, B):
        s1 = np.sqrt(1.0 + P[1] * P[1] + P[2] * P[2])
        cx.append(-R * P[1] / s1)
        cy.append(-R * P[2] / s1)
        for c in (xlo, xhi):
            ux, uy = _line_min(P[1], P[2], c, zero, zero, one, R)
            cx.append(ux)
            cy.append(uy)
        for c in (ylo, yhi):
            ux, uy = _line_min(P[1], P[2], zero, c, one, zero, R)
            cx.append(ux)
            cy.append(uy)
    # the kink line la = lb: n . u = d0
    dx, dy = A[1] - B[1], A[2] - B[2]
    dn = np.hypot(dx, dy)
    with np.errstate(invalid="ignore", divide="ignore"):
        rhs = (B[0] - B[1] * B[3] - B[2] * B[4]) - (A[0] - A[1] * A[3] - A[2] * A[4])
        nx, ny, d0 = dx / dn, dy / dn, rhs / dn
        ux, uy = _line_min(A[1], A[2], d0 * nx, d0 * ny, -ny, nx, R)
        cx.append(ux)
        cy.append(uy)
        for c in (xlo, xhi):                  # the kink line across a side
            cx.append(c)
            cy.append((d0 - nx * c) / ny)
        for c in (ylo, yhi):
            cx.append((d0 - ny * c) / nx)
            cy.append(c)
    for a in (xlo, xhi):                      # the corners
        for b in (ylo, yhi):
            cx.append(a)
            cy.append(b)
    UX, UY = np.stack(cx), np.stack(cy)
    with np.errstate(invalid="ignore"):
        la = A[0] + A[1] * (UX - A[3]) + A[2] * (UY - A[4])
        lb = np.where(hb, B[0] + B[1] * (UX - B[3]) + B[2] * (UY - B[4]), -np.inf)
        M = np.maximum(la, lb) - np.sqrt(R * R - UX * UX - UY * UY)
    eps = 1e-12 * R
    feas = (np.isfinite(M) & (UX >= xlo - eps) & (UX <= xhi + eps) & (UY >= ylo - eps) & (UY <= yhi + eps))
    M = np.where(feas, M, np.inf)
    k = np.argmin(M, axis=0)
    r = np.arange(k.size)
    return np.clip(UX[k, r], xlo, xhi), np.clip(UY[k, r], ylo, yhi), M[k, r]


def _descend(probe, best, bo_x, bo_y, R, box, iters=None):
    """Lower each point's best ball (in place) by a model descent: the centre height is
    modelled as the larger of two linear pieces, the drops' exact heights and
    slopes (from their contacts) on either side of the kink where the lowest ball rests
    on two walls; each step drops the model's lowest ball (closed form, within the
    allowed centres ``box``: offsets (xlo, xhi, ylo, yhi) per point) within a trust
    radius. Every value kept is a real drop. Returns the points not settled on a kink
    after REACH_ITERS drops (bool)."""
    n = best.size
    act = np.arange(n)
    g, za, ax, ay = probe(bo_x, bo_y, act)
    ok = np.isfinite(za) & np.isfinite(ax) & np.isfinite(ay)
    uax, uay = bo_x.copy(), bo_y.copy()
    zb, bgx, bgy, ubx, uby = (np.zeros(n) for _ in range(5))
    has_b = np.zeros(n, bool)
    delta = np.full(n, 0.5 * REACH_GRID * R)
    refresh = np.zeros(n, bool)
    fresh = np.zeros(n, bool)                       # the last drop was a refresh
    nref = np.zeros(n)                              # refreshes in a row on the same side
    prev = np.full(n, 0.5 * REACH_GRID * R)        # the last model step's length
    last = np.zeros(n, np.int8)
    act = act[ok & np.isfinite(best)]
    for _ in range(REACH_ITERS if iters is None else iters):
        if not act.size:
            break
        A = (za[act], ax[act], ay[act], uax[act], uay[act])
        B = (zb[act], bgx[act], bgy[act], ubx[act], uby[act])
        hb = has_b[act]
        tx, ty, M = _model_min(A, B, hb, tuple(b[act] for b in box), R)
        none = ~np.isfinite(M)
        sx, sy = tx - bo_x[act], ty - bo_y[act]
        sn = np.hypot(sx, sy)
        f = np.where(sn > delta[act], delta[act] / np.maximum(sn, 1e-300), 1.0)
        sx, sy = np.where(none, 0.0, sx * f), np.where(none, 0.0, sy * f)
        sn = np.hypot(sx, sy)
        # after a step that did not lower the point, the piece not updated by it may be
        # stale (a curved wall): drop a ball just across the kink line on its side instead
        # (or that is stale: linearised farther from the best ball than 8 last steps)
        la0 = last[act] == 0
        ox_, oy_ = np.where(la0, B[3], A[3]), np.where(la0, B[4], A[4])
        bx_, by_ = bo_x[act], bo_y[act]
        sp = np.maximum(prev[act], 1e-7 * R)
        rf = hb & ~fresh[act] & (refresh[act] | (np.hypot(ox_ - bx_, oy_ - by_) > 8.0 * sp))
        ex, ey = np.where(la0, B[1] - A[1], A[1] - B[1]), np.where(la0, B[2] - A[2], A[2] - B[2])
        en = np.maximum(np.hypot(ex, ey), 1e-300)
        # across the model's kink line: twice the model's distance to it, plus the last step
        with np.errstate(invalid="ignore"):
            gap = np.abs((A[0] + A[1] * (bx_ - A[3]) + A[2] * (by_ - A[4]))
                         - (B[0] + B[1] * (bx_ - B[3]) + B[2] * (by_ - B[4]))) / en
        # (4 times farther after each that landed on the same side)
        eps = np.minimum(np.maximum(np.nan_to_num(2.0 * gap), 1e-6 * R) * 4.0 ** nref[act], 0.5 * REACH_GRID * R)
        # (shortened to stay a ball the point allows: within R of it and in the box)
        xlo, xhi, ylo, yhi = (b[act] for b in box)
        for _ in range(8):
            qx, qy = bx_ + eps * ex / en, by_ + eps * ey / en
            out = (qx * qx + qy * qy >= R * R) | (qx < xlo) | (qx > xhi) | (qy < ylo) | (qy > yhi)
            eps = np.where(out, 0.25 * eps, eps)
        sx, sy = np.where(rf, eps * ex / en, sx), np.where(rf, eps * ey / en, sy)
        none &= ~rf
        nx2, ny2 = bo_x[act] + sx, bo_y[act] + sy
        gn, zn, gxn, gyn = probe(nx2, ny2, act)
        up = gn < best[act]
        ia = act[up]
        best[ia], bo_x[ia], bo_y[ia] = gn[up], nx2[up], ny2[up]
        delta[act] = np.where(up, np.minimum(np.maximum(delta[act], 2 * sn), 0.25 * R),
                              np.where(rf, delta[act], 0.5 * sn))
        refresh[act] = ~up & ~rf
        fresh[act] = rf
        prev[act] = np.where(rf, prev[act], sn)
        sn = np.where(rf, eps, sn)
        # the new piece replaces the one whose slope is nearer (the first other slope: b)
        fin = np.isfinite(zn) & np.isfinite(gxn) & np.isfinite(gyn)
        da = np.hypot(gxn - A[1], gyn - A[2])
        near_a = da <= np.hypot(gxn - B[1], gyn - B[2])
        new_b = ~hb & (da > 1e-9)
        to_a = fin & ((hb & near_a) | (~hb & ~new_b))
        to_b = fin & ((hb & ~near_a) | new_b)
        for Pz, Px, Py, Pux, Puy, sel in ((za, ax, ay, uax, uay, to_a), (zb, bgx, bgy, ubx, uby, to_b)):
            i = act[sel]
            Pz[i], Px[i], Py[i], Pux[i], Puy[i] = zn[sel], gxn[sel], gyn[sel], nx2[sel], ny2[sel]
        has_b[act[to_b]] = True
        # a refresh that updated the piece it meant to leave fresh (the same side) counts
        same = rf & np.where(la0, to_a, to_b)
        nref[act] = np.where(same, nref[act] + 1, 0)
        last[act[to_a]] = 0
        last[act[to_b]] = 1
        tol = 1e-4 * R
        near = has_b[act] & (np.hypot(uax[act] - bo_x[act], uay[act] - bo_y[act]) < tol) \
            & (np.hypot(ubx[act] - bo_x[act], uby[act] - bo_y[act]) < tol)
        still = (sn > 1e-9 * R) & (delta[act] > 1e-9 * R)
        act = act[~none & (still | ~near)]
    # settled: both pieces linearised next to the best ball, on either side of its kink
    # (the others, still moving or stopped on a model of one wall, are for the compass)
    tol = 1e-4 * R
    settled = has_b & (np.hypot(uax - bo_x, uay - bo_y) < tol) & (np.hypot(ubx - bo_x, uby - bo_y) < tol) \
        & (np.hypot(ax - bgx, ay - bgy) > 1e-3)
    moving = np.isfinite(best) & ~settled
    moving[act] = True
    return moving


def _share(bx, by, best, bo_x, bo_y, R, src, dst):
    """Offer the points ``dst`` the balls the points ``src`` ended on (in place): per cell
    of REACH_SHARE_CELL x R the ball with the lowest centre, at its exact height. Returns
    the indices of the points it lowered."""
    src = src[np.isfinite(best[src])]
    if not src.size or not dst.size:
        return np.zeros(0, dtype=np.intp)
    cx, cy = bx[src] + bo_x[src], by[src] + bo_y[src]
    zc = best[src] + np.sqrt(np.maximum(R * R - bo_x[src] ** 2 - bo_y[src] ** 2, 0.0))
    h = REACH_SHARE_CELL * R
    key = np.floor(cx / h).astype(np.int64) * 1_000_003 + np.floor(cy / h).astype(np.int64)
    o = np.lexsort((zc, key))
    first = np.r_[True, key[o][1:] != key[o][:-1]]
    cx, cy, zc = cx[o][first], cy[o][first], zc[o][first]
    # bins of size R: a point looks at the 3 x 3 bins around its own
    x0, y0 = cx.min(), cy.min()
    ix, iy = np.floor((cx - x0) / R).astype(np.int64), np.floor((cy - y0) / R).astype(np.int64)
    ny = int(iy.max()) + 3
    cid = (ix + 1) * ny + (iy + 1)
    order = np.argsort(cid, kind="stable")
    cid_s = cid[order]
    px, py = bx[dst], by[dst]
    from ..finish.kernels import module

    kern = module()
    if kern is not None:
        m, mx, my = np.empty(dst.size), np.empty(dst.size), np.empty(dst.size)
        ptr = np.searchsorted(cid_s, np.arange(int(cid_s[-1]) + 2))
        kern.reach_share(np.ascontiguousarray(px), np.ascontiguousarray(py), float(x0), float(y0), float(R),
                         int(ny), ptr.astype(np.int64), np.ascontiguousarray(cx[order]),
                         np.ascontiguousarray(cy[order]), np.ascontiguousarray(zc[order]), m, mx, my)
        up = m < best[dst] - 1e-12 * R
        d = dst[up]
        best[d], bo_x[d], bo_y[d] = m[up], mx[up], my[up]
        return d
    px_i = np.floor((px - x0) / R).astype(np.int64) + 1
    py_i = np.floor((py - y0) / R).astype(np.int64) + 1
    m = np.full(dst.size, np.inf)
    mx, my = np.zeros(dst.size), np.zeros(dst.size)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            c = (px_i + di) * ny + (py_i + dj)
            valid = (px_i + di >= 0) & (py_i + dj >= 0) & (py_i + dj < ny)
            lo = np.searchsorted(cid_s, c, "left")
            hi = np.searchsorted(cid_s, c, "right")
            cnt = np.where(valid, hi - lo, 0)
            tot = int(cnt.sum())
            if not tot:
                continue
            own = np.repeat(np.arange(dst.size), cnt)
            off = np.arange(tot) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            k = order[np.repeat(lo, cnt) + off]
            ux, uy = cx[k] - px[own], cy[k] - py[own]
            with np.errstate(invalid="ignore"):
                g = zc[k] - np.sqrt(R * R - ux * ux - uy * uy)
            g = np.where(np.isfinite(g), g, np.inf)
            mm = np.full(dst.size, np.inf)
            np.minimum.at(mm, own, g)
            hit = np.nonzero(g == mm[own])[0]
            j = np.full(dst.size, -1)
            j[own[hit]] = hit
            up = mm < m
            u = np.nonzero(up)[0]
            m[u], mx[u], my[u] = mm[u], ux[j[u]], uy[j[u]]
    up = m < best[dst] - 1e-12 * R
    d = dst[up]
    best[d], bo_x[d], bo_y[d] = m[up], mx[up], my[up]
    return d


def _leaders(bx, by, cell, always):
    """(lead, rest): the first point in each cell of size ``cell`` and the points
    ``always`` (bool), and the others."""
    key = np.floor(bx / cell).astype(np.int64) * 1_000_003 + np.floor(by / cell).astype(np.int64)
    _, first = np.unique(key, return_index=True)
    mask = always.copy()
    mask[first] = True
    return np.nonzero(mask)[0], np.nonzero(~mask)[0]

def _compass(surface_at, best, bo_x, bo_y, R, step0=0.5 * REACH_GRID):
    """The compass search from the best start (in place): 8 directions, first steps
    ``step0`` x R, halved when none lowers the point."""
    r = np.arange(best.size)
    dirs = 2 * np.pi * np.arange(REACH_DIRS) / REACH_DIRS
    dx, dy = np.cos(dirs), np.sin(dirs)
    step = np.full(best.size, step0 * R)
    act = r
    for _ in range(REACH_SEARCH):
        if not act.size:
            break
        tx, ty = bo_x[act, None] + step[act, None] * dx, bo_y[act, None] + step[act, None] * dy
        G = surface_at(tx, ty, act)
        j = np.argmin(G, axis=1)
        ra = np.arange(act.size)
        g = G[ra, j]
        up = g < best[act]
        best[act] = np.where(up, g, best[act])
        bo_x[act] = np.where(up, tx[ra, j], bo_x[act])
        bo_y[act] = np.where(up, ty[ra, j], bo_y[act])
        step[act] = np.where(up, step[act], 0.5 * step[act])
        # a point whose step fell below REACH_STEP_MIN x R stops (the next steps could
        # lower it by less than about that: a few 1e-5 mm)
        act = act[step[act] >= REACH_STEP_MIN * R]


def _grid_starts(ws, bx, by, R, drop, overhang=(0.0, 0.0), split=False):
    """Per point (bx, by), the lowest surface above it of the balls centred on a grid of
    spacing REACH_GRID x R over the stock and up to ``overhang`` (x, y) beyond it (the last
    node of each side at ``overhang``; exact drop-cutter heights; only the nodes within R
    of some point are dropped): (g, centre offset x, y), +inf where none. With ``split``
    the same as two lists, [on the stock, beyond its edges]."""
    h = REACH_GRID * R

    def axis(length, overhang):
        n = int(math.ceil(length / h)) + 1
        g = np.linspace(0.0, length, n)
        st = g[1] - g[0] if n > 1 else h
        k = int(math.ceil(overhang / st - 1e-9)) if overhang > 0 else 0
        out = np.minimum(st * np.arange(1, k + 1), overhang)
        return np.r_[-out[::-1], g, length + out], st, k

    xs, hx, kx = axis(ws.L, overhang[0])
    ys, hy, ky = axis(ws.W, overhang[1])
    nx, ny = xs.size, ys.size
    ix = np.clip(np.rint(bx / hx).astype(int) + kx, 0, nx - 1)
    iy = np.clip(np.rint(by / hy).astype(int) + ky, 0, ny - 1)
    rx, ry = int(math.ceil(R / hx)) + 1, int(math.ceil(R / hy)) + 1
    near = np.zeros((nx, ny), bool)
    near[ix, iy] = True
    # dilated by (rx, ry) nodes: a box sum over a summed-area table
    S = np.zeros((nx + 1, ny + 1))
    S[1:, 1:] = np.cumsum(np.cumsum(near, axis=0), axis=1)
    i0, i1 = np.clip(np.arange(nx) - rx, 0, nx), np.clip(np.arange(nx) + rx + 1, 0, nx)
    j0, j1 = np.clip(np.arange(ny) - ry, 0, ny), np.clip(np.arange(ny) + ry + 1, 0, ny)
    near = (S[i1][:, j1] - S[i0][:, j1] - S[i1][:, j0] + S[i0][:, j0]) > 0
    Z = np.full((nx, ny), np.inf)
    qi, qj = np.nonzero(near)
    z = drop(xs[qi], ys[qj])
    Z[qi, qj] = np.where(np.isfinite(z), z, np.inf)
    from ..finish.kernels import module

    kern = module()
    if kern is not None and bx.size:
        B, OX, OY = (np.empty((2, bx.size)) for _ in range(3))
        kern.reach_grid_best(np.ascontiguousarray(bx, dtype=float), np.ascontiguousarray(by, dtype=float),
                             ix.astype(np.int64), iy.astype(np.int64), xs, ys, np.ascontiguousarray(Z),
                             int(kx), int(ky), int(rx), int(ry), float(R), B, OX, OY)
        best, ox, oy = [B[0], B[1]], [OX[0], OX[1]], [OY[0], OY[1]]
        if split:
            return best, ox, oy
        lo = best[1] < best[0]
        return (np.where(lo, best[1], best[0]), np.where(lo, ox[1], ox[0]), np.where(lo, oy[1], oy[0]))
    # the best node on the stock and the best beyond its edges, apart
    best = [np.full(bx.size, np.inf), np.full(bx.size, np.inf)]
    ox, oy = [np.zeros(bx.size), np.zeros(bx.size)], [np.zeros(bx.size), np.zeros(bx.size)]
    R2 = R * R
    for di in range(-rx, rx + 1):
        i = ix + di
        okx = (i >= 0) & (i < nx)
        i = np.clip(i, 0, nx - 1)
        dx = xs[i] - bx
        offx = (i < kx) | (i >= nx - kx)
        dx2 = dx * dx
        for dj in range(-ry, ry + 1):
            jj = iy + dj
            ok = okx & (jj >= 0) & (jj < ny)
            jj = np.clip(jj, 0, ny - 1)
            dy = ys[jj] - by
            d2 = dx2 + dy * dy
            ok &= d2 < R2
            if not ok.any():
                continue
            with np.errstate(invalid="ignore"):
                g = Z[i, jj] + R - np.sqrt(R2 - d2)
            off = offx | (jj < ky) | (jj >= ny - ky)
            for side in (0, 1):
                up = ok & (g < best[side]) & (off == bool(side))
                if up.any():
                    best[side] = np.where(up, g, best[side])
                    ox[side], oy[side] = np.where(up, dx, ox[side]), np.where(up, dy, oy[side])
    if split:
        return best, ox, oy
    lo = best[1] < best[0]
    return (np.where(lo, best[1], best[0]), np.where(lo, ox[1], ox[0]), np.where(lo, oy[1], oy[0]))


__all__ = ["reachable_height", "OVERHANG", "OVERHANG_ALONG"]
