"""Pass placement for the ball-end raster: the passes across, each with its exact
tip heights (drop cutter) along the pass, spaced by the slope-aware stepover.

Work coordinates, mm. A pass runs along ``u`` (X for ``direction: x``, Y for
``direction: y``) at a fixed ``v`` across.

* Stepover, pass by pass: the next pass is the farthest (never beyond the
  flat-ground stepover) for which the scallop bound of :mod:`fabkit.toolpath.finish.scallop`
  (the material left between the two balls, from their actual centres, along the
  design's normal or vertically) stays <= 0.95 * scallop; that module says how it
  holds on steep walls and on slopes along the pass.
* Reachable surface: where passes right between the two (three more, evenly
  spaced) leave more than a quarter of the target too, that material is beyond
  the ball's reach (a valley tighter than the tool, a V crease); the bound then
  applies to the material ABOVE what those dense passes leave (FLOOR_EXCESS of the
  target: across a V crease the cusp above the ball's fillet is a flat-ground
  cusp, so nearly the flat stepover holds there), so the stepover is
  bounded by the reachable surface and the unreachable material is reported, not
  chased with ever smaller stepovers.
* Edges: across, the first and last passes lie on the footprint edges or beyond
  them (up to 0.999 R out: a steep wall at the edge is reached only by a ball
  almost wholly outside), until the edge is milled.
* Open ends of unreachable regions (:func:`edge_comb`): within R of an edge across, a
  ball hanging off the edge reaches deeper into a groove tighter than itself than any
  ball over the stock (a 45-degree V under a 6 mm ball: 0.49 mm deeper 0.1 mm from the
  edge). Where the placed passes leave more than the target in that band and a comb of
  passes hanging off the edge (:func:`comb_offsets`) leaves less, the comb's passes are
  added over that stretch along the pass (before, a band 0.1-0.3 mm wide at the last
  edge was left up to 0.9 mm higher than the tool can cut).
"""

from __future__ import annotations

import math

import numpy as np

from ...errors import SpecError
from .compensate import INTERIOR, TOP, compensate
# the scallop bound has its own module; its names stay importable from here
from .scallop import (EDGE_NODES, SCALLOP_SAFETY, STEEP_ALONG, between_rows, flat_stepover,  # noqa: F401
                      grid_memo, hermite_profile, hermite_weights, node_index, slope_scale, stack_profiles,
                      sweep_material, tilted_plane_cusp)

AIR_EPS = 1e-7          # mm: a tip this close below the top face touches nothing worth a move
FLOOR_SHARE = 0.25      # material the dense passes leave above this share of the target: unreachable
FLOOR_EXCESS = 0.9      # above unreachable material, the bound allows this share of the target
FLOOR_EXCESS_VERTICAL = 0.5   # the same, measured vertically (steep fillet flanks: 0.9 left 0.085 mm)
MIN_STEP_SHARE = 0.02   # smallest stepover tried, share of the flat-ground stepover
REFINE_SHARE = 0.5      # the material bound's crest is refined where it exceeds this share of the target
GROWTH = 1.5            # the next stepover grows at most by this factor (cusp ~ s^2 predicts it)
EDGE_OUT = (0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 0.95, 0.99, 0.999)  # edge passes, x R out
COMB_EVEN, COMB_RIM = 60, 20    # the comb hanging off an edge: passes evenly to 0.9 R out, then toward 0.999 R
COMB_GAIN = 0.25        # comb passes run where they lower the edge band by this share of the target


def comb_offsets() -> np.ndarray:
    """Offsets beyond an edge (x R) of the comb of passes whose balls, hanging off the edge,
    cut the open end of a groove tighter than the tool: COMB_EVEN evenly from 0 to 0.9 R,
    COMB_RIM geometrically from 0.9 to 0.999 R (the balls' cross-sections on the edge shrink
    fast there, and the deepest ball for a point d from the edge stands ~R - d out). On a
    45-degree V under a 6 mm ball the lowest of these balls lies at most 0.0025 mm above the
    lowest of all balls up to 0.999 R out, 0 to 1.5 mm from the edge (closed form of the
    cross-section at the crease; 0.007 mm with 20 even ones). In a 2 mm groove with tanh
    walls under a 1/8 in ball 20 even ones (0.075 mm apart) left 0.10 mm more than the
    lowest ball 0.2 mm from the edge."""
    return np.unique(np.r_[np.linspace(0.0, 0.9, COMB_EVEN), 1.0 - np.geomspace(1e-3, 0.1, COMB_RIM)])


class Frame:
    """Pass coordinates (u along, v across) <-> work (X, Y)."""

    def __init__(self, direction: str, L: float, W: float):
        self.direction = direction
        self.Lu, self.Lv = (L, W) if direction == "x" else (W, L)

    def xy(self, u, v):
        return (u, v) if self.direction == "x" else (v, u)


class _Pass:
    """One pass: v, exact tip heights Z and slopes dZ/du at the grid ug, the nodes
    kept, and the profile on a fine grid uf (Hermite; +inf where not machined)."""

    comb = False        # a pass of an edge comb (:func:`edge_comb`), run over a stretch only

    def __init__(self, fr, R, ug, uf, v, X, Y, Z, ci, depth_lim=math.inf, contact_top=None):
        pu = ci.contact_x if fr.direction == "x" else ci.contact_y
        d2 = (ci.contact_x - X) ** 2 + (ci.contact_y - Y) ** 2
        with np.errstate(all="ignore"):
            slope = np.nan_to_num((pu - ug) / np.sqrt(np.maximum(R * R - d2, 0.0)))
        dZ = np.clip(slope, -20, 20)
        self.v, self.Z, self.dZ, self.bridged = v, Z, dZ, ci.bridged
        self.slope = slope          # dZ/du unclipped (the point spacing's chord bound)
        # the contact curve where it crosses each cross-section u (contacts lie up to
        # R along the pass from their ball's centre on steep ground)
        cv = ci.contact_y if fr.direction == "x" else ci.contact_x
        self.cv = contact_curve(ug, pu, cv, v, R, np.where(ci.kind == INTERIOR, ug - pu, np.nan))
        self.keep = _trim_outside(ug, Z, fr.Lu, depth_lim, contact_top)
        k = np.nonzero(self.keep)[0]
        f = hermite_profile(ug, Z, dZ, uf, self.bridged)
        # the material bounds count the balls at most 7/8 R beyond the edges, and further
        # out only those at the nodes (exact heights): there the tip height rises too
        # steeply for the Hermite profile (fewer balls: a higher, still valid bound)
        out = np.maximum(-uf, uf - fr.Lu)
        j = node_index(ug, uf)          # np.isin(uf, ug[np.isfinite(Z)])
        f = np.where((out <= 0.875 * R) | ((j >= 0) & np.isfinite(Z)[np.maximum(j, 0)]), f, np.inf)
        self.fine = np.where((uf >= ug[k[0]]) & (uf <= ug[k[-1]]), f, np.inf) if k.size \
            else np.full_like(uf, np.inf)
        self._ug = ug
        self._lo = max(ug[k[0]], -0.875 * R) if k.size else math.inf
        self._hi = min(ug[k[-1]], fr.Lu + 0.875 * R) if k.size else -math.inf



def contact_curve(ug, pu, cv, v, R=None, du=None):
    """The pass's contact curve: v across where it crosses each cross-section ug.

    Contacts (pu along, cv across) of the balls at ug, interpolated in pu. Where
    several balls touch the same cross-section (the stock edge across the pass: every
    ball beyond it touches the edge line, from the ball at the edge, a full radius in
    the cross-section, to the ball a radius out, touching with its equator, at its own
    v), the contact of the ball nearest that cross-section is the pass's: the curves of
    successive passes then bound, per cross-section, the cusp between two full-radius
    balls (the balls beyond the edge, ever smaller in the cross-section, are not the ones
    the stepover is spaced for). Any curve increasing with v from pass to pass tiles
    the cross-section, so the material bounds between consecutive curves cover it."""
    ok = np.isfinite(pu) & np.isfinite(cv)
    if not ok.any():
        return np.full_like(ug, v)
    p, c, d = pu[ok], cv[ok], np.abs(ug[ok] - pu[ok])
    o = np.lexsort((d, p))
    p, c = p[o], c[o]
    first = np.r_[True, np.diff(p) > 1e-9]
    out = np.interp(ug, p[first], c[first])
    if R is None:
        return out
    # cross-sections no contact lies near (more than R/4 from every contact along the
    # pass): a valley or V crease tighter than the ball, where the balls touch the
    # design only on its flanks. There the ball centred in the cross-section cuts it
    # with its bottom, at the envelope's touch across, v + R dv / sqrt(R^2 - du^2)
    # (dv, du: its contact's offsets across and along, ``du`` nan where the contact is
    # not on the design's smooth part: an edge, the top face; the contact where du = 0);
    # interpolated from the flanks' contacts instead, the curve missed the cusps in a V
    # crease whose floor slopes across the passes (3*abs(x) + 2*abs(y): 0.18 mm left)
    pf = p[first]
    j = np.clip(np.searchsorted(pf, ug), 1, max(pf.size - 1, 1))
    gap = np.minimum(np.abs(ug - pf[np.minimum(j, pf.size - 1)]), np.abs(ug - pf[j - 1]))
    with np.errstate(all="ignore"):
        touch = v + R * (cv - v) / np.sqrt(R * R - du * du)
    band = (gap > 0.25 * R) & np.isfinite(touch) & ok
    return np.where(band, touch, out)


def compensate_passes(ws, fr, R, ug, uf, vlist, depth_lim, target=0.0):
    """Several passes at once (one vectorized compensation call). ``target``: the
    material bound's target (mm), for :func:`_exact_where_contact_changes`."""
    vv = np.asarray(vlist, float)[:, None] + 0 * ug[None, :]
    uu = np.broadcast_to(ug, vv.shape)
    X, Y = fr.xy(uu, vv)
    Z, ci = compensate(ws, X, Y, R, return_info=True)
    # the ball touches the stock only on its top face (contact at or above it)
    top = ws.H(np.nan_to_num(ci.contact_x), np.nan_to_num(ci.contact_y)) >= -AIR_EPS
    top &= np.isfinite(ci.contact_x)
    out = []
    for k, v in enumerate(vlist):
        row = type(ci)(ci.contact_x[k], ci.contact_y[k], ci.kind[k], ci.bridged[k])
        out.append(_Pass(fr, R, ug, uf, float(v), X[k], Y[k], Z[k], row, depth_lim, top[k]))
    _exact_where_contact_changes(ws, fr, R, ug, uf, out, ci.kind, target)
    _extend_where_profile_holds(ws, fr, R, ug, out, target)
    return out


def _extend_where_profile_holds(ws, fr, R, ug, passes, target):
    """The rim search of the material bound (:func:`sweep_material`, stage 3) takes balls
    up to 7/8 R beyond the edges, where the Hermite profile is trusted. Further out, each
    segment between the nodes at 7/8, 0.95 and 0.99 R is taken too where the profile holds
    there: exact slopes unclipped and the cubic within a hundredth of the target of the
    exact tip height at the segment's quarter points. On ground rising from an edge (a
    plane of slope 8 along the pass) the ball finishing the edge's foot stands 0.99 R out:
    without those balls the bound at the edge was 0.42 mm high against 0.38 mm (normal:
    0.052 against 0.047, above the target) and the stepover shrank on the whole block. On
    ground falling to an edge the tip rises with a nearly vertical tangent there and the
    check fails: the segment stays out."""
    grid = _edge_segments(ug, fr.Lu, R)
    if grid is None:
        return
    segs, uq = grid
    live = [p for p in passes if p.keep.any()]
    if not live:
        return
    V = np.array([p.v for p in live])[:, None] + 0 * uq[None, :]
    X, Y = fr.xy(np.broadcast_to(uq, V.shape), V)
    Zx = compensate(ws, X, Y, R)
    for k, p in enumerate(live):
        h = hermite_profile(ug, p.Z, p.dZ, uq, p.bridged)
        # per segment: its three quarter points' exact heights finite, and the cubic within
        # a hundredth of the target of them
        fin = np.isfinite(Zx[k]).reshape(-1, 3).all(axis=1)
        near = (np.abs(h - Zx[k]) <= 0.01 * target).reshape(-1, 3).all(axis=1)
        for j, (sign, a, b) in enumerate(segs):
            if not (p.keep[a] and p.keep[b]):
                continue
            good = abs(p.dZ[a]) < 19.9 and abs(p.dZ[b]) < 19.9 and fin[j] and near[j]
            if not good:
                continue
            if sign < 0 and abs(p._lo - ug[a]) < 1e-9:
                p._lo = max(ug[b], ug[np.nonzero(p.keep)[0][0]])
            elif sign > 0 and abs(p._hi - ug[a]) < 1e-9:
                p._hi = min(ug[b], ug[np.nonzero(p.keep)[0][-1]])


def _edge_segments(ug, Lu, R):
    """(segments (sign, a, b) between the nodes at 7/8, 0.95 and 0.99 R out on both sides,
    their quarter points uq (read-only)), or None where the grid lacks those nodes. Kept
    per read-only grid (:func:`fabkit.toolpath.finish.scallop.grid_memo`)."""
    def make():
        sides = []
        for sign, edge in ((-1.0, 0.0), (1.0, Lu)):
            nodes = [edge + sign * f * R for f in (0.875, 0.95, 0.99)]
            idx = [int(np.argmin(np.abs(ug - n))) for n in nodes]
            if any(abs(ug[i] - n) > 1e-9 for i, n in zip(idx, nodes)):
                return None
            sides.append((sign, idx))
        t = np.array([0.25, 0.5, 0.75])
        segs = [(sign, a, b) for sign, idx in sides for a, b in zip(idx[:-1], idx[1:])]
        uq = np.concatenate([ug[a] + t * (ug[b] - ug[a]) for _, a, b in segs])
        uq.flags.writeable = False
        return segs, uq

    return grid_memo(("edges", float(Lu), float(R)), (ug,), make)


def _exact_where_contact_changes(ws, fr, R, ug, uf, passes, kind, target):
    """Exact tip heights on the fine grid between nodes whose contacts are of different
    kinds (the ball leaving the top face onto the crease, the crease onto the surface,
    an edge): there the tip path's second derivative jumps (0 on the top face, -1/R on
    the crease) and the Hermite cubic between nodes ~0.8 mm apart is off by up to
    ~4 um, more than a small scallop's whole target; the material bound then found
    cusps that are not there and the stepover collapsed in bursts beside the top face.
    The exact height replaces the cubic where it is higher (the cubic took the ball for
    lower than it is) or more than a tenth of ``target`` lower (a cusp the bound would
    chase); a smaller excess of the cubic is kept (a higher ball: a valid bound)."""
    chg = (kind[:, 1:] != kind[:, :-1]) & ~((kind[:, 1:] == TOP) & (kind[:, :-1] == TOP))
    if not chg.any():
        return
    seg = hermite_weights(ug, uf)[0]       # np.clip(searchsorted(ug, uf, "right") - 1, 0, n - 2)
    interior = node_index(ug, uf) < 0      # ~np.isin(uf, ug)
    rows, cols = [], []
    for k, p in enumerate(passes):
        j = np.nonzero(chg[k][seg] & interior & np.isfinite(p.fine))[0]
        rows.append(np.full(j.size, k))
        cols.append(j)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    if not rows.size:
        return
    V = np.array([p.v for p in passes])[rows]
    X, Y = fr.xy(uf[cols], V)
    Z = compensate(ws, X, Y, R)
    for k, p in enumerate(passes):
        m = (rows == k) & np.isfinite(Z)
        f = p.fine[cols[m]]
        p.fine[cols[m]] = np.where((Z[m] > f) | (f - Z[m] > 0.1 * target), Z[m], f)


def _beside(v, step, Lv):
    """The pass right beside the pass at v (``step`` further across): short of the edge
    it stops at the edge; beyond it (the edge passes lie up to R out) it lies further
    out still, never behind v (a pass behind it bounds the material between the two as
    unreachable: on a dome falling to the edge, 0.24 mm was left that way)."""
    return v + step if v >= Lv else min(v + step, Lv)


def u_grid(fr, R):
    """Nodes along the passes: at most 1 mm (or R/2) apart inside, R/8 apart beyond
    the edges, and at EDGE_NODES x R out: on ground rising steeply away from an edge the
    ball reaches the edge's foot only from almost a whole radius out (slope 8: 0.992 R)."""
    du = min(1.0, R / 2.0)
    n_in = max(2, int(math.ceil(fr.Lu / du)) + 1)
    side = np.sort(np.r_[np.linspace(0.0, R, 9), R * np.array(EDGE_NODES)])
    return np.concatenate([-side[:0:-1], np.linspace(0.0, fr.Lu, n_in), fr.Lu + side[1:]])


def fine_grid_size(ug, R, target):
    """(size, step mm) of :func:`fine_grid` without building it (the guards' estimate:
    the grid of a tiny scallop is refused before it is allocated)."""
    du = float(np.diff(ug).max())
    sub = max(4, int(math.ceil(du / math.sqrt(0.8 * R * target)))) if target > 0 else 4
    n = sub * (len(ug) - 1 - 2 * len(EDGE_NODES)) + 1
    return n, float(ug[-1] - ug[0]) / max(n - 1, 1)


def fine_grid(ug, R=None, target=None):
    """The material bounds' grid along u: four steps per even node step (more where
    the target is small: the balls df apart along a pass leave up to df^2 / (8 R) between
    them, kept below a tenth of the target; else the bound never meets a small scallop
    and the stepover collapses), and the nodes beyond the edges."""
    n = fine_grid_size(ug, R, target if R is not None and target else 0.0)[0]
    lu = ug[-1] + ug[0]
    out = np.maximum(-ug, ug - lu) / -ug[0]
    return np.unique(np.r_[np.linspace(ug[0], ug[-1], n), ug[(out > 0.9) & (out < 1.0)]])


def _trim_outside(ug, Z, Lu, depth_lim, contact_top=None):
    """Nodes kept along u: all inside the footprint; outside, while the ball still
    overlaps the stock (within R of the edge: it mills the edge from the side) and
    the tip stays within the depth limit. ``contact_top`` (bool per node): the ball
    touches the stock only on its top face; such nodes beyond the stock mill nothing,
    and they are dropped from the outer end inward (the kept nodes stay contiguous)."""
    inside = (ug >= 0) & (ug <= Lu)
    # not the nodes a whole radius out: there the ball touches the edge with its equator
    # and the tip height has a vertical tangent (Z = H_edge + sqrt(R^2 - u^2) - R) that no
    # chord of the program's resolution follows within the tolerance (it gouged the edge
    # by 6-7 um); the next node in, 7/8 R out, has a slope below 2
    reach = np.maximum(-ug, ug - Lu) < (1.0 - 1e-9) * np.max(np.maximum(-ug, ug - Lu))
    keep = inside | (reach & np.isfinite(Z) & (Z >= -depth_lim))
    if contact_top is not None:
        n = len(ug)
        i = 0
        while i < n and not inside[i] and (contact_top[i] or not keep[i]):
            keep[i] = False
            i += 1
        i = n - 1
        while i >= 0 and not inside[i] and (contact_top[i] or not keep[i]):
            keep[i] = False
            i -= 1
    return keep




class PassPlan:
    """The placed passes and what the placement found.

    passes:       list of :class:`_Pass`, increasing v
    ug, uf:       the node grid along u and the fine grid of the material bounds
    s_flat:       the flat-ground stepover (mm)
    unreachable:  (mm, u, v): the most material the dense passes between two
                  passes leave (beyond the ball's reach), and where
    relaxed:      (mm, u, v) or None: the stepover hit its floor with the bound unmet
    """

    def __init__(self, passes, ug, uf, s_flat, unreachable, relaxed):
        self.passes, self.ug, self.uf, self.s_flat = passes, ug, uf, s_flat
        self.unreachable, self.relaxed = unreachable, relaxed


def place_passes(ws, fr, R: float, scallop: float, depth_lim: float, max_passes: int,
                 spec_path=None, chord: float = 0.0, normal: bool = True) -> PassPlan:
    """Place the passes across, pass by pass (the rules in the module docstring).
    ``chord``: the program's chord tolerance (mm), added to the bound where it follows
    the exact path (steep ground along the pass). ``normal``: the scallop is measured
    along the design's normal (``machining.scallop_measure: normal``), else vertically.

    Raises SpecError (``machining.scallop``) past ``max_passes`` passes."""
    return PassPlacer(ws, fr, R, scallop, depth_lim, spec_path=spec_path, chord=chord,
                      normal=normal).place(max_passes)


class PassPlacer:
    """Places the passes across one block (:func:`place_passes`): the first pass on or
    beyond the edge v = 0, then each next pass as far as the scallop bound
    (:func:`fabkit.toolpath.finish.scallop.sweep_material`) allows, the last one on or beyond
    the edge v = Lv, then the combs hanging off the edges (:func:`edge_comb`).

    What the placement finds on the way: ``unreach`` [mm, u, v], the most material
    beyond the ball's reach, and ``relaxed`` (mm, u, v) or None, where the stepover hit
    its floor with the bound unmet. ``ahead``: passes computed ahead at the flat
    stepover; ``floor_used``: the step needed the pass right beside the previous one
    (:meth:`floor_of`), so the next step computes that one with its candidate
    (``floor_ahead``)."""

    def __init__(self, ws, fr, R: float, scallop: float, depth_lim: float, *, spec_path=None,
                 chord: float = 0.0, normal: bool = True):
        self.ws, self.fr, self.R, self.depth_lim = ws, fr, R, depth_lim
        self.spec_path, self.chord, self.normal = spec_path, chord, normal
        self.ug = u_grid(fr, R)
        self.inside_u = (self.ug >= 0) & (self.ug <= fr.Lu)
        self.uq = self.ug[self.inside_u]
        self.target = SCALLOP_SAFETY * scallop
        self.uf = fine_grid(self.ug, R, self.target)
        # fixed for the placement: read-only, so that the profiles' weights and the nodes'
        # places on the fine grid are computed once (scallop.hermite_weights, node_index)
        self.ug.flags.writeable = False
        self.uf.flags.writeable = False
        self.s_flat = flat_stepover(R, self.target)
        self.s_min = MIN_STEP_SHARE * self.s_flat
        self.Lv = fr.Lv
        self.unreach = [0.0, math.nan, math.nan]
        self.relaxed = None
        self.ahead: list = []
        self.floor_used = False
        self.floor_ahead: dict = {}

    # ------------------------------------------------------------------ the loop
    def place(self, max_passes: int) -> PassPlan:
        passes = [self.first_pass()]
        s_next = self.s_flat
        while True:
            pa, older = passes[-1], passes[-2:-1]
            floor_last, self.floor_used = self.floor_used, False
            self.floor_ahead.clear()
            s = max(min(s_next, self.s_flat), self.s_min)
            allowed = (np.zeros(self.uq.shape), np.full(self.uq.shape, self.target))
            if pa.v + s >= self.Lv:
                end, s, allowed = self.last_pass(pa, older, s, allowed)
                if end is not None:
                    passes.append(end)
                    break
            pb, ratio = self.next_pass(pa, older, s, allowed, floor_last)
            passes.append(pb)
            if len(passes) > max_passes:
                raise SpecError(f"needs more than {max_passes} passes; raise the scallop",
                                file=self.spec_path, key="machining.scallop")
            # predict the next stepover from this one's margin (cusp ~ s^2)
            s_next = max(pb.v - pa.v, self.s_min) * min(GROWTH, 0.97 / math.sqrt(max(ratio, 1e-12)))
        comb = edge_comb(self.ws, self.fr, self.R, self.ug, self.uf, passes, self.target, self.chord,
                         self.normal, self.make, self.deep)
        if comb:
            passes = sorted(passes + comb, key=lambda p: p.v)
        return PassPlan(passes, self.ug, self.uf, self.s_flat, tuple(self.unreach), self.relaxed)

    # ------------------------------------------------------------------ the steps
    def first_pass(self):
        """The pass on or beyond the edge v = 0 that mills it (v = 0 if none does)."""
        p0, ml0 = self.edge_pass(0.0, -1.0, [])
        if p0 is None:
            p0, ml0 = self.make([0.0])[0], math.inf
        if ml0 > self.target and math.isfinite(ml0) and ml0 > self.unreach[0]:
            self.unreach[:] = [ml0, float(self.uq[0]) if self.uq.size else 0.0, 0.0]
        return p0

    def last_pass(self, pa, older, s, allowed):
        """The pass on or beyond the edge v = Lv, when the material up to it is within
        the bound (or the gap is too narrow for another pass): (that pass, s, allowed).
        Else (None, the stepover toward it, the bound): a pass between pa and the edge
        pass, beyond the edge if need be (where the ground falls toward the edge the edge
        pass lies up to R out, its contact inside; passes short of the edge alone never
        come close enough to it); :meth:`check` bounds the material from a pass beyond
        the edge to the edge too."""
        Lv, target = self.Lv, self.target
        pb, ml = self.edge_pass(Lv, 1.0, [pa] + older)
        if pb is None:
            pb, ml = self.make([Lv])[0], math.inf
        r = self.check(pa, pb, older, allowed, last=True)
        if r > 1.0:
            allowed = self.above_floor(self.floor_of(pa, older))
            r = self.check(pa, pb, older, allowed, last=True)
        if r <= 1.0 or max(pb.v, Lv) - pa.v <= 2 * self.s_min:
            if r > 1.0 and (self.relaxed is None or r * target > self.relaxed[0]):
                self.relaxed = (r * target, float(self.uq[-1]) if self.uq.size else 0.0, Lv)
            if target < ml < math.inf and ml > self.unreach[0]:
                self.unreach[:] = [ml, float(self.uq[-1]) if self.uq.size else 0.0, Lv]
            return pb, s, allowed
        self.ahead = []
        return None, min(s, 0.6 * (max(pb.v, Lv) - pa.v)), allowed

    def candidate(self, pa, s, floor_last):
        """The pass s beyond pa: computed ahead, or now. At the flat stepover the next
        passes likely follow at the same stepover: computed with this one (one call);
        elsewhere the next stepover depends on this pass's margin, and speculative
        passes would be wasted."""
        ahead = self.ahead
        cand = ahead.pop(0) if ahead and abs(ahead[0].v - (pa.v + s)) < 1e-12 else None
        if cand is None:
            look = (1, 2, 3) if s >= self.s_flat else (1,)
            vl = [pa.v + k * s for k in look if k == 1 or pa.v + k * s < self.Lv]
            vf = _beside(pa.v, MIN_STEP_SHARE * self.s_flat, self.Lv)
            cands = self.make(vl + [vf] if floor_last else vl)
            if floor_last:
                self.floor_ahead[vf] = cands.pop()
            cand, self.ahead = cands[0], cands[1:]
        return cand

    def next_pass(self, pa, older, s, allowed, floor_last):
        """(the next pass after pa, its ratio to the bound): the candidate s beyond pa if
        within the bound, else :meth:`closer`."""
        cand = self.candidate(pa, s, floor_last)
        ratio = self.check(pa, cand, older, allowed)
        if ratio <= 1.0:
            return cand, ratio
        return self.closer(pa, older, s, allowed, cand, ratio)

    def closer(self, pa, older, s, allowed, cand, ratio):
        """The candidate failed: first allow the material even a pass right beside pa
        leaves (reported as unreachable), then shrink the stepover (predicted from the
        ratio, four trials a round), and relax at the floor (or after 8 rounds): the
        largest stepover within 10 % of the best ratio (smaller ones do not help)."""
        target, s_min = self.target, self.s_min
        tried = [(ratio, cand)]
        floor_done = False
        tries = 0
        while True:
            self.ahead = []
            tries += 1
            if not floor_done:
                floor_done = True
                fl = self.floor_of(pa, older)
                if (fl > target).any():
                    allowed = self.above_floor(fl)
                    ratio = self.check(pa, cand, older, allowed)
                    tried.append((ratio, cand))
                    if ratio <= 1.0:
                        return cand, ratio
            f = min(0.97, max(0.3, 0.99 / math.sqrt(max(ratio, 1e-12))))
            s = max(s * f, s_min)
            trial = sorted({max(s * g, s_min) for g in (1.0, 0.85, 0.7, 0.55)}, reverse=True)
            for c in self.make([pa.v + t for t in trial]):
                ratio = self.check(pa, c, older, allowed)
                tried.append((ratio, c))
                if ratio <= 1.0:
                    return c, ratio
            if trial[-1] <= s_min * (1 + 1e-9) or tries >= 8:
                rmin = min(r for r, _ in tried)
                ratio, pb = max(((r, c) for r, c in tried if r <= 1.1 * rmin), key=lambda rc: rc[1].v)
                if self.relaxed is None or ratio * target > self.relaxed[0]:
                    self.relaxed = (ratio * target, float(self.uq[0]) if self.uq.size else 0.0, pa.v)
                return pb, ratio
            s = trial[-1]

    # ------------------------------------------------------------------ the passes
    def make(self, vlist):
        """The passes at ``vlist`` across (one compensation call)."""
        return compensate_passes(self.ws, self.fr, self.R, self.ug, self.uf, vlist, self.depth_lim, self.target)

    def deep(self, p) -> bool:
        """The pass goes below the depth limit."""
        k = p.keep
        return bool(k.any() and p.Z[k].min() < -self.depth_lim)

    def edge_pass(self, edge, sign, older):
        """The first pass on or beyond an edge that mills it (v = edge + sign f R)."""
        cands = self.make([edge + sign * f * self.R for f in EDGE_OUT])
        best, best_ml = None, math.inf
        for c in cands:
            if self.deep(c) or not c.keep.any():
                continue
            ml = self.edge_left(c, older, edge).max(initial=0.0)
            if ml <= self.target:
                return c, 0.0
            if ml < best_ml:
                best, best_ml = c, ml
        return best, best_ml

    # ------------------------------------------------------------------ the bound
    def left(self, vs, cutters):
        """The material the ``cutters`` leave at (uq, vs) (:func:`sweep_material`)."""
        ml = sweep_material(self.ws, self.fr, self.R, self.uq, vs, cutters, self.uf, 0.5 * self.target,
                            self.chord, self.normal)
        return np.nan_to_num(ml, nan=np.inf, posinf=np.inf)

    def peak(self, vs, cutters):
        """(per u, the largest material between the rows of vs; the material at vs).
        Refined around each column's largest sample where that exceeds REFINE_SHARE of
        the target: on ground steep across the passes the cusp is a sharp V (its flanks
        rise vertically ~ alpha / cos^2 theta over a horizontal step), and the 9 rows
        between the contact curves missed its crest by up to a quarter of the target (a
        tanh wall of slope 7: 0.053 mm left against the 0.0475 planned)."""
        ml = self.left(vs, cutters)
        top = ml.max(axis=0)
        if not self.normal:      # vertically the crest is held by the floor rules as before
            return top, ml
        cols = np.nonzero(np.isfinite(top) & (top > REFINE_SHARE * self.target))[0]
        if cols.size:
            i = np.argmax(ml[:, cols], axis=0)
            h = (vs[-1, cols] - vs[0, cols]) / (vs.shape[0] - 1)
            off = np.linspace(-1.0, 1.0, 9)[1:-1]
            vr = np.clip(vs[i, cols][None, :] + off[:, None] * h[None, :], 0.0, self.Lv)
            m2 = sweep_material(self.ws, self.fr, self.R, self.uq[cols], vr, cutters, self.uf,
                                0.5 * self.target, self.chord, self.normal)
            top[cols] = np.maximum(top[cols], np.nan_to_num(m2, nan=np.inf, posinf=np.inf).max(axis=0))
        return top, ml

    def edge_left(self, p, older, edge):
        """Per u, the material between pass p and the edge."""
        return self.peak(between_rows(p.cv[self.inside_u], np.full(self.uq.shape, edge), self.Lv), [p] + older)[0]

    def check(self, pa, pb, older, allowed, last=False):
        """Largest ratio, per position along u, of the material between pa and pb
        (and beyond pb to the edge when pb is the ``last`` pass) to ``allowed`` = (base,
        limit): (material - base) / (limit - base), base the unreachable material
        (0 where there is none). <= 1: within the bound; a cusp's share of what is
        allowed above the base, ~ s^2 (the next stepover is predicted from it)."""
        base, lim = allowed
        vs = between_rows(pa.cv[self.inside_u], pb.cv[self.inside_u], self.Lv)
        ml = self.peak(vs, [pb, pa] + older)[0]
        if last:
            ml = np.maximum(ml, self.edge_left(pb, [pa] + older, self.Lv))
        return float(((ml - base) / (lim - base)).max(initial=0.0))

    def above_floor(self, fl):
        """(base, limit): FLOOR_EXCESS (vertically FLOOR_EXCESS_VERTICAL) x target above
        the unreachable material fl where that exceeds the target, else the target."""
        target = self.target
        lim = np.maximum(target, fl + (FLOOR_EXCESS if self.normal else FLOOR_EXCESS_VERTICAL) * target)
        return np.where(lim > target, fl, 0.0), lim

    def floor_of(self, pa, older):
        """Per u, the material a pass right beside pa leaves too: beyond the ball's
        reach (a valley tighter than the tool, a V crease); no stepover removes it."""
        self.floor_used = True
        vf = _beside(pa.v, MIN_STEP_SHARE * self.s_flat, self.Lv)
        pt = self.floor_ahead.pop(vf, None) or self.make([vf])[0]
        vs = between_rows(pa.cv[self.inside_u], pt.cv[self.inside_u], self.Lv)
        fl = self.left(vs, [pt, pa] + older)      # not refined: a lower floor allows less
        self.note_floor(np.where(fl > FLOOR_SHARE * self.target, fl, 0.0), vs)
        return fl.max(axis=0)

    def note_floor(self, fl, vs):
        """Record the most unreachable material ``fl`` at (uq, vs), and where."""
        if fl.size and fl.max() > self.unreach[0]:
            i, j = np.unravel_index(int(np.argmax(fl)), fl.shape)
            self.unreach[:] = [float(fl[i, j]), float(self.uq[j]), float(vs[i, j])]


def edge_comb(ws, fr, R, ug, uf, passes, target, chord, normal, make, deep):
    """Passes hanging off the edges across, at :func:`comb_offsets`, each kept over the
    stretch along u (columns where the comb lowers the material in the band within R of
    the edge by more than COMB_GAIN x target, where the placed passes leave more than the
    target, plus R either side). The band is sampled at 16 distances from the edge (0 and
    0.005 R to R, geometric); the material is bounded as in :func:`sweep_material`.
    ``make`` computes passes at given v, ``deep`` tells a pass below the depth limit.
    Returns the passes to add (none on a block whose bands the placed passes finish)."""
    Lv = fr.Lv
    uq = ug[(ug >= 0) & (ug <= fr.Lu)]
    dist = np.r_[0.0, np.geomspace(0.005, 1.0, 15)] * R
    added = []
    for edge, sign in ((0.0, -1.0), (Lv, 1.0)):
        vrow = np.clip(edge - sign * dist, 0.0, Lv)
        vs = np.repeat(vrow[:, None], uq.size, axis=1)
        near = [p for p in passes if abs(p.v - edge) <= 2.0 * R]
        if not near or not uq.size:
            continue

        def left(cutters):
            ml = sweep_material(ws, fr, R, uq, vs, cutters, uf, 0.5 * target, chord, normal)
            return np.nan_to_num(ml, nan=np.inf, posinf=np.inf)

        m0 = left(near)
        if not (m0 > target).any():
            continue
        comb = [c for c in make([edge + sign * f * R for f in comb_offsets()])
                if c.keep.any() and not deep(c) and all(abs(c.v - p.v) > 1e-9 for p in near)]
        if not comb:
            continue
        m1 = left(near + comb)
        cols = np.nonzero(((m0 - m1 > COMB_GAIN * target) & (m0 > target)).any(axis=0))[0]
        if not cols.size:
            continue
        span = (ug >= uq[cols].min() - R) & (ug <= uq[cols].max() + R)
        for c in comb:
            c.keep = c.keep & span
            c.comb = True
            if c.keep.any():
                added.append(c)
    return added
