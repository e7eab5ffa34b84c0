"""Compiled kernel of the point spacing's simplification (:func:`fabkit.toolpath.finish.spacing._simplify`).

The numpy code works each round on every sample at once (a search of each sample's
segment, two chord errors, scattered maxima): 15 rounds over the 210 000 samples of
``specs/surface.yaml`` cost 0.8 s of CPU. This is the same rounds as one loop over
the samples per round, with the same arithmetic in the same order (the chord error
``|z - (za + t (zb - za))|``, ``t = (u - ua) / (ub - ua)``), so the same comparisons
and the same nodes, bit for bit. ``FABKIT_NO_KERNELS=1`` runs the numpy code.

Compiled with ``cache=True`` like :mod:`fabkit.toolpath.cut.stock_kernels` (numba's cache next to this
module, or ``NUMBA_CACHE_DIR``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ... import numba_start  # noqa: F401  (numba's short start-up for cached code)

jit = njit(cache=True, nogil=True, error_model="numpy")


@jit
def _chord_err(u, z, ua, za, ub, zb):
    """spacing._chord_err of one sample."""
    t = (u - ua) / (ub - ua) if ub > ua else 0.0
    return abs(z - (za + t * (zb - za)))


@jit
def _chord_rise(u, z, ua, za, ub, zb):
    """spacing._chord_rise of one sample."""
    t = (u - ua) / (ub - ua) if ub > ua else 0.0
    return z - (za + t * (zb - za))


@jit
def _tent_over(su, sz, i, ua, za, ub, zb, tent, bound):
    """The interval (i, i + 1): the larger rise of its samples above the chord
    (ua, za) - (ub, zb), at least 0, plus its tent bound exceeds ``bound`` (NaN: yes)."""
    r = max(_chord_rise(su[i], sz[i], ua, za, ub, zb), _chord_rise(su[i + 1], sz[i + 1], ua, za, ub, zb))
    r = max(r, 0.0)
    return not (r + tent[i] <= bound)


@jit
def _nanmax(w, e):
    """np.maximum: NaN if either is NaN."""
    if w != w:
        return w
    if e != e:
        return e
    return w if w >= e else e


@jit
def simplify(sp, su, sz, nodes, air, etol, rounds, tent, bound):
    """spacing._simplify's rounds on ``nodes`` (bool, modified in place): node k (by
    its rank among the current nodes) is dropped in round r if k and r have the same
    parity, its neighbours are of its pass, every sample between them is within
    ``etol`` of their chord (NaN: not), every interval (i, i + 1) between them whose
    tent bound ``tent[i]`` exceeds bound - etol has its samples' larger rise above the
    chord plus that bound within ``bound``, and no sample of its two segments, nor the
    nodes closing them, is in air (``air``)."""
    n = su.size
    ni = np.empty(n, dtype=np.int64)
    seg = np.empty(n, dtype=np.int64)
    worst = np.empty(n)
    airseg = np.empty(n, dtype=np.bool_)
    over = np.empty(n, dtype=np.bool_)
    sharp = bound - etol
    idle = 0
    for r in range(rounds):
        m = 0
        for i in range(n):
            if nodes[i]:
                ni[m] = i
                m += 1
        if m < 3:
            break
        # each sample's segment: the last node at or before it (clipped to [0, m - 1])
        c = -1
        for i in range(n):
            if c + 1 < m and ni[c + 1] <= i:
                c += 1
            seg[i] = c if c >= 0 else 0
        for j in range(m):
            worst[j] = 0.0
            airseg[j] = False
            over[j] = False
        for i in range(n):
            s = seg[i]
            # candidate s: the chord (s - 1, s + 1) over its segment s
            kl = s - 1 if s >= 1 else 0
            kr = s + 1 if s + 1 <= m - 1 else m - 1
            ea = _chord_err(su[i], sz[i], su[ni[kl]], sz[ni[kl]], su[ni[kr]], sz[ni[kr]])
            worst[s] = _nanmax(worst[s], ea)
            # candidate s + 1: the chord (s, s + 2) over segment s (0 at a node)
            k2 = s + 2 if s + 2 <= m - 1 else m - 1
            eb = 0.0 if nodes[i] else _chord_err(su[i], sz[i], su[ni[s]], sz[ni[s]], su[ni[k2]], sz[ni[k2]])
            s1 = s + 1 if s + 1 <= m - 1 else m - 1
            worst[s1] = _nanmax(worst[s1], eb)
            if air[i]:
                airseg[s] = True
            if tent[i] > sharp:
                if _tent_over(su, sz, i, su[ni[kl]], sz[ni[kl]], su[ni[kr]], sz[ni[kr]], tent, bound):
                    over[s] = True
                if _tent_over(su, sz, i, su[ni[s]], sz[ni[s]], su[ni[k2]], sz[ni[k2]], tent, bound):
                    over[s1] = True
        for j in range(m - 1):
            if air[ni[j + 1]]:
                airseg[j] = True
        airseg[m - 1] = True
        any_ok = False
        for j in range(1, m - 1):
            if j % 2 != r % 2:
                continue
            if not (sp[ni[j]] == sp[ni[j - 1]] and sp[ni[j]] == sp[ni[j + 1]]):
                continue
            if not (worst[j] <= etol) or over[j] or airseg[j - 1] or airseg[j]:
                continue
            nodes[ni[j]] = False
            any_ok = True
        if any_ok:
            idle = 0
        else:
            idle += 1
            if idle >= 2:
                break
    return nodes
