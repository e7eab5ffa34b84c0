"""The outcome of a launch: its integer code and its name, defined once for the
simulator (:mod:`fabkit.physics.models`, the compiled engine
:mod:`fabkit.physics.engine.dop853`), the phi^4 collisions (:mod:`fabkit.waves.phi4`,
which use the first two) and every report.

``captured`` also covers a launch too slow to arrive anywhere before ``t_max`` (it is
still on the surface, trapped, when time runs out). ``bridged`` and ``slipped`` occur
only in the ``ball`` model (:mod:`fabkit.physics.ball`): the ball touches the surface at
two points (r times the largest concave principal curvature reaches 1), or the friction
it needs exceeds ``ball.friction``.
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np


class Outcome(StrEnum):
    """The outcome labels, in the order of their integer codes. A member is its label
    (a ``str``: it compares, hashes and formats as the label); results and JSON carry
    the plain label (``Outcome.X.value``)."""

    ESCAPED = "escaped"
    CAPTURED = "captured"
    FLEW_OFF = "flew_off"
    LOST_CONTACT = "lost_contact"
    BRIDGED = "bridged"
    SLIPPED = "slipped"

    @property
    def code(self) -> int:
        """The integer outcome code of the simulator's results."""
        return OUTCOMES.index(self.value)

    @classmethod
    def of(cls, code) -> "Outcome":
        """The outcome of an integer code."""
        return cls(OUTCOMES[int(code)])


#: outcome names; the index is the integer outcome code of the simulator's results
OUTCOMES = tuple(o.value for o in Outcome)
ESCAPED, CAPTURED, FLEW_OFF, LOST_CONTACT, BRIDGED, SLIPPED = range(6)
#: outcomes where the ball leaves the modelled motion: a design with one is unsafe
UNSAFE = (FLEW_OFF, LOST_CONTACT, BRIDGED, SLIPPED)


def unsafe(outcome) -> np.ndarray:
    """Boolean mask of the unsafe outcome codes (:data:`UNSAFE`)."""
    return np.isin(np.asarray(outcome), UNSAFE)


def outcome_names(codes) -> list[str]:
    """The names of integer outcome codes, in order."""
    return [OUTCOMES[int(c)] for c in np.asarray(codes).ravel().tolist()]


def outcome_counts(names) -> dict:
    """{name: how many} over outcome names, in order of first appearance."""
    out: dict = {}
    for o in names:
        out[o] = out.get(o, 0) + 1
    return out
