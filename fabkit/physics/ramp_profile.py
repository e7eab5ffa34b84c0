"""The ramp's running line: the profile the calibration integrates the ball's descent
along and ``fabkit ramp`` builds.

fabkit's own ramp (:class:`RampProfile`) is a copy of the block's channel, lifted by
D(u), u = start - x >= 0 back from the launch point: D'(u) = tan(theta) S(u / L) with
the smoothstep S(s) = 3 s^2 - 2 s^3 for u < L and tan(theta) beyond, so the running
surface joins the block's with the same height, slope and curvature (see
``fabkit/lab/ramp.py`` for the solid and its marks). A user's straight incline is
:class:`StraightRamp`. Design units throughout. This module needs nothing from the lab:
the lab builds on it, the calibration (``physics/calibrate.py``) integrates along it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import SpecError

ANGLE_DEG = 30.0


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


@dataclass(frozen=True)
class RampProfile:
    """The lift D(u) (design units) and the launch line; see the module doc."""

    start: float
    y0: float
    tan: float
    L: float
    u_end: float
    radius: float
    fns: object

    def lift(self, u):
        u = np.asarray(u, dtype=float)
        s = np.clip(u / self.L, 0.0, 1.0)
        inner = self.tan * self.L * (s ** 3 - 0.5 * s ** 4)
        return np.where(u <= self.L, inner, self.tan * (0.5 * self.L + (u - self.L)))

    def dlift(self, u):
        s = np.clip(np.asarray(u, dtype=float) / self.L, 0.0, 1.0)
        return self.tan * (3 * s ** 2 - 2 * s ** 3)

    def ddlift(self, u):
        s = np.clip(np.asarray(u, dtype=float) / self.L, 0.0, 1.0)
        return np.where(np.asarray(u) <= self.L, self.tan / self.L * (6 * s - 6 * s ** 2), 0.0)

    def z(self, u):
        """Height of the running surface on the launch line (design units)."""
        u = np.asarray(u, dtype=float)
        return self.fns.h(self.start - u, np.full_like(u, self.y0)) + self.lift(u)

    def slope(self, u):
        """dz/du on the launch line."""
        u = np.asarray(u, dtype=float)
        hx = self.fns.grad(self.start - u, np.full_like(u, self.y0))[0]
        return -hx + self.dlift(u)

    def curvature(self, u):
        """d^2z/du^2 on the launch line (design units^-1)."""
        u = np.asarray(u, dtype=float)
        hxx = self.fns.hess(self.start - u, np.full_like(u, self.y0))[0]
        return hxx + self.ddlift(u)

    def centre(self, u):
        """Height of a resting ball's centre over the contact point at u."""
        return self.z(u) + self.radius / np.sqrt(1.0 + self.slope(u) ** 2)

    def drop(self, u):
        """Release height H of a ball whose contact point is at u."""
        return self.centre(u) - self.centre(0.0)

    # the interface of a ramp's running line for the entry-speed integration
    # (physics/calibrate.py): the ball rolls from u_release(H) to u_stop, then crosses kink_angle
    u_stop = 0.0
    kink_angle = 0.0

    @property
    def breaks(self) -> tuple:
        """Where the line's curvature has a kink: the end of the lift's transition."""
        return (self.L,)

    @property
    def resolution(self) -> float:
        """The smallest release height the line resolves: H is a difference of the centre's
        heights (|centre| + r in size), which rounding knows to ~2e-16 of that; below 1e-7 of
        it the release point (and v_in to ~1e-9) cannot be placed."""
        return 1e-7 * (abs(float(self.centre(0.0))) + self.radius)

    @property
    def top(self) -> float:
        """The highest release height the ramp offers (the ball's contact at its far end)."""
        return float(self.drop(self.u_end))

    def u_release(self, H) -> np.ndarray:
        """Release points u (design units) for heights ``H`` (array): the first u from the
        launch point where the centre stands H above its height at the launch point (so the
        ball, released there, has the line below it), to 1e-13 relative; nan
        beyond the top, 0 for H <= 0."""
        H = np.atleast_1d(np.asarray(H, dtype=float))
        grid = np.linspace(0.0, self.u_end, 4001)
        d = np.maximum.accumulate(self.drop(grid))        # highest centre met so far
        i = np.searchsorted(d, H, side="left")            # first node at or above H
        ok = (H > 0) & (i < len(grid)) & np.isfinite(H)
        j = np.clip(i, 1, len(grid) - 1)
        lo, hi = grid[j - 1], grid[j]
        # to 1e-13 relative to u (a tiny height's release point is a tiny u; at most 1100 halvings
        # reach the smallest double from the first node)
        for _ in range(1100):
            mid = 0.5 * (lo + hi)
            above = self.drop(mid) >= H
            hi, lo = np.where(above, mid, hi), np.where(above, lo, mid)
            if not np.any(ok & (hi - lo > 1e-13 * hi)):
                break
        u = np.where(ok, hi, np.nan)
        return np.where(H <= 0, 0.0, u)

    def u_for_height(self, H: float) -> float:
        from scipy.optimize import brentq

        if not 0 <= H <= float(self.drop(self.u_end)):
            raise SpecError(f"release height {H:g} is beyond the ramp (top {float(self.drop(self.u_end)):g})",
                            key="ramp.heights")
        if H == 0:
            return 0.0
        return float(brentq(lambda u: float(self.drop(u)) - H, 0.0, self.u_end, xtol=1e-12 * self.u_end,
                            rtol=1e-14))


def ramp_angle(spec) -> float:
    """The incline's angle (degrees): ``ramp.angle``, 30 for fabkit's ramp if not given."""
    a = getattr(spec.ramp, "angle", None) if spec.has("ramp") else None
    return ANGLE_DEG if a is None else float(a)


@dataclass(frozen=True)
class StraightRamp:
    """A user's straight ramp (``ramp.profile: straight``): an incline at ``ramp.angle``
    to the horizontal whose running surface meets the block's surface at the launch point
    (x = simulation.start, y = y0) along a straight edge, ``ramp.length`` long along its
    surface from that edge. u is the horizontal distance back from the edge.

    The ball rolls down the incline until it touches both the incline and the block: its
    contacts are then r tan(kink/2) from the edge on both (tangent lengths), with kink =
    angle + beta the turn of the running surface (beta the block's slope angle along x at
    the launch point, from its tangent plane). It crosses the kink as an impact without
    bounce or slip: the angular momentum about the new contact is kept, so its centre's
    speed becomes V (k + cos kink) / (1 + k). H is the drop of the centre from release to
    its height resting on the block at the launch point."""

    angle: float          # degrees
    length: float         # design units, along the incline
    radius: float
    beta: float           # radians, the block's slope angle at the launch point (descending < 0)

    @property
    def tan(self) -> float:
        return math.tan(math.radians(self.angle))

    @property
    def kink_angle(self) -> float:
        return math.radians(self.angle) + self.beta

    @property
    def d_star(self) -> float:
        """The contacts' distance from the edge when the ball touches both surfaces."""
        return self.radius * math.tan(0.5 * self.kink_angle)

    @property
    def u_stop(self) -> float:
        return self.d_star * math.cos(math.radians(self.angle))

    breaks = ()
    resolution = 0.0          # the drop is linear in u: no cancellation

    def dlift(self, u):
        return np.full_like(np.asarray(u, dtype=float), self.tan)

    slope = dlift

    def curvature(self, u):
        return np.zeros_like(np.asarray(u, dtype=float))

    def drop(self, u):
        """Release height H of a ball whose contact on the incline is at u."""
        th = math.radians(self.angle)
        d = np.asarray(u, dtype=float) / math.cos(th)
        return d * math.sin(th) + self.radius * (math.cos(th) - math.cos(self.beta))

    @property
    def top(self) -> float:
        return float(self.drop(self.length * math.cos(math.radians(self.angle))))

    @property
    def u_end(self) -> float:
        return self.length * math.cos(math.radians(self.angle))

    def u_release(self, H) -> np.ndarray:
        """Release points for heights H: nan above the top, u_stop at or below the corner's
        height (the ball is already in the corner)."""
        H = np.atleast_1d(np.asarray(H, dtype=float))
        th = math.radians(self.angle)
        u = (H - self.radius * (math.cos(th) - math.cos(self.beta))) / math.tan(th)
        u = np.maximum(u, self.u_stop)
        return np.where((H <= self.top) & np.isfinite(H), u, np.nan)


def ramp_profile(spec):
    """The running line of the spec's ramp: fabkit's own (:func:`design_profile` for the
    highest of ``ramp.heights``) or the user's straight incline (:class:`StraightRamp`)."""
    r = 0.5 * float(spec.ball.diameter) if spec.has("ball") else 0.0
    if getattr(spec.ramp, "profile", "fabkit") == "straight":
        beta = 0.0
        if spec.has("surface") and spec.has("simulation"):
            hx = float(spec.surface_functions().grad(float(spec.simulation.start), float(spec.simulation.y0))[0])
            beta = math.atan(hx) if math.isfinite(hx) else 0.0
        prof = StraightRamp(angle=ramp_angle(spec), length=float(spec.ramp.length), radius=r, beta=beta)
        if not prof.kink_angle > 0:
            raise SpecError(f"the incline ({prof.angle:g} deg) does not descend onto the block, whose surface "
                            f"falls at {math.degrees(-beta):.4g} deg at the launch point", file=spec.path,
                            key="ramp.angle")
        if not prof.length > prof.d_star:
            raise SpecError(f"{prof.length:g} is shorter than the ball's contact in the corner "
                            f"({prof.d_star:.4g} from the edge)", file=spec.path, key="ramp.length")
        return prof
    return design_profile(spec, float(np.max(ramp_heights(spec))))


def design_profile(spec, h_needed: float) -> RampProfile:
    """The ramp for release heights up to ``h_needed`` (design units) plus two ball radii."""
    sim = spec.simulation
    r = 0.5 * float(spec.ball.diameter) if spec.has("ball") else 0.0
    tan = math.tan(math.radians(ramp_angle(spec)))
    lift_top = h_needed + 3.0 * r             # room for the ball above the highest mark
    L = lift_top / tan                        # the transition rises half of it
    u_end = 1.5 * L                           # D(u_end) = tan (L/2 + u_end - L) = lift_top
    prof = RampProfile(start=float(sim.start), y0=float(sim.y0), tan=tan, L=L, u_end=u_end, radius=r,
                       fns=spec.surface_functions())
    # grow the straight part until the highest mark fits (the surface may slope the other way)
    for _ in range(60):
        if float(prof.drop(prof.u_end)) >= h_needed + 2.0 * r:
            break
        prof = RampProfile(**{**prof.__dict__, "u_end": prof.u_end * 1.25})
    else:
        raise SpecError("the ramp cannot reach the release heights on this surface", key="ramp.heights")
    return prof
