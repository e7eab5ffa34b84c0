"""The fits' integrator: lanes of one model carried from one time to a camera's frame
times, wholly in compiled code.

This file is a *template*, like :mod:`.dop853`: :mod:`.fit` writes it after a model
template (:mod:`.point`, :mod:`.ball`) and the step loop's source (whose ``rk_step``,
``error_norm`` and ``initial_step`` it calls) into one module in the user cache,
compiled once per installation. The launch engine's own module is not changed.

``frames`` carries m lanes, each with its own start and its own run-time parameters
(a row of ``PA``: the damping, the rolling resistance...), through the same steps:

* every lane takes the same steps, chosen on the largest of the lanes' errors
  (scipy's error norm, step controller and initial step, ``rtol``/``atol`` as in
  scipy): each lane is accurate to rtol, and lanes that differ by a small change of a
  start value or a coefficient are one discrete map at nearby points, so a finite
  difference between them is the derivative of that map ("internal numerical
  differentiation", Bock 1981), smooth in the change, without the noise of two step
  sequences (a finite difference over separately adapted steps has an error of
  order rtol / (relative step));
* each step ends exactly on the next frame time when it would pass it (the frames
  are outputs of the integration, not interpolated);
* time runs forward or backward (the frame times all after ``t0``, or all before).

Out: ``OUT[i, k]`` the state of lane i at frame k and ``DOUT[i, k]`` its derivative
(the model's right-hand side there), ``IO`` = (status, steps, rejected): status 0
done, 1 the step budget ``max_steps`` ran out, 2 a state or derivative not finite (a
trial state off the surface's finite values), 3 the step size underflowed.
"""


@jit
def frames(S0, PA, fn, t0, TE, rtol, atol, max_steps, A, Bw, Ew, E3w, ns, order, dop, OUT, DOUT, IO):
    """Lanes S0 (m, k <= NV; missing components 0) with parameters PA (m, n_pa) from t0
    to the frame times TE (monotonic, from t0 on): OUT, DOUT (m, len(TE), NV)."""
    m = S0.shape[0]
    nt = TE.shape[0]
    nv = NV
    K = np.empty((m, ns + 1, NV))
    Y = np.zeros((m, NV))
    F = np.empty((m, NV))
    Ynew = np.empty((m, NV))
    Ys = np.empty(NV)
    scale = np.empty(NV)
    Y1 = np.empty(NV)
    F1 = np.empty(NV)
    D = np.empty(NV)
    IO[0] = 0
    IO[1] = 0
    IO[2] = 0
    for i in range(m):
        for c in range(S0.shape[1]):
            Y[i, c] = S0[i, c]
        rhs(Y[i], (PA[i], fn), F[i], False)
    t = t0
    j = 0
    while j < nt and TE[j] == t0:
        for i in range(m):
            for c in range(nv):
                OUT[i, j, c] = Y[i, c]
                DOUT[i, j, c] = F[i, c]
        j += 1
    if j >= nt:
        return
    d = 1.0 if TE[nt - 1] >= t0 else -1.0
    span = abs(TE[nt - 1] - t0)
    h = initial_step(Y[0], F[0], (PA[0], fn), rtol, atol, span, order, scale, Y1, F1, D)
    expo = -1.0 / (order + 1)
    steps = 0
    rej = 0
    was_rejected = False
    while j < nt:
        rem = abs(TE[j] - t)
        hs = min(h, rem)
        land = hs >= rem
        err = 0.0
        finite = True
        for i in range(m):
            Pi = (PA[i], fn)
            rk_step(Y[i], F[i], d * hs, Pi, A, Bw, ns, K[i], Ys, Ynew[i])
            rhs(Ynew[i], Pi, K[i, ns], False)
            for c in range(NE):
                scale[c] = atol + max(abs(Y[i, c]), abs(Ynew[i, c])) * rtol
            e = error_norm(K[i], hs, scale, Ew, E3w, ns + 1, dop)
            err = max(err, e) if e == e else np.nan
            for c in range(nv):
                finite = finite and math.isfinite(Ynew[i, c]) and math.isfinite(K[i, ns, c])
        finite = finite and math.isfinite(err)
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
            if land and f2 >= 1.0:
                h = max(h, hs * f2)     # a step cut short to land on a frame does not shrink the next
            else:
                h = hs * f2
            ok = True
            for i in range(m):
                for c in range(nv):
                    Y[i, c] = Ynew[i, c]
                    F[i, c] = K[i, ns, c]
                    ok = ok and math.isfinite(Y[i, c]) and math.isfinite(F[i, c])
            if not ok:
                IO[0] = 2
                break
            if land:
                t = TE[j]
                while j < nt and TE[j] == t:
                    for i in range(m):
                        for c in range(nv):
                            OUT[i, j, c] = Y[i, c]
                            DOUT[i, j, c] = F[i, c]
                    j += 1
            else:
                t = t + d * hs
        else:
            rej += 1
            h = hs * (max(MIN_FACTOR, fac) if finite else MIN_FACTOR)
        was_rejected = not acc
        if steps + rej >= max_steps:
            IO[0] = 1
            break
        if not acc and h <= 10.0 * np.spacing(abs(t)):
            IO[0] = 3
            break
    IO[1] = steps
    IO[2] = rej
