"""Z-level roughing (``machining.stepdown``) on the finishing passes."""

from __future__ import annotations

import math

import numpy as np

from ..finish.passes import AIR_EPS


def rough_runs(spec, ws, fr, R, V, runs, passes_cut, depth_lim):
    """Z-level roughing runs: levels every ``machining.stepdown`` below the top face,
    on finishing passes at most R apart, tip at max(level, finish + leave) (never
    below the finish path plus the stock to leave: the finish path's chord error is
    within the tolerance, and the max of a level and a chord only lies higher).
    Only where the level removes material the level above left. Links between
    roughing runs retract to safe_z. Returns [(key, (k, 3) points)] in cutting order."""
    m = spec.machining
    step, leave = float(m.stepdown), float(m.leave)
    zmin = min((float(r[:, 1].min()) for p in passes_cut for r in runs[p]), default=0.0)
    bottom = zmin + leave
    if bottom >= 0:
        return []
    nlev = int(math.ceil(-bottom / step))
    # finishing passes at most R apart
    sel, last = [], -math.inf
    for p in passes_cut:
        if V[p] - last >= R or p == passes_cut[-1]:
            sel.append(p)
            last = V[p]
    out = []
    for k in range(1, nlev + 1):
        level, prev = max(-k * step, bottom), -(k - 1) * step
        for n, p in enumerate(sel):
            pieces = []
            for r in runs[p]:
                z = np.maximum(level, r[:, 1] + leave)
                act = z < prev - AIR_EPS
                # keep nodes that are active or next to an active one, in runs of >= 2
                near = act | np.r_[act[1:], False] | np.r_[False, act[:-1]]
                if not near.any():
                    continue
                edges = np.diff(np.r_[0, near.astype(np.int8), 0])
                for i, j in zip(np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]):
                    if j - i >= 2:
                        X, Y = fr.xy(r[i:j, 0], np.full(j - i, V[p]))
                        pieces.append(np.column_stack([X, Y, z[i:j]]))
            if n % 2:
                pieces = [q[::-1] for q in pieces[::-1]]
            out += [(("r", k, p), q) for q in pieces]
    return out
