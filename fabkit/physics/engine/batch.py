"""Drivers of the compiled engine: load (or build) the engine of a problem, and run
batches of launches serially or on threads.

Every launch runs wholly in compiled code (:mod:`.dop853`), sharing nothing with
the others, so a launch's result is bit-identical whatever the batch it is in,
the block size and the number of threads. Threads run disjoint blocks of
launches with the GIL released (numba ``nogil``): no OpenMP pool, so no
spin-waiting threads on a loaded machine.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from . import codegen

#: launches per block between progress reports (results do not depend on it)
BLOCK = 2048
#: CPU seconds of the first compile of an engine with its formula, measured on the 2-core
#: machine from a fresh clone with an empty cache (the finite ball's 12.5-12.7 s, the point
#: model's 10.6 s: ``python benchmarks/bench_first_run.py``); replaced by the last measured
#: figure, stored in the cache
COMPILE_GUESS_S = 12.5

_LOADED: dict = {}          # module path -> module
_BY_FNS: dict = {}          # id(fns) -> (fns, Formula, surface module path)
_LOCK = threading.RLock()


@dataclass(frozen=True)
class Engine:
    """A loaded engine: the compiled step loop of a model template, and the
    compiled surface functions of one formula."""

    module: object            # the engine module (run_batch)
    surface: object           # the formula's module (its C callbacks)
    formula: codegen.Formula
    template: codegen.Template

    def params(self, problem) -> tuple:
        """P: (Pa, surface functions...) with Pa the model's run-time parameters (see
        the template: point.py, ball.py), then the surface's."""
        tail = MODEL_TAIL.get(self.template.name)
        Pa = np.array([*MODEL_PARAMS[self.template.name](problem), *self.formula.values,
                       *(tail(problem) if tail else ())], dtype=float)
        return (Pa, *self.params_functions())

    def params_functions(self) -> tuple:
        return tuple(getattr(self.surface, name) for name, _ in self.template.functions)


def _point_params(problem) -> list:
    """point.py's Pa[:4]: g~, mu, mu_nl, 1 for the full model (0 simplified)."""
    return [problem.g_tilde, float(problem.damping), float(problem.nonlinear_damping),
            1.0 if problem.model == "full" else 0.0]


def _ball_params(problem) -> list:
    """ball.py's Pa[:8]: g, k, r, mu, c_rr, friction, v_s, g~ (physics/ball.Params)."""
    from ..ball import Params

    b = Params.of(problem)
    return [b.g, b.k, b.r, b.mu, b.c_rr, b.friction, b.v_s, problem.g_tilde]


def _point_tail(problem) -> list:
    """point.py's Pa[-3:], after the surface's parameters: c_rr / (1 + k), v_s, g (the
    rolling resistance; models.py's module doc)."""
    from ..models import rolling_smoothing_speed

    crr = float(problem.rolling_resistance)
    return [crr / (1.0 + problem.k), rolling_smoothing_speed(problem), float(problem.g)]


#: each template's run-time model parameters from a problem (MODEL_TAIL: after the surface's)
MODEL_PARAMS = {"point": _point_params, "ball": _ball_params}
MODEL_TAIL = {"point": _point_tail}


def _formula(fns, template=codegen.POINT):
    """(Formula, surface module path) of surface functions under a template, memoized."""
    hit = _BY_FNS.get((id(fns), template.name))
    if hit is not None and hit[0] is fns:
        return hit[1], hit[2]
    known = codegen.known_surface(fns, template)     # a known formula: no sympy
    if known is not None:
        f, path = known
    else:
        f = codegen.formula(fns)
        path = codegen.write_surface(f, template)
        codegen.remember_surface(fns, template, f, path)
    with _LOCK:
        if len(_BY_FNS) > 256:
            _BY_FNS.clear()
        _BY_FNS[(id(fns), template.name)] = (fns, f, path)
    return f, path


def _cached(path, entry: str) -> bool:
    if str(path) in _LOADED:
        return True
    folder = path.parent / "__pycache__"
    return folder.is_dir() and any(folder.glob(f"{path.stem}.{entry}-*.nbi"))


def is_compiled(problem) -> bool:
    """True when the engine and ``problem``'s surface are in the cache (they load quickly)."""
    tpl = codegen.template_of(problem.model)
    _, path = _formula(problem.fns, tpl)
    return _cached(codegen.write_engine(tpl), "run_batch") and _cached(path, tpl.functions[0][0])


def compile_estimate() -> float:
    """CPU seconds the last first-time compile of an engine and its formula took here (a
    measured guess before any)."""
    try:
        return float((codegen.cache_dir() / "compile_seconds").read_text())
    except (OSError, ValueError):
        return COMPILE_GUESS_S


def engine(problem, notify=None) -> Engine:
    """The compiled engine for ``problem``, built and compiled on first use.

    The model picks the template (:func:`codegen.template_of`: the point's or the
    finite ball's); the step loop, the events and these drivers are shared. Each
    template's engine compiles once per installation, each formula's surface
    functions once per template (a second or two); later runs load both from the
    cache. ``notify(message)`` is called before a first-time compile (the commands
    print ``compiling the simulator for this surface (once, about N s)``).
    """
    tpl = codegen.template_of(problem.model)
    f, spath = _formula(problem.fns, tpl)
    epath = codegen.write_engine(tpl)
    with _LOCK:
        cold_e = not _cached(epath, "run_batch")
        cold_s = not _cached(spath, tpl.functions[0][0])
        if (cold_e or cold_s) and notify is not None:
            est = compile_estimate() if cold_e else 2.0
            notify(f"compiling the simulator for this surface (once, about {max(1, round(est))} s)")
        t0 = time.process_time()      # CPU, as the estimate is stated: the load does not inflate it
        smod = _LOADED.get(str(spath)) or _import(spath)
        emod = _LOADED.get(str(epath))
        eng = Engine(emod, smod, f, tpl)
        if emod is None:
            emod = _import(epath)
            eng = Engine(emod, smod, f, tpl)
            _warm(eng)
            if cold_e:
                _store_estimate(time.process_time() - t0)
        _LOADED[str(spath)] = smod
        _LOADED[str(epath)] = emod
    return eng


def _import(path):
    import importlib.util
    import sys

    from ... import numba_start  # noqa: F401  (numba's short start-up for cached code)

    name = path.stem
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _store_estimate(seconds: float) -> None:
    codegen.replace_quietly(codegen.cache_dir() / "compile_seconds", f"{seconds:.1f}\n")


# ----------------------------------------------------------------------------
# tableaux as arrays
# ----------------------------------------------------------------------------
_TABS: dict = {}


def tableau_arrays(method: str):
    """(A (S, S), B (S,), E (S + 1,), E3 (S + 1,), S, order, dop) of 'DOP853' | 'RK45'
    from scipy's own coefficients (:func:`fabkit.physics.rk.tableau`)."""
    if method not in _TABS:
        from ..rk import tableau

        t = tableau(method)
        n = t.n_stages
        A = np.zeros((n, n))
        for s, row in enumerate(t.A):
            for j, a in row:
                A[s, j] = a
        B = np.zeros(n)
        for j, b in t.B:
            B[j] = b
        E = np.zeros(n + 1)
        for j, e in t.E:
            E[j] = e
        E3 = np.zeros(n + 1)
        for j, e in t.E3:
            E3[j] = e
        _TABS[method] = (A, B, E, E3, n, t.order, bool(t.E3))
    return _TABS[method]


def _warm(eng: Engine) -> None:
    """Compile (or load) the batch entry point with its one signature: zero launches."""
    A, B, E, E3, n, order, dop = tableau_arrays("DOP853")
    z = np.zeros(0)
    P = (np.zeros(eng.template.n_model_params + 4), *eng.params_functions())
    eng.module.run_batch(z, z, z, P, np.zeros(16), A, B, E, E3, n, order, dop,
                         np.zeros((0, 8)), np.zeros((0, N_FLOAT)), np.zeros((0, N_INT), dtype=np.int64),
                         np.zeros((0, 0, 7)), False)


# ----------------------------------------------------------------------------
# runs
# ----------------------------------------------------------------------------
N_FLOAT, N_INT = 10, 6


def config(problem, rtol, atol, t_max, max_steps, e_star) -> np.ndarray:
    """C: start, the shrunk footprint, z limit, t_max, tolerances, trapping energy and box."""
    from ..trap import region

    m = float(problem.margin)
    tx0, tx1, ty0, ty1 = region(problem)
    return np.array([
        float(problem.start), problem.x_range[0] + m, problem.x_range[1] - m, problem.y_range[0] + m,
        problem.y_range[1] - m, float(problem.top) - m, t_max, rtol, atol,
        np.nan if e_star is None else float(e_star), tx0, tx1, ty0, ty1, float(max_steps), 0.0], dtype=float)


def run(eng: Engine, problem, v, y0, vy0, *, rtol, atol, t_max, max_steps, k_keep, method="DOP853",
        record=False, e_star=None, threads=1, progress=None, rec_cap=4096):
    """Launch every v[i] (y0[i], vy0[i]); returns (FO (N, 10), IO (N, 6), BT (N, K), TR).

    ``threads`` > 1 runs blocks of launches on that many threads; ``progress(done)``
    is called after each block. Results do not depend on either.
    """
    A, B, E, E3, ns, order, dop = tableau_arrays(method)
    P = eng.params(problem)
    C = config(problem, rtol, atol, t_max, max_steps, e_star)
    n = len(v)
    FO = np.full((n, N_FLOAT), np.nan)
    IO = np.zeros((n, N_INT), dtype=np.int64)
    BT = np.full((n, k_keep), np.nan)
    cap = rec_cap if record else 0
    TR = np.zeros((n, cap, 7))
    fn = eng.module.run_batch

    def block(a, b):
        fn(v[a:b], y0[a:b], vy0[a:b], P, C, A, B, E, E3, ns, order, dop, BT[a:b], FO[a:b], IO[a:b], TR[a:b],
           bool(record))

    size = BLOCK if progress is not None or threads > 1 else max(n, 1)
    if threads > 1 and n > 1:
        size = max(1, min(size, math.ceil(n / (4 * threads))))
    pieces = [(a, min(a + size, n)) for a in range(0, n, size)]
    if threads > 1 and len(pieces) > 1:
        from concurrent.futures import ThreadPoolExecutor

        done = 0
        with ThreadPoolExecutor(max_workers=threads) as pool:
            for (a, b), _ in zip(pieces, pool.map(lambda ab: block(*ab), pieces)):
                done += b - a
                if progress is not None:
                    progress(done)
    else:
        for a, b in pieces:
            block(a, b)
            if progress is not None:
                progress(b)
    trajs = None
    if record:
        trajs = []
        for i in range(n):
            m = int(IO[i, 5])
            if m > cap:   # more step points than the buffer: run this launch again, larger
                return run(eng, problem, v, y0, vy0, rtol=rtol, atol=atol, t_max=t_max, max_steps=max_steps,
                           k_keep=k_keep, method=method, record=True, e_star=e_star, threads=1,
                           progress=None, rec_cap=2 * m)
            a = TR[i, :m]
            trajs.append({"t": a[:, 0].copy(), "x": a[:, 1].copy(), "y": a[:, 2].copy(), "vx": a[:, 3].copy(),
                          "vy": a[:, 4].copy(), "ax": a[:, 5].copy(), "ay": a[:, 6].copy()})
    return FO, IO, BT, trajs
