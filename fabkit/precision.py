"""Work-precision studies: error against run time, for the simulator, the toolpath and the mesh.

Pure functions (no printing, no files); ``fabkit precision`` is the command.

Simulation
----------
The problem is the spec's surface and ball with the damping set to 0 (the paper's
undamped apparatus: the energy is then conserved, and its drift is a third check
on each integrator). The launches are picked from the physics, so that the
measured quantities are well conditioned:

1. a sweep over ``v_grid`` (fabkit's integrator at its default tolerance) gives
   the outcome and bounce count of every sample and v_critical;
2. launches inside the widest two-bounce windows (their middle samples, at least
   ``edge`` samples from either edge) and launches above v_critical (one bounce,
   at least 5 % above it and ``edge`` samples from the top of the range or any
   launch that flies off) are chosen.

Near a window edge v_out depends on v_in chaotically: no tolerance makes it
accurate and the bounce count itself can change, so such launches are avoided.

Each method (fabkit's batched DOP853 and RK45; scipy's RK45, DOP853, Radau and
LSODA, one ``solve_ivp`` per launch) runs the launch set at each of its
tolerances (atol = rtol / 100). The error of a run is the largest, over its
launches, of the relative v_out error and the bounce-time errors relative to the
last bounce time, against a reference computed far tighter (scipy DOP853 at
rtol 1e-13, atol 1e-15; its own error is estimated against rtol 1e-12 and
reported). A launch whose outcome or bounce count differs from the reference is
counted in ``mismatched`` and given error 1 (the result is qualitatively wrong).
The wall time is that of the whole launch set: a warm-up run on one launch, then
the best of up to ``repeats`` runs (fewer when one run exceeds ``budget`` s).

Toolpath and mesh
-----------------
The toolpath job (:func:`fabkit.toolpath.job.run_job`, the one ``fabkit gcode``
runs: planned, written, read back, verified, passes added where material is left)
runs at each ``machining.tolerance``; the row gives the verified largest gouge
(``max_deviation``) and material left of the program gcode would write, the
program lines, the job's verdict (``ok``) and the time (plan and write; the
verification with its added passes separately). The mesh rows come from
:func:`fabkit.solid.mesh_precision`: chordal tolerance against the measured
largest deviation, triangles and time.
"""

from __future__ import annotations

import math
import time

import numpy as np

REFERENCE = {"method": "DOP853", "rtol": 1e-13, "atol": 1e-15}

FULL = {
    "v_samples": 400,
    "launches": (2, 2),   # (inside two-bounce windows, above v_critical)
    "methods": {
        "fabkit DOP853": (1e-4, 1e-6, 1e-8, 1e-10, 1e-12),
        "fabkit RK45": (1e-4, 1e-6, 1e-8, 1e-10),
        "scipy DOP853": (1e-4, 1e-6, 1e-8, 1e-10, 1e-12),
        "scipy RK45": (1e-4, 1e-6, 1e-8, 1e-10),
        "scipy LSODA": (1e-4, 1e-6, 1e-8, 1e-10),
        "scipy Radau": (1e-4, 1e-6, 1e-8, 1e-10),
    },
    "repeats": 3,
    "budget": 3.0,
    "toolpath": (0.04, 0.02, 0.01, 0.005),
    "mesh": (0.1, 0.03, 0.01, 0.003),
    "tile": None,
}

QUICK = {
    "v_samples": 160,
    "launches": (1, 1),
    "methods": {
        "fabkit DOP853": (1e-4, 1e-6, 1e-8, 1e-10),
        "fabkit RK45": (1e-4, 1e-6, 1e-8),
        "scipy DOP853": (1e-4, 1e-6, 1e-8),
        "scipy RK45": (1e-4, 1e-6, 1e-8),
        "scipy LSODA": (1e-4, 1e-6, 1e-8),
        "scipy Radau": (1e-3, 1e-5, 1e-7),
    },
    "repeats": 2,
    "budget": 0.5,
    "toolpath": (0.1, 0.05, 0.02, 0.01),
    "mesh": (0.1, 0.03, 0.01),
    # a 14 x 8 design-unit tile of the footprint, coarse scallop and few check points
    "tile": {"x_len": 14.0, "y_len": 8.0, "scallop": 0.2, "verify_points": 4000},
}


# ----------------------------------------------------------------------------
# timing
# ----------------------------------------------------------------------------
def best_time(fn, repeats: int = 3, budget: float = 3.0):
    """(best wall time of up to ``repeats`` calls, result of the last call); stops
    early once the calls so far took more than ``budget`` s (at least one call)."""
    best, spent, out = math.inf, 0.0, None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        dt = time.perf_counter() - t0
        best = min(best, dt)
        spent += dt
        if spent > budget:
            break
    return best, out


# ----------------------------------------------------------------------------
# launches
# ----------------------------------------------------------------------------
def _runs(n: np.ndarray):
    """Maximal runs of equal values: (value, i, j) inclusive."""
    out, i = [], 0
    while i < len(n):
        j = i
        while j + 1 < len(n) and n[j + 1] == n[i]:
            j += 1
        out.append((int(n[i]), i, j))
        i = j + 1
    return out


class NoWellConditionedLaunch(Exception):
    """The speed range offers no launch the simulation study can measure on (the
    message says why); the toolpath and mesh studies do not need one."""


def choose_launches(problem, v_grid, n_window: int = 2, n_above: int = 2, edge: int = 3) -> dict:
    """Well-conditioned launches of ``problem`` (see the module docstring).

    Returns {"v_in": [...], "kind": ["window" | "above" | "below", ...], "v_critical",
    "windows" (the two-bounce runs used, as (lo, hi))}. "above"/"below": one-bounce
    escapes above v_critical, or below it (a surface where slow balls pass after
    one bounce), at least 5 % from it. Raises :class:`NoWellConditionedLaunch` when
    the range has neither a two-bounce window nor such one-bounce escapes."""
    from .physics.models import ESCAPED, OUTCOMES, unsafe
    from .physics.sweep import critical_bracket, make_launcher

    v = np.sort(np.asarray(v_grid, dtype=float))
    res = make_launcher(problem)(v)
    lo, hi, _ = critical_bracket(v, res)
    vc = None if lo is None else 0.5 * (lo + hi)
    n = np.where(res.outcome == ESCAPED, res.bounces, -1)
    picks, kinds, used = [], [], []
    wide = sorted([r for r in _runs(n) if r[0] == 2 and r[2] - r[1] + 1 >= 2 * edge + 1],
                  key=lambda r: r[1] - r[2])
    if len(wide) >= n_window:   # the middle of each of the widest windows
        chosen = [(i, j, [(i + j) // 2]) for _, i, j in wide[:n_window]]
    elif wide:                  # spread over the interior of the widest one
        _, i, j = wide[0]
        ks = np.linspace(i + edge, j - edge, n_window + 2)[1:-1].round().astype(int)
        chosen = [(i, j, sorted(set(int(k) for k in ks)))]
    else:
        chosen = []
    for i, j, ks in chosen:
        used.append((float(v[i]), float(v[j])))
        for k in ks:
            picks.append(float(v[k]))
            kinds.append("window")
    # above v_critical: one-bounce escapes, away from v_critical and from the unsafe top
    ok = (n == 1)
    bad = unsafe(res.outcome)
    cand = []
    for i in range(edge, len(v) - edge):
        if ok[i - edge:i + edge + 1].all() and not bad[i - edge:i + edge + 1].any() \
                and (vc is None or abs(v[i] - vc) > 0.05 * vc):
            cand.append(i)
    if cand:
        for k in np.linspace(0, len(cand) - 1, n_above + 2)[1:-1].round().astype(int):
            picks.append(float(v[cand[k]]))
            kinds.append("above" if vc is None or v[cand[k]] > vc else "below")
    if not picks:
        counts = {}
        for o, b in zip(res.outcome.tolist(), res.bounces.tolist()):
            name = f"escaped after {b}" if o == ESCAPED else OUTCOMES[o]
            counts[name] = counts.get(name, 0) + 1
        raise NoWellConditionedLaunch(
            f"no well-conditioned launch among {len(v)} from v_in {v[0]:.6g} to {v[-1]:.6g} (undamped): no "
            f"two-bounce window of {2 * edge + 1} samples and no {2 * edge + 1} consecutive one-bounce escapes "
            "5 % away from v_critical; the launches: " + ", ".join(f"{k} {n}" for k, n in sorted(counts.items())))
    return {"v_in": picks, "kind": kinds, "v_critical": vc, "windows": used,
            "sweep_launches": int(len(v))}


# ----------------------------------------------------------------------------
# runs of the launch set by one method
# ----------------------------------------------------------------------------
def _fabkit_runner(problem, v, integrator, rtol, atol):
    from .physics.integrate import launch_batch

    def run():
        r = launch_batch(problem, v, rtol=rtol, atol=atol, method=integrator)
        return [{"outcome": int(r.outcome[i]), "bounces": int(r.bounces[i]), "v_out": float(r.v_out[i]),
                 "bounce_times": r.bounce_times[i, :r.bounces[i]].copy(),
                 "energy": float(r.energy_error[i]), "steps": int(r.steps[i] + r.rejected[i])}
                for i in range(len(v))]
    return run


def _scipy_runner(problem, v, integrator, rtol, atol):
    from .physics.models import OUTCOMES
    from .physics.reference import solve_launch

    def run():
        rows = []
        for vi in v:
            s = solve_launch(problem, float(vi), float(problem.y0), float(problem.vy0), method=integrator,
                             rtol=rtol, atol=atol)
            rows.append({"outcome": OUTCOMES.index(s["outcome"]), "bounces": int(s["bounces"]),
                         "v_out": float(s["v_out"]), "bounce_times": np.asarray(s["bounce_times"], float),
                         "energy": float(s["energy_error"]), "nfev": int(s["nfev"])})
        return rows
    return run


def runner(problem, v, method: str, rtol: float, atol: float):
    """A callable running the launch set ``v`` with ``method`` ('fabkit DOP853', 'scipy Radau', ...)."""
    family, integrator = method.split(" ", 1)
    make = _fabkit_runner if family == "fabkit" else _scipy_runner
    return make(problem, np.asarray(v, dtype=float), integrator, rtol, atol)


def launch_errors(rows, ref) -> tuple[float, int]:
    """(largest error over the launches, launches whose outcome or bounce count differ).

    Per launch: |v_out - v_out_ref| / v_out_ref and max |t_k - t_k,ref| / t_last,ref."""
    worst, mismatched = 0.0, 0
    for a, b in zip(rows, ref):
        if a["outcome"] != b["outcome"] or a["bounces"] != b["bounces"]:
            mismatched += 1
            worst = max(worst, 1.0)
            continue
        e = 0.0
        if math.isfinite(b["v_out"]) and b["v_out"] > 0:
            e = max(e, abs(a["v_out"] - b["v_out"]) / b["v_out"])
        if b["bounces"]:
            tb, tr = np.asarray(a["bounce_times"]), np.asarray(b["bounce_times"])
            e = max(e, float(np.max(np.abs(tb - tr))) / max(float(tr[-1]), 1e-300))
        worst = max(worst, e if math.isfinite(e) else 1.0)
    return worst, mismatched


def simulation_study(problem, cfg: dict = FULL, progress=None, v_range=None) -> dict:
    """The simulation rows of the work-precision study (see the module docstring).

    ``problem``: the spec's problem (its damping is replaced by 0 here).
    ``progress``: optional callable(str) told what runs next. ``v_range``: (lo, hi) of the
    sweep that picks the launches (default :func:`_speed_range`).
    Returns {"rows": [{method, rtol, atol, error, seconds, mismatched, energy_drift,
    per_launch, steps (fabkit) | nfev (scipy)}], "launches": {...}, "reference": {...}, "monotone": {method: bool},
    "problem": str}."""
    p = problem.with_(damping=0.0, nonlinear_damping=0.0)
    lo, hi = v_range if v_range is not None else _speed_range(p)
    say = progress or (lambda s: None)
    say("choosing launches")
    pick = choose_launches(p, np.linspace(lo, hi, cfg["v_samples"]), *cfg["launches"])
    v = pick["v_in"]
    say("reference")
    ref = runner(p, v, "scipy " + REFERENCE["method"], REFERENCE["rtol"], REFERENCE["atol"])()
    ref_check = runner(p, v, "scipy " + REFERENCE["method"], 1e-12, 1e-14)()
    ref_err, ref_mis = launch_errors(ref_check, ref)
    rows = []
    for method, tols in cfg["methods"].items():
        say(method)
        runner(p, v[:1], method, tols[0], tols[0] * 1e-2)()   # warm-up (imports, compiled RHS, caches)
        for rt in tols:
            at = rt * 1e-2
            sec, out = best_time(runner(p, v, method, rt, at), cfg["repeats"], cfg["budget"])
            err, mis = launch_errors(out, ref)
            drift = [r["energy"] for r in out if math.isfinite(r["energy"])]
            rows.append({"method": method, "rtol": rt, "atol": at, "error": err, "seconds": sec,
                         "per_launch": sec / len(v), "mismatched": mis,
                         "energy_drift": max(drift) if drift else None})
            for k in ("steps", "nfev"):   # fabkit: steps taken (all lanes); scipy: RHS evaluations
                if k in out[0]:
                    rows[-1][k] = int(sum(r[k] for r in out))
    floor = 10 * max(ref_err, 1e-15)
    monotone = {}
    for method in cfg["methods"]:
        e = [r["error"] for r in rows if r["method"] == method]
        monotone[method] = all(b <= a or b <= floor for a, b in zip(e, e[1:]))
    return {"rows": rows, "monotone": monotone,
            "launches": {"v_in": v, "kind": pick["kind"], "v_critical": pick["v_critical"],
                         "windows": pick["windows"], "sweep_samples": pick["sweep_launches"]},
            "reference": dict(REFERENCE, estimated_error=ref_err, mismatched=ref_mis, floor=floor),
            "problem": f"{p.model} model, damping 0 (undamped apparatus), {len(v)} launches"}


def _speed_range(problem) -> tuple[float, float]:
    """The entry speeds to sweep: 0.4 to 1.8 times the speed that climbs the surface's
    rise from the launch point to its lowest point and back (about the paper's
    ramp range on its surface)."""
    x0, x1 = problem.x_range
    xs = np.linspace(max(x0, problem.start), x1, 2001)
    hs = np.asarray(problem.fns.h(xs, np.zeros_like(xs)), dtype=float)
    h0 = float(problem.fns.h(problem.start, 0.0))
    hs = hs[np.isfinite(hs)]
    drop = max(h0 - float(np.min(hs)), 1e-9) if hs.size else 1.0
    v = math.sqrt(2 * problem.g_tilde * drop)
    return 0.4 * v, 1.8 * v


def ramp_or_default_range(spec, problem) -> tuple[float, float]:
    """The ramp's calibrated speed range when the spec has one, else :func:`_speed_range`."""
    if spec.has("ramp") and spec.has("ball"):
        from . import units
        from .physics.calibrate import ball_k, ramp_heights, v_in_from_height

        v = v_in_from_height(ramp_heights(spec), units.gravity(spec.units), ball_k(spec))
        v = np.asarray(v, dtype=float)
        v = v[np.isfinite(v) & (v > 0)]
        if v.size >= 2 and v.max() > v.min():
            return float(v.min()), float(v.max())
    return _speed_range(problem)


# ----------------------------------------------------------------------------
# toolpath and mesh
# ----------------------------------------------------------------------------
def tile_spec(spec, tile: dict | None):
    """The spec itself, or (``tile``) a smaller footprint around the lowest point of
    the surface, with a coarser scallop and fewer check points (for quick studies)."""
    if not tile:
        return spec
    (x0, x1), (y0, y1) = spec.surface.x, spec.surface.y
    fns = spec.surface_functions()
    xs, ys = np.meshgrid(np.linspace(x0, x1, 201), np.linspace(y0, y1, 81))
    z = np.asarray(fns.h(xs, ys), dtype=float)
    k = int(np.nanargmin(np.where(np.isfinite(z), z, np.inf)))
    cx, cy = float(xs.flat[k]), float(ys.flat[k])
    lx, ly = min(tile["x_len"], x1 - x0), min(tile["y_len"], y1 - y0)
    ax = min(max(cx - lx / 2, x0), x1 - lx)
    ay = min(max(cy - ly / 2, y0), y1 - ly)
    over = {"surface.x": [ax, ax + lx], "surface.y": [ay, ay + ly],
            "machining.scallop": max(float(spec.machining.scallop), tile["scallop"]),
            "machining.verify_points": tile["verify_points"]}
    if spec.has("simulation"):
        over["simulation.start"] = ax + lx / 2
    return spec.with_overrides(over)


def toolpath_study(spec, tolerances) -> list[dict]:
    """One row per ``machining.tolerance`` (mm): the verified cut and the cost, from the
    toolpath job :func:`fabkit.toolpath.job.run_job` (the same verification, added passes
    included, as ``fabkit gcode``: the same program reports the same figures)."""
    from .surface import Surface
    from .toolpath.job import run_job

    rows = []
    for tol_mm in tolerances:
        s = spec.with_overrides({"machining.tolerance": float(tol_mm)})
        job = run_job(s, Surface.from_spec(s))
        cut = job.cut
        rows.append({"tolerance": float(tol_mm), "max_deviation": float(cut.max_gouge),
                     "material_left": float(cut.max_material_left), "scallop": float(s.machining.scallop),
                     "within_tolerance": bool(cut.max_gouge <= tol_mm),
                     "lines": job.lines, "passes": int(job.toolpath.passes),
                     "checked_points": int(cut.checked_points),
                     "seconds": job.timings["plan"] + job.timings["write"],
                     "verify_seconds": job.timings["verify"], "ok": job.ok})
    return rows


def mesh_study(spec, tolerances) -> list[dict]:
    """One row per chordal tolerance (mm), from :func:`fabkit.solid.mesh_precision`."""
    from .solid import mesh_precision

    rows = mesh_precision(spec, tuple(float(t) for t in tolerances))
    for r in rows:
        r["within_tolerance"] = bool(r["max_deviation"] <= r["tolerance"])
    return rows
