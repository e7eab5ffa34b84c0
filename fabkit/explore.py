"""Design studies: grids of designs over spec keys (``fabkit explore``).

Pure library code (no printing, no files): the command is the edge. The concerns
around it each have one module: the ``--vary`` keys and the grid
(:mod:`fabkit.vary`), the launches in this process or on a Dask cluster
(:mod:`fabkit.launches`, :mod:`fabkit.cluster`), the Monte Carlo over the launch
(:mod:`fabkit.robustness`) and the per-launch tables (:mod:`fabkit.tables`); their
names are importable from here too.

Explore
-------
:func:`explore` evaluates every design of a grid (:func:`parse_vary`,
:func:`design_grid`): the spec with the grid's keys replaced and fully
re-validated (an invalid combination becomes that design's ``error``). Per
design: ``v_critical`` (± ``v_critical_error``, the half-width of its bracket,
1e-6 relative) and the n-bounce ``windows`` by :func:`sweep.sweep`, and the
pre-fabrication check: with a ramp, all of it is :func:`physics.check.check`
itself, run through the engine (``launcher``): the ramp's release heights
launched (with the ``--v-in`` speeds in the same batch), the highest safe
release height (1e-4 relative) and the first failing height, and the machining
feasibility (depth of the cut against the stock and tool, tool radius against
the smallest concave radius). ``safe`` is the check's verdict: no ramp height
flies off, loses contact, bridges or slips, and the cut is machinable (without
a ``ramp`` section, judged over the ``--v-in`` launches instead). ``model``:
the model that made the design's results (the spec's: the finite ball unless
it names another).
"""

from __future__ import annotations

import time

import numpy as np

from .errors import SpecError
from .launches import (MAX_CACHED, MAX_CHUNK, MIN_CHUNK, TASK_PREFIX, Design, Engine,  # noqa: F401
                       design_of, problem_of, run_chunk)
from .physics.outcomes import outcome_counts, outcome_names
from .robustness import MAX_SIGMA_VY, check_scatter, check_scatter_size, draw_scatter, robustness  # noqa: F401
from .tables import table_bytes, table_format  # noqa: F401
from .tolerances import DEFAULT
from .vary import (MAX_DESIGNS, MIN_SPAN_ABS, MIN_SPAN_REL, Vary, check_interval, check_value,  # noqa: F401
                   design_grid, parse_vary, refuse_key, variable_keys)


def evaluate_design(spec, v_grid, engine: Engine, *, rel_tol: float = 1e-6, height_rel_tol: float = 1e-4,
                    tol=DEFAULT) -> dict:
    """One design (a validated spec): v_critical, windows, ramp safety, machining.

    With a ramp, this is the pre-fabrication check itself (:func:`physics.check.check`)
    run through the engine, its sweep over ``v_grid`` (sorted entry speeds) or, for
    None, the ramp's calibrated speeds; ``safe`` is the check's verdict. Without a
    ramp, the sweep over ``v_grid`` and safety judged over those launches.
    Returns the design's entry without ``params``, plus ``grid`` (the grid launches:
    v_in, outcome, bounces, v_out arrays) for the per-launch table."""
    from .physics.check import check, machining
    from .physics.models import OUTCOMES
    from .physics.models import unsafe as unsafe_mask
    from .physics.sweep import sweep

    t0 = time.perf_counter()
    design = design_of(spec)
    problem = problem_of(design)
    counted = {"n": 0}

    def launch(v):
        counted["n"] += len(v)
        return engine.launch(design, v)

    has_ramp = spec.has("ramp") and spec.has("ball")
    if v_grid is None and not has_ramp:
        raise SpecError("missing section (needed by explore without --v-in)", file=spec.path, key="ramp")
    if has_ramp:
        if v_grid is not None and np.size(v_grid) * 2 > tol.max_launches:
            raise SpecError(f"{np.size(v_grid)} launches exceed the limit {tol.max_launches}", key="--v-in")
        sweep_v = None if v_grid is None else np.sort(np.asarray(v_grid, dtype=float))
        rep = check(spec, launcher=launch, sweep_v=sweep_v, problem=problem, rel_tol=height_rel_tol,
                    v_rel_tol=rel_tol, edge_rel_tol=rel_tol, tol=tol, window_bounces=None)   # every n-bounce window
        out: dict = {"v_critical": rep.v_critical, "v_critical_error": rep.v_critical_error,
                     "v_critical_reason": rep.v_critical_reason, "windows": rep.windows, "safe_over": "ramp",
                     "highest_safe_height": rep.highest_safe_height, "first_failure": rep.first_failure}
        m, grid, safe, v = rep.machining, rep.grid, rep.safe, rep.grid.v_in
    else:
        v = np.sort(np.asarray(v_grid, dtype=float))
        if v.size > tol.max_launches:
            raise SpecError(f"{v.size} launches exceed the limit {tol.max_launches}", key="--v-in")
        grid = launch(v)
        sw = sweep(problem, v, launcher=launch, initial=grid, rel_tol=rel_tol, error_samples=0, tn=False,
                   tol=tol)
        unsafe = unsafe_mask(grid.outcome)
        first_failure = None
        if unsafe.any():
            i = int(np.flatnonzero(unsafe)[0])
            first_failure = {"height": None, "v_in": float(v[i]), "outcome": OUTCOMES[int(grid.outcome[i])]}
        out = {"v_critical": sw["v_critical"], "v_critical_error": sw["v_critical_error"],
               "v_critical_reason": sw["v_critical_reason"], "windows": sw["windows"], "safe_over": "v_in",
               "highest_safe_height": None, "first_failure": first_failure}
        m = machining(spec)
        safe = not bool(unsafe.any()) and (m is None or bool(m["feasible"]))
    out["model"] = problem.model
    out["depth_mm"] = None if m is None else m["depth_mm"]
    out["depth_ok"] = None if m is None else m["depth_ok"]
    out["machining"] = m
    out["safe"] = bool(safe)
    out["outcomes"] = outcome_counts(outcome_names(grid.outcome))
    out["launches"] = counted["n"]
    out["seconds"] = time.perf_counter() - t0
    out["grid"] = {"v_in": v, "outcome": outcome_names(grid.outcome), "bounces": grid.bounces,
                   "v_out": grid.v_out}
    return out


def explore(spec, varies: list[Vary], v_grid=None, *, engine: Engine, rel_tol: float = 1e-6,
            tol=DEFAULT) -> dict:
    """Evaluate every design of the grid. Returns ``{"designs": [...], "launches",
    "seconds", "engine"}``; each design ``{"params", "v_critical", "windows", "safe",
    ...}`` (see :func:`evaluate_design`) or ``{"params", "error", "safe": None, ...}``
    when its spec is invalid."""
    t0 = time.perf_counter()
    grid = design_grid(varies)
    if v_grid is not None and len(grid) * len(v_grid) > tol.max_launches:
        raise SpecError(f"{len(grid)} designs x {len(v_grid)} speeds exceed the limit of {tol.max_launches} "
                        "launches", key="--v-in")

    def one(params: dict) -> dict:
        entry: dict = {"params": params}
        try:
            dspec = spec.with_overrides(params) if params else spec
            entry.update(evaluate_design(dspec, v_grid, engine, rel_tol=rel_tol, tol=tol))
        except SpecError as exc:
            entry.update({"error": str(exc), "v_critical": None, "v_critical_error": None, "windows": [],
                          "highest_safe_height": None, "safe": None})
        return entry

    designs = engine.map(one, grid)
    return {"designs": designs, "launches": engine.launches, "seconds": time.perf_counter() - t0,
            "engine": engine.info()}
