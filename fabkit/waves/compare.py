"""The seed paper's Fig. 1 for an apparatus: v_out(v_in) of four models side by side.

Panels (each a dict: name, params, v_in, v_out, bounces, outcome, v_critical,
v_critical_note, units, seconds; the apparatus also model, windows, tn_fit, length_unit):

1. ``pde``: phi^4 kink-antikink collisions (:mod:`fabkit.waves.phi4`); v_critical from
   a phi^4 sweep's bisection (:func:`fabkit.waves.sweep.phi4_sweep`).
2. ``ode``: the collective-coordinate model eq. (CCODE) with c = 1/4, omega = 1
   (Goodman's parameters), scipy DOP853 (:func:`fabkit.physics.cc.cc_launch`); its
   v_critical by bisection (:func:`fabkit.physics.cc.cc_critical_velocity`, about 0.2936).
3. ``map``: the separatrix map eq. (themap) with the same c and omega; v_critical =
   omega C = sqrt(2) pi c exp(-sqrt(2) omega) (0.2700 at c = 1/4, omega = 1).
4. ``apparatus``: the spec's rolling ball through the simulator's sweep
   (:func:`fabkit.physics.sweep.sweep`, the one ``fabkit sweep`` runs) over the ramp's
   calibrated speeds, with the spec's model (named in the panel), and its eq. (tn) fit.

The model panels sample v_in / v_critical over ``SPAN``; the apparatus samples its ramp's
range, which is wider. The figure draws all four over ``SPAN`` (the JSON keeps every
launch). Launches with five or more collisions are stopped at the fifth (the figure colours
up to four) and drawn with the captured ones.

:func:`lab_tn_comparison` sets the lab's published T_n fit (Goodman et al., section
"The laboratory experiment": T_n = 0.961 n + 0.755 s, n = 2..6 transverse oscillations)
beside the apparatus's fitted T_n (docs/paper.md).
"""

from __future__ import annotations

import time

import numpy as np

from ..physics import cc

C_CC, OMEGA_CC = 0.25, 1.0          # Goodman (2019): m = 1, omega = 1, eps = 1/4
PDE_VC_NOMINAL = 0.2598             # Anninos et al. 1991; Goodman & Haberman 2005 (to place the samples)
SPAN = (0.65, 1.25)                  # v_in / v_critical sampled in the model panels
STOP_AFTER = 5

#: the lab's T_n fit as published (Goodman et al., section "The laboratory experiment", Fig. July15(f)):
#: T_n = T n + delta in seconds, n = 2..6 transverse oscillations between the two bounces
LAB_TN = {"T": 0.961, "delta": 0.755, "n": [2, 3, 4, 5, 6], "units": "s",
          "source": "Goodman et al., section 'The laboratory experiment', Fig. July15(f): T_n = 0.961 n + 0.755"}


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
    # the sweep `fabkit sweep` runs (windows resolved, v_out maximized in each two-bounce
    # window), so the T_n fit is the sweep's own
    r = sweep(problem, v, progress=progress, error_samples=0)
    u = f"{spec.units}/s"
    note = (f"bisection ± {r['v_critical_error']:.1e} {u}" if r["v_critical"] is not None
            else r["v_critical_reason"])
    return {"name": f"the apparatus ({spec.name}, {problem.model} model)", "model": problem.model,
            "params": f"{problem.model} model, damping {problem.damping:g} 1/s, ramp's speeds "
                      f"{v[0]:.4g}..{v[-1]:.4g} {u}",
            "v_in": r["v_in"], "v_out": r["v_out"], "bounces": r["bounces"], "outcome": r["outcome"],
            "v_critical": r["v_critical"], "v_critical_note": note, "windows": r["windows"], "units": u,
            "tn_fit": r["tn_fit"], "length_unit": spec.units,
            "launches": r["launches"], "seconds": time.perf_counter() - t0}


def lab_tn_comparison(tn_fit: dict, *, model: str, length_unit: str, lab: dict = LAB_TN) -> dict:
    """The lab's published T_n fit beside the apparatus's (:func:`fabkit.physics.sweep.fit_tn`).

    Returns ``{lab, fabkit, by_n, max_rel_diff, note}``: ``lab`` as published; ``fabkit``
    ``{T, delta, n, T_n, model, length_unit, T_shape}`` (T and delta None when fewer than two
    windows entered the fit); ``by_n`` for each of the lab's n: the lab's line, fabkit's
    line and, where a window has that n, the window's own T_n, and (fabkit - lab) / lab of
    the lines; ``fabkit_over_lab_n`` ``{T, delta, n}``: fabkit's windows with the lab's n only,
    fitted alone; ``max_rel_diff`` the largest |relative difference| over the lab's n that
    fabkit's windows cover. Both number n the same way: complete transverse oscillations
    between the bounces (fabkit: n_0 = floor(T_0 / T_shape), then by differences)."""
    T, delta = tn_fit.get("T"), tn_fit.get("delta")
    ns, tns = list(tn_fit.get("n") or []), list(tn_fit.get("T_n") or [])
    own = dict(zip(ns, tns))
    rows = []
    for n in lab["n"]:
        t_lab = lab["T"] * n + lab["delta"]
        t_fit = None if T is None else T * n + delta
        rows.append({"n": n, "lab": t_lab, "fabkit": t_fit, "fabkit_window": own.get(n),
                     "rel_diff": None if t_fit is None else (t_fit - t_lab) / t_lab})
    # fabkit's own windows over the lab's n only (the lab's range of the line)
    sel = [(n, t) for n, t in zip(ns, tns) if lab["n"][0] <= n <= lab["n"][-1]]
    over_lab = {"T": None, "delta": None, "n": [n for n, _ in sel]}
    if len({n for n, _ in sel}) >= 2:
        A = np.column_stack([[n for n, _ in sel], np.ones(len(sel))])
        (Tl, dl), *_ = np.linalg.lstsq(A, np.array([t for _, t in sel]), rcond=None)
        over_lab.update(T=float(Tl), delta=float(dl))
    covered = [r["rel_diff"] for r in rows if r["rel_diff"] is not None and ns and min(ns) <= r["n"] <= max(ns)]
    return {"lab": dict(lab),
            "fabkit": {"T": T, "delta": delta, "n": ns, "T_n": tns, "model": model, "length_unit": length_unit,
                       "T_shape": tn_fit.get("T_shape"), "units": "s"},
            "fabkit_over_lab_n": over_lab, "by_n": rows, "max_rel_diff": max((abs(x) for x in covered), default=None),
            "note": "n: complete transverse oscillations between the two bounces; the lab's fit is over its "
                    "n = 2..6, fabkit's over its resolved two-bounce windows"}


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
