"""The fits' side of the compiled engine: lanes of a model, each with its own start and
its own losses, carried to a camera's frame times (:mod:`.frames`, a template).

Its module is written once per model template to the user cache beside the launch
engine's (the model template, the step loop, then :mod:`.frames`), under a key of
those three sources and the versions; the launch engine's module, its key and its
results are untouched. The formula's surface functions are the launch engine's own
compiled callbacks (:func:`.batch.engine`), so a surface compiles once for both.

Per-lane parameters: the template's run-time vector (``Engine.params``) with the
viscous damping mu and the rolling resistance c_rr replaced lane by lane (the point
template: Pa[1] = mu, Pa[-3] = c_rr / (1 + k); the ball's: Pa[3] = mu, Pa[4] = c_rr).
"""

from __future__ import annotations

import threading

import numpy as np

from . import codegen

FRAMES_TEMPLATE = "frames.py"
_LOCK = threading.RLock()
_MODULES: dict = {}


def _key(template) -> str:
    return codegen._digest(["frames", template.name, codegen._source(template.source),
                            codegen._source(codegen.ENGINE_TEMPLATE), codegen._source(FRAMES_TEMPLATE),
                            *codegen._versions()])


def _generate(template) -> str:
    from ... import __version__

    parts = [codegen._HEADER.format(version=__version__, what=f"the fits' integrator, {template.name} template")]
    for src in (template.source, codegen.ENGINE_TEMPLATE, FRAMES_TEMPLATE):
        parts.append(f"# ---- {src} " + "-" * 60 + "\n" + codegen._source(src))
    return "\n\n".join(parts)


def module(template):
    """The compiled frames module of a model template (written and imported once)."""
    with _LOCK:
        mod = _MODULES.get(template.name)
        if mod is None:
            from .batch import _import

            path = codegen._write_once(codegen.cache_dir() / f"fk_frames_{template.name}_{_key(template)}.py",
                                       lambda: _generate(template))
            mod = _import(path)
            _MODULES[template.name] = mod
    return mod


def lane_params(eng, problem, mu, crr) -> np.ndarray:
    """PA (m, n_pa): the engine's run-time parameters of ``problem`` with each lane's
    viscous damping ``mu`` (m,) and rolling resistance ``crr`` (m,)."""
    Pa = eng.params(problem)[0]
    m = len(mu)
    PA = np.array(np.broadcast_to(Pa, (m, Pa.size)), dtype=float, order="C")
    if eng.template.name == "ball":
        PA[:, 3] = mu
        PA[:, 4] = crr
    else:
        PA[:, 1] = mu
        PA[:, -3] = np.asarray(crr, dtype=float) / (1.0 + float(problem.k))
    return PA


_ENGINES: dict = {}


def _engine(problem):
    """The launch engine of ``problem``'s formula and model, memoized on the surface
    functions (the fits call this hundreds of times)."""
    key = (id(problem.fns), problem.model == "ball")
    hit = _ENGINES.get(key)
    if hit is not None and hit[0] is problem.fns:
        return hit[1]
    from .batch import engine

    eng = engine(problem)
    with _LOCK:
        if len(_ENGINES) > 64:
            _ENGINES.clear()
        _ENGINES[key] = (problem.fns, eng)
    return eng


def frames(problem, S0, mu, crr, t0: float, t_eval, *, rtol: float, atol: float, max_steps: int):
    """Carry lanes S0 (m, k) (the model's state without its dissipated work: 4 for a
    point, 5 for the ball) with damping ``mu`` (m,) and rolling resistance ``crr`` (m,)
    from t0 to the times ``t_eval`` (monotonic from t0, forward or backward). Returns
    (Y (m, n, NV), dY (m, n, NV), status, steps, rejected): status 0 done, 1 the step
    budget ran out, 2 a state not finite, 3 the step size underflowed."""
    from .batch import tableau_arrays

    eng = _engine(problem)
    mod = module(eng.template)
    A, B, E, E3, ns, order, dop = tableau_arrays("DOP853")
    S0 = np.ascontiguousarray(S0, dtype=float)
    m = S0.shape[0]
    PA = lane_params(eng, problem, np.asarray(mu, dtype=float).reshape(m), np.asarray(crr, dtype=float).reshape(m))
    te = np.ascontiguousarray(t_eval, dtype=float)
    nv = int(mod.NV)
    OUT = np.full((m, te.size, nv), np.nan)
    DOUT = np.full((m, te.size, nv), np.nan)
    IO = np.zeros(3, dtype=np.int64)
    fn = eng.params_functions()[0]
    with np.errstate(all="ignore"):
        mod.frames(S0, PA, fn, float(t0), te, float(rtol), float(atol), int(max_steps), A, B, E, E3, ns, order,
                   dop, OUT, DOUT, IO)
    return OUT, DOUT, int(IO[0]), int(IO[1]), int(IO[2])
