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
#: the tent bound (:func:`tent_bound`) between consecutive samples is kept below this
#: fraction of the tolerance (a concave path's rise above the samples' chord)
TENT_SHARE = 0.5
#: a program chord's rise below the exact path, bounded as its largest rise at the two
#: samples closing an interval plus that interval's tent bound, is kept below this
#: fraction of the tolerance (the rest is the program's rounding, ROUNDING_SHARE)
TENT_BOUND_SHARE = 0.9
#: a tip less than this fraction of the tolerance below the top face cuts air: the
#: program's coordinates are rounded to tolerance/20 at most (gcode.MachineProfile.decimals),
#: so such a tip is written at or above Z0; leaving those positions out leaves at most
#: tolerance/20 of material there
AIR_CUT_FRACTION = 0.05


def tip_slope(ci, X, Y, u, R, along_x):
    """dZ/du of the exact tip path at the positions (X, Y) (u: their coordinate along
    the pass; ``along_x``: the pass runs along X, a bool or an array of them) from the
    contact points of :func:`~.compensate.compensate` (``ci``): the derivative of the
    contact's own sphere, (q_u - u) / sqrt(R^2 - |q - c|^2); unclipped, 0 where undefined."""
    pu = np.where(along_x, ci.contact_x, ci.contact_y)
    with np.errstate(all="ignore"):
        q = np.sqrt(np.maximum(R * R - (ci.contact_x - X) ** 2 - (ci.contact_y - Y) ** 2, 0.0))
        return np.nan_to_num((pu - u) / q)


def tent_bound(ua, za, da, ub, zb, db):
    """Largest rise above the chord (ua, za) - (ub, zb) of a CONCAVE path with these
    end values and slopes: the tangents at the ends bound it from above, so its rise is
    at most the height of their intersection above the chord,
    h / (1 / (da - s) + 1 / (s - db)) (s the chord's slope, h = ub - ua), and 0 when the
    slopes do not leave the chord upwards at both ends (no concave path rises then).
    Exact for two straight pieces; for a parabola twice the true rise. Infinite slopes
    (a vertical tangent) give the other end's one-sided bound (s - db) h or (da - s) h."""
    with np.errstate(all="ignore"):
        h = ub - ua
        s = (zb - za) / h
        p, q = da - s, s - db
        t = h / (1.0 / p + 1.0 / q)
    return np.where((p > 0) & (q > 0) & (h > 0), np.nan_to_num(t, nan=np.inf), 0.0)


def space_points(ws, fr, R, V, ug, Z, dZ, keep, tolerance, max_points, spec_path=None, slope=None):
    """Refine and simplify every pass at once.

    V (P,): pass positions across; ug: nodes along; Z, dZ, keep (P, len(ug)): exact
    tip heights, slopes dZ/du (clipped to +-20, for the Hermite test) and the nodes
    kept; ``slope``: the same slopes unclipped (default dZ). Returns (sp, su, sz,
    nodes): every evaluated sample (pass index, u, exact tip z), sorted by pass then u,
    and the mask of the samples kept as program points. Raises SpecError
    (``machining.tolerance``) past 4 x ``max_points`` samples.

    Besides the midpoint and Hermite tests, a segment is halved while either half's
    :func:`tent_bound` (from the exact end values and unclipped slopes) exceeds
    ``TENT_SHARE`` x tolerance: where the tip path is concave between two samples (a
    ball rolling over a convex rim at any angle to the pass, a circle about a corner)
    that bounds its rise above their chord, including a rise crowded against one end
    that the midpoint sees only half of.
    """
    etol = CHORD_SAFETY * tolerance
    ttol = TENT_SHARE * tolerance
    slope = dZ if slope is None else slope
    pid0, j0 = np.nonzero(keep)
    node_p, node_u, node_z, node_d = pid0, ug[j0], Z[pid0, j0], dZ[pid0, j0]
    node_s = slope[pid0, j0]
    # segments between consecutive kept nodes of the same pass
    same = node_p[1:] == node_p[:-1]
    sp, sa, sb = node_p[:-1][same], np.nonzero(same)[0], np.nonzero(same)[0] + 1
    seg = (sp, node_u[sa], node_z[sa], node_d[sa], node_u[sb], node_z[sb], node_d[sb],
           node_s[sa], node_s[sb])
    samp_p, samp_u, samp_z, samp_node = [node_p], [node_u], [node_z], [np.ones(len(node_p), bool)]
    samp_s = [node_s]
    total = len(node_p)
    th = np.array([0.1, 0.25, 0.75, 0.9])
    for _ in range(40):
        p, ua, za, da, ub, zb, db, sa_, sb_ = seg
        if p.size == 0:
            break
        um = 0.5 * (ua + ub)
        X, Y = fr.xy(um, V[p])
        zm, ci = compensate(ws, X, Y, R, return_info=True)
        fin = np.isfinite(zm)           # never -inf between kept nodes; if so, not refined
        zm = np.where(fin, zm, np.maximum(za, zb))
        sm = tip_slope(ci, X, Y, um, R, fr.direction == "x")
        dm = np.clip(sm, -20, 20)
        err = np.abs(zm - 0.5 * (za + zb))
        # and the deviation of the Hermite cubic (exact end values and slopes) from the
        # chord: catches a sharp rise between a midpoint and an end
        h = (ub - ua)[:, None]
        t = th[None, :]
        herm = ((2 * t**3 - 3 * t**2 + 1) * za[:, None] + (t**3 - 2 * t**2 + t) * h * da[:, None]
                + (-2 * t**3 + 3 * t**2) * zb[:, None] + (t**3 - t**2) * h * db[:, None])
        chord = za[:, None] + t * (zb - za)[:, None]
        err = np.maximum(err, np.nan_to_num(np.abs(herm - chord), nan=np.inf).max(axis=1))
        # the halves' tent bounds (a concave path's rise above their chords)
        tent = np.maximum(tent_bound(ua, za, sa_, um, zm, sm), tent_bound(um, zm, sm, ub, zb, sb_))
        both_air = (za >= -AIR_EPS) & (zb >= -AIR_EPS) & (zm >= -AIR_EPS)
        bad = ((err > etol) | (tent > ttol)) & (ub - ua > 1e-4) & ~both_air & fin
        samp_p.append(p)
        samp_u.append(um)
        samp_z.append(zm)
        samp_node.append(bad)
        samp_s.append(np.where(fin, sm, 0.0))
        total += p.size
        if total > 4 * max_points:
            raise SpecError(f"needs more than {max_points} program points; raise the tolerance",
                            file=spec_path, key="machining.tolerance")
        b = bad
        seg = (np.concatenate([p[b], p[b]]), np.concatenate([ua[b], um[b]]),
               np.concatenate([za[b], zm[b]]), np.concatenate([da[b], dm[b]]),
               np.concatenate([um[b], ub[b]]), np.concatenate([zm[b], zb[b]]),
               np.concatenate([dm[b], db[b]]), np.concatenate([sa_[b], sm[b]]),
               np.concatenate([sm[b], sb_[b]]))
    sp_ = np.concatenate(samp_p)
    su = np.concatenate(samp_u)
    sz = np.concatenate(samp_z)
    sn = np.concatenate(samp_node)
    ss = np.concatenate(samp_s)
    order = np.lexsort((su, sp_))
    sp_, su, sz, sn, ss = sp_[order], su[order], sz[order], sn[order], ss[order]
    # each interval between consecutive samples of a pass: its tent bound
    tent = np.zeros(len(su))
    if len(su) > 1:
        inner = sp_[1:] == sp_[:-1]
        tent[:-1] = np.where(inner, tent_bound(su[:-1], sz[:-1], ss[:-1], su[1:], sz[1:], ss[1:]), 0.0)
    nodes = _simplify(sp_, su, sz, sn, etol, tent=tent, bound=TENT_BOUND_SHARE * tolerance)
    return sp_, su, sz, nodes



def _simplify(sp, su, sz, sn, etol, rounds=64, tent=None, bound=np.inf):
    """Drop nodes (sn) while every sample between the surviving neighbours stays
    within etol of their chord and, for each interval between consecutive samples
    (``tent``: its tent bound, see :func:`tent_bound`; 0 after a pass's last sample),
    the larger rise of its two samples above that chord plus its tent bound stays
    within ``bound``. Nodes flanked by air (tip at/above the top face)
    or at pass ends stay. Returns the boolean node mask over the samples.

    In compiled code (:mod:`.spacing_kernels`: the same rounds and arithmetic, the
    same nodes) unless the kernels are off (``FABKIT_NO_KERNELS``)."""
    tent = np.zeros(len(su)) if tent is None else np.ascontiguousarray(tent, dtype=float)
    kern = _kernel()
    if kern is None:
        return _simplify_numpy(sp, su, sz, sn, etol, rounds, tent, bound)
    return kern(np.ascontiguousarray(sp, dtype=np.int64), np.ascontiguousarray(su, dtype=float),
                np.ascontiguousarray(sz, dtype=float), np.array(sn, dtype=bool),
                np.ascontiguousarray(sz >= -AIR_EPS), float(etol), int(rounds), tent, float(bound))


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


def _simplify_numpy(sp, su, sz, sn, etol, rounds=64, tent=None, bound=np.inf):
    """_simplify in numpy: every sample of every pass at once, round by round."""
    nodes = sn.copy()
    air = sz >= -AIR_EPS
    tent = np.zeros(len(su)) if tent is None else tent
    # the intervals whose tent bound can matter: elsewhere etol at the samples suffices
    sharp = np.nonzero(tent[:-1] > bound - etol)[0]
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
        if sharp.size:
            i, i1 = sharp, sharp + 1
            s, kl, kr, k2 = seg_of[i], k_left[i], k_right[i], k_r2[i]
            over = np.zeros(ni.size, bool)
            for cand, a, b in ((s, kl, kr), (np.clip(s + 1, 0, ni.size - 1), s, k2)):
                ua, za, ub, zb = su[ni[a]], sz[ni[a]], su[ni[b]], sz[ni[b]]
                rise = np.maximum(np.maximum(_chord_rise(su[i], sz[i], ua, za, ub, zb),
                                             _chord_rise(su[i1], sz[i1], ua, za, ub, zb)), 0.0)
                np.logical_or.at(over, cand, ~(rise + tent[i] <= bound))
            ok &= ~over
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


def _chord_rise(u, z, ua, za, ub, zb):
    """How far the sample (u, z) lies above the chord (signed)."""
    with np.errstate(all="ignore"):
        t = np.where(ub > ua, (u - ua) / (ub - ua), 0.0)
    return z - (za + t * (zb - za))


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


