"""The first run: every kernel the shipped commands need for a spec, compiled once.

``fabkit gcode``, ``check``, ``sweep`` and ``report`` call :func:`prepare` before their work:
whichever runs first on a cold cache compiles what all of them need for the spec's surface
(the launch engine and the toolpath's kernels) and says so with the total to expect, so a user
does not pay several compilations in turn. :func:`cold_kernels` estimates what is cold.
In: a spec. Out: compiled kernels in the user cache, and the estimate of what was compiled.
(numba's short start-up for cached code, which every kernel module imports first, is
:mod:`fabkit.numba_start`; this module sits above the engine and the toolpath.)
"""

from __future__ import annotations


def _toolpath_signatures():
    """The argument types the toolpath's formula-free kernels are called with by ``fabkit
    gcode`` and ``fabkit report`` (the material bound, its rim search, the point spacing's
    simplification, the verification's swept cut): compiling them ahead needs no job."""
    from numba import types as T

    f8, i8, b1 = T.float64, T.int64, T.boolean

    def A(dt, nd, readonly=False):
        return T.Array(dt, nd, "C", readonly=readonly)

    from .toolpath.finish import kernels, scallop_kernels, spacing_kernels

    out = [(scallop_kernels.sweep_balls, (A(f8, 1), A(f8, 1, True), A(f8, 2), A(f8, 2), A(f8, 1), f8, i8,
                                          A(f8, 2), A(f8, 2), f8)),
           (scallop_kernels.rim_cut, (A(f8, 1), A(f8, 2), A(f8, 1, True), A(f8, 2), A(f8, 2), A(b1, 2),
                                      A(f8, 1), A(f8, 1), A(f8, 1), f8, A(f8, 1), f8, f8, i8)),
           (spacing_kernels.simplify, (A(i8, 1), A(f8, 1), A(f8, 1), A(b1, 1), A(b1, 1), f8, i8, A(f8, 1), f8))]
    mod = kernels.module()
    if mod is not None:
        out.append((mod.lowest_batch_sorted, (A(f8, 1), A(f8, 1), A(i8, 1), A(i8, 1), A(i8, 1), A(f8, 2),
                                              A(f8, 2), f8, A(i8, 1), b1, A(f8, 1), A(f8, 1))))
    return out


def cold_kernels(spec) -> dict:
    """What a first run of ``fabkit gcode``, ``check`` or ``report`` on ``spec`` would compile,
    in seconds of CPU (estimates measured on the 2-core reference machine): ``simulator``
    (the launch engine of the spec's model and its surface functions; 0 without the
    sections that simulate, or when cached), ``toolpath`` (the drop cutter for the formula
    and the formula-free kernels; 0 without stock and tool, or when cached), and whether
    the part compiled once per installation is among them (``simulator_install``: the
    engine; ``toolpath_install``: the drop cutter's kernel or the formula-free ones)."""
    out = {"simulator": 0.0, "toolpath": 0.0, "simulator_install": False, "toolpath_install": False}
    if spec.has("simulation") and spec.has("surface"):
        from .physics.integrate import ENGINE_MODELS, is_stiff
        from .physics.models import problem_from_spec

        problem = problem_from_spec(spec)
        if problem.model in ENGINE_MODELS and not is_stiff(problem, problem.t_max):
            from .physics.engine import batch

            if not batch.is_compiled(problem):
                tpl = batch.codegen.template_of(problem.model)
                cold_engine = not batch._cached(batch.codegen.write_engine(tpl), "run_batch")
                out["simulator"] = batch.compile_estimate() if cold_engine else 2.0
                out["simulator_install"] = cold_engine
    if spec.has("tool") and spec.has("stock"):
        from .surface import Surface
        from .toolpath.finish import kernels

        out["toolpath"] = kernels.cold_build_seconds(Surface.from_spec(spec))
        out["toolpath_install"] = out["toolpath"] > kernels.BUILD_FORMULA_S + 1e-9
    return out


def prepare(spec, say=None, *, need=("simulator", "toolpath"), quiet: bool = False) -> dict:
    """Compile ahead what ``fabkit gcode``, ``check`` and ``report`` need for ``spec`` and
    the caches lack, and say so first with the total to expect: ``compiling fabkit's
    kernels for this surface (once, about N s of CPU in all: the simulator A s, the
    toolpath's kernels B s; then gcode, check and report load them)``, through
    ``say(message)`` (a stage bar's stage) or, on a terminal, stderr.

    ``need``: the parts the calling command uses (gcode: the toolpath; check and sweep:
    the simulator; report: both), compiled whenever cold. The other part is compiled
    too when its once-per-installation kernels are cold (the first run after installing:
    the next command then loads everything); a new formula later costs each part a
    second or two, in the command that needs it. Returns :func:`cold_kernels`' estimate
    of what was compiled (0: nothing). A kernel that cannot be compiled (no writable
    cache) is left to the code that needs it (the numpy path)."""
    import sys

    cold = cold_kernels(spec)
    do = {part: cold[part] > 0 and (part in need or cold[f"{part}_install"]) for part in ("simulator", "toolpath")}
    total = sum(cold[p] for p in do if do[p])
    if total <= 0:
        return {"simulator": 0.0, "toolpath": 0.0}
    parts = [f"{name} about {round(cold[p])} s" for p, name in (("simulator", "the simulator"),
                                                                ("toolpath", "the toolpath's kernels")) if do[p]]
    msg = (f"compiling fabkit's kernels for this surface (once, about {max(1, round(total))} s of CPU in all: "
           f"{', '.join(parts)}; then gcode, check and report load them)")
    if say is not None:
        say(msg)
    elif not quiet and sys.stderr.isatty():
        sys.stderr.write(msg + "\n")
        sys.stderr.flush()
    if do["simulator"]:
        from .physics.engine.batch import engine
        from .physics.models import problem_from_spec

        engine(problem_from_spec(spec))
    if do["toolpath"]:
        from .surface import Surface
        from .toolpath.finish import kernels

        kernels.kernel_for(Surface.from_spec(spec))
        if kernels.enabled():
            for disp, sig in _toolpath_signatures():
                try:
                    disp.compile(sig)
                except Exception:   # pragma: no cover - a kernel numba cannot build: the numpy code runs
                    pass
    return {p: (cold[p] if do[p] else 0.0) for p in do}
