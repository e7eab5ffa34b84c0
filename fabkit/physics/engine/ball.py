"""The finite-radius rolling ball's template of the compiled engine (``model: ball``).

A template, not imported: :mod:`.codegen` writes it into the generated engine
module before the step loop (:mod:`.dop853`, whose docstring states the contract).
The physics and its derivation are those of :mod:`fabkit.physics.ball` and
docs/ball.md, written here as scalar arithmetic on one state. The surface
function it calls is generated from the user's formula (exact sympy derivatives,
common subexpressions shared), a compiled C callback:

    jet(x, y, P) -> (h, h_x, h_y, h_xx, h_xy, h_yy, h_xxx, h_xxy, h_xyy, h_yyy)

``P`` is the tuple (Pa, jet) with the run-time parameters Pa:

    Pa[0] g    Pa[1] k    Pa[2] r    Pa[3] mu (1/s)    Pa[4] c_rr    Pa[5] friction (inf: none)
    Pa[6] v_s, the rolling resistance's smoothing speed    Pa[7] g~ = g / (1 + k)
    Pa[8:] the surface's parameters, in the order of ``codegen.Formula.names``

State (NV = 6): the contact point (x, y), its velocity (xd, yd), the spin about the
normal u (a speed) and W, the energy dissipated per unit (1 + k) m; the error norm
runs over the first NE = 5. The contact bracket B is the guard
min(N / (m g), 1 - r kappa_1, friction - |F_t| / N): its fall to 0 ends the launch
(:func:`GUARD_OUTCOME` names which limit). The launch's velocity is the centre's
horizontal one (:func:`INIT`, :func:`VEL`).
"""
import math

from numba import njit

jit = njit(cache=True, nogil=True, error_model="numpy")

NV = 6
NE = 5
W = 5
N_MODEL_PARAMS = 8
#: Illinois iterations locating the guard's zero (to rounding: it is a min of three limits)
GUARD_ITERS = 40
#: a ball launched where its guard is down (bridged there, say) ends there
GUARD_AT_LAUNCH = True
#: the outcomes of models.OUTCOMES the guard can name
_LOST_CONTACT, _BRIDGED, _SLIPPED = 3, 4, 5


@jit
def FULL(P):
    return True


@jit
def GT(P):
    return P[0][7]


@jit
def _frame(x, y, P):
    """The frame at the contact point: h, h_x, h_y, the second derivatives, n, n_x,
    n_y, C_x, C_y, C_xx, C_xy, C_yy (3-tuples), as in ball.geometry."""
    Pa, jet = P
    r = Pa[2]
    h, p, q, hxx, hxy, hyy, hxxx, hxxy, hxyy, hyyy = jet(x, y, Pa.ctypes)
    w = 1.0 / math.sqrt(1.0 + p * p + q * q)
    w3 = w * w * w
    w5 = w3 * w * w
    Ax = p * hxx + q * hxy
    Ay = p * hxy + q * hyy
    wx = -w3 * Ax
    wy = -w3 * Ay
    Axx = hxx * hxx + hxy * hxy + p * hxxx + q * hxxy
    Axy = hxx * hxy + hxy * hyy + p * hxxy + q * hxyy
    Ayy = hxy * hxy + hyy * hyy + p * hxyy + q * hyyy
    wxx = 3.0 * w5 * Ax * Ax - w3 * Axx
    wxy = 3.0 * w5 * Ax * Ay - w3 * Axy
    wyy = 3.0 * w5 * Ay * Ay - w3 * Ayy
    n = (-p * w, -q * w, w)
    nx = (-hxx * w - p * wx, -hxy * w - q * wx, wx)
    ny = (-hxy * w - p * wy, -hyy * w - q * wy, wy)
    nxx = (-hxxx * w - 2.0 * hxx * wx - p * wxx, -hxxy * w - 2.0 * hxy * wx - q * wxx, wxx)
    nxy = (-hxxy * w - hxx * wy - hxy * wx - p * wxy, -hxyy * w - hxy * wy - hyy * wx - q * wxy, wxy)
    nyy = (-hxyy * w - 2.0 * hxy * wy - p * wyy, -hyyy * w - 2.0 * hyy * wy - q * wyy, wyy)
    Cx = (1.0 + r * nx[0], r * nx[1], p + r * nx[2])
    Cy = (r * ny[0], 1.0 + r * ny[1], q + r * ny[2])
    Cxx = (r * nxx[0], r * nxx[1], hxx + r * nxx[2])
    Cxy = (r * nxy[0], r * nxy[1], hxy + r * nxy[2])
    Cyy = (r * nyy[0], r * nyy[1], hyy + r * nyy[2])
    return h, p, q, hxx, hxy, hyy, n, nx, ny, Cx, Cy, Cxx, Cxy, Cyy


@jit
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@jit
def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@jit
def _kappa1(p, q, hxx, hxy, hyy):
    """The largest principal curvature of z = h, upward normal (surface.principal_curvatures)."""
    w = math.sqrt(1.0 + p * p + q * q)
    E = 1.0 + p * p
    Fm = p * q
    G = 1.0 + q * q
    L = hxx / w
    M = hxy / w
    N = hyy / w
    det = E * G - Fm * Fm
    K = (L * N - M * M) / det
    H = (E * N - 2.0 * Fm * M + G * L) / (2.0 * det)
    return H + math.sqrt(max(H * H - K, 0.0))


@jit
def _eval(S, P, F, contact):
    """F = dS/dt (ball.evaluate); returns (h, dh/dt, guard, slip, v, zc, N / m, kappa_1).
    Without ``contact`` (Runge-Kutta stages) guard and slip are not computed (1, nan)."""
    x = S[0]
    y = S[1]
    xd = S[2]
    yd = S[3]
    u = S[4]
    Pa = P[0]
    g = Pa[0]
    k = Pa[1]
    r = Pa[2]
    mu = Pa[3]
    c_rr = Pa[4]
    h, p, q, hxx, hxy, hyy, n, nx, ny, Cx, Cy, Cxx, Cxy, Cyy = _frame(x, y, P)
    v = (Cx[0] * xd + Cy[0] * yd, Cx[1] * xd + Cy[1] * yd, Cx[2] * xd + Cy[2] * yd)
    nd = (nx[0] * xd + ny[0] * yd, nx[1] * xd + ny[1] * yd, nx[2] * xd + ny[2] * yd)
    xd2 = xd * xd
    xyd = 2.0 * xd * yd
    yd2 = yd * yd
    Q = (Cxx[0] * xd2 + Cxy[0] * xyd + Cyy[0] * yd2, Cxx[1] * xd2 + Cxy[1] * xyd + Cyy[1] * yd2,
         Cxx[2] * xd2 + Cxy[2] * xyd + Cyy[2] * yd2)
    Nm = g * n[2] - _dot(v, nd)
    nxn = _cross(n, nd)
    vv = _dot(v, v)
    f0 = 0.0
    f1 = 0.0
    f2 = 0.0
    if mu != 0.0:
        c = -(1.0 + k) * mu
        f0 = c * v[0]
        f1 = c * v[1]
        f2 = c * v[2]
    if c_rr != 0.0:
        c = -c_rr * max(Nm, 0.0) / math.sqrt(vv + Pa[6] * Pa[6])
        f0 = f0 + c * v[0]
        f1 = f1 + c * v[1]
        f2 = f2 + c * v[2]
    R = (k * u * nxn[0] + f0, k * u * nxn[1] + f1, -g + k * u * nxn[2] + f2)
    inv = 1.0 / (1.0 + k)
    b1 = _dot(Cx, R) * inv - _dot(Cx, Q)
    b2 = _dot(Cy, R) * inv - _dot(Cy, Q)
    G11 = _dot(Cx, Cx)
    G12 = _dot(Cx, Cy)
    G22 = _dot(Cy, Cy)
    det = G11 * G22 - G12 * G12
    F[0] = xd
    F[1] = yd
    F[2] = (G22 * b1 - G12 * b2) / det
    F[3] = (G11 * b2 - G12 * b1) / det
    F[4] = _dot(_cross(n, v), nd)
    F[5] = -(f0 * v[0] + f1 * v[1] + f2 * v[2]) * inv
    zc = h + r * n[2]
    zd = p * xd + q * yd
    if not contact:
        return h, zd, 1.0, math.nan, v, zc, Nm, 0.0
    # the friction the rolling needs: F_t / m = k / (1 + k) (u (n x n') - g_t - f_t)
    gn = -g * n[2]
    fn = f0 * n[0] + f1 * n[1] + f2 * n[2]
    t0 = k * inv * (u * nxn[0] + gn * n[0] - (f0 - fn * n[0]))
    t1 = k * inv * (u * nxn[1] + gn * n[1] - (f1 - fn * n[1]))
    t2 = k * inv * (u * nxn[2] - (-g - gn * n[2]) - (f2 - fn * n[2]))
    Ftm = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    slip = Ftm / Nm if Nm > 0 else math.inf
    kappa = _kappa1(p, q, hxx, hxy, hyy)
    gd = min(Nm / g, 1.0 - r * kappa)
    fr = Pa[5]
    if math.isfinite(fr):
        gd = min(gd, fr - slip if Nm > 0 else -1.0)
    return h, zd, gd, slip, v, zc, Nm, kappa


@jit
def rhs(S, P, F, contact):
    """F = dS/dt; returns (h, dh/dt, B, slip) with B the guard (see the module doc)."""
    h, zd, gd, slip, v, zc, Nm, kappa = _eval(S, P, F, contact)
    return h, zd, gd, slip


@jit
def GUARD_OUTCOME(S, P, F):
    """Which limit the guard reached at S: lost_contact, bridged or slipped (ball.guard_reason)."""
    h, zd, gd, slip, v, zc, Nm, kappa = _eval(S, P, F, True)
    Pa = P[0]
    a = Nm / Pa[0]
    b = 1.0 - Pa[2] * kappa
    c = math.inf
    if math.isfinite(Pa[5]):
        c = Pa[5] - slip if Nm > 0 else -1.0
    if b <= a and b <= c:
        return _BRIDGED
    if c < a:
        return _SLIPPED
    return _LOST_CONTACT


@jit
def INIT(S, P):
    """The launch: S[2], S[3] hold the centre's horizontal velocity; replace them by the
    contact point's velocity with that centre velocity (ball.contact_velocity)."""
    h, p, q, hxx, hxy, hyy, n, nx, ny, Cx, Cy, Cxx, Cxy, Cyy = _frame(S[0], S[1], P)
    a = Cx[0]
    b = Cy[0]
    c = Cx[1]
    d = Cy[1]
    det = a * d - b * c
    vx = S[2]
    vy = S[3]
    S[2] = (d * vx - b * vy) / det
    S[3] = (a * vy - c * vx) / det


@jit
def VEL(S, P):
    """The reported horizontal velocity: the centre's."""
    h, p, q, hxx, hxy, hyy, n, nx, ny, Cx, Cy, Cxx, Cxy, Cyy = _frame(S[0], S[1], P)
    return Cx[0] * S[2] + Cy[0] * S[3], Cx[1] * S[2] + Cy[1] * S[3]


@jit
def _energies(S, P, inv):
    """(kinetic, potential) per unit (1 + k) m, velocities (and u) scaled by inv."""
    h, p, q, hxx, hxy, hyy, n, nx, ny, Cx, Cy, Cxx, Cxy, Cyy = _frame(S[0], S[1], P)
    Pa = P[0]
    k = Pa[1]
    xd = S[2] * inv
    yd = S[3] * inv
    vx = Cx[0] * xd + Cy[0] * yd
    vy = Cx[1] * xd + Cy[1] * yd
    vz = Cx[2] * xd + Cy[2] * yd
    u = S[4] * inv
    kin = 0.5 * (vx * vx + vy * vy + vz * vz) + 0.5 * k / (1.0 + k) * u * u
    return kin, Pa[7] * ((h + Pa[2] * n[2]) * (inv * inv))


@jit
def kinetic(S, P, inv):
    """The kinetic energy (translation and spin) per unit (1 + k) m, times inv^2."""
    return _energies(S, P, inv)[0]


@jit
def energy(S, P, inv):
    """E = 1/2 |v|^2 + k / (2 (1 + k)) u^2 + g~ z_C, times inv^2."""
    kin, pot = _energies(S, P, inv)
    return kin + pot
