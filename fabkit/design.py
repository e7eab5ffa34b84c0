"""The design search: the surface that shows the two-bounce resonance best in the given stock.

Pure library code (no printing, no files); ``fabkit design`` is the edge.

Objective
---------
A design is the spec with some keys replaced (:class:`Bound`, ``--vary KEY=LO:HI``),
re-validated from scratch. Its **observable two-bounce windows** are the two-bounce
windows the ramp can reach (both edges inside the ramp's entry speeds, as
:func:`physics.check.check` reports them) whose width in release height is at least
``min_width`` and at whose centre a launch ends in two bounces with probability at
least :data:`MIN_P_TWO` under the launch scatter (``sigma_y``, ``sigma_vy``, normal
around ``simulation.y0`` / ``vy0``, as in ``fabkit robustness``; without scatter the
nominal launch at the centre must bounce twice). Designs are ranked by
:func:`rank_key`: feasible first, then the number of observable windows, then their
total width (the issue's tie rule), then the total width of every reachable
two-bounce window (this only orders designs that tie on both, mostly those with no
observable window, so that the search has a slope to climb there).

Constraints (those of the pre-fabrication check, plus two the check only reports):
the ball stays on the part for every ramp height (no launch flies off or loses
contact); the cut's depth within ``stock.depth_limit``, ``stock.thickness`` and
``tool.reach``; the tool radius at most the surface's smallest concave radius; and
v_critical reachable with a margin: the top of the ramp launches at least
:data:`VC_MARGIN` (5 %) above v_critical, so the critical velocity can be measured.
A design that violates any is infeasible; ``violation`` measures by how much (a sum
of relative excesses), so the search is led back toward feasible designs.

Two evaluations
---------------
:func:`screen` is the cheap one the search runs: the machining constraints first (no
launch if they fail), then the ramp launched at release heights spaced
``min_width / 3`` apart (every window of the minimum width holds at least two of
them) in one batch, read by :func:`physics.sweep.critical_bracket` and
:func:`physics.sweep.find_runs` without refinement launches (v_critical to one sample
spacing, about 1 %; window edges halfway between samples, to ``min_width / 6``), then
the scatter launches at each candidate window's centre. :func:`verify` is the full one:
:func:`physics.check.check` itself with its defaults (400 heights, window edges and
v_critical bisected to 1e-6 relative, :func:`check_tolerances`; the highest safe height)
and the same centre launches. Only verified designs are reported or written; the screen only
steers the search (the report gives both counts for each finalist).

Search
------
:func:`optimize`: scipy's ``differential_evolution`` (best1bin, Latin hypercube
start, ``rng = seed``, deferred updating, no gradient polish: the objective is
piecewise constant) on the scalar :func:`objective`, with the spec's own values as
one member of the first population when they lie inside the bounds. Each
generation is one batch of designs, so a Dask cluster evaluates a population side
by side (:class:`Runner`); every evaluation is a deterministic function of the
design, so the search and its result are the same in-process and on the cluster,
and the same for the same seed. Values are rounded to :attr:`Bound.step` (1e-3 of
the range, to a power of ten) before evaluation, so the written spec carries short
numbers and is exactly the design that was verified. The best ``top`` distinct
feasible designs of the search are then verified (more, ``top`` at a time, if none
passes), and the winner is the best verified design, the spec's own included.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .cluster import Cluster
from .errors import SpecError

MIN_P_TWO = 0.8          # P(two bounces) at a window's centre for the window to count
VC_MARGIN = 0.05         # the top of the ramp launches at least 5 % above v_critical
DEFAULT_BUDGET = 48      # screen evaluations of the search
DEFAULT_TOP = 3          # finalists verified by the full check
DEFAULT_SAMPLES = 64     # scatter launches at each window centre (when a sigma > 0)
MAX_BUDGET = 100_000
MAX_SAMPLES = 100_000
TASK_PREFIX = "fabkit-design"
INVALID = 10.0           # violation of a spec the bounds make invalid


# ----------------------------------------------------------------------------
# --vary KEY=LO:HI
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Bound:
    """One searched key: a number key of the spec (``surface.params.eps``,
    ``surface.top``, ``stock.depth_limit``), or one end of a footprint interval
    (``surface.x.lo``, ``surface.y.hi``), between ``lo`` and ``hi`` as written in
    the YAML (the spec's units)."""

    key: str
    lo: float
    hi: float
    integer: bool = False

    @property
    def step(self) -> float:
        """Resolution of the search: a power of ten, at most 1e-3 of the range (1 for
        whole-number keys)."""
        if self.integer:
            return 1.0
        return 10.0 ** math.floor(math.log10((self.hi - self.lo) / 1000.0))

    def snap(self, x: float) -> float | int:
        """``x`` rounded to the step, inside [lo, hi]."""
        if self.integer:
            return int(min(max(round(x), math.ceil(self.lo)), math.floor(self.hi)))
        nd = max(0, -int(round(math.log10(self.step))))
        y = round(round(float(x) / self.step) * self.step, nd)
        return float(min(max(y, self.lo), self.hi))


PAIR_ENDS = {"lo": 0, "hi": 1}


def searchable_keys(spec) -> list[str]:
    """The keys a search may vary: every number key of the spec's sections,
    ``surface.params.<name>``, and the ends of the footprint (``surface.x.lo`` ...)."""
    from .vary import variable_keys
    from .spec import SCHEMA, Num

    keys = [k for k in variable_keys(spec) if k.startswith("surface.params.")
            or isinstance(SCHEMA[k.split(".")[0]][k.split(".")[1]], Num)]
    if spec.has("surface"):
        keys += [f"surface.{ax}.{end}" for ax in ("x", "y") for end in PAIR_ENDS]
    return keys


def parse_bound(text: str, spec, flag: str = "--vary") -> Bound:
    """``KEY=LO:HI`` -> :class:`Bound`; SpecError naming ``--vary`` (did-you-mean
    for an unknown key)."""
    from .vary import check_interval, parse_number, split_key
    from .spec import SCHEMA

    key, rhs = split_key(text, spec, flag, "KEY=LO:HI", searchable_keys(spec),
                         "not a number key (a search varies numbers)")
    parts = rhs.split(":")
    if len(parts) != 2 or not all(p.strip() for p in parts):
        raise SpecError(f"{key}: expected LO:HI, got {rhs!r}", key=flag)
    lo, hi = parse_number(parts[0], "LO", flag), parse_number(parts[1], "HI", flag)
    check_interval(key, lo, hi, spec, flag)       # the key's own range, and a span the search can divide
    integer = False
    sec, _, name = key.partition(".")
    if not key.startswith("surface.params.") and name in SCHEMA[sec]:
        integer = bool(getattr(SCHEMA[sec][name], "integer", False))
        if integer and math.floor(hi) < math.ceil(lo):
            raise SpecError(f"{key}: no whole number in {lo:g}:{hi:g}", key=flag)
    return Bound(key, lo, hi, integer)


def check_bounds(bounds: list[Bound]) -> None:
    if not bounds:
        raise SpecError("give at least one KEY=LO:HI to search", key="--vary")
    keys = [b.key for b in bounds]
    for k in keys:
        if keys.count(k) > 1:
            raise SpecError(f"{k} is varied twice", key="--vary")


def current_value(spec, key: str) -> float | None:
    """The spec's own value of a searchable key (None if unset)."""
    parts = key.split(".")
    if key.startswith("surface.params."):
        return float(spec.surface.params[parts[2]])
    if len(parts) == 3:
        return float(getattr(spec.surface, parts[1])[PAIR_ENDS[parts[2]]])
    v = getattr(getattr(spec, parts[0]), parts[1])
    return None if v is None or not math.isfinite(float(v)) else float(v)


def overrides(spec, bounds: list[Bound], x) -> dict:
    """``{dotted key: value}`` for :meth:`Spec.with_overrides` (a footprint end
    replaces the interval with the other end kept)."""
    out: dict = {}
    for b, v in zip(bounds, x):
        parts = b.key.split(".")
        if len(parts) == 3 and parts[0] == "surface" and parts[1] in ("x", "y"):
            pair = out.get(f"surface.{parts[1]}") or [float(e) for e in getattr(spec.surface, parts[1])]
            pair[PAIR_ENDS[parts[2]]] = v
            out[f"surface.{parts[1]}"] = pair
        else:
            out[b.key] = v
    return out


# ----------------------------------------------------------------------------
# options and the launch scatter
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Options:
    """What makes a window observable. ``min_width``: design units of release height;
    ``sigma_y`` (design units) and ``sigma_vy`` (design units/s): launch scatter;
    ``samples``: scatter launches at a window's centre; ``seed``: their draws."""

    min_width: float
    sigma_y: float = 0.0
    sigma_vy: float = 0.0
    samples: int = DEFAULT_SAMPLES
    seed: int = 0

    @property
    def scatter(self) -> bool:
        return self.sigma_y > 0 or self.sigma_vy > 0


def check_options(opts: Options, spec) -> None:
    for flag, s in (("--sigma-y", opts.sigma_y), ("--sigma-vy", opts.sigma_vy)):
        if not (math.isfinite(s) and s >= 0):
            raise SpecError(f"must be finite and >= 0, got {s}", key=flag)
    if not (math.isfinite(opts.min_width) and opts.min_width > 0):
        raise SpecError(f"must be finite and > 0, got {opts.min_width}", key="--min-width")
    if not 1 <= opts.samples <= MAX_SAMPLES:
        raise SpecError(f"must be a whole number in 1..{MAX_SAMPLES}, got {opts.samples}", key="--samples")
    if not 0 <= opts.seed < 2**63:      # as fabkit robustness (a seed JSON readers can hold)
        raise SpecError(f"must be a whole number in 0..2**63-1, got {opts.seed}", key="--seed")
    from .robustness import check_scatter_size

    check_scatter_size(spec, opts.sigma_y, opts.sigma_vy)
    from .physics.calibrate import ramp_heights

    H = ramp_heights(spec)
    span = float(np.max(H) - np.min(H))
    if opts.min_width >= span:
        raise SpecError(f"{opts.min_width:g} {spec.units} is not less than the ramp's range of heights "
                        f"({float(np.min(H)):g}..{float(np.max(H)):g} {spec.units})", key="--min-width")
    if opts.min_width < 1e-9 * span:     # the screen spaces its heights min_width / 3 apart
        raise SpecError(f"{opts.min_width:g} {spec.units} is below 1e-9 of the ramp's range of heights "
                        f"({span:g} {spec.units}): no window can be measured that narrow", key="--min-width")


def scatter_draws(opts: Options, y0: float, vy0: float) -> tuple[np.ndarray, np.ndarray]:
    """The launch offsets (y0, vy0) tried at every window centre, (M,) each: the
    nominal launch alone without scatter; else M normal draws from
    ``default_rng(seed)``, the same for every window and every design (common random
    numbers: designs are compared on the same launches)."""
    if not opts.scatter:
        return np.array([y0]), np.array([vy0])
    z = np.random.default_rng(opts.seed).standard_normal((2, opts.samples))
    return y0 + opts.sigma_y * z[0], vy0 + opts.sigma_vy * z[1]


# ----------------------------------------------------------------------------
# evaluation: screen (the search) and verify (the full check)
# ----------------------------------------------------------------------------
def _problem(spec):
    from .physics.models import problem_from_spec

    # captured launches stop once trapped (physics/trap.py), as in the check
    return problem_from_spec(spec).with_(stop_trapped=True)


def _machining_violation(m: dict | None) -> tuple[float, str]:
    """(violation, reason) of the machining constraints (0, '' when met): the depth limits
    and the tool radius against the smallest concave radius. (The finite ball's own
    contact limits, bridging, lost contact and slip, are the check's: dynamic, where the
    ball rolls, not over the whole footprint.)"""
    if m is None:
        return 0.0, ""
    viol, why = 0.0, []
    for key, over in (m.get("depth_over_mm") or {}).items():
        lim = m["limits_mm"][key]
        viol += over / lim
        why.append(f"the cut is {m['depth_mm']:.2f} mm deep, over {key} ({lim:g} mm)")
    if m.get("radius_ok") is False:
        r = m["min_concave_radius_mm"]
        viol += m["tool_radius_mm"] / r - 1.0
        why.append(f"tool radius {m['tool_radius_mm']:.3f} mm > smallest concave radius {r:.3f} mm")
    return viol, "; ".join(why)


def _vc_violation(vc: float | None, v_top: float, reason: str) -> tuple[float, str]:
    if vc is None:
        # above the ramp (not reached), or below its lowest launch (every launch escapes
        # after one bounce): either way the ramp cannot bracket it, so it cannot be measured
        return 1.0, f"v_critical cannot be measured with this ramp ({reason})"
    need = (1.0 + VC_MARGIN) * vc
    if v_top >= need:
        return 0.0, ""
    return (need - v_top) / vc, (f"the top of the ramp launches at {v_top:.4g}, less than {1 + VC_MARGIN:g} x "
                                 f"v_critical = {need:.4g}")


def _centres(spec, problem, windows: list[dict], opts: Options) -> list[dict]:
    """Each window ``{lo, hi, height_lo, height_hi}`` with ``width`` (release height),
    and, for those at least ``min_width`` wide, ``p_two``: the fraction of the scatter
    launches at the centre height that end in two bounces (one batch for all)."""
    from .physics.check import entry_speeds
    from .physics.integrate import launch_batch
    from .physics.models import ESCAPED

    Y, VY = scatter_draws(opts, problem.y0, problem.vy0)
    out, todo = [], []
    for w in windows:
        w = dict(w)
        w["width"] = float(w["height_hi"] - w["height_lo"])
        w["centre"] = 0.5 * float(w["height_hi"] + w["height_lo"])
        w["p_two"] = None
        w["observable"] = False
        if w["width"] >= opts.min_width:
            todo.append(len(out))
        out.append(w)
    if todo:
        m = Y.size
        v = np.repeat(entry_speeds(spec, [out[i]["centre"] for i in todo]), m)
        r = launch_batch(problem, v, np.tile(Y, len(todo)), np.tile(VY, len(todo)), workers=1)
        two = ((np.asarray(r.outcome) == ESCAPED) & (np.asarray(r.bounces) == 2)).reshape(len(todo), m)
        for q, i in enumerate(todo):
            p = float(two[q].mean())
            out[i]["p_two"] = p
            out[i]["observable"] = p >= MIN_P_TWO
    return out


def _summarise(ev: dict) -> dict:
    obs = [w for w in ev["windows"] if w["observable"]]
    ev["observable"] = len(obs)
    ev["observable_width"] = float(sum(w["width"] for w in obs))
    ev["two_width"] = float(sum(w["width"] for w in ev["windows"]))
    return ev


def _infeasible(stage: str, viol: float, reason: str, **extra) -> dict:
    ev = {"stage": stage, "feasible": False, "violation": float(viol), "reason": reason, "windows": [],
          "v_critical": None, "v_top": None, "depth_mm": None, "check": None}
    ev.update(extra)
    return _summarise(ev)


def screen_heights(spec, min_width: float) -> np.ndarray:
    """The screen's release heights: spaced at most ``min_width / 3`` over the ramp's
    range, never more than the check's own heights (which are then used as they are)."""
    from .physics.calibrate import ramp_heights

    H = np.sort(np.asarray(ramp_heights(spec), dtype=float))
    lo, hi = float(H[0]), float(H[-1])
    n = max(32, math.ceil(3 * (hi - lo) / min_width) + 1)
    return H if n >= H.size else np.linspace(lo, hi, n)


def screen(spec, opts: Options) -> dict:
    """The cheap evaluation the search runs (module doc): the machining constraints
    (no launch if they fail), then the check unrefined on the screen's heights. Returns
    ``feasible``, ``violation``, ``reason``, ``windows`` [{lo, hi, height_lo, height_hi,
    width, centre, p_two, observable}], ``observable``, ``observable_width``,
    ``two_width``, ``v_critical``, ``v_top``, ``depth_mm``, ``model``, ``launches``."""
    from .physics.check import check, machining

    spec.require("surface", "ball", "ramp", "simulation", command="design")
    m = machining(spec)
    viol, why = _machining_violation(m)
    if viol > 0:
        return _infeasible("screen", viol, why, depth_mm=None if m is None else m["depth_mm"], launches=0,
                           model=spec.simulation.model)
    # no refinement launches: v_critical from the bracket of neighbouring samples (its
    # midpoint, to one spacing: ~1 %, against a 5 % margin), window edges halfway between
    # the outermost two-bounce sample and the next one out (to half a spacing, min_width / 6)
    problem = _problem(spec)
    rep = check(spec, heights=screen_heights(spec, opts.min_width), problem=problem, machining_report=m,
                refine=False)
    return _judge(spec, problem, rep, opts, "screen")


def check_tolerances() -> dict:
    """The tolerances :func:`verify` runs the check with (its defaults): ``rel_tol``
    (highest safe height), ``v_rel_tol`` (v_critical), ``edge_rel_tol`` (window edges),
    ``gap_rel_tol`` (gaps between windows seen), all relative."""
    from .physics.check import TOLERANCES

    return dict(TOLERANCES)


def verify(spec, opts: Options) -> dict:
    """The full evaluation: :func:`physics.check.check` of the design and the centre
    launches on its reachable windows. Returns what :func:`screen` returns, plus
    ``v_critical_error`` and each window's ``edge_error`` (the check's bisection brackets,
    half-widths in v_in), ``check`` ('pass' | 'fail': what ``fabkit check`` would say), ``highest_safe_height``,
    ``first_failure``, ``machining``, and ``sweep`` (the check's heights, outcomes,
    bounces and v_out, for the plot)."""
    from .physics.check import check

    problem = _problem(spec)
    return _judge(spec, problem, check(spec, problem=problem), opts, "check")


def _judge(spec, problem, rep, opts: Options, stage: str) -> dict:
    """A design's evaluation from its check report ``rep``: the check's verdict, the
    search's constraints (the check's, plus the tool radius and the v_critical margin)
    with their violation, and the reachable windows with their centre launches."""
    viol, why = _machining_violation(rep.machining)
    reasons = [why] if why else []
    if not rep.ramp_safe:
        from .physics.models import unsafe as unsafe_mask

        viol += float(unsafe_mask(rep.outcome).mean())
        f = rep.first_failure
        reasons.append(f"release height {f['height']:.4g} {spec.units} {f['outcome'].replace('_', ' ')} "
                       f"({f['reason']})")
    v_top = float(np.max(rep.v_in))
    dv, why = _vc_violation(rep.v_critical, v_top, rep.v_critical_reason)
    viol += dv
    if why:
        reasons.append(why)
    m = rep.machining
    windows = []
    if rep.ramp_safe or stage == "check":
        windows = _centres(spec, problem, [{kk: w.get(kk) for kk in ("lo", "hi", "height_lo", "height_hi",
                                                                    "edge_error")}
                                           for w in rep.reachable_windows], opts)
    ev = {"stage": stage, "model": rep.model, "feasible": viol == 0, "violation": viol,
          "reason": "; ".join(reasons), "check": None if stage == "screen" else ("pass" if rep.safe else "fail"),
          "v_critical": rep.v_critical, "v_top": v_top, "depth_mm": None if m is None else m["depth_mm"],
          "windows": windows,
          "launches": rep.launches + sum(1 for w in windows if w["p_two"] is not None) * (
              opts.samples if opts.scatter else 1)}
    if stage == "check":
        ev.update(critical_height=rep.critical_height, highest_safe_height=rep.highest_safe_height,
                  first_failure=rep.first_failure, machining=m, v_critical_error=rep.v_critical_error,
                  sweep={"heights": rep.heights, "v_in": rep.v_in, "outcome": rep.outcomes,
                         "bounces": rep.bounces, "v_out": rep.v_out})
    return _summarise(ev)


def rank_key(ev: dict) -> tuple:
    """Larger is better: (feasible, observable windows, their total width, the total
    width of all reachable two-bounce windows, -violation); infeasible designs by their
    violation alone."""
    if ev is None:
        return (False, 0, 0.0, 0.0, -math.inf)
    if not ev["feasible"]:
        return (False, 0, 0.0, 0.0, -float(ev["violation"]))
    return (True, int(ev["observable"]), round(ev["observable_width"], 12),
            round(ev["two_width"], 12), -float(ev["violation"]))


def objective(ev: dict, span: float) -> float:
    """The scalar the optimizer minimizes: 1 + violation for an infeasible design (> 0);
    else -(observable + 0.999 observable_width / span + 0.001 two_width / span) (<= 0),
    ``span`` the ramp's range of heights (so each width term is below 1 and the count
    decides first)."""
    if not ev["feasible"]:
        return 1.0 + min(float(ev["violation"]), 1e6)
    return -(ev["observable"] + 0.999 * ev["observable_width"] / span + 0.001 * ev["two_width"] / span)


def evaluate(kind: str, raw: dict, path: str, opts: Options) -> dict:
    """One evaluation of a design given as its raw spec mapping (what a Dask task
    carries: compiled surfaces do not pickle). ``kind``: 'screen' | 'verify'. An
    invalid spec is an infeasible design whose reason is the error."""
    from .spec import validate

    t0 = time.perf_counter()
    try:
        spec = validate(raw, path)
        ev = screen(spec, opts) if kind == "screen" else verify(spec, opts)
    except SpecError as exc:
        ev = _infeasible(kind if kind == "screen" else "check", INVALID, str(exc), launches=0)
    ev["seconds"] = time.perf_counter() - t0
    return ev


# ----------------------------------------------------------------------------
# where evaluations run
# ----------------------------------------------------------------------------
class Runner:
    """Evaluates batches of designs: in this process one after the other, or on a
    Dask cluster (``scheduler``, :class:`fabkit.cluster.Cluster`) one task per design
    (``fabkit-design-<id>``), side by side. ``progress(done)``: called with the running
    count of evaluations."""

    def __init__(self, scheduler: str | None = None, *, progress=None, timeout: float = 10.0):
        self.address = scheduler
        self.progress = progress
        self.cluster = Cluster(scheduler, timeout) if scheduler else None
        self.done = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.cluster is not None:
            self.cluster.close()

    def _tick(self, *_):
        self.done += 1
        if self.progress is not None:
            self.progress(self.done)

    def map(self, kind: str, specs: list, opts: Options) -> list[dict]:
        if self.cluster is None:
            out = []
            for s in specs:
                out.append(evaluate(kind, s.raw, s.path, opts))
                self._tick()
            return out
        return self.cluster.run(evaluate, [(kind, s.raw, s.path, opts) for s in specs], TASK_PREFIX,
                                on_done=self._tick)

    def info(self) -> dict:
        if self.cluster is None:
            return {"scheduler": self.address, "tasks": 0, "workers": {}}
        return self.cluster.info()


# ----------------------------------------------------------------------------
# the optimizer
# ----------------------------------------------------------------------------
def population_size(ndim: int, budget: int) -> int:
    """Designs per generation: 4 per searched key, 10..24, never above the budget."""
    return max(5, min(budget, max(10, min(24, 4 * ndim))))


def optimize(fn, lo, hi, *, budget: int, seed: int, x0=None, integrality=None) -> dict:
    """Minimize ``fn`` over the box [lo, hi] by differential evolution within
    ``budget`` evaluations. ``fn(X (S, D)) -> (S,)`` evaluates a whole population at
    once (one call per generation). Deterministic for a seed. Returns ``x``, ``fun``,
    ``population``, ``generations``, ``calls`` (the points evaluated, in order)."""
    from scipy.optimize import differential_evolution

    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    d = lo.size
    if not isinstance(budget, int) or budget < 5:
        raise SpecError(f"must be a whole number >= 5, got {budget}", key="--budget")
    S = population_size(d, budget)
    popsize = max(1, math.ceil(S / d))
    S = popsize * d if popsize * d >= 5 else 5
    maxiter = max(0, budget // S - 1)
    calls: list = []

    def f(x):
        X = np.atleast_2d(np.asarray(x, dtype=float).T).reshape(-1, d)
        y = np.asarray(fn(X), dtype=float)
        calls.extend(zip(X.tolist(), y.tolist()))
        return y

    if x0 is not None:
        x0 = np.clip(np.asarray(x0, dtype=float), lo, hi)
    res = differential_evolution(f, list(zip(lo, hi)), strategy="best1bin", maxiter=maxiter, popsize=popsize,
                                 tol=0.0, atol=0.0, rng=np.random.default_rng(seed), polish=False,
                                 init="latinhypercube", updating="deferred", vectorized=True, x0=x0,
                                 integrality=integrality)
    return {"x": np.asarray(res.x, dtype=float), "fun": float(res.fun), "population": S,
            "generations": maxiter, "calls": calls}


# ----------------------------------------------------------------------------
# the search
# ----------------------------------------------------------------------------
@dataclass
class Search:
    """The run's state: every screened design by its (snapped) values."""

    spec: object
    bounds: list
    opts: Options
    runner: Runner
    span: float
    screened: dict = field(default_factory=dict)    # values -> evaluation
    history: list = field(default_factory=list)     # (values, objective) in evaluation order

    def design_spec(self, values: tuple):
        return self.spec.with_overrides(overrides(self.spec, self.bounds, values))

    def batch(self, X) -> np.ndarray:
        vals = [tuple(b.snap(x) for b, x in zip(self.bounds, row)) for row in np.asarray(X)]
        new = list(dict.fromkeys(v for v in vals if v not in self.screened))
        specs, bad = [], {}
        for v in new:
            try:
                specs.append((v, self.design_spec(v)))
            except SpecError as exc:
                bad[v] = _infeasible("screen", INVALID, str(exc), launches=0, seconds=0.0)
        evs = self.runner.map("screen", [s for _, s in specs], self.opts)
        for (v, _), ev in zip(specs, evs):
            self.screened[v] = ev
        for v, ev in bad.items():
            self.screened[v] = ev
            self.runner._tick()
        out = np.array([objective(self.screened[v], self.span) for v in vals])
        for v, y in zip(vals, out):
            self.history.append((v, float(y)))
        return out


def check_request(spec, bounds: list[Bound], opts: Options, *, budget: int, top: int) -> None:
    """SpecError (naming the flag) for a request the search cannot run."""
    spec.require("surface", "ball", "ramp", "simulation", command="design")
    check_bounds(bounds)
    check_options(opts, spec)
    if isinstance(top, bool) or not isinstance(top, int) or top < 1:
        raise SpecError(f"must be a whole number >= 1, got {top}", key="--top")
    if isinstance(budget, bool) or not isinstance(budget, int) or not 5 <= budget <= MAX_BUDGET:
        raise SpecError(f"must be a whole number in 5..{MAX_BUDGET}, got {budget}", key="--budget")


def search(spec, bounds: list[Bound], opts: Options, *, runner: Runner, budget: int = DEFAULT_BUDGET,
           top: int = DEFAULT_TOP) -> dict:
    """The whole design search (module doc). Returns ``baseline`` (the spec's own
    design, verified), ``finalists`` (verified, best first, each with ``values``,
    ``screen`` and its verification), ``winner`` (the best verified design: a
    finalist or the baseline), ``winner_spec`` (its validated spec), ``history``
    ([{values, objective, observable, feasible}] in evaluation order), ``optimizer``
    and ``seconds``."""
    from .physics.calibrate import ramp_heights

    t0 = time.perf_counter()
    check_request(spec, bounds, opts, budget=budget, top=top)
    H = ramp_heights(spec)
    span = float(np.max(H) - np.min(H))
    own = tuple(current_value(spec, b.key) for b in bounds)

    # 1. the spec's own design, first, with the full check
    baseline = runner.map("verify", [spec], opts)[0]
    baseline["values"] = own

    # 2. the search on the screen
    st = Search(spec, bounds, opts, runner, span)
    inside = all(v is not None and b.lo <= v <= b.hi for b, v in zip(bounds, own))
    integrality = [b.integer for b in bounds] if any(b.integer for b in bounds) else None
    res = optimize(st.batch, [b.lo for b in bounds], [b.hi for b in bounds], budget=budget, seed=opts.seed,
                   x0=list(own) if inside else None, integrality=integrality)

    # 3. the best distinct feasible screened designs, verified `top` at a time
    ranked = sorted((v for v, ev in st.screened.items() if ev["feasible"] and v != own),
                    key=lambda v: (rank_key(st.screened[v]), [-x for x in v]), reverse=True)
    finalists: list[dict] = []
    for start in range(0, min(len(ranked), 3 * top), top):
        group = ranked[start:start + top]
        evs = runner.map("verify", [st.design_spec(v) for v in group], opts)
        for v, ev in zip(group, evs):
            ev["values"] = v
            ev["screen"] = {kk: st.screened[v][kk] for kk in ("observable", "observable_width", "v_critical",
                                                               "feasible", "reason")}
            finalists.append(ev)
        if any(ev["feasible"] for ev in evs):
            break
    finalists.sort(key=lambda ev: rank_key(ev), reverse=True)

    cands = [ev for ev in finalists if ev["feasible"]]
    best = max(cands, key=rank_key) if cands else None
    if best is None or rank_key(baseline) >= rank_key(best):
        winner = baseline if baseline["feasible"] else best
    else:
        winner = best
    winner_spec = None
    if winner is not None:
        winner_spec = spec if winner is baseline else st.design_spec(winner["values"])
    history = [{"values": list(v), "objective": y, "observable": st.screened[v]["observable"],
                "feasible": st.screened[v]["feasible"]} for v, y in st.history]
    return {"baseline": baseline, "finalists": finalists, "winner": winner, "winner_spec": winner_spec,
            "history": history, "screened": len(st.screened),
            "optimizer": {"method": "scipy.optimize.differential_evolution (best1bin, latinhypercube, deferred)",
                          "population": res["population"], "generations": res["generations"],
                          "budget": budget, "evaluations": len(res["calls"]), "seed": opts.seed},
            "options": asdict(opts), "span": span, "seconds": time.perf_counter() - t0}


def winner_yaml(result: dict, spec, bounds: list[Bound], source: str) -> str:
    """The winner as a complete spec (YAML text): the original mapping with the
    searched keys replaced and ``name`` = ``<name>.design`` (so its outputs do not
    overwrite the original's), with a header saying where it came from."""
    import copy

    import yaml

    w = result["winner"]
    raw = copy.deepcopy(result["winner_spec"].raw)
    raw["name"] = f"{spec.name[:57]}.design"
    body = yaml.safe_dump(raw, sort_keys=False, default_flow_style=None, width=100)
    vals = ", ".join(f"{b.key}={v!r}" for b, v in zip(bounds, w["values"]))
    head = [f"# fabkit design: from {source}, searching " + ", ".join(f"{b.key}={b.lo:g}:{b.hi:g}" for b in bounds),
            f"# seed {result['optimizer']['seed']}, budget {result['optimizer']['budget']}; "
            f"{'the spec as it is' if w is result['baseline'] else 'chosen'}: {vals}",
            f"# {w['observable']} observable two-bounce windows (fabkit check: {w['check']})"]
    return "\n".join(head) + "\n" + body


__all__ = ["Bound", "Options", "Runner", "evaluate", "objective", "optimize", "parse_bound", "rank_key",
           "screen", "search", "verify", "winner_yaml"]
