"""Ramp calibration: release height <-> entry speed for a ball rolling without slipping.

Energy balance on the ramp (rolling without slipping, no losses):

    m g H = 1/2 m v^2 (1 + k),     k = I / (m r^2)

so ``v_in = sqrt(2 g H / (1 + k))`` and ``H = (1 + k) v_in^2 / (2 g)``. For a
solid sphere k = 2/5 (the paper's 7/5 factor), hollow k = 2/3, or a number
from ``ball.inertia``. ``g`` is standard gravity in design units/s^2
(:func:`fabkit.units.gravity`); H is measured from the entry level (the height
of the surface where the ball enters it). Both directions are exact closed
forms (rounding only).

>>> round(float(v_in_from_height(4.5, 980.665, 0.4)), 3)     # cm, cm/s
79.28
"""

from __future__ import annotations

import numpy as np

from ..errors import SpecError
from ..units import gravity


def v_in_from_height(H, g: float, k: float):
    """Entry speed (design units/s) for release height(s) ``H`` (design units, >= 0).

    H: scalar or array; g: gravity in design units/s^2; k = I/(m r^2).
    Returns an array of H's shape (a float for a scalar H).
    """
    H = np.asarray(H, dtype=float)
    # sqrt(2 g / (1 + k)) sqrt(H): no overflow for any finite H
    return np.sqrt(2.0 * g / (1.0 + k)) * np.sqrt(H)


def height_from_v_in(v, g: float, k: float):
    """Release height (design units) that gives entry speed(s) ``v`` (design units/s)."""
    v = np.asarray(v, dtype=float)
    with np.errstate(over="ignore"):
        return (1.0 + k) / (2.0 * g) * v * v


def ramp_heights(spec) -> np.ndarray:
    """The ramp's release heights, (M,) design units.

    ``ramp.heights`` with 2 values is ``[min, max]`` sampled at ``ramp.samples``
    evenly spaced points (both ends included); 3 or more values are used as given.
    """
    spec.require("ramp")
    hs = [float(h) for h in spec.ramp.heights]
    if len(hs) == 2:
        lo, hi = hs
        if not hi >= lo:
            raise SpecError(f"[min, max] must have min <= max, got [{lo:g}, {hi:g}]",
                            file=spec.path, key="ramp.heights")
        n = int(spec.ramp.samples)
        return np.linspace(lo, hi, n)
    return np.asarray(hs, dtype=float)


def ball_k(spec) -> float:
    """k = I/(m r^2) of the spec's ball (0.4 solid, 2/3 hollow, or the number given)."""
    return float(spec.ball.inertia) if spec.has("ball") else 0.4


def calibration_table(spec) -> dict:
    """Heights and entry speeds for the spec's ramp.

    Returns ``{"heights": (M,), "v_in": (M,), "g": float, "k": float, "units": str}``
    (heights in design units, v_in in design units/s, g in design units/s^2).
    """
    spec.require("ball", "ramp", command="calibrate")
    g = gravity(spec.units)
    k = ball_k(spec)
    H = ramp_heights(spec)
    return {"heights": H, "v_in": v_in_from_height(H, g, k), "g": g, "k": k, "units": spec.units}
