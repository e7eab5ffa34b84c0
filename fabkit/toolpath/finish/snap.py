"""Cut points on the grid the controller reads back.

A program's coordinates are rounded to its decimals, and LinuxCNC's interpreter (and
most controller displays) keep 4 decimals of the program's unit: 1e-4 in = 2.54 um. On
steep ground a rounding of X or Y moves the ball sideways into the wall: at an edge
pass 0.999 R beyond the stock the ball's flank there has slope ~22, and a 1.27 um
rounding across was a 0.028 mm gouge in the moves ``rs274 -g`` read back from an inch
program (0.0063 mm in the program's own 5-decimal moves).

So where the program's decimals are finer than that grid, the cut points are put on
it before writing: X and Y rounded to the grid, the exact tip height computed again
at the rounded position (the drop cutter), and Z rounded UP to the grid. Every cut
point is then exactly what the controller reads, and never below the exact tip height
there (no gouge at the points; at most one grid step, 2.54 um, of extra material).
"""

from __future__ import annotations

import numpy as np

from .compensate import compensate
from ..path import RAPID

READBACK_DECIMALS = 4   # decimals of the program's unit the controller reads back


def readback_step(units_mm: float, decimals: int) -> float | None:
    """The grid step (mm) the cut points are put on, or None where the program's own
    ``decimals`` are no finer than the read-back grid (its rounding is the controller's)."""
    if decimals <= READBACK_DECIMALS:
        return None
    return 10.0 ** -READBACK_DECIMALS * units_mm


def program_grid(machining) -> tuple[float, float, float | None]:
    """(step mm, mm per program unit, slack mm or None): the grid a program's feed points
    are put on (:func:`snap_points`' ``step``, ``units_mm`` and ``slack_mm``) for a spec's
    ``machining`` section: the read-back grid where the program's decimals are finer
    than it (every point on it), else the program's own grid, a point put on it only
    where rounding costs more than tolerance / ROUNDING_SHARE."""
    from ..program.gcode import UNITS, MachineProfile
    from ...units import ROUNDING_SHARE

    k = UNITS[machining.units].mm_per_unit
    dec = MachineProfile(units=machining.units, tolerance=float(machining.tolerance)).decimals
    step = readback_step(k, dec)
    if step is None:
        return 10.0 ** -dec * k, k, float(machining.tolerance) / ROUNDING_SHARE
    return step, k, None


def snap_points(ws, R: float, points: np.ndarray, kinds: np.ndarray, step: float,
                units_mm: float, slack_mm: float | None = None, height=None) -> np.ndarray:
    """(n, 3) tip points (work mm) with every feed move's end point on the read-back
    grid of ``step`` mm: X, Y rounded, Z = the larger of the rounded Z and the exact tip
    height at the rounded X, Y rounded up (links above the material keep their height;
    points beyond the stock, where nothing is touched, too). Rapids are left to the
    writer's rounding. Grid values are whole multiples of 1e-4 program units, computed
    in program units so that the writer's decimal text of them is exact.

    ``slack_mm``: the grid is the program's own (its decimals no finer than the read-back
    grid); a point is put on it (X, Y rounded, Z rounded up to the exact tip height
    there) only where the exact tip height at the rounded X, Y lies more than
    ``slack_mm`` above the rounded Z: where rounding X, Y costs more than the share of
    the tolerance given to rounding (units.ROUNDING_SHARE). That happens on the ball's
    steep flank at an edge pass (the disk overhangs the stock but for a sliver: slope
    ~270 on a slope-20 wall, so 0.05 um across is 0.013 mm down); elsewhere every point
    is written as before.

    ``height``: callable(X, Y) -> the lowest tip height allowed at (X, Y), work mm
    (default: the ball's exact tip height on the design, :func:`.compensate.compensate`
    of ``ws`` and ``R``): a rest pass's ask (its drop plus the allowance)."""
    out = points.copy()
    feed = kinds != RAPID
    if not feed.any():
        return out
    k = units_mm
    q = step / k                                          # program units (1e-4)
    P = points[feed] / k
    XY = np.round(P[:, :2] / q) * q
    X, Y = np.ascontiguousarray(XY[:, 0] * k), np.ascontiguousarray(XY[:, 1] * k)
    Zx = (compensate(ws, X, Y, R) if height is None else np.asarray(height(X, Y), float)) / k
    z_round = np.round(P[:, 2] / q) * q
    with np.errstate(invalid="ignore"):
        z_up = np.ceil(np.where(np.isfinite(Zx), Zx, -np.inf) / q - 1e-9) * q
    if slack_mm is not None:
        with np.errstate(invalid="ignore"):
            far = np.isfinite(Zx) & (Zx > z_round + slack_mm / k)
        Z = np.where(far, np.maximum(z_round, z_up), P[:, 2])
        XY = np.where(far[:, None], XY, P[:, :2])
    else:
        Z = np.maximum(z_round, z_up)
    out[feed] = np.column_stack([XY, Z]) * k
    return out


def _along(a, b, step):
    """Moves along X (Y the same as written, on the grid of ``step``) and along Y."""
    same_y = np.abs(b[:, 1] - a[:, 1]) < 0.5 * step
    same_x = np.abs(b[:, 0] - a[:, 0]) < 0.5 * step
    return same_y & ~same_x, same_x & ~same_y


def refine_moves(ws, R: float, planned: np.ndarray, points: np.ndarray, kinds: np.ndarray,
                 step: float, slack_mm: float, etol: float, ttol: float, rounds: int = 24):
    """Points added on the moves whose ends the grid moved up by more than ``slack_mm``
    (the ball's flank at an edge pass: there the exact tip path along the written
    across coordinate is not the one the point spacing followed, its rim shifted by up
    to 270 x the rounding). Each such move along a pass (X or Y constant) is halved, at
    points on the grid of ``step`` mm, while the exact path (drop cutter at the written
    across coordinate) at the middle lies more than ``etol`` above the chord, or either
    half's tent bound (:func:`~fabkit.toolpath.finish.spacing.tent_bound`) exceeds
    ``ttol``; the added points' Z is their exact tip height rounded up to the grid.
    Returns (points, kinds)."""
    from .spacing import tent_bound, tip_slope

    n = len(points)
    if n < 2:
        return points, kinds
    feed = (kinds[1:] != RAPID) & (kinds[:-1] != RAPID)
    a, b = points[:-1], points[1:]
    rose = np.maximum(b[:, 2] - planned[1:, 2], a[:, 2] - planned[:-1, 2]) > slack_mm
    along_x, along_y = _along(a, b, step)
    cand = np.nonzero(feed & rose & (along_x | along_y) & (np.minimum(a[:, 2], b[:, 2]) < 0))[0]
    if not cand.size:
        return _lift_short(ws, R, points, kinds, step, etol)
    ax = along_x[cand]
    ua = np.where(ax, a[cand, 0], a[cand, 1])
    ub = np.where(ax, b[cand, 0], b[cand, 1])
    v = np.round(np.where(ax, a[cand, 1], a[cand, 0]) / step) * step     # as written

    def exact(u, v, ax):
        X, Y = np.where(ax, u, v), np.where(ax, v, u)
        z, ci = compensate(ws, X, Y, R, return_info=True)
        return z, np.where(np.isfinite(z), tip_slope(ci, X, Y, u, R, ax), 0.0)

    za_x, sa = exact(ua, v, ax)
    zb_x, sb = exact(ub, v, ax)
    za, zb = a[cand, 2], b[cand, 2]
    move = np.arange(cand.size)
    seg = (move, ua, za, sa, ub, zb, sb)
    added_m, added_u, added_z = [], [], []
    for _ in range(rounds):
        m_, ua_, za_, sa_, ub_, zb_, sb_ = seg
        if not m_.size:
            break
        um = np.round(0.5 * (ua_ + ub_) / step) * step
        inner = (um > np.minimum(ua_, ub_) + 0.5 * step) & (um < np.maximum(ua_, ub_) - 0.5 * step)
        m_, ua_, za_, sa_, ub_, zb_, sb_, um = (x[inner] for x in (m_, ua_, za_, sa_, ub_, zb_, sb_, um))
        if not m_.size:
            break
        zm, sm = exact(um, v[m_], ax[m_])
        fin = np.isfinite(zm)
        with np.errstate(all="ignore"):
            t = (um - ua_) / (ub_ - ua_)
            rise = zm - (za_ + t * (zb_ - za_))
        # slopes are d/du along the move's own direction of travel
        sgn = np.sign(ub_ - ua_)
        ta = np.maximum(tent_bound(0.0 * um, za_, sa_ * sgn, np.abs(um - ua_), zm, sm * sgn),
                        tent_bound(0.0 * um, zm, sm * sgn, np.abs(ub_ - um), zb_, sb_ * sgn))
        bad = fin & ((rise > etol) | (ta > ttol))
        zw = np.ceil(np.where(fin, zm, -np.inf) / step - 1e-9) * step
        added_m.append(m_[bad])
        added_u.append(um[bad])
        added_z.append(zw[bad])
        b_ = bad
        seg = (np.r_[m_[b_], m_[b_]], np.r_[ua_[b_], um[b_]], np.r_[za_[b_], zw[b_]], np.r_[sa_[b_], sm[b_]],
               np.r_[um[b_], ub_[b_]], np.r_[zw[b_], zb_[b_]], np.r_[sm[b_], sb_[b_]])
    if not added_m or not sum(x.size for x in added_m):
        return _lift_short(ws, R, points, kinds, step, etol)
    am, au, az = np.concatenate(added_m), np.concatenate(added_u), np.concatenate(added_z)
    # the added points of each move in its direction of travel
    i = cand[am]
    key = np.abs(au - ua[am])
    order = np.lexsort((key, i))
    i, au, az, am = i[order], au[order], az[order], am[order]
    newp = np.column_stack([np.where(ax[am], au, v[am]), np.where(ax[am], v[am], au), az])
    at = i + 1                                   # before the move's end point
    pts = np.insert(points, at, newp, axis=0)
    kds = np.insert(kinds, at, kinds[at], axis=0)
    return _lift_short(ws, R, pts, kds, step, etol)


#: where the rise of a one-step move is measured: 65 even points and 2^-6 .. 2^-29 of it
#: from either end (a nearly vertical tangent crowds it against an end)
_SHORT_T = np.unique(np.r_[np.linspace(0.0, 1.0, 65), 2.0 ** -np.arange(6, 30), 1 - 2.0 ** -np.arange(6, 30)])


def _lift_short(ws, R, points, kinds, step, etol):
    """Moves along a pass one grid step long (no grid point between their ends to add)
    whose exact tip path still rises more than ``etol`` above them (the ball's flank at
    the end of a pass hanging off the stock, its path nearly vertical: an inch program's
    2.54 um step is 0.05 mm of it) get their lower end raised, on the grid, until the
    chord clears the path (more material there, never a gouge: a raised point only
    raises the chords through it). Returns (points, kinds)."""
    if len(points) < 2:
        return points, kinds
    a, b = np.round(points[:-1] / step) * step, np.round(points[1:] / step) * step    # as written
    feed = (kinds[1:] != RAPID) & (kinds[:-1] != RAPID)
    ax, ay = _along(a, b, step)
    length = np.abs(b[:, 0] - a[:, 0]) + np.abs(b[:, 1] - a[:, 1])
    short = np.nonzero(feed & (ax | ay) & (length < 1.5 * step) & (np.minimum(a[:, 2], b[:, 2]) < 0))[0]
    if not short.size:
        return points, kinds
    t = _SHORT_T
    A, B = a[short], b[short]
    P = A[:, None, :] + t[None, :, None] * (B - A)[:, None, :]
    Z = compensate(ws, P[..., 0], P[..., 1], R)
    rise = np.where(np.isfinite(Z), Z - P[..., 2], -np.inf)
    bad = rise.max(axis=1) > etol
    if not bad.any():
        return points, kinds
    out = points.copy()
    for k in np.nonzero(bad)[0]:
        j = int(short[k])
        r = rise[k]
        # lifting the end b by d raises the chord by d t; the end a, by d (1 - t)
        with np.errstate(divide="ignore", invalid="ignore"):
            need_b = np.max(np.where(r > 0, r / t, 0.0))
            need_a = np.max(np.where(r > 0, r / (1.0 - t), 0.0))
        end, d = (j + 1, need_b) if out[j + 1, 2] <= out[j, 2] else (j, need_a)
        if np.isfinite(d):
            out[end, 2] = np.ceil((out[end, 2] + d) / step - 1e-9) * step
    return out, kinds
