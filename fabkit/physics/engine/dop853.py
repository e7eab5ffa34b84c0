"""The compiled launch engine's step loop: one launch wholly in compiled code.

This file is a *template*: it is not imported (the names below come from the
model template). :mod:`.codegen` writes it, after a model template
(:mod:`.point`, or a model of its own such as the finite-radius ball), into one
engine module in the user cache, where numba compiles it once per installation
(``cache=True``). The formula's surface functions are compiled separately (C
callbacks, one small module per formula) and reach the engine inside ``P``, which
the engine passes through untouched to the model. The model supplies

    NV, NE            state size and the number of components in the error norm; the
                      state starts (x, y, xd, yd, ...) with (x, y) the point whose events
                      are watched (the ball's contact point)
    rhs(S, P, F, contact)   F = dS/dt for the state S (NV,); returns (z, zd, B, slip): the
                      height, dz/dt, the contact bracket (B <= 0: the model no longer
                      holds) and the slip ratio |F_t| / N (nan for a point). B and slip
                      are needed only where ``contact`` (step ends, not the stages)
    GUARD_ITERS       iterations locating the bracket's zero (<= 4: secant steps, more:
                      Illinois steps to rounding)
    GUARD_OUTCOME(S, P, F)  the outcome where the bracket reached 0 at S (F scratch)
    GUARD_AT_LAUNCH   True: a launch whose bracket is already <= 0 ends at once with
                      that outcome (the ball bridged at the launch, say)
    INIT(S, P)        turns the launch velocity in S[2:4] into the state's
    VEL(S, P)         the reported horizontal velocity (vx, vy) at S
    energy(S, P, inv) the energy per unit (1 + k) m, velocities scaled by inv
    kinetic(S, P, inv)   its kinetic part
    W                 the index of the dissipated work in S
    FULL(P)           True when the model can lose contact (the bracket is checked)
    GT(P)             g~, the gravity the energy scale uses

Method: an embedded explicit Runge-Kutta pair given as data (``A``, ``B``, ``E``,
``E3``: Dormand-Prince 8(5,3), the method of scipy's ``DOP853``, or 5(4), scipy's
``RK45``), with scipy's error norm, step-size controller and initial step, so
``rtol``/``atol`` mean what they mean in scipy. Events are located by Henon's
trick (one RK step with the event's quantity as the independent variable, landing
on it exactly, from the start of the step that crossed it; where that fails, as in a
long step holding a bounce and the escape, by Illinois regula falsi on re-taken
steps), the loss of contact by secant iterations on re-taken steps: each event
carries the step's own local error.
Scalar arithmetic on small per-launch arrays; nothing is allocated in the step loop.

Per-launch outputs (``FO`` floats, ``IO`` ints, ``BT`` bounce times) use the column
indices below; :mod:`.batch` turns them into a ``LaunchResult``.
"""
import math

import numpy as np
from numba import njit

jit = njit(cache=True, nogil=True, error_model="numpy")

# outcomes (physics/outcomes.py) and the output columns
from fabkit.physics.outcomes import BRIDGED, CAPTURED, ESCAPED, FLEW_OFF, LOST_CONTACT  # noqa: E402,F401  (absolute: this text is compiled into a generated module)

F_VOUT, F_T, F_X, F_Y, F_VX, F_VY, F_ZMAX, F_YMAX, F_EERR, F_SLIP = 0, 1, 2, 3, 4, 5, 6, 7, 8, 9
I_OUT, I_NB, I_STEPS, I_REJ, I_STATUS, I_NREC = 0, 1, 2, 3, 4, 5
# the configuration vector C
C_START, C_XLO, C_XHI, C_YLO, C_YHI, C_ZLIM, C_TMAX, C_RTOL, C_ATOL = 0, 1, 2, 3, 4, 5, 6, 7, 8
C_ESTAR, C_TX0, C_TX1, C_TY0, C_TY1, C_MAXSTEPS = 9, 10, 11, 12, 13, 14
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 10.0
TRAP_EVERY = 8      # steps between trapping-energy checks
# Henon kinds: the independent variable
K_X, K_Y, K_VX, K_Z = 0, 1, 2, 3


@jit
def pow2(a):
    """The power of two at or above |a| (1 where a is 0 or not finite)."""
    if math.isfinite(a) and a > 0:
        return 2.0 ** math.ceil(math.log2(a))
    return 1.0


@jit
def rk_step(Y, F0, h, P, A, Bw, ns, K, Ys, Ynew):
    """One step of size h from Y with f(Y) = F0: stages in K[0..ns-1], result in Ynew."""
    n = Y.shape[0]
    for c in range(n):
        K[0, c] = F0[c]
    for s in range(1, ns):
        for c in range(n):
            acc = 0.0
            for j in range(s):
                acc += A[s, j] * K[j, c]
            Ys[c] = Y[c] + h * acc
        rhs(Ys, P, K[s], False)
    for c in range(n):
        acc = 0.0
        for j in range(ns):
            acc += Bw[j] * K[j, c]
        Ynew[c] = Y[c] + h * acc


@jit
def _est(K, Ew, nk, c, scale_c):
    acc = 0.0
    for j in range(nk):
        acc += Ew[j] * K[j, c]
    return acc / scale_c


@jit
def error_norm(K, h, scale, Ew, E3w, nk, dop):
    """scipy's error norm over the NE error components (DOP853: the 5th and 3rd
    order estimates combined, as in Hairer's DOP853)."""
    e5 = 0.0
    e3 = 0.0
    for c in range(NE):
        a = _est(K, Ew, nk, c, scale[c])
        e5 += a * a
        if dop:
            b = _est(K, E3w, nk, c, scale[c])
            e3 += b * b
    if dop:
        denom = e5 + 0.01 * e3
        if denom > 0:
            return abs(h) * e5 / math.sqrt(denom * NE)
        return 0.0
    return abs(h) * math.sqrt(e5 / NE)


@jit
def error_norm_scaled(K, h, scale, Ew, E3w, nk, dop):
    """:func:`error_norm` without overflow (each estimate divided by its largest
    component, a power of two, before squaring): for speeds beyond ~1e100."""
    b5 = 0.0
    b3 = 0.0
    for c in range(NE):
        b5 = max(b5, abs(_est(K, Ew, nk, c, scale[c])))
        if dop:
            b3 = max(b3, abs(_est(K, E3w, nk, c, scale[c])))
    b5 = pow2(b5)
    b3 = pow2(b3)
    e5 = 0.0
    e3 = 0.0
    for c in range(NE):
        a = _est(K, Ew, nk, c, scale[c]) / b5
        e5 += a * a
        if dop:
            b = _est(K, E3w, nk, c, scale[c]) / b3
            e3 += b * b
    if dop:
        M = max(b5, b3)
        r5 = b5 / M
        r3 = b3 / M
        denom = e5 * r5 * r5 + 0.01 * e3 * r3 * r3
        if denom > 0:
            return abs(h) * M * (e5 * r5 * r5) / math.sqrt(denom * NE)
        return 0.0
    return abs(h) * b5 * math.sqrt(e5 / NE)


@jit
def rms(a, scale):
    """sqrt(mean((a / scale)^2)) over the NE components, without overflow."""
    s = 0.0
    for c in range(NE):
        q = a[c] / scale[c]
        s += q * q
    r = math.sqrt(s / NE)
    if math.isfinite(r):
        return r
    big = 0.0
    for c in range(NE):
        q = a[c] / scale[c]
        if not math.isfinite(q):
            return r
        big = max(big, abs(q))
    big = pow2(big)
    s = 0.0
    for c in range(NE):
        q = a[c] / scale[c] / big
        s += q * q
    return big * math.sqrt(s / NE)


@jit
def initial_step(Y, F, P, rtol, atol, t_max, order, scale, Y1, F1, D):
    """scipy's initial step (Hairer's): a huge entry speed gives a tiny first step."""
    for c in range(NE):
        scale[c] = atol + abs(Y[c]) * rtol
    d0 = rms(Y, scale)
    d1 = rms(F, scale)
    if d0 < 1e-5 or d1 < 1e-5:
        h0 = 1e-6
    else:
        h0 = 0.01 * d0 / d1
    for c in range(Y.shape[0]):
        Y1[c] = Y[c] + h0 * F[c]
    rhs(Y1, P, F1, False)
    for c in range(NE):
        D[c] = F1[c] - F[c]
    d2 = rms(D, scale) / h0
    dm = max(d1, d2)
    if dm <= 1e-15:
        h1 = max(1e-6, h0 * 1e-3)
    else:
        h1 = (0.01 / dm) ** (1.0 / (order + 1))
    h = min(min(100 * h0, h1), t_max)
    if math.isfinite(h) and h > 0:
        return h
    if math.isfinite(h0) and h0 > 0:
        return h0
    return 1e-6


@jit
def _henon_g(Z, P, kind, G):
    """d/ds of the augmented state (S, t) with s the event quantity of ``kind``."""
    nv = Z.shape[0] - 1
    z, zd, B, sl = rhs(Z[:nv], P, G[:nv], False)
    if kind == K_Z:
        r = zd
    else:
        r = G[kind]
    for c in range(nv):
        G[c] = G[c] / r
    G[nv] = 1.0 / r


@jit
def henon(Y, t, kind, target, P, A, Bw, ns, KH, Z, Zs, Zout):
    """Henon's trick: one RK step from (Y, t) with the quantity ``kind`` as the
    independent variable, to ``target``. Returns the event time; the state is in
    Zout[:NV]. As accurate as the step (its local error)."""
    nv = Y.shape[0]
    for c in range(nv):
        Z[c] = Y[c]
    Z[nv] = t
    if kind == K_Z:
        z0, zd0, B0, sl0 = rhs(Y, P, Zs[:nv], False)
        s0 = z0
    else:
        s0 = Y[kind]
    ds = target - s0
    _henon_g(Z, P, kind, KH[0])
    for s in range(1, ns):
        for c in range(nv + 1):
            acc = 0.0
            for j in range(s):
                acc += A[s, j] * KH[j, c]
            Zs[c] = Z[c] + ds * acc
        _henon_g(Zs, P, kind, KH[s])
    for c in range(nv + 1):
        acc = 0.0
        for j in range(ns):
            acc += Bw[j] * KH[j, c]
        Zout[c] = Z[c] + ds * acc
    if kind != K_Z:
        Zout[kind] = target   # the independent variable lands on its target exactly
    return Zout[nv]


@jit
def secant(Y, F0, t, h, b0, b1, P, A, Bw, ns, K, Ys, Yt):
    """Time where the bracket B crosses 0 inside the step of size h from Y, on re-taken
    RK steps (each as accurate as the step): GUARD_ITERS secant iterations, or beyond
    four Illinois iterations until the bracket is at rounding. The state is left in Yt."""
    lo, hi = 0.0, 1.0
    blo, bhi = b0, b1
    th = 1.0
    illinois = GUARD_ITERS > 4     # a template constant: numba folds the branches
    side = 0
    for _ in range(GUARD_ITERS):
        th = lo + (hi - lo) * blo / (blo - bhi)
        if math.isfinite(th):
            th = min(max(th, lo), hi)
        else:
            th = 0.5 * (lo + hi)
        rk_step(Y, F0, h * th, P, A, Bw, ns, K, Ys, Yt)
        z, zd, b, sl = rhs(Yt, P, Ys, True)
        if b > 0:
            lo = th
            blo = b
            if illinois and side == 1:
                bhi = 0.5 * bhi
            side = 1
        else:
            hi = th
            bhi = b
            if illinois and side == -1:
                blo = 0.5 * blo
            side = -1
        if illinois and (hi - lo <= 4 * np.spacing(1.0) or b == 0 or abs(b) <= 1e-15):
            break
    return t + h * th


@jit
def _quantity(S, P, kind, Fs):
    """The event quantity of ``kind`` at S (x, y, xd, or the height)."""
    if kind == K_Z:
        return rhs(S, P, Fs, False)[0]
    return S[kind]


@jit
def _sign(a):
    return 1.0 if a > 0 else (-1.0 if a < 0 else (0.0 if a == 0 else a))


@jit
def bracketed(Y, F0, t, h, kind, target, P, A, Bw, ns, K, Ys, Yn, Yt, Fs):
    """Where Henon's step fails (the event's quantity turns inside the step, e.g. a bounce
    and the escape in one long step): the event's time by Illinois regula falsi on
    re-taken RK steps over fractions of the step h. The quantity changes sign over the
    step by construction; each iterate is as accurate as a step; iterations stop when
    the bracket is at rounding. The state is left in Yt."""
    nv = Y.shape[0]
    lo, hi = 0.0, 1.0
    glo = _quantity(Y, P, kind, Fs) - target
    rk_step(Y, F0, h, P, A, Bw, ns, K, Ys, Yt)
    ghi = _quantity(Yt, P, kind, Fs) - target
    th = 1.0
    side = 0
    for _ in range(60):
        tn = (lo * ghi - hi * glo) / (ghi - glo)
        if not (math.isfinite(tn) and tn > lo and tn < hi):
            tn = 0.5 * (lo + hi)
        rk_step(Y, F0, h * tn, P, A, Bw, ns, K, Ys, Yn)
        gn = _quantity(Yn, P, kind, Fs) - target
        th = tn
        for c in range(nv):
            Yt[c] = Yn[c]
        if _sign(gn) == _sign(glo):
            lo = tn
            glo = gn
            if side == 1:
                ghi = 0.5 * ghi
            side = 1
        else:
            hi = tn
            ghi = gn
            if side == -1:
                glo = 0.5 * glo
            side = -1
        if hi - lo <= 4 * np.spacing(1.0) or gn == 0:
            break
    if kind != K_Z:
        Yt[kind] = target
    return t + h * th


@jit
def locate(Y, F0, t, h, kind, target, P, A, Bw, ns, K, KH, Z, Zs, Zout, Yn, Yt, Fs):
    """The time of an event inside the step of size h from (Y, t): Henon's step, and
    where it fails (outside the step, not finite) the bracketed fallback. Returns
    (time, ok); the state is in Zout[:NV]."""
    nv = Y.shape[0]
    te = henon(Y, t, kind, target, P, A, Bw, ns, KH, Z, Zs, Zout)
    if math.isfinite(te) and te >= t and te <= t + h + 1e-9 * h and _all_finite(Zout, NE):
        return te, True
    tb = bracketed(Y, F0, t, h, kind, target, P, A, Bw, ns, K, Zs[:nv], Yn, Yt, Fs)
    if math.isfinite(tb) and _all_finite(Yt, NE):
        for c in range(nv):
            Zout[c] = Yt[c]
        return tb, True
    return te, False


@jit
def dip(Y, F0, t, h, start, P, A, Bw, ns, K, KH, Z, Zs, Zout, Yn, Yt, Fs):
    """A step from (Y, t) of size h over which xd turns from - to +: the time where x
    first reaches ``start`` inside it, or inf when the minimum of x stays above it.
    The minimum is located like a bounce (Henon's step to xd = 0); where it lies at or
    beyond the start line, the crossing before it by Illinois regula falsi on re-taken
    steps over [t, t_min] (x - start changes sign there). Each is as accurate as a step;
    the crossing's state is left in Zout[:NV]."""
    nv = Y.shape[0]
    tm, ok = locate(Y, F0, t, h, K_VX, 0.0, P, A, Bw, ns, K, KH, Z, Zs, Zout, Yn, Yt, Fs)
    if not (ok and tm >= t and tm <= t + h + 1e-9 * h):
        # the minimum's time not found: the step's end stands for it
        tm = t + h
        rk_step(Y, F0, h, P, A, Bw, ns, K, Zs[:nv], Zout[:nv])
    if not Zout[0] <= start:
        return np.inf
    hm = tm - t
    rk_step(Y, F0, hm, P, A, Bw, ns, K, Zs[:nv], Yt)
    if not Yt[0] <= start:
        # the re-taken step to t_min ends above the line by a rounding: the minimum is the crossing
        Zout[0] = start
        return tm
    te = bracketed(Y, F0, t, hm, K_X, start, P, A, Bw, ns, K, Zs[:nv], Yn, Yt, Fs)
    if not (math.isfinite(te) and _all_finite(Yt, NE)):
        Zout[0] = start
        return tm
    for c in range(nv):
        Zout[c] = Yt[c]
    return te


@jit
def _all_finite(a, n):
    for c in range(n):
        if not math.isfinite(a[c]):
            return False
    return True


@jit
def _record(TR, IO, t, S, F):
    n = IO[I_NREC]
    if n < TR.shape[0]:
        TR[n, 0] = t
        TR[n, 1] = S[0]
        TR[n, 2] = S[1]
        TR[n, 3] = S[2]
        TR[n, 4] = S[3]
        TR[n, 5] = F[2]
        TR[n, 6] = F[3]
    IO[I_NREC] = n + 1


@jit
def _fmax(a, b):
    """max ignoring nan (numpy's fmax)."""
    if a != a:
        return b
    if b != b:
        return a
    return max(a, b)


@jit
def _finish(S, t, outcome, status, P, E0, kin0, inv, zmax, zmin, ymax, smax, FO, IO, F):
    """The launch's summary at its final state S, time t."""
    z, zd, B, sl = rhs(S, P, F, True)
    IO[I_OUT] = outcome
    IO[I_STATUS] = status
    vx, vy = VEL(S, P)
    FO[F_T] = t
    FO[F_X] = S[0]
    FO[F_Y] = S[1]
    FO[F_VX] = vx
    FO[F_VY] = vy
    FO[F_VOUT] = abs(vx) if outcome == ESCAPED else np.nan
    # the slip ratio at the end counts, except where contact is lost or the ball bridges
    FO[F_SLIP] = smax if outcome == LOST_CONTACT or outcome == BRIDGED else _fmax(smax, sl)
    zmax = max(zmax, z)
    zmin = min(zmin, z)
    FO[F_ZMAX] = zmax
    FO[F_YMAX] = max(ymax, abs(S[1]))
    i2 = inv * inv
    E = energy(S, P, inv)
    escale = kin0 + GT(P) * (zmax - zmin) * i2
    FO[F_EERR] = abs(E + S[W] * i2 - E0) / max(escale, 1e-300)


@jit
def _start_end(Y, P, outcome, status, z, sl, FO, IO, F):
    """A launch that ends where it starts (status 3: derivatives that overflow; or the
    bracket already down: the ball bridged at the launch, say)."""
    IO[I_OUT] = outcome
    IO[I_STATUS] = status
    vx, vy = VEL(Y, P)
    FO[F_T] = 0.0
    FO[F_X] = Y[0]
    FO[F_Y] = Y[1]
    FO[F_VX] = vx
    FO[F_VY] = vy
    FO[F_VOUT] = np.nan
    FO[F_ZMAX] = z
    FO[F_YMAX] = abs(Y[1])
    FO[F_EERR] = 0.0
    FO[F_SLIP] = sl


@jit
def launch(v, y0, vy0, P, C, A, Bw, Ew, E3w, ns, order, dop, BT, FO, IO, TR, record, WS):
    """One launch at x = C[C_START], y = y0 with velocity (v, vy0), to its end.

    BT (K,) bounce times (nan padded); FO, IO the summaries; TR (cap, 7) the step
    points when ``record``; WS the scratch arrays of :func:`workspace`.
    """
    nv = NV
    K, KH, Y, F, Ynew, Ys, scale, Yev, Z, Zout, Fnew, Yn, Yt, Fs = WS
    for c in range(nv):
        Y[c] = 0.0
    Y[0] = C[C_START]
    Y[1] = y0
    Y[2] = v
    Y[3] = vy0
    INIT(Y, P)
    for j in range(BT.shape[0]):
        BT[j] = np.nan
    kkeep = BT.shape[0]
    IO[I_NREC] = 0
    t_max = C[C_TMAX]
    rtol = C[C_RTOL]
    atol = C[C_ATOL]
    start = C[C_START]
    x_lo, x_hi, y_lo, y_hi, z_lim = C[C_XLO], C[C_XHI], C[C_YLO], C[C_YHI], C[C_ZLIM]
    e_star = C[C_ESTAR]
    max_steps = C[C_MAXSTEPS]
    full = FULL(P)
    z, zd, B, smax = rhs(Y, P, F, True)
    vmax = max(abs(Y[2]), abs(Y[3]))
    inv = 1.0 / pow2(vmax) if vmax > 1e100 else 1.0
    E0 = energy(Y, P, inv)
    kin0 = kinetic(Y, P, inv)
    zmax = z
    zmin = z
    ymax = abs(Y[1])
    IO[I_NB] = 0
    IO[I_STEPS] = 0
    IO[I_REJ] = 0
    if record:
        _record(TR, IO, 0.0, Y, F)
    if not _all_finite(F, NE):
        # derivatives that overflow at the launch: no step can be taken, and no surface
        # holds such a ball: flew_off at once, status 3
        _start_end(Y, P, FLEW_OFF, 3, z, np.nan, FO, IO, Fs)
        return
    if GUARD_AT_LAUNCH and B <= 0:
        # the model does not hold at the launch (the ball bridged there, say): it ends there
        _start_end(Y, P, GUARD_OUTCOME(Y, P, Fs), 0, z, smax, FO, IO, Fs)
        return
    t = 0.0
    h = initial_step(Y, F, P, rtol, atol, t_max, order, scale, Ynew, K[1], K[2])
    expo = -1.0 / (order + 1)
    nb = 0
    steps = 0
    rej = 0
    it = 0
    was_rejected = False
    while True:
        it += 1
        hstep = min(h, t_max - t)
        last = hstep >= t_max - t
        rk_step(Y, F, hstep, P, A, Bw, ns, K, Ys[:nv], Ynew)
        zn, zdn, Bn, sln = rhs(Ynew, P, K[ns], True)
        for c in range(NE):
            scale[c] = atol + max(abs(Y[c]), abs(Ynew[c])) * rtol
        err = error_norm(K, hstep, scale, Ew, E3w, ns + 1, dop)
        for c in range(nv):
            Fnew[c] = K[ns, c]     # (K is scratch for the event location below)
        okK = _all_finite(Ynew, NE) and _all_finite(Fnew, NE)
        if okK and not math.isfinite(err):
            err = error_norm_scaled(K, hstep, scale, Ew, E3w, ns + 1, dop)
        finite = okK and math.isfinite(err)
        acc = finite and err <= 1.0
        if err == 0.0:
            fac = MAX_FACTOR
        elif finite:
            fac = SAFETY * err ** expo
        else:
            fac = SAFETY
        if acc:
            steps += 1
            f2 = min(MAX_FACTOR, fac)
            if was_rejected:
                f2 = min(1.0, f2)
            h = hstep * f2
        else:
            rej += 1
            h = hstep * (max(MIN_FACTOR, fac) if finite else MIN_FACTOR)
        was_rejected = not acc

        term = False
        if acc:
            tnew = t + hstep
            t_ev = np.inf
            code = -1
            # terminal candidates: the earliest located one wins
            for q in range(6):
                kind = -1
                target = 0.0
                oc = FLEW_OFF
                if q == 0 and Y[0] > start and Ynew[0] <= start and Ynew[2] < 0:
                    kind, target, oc = K_X, start, ESCAPED
                elif q == 1 and zn >= z_lim and z < z_lim:
                    kind, target = K_Z, z_lim
                elif q == 2 and Ynew[0] >= x_hi and Y[0] < x_hi:
                    kind, target = K_X, x_hi
                elif q == 3 and Ynew[0] <= x_lo and Y[0] > x_lo:
                    kind, target = K_X, x_lo
                elif q == 4 and Ynew[1] >= y_hi and Y[1] < y_hi:
                    kind, target = K_Y, y_hi
                elif q == 5 and Ynew[1] <= y_lo and Y[1] > y_lo:
                    kind, target = K_Y, y_lo
                if kind < 0:
                    continue
                te, ok = locate(Y, F, t, hstep, kind, target, P, A, Bw, ns, K, KH, Z, Ys, Zout, Yn, Yt, Fs)
                if not ok:
                    te = tnew
                    for c in range(nv):
                        Zout[c] = Ynew[c]
                if te < t_ev:
                    t_ev = te
                    code = oc
                    for c in range(nv):
                        Yev[c] = Zout[c]
            if Y[2] < 0 and Ynew[2] >= 0 and Y[0] > start:
                # a minimum of x inside the step: the start line crossed and crossed back
                # within one step (however short the excursion) is an escape too
                te = dip(Y, F, t, hstep, start, P, A, Bw, ns, K, KH, Z, Ys, Zout, Yn, Yt, Fs)
                if te < t_ev:
                    t_ev = te
                    code = ESCAPED
                    for c in range(nv):
                        Yev[c] = Zout[c]
            if full and Bn <= 0 and B > 0:
                te = secant(Y, F, t, hstep, B, Bn, P, A, Bw, ns, K, Ys[:nv], Zout[:nv])
                if te < t_ev:
                    t_ev = te
                    code = GUARD_OUTCOME(Zout[:nv], P, Fs)
                    for c in range(nv):
                        Yev[c] = Zout[c]
            if Y[2] > 0 and Ynew[2] <= 0:
                # a bounce (maximum of x): not terminal; counts only before a terminal event
                tb, ok = locate(Y, F, t, hstep, K_VX, 0.0, P, A, Bw, ns, K, KH, Z, Ys, Zout, Yn, Yt, Fs)
                if not (ok and tb <= tnew + 1e-9 * hstep):
                    tb = tnew
                if code < 0 or tb <= t_ev:
                    if nb < kkeep:
                        BT[nb] = tb
                    nb += 1
            term = code >= 0
            if not term:
                for c in range(nv):
                    Y[c] = Ynew[c]
                    F[c] = Fnew[c]
                z, B = zn, Bn
                t = tnew
                zmax = max(zmax, z)
                zmin = min(zmin, z)
                ymax = max(ymax, abs(Y[1]))
                smax = _fmax(smax, sln)
                if record:
                    _record(TR, IO, t, Y, F)
            else:
                IO[I_NB] = nb
                IO[I_STEPS] = steps
                IO[I_REJ] = rej
                _finish(Yev[:nv], t_ev, code, 0, P, E0, kin0, inv, zmax, zmin, ymax, smax, FO, IO, Ys[:nv])
                if record:
                    _record(TR, IO, t_ev, Yev, Ys)
                return
        captured = acc and last
        status = 0
        if (not captured and acc and e_star == e_star and it % TRAP_EVERY == 0 and inv == 1.0
                and Y[0] > C[C_TX0] and Y[0] < C[C_TX1] and Y[1] > C[C_TY0] and Y[1] < C[C_TY1]):
            # energy below every exit (trap.py): captured for good
            if energy(Y, P, 1.0) < e_star:
                captured = True
                status = 4
        if not captured:
            if steps + rej >= max_steps:
                status = 1
            elif not acc and h <= 10.0 * np.spacing(abs(t)):
                status = 1    # step-size underflow: the next step would not move t
        if captured or status == 1:
            IO[I_NB] = nb
            IO[I_STEPS] = steps
            IO[I_REJ] = rej
            _finish(Y, t, CAPTURED, status, P, E0, kin0, inv, zmax, zmin, ymax, smax, FO, IO, Ys[:nv])
            return


@jit
def workspace(ns):
    """Scratch arrays of one launch: K (ns + 1, NV) stages, KH (ns + 1, NV + 1) Henon
    stages, and the vectors Y, F, Ynew, Ys, scale, Yev, Z, Zout, Fnew, Yn, Yt, Fs."""
    return (np.empty((ns + 1, NV)), np.empty((ns + 1, NV + 1)), np.empty(NV), np.empty(NV), np.empty(NV),
            np.empty(NV + 1), np.empty(NV), np.empty(NV + 1), np.empty(NV + 1), np.empty(NV + 1), np.empty(NV),
            np.empty(NV), np.empty(NV), np.empty(NV))


@jit
def run_batch(V, Y0, VY0, P, C, A, Bw, Ew, E3w, ns, order, dop, BT, FO, IO, TR, record):
    """Launches V[i] (y0 Y0[i], vy0 VY0[i]) one after the other; row i of BT, FO, IO
    (and TR when ``record``) receives launch i. Releases the GIL: threads may run
    disjoint slices at once, with results identical to one run (launches share nothing)."""
    WS = workspace(ns)
    for i in range(V.shape[0]):
        launch(V[i], Y0[i], VY0[i], P, C, A, Bw, Ew, E3w, ns, order, dop, BT[i], FO[i], IO[i],
               TR[i], record, WS)
