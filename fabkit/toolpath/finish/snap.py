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


def snap_points(ws, R: float, points: np.ndarray, kinds: np.ndarray, step: float,
                units_mm: float, slack_mm: float | None = None) -> np.ndarray:
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
    is written as before."""
    out = points.copy()
    feed = kinds != RAPID
    if not feed.any():
        return out
    k = units_mm
    q = step / k                                          # program units (1e-4)
    P = points[feed] / k
    XY = np.round(P[:, :2] / q) * q
    Zx = compensate(ws, XY[:, 0] * k, XY[:, 1] * k, R) / k
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
