"""Linking the cut runs into one program: short feed links over the material,
retracts and rapids otherwise.

Runs less than max(4 R, 4 stepover) apart are linked locally at ``clearance``
above the highest material along the straight link (drop cutter every R/4): up,
across, and a plunge. Below the top face the link may meet stock not cut yet, so
it is fed (G1); at or above it (over ground that rises above the top face, where
the ball touches nothing) it is a short lift: rapid straight up out of the cut to
``clearance`` above the top face (or the link height, if higher), rapid across,
rapid down to ``clearance`` above the top face and plunge. Other runs retract to
safe_z, rapid across, rapid down to the clearance above the top face and plunge.
Rapids move only straight up out of the cut, across at the safe height or at
least ``clearance`` above the top face, or down to above the top face; every
rapid below the top face is checked against the material present by
:func:`fabkit.toolpath.cut.verify.verify_cut`.
"""

from __future__ import annotations

import math

import numpy as np

from .compensate import compensate
from ..path import CUT, PLUNGE, RAPID


def link_runs(ws, R, all_runs, link_max, one_way, safe_z, clr):
    """all_runs: [(key, (k, 3) tip points)] in cutting order; key[0] == "f" for
    finishing runs (the only ones joined by local links). Returns (points, kinds)."""
    pts, kinds = [], []
    # local link heights, all links at once: 1 mm above the highest material along
    # the straight link (drop cutter every R/4), None where a full retract is needed
    zlink = [None] * len(all_runs)
    idx, TX, TY, owner = [], [], [], []
    for i in range(1, len(all_runs)):
        (pkey, pr), (key, r) = all_runs[i - 1], all_runs[i]
        a, b = pr[-1], r[0]
        d = math.hypot(b[0] - a[0], b[1] - a[1])
        if d <= link_max and not (one_way and pkey != key) and pkey[0] == key[0] == "f":
            n = max(2, int(math.ceil(d / (R / 4))) + 1)
            t = np.linspace(0.0, 1.0, n)
            TX.append(a[0] + t * (b[0] - a[0]))
            TY.append(a[1] + t * (b[1] - a[1]))
            owner.append(np.full(n, len(idx)))
            idx.append(i)
    if idx:
        zc = compensate(ws, np.concatenate(TX), np.concatenate(TY), R)
        high = np.full(len(idx), -np.inf)
        np.maximum.at(high, np.concatenate(owner), zc)
        for j, i in enumerate(idx):
            a, b = all_runs[i - 1][1][-1], all_runs[i][1][0]
            zl = max(a[2], b[2], float(high[j])) + clr
            zlink[i] = zl if zl <= safe_z else None
    prev = None
    for i, (key, r) in enumerate(all_runs):
        if prev is None:
            _approach(pts, kinds, r[0], safe_z, clr, first=True)
        else:
            a, b = prev[1], r[0]
            zl = zlink[i]
            if zl is not None and zl < 0.0:
                pts += [(a[0], a[1], zl), (b[0], b[1], zl), tuple(b)]
                kinds += [CUT, CUT, PLUNGE]
            elif zl is not None:
                # over the top face: nothing to cut, so no feed move in the air
                zl = max(zl, clr)
                pts += [(a[0], a[1], zl)]
                kinds += [RAPID]
                _approach(pts, kinds, b, zl, clr)
            else:
                pts += [(a[0], a[1], safe_z)]
                kinds += [RAPID]
                _approach(pts, kinds, b, safe_z, clr)
        pts += [tuple(q) for q in r[1:]]
        kinds += [CUT] * (len(r) - 1)
        prev = (key, r[-1])
    if prev is not None:
        a = prev[1]
        pts.append((a[0], a[1], safe_z))
        kinds.append(RAPID)
    points = np.array(pts, float).reshape(-1, 3)
    kinds = np.array(kinds, np.int8)
    return points, kinds


def _approach(pts, kinds, b, safe_z, clr, first=False):
    """Rapid above b at safe_z (or a lower link height), rapid down to clr above the top face, plunge to b."""
    pts += [(b[0], b[1], safe_z), (b[0], b[1], max(clr, b[2]))]
    kinds += [RAPID, RAPID]
    if b[2] < max(clr, b[2]):
        pts.append(tuple(b))
        kinds.append(PLUNGE)


