"""The rolling-ball models: a point particle on the surface z = h(x, y).

Two models (the paper, section "A mechanical analog"):

``full``, eq. (xyODE): the exact equations of a particle on z = h(x, y) with the
ball's rotational inertia folded into g~ = g / (1 + k) (g~ = 5/7 g for a solid
ball):

    [xdd, ydd] = - B / (1 + h_x^2 + h_y^2) [h_x, h_y],
    B = h_xx xd^2 + 2 h_xy xd yd + h_yy yd^2 + g~     (the normal-force bracket)

``simplified``, eq. (xyODE_simp): [xdd, ydd] = - g~ [h_x, h_y].

Dissipation (section "Effects of dissipation"), added to both models:

* viscous damping ``damping`` = mu (1/s) on both velocities: - mu [xd, yd];
* the paper's localized nonlinear damping (after Goodman, Holmes & Weinstein),
  coefficient ``nonlinear_damping`` = mu_nl (1/(s length^2)): the y equation gets
  ``- mu_nl F(x)^2 y^2 yd`` with F(x) = h_y(x, 0), the coefficient of the term
  linear in y of h (for the paper's surface F(x) = eps exp(d x)); it acts only
  where the coupling F is large and only on large transverse amplitude;
* rolling resistance ``ball.rolling_resistance`` = c_rr: a force c_rr N on the ball
  opposing its velocity, N the normal force. The ball's tangential equation is
  (1 + k) m a_t = m g_t + f_t (the friction carries the rest), and a tangent force f
  per unit effective mass (1 + k) m enters the horizontal accelerations as its own
  horizontal components (f = fx C_x + fy C_y with C_x = (1, 0, h_x), C_y = (0, 1, h_y):
  G^-1 (C . f) = (fx, fy)), so

      [xdd, ydd] += - c_rr / (1 + k) * max(N/m, 0) * [xd, yd] / sqrt(|v|^2 + v_s^2)

  full: N/m = (g + Q) / sqrt(1 + h_x^2 + h_y^2), Q = h_xx xd^2 + 2 h_xy xd yd + h_yy yd^2
  (the real normal force: g, not g~), |v|^2 = xd^2 + yd^2 + (h_x xd + h_y yd)^2;
  simplified: N/m = g, |v|^2 = xd^2 + yd^2. v_s = 1e-3 sqrt(g max(r, 1e-3)) smooths the
  direction at rest, as in the ball model (:mod:`fabkit.physics.ball`). On a flat floor
  the speed falls at the constant rate c_rr g~ (c_rr g / (1 + k)), as the ball's does.

State layout: ``state`` has shape (4, ...) = (x, y, xd, yd) along the first
axis; any trailing shape (a scalar launch (4,), a batch (4, N)).
Lengths in design units, times in seconds.

Energy (per unit (1 + k) m, so a length^2/s^2):
    full:       E = 1/2 (xd^2 + yd^2 + (h_x xd + h_y yd)^2) + g~ h
    simplified: E = 1/2 (xd^2 + yd^2) + g~ h
Both are conserved exactly by their model without damping.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ..errors import SpecError
from ..units import gravity

#: outcome codes and names: defined once in physics/outcomes.py
from .outcomes import (BRIDGED, CAPTURED, ESCAPED, FLEW_OFF, LOST_CONTACT, OUTCOMES, SLIPPED,  # noqa: F401
                       UNSAFE, unsafe)

MODELS = ("full", "simplified", "ball")


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything a launch needs, in design units and seconds.

    fns       compiled surface functions (``spec.surface_functions()``): ``.all(x, y)`` ->
              (h, h_x, h_y, h_xx, h_xy, h_yy), ``.accel``, ``.h``
    g, k      gravity (design units/s^2) and k = I/(m r^2); ``g_tilde`` = g / (1 + k)
    model     'full' (eq. xyODE) | 'simplified' (eq. xyODE_simp)
    damping   viscous coefficient mu, 1/s;  nonlinear_damping: mu_nl (see module doc)
    start     launch x; y0, vy0: transverse launch offset and speed
    x_range, y_range   the footprint; top: the stock's top face; margin: the safety margin
    t_max     time limit, s; rtol, atol: default integrator tolerances
    stop_trapped   end a launch as ``captured`` as soon as its energy is below the
              trapping energy (:mod:`fabkit.physics.trap`) instead of at ``t_max``;
              escaped, flew_off and lost_contact results are unchanged
    radius    the ball's radius r (design units; the ``ball`` model only)
    friction  static friction coefficient (``ball`` model; inf: never slips)
    rolling_resistance   coefficient c_rr of the rolling resistance c_rr N (every model; see the module doc)
    """

    fns: Any
    g: float
    k: float
    model: str = "full"
    damping: float = 0.0
    nonlinear_damping: float = 0.0
    start: float = 0.0
    x_range: tuple = (-np.inf, np.inf)
    y_range: tuple = (-np.inf, np.inf)
    top: float = np.inf
    margin: float = 0.0
    t_max: float = 60.0
    y0: float = 0.0
    vy0: float = 0.0
    rtol: float = 1e-10
    atol: float = 1e-12
    units: str = "mm"
    stop_trapped: bool = False
    radius: float = 0.0
    friction: float = np.inf
    rolling_resistance: float = 0.0

    @property
    def g_tilde(self) -> float:
        return self.g / (1.0 + self.k)

    @property
    def surface(self):
        return self.fns

    def with_(self, **changes) -> "Problem":
        """A copy with fields replaced."""
        return replace(self, **changes)


def problem_from_spec(spec, **overrides) -> Problem:
    """The :class:`Problem` of a spec (sections surface, ball, simulation needed).

    ``overrides``: Problem fields to replace (``model='simplified'``, ``damping=0`` ...).
    """
    spec.require("surface", "simulation", command=None)
    sim, sur = spec.simulation, spec.surface
    k = float(spec.ball.inertia) if spec.has("ball") else 0.4
    ball = spec.ball if spec.has("ball") else None
    fr = getattr(ball, "friction", None) if ball is not None else None
    fields = dict(
        fns=spec.surface_functions(), g=gravity(spec.units), k=k, model=sim.model,
        damping=float(sim.damping), nonlinear_damping=float(sim.nonlinear_damping),
        start=float(sim.start), x_range=(float(sur.x[0]), float(sur.x[1])),
        y_range=(float(sur.y[0]), float(sur.y[1])), top=float(sur.top), margin=float(sim.margin),
        t_max=float(sim.t_max), y0=float(sim.y0), vy0=float(sim.vy0), rtol=float(sim.rtol),
        atol=float(sim.atol), units=spec.units,
        radius=0.5 * float(ball.diameter) if ball is not None else 0.0,
        friction=np.inf if fr is None else float(fr),
        rolling_resistance=float(getattr(ball, "rolling_resistance", 0.0) or 0.0) if ball is not None else 0.0,
    )
    unknown = set(overrides) - set(fields)
    if unknown:
        raise TypeError(f"unknown Problem fields: {sorted(unknown)}")
    fields.update(overrides)
    if fields["model"] not in MODELS:
        raise SpecError(f"must be one of {' | '.join(MODELS)}, got {fields['model']!r}",
                        file=spec.path, key="simulation.model")
    if fields["model"] == "ball" and fields["nonlinear_damping"]:
        raise SpecError("the paper's localized damping is a term of the point models; model ball takes "
                        "simulation.damping and ball.rolling_resistance", file=spec.path,
                        key="simulation.nonlinear_damping")
    if fields["model"] == "ball" and ball is None:
        raise SpecError("model ball needs the ball section (its diameter and inertia)",
                        file=spec.path, key="simulation.model")
    if fields["model"] == "ball":
        # the ball's rolling needs h's third derivatives: refuse a formula whose third
        # derivatives would explode before any is built (expr.derivative_size)
        from ..expr import check_derivative_size

        try:
            check_derivative_size(fields["fns"], 3)   # the estimate kept with the formula: no sympy
        except SpecError as exc:
            raise exc.with_location(file=spec.path) from None
    return Problem(**fields)


_FUSED: dict = {}


def fused(problem: Problem):
    """The model's right-hand side as one generated function (cached).

    ``f(x, y, xd, yd) -> (xdd, ydd, h, h_x, h_y, B, P)`` on arrays of one shape:
    the accelerations of eq. (xyODE) or eq. (xyODE_simp) with the damping terms,
    the height, its gradient, the normal-force bracket B, and P, the power
    dissipated by damping (:func:`dissipated_power`; 0 undamped). Generated by sympy
    from the exact symbolic h with common subexpressions shared (each exp of the
    surface is evaluated once), so one call costs a few dozen array operations.
    Outputs that do not depend on the state come back as arrays of the input's shape.
    """
    if problem.model not in ("full", "simplified"):
        raise ValueError(f"fused() is the point models' right-hand side; model {problem.model!r} has its own "
                         "(physics/ball.py)")
    crr = float(problem.rolling_resistance)
    key = (problem.fns, problem.model, problem.g_tilde, float(problem.damping),
           float(problem.nonlinear_damping), crr / (1.0 + problem.k) if crr else 0.0,
           rolling_smoothing_speed(problem) if crr else 0.0, float(problem.g) if crr else 0.0)
    fn = _FUSED.get(key)
    if fn is None:
        fn = _build_fused(*key)
        if len(_FUSED) > 64:
            _FUSED.clear()
        _FUSED[key] = fn
    return fn


def rolling_smoothing_speed(problem: Problem) -> float:
    """v_s of the rolling resistance's direction v / sqrt(|v|^2 + v_s^2), design units/s:
    1e-3 sqrt(g max(r, 1e-3)), the ball model's (:class:`fabkit.physics.ball.Params`)."""
    return 1e-3 * float(np.sqrt(problem.g * max(problem.radius, 1e-3)))


def _build_fused(fns, model, gt, mu, mu_nl, crr_k=0.0, vs=0.0, g=0.0):
    import sympy as sp

    from ..expr import cse_unevaluated   # sympy's cse re-evaluates: exponential on nested functions

    h = fns.symbolic
    syms = sorted(h.free_symbols, key=lambda s: s.name)
    x = next((s for s in syms if s.name == "x"), sp.Symbol("x", real=True))
    y = next((s for s in syms if s.name == "y"), sp.Symbol("y", real=True))
    vx, vy = sp.symbols("vx vy", real=True)
    hx, hy = sp.diff(h, x), sp.diff(h, y)
    hxx, hxy, hyy = sp.diff(hx, x), sp.diff(hx, y), sp.diff(hy, y)
    parts = [e.replace(sp.DiracDelta, lambda *a: sp.Integer(0)) for e in (h, hx, hy, hxx, hxy, hyy)]
    h, hx, hy, hxx, hxy, hyy = parts
    gts = sp.Float(gt, 17)
    B = hxx * vx**2 + 2 * hxy * vx * vy + hyy * vy**2 + gts
    q = B / (1 + hx**2 + hy**2) if model == "full" else gts   # eq. (xyODE) | eq. (xyODE_simp)
    dx = -sp.Float(mu, 17) * vx
    dy = -sp.Float(mu, 17) * vy
    if mu_nl:
        F = hy.subs(y, 0)
        dy = dy - sp.Float(mu_nl, 17) * F**2 * y**2 * vy
    if crr_k:   # rolling resistance (module doc); crr_k = c_rr / (1 + k)
        if model == "full":
            Nm = (sp.Float(g, 17) + B - gts) / sp.sqrt(1 + hx**2 + hy**2)
            v2 = vx**2 + vy**2 + (hx * vx + hy * vy) ** 2
        else:
            Nm = sp.Float(g, 17)
            v2 = vx**2 + vy**2
        c = -sp.Float(crr_k, 17) * (Nm + sp.Abs(Nm)) / 2 / sp.sqrt(v2 + sp.Float(vs * vs, 17))
        dx = dx + c * vx
        dy = dy + c * vy
    ax = -q * hx + dx
    ay = -q * hy + dy
    if model == "full":
        zd = hx * vx + hy * vy
        P = -(dx * (vx + zd * hx) + dy * (vy + zd * hy))
    else:
        P = -(dx * vx + dy * vy)
    outs = [ax, ay, h, hx, hy, B, P]
    if P == 0:  # undamped: leave P out of the generated code (the caller gets 0.0)
        f0 = sp.lambdify((x, y, vx, vy), outs[:6], modules="numpy", cse=cse_unevaluated)
        outs = outs[:6]

        def f(xa, ya, vxa, vya, _f=f0):
            return (*_f(xa, ya, vxa, vya), 0.0)
    else:
        f = sp.lambdify((x, y, vx, vy), outs, modules="numpy", cse=cse_unevaluated)
    const = [i for i, e in enumerate(outs) if not (e.free_symbols & {x, y, vx, vy})]

    if not const:
        return f

    def wrapped(xa, ya, vxa, vya, _f=f, _const=tuple(const)):
        out = list(_f(xa, ya, vxa, vya))
        shape = np.shape(xa)
        for i in _const:
            out[i] = np.full(shape, float(out[i]))
        return out

    return wrapped


def _unpack(args):
    if len(args) == 1:
        s = np.asarray(args[0], dtype=float)
        return s[0], s[1], s[2], s[3]
    if len(args) == 4:
        return tuple(np.asarray(a, dtype=float) for a in args)
    raise TypeError("pass a state (4, ...) or x, y, xd, yd")


def accelerations(problem: Problem, x, y, vx, vy):
    """(xdd, ydd, parts) at the given positions and velocities (arrays of one shape).

    ``parts`` = (h, h_x, h_y, B) with B the normal-force bracket of eq. (xyODE)
    (for the simplified model B is still reported, computed the same way).
    """
    h, hx, hy, hxx, hxy, hyy = problem.fns.all(x, y)
    gt = problem.g_tilde
    bracket = hxx * vx * vx + 2.0 * hxy * vx * vy + hyy * vy * vy + gt
    if problem.model == "full":  # eq. (xyODE)
        q = bracket / (1.0 + hx * hx + hy * hy)
    else:  # eq. (xyODE_simp)
        q = gt
    ax = -q * hx
    ay = -q * hy
    mu = problem.damping
    if mu:
        ax = ax - mu * vx
        ay = ay - mu * vy
    if problem.nonlinear_damping:
        F = problem.fns.grad(x, np.zeros_like(y))[1]
        ay = ay - problem.nonlinear_damping * F * F * y * y * vy
    if problem.rolling_resistance:
        c = rolling_coefficient(problem, vx, vy, hx, hy, bracket)
        ax = ax + c * vx
        ay = ay + c * vy
    return ax, ay, (h, hx, hy, bracket)


def rolling_coefficient(problem: Problem, vx, vy, hx, hy, bracket):
    """c with the rolling resistance's accelerations c [xd, yd] (module doc), <= 0;
    ``bracket`` = B of eq. (xyODE) (h_xx xd^2 + 2 h_xy xd yd + h_yy yd^2 + g~)."""
    vs = rolling_smoothing_speed(problem)
    if problem.model == "full":
        Nm = (problem.g + bracket - problem.g_tilde) / np.sqrt(1.0 + hx * hx + hy * hy)
        zd = hx * vx + hy * vy
        v2 = vx * vx + vy * vy + zd * zd
    else:
        Nm = problem.g
        v2 = vx * vx + vy * vy
    return -problem.rolling_resistance / (1.0 + problem.k) * np.maximum(Nm, 0.0) / np.sqrt(v2 + vs * vs)


def rhs(problem: Problem, state):
    """d(state)/dt for ``state`` (4, ...) = (x, y, xd, yd): returns an array (4, ...).
    The ball model: ``state`` (5, ...) = (x, y, xd, yd, u) (:func:`ball_rhs`)."""
    if problem.model == "ball":
        return ball_rhs(problem, state)
    x, y, vx, vy = _unpack((state,))
    with np.errstate(all="ignore"):
        ax, ay = fused(problem)(x, y, vx, vy)[:2]
    return np.stack(np.broadcast_arrays(vx, vy, ax, ay))


def energy(problem: Problem, *args):
    """Mechanical energy per unit (1 + k) m (length^2/s^2): ``energy(problem, state)``
    with state (4, ...) or ``energy(problem, x, y, xd, yd)``; see the module doc."""
    if problem.model == "ball":   # state (5, ...): 1/2 |v|^2 + k/(2 (1 + k)) u^2 + g~ z_C
        return ball_quantities(problem, args[0])["energy"]
    x, y, vx, vy = _unpack(args)
    h, hx, hy = problem.fns.all(x, y)[:3]
    kin = vx * vx + vy * vy
    if problem.model == "full":
        zd = hx * vx + hy * vy
        kin = kin + zd * zd
    return 0.5 * kin + problem.g_tilde * h


def normal_bracket(problem: Problem, *args):
    """B = h_xx xd^2 + 2 h_xy xd yd + h_yy yd^2 + g~ (eq. xyODE), length/s^2.

    The normal force is proportional to B / sqrt(1 + |grad h|^2): in the full model
    the ball loses contact with the surface where B <= 0.
    """
    x, y, vx, vy = _unpack(args)
    _, _, _, hxx, hxy, hyy = problem.fns.all(x, y)
    return hxx * vx * vx + 2.0 * hxy * vx * vy + hyy * vy * vy + problem.g_tilde


def dissipated_power(problem: Problem, x, y, vx, vy, hx, hy):
    """Rate at which damping removes energy E (per unit (1 + k) m), >= 0.

    With the damping acceleration D added to the xy equations, dE/dt = D . (v + zd grad h)
    for the full model (zd = h_x xd + h_y yd) and D . v for the simplified one.
    """
    dx = -problem.damping * vx
    dy = -problem.damping * vy
    if problem.nonlinear_damping:
        F = problem.fns.grad(x, np.zeros_like(y))[1]
        dy = dy - problem.nonlinear_damping * F * F * y * y * vy
    if problem.rolling_resistance:
        c = rolling_coefficient(problem, vx, vy, hx, hy, normal_bracket(problem, x, y, vx, vy))
        dx = dx + c * vx
        dy = dy + c * vy
    if problem.model == "full":
        zd = hx * vx + hy * vy
        return -(dx * (vx + zd * hx) + dy * (vy + zd * hy))
    return -(dx * vx + dy * vy)


# ----------------------------------------------------------------------------
# the ball model (fabkit/physics/ball.py) through the same entry points
# ----------------------------------------------------------------------------
def state_size(problem: Problem) -> int:
    """Rows of a launch state: 4 (x, y, xd, yd) for the point models, 5 for the ball
    (+ u, its spin about the normal, a speed)."""
    return 5 if problem.model == "ball" else 4


def ball_quantities(problem: Problem, state) -> dict:
    """The ball's derivatives, contact force, slip ratio, centre velocity and energy at
    ``state`` (5, ...) = (x, y, xd, yd, u) (see :func:`fabkit.physics.ball.evaluate`),
    plus ``kappa`` (largest concave curvature), ``guard`` and ``energy``."""
    from . import ball

    s = np.asarray(state, dtype=float)
    P = ball.Params.of(problem)
    j = ball.jet_function(problem.fns)(s[0], s[1])
    with np.errstate(all="ignore"):
        ev = ball.evaluate(j, s[2], s[3], s[4], P)
        ev["kappa"] = ball.max_concave_curvature(j)
        ev["guard"] = ball.guard(ev, ev["kappa"], P)
        ev["energy"] = ball.energy(ev, s[4], P)
    return ev


def ball_rhs(problem: Problem, state):
    """d(state)/dt of the ball, ``state`` (5, ...) -> (5, ...) (no W row)."""
    s = np.asarray(state, dtype=float)
    ev = ball_quantities(problem, s)
    return np.stack(np.broadcast_arrays(s[2], s[3], ev["xdd"], ev["ydd"], ev["ud"]))
