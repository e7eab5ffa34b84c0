"""The explicit Runge-Kutta kernel of the batched integrator (integrate.py).

Butcher tableaux as data (scipy's Dormand-Prince 8(5,3) ``DOP853`` and 5(4)
``RK45`` coefficients, as in ``scipy.integrate._ivp.rk``), the right-hand side on
a batch of lanes, one step, its error norm (scipy's, so tolerances mean the same)
and the initial step. Pure array functions: every lane's arithmetic is
elementwise and in a fixed order, so a lane's result never depends on the other
lanes of its batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# ----------------------------------------------------------------------------
# tableaux (data, as in scipy.integrate._ivp.rk)
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Tableau:
    name: str
    n_stages: int
    C: tuple
    A: tuple          # A[s] = ((j, a_sj), ...) nonzero entries only
    B: tuple          # ((j, b_j), ...)
    E: tuple          # error weights over stages + f(y_new)
    E3: tuple         # DOP853's second estimate (empty for RK45)
    order: int        # error estimator order (the step-size exponent is -1/(order+1))


def _nz(row):
    return tuple((j, float(a)) for j, a in enumerate(row) if a != 0.0)


_TABLEAUX: dict[str, Tableau] = {}


def tableau(name: str) -> Tableau:
    """The Butcher tableau of 'DOP853' or 'RK45' (from scipy's own coefficients)."""
    if name not in _TABLEAUX:
        if name == "DOP853":
            from scipy.integrate._ivp import dop853_coefficients as d

            n = d.N_STAGES
            _TABLEAUX[name] = Tableau(
                name, n, tuple(float(c) for c in d.C[:n]), tuple(_nz(d.A[s, :s]) for s in range(n)),
                _nz(d.B), _nz(d.E5), _nz(d.E3), 7)
        elif name == "RK45":
            from scipy.integrate import RK45

            n = RK45.n_stages
            _TABLEAUX[name] = Tableau(
                name, n, tuple(float(c) for c in RK45.C), tuple(_nz(RK45.A[s, :s]) for s in range(n)),
                _nz(RK45.B), _nz(RK45.E), (), 4)
        else:
            raise ValueError(f"method must be DOP853 or RK45, got {name!r}")
    return _TABLEAUX[name]


# ----------------------------------------------------------------------------
# the right-hand side on the batch
# ----------------------------------------------------------------------------
class _System:
    """d/dt of the lane states on (nv, m) arrays, nv = 4 (x, y, xd, yd) or 5 (+ W, the
    dissipated energy, when damped), with aux (h, h_x, h_y, B) from the same evaluation.

    The interface the loop uses (the ball's :class:`_BallSystem` has the same):
    ``nv`` state rows, ``ne`` rows in the error norm, ``iw`` the row of W, ``guarded``
    (aux[3] is a guard whose fall to 0 ends the launch), ``gt``, ``damped``,
    ``__call__``, ``energy``, ``kinetic``, ``initial``, ``velocity`` and ``guard_outcome``.
    """

    ne = 4
    guard_iters = 4   # secant iterations locating the loss of contact

    def __init__(self, problem):
        from .models import fused

        self.p = problem
        self.full = problem.model == "full"
        self.guarded = self.full
        self.gt = problem.g_tilde
        self.damped = float(problem.damping) > 0 or float(problem.nonlinear_damping) > 0
        self.nv = 5 if self.damped else 4
        self.iw = 4
        self.f = fused(problem)

    def deriv(self, S, out=None):
        """Only d(state)/dt (the Runge-Kutta stages)."""
        return self(S, out)[0]

    def __call__(self, S, out=None):
        # floating-point warnings are silenced by the caller (np.errstate around the run):
        # overflow in a rejected trial step is expected and handled by the step control
        ax, ay, h, hx, hy, br, P = self.f(S[0], S[1], S[2], S[3])
        F = np.empty_like(S) if out is None else out
        F[0] = S[2]
        F[1] = S[3]
        F[2] = ax
        F[3] = ay
        if self.damped:
            F[4] = P
        return F, (h, hx, hy, br)

    def initial(self, start, y0, v_in, vy0):
        """The launch states (nv, n)."""
        Y = np.zeros((self.nv, np.size(v_in)))
        Y[0] = start
        Y[1] = y0
        Y[2] = v_in
        Y[3] = vy0
        return Y

    def velocity(self, S):
        """The reported horizontal velocity (vx, vy) of the states: the ball's."""
        return S[2], S[3]

    def guard_outcome(self, S):
        from .models import LOST_CONTACT

        return np.full(S.shape[1], LOST_CONTACT, dtype=np.int8)

    def kinetic(self, S, aux, inv):
        Vx, Vy = S[2] * inv, S[3] * inv
        return 0.5 * (Vx ** 2 + Vy ** 2 + ((aux[1] * Vx + aux[2] * Vy) ** 2 if self.full else 0.0))

    def energy(self, S, aux, inv=None):
        """E per unit (1 + k) m; with ``inv`` (m,), powers of two, E * inv^2 (exactly
        E where inv is 1): keeps the energy finite for speeds beyond ~1e150."""
        h, hx, hy = aux[0], aux[1], aux[2]
        vx, vy = S[2], S[3]
        if inv is not None:
            vx, vy, h = vx * inv, vy * inv, h * (inv * inv)
        kin = vx * vx + vy * vy
        if self.full:
            zd = hx * vx + hy * vy
            kin = kin + zd * zd
        return 0.5 * kin + self.gt * h


class _BallSystem:
    """The finite ball (:mod:`fabkit.physics.ball`) on the batch: state (x, y, xd, yd, u[, W])
    with (x, y) the contact point; aux = (h, h_x, h_y, guard, slip ratio)."""

    ne = 5
    full = False
    guarded = True
    guard_iters = 40  # the guard (a min of three limits) is located to rounding

    def __init__(self, problem):
        from . import ball

        self.b = ball
        self.p = problem
        self.P = ball.Params.of(problem)
        self.jet = ball.jet_function(problem.fns)
        self.gt = problem.g_tilde
        self.damped = float(problem.damping) > 0 or float(problem.rolling_resistance) > 0
        self.nv = 6 if self.damped else 5
        self.iw = 5

    def _eval(self, S):
        j = self.jet(S[0], S[1])
        ev = self.b.evaluate(j, S[2], S[3], S[4], self.P)
        return j, ev

    def deriv(self, S, out=None):
        """Only d(state)/dt (the Runge-Kutta stages): no contact quantities."""
        j = self.jet(S[0], S[1])
        ev = self.b.evaluate(j, S[2], S[3], S[4], self.P, contact=False)
        F = np.empty_like(S) if out is None else out
        F[0] = S[2]
        F[1] = S[3]
        F[2] = ev["xdd"]
        F[3] = ev["ydd"]
        F[4] = ev["ud"]
        if self.damped:
            F[5] = ev["power"]
        return F

    def __call__(self, S, out=None):
        j, ev = self._eval(S)
        F = np.empty_like(S) if out is None else out
        F[0] = S[2]
        F[1] = S[3]
        F[2] = ev["xdd"]
        F[3] = ev["ydd"]
        F[4] = ev["ud"]
        if self.damped:
            F[5] = ev["power"]
        gd = self.b.guard(ev, self.b.max_concave_curvature(j), self.P)
        return F, (j[0], j[1], j[2], gd, ev["slip"])

    def initial(self, start, y0, v_in, vy0):
        n = np.size(v_in)
        Y = np.zeros((self.nv, n))
        Y[0] = start
        Y[1] = y0
        j = self.jet(Y[0], Y[1])
        geo = self.b.geometry(j, self.P.r)
        Y[2], Y[3] = self.b.contact_velocity(geo, np.asarray(v_in, dtype=float), np.asarray(vy0, dtype=float))
        return Y

    def velocity(self, S):
        j = self.jet(S[0], S[1])
        v = self.b.centre_velocity(self.b.geometry(j, self.P.r), S[2], S[3])
        return v[0], v[1]

    def guard_outcome(self, S):
        j, ev = self._eval(S)
        return self.b.guard_reason(ev, self.b.max_concave_curvature(j), self.P)

    def _energy(self, S, inv):
        j, ev = self._eval(S)
        if inv is None:
            return self.b.energy(ev, S[4], self.P), ev
        s = {"vx": ev["vx"] * inv, "vy": ev["vy"] * inv, "vz": ev["vz"] * inv, "zc": ev["zc"] * (inv * inv)}
        return self.b.energy(s, S[4] * inv, self.P), ev

    def kinetic(self, S, aux, inv):
        return self._energy(S, inv)[0] - self.gt * self._energy(S, None)[1]["zc"] * inv * inv

    def energy(self, S, aux, inv=None):
        return self._energy(S, inv)[0]


def system(problem):
    """The batch right-hand side of ``problem``'s model."""
    return _BallSystem(problem) if problem.model == "ball" else _System(problem)


def _combine(Y, h, K, coeffs, out):
    """out = Y + h * sum_j c_j K_j (K: (S, nv, m), coeffs: ((j, c_j), ...)).

    The stage sum is one multiply and one reduction over the leading (stage) axis:
    numpy adds the rows in order, element by element, so each lane's value depends
    only on that lane (no pairwise or BLAS reordering across lanes).
    """
    if not coeffs:
        out[...] = Y
        return out
    n = coeffs[-1][0] + 1
    col = _dense(coeffs, n)
    acc = _add_reduce(np.multiply(K[:n], col), axis=0)
    np.multiply(acc, h, out=acc)
    np.add(Y, acc, out=out)
    return out


_DENSE: dict = {}
_add_reduce = np.add.reduce


def _dense(coeffs, n):
    """The coefficients as a dense (n, 1, 1) column (cached by identity of ``coeffs``)."""
    col = _DENSE.get(id(coeffs))
    if col is not None and col[0] is coeffs:
        return col[1]
    if True:
        col = np.zeros((n, 1, 1))
        for j, c in coeffs:
            col[j, 0, 0] = c
        _DENSE[id(coeffs)] = (coeffs, col)  # keeps coeffs alive, so its id stays unique
    return col


def _rk_step(sys, tab, Y, F0, h, K):
    """One step of size h (m,) from Y (5, m) with f(Y) = F0; K (n_stages + 1, 5, m) scratch.

    Returns Ynew (5, m); K[0..n_stages-1] hold the stages.
    """
    K[0] = F0
    Ys = np.empty_like(Y)
    for s in range(1, tab.n_stages):
        _combine(Y, h, K, tab.A[s], Ys)
        sys.deriv(Ys, out=K[s])
    Ynew = np.empty_like(Y)
    _combine(Y, h, K, tab.B, Ynew)
    return Ynew


def _rowsum(a):
    """a[0] + a[1] + ... in order (the same arithmetic for any number of rows)."""
    s = a[0] + a[1]
    for i in range(2, a.shape[0]):
        s = s + a[i]
    return s


def _error_norm(tab, K, h, scale):
    """scipy's error norm per lane (m,), over the ne = len(scale) state components
    (4: x, y, xd, yd; the ball adds its spin u)."""
    ne = scale.shape[0]

    def est(coeffs):
        n = coeffs[-1][0] + 1
        acc = _add_reduce(np.multiply(K[:n, :ne], _dense(coeffs, n)), axis=0)
        acc /= scale
        acc *= acc
        return _rowsum(acc)

    if tab.E3:  # DOP853: the 5th and 3rd order estimates combined (Hairer's DOP853)
        e5 = est(tab.E)
        e3 = est(tab.E3)
        denom = e5 + 0.01 * e3
        err = np.abs(h) * e5 / np.sqrt(denom * float(ne))
        return np.where(denom > 0, err, 0.0)
    e = est(tab.E)
    return np.abs(h) * np.sqrt(e / float(ne))


def _error_norm_scaled(tab, K, h, scale):
    """:func:`_error_norm` without overflow: each estimate is divided by its largest
    component (a power of two, so exactly) before squaring. Used only for lanes where
    the plain norm overflows (speeds beyond ~1e100 design units/s), so ordinary lanes
    keep the plain arithmetic bit for bit."""
    ne = scale.shape[0]

    def est(coeffs):
        n = coeffs[-1][0] + 1
        acc = _add_reduce(np.multiply(K[:n, :ne], _dense(coeffs, n)), axis=0)
        acc /= scale
        big = _pow2(np.max(np.abs(acc), axis=0))
        acc /= big
        acc *= acc
        return _rowsum(acc), big

    if tab.E3:
        e5, b5 = est(tab.E)
        e3, b3 = est(tab.E3)
        # err = |h| e5 b5^2 / sqrt(4 (e5 b5^2 + 0.01 e3 b3^2)), with M = max(b5, b3) factored out
        M = np.maximum(b5, b3)
        r5, r3 = b5 / M, b3 / M
        denom = e5 * r5 * r5 + 0.01 * e3 * r3 * r3
        err = np.abs(h) * M * (e5 * r5 * r5) / np.sqrt(denom * float(ne))
        return np.where(denom > 0, err, 0.0)
    e, b = est(tab.E)
    return np.abs(h) * b * np.sqrt(e / float(ne))


def _pow2(a):
    """The power of two at or above |a| (1 where a is 0 or not finite)."""
    ok = np.isfinite(a) & (a > 0)
    return np.where(ok, np.exp2(np.ceil(np.log2(np.where(ok, a, 1.0)))), 1.0)


def _rms4(a):
    """sqrt(mean of squares) over the rows of ``a`` (the error components) (m,),
    without overflow."""
    big = _pow2(np.max(np.abs(a), axis=0))
    b = a / big
    b = b * b
    return big * np.sqrt(_rowsum(b) / float(a.shape[0]))


def _initial_step(sys, tab, Y, F, rtol, atol, t_max):
    """scipy's initial step (Hairer's), per lane. The norms are taken without overflow
    (:func:`_rms4`), so a huge entry speed gives a correspondingly tiny first step
    instead of 0 or nan."""
    ne = sys.ne
    scale = atol + np.abs(Y[:ne]) * rtol

    def rms(a):
        sq = a * a
        r = np.sqrt(_rowsum(sq) / float(ne))
        bad = ~np.isfinite(r) & np.isfinite(a).all(axis=0)
        return np.where(bad, _rms4(a), r) if bad.any() else r

    d0 = rms(Y[:ne] / scale)
    d1 = rms(F[:ne] / scale)
    h0 = np.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1)
    Y1 = Y + h0 * F
    F1 = sys(Y1)[0]
    d2 = rms((F1[:ne] - F[:ne]) / scale) / h0
    dm = np.maximum(d1, d2)
    h1 = np.where(dm <= 1e-15, np.maximum(1e-6, h0 * 1e-3), (0.01 / dm) ** (1.0 / (tab.order + 1)))
    h = np.minimum(np.minimum(100 * h0, h1), t_max)
    # a non-finite or zero first step (derivatives that overflow): the step control
    # shrinks it from the smaller sane estimate
    return np.where(np.isfinite(h) & (h > 0), h, np.where(np.isfinite(h0) & (h0 > 0), h0, 1e-6))
