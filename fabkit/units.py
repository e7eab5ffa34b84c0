"""Length units. Internally: design lengths stay in design units; machine
lengths (stock, tool, machining) are in millimetres; programs are written in
their own units at the edge."""

from __future__ import annotations

MM_PER = {"mm": 1.0, "cm": 10.0, "in": 25.4}

#: standard gravity, m/s^2 (exact by definition)
G_STANDARD = 9.80665


def mm_per(unit: str) -> float:
    """Millimetres per one ``unit`` (mm, cm or in)."""
    return MM_PER[unit]


def gravity(unit: str) -> float:
    """Standard gravity in ``unit``/s^2."""
    return G_STANDARD * 1000.0 / MM_PER[unit]
