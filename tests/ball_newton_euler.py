"""An independent implementation of the rolling ball, for tests and benchmarks.

Newton-Euler in three dimensions, with the rolling constraint enforced by solving
for the contact force, instead of fabkit's reduced equations in the contact point's
coordinates (fabkit/physics/ball.py):

    state  (x, y, omega_x, omega_y, omega_z): the contact point and the angular velocity
    v      = r omega x n                                (rolling without slipping)
    (xd, yd) from the centre's horizontal velocity: [I + r dn/dP] (xd, yd) = (v_x, v_y)
    m a    = m g + R + F_d,   I omega' = (-r n) x R,    a = d/dt (r omega x n)

Substituting omega' and a = r omega' x n + r omega x n' gives a 3x3 linear system
for the contact force R, solved numerically here. Only h and its first and second
derivatives enter (n and its Jacobian, by sympy); no third derivatives, no offset
surface metric, no spin variable u. The events are scipy's root finding on the
dense output. Lengths in design units, times in s.
"""

from __future__ import annotations

import math

import numpy as np
import sympy as sp
from scipy.integrate import solve_ivp


class NewtonEuler:
    def __init__(self, problem):
        self.p = problem
        h = problem.fns.symbolic
        syms = {s.name: s for s in h.free_symbols}
        x = syms.get("x", sp.Symbol("x", real=True))
        y = syms.get("y", sp.Symbol("y", real=True))
        hx, hy = sp.diff(h, x), sp.diff(h, y)
        s = sp.sqrt(1 + hx ** 2 + hy ** 2)
        n = [-hx / s, -hy / s, 1 / s]
        dn = [[sp.diff(c, x), sp.diff(c, y)] for c in n]
        self._h = sp.lambdify((x, y), h, "math")
        self._n = sp.lambdify((x, y), n, "math")
        self._dn = sp.lambdify((x, y), dn, "math")
        self.r = float(problem.radius)
        self.k = float(problem.k)
        self.g = float(problem.g)
        self.mu = float(problem.damping)

    # -- kinematics ---------------------------------------------------------------
    def frame(self, s):
        x, y, w = s[0], s[1], np.asarray(s[2:5], dtype=float)
        n = np.array(self._n(x, y), dtype=float)
        dn = np.array(self._dn(x, y), dtype=float)          # dn[i, j] = d n_i / d x_j
        v = self.r * np.cross(w, n)
        J = np.eye(2) + self.r * dn[:2, :2]
        xd, yd = np.linalg.solve(J, v[:2])
        nd = dn[:, 0] * xd + dn[:, 1] * yd
        return n, v, xd, yd, nd

    def forces(self, s):
        """(R / m, xd, yd, omega', v): the contact force per unit mass and the rates."""
        n, v, xd, yd, nd = self.frame(s)
        w = np.asarray(s[2:5], dtype=float)
        k, r = self.k, self.r
        gvec = np.array([0.0, 0.0, -self.g])
        f = -(1.0 + k) * self.mu * v
        # -R_t / k + r w x n' = g + R + f,  R_t = R - (R . n) n
        M = (1.0 + 1.0 / k) * np.eye(3) - np.outer(n, n) / k
        R = np.linalg.solve(M, r * np.cross(w, nd) - gvec - f)
        wd = -np.cross(n, R) / (k * r)
        return R, xd, yd, wd, v, n

    def rhs(self, t, s):
        R, xd, yd, wd, v, n = self.forces(s)
        return np.array([xd, yd, wd[0], wd[1], wd[2]])

    def energy(self, s):
        """Per unit m: 1/2 |v|^2 + k r^2 / 2 |omega|^2 + g z_C."""
        n, v, *_ = self.frame(s)
        w = np.asarray(s[2:5], dtype=float)
        zc = self._h(s[0], s[1]) + self.r * n[2]
        return 0.5 * v @ v + 0.5 * self.k * self.r ** 2 * (w @ w) + self.g * zc

    def initial(self, v_in, y0=0.0, vy0=0.0):
        x = float(self.p.start)
        n = np.array(self._n(x, y0), dtype=float)
        v = np.array([v_in, vy0, -(n[0] * v_in + n[1] * vy0) / n[2]])
        w = np.cross(n, v) / self.r       # omega . n = 0: no spin about the normal
        return np.array([x, y0, *w])

    # -- one launch ---------------------------------------------------------------
    def launch(self, v_in, y0=0.0, vy0=0.0, *, rtol=1e-11, atol=1e-13, t_max=None):
        p = self.p
        t_max = float(p.t_max if t_max is None else t_max)
        start, mg = float(p.start), float(p.margin)
        x0, x1 = p.x_range
        ya, yb = p.y_range
        z_lim = float(p.top) - mg

        def ev(fn, terminal, direction):
            fn.terminal, fn.direction = terminal, direction
            return fn

        events = [
            ev(lambda t, s: self.frame(s)[2], False, -1),                          # bounce
            ev(lambda t, s: (s[0] - start) if (t > 0 and self.frame(s)[2] < 0) else 1.0, True, -1),
            ev(lambda t, s: self._h(s[0], s[1]) - z_lim, True, 1),
            ev(lambda t, s: s[0] - (x1 - mg), True, 1),
            ev(lambda t, s: (x0 + mg) - s[0], True, 1),
            ev(lambda t, s: s[1] - (yb - mg), True, 1),
            ev(lambda t, s: (ya + mg) - s[1], True, 1),
            ev(lambda t, s: float(self.forces(s)[0] @ self.forces(s)[5]), True, -1),   # N
        ]
        names = ["bounce", "escaped", "flew_off", "flew_off", "flew_off", "flew_off", "flew_off", "lost_contact"]
        s0 = self.initial(v_in, y0, vy0)
        sol = solve_ivp(self.rhs, (0.0, t_max), s0, method="DOP853", rtol=rtol, atol=atol, events=events)
        outcome, t_end, end = "captured", float(sol.t[-1]), sol.y[:, -1]
        if sol.status == 1:
            best = None
            for i, nm in enumerate(names):
                if nm != "bounce" and len(sol.t_events[i]):
                    te = float(sol.t_events[i][0])
                    if best is None or te < best[0]:
                        best = (te, nm, sol.y_events[i][0])
            t_end, outcome, end = best
        tb = np.asarray(sol.t_events[0], dtype=float)
        tb = tb[tb <= t_end]
        v_end = self.frame(end)[1]
        e = [self.energy(sol.y[:, i]) for i in range(0, sol.y.shape[1], max(1, sol.y.shape[1] // 200))]
        e0 = self.energy(s0)
        return {"outcome": outcome, "bounces": int(tb.size), "bounce_times": tb,
                "v_out": abs(float(v_end[0])) if outcome == "escaped" else math.nan,
                "t_end": t_end, "x_end": float(end[0]), "y_end": float(end[1]),
                "energy_drift": float(np.max(np.abs(np.array(e) - e0)) / max(abs(e0), 1e-300)),
                "spin": float(np.asarray(end[2:5]) @ np.array(self._n(end[0], end[1])) * self.r)}
