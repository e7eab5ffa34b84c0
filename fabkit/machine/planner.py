"""The run time the controller really takes: its motion planner simulated on the
program as the controller reads it (:func:`fabkit.machine.program.read_moves`: arcs cut
as grbl's mc_arc cuts them, the buffer syncs, the dwells).

grbl 1.1 (planner.c, stepper.c), as modelled here:

- **Blocks.** Each line is a block between whole-step positions
  (``round(mm * steps_per_mm)``, grbl's ``lround``); a block of no steps is dropped.
  Its length, unit vector, acceleration and rapid rate follow
  ``limit_value_by_axis_maximum``: min over moving axes of ``limit_i / |u_i|``.
  Nominal speed: the rapid rate for G0, ``min(F, rapid rate)`` for G1 (at least 1 mm/min).
- **Junctions.** grbl's junction deviation: ``v^2 = a_j * delta * s / (1 - s)``,
  ``s = sin(theta/2) = sqrt((1 - cos)/2)`` (cos of the angle between the moves,
  negated as in grbl), ``a_j`` the axis-limited acceleration along ``u - u_prev``;
  a reversal stops, a straight junction is free. The entry speed is also capped by
  the nominal speeds of both blocks. The first block after an empty buffer starts at rest.
- **Look-ahead while streaming.** The buffer holds 16 blocks, 15 usable. When the
  segment generator takes block k, the buffer holds blocks k .. k+14 and the last
  one must end at rest (planner_recalculate's reverse pass from it); the forward
  pass limits k+1's entry by what block k can reach from its own (fixed) entry.
  Each block's exit speed is fixed when it starts (no new block arrives while it
  runs: a slot frees only when the segment generator finishes a block). The host
  is assumed to keep the buffer full (the serial line keeps up).
- **Synchronisation.** grbl 1.1h's rules (gcode.c): a spindle or coolant state change,
  an S change while the spindle runs, G4, M0-M2, M30 empty the buffer: the move before
  them ends at rest.
- **Trapezoids.** Each block runs accelerate / cruise / decelerate at the block's
  acceleration between its entry and exit speeds; the time is the integral of this
  profile (closed form). The segment generator runs it in 10 ms segments of whole
  steps; the difference is the step-timing rounding (measured against grbl 1.1h's
  own parser, planner and segment generator: docs/machine.md).

Not modelled: the spindle's spin-up (M3 dwell on controllers that have one),
feed/rapid overrides (100 %), the serial line's own limit on short blocks.

LinuxCNC (:func:`_plan` with :func:`naivecam_keep`, :func:`blend_junction_sqr`,
:func:`_with_blend_arcs`): canon's naive-CAM merge (G64 Q), its axis-limited velocity
and acceleration, tangent blend arcs within G64 P as segments of their own, half
acceleration on a run's last segment, a 50-segment look-ahead; measured against
LinuxCNC's own planner in docs/machine.md, with what is still approximated.

The feed cap's cost (``lost_rate_s``): the run time minus the run time with the axis
rates raised to the highest programmed feed (:func:`raised_rates`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..toolpath.program.reader import FEED, RAPID

#: grbl 1.1: BLOCK_BUFFER_SIZE 16 on the ATmega328p, one slot kept empty
GRBL_LOOKAHEAD = 15
#: LinuxCNC's trajectory optimiser depth ([TRAJ] ARC_BLEND_OPTIMIZATION_DEPTH, default 50)
LINUXCNC_LOOKAHEAD = 50
#: LinuxCNC blendmath.h: the share of the acceleration a blend arc may use normal to the path
BLEND_ACC_RATIO_NORMAL = math.sqrt(1.0 - 0.5 ** 2)
#: emccanon.cc linkable(): at most this many points merged into one line
NAIVECAM_MAX_POINTS = 100
MINIMUM_FEED_RATE = 1.0          # mm/min (grbl config.h)
SOME_LARGE_VALUE = 1.0e38
#: a feed block counts as capped when its peak speed is below this fraction of F
CAPPED_BELOW = 0.99


@dataclass
class CapRegion:
    """A run of consecutive feed moves the look-ahead or the corners kept below their
    feed (the feed already clipped by the axis rates)."""

    first_line: int
    last_line: int
    at: tuple                   # (x, y) mm where the run starts
    feed: float                 # F clipped by the axis rates, mm/min
    speed: float                # mean speed over the run (length / time), mm/min
    lost_s: float               # time over length/feed along the run

    def to_json(self) -> dict:
        return {"lines": [self.first_line, self.last_line], "at": [round(float(v), 3) for v in self.at],
                "feed": round(self.feed, 1), "mean_speed": round(self.speed, 1), "time_lost_s": round(self.lost_s, 1)}


@dataclass
class RunTime:
    """The controller's run time of a program (seconds) and where it goes."""

    controller: str
    machine: str
    total_s: float
    feed_s: float               # G1 moves other than plunges
    plunge_s: float             # G1 moves straight down
    rapid_s: float              # G0 moves
    length_over_feed_s: float   # the same program at its feeds and rapid rates with no acceleration
    capped_fraction: float      # share of the cut length run below CAPPED_BELOW x F
    rate_capped_fraction: float  # ... where the axis rates allow less than F
    accel_capped_fraction: float  # ... held below min(F, axis rates) by acceleration
    lost_rate_s: float          # time over length/feed because the axis rates clip F
    lost_lookahead_s: float     # ... because of acceleration: look-ahead, corners, starts and stops
    regions: list = field(default_factory=list)    # the CapRegion's (acceleration) losing the most time
    passes: dict | None = None  # per raster pass (see :func:`pass_times`), when the raster axis is known
    blocks: int = 0
    model: str = ""
    dwell_s: float = 0.0        # G4 (grbl: in its 50 ms steps)
    syncs: int = 0              # buffer syncs (the move before ends at rest)
    arcs: int = 0
    arc_segments: int = 0       # the lines the arcs were cut into
    cap_cost_model: str = "length/feed"

    def to_json(self) -> dict:
        return {"controller": self.controller, "machine": self.machine, "total_s": round(self.total_s, 1),
                "feed_s": round(self.feed_s, 1), "plunge_s": round(self.plunge_s, 1),
                "rapid_s": round(self.rapid_s, 1), "length_over_feed_s": round(self.length_over_feed_s, 1),
                "feed_capped_fraction": round(self.capped_fraction, 4),
                "feed_capped_by_rates_fraction": round(self.rate_capped_fraction, 4),
                "feed_capped_by_acceleration_fraction": round(self.accel_capped_fraction, 4),
                "time_lost_to_axis_rates_s": round(self.lost_rate_s, 1),
                "time_lost_to_acceleration_s": round(self.lost_lookahead_s, 1),
                "capped_regions": [r.to_json() for r in self.regions], "per_pass": self.passes,
                "blocks": self.blocks, "model": self.model, "dwell_s": round(self.dwell_s, 2),
                "buffer_syncs": self.syncs, "arcs": self.arcs, "arc_segments": self.arc_segments,
                "feed_cap_cost_s": round(self.lost_rate_s, 1), "feed_cap_cost_model": self.cap_cost_model}

    def summary(self) -> str:
        head = _hm(self.total_s) if self.total_s >= 59.5 else f"{self.total_s:.1f} s"
        s = (f"run time on {self.machine}: {head} ({self.total_s:.0f} s: feeds {self.feed_s:.0f}, "
             f"plunges {self.plunge_s:.0f}, rapids {self.rapid_s:.0f}"
             + (f", dwells {self.dwell_s:.0f}" if self.dwell_s else "")
             + f"); length/feed {_hm(self.length_over_feed_s) if self.length_over_feed_s >= 59.5 else f'{self.length_over_feed_s:.1f} s'}")
        if self.passes:
            p = self.passes
            s += (f"; {p['passes']} passes of {p['median_s']:.1f} s median ({p['min_s']:.1f}-{p['max_s']:.1f}; "
                  f"length/feed {p['median_length_over_feed_s']:.1f})")
        if self.capped_fraction > 0:
            s += (f"; feed capped on {100 * self.capped_fraction:.0f} % of the cut length: by the axis rates on "
                  f"{100 * self.rate_capped_fraction:.0f} % (+{self.lost_rate_s:.0f} s), by acceleration on "
                  f"{100 * self.accel_capped_fraction:.0f} % (+{self.lost_lookahead_s:.0f} s)")
        return s


def _hm(seconds: float) -> str:
    m = int(round(seconds / 60.0))
    return f"{m // 60} h {m % 60} min" if m >= 60 else f"{m} min"


# ----------------------------------------------------------------------------
# blocks
# ----------------------------------------------------------------------------
def _axis_limit(limit: np.ndarray, u: np.ndarray) -> np.ndarray:
    """grbl's limit_value_by_axis_maximum, row-wise: min over u_i != 0 of limit_i / |u_i|."""
    with np.errstate(divide="ignore"):
        r = np.where(u != 0, limit[None, :] / np.abs(u), np.inf)
    return np.minimum(r.min(axis=1), SOME_LARGE_VALUE)


@dataclass
class Blocks:
    """The planner's blocks (mm, mm/min, mm/min^2) and which move each came from."""

    move: np.ndarray            # index into the program's moves
    length: np.ndarray
    unit: np.ndarray            # (n, 3)
    accel: np.ndarray
    nominal: np.ndarray
    feed: np.ndarray            # programmed F (rapid rate for G0)
    rate_cap: np.ndarray        # the axis-limited rate along the block
    rapid: np.ndarray           # bool
    plunge: np.ndarray          # bool
    fresh: np.ndarray           # bool: starts from an empty buffer


def make_blocks(program, machine, sync: np.ndarray | None = None, quantize: bool = True,
                uncap: bool = False) -> Blocks:
    """Blocks of ``program`` (a :class:`fabkit.machine.program.Moves` or a read-back
    Program) on ``machine`` (positions in whole steps when ``quantize``). ``uncap``: the
    feed moves run at their programmed F whatever the axis rates (the axis rates raised
    to the programmed feed; rapids and accelerations unchanged), for the feed cap's cost."""
    pts = np.vstack([program.start[None, :], program.points]) if len(program) else program.start[None, :]
    pts = np.nan_to_num(pts, nan=0.0)
    spm = np.asarray(machine.steps_per_mm, dtype=float)
    if quantize:
        x = pts * spm
        steps = np.sign(x) * np.floor(np.abs(x) + 0.5)          # lround: half away from zero
        delta = np.diff(steps, axis=0) / spm
        moving = np.any(np.diff(steps, axis=0) != 0, axis=1)
    else:
        delta = np.diff(pts, axis=0)
        moving = np.any(delta != 0, axis=1)
    keep = np.flatnonzero(moving)
    d = delta[keep]
    length = np.linalg.norm(d, axis=1)
    unit = d / length[:, None] if len(keep) else d
    acc = np.asarray(machine.acceleration, dtype=float) * 3600.0            # mm/s^2 -> mm/min^2
    accel = _axis_limit(acc, unit)
    rate = _axis_limit(np.asarray(machine.max_rate, dtype=float), unit)
    rapid = program.kinds[keep] == RAPID
    if getattr(machine, "rapid", None):
        rate_g0 = np.minimum(rate, machine.rapid)
    else:
        rate_g0 = rate
    vmax = getattr(machine, "max_velocity", None)
    if vmax:
        rate = np.minimum(rate, vmax)
        rate_g0 = np.minimum(rate_g0, vmax)
    amax = getattr(machine, "max_acceleration", None)
    if amax:
        accel = np.minimum(accel, amax * 3600.0)
    feed = np.where(rapid, rate_g0, program.feed[keep])
    if uncap:
        rate = np.maximum(rate, np.where(rapid, 0.0, feed))
    nominal = np.maximum(np.where(rapid, rate_g0, np.minimum(feed, rate)), MINIMUM_FEED_RATE)
    plunge = ~rapid & (np.abs(d[:, 0]) + np.abs(d[:, 1]) == 0) & (d[:, 2] < 0)
    fresh = np.zeros(len(keep), dtype=bool)
    if len(keep):
        fresh[0] = True
        if sync is not None and sync.any():
            # a sync line before any dropped move still empties the buffer before the next block
            s_idx = np.flatnonzero(sync)
            pos = np.searchsorted(keep, s_idx, side="left")
            fresh[pos[pos < len(keep)]] = True
    return Blocks(move=keep, length=length, unit=unit, accel=accel, nominal=nominal, feed=feed,
                  rate_cap=np.where(rapid, rate_g0, rate), rapid=rapid, plunge=plunge, fresh=fresh)


def grbl_junction_sqr(unit: np.ndarray, accel_limits: np.ndarray, deviation: float) -> np.ndarray:
    """(n,) grbl 1.1's max junction speed^2 (mm/min)^2 at the start of each block
    (entry 0 for the first block; the caller applies the buffer-empty rule)."""
    n = len(unit)
    out = np.zeros(n)
    if n < 2:
        return out
    prev, cur = unit[:-1], unit[1:]
    cos = -np.sum(prev * cur, axis=1)
    jv = cur - prev
    norm = np.linalg.norm(jv, axis=1)
    jv = jv / np.where(norm > 0, norm, 1.0)[:, None]
    ja = _axis_limit(accel_limits, jv)
    sin_d2 = np.sqrt(np.clip(0.5 * (1.0 - cos), 0.0, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        v2 = np.maximum(0.0, ja * deviation * sin_d2 / (1.0 - sin_d2))
    v2 = np.where(cos > 0.999999, 0.0, np.where(cos < -0.999999, SOME_LARGE_VALUE, v2))
    out[1:] = v2
    return out


def blend_junction_sqr(unit: np.ndarray, length: np.ndarray, accel: np.ndarray, tolerance: float | None,
                       axis_accel: np.ndarray | None = None, nominal: np.ndarray | None = None,
                       arcs: bool = False):
    """(n,) LinuxCNC's corner speed^2 through its tangent blend arc (tp.c, blendmath.c
    ``blendComputeParameters``); with ``arcs`` also (d, s): how much of each line the arc
    takes at the corner and the arc's length.

    The arc touches both lines at ``d`` from the corner, ``d <= min(L1, L2) / 2`` and
    within the G64 P ``tolerance`` (None or 0: no limit but the segments),
    ``d_tol = cos(t) P / (1 - sin(t))``, ``t`` half the angle between the lines; radius
    ``R = tan(t) d``; speed ``v = min(sqrt(a_n R), v_goal)``, ``a_n`` the normal share
    (sqrt(1 - 0.5^2)) of the acceleration in the plane of the two lines
    (``calculateInscribedDiameter``: min over axes of ``a_axis / sqrt(1 - n_axis^2)``, n
    the plane's normal; ``axis_accel`` the axes' limits, else the lines' own), ``v_goal``
    the faster line's feed (``nominal``). The arc actually planned: ``R = max(v^2 / a_n,
    min(t_b v / phi, R))``, ``t_b = min(sqrt(a d), v) / (a / 2)`` (the "equivalent parabolic
    blend"), phi the turning angle. A reversal stops; a straight junction is free."""
    n = len(unit)
    out = np.zeros(n)
    d_out = np.zeros(n)
    s_out = np.zeros(n)
    if n < 2:
        return (out, d_out, s_out, np.zeros(n)) if arcs else out
    u1, u2 = unit[:-1], unit[1:]
    cosd = np.clip(np.sum(u1 * u2, axis=1), -1.0, 1.0)      # cos of the turning angle
    turn = np.arccos(cosd)
    t = 0.5 * (np.pi - turn)
    sin_t, cos_t, tan_t = np.sin(t), np.cos(t), np.tan(t)
    if axis_accel is not None:
        nrm = np.cross(u1, u2)
        nn = np.linalg.norm(nrm, axis=1)
        nrm = nrm / np.where(nn > 0, nn, 1.0)[:, None]
        scale = np.maximum(np.sqrt(np.clip(1.0 - nrm * nrm, 0.0, 1.0)), 1e-12)
        a_plane = np.min(np.asarray(axis_accel, dtype=float)[None, :] / scale, axis=1)
    else:
        a_plane = np.minimum(accel[:-1], accel[1:])
    a_n = BLEND_ACC_RATIO_NORMAL * a_plane
    d = 0.5 * np.minimum(length[:-1], length[1:])
    with np.errstate(divide="ignore", invalid="ignore"):
        if tolerance:
            d = np.minimum(d, cos_t * tolerance / (1.0 - sin_t))
        r_geom = tan_t * d
        v = np.sqrt(a_n * r_geom)
        if nominal is not None:
            v = np.minimum(v, np.maximum(nominal[:-1], nominal[1:]))
        a_par = 0.5 * a_plane
        t_b = np.minimum(np.sqrt(2.0 * a_par * d), v) / a_par
        r_blend = np.minimum(t_b * v / np.maximum(turn, 1e-12), r_geom)
        r_plan = np.maximum(v * v / a_n, r_blend)
        d_plan = np.minimum(r_plan / tan_t, d)
        s_arc = r_plan * turn
    ok = (turn >= 1e-6) & (t >= 1e-6)
    v2 = np.where(turn < 1e-6, SOME_LARGE_VALUE, np.where(t < 1e-6, 0.0, v * v))
    out[1:] = np.nan_to_num(v2, nan=0.0, posinf=SOME_LARGE_VALUE)
    d_out[1:] = np.where(ok, np.nan_to_num(d_plan), 0.0)
    s_out[1:] = np.where(ok, np.nan_to_num(s_arc), 0.0)
    if arcs:
        a_out = np.zeros(n)
        a_out[1:] = a_plane
        return out, d_out, s_out, a_out
    return out


def naivecam_keep(points: np.ndarray, start: np.ndarray, kinds: np.ndarray, feed: np.ndarray, sync: np.ndarray,
                  term: np.ndarray, q: float) -> np.ndarray:
    """(n,) bool: the feed moves LinuxCNC's canon keeps after its naive-CAM merge (G64 Q,
    emccanon.cc ``see_segment``/``linkable``): consecutive G1 points at one feed join
    into one line while every point of the chain lies within ``q`` of the line from the
    chain's start to the new point (at most 101 points). A rapid, a feed change, a sync
    or another path mode ends a chain. (Short chains in plain Python, long ones with
    numpy: the same test.)"""
    n = len(points)
    keep = np.ones(n, dtype=bool)
    if not q or q <= 0 or n == 0:
        return keep
    pts = np.nan_to_num(points)
    xs, ys, zs = pts[:, 0].tolist(), pts[:, 1].tolist(), pts[:, 2].tolist()
    st = np.nan_to_num(np.asarray(start, dtype=float))
    ex, ey, ez = float(st[0]), float(st[1]), float(st[2])          # canon.endPoint
    linkable_mode = ((kinds == FEED) & (term == 2) & ~sync).tolist()
    fl = feed.tolist()
    qq = q * q
    chain: list = []
    f_chain = None
    for i in range(n):
        if chain and (not linkable_mode[i] or fl[i] != f_chain or len(chain) > NAIVECAM_MAX_POINTS):
            keep[chain[:-1]] = False
            j = chain[-1]
            ex, ey, ez = xs[j], ys[j], zs[j]
            chain = []
        if not linkable_mode[i]:
            ex, ey, ez = xs[i], ys[i], zs[i]
            continue
        if chain:
            mx, my, mz = xs[i] - ex, ys[i] - ey, zs[i] - ez
            mm = mx * mx + my * my + mz * mz
            ok = mm > 0
            if ok and len(chain) <= 16:
                for j in chain:
                    px, py, pz = xs[j] - ex, ys[j] - ey, zs[j] - ez
                    t0 = (px * mx + py * my + pz * mz) / mm
                    t0 = 0.0 if t0 < 0 else 1.0 if t0 > 1 else t0
                    dx, dy, dz = px - t0 * mx, py - t0 * my, pz - t0 * mz
                    if dx * dx + dy * dy + dz * dz > qq:
                        ok = False
                        break
            elif ok:                # a chain is consecutive points: a slice
                m = np.array([mx, my, mz])
                c = pts[chain[0]:i] - np.array([ex, ey, ez])
                t0 = c @ m / mm
                np.clip(t0, 0.0, 1.0, out=t0)
                c -= t0[:, None] * m
                ok = float((c * c).sum(axis=1).max()) <= qq
            if not ok:
                keep[chain[:-1]] = False
                j = chain[-1]
                ex, ey, ez = xs[j], ys[j], zs[j]
                chain = []
        chain.append(i)
        f_chain = fl[i]
    if chain:
        keep[chain[:-1]] = False
    return keep


# ----------------------------------------------------------------------------
# the look-ahead and the trapezoids
# ----------------------------------------------------------------------------
def streamed_speeds(max_entry_sqr: np.ndarray, accel: np.ndarray, length: np.ndarray, fresh: np.ndarray,
                    window: int = GRBL_LOOKAHEAD) -> np.ndarray:
    """(n + 1,) speed^2 at each block boundary: entry of block k, exit of the last.

    While block k runs the buffer holds blocks k .. k + window - 1 and the last must end
    at rest (so must the block before a ``fresh`` one: the buffer empties there). The
    reverse pass over that window gives the most block k+1 may enter at (R_k); the
    forward pass: v_{k+1}^2 = min(R_k, v_k^2 + 2 a_k L_k). Vectorised: the reverse pass is
    ``window - 1`` array steps; the forward recursion is a running minimum of
    R_k - S_{k+1} with S the prefix sums of 2 a L (exact in real arithmetic)."""
    n = len(length)
    v2 = np.zeros(n + 1)
    if n == 0:
        return v2
    c = 2.0 * accel * length
    # a fresh block is entered at rest (the buffer empties before it): max entry 0, so the
    # reverse pass through it makes the blocks before it stop there; past the program's
    # end the padding (max entry 0) stops the last block
    maxe = np.where(fresh, 0.0, max_entry_sqr)
    maxe_p = np.concatenate([maxe, np.zeros(window)])
    c_p = np.concatenate([c, np.zeros(window)])
    k = np.arange(n)
    b = np.zeros(n)                        # entry^2 allowed at block k + j, from j = window - 1 down to 1
    for j in range(window - 1, 0, -1):
        idx = k + j
        b = np.minimum(maxe_p[idx], b + c_p[idx])
    R = b                                  # R[k]: allowed entry^2 of block k + 1 seen from block k
    S = np.concatenate([[0.0], np.cumsum(c)])
    u = np.minimum.accumulate(np.concatenate([[0.0], R - S[1:]]))
    v2 = np.maximum(u + S, 0.0)
    v2[-1] = 0.0
    return v2


def trapezoid_times(v0: np.ndarray, v1: np.ndarray, vmax: np.ndarray, accel: np.ndarray,
                    length: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(time in minutes, peak speed) of each block's accelerate/cruise/decelerate profile
    between entry ``v0`` and exit ``v1`` (mm/min), nominal ``vmax``, acceleration
    ``accel`` (mm/min^2), length mm. Closed form."""
    peak2 = np.minimum(vmax * vmax, 0.5 * (v0 * v0 + v1 * v1) + accel * length)
    peak = np.sqrt(np.maximum(peak2, np.maximum(v0, v1) ** 2))
    d_acc = (peak * peak - v0 * v0) / (2.0 * accel)
    d_dec = (peak * peak - v1 * v1) / (2.0 * accel)
    cruise = np.maximum(length - d_acc - d_dec, 0.0)
    t = (peak - v0) / accel + (peak - v1) / accel + np.where(peak > 0, cruise / np.where(peak > 0, peak, 1), 0)
    return t, peak


# ----------------------------------------------------------------------------
# the run time
# ----------------------------------------------------------------------------
def run_time(text: str | None, machine, program=None, top: int = 5, raster_axis: int | None = None,
             moves=None, cap_cost: bool = True, file: str | None = None) -> RunTime:
    """The controller's run time of the program ``text`` on ``machine``
    (:class:`fabkit.machine.profile.Machine`), read by the permissive reader
    (:func:`fabkit.machine.program.read_moves`) unless ``moves`` is given; ``program``
    (the strict read-back) is no longer needed and kept for the callers.
    ``raster_axis`` (0: x, 1: y): the passes' direction, for the per-pass figures.
    ``cap_cost``: also plan the program with the axis rates raised to the programmed
    feeds, for the feed cap's cost (``lost_rate_s``)."""
    from .program import read_moves

    if moves is None:
        moves = read_moves(text, machine.controller, machine.arc_tolerance, file=file)
    t, peak, blocks, model = _plan(moves, machine)
    rt = _report(moves, blocks, t, peak, machine, model, top)
    rt.dwell_s = float(moves.dwell_s)
    rt.total_s += rt.dwell_s
    rt.syncs, rt.arcs, rt.arc_segments = int(moves.syncs), int(moves.arcs), int(moves.arc_segments)
    cut = ~blocks.rapid
    if cap_cost and bool(np.any(cut & (blocks.rate_cap < CAPPED_BELOW * blocks.feed))):
        t_free, _, _, _ = _plan(moves, raised_rates(machine, moves))
        rt.lost_rate_s = float(t.sum() - t_free.sum())
        rt.cap_cost_model = ("planner: the run time minus the run time with the axis rates raised to the "
                             "highest programmed feed")
    elif cap_cost:
        rt.lost_rate_s = 0.0
    ideal = blocks.length / np.where(blocks.rapid, blocks.rate_cap, blocks.feed) * 60.0
    rt.lost_lookahead_s = float(np.sum((t - ideal)[cut])) - rt.lost_rate_s
    if raster_axis is not None:
        rt.passes = pass_times(moves, blocks, t, ideal, raster_axis)
    return rt


def _merged(moves, machine):
    """``moves`` after LinuxCNC canon's naive-CAM merge (Q: the program's G64 Q, else P)."""
    import dataclasses

    q = getattr(moves, "naivecam", None)
    if q is None:
        given = moves.tolerance[np.isfinite(moves.tolerance)] if len(moves.tolerance) else []
        q = machine.path_tolerance if machine.path_tolerance is not None else (float(given[0]) if len(given) else 0.0)
    keep = naivecam_keep(moves.points, moves.start, moves.kinds, moves.feed, moves.sync, moves.term, q)
    if keep.all():
        return moves
    # a sync before a dropped point moves to the next kept one
    sync = moves.sync.copy()
    idx = np.flatnonzero(sync & ~keep)
    for i in idx:
        j = i + 1 + int(np.argmax(keep[i + 1:])) if keep[i + 1:].any() else None
        if j is not None:
            sync[j] = True
    return dataclasses.replace(moves, points=moves.points[keep], kinds=moves.kinds[keep], feed=moves.feed[keep],
                               line=moves.line[keep], sync=sync[keep], term=moves.term[keep],
                               tolerance=moves.tolerance[keep])


def raised_rates(machine, moves):
    """``machine`` with each axis rate (and [TRAJ] velocity) raised to the highest
    programmed feed: the same machine without the feed cap (its rapids also run at
    the raised rates, as the controller would run them)."""
    import dataclasses

    f = moves.feed[np.isfinite(moves.feed)]
    fmax = float(f.max()) if len(f) else 0.0
    return dataclasses.replace(machine, max_rate=tuple(max(float(r), fmax) for r in machine.max_rate),
                               max_velocity=None if machine.max_velocity is None else max(machine.max_velocity, fmax))


def _plan(moves, machine, uncap: bool = False):
    """(block times s, peak speeds, blocks, model) of ``moves`` on ``machine``."""
    grbl = machine.controller == "grbl"
    if not grbl:
        moves = _merged(moves, machine)
    blocks = make_blocks(moves, machine, moves.sync, quantize=grbl, uncap=uncap)
    acc = np.asarray(machine.acceleration, dtype=float) * 3600.0
    if grbl:
        junction = grbl_junction_sqr(blocks.unit, acc, machine.junction_deviation)
        window = GRBL_LOOKAHEAD
        model = "grbl 1.1 planner: 15-block streamed look-ahead, junction deviation, axis limits, trapezoids"
    else:
        tol = machine.path_tolerance
        if tol is None:
            given = moves.tolerance[np.isfinite(moves.tolerance)] if len(moves.tolerance) else []
            tol = float(given[0]) if len(given) else None
        junction, d_arc, s_arc, a_arc = blend_junction_sqr(blocks.unit, blocks.length, blocks.accel, tol, acc,
                                                           blocks.nominal, arcs=True)
        term = moves.term[blocks.move] if len(moves.term) else np.zeros(0)
        blend = (term == 2) & ~blocks.fresh
        junction = np.where(blend, junction, np.where(np.isclose(junction, SOME_LARGE_VALUE), junction, 0.0))
        d_arc = np.where(blend, d_arc, 0.0)
        s_arc = np.where(blend, s_arc, 0.0)
        # the blend arcs take d from the lines on both sides of each corner
        if len(blocks.length):
            take = d_arc + np.concatenate([d_arc[1:], [0.0]])
            blocks.length = np.maximum(blocks.length - take, 1e-9)
        # the last segment of a blended run keeps LinuxCNC's parabolic term condition:
        # half its acceleration (tc.c tcGetOverallMaxAccel)
        if len(blocks.length):
            stops_after = np.concatenate([blocks.fresh[1:], [True]])
            blocks.accel = np.where(stops_after & (term == 2), 0.5 * blocks.accel, blocks.accel)
        window = LINUXCNC_LOOKAHEAD
        model = ("LinuxCNC trajectory planner, approximate: canon's naive-CAM merge (G64 Q), axis limits, "
                 f"{LINUXCNC_LOOKAHEAD}-segment look-ahead, tangent arc blends within G64 P at the normal "
                 "acceleration share, half acceleration on a run's last segment, trapezoids")
    nom = blocks.nominal
    prev_nom = np.concatenate([[0.0], nom[:-1]])
    max_entry = np.minimum(junction, np.minimum(nom, prev_nom) ** 2)
    if not grbl and np.any(s_arc > 0):
        t_min, peak = _with_blend_arcs(blocks, nom, max_entry, junction, s_arc, a_arc, window)
        return t_min * 60.0, peak, blocks, model
    v2 = streamed_speeds(max_entry, blocks.accel, blocks.length, blocks.fresh, window)
    v = np.sqrt(v2)
    t_min, peak = trapezoid_times(v[:-1], v[1:], nom, blocks.accel, blocks.length)
    return t_min * 60.0, peak, blocks, model


def _with_blend_arcs(blocks, nom, max_entry, junction, s_arc, a_arc, window):
    """LinuxCNC's queue with a blend arc between two lines where it blends: each arc a
    segment of its own (length ``s_arc``, at most the corner's speed, tangential
    acceleration half the plane's, BLEND_ACC_RATIO_TANGENTIAL), tangent to both lines.
    Returns (minutes per line, the arc before it counted with it; peak speed per line)."""
    n = len(blocks.length)
    arc = s_arc > 0                       # arc at the start of line i (between i-1 and i)
    n_before = np.cumsum(arc)             # arcs up to and including line i's own
    line_pos = np.arange(n) + n_before
    arc_idx = np.flatnonzero(arc)
    arc_pos = line_pos[arc_idx] - 1
    m = n + len(arc_idx)
    length = np.empty(m)
    accel = np.empty(m)
    nominal = np.empty(m)
    entry = np.empty(m)
    fresh = np.zeros(m, dtype=bool)
    v_arc = np.sqrt(np.minimum(junction[arc_idx], SOME_LARGE_VALUE))
    length[line_pos] = blocks.length
    accel[line_pos] = blocks.accel
    nominal[line_pos] = nom
    fresh[line_pos] = blocks.fresh
    e = max_entry.copy()
    e[arc_idx] = np.minimum(v_arc, nom[arc_idx]) ** 2     # tangent from the arc
    entry[line_pos] = e
    length[arc_pos] = s_arc[arc_idx]
    accel[arc_pos] = 0.5 * a_arc[arc_idx]
    nominal[arc_pos] = v_arc
    entry[arc_pos] = np.minimum(v_arc, nom[arc_idx - 1]) ** 2
    v2 = streamed_speeds(entry, accel, length, fresh, window)
    v = np.sqrt(v2)
    t, peak = trapezoid_times(v[:-1], v[1:], nominal, accel, length)
    t_line = t[line_pos].copy()
    t_line[arc_idx] += t[arc_pos]
    return t_line, peak[line_pos]


def pass_times(program, blocks: Blocks, t: np.ndarray, ideal: np.ndarray, axis: int) -> dict | None:
    """Per raster pass: a pass is a run of cutting moves along ``axis`` in one direction
    (it ends where the direction along ``axis`` reverses or at a rapid, so a pass the
    program interrupts with a lift counts as two; the moves that step across between
    passes count with the pass they lead into). Returns the count,
    the median, shortest and longest pass times (s), the median length/feed time, and
    the slowest pass's lines; None when there is no pass."""
    cut = ~blocks.rapid
    if not cut.any():
        return None
    sgn = np.sign(np.round(blocks.unit[:, axis], 12))
    along = cut & (sgn != 0)
    idx = np.flatnonzero(along)
    if not len(idx):
        return None
    # a new pass where the sign along the axis flips, or a rapid lies between two along-moves
    rapid_before = np.concatenate([[0], np.cumsum(blocks.rapid)])
    new = np.ones(len(idx), dtype=bool)
    new[1:] = (sgn[idx[1:]] != sgn[idx[:-1]]) | (rapid_before[idx[1:]] != rapid_before[idx[:-1] + 1])
    starts = idx[new]
    bounds = np.concatenate([starts, [len(t)]])
    pt = np.add.reduceat(np.where(cut, t, 0.0), starts)
    pi = np.add.reduceat(np.where(cut, ideal, 0.0), starts)
    # the last pass ends at its last along-move
    last = idx[-1] + 1
    pt[-1] = t[starts[-1]:last][cut[starts[-1]:last]].sum()
    pi[-1] = ideal[starts[-1]:last][cut[starts[-1]:last]].sum()
    k = int(np.argmax(pt))
    end = min(int(bounds[k + 1]) - 1, len(t) - 1)
    return {"passes": int(len(starts)), "median_s": round(float(np.median(pt)), 2),
            "min_s": round(float(pt.min()), 2), "max_s": round(float(pt.max()), 2),
            "median_length_over_feed_s": round(float(np.median(pi)), 2),
            "slowest_lines": [int(program.line[blocks.move[starts[k]]]), int(program.line[blocks.move[end]])]}


def _report(program, blocks: Blocks, t: np.ndarray, peak: np.ndarray, machine, model: str, top: int) -> RunTime:
    feed = ~blocks.rapid & ~blocks.plunge
    # the length/feed estimate of the same moves: G0 at the axis-limited rapid rate
    ideal = blocks.length / np.where(blocks.rapid, blocks.rate_cap, blocks.feed) * 60.0
    reach = np.where(blocks.rapid, blocks.rate_cap, np.minimum(blocks.feed, blocks.rate_cap))
    clipped = blocks.length / reach * 60.0
    cut = ~blocks.rapid
    cut_len = blocks.length[cut].sum()

    def share(mask):
        return float(blocks.length[mask].sum() / cut_len) if cut_len > 0 else 0.0

    frac = share(cut & (peak < CAPPED_BELOW * blocks.feed))
    frac_rate = share(cut & (blocks.rate_cap < CAPPED_BELOW * blocks.feed))
    slowed = cut & (peak < CAPPED_BELOW * reach)          # held below what the axis rates allow
    lost_rate = float(np.sum((clipped - ideal)[cut]))
    lost_acc = float(np.sum((t - clipped)[cut]))
    regions = _regions(program, blocks, slowed, t, clipped, top)
    name = machine.name or machine.controller
    return RunTime(controller=machine.controller, machine=name, total_s=float(t.sum()),
                   feed_s=float(t[feed].sum()), plunge_s=float(t[blocks.plunge].sum()),
                   rapid_s=float(t[blocks.rapid].sum()), length_over_feed_s=float(ideal.sum()),
                   capped_fraction=frac, rate_capped_fraction=frac_rate, accel_capped_fraction=share(slowed),
                   lost_rate_s=lost_rate, lost_lookahead_s=lost_acc,
                   regions=regions, blocks=int(len(blocks.length)), model=model)


def _regions(program, blocks: Blocks, slowed: np.ndarray, t, clipped, top: int) -> list:
    """The ``top`` runs of consecutive feed blocks held below their (rate-clipped) feed
    by acceleration that lose the most time."""
    if not slowed.any():
        return []
    idx = np.flatnonzero(slowed)
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts = np.concatenate([[0], breaks + 1])
    ends = np.concatenate([breaks, [len(idx) - 1]])
    lost = np.add.reduceat((t - clipped)[idx], starts)
    order = np.argsort(-lost)[:top]
    out = []
    for r in order:
        a, b = idx[starts[r]], idx[ends[r]]
        sel = slice(a, b + 1)
        length = blocks.length[sel][slowed[sel]].sum()
        time = t[sel][slowed[sel]].sum()
        mv = blocks.move[a]
        p0 = program.points[mv - 1] if mv > 0 else program.start
        out.append(CapRegion(first_line=int(program.line[blocks.move[a]]), last_line=int(program.line[blocks.move[b]]),
                             at=(float(np.nan_to_num(p0[0])), float(np.nan_to_num(p0[1]))),
                             feed=float(np.median(np.minimum(blocks.feed, blocks.rate_cap)[sel])),
                             speed=float(length / time * 60.0), lost_s=float(lost[r])))
    return out
