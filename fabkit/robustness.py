"""Monte Carlo over the launch: how often each outcome happens when the ball is not
launched exactly on the line (``fabkit robustness``; ``fabkit design`` uses the same
scatter at a window's centre).

:func:`robustness` launches, for each entry speed, ``samples`` launches with
the transverse offset and velocity drawn from normal distributions around the
spec's ``simulation.y0`` / ``vy0`` (standard deviations ``sigma_y``,
``sigma_vy``), plus the nominal (zero-scatter) launch. The draws come from
``numpy.random.default_rng(seed)`` all at once, before any launch, so they do
not depend on chunking or on the scheduler. Per entry speed it reports the
probability of each bounce count (escaped launches) and of each outcome; the
probabilities sum to 1 and each has the binomial standard error
sqrt(p (1 - p) / samples).

Pure library code (no printing, no files): launches go through a
:class:`fabkit.launches.Engine` (in this process or on a Dask cluster).
"""

from __future__ import annotations

import math
import time

import numpy as np

from .errors import SpecError
from .launches import Engine, design_of, problem_of
from .tolerances import DEFAULT


def draw_scatter(n_v: int, samples: int, sigma_y: float, sigma_vy: float, y0: float, vy0: float,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(y0, vy0), each (n_v, samples): normal draws around the nominal launch,
    from ``default_rng(seed)``, drawn all at once (chunking cannot change them)."""
    z = np.random.default_rng(seed).standard_normal((2, n_v, samples))
    return y0 + sigma_y * z[0], vy0 + sigma_vy * z[1]


def check_scatter(sigma_y: float, sigma_vy: float, samples: int, n_v: int, tol=DEFAULT, seed: int = 0) -> None:
    """SpecError (naming the flag) for a bad sigma, sample count, launch count or seed."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**63:
        raise SpecError(f"must be a whole number in 0..2**63-1, got {seed}", key="--seed")
    for flag, s in (("--sigma-y", sigma_y), ("--sigma-vy", sigma_vy)):
        if not (isinstance(s, (int, float)) and math.isfinite(s) and s >= 0):
            raise SpecError(f"must be finite and >= 0, got {s}", key=flag)
    if not (isinstance(samples, int) and samples >= 1):
        raise SpecError(f"must be a whole number >= 1, got {samples}", key="--samples")
    total = n_v * (samples + 1)
    if total > tol.max_launches:
        raise SpecError(f"{n_v} speeds x ({samples} samples + 1 nominal) = {total} launches exceed the limit "
                        f"{tol.max_launches}", key="--samples")


#: the largest transverse velocity scatter, design units/s: far beyond any launch, and far
#: below the numbers whose draws overflow
MAX_SIGMA_VY = 1e6


def check_scatter_size(spec, sigma_y, sigma_vy) -> None:
    """SpecError (naming the flag) for a launch scatter too large to mean anything: a
    transverse offset spread wider than the footprint (most launches would start off the
    block), or a velocity spread above :data:`MAX_SIGMA_VY`. Finite, >= 0 is checked by
    the callers."""
    width = float(spec.surface.y[1] - spec.surface.y[0])
    u = spec.units
    if isinstance(sigma_y, (int, float)) and math.isfinite(sigma_y) and sigma_y > width:
        raise SpecError(f"{sigma_y:g} {u} is wider than the footprint ({width:g} {u} across): most launches "
                        "would start off the block", key="--sigma-y")
    if isinstance(sigma_vy, (int, float)) and math.isfinite(sigma_vy) and sigma_vy > MAX_SIGMA_VY:
        raise SpecError(f"must be at most {MAX_SIGMA_VY:g} {u}/s, got {sigma_vy:g}", key="--sigma-vy")


def robustness(spec, v, *, sigma_y: float, sigma_vy: float, samples: int, seed: int = 0,
               engine: Engine, tol=DEFAULT) -> dict:
    """Monte Carlo over the launch's transverse offset and velocity (module doc).

    Returns ``v_in`` (N,), ``rows`` (one per v_in: ``v_in``, ``nominal_outcome``,
    ``nominal_bounces``, ``p_bounces`` {n: P(escaped after n bounces)}, ``p_outcome``
    {outcome: P}, ``p_nominal`` (P(same outcome and bounce count as the nominal
    launch)), ``most_likely``, ``standard_error`` (largest over the row)), ``summary``,
    ``launches`` (arrays over all sampled launches, for the table), ``seconds``."""
    from .physics.outcomes import ESCAPED, OUTCOMES, outcome_names

    t0 = time.perf_counter()
    v = np.asarray(v, dtype=float).ravel()
    check_scatter(sigma_y, sigma_vy, samples, v.size, tol, seed=seed)
    design = design_of(spec)
    problem = problem_of(design)
    Y, VY = draw_scatter(v.size, samples, float(sigma_y), float(sigma_vy), problem.y0, problem.vy0, seed)
    V = np.repeat(v, samples)
    allv = np.concatenate([v, V])
    ally = np.concatenate([np.full(v.size, problem.y0), Y.ravel()])
    allvy = np.concatenate([np.full(v.size, problem.vy0), VY.ravel()])
    r = engine.launch(design, allv, ally, allvy)
    n = v.size
    nom_o, nom_b = r.outcome[:n], r.bounces[:n]
    O = r.outcome[n:].reshape(n, samples)
    B = r.bounces[n:].reshape(n, samples)
    rows = []
    for i in range(n):
        esc = O[i] == ESCAPED
        pb = {}
        for b in sorted(set(B[i][esc].tolist())):
            pb[str(int(b))] = float(np.count_nonzero(esc & (B[i] == b)) / samples)
        po = {name: float(np.count_nonzero(O[i] == j) / samples) for j, name in enumerate(OUTCOMES)}
        same = (O[i] == nom_o[i]) & ((B[i] == nom_b[i]) | (nom_o[i] != ESCAPED))
        p_nom = float(np.count_nonzero(same) / samples)
        cands = {f"escaped_{b}": p for b, p in pb.items()}
        cands.update({name: p for name, p in po.items() if name != "escaped"})
        most = max(cands.items(), key=lambda kv: kv[1])[0] if cands else None
        ps = list(pb.values()) + [p for name, p in po.items() if name != "escaped"]
        se = max((math.sqrt(p * (1 - p) / samples) for p in ps), default=0.0)
        nominal_name = (f"escaped_{int(nom_b[i])}" if nom_o[i] == ESCAPED else OUTCOMES[int(nom_o[i])])
        rows.append({"v_in": float(v[i]), "nominal_outcome": OUTCOMES[int(nom_o[i])],
                     "nominal_bounces": int(nom_b[i]), "p_bounces": pb, "p_outcome": po, "p_nominal": p_nom,
                     "most_likely": most, "most_likely_is_nominal": most == nominal_name, "standard_error": se})
    p_nom = np.array([row["p_nominal"] for row in rows])
    two_nom = np.array([row["nominal_outcome"] == "escaped" and row["nominal_bounces"] == 2 for row in rows])
    p_two = np.array([row["p_bounces"].get("2", 0.0) for row in rows])
    summary = {
        "mean_p_nominal": float(p_nom.mean()), "min_p_nominal": float(p_nom.min()),
        "v_in_min_p_nominal": float(v[int(np.argmin(p_nom))]),
        "most_likely_differs": int(sum(not row["most_likely_is_nominal"] for row in rows)),
        "nominal_two_bounce": int(two_nom.sum()),
        "mean_p_two_where_nominal_two": float(p_two[two_nom].mean()) if two_nom.any() else None,
        "mean_p_two_elsewhere": float(p_two[~two_nom].mean()) if (~two_nom).any() else None,
        "max_standard_error": float(max(row["standard_error"] for row in rows)),
        "bound_standard_error": 0.5 / math.sqrt(samples),
    }
    launches = {"v_in": V, "sample": np.tile(np.arange(samples), n), "y0": Y.ravel(), "vy0": VY.ravel(),
                "outcome": outcome_names(r.outcome[n:]), "bounces": r.bounces[n:],
                "v_out": r.v_out[n:]}
    return {"v_in": v, "rows": rows, "summary": summary, "sigma_y": float(sigma_y), "sigma_vy": float(sigma_vy),
            "samples": int(samples), "seed": int(seed), "y0": problem.y0, "vy0": problem.vy0,
            "model": problem.model, "damping": problem.damping, "launches": launches,
            "launch_count": int(allv.size), "seconds": time.perf_counter() - t0, "engine": engine.info()}
