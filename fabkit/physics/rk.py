"""The explicit Runge-Kutta pairs of the launch engine, as data.

Butcher tableaux (scipy's Dormand-Prince 8(5,3) ``DOP853`` and 5(4) ``RK45``
coefficients, as in ``scipy.integrate._ivp.rk``); the compiled engine
(``engine/dop853.py``) takes them as arrays (``engine.batch.tableau_arrays``) with
scipy's error norm, step-size controller and initial step.
"""

from __future__ import annotations

from dataclasses import dataclass


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
