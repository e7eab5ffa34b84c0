"""The lab stage's fitting machinery: bounded least-squares fits of the model to tracks: the integration of lanes of the
spec's model on the compiled engine (:func:`model_solve`), the budget the fits of one
track share, and a bounded Levenberg-Marquardt driver (:func:`least_squares_bounded`).

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


def least_squares_bounded(fun, jac, p0, budget, lower=None, xtol: float = 1e-10, ftol: float = 1e-10,
                          max_nfev: int = 100):
    """Bounded Levenberg-Marquardt (Marquardt's scaled damping, the bound by an active
    set): minimise |fun(p)|^2 with p >= ``lower`` (-inf where None), at most ``max_nfev``
    residual evaluations, each residual and Jacobian counted on ``budget``.

    Each iteration solves (J^T J + lam diag(J^T J)) dp = -J^T r over the free
    parameters (a parameter on its bound whose gradient pushes it further is held
    there), in Jacobi-scaled form (columns of unit norm); a step that lowers the
    cost is taken (lam / 3), one that does not raises lam 4x. Converged: a trial step
    changes the cost by less than ``ftol`` of it (either way: rounding), or a taken
    step's scaled size is below ``xtol`` times the scaled parameters, or the projected
    gradient vanishes (its largest cosine with the
    residual below 1e-12). Linear algebra on n x n matrices only (J^T J): the cost of
    an iteration is one product J^T J, whatever the number of residuals.

    Returns (x, residuals, jacobian or None, nfev, status): status "converged",
    "evaluations" (max_nfev reached), or the reason a :class:`FitStopped` ended it
    (then x is the best point evaluated, no jacobian). Only "converged" is a fit.
    Raises FitStopped if not even the first point could be evaluated."""
    x = np.asarray(p0, dtype=float).copy()
    n = x.size
    lo = np.full(n, -np.inf) if lower is None else np.asarray(lower, dtype=float)
    low = np.isfinite(lo) & (x <= lo)
    x[low] = lo[low] + 1e-6 * np.maximum(1.0, np.abs(lo[low]))     # start strictly inside
    state = {"nfev": 0}

    def f(p):
        if budget is not None:
            budget.count_run()
        r = np.asarray(fun(p), dtype=float)
        state["nfev"] += 1
        if not np.all(np.isfinite(r)):
            raise FitStopped("the model left the surface's finite values")
        return r

    def J_of(p):
        if budget is not None:
            budget.count_run()
        out = np.asarray(jac(p), dtype=float)
        if not np.all(np.isfinite(out)):
            raise FitStopped("the model left the surface's finite values")
        return out

    r = f(x)                        # raises: not even the first point
    cost = float(r @ r)
    J = None
    lam = 1e-3
    status = "evaluations"
    try:
        J = J_of(x)
        while state["nfev"] < max_nfev:
            g = J.T @ r
            A = J.T @ J
            free = ~(np.isfinite(lo) & (x <= lo) & (g > 0))
            d = np.sqrt(np.maximum(np.diag(A), 0.0))
            d[d == 0] = 1.0
            As = A / np.outer(d, d)
            gs = g / d
            # the projected gradient's largest cosine with the residual (MINPACK's gtol)
            if cost == 0 or np.max(np.abs(gs[free])) <= 1e-12 * math.sqrt(cost):
                status = "converged"
                break
            fi = np.flatnonzero(free)
            M = As[np.ix_(fi, fi)] + lam * np.eye(fi.size)
            try:
                step_s = np.linalg.solve(M, -gs[fi])
            except np.linalg.LinAlgError:
                lam *= 4.0
                continue
            dp = np.zeros(n)
            dp[fi] = step_s / d[fi]
            x_new = np.maximum(x + dp, lo)
            try:
                r_new = f(x_new)
            except FitStopped as exc:
                if "budget" in exc.reason:
                    raise
                lam *= 4.0          # a trial the model cannot follow: a shorter step
                continue
            cost_new = float(r_new @ r_new)
            if abs(cost - cost_new) <= ftol * cost:
                # the cost no longer changes beyond ftol (rounding): a minimum
                if cost_new < cost:
                    x, r, cost = x_new, r_new, cost_new
                    J = J_of(x)
                status = "converged"
                break
            if cost_new < cost:
                small = np.linalg.norm((x_new - x) * d) <= xtol * (xtol + np.linalg.norm(x * d))
                x, r, cost = x_new, r_new, cost_new
                J = J_of(x)
                lam = max(lam / 3.0, 1e-12)
                if small:
                    status = "converged"
                    break
            else:
                lam *= 4.0
                if lam > 1e16:      # no step lowers the cost: a minimum to rounding
                    status = "converged"
                    break
    except FitStopped as exc:
        if budget is not None:
            budget.stopped.append(exc.reason)
        return x, r, None, state["nfev"], exc.reason
    if status != "converged" and budget is not None:
        budget.stopped.append(f"the fit stopped after {state['nfev']} evaluations without converging")
    return x, r, J, state["nfev"], status


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
