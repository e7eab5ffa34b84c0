"""The pre-fabrication check: does the ball stay on the milled part for every ramp height?

The one check of fabkit: ``fabkit check``, ``explore`` (each design, through its Dask
engine), ``design`` (its screen, unrefined, and its verification), ``report`` and
``ramp`` (the marks) all call :func:`check`, which returns a :class:`CheckReport` that
carries the verdict (``safe``: every ramp height safe and the cut machinable) and why.

:func:`check` launches the ramp's release heights (``ramp.heights`` sampled
densely, :func:`calibrate.ramp_heights`, or the ``heights`` given), turned into entry
speeds by :func:`entry_speeds` (the one place), with the spec's model (the finite
``ball`` unless the spec names another) and damping, through a launcher (default the
compiled engine in this process). A launch is unsafe if it flies off (reaches top -
margin, or leaves the footprint shrunk by the margin), loses contact, or (the finite
ball) bridges or slips. It reports:

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
  alone ends on any of their edges); ``window_completeness`` (:func:`sweep.completeness`):
  a window wider than the swept speeds' largest spacing is certain to be found, a narrower
  one only if a sample falls in it;
* machining feasibility when the spec has stock and tool: the depth of the cut
  against ``stock.depth_limit``, ``stock.thickness`` and ``tool.reach``, and the
  tool radius against the surface's smallest concave radius.

Pure: no printing. Raises nothing for an unsafe design; the command turns
``safe = False`` into a :class:`DesignError`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .models import BRIDGED, CAPTURED, ESCAPED, FLEW_OFF, LOST_CONTACT, OUTCOMES, SLIPPED
from .models import unsafe as unsafe_mask
from .sweep import Launches, find_runs, sweep


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


# ----------------------------------------------------------------------------
# the ramp: release height <-> entry speed, in one place
# ----------------------------------------------------------------------------
def entry_speeds(spec, heights) -> np.ndarray:
    """The entry speeds (design units/s) of release heights ``heights`` (design units, the
    drop of the ball's centre) on the spec's ramp, with the ramp's own losses
    (:func:`calibrate.entry`: the ball's descent of fabkit's ramp or the user's straight one;
    the closed form sqrt(2 g H / (1 + k)) without losses): the one place every command
    turns heights into speeds. A height from which the ball does not reach the block is a
    :class:`DesignError` that says why."""
    from ..errors import DesignError
    from .calibrate import entry

    H = np.asarray(heights, dtype=float)
    e = entry(spec, H)
    if not np.all(e.reached):
        bad = float(np.atleast_1d(H)[~np.asarray(e.reached)][0])
        raise DesignError(f"{spec.path}: a ball released from {bad:.6g} {spec.units} does not reach the block: {e.why}")
    return np.asarray(e.v_in, dtype=float).reshape(H.shape)


def release_heights(spec, v_in) -> np.ndarray:
    """The release heights (design units) that give entry speeds ``v_in`` (design
    units/s): the inverse of :func:`entry_speeds` (:func:`calibrate.release_height`, to
    1e-10 relative; nan beyond the ramp's reach). One call for many speeds: each call
    integrates the descent."""
    from .calibrate import release_height

    return np.asarray(release_height(spec, np.asarray(v_in, dtype=float)), dtype=float)


# ----------------------------------------------------------------------------
# the report
# ----------------------------------------------------------------------------
@dataclass
class CheckReport:
    """What :func:`check` found, with its verdict (:attr:`safe`) and why (:attr:`reason`).

    Arrays (M,) over the ramp's release heights ``heights`` (design units, sorted):
    ``v_in`` (design units/s), ``outcome`` (codes of :data:`models.OUTCOMES`),
    ``bounces``, ``v_out`` (nan unless escaped). ``windows``: every n-bounce window of
    the sweep; ``reachable_windows``: the two-bounce ones the ramp reaches. ``grid``:
    the launches the sweep started from (the ramp's, or ``sweep_v``'s). ``tolerances``:
    the relative tolerances it ran with; ``refined`` False: the unrefined reading of the
    samples (v_critical to one sample spacing, window edges halfway between samples,
    no highest-safe bisection)."""

    model: str
    damping: float
    units: str
    heights: np.ndarray
    v_in: np.ndarray
    outcome: np.ndarray
    bounces: np.ndarray
    v_out: np.ndarray
    first_failure: dict | None
    highest_safe_height: float | None
    v_critical: float | None
    v_critical_error: float | None
    v_critical_reason: str
    critical_height: float | None
    windows: list
    reachable_windows: list
    machining: dict | None
    ball: dict | None
    grid: object
    tolerances: dict
    refined: bool = True
    launches: int = 0
    seconds: float = 0.0
    window_completeness: dict | None = None

    @property
    def ramp_safe(self) -> bool:
        """No ramp height flies off, loses contact, bridges or slips."""
        return not bool(unsafe_mask(self.outcome).any())

    @property
    def feasible(self) -> bool:
        """The cut is machinable (no stock or tool: nothing to violate)."""
        return self.machining is None or bool(self.machining["feasible"])

    @property
    def safe(self) -> bool:
        """The verdict: safe for every ramp height and machinable."""
        return self.ramp_safe and self.feasible

    @property
    def outcomes(self) -> list[str]:
        return [OUTCOMES[int(o)] for o in self.outcome]

    @property
    def reason(self) -> str:
        """Why the check fails, one line ('' when it passes): the first failing height
        first, else the machining limit the cut exceeds."""
        f, u = self.first_failure, self.units
        if f is not None:
            return (f"UNSAFE: release height {f['height']:.4f} {u} (v_in {f['v_in']:.4g} {u}/s) "
                    f"{f['outcome'].replace('_', ' ')} at x={f['x']:.4g}, y={f['y']:.4g}, "
                    f"t={f['t']:.3g} s ({f['reason']})")
        if not self.feasible:
            m = self.machining
            key, over = next(iter(m["depth_over_mm"].items()))
            return f"UNMACHINABLE: the cut is {m['depth_mm']:.2f} mm deep, {over:.2f} mm over {key}"
        return ""

    def to_json(self) -> dict:
        """The JSON of ``fabkit check --json`` (every key of earlier versions kept;
        ``safe`` is the verdict)."""
        out = {"safe": self.safe, "highest_safe_height": self.highest_safe_height,
               "first_failure": self.first_failure, "v_critical": self.v_critical,
               "v_critical_error": self.v_critical_error, "critical_height": self.critical_height,
               "reachable_windows": self.reachable_windows, "machining": self.machining,
               "heights": self.heights, "outcomes": self.outcomes, "seconds": self.seconds, "v_in": self.v_in,
               "model": self.model}
        if self.ball is not None:
            out["ball"] = self.ball
        out.update(units=self.units, damping=self.damping, v_critical_reason=self.v_critical_reason,
                   ramp_safe=self.ramp_safe, reason=self.reason, bounces=self.bounces, v_out=self.v_out,
                   tolerances=self.tolerances,
                   # the reported windows hold no launch of another outcome down to this (relative)
                   resolution=self.tolerances.get("gap_rel_tol") if self.refined else None,
                   # windows wider than the swept speeds' largest spacing are certain to be found
                   window_completeness=self.window_completeness)
        return out


#: the check's tolerances (relative): highest safe height, v_critical, window edges,
#: gaps between windows seen
TOLERANCES = {"rel_tol": 1e-4, "v_rel_tol": 1e-6, "edge_rel_tol": 1e-6, "gap_rel_tol": 1e-4}


def _as_launches(r):
    """A launcher's result as the sweep's :class:`Launches` (a full ``LaunchResult``
    keeps only the fields the sweep reads)."""
    if isinstance(r, Launches):
        return r
    return Launches(np.asarray(r.v_in, dtype=float), np.asarray(r.outcome, dtype=np.int8),
                    np.asarray(r.bounces, dtype=int), np.asarray(r.v_out, dtype=float),
                    np.asarray(r.bounce_times, dtype=float))


def _in_process(problem, progress=None):
    """The default launcher: the compiled engine in this process, keeping the end
    states (``LaunchResult``); ``progress`` goes to the first call only."""
    from .integrate import launch_batch

    state = {"progress": progress}

    def launch(v):
        cb, state["progress"] = state["progress"], None
        return launch_batch(problem, np.asarray(v, dtype=float), **({"progress": cb} if cb is not None else {}))

    return launch


def _take(r, sl):
    """Rows ``sl`` of a launcher's result (a ``Launches`` or a ``LaunchResult``)."""
    if isinstance(r, Launches):
        return Launches(r.v_in[sl], r.outcome[sl], r.bounces[sl], r.v_out[sl], r.bounce_times[sl])
    from dataclasses import fields, replace

    return replace(r, **{f.name: getattr(r, f.name)[sl] for f in fields(r)
                         if isinstance(getattr(r, f.name), np.ndarray)})


def check(spec, *, launcher=None, heights=None, sweep_v=None, progress=None, problem=None, machining_report=None,
          refine: bool = True, rel_tol: float = TOLERANCES["rel_tol"], v_rel_tol: float = TOLERANCES["v_rel_tol"],
          edge_rel_tol: float = TOLERANCES["edge_rel_tol"], gap_rel_tol: float = TOLERANCES["gap_rel_tol"],
          tol=None, window_bounces: tuple | None = (2,), stage=None) -> CheckReport:
    """The pre-fabrication check of ``spec`` (sections surface, ball, ramp, simulation;
    stock and tool optional), on the spec's model (module doc). ``window_bounces``: the
    bounce counts whose windows are resolved and reported (default the two-bounce ones the
    check judges; None: every n, as explore reports them). Returns a
    :class:`CheckReport`; raises nothing for an unsafe design.

    ``launcher``: ``v_in (M,) -> Launches`` running the spec's problem (default: the
    compiled engine in this process; explore passes its Dask engine). ``heights``: the
    release heights to launch (default the ramp's, :func:`calibrate.ramp_heights`).
    ``sweep_v``: the entry speeds v_critical and the windows are swept over (default
    the ramp's own), launched in one batch with the ramp's. ``problem``: the spec's
    :class:`models.Problem` if already built. ``machining_report``: :func:`machining`
    of the spec if already computed. ``refine`` False: no refinement launches (see
    :class:`CheckReport`). Heights in design units, speeds in design units/s. ``stage(name)``:
    called as each stage after the ramp's launches starts (a progress bar's stage names)."""
    from ..tolerances import DEFAULT
    from .calibrate import ramp_heights
    from .models import problem_from_spec

    t0 = time.perf_counter()
    tol = DEFAULT if tol is None else tol
    spec.require("surface", "ball", "ramp", "simulation", command="check")
    if problem is None:
        # a launch whose energy falls below every exit is captured for good: stop it there
        # (trap.py; only captured launches are affected, and the check asks only which fly off)
        problem = problem_from_spec(spec).with_(stop_trapped=True)
    full_results = launcher is None
    launch = _in_process(problem, progress) if launcher is None else launcher
    counted = {"n": 0}

    def counting(v):
        counted["n"] += len(v)
        return launch(v)

    def launches_of(v):
        return _as_launches(counting(v))

    H = np.sort(np.asarray(ramp_heights(spec) if heights is None else heights, dtype=float))
    v = entry_speeds(spec, H)
    if sweep_v is None:
        lr = counting(v)
        grid = _as_launches(lr)
        vs = v
    else:
        vs = np.sort(np.asarray(sweep_v, dtype=float))
        both = counting(np.concatenate([vs, v]))
        n = vs.size
        grid = _as_launches(_take(both, slice(0, n)))
        lr = _take(both, slice(n, None))
    ramp = _as_launches(lr)
    bad = unsafe_mask(ramp.outcome)

    first = highest = None
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        # the end state of the failing launch: from the launcher if it kept it, else that
        # one launch again in this process (a launch does not depend on its batch)
        end = lr if full_results else _in_process(problem)(v[i:i + 1])
        j = i if full_results else 0
        o = int(end.outcome[j])
        first = {"height": float(H[i]), "v_in": float(v[i]), "outcome": OUTCOMES[o],
                 "reason": _why(problem, o, float(end.x_end[j]), float(end.y_end[j])),
                 "x": float(end.x_end[j]), "y": float(end.y_end[j]), "t": float(end.t_end[j])}
        if i > 0 and refine and stage is not None:
            stage("finding the highest safe height")
        if i > 0:
            highest = (highest_safe(launches_of, float(H[i - 1]), float(H[i]), lambda h: entry_speeds(spec, h),
                                    rel_tol) if refine else float(H[i - 1]))
    else:
        highest = float(H[-1])

    # v_critical and windows over the swept speeds (reusing these launches)
    sw = sweep(problem, vs, launcher=launches_of, initial=grid, rel_tol=v_rel_tol, error_samples=0, tn=False,
               k=1, k_edge=1, edge_rel_tol=edge_rel_tol, gap_rel_tol=gap_rel_tol, refine=refine, tol=tol,
               bounces=window_bounces, stage=stage)
    vc = sw["v_critical"]
    windows = sw["windows"] if refine else _midpoint_windows(vs, grid)
    vmin, vmax = float(v[0]), float(v[-1])
    inside = [w for w in windows if w["bounces"] == 2 and vmin < w["lo"] and w["hi"] < vmax]
    # every height this report states, in one inverse calibration (each call integrates the descent)
    speeds = [s for w in inside for s in (w["lo"], w["hi"])] + ([vc] if vc is not None else [])
    if speeds and stage is not None:
        stage("the windows' release heights")
    hs = release_heights(spec, np.asarray(speeds, dtype=float)) if speeds else np.zeros(0)
    reach = [{"lo": w["lo"], "hi": w["hi"], "height_lo": float(hs[2 * i]), "height_hi": float(hs[2 * i + 1]),
              "v_out_max": w.get("v_out_max"), "edge_error": w.get("edge_error")} for i, w in enumerate(inside)]
    m = machining(spec) if machining_report is None else machining_report
    ball = _ball_summary(problem, H, lr) if problem.model == "ball" else None
    return CheckReport(
        model=problem.model, damping=problem.damping, units=spec.units, heights=H, v_in=v,
        outcome=np.asarray(ramp.outcome, dtype=np.int8), bounces=np.asarray(ramp.bounces, dtype=int),
        v_out=np.asarray(ramp.v_out, dtype=float), first_failure=first, highest_safe_height=highest,
        v_critical=vc, v_critical_error=sw["v_critical_error"], v_critical_reason=sw["v_critical_reason"],
        critical_height=None if vc is None else float(hs[-1]), windows=windows,
        reachable_windows=reach, machining=m, ball=ball, grid=grid,
        tolerances={"rel_tol": rel_tol, "v_rel_tol": v_rel_tol, "edge_rel_tol": edge_rel_tol,
                    "gap_rel_tol": gap_rel_tol},
        refined=refine, launches=counted["n"], seconds=time.perf_counter() - t0,
        window_completeness=_completeness(sw["window_completeness"], H if sweep_v is None else None))


def _completeness(c: dict | None, H) -> dict | None:
    """The sweep's :func:`sweep.completeness` of the swept speeds, with, when those are
    the ramp's own, ``certain_height_width``: the largest spacing of the release heights
    (a window wider than that in release height holds a sample and is found)."""
    if c is None or H is None or len(H) < 2:
        return c
    return dict(c, certain_height_width=float(np.max(np.diff(np.sort(np.asarray(H, dtype=float))))))


def _midpoint_windows(v: np.ndarray, res) -> list[dict]:
    """The windows of sorted samples without refinement: each run of equal bounce
    counts (n >= 2), its edges halfway between its outermost samples and the next ones
    out (to half a sample spacing; the range's own end where the run reaches it)."""
    out = []
    for nb, i, j in find_runs(res):
        lo = 0.5 * (v[i - 1] + v[i]) if i > 0 else float(v[i])
        hi = 0.5 * (v[j] + v[j + 1]) if j + 1 < v.size else float(v[j])
        out.append({"bounces": nb, "lo": float(lo), "hi": float(hi), "samples": j - i + 1, "edge_error": None})
    return out


def _ball_summary(problem, H, lr) -> dict:
    """The finite ball's contact figures over the ramp's heights: the largest slip ratio
    |F_t|/N (the static friction the rolling needs) and where, the counts of the ball's
    unsafe outcomes, and the surface's bridging limit. (The slip ratio only when the
    launcher kept it.)"""
    s = np.asarray(getattr(lr, "max_slip", np.full(len(H), np.nan)), dtype=float)
    ok = np.isfinite(s)
    i = int(np.nanargmax(np.where(ok, s, -np.inf))) if ok.any() else None
    counts = {OUTCOMES[c]: int(np.sum(lr.outcome == c)) for c in (LOST_CONTACT, BRIDGED, SLIPPED)}
    return {"radius": float(problem.radius),
            "friction": None if not math.isfinite(problem.friction) else float(problem.friction),
            "max_slip": None if i is None else float(s[i]),
            "max_slip_height": None if i is None else float(H[i]),
            "max_slip_per_height": [None if not math.isfinite(v) else float(v) for v in s],
            "unsafe_counts": counts}


def highest_safe(launch, h_safe: float, h_fail: float, speeds, rel_tol: float, m: int = 1) -> float:
    """Highest safe release height in [h_safe, h_fail] (design units) by bisection
    (``m`` = 1, the default) or batched k-section, ``m`` launches a round, to width <= rel_tol * h_fail; returns the safe
    end of the bracket. ``launch``: a launcher ``v_in (M,) -> Launches`` (sweep.py);
    ``speeds``: release heights -> entry speeds (:func:`entry_speeds`)."""
    while h_fail - h_safe > rel_tol * h_fail:
        hs = h_safe + (h_fail - h_safe) * np.arange(1, m + 1) / (m + 1)
        r = launch(np.asarray(speeds(hs), dtype=float))
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


__all__ = ["CheckReport", "TOLERANCES", "check", "entry_speeds", "machining", "end_reason", "release_heights",
           "ESCAPED"]
