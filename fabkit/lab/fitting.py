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
def _count(calls: list, budget) -> None:
    """One evaluation of a fit's right-hand side: FitStopped past MAX_RHS_CALLS in one
    integration, and the fit's budget checked every 64 evaluations."""
    calls[0] += 1
    if calls[0] > MAX_RHS_CALLS:
        raise FitStopped(f"an integration of the model took more than {MAX_RHS_CALLS} evaluations "
                         "(a stiff trial: the fit wandered far from the track)")
    if budget is not None and calls[0] % 64 == 0:
        budget.check()


def model_solve(problem, S0: np.ndarray, mu: np.ndarray, t0: float, t_eval: np.ndarray,
                rtol: float = FIT_RTOL, dense: bool = False, budget: Budget | None = None, crr=None):
    """Integrate lanes of the spec's model from t0: S0 (4, m) states (the ball: (5, m), see
    :func:`_ball_solve`), mu (m,) viscous damping,
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
    if problem.model == "ball":
        return _ball_solve(problem, S0, mu, crr, t0, t_eval, rtol, dense, budget)
    rolling = bool(np.any(crr != 0))
    p1 = problem.with_(rolling_resistance=1.0)
    fn = fused(problem.with_(damping=0.0, rolling_resistance=0.0))   # the model's generated right-hand side
    d = np.empty((4, m))
    calls = [0]

    def f(t, Yf):
        _count(calls, budget)
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


# ----------------------------------------------------------------------------
# the ball model: its state is the contact point's, a camera sees the centre
# ----------------------------------------------------------------------------
def state_size(problem) -> int:
    """Rows of a fitted state: 4 (x, y, xd, yd) for the point models; 5 for the ball
    (the contact point, its velocity, and u, the spin about the normal)."""
    return 5 if problem.model == "ball" else 4


def _ball_geometry(problem, x, y):
    from ..physics import ball

    return ball.geometry(ball.jet_function(problem.fns)(x, y), float(problem.radius))


def centre_of(problem, x, y, xd=None, yd=None):
    """The ball's centre C = P + r n(P) seen from above: (X, Y) of contact points (x, y),
    and with (xd, yd) also the centre's horizontal velocity (VX, VY). Exact (the
    surface's derivatives are sympy's)."""
    geo = _ball_geometry(problem, np.asarray(x, dtype=float), np.asarray(y, dtype=float))
    r = float(problem.radius)
    X, Y = x + r * geo["n"][0], y + r * geo["n"][1]
    if xd is None:
        return X, Y
    Cx, Cy = geo["Cx"], geo["Cy"]
    return X, Y, Cx[0] * xd + Cy[0] * yd, Cx[1] * xd + Cy[1] * yd


#: Newton on the contact point of a seen centre: stop when a step is below this
#: fraction of the ball's radius (quadratic convergence: 3-5 steps)
CONTACT_NEWTON_TOL = 1e-13
CONTACT_NEWTON_ITERS = 50


def contact_of(problem, X, Y, VX=None, VY=None):
    """The contact point P whose centre P + r n(P) has the horizontal position (X, Y):
    C_xy(P) = (X, Y) solved by Newton on P, the Jacobian d C_xy / d P the horizontal
    rows of the offset surface's tangents C_x, C_y (regular until the ball bridges).
    With the centre's horizontal velocity (VX, VY) also the contact point's (xd, yd)
    (``ball.contact_velocity``). Raises ValueError if Newton does not converge."""
    from ..physics import ball

    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    r = float(problem.radius)
    x, y = X.copy(), Y.copy()
    for _ in range(CONTACT_NEWTON_ITERS):
        geo = _ball_geometry(problem, x, y)
        fx = x + r * geo["n"][0] - X
        fy = y + r * geo["n"][1] - Y
        a, b, c, d = geo["Cx"][0], geo["Cy"][0], geo["Cx"][1], geo["Cy"][1]
        det = a * d - b * c
        dx = (d * fx - b * fy) / det
        dy = (a * fy - c * fx) / det
        x, y = x - dx, y - dy
        step = float(np.max(np.abs(np.concatenate([np.ravel(dx), np.ravel(dy)]))))
        if not math.isfinite(step):
            break
        if step <= CONTACT_NEWTON_TOL * max(r, 1.0):
            if VX is None:
                return x, y
            geo = _ball_geometry(problem, x, y)
            xd, yd = ball.contact_velocity(geo, np.asarray(VX, dtype=float), np.asarray(VY, dtype=float))
            return x, y, xd, yd
    raise ValueError("no contact point under this centre (off the surface, or where the ball bridges)")


def _ball_solve(problem, S0, mu, crr, t0, t_eval, rtol, dense, budget):
    """:func:`model_solve` of the ball (fabkit.physics.ball.evaluate, each lane with its
    own mu and c_rr): S0 (5, m) = the contact point (x, y), its velocity (xd, yd) and the
    spin u; returns Y (4, m, len(t_eval)) of what a camera sees, the centre's (X, Y, VX,
    VY) (:func:`centre_of`), and the solution of the contact state (``sol``)."""
    from scipy.integrate import solve_ivp

    from ..physics import ball

    m = S0.shape[1]
    P = ball.Params.of(problem)
    P.mu, P.c_rr = mu, crr
    jet = ball.jet_function(problem.fns)
    calls = [0]

    def f(t, Yf):
        _count(calls, budget)
        S = Yf.reshape(5, m)
        ev = ball.evaluate(jet(S[0], S[1]), S[2], S[3], S[4], P, contact=False)
        return np.concatenate([S[2], S[3], ev["xdd"], ev["ydd"], ev["ud"]])

    scale = max(1.0, float(np.max(np.abs(S0[:4]))))
    with np.errstate(all="ignore"):
        sol = solve_ivp(f, (t0, float(t_eval[-1])), np.asarray(S0, dtype=float).ravel(), method="DOP853",
                        rtol=rtol, atol=rtol * scale, t_eval=t_eval, dense_output=dense)
    if sol.status != 0 or sol.y.shape[1] != len(t_eval) or not np.all(np.isfinite(sol.y)):
        raise FitStopped(f"the model cannot follow this track ({sol.message})")
    S = sol.y.reshape(5, m, len(t_eval))
    with np.errstate(all="ignore"):
        out = np.stack(centre_of(problem, S[0], S[1], S[2], S[3]))
    if not np.all(np.isfinite(out)):
        raise FitStopped("the model left the surface's finite values")
    return out, sol
