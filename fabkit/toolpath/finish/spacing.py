"""Point spacing along the passes: the exact path between the pass nodes is
followed by chords within the tolerance.

Segments between pass nodes are halved until the exact path (drop cutter) at each
segment's midpoint, and the Hermite cubic through the ends (exact values and
slopes), are within tolerance/2 of the chord; then nodes are dropped while every
evaluated point between the surviving nodes stays within tolerance/2 of their chord
(long segments on flat ground, short ones over creases and walls).
"""

from __future__ import annotations

import numpy as np

from ...errors import SpecError
from .compensate import compensate
from .passes import AIR_EPS

CHORD_SAFETY = 0.5      # evaluated chord errors kept below this fraction of the tolerance
#: a tip less than this fraction of the tolerance below the top face cuts air: the
#: program's coordinates are rounded to tolerance/20 at most (gcode.MachineProfile.decimals),
#: so such a tip is written at or above Z0; leaving those positions out leaves at most
#: tolerance/20 of material there
AIR_CUT_FRACTION = 0.05


def space_points(ws, fr, R, V, ug, Z, dZ, keep, tolerance, max_points, spec_path=None):
    """Refine and simplify every pass at once.

    V (P,): pass positions across; ug: nodes along; Z, dZ, keep (P, len(ug)): exact
    tip heights, slopes dZ/du and the nodes kept. Returns (sp, su, sz, nodes): every
    evaluated sample (pass index, u, exact tip z), sorted by pass then u, and the mask
    of the samples kept as program points. Raises SpecError (``machining.tolerance``)
    past 4 x ``max_points`` samples.
    """
    etol = CHORD_SAFETY * tolerance
    pid0, j0 = np.nonzero(keep)
    node_p, node_u, node_z, node_d = pid0, ug[j0], Z[pid0, j0], dZ[pid0, j0]
    # segments between consecutive kept nodes of the same pass
    same = node_p[1:] == node_p[:-1]
    sp, sa, sb = node_p[:-1][same], np.nonzero(same)[0], np.nonzero(same)[0] + 1
    seg = (sp, node_u[sa], node_z[sa], node_d[sa], node_u[sb], node_z[sb], node_d[sb])
    samp_p, samp_u, samp_z, samp_node = [node_p], [node_u], [node_z], [np.ones(len(node_p), bool)]
    total = len(node_p)
    th = np.array([0.1, 0.25, 0.75, 0.9])
    for _ in range(40):
        p, ua, za, da, ub, zb, db = seg
        if p.size == 0:
            break
        um = 0.5 * (ua + ub)
        X, Y = fr.xy(um, V[p])
        zm, ci = compensate(ws, X, Y, R, return_info=True)
        fin = np.isfinite(zm)           # never -inf between kept nodes; if so, not refined
        zm = np.where(fin, zm, np.maximum(za, zb))
        pu = ci.contact_x if fr.direction == "x" else ci.contact_y
        with np.errstate(all="ignore"):
            q = np.sqrt(np.maximum(R * R - (ci.contact_x - X) ** 2 - (ci.contact_y - Y) ** 2, 0.0))
            dm = np.clip(np.nan_to_num((pu - um) / q), -20, 20)
        err = np.abs(zm - 0.5 * (za + zb))
        # and the deviation of the Hermite cubic (exact end values and slopes) from the
        # chord: catches a sharp rise between a midpoint and an end
        h = (ub - ua)[:, None]
        t = th[None, :]
        herm = ((2 * t**3 - 3 * t**2 + 1) * za[:, None] + (t**3 - 2 * t**2 + t) * h * da[:, None]
                + (-2 * t**3 + 3 * t**2) * zb[:, None] + (t**3 - t**2) * h * db[:, None])
        chord = za[:, None] + t * (zb - za)[:, None]
        err = np.maximum(err, np.nan_to_num(np.abs(herm - chord), nan=np.inf).max(axis=1))
        both_air = (za >= -AIR_EPS) & (zb >= -AIR_EPS) & (zm >= -AIR_EPS)
        bad = (err > etol) & (ub - ua > 1e-4) & ~both_air & fin
        samp_p.append(p)
        samp_u.append(um)
        samp_z.append(zm)
        samp_node.append(bad)
        total += p.size
        if total > 4 * max_points:
            raise SpecError(f"needs more than {max_points} program points; raise the tolerance",
                            file=spec_path, key="machining.tolerance")
        b = bad
        seg = (np.concatenate([p[b], p[b]]), np.concatenate([ua[b], um[b]]),
               np.concatenate([za[b], zm[b]]), np.concatenate([da[b], dm[b]]),
               np.concatenate([um[b], ub[b]]), np.concatenate([zm[b], zb[b]]),
               np.concatenate([dm[b], db[b]]))
    sp_ = np.concatenate(samp_p)
    su = np.concatenate(samp_u)
    sz = np.concatenate(samp_z)
    sn = np.concatenate(samp_node)
    order = np.lexsort((su, sp_))
    sp_, su, sz, sn = sp_[order], su[order], sz[order], sn[order]
    nodes = _simplify(sp_, su, sz, sn, etol)
    return sp_, su, sz, nodes



def _simplify(sp, su, sz, sn, etol, rounds=64):
    """Drop nodes (sn) while every sample between the surviving neighbours stays
    within etol of their chord. Nodes flanked by air (tip at/above the top face)
    or at pass ends stay. Returns the boolean node mask over the samples.

    In compiled code (:mod:`.spacing_kernels`: the same rounds and arithmetic, the
    same nodes) unless the kernels are off (``FABKIT_NO_KERNELS``)."""
    kern = _kernel()
    if kern is None:
        return _simplify_numpy(sp, su, sz, sn, etol, rounds)
    return kern(np.ascontiguousarray(sp, dtype=np.int64), np.ascontiguousarray(su, dtype=float),
                np.ascontiguousarray(sz, dtype=float), np.array(sn, dtype=bool),
                np.ascontiguousarray(sz >= -AIR_EPS), float(etol), int(rounds))


def _kernel():
    """spacing_kernels.simplify, or None (kernels off, numba missing)."""
    from .kernels import enabled

    if not enabled():
        return None
    try:
        from .spacing_kernels import simplify
    except ImportError:  # pragma: no cover - numba is a dependency
        return None
    return simplify


def _simplify_numpy(sp, su, sz, sn, etol, rounds=64):
    """_simplify in numpy: every sample of every pass at once, round by round."""
    nodes = sn.copy()
    air = sz >= -AIR_EPS
    idle = 0
    for r in range(rounds):
        ni = np.nonzero(nodes)[0]
        if ni.size < 3:
            break
        npass = sp[ni]
        interior = np.zeros(ni.size, bool)
        interior[1:-1] = (npass[1:-1] == npass[:-2]) & (npass[1:-1] == npass[2:])
        # node k removable if the chord (k-1, k+1) covers all samples in between
        seg_of = np.searchsorted(ni, np.arange(len(su)), side="right") - 1   # node at left
        seg_of = np.clip(seg_of, 0, ni.size - 1)
        k_left = np.clip(seg_of - 1, 0, ni.size - 1)
        k_right = np.clip(seg_of + 1, 0, ni.size - 1)
        # samples in segment j (between node j and j+1), chord of candidate j (j-1 .. j+1)
        # and of candidate j+1 (j .. j+2)
        errA = _chord_err(su, sz, su[ni[k_left]], sz[ni[k_left]], su[ni[k_right]], sz[ni[k_right]])
        k_r2 = np.clip(seg_of + 2, 0, ni.size - 1)
        errB = _chord_err(su, sz, su[ni[seg_of]], sz[ni[seg_of]], su[ni[k_r2]], sz[ni[k_r2]])
        # a sample at node j (itself) belongs to segment j and to candidate j's range only
        isn = nodes
        errB = np.where(isn, 0.0, errB)
        worst = np.zeros(ni.size)
        np.maximum.at(worst, seg_of, errA)                       # candidate j: its segment j
        np.maximum.at(worst, np.clip(seg_of + 1, 0, ni.size - 1), errB)  # candidate j+1
        airseg = np.zeros(ni.size, bool)                         # segment j touches air
        np.logical_or.at(airseg, seg_of, air)
        airseg |= np.r_[air[ni][1:], True]
        ok = interior & (worst <= etol)
        ok[1:] &= ~airseg[:-1]
        ok &= ~airseg
        ok &= np.arange(ni.size) % 2 == r % 2
        if ok.any():
            nodes[ni[ok]] = False
            idle = 0
        else:
            idle += 1
            if idle >= 2:
                break
    return nodes


def _chord_err(u, z, ua, za, ub, zb):
    with np.errstate(all="ignore"):
        t = np.where(ub > ua, (u - ua) / (ub - ua), 0.0)
    return np.abs(z - (za + t * (zb - za)))


def cut_runs(sp, su, sz, nodes, air_depth=AIR_EPS):
    """Per pass, the runs of consecutive cut segments as (k, 2) arrays of [u, z]. A
    sample whose tip is less than ``air_depth`` mm below the top face (or -inf: the
    ball misses the stock) cuts air; a run starts at the node before the material
    and ends at the node after it."""
    P = int(sp.max()) + 1 if sp.size else 0
    out = [[] for _ in range(P)]
    ni = np.nonzero(nodes)[0]
    air = ~(sz < -air_depth) | ~np.isfinite(sz)
    # a segment (node j .. j+1, same pass) cuts if any sample in [j, j+1] is below the top
    seg_of = np.clip(np.searchsorted(ni, np.arange(len(su)), side="right") - 1, 0, max(ni.size - 1, 0))
    cuts = np.zeros(ni.size, bool)
    np.logical_or.at(cuts, seg_of, ~air)
    cuts[:-1] |= ~air[ni[1:]]
    samepass = np.r_[sp[ni][1:] == sp[ni][:-1], False]
    cuts &= samepass
    j = 0
    while j < ni.size:
        if not cuts[j]:
            j += 1
            continue
        k = j
        while k < ni.size and cuts[k]:
            k += 1
        idx = ni[j:k + 1]
        out[int(sp[idx[0]])].append(np.column_stack([su[idx], sz[idx]]))
        j = k + 1
    return out


