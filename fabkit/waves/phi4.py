"""Kink-antikink collisions of the phi^4 equation: grid, scheme, initial data, bounce counting.

The equation (units with c = 1, mass sqrt 2)::

    phi_tt - phi_xx - phi + phi^3 = 0,     V(phi) = (phi^2 - 1)^2 / 4,
    E = integral  phi_t^2/2 + phi_x^2/2 + V(phi)  dx                       (conserved),

whose kink is phi_K(x) = tanh(x / sqrt 2) (energy 2 sqrt(2)/3), whose shape mode
chi(xi) = (3/sqrt 2)^(1/2) sech(xi/sqrt 2) tanh(xi/sqrt 2) oscillates at omega_1 =
sqrt(3/2), and whose vacua +-1 carry linear waves of frequency sqrt(k^2 + 2).
(The seed paper's eq. (phi4) prints the linear term as + phi - phi^3; its kink
(eq. phi4kink) and shape mode solve the equation above.)

Initial data (eq. ansatz with A = 0): a Lorentz-boosted kink at -X0 moving right
and an antikink at +X0 moving left, each at speed v (gamma = 1/sqrt(1 - v^2)),

    phi   = tanh(gamma (x + X0)/sqrt 2) - tanh(gamma (x - X0)/sqrt 2) - 1,
    phi_t = -(gamma v / sqrt 2) [sech^2(gamma (x + X0)/sqrt 2) + sech^2(gamma (x - X0)/sqrt 2)].

Both are even in x, and the equation keeps that symmetry, so only x in [0, L] is
computed (Neumann at x = 0 is the symmetry, at x = L the wall behind the sponge).
The superposition error at X0 >= 10 is of order exp(-2 sqrt(2) X0) < 1e-12.

Scheme. u = phi + 1 (the outer vacuum is u = 0) obeys u_tt = u_xx - 2u + N,
N = 3u^2 - u^3 - sigma(x) u_t. In the cosine basis cos(k x), k = pi j / L (DCT-I on the
N + 1 points x_j = j dx, spectrally accurate for smooth even data) the linear part is
diagonal: with w = u^_t - i omega_k u^, omega_k = sqrt(k^2 + 2),

    w_t = -i omega_k w + N^,

integrated by ETDRK4 (Cox & Matthews 2002; coefficients by the contour integrals of
Kassam & Trefethen 2005): the linear waves are exact, the scheme is fourth order in dt,
and the step is not limited by the grid (omega_max dt = 0.63 at dx = 1/4, dt = 1/20).
This is Goodman & Haberman's (2005) method.

Absorbing layer: sigma(x) = sigma_max s^2, s = (x - x_s)/(L - x_s) on [x_s, L] and 0
before, damps outgoing radiation (its group velocity k/omega_k < 1) before the wall;
x_s = X0 + 10 keeps the kinks' tails (exp(-sqrt 2 * 10) ~ 1e-6) out of it until they
are declared escaped. docs/numerics.md ("phi^4") measures what the layer and the grid
change.

Kink position and bounces. X(t) is the zero of phi on x > 0 bounding the region
phi > 0 around the origin (a quintic Lagrange interpolant through six grid values,
solved by Newton: error ~ dx^6), and X = 0 while phi(0, t) <= 0 (the kinks overlap:
this is where the nonlinear projection onto eq. ansatz is singular). A bounce is
each excursion of X to 0, i.e. each time phi(0, t) falls through 0; its time is the
middle of the excursion (crossings interpolated linearly in t). Escape: X back at X0
moving outward after at least one bounce; the launch stops there. A launch not
escaped at ``t_max`` is ``captured``. v_out is the least-squares slope of X(t) over
the outgoing leg from X0/2 to X0 (the interaction there is ~exp(-2 sqrt 2 X0/2) <
1e-6 of v^2; the shape mode left on the kink is odd about its centre and moves the
zero only at second order in its amplitude).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

SQRT2 = math.sqrt(2.0)
OMEGA_SHAPE = math.sqrt(1.5)            # shape-mode frequency omega_1
KINK_ENERGY = 2.0 * SQRT2 / 3.0         # rest energy of one kink
from ..physics.outcomes import CAPTURED, ESCAPED  # noqa: E402
from ..physics.outcomes import OUTCOMES as _ALL_OUTCOMES  # noqa: E402

OUTCOMES = _ALL_OUTCOMES[:CAPTURED + 1]     # a collision escapes or is captured


@dataclass(frozen=True)
class Phi4Config:
    """Grid, step and run parameters (defaults from docs/numerics.md, "phi^4").

    dx: grid spacing; dt: ETDRK4 step; x0: initial half-separation X0 (>= 10);
    layer: width of the absorbing layer; sigma: its peak damping rate; gap: distance
    from X0 to the layer's start; t_max: end of the run (captured if not escaped).
    """

    dx: float = 0.25
    dt: float = 0.05
    x0: float = 10.0
    gap: float = 10.0
    layer: float = 20.0
    sigma: float = 1.0
    t_max: float = 800.0

    @property
    def x_layer(self) -> float:
        return self.x0 + self.gap

    @property
    def length(self) -> float:
        return self.x_layer + self.layer

    @property
    def n(self) -> int:
        """Grid intervals on [0, L] (the grid has n + 1 points)."""
        return max(8, int(math.ceil(self.length / self.dx)))

    def with_(self, **kw) -> "Phi4Config":
        return replace(self, **kw)


DEFAULT_CONFIG = Phi4Config()


# ----------------------------------------------------------------------------
# closed forms
# ----------------------------------------------------------------------------
def kink(x, v: float = 0.0, center: float = 0.0):
    """Boosted kink tanh(gamma (x - center)/sqrt 2) at t = 0."""
    g = 1.0 / math.sqrt(1.0 - v * v)
    return np.tanh(g * (np.asarray(x, dtype=float) - center) / SQRT2)


def sech(a):
    """1/cosh(a) without overflow: 2 e^-|a| / (1 + e^-2|a|) (cosh overflows past |a| = 710,
    which a kink 1000 away reaches)."""
    e = np.exp(-np.abs(np.asarray(a, dtype=float)))
    return 2.0 * e / (1.0 + e * e)


def shape_mode(xi):
    """chi(xi) = (3/sqrt 2)^(1/2) sech(xi/sqrt 2) tanh(xi/sqrt 2) (the paper's normalization)."""
    s = np.asarray(xi, dtype=float) / SQRT2
    return math.sqrt(3.0 / SQRT2) * np.tanh(s) * sech(s)


def pair(x, v, X):
    """Kink at -X moving right and antikink at +X moving left, both at speed v, as
    (phi, phi_t); ``v``, ``X`` scalars or (M,) -> arrays (M, len(x))."""
    x = np.asarray(x, dtype=float)[None, :]
    v = np.atleast_1d(np.asarray(v, dtype=float))[:, None]
    X = np.broadcast_to(np.atleast_1d(np.asarray(X, dtype=float))[:, None], v.shape)
    g = 1.0 / np.sqrt(1.0 - v * v)
    a, b = g * (x + X) / SQRT2, g * (x - X) / SQRT2
    phi = np.tanh(a) - np.tanh(b) - 1.0
    phi_t = -(g * v / SQRT2) * (sech(a) ** 2 + sech(b) ** 2)
    return phi, phi_t


def max_gamma_dx() -> float:
    """Largest gamma dx at which the boosted kink is resolved: the cosine coefficients of
    tanh(gamma x / sqrt 2) at the grid's highest wavenumber pi/dx fall like
    exp(-pi^2 sqrt(2) / (2 gamma dx)); gamma dx <= 0.6 keeps them below 1e-5 (dx = 1/2
    at v = 0.27, gamma dx = 0.52, changes v_out by 1e-6 from dx = 1/8: docs/numerics.md)."""
    return 0.6


def check_resolution(v, dx: float) -> str | None:
    """A one-line reason if the fastest speed of ``v`` is under-resolved at ``dx``, else None."""
    vmax = float(np.max(np.atleast_1d(v)))
    g = 1.0 / math.sqrt(1.0 - vmax * vmax)
    if g * dx <= max_gamma_dx():
        return None
    return (f"v_in = {vmax:g}: the Lorentz-contracted kink (width sqrt(2)/gamma = {SQRT2 / g:.3g}) is "
            f"under-resolved at dx = {dx:g}; use dx <= {max_gamma_dx() / g:.3g} (--dx)")


# ----------------------------------------------------------------------------
# grid and scheme
# ----------------------------------------------------------------------------
class Scheme:
    """The cosine pseudo-spectral ETDRK4 stepper on [0, L] for a config (see the module doc)."""

    def __init__(self, cfg: Phi4Config = DEFAULT_CONFIG, *, absorb: bool = True):
        self.cfg = cfg
        n = cfg.n
        self.L = cfg.length
        self.dx = self.L / n
        self.x = np.linspace(0.0, self.L, n + 1)
        self.k = np.pi * np.arange(n + 1) / self.L
        self.omega = np.sqrt(self.k ** 2 + 2.0)
        s = np.clip((self.x - cfg.x_layer) / max(self.L - cfg.x_layer, 1e-12), 0.0, 1.0)
        self.sigma = cfg.sigma * s * s if absorb else np.zeros_like(self.x)
        self.absorb = absorb and cfg.sigma > 0
        self.h = cfg.dt
        self._coefficients()
        # trapezoid weights: exact for the cosine series' quadratic forms up to aliasing
        self.wq = np.full(n + 1, self.dx)
        self.wq[0] = self.wq[-1] = 0.5 * self.dx

    def _coefficients(self, m: int = 64):
        """ETDRK4 coefficients for L = -i omega (Kassam & Trefethen's contour mean)."""
        h = self.h
        Lh = -1j * self.omega * h
        r = np.exp(2j * np.pi * (np.arange(1, m + 1) - 0.5) / m)   # full circle: L is complex
        LR = Lh[:, None] + r[None, :]
        e = np.exp(LR)
        self.E = np.exp(Lh)
        self.E2 = np.exp(Lh / 2)
        self.Q = h * np.mean((np.exp(LR / 2) - 1) / LR, axis=1)
        self.f1 = h * np.mean((-4 - LR + e * (4 - 3 * LR + LR ** 2)) / LR ** 3, axis=1)
        self.f2 = h * np.mean((2 + LR + e * (LR - 2)) / LR ** 3, axis=1)
        self.f3 = h * np.mean((-4 - 3 * LR - LR ** 2 + e * (4 - LR)) / LR ** 3, axis=1)

    # transforms: DCT-I maps grid values to cosine coefficients and back
    @staticmethod
    def _fwd(a):
        from scipy.fft import dct

        return dct(a, type=1, axis=-1)

    @staticmethod
    def _inv(a):
        from scipy.fft import idct

        return idct(a, type=1, axis=-1)

    def to_w(self, phi, phi_t):
        """Field (M, n+1) -> w = u^_t - i omega u^ (M, n+1) complex, u = phi + 1."""
        uh = self._fwd(np.asarray(phi) + 1.0)
        vh = self._fwd(np.asarray(phi_t))
        return vh - 1j * self.omega * uh

    def fields(self, w):
        """w -> (phi, phi_t) on the grid."""
        m = w.shape[0]
        both = np.concatenate([-w.imag / self.omega, w.real], axis=0)
        f = self._inv(both)
        return f[:m] - 1.0, f[m:]

    def _nonlinear(self, w):
        """N^ at w, and the fields (u = phi + 1, u_t) it was computed from."""
        m = w.shape[0]
        both = self._inv(np.concatenate([-w.imag / self.omega, w.real], axis=0))
        u, ut = both[:m], both[m:]
        nl = u * u * (3.0 - u)
        if self.absorb:
            nl = nl - self.sigma * ut
        return self._fwd(nl), u, ut

    def step(self, w, Nv=None):
        """One ETDRK4 step of size dt (Cox & Matthews); ``Nv``: N^ at w if known."""
        E2, Q = self.E2, self.Q
        if Nv is None:
            Nv = self._nonlinear(w)[0]
        a = E2 * w + Q * Nv
        Na = self._nonlinear(a)[0]
        b = E2 * w + Q * Na
        Nb = self._nonlinear(b)[0]
        c = E2 * a + Q * (2 * Nb - Nv)
        Nc = self._nonlinear(c)[0]
        return self.E * w + Nv * self.f1 + 2 * (Na + Nb) * self.f2 + Nc * self.f3

    # diagnostics
    def energy(self, phi, phi_t):
        """E on [0, L] (half the pair's energy) (M,): phi_x by the cosine series
        (sine series of the coefficients), trapezoid quadrature."""
        from scipy.fft import dst

        ah = self._fwd(np.asarray(phi) + 1.0) / self.cfg_n
        # phi_x(x_j) = -sum_k c_k a_k k sin(k x_j); DST-I over the interior modes
        interior = -(self.k[1:-1] * ah[..., 1:-1]) / 2.0
        px = np.zeros_like(np.asarray(phi, dtype=float))
        px[..., 1:-1] = dst(interior, type=1, axis=-1)
        dens = 0.5 * phi_t ** 2 + 0.5 * px ** 2 + 0.25 * (phi ** 2 - 1.0) ** 2
        return dens @ self.wq

    @property
    def cfg_n(self) -> int:
        return len(self.x) - 1

    def residual(self, phi):
        """-phi_xx - phi + phi^3 on the grid by the cosine series (the static equation)."""
        uh = self._fwd(np.asarray(phi) + 1.0)
        pxx = self._inv(-(self.k ** 2) * uh)
        return -pxx - phi + phi ** 3


# ----------------------------------------------------------------------------
# kink position
# ----------------------------------------------------------------------------
_NODES = np.arange(-2, 4, dtype=float)
_LAGRANGE = np.linalg.inv(np.vander(_NODES, increasing=True))   # values -> monomial coefficients


def kink_position(phi, dx: float):
    """X (M,): the zero of phi (M, n+1) bounding {phi > 0} around x = 0, 0 if phi(0) <= 0.

    Quintic Lagrange interpolation through six grid values (even reflection at x = 0),
    root by Newton from the linear guess: error ~ dx^6 |phi^(6)| / |phi'|."""
    phi = np.asarray(phi, dtype=float)
    m, npts = phi.shape
    pos = phi > 0
    first_neg = np.argmax(~pos, axis=1)
    none_neg = pos.all(axis=1)
    i = np.clip(first_neg - 1, 0, npts - 2)
    idx = i[:, None] + np.arange(-2, 4)[None, :]
    idx = np.abs(idx)
    idx = np.where(idx > npts - 1, 2 * (npts - 1) - idx, idx)
    f = np.take_along_axis(phi, idx, axis=1)
    c = f @ _LAGRANGE.T                                  # (M, 6) monomial coefficients in s
    f0, f1 = f[:, 2], f[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(f0 != f1, f0 / (f0 - f1), 0.5)
    s = np.clip(s, 0.0, 1.0)
    for _ in range(4):
        p = c[:, 5]
        d = np.zeros(m)
        for j in range(4, -1, -1):
            d = d * s + p
            p = p * s + c[:, j]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.clip(s - np.where(d != 0, p / d, 0.0), 0.0, 1.0)
    X = (i + s) * dx
    X = np.where(pos[:, 0], X, 0.0)
    return np.where(none_neg, (npts - 1) * dx, X)


#: kink speeds for the projection's Lorentz contraction: dX/dt where X >= SPEED_APART (the
#: kinks apart), the last such speed held where X <= SPEED_NEAR (there the zero of phi does
#: not move with the kinks), a linear blend between (A(t) continuous; see kink_speed)
SPEED_NEAR, SPEED_APART = 3.0, 4.0


def kink_speed(X, dXdt, held):
    """The speed at which :func:`shape_amplitude` contracts the kink and its shape mode
    (M,), and the new held speed (M,): |dX/dt| where X >= SPEED_APART, ``held`` (the
    last speed measured there; at first the launch speed) where X <= SPEED_NEAR, and
    linear in X between, so that the speed, and A(t), are continuous in time."""
    X, meas, held = (np.asarray(a, dtype=float) for a in (X, dXdt, held))
    meas = np.abs(meas)
    w = np.clip((X - SPEED_NEAR) / (SPEED_APART - SPEED_NEAR), 0.0, 1.0)
    return held + (meas - held) * w, np.where(X >= SPEED_APART, meas, held)


def shape_amplitude(phi, X, x, wq, V=None):
    """A (M,): projection of phi - phi_0(x; X) onto chi(x - X) on x > 0 (eq. ansatz,
    the antikink's shape mode), both Lorentz-contracted at the speed ``V`` (M,) if
    given (:func:`kink_speed`); nan while X < 1 (the projection is singular at X = 0)."""
    X = np.asarray(X, dtype=float)[:, None]
    V = np.zeros_like(X) if V is None else np.clip(np.abs(np.asarray(V, dtype=float)), 0, 0.9)[:, None]
    g = 1.0 / np.sqrt(1.0 - V * V)
    xr = x[None, :]
    base = np.tanh(g * (xr + X) / SQRT2) - np.tanh(g * (xr - X) / SQRT2) - 1.0
    chi = -shape_mode(g * (xr - X))          # the antikink -tanh carries -chi
    num = ((phi - base) * chi) @ wq
    den = (chi * chi) @ wq
    return np.where(X[:, 0] >= 1.0, num / den, np.nan)


# ----------------------------------------------------------------------------
# collisions
# ----------------------------------------------------------------------------
@dataclass
class Collisions:
    """Results of M collisions ((M,) arrays; bounce_times (M, K) nan padded)."""

    v_in: np.ndarray
    outcome: np.ndarray
    bounces: np.ndarray
    v_out: np.ndarray
    bounce_times: np.ndarray
    t_end: np.ndarray
    energy_error: np.ndarray      # |E(t_end) / E(0) - 1| with absorb=False, else nan (the layer takes energy)
    record: dict | None = None    # t (T,), X (M, T), A (M, T) when asked

    @property
    def one_bounce(self) -> np.ndarray:
        return (self.outcome == ESCAPED) & (self.bounces == 1)


class _Tracks:
    """Per-launch bookkeeping of the live launches: overlaps of phi(0) (bounces), the
    running least-squares sums of X(t) on the outgoing leg, and the previous sample."""

    def __init__(self, phi0, X0: float):
        m = phi0.shape[0]
        self.X0 = X0
        self.inside = np.zeros(m, dtype=bool)     # phi(0) <= 0: the kinks overlap
        self.t_in = np.zeros(m)                   # when the current overlap began
        self.prev_phi0 = phi0.copy()
        self.prev_X = np.full(m, X0)
        self.fit = np.zeros((m, 5))               # n, sum t', sum X, sum t'^2, sum t' X (t' from fit start)
        self.fit_t0 = np.full(m, np.nan)

    def bounces_ended(self, t: float, dt: float, phi0):
        """Advance the overlap state to ``phi0`` at ``t``; returns (indices, times) of the
        overlaps that ended in this step (bounce time: the overlap's middle)."""
        down = (self.prev_phi0 > 0) & (phi0 <= 0)
        up = (self.prev_phi0 <= 0) & (phi0 > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            tc = t - dt * phi0 / (phi0 - self.prev_phi0)       # crossing, linear in t
        self.t_in = np.where(down, tc, self.t_in)
        self.inside |= down
        ended = np.flatnonzero(up & self.inside)
        self.inside &= ~up
        return ended, 0.5 * (self.t_in[ended] + tc[ended])

    def outgoing(self, t: float, X, bounced):
        """Accumulate X(t) on the outgoing leg (X from X0/2 up, after a bounce, reset by
        any return below X0/2); returns the mask of launches back at X0 moving outward."""
        X0 = self.X0
        free = bounced & ~self.inside
        start = free & (X >= 0.5 * X0) & (self.prev_X < 0.5 * X0)
        self.fit_t0 = np.where(start, t, self.fit_t0)
        self.fit[start] = 0.0
        going = free & (X >= 0.5 * X0) & np.isfinite(self.fit_t0)
        tp, Xg = t - self.fit_t0[going], X[going]
        self.fit[going] += np.column_stack([np.ones(tp.size), tp, Xg, tp * tp, tp * Xg])
        self.fit_t0 = np.where(X < 0.5 * X0, np.nan, self.fit_t0)
        return free & (X >= X0) & (X > self.prev_X)

    def slope(self, idx):
        """Least-squares dX/dt on the outgoing leg (nan with fewer than 3 samples)."""
        F = self.fit[idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (F[:, 0] * F[:, 4] - F[:, 1] * F[:, 2]) / (F[:, 0] * F[:, 3] - F[:, 1] ** 2)
        return np.where(F[:, 0] >= 3, s, np.nan)

    def remember(self, phi0, X):
        self.prev_phi0, self.prev_X = phi0, X

    def keep(self, mask):
        for name in ("inside", "t_in", "prev_phi0", "prev_X", "fit", "fit_t0"):
            setattr(self, name, getattr(self, name)[mask])


def collide(v_in, cfg: Phi4Config = DEFAULT_CONFIG, *, record: bool = False, record_every: int = 5,
            absorb: bool = True, max_bounces: int = 64, stop_after: int | None = None) -> Collisions:
    """Collide a kink-antikink pair at each speed of ``v_in`` (M,), all on one grid
    as arrays (M, n+1); launches leave the batch as they escape.

    ``record``: keep X(t) and A(t) every ``record_every`` steps (for Fig. 3 plots).
    ``absorb``: False removes the absorbing layer (then energy is conserved and its
    relative error at the end is returned in ``energy_error``).
    ``stop_after``: end a launch as ``captured`` at its ``stop_after``-th bounce (t_end
    says when); for questions such as "one bounce or more", never for a reported sweep.
    """
    v = np.atleast_1d(np.asarray(v_in, dtype=float))
    m = v.size
    sch = Scheme(cfg, absorb=absorb)
    X0 = cfg.x0
    phi, phi_t = pair(sch.x, v, X0)
    w = sch.to_w(phi, phi_t)
    e0 = sch.energy(phi, phi_t) if not absorb else None

    live = np.arange(m)
    outcome = np.full(m, CAPTURED, dtype=np.int8)
    bounces = np.zeros(m, dtype=int)
    bt = np.full((m, max_bounces), np.nan)
    t_end = np.full(m, cfg.t_max)
    v_out = np.full(m, np.nan)
    energy_error = np.full(m, np.nan)
    tracks = _Tracks(phi[:, 0], X0)

    def energy_error_of(rows, w_rows, e_rows):
        p_, pt_ = sch.fields(w_rows)
        energy_error[rows] = np.abs(sch.energy(p_, pt_) / e_rows - 1.0)

    steps = int(math.ceil(cfg.t_max / cfg.dt - 1e-9))
    rec_t, rec_X, rec_A = [], [], []
    if record:
        rec_t.append(0.0)
        rec_X.append(kink_position(phi, sch.dx))
        rec_A.append(shape_amplitude(phi, rec_X[-1], sch.x, sch.wq, v))
    held = np.abs(v)          # the kinks' speed while they overlap (kink_speed)
    Nv = sch._nonlinear(w)[0]
    for n in range(1, steps + 1):
        if live.size == 0:
            break
        w = sch.step(w, Nv)
        t = n * cfg.dt
        Nv, u, _ = sch._nonlinear(w)       # the next step's first stage gives the fields
        phi = u - 1.0
        X = kink_position(phi, sch.dx)
        phi0 = phi[:, 0]
        ended, t_b = tracks.bounces_ended(t, cfg.dt, phi0)
        for j, tb in zip(ended, t_b):
            g = live[j]
            if bounces[g] < max_bounces:
                bt[g, bounces[g]] = tb
            bounces[g] += 1
        esc = tracks.outgoing(t, X, bounces[live] > 0)
        if record:
            V, held[live] = kink_speed(X, (X - tracks.prev_X) / cfg.dt, held[live])
        if record and n % record_every == 0:
            rt, ra = np.full(m, np.nan), np.full(m, np.nan)
            rt[live] = X
            ra[live] = shape_amplitude(phi, X, sch.x, sch.wq, V)
            rec_t.append(t)
            rec_X.append(rt)
            rec_A.append(ra)
        tracks.remember(phi0, X)
        stop = np.zeros_like(esc) if stop_after is None else (bounces[live] >= stop_after) & ~esc
        if not (esc.any() or stop.any()):
            continue
        g = live[esc]
        outcome[g] = ESCAPED
        v_out[g] = tracks.slope(esc)
        t_end[live[esc | stop]] = t
        if not absorb:
            energy_error_of(live[esc | stop], w[esc | stop], e0[esc | stop])
        keep = ~(esc | stop)
        live, w, Nv = live[keep], w[keep], Nv[keep]
        tracks.keep(keep)
        if not absorb:
            e0 = e0[keep]
    if live.size and not absorb:
        energy_error_of(live, w, e0)
    k = max(1, int(bounces.max(initial=0)))
    rec = None
    if record:
        rec = {"t": np.asarray(rec_t), "X": np.array(rec_X).T, "A": np.array(rec_A).T}
    return Collisions(v, outcome, bounces, v_out, bt[:, :min(k, max_bounces)], t_end, energy_error, rec)
