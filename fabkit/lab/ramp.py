"""The launch ramp: a watertight solid that lifts the channel up to the release heights.

Geometry (design units, then work coordinates of the block, mm)
--------------------------------------------------------------
The ramp is a copy of the block's own channel, lifted: its running surface is

    T(x, y) = h(x, y) + D(u),    u = start - x >= 0 (back from the launch point),

with D(u) = 0 at the launch point. D'(u) = tan(theta) S(u / L) with the smoothstep
S(s) = 3 s^2 - 2 s^3 for u < L and D' = tan(theta) beyond (a straight incline), so
D(0) = D'(0) = D''(0) = 0: the ramp's surface joins the block's surface along the
whole line x = start with the same height, slope and curvature in every direction
(tangent- and curvature-continuous), and the transition joins the incline with
D'' = 0 (again curvature-continuous). theta = 30 degrees; L is chosen so that the
transition rises half the ramp. The ball rolls along y = simulation.y0 (the launch
line) in the lifted channel, touching it at one point (its radius is below the
channel's radius of curvature across), so the rolling calibration applies.

The solid is the region above the table (the stock's bottom plane, Z = -thickness)
and below T, over u in [0, u_end] and |y - y0| <= the half width, minus the block
itself (sampled on the same grid, so T - h = D >= 0 holds triangle by triangle): it
rests on the milled channel from the launch point back to the block's end and on the
table beyond, and thins out to nothing at the launch point. In the block's work
coordinates: (X, Y, Z) = s (x - x0, y - y0, z - top), X < 0 beyond the block's end.

Release marks
-------------
A ball released with its centre H above its centre at the launch point enters at
v_in = sqrt(2 g H / (1 + k)) (``fabkit calibrate``). Its centre stands at
T + r cos(phi) over the contact point (phi the ramp's slope angle), so a mark for H is
placed where T(u) + r cos(phi(u)) - (T(0) + r cos(phi(0))) = H (root found to 1e-12
relative): the ball's contact point when released there. Marks: the centre (in v_in)
of every two-bounce window the ramp can reach (from ``fabkit check``) and v_critical;
each is an engraved groove across the ramp (0.6 mm wide, 0.8 mm deep, following the
surface) beside the ball's path, which stays smooth over 0.8 ball radii; window marks
alternate sides (their windows crowd together near v_critical), v_critical's mark is a
double groove (2 mm apart) on both sides. Marks closer than a groove are flagged
``crowded``: the ramp cannot show them apart, the table (height, distance along the
surface) still can.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import SpecError
from ..physics.ramp_profile import (ANGLE_DEG, RampProfile, StraightRamp, design_profile,  # noqa: F401
                                    ramp_angle, ramp_profile)

GROOVE_WIDTH_MM = 0.6
GROOVE_DEPTH_MM = 0.8
GROOVE_MIN_DEPTH_MM = 0.05   # shallower than this a groove is not cut (the ramp under it is too thin)
GROOVE_GAP_MM = 2.0          # between the two lines of a double groove
GROOVE_CLEAR_MM = 0.4        # least wall between two grooves in one lane (else set apart across the ramp)
LANE_GAP_MM = 2.0            # between two lanes of grooves across the ramp
LANE_MIN_MM = 3.0            # the shortest groove a lane may hold
STEP_MM = 1.0                # grid spacing along the ramp
STEP_Y_MM = 2.0              # grid spacing across


def half_width(spec, prof: RampProfile) -> float:
    """Half width of the ramp across y (design units): three ball diameters, less where the
    channel at the launch point rises to the block's top - margin, and inside the footprint."""
    r = prof.radius
    y_lo, y_hi = (float(v) for v in spec.surface.y)
    top = float(spec.surface.top)
    margin = float(spec.simulation.margin)
    w = min(6.0 * r if r > 0 else 0.25 * (y_hi - y_lo), prof.y0 - y_lo, y_hi - prof.y0)
    ys = np.linspace(0.0, w, 401)
    z0 = float(prof.fns.h(prof.start, prof.y0))
    for sign in (1, -1):
        zz = prof.fns.h(np.full_like(ys, prof.start), prof.y0 + sign * ys)
        over = np.flatnonzero(zz > top - margin)
        if over.size:
            w = min(w, ys[max(over[0] - 1, 1)])
    if not w > 1.5 * r:
        raise SpecError(f"the channel at the launch point is too narrow for a ramp (half width {w:g} at "
                        f"top - margin, the ball's radius is {r:g}; entry level {z0:g})", key="simulation.start")
    return float(w)


# ----------------------------------------------------------------------------
# meshes
# ----------------------------------------------------------------------------
def heightfield(X: np.ndarray, Y: np.ndarray, Ztop: np.ndarray, Zbot) -> tuple[np.ndarray, np.ndarray]:
    """A closed mesh between two heightfields over the grid X (nx,) x Y (ny,) (increasing):
    vertices (2 nx ny, 3), faces (m, 3) outward. Ztop (nx, ny); Zbot scalar or (nx, ny), below."""
    nx, ny = len(X), len(Y)
    GX, GY = np.meshgrid(X, Y, indexing="ij")
    Zb = np.broadcast_to(np.asarray(Zbot, dtype=float), (nx, ny))
    V = np.concatenate([np.stack([GX, GY, Ztop], -1).reshape(-1, 3), np.stack([GX, GY, Zb], -1).reshape(-1, 3)])
    off = nx * ny
    idx = np.arange(off).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    top = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    bot = top[:, ::-1] + off
    loop = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    p, q = loop, np.roll(loop, -1)
    sides = np.concatenate([np.stack([p + off, q + off, q], 1), np.stack([p + off, q, p], 1)])
    return V, np.concatenate([top, bot, sides]).astype(np.int64)


def _manifold(V, F):
    import manifold3d

    m = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.ascontiguousarray(V, dtype=float),
                                              tri_verts=np.ascontiguousarray(F, dtype=np.uint64)))
    if m.status() != manifold3d.Error.NoError:
        raise RuntimeError(f"manifold3d rejected a ramp part: {m.status().name}")
    return m


@dataclass
class RampSolid:
    vertices: np.ndarray
    faces: np.ndarray
    volume_mm3: float
    bodies: int
    genus: int
    profile_error_mm: float
    extent_mm: dict


def build_ramp(spec, prof: RampProfile, marks: list[dict]) -> RampSolid:
    """The ramp as one body in the block's work coordinates (mm), with the marks' grooves
    engraved. ``marks``: from :func:`place_marks` (``u`` design units, ``double``, and
    ``grooves``, each side's extent across the ramp). Whether the mesh is one watertight
    body is checked on the bytes written (:func:`mesh_verdict`)."""
    s = float(spec.scale)
    x0f, y0f = float(spec.surface.x[0]), float(spec.surface.y[0])
    top = float(spec.surface.top)
    z_table = -float(spec.stock.thickness)            # mm, the stock's bottom plane
    hw = half_width(spec, prof)
    fns = prof.fns
    xs = prof.start - prof.u_end
    # grid along x: STEP_MM apart, with the block's end x0 and the launch point as nodes
    nxa = max(8, int(math.ceil(prof.u_end * s / STEP_MM)))
    gx = np.linspace(xs, prof.start, nxa + 1)
    if xs < x0f < prof.start:
        gx = np.unique(np.concatenate([gx, [x0f]]))
    nya = max(8, int(math.ceil(2 * hw * s / STEP_Y_MM)))
    gy = np.unique(np.concatenate([np.linspace(prof.y0 - hw, prof.y0 + hw, nya + 1), [prof.y0]]))
    GX, GY = np.meshgrid(gx, gy, indexing="ij")
    H = fns.h(GX, GY)
    T = H + prof.lift(prof.start - GX)

    def work(x, y, z):
        return (x - x0f) * s, (y - y0f) * s, (z - top) * s

    Xw, Yw = (gx - x0f) * s, (gy - y0f) * s
    V, F = heightfield(Xw, Yw, (T - top) * s, z_table)
    ramp = _manifold(V, F)
    if gx[-1] > x0f:   # the part resting on the block: subtract the block on the same grid
        bx = np.concatenate([gx[gx >= x0f], [prof.start + max(1.0, 2 * prof.radius)]])
        by = np.concatenate([[gy[0] - 1.0], gy, [gy[-1] + 1.0]])
        BX, BY = np.meshgrid(bx, by, indexing="ij")
        Bz = np.minimum(fns.h(BX, BY), top)
        Vb, Fb = heightfield((bx - x0f) * s, (by - y0f) * s, (Bz - top) * s, z_table - 10.0)
        ramp = ramp - _manifold(Vb, Fb)
    # grooves: a thin solid following the surface, from the depth to above it
    for mk in marks:
        offsets = [-0.5 * GROOVE_GAP_MM / s, 0.5 * GROOVE_GAP_MM / s] if mk.get("double") else [0.0]
        for off in offsets:
            xm = prof.start - mk["u"] + off
            half = 0.5 * GROOVE_WIDTH_MM / s
            gxm = np.array([xm - half, xm, xm + half])
            for side, (a, b) in sorted(mk["grooves"].items()):
                sign = 1 if side == "+y" else -1
                gym = prof.y0 + sign * np.linspace(a, b, max(4, int(math.ceil((b - a) * s / STEP_Y_MM)) + 1))
                gym = np.sort(gym)
                MX, MY = np.meshgrid(gxm, gym, indexing="ij")
                Tm = fns.h(MX, MY) + prof.lift(prof.start - MX)
                Vg, Fg = heightfield((gxm - x0f) * s, (gym - y0f) * s, (Tm - top) * s + 2.0,
                                     (Tm - top) * s - mk.get("groove_depth_mm", GROOVE_DEPTH_MM))
                ramp = ramp - _manifold(Vg, Fg)
    mesh = ramp.to_mesh()
    Vr = np.asarray(mesh.vert_properties, dtype=float)[:, :3]
    Fr = np.asarray(mesh.tri_verts, dtype=np.int64)
    # the running surface along the launch line: piecewise linear between the nodes
    zl = prof.z(prof.start - gx)
    um = prof.start - 0.5 * (gx[1:] + gx[:-1])
    err = float(np.max(np.abs(0.5 * (zl[1:] + zl[:-1]) - prof.z(um)))) * s
    X0, Y0, Z0 = work(prof.start, prof.y0, float(fns.h(prof.start, prof.y0)))
    ext = {"X": [float(Vr[:, 0].min()), float(Vr[:, 0].max())], "Y": [float(Vr[:, 1].min()), float(Vr[:, 1].max())],
           "Z": [float(Vr[:, 2].min()), float(Vr[:, 2].max())], "launch_point": [float(X0), float(Y0), float(Z0)]}
    return RampSolid(vertices=Vr, faces=Fr, volume_mm3=float(ramp.volume()), bodies=len(ramp.decompose()),
                     genus=int(ramp.genus()), profile_error_mm=err, extent_mm=ext)


# ----------------------------------------------------------------------------
# marks
# ----------------------------------------------------------------------------
def mark_targets(check_result: dict, g: float, k: float, spec=None) -> list[dict]:
    """{height, v_in, label, double} for the reachable two-bounce window centres (centre
    in v_in) and v_critical, from a ``physics.check.check`` result. The heights come from
    :func:`fabkit.physics.calibrate.release_height` (the ramp's losses included) when
    ``spec`` is given, else from the lossless closed form; nan where the speed is beyond
    the ramp's reach."""
    from ..physics.calibrate import height_from_v_in, release_height

    out = []
    for i, w in enumerate(check_result.get("reachable_windows") or [], start=1):
        v = 0.5 * (w["lo"] + w["hi"])
        out.append({"v_in": float(v), "label": f"2-bounce window {i} centre ({w['lo']:.2f}..{w['hi']:.2f})",
                    "double": False})
    vc = check_result.get("v_critical")
    if vc is not None:
        out.append({"v_in": float(vc), "label": "v_critical", "double": True})
    v = np.array([m["v_in"] for m in out], dtype=float)
    hs = (release_height(spec, v) if spec is not None else height_from_v_in(v, g, k)) if len(v) else v
    for m, h in zip(out, hs):
        m["height"] = float(h)
    return sorted(out, key=lambda m: (not math.isfinite(m["height"]), m["height"]))


def place_marks(spec, prof: RampProfile, targets: list[dict]) -> list[dict]:
    """Each target with its place: ``u`` along the launch line (design units), the contact
    point in work coordinates (mm), and the distance along the running surface from the
    launch point (mm, for measuring it off by hand)."""
    from scipy.integrate import quad

    s = float(spec.scale)
    x0f, y0f, top = float(spec.surface.x[0]), float(spec.surface.y[0]), float(spec.surface.top)
    out = []
    for t in targets:
        u = prof.u_for_height(t["height"])
        z = float(prof.z(u))
        arc = quad(lambda w: math.sqrt(1.0 + float(prof.slope(w)) ** 2), 0.0, u, epsabs=1e-12, epsrel=1e-12)[0]
        out.append({**t, "u": u, "X": (prof.start - u - x0f) * s, "Y": (prof.y0 - y0f) * s, "Z": (z - top) * s,
                    "along_mm": arc * s, "drop_check": float(prof.drop(u))})
    # window marks alternate sides (neighbouring windows crowd together near v_critical);
    # v_critical's double groove runs on both sides
    side = 0
    for m in out:
        if m["double"]:
            m["side"] = "both"
        else:
            m["side"] = "+y" if side % 2 == 0 else "-y"
            side += 1
    assign_lanes(out)
    _lane_spans(out, 0.4 * prof.radius, half_width(spec, prof) - 2.0 / s, s)
    # a groove never cuts through: where the ramp rests on the block it is D(u) thick under
    # the running surface (the lift, least at the groove's edge nearest the launch point)
    x0f = float(spec.surface.x[0])
    for m in out:
        reach = (0.5 * GROOVE_WIDTH_MM + (0.5 * GROOVE_GAP_MM if m["double"] else 0.0)) / s
        u_near = max(0.0, m["u"] - reach)
        on_block = prof.start - m["u"] - reach >= x0f
        thick = float(prof.lift(u_near)) * s if on_block else math.inf
        m["groove_depth_mm"] = float(min(GROOVE_DEPTH_MM, 0.5 * thick))
        if m["groove_depth_mm"] < GROOVE_MIN_DEPTH_MM:
            m["grooves"], m["engraved"] = {}, False
            m["too_thin"] = True
    return out


def _groove_lines(m: dict) -> list[float]:
    """The work X (mm) of a mark's groove lines: one, or two GROOVE_GAP_MM apart."""
    return [m["X"] - 0.5 * GROOVE_GAP_MM, m["X"] + 0.5 * GROOVE_GAP_MM] if m["double"] else [m["X"]]


def _sides(m: dict) -> tuple:
    return ("+y", "-y") if m["side"] == "both" else (m["side"],)


def assign_lanes(marks: list[dict]) -> None:
    """Set apart the grooves of marks that lie too close along the ramp, in place.

    Two groove lines on the same side of the path whose centres are closer than
    GROOVE_WIDTH_MM + GROOVE_CLEAR_MM would overlap or leave a wall too thin to see (and
    a mesh with slivers): such marks go into separate lanes across the ramp, each mark
    keeping its exact place along it. Greedy, v_critical first, then by height: a mark
    takes the lowest lane (0: nearest the path) where it is clear of every groove
    already there. Sets ``lane`` ({side: lane}) and ``crowded`` (True when the mark's
    grooves would have met another's in one lane)."""
    need = GROOVE_WIDTH_MM + GROOVE_CLEAR_MM
    lanes: dict = {"+y": [], "-y": []}          # side -> list of lanes, each a list of groove X
    order = sorted(range(len(marks)), key=lambda i: (not marks[i]["double"], i))
    for i in order:
        m = marks[i]
        xs = _groove_lines(m)
        m["lane"] = {}
        crowded = False
        for side in _sides(m):
            for j, lane in enumerate(lanes[side] + [[]]):
                if all(abs(x - o) >= need for x in xs for o in lane):
                    break
                crowded = True
            if j == len(lanes[side]):
                lanes[side].append([])
            lanes[side][j].extend(xs)
            m["lane"][side] = j
        m["crowded"] = crowded
    for m in marks:
        m["lanes"] = {side: len(lanes[side]) for side in _sides(m)}


def _lane_spans(marks: list[dict], a: float, b: float, s: float) -> None:
    """Each mark's grooves' extent across the ramp, in place: ``grooves`` {side: (lo, hi)},
    distances from the launch line (design units; a the first, b the last, s mm per design
    unit). A side's span [a, b] is shared by its lanes, LANE_GAP_MM apart; lanes that would
    be shorter than LANE_MIN_MM are dropped from the far end: a mark left without a groove
    on any side is ``engraved`` False (its place stays in the table)."""
    for m in marks:
        m["grooves"] = {}
        for side in _sides(m):
            n = m["lanes"][side]
            fit = int(math.floor(((b - a) * s + LANE_GAP_MM) / (LANE_MIN_MM + LANE_GAP_MM)))
            n_used = max(0, min(n, fit))
            j = m["lane"][side]
            if j >= n_used:
                continue
            ll = ((b - a) - (n_used - 1) * LANE_GAP_MM / s) / n_used
            lo = a + j * (ll + LANE_GAP_MM / s)
            m["grooves"][side] = (lo, lo + ll)
        m["engraved"] = bool(m["grooves"])


# ----------------------------------------------------------------------------
# the mesh as written, read back
# ----------------------------------------------------------------------------
#: a face smaller than this (mm^2) is degenerate: a sliver a slicer flags (a triangle 1 um
#: long and 1 nm high)
DEGENERATE_AREA_MM2 = 1e-9


@dataclass(frozen=True)
class MeshVerdict:
    """The written mesh read back by trimesh (vertices merged, as a slicer reads it):
    ``ok`` when it is one watertight body of positive volume with no degenerate face."""

    watertight: bool
    bodies: int
    volume_mm3: float
    degenerate: int
    triangles: int

    @property
    def ok(self) -> bool:
        return self.watertight and self.bodies == 1 and self.volume_mm3 > 0 and self.degenerate == 0

    @property
    def message(self) -> str:
        return (f"{'watertight' if self.watertight else 'NOT watertight'}, {self.bodies} "
                f"bod{'y' if self.bodies == 1 else 'ies'}, volume {self.volume_mm3:.6e} mm^3, "
                f"{self.degenerate} degenerate of {self.triangles} triangles")


def mesh_verdict(data: bytes, fmt: str) -> MeshVerdict:
    """Read the bytes about to be written (format ``fmt``, a file extension) with trimesh
    and judge them: watertight (every edge shared by exactly two faces, consistently
    wound), the number of connected bodies (faces joined by edges), the volume and the
    faces of area under DEGENERATE_AREA_MM2."""
    import io

    import trimesh

    m = trimesh.load(io.BytesIO(data), file_type=fmt, force="mesh")
    bodies = len(m.split(only_watertight=False)) if len(m.faces) else 0
    return MeshVerdict(watertight=bool(m.is_watertight), bodies=int(bodies), volume_mm3=float(m.volume),
                       degenerate=int(np.count_nonzero(m.area_faces < DEGENERATE_AREA_MM2)),
                       triangles=int(len(m.faces)))
