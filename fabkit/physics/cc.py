"""The collective-coordinate model eq. (CCODE) and its separatrix map eq. (themap).

Eq. (CCODE), nondimensional::

    X'' + U'(X) + c A F'(X) = 0,      A'' + omega^2 A + c F(X) = 0,
    U(X) = exp(-2X) - exp(-X),        F(X) = exp(-X),
    E = X'^2/2 + U(X) + (A'^2 + omega^2 A^2)/2 + c A F(X)   (conserved).

Separatrix (the E = 0 orbit of X'' + U'(X) = 0): X_S(t) = log(1 + t^2/2)
(check: X_S' = t / (1 + t^2/2), X_S'^2/2 = (t^2/2)/(1 + t^2/2)^2 = e^{-X} - e^{-2X}
= -U(X_S)). Hence F(X_S(t)) = 1/(1 + t^2/2) = 2/(2 + t^2) and the Melnikov
constant of the map has the closed form

    C = (c/omega) * integral F(X_S(t)) cos(omega t) dt = (c/omega) * sqrt(2) pi exp(-sqrt(2) omega).

One passage along the separatrix leaves A ~ -C sin(omega t) (from A = 0), i.e.
the energy omega^2 C^2 / 2 moves from X to A. Capture after the first bounce
therefore happens when v^2/2 < omega^2 C^2/2:

    v_c ~ omega C = sqrt(2) pi c exp(-sqrt(2) omega)        (leading order in c),

where v is the speed of X far from the collision (the approach speed of one
kink, X being half the separation). That is the issue's small-c formula: it
is the critical velocity itself, not C.

Eq. (themap), read correctly (the paper's text has two typos): with
z = c_j + i s_j (the scaled amplitude and phase of A before bounce j),

    E_{j+1} = H - (omega^2 C^2 / 2) |z_j - i|^2,              (the kick is z - i)
    z_{j+1} = exp(-i theta_{j+1}) (z_j - i),   theta = omega T(E_{j+1}),

with H = E_j + (omega^2 C^2/2) |z_j|^2 conserved and T(E) = pi sqrt(2) / sqrt(-E)
the period of the bounded X orbit at energy E < 0 (U is a Morse potential:
e^{-X} = e^{-Y}/2 gives U = (e^{-2Y} - 2 e^{-Y})/4). In the paper's scaled
form theta = alpha (|z - i|^2 - H~)^{-1/2} with H~ = 2H / (omega C)^2 and
alpha = 2 pi / C: the bracket is |z - i|^2 - H~ (> 0 while bound), not
H~ - |z - 1|^2. The ball escapes at the first j with E_{j+1} > 0, with
v_out = sqrt(2 E_{j+1}). Checked against the ODE in tests/test_cc.py.
"""

from __future__ import annotations

import math

import numpy as np

SQRT2 = math.sqrt(2.0)


def U(X):
    return np.exp(-2 * X) - np.exp(-X)


def F(X):
    return np.exp(-X)


def cc_rhs(t, s, c: float, omega: float):
    """Eq. (CCODE) as a first-order system, s = (X, X', A, A') of shape (4,) or (4, M)."""
    X, P, A, Q = s
    e1 = np.exp(-X)
    e2 = e1 * e1
    return np.array([P, 2 * e2 - e1 + c * A * e1, Q, -omega * omega * A - c * e1])


def cc_energy(s, c: float, omega: float):
    """E of eq. (CCODE) for s = (X, X', A, A')."""
    X, P, A, Q = s
    return 0.5 * P * P + U(X) + 0.5 * (Q * Q + omega * omega * A * A) + c * A * F(X)


def melnikov_C(c: float, omega: float) -> float:
    """C = (c/omega) sqrt(2) pi exp(-sqrt(2) omega), the closed form (exact)."""
    return c / omega * SQRT2 * math.pi * math.exp(-SQRT2 * omega)


def melnikov_C_quad(c: float, omega: float) -> float:
    """C by quadrature of (c/omega) * integral F(X_S(t)) cos(omega t) dt along
    X_S(t) = log(1 + t^2/2) (scipy QAWF Fourier integral, ~1e-12 relative)."""
    from scipy.integrate import quad

    val, _ = quad(lambda t: F(math.log1p(0.5 * t * t)), 0.0, np.inf, weight="cos", wvar=omega)
    return c / omega * 2.0 * val


def v_critical_map(c: float, omega: float) -> float:
    """v_c = omega C = sqrt(2) pi c exp(-sqrt(2) omega) (the map's estimate)."""
    return omega * melnikov_C(c, omega)


def cc_launch(v: float, c: float, omega: float, *, X0: float = 12.0, rtol: float = 1e-10,
              atol: float = 1e-13, t_max: float | None = None, method: str = "DOP853",
              max_bounces: int | None = None, decide: bool = False, dense: bool = False) -> dict:
    """One collision of eq. (CCODE): X starts at ``X0`` moving toward 0, A = A' = 0.

    ``v`` is the speed far from the collision (|X'| at X = infinity): the launch
    speed at X0 is sqrt(v^2 - 2 U(X0)), and v_out is converted back the same way
    (exact for the X subsystem; the coupling c A F(X0) is ~ c e^{-X0} |A|).
    Bounces are minima of X (X' crossing 0 upward). Escape: X back at X0 with
    X' > 0. ``max_bounces``: stop (outcome 'captured') at that bounce, to
    decide "one bounce or more" cheaply (needs scipy >= 1.14; ignored before).
    ``decide``: stop as soon as the fate is certain: on the way out (X' > 0,
    X > 3) the X energy E_X = X'^2/2 + U + c A F can still change by at most
    about c |A| e^{-X} (dE_X/dt = c A' F), so |E_X| > 4 c |A| e^{-X} decides
    escape (E_X > 0; v_out = sqrt(2 E_X), relative error ~ c|A|e^{-X}/E_X) or
    capture (E_X < 0). Near v_c this is what keeps slow escapes and long
    excursions within the time limit.
    Returns {outcome: 'escaped' | 'captured', bounces, bounce_times,
    v_out (nan unless escaped), t_end, energy_error (relative to v^2/2), nfev}
    (plus ``solution``, the solve_ivp dense output s(t), if ``dense``).
    """
    from scipy.integrate import solve_ivp

    p0 = math.sqrt(v * v - 2 * float(U(X0)))
    if t_max is None:
        t_max = 4.0 * X0 / max(v, 1e-9) + 4000.0
    s0 = np.array([X0, -p0, 0.0, 0.0])

    def bounce(t, s):
        return s[1]

    bounce.direction = 1
    bounce.terminal = False
    if max_bounces is not None and _scipy_counts_events():
        bounce.terminal = int(max_bounces)

    def escape(t, s):
        return s[0] - X0 if t > 0 else -1.0

    escape.direction = 1
    escape.terminal = True
    def fate(t, s):
        X, P, A, Q = s
        if P <= 0 or X <= 3.0:
            return -1.0
        ex = 0.5 * P * P + float(U(X)) + c * A * math.exp(-X)
        amp = math.hypot(A, Q / omega)
        return abs(ex) - 4.0 * abs(c) * amp * math.exp(-X)

    fate.direction = 1
    fate.terminal = True
    events = [bounce, escape] + ([fate] if decide else [])
    sol = solve_ivp(lambda t, s: cc_rhs(t, s, c, omega), (0.0, t_max), s0, method=method, rtol=rtol,
                    atol=atol, events=events, dense_output=dense)
    escaped = len(sol.t_events[1]) > 0
    decided = decide and len(sol.t_events[2]) > 0
    if decided:
        end = sol.y_events[2][0]
        t_end = float(sol.t_events[2][0])
        ex = 0.5 * end[1] ** 2 + float(U(end[0])) + c * end[2] * math.exp(-end[0])
        escaped = ex > 0
        v_out = math.sqrt(2 * ex) if escaped else math.nan
    else:
        t_end = float(sol.t_events[1][0]) if escaped else float(sol.t[-1])
        end = sol.y_events[1][0] if escaped else sol.y[:, -1]
        v_out = math.sqrt(max(end[1] ** 2 + 2 * float(U(X0)), 0.0)) if escaped else math.nan
    tb = np.asarray(sol.t_events[0])
    tb = tb[tb <= t_end]
    e0 = cc_energy(s0, c, omega)
    return {
        "outcome": "escaped" if escaped else "captured",
        "bounces": int(len(tb)),
        "bounce_times": tb,
        "v_out": v_out,
        "t_end": t_end,
        "energy_error": float(abs(cc_energy(end, c, omega) - e0) / (0.5 * v * v)),
        "nfev": int(sol.nfev),
        **({"solution": sol.sol} if dense else {}),
    }


def _scipy_counts_events() -> bool:
    import scipy

    major, minor = (int(p) for p in scipy.__version__.split(".")[:2])
    return (major, minor) >= (1, 14)


def cc_critical_velocity(c: float, omega: float, *, rel_tol: float = 1e-7, scan: int = 12,
                         lo: float | None = None, hi: float | None = None, **launch_kw) -> float:
    """v_c of eq. (CCODE): the smallest v above which every launch escapes after one bounce.

    A scan of ``scan`` speeds over [lo, hi] (default [0.5, 2] x the map's v_c,
    widened upward until its top escapes after one bounce) brackets the largest
    non-one-bounce speed; bisection then narrows it to ``rel_tol`` relative.
    Accurate to rel_tol plus the integrator's error (``launch_kw``: rtol, atol, X0).
    """
    vm = v_critical_map(c, omega)
    lo = 0.5 * vm if lo is None else lo
    hi = 2.0 * vm if hi is None else hi

    def one(v):
        r = cc_launch(v, c, omega, max_bounces=2, decide=True, **launch_kw)
        return r["outcome"] == "escaped" and r["bounces"] == 1

    for _ in range(20):
        if one(hi):
            break
        lo, hi = hi, 2 * hi
    else:
        raise RuntimeError("no one-bounce escape found")
    vs = np.linspace(lo, hi, scan)
    ok = [one(float(v)) for v in vs[:-1]] + [True]
    bad = [i for i, o in enumerate(ok) if not o]
    if not bad:
        a, b = 0.0, float(vs[0])
        if one(a + 1e-12):
            return 0.0
    else:
        a, b = float(vs[bad[-1]]), float(vs[bad[-1] + 1])
    while b - a > rel_tol * b:
        m = 0.5 * (a + b)
        if one(m):
            b = m
        else:
            a = m
    return 0.5 * (a + b)


def cc_map(v, c: float, omega: float, *, max_bounces: int = 200):
    """Iterate eq. (themap) from z = 0, E_0 = v^2/2, for speeds ``v`` (M,).

    Returns (bounces (M,) int, v_out (M,) float): the number of bounces before
    escape and sqrt(2 E) after it (0 bounces / nan: still bound after
    ``max_bounces``). Vectorized over v.
    """
    v = np.atleast_1d(np.asarray(v, dtype=float))
    Cw2 = 0.5 * (omega * melnikov_C(c, omega)) ** 2
    H = 0.5 * v * v
    z = np.zeros(v.shape, dtype=complex)
    bounces = np.zeros(v.shape, dtype=int)
    v_out = np.full(v.shape, np.nan)
    live = np.ones(v.shape, dtype=bool)
    for j in range(1, max_bounces + 1):
        E = H - Cw2 * np.abs(z - 1j) ** 2
        esc = live & (E > 0)
        bounces[esc] = j
        v_out[esc] = np.sqrt(2 * E[esc])
        live &= ~esc
        if not live.any():
            break
        with np.errstate(all="ignore"):
            theta = omega * math.pi * SQRT2 / np.sqrt(np.where(live, -E, 1.0))
            z = np.where(live, np.exp(-1j * theta) * (z - 1j), z)
    return bounces, v_out
