"""A machining job as a sequence of operations, each with its own tool.

An :class:`Operation` is what one tool does: roughing in Z levels with a flat end mill
or bull nose, rest passes where the roughing tool could not reach, the finishing
passes with the ball. Its :class:`~fabkit.toolpath.path.Toolpath` holds tool-TIP
positions in work millimetres (origin on the top face, Z up), links and rapids
included, so a writer only formats it and a cut simulation only replays it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .path import Toolpath
from .tools import Tool

__all__ = ["OPERATION_KINDS", "Operation"]

#: the operations in the order a job runs them
OPERATION_KINDS = ("rough", "rest", "finish")


@dataclass
class Operation:
    """One tool's part of the job.

    kind: "rough" | "rest" | "finish"
    tool: the tool that cuts it (its shape sets the cut)
    toolpath: tip positions and move kinds (work mm), links included
    leave: mm of material this operation leaves above the design where its tool
        reaches (0 for the finish)
    levels: Z levels cut (0 for a surface-following operation)
    passes: passes (or contour loops) cut
    info: planning figures for the setup sheet and the summary
    """

    kind: str
    tool: Tool
    toolpath: Toolpath
    leave: float = 0.0
    levels: int = 0
    passes: int = 0
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in OPERATION_KINDS:
            raise ValueError(f"operation kind {self.kind!r}: one of {', '.join(OPERATION_KINDS)}")

    @property
    def name(self) -> str:
        """``rough``, ``rest`` or ``finish``: also the grbl file's suffix (``<stem>.1-rough.nc``)."""
        return self.kind
