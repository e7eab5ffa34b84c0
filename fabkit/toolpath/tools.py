"""Cutting tools as shapes: flat end mill, bull nose (corner radius) and ball.

A tool is a solid of revolution about its axis. Its cutting surface is described by
:meth:`Tool.lift`: the height of the surface above the tip at a radial distance rho
from the axis (0 on a flat bottom, a quarter circle on a corner). Every cut
simulation and every compensation takes the tool's shape from here, so the three
shapes are written once. Lengths are millimetres. Also the spec's tools as Tools
(:func:`spec_tools`, :func:`finish_tool`), their depths of cut and feeds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["SHAPES", "Tool", "spec_tools", "finish_tool", "depth_of_cut", "feeds_of"]

SHAPES = ("flat", "bull", "ball")


@dataclass(frozen=True)
class Tool:
    """One cutting tool (mm, mm/min, rpm).

    ``corner_radius`` is 0 for a flat end mill, the radius for a ball and in between
    for a bull nose. ``reach`` is the usable length below the holder (flute length or
    stick-out): no cut may be deeper. ``number`` is the tool-table number (None: no
    tool call). ``feed``, ``plunge`` and ``spindle`` are the tool's own (None: the
    machining section's)."""

    shape: str
    diameter: float
    corner_radius: float = 0.0
    reach: float = math.inf
    number: int | None = None
    feed: float | None = None
    plunge: float | None = None
    spindle: float | None = None

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise ValueError(f"tool shape {self.shape!r}: one of {', '.join(SHAPES)}")
        R = 0.5 * self.diameter
        if self.shape == "ball":
            object.__setattr__(self, "corner_radius", R)
        elif self.shape == "flat":
            object.__setattr__(self, "corner_radius", 0.0)
        elif not 0.0 < self.corner_radius <= R:
            raise ValueError(f"bull nose corner radius {self.corner_radius:g} mm: must be in (0, {R:g}]")

    @classmethod
    def ball(cls, diameter: float, **kw) -> "Tool":
        return cls("ball", float(diameter), 0.5 * float(diameter), **kw)

    @property
    def radius(self) -> float:
        return 0.5 * self.diameter

    @property
    def flat_radius(self) -> float:
        """Radius of the flat bottom (0 for a ball)."""
        return self.radius - self.corner_radius

    def lift(self, rho):
        """Height of the cutting surface above the tip at radial distance ``rho`` (mm);
        +inf beyond the tool's radius. Works on arrays."""
        rho = np.abs(np.asarray(rho, dtype=float))
        r, f = self.corner_radius, self.flat_radius
        out = np.full(rho.shape, np.inf)
        inside = rho <= self.radius
        u = np.clip(rho - f, 0.0, None)
        corner = r - np.sqrt(np.clip(r * r - u * u, 0.0, None)) if r > 0 else np.zeros_like(u)
        out[inside] = corner[inside]
        return out

    def describe(self) -> str:
        d = f"{self.diameter:g} mm"
        name = {"flat": "flat end mill", "ball": "ball-end mill",
                "bull": f"bull nose (corner {self.corner_radius:g} mm)"}[self.shape]
        return f"{d} {name}" + (f", T{self.number}" if self.number is not None else "")


def finish_tool(spec) -> Tool:
    """The finishing ball of the ``tool`` section."""
    t = spec.tool
    return Tool.ball(float(t.diameter), reach=float(t.reach), number=t.number)


def spec_tools(spec) -> dict[int, Tool]:
    """Every numbered tool of the spec: the ``tools`` list and the finishing ``tool``
    (when it has a number), by tool number. Feeds None mean the machining section's."""
    out = {}
    if spec.has("tool") and spec.tool.number is not None:
        out[int(spec.tool.number)] = finish_tool(spec)
    for t in (spec.tools if spec.has("tools") else ()):
        out[int(t.number)] = Tool(t.shape, float(t.diameter),
                                  float(t.corner_radius or 0.0), reach=float(t.reach), number=int(t.number),
                                  feed=t.feed, plunge=t.plunge, spindle=t.spindle)
    return out


def depth_of_cut(spec, number) -> float:
    """The axial depth of cut (mm) of tool ``number`` (None: the finishing tool)."""
    if number is None or (spec.tool.number is not None and number == spec.tool.number):
        return float(spec.tool.depth_of_cut)
    for t in spec.tools:
        if t.number == number:
            return float(t.depth_of_cut)
    raise KeyError(number)


def feeds_of(spec, tool: Tool) -> tuple[float, float]:
    m = spec.machining
    return float(tool.feed or m.feed), float(tool.plunge or m.plunge)
