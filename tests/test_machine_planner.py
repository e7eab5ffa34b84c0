"""The controller's run time (fabkit/machine/planner.py) against closed forms:
a single long move's trapezoid, the streamed look-ahead's steady state on a long run
of equal short segments, a junction-deviation corner, rate and acceleration clipping
by axis, and a buffer sync. (Against grbl 1.1h's own planner: docs/machine.md.)"""

import dataclasses
import math

import numpy as np
import pytest

from fabkit.machine.planner import run_time
from fabkit.machine.profile import Machine, grbl_defaults

GRBL = grbl_defaults()      # 500 mm/min, 10 mm/s^2, 250 steps/mm, junction deviation 0.01 mm


def prog(lines, feed=None):
    head = ["G21 G90"]
    return "\n".join(head + lines) + "\n"


def trapezoid(L, v0, v1, V, a):
    """Time (s) of a move of length L (mm) from v0 to v1 (mm/s) with cruise V and accel a (mm/s^2)."""
    peak = min(V, math.sqrt((v0 * v0 + v1 * v1) / 2 + a * L))
    da, dd = (peak ** 2 - v0 ** 2) / (2 * a), (peak ** 2 - v1 ** 2) / (2 * a)
    return (peak - v0) / a + (peak - v1) / a + (L - da - dd) / peak


def test_single_long_move():
    r = run_time(prog(["G1 X100 F300"]), GRBL)
    v, a = 300 / 60, 10.0
    assert r.total_s == pytest.approx(100 / v + v / a, rel=1e-12)
    assert r.length_over_feed_s == pytest.approx(100 / v, rel=1e-12)


def test_short_move_triangle():
    r = run_time(prog(["G1 X0.4 F3000"]), GRBL)          # never reaches F: triangle, peak sqrt(a L)
    assert r.total_s == pytest.approx(2 * math.sqrt(0.4 / 10.0), rel=1e-12)


def test_axis_rate_clips_feed():
    m = dataclasses.replace(GRBL, max_rate=(500.0, 300.0, 500.0), acceleration=(10.0, 6.0, 10.0))
    r = run_time(prog(["G1 X80 Y80 F5000"]), m)
    u = 1 / math.sqrt(2)
    V = min(500 / u, 300 / u) / 60        # limit_value_by_axis_maximum
    a = min(10 / u, 6 / u)
    L = 80 * math.sqrt(2)
    assert r.total_s == pytest.approx(L / V + V / a, rel=1e-12)
    # the cap's cost: the same move with the rates raised to F (5000 mm/min: a triangle)
    assert r.lost_rate_s == pytest.approx(L / V + V / a - 2 * math.sqrt(L / a), rel=1e-9)


def test_junction_deviation_corner():
    m = dataclasses.replace(GRBL, max_rate=(6000.0,) * 3, acceleration=(100.0,) * 3, junction_deviation=0.02)
    r = run_time(prog(["G1 X100 F3000", "Y100"]), m)
    # 90 degrees: sin(theta/2) = sqrt(1/2); the junction vector (-1, 1)/sqrt2 allows a*sqrt2
    s = math.sqrt(0.5)
    a = 100.0
    vc = math.sqrt(a * math.sqrt(2) * 0.02 * s / (1 - s))
    V = 50.0
    assert vc < V
    expect = trapezoid(100, 0, vc, V, a) + trapezoid(100, vc, 0, V, a)
    assert r.total_s == pytest.approx(expect, rel=1e-12)


def test_reversal_stops_and_straight_is_free():
    m = dataclasses.replace(GRBL, max_rate=(6000.0,) * 3)
    back = run_time(prog(["G1 X40 F3000", "X0"]), m)
    assert back.total_s == pytest.approx(2 * trapezoid(40, 0, 0, 50, 10), rel=1e-12)
    straight = run_time(prog(["G1 X20 F3000", "X40"]), m)
    assert straight.total_s == pytest.approx(trapezoid(40, 0, 0, 50, 10), rel=1e-12)


def test_lookahead_steady_state():
    """Equal collinear segments s, F far above what 15 blocks allow: while block k runs
    the buffer holds k..k+14 and k+14 ends at rest, so each block enters and leaves at
    v^2 = 2 a (14 s) and peaks at v^2 = 2 a (14.5 s); the speed stays below sqrt(2 a 15 s)."""
    m = dataclasses.replace(GRBL, max_rate=(60000.0,) * 3)
    s, a, n = 0.5, 10.0, 400
    r = run_time(prog([f"G1 X{s * (i + 1):.3f} F20000" for i in range(n)]), m)
    v0, vp = math.sqrt(2 * a * 14 * s), math.sqrt(2 * a * 14.5 * s)
    per_block = 2 * (vp - v0) / a
    # the run: 15 - 1 blocks accelerating from rest at the start and the last 14 stopping
    # (closed forms below), the rest at the steady state
    start = sum(trapezoid(s, math.sqrt(2 * a * s * k), math.sqrt(min(2 * a * s * (k + 1), 2 * a * 14 * s)),
                          1e9, a) for k in range(14))
    end = sum(trapezoid(s, math.sqrt(2 * a * s * (k + 1)), math.sqrt(2 * a * s * k), 1e9, a) for k in range(14))
    expect = start + (n - 28) * per_block + end
    assert r.total_s == pytest.approx(expect, rel=1e-9)
    assert vp * 60 < math.sqrt(2 * a * 15 * s) * 60 < 736      # the 735 mm/min bound


def test_sync_empties_the_buffer():
    m = dataclasses.replace(GRBL, max_rate=(6000.0,) * 3)
    joined = run_time(prog(["G1 X20 F3000", "M5", "M3 S1000", "G1 X40"]), m)
    assert joined.total_s == pytest.approx(2 * trapezoid(20, 0, 0, 50, 10), rel=1e-12)


def test_breakdown_sums_to_total():
    # M3 and M5 wait for the buffer to empty: the plunge starts and ends at rest
    r = run_time(prog(["G0 Z5", "G0 X10 Y10", "M3 S1000", "G1 Z-1 F300", "M5", "G1 X30 F800", "G0 Z5"]), GRBL)
    assert r.feed_s + r.plunge_s + r.rapid_s == pytest.approx(r.total_s, rel=1e-12)
    assert r.plunge_s == pytest.approx(trapezoid(6, 0, 0, 5, 10), rel=1e-12)


def test_linuxcnc_blend_corner():
    m = Machine(controller="linuxcnc", max_rate=(6000.0,) * 3, acceleration=(100.0,) * 3, path_tolerance=0.05)
    r = run_time(prog(["G1 X100 F3000", "Y100"]), m)
    # LinuxCNC's blend arc at a 90 degree corner (blendmath.c): half the angle between the
    # lines t = 45 deg; the arc touches each line d = cos(t) P / (1 - sin(t)) from the
    # corner, radius R = tan(t) d; it runs at v = sqrt(a_n R), a_n = sqrt(1 - 0.5^2) a, for
    # R pi / 2 mm; the last line of the run keeps the parabolic term: half acceleration.
    # (LinuxCNC's own planner, 50 mm lines on 25 mm/s, 100 mm/s^2 at P0.1: 4.690 s, this
    # closed form 4.6895 s.)
    t = math.pi / 4
    d = math.cos(t) * 0.05 / (1 - math.sin(t))
    rad = math.tan(t) * d
    vc = math.sqrt(math.sqrt(0.75) * 100.0 * rad)
    expect = trapezoid(100 - d, 0, vc, 50, 100) + rad * math.pi / 2 / vc + trapezoid(100 - d, vc, 0, 50, 50)
    assert r.total_s == pytest.approx(expect, rel=1e-12)


def test_linuxcnc_collinear_merge():
    # canon's naive-CAM merge (G64 Q = P): 0.1 mm steps on a straight line become one
    # segment (of at most 101 points): no corners, the last segment at half acceleration
    m = Machine(controller="linuxcnc", max_rate=(6000.0,) * 3, acceleration=(100.0,) * 3)
    r = run_time(prog(["G64 P0.01", "G1 X0.1 F1200"] + [f"X{0.1 * i:.1f}" for i in range(2, 101)]), m)
    assert r.blocks == 1 and r.total_s == pytest.approx(trapezoid(10, 0, 0, 20, 50), rel=1e-12)


def _ring_buffer_reference(blocks_len, accel, max_entry, fresh, size=16):
    """grbl's planner written out plainly: a ring of ``size`` slots (size - 1 usable),
    planner_recalculate's reverse and forward passes from the executing block, blocks
    added one at a time while the buffer has room, a block's exit fixed when it starts.
    Returns the boundary speeds^2 (entry of each block, exit of the last)."""
    n = len(blocks_len)
    out = [0.0] * (n + 1)
    entry = [0.0] * n
    queue = []              # block indices in the buffer; queue[0] is executing
    nxt = 0
    current_entry = 0.0
    k = 0
    while k < n:
        # stream: fill the buffer (a fresh block waits until the buffer has emptied)
        while nxt < n and len(queue) < size - 1 and not (fresh[nxt] and nxt != k and queue):
            queue.append(nxt)
            nxt += 1
        # planner_recalculate over the queue: the last ends at rest; reverse then forward
        for i in queue:
            entry[i] = max_entry[i] if i != k else current_entry
        exit_sqr = 0.0
        for i in reversed(queue[1:]):
            entry[i] = min(max_entry[i], exit_sqr + 2 * accel[i] * blocks_len[i])
            exit_sqr = entry[i]
        prev = current_entry
        for i in queue[1:]:
            entry[i] = min(entry[i], prev + 2 * accel[i - 1] * blocks_len[i - 1])
            prev = entry[i]
        # block k runs: its exit is the next block's entry (0 when it is the last queued)
        out[k] = current_entry
        current_entry = entry[queue[1]] if len(queue) > 1 else 0.0
        queue.pop(0)
        k += 1
    out[n] = 0.0
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_streamed_speeds_match_a_plain_ring_buffer(seed):
    from fabkit.machine.planner import streamed_speeds

    r = np.random.default_rng(seed)
    n = 300
    L = r.choice([0.05, 0.5, 3.0, 40.0], size=n) * r.uniform(0.5, 1.5, size=n)
    a = r.uniform(3e4, 2e6, size=n)
    me = r.uniform(0, 3e6, size=n) * (r.random(n) > 0.1)
    fresh = r.random(n) < 0.02
    fresh[0] = True
    me = np.where(fresh, 0.0, me)
    got = streamed_speeds(me, a, L, fresh)
    want = _ring_buffer_reference(L, a, me, fresh)
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-6)


def test_per_pass_times():
    m = dataclasses.replace(GRBL, max_rate=(6000.0,) * 3)
    sync = ["M5", "M3 S1000"]
    text = prog(["G1 X50 F3000", *sync, "G1 Y1", *sync, "G1 X0", *sync, "G1 Y2", *sync, "G1 X50", "M5", "G0 Z5"])
    r = run_time(text, m, raster_axis=0)
    p = r.passes
    assert p["passes"] == 3
    first = trapezoid(50, 0, 0, 50, 10)
    later = trapezoid(1, 0, 0, 50, 10) + first          # the step across counts with the pass it leads into
    assert p["min_s"] == pytest.approx(first, abs=0.006) and p["max_s"] == pytest.approx(later, abs=0.006)
    assert p["median_s"] == pytest.approx(later, abs=0.006)
