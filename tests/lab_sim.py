"""An independent simulation of the paper's apparatus, for the lab-analysis tests.

The paper's eq. (xyODE) with viscous damping, written out by hand for the appendix
surface h = eta (e^{ax} - e^{bx}) + c y^2 + eps y e^{dx} (cm) and integrated with
scipy's DOP853 at rtol 1e-12 (nothing of fabkit's models or integrator is used), then
sampled like a camera: frames at ``fps``, Gaussian noise of ``noise`` cm on x and y.

Rolling resistance ``crr``: a force crr N on the ball opposing its velocity. With the
ball's mass m and inertia k m r^2, its tangential equation is (1 + k) m a = m g_t + F,
so F adds F/((1 + k) m) to the acceleration along the surface; F is tangent, so its
horizontal part is what enters (xdd, ydd). N = m (g + v^T H v) / |(-h_x, -h_y, 1)|
(gravity's normal part plus the centripetal term of the path's normal curvature), |v|
the 3-D speed; the direction is smoothed as v / sqrt(|v|^2 + VS^2) (VS = 1e-3 sqrt(g r),
r = 1.25 cm) so a release from rest starts.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

P = dict(a=0.389, b=0.306, c=0.0764, d=0.306, eta=3.27, eps=0.25)
G = 980.665                      # cm/s^2
G_TILDE = G / 1.4                # cm/s^2, solid ball (k = 2/5)
START = -30.0
VS = 1e-3 * (G * 1.25) ** 0.5    # cm/s


def rhs(t, s, mu, crr=0.0):
    x, y, vx, vy = s
    a, b, c, d, eta, eps = P["a"], P["b"], P["c"], P["d"], P["eta"], P["eps"]
    ea, eb, ed = np.exp(a * x), np.exp(b * x), np.exp(d * x)
    hx = eta * (a * ea - b * eb) + eps * d * y * ed
    hy = 2 * c * y + eps * ed
    hxx = eta * (a * a * ea - b * b * eb) + eps * d * d * y * ed
    hxy = eps * d * ed
    hyy = 2 * c
    curv = hxx * vx * vx + 2 * hxy * vx * vy + hyy * vy * vy
    B = curv + G_TILDE
    q = B / (1 + hx * hx + hy * hy)
    ax, ay = -q * hx - mu * vx, -q * hy - mu * vy
    if crr:
        n_over_m = max(G + curv, 0.0) / np.sqrt(1 + hx * hx + hy * hy)
        speed2 = vx * vx + vy * vy + (hx * vx + hy * vy) ** 2
        f = crr * n_over_m / 1.4 / np.sqrt(speed2 + VS * VS)
        ax, ay = ax - f * vx, ay - f * vy
    return [vx, vy, ax, ay]


def run(state0, mu, t_max, *, escape=True, crr=0.0):
    """Dense solution from ``state0`` = (x, y, vx, vy) at t = 0; stops on escape
    (x back through START moving toward -x) when ``escape``."""
    def bounce(t, s, mu, crr):
        return s[2]
    bounce.direction = -1

    def out(t, s, mu, crr):
        return s[0] - START
    out.terminal, out.direction = True, -1
    ev = [bounce, out] if escape else [bounce]
    sol = solve_ivp(rhs, (0.0, t_max), list(state0), method="DOP853", rtol=1e-12, atol=1e-12,
                    dense_output=True, events=ev, args=(mu, crr))
    escaped = escape and len(sol.t_events[1]) > 0
    return {"sol": sol, "t_end": float(sol.t[-1]), "bounce_times": list(sol.t_events[0]),
            "escaped": escaped, "v_out": abs(float(sol.y_events[1][0][2])) if escaped else None}


def frames(truth, fps=125.0, noise=0.03, seed=0, t_end=None):
    """Camera samples of a dense solution: (t, x, y) with noise (cm)."""
    rng = np.random.default_rng(seed)
    te = truth["t_end"] if t_end is None else t_end
    t = np.arange(0.0, te, 1.0 / fps)
    x, y = truth["sol"].sol(t)[:2]
    return t, x + rng.normal(0, noise, t.size), y + rng.normal(0, noise, t.size)


def transverse_extrema(truth, t0, t1, n=20000):
    """Times of the extrema of y(t) (roots of vy) of a dense solution in [t0, t1]."""
    from scipy.optimize import brentq

    ts = np.linspace(t0, t1, n)
    vy = truth["sol"].sol(ts)[3]
    out = []
    for i in np.flatnonzero(np.sign(vy[:-1]) * np.sign(vy[1:]) < 0):
        out.append(brentq(lambda s: truth["sol"].sol(s)[3], ts[i], ts[i + 1], xtol=1e-13))
    return np.array(out)


def csv_text(t, x, y):
    return "t,x,y\n" + "".join(f"{a:.6f},{b:.6f},{c:.6f}\n" for a, b, c in zip(t, x, y))


# ----------------------------------------------------------------------------
# the lab loop: launches from release heights on a ramp, with a launch scatter
# ----------------------------------------------------------------------------
def speed_from_height(H):
    """Entry speed (cm/s) of a solid ball released H cm above the entry level on a
    loss-free ramp: (1 + k) v^2 / 2 = g H, v = sqrt(2 g~ H)."""
    return float(np.sqrt(2.0 * G_TILDE * H))


def scattered_launches(heights, mu, crr=0.0, seed=0, speed_rel=0.005, y_sd=0.1, vy_sd=0.5, t_max=15.0):
    """One launch per release height, each with a launch scatter (the speed off by a
    relative N(0, speed_rel), the entry point's y by N(0, y_sd) cm, its vy by N(0, vy_sd)
    cm/s): [(H, v, y0, vy0, truth)]."""
    rng = np.random.default_rng(seed)
    out = []
    for H in heights:
        v = speed_from_height(H) * (1.0 + rng.normal(0.0, speed_rel))
        y0, vy0 = rng.normal(0.0, y_sd), rng.normal(0.0, vy_sd)
        out.append((float(H), v, float(y0), float(vy0), run((START, y0, v, vy0), mu, t_max, crr=crr)))
    return out


def track_csv(truth, fps=125.0, noise=0.03, seed=0, t_end=None):
    """The camera's track of a dense solution as ``t,x,y,sigma_x,sigma_y`` (the format
    ``fabkit track`` writes): Gaussian noise of ``noise`` cm, its sigma in the columns;
    filmed to ``t_end`` (default: the end of the solution, the escape or t_max)."""
    t, x, y = frames(truth, fps=fps, noise=noise, seed=seed, t_end=t_end)
    return "t,x,y,sigma_x,sigma_y\n" + "".join(f"{a:.6f},{b:.6f},{c:.6f},{noise:.3g},{noise:.3g}\n"
                                                for a, b, c in zip(t, x, y))
