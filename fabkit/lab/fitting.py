"""Bounded least-squares fits of the model to tracks: the integration of lanes of the
spec's model on the compiled engine (:func:`model_solve`), the budget the fits of one
track share, and a bounded trust-region driver that keeps its best point when the
budget runs out.

Budgets count work, never seconds, so the same tracks give the same fit on any
machine at any load: the fits of one track stop after MAX_MODEL_RUNS model runs (each
residual or Jacobian is one run), one integration after MAX_STEPS steps (a stiff or
runaway trial: a damping of 1e6 1/s, a state far off the surface). What ran out is
reported by the caller (the track's ``fit_status`` and its notes); a fit that did not
converge is reported as not fitted (:func:`least_squares_bounded`'s status).

Integration: :func:`fabkit.physics.engine.fit.frames` (DOP853 with scipy's step control,
rtol FIT_RTOL; every lane of one call takes the same steps, each step ends on the next
frame time). Jacobians: central differences between lanes of one call (the lanes share
their steps, so a difference is the derivative of one discrete map: no step-control
noise), steps STATE_STEP max(1, |p|) for a start value and COEF_STEP max(|q|, floor) for
a loss coefficient (floors COEF_FLOOR); their truncation error is O(step^2), about 1e-9
of the derivative's scale, and their rounding error about 1e-16 |x| / step.
"""

from __future__ import annotations

import math

import numpy as np

FIT_RTOL = 1e-8
#: budgets of the iterative work, stated up front: model runs (residuals and Jacobians)
#: of all the fits of one track; steps of one integration
MAX_MODEL_RUNS = 2000
MAX_STEPS = 200_000
#: central-difference steps of the Jacobians (module doc)
STATE_STEP = 1e-5
COEF_STEP = 1e-3
COEF_FLOOR = {"damping": 1e-2, "rolling_resistance": 1e-4}


class FitStopped(Exception):
    """An integration or a fit ran out of its budget, or the model could not follow a
    trial state (``reason``, one line). Caught by the fits: they keep their best point."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class Budget:
    """The budget shared by the fits of one track: MAX_MODEL_RUNS runs of the model (each
    residual or Jacobian of a fit is one run). No clock: the same work on any machine."""

    def __init__(self, runs: int | None = None):
        self.runs_max = int(MAX_MODEL_RUNS if runs is None else runs)
        self.runs = 0
        self.stopped: list[str] = []

    def count_run(self) -> None:
        self.runs += 1
        if self.runs > self.runs_max:
            raise FitStopped(f"the fits' budget of {self.runs_max} model runs a track ran out")


def least_squares_bounded(fun, jac, p0, budget, lower=None, **kw):
    """scipy's least_squares (trust region reflective, bounded below by ``lower``, -inf
    where None): ``max_nfev`` evaluations (in ``kw``) and the track's ``budget``.
    Returns (x, residuals, jacobian or None, nfev, status): status "converged",
    "evaluations" (max_nfev reached), or the reason a :class:`FitStopped` ended it
    (then x is the best point evaluated, no jacobian). Only "converged" is a fit.
    Raises FitStopped if not even the first point could be evaluated."""
    from scipy.optimize import least_squares

    best = {"cost": math.inf, "x": None, "r": None, "n": 0}
    p0 = np.asarray(p0, dtype=float)
    lo = np.full(p0.size, -np.inf) if lower is None else np.asarray(lower, dtype=float)
    # a start on a bound moves just inside it (the method needs a strictly feasible start)
    low = np.isfinite(lo) & (p0 <= lo)
    p0 = p0.copy()
    p0[low] = lo[low] + 1e-6 * np.maximum(1.0, np.abs(lo[low]))

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
        res = least_squares(f, p0, jac=J, method="trf", bounds=(lo, np.full(p0.size, np.inf)),
                            x_scale="jac", **kw)
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


def central_jacobian(run, p, steps) -> np.ndarray:
    """d r / d p by central differences, all 2 len(p) perturbed lanes in ONE run (they
    share their steps): ``run(P)`` (lanes, N) for parameter rows P (lanes, len(p))."""
    n = p.size
    P = np.vstack([p + np.eye(n)[j] * steps[j] for j in range(n)] + [p - np.eye(n)[j] * steps[j] for j in range(n)])
    Y = run(P)
    return ((Y[:n] - Y[n:]) / (2.0 * np.asarray(steps))[:, None]).T


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
# model integration (for the fits): lanes on the compiled engine
# ----------------------------------------------------------------------------
def model_solve(problem, S0: np.ndarray, mu: np.ndarray, t0: float, t_eval: np.ndarray,
                rtol: float = FIT_RTOL, budget: Budget | None = None, crr=None, derivatives: bool = False):
    """Integrate lanes of the spec's model from t0 to the times ``t_eval`` (monotonic,
    forward or backward) on the compiled engine: S0 (4, m) states (x, y, xd, yd; the
    ball's (5, m): the contact point, its velocity and the spin u), mu (m,) viscous
    damping, ``crr`` (m,) rolling resistance (None: the spec's); the spec's nonlinear
    damping as the model has it. Returns Y (4, m, len(t_eval)): what a camera sees,
    (x, y, xd, yd) of a point, the centre's (X, Y, VX, VY) of the ball
    (:func:`centre_of`); with ``derivatives`` also (state, d state / dt) of the model
    (m, len(t_eval), NV). Raises :class:`FitStopped` after MAX_STEPS steps or where
    the model leaves the surface's finite values. ``budget`` is counted by the
    fits (a run each residual or Jacobian), not here."""
    from ..physics.engine.fit import frames

    ns = state_size(problem)
    S0 = np.asarray(S0, dtype=float)
    m = S0.shape[1]
    mu = np.asarray(mu, dtype=float).reshape(m)
    crr = np.full(m, float(problem.rolling_resistance)) if crr is None else \
        np.asarray(crr, dtype=float).reshape(m)
    t_eval = np.asarray(t_eval, dtype=float)
    scale = max(1.0, float(np.max(np.abs(S0[:4]))))
    Y, dY, status, steps, _ = frames(problem, S0[:ns].T, mu, crr, float(t0), t_eval, rtol=rtol,
                                     atol=rtol * scale, max_steps=MAX_STEPS)
    if status == 1:
        raise FitStopped(f"an integration of the model took more than {MAX_STEPS} steps "
                         "(a stiff trial: the fit wandered far from the track)")
    if status != 0:
        raise FitStopped("the model cannot follow this track (it left the surface's finite values)")
    if problem.model == "ball":
        with np.errstate(all="ignore"):
            out = np.stack(centre_of(problem, Y[:, :, 0], Y[:, :, 1], Y[:, :, 2], Y[:, :, 3]))
        if not np.all(np.isfinite(out)):
            raise FitStopped("the model left the surface's finite values")
    else:
        out = np.moveaxis(Y[:, :, :4], 2, 0)
    return (out, Y, dY) if derivatives else out


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
