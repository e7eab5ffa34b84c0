"""Bounded least-squares fits of the model to tracks: the integration of lanes of the
spec's model (:func:`model_solve`), the budget the fits of one track share, and a
Levenberg-Marquardt driver that keeps its best point when the budget runs out.

Budgets, stated up front: the fits of one track stop after TRACK_BUDGET_S s of wall
time or MAX_MODEL_RUNS model runs (each residual or Jacobian is one run), one
integration after MAX_RHS_CALLS evaluations of the model (a stiff or runaway trial: a
damping of 1e6 1/s, a state far off the surface). What ran out is reported by the
caller (:mod:`fabkit.lab.analyze`: the track's ``fit_status`` and its notes).
"""

from __future__ import annotations

import math
import time

import numpy as np

FIT_RTOL = 1e-8
#: budgets of the iterative work, stated up front: the fits of one track stop after
#: TRACK_BUDGET_S s of wall time, one integration after MAX_RHS_CALLS evaluations of the
#: model (a stiff or runaway trial: a damping of 1e6 1/s, a state far off the surface);
#: what ran out is reported in the track's ``fit_status`` and its notes
TRACK_BUDGET_S = 60.0
MAX_RHS_CALLS = 200_000
MAX_MODEL_RUNS = 500  # model runs (residuals and jacobians) of all the fits of one track


class FitStopped(Exception):
    """An integration or a fit ran out of its budget, or the model could not follow a
    trial state (``reason``, one line). Caught by the fits: they keep their best point."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class Budget:
    """The budget shared by the fits of one track: TRACK_BUDGET_S s of wall time and
    MAX_MODEL_RUNS runs of the model (each residual or jacobian of a fit is one run)."""

    def __init__(self, seconds: float | None = None, runs: int | None = None):
        self.seconds = float(TRACK_BUDGET_S if seconds is None else seconds)
        self.runs_max = int(MAX_MODEL_RUNS if runs is None else runs)
        self.deadline = time.perf_counter() + self.seconds
        self.runs = 0
        self.stopped: list[str] = []

    def check(self) -> None:
        if time.perf_counter() > self.deadline:
            raise FitStopped(f"the fits' time budget ({self.seconds:g} s a track) ran out")

    def count_run(self) -> None:
        self.check()
        self.runs += 1
        if self.runs > self.runs_max:
            raise FitStopped(f"the fits' budget of {self.runs_max} model runs a track ran out")

    @property
    def left(self) -> float:
        return self.deadline - time.perf_counter()


def least_squares_bounded(fun, jac, p0, budget, **kw):
    """scipy's least_squares (Levenberg-Marquardt), bounded: ``max_nfev`` evaluations
    (in ``kw``) and the track's ``budget``. Returns (x, residuals, jacobian or None,
    nfev, status): status "converged", "evaluations" (max_nfev reached), or the reason
    a :class:`FitStopped` ended it (then x is the best point evaluated, no jacobian).
    Raises FitStopped if not even the first point could be evaluated."""
    from scipy.optimize import least_squares

    best = {"cost": math.inf, "x": None, "r": None, "n": 0}

    def f(p):
        if budget is not None:
            budget.count_run()
        r = fun(p)
        best["n"] += 1
        c = float(r @ r)
        if not math.isfinite(c):
            raise FitStopped("the model left the surface's finite values")
        if c < best["cost"]:
            best.update(cost=c, x=np.array(p, dtype=float), r=np.array(r))
        return r

    def J(p):
        if budget is not None:
            budget.count_run()
        out = jac(p)
        if not np.all(np.isfinite(out)):
            raise FitStopped("the model left the surface's finite values")
        return out

    try:
        res = least_squares(f, p0, jac=J, method="lm", **kw)
    except FitStopped as exc:
        if best["x"] is None:
            raise
        if budget is not None:
            budget.stopped.append(exc.reason)
        return best["x"], best["r"], None, best["n"], exc.reason
    status = "converged" if res.status > 0 else "evaluations"
    if status != "converged" and budget is not None:
        budget.stopped.append(f"the fit stopped after {res.nfev} evaluations without converging")
    return res.x, res.fun, res.jac, res.nfev, status


def covariance_errors(jac, r, n_par):
    """One-sigma errors of least-squares parameters: sqrt(diag((J^T J)^-1 s^2)),
    s^2 = |r|^2 / (N - n_par); nan where J is missing or singular."""
    if jac is None:
        return np.full(n_par, np.nan)
    s2 = float(r @ r) / max(1, r.size - n_par)
    try:
        with np.errstate(all="ignore"):
            cov = np.linalg.inv(jac.T @ jac) * s2
        return np.sqrt(np.maximum(np.diag(cov), 0.0))
    except np.linalg.LinAlgError:
        return np.full(n_par, np.nan)


# ----------------------------------------------------------------------------
# model integration (for the fits): the spec's right-hand side, damping per lane
# ----------------------------------------------------------------------------
def model_solve(problem, S0: np.ndarray, mu: np.ndarray, t0: float, t_eval: np.ndarray,
                rtol: float = FIT_RTOL, dense: bool = False, budget: Budget | None = None, crr=None):
    """Integrate lanes of the spec's model from t0: S0 (4, m) states, mu (m,) viscous damping,
    ``crr`` (m,) rolling resistance (None: the spec's; models.py's module doc, the same
    terms as :func:`fabkit.physics.models.rolling_coefficient`).

    The conservative part (and any nonlinear damping) is ``models.rhs`` of the problem
    with its viscous damping set to 0; -mu v is added per lane, exactly as the model
    adds it. Returns (Y (4, m, len(t_eval)), sol). Raises :class:`FitStopped` after
    MAX_RHS_CALLS evaluations, when ``budget`` runs out, or when the integration fails."""
    from scipy.integrate import solve_ivp

    from ..physics.models import fused

    from ..physics.models import rolling_coefficient

    m = S0.shape[1]
    mu = np.asarray(mu, dtype=float).reshape(m)
    crr = np.full(m, float(problem.rolling_resistance)) if crr is None else \
        np.asarray(crr, dtype=float).reshape(m)
    rolling = bool(np.any(crr != 0))
    p1 = problem.with_(rolling_resistance=1.0)
    fn = fused(problem.with_(damping=0.0, rolling_resistance=0.0))   # the model's generated right-hand side
    d = np.empty((4, m))
    calls = [0]

    def f(t, Yf):
        calls[0] += 1
        if calls[0] > MAX_RHS_CALLS:
            raise FitStopped(f"an integration of the model took more than {MAX_RHS_CALLS} evaluations "
                             "(a stiff trial: the fit wandered far from the track)")
        if budget is not None and calls[0] % 64 == 0:
            budget.check()
        S = Yf.reshape(4, m)
        ax, ay, _, hx, hy, B, _ = fn(S[0], S[1], S[2], S[3])
        d[0], d[1] = S[2], S[3]
        c = -mu
        if rolling:
            c = c + crr * rolling_coefficient(p1, S[2], S[3], hx, hy, B)
        d[2] = ax + c * S[2]
        d[3] = ay + c * S[3]
        return d.ravel().copy()

    scale = max(1.0, float(np.max(np.abs(S0))))
    with np.errstate(all="ignore"):
        sol = solve_ivp(f, (t0, float(t_eval[-1])), S0.ravel(), method="DOP853", rtol=rtol,
                        atol=rtol * scale, t_eval=t_eval, dense_output=dense)
    if sol.status != 0 or sol.y.shape[1] != len(t_eval) or not np.all(np.isfinite(sol.y)):
        raise FitStopped(f"the model cannot follow this track ({sol.message})")
    return sol.y.reshape(4, m, len(t_eval)), sol
