"""Sweeps of the entry speed: v_out(v_in), v_critical, n-bounce windows, the T_n fit.

Pure functions (no printing, no files). Launches go through a *launcher*: a
callable ``launch(v_in (M,)) -> Launches`` that runs M launches of one problem.
The default is fabkit's batched integrator (:func:`integrate.launch_batch`);
:func:`make_launcher` with a scipy method name runs the single-launch reference
path (:func:`reference.solve_launch`) instead, for tests and peers.

What :func:`sweep` computes, and how accurately
------------------------------------------------
* ``v_critical``: the smallest v_in above which every launch escapes after
  exactly one bounce. The largest sampled v_in that does not escape after one
  bounce and the next sample up bracket it; the bracket is then narrowed by
  plain bisection (or, with ``k`` > 1, batched k-section, ``k`` launches per
  round, always keeping the largest non-one-bounce launch as the lower end)
  until its width is below ``rel_tol``
  (default 1e-6) times v_critical. Reported value: the bracket's midpoint;
  ``v_critical_error``: half its width (the integrator's own error, far smaller
  at the default tolerances, adds to it). Launches that fly off or lose contact
  at the top of the range are set aside first (the surface cannot hold them);
  if no launch at the top escapes after one bounce, ``v_critical`` is None and
  ``v_critical_reason`` says why.
* ``windows``: the n-bounce windows (n >= 2), resolved to ``gap_rel_tol``
  (the *resolution*, default 1e-4 relative in v_in, reported as ``resolution``): a
  reported window holds no launch of another outcome at that resolution. From each
  maximal run of consecutive samples escaping after n bounces: probes between its
  samples, at most the resolution apart, split it where a launch of another outcome
  lies between them (near v_critical the windows crowd together, separated by capture
  gaps far narrower than the sampling); every edge is bisected to ``edge_rel_tol``
  (default ``rel_tol``) toward the boundary of the connected run, after a walk from the
  inside end at the resolution where the next launch outside is a sample
  (``edge_error``: the half-width; ``lo``/``hi``: the brackets' midpoints); each part is
  then probed again at its own scale, min(resolution |v|, width / MIN_PROBES) apart
  (MIN_PROBES = 32), and split and bisected again where needed, until each part is
  clean or narrower than the resolution. Parts narrower than the resolution (in the
  fractal region near v_critical, where outcomes alternate on every scale) cannot be
  resolved at it: they are not windows; ``unresolved_windows`` lists them
  ``{bounces, lo, hi}``. Gaps narrower than the probes' spacing are not seen.
* ``tn_fit`` (the paper's eq. tn): in each two-bounce window, v_out is maximized
  inside it: from the best of its samples and probes (at most the resolution apart),
  two rounds of batched k-section between that launch's neighbours; there T_n =
  t_2 - t_1 (time between the two bounces), at a speed inside the window. Every
  two-bounce window enters the fit. Each window gets n = the number of complete
  transverse oscillations between its bounces: n_0 = floor(T_0 / T_shape) for
  the first window (in the order of increasing v_in) and n_i = n_{i-1} +
  max(1, round((T_i - T_{i-1}) / d)) for the others, d = T_shape first and then
  the fitted T (iterated), so consecutive windows differ by one and a window
  missed by the sampling leaves a gap, named in ``missing_n``; T_shape = 2 pi /
  omega_y, omega_y = sqrt(g~ h_yy) (= sqrt(2 g~ c) for c y^2) at the bottom of
  the channel's well on y = 0. T and delta come from least squares of
  T_n = T n + delta.
* ``window_completeness`` (:func:`completeness`): windows wider than the samples'
  largest spacing are certain to be found; a narrower one is found only if a sample
  falls in it (the probes and walks refine what the samples found, they do not search
  between them).
* ``error_estimate``: a subset of escaped launches away from window edges is
  re-run at ten times tighter rtol and atol; the largest change of v_out
  (absolute and relative, where bounce counts agree) estimates the v_out error.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..errors import SpecError
from ..tolerances import DEFAULT

from .outcomes import (BRIDGED, CAPTURED, ESCAPED, FLEW_OFF, LOST_CONTACT, SLIPPED, outcome_counts,  # noqa: F401
                       outcome_names, unsafe)


@dataclass
class Launches:
    """Results of M launches (arrays of shape (M,), bounce_times (M, K))."""

    v_in: np.ndarray
    outcome: np.ndarray        # int8 index into models.OUTCOMES
    bounces: np.ndarray        # int
    v_out: np.ndarray          # design units/s, nan unless escaped
    bounce_times: np.ndarray   # (M, K) s, nan padded

    @property
    def one_bounce(self) -> np.ndarray:
        return (self.outcome == ESCAPED) & (self.bounces == 1)


def make_launcher(problem, *, method: str = "fabkit", rtol: float | None = None, atol: float | None = None,
                  progress=None):
    """A callable ``launch(v_in (M,)) -> Launches`` for ``problem``.

    method 'fabkit': the batched integrator (rtol/atol None: its defaults).
    'DOP853' | 'RK45' | 'Radau' | 'LSODA': one scipy solve_ivp per launch
    (rtol/atol None: 1e-12/1e-14, the converged reference).
    ``progress``: passed to the batched integrator for the first call only.
    """
    state = {"progress": progress}
    if method == "fabkit":
        from .integrate import launch_batch

        def launch(v):
            v = np.asarray(v, dtype=float)
            cb, state["progress"] = state["progress"], None
            kw = {}
            if cb is not None:
                kw["progress"] = cb
            r = launch_batch(problem, v, rtol=rtol, atol=atol, workers=_threads(len(v)), **kw)
            return Launches(v, np.asarray(r.outcome, dtype=np.int8), np.asarray(r.bounces, dtype=int),
                            np.asarray(r.v_out, dtype=float), np.asarray(r.bounce_times, dtype=float))

        return launch

    from .models import OUTCOMES
    from .reference import solve_launch

    kw = {"rtol": 1e-12 if rtol is None else rtol, "atol": 1e-14 if atol is None else atol}

    def launch(v):
        v = np.asarray(v, dtype=float)
        rows = [solve_launch(problem, float(vi), float(problem.y0), float(problem.vy0), method=method, **kw)
                for vi in v]
        k = max([8] + [r["bounces"] for r in rows])
        bt = np.full((len(v), k), np.nan)
        for i, r in enumerate(rows):
            bt[i, :r["bounces"]] = r["bounce_times"]
        return Launches(v, np.array([OUTCOMES.index(r["outcome"]) for r in rows], dtype=np.int8),
                        np.array([r["bounces"] for r in rows], dtype=int),
                        np.array([r["v_out"] for r in rows], dtype=float), bt)

    return launch


THREADED_BATCH = 256    # launches from which a batch runs on every core (results do not depend on it)


def _threads(n: int) -> int:
    """Threads for a batch of n launches on the compiled engine: every core for large
    batches (the window probes), one for the small rounds of the bisections."""
    import os

    return max(1, min(os.cpu_count() or 1, 8)) if n >= THREADED_BATCH else 1


def _concat(parts: list[Launches]) -> Launches:
    k = max(p.bounce_times.shape[1] for p in parts)
    bt = np.concatenate([np.pad(p.bounce_times, ((0, 0), (0, k - p.bounce_times.shape[1])),
                                constant_values=np.nan) for p in parts])
    return Launches(np.concatenate([p.v_in for p in parts]), np.concatenate([p.outcome for p in parts]),
                    np.concatenate([p.bounces for p in parts]), np.concatenate([p.v_out for p in parts]), bt)


def _split(res: Launches, sizes: list[int]) -> list[Launches]:
    out, i = [], 0
    for n in sizes:
        sl = slice(i, i + n)
        out.append(Launches(res.v_in[sl], res.outcome[sl], res.bounces[sl], res.v_out[sl],
                            res.bounce_times[sl]))
        i += n
    return out


# ----------------------------------------------------------------------------
# v_critical
# ----------------------------------------------------------------------------
def critical_bracket(v: np.ndarray, res: Launches):
    """From sorted samples: (lo, hi, reason). lo does not escape after one bounce,
    every sample from hi up does (after setting aside launches flying off or
    losing contact at the top). lo/hi None with a reason if there is no bracket."""
    bad = unsafe(res.outcome)
    top = len(v)
    while top > 0 and bad[top - 1]:
        top -= 1
    n_off = len(v) - top
    off = (f"the {n_off} launches from v_in {v[top]:.6g} up" if n_off > 1
           else f"the launch at v_in {v[-1]:.6g}") if n_off else ""
    if top == 0:
        return None, None, (f"every launch in the range ({len(v)}, v_in {v[0]:.6g} to {v[-1]:.6g}) "
                            f"{_unsafe_words(res.outcome, singular=True)}")
    e1 = res.one_bounce[:top]
    if not e1[-1]:
        if not n_off:
            return None, None, (f"no one-bounce escape at the top of the range (v_in up to {v[-1]:.6g}): "
                                "v_critical is above it")
        return None, None, (f"no one-bounce escape at v_in {v[top - 1]:.6g} (the fastest launch that stays "
                            f"on the surface), and {off} "
                            f"{_unsafe_words(res.outcome[top:], singular=n_off == 1)}: "
                            "v_critical is not in the range")
    bad = np.flatnonzero(~e1)
    if len(bad) == 0:
        if not n_off:
            return None, None, (f"every launch escapes after one bounce: v_critical is below the range "
                                f"(v_in from {v[0]:.6g})")
        low = (f"the {top} launches from v_in {v[0]:.6g} to {v[top - 1]:.6g} escape" if top > 1
               else f"the launch at v_in {v[0]:.6g} escapes")
        return None, None, (f"{low} after one bounce and {off} "
                            f"{_unsafe_words(res.outcome[top:], singular=n_off == 1)}: "
                            "v_critical is not in the range")
    i = int(bad[-1])
    return float(v[i]), float(v[i + 1]), ""


def _unsafe_words(outcome: np.ndarray, singular: bool = False) -> str:
    """What the unsafe launches among ``outcome`` did: 'fly off', 'lose contact or
    bridge', ... (only those present)."""
    words = []
    for code, one, many in ((FLEW_OFF, "flies off", "fly off"), (LOST_CONTACT, "loses contact", "lose contact"),
                            (BRIDGED, "bridges", "bridge"), (SLIPPED, "slips", "slip")):
        if (outcome == code).any():
            words.append(one if singular else many)
    return ", ".join(words[:-1]) + (" or " if len(words) > 1 else "") + words[-1] if words else "end unsafely"


def _isolate(inside_end: float, outside_end: float, gap: float, inside, scan: int = 16):
    """Generator: walks from ``inside_end`` (a launch that is inside) toward
    ``outside_end`` (one that is not) in steps of at most ``gap`` (absolute), ``scan``
    launches the first round and twice as many each round after, and stops at the first
    launch that is not inside. ``inside(Launches) -> bool array``. Returns (last inside,
    first outside): a bracket of the boundary of the connected run that starts at
    ``inside_end``, in which no gap (or island) wider than ``gap`` is left unseen.
    A plain bisection of a bracket holding several boundaries converges to any one of
    them (near v_critical the two-bounce windows crowd together, separated by gaps
    narrower than the samples' spacing): this walk is what makes the bisection that
    follows refine the right one."""
    d = outside_end - inside_end
    n_total = int(math.ceil(abs(d) / gap)) - 1 if gap > 0 else 0
    if n_total <= 0:
        return inside_end, outside_end
    step = d / (n_total + 1)
    last_in, done, size = inside_end, 0, max(int(scan), 1)
    while done < n_total:
        m = min(size, n_total - done)
        pts = inside_end + step * (done + 1 + np.arange(m))
        r = yield pts
        out = np.flatnonzero(~inside(r))
        if len(out):
            j = int(out[0])
            return (float(pts[j - 1]) if j > 0 else last_in), float(pts[j])
        last_in, done, size = float(pts[-1]), done + m, 2 * size
    return last_in, outside_end


def critical_task(lo: float, hi: float, rel_tol: float, k: int, max_rounds: int = 40,
                   gap_rel_tol: float | None = None):
    """Generator: narrows [lo, hi] (lo: not a one-bounce escape, hi: one) by
    k-section (``k`` = 1: plain bisection); yields speeds to launch, receives their
    Launches; returns (lo, hi). With ``gap_rel_tol``, a walk down from ``hi``
    (:func:`_isolate`) first finds the highest launch that is not a one-bounce escape
    to that resolution, so one-bounce islands below v_critical cannot capture the
    bisection."""
    if gap_rel_tol:
        hi, lo = yield from _isolate(hi, lo, gap_rel_tol * abs(hi), lambda r: r.one_bounce)
    for _ in range(max_rounds):
        if hi - lo <= rel_tol * abs(hi):
            break
        pts = lo + (hi - lo) * np.arange(1, k + 1) / (k + 1)
        r = yield pts
        bad = np.flatnonzero(~r.one_bounce)
        if len(bad):
            j = int(bad[-1])
            lo = float(pts[j])
            hi = float(pts[j + 1]) if j + 1 < len(pts) else hi
        else:
            hi = float(pts[0])
    return lo, hi


def _together(tasks: list):
    """Generator: drives refinement generators together, yielding every round the
    speeds all live tasks ask for as ONE array and sending each its share of the
    results; returns each task's return value. A task may itself drive sub-tasks with
    ``yield from _together(...)``."""
    results = [None] * len(tasks)
    pending = {}
    for i, t in enumerate(tasks):
        try:
            pending[i] = next(t)
        except StopIteration as stop:
            results[i] = stop.value
    while pending:
        ids = sorted(pending)
        sizes = [len(pending[i]) for i in ids]
        parts = _split((yield np.concatenate([np.asarray(pending[i], dtype=float) for i in ids])), sizes)
        pending = {}
        for i, r in zip(ids, parts):
            try:
                pending[i] = tasks[i].send(r)
            except StopIteration as stop:
                results[i] = stop.value
    return results


def run_tasks(launch, tasks: list) -> list:
    """Drive refinement generators together: every round, the speeds all live
    tasks ask for go to the launcher in ONE batch (one call into the compiled
    engine, or one set of Dask tasks, per round).
    Returns each task's return value."""
    g = _together(tasks)
    try:
        pts = next(g)
        while True:
            pts = g.send(launch(pts))
    except StopIteration as stop:
        return stop.value


def refine_critical(launch, lo: float, hi: float, *, rel_tol: float = 1e-6, k: int = 64) -> tuple[float, float]:
    """Narrow [lo, hi] (lo: not a one-bounce escape, hi: one) by batched k-section
    to width <= rel_tol * hi. Returns (lo, hi)."""
    return run_tasks(launch, [critical_task(lo, hi, rel_tol, k)])[0]


# ----------------------------------------------------------------------------
# windows
# ----------------------------------------------------------------------------
def find_runs(res: Launches) -> list[tuple[int, int, int]]:
    """Maximal runs [i, j] (inclusive) of consecutive escaped samples with the same
    bounce count n >= 2, as (n, i, j), in order of increasing index."""
    n = np.where(res.outcome == ESCAPED, res.bounces, -1)
    runs, i = [], 0
    while i < len(n):
        j = i
        while j + 1 < len(n) and n[j + 1] == n[i]:
            j += 1
        if n[i] >= 2:
            runs.append((int(n[i]), i, j))
        i = j + 1
    return runs


def two_bounce(r: Launches) -> np.ndarray:
    return (r.outcome == ESCAPED) & (r.bounces == 2)


def edge_task(a: float, b: float, side: int, rel_tol: float, k: int = 16, max_rounds: int = 40,
               gap_rel_tol: float | None = None, inside=None):
    """Generator: k-section (``k`` = 1: plain bisection) of one window edge. side -1
    (left edge): b inside the two-bounce window, a outside; +1 (right edge): a inside,
    b outside. Keeps the edge of the connected two-bounce run touching the inside end;
    returns (a, b) narrowed to width <= rel_tol * max(|a|, |b|). With ``gap_rel_tol``,
    a walk from the inside end (:func:`_isolate`) first brackets the run's first
    boundary to that resolution (gaps narrower than it are not seen). ``inside``:
    ``Launches -> bool array``, the window's outcome (default: two-bounce escapes)."""
    inside_fn = two_bounce if inside is None else inside
    if gap_rel_tol:
        gap = gap_rel_tol * max(abs(a), abs(b))
        if side < 0:
            b, a = yield from _isolate(b, a, gap, inside_fn)
        else:
            a, b = yield from _isolate(a, b, gap, inside_fn)
    for _ in range(max_rounds):
        if b - a <= rel_tol * max(abs(a), abs(b)):
            break
        p = a + (b - a) * np.arange(1, k + 1) / (k + 1)
        r = yield p
        inside = inside_fn(r)
        if side < 0:   # walk down from b while inside: p[j:] inside, p[j-1] outside
            j = k
            while j > 0 and inside[j - 1]:
                j -= 1
            a, b = (float(p[j - 1]) if j > 0 else a), (float(p[j]) if j < k else b)
        else:          # walk up from a while inside: p[:j+1] inside, p[j+1] outside
            j = -1
            while j + 1 < k and inside[j + 1]:
                j += 1
            a, b = (float(p[j]) if j >= 0 else a), (float(p[j + 1]) if j + 1 < k else b)
    return a, b


def _outcome_of(n: int):
    """The predicate of an n-bounce window: ``Launches -> bool array``."""
    def inside(r: Launches) -> np.ndarray:
        return (r.outcome == ESCAPED) & (r.bounces == n)
    return inside


def _between(a: float, b: float, resolution: float) -> np.ndarray:
    """Probes strictly between a < b, evenly spaced at most ``resolution`` * |b| apart."""
    m = int(math.ceil((b - a) / (resolution * abs(b)))) - 1 if resolution and resolution > 0 else 0
    return a + (b - a) * np.arange(1, m + 1) / (m + 1) if m > 0 else np.zeros(0)


MIN_PROBES = 32    # interior probes of a window at least, however narrow (see _clean_task)


def _parts(x: np.ndarray, ins: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [a, b] (inclusive) of True in ``ins``."""
    out, q = [], 0
    while q < len(x):
        if not ins[q]:
            q += 1
            continue
        e = q
        while e + 1 < len(x) and ins[e + 1]:
            e += 1
        out.append((q, e))
        q = e + 1
    return out


def _clean_task(lo_br: tuple, hi_br: tuple, inside, resolution: float | None, edge_rel_tol: float, k_edge: int,
                probed: float):
    """Generator: one window between the edge brackets ``lo_br`` = (outside, inside) and
    ``hi_br`` = (inside, outside), checked inside: a window at least ``resolution``
    relative wide gets interior probes at most min(resolution |v|, width / MIN_PROBES)
    apart (none where ``probed``, the spacing already launched over it, is that fine);
    where one has another outcome it splits there, the new edges are bisected to
    ``edge_rel_tol`` and each part is checked the same way. A part narrower than
    ``resolution`` relative is not resolved at that resolution: returned apart. Returns
    (windows, unresolved), each a list of (lo_br, hi_br)."""
    lo_in, hi_in = float(lo_br[1]), float(hi_br[0])
    lo, hi = 0.5 * (lo_br[0] + lo_br[1]), 0.5 * (hi_br[0] + hi_br[1])
    if resolution and hi - lo < resolution * abs(hi):
        return [], [(lo_br, hi_br)]
    if not resolution:
        return [(lo_br, hi_br)], []
    step = min(resolution * abs(hi_in), (hi_in - lo_in) / MIN_PROBES)
    if probed <= step * (1 + 1e-9):
        return [(lo_br, hi_br)], []
    m = int(math.ceil((hi_in - lo_in) / step)) - 1
    if m <= 0:
        return [(lo_br, hi_br)], []
    pts = lo_in + (hi_in - lo_in) * np.arange(1, m + 1) / (m + 1)
    r = yield pts
    ins = inside(r)
    if ins.all():
        return [(lo_br, hi_br)], []
    x = np.concatenate([[lo_in], pts, [hi_in]])
    ins = np.concatenate([[True], ins, [True]])
    spacing = (hi_in - lo_in) / (m + 1)
    edges, parts = [], _parts(x, ins)
    for a, b in parts:
        edges.append(edge_task(float(x[a - 1]), float(x[a]), -1, edge_rel_tol, k_edge, inside=inside)
                     if a > 0 else iter(()))
        edges.append(edge_task(float(x[b]), float(x[b + 1]), +1, edge_rel_tol, k_edge, inside=inside)
                     if b + 1 < len(x) else iter(()))
    br = yield from _together(edges)
    subs = [_clean_task(lo_br if a == 0 else br[2 * q], hi_br if b == len(x) - 1 else br[2 * q + 1], inside,
                        resolution, edge_rel_tol, k_edge, spacing)
            for q, (a, b) in enumerate(parts)]
    done = yield from _together(subs)
    return [w for d in done for w in d[0]], [u for d in done for u in d[1]]


def _window_task(v: np.ndarray, v_out: np.ndarray, run: tuple[int, int, int], resolution: float | None,
                 edge_rel_tol: float, k_edge: int = 1, tn: bool = True):
    """Generator: the n-bounce windows of one run of samples (``find_runs``' (n, i, j)),
    resolved. Probes between its consecutive samples, at most ``resolution`` relative
    apart, split it where a launch of another outcome lies between them; every edge of
    every part is bisected to ``edge_rel_tol`` relative (an edge next to a sample
    outside the run after a walk from the inside end at ``resolution``, as in
    :func:`edge_task`); each part is then checked inside at its own scale
    (:func:`_clean_task`: at least MIN_PROBES probes), and parts narrower than
    ``resolution`` relative are set apart as unresolved. For n = 2 with ``tn``, v_out is
    maximized inside each window. Returns (windows, unresolved): the windows in order,
    each ``{bounces, lo, hi, samples, edge_error, lo_in, hi_in}`` (``lo_in``/``hi_in``:
    the inside ends of the edge brackets, launches with the window's outcome) and, for
    n = 2 with ``tn``, ``best`` (v_in, v_out, T_n) or None; unresolved ``{bounces, lo, hi}``."""
    n, i, j = run
    inside = _outcome_of(n)
    x = np.asarray(v[i:j + 1], dtype=float)
    vout = np.asarray(v_out[i:j + 1], dtype=float)
    ins = np.ones(len(x), dtype=bool)
    sample = np.ones(len(x), dtype=bool)
    if resolution:
        pts = np.concatenate([np.zeros(0)] + [_between(float(v[q]), float(v[q + 1]), resolution)
                                             for q in range(i, j)])
        if len(pts):
            r = yield pts
            x = np.concatenate([x, pts])
            vout = np.concatenate([vout, r.v_out])
            ins = np.concatenate([ins, inside(r)])
            sample = np.concatenate([sample, np.zeros(len(pts), dtype=bool)])
            order = np.argsort(x, kind="stable")
            x, vout, ins, sample = x[order], vout[order], ins[order], sample[order]
    parts = _parts(x, ins)
    edges = []
    for a, b in parts:
        lo_out = float(x[a - 1]) if a > 0 else (float(v[i - 1]) if i > 0 else None)
        hi_out = float(x[b + 1]) if b + 1 < len(x) else (float(v[j + 1]) if j + 1 < len(v) else None)
        edges.append(edge_task(float(x[a]) if lo_out is None else lo_out, float(x[a]), -1, edge_rel_tol, k_edge,
                                gap_rel_tol=resolution, inside=inside))
        edges.append(edge_task(float(x[b]), float(x[b]) if hi_out is None else hi_out, +1, edge_rel_tol, k_edge,
                                gap_rel_tol=resolution, inside=inside))
    brackets = yield from _together(edges)
    # each part checked at its own scale: the probes so far were at most resolution |v| apart
    # between samples (a part holding a single sample: its edges only)
    spacing = [(float(np.max(np.diff(x[a:b + 1]))) if b > a else math.inf) for a, b in parts]
    checked = yield from _together([_clean_task(brackets[2 * q], brackets[2 * q + 1], inside, resolution,
                                                edge_rel_tol, k_edge, spacing[q]) for q in range(len(parts))])
    wins, unresolved = [], []
    for q, (a, b) in enumerate(parts):
        for lo_br, hi_br in checked[q][0]:
            (a1, b1), (a2, b2) = lo_br, hi_br
            held = int(np.sum(sample[a:b + 1] & (x[a:b + 1] >= b1) & (x[a:b + 1] <= a2)))
            wins.append({"bounces": n, "lo": 0.5 * (a1 + b1), "hi": 0.5 * (a2 + b2), "samples": held,
                         "edge_error": 0.5 * max(b1 - a1, b2 - a2), "lo_in": float(b1), "hi_in": float(a2)})
        for lo_br, hi_br in checked[q][1]:
            unresolved.append({"bounces": n, "lo": 0.5 * (lo_br[0] + lo_br[1]), "hi": 0.5 * (hi_br[0] + hi_br[1])})
    if n == 2 and tn:
        # v_out is maximized from the best of the samples and probes inside each window
        # (at most ``resolution`` apart): between its neighbours, within the window
        starts = []
        for w in wins:
            sel = (x >= w["lo_in"]) & (x <= w["hi_in"])
            xs, vo = x[sel], np.where(np.isfinite(vout[sel]), vout[sel], -np.inf)
            if len(xs) == 0 or not np.isfinite(vo).any():
                starts.append(_maximize_task(w["lo_in"], w["hi_in"]))
                continue
            m = int(np.argmax(vo))
            lo_m = float(xs[m - 1]) if m > 0 else w["lo_in"]
            hi_m = float(xs[m + 1]) if m + 1 < len(xs) else w["hi_in"]
            starts.append(_maximize_task(lo_m, hi_m, rounds=2))
        best = yield from _together(starts)
        for w, bb in zip(wins, best):
            w["best"] = bb
    return wins, unresolved


def resolve_windows(launch, v, res: Launches, *, resolution: float | None = 1e-4, edge_rel_tol: float = 1e-6,
                    k_edge: int = 1, tn: bool = False) -> list[dict]:
    """The resolved n-bounce windows (n >= 2) of sorted samples ``v`` with results
    ``res``, launching more through ``launch`` (v_in (M,) -> Launches): see
    :func:`_window_task`. Every window's probes and edges share one batch per round."""
    v = np.asarray(v, dtype=float)
    done = run_tasks(launch, [_window_task(v, res.v_out, run, resolution, edge_rel_tol, k_edge, tn)
                              for run in find_runs(res)])
    return [w for part in done for w in part[0]]


def _maximize_task(a: float, b: float, rounds: int = 3, k: int = 24):
    """Generator: k-section maximization of v_out over two-bounce launches in
    [a, b]; returns (v_in, v_out, t2 - t1) at the best launch found (resolution
    (b - a) / k^rounds), or None if no two-bounce launch was found."""
    best = None
    for _ in range(rounds):
        p = a + (b - a) * np.arange(0, k + 1) / k
        r = yield p
        ok = (r.outcome == ESCAPED) & (r.bounces == 2) & np.isfinite(r.v_out)
        if not ok.any():
            break
        j = int(np.argmax(np.where(ok, r.v_out, -np.inf)))
        cand = (float(p[j]), float(r.v_out[j]), float(r.bounce_times[j, 1] - r.bounce_times[j, 0]))
        if best is None or cand[1] >= best[1]:
            best = cand
        step = p[1] - p[0]
        a, b = max(a, p[j] - step), min(b, p[j] + step)
    return best


def transverse_period(problem) -> tuple[float, float]:
    """(omega_y, T_shape): the small transverse oscillation at the bottom of the
    well on y = 0, omega_y = sqrt(g~ h_yy) in rad/s (eq. xyODE_simp linearized)."""
    from scipy.optimize import minimize_scalar

    x0, x1 = problem.x_range
    xs = np.linspace(x0, x1, 2001)
    hs = np.asarray(problem.fns.h(xs, np.zeros_like(xs)))
    i = int(np.argmin(hs))
    a, b = xs[max(i - 1, 0)], xs[min(i + 1, len(xs) - 1)]
    xm = minimize_scalar(lambda x: float(problem.fns.h(x, 0.0)), bounds=(a, b), method="bounded",
                         options={"xatol": 1e-10}).x if b > a else xs[i]
    hyy = float(problem.fns.hess(xm, 0.0)[2])
    if not hyy > 0:
        return math.nan, math.nan
    omega = math.sqrt(problem.g_tilde * hyy)
    return omega, 2 * math.pi / omega


def fit_tn(T_n: list[float], v_in: list[float], T_shape: float) -> dict:
    """Eq. (tn): T_n = T n + delta by least squares (see the module docstring for n)."""
    out = {"T": None, "delta": None, "n": [], "T_n": list(T_n), "v_in": list(v_in), "T_shape": T_shape,
           "omega": 2 * math.pi / T_shape if T_shape and math.isfinite(T_shape) else None, "missing_n": []}
    if not T_n or not math.isfinite(T_shape):
        return out
    n0 = max(int(math.floor(T_n[0] / T_shape)), 0)
    d = T_shape
    n = [n0]
    for _ in range(4):   # number by consecutive differences; re-estimate the spacing from the fit
        n = [n0]
        for a, b in zip(T_n[:-1], T_n[1:]):
            n.append(n[-1] + max(1, int(round((b - a) / d))))
        if len(set(n)) < 2:
            break
        A = np.column_stack([n, np.ones(len(n))])
        (T, delta), *_ = np.linalg.lstsq(A, np.asarray(T_n), rcond=None)
        if not T > 0 or abs(T - d) < 1e-12 * d:
            break
        d = float(T)
    out["n"] = n
    # the n between the first and the last window that no window was found for (each a
    # window narrower than the samples' spacing, missed: see :func:`completeness`)
    out["missing_n"] = sorted(set(range(n[0], n[-1] + 1)) - set(n)) if n else []
    if len(set(n)) >= 2:
        A = np.column_stack([n, np.ones(len(n))])
        (T, delta), *_ = np.linalg.lstsq(A, np.asarray(T_n), rcond=None)
        out["T"], out["delta"] = float(T), float(delta)
        out["T_over_T_shape"] = float(T / T_shape)
        out["residual_max"] = float(np.max(np.abs(A @ np.array([T, delta]) - np.asarray(T_n))))
    return out


def completeness(v, v_critical: float | None = None) -> dict:
    """How complete the windows found from the sorted samples ``v`` (design units/s) are.

    A window is found from the samples that fall in it (:func:`find_runs`): one wider
    than the largest spacing between consecutive samples holds at least one sample and
    is certain to be found; a narrower one is found only where a sample happens to fall
    in it, and is missed otherwise (near v_critical the windows narrow toward zero width
    and crowd together, so some are always missed there). Returns ``certain_width``
    (the largest spacing: every window wider than it is found), ``certain_width_at``
    (the lower sample of that spacing), ``spacing_near_critical`` (the spacing of the
    two samples that bracket ``v_critical``, None without it) and ``samples``."""
    v = np.sort(np.asarray(v, dtype=float).ravel())
    if v.size < 2:
        return {"certain_width": None, "certain_width_at": None, "spacing_near_critical": None,
                "samples": int(v.size)}
    d = np.diff(v)
    i = int(np.argmax(d))
    near = None
    if v_critical is not None and v[0] <= v_critical <= v[-1]:
        j = min(max(int(np.searchsorted(v, v_critical)) - 1, 0), d.size - 1)
        near = float(d[j])
    return {"certain_width": float(d[i]), "certain_width_at": float(v[i]), "spacing_near_critical": near,
            "samples": int(v.size)}


# ----------------------------------------------------------------------------
# the sweep
# ----------------------------------------------------------------------------
def sweep(problem, v_in, *, launcher=None, method: str = "fabkit", rtol: float | None = None,
          atol: float | None = None, progress=None, rel_tol: float = 1e-6, k: int = 1,
          refine: bool = True, error_samples: int = 48, initial: Launches | None = None, tn: bool = True,
          k_edge: int = 1, edge_rel_tol: float | None = None, gap_rel_tol: float | None = 1e-4,
          bounces: tuple | None = None, tol=DEFAULT, stage=None) -> dict:
    """Launch at every ``v_in`` (N,) (design units/s, sorted ascending here) and analyse.

    Returns a dict: ``v_in`` (N,) sorted, ``v_out`` (N,) (nan unless escaped),
    ``bounces`` (N,), ``outcome`` (N,) names, ``v_critical`` (float or None),
    ``v_critical_error``, ``v_critical_reason``, ``windows`` [{bounces, lo, hi,
    samples, edge_error}] (two-bounce ones also v_in_max, v_out_max, T_n),
    ``resolution`` (the windows' resolution, relative; None without ``refine``),
    ``unresolved_windows`` [{bounces, lo, hi}] (parts narrower than the resolution),
    ``tn_fit`` {T, delta, n, T_n, v_in, T_shape, omega, missing_n},
    ``window_completeness`` (:func:`completeness`),
    ``error_estimate`` {v_out_abs, v_out_rel, launches, rtol_ref}, ``launches``
    (total run), ``seconds``. Accuracy: see the module docstring.
    ``initial``: results already computed for the sorted ``v_in`` (not re-run).
    ``tn``: False skips the v_out maximization (no T_n fit). ``k``, ``k_edge``:
    launches per refinement round for v_critical and for each window edge (default
    1: plain bisection; a launch costs a few hundredths of a millisecond on the
    compiled engine, so rounds of one launch per task are the cheapest).
    ``edge_rel_tol``: relative width the two-bounce window edges are refined to
    (default ``rel_tol``). ``gap_rel_tol``: the resolution (default 1e-4 relative):
    the windows are probed inside at most that far apart (see the module doc), and
    before the bisections a walk from the bracket's known end isolates the boundary to
    it (gaps between windows, and islands below v_critical, narrower than that are not
    seen); None skips the probes and walks. ``bounces``: resolve and report only the
    windows of these bounce counts (``check``: (2,)); None, every n >= 2.
    ``stage(name)``: called as each stage after the first launches starts (a progress bar's
    stage names: refining, estimating the error).
    Large batches (the probes) run on every core (``_threads``): results do not
    depend on it.
    """
    t0 = time.perf_counter()
    v = np.sort(np.asarray(v_in, dtype=float).ravel())
    if v.size == 0:
        raise SpecError("no launch speeds given", key="v_in")
    if v.size > tol.max_launches:
        raise SpecError(f"{v.size} launches exceed the limit {tol.max_launches}", key="v_in")
    if not np.all(np.isfinite(v)) or v[0] <= 0:
        raise SpecError("launch speeds must be finite and > 0", key="v_in")
    launch = launcher or make_launcher(problem, method=method, rtol=rtol, atol=atol, progress=progress)
    counted = {"n": 0}

    def counting(x):
        counted["n"] += len(x)
        return launch(x)

    res = initial if initial is not None else counting(v)
    out: dict = {
        "v_in": v, "v_out": res.v_out, "bounces": res.bounces,
        "outcome": outcome_names(res.outcome),
    }

    # v_critical, windows (probes, edges, v_out maxima): refinement tasks run together
    lo, hi, reason = critical_bracket(v, res)
    runs = [run for run in find_runs(res) if bounces is None or run[0] in bounces]
    e_tol = rel_tol if edge_rel_tol is None else float(edge_rel_tol)
    tasks = []
    if refine:
        tasks.append(critical_task(lo, hi, rel_tol, k, gap_rel_tol=gap_rel_tol) if lo is not None else iter(()))
        tasks += [_window_task(v, res.v_out, run, gap_rel_tol, e_tol, k_edge, tn) for run in runs]
        if stage is not None:
            stage("refining v_critical and the windows")
    done = run_tasks(counting, tasks)
    if refine and lo is not None:
        lo, hi = done[0]
    out["v_critical"] = None if lo is None else 0.5 * (lo + hi)
    out["v_critical_error"] = None if lo is None else 0.5 * (hi - lo)
    out["v_critical_reason"] = reason

    best = []
    windows = []
    if refine:
        for w in (w for part in done[1:] for w in part[0]):
            b = w.pop("best", None)
            w.pop("lo_in")
            w.pop("hi_in")
            if b is not None:
                w["v_in_max"], w["v_out_max"], w["T_n"] = b
                best.append(b)
            windows.append(w)
    else:
        for n, i, j in runs:
            w = {"bounces": n, "lo": float(v[i]), "hi": float(v[j]), "samples": j - i + 1, "edge_error": None}
            if n == 2:
                m = i + int(np.nanargmax(res.v_out[i:j + 1]))
                b = (float(v[m]), float(res.v_out[m]), float(res.bounce_times[m, 1] - res.bounce_times[m, 0]))
                w["v_in_max"], w["v_out_max"], w["T_n"] = b
                best.append(b)
            windows.append(w)
    out["windows"] = windows
    out["resolution"] = gap_rel_tol if refine else None
    out["window_completeness"] = completeness(v, out["v_critical"])
    out["unresolved_windows"] = [u for part in done[1:] for u in part[1]] if refine else []

    # eq. (tn) fit
    _, T_shape = transverse_period(problem)
    out["tn_fit"] = fit_tn([b[2] for b in best], [b[0] for b in best], T_shape)

    # error estimate: re-run a subset of escaped interior launches 10x tighter
    out["error_estimate"] = None
    if error_samples and launcher is None:
        if stage is not None:
            stage("estimating the v_out error")
        out["error_estimate"] = estimate_error(problem, v, res, method=method, rtol=rtol, atol=atol,
                                               samples=error_samples, counter=counted)
    out["launches"] = counted["n"]
    out["seconds"] = time.perf_counter() - t0
    return out


#: the keys of ``fabkit sweep --json``, in order (a contract: every key stays)
SWEEP_JSON_KEYS = ("v_in", "v_out", "bounces", "outcome", "v_critical", "windows", "tn_fit", "seconds",
                   "error_estimate", "v_critical_error", "v_critical_reason", "launches", "resolution",
                   "unresolved_windows", "model", "units", "window_completeness")


@dataclass
class SweepReport:
    """What ``fabkit sweep`` found (:func:`sweep` over a model), with its verdict.

    Arrays (N,) over the sorted entry speeds ``v_in`` (design units/s): ``v_out`` (nan
    unless escaped), ``bounces``, ``outcome`` (names of :data:`outcomes.OUTCOMES`).
    ``v_critical`` ± ``v_critical_error`` (None, and ``v_critical_reason`` says why, when
    no capture-to-escape step lies in the range); ``windows``: every n-bounce window,
    resolved to ``resolution`` (relative); ``tn_fit``: eq. (tn) over the two-bounce
    windows; ``error_estimate``: the v_out error estimated by re-running launches 10x
    tighter (None when not estimated). The verdict, :attr:`resonant`: the range shows the
    two-bounce resonance (at least one two-bounce window); :attr:`reason` says why not."""

    v_in: np.ndarray
    v_out: np.ndarray
    bounces: np.ndarray
    outcome: list
    v_critical: float | None
    v_critical_error: float | None
    v_critical_reason: str
    windows: list
    resolution: float | None
    unresolved_windows: list
    tn_fit: dict
    error_estimate: dict | None
    launches: int
    seconds: float
    model: str
    damping: float
    units: str
    window_completeness: dict | None = None

    @classmethod
    def of(cls, result: dict, problem, units: str, seconds: float | None = None) -> "SweepReport":
        """The report of :func:`sweep`'s ``result`` for ``problem`` (its model and
        damping); ``seconds``: the run's wall time (default: the sweep's own)."""
        return cls(v_in=result["v_in"], v_out=result["v_out"], bounces=result["bounces"],
                   outcome=list(result["outcome"]), v_critical=result["v_critical"],
                   v_critical_error=result["v_critical_error"], v_critical_reason=result["v_critical_reason"],
                   windows=result["windows"], resolution=result["resolution"],
                   unresolved_windows=result["unresolved_windows"], tn_fit=result["tn_fit"],
                   error_estimate=result["error_estimate"], launches=result["launches"],
                   seconds=result["seconds"] if seconds is None else seconds, model=problem.model,
                   damping=float(problem.damping), units=units,
                   window_completeness=result.get("window_completeness"))

    @property
    def two_bounce_windows(self) -> list:
        return [w for w in self.windows if w["bounces"] == 2]

    @property
    def outcome_counts(self) -> dict:
        """{outcome name: launches}, in order of first appearance."""
        return outcome_counts(self.outcome)

    @property
    def resonant(self) -> bool:
        """The verdict: at least one two-bounce window in the range."""
        return bool(self.two_bounce_windows)

    @property
    def reason(self) -> str:
        """Why the sweep shows no two-bounce window, one line ('' when it does)."""
        if self.resonant:
            return ""
        u = self.units
        where = f"v_in {float(self.v_in[0]):.4g}..{float(self.v_in[-1]):.4g} {u}/s"
        if self.v_critical is None:
            return f"no two-bounce window in {where}; no v_critical ({self.v_critical_reason})"
        return f"no two-bounce window in {where}"

    def to_json(self) -> dict:
        """The JSON of ``fabkit sweep --json`` (:data:`SWEEP_JSON_KEYS`, unchanged)."""
        return {k: getattr(self, k) for k in SWEEP_JSON_KEYS}

    def as_result(self) -> dict:
        """The mapping :func:`sweep` returns (what the figures read)."""
        out = self.to_json()
        out["damping"] = self.damping
        return out


def estimate_error(problem, v, res: Launches, *, method: str, rtol, atol, samples: int = 48,
                   counter=None) -> dict | None:
    """Largest change of v_out when a subset of escaped launches (both neighbours
    with the same bounce count, so away from window edges) is re-run with rtol and
    atol ten times tighter."""
    n = np.where(res.outcome == ESCAPED, res.bounces, -1)
    interior = np.zeros(len(v), dtype=bool)
    if len(v) >= 3:
        interior[1:-1] = (n[1:-1] >= 1) & (n[:-2] == n[1:-1]) & (n[2:] == n[1:-1])
    idx = np.flatnonzero(interior)
    if len(idx) == 0:
        return None
    idx = idx[np.unique(np.linspace(0, len(idx) - 1, min(samples, len(idx))).round().astype(int))]
    if method == "fabkit":
        from .integrate import launch_batch  # noqa: F401  (same defaults as the sweep)
        base_rtol = rtol if rtol is not None else _default_rtol(problem)
        base_atol = atol if atol is not None else _default_atol(problem)
    else:
        base_rtol = 1e-12 if rtol is None else rtol
        base_atol = 1e-14 if atol is None else atol
    tight = make_launcher(problem, method=method, rtol=base_rtol / 10, atol=base_atol / 10)(v[idx])
    if counter is not None:
        counter["n"] += len(idx)
    same = (tight.outcome == res.outcome[idx]) & (tight.bounces == res.bounces[idx]) & np.isfinite(tight.v_out)
    if not same.any():
        return None
    d = np.abs(tight.v_out[same] - res.v_out[idx][same])
    return {"v_out_abs": float(d.max()), "v_out_rel": float(np.max(d / np.abs(tight.v_out[same]))),
            "launches": int(len(idx)), "agree": int(same.sum()), "rtol": base_rtol, "rtol_ref": base_rtol / 10}


def _default_rtol(problem) -> float:
    r = getattr(problem, "rtol", None)
    return float(r) if r else 1e-10


def _default_atol(problem) -> float:
    a = getattr(problem, "atol", None)
    return float(a) if a else 1e-12
