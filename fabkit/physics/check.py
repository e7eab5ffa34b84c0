"""The pre-fabrication check: does the ball stay on the milled part for every ramp height?

:func:`check` launches the ramp's release heights (``ramp.heights`` sampled
densely, :func:`calibrate.ramp_heights`), calibrated to entry speeds, with the
spec's model and damping, through the batched integrator. A launch is unsafe
if it flies off (reaches top - margin, or leaves the footprint shrunk by the
margin) or loses contact (full model). It reports:

* ``safe`` and the first (lowest) failing height with the launch's end point
  and the reason;
* ``highest_safe_height``: the top of the ramp if all are safe; otherwise the
  boundary between the last safe and the first failing sampled height,
  narrowed by bisection to ``rel_tol`` (1e-4) relative (the reported
  height is the safe end of the final bracket);
* ``v_critical`` (by :func:`sweep.sweep` over the ramp's speeds, bisection to 1e-6
  relative) and the release height that gives it; the two-bounce windows the ramp
  can reach (both edges inside the ramp's v_in range), each edge bisected to 1e-6
  relative (``edge_error``) after a walk from the window's end sample that isolates the
  edge of its connected two-bounce run (``sweep.py``: gaps between windows narrower than
  1e-4 relative are not seen; near v_critical the windows crowd together, separated by
  gaps far narrower than the ramp's sampling, and a bisection of the sampled bracket
  alone ends on any of their edges);
* machining feasibility when the spec has stock and tool: the depth of the cut
  against ``stock.depth_limit``, ``stock.thickness`` and ``tool.reach``, and the
  tool radius against the surface's smallest concave radius.

Pure: no printing. Raises nothing for an unsafe design; the command turns
``safe = False`` into a :class:`DesignError`.
"""

from __future__ import annotations

import math
import time

import numpy as np

from .models import unsafe as unsafe_mask
from .sweep import CAPTURED, ESCAPED, FLEW_OFF, LOST_CONTACT, Launches, make_launcher, sweep


def end_reason(problem, outcome: int, x: float, y: float, status: int = 0) -> str:
    """Why a launch ended where it did (x, y in design units): which bound a launch
    that flies off crossed, that a launch losing contact lost its normal force,
    what stopped a captured one."""
    if outcome == ESCAPED:
        return "crossed the exit"
    if outcome == CAPTURED:
        return {1: "the step guard stopped it (counted as captured)",
                4: "its energy fell below every exit (trapped for good)"}.get(status, "still trapped at t_max")
    if outcome == FLEW_OFF and status == 3:
        return "flies off at the launch: the derivatives overflow"
    return _why(problem, outcome, x, y)


def _why(problem, outcome: int, x: float, y: float) -> str:
    """A short reason for an unsafe end state."""
    from .models import BRIDGED, SLIPPED

    if outcome == LOST_CONTACT:
        return ("loses contact (the normal force falls to zero: the surface falls away faster than gravity "
                "holds the ball)")
    if outcome == BRIDGED:
        r = float(problem.radius)
        return (f"bridges: the surface is tighter than the ball (radius {r:g} {problem.units}), which touches it at "
                f"two points (r times the concave curvature reaches 1)")
    if outcome == SLIPPED:
        return f"slips: the rolling needs more friction than ball.friction = {problem.friction:g}"
    x0, x1 = problem.x_range
    y0, y1 = problem.y_range
    m = problem.margin
    z = float(problem.fns.h(x, y))
    eps = 1e-6 * max(1.0, abs(problem.top))
    if z >= problem.top - m - eps:
        return "z reaches top - margin"
    if x >= x1 - m - eps or x <= x0 + m + eps:
        return "leaves the footprint along x (margin included)"
    if y >= y1 - m - eps or y <= y0 + m + eps:
        return "leaves the footprint across y (margin included)"
    return "flies off"


def _full_launches(problem, v, progress=None, rtol=None, atol=None):
    """Launch ``v`` with the batched integrator, keeping the end states."""
    from .integrate import launch_batch

    kw = {"progress": progress} if progress is not None else {}
    r = launch_batch(problem, v, rtol=rtol, atol=atol, **kw)
    return r


def check(spec, *, progress=None, rel_tol: float = 1e-4, v_rel_tol: float = 1e-6,
          edge_rel_tol: float = 1e-6, gap_rel_tol: float = 1e-4) -> dict:
    """Run the pre-fabrication check of ``spec`` (sections surface, ball, ramp,
    simulation; stock and tool optional). Returns the report dict (see module doc):
    safe, highest_safe_height, first_failure {height, v_in, outcome, reason, x, y, t},
    v_critical, v_critical_error, critical_height, reachable_windows [{lo, hi, height_lo,
    height_hi, v_out_max, edge_error}], machining, heights, v_in,
    outcomes, bounces, v_out (nan unless escaped), seconds. Heights in design units,
    speeds in design units/s."""
    from ..units import gravity
    from .calibrate import ball_k, height_from_v_in, ramp_heights, v_in_from_height
    from .models import OUTCOMES, problem_from_spec

    t0 = time.perf_counter()
    spec.require("surface", "ball", "ramp", "simulation", command="check")
    # a launch whose energy falls below every exit is captured for good: stop it there
    # (trap.py; only captured launches are affected, and the check asks only which fly off)
    problem = problem_from_spec(spec).with_(stop_trapped=True)
    g, k = gravity(spec.units), ball_k(spec)
    H = np.sort(np.asarray(ramp_heights(spec), dtype=float))
    v = v_in_from_height(H, g, k)
    lr = _full_launches(problem, v, progress)
    unsafe = unsafe_mask(lr.outcome)

    out: dict = {"safe": not bool(unsafe.any()), "model": problem.model, "damping": problem.damping}
    if problem.model == "ball":
        out["ball"] = _ball_summary(problem, H, lr)
    first = None
    if unsafe.any():
        i = int(np.flatnonzero(unsafe)[0])
        first = {"height": float(H[i]), "v_in": float(v[i]), "outcome": OUTCOMES[int(lr.outcome[i])],
                 "reason": _why(problem, int(lr.outcome[i]), float(lr.x_end[i]), float(lr.y_end[i])),
                 "x": float(lr.x_end[i]), "y": float(lr.y_end[i]), "t": float(lr.t_end[i])}
        if i == 0:
            highest = None
        else:
            highest = highest_safe(make_launcher(problem), float(H[i - 1]), float(H[i]), g, k, rel_tol)
    else:
        highest = float(H[-1])
    out["highest_safe_height"] = highest
    out["first_failure"] = first

    # v_critical and windows over the ramp's speeds (reusing these launches)
    initial = Launches(v, lr.outcome, lr.bounces, lr.v_out, lr.bounce_times)
    sw = sweep(problem, v, initial=initial, rel_tol=v_rel_tol, error_samples=0, tn=False, k=1, k_edge=1,
               edge_rel_tol=edge_rel_tol, gap_rel_tol=gap_rel_tol, bounces=(2,))
    vc = sw["v_critical"]
    out["v_critical"] = vc
    out["v_critical_error"] = sw["v_critical_error"]
    out["v_critical_reason"] = sw["v_critical_reason"]
    out["critical_height"] = None if vc is None else float(height_from_v_in(vc, g, k))
    vmin, vmax = float(v[0]), float(v[-1])
    reach = []
    for w in sw["windows"]:
        if w["bounces"] == 2 and vmin < w["lo"] and w["hi"] < vmax:
            reach.append({"lo": w["lo"], "hi": w["hi"], "height_lo": float(height_from_v_in(w["lo"], g, k)),
                          "height_hi": float(height_from_v_in(w["hi"], g, k)),
                          "v_out_max": w.get("v_out_max"), "edge_error": w.get("edge_error")})
    out["reachable_windows"] = reach
    out["machining"] = machining(spec)
    out["heights"] = H
    out["v_in"] = v
    out["outcomes"] = [OUTCOMES[int(o)] for o in lr.outcome]
    out["bounces"] = lr.bounces
    out["v_out"] = lr.v_out
    out["seconds"] = time.perf_counter() - t0
    return out


def _ball_summary(problem, H, lr) -> dict:
    """The finite ball's contact figures over the ramp's heights: the largest slip ratio
    |F_t|/N (the static friction the rolling needs) and where, the counts of the ball's
    unsafe outcomes, and the surface's bridging limit."""
    from .models import BRIDGED, OUTCOMES, SLIPPED

    s = np.asarray(lr.max_slip, dtype=float)
    ok = np.isfinite(s)
    i = int(np.nanargmax(np.where(ok, s, -np.inf))) if ok.any() else None
    counts = {OUTCOMES[c]: int(np.sum(lr.outcome == c)) for c in (LOST_CONTACT, BRIDGED, SLIPPED)}
    return {"radius": float(problem.radius),
            "friction": None if not math.isfinite(problem.friction) else float(problem.friction),
            "max_slip": None if i is None else float(s[i]),
            "max_slip_height": None if i is None else float(H[i]),
            "max_slip_per_height": [None if not math.isfinite(v) else float(v) for v in s],
            "unsafe_counts": counts}


def highest_safe(launch, h_safe: float, h_fail: float, g: float, k: float, rel_tol: float,
                 m: int = 1) -> float:
    """Highest safe release height in [h_safe, h_fail] (design units) by bisection
    (``m`` = 1, the default) or batched k-section, ``m`` launches a round, to width <= rel_tol * h_fail; returns the safe
    end of the bracket. ``launch``: a launcher ``v_in (M,) -> Launches`` (sweep.py)."""
    from .calibrate import v_in_from_height

    while h_fail - h_safe > rel_tol * h_fail:
        hs = h_safe + (h_fail - h_safe) * np.arange(1, m + 1) / (m + 1)
        r = launch(np.asarray(v_in_from_height(hs, g, k), dtype=float))
        bad = np.flatnonzero(unsafe_mask(r.outcome))
        if len(bad) == 0:
            h_safe = float(hs[-1])
        else:
            j = int(bad[0])
            h_fail = float(hs[j])
            if j > 0:
                h_safe = float(hs[j - 1])
    return h_safe


def machining(spec) -> dict | None:
    """Machining feasibility (mm): depth of the cut against stock.depth_limit,
    stock.thickness and tool.reach; tool radius against the smallest concave
    radius of the cut surface. None when the spec has neither stock nor tool."""
    if not (spec.has("stock") or spec.has("tool")):
        return None
    from ..surface import Surface

    surf = Surface.from_spec(spec)
    depth = surf.depth_mm()
    out: dict = {"depth_mm": depth}
    limits = {}
    if spec.has("stock"):
        limits["stock.depth_limit"] = float(spec.stock.depth_limit)
        limits["stock.thickness"] = float(spec.stock.thickness)
    if spec.has("tool"):
        limits["tool.reach"] = float(spec.tool.reach)
    out["limits_mm"] = {kk: (vv if math.isfinite(vv) else None) for kk, vv in limits.items()}
    over = {kk: depth - vv for kk, vv in limits.items() if depth > vv}
    out["depth_ok"] = not over
    out["depth_over_mm"] = over
    if spec.has("tool"):
        rmin = surf.min_concave_radius()
        r_mm = rmin.z * spec.scale
        out["tool_radius_mm"] = 0.5 * float(spec.tool.diameter)
        out["min_concave_radius_mm"] = r_mm if math.isfinite(r_mm) else None
        out["min_concave_at"] = None if not math.isfinite(r_mm) else [rmin.x, rmin.y]
        out["radius_ok"] = bool(out["tool_radius_mm"] <= r_mm)
    out["feasible"] = bool(out["depth_ok"])
    return out


__all__ = ["check", "machining", "end_reason", "ESCAPED"]
