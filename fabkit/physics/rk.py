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
    dissipated energy, when damped), with aux (h, h_x, h_y, B) from the same evaluation."""

    def __init__(self, problem):
        from .models import fused

        self.p = problem
        self.full = problem.model == "full"
        self.gt = problem.g_tilde
        self.damped = float(problem.damping) > 0 or float(problem.nonlinear_damping) > 0
        self.nv = 5 if self.damped else 4
        self.f = fused(problem)

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
        sys(Ys, out=K[s])
    Ynew = np.empty_like(Y)
    _combine(Y, h, K, tab.B, Ynew)
    return Ynew


def _error_norm(tab, K, h, scale):
    """scipy's error norm per lane (m,), over the 4 state components."""
    def est(coeffs):
        n = coeffs[-1][0] + 1
        acc = _add_reduce(np.multiply(K[:n, :4], _dense(coeffs, n)), axis=0)
        acc /= scale
        acc *= acc
        return acc[0] + acc[1] + acc[2] + acc[3]

    if tab.E3:  # DOP853: the 5th and 3rd order estimates combined (Hairer's DOP853)
        e5 = est(tab.E)
        e3 = est(tab.E3)
        denom = e5 + 0.01 * e3
        err = np.abs(h) * e5 / np.sqrt(denom * 4.0)
        return np.where(denom > 0, err, 0.0)
    e = est(tab.E)
    return np.abs(h) * np.sqrt(e / 4.0)


def _error_norm_scaled(tab, K, h, scale):
    """:func:`_error_norm` without overflow: each estimate is divided by its largest
    component (a power of two, so exactly) before squaring. Used only for lanes where
    the plain norm overflows (speeds beyond ~1e100 design units/s), so ordinary lanes
    keep the plain arithmetic bit for bit."""
    def est(coeffs):
        n = coeffs[-1][0] + 1
        acc = _add_reduce(np.multiply(K[:n, :4], _dense(coeffs, n)), axis=0)
        acc /= scale
        big = _pow2(np.max(np.abs(acc), axis=0))
        acc /= big
        acc *= acc
        return acc[0] + acc[1] + acc[2] + acc[3], big

    if tab.E3:
        e5, b5 = est(tab.E)
        e3, b3 = est(tab.E3)
        # err = |h| e5 b5^2 / sqrt(4 (e5 b5^2 + 0.01 e3 b3^2)), with M = max(b5, b3) factored out
        M = np.maximum(b5, b3)
        r5, r3 = b5 / M, b3 / M
        denom = e5 * r5 * r5 + 0.01 * e3 * r3 * r3
        err = np.abs(h) * M * (e5 * r5 * r5) / np.sqrt(denom * 4.0)
        return np.where(denom > 0, err, 0.0)
    e, b = est(tab.E)
    return np.abs(h) * b * np.sqrt(e / 4.0)


def _pow2(a):
    """The power of two at or above |a| (1 where a is 0 or not finite)."""
    ok = np.isfinite(a) & (a > 0)
    return np.where(ok, np.exp2(np.ceil(np.log2(np.where(ok, a, 1.0)))), 1.0)


def _rms4(a):
    """sqrt(mean of squares) over the 4 state components (m,), without overflow."""
    big = _pow2(np.max(np.abs(a[:4]), axis=0))
    b = a[:4] / big
    b = b * b
    return big * np.sqrt((b[0] + b[1] + b[2] + b[3]) / 4.0)


def _initial_step(sys, tab, Y, F, rtol, atol, t_max):
    """scipy's initial step (Hairer's), per lane. The norms are taken without overflow
    (:func:`_rms4`), so a huge entry speed gives a correspondingly tiny first step
    instead of 0 or nan."""
    scale = atol + np.abs(Y[:4]) * rtol

    def rms(a):
        sq = a * a
        r = np.sqrt((sq[0] + sq[1] + sq[2] + sq[3]) / 4.0)
        bad = ~np.isfinite(r) & np.isfinite(a).all(axis=0)
        return np.where(bad, _rms4(a), r) if bad.any() else r

    d0 = rms(Y[:4] / scale)
    d1 = rms(F[:4] / scale)
    h0 = np.where((d0 < 1e-5) | (d1 < 1e-5), 1e-6, 0.01 * d0 / d1)
    Y1 = Y + h0 * F
    F1 = sys(Y1)[0]
    d2 = rms((F1[:4] - F[:4]) / scale) / h0
    dm = np.maximum(d1, d2)
    h1 = np.where(dm <= 1e-15, np.maximum(1e-6, h0 * 1e-3), (0.01 / dm) ** (1.0 / (tab.order + 1)))
    h = np.minimum(np.minimum(100 * h0, h1), t_max)
    # a non-finite or zero first step (derivatives that overflow): the step control
    # shrinks it from the smaller sane estimate
    return np.where(np.isfinite(h) & (h > 0), h, np.where(np.isfinite(h0) & (h0 > 0), h0, 1e-6))
