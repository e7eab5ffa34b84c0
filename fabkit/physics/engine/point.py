"""The point-particle model template of the compiled engine (``full`` and
``simplified``, with viscous and localized nonlinear damping).

A template, not imported: :mod:`.codegen` writes it into the generated module
after the surface functions, and :mod:`.dop853` uses what it defines (see that
module's docstring for the contract). The surface functions it calls are
generated from the user's formula:

    surface(x, y, P) -> (h, h_x, h_y, h_xx, h_xy, h_yy, F)     F(x) = h_y(x, 0)

It is a compiled C callback (numba ``cfunc``) of the formula's own generated
module (one callback: each load from the cache costs a few tenths of a second), passed in at run time: the engine itself is compiled once for every
formula. ``P`` is the tuple (Pa, surface) with the run-time
parameters Pa (so one compiled module serves every model variant and every value
of ``surface.params``):

    Pa[0] g~ = g / (1 + k)    Pa[1] mu (1/s)    Pa[2] mu_nl    Pa[3] 1 full | 0 simplified
    Pa[4:-3] the surface's parameters, in the order of ``codegen.Formula.names``
    Pa[-3] c_rr / (1 + k)   Pa[-2] v_s   Pa[-1] g: the rolling resistance (models.py's
    module doc), after the surface's parameters so that their offset stays N_MODEL_PARAMS

State (NV = 5): x, y, xd, yd and W, the energy dissipated by damping (per unit
(1 + k) m); the error norm runs over the first NE = 4. Equations: eq. (xyODE)

    [xdd, ydd] = - B / (1 + h_x^2 + h_y^2) [h_x, h_y],  B = h_xx xd^2 + 2 h_xy xd yd + h_yy yd^2 + g~

or eq. (xyODE_simp) [xdd, ydd] = - g~ [h_x, h_y], plus the damping - mu [xd, yd],
- mu_nl F(x)^2 y^2 yd on y and the rolling resistance c [xd, yd],
c = - c_rr / (1 + k) max(N/m, 0) / sqrt(|v|^2 + v_s^2); dW/dt = - D . (v + zd grad h)
(full) or - D . v.
"""
import math

from numba import njit

jit = njit(cache=True, nogil=True, error_model="numpy")

NV = 5
NE = 4
W = 4
N_MODEL_PARAMS = 4
#: secant iterations locating the loss of contact
GUARD_ITERS = 4
#: the bracket is watched from the first step on (a launch beyond the surface's hold, such
#: as 1e20 cm/s over a crest, leaves the footprint within the first step: flew_off)
GUARD_AT_LAUNCH = False


@jit
def FULL(P):
    return P[0][3] != 0.0


@jit
def GT(P):
    return P[0][0]


@jit
def rhs(S, P, F, contact):
    """F = dS/dt; returns (z, dz/dt, B, slip) (B = 1 in the simplified model: no contact
    check; no slip ratio for a point: nan). ``contact`` is the ball's (B costs nothing here)."""
    x = S[0]
    y = S[1]
    vx = S[2]
    vy = S[3]
    Pa, surface = P
    gt = Pa[0]
    mu = Pa[1]
    mu_nl = Pa[2]
    full = Pa[3] != 0.0
    n_pa = Pa.shape[0]
    crr_k = Pa[n_pa - 3]
    h, hx, hy, hxx, hxy, hyy, fy = surface(x, y, Pa.ctypes)
    if full:          # eq. (xyODE)
        B = hxx * vx * vx + 2.0 * hxy * vx * vy + hyy * vy * vy + gt
        q = B / (1.0 + hx * hx + hy * hy)
    else:             # eq. (xyODE_simp)
        B = 1.0
        q = gt
    F[0] = vx
    F[1] = vy
    zd = hx * vx + hy * vy
    if mu != 0.0 or mu_nl != 0.0 or crr_k != 0.0:
        dx = -mu * vx
        dy = -mu * vy
        if mu_nl != 0.0:
            dy = dy - mu_nl * fy * fy * y * y * vy
        if crr_k != 0.0:   # rolling resistance: c_rr N opposing v (models.py's module doc)
            vs = Pa[n_pa - 2]
            g = Pa[n_pa - 1]
            if full:
                Nm = (g + B - gt) / math.sqrt(1.0 + hx * hx + hy * hy)
                v2 = vx * vx + vy * vy + zd * zd
            else:
                Nm = g
                v2 = vx * vx + vy * vy
            c = -crr_k * max(Nm, 0.0) / math.sqrt(v2 + vs * vs)
            dx = dx + c * vx
            dy = dy + c * vy
        F[2] = -q * hx + dx
        F[3] = -q * hy + dy
        if full:
            F[4] = -(dx * (vx + zd * hx) + dy * (vy + zd * hy))
        else:
            F[4] = -(dx * vx + dy * vy)
    else:
        F[2] = -q * hx
        F[3] = -q * hy
        F[4] = 0.0
    return h, zd, B, math.nan


@jit
def GUARD_OUTCOME(S, P, F):
    """The bracket of eq. (xyODE) fell to 0: the point lost contact."""
    return 3


@jit
def INIT(S, P):
    """The launch state needs no change: (xd, yd) is the launch velocity."""
    return


@jit
def VEL(S, P):
    """The reported horizontal velocity (xd, yd)."""
    return S[2], S[3]


@jit
def kinetic(S, P, inv):
    """Kinetic energy per unit (1 + k) m, velocities scaled by inv (a power of two)."""
    Pa, surface = P
    h, hx, hy, hxx, hxy, hyy, fy = surface(S[0], S[1], Pa.ctypes)
    vx = S[2] * inv
    vy = S[3] * inv
    kin = vx * vx + vy * vy
    if Pa[3] != 0.0:
        zd = hx * vx + hy * vy
        kin = kin + zd * zd
    return 0.5 * kin


@jit
def energy(S, P, inv):
    """E = kinetic + g~ h, times inv^2 (exactly E where inv is 1)."""
    Pa, surface = P
    h, hx, hy, hxx, hxy, hyy, fy = surface(S[0], S[1], Pa.ctypes)
    return kinetic(S, P, inv) + Pa[0] * (h * (inv * inv))
