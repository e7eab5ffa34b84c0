"""Sweeps of the phi^4 collision speed: v_out(v_in), v_critical, n-bounce windows.

The refinement is the simulator's (:mod:`fabkit.physics.sweep`): the same bracket,
batched k-section and window-edge tasks, driven by a launcher that runs a batch of
PDE collisions on one grid (:func:`fabkit.waves.phi4.collide`). Keys as ``fabkit sweep``.

Accuracy of ``v_critical``. A launch counts as a one-bounce escape when X(t) is back
at X0 before ``t_max``. Just above threshold v_out is small (v_out^2 grows about
linearly in v - v_c) and the pair needs X0 / v_out to get back, so a finite ``t_max``
moves the bisected value up by the speed at which X0 / v_out(v) equals the time left
after the collision. ``v_critical_extrapolated`` removes that: a straight-line fit of
v_out^2 against v_in over the one-bounce escapes within ``fit_width`` of v_critical,
extrapolated to v_out = 0. ``v_critical_error`` is the bracket's half-width;
``t_max_bias`` = v_critical - v_critical_extrapolated estimates the criterion's share.
Grid and step errors: docs/numerics.md ("phi^4").
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..errors import SpecError
from ..physics.sweep import Launches, critical_task, edge_task, critical_bracket, find_runs, run_tasks
from .phi4 import DEFAULT_CONFIG, OUTCOMES, Phi4Config, check_resolution, collide


def make_launcher(cfg: Phi4Config = DEFAULT_CONFIG, *, batch: int = 64, progress=None, counter=None,
                  stop_after: int | None = None):
    """``launch(v (M,)) -> Launches``: PDE collisions in batches of ``batch`` on one grid
    (``stop_after``: see :func:`fabkit.waves.phi4.collide`)."""

    def launch(v):
        v = np.asarray(v, dtype=float)
        parts = []
        for i in range(0, len(v), batch):
            parts.append(collide(v[i:i + batch], cfg, stop_after=stop_after))
            if counter is not None:
                counter["n"] += len(v[i:i + batch])
                if progress is not None:
                    progress(counter["n"])
        k = max(p.bounce_times.shape[1] for p in parts)
        bt = np.concatenate([np.pad(p.bounce_times, ((0, 0), (0, k - p.bounce_times.shape[1])),
                                    constant_values=np.nan) for p in parts])
        return Launches(v, np.concatenate([p.outcome for p in parts]).astype(np.int8),
                        np.concatenate([p.bounces for p in parts]), np.concatenate([p.v_out for p in parts]), bt)

    return launch


def extrapolate_critical(v, res: Launches, v_c: float, fit_width: float = 0.01):
    """v where v_out^2 (fitted linear in v over one-bounce escapes in [v_c, v_c + fit_width])
    reaches 0; None with fewer than 3 such launches."""
    m = res.one_bounce & (v >= v_c) & (v <= v_c + fit_width) & np.isfinite(res.v_out)
    if m.sum() < 3:
        return None
    a, b = np.polyfit(v[m], res.v_out[m] ** 2, 1)
    if not a > 0:
        return None
    return float(-b / a)


def split_runs(v: np.ndarray, runs: list[tuple[int, int, int]], probe, gap_rel_tol: float) -> list[dict]:
    """The two-bounce runs of sorted samples ``v`` (``find_runs``' ``(2, i, j)``), each
    checked between its consecutive samples for windows that the sampling merged: two
    neighbouring samples may escape after two bounces in two different windows with a
    capture between them (near v_critical the windows crowd together). Probes are
    launched (``probe(x) -> Launches``, all in one call) between consecutive samples of
    every run, spaced at most ``gap_rel_tol`` relative, so no gap wider than that is left
    unseen inside a run. Returns the connected sub-runs in order, each ``{run, lo_in,
    hi_in, lo_out, hi_out, samples}``: its outermost two-bounce launches, the launches just
    outside it (None at the range's ends) and the number of samples it holds."""
    from ..physics.sweep import two_bounce

    plan = []
    for _, i, j in runs:
        pts = []
        for q in range(i, j):
            a, b = float(v[q]), float(v[q + 1])
            n = int(math.ceil((b - a) / (gap_rel_tol * abs(b)))) - 1 if gap_rel_tol > 0 else 0
            if n > 0:
                pts.append(a + (b - a) * np.arange(1, n + 1) / (n + 1))
        plan.append(np.concatenate(pts) if pts else np.zeros(0))
    sizes = [len(x) for x in plan]
    inside = np.zeros(0, dtype=bool)
    if sum(sizes):
        inside = np.asarray(two_bounce(probe(np.concatenate(plan))), dtype=bool)
    out, at = [], 0
    for (n_b, i, j), pts, m in zip(runs, plan, sizes):
        x = np.concatenate([v[i:j + 1], pts])
        ins = np.concatenate([np.ones(j - i + 1, dtype=bool), inside[at:at + m]])
        sample = np.concatenate([np.ones(j - i + 1, dtype=bool), np.zeros(m, dtype=bool)])
        at += m
        order = np.argsort(x, kind="stable")
        x, ins, sample = x[order], ins[order], sample[order]
        q = 0
        while q < len(x):
            if not ins[q]:
                q += 1
                continue
            r = q
            while r + 1 < len(x) and ins[r + 1]:
                r += 1
            lo_out = float(x[q - 1]) if q > 0 else (float(v[i - 1]) if i > 0 else None)
            hi_out = float(x[r + 1]) if r + 1 < len(x) else (float(v[j + 1]) if j + 1 < len(v) else None)
            out.append({"run": (n_b, i, j), "lo_in": float(x[q]), "hi_in": float(x[r]), "lo_out": lo_out,
                        "hi_out": hi_out, "samples": int(sample[q:r + 1].sum())})
            q = r + 1
    return out


def phi4_sweep(v_in, cfg: Phi4Config = DEFAULT_CONFIG, *, rel_tol: float = 2e-5, k: int = 8,
               k_edge: int = 6, edge_rel_tol: float = 2e-4, gap_rel_tol: float = 2e-4, refine: bool = True,
               refine_windows: bool = True, progress=None,
               batch: int = 64, stop_after: int | None = None, launchers=None) -> dict:
    """Collide at every ``v_in`` (N,) (sorted here) and analyse, as :func:`fabkit.physics.sweep.sweep`.

    Returns ``v_in``, ``v_out``, ``bounces``, ``outcome``, ``v_critical``,
    ``v_critical_error``, ``v_critical_reason``, ``v_critical_extrapolated``,
    ``t_max_bias``, ``windows`` [{bounces, lo, hi, samples, edge_error}],
    ``launches``, ``seconds``, ``seconds_per_collision``.
    ``refine_windows``: False leaves the two-bounce window edges at the samples; True
    first probes every sampled two-bounce run between its samples (:func:`split_runs`,
    ``gap_rel_tol``) and splits it where a probe does not escape after two bounces, then
    refines each window's edges. ``launchers``: ``(launch, refine_launch)`` in place of
    the PDE (each ``v (M,) -> Launches``; the tests' closed-form stand-ins).
    ``stop_after``: end sampled launches at that bounce (shown as captured; for
    figures that colour up to four bounces). Refinement launches always stop at their
    third bounce: they only ask "one-bounce escape or not" and "two-bounce escape or not".
    """
    t0 = time.perf_counter()
    v = np.sort(np.asarray(v_in, dtype=float).ravel())
    if v.size == 0:
        raise SpecError("no launch speeds given", key="--v-in")
    if not np.all(np.isfinite(v)) or v[0] <= 0 or v[-1] >= 1:
        raise SpecError("speeds must lie in (0, 1) (units of the speed of light)", key="--v-in")
    reason = check_resolution(v, cfg.dx)
    if reason:
        raise SpecError(reason, key="--v-in")
    counted = {"n": 0}
    if launchers is None:
        launch = make_launcher(cfg, batch=batch, progress=progress, counter=counted, stop_after=stop_after)
        refine_launch = make_launcher(cfg, batch=batch, progress=progress, counter=counted, stop_after=3)
    else:
        def counting(f):
            def g(x):
                counted["n"] += len(x)
                return f(x)
            return g
        launch, refine_launch = (counting(f) for f in launchers)
    extra: list[Launches] = []

    def keep(x):
        r = refine_launch(x)
        extra.append(r)
        return r

    res = launch(v)
    out: dict = {"v_in": v, "v_out": res.v_out, "bounces": res.bounces,
                 "outcome": [OUTCOMES[int(i)] for i in res.outcome]}
    lo, hi, reason = critical_bracket(v, res)
    runs = find_runs(res)
    two_runs = [r for r in runs if r[0] == 2]
    if refine and refine_windows:
        subs = split_runs(v, two_runs, keep, gap_rel_tol)
    else:
        subs = [{"run": r, "lo_in": float(v[r[1]]), "hi_in": float(v[r[2]]),
                 "lo_out": float(v[r[1] - 1]) if r[1] > 0 else None,
                 "hi_out": float(v[r[2] + 1]) if r[2] + 1 < len(v) else None, "samples": r[2] - r[1] + 1}
                for r in two_runs]
    windows, two = [], []
    for n, i, j in runs:
        if n != 2:
            windows.append({"bounces": n, "lo": float(v[i]), "hi": float(v[j]), "samples": j - i + 1,
                            "edge_error": None})
            continue
        for sub in (x for x in subs if x["run"] == (n, i, j)):
            w = {"bounces": 2, "lo": sub["lo_in"], "hi": sub["hi_in"], "samples": sub["samples"], "edge_error": None}
            windows.append(w)
            two.append((w, sub))
    tasks = []
    if refine:
        if lo is not None:
            tasks.append(critical_task(lo, hi, rel_tol, k))
        for w, sub in (two if refine_windows else []):
            a = sub["lo_out"] if sub["lo_out"] is not None else sub["lo_in"]
            b = sub["hi_out"] if sub["hi_out"] is not None else sub["hi_in"]
            tasks.append(edge_task(a, sub["lo_in"], -1, edge_rel_tol, k_edge))
            tasks.append(edge_task(sub["hi_in"], b, +1, edge_rel_tol, k_edge))

    done = run_tasks(keep, tasks)
    if refine and lo is not None:
        lo, hi = done.pop(0)
    vc = None if lo is None else 0.5 * (lo + hi)
    out["v_critical"] = vc
    out["v_critical_error"] = None if lo is None else 0.5 * (hi - lo)
    out["v_critical_reason"] = reason
    for q, (w, sub) in enumerate(two):
        if refine and refine_windows:
            (a1, b1), (a2, b2) = done[2 * q: 2 * q + 2]
            w["lo"] = 0.5 * (a1 + b1) if sub["lo_out"] is not None else sub["lo_in"]
            w["hi"] = 0.5 * (a2 + b2) if sub["hi_out"] is not None else sub["hi_in"]
            w["edge_error"] = 0.5 * max(b1 - a1, b2 - a2)
    out["windows"] = windows
    # v_out -> 0 extrapolation over every launch run (samples and refinement)
    out["v_critical_extrapolated"] = None
    out["t_max_bias"] = None
    if vc is not None:
        allv = np.concatenate([v] + [e.v_in for e in extra])
        allr = Launches(allv, np.concatenate([res.outcome] + [e.outcome for e in extra]),
                        np.concatenate([res.bounces] + [e.bounces for e in extra]),
                        np.concatenate([res.v_out] + [e.v_out for e in extra]),
                        np.zeros((allv.size, 0)))
        ve = extrapolate_critical(allv, allr, vc)
        if ve is not None and abs(ve - vc) < 0.01:
            out["v_critical_extrapolated"] = ve
            out["t_max_bias"] = vc - ve
    out["launches"] = counted["n"]
    out["seconds"] = time.perf_counter() - t0
    out["seconds_per_collision"] = out["seconds"] / max(counted["n"], 1)
    out["config"] = config_dict(cfg)
    return out


def config_dict(cfg: Phi4Config) -> dict:
    return {"dx": cfg.dx, "dt": cfg.dt, "x0": cfg.x0, "length": cfg.length, "layer": cfg.layer,
            "layer_start": cfg.x_layer, "sigma": cfg.sigma, "t_max": cfg.t_max,
            "scheme": "cosine pseudo-spectral (DCT-I, even symmetry) + ETDRK4"}
