"""Length units. Internally: design lengths stay in design units; machine
lengths (stock, tool, machining) are in millimetres; programs are written in
their own units at the edge.

The program's rounding rules live here too (one home for the writer,
:mod:`fabkit.toolpath.program.gcode`, and the spec's checks, :mod:`fabkit.spec`): each
program unit's coordinate and feed decimals, the most decimals a coordinate
carries (:data:`MAX_DECIMALS`), and the share of the machining tolerance a
coordinate's rounding may take (half a unit in the last place at most
tolerance / :data:`ROUNDING_SHARE`).
"""

from __future__ import annotations

from dataclasses import dataclass

#: millimetres per inch (exact by definition)
MM_PER_INCH = 25.4

MM_PER = {"mm": 1.0, "cm": 10.0, "in": MM_PER_INCH}

#: standard gravity, m/s^2 (exact by definition)
G_STANDARD = 9.80665


def mm_per(unit: str) -> float:
    """Millimetres per one ``unit`` (mm, cm or in)."""
    return MM_PER[unit]


def gravity(unit: str) -> float:
    """Standard gravity in ``unit``/s^2."""
    return G_STANDARD * 1000.0 / MM_PER[unit]


# ----------------------------------------------------------------------------
# the program's units and rounding
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class ProgramUnits:
    """Program units: G word, mm per unit, coordinate and feed decimals."""

    name: str
    gword: str
    mm_per_unit: float
    decimals: int
    feed_decimals: int


PROGRAM_UNITS: dict[str, ProgramUnits] = {
    "mm": ProgramUnits("mm", "G21", 1.0, 4, 1),
    "in": ProgramUnits("in", "G20", MM_PER_INCH, 5, 3),
}

#: the most decimals a program coordinate carries
MAX_DECIMALS = 6
#: half a unit in a coordinate's last place is at most tolerance / ROUNDING_SHARE
ROUNDING_SHARE = 20


def program_rounding(value: float, decimals: int) -> float:
    """``value`` as the program writes it with ``decimals`` decimals, read back."""
    return float(f"{value:.{decimals}f}")


def coordinate_decimals(unit: str, tolerance_mm: float) -> int:
    """Coordinate decimals in program ``unit``: the unit's default, raised until half a
    unit in the last place is at most tolerance / :data:`ROUNDING_SHARE` (capped at
    :data:`MAX_DECIMALS`)."""
    u = PROGRAM_UNITS[unit]
    dec = u.decimals
    while dec < MAX_DECIMALS and 0.5 * 10.0 ** -dec * u.mm_per_unit > tolerance_mm / ROUNDING_SHARE:
        dec += 1
    return dec


def finest_tolerance(unit: str) -> float:
    """The finest machining tolerance, mm, a program in ``unit`` can carry: the rounding at
    :data:`MAX_DECIMALS` decimals is then exactly tolerance / :data:`ROUNDING_SHARE`."""
    return ROUNDING_SHARE * (0.5 * 10.0 ** -MAX_DECIMALS) * PROGRAM_UNITS[unit].mm_per_unit
