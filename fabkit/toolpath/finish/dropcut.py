"""The drop cutter's compiled kernel: one tool position wholly in compiled code.

This file is a *template*: it is not imported. :mod:`.kernels` writes it into one
module in the user cache (``FABKIT_CACHE_DIR``, see
:mod:`fabkit.physics.engine.codegen`), where numba compiles it once per installation
(``cache=True``). The formula's surface functions are compiled separately, as the
simulator's are (:func:`fabkit.physics.engine.codegen.write_surface`: C callbacks, one
small module per formula), and reach the kernel inside ``P = (Pa, jet, height, heights)``:

    jet(x, y, Pa)    -> (h, h_x, h_y, h_xx, h_xy, h_yy)   design units
    height(x, y, Pa) -> (h,)
    heights(n, X, Y, OUT, Pa): OUT[i] = height(X[i], Y[i], Pa)[0], i < n (pointers; the
                     same source per point: the same bits, without a call per point)

It is the scalar transcription of :func:`fabkit.toolpath.finish.compensate._compensate`,
candidates (i)-(iv) (the samples, the interior Newton, the crease, the footprint's
edges and corners): the same operations in the same order on each position, so the
same candidates and the same maximum (to the last bits of the surface's own
arithmetic: numpy's and the C library's exp or sin may differ in the last bit, and a
crease crossing on an edge stops its Newton on its own step, not on the batch's:
differences far below 1e-9 mm). The rare candidate (v), a ridge, stays in numpy,
on the positions the kernel reports unconverged (``CONV``).

G = (s, x0, y0, top, L, W): the work surface H(X, Y) = s (h(X / s + x0, Y / s + y0) - top).
"""
import math

import numpy as np
from numba import njit

jit = njit(cache=True, nogil=True, error_model="numpy")

K_NONE = -1
K_SAMPLE = 0
K_INTERIOR = 1
K_TOP = 2
K_CREASE = 3
K_EDGE = 4
K_RIDGE = 5
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
RIDGE_ITERS = 34
KINK_ITERS = 24
XTOL = 1e-10
SEED_MARGIN = 1e-9      # compensate.SEED_MARGIN
WALL_STARTS = 2         # compensate.WALL_STARTS
NRIM = 36               # compensate.RIM_POINTS
WALL_GATE = 0.25        # compensate.WALL_GATE
WALL_NEAR = 0.0625      # compensate.WALL_NEAR
BIG = 1.7976931348623157e308


@jit
def _fmin(a, b):
    """np.minimum: NaN if either is NaN."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@jit
def _fmax(a, b):
    """np.maximum: NaN if either is NaN."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@jit
def _clip(a, lo, hi):
    return _fmin(_fmax(a, lo), hi)


@jit
def _n2n(a):
    """np.nan_to_num of a scalar."""
    if a != a:
        return 0.0
    if a == math.inf:
        return BIG
    if a == -math.inf:
        return -BIG
    return a


@jit
def _fin(a):
    return a == a and a != math.inf and a != -math.inf


@jit
def _H(x, y, G, P):
    s = G[0]
    h = P[2](x / s + G[1], y / s + G[2], P[0].ctypes)[0]
    return s * (h - G[3])


@jit
def _all(x, y, G, P):
    s = G[0]
    h, hx, hy, hxx, hxy, hyy = P[1](x / s + G[1], y / s + G[2], P[0].ctypes)
    return s * (h - G[3]), hx, hy, hxx / s, hxy / s, hyy / s


@jit
def _inside(x, y, G):
    return (x >= 0.0) and (x <= G[4]) and (y >= 0.0) and (y <= G[5])


@jit
def _offer(i, v, x, y, kind, VAL, PX, PY, KIND):
    if not _fin(v):
        v = -math.inf
    if v > VAL[i]:
        VAL[i] = v
        PX[i] = x
        PY[i] = y
        KIND[i] = kind


@jit
def _value(cx, cy, R, px, py, G, P):
    """F at (px, py) (-inf outside the disk or the footprint) and H there."""
    ddx = px - cx
    ddy = py - cy
    d2 = ddx * ddx + ddy * ddy
    ok = _inside(px, py, G) and d2 <= R * R
    H = _H(px, py, G, P)
    zc = _fmin(H, 0.0)
    v = zc + math.sqrt(_fmax(R * R - d2, 0.0))
    if not (ok and _fin(v)):
        v = -math.inf
    return v, H


@jit
def _newton_interior(cx, cy, R, px, py, iters, G, P):
    """compensate._newton_interior for one start: (x, y, converged)."""
    dx = px - cx
    dy = py - cy
    q = math.sqrt(_fmax(R * R - dx * dx - dy * dy, 1e-6 * R * R))
    wx = dx / q
    wy = dy / q
    conv = False
    for _ in range(iters):
        ax = wx
        ay = wy
        s = math.sqrt(1.0 + ax * ax + ay * ay)
        x = cx + R * ax / s
        y = cy + R * ay / s
        H, gx, gy, hxx, hxy, hyy = _all(x, y, G, P)
        F0 = _fmin(H, 0.0) + R / s
        Gx = gx - ax
        Gy = gy - ay
        k = s / R
        a = hxx - k * (1 + ax * ax)
        b = hxy - k * ax * ay
        d = hyy - k * (1 + ay * ay)
        det = a * d - b * b
        negdef = (a < 0) and (det > 0) and _fin(det)
        safe = det if negdef else 1.0
        if negdef:
            sx = -(d * Gx - b * Gy) / safe
            sy = -(-b * Gx + a * Gy) / safe
        else:
            # ascent along G, at most R/4 (its length only needed here)
            asc = 0.25 * R / _fmax(1.0, math.hypot(Gx, Gy)) / _fmax(1.0, k * R)
            sx = Gx * asc
            sy = Gy * asc
        sx = _n2n(sx)
        sy = _n2n(sy)
        wd = ax * sx + ay * sy
        dwx = k * (sx + ax * wd)
        dwy = k * (sy + ay * wd)
        # the step limit in w: lim = (1 + |w|) / 2 >= 1/2, so a step whose squared length
        # is below 0.24 (|dw| < 0.49 whatever the rounding) is within it and f = 1, as
        # from the two lengths, which are then not computed (most steps: 4 % of the time)
        f = 1.0
        if not (dwx * dwx + dwy * dwy < 0.24):
            lim = 0.5 * (1.0 + math.hypot(ax, ay))
            nw = math.hypot(dwx, dwy)
            f = lim / _fmax(nw, 1e-300) if nw > lim else 1.0
        dwx = dwx * f
        dwy = dwy * f
        step = math.hypot(sx, sy) * f
        ok = negdef and (step < 0.02 * R) and (f == 1.0)
        nx_ = ax
        ny_ = ay
        if ok:
            nx_ = ax + dwx
            ny_ = ay + dwy
        else:
            # the full step, then the halvings 1/2 .. 1/128: the first that does not decrease F
            hv = 1.0
            for hh in range(8):
                tx = ax + dwx * hv
                ty = ay + dwy * hv
                s1 = math.sqrt(1.0 + tx * tx + ty * ty)
                F1 = _fmin(_H(cx + R * tx / s1, cy + R * ty / s1, G, P), 0.0) + R / s1
                if _fin(F1) and F1 >= F0 - 1e-13 * R:
                    nx_ = tx
                    ny_ = ty
                    ok = True
                    step *= 0.5 * hv
                    break
                hv = 0.5 ** (hh + 1)
            if not ok:
                step *= 0.5 ** 8
        wx = nx_
        wy = ny_
        if (negdef and ok and step < XTOL) or not ok:
            conv = negdef and ok
            break
    s = math.sqrt(1.0 + wx * wx + wy * wy)
    return cx + R * wx / s, cy + R * wy / s, conv


@jit
def _newton_crease(cx, cy, px, py, iters, G, P):
    """compensate._newton_crease for one seed."""
    for _ in range(2):
        H, gx, gy, _a, _b, _c = _all(px, py, G, P)
        g2 = gx * gx + gy * gy
        npx = px - _n2n(H * gx / g2)
        py = py - _n2n(H * gy / g2)
        px = npx
    H, gx, gy, _a, _b, _c = _all(px, py, G, P)
    lam = _n2n(((px - cx) * gx + (py - cy) * gy) / (gx * gx + gy * gy))
    for _ in range(iters):
        x = px
        y = py
        la = lam
        H, gx, gy, hxx, hxy, hyy = _all(x, y, G, P)
        A = 1 - la * hxx
        B = -la * hxy
        D = 1 - la * hyy
        r1 = la * gx - (x - cx)
        r2 = la * gy - (y - cy)
        r3 = -H
        det = A * gy * gy - 2.0 * B * gx * gy + D * gx * gx
        ok = _fin(det) and (abs(det) > 1e-300) and _fin(r1) and _fin(r2) and _fin(r3)
        if not ok:
            break
        sx = (gy * (r1 * gy - r2 * gx) + r3 * (D * gx - B * gy)) / det
        sy = (gx * (r2 * gx - r1 * gy) + r3 * (A * gy - B * gx)) / det
        sl = (A * (D * r3 - r2 * gy) - B * (B * r3 - r2 * gx) + r1 * (B * gy - D * gx)) / det
        px = x + sx
        py = y + sy
        lam = la + sl
        if max(abs(sx), abs(sy)) < XTOL:
            break
    return px, py


@jit
def _pts(axis, level, t):
    if axis == 1:
        return t, level
    return level, t


@jit
def _edge(i, cx, cy, R, axis, level, length, G, P, U, EOFF, iters, VAL, PX, PY, KIND, WF, WB):
    """compensate._edges on one edge (axis 1: Y = level, t = X; axis 0: X = level, t = Y).
    WF (8, n), WB (n,): scratch (n = U.size + EOFF.size), allocated once per batch."""
    perp = cy if axis == 1 else cx
    tc = cx if axis == 1 else cy
    dp = abs(perp - level)
    if not dp < R:
        return
    a = math.sqrt(R * R - dp * dp)
    t0 = _fmax(tc - a, 0.0)
    t1 = _fmin(tc + a, length)
    if not t0 <= t1:
        return
    rho2 = a * a
    nu = U.size
    ne = EOFF.size
    n = nu + ne
    T = WF[0]
    for j in range(nu):
        T[j] = t0 + (t1 - t0) * U[j]
    for j in range(ne):
        T[nu + j] = _clip(tc + a * EOFF[j], t0, t1)
    # np.sort (insertion: n is about 30)
    for j in range(1, n):
        v = T[j]
        m = j - 1
        while m >= 0 and T[m] > v:
            T[m + 1] = T[m]
            m -= 1
        T[m + 1] = v
    V = WF[1]
    Hs = WF[2]
    # the design coordinates of all samples first, then the surface (the same values as
    # _H point by point: the divisions do not wait on each callback)
    XD = WF[6]
    YD = WF[7]
    s = G[0]
    for j in range(n):
        X, Y = _pts(axis, level, T[j])
        XD[j] = X / s + G[1]
        YD[j] = Y / s + G[2]
    P[3](n, XD.ctypes, YD.ctypes, Hs.ctypes, P[0].ctypes)
    for j in range(n):
        Hs[j] = s * (Hs[j] - G[3])
    for j in range(n):
        dt = T[j] - tc
        V[j] = _fmin(Hs[j], 0.0) + math.sqrt(_fmax(rho2 - dt * dt, 0.0))
    for j in range(n):
        X, Y = _pts(axis, level, T[j])
        _offer(i, V[j], X, Y, K_EDGE, VAL, PX, PY, KIND)
    # flat part: the point of the edge nearest c, if in the top region
    tf = _clip(tc, t0, t1)
    Xf, Yf = _pts(axis, level, tf)
    Hf = _H(Xf, Yf, G, P)
    if Hf >= 0:
        dt = tf - tc
        vf = _fmin(Hf, 0.0) + math.sqrt(_fmax(rho2 - dt * dt, 0.0))
    else:
        vf = -math.inf
    _offer(i, vf, Xf, Yf, K_EDGE, VAL, PX, PY, KIND)
    # smooth part: 1-D Newton in phi from the three best local maxima of the samples
    key = WF[3]
    for j in range(n):
        vj = V[j] if _fin(V[j]) else -math.inf
        lm = True
        if j > 0:
            vp = V[j - 1] if _fin(V[j - 1]) else -math.inf
            lm = lm and vj >= vp
        if j < n - 1:
            vn = V[j + 1] if _fin(V[j + 1]) else -math.inf
            lm = lm and vj >= vn
        key[j] = vj if lm else -math.inf
    lo = math.asin(_clip((t0 - tc) / a, -1.0, 1.0))
    hi = math.asin(_clip((t1 - tc) / a, -1.0, 1.0))
    taken = WB
    for j in range(n):
        taken[j] = False
    res_t = np.empty(3)
    nstart = min(3, n)
    for r in range(nstart):
        # the largest key not taken, the first among ties (a stable sort)
        bj = -1
        for j in range(n):
            if taken[j]:
                continue
            if bj < 0 or key[j] > key[bj]:
                bj = j
        taken[bj] = True
        ph = _clip(math.asin(_clip((T[bj] - tc) / a, -1.0, 1.0)), lo, hi)
        for _ in range(iters + 4):
            sn = math.sin(ph)
            cs = math.cos(ph)
            X, Y = _pts(axis, level, tc + a * sn)
            H0, gx, gy, hxx, _hxy, hyy = _all(X, Y, G, P)
            if axis == 1:
                Ht = gx
                Htt = hxx
            else:
                Ht = gy
                Htt = hyy
            d1 = a * (Ht * cs - sn)
            d2 = a * (Htt * a * cs * cs - Ht * sn - cs)
            if d2 < 0:
                st = -d1 / d2
            else:
                sg = d1 if d1 != d1 else (1.0 if d1 > 0 else (-1.0 if d1 < 0 else 0.0))
                st = 0.1 * sg
            st = _clip(_n2n(st), -0.5, 0.5)
            f0 = _fmin(H0, 0.0) + a * cs
            moved = False
            hv = 1.0
            for hh in range(6):
                cand = _clip(ph + st * hv, lo, hi)
                X1, Y1 = _pts(axis, level, tc + a * math.sin(cand))
                f1 = _fmin(_H(X1, Y1, G, P), 0.0) + a * math.cos(cand)
                if _fin(f1) and f1 >= f0 - 1e-13 * R:
                    ph = cand
                    moved = True
                    st *= hv
                    break
                hv = 0.5 ** (hh + 1)
            if not moved:
                st *= 0.5 ** 6
            if (not moved) or abs(st) * a < XTOL:
                break
        res_t[r] = tc + a * math.sin(ph)
    for r in range(nstart):
        t = res_t[r]
        X, Y = _pts(axis, level, t)
        dt = t - tc
        v = _fmin(_H(X, Y, G, P), 0.0) + math.sqrt(_fmax(rho2 - dt * dt, 0.0))
        _offer(i, v, X, Y, K_EDGE, VAL, PX, PY, KIND)
    # crease crossings on the edge: safeguarded Newton inside each sign change
    ct = WF[4]
    cs_ = WF[5]
    nc = 0
    for j in range(n - 1):
        if (Hs[j] >= 0) == (Hs[j + 1] >= 0):
            continue
        a_ = T[j]
        b_ = T[j + 1]
        Ha = Hs[j]
        t = 0.5 * (a_ + b_)
        for _ in range(iters + 20):
            X, Y = _pts(axis, level, t)
            H, gx, gy, _p, _q, _r = _all(X, Y, G, P)
            Ht = gx if axis == 1 else gy
            if (H >= 0) == (Ha >= 0):
                a_ = t
            else:
                b_ = t
            tn = t - H / Ht
            bad = (not _fin(tn)) or (tn <= _fmin(a_, b_)) or (tn >= _fmax(a_, b_))
            t_old = t
            t = 0.5 * (a_ + b_) if bad else tn
            if abs(t - t_old) < XTOL:
                break
        ct[nc] = t
        cs_[nc] = a_ if Ha >= 0 else b_
        nc += 1
    for pass_ in range(2):
        for c in range(nc):
            tt = ct[c] if pass_ == 0 else cs_[c]
            X, Y = _pts(axis, level, tt)
            dt = tt - tc
            v = _fmin(_H(X, Y, G, P), 0.0) + math.sqrt(_fmax(a * a - dt * dt, 0.0))
            _offer(i, v, X, Y, K_CREASE, VAL, PX, PY, KIND)


@jit
def _kinked(cx, cy, R, px, py, G, P, V5):
    """compensate._kinked for one position."""
    KUX, KUY = V5[0], V5[1]
    f0, _h = _value(cx, cy, R, px, py, G, P)
    d2 = np.empty((4, KUX.size))
    for m in range(4):
        d = R / (25.0 * 4.0 ** m)
        for j in range(KUX.size):
            fp, _h = _value(cx, cy, R, px + d * KUX[j], py + d * KUY[j], G, P)
            fm, _h = _value(cx, cy, R, px - d * KUX[j], py - d * KUY[j], G, P)
            d2[m, j] = fp + fm - 2 * f0 if (_fin(fp) and _fin(fm)) else 0.0
    for j in range(KUX.size):
        for m in range(3):
            big = d2[m, j]
            small = d2[m + 1, j]
            if (d2[0, j] < -1e-3 * R / 25) and ((big > 10.0 * small) or (big < 26.0 * small)):
                return True
    return False


@jit
def _rises_inward(cx, cy, R, px, py, val, G, P, V5):
    """compensate._rises_inward for one position."""
    L = G[4]
    W = G[5]
    RC, RS, RD = V5[2], V5[3], V5[4]
    tiny = 1e-9 * max(L, W, 1.0)
    nx = (1.0 if px <= tiny else 0.0) - (1.0 if px >= L - tiny else 0.0)
    ny = (1.0 if py <= tiny else 0.0) - (1.0 if py >= W - tiny else 0.0)
    nn = math.hypot(nx, ny)
    if not nn > 0:
        return False
    nx = nx / nn
    ny = ny / nn
    na = RC.size
    for j in range(RD.size):
        c = RC[j % na]
        sn = RS[j % na]
        d = R * RD[j]
        dx = (nx * c - ny * sn) * d
        dy = (nx * sn + ny * c) * d
        f, _h = _value(cx, cy, R, px + dx, py + dy, G, P)
        if f > val + 1e-12 * R:
            return True
    return False


@jit
def _fd(t, cx, cy, R, bx, by, nx, ny, G, P):
    x = bx + t * nx
    y = by + t * ny
    H, hx, hy, _a, _b, _c = _all(x, y, G, P)
    ddx = x - cx
    ddy = y - cy
    d2 = ddx * ddx + ddy * ddy
    ok = _inside(x, y, G) and d2 <= R * R
    q = math.sqrt(_fmax(R * R - d2, 0.0))
    top = H >= 0
    v = (0.0 if top else H) + q
    g = (0.0 if top else hx * nx + hy * ny) - ((x - cx) * nx + (y - cy) * ny) / _fmax(q, 1e-300)
    if not (ok and _fin(v)):
        v = -math.inf
    return v, (g if _fin(g) else 0.0)


@jit
def _kink_max(cx, cy, R, bx, by, nx, ny, T, G, P):
    """compensate._kink_max for one segment: (t, value)."""
    a = -T
    b = T
    fa, ga = _fd(a, cx, cy, R, bx, by, nx, ny, G, P)
    fb, gb = _fd(b, cx, cy, R, bx, by, nx, ny, G, P)
    bt = a if fa >= fb else b
    bf = _fmax(fa, fb)
    for i in range(KINK_ITERS):
        tm = (fb - fa + ga * a - gb * b) / (ga - gb)
        mid = 0.5 * (a + b)
        bad = (not _fin(tm)) or (tm <= a) or (tm >= b) or (not _fin(fa)) or (not _fin(fb)) \
            or (ga <= 0) or (gb >= 0) or (i % 3 == 2)
        t = mid if bad else tm
        ft, gt = _fd(t, cx, cy, R, bx, by, nx, ny, G, P)
        if ft > bf:
            bt = t
            bf = ft
        right = (gt > 0) and _fin(ft)
        if not _fin(ft):
            right = fb > fa
        if right:
            a = t
            fa = ft
            ga = gt
        else:
            b = t
            fb = ft
            gb = gt
    return bt, bf


@jit
def _ridge(cx, cy, R, px, py, G, P, V5):
    """compensate._ridge for one position: (value, x, y)."""
    QC, QS = V5[5], V5[6]
    nq = QC.size
    rho = R / 8.0
    i1 = 0
    f1 = -math.inf
    Fq = np.empty(nq)
    for j in range(nq):
        Fq[j], _h = _value(cx, cy, R, px + rho * QC[j], py + rho * QS[j], G, P)
        if j == 0 or Fq[j] > f1:
            f1 = Fq[j]
            i1 = j
    i2 = 0
    f2 = 0.0
    half = nq // 2
    for j in range(nq):
        far = abs((j - i1 + half) % nq - half) >= nq // 4
        v = Fq[j] if far else -math.inf
        if j == 0 or v > f2:
            f2 = v
            i2 = j
    tx = (px + rho * QC[i1]) - (px + rho * QC[i2])
    ty = (py + rho * QS[i1]) - (py + rho * QS[i2])
    tn = math.hypot(tx, ty)
    if tn > 0:
        tx = tx / tn
        ty = ty / tn
    else:
        tx = 1.0
        ty = 0.0
    nx = -ty
    ny = tx
    S = 0.5 * R
    T = 0.25 * R
    bv = -math.inf
    bxr = px
    byr = py
    # golden section over s in [-S, S] of the maxima across (compensate._golden_max)
    a = 0.0 - S
    b = 0.0 + S
    c = b - GOLDEN * (b - a)
    d = a + GOLDEN * (b - a)
    fc = 0.0
    fd = 0.0
    for m in range(2 + RIDGE_ITERS):
        if m == 0:
            s = c
        elif m == 1:
            s = d
        else:
            left = fc >= fd
            if left:
                b = d
            else:
                a = c
            s = b - GOLDEN * (b - a) if left else a + GOLDEN * (b - a)
        bx = px + s * tx
        by = py + s * ty
        t, v = _kink_max(cx, cy, R, bx, by, nx, ny, T, G, P)
        if v > bv:
            bv = v
            bxr = bx + t * nx
            byr = by + t * ny
        if m == 0:
            fc = v
        elif m == 1:
            fd = v
        else:
            if left:
                d = c
                c = s
                fd = fc
                fc = v
            else:
                c = d
                d = s
                fc = fd
                fd = v
    return bv, bxr, byr


@jit
def drop_batch(CX, CY, R, G, P, OFFX, OFFY, SQ, R2, QUAD, U, EOFF, starts, iters,
               VAL, PX, PY, KIND, BRIDGED, CONV, V5):
    """Candidates (i)-(v) of every position (CX[i], CY[i]): the running maximum in
    VAL, PX, PY, KIND; BRIDGED; CONV: some interior start converged (positions on
    the top face: True). V5: the tables of (v) (compensate._tables)."""
    L = G[4]
    W = G[5]
    K = OFFX.size
    k = min(starts, K)
    FS = np.empty(K)
    HS = np.empty(K)
    INF = np.empty(K, dtype=np.bool_)
    key = np.empty(K)
    order = np.empty(k, dtype=np.int64)
    qx = np.empty(k)
    qy = np.empty(k)
    lmk = np.empty(k, dtype=np.bool_)
    seeds = np.empty(9, dtype=np.int64)
    WF = np.empty((8, U.size + EOFF.size))
    WB = np.empty(U.size + EOFF.size, dtype=np.bool_)
    XD = np.empty(K)
    TS, SXS, SYS = np.empty(K + NRIM), np.empty(K + NRIM), np.empty(K + NRIM)
    WV, WX, WY = np.empty(CX.size), np.empty(CX.size), np.empty(CX.size)   # (i'), offered last
    RIMX, RIMY, XR, YR, HR = np.empty(NRIM), np.empty(NRIM), np.empty(NRIM), np.empty(NRIM), np.empty(NRIM)
    RIN = np.empty(NRIM, dtype=np.bool_)
    for m_ in range(NRIM):
        RIMX[m_], RIMY[m_] = R * math.cos(2 * np.pi * m_ / NRIM), R * math.sin(2 * np.pi * m_ / NRIM)
    YD = np.empty(K)
    s = G[0]
    x0 = G[1]
    y0 = G[2]
    top = G[3]
    Pa = P[0].ctypes
    # sample 0 at the centre itself: its H is Hc (cx + 0.0 is cx, unless cx is -0.0)
    centre0 = K > 0 and OFFX[0] == 0.0 and OFFY[0] == 0.0
    for i in range(CX.size):
        cx = CX[i]
        cy = CY[i]
        VAL[i] = -math.inf
        PX[i] = math.nan
        PY[i] = math.nan
        KIND[i] = K_NONE
        BRIDGED[i] = False
        CONV[i] = True
        WV[i] = -math.inf
        Hc = _H(cx, cy, G, P)
        ontop = _inside(cx, cy, G) and Hc >= 0
        if ontop:
            _offer(i, R, cx, cy, K_TOP, VAL, PX, PY, KIND)
            continue
        # samples: the design coordinates of all first, then the surface at all of them
        # in one call (heights: the same values as _H point by point), the centre's
        # (offset 0) from Hc. The footprint test is _inside's without its branches (the
        # same four comparisons), so that this loop's divisions run as vector
        # instructions (exact, as the scalar ones)
        for j in range(K):
            x = cx + OFFX[j]
            y = cy + OFFY[j]
            INF[j] = (x >= 0.0) & (x <= L) & (y >= 0.0) & (y <= W)
            XD[j] = x / s + x0
            YD[j] = y / s + y0
        j0 = 0
        if centre0 and not (cx == 0.0 and math.copysign(1.0, cx) < 0.0) \
                and not (cy == 0.0 and math.copysign(1.0, cy) < 0.0):
            j0 = 1
            HS[0] = Hc
        P[3](K - j0, XD[j0:].ctypes, YD[j0:].ctypes, HS[j0:].ctypes, Pa)
        for j in range(j0, K):
            HS[j] = s * (HS[j] - top)
        for j in range(K):
            f = _fmin(HS[j], 0.0) + SQ[j] if INF[j] else -math.inf
            FS[j] = f if _fin(f) else -math.inf
        for j in range(K):
            _offer(i, FS[j], cx + OFFX[j], cy + OFFY[j], K_SAMPLE, VAL, PX, PY, KIND)
        # (i) interior Newton from the best k samples
        for j in range(K):
            key[j] = FS[j] if _fin(FS[j]) else -BIG
        for r in range(k):
            bj = 0
            for j in range(1, K):
                if key[j] > key[bj]:
                    bj = j
            order[r] = bj
            key[bj] = -math.inf
        conv_any = False
        for r in range(k):
            x, y, cv = _newton_interior(cx, cy, R, cx + OFFX[order[r]], cy + OFFY[order[r]],
                                        iters + 8, G, P)
            v, Hp = _value(cx, cy, R, x, y, G, P)
            qx[r] = x
            qy[r] = y
            lmk[r] = cv and _fin(v) and Hp < 0
            if cv and _fin(v):
                conv_any = True
            _offer(i, v, x, y, K_INTERIOR, VAL, PX, PY, KIND)
        fx = math.inf
        for r in range(k):
            if lmk[r] and qx[r] < fx:
                fx = qx[r]
        fy = math.inf
        for r in range(k):
            if lmk[r] and qx[r] == fx and qy[r] < fy:
                fy = qy[r]
        for r in range(k):
            if lmk[r] and math.hypot(qx[r] - fx, qy[r] - fy) > 1e-4 * R:
                BRIDGED[i] = True
        # (i') a wall rising into the disk (compensate._wall_starts); the rim's heights in one call
        for m_ in range(NRIM):
            x, y = cx + RIMX[m_], cy + RIMY[m_]
            RIN[m_] = (x >= 0.0) & (x <= L) & (y >= 0.0) & (y <= W)
            XR[m_], YR[m_] = x / s + x0, y / s + y0
        P[3](NRIM, XR.ctypes, YR.ctypes, HR.ctypes, Pa)
        gate = VAL[i] - WALL_GATE * R
        for j in range(K + NRIM):
            TS[j] = -math.inf
            if j < K:
                fj, ux, uy = FS[j], cx + OFFX[j], cy + OFFY[j]
            else:
                fj = _fmin(s * (HR[j - K] - top), 0.0) if RIN[j - K] else -math.inf
                ux, uy = cx + RIMX[j - K], cy + RIMY[j - K]
            if fj > gate:
                H0, gx0, gy0, _a, _b, _c = _all(ux, uy, G, P)
                m = math.sqrt(1.0 + gx0 * gx0 + gy0 * gy0)
                t = H0 + gx0 * (cx - ux) + gy0 * (cy - uy) + R * m
                if H0 < 0 and _fin(t):
                    TS[j], SXS[j], SYS[j] = t, cx + R * gx0 / m, cy + R * gy0 / m
        for r in range(k):
            TS[order[r]] = -math.inf
        vb, bpx, bpy = VAL[i], PX[i], PY[i]
        r = 0
        while r < WALL_STARTS:
            bj = 0
            for j in range(1, K + NRIM):
                if TS[j] > TS[bj]:
                    bj = j
            tj = TS[bj]
            TS[bj] = -math.inf
            if not (tj > vb + SEED_MARGIN):
                break
            if math.hypot(SXS[bj] - bpx, SYS[bj] - bpy) < WALL_NEAR * R:
                continue        # on the best point's own slope: it climbs back to it (not counted)
            r += 1
            x, y, cv = _newton_interior(cx, cy, R, SXS[bj], SYS[bj], iters + 8, G, P)
            v, _h = _value(cx, cy, R, x, y, G, P)
            if v > WV[i]:
                WV[i], WX[i], WY[i] = v, x, y
        CONV[i] = conv_any
        # (ii) crease: the nearest top-region sample in each quadrant, and the best sample
        has_top = False
        hmax = -math.inf
        jh = -1
        hnan = False
        for j in range(K):
            if INF[j] and HS[j] >= 0:
                has_top = True
            hv = HS[j] if INF[j] else -math.inf
            if hv != hv:
                hnan = True
            elif hv > hmax:
                hmax = hv
                jh = j
        near = has_top or ((not hnan) and hmax > -0.25 * R)
        if not near and not hnan and jh >= 0:
            # the tangent plane at the highest sample rising to within R/4 of the top
            # inside the disk (compensate: a crease cutting a thin cap off the rim)
            hx_ = cx + OFFX[jh]
            hy_ = cy + OFFY[jh]
            H0, gx0, gy0, _a, _b, _c = _all(hx_, hy_, G, P)
            near = H0 + gx0 * (cx - hx_) + gy0 * (cy - hy_) + R * math.hypot(gx0, gy0) > -0.25 * R
        if not near:
            continue
        ns = 0
        for qd in range(4):
            bj = -1
            for j in range(K):
                if INF[j] and HS[j] >= 0 and QUAD[j] == qd:
                    if bj < 0 or R2[j] < R2[bj]:
                        bj = j
            if bj >= 0:
                seeds[ns] = bj
                ns += 1
        seeds[ns] = order[0]
        ns += 1
        nbase = ns
        # and the highest sample below the top face in each quadrant (compensate: a wavy crease)
        for qd in range(4):
            bj = -1
            for j in range(K):
                if INF[j] and HS[j] < 0 and QUAD[j] == qd:
                    if bj < 0 or HS[j] > HS[bj]:
                        bj = j
            if bj >= 0:
                seeds[ns] = bj
                ns += 1
        for r in range(ns):
            x, y = _newton_crease(cx, cy, cx + OFFX[seeds[r]], cy + OFFY[seeds[r]], iters, G, P)
            v, _h = _value(cx, cy, R, x, y, G, P)
            if r >= nbase and not (v > VAL[i] + SEED_MARGIN):
                continue        # the quadrants' highest samples: only another maximum
            _offer(i, v, x, y, K_CREASE, VAL, PX, PY, KIND)
    # (iii)/(iv) the edges and corners where the disk crosses the footprint's boundary
    for i in range(CX.size):
        if KIND[i] == K_TOP:
            continue
        cx = CX[i]
        cy = CY[i]
        if not ((cx < R) or (cy < R) or (cx > L - R) or (cy > W - R)):
            continue
        _edge(i, cx, cy, R, 1, 0.0, L, G, P, U, EOFF, iters, VAL, PX, PY, KIND, WF, WB)
        _edge(i, cx, cy, R, 1, W, L, G, P, U, EOFF, iters, VAL, PX, PY, KIND, WF, WB)
        _edge(i, cx, cy, R, 0, 0.0, W, G, P, U, EOFF, iters, VAL, PX, PY, KIND, WF, WB)
        _edge(i, cx, cy, R, 0, L, W, G, P, U, EOFF, iters, VAL, PX, PY, KIND, WF, WB)
    # (v) a ridge: where no start converged and the best point is a sample or an
    # interior point at a kink, or an edge point with F rising inwards
    for i in range(CX.size):
        if CONV[i]:
            continue
        kd = KIND[i]
        if kd == K_SAMPLE or kd == K_INTERIOR:
            stuck = _kinked(CX[i], CY[i], R, PX[i], PY[i], G, P, V5)
        elif kd == K_EDGE:
            stuck = _rises_inward(CX[i], CY[i], R, PX[i], PY[i], VAL[i], G, P, V5)
        else:
            stuck = False
        if stuck:
            v, x, y = _ridge(CX[i], CY[i], R, PX[i], PY[i], G, P, V5)
            _offer(i, v, x, y, K_RIDGE, VAL, PX, PY, KIND)
    # (i')'s points, last: only where higher than every other candidate by SEED_MARGIN
    for i in range(CX.size):
        if KIND[i] != K_TOP and WV[i] > VAL[i] + SEED_MARGIN:
            _offer(i, WV[i], WX[i], WY[i], K_INTERIOR, VAL, PX, PY, KIND)
            BRIDGED[i] = True


# ----------------------------------------------------------------------------
# the verification's swept cut (verify.capsule_lower over SegmentGrid's cells)
# ----------------------------------------------------------------------------
@jit
def _capsule_lower(px, py, ax, ay, az, bx, by, bz, R):
    """verify.capsule_lower for one point and one segment."""
    ca_z = az + R
    cb_z = bz + R
    dxa = px - ax
    dya = py - ay
    dxb = px - bx
    dyb = py - by
    R2 = R * R
    za = ca_z - math.sqrt(R2 - dxa * dxa - dya * dya)
    zb = cb_z - math.sqrt(R2 - dxb * dxb - dyb * dyb)
    if za != za:
        za = math.inf
    if zb != zb:
        zb = math.inf
    z = za if za <= zb else zb
    d0 = bx - ax
    d1 = by - ay
    d2 = bz - az
    dd = d0 * d0 + d1 * d1 + d2 * d2
    if not dd > 0:
        return z
    inv = 1.0 / math.sqrt(dd)
    ux = d0 * inv
    uy = d1 * inv
    uz = d2 * inv
    k = dxa * ux + dya * uy
    qa = 1.0 - uz * uz
    beta = k * uz
    c = dxa * dxa + dya * dya - k * k - R2
    disc = beta * beta - qa * c
    if not ((qa > 1e-12) and (disc >= 0)):
        return z
    sd = math.sqrt(disc)
    if beta >= 0:
        zl = c / (beta + sd)
    else:
        zl = (beta - sd) / qa
    t = (dxa * d0 + dya * d1 + zl * d2) / dd
    if _fin(zl) and t >= 0.0 and t <= 1.0:
        w = ca_z + zl
        return _fmin(z, w)
    return z


@jit
def reach_grid_best(bx, by, ix, iy, xs, ys, Z, kx, ky, rx, ry, R, BEST, OX, OY):
    """verify._grid_starts: per point, the lowest g = Z + R - sqrt(R^2 - d^2) over the grid
    nodes (xs[i], ys[j]) within R of it, apart on the stock (row 0 of BEST, OX, OY) and
    beyond its edges (row 1); the first lowest in the order (i, then j) of the offsets."""
    nx = xs.size
    ny = ys.size
    R2 = R * R
    for p in range(bx.size):
        BEST[0, p] = math.inf
        BEST[1, p] = math.inf
        OX[0, p] = 0.0
        OX[1, p] = 0.0
        OY[0, p] = 0.0
        OY[1, p] = 0.0
        for di in range(-rx, rx + 1):
            i = ix[p] + di
            if i < 0 or i >= nx:
                continue
            dx = xs[i] - bx[p]
            offx = (i < kx) or (i >= nx - kx)
            for dj in range(-ry, ry + 1):
                j = iy[p] + dj
                if j < 0 or j >= ny:
                    continue
                dy = ys[j] - by[p]
                d2 = dx * dx + dy * dy
                if not d2 < R2:
                    continue
                g = Z[i, j] + R - math.sqrt(R2 - d2)
                if not _fin(g):
                    continue
                side = 1 if (offx or (j < ky) or (j >= ny - ky)) else 0
                if g < BEST[side, p]:
                    BEST[side, p] = g
                    OX[side, p] = dx
                    OY[side, p] = dy


@jit
def reach_share(px, py, x0, y0, R, nyb, ptr, CX, CY, ZC, M, MX, MY):
    """verify._share: per point, the lowest g = ZC - sqrt(R^2 - |c - p|^2) over the pooled
    ball centres c binned in cells of size R (the 3 x 3 cells around the point's; ``ptr``
    the cells' starts in CX, CY, ZC, cell id (ix + 1) * nyb + (iy + 1)); the first lowest in
    the cells' order (M = inf where none)."""
    R2 = R * R
    ncell = ptr.size - 1
    for p in range(px.size):
        M[p] = math.inf
        MX[p] = 0.0
        MY[p] = 0.0
        pi = int(math.floor((px[p] - x0) / R)) + 1
        pj = int(math.floor((py[p] - y0) / R)) + 1
        for di in range(-1, 2):
            for dj in range(-1, 2):
                ci = pi + di
                cj = pj + dj
                if ci < 0 or cj < 0 or cj >= nyb:
                    continue
                c = ci * nyb + cj
                if c >= ncell:
                    continue
                for k in range(ptr[c], ptr[c + 1]):
                    ux = CX[k] - px[p]
                    uy = CY[k] - py[p]
                    d2 = ux * ux + uy * uy
                    if not d2 <= R2:
                        continue
                    g = ZC[k] - math.sqrt(R2 - d2)
                    if _fin(g) and g < M[p]:
                        M[p] = g
                        MX[p] = ux
                        MY[p] = uy


@jit
def lowest_batch_sorted(px, py, cid, ptr, seg, A, B, R, before, use_before, out, ZMIN):
    """verify.SegmentGrid.lowest: out[i] = min(out[i], lowest swept z of the segments
    binned in point i's cell (only those with index < before[i] with use_before)), each
    cell's segments in ascending order of their lowest tip z (ZMIN[s] = min(A[s, 2],
    B[s, 2])): the swept ball is nowhere below its lowest tip, so a point stops at the
    first segment whose ZMIN is not below its lowest so far (the same minimum as trying
    them all)."""
    for i in range(px.size):
        c = cid[i]
        m = out[i]
        for p in range(ptr[c], ptr[c + 1]):
            s = seg[p]
            if not ZMIN[s] < m:
                break
            if use_before and s >= before[i]:
                continue
            z = _capsule_lower(px[i], py[i], A[s, 0], A[s, 1], A[s, 2], B[s, 0], B[s, 1], B[s, 2], R)
            if z < m:
                m = z
        out[i] = m
