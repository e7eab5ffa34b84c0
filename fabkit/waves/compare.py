"""The seed paper's Fig. 1 for an apparatus: v_out(v_in) of four models side by side.

Panels (each a dict: name, params, v_in, v_out, bounces, outcome, v_critical,
v_critical_note, units, seconds):

1. ``pde``: phi^4 kink-antikink collisions (:mod:`fabkit.waves.phi4`); v_critical from
   a phi^4 sweep's bisection (:func:`fabkit.waves.sweep.phi4_sweep`).
2. ``ode``: the collective-coordinate model eq. (CCODE) with c = 1/4, omega = 1
   (Goodman's parameters), scipy DOP853 (:func:`fabkit.physics.cc.cc_launch`); its
   v_critical by bisection (:func:`fabkit.physics.cc.cc_critical_velocity`, about 0.2936).
3. ``map``: the separatrix map eq. (themap) with the same c and omega; v_critical =
   omega C = sqrt(2) pi c exp(-sqrt(2) omega) (0.2700 at c = 1/4, omega = 1).
4. ``apparatus``: the spec's rolling ball through the simulator's sweep
   (:func:`fabkit.physics.sweep.sweep`) over the ramp's calibrated speeds.

Every panel samples v_in / v_critical over the same span (``span``; the apparatus:
its ramp's range), so the axes compare. Launches with five or more collisions are
stopped at the fifth (the figure colours up to four) and drawn with the captured ones.
"""

from __future__ import annotations

import time

import numpy as np

from ..physics import cc

C_CC, OMEGA_CC = 0.25, 1.0          # Goodman (2019): m = 1, omega = 1, eps = 1/4
PDE_VC_NOMINAL = 0.2598             # Anninos et al. 1991; Goodman & Haberman 2005 (to place the samples)
SPAN = (0.65, 1.25)                  # v_in / v_critical sampled in the model panels
STOP_AFTER = 5


def pde_panel(n: int, cfg=None, *, span=SPAN, progress=None) -> dict:
    from .phi4 import DEFAULT_CONFIG
    from .sweep import phi4_sweep

    cfg = cfg or DEFAULT_CONFIG
    t0 = time.perf_counter()
    v = np.linspace(span[0] * PDE_VC_NOMINAL, span[1] * PDE_VC_NOMINAL, n)
    r = phi4_sweep(v, cfg, progress=progress, stop_after=STOP_AFTER, refine_windows=False)
    note = (f"bisection, escape = X back at X0 = {cfg.x0:g} by t = {cfg.t_max:g}, ± {r['v_critical_error']:.1e}"
            if r["v_critical"] is not None else r["v_critical_reason"])
    return {"name": "phi^4 PDE (kink-antikink)",
            "params": f"phi_tt - phi_xx - phi + phi^3 = 0; X0 {cfg.x0:g}, dx {cfg.dx:g}, dt {cfg.dt:g}, "
                      f"t_max {cfg.t_max:g}",
            "v_in": r["v_in"], "v_out": r["v_out"], "bounces": r["bounces"], "outcome": r["outcome"],
            "v_critical": r["v_critical"], "v_critical_note": note, "windows": r["windows"], "units": "c",
            "launches": r["launches"], "seconds": time.perf_counter() - t0}


def ode_panel(n: int, *, c: float = C_CC, omega: float = OMEGA_CC, span=SPAN, rtol: float = 1e-9) -> dict:
    t0 = time.perf_counter()
    vc = cc.cc_critical_velocity(c, omega, rel_tol=1e-6, rtol=rtol, atol=rtol * 1e-3)
    v = np.linspace(span[0] * vc, span[1] * vc, n)
    # decide=False: a launch bound after one bounce may still escape after more
    rows = [cc.cc_launch(float(x), c, omega, rtol=rtol, atol=rtol * 1e-3, max_bounces=STOP_AFTER) for x in v]
    return {"name": "collective-coordinate ODE (eq. CCODE)",
            "params": f"c = {c:g}, omega = {omega:g} (U = e^-2X - e^-X, F = e^-X); DOP853 rtol {rtol:g}",
            "v_in": v, "v_out": np.array([r["v_out"] for r in rows]),
            "bounces": np.array([r["bounces"] for r in rows]), "outcome": [r["outcome"] for r in rows],
            "v_critical": vc, "v_critical_note": "bisection to 1e-6 relative", "units": "",
            "launches": len(v), "seconds": time.perf_counter() - t0}


def map_panel(n: int, *, c: float = C_CC, omega: float = OMEGA_CC, span=SPAN) -> dict:
    t0 = time.perf_counter()
    vc = cc.v_critical_map(c, omega)
    v = np.linspace(span[0] * vc, span[1] * vc, n)
    b, vo = cc.cc_map(v, c, omega, max_bounces=STOP_AFTER)
    C = cc.melnikov_C(c, omega)
    return {"name": "separatrix map (eq. themap)",
            "params": f"c = {c:g}, omega = {omega:g}, C = {C:.5f}, T(E) = pi sqrt(2) / sqrt(-E)",
            "v_in": v, "v_out": vo, "bounces": b, "outcome": ["escaped" if k > 0 else "captured" for k in b],
            "v_critical": vc, "v_critical_note": "omega C (exact for the map)", "units": "",
            "launches": len(v), "seconds": time.perf_counter() - t0}


def apparatus_panel(spec, v, *, progress=None) -> dict:
    from ..physics.models import problem_from_spec
    from ..physics.sweep import sweep

    t0 = time.perf_counter()
    problem = problem_from_spec(spec)
    r = sweep(problem, v, progress=progress, tn=False, error_samples=0)
    u = f"{spec.units}/s"
    note = (f"bisection ± {r['v_critical_error']:.1e} {u}" if r["v_critical"] is not None
            else r["v_critical_reason"])
    return {"name": f"the apparatus ({spec.name}, rolling ball)",
            "params": f"{problem.model} model, damping {problem.damping:g} 1/s, ramp's speeds "
                      f"{v[0]:.4g}..{v[-1]:.4g} {u}",
            "v_in": r["v_in"], "v_out": r["v_out"], "bounces": r["bounces"], "outcome": r["outcome"],
            "v_critical": r["v_critical"], "v_critical_note": note, "windows": r["windows"], "units": u,
            "launches": r["launches"], "seconds": time.perf_counter() - t0}


def summary_rows(panels: list[dict]) -> list[dict]:
    """Per panel: name, v_critical, its note, counts of 1..4-bounce escapes."""
    rows = []
    for p in panels:
        nb = np.asarray(p["bounces"])
        esc = np.array([o == "escaped" for o in p["outcome"]])
        counts = {str(k): int((esc & (nb == k)).sum()) for k in (1, 2, 3, 4)}
        counts["other"] = int(len(nb) - sum(counts.values()))
        rows.append({"name": p["name"], "v_critical": p["v_critical"], "note": p["v_critical_note"],
                     "counts": counts, "seconds": p["seconds"]})
    return rows
