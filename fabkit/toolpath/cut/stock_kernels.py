"""Compiled kernels of the height-field stock model (:mod:`fabkit.toolpath.cut.stock`).

The tool is a solid of revolution given by its radius R, corner radius r and flat
radius f = R - r (flat end mill: r = 0; ball: f = 0; bull nose: both > 0), its cutting
surface at height lift(rho) above the tip at radial distance rho (0 on the flat
bottom, r - sqrt(r^2 - (rho - f)^2) on the corner). Along a straight move a -> b the
lowest point of the swept tool over the vertical line through a node p is

    g = min over s of  a_z + k s + lift(sqrt((s - s0)^2 + e^2)),  s in [lo, hi]

with s the distance travelled in XY (k = dz / XY length), s0 the foot of p on the
move's XY line, e the distance of p from that line and [lo, hi] the part of [0, len]
where the tool's disk covers p. lift is nondecreasing and convex in rho and rho is
convex in s, so g's objective is convex: its minimum is the end of the interval for
a flat end mill (closed form), the stationary point s0 - k w / sqrt(1 + k^2)
(w = sqrt(R^2 - e^2)) clamped to the interval for a ball (closed form), and a
bisection of the (monotone) derivative to 1e-12 mm for a bull nose. Exact at the
nodes to floating point (~1e-12 mm; the bull nose's bisection adds at most ~1e-9 mm).

Compiled with ``cache=True`` like the engine's static kernels (numba's cache next to
this module, or NUMBA_CACHE_DIR).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ... import numba_start  # noqa: F401  (numba's short start-up for cached code)

jit = njit(cache=True, nogil=True, error_model="numpy")

BISECT = 64   # bull nose: bracket halvings (2R / 2^64: far below 1e-12 mm)


@jit
def lift(rho, R, r, f):
    """Height of the cutting surface above the tip at radial distance rho (inf beyond R)."""
    if rho > R:
        return np.inf
    u = rho - f
    if u <= 0.0 or r <= 0.0:
        return 0.0
    v = r * r - u * u
    return r - math.sqrt(v if v > 0.0 else 0.0)


@jit
def _bull_value(s, s0, e2, az, k, R, r, f):
    w = s - s0
    rho2 = w * w + e2
    if rho2 > R * R:
        rho2 = R * R
    return az + k * s + lift(math.sqrt(rho2), R, r, f)


@jit
def _bull_slope(s, s0, e2, k, R, r, f):
    """Derivative of the bull nose's objective (monotone nondecreasing in s)."""
    w = s - s0
    rho = math.sqrt(w * w + e2)
    u = rho - f
    if u <= 0.0 or rho <= 0.0:
        return k
    v = r * r - u * u
    if v <= 0.0:
        return k + (np.inf if w > 0 else (-np.inf if w < 0 else 0.0))
    return k + u / math.sqrt(v) * w / rho


@jit
def lowest(px, py, ax, ay, az, bx, by, bz, R, r, f):
    """Lowest point of the tool swept from tip a to tip b on the vertical line through
    (px, py); +inf where the tool does not pass over it."""
    dx, dy = bx - ax, by - ay
    L2 = dx * dx + dy * dy
    if L2 <= 1e-18:                    # XY travel below 1e-9 mm: a vertical move
        return _lowest_on(px - ax, py - ay, 0.0, 0.0, 0.0, az, bz, 0.0, R, r, f)
    Ln = math.sqrt(L2)
    return _lowest_on(px - ax, py - ay, dx / Ln, dy / Ln, Ln, az, bz, (bz - az) / Ln, R, r, f)


@jit
def _lowest_on(qx, qy, ux, uy, Ln, az, bz, k, R, r, f):
    """:func:`lowest` with the move's constants: (qx, qy) = p - a, (ux, uy) the unit XY
    direction, Ln the XY length (0: vertical), k = dz / Ln."""
    R2 = R * R
    if Ln <= 0.0:
        rho2 = qx * qx + qy * qy
        if rho2 > R2:
            return np.inf
        return min(az, bz) + lift(math.sqrt(rho2), R, r, f)
    s0 = qx * ux + qy * uy
    e = qx * uy - qy * ux
    e2 = e * e
    if e2 > R2:
        return np.inf
    half = math.sqrt(R2 - e2)
    lo = s0 - half
    hi = s0 + half
    if lo < 0.0:
        lo = 0.0
    if hi > Ln:
        hi = Ln
    if lo > hi:
        return np.inf
    if r <= 0.0:                       # flat end mill: the lower end of the interval
        s = lo if k >= 0.0 else hi
        return az + k * s
    if f <= 0.0:                       # ball: closed-form stationary point, clamped
        s = s0 - k * half / math.sqrt(1.0 + k * k)
        if s < lo:
            s = lo
        elif s > hi:
            s = hi
        w = s - s0
        v = R2 - e2 - w * w
        return az + k * s + R - math.sqrt(v if v > 0.0 else 0.0)
    # bull nose: bisection of the monotone derivative
    if _bull_slope(lo, s0, e2, k, R, r, f) >= 0.0:
        return _bull_value(lo, s0, e2, az, k, R, r, f)
    if _bull_slope(hi, s0, e2, k, R, r, f) <= 0.0:
        return _bull_value(hi, s0, e2, az, k, R, r, f)
    a, b = lo, hi
    for _ in range(BISECT):
        m = 0.5 * (a + b)
        if m <= a or m >= b:
            break
        if _bull_slope(m, s0, e2, k, R, r, f) < 0.0:
            a = m
        else:
            b = m
    va = _bull_value(a, s0, e2, az, k, R, r, f)
    vb = _bull_value(b, s0, e2, az, k, R, r, f)
    return va if va < vb else vb


@jit
def _lowest_column(out, ja, jb, qx, hy, ay, ux, uy, Ln, az, k, sk, R, r):
    """out[j - ja] = :func:`_lowest_on` (qx, j hy - ay, ...) for j = ja..jb, for a flat
    end mill (r <= 0) or a ball (r = R) on a move with XY travel (Ln > 0), sk = sqrt(1 +
    k^2): the same floating-point operations in the same order, written without branches
    (selects) so that the loop vectorises; +inf where the tool misses the node."""
    R2 = R * R
    ball = r > 0.0
    for t in range(jb - ja + 1):
        qy = (ja + t) * hy - ay
        s0 = qx * ux + qy * uy
        e = qx * uy - qy * ux
        e2 = e * e
        inside = e2 <= R2
        half = math.sqrt(R2 - e2 if inside else 0.0)
        lo = s0 - half
        hi = s0 + half
        lo = 0.0 if lo < 0.0 else lo
        hi = Ln if hi > Ln else hi
        inside = inside and lo <= hi
        if ball:
            sb = s0 - k * half / sk
            sb = lo if sb < lo else (hi if sb > hi else sb)
            w = sb - s0
            v = R2 - e2 - w * w
            g = az + k * sb + R - math.sqrt(v if v > 0.0 else 0.0)
        else:
            sf = lo if k >= 0.0 else hi
            g = az + k * sf
        out[t] = g if inside else np.inf


#: :func:`cut_moves`: the skipped band's margin inside the flat's reach (mm): nodes
#: nearer the band's edge than this are evaluated (floating point of the band's bounds)
SKIP_MARGIN = 1e-7


@jit
def _band_consts(px, py, qx, qy):
    """Per-segment constants of :func:`_band_in_column`: (ux, uy, Ln, 1/ux or 0, 1/uy or 0)."""
    dx, dy = qx - px, qy - py
    Ln = math.sqrt(dx * dx + dy * dy)
    if Ln > 1e-12:
        ux, uy = dx / Ln, dy / Ln
    else:
        ux = uy = 0.0
    iux = 1.0 / ux if abs(ux) > 1e-12 else 0.0
    iuy = 1.0 / uy if abs(uy) > 1e-12 else 0.0
    return ux, uy, Ln, iux, iuy


@jit
def _band_in_column(x, px, py, qx, qy, d, ux, uy, Ln, iux, iuy):
    """The y interval [lo, hi] of the vertical line X = x within distance d of the
    segment p-q (XY) (a capsule: convex, so an interval; lo > hi: none), from its two
    discs and its band; the segment's constants from :func:`_band_consts` (once per
    move; divisions as products with the reciprocals: the interval to ~1e-13 mm, far
    within the SKIP_MARGIN its caller keeps both ways)."""
    lo, hi = np.inf, -np.inf
    d2 = d * d
    u = x - px
    if u * u <= d2:
        h = math.sqrt(d2 - u * u)
        lo = min(lo, py - h)
        hi = max(hi, py + h)
    u = x - qx
    if u * u <= d2:
        h = math.sqrt(d2 - u * u)
        lo = min(lo, qy - h)
        hi = max(hi, qy + h)
    if Ln > 1e-12:
        a, b = -np.inf, np.inf
        if iux != 0.0:
            c0 = (x - px) * (-uy)
            y1, y2 = py + (-d - c0) * iux, py + (d - c0) * iux
            a, b = max(a, min(y1, y2)), min(b, max(y1, y2))
        elif abs((x - px) * uy) > d:
            a, b = np.inf, -np.inf
        if iuy != 0.0:
            c1 = (x - px) * ux
            y1, y2 = py + (0.0 - c1) * iuy, py + (Ln - c1) * iuy
            a, b = max(a, min(y1, y2)), min(b, max(y1, y2))
        else:
            t = (x - px) * ux
            if t < 0.0 or t > Ln:
                a, b = np.inf, -np.inf
        if a <= b:
            lo = min(lo, a)
            hi = max(hi, b)
    return lo, hi


@jit
def cut_moves(Z, hx, hy, A, B, feed, R, r, f, rapid_tol, engage, rapid_depth, rapid_node):
    """Sweep the tool along the moves A[m] -> B[m] in order over the stock height field
    Z (nx, ny; node (i, j) at (i hx, j hy)). Feed moves (feed[m]) lower Z to the tool's
    lowest point; ``engage[m]`` gets the largest thickness the move removes at a node.
    Rapids do not cut: ``rapid_depth[m]`` gets the deepest the tool would go into the
    stock present then (0 if it stays clear by ``rapid_tol``), at node rapid_node[m].

    Nodes a move cannot change are not visited: after a level feed move at height z0
    every node within the flat radius f of its XY segment is at most z0 (the flat
    bottom passes over it at z0; Z never rises), and a later move whose lowest tip is at
    or above z0 cuts nothing there, nor does a rapid pass into it (its tool is nowhere
    below its lowest tip). Such nodes of the last level feed's band (less SKIP_MARGIN)
    are skipped: the same stock and figures, to the bit, with the roughing's loops
    visiting a fraction of their nodes. A column's nodes are those of the move's capsule
    of radius R + SKIP_MARGIN (the tool misses any other), its interval from the move's
    constants computed once."""
    nx, ny = Z.shape
    buf = np.empty(ny)
    top = -np.inf
    for i in range(nx):
        for j in range(ny):
            if Z[i, j] > top:
                top = Z[i, j]
    band = False              # the last level feed: its segment and height
    pax = pay = pbx = pby = pz = 0.0
    pux = puy = pLn = piux = piuy = 0.0
    dband = f - SKIP_MARGIN
    for m in range(A.shape[0]):
        ax, ay, az = A[m, 0], A[m, 1], A[m, 2]
        bx, by, bz = B[m, 0], B[m, 1], B[m, 2]
        zlo = min(az, bz)
        skip = band and zlo >= pz
        if zlo >= top:
            continue
        x0, x1 = min(ax, bx) - R, max(ax, bx) + R
        i0 = max(0, int(math.ceil(x0 / hx)))
        i1 = min(nx - 1, int(math.floor(x1 / hx)))
        dx, dy = bx - ax, by - ay
        L2 = dx * dx + dy * dy
        if L2 <= 1e-18:                # a vertical move
            ux = uy = Ln = k = 0.0
        else:
            Ln = math.sqrt(L2)
            ux, uy, k = dx / Ln, dy / Ln, (bz - az) / Ln
        is_feed = feed[m]
        # a ball or a flat end mill on a move with XY travel: the column's lowest points in
        # one branch-free pass (vectorised), the same operations as _lowest_on's
        closed = Ln > 0.0 and (r <= 0.0 or f <= 0.0)
        sk = math.sqrt(1.0 + k * k)
        cux, cuy, cLn, ciux, ciuy = _band_consts(ax, ay, bx, by)
        worst = 0.0
        for i in range(i0, i1 + 1):
            x = i * hx
            # within the move's capsule of radius R (+ SKIP_MARGIN): beyond, the tool misses the node
            clo, chi = _band_in_column(x, ax, ay, bx, by, R + SKIP_MARGIN, cux, cuy, cLn, ciux, ciuy)
            if not clo <= chi:
                continue
            y0, y1 = clo - SKIP_MARGIN, chi + SKIP_MARGIN
            j0 = max(0, int(math.ceil(y0 / hy)))
            j1 = min(ny - 1, int(math.floor(y1 / hy)))
            k0, k1 = 1, 0             # nodes j in [k0, k1]: in the last level feed's band
            if skip:
                slo, shi = _band_in_column(x, pax, pay, pbx, pby, dband, pux, puy, pLn, piux, piuy)
                if slo <= shi:
                    k0 = int(math.ceil((slo + SKIP_MARGIN) / hy))
                    k1 = int(math.floor((shi - SKIP_MARGIN) / hy))
            # the nodes below the band, then above it (the whole range without one)
            ja1 = j1 if k0 > k1 else min(j1, k0 - 1)
            jb0 = j1 + 1 if k0 > k1 else max(j0, k1 + 1)
            for part in range(2):
                ja, jb = (j0, ja1) if part == 0 else (jb0, j1)
                if closed and jb >= ja:
                    _lowest_column(buf, ja, jb, x - ax, hy, ay, ux, uy, Ln, az, k, sk, R, r)
                for j in range(ja, jb + 1):
                    zc = Z[i, j]
                    if zlo >= zc:
                        continue
                    if closed:
                        g = buf[j - ja]
                    else:
                        g = _lowest_on(x - ax, j * hy - ay, ux, uy, Ln, az, bz, k, R, r, f)
                    if g < zc:
                        d = zc - g
                        if is_feed:
                            Z[i, j] = g
                            if d > worst:
                                worst = d
                        elif d > rapid_tol and d > worst:
                            worst = d
                            rapid_node[m, 0] = i
                            rapid_node[m, 1] = j
        if is_feed:
            engage[m] = worst
            if az == bz and dband > 0.0:
                band = True
                pax, pay, pbx, pby, pz = ax, ay, bx, by, az
                pux, puy, pLn, piux, piuy = cux, cuy, cLn, ciux, ciuy
        else:
            rapid_depth[m] = worst


@jit
def reach_at(S, hx, hy, R, r, f, pi, pj, D, beyond, d_i0=0, d_j0=0):
    """Lowest height the tool can cut at the nodes (pi[k], pj[k]) without cutting below
    S anywhere on the grid: the grey-scale opening of S by the tool, min over tool
    positions c on the grid nodes (and up to R beyond the edges, where there is no
    material) within R of p of drop(c) + lift(|p - c|), drop(c) = max over nodes q
    within R of c of S(q) - lift(|q - c|). The drops are computed once per centre and
    kept in ``D`` ((nx + 2 ceil(R / hx), ny + 2 ceil(R / hy)), nan: not yet), so that the
    nodes can be given in chunks (the caller stays interruptible between them). ``D`` may
    cover the nodes' bounding box only: its row 0 is then centre row d_i0 - ceil(R / hx)
    (column 0 centre column d_j0 - ceil(R / hy))."""
    nx, ny = S.shape
    pi_ = int(math.ceil(R / hx))
    pj_ = int(math.ceil(R / hy))
    # offsets within R and their lifts
    n_off = 0
    for di in range(-pi_, pi_ + 1):
        for dj in range(-pj_, pj_ + 1):
            if (di * hx) ** 2 + (dj * hy) ** 2 <= R * R:
                n_off += 1
    oi = np.empty(n_off, np.int64)
    oj = np.empty(n_off, np.int64)
    ol = np.empty(n_off)
    n = 0
    for di in range(-pi_, pi_ + 1):
        for dj in range(-pj_, pj_ + 1):
            rho2 = (di * hx) ** 2 + (dj * hy) ** 2
            if rho2 <= R * R:
                oi[n], oj[n] = di, dj
                ol[n] = lift(math.sqrt(rho2), R, r, f)
                n += 1
    out = np.empty(pi.size)
    for k in range(pi.size):
        best = np.inf
        for a in range(n_off):
            ci, cj = pi[k] + oi[a], pj[k] + oj[a]
            # centres at most ``beyond`` outside the grid (a tool standing farther out
            # than its passes go is no position it takes)
            ex = max(0.0, -ci * hx, (ci - (nx - 1)) * hx)
            ey = max(0.0, -cj * hy, (cj - (ny - 1)) * hy)
            if ex * ex + ey * ey > beyond * beyond:
                continue
            dd = D[ci - d_i0 + pi_, cj - d_j0 + pj_]
            if dd != dd:
                dd = -np.inf
                for b in range(n_off):
                    qi, qj = ci + oi[b], cj + oj[b]
                    if 0 <= qi < nx and 0 <= qj < ny:
                        v = S[qi, qj] - ol[b]
                        if v > dd:
                            dd = v
                D[ci - d_i0 + pi_, cj - d_j0 + pj_] = dd
            v = dd + ol[a]
            if v < best:
                best = v
        out[k] = best
    return out


@jit
def block_max(S, bs):
    """The highest node of each block of bs x bs nodes of S (the last blocks partial),
    nan nodes left out (-inf for a block of nan nodes only): :func:`drop_grid`'s bmax."""
    n0, n1 = S.shape
    m0, m1 = (n0 + bs - 1) // bs, (n1 + bs - 1) // bs
    out = np.full((m0, m1), -np.inf)
    for i in range(n0):
        bi = i // bs
        for j in range(n1):
            v = S[i, j]
            if v > out[bi, j // bs]:
                out[bi, j // bs] = v
    return out


@jit
def drop_grid(S, hx, hy, X, Y, di, dj, lift, out, bmax, bs, ri, rj):
    """roughing_rest.drop_on_grid's maximum: per position k, max over the offsets a of
    S[i0 + di[a], j0 + dj[a]] - lift[a] over the nodes inside the grid (S is (ny, nx):
    rows along y), i0, j0 the node nearest (X[k], Y[k]); -inf where none.

    ``bmax`` (size 0: not used): the highest node of each block of bs x bs nodes (nan
    nodes, which never win, left out), the offsets in rising ``lift`` and |di| <= ri,
    |dj| <= rj: the search stops at the first offset whose lift puts the highest node of
    the blocks it can reach no higher than the best so far (S - lift <= top - lift in
    floating point too: the same maximum)."""
    ny, nx = S.shape
    bounded = bmax.size > 0
    for k in range(X.size):
        i0 = int(np.rint(Y[k] / hy))
        j0 = int(np.rint(X[k] / hx))
        best = -np.inf
        top = np.inf
        if bmax.size:
            # the highest node of the blocks the offsets reach: no offset a with
            # top - lift[a] <= best (lift ascending) can raise the maximum
            top = -np.inf
            for bi in range(max(0, (i0 - ri) // bs), min(bmax.shape[0] - 1, (i0 + ri) // bs) + 1):
                for bj in range(max(0, (j0 - rj) // bs), min(bmax.shape[1] - 1, (j0 + rj) // bs) + 1):
                    if not (bmax[bi, bj] <= top):
                        top = bmax[bi, bj]
        for a in range(di.size):
            if bounded and top - lift[a] <= best:     # (loop-invariant flag: the compiler unswitches it)
                break
            i = i0 + di[a]
            j = j0 + dj[a]
            if 0 <= i < ny and 0 <= j < nx:
                v = S[i, j] - lift[a]
                if v > best:
                    best = v
        out[k] = best


# ----------------------------------------------------------------------------
# a grid's steepest slope in a band of heights: numpy.gradient's differences (central
# inside, one-sided at the edges, edge_order=1, uniform spacing) to the last bit,
# without its two arrays (roughing._band_slope)
# ----------------------------------------------------------------------------
@jit
def _d0(f, i, j, h):
    """numpy.gradient(f, h, axis=0)[i, j] (f has at least 2 rows)."""
    n = f.shape[0]
    if i == 0:
        return (f[1, j] - f[0, j]) / h
    if i == n - 1:
        return (f[n - 1, j] - f[n - 2, j]) / h
    return (f[i + 1, j] - f[i - 1, j]) / (2.0 * h)


@jit
def _d1(f, i, j, h):
    """numpy.gradient(f, h, axis=1)[i, j] (f has at least 2 columns)."""
    n = f.shape[1]
    if j == 0:
        return (f[i, 1] - f[i, 0]) / h
    if j == n - 1:
        return (f[i, n - 1] - f[i, n - 2]) / h
    return (f[i, j + 1] - f[i, j - 1]) / (2.0 * h)


@jit
def curvature_bounds(H, lo, hi, hxx2, hyy2, hxy):
    """roughing.LevelSets' second differences of H (rows along y, columns along x),
    their largest magnitudes over the centre nodes whose H lies in [lo, hi]: |H[i, j+1]
    - 2 H[i, j] + H[i, j-1]| / hxx2, |H[i+1, j] - 2 H[i, j] + H[i-1, j]| / hyy2 and, at
    (i, j) with i, j >= 1, |H[i, j] - H[i, j-1] - H[i-1, j] + H[i-1, j-1]| / hxy; the
    operations of its array expressions in their order. Returns (cxx, cyy, cxy), -1 for
    none."""
    n0, n1 = H.shape
    cxx = cyy = cxy = -1.0
    for i in range(n0):
        for j in range(n1):
            v = H[i, j]
            if not (v >= lo and v <= hi):
                continue
            if 0 < j < n1 - 1:
                a = abs(H[i, j + 1] - 2 * H[i, j] + H[i, j - 1]) / hxx2
                if a > cxx:
                    cxx = a
            if 0 < i < n0 - 1:
                a = abs(H[i + 1, j] - 2 * H[i, j] + H[i - 1, j]) / hyy2
                if a > cyy:
                    cyy = a
            if i > 0 and j > 0:
                a = abs(H[i, j] - H[i, j - 1] - H[i - 1, j] + H[i - 1, j - 1]) / hxy
                if a > cxy:
                    cxy = a
    return cxx, cyy, cxy


@jit
def slope_grids(f, h0, h1, normal, slope):
    """With g0, g1 = numpy.gradient(f, h0, h1): normal[i, j] = 1 / sqrt((1 + g0^2) + g1^2)
    (a vertical height to the normal distance) and slope[i, j] = hypot(g0, g1), the
    operations in the order of the array expressions they replace; an output of size 0
    is not computed. f: (n0, n1), n0, n1 >= 2."""
    n0, n1 = f.shape
    want_n = normal.size == f.size
    want_s = slope.size == f.size
    for i in range(n0):
        for j in range(n1):
            g0 = _d0(f, i, j, h0)
            g1 = _d1(f, i, j, h1)
            if want_n:
                t = 1.0 + g0 * g0
                t = t + g1 * g1
                normal[i, j] = 1.0 / math.sqrt(t)
            if want_s:
                slope[i, j] = math.hypot(g0, g1)


@jit
def band_max_slope(f, h0, h1, low, high):
    """max of hypot(g0, g1) (g0, g1 = numpy.gradient(f, h0, h1)) over the nodes with
    low <= f <= high and both differences finite; -1 where there is none. f: (n0, n1),
    n0, n1 >= 2."""
    n0, n1 = f.shape
    best = -1.0
    for i in range(n0):
        for j in range(n1):
            v = f[i, j]
            if not (v >= low and v <= high):
                continue
            g0 = _d0(f, i, j, h0)
            g1 = _d1(f, i, j, h1)
            if not (math.isfinite(g0) and math.isfinite(g1)):
                continue
            s = math.hypot(g0, g1)
            if s > best:
                best = s
    return best


# ----------------------------------------------------------------------------
# the whole job's per-node checks (stock.verify_job): one pass over the grid each,
# the same floating-point operations, in the same order, as the array expressions
# they replace (so the same figures to the last bit)
# ----------------------------------------------------------------------------
@jit
def node_bounds(z, dz, before, scale, use_scale, slope, extra_h, slack, leave, tol, high):
    """Per node (flat arrays): above = z - dz, the allowance's target
    T = min(dz + leave, 0), its upper bound hi = (T - dz) + (slack + extra_h slope)
    (slope: only when extra_h is given as used: ``slope.size``), high[k] = above
    (times scale[k] when use_scale) > hi. Returns (ig, gouge, irm, removed): the first
    node of largest -above and its value, the first of largest before - z and its value."""
    n = z.size
    ig, gmax = 0, -np.inf
    irm, rmax = 0, -np.inf
    gnan = rnan = False
    use_slope = slope.size == n
    for k in range(n):
        above = z[k] - dz[k]
        g = -above
        if not gnan:
            if g != g:
                ig, gmax, gnan = k, g, True
            elif g > gmax:
                ig, gmax = k, g
        rm = before[k] - z[k]
        if not rnan:
            if rm != rm:
                irm, rmax, rnan = k, rm, True
            elif rm > rmax:
                irm, rmax = k, rm
        t = dz[k] + leave
        if not (t <= 0.0):
            t = 0.0 if t == t else t
        s = slack + extra_h * slope[k] if use_slope else slack
        hi = (t - dz[k]) + s
        a = above * scale[k] if use_scale else above
        high[k] = a > hi
    return ig, gmax, irm, rmax


@jit
def node_verdicts(z, dz, scale, use_scale, slope, extra_h, slack, leave, tol, reach, reach_c, high):
    """The figures of the nodes above their bound (``high``, from :func:`node_bounds`)
    against the tool's reach (nan: not computed) raised by reach_c x slope (the reach's
    own error; reach_c < 0: none), and of all nodes against the low bound and the
    allowance left. Returns
    (n_over, over_max, over_at, n_unre, unre_max, unre_at, low_at, low_max,
     left_min, left_max, left_at) with -1 for an index that does not exist."""
    n = z.size
    use_slope = slope.size == n
    n_over, over_max, over_at = 0, -np.inf, -1
    n_unre, unre_max, unre_at = 0, -np.inf, -1
    low_at, low_max = -1, -np.inf
    left_min, left_max, left_at = np.inf, -np.inf, -1
    for k in range(n):
        above = z[k] - dz[k]
        d = dz[k] + leave
        t = d
        if not (t <= 0.0):
            t = 0.0 if t == t else t
        want = t - dz[k]
        lo = want - tol
        sl = slope[k] if use_slope else 0.0
        s = slack + extra_h * sl if use_slope else slack
        hi = want + s
        a = above * scale[k] if use_scale else above
        unre = False
        if high[k]:
            if reach_c >= 0.0:
                r = reach[k] + sl * 0.5 * reach_c
            else:
                r = reach[k] + 0.0
            m = t if r != r else (r if t != t else (t if t >= r else r))
            ex = z[k] - m
            if use_scale:
                ex = ex * scale[k]
            ex = ex - s
            if ex > 0.0:
                n_over += 1
                if ex > over_max:
                    over_max, over_at = ex, k
            else:
                unre = True
                n_unre += 1
                u = above - hi
                if u > unre_max or unre_at < 0:
                    unre_max, unre_at = u, k
        if above < lo:
            v = lo - above
            if v > low_max or low_at < 0:
                low_max, low_at = v, k
        if d < 0.0 and not unre:
            if a == a:
                if a < left_min:
                    left_min = a
                if a > left_max or left_at < 0:
                    left_max, left_at = a, k
    return n_over, over_max, over_at, n_unre, unre_max, unre_at, low_at, low_max, left_min, left_max, left_at


# ----------------------------------------------------------------------------
# window filters along the rows of a 2-D array, the edges repeated (scipy.ndimage's
# mode "nearest"), to the last bit of scipy.ndimage's own (its running sum for the
# mean; min and max are exact); :func:`window_minmax` and :func:`window_mean` apply
# them along both axes
# ----------------------------------------------------------------------------
@jit
def _minmax_rows(a_lo, a_hi, size, lo, hi):
    n0, n = a_lo.shape
    s1 = size // 2
    for i in range(n0):
        for t in range(n):
            m, M = np.inf, -np.inf
            for u in range(t - s1, t - s1 + size):
                q = min(max(u, 0), n - 1)
                if a_lo[i, q] < m:
                    m = a_lo[i, q]
                if a_hi[i, q] > M:
                    M = a_hi[i, q]
            lo[i, t] = m
            hi[i, t] = M


@jit
def _minmax_cols(a_lo, a_hi, size, lo, hi, want_lo):
    """:func:`_minmax_rows` along axis 0 (the window over rows, each row's nodes in
    turn: contiguous, no transposed copy); the same comparisons, so the same values.
    ``want_lo`` False: the maximum alone (``lo`` untouched)."""
    n, n1 = a_lo.shape
    s1 = size // 2
    for t in range(n):
        for j in range(n1):
            hi[t, j] = -np.inf
        if want_lo:
            for j in range(n1):
                lo[t, j] = np.inf
        for u in range(t - s1, t - s1 + size):
            q = min(max(u, 0), n - 1)
            for j in range(n1):
                if a_hi[q, j] > hi[t, j]:
                    hi[t, j] = a_hi[q, j]
            if want_lo:
                for j in range(n1):
                    if a_lo[q, j] < lo[t, j]:
                        lo[t, j] = a_lo[q, j]


@jit
def _max_rows(a, size, hi):
    """:func:`_minmax_rows`'s maximum alone."""
    n0, n = a.shape
    s1 = size // 2
    for i in range(n0):
        for t in range(n):
            M = -np.inf
            for u in range(t - s1, t - s1 + size):
                q = min(max(u, 0), n - 1)
                if a[i, q] > M:
                    M = a[i, q]
            hi[i, t] = M


@jit
def _mean_rows(a, size, out):
    n0, n = a.shape
    s1 = size // 2
    for i in range(n0):
        tmp = 0.0
        for u in range(-s1, size - s1):
            tmp += a[i, min(max(u, 0), n - 1)]
        out[i, 0] = tmp / size
        for t in range(1, n):
            tmp += a[i, min(t + size - 1 - s1, n - 1)] - a[i, max(t - 1 - s1, 0)]
            out[i, t] = tmp / size


@jit
def _mean_cols(a, size, out, tmp):
    """:func:`_mean_rows` along axis 0: each column's running sum (``tmp``, one per
    column) takes the same terms in the same order, so the same bits."""
    n, n1 = a.shape
    s1 = size // 2
    for j in range(n1):
        tmp[j] = 0.0
    for u in range(-s1, size - s1):
        q = min(max(u, 0), n - 1)
        for j in range(n1):
            tmp[j] += a[q, j]
    for j in range(n1):
        out[0, j] = tmp[j] / size
    for t in range(1, n):
        qa, qb = min(t + size - 1 - s1, n - 1), max(t - 1 - s1, 0)
        for j in range(n1):
            tmp[j] += a[qa, j] - a[qb, j]
            out[t, j] = tmp[j] / size


def window_minmax(a, size):
    """(min, max) of ``a`` (2-D, float) over windows of ``size`` = (s0, s1) nodes (odd)
    centred on each node, the edges repeated: scipy.ndimage.minimum_filter and
    maximum_filter(a, size, mode="nearest") (a max window reaching past the edge is the
    same with mode "constant", cval -inf)."""
    lo = np.ascontiguousarray(a, dtype=float)
    hi = lo
    if size[0] > 1:
        l2, h2 = np.empty_like(lo), np.empty_like(hi)
        _minmax_cols(lo, hi, int(size[0]), l2, h2, True)
        lo, hi = l2, h2
    if size[1] > 1:
        l2, h2 = np.empty_like(lo), np.empty_like(hi)
        _minmax_rows(lo, hi, int(size[1]), l2, h2)
        lo, hi = l2, h2
    return lo, hi


def window_max(a, size, out=None):
    """The maximum of :func:`window_minmax` alone (half the work); ``out``: the array
    to write it to (C-contiguous float, ``a`` itself allowed), else a new one."""
    hi = np.ascontiguousarray(a, dtype=float)
    if size[0] > 1:
        h2 = np.empty_like(hi)
        _minmax_cols(hi, hi, int(size[0]), np.empty((0, 0)), h2, False)
        hi = h2
    if size[1] > 1:
        h2 = np.empty_like(hi) if out is None or out is hi else out
        _max_rows(hi, int(size[1]), h2)
        hi = h2
    if out is not None and out is not hi:
        out[...] = hi
        hi = out
    return hi


def window_mean(a, size):
    """scipy.ndimage.uniform_filter(a, size, mode="nearest") (2-D, float64; axes of size
    1 untouched, as there), to the last bit."""
    out = np.ascontiguousarray(a, dtype=float)
    if size[0] > 1:
        res = np.empty_like(out)
        _mean_cols(out, int(size[0]), res, np.empty(out.shape[1]))
        out = res
    if size[1] > 1:
        res = np.empty_like(out)
        _mean_rows(out, int(size[1]), res)
        out = res
    return out


# ----------------------------------------------------------------------------
# the picture's pooling (stock.stock_png): k x k blocks of nodes to one pixel
# ----------------------------------------------------------------------------
@jit
def pool_envelope(lo, hi, k, out):
    """Per block of k x k nodes (the last partial rows and columns dropped): the node
    envelopes env = lo where -lo > hi, else hi, and of those the one of largest
    magnitude, the minimum where -min > max, else the maximum (nan if any is nan, as
    numpy's max and min give)."""
    n0, n1 = out.shape
    for I in range(n0):
        for J in range(n1):
            M, m = -np.inf, np.inf
            nan = False
            for u in range(I * k, I * k + k):
                for v in range(J * k, J * k + k):
                    a, b = lo[u, v], hi[u, v]
                    e = a if -a > b else b
                    if e != e:
                        nan = True
                    if e > M:
                        M = e
                    if e < m:
                        m = e
            if nan:
                out[I, J] = np.nan
            else:
                out[I, J] = m if -m > M else M


@jit
def pool_window_envelope(a, k, w0, w1, out):
    """:func:`pool_envelope` of :func:`window_minmax` (a, (w0, w1)) without the full-size
    windows: a block of k x k nodes takes the minimum m and maximum M of ``a`` over the
    union of its nodes' windows (the edges repeated: clamped to the grid), m where -m >
    M, else M. The same value: the node whose window holds the minimum has it as its
    window's minimum, and its window's maximum is at most M, so where -m > M that node's
    envelope is m and none is larger in magnitude; else the node whose window holds the
    maximum has M as its envelope, and every envelope lies within [m, M] with -m <= M.
    ``a`` without nan (a window of nan nodes only gives its node the envelope -inf, which
    this does not see; infinities are fine)."""
    n0, n1 = a.shape
    N0, N1 = out.shape
    s0, s1 = w0 // 2, w1 // 2
    lo = np.empty((n0, N1))
    hi = np.empty((n0, N1))
    for i in range(n0):
        for J in range(N1):
            m, M = np.inf, -np.inf
            for v in range(max(0, J * k - s1), min(n1 - 1, J * k + k - 1 + s1) + 1):
                x = a[i, v]
                if x < m:
                    m = x
                if x > M:
                    M = x
            lo[i, J] = m
            hi[i, J] = M
    for I in range(N0):
        for J in range(N1):
            m, M = np.inf, -np.inf
            for u in range(max(0, I * k - s0), min(n0 - 1, I * k + k - 1 + s0) + 1):
                if lo[u, J] < m:
                    m = lo[u, J]
                if hi[u, J] > M:
                    M = hi[u, J]
            out[I, J] = m if -m > M else M


@jit
def pool_mean(a, k, out):
    """Per block of k x k nodes (the last partial rows and columns dropped) the mean:
    each of its rows summed, the row sums added, over k^2 (numpy's mean over the block
    axes adds in this order)."""
    n0, n1 = out.shape
    for I in range(n0):
        for J in range(n1):
            s = 0.0
            for u in range(I * k, I * k + k):
                t = 0.0
                for v in range(J * k, J * k + k):
                    t += a[u, v]
                s += t
            out[I, J] = s / (k * k)


@jit
def shaded_rgb(dv, shade, gmax, lmax, zero, gouge, left, out):
    """stock.stock_png's picture, per pixel, the same operations as its array expressions:
    the deviation dv (pooled, (n0, n1)) coloured on the scale (gouge side for dv < 0:
    zero + (gouge - zero) clip(-dv / gmax, 0, 1), else zero + (left - zero) clip(dv /
    lmax, 0, 1)), times the hill shade, rounded half to even, clipped to 0..255, into
    ``out`` (n1, n0, 3) uint8 with +Y up (row r holds column n1 - 1 - r of dv). dv finite."""
    n0, n1 = dv.shape
    for i in range(n0):
        for j in range(n1):
            d = dv[i, j]
            sh = shade[i, j]
            r = n1 - 1 - j
            if d < 0:
                t = -d / gmax
                t = min(max(t, 0.0), 1.0)
                for c in range(3):
                    v = np.rint((zero[c] + (gouge[c] - zero[c]) * t) * sh)
                    out[r, i, c] = np.uint8(min(max(v, 0.0), 255.0))
            else:
                t = d / lmax
                t = min(max(t, 0.0), 1.0)
                for c in range(3):
                    v = np.rint((zero[c] + (left[c] - zero[c]) * t) * sh)
                    out[r, i, c] = np.uint8(min(max(v, 0.0), 255.0))

