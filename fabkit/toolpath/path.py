"""The toolpath passed from planning (raster.py) to the G-code writer (gcode.py).

All coordinates are work coordinates in millimetres (origin on the top face at
the footprint corner of smallest x and y, Z up, stock occupies
[0, L] x [0, W] x [-thickness, 0]) and are positions of the TOOL TIP (the
lowest point of the ball; the ball's centre is tip + (0, 0, R)).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

RAPID = 0    # G0 to this point
PLUNGE = 1   # G1 at the plunge feed to this point (entering material / going down)
CUT = 2      # G1 at the cutting feed to this point


@dataclass
class Toolpath:
    """A sequence of moves. ``points[i]`` is reached by a move of kind ``kinds[i]``
    from ``points[i-1]`` (the first point is reached by a rapid from the safe height).

    points: (n, 3) float, tip positions, mm, work coordinates
    kinds:  (n,) int8, RAPID | PLUNGE | CUT
    """

    points: np.ndarray
    kinds: np.ndarray
    tool_radius: float                  # mm
    safe_z: float                       # mm, work Z of the safe plane (top face + safe_height)
    passes: int = 0                     # finishing passes (roughing passes not counted)
    stepover: float = 0.0               # mm, largest stepover between adjacent finishing passes
    stepover_min: float = 0.0           # mm, smallest (variable stepover)
    info: dict = field(default_factory=dict)  # planning figures for the setup sheet / summary
    plan: object = field(default=None, repr=False, compare=False)  # the placed passes (add_passes)

    def __post_init__(self):
        self.points = np.ascontiguousarray(self.points, dtype=float).reshape(-1, 3)
        self.kinds = np.ascontiguousarray(self.kinds, dtype=np.int8).reshape(-1)
        if len(self.points) != len(self.kinds):
            raise ValueError("points and kinds differ in length")

    def __len__(self) -> int:
        return len(self.points)
