"""The height-field stock against exact answers: a flat end mill's slot, a ball's and a
bull nose's groove profiles in closed form, sloped moves and a helical entry against a
dense sampling of the tool's positions written here, rapids through the stock, the
whole-job check on a block whose allowance and scallop are known in closed form, tool
changes read back, and the simulation of LinuxCNC's own reading of a two-tool program."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest

from fabkit.errors import DesignError
from fabkit.toolpath.path import CUT, PLUNGE, RAPID, Toolpath
from fabkit.toolpath.operations import Operation
from fabkit.toolpath.cut.stock import cut, make_stock, operations_from_program, stock_png, verify_job
from fabkit.toolpath.tools import Tool
from fabkit.toolpath.program.reader import read_program

RS274 = shutil.which("rs274")


def lift_exact(tool, rho):
    """The tool's cutting surface above its tip, written out (not Tool.lift)."""
    R, r = tool.radius, tool.corner_radius
    f = R - r
    rho = np.abs(np.asarray(rho, float))
    u = np.clip(rho - f, 0.0, None)
    z = r - np.sqrt(np.clip(r * r - u * u, 0.0, None)) if r > 0 else np.zeros_like(u)
    return np.where(rho <= R, z, np.inf)


def brute(px, py, a, b, tool, n=200_001):
    """Lowest point of the tool over (px, py) for n tip positions evenly spaced from a
    to b: a direct sampling of the sweep (an upper bound of the exact envelope)."""
    t = np.linspace(0.0, 1.0, n)
    c = a[None, :] + t[:, None] * (b - a)[None, :]
    out = np.empty(len(px))
    for i in range(len(px)):
        rho = np.hypot(px[i] - c[:, 0], py[i] - c[:, 1])
        out[i] = np.min(c[:, 2] + lift_exact(tool, rho))
    return np.minimum(out, 0.0)


def plunge_slot(x0, x1, y, depth):
    return (np.array([[x0, y, 5.0], [x0, y, -depth], [x1, y, -depth], [x1, y, 5.0]]),
            np.array([RAPID, PLUNGE, CUT, RAPID]))


def test_flat_end_mill_slot_is_exact_trench():
    tool = Tool("flat", 6.0)
    s = make_stock(40.0, 20.0, 0.1)
    P, K = plunge_slot(10.0, 30.0, 10.03, 2.0)     # centre line between nodes: no node at distance R
    res = cut(s, tool, P, K)
    X, Y = s.grid()
    # distance of each node to the slot's centre segment
    dx = np.clip(X, 10.0, 30.0) - X
    d = np.hypot(dx, Y - 10.03)
    expect = np.where(d <= 3.0, -2.0, 0.0)
    np.testing.assert_array_equal(s.z, expect)
    # the trench: exactly 2 mm deep, and across it the nodes in |y - 10.03| <= 3 (60 of them)
    col = s.z[200]
    assert col.min() == -2.0 and np.count_nonzero(col < 0) == 60
    assert res.max_engagement == 2.0 and res.rapids_into_stock == 0 and res.deepest_cut == 2.0


@pytest.mark.parametrize("tool", [Tool.ball(6.0), Tool("bull", 8.0, corner_radius=1.5)])
def test_groove_profile_closed_form(tool):
    """A horizontal groove at tip depth z0: across it z = z0 + lift(d) (ball: z0 + R -
    sqrt(R^2 - d^2); bull nose: flat bottom for d <= R - r, then the corner's arc)."""
    z0 = -2.5
    s = make_stock(40.0, 20.0, 0.05)
    P, K = plunge_slot(5.0, 35.0, 10.0, -z0)
    cut(s, tool, P, K)
    y = s.y
    d = np.abs(y - 10.0)
    R, r = tool.radius, tool.corner_radius
    f = R - r
    u = np.clip(d - f, 0, None)
    expect = np.where(d <= R, z0 + r - np.sqrt(np.clip(r * r - u * u, 0, None)), np.inf)
    expect = np.minimum(expect, 0.0)
    i = int(round(20.0 / s.hx))
    np.testing.assert_allclose(s.z[i], expect, atol=1e-9, rtol=0)
    if f > 0:
        assert np.all(s.z[i][d <= f] == z0)


@pytest.mark.parametrize("tool", [Tool("flat", 6.0), Tool.ball(6.0), Tool("bull", 6.0, corner_radius=2.0)])
@pytest.mark.parametrize("ab", [((4.0, 5.0, -0.5), (14.0, 9.0, -3.0)),     # descending ramp
                                ((14.0, 5.0, -3.2), (6.0, 12.0, -0.4)),    # ascending
                                ((10.0, 9.0, -0.5), (10.3, 9.1, -4.0))])   # steep, nearly a plunge
def test_sloped_move_against_dense_sampling(tool, ab):
    a, b = np.array(ab[0]), np.array(ab[1])
    s = make_stock(20.0, 18.0, 0.25)
    cut(s, tool, np.array([a, b]), np.array([CUT, CUT]), start=a)
    X, Y = s.grid()
    rng = np.random.default_rng(3)
    near = np.nonzero((s.z < 0).ravel())[0]
    pick = rng.choice(near, 40, replace=False)
    ref = brute(X.ravel()[pick], Y.ravel()[pick], a, b, tool)
    got = s.z.ravel()[pick]
    # the sampling is an upper bound of the exact envelope, within its step's effect
    assert np.all(got <= ref + 1e-9)
    assert np.max(ref - got) < 2e-4
    # nodes farther than R from the move's XY path are untouched
    d = b[:2] - a[:2]
    t = np.clip(((X - a[0]) * d[0] + (Y - a[1]) * d[1]) / (d @ d), 0, 1)
    dist = np.hypot(X - a[0] - t * d[0], Y - a[1] - t * d[1])
    assert np.all(s.z[dist > tool.radius + 1e-9] == 0.0)


def test_helix_entry():
    """A bull nose enters by a helix (radius 2 mm, 1 mm a turn, 4 turns down to -4) and
    one closing circle at -4: inside radius 2 + R - sagitta the floor is exactly -4 (the
    tool's flat radius 2 covers the axis), outside 2 + R the stock is untouched, and every
    node equals the dense sampling of the chords."""
    tool = Tool("bull", 8.0, corner_radius=1.0)
    n_turn, seg = 4, 72
    th = np.linspace(0.0, 2 * np.pi * (n_turn + 1), seg * (n_turn + 1) + 1)
    z = np.maximum(-th / (2 * np.pi), -4.0)
    cx, cy, rh = 10.0, 10.0, 2.0
    P = np.column_stack([cx + rh * np.cos(th), cy + rh * np.sin(th), z])
    P = np.vstack([[cx + rh, cy, 5.0], [cx + rh, cy, 0.0], P[1:]])
    K = np.full(len(P), CUT)
    K[0] = RAPID
    s = make_stock(20.0, 20.0, 0.1)
    before = s.z.copy()
    res = cut(s, tool, P, K)
    X, Y = s.grid()
    rho = np.hypot(X - cx, Y - cy)
    sag = rh * (1 - np.cos(np.pi / seg))
    inner = rho < rh + tool.radius - tool.corner_radius - sag - 1e-6
    assert np.all(s.z[inner] == -4.0)
    assert np.all(s.z[rho > rh + tool.radius + 1e-9] == 0.0)
    assert np.all(s.z <= before)
    # each turn goes 1 mm deeper: no single chord removes more than a turn's descent
    # plus the descent of the chord itself at a node (the tool sinks into its own cut)
    assert res.max_engagement <= 1.0 + 1.0 / seg + 1e-9
    rng = np.random.default_rng(5)
    band = np.nonzero(((rho > 4.5) & (rho < 6.0)).ravel())[0]
    pick = rng.choice(band, 25, replace=False)
    ref = np.full(pick.size, 0.0)
    for a, b in zip(P[1:-1], P[2:]):
        ref = np.minimum(ref, brute(X.ravel()[pick], Y.ravel()[pick], a, b, tool, n=2001))
    got = s.z.ravel()[pick]
    assert np.all(got <= ref + 1e-9) and np.max(ref - got) < 1e-4


def test_stock_never_rises_and_rapids_do_not_cut():
    rng = np.random.default_rng(11)
    s = make_stock(30.0, 30.0, 0.25)
    tools = [Tool("flat", 6.0), Tool.ball(4.0), Tool("bull", 5.0, corner_radius=1.0)]
    for k in range(6):
        P = np.column_stack([rng.uniform(0, 30, 12), rng.uniform(0, 30, 12), rng.uniform(-4, 1, 12)])
        K = rng.choice([RAPID, CUT], 12)
        before = s.z.copy()
        cut(s, tools[k % 3], P, K, start=P[0])
        assert np.all(s.z <= before)
    # a run of rapids only: nothing changes
    before = s.z.copy()
    P = np.column_stack([rng.uniform(0, 30, 20), rng.uniform(0, 30, 20), rng.uniform(-4, 1, 20)])
    res = cut(s, tools[0], P, np.full(20, RAPID), start=P[0])
    np.testing.assert_array_equal(s.z, before)
    assert res.rapids_into_stock > 0


def test_rapid_through_stock_reported():
    tool = Tool("flat", 6.0)
    s = make_stock(40.0, 20.0, 0.1)
    P, K = plunge_slot(10.0, 30.0, 10.0, 2.0)
    cut(s, tool, P, K)
    cleared = s.z.copy()
    # inside the slot at -1 (above its -2 floor, the whole disk over the floor): clear
    res = cut(s, tool, np.array([[15.0, 10.0, -1.0], [25.0, 10.0, -1.0]]), np.array([RAPID, RAPID]),
              start=np.array([15.0, 10.0, -1.0]))
    assert res.rapids_into_stock == 0
    # across the uncut stock at -1: 1 mm into it, reported and not cut
    res = cut(s, tool, np.array([[20.0, 10.0, -1.0], [20.0, 2.0, -1.0]]), np.array([RAPID, RAPID]),
              start=np.array([20.0, 10.0, -1.0]))
    assert res.rapids_into_stock == 1 and res.rapid_move == 1
    assert abs(res.rapid_depth - 1.0) < 1e-12
    assert res.rapid_at[1] < 7.0
    np.testing.assert_array_equal(s.z, cleared)


# ----------------------------------------------------------------------------
# the whole job on a block with a known answer
# ----------------------------------------------------------------------------
class FlatFloor:
    """A design whose work surface is a flat floor 3 mm below the top face over a
    40 x 30 mm block (the Surface attributes WorkSurface reads)."""

    scale = 1.0
    x_range = (0.0, 40.0)
    y_range = (0.0, 30.0)
    top = 0.0
    stock_size_mm = (40.0, 30.0)
    depth = 3.0

    def height(self, x, y):
        return np.full(np.broadcast(x, y).shape, -self.depth)

    def derivatives(self, x, y):
        """h and its exact first and second derivatives (a flat floor: zero)."""
        h = self.height(x, y)
        return (h,) + tuple(np.zeros_like(h) for _ in range(5))


def raster(tool, z, step, L=40.0, W=30.0):
    """Passes along x at tip height z, every ``step`` mm across y, overhanging the
    block by the tool radius; rapids up between passes."""
    R = tool.radius
    pts, kinds = [], []
    for y in np.linspace(0.0, W, int(np.ceil(W / step - 1e-9)) + 1):
        pts += [[-R - 1, y, 5.0], [-R - 1, y, z], [L + R + 1, y, z], [L + R + 1, y, 5.0]]
        kinds += [RAPID, PLUNGE, CUT, RAPID]
    return Toolpath(np.array(pts), np.array(kinds), R, 5.0)


def test_verify_job_allowance_scallop_and_depth_of_cut():
    rough_tool, ball = Tool("flat", 10.0, number=1), Tool.ball(6.0, number=2)
    leave, step = 0.5, 1.5
    scallop = 3.0 - np.sqrt(9.0 - (step / 2) ** 2)       # the ball's scallop between passes
    ops = [Operation("rough", rough_tool, raster(rough_tool, -2.5, 8.0), leave=leave, info={"cusp_mm": 0.0}),
           Operation("finish", ball, raster(ball, -3.0, step), info={"scallop": 0.1, "depth_of_cut_mm": 1.0})]
    job = verify_job(FlatFloor(), ops, 0.01, spacing=0.25, measure="vertical")
    assert job.ok, job.failures
    assert "largest gouge 0.0000 mm" in job.message
    r, f = job.operations
    # roughing: a flat floor exactly 0.5 above the design everywhere
    assert r.min_left == leave and r.max_left == leave and r.max_gouge == 0.0
    assert r.max_removed == 2.5
    # finishing: the scallop between passes 1.5 mm apart (nodes lie on the midlines)
    assert abs(f.max_left - scallop) < 1e-12 and f.min_left == 0.0
    assert f.max_removed == leave and f.max_gouge == 0.0
    np.testing.assert_array_equal(job.snapshots[0].z, np.full(job.snapshots[0].z.shape, -2.5))
    # the ball's allowed depth of cut below what it removes, and a finish 0.02 too deep
    ops[1].info["depth_of_cut_mm"] = 0.4
    ops[1].toolpath = raster(ball, -3.02, step)
    job = verify_job(FlatFloor(), ops, 0.01, spacing=0.25, measure="vertical")
    assert not job.ok
    text = " ".join(job.failures)
    assert "gouge 0.0200" in text and "depth of cut 0.4" in text and "reach" not in text
    report = json.loads(json.dumps(job.to_json()))
    assert report["ok"] is False and len(report["failures"]) == 2, report["failures"]
    assert report["operations"][1]["max_removed"] == pytest.approx(0.52, abs=1e-12)
    # a ball whose reach (its flute length) is shorter than the 3.02 mm it cuts down to
    ops[1].tool = Tool.ball(6.0, reach=3.0)
    job = verify_job(FlatFloor(), ops, 0.01, spacing=0.25, measure="vertical")
    assert any("cuts 3.020 mm below the top face, deeper than the tool's reach 3 mm" in f for f in job.failures)


def test_verify_job_narrow_valley_is_unreachable_not_a_failure():
    """A 4 mm wide, 2 mm deep slot in the floor, 30 mm long and closed at both ends (a
    slot open on the block's edge is reached by a tool hanging off it, and the
    simulation says so): a 10 mm flat end mill cannot enter it,
    so the 2 mm of material it leaves there is reported as unreachable, not as material
    left where the tool reaches."""

    class Slot(FlatFloor):
        def height(self, x, y):
            x, y = np.asarray(x), np.asarray(y)
            return np.where((np.abs(y - 15.0) < 2.0) & (np.abs(x - 20.0) < 15.0), -5.0, -3.0)

    tool = Tool("flat", 10.0)
    ops = [Operation("rough", tool, raster(tool, -2.5, 8.0), leave=0.5, info={"cusp_mm": 0.0})]
    job = verify_job(Slot(), ops, 0.01, spacing=0.25)
    assert job.ok, job.failures
    r = job.operations[0]
    assert abs(r.unreachable - (2.0 - 0.01)) < 1e-12        # 2.5 left, bound 0.51
    assert 3.5 * 30 <= r.unreachable_area <= 4.0 * 30 + 1e-9
    assert r.max_left == 0.5
    # the same stock with the slot's floor declared reachable fails: a 3 mm flat end
    # mill does fit, and did not go down
    small = Tool("flat", 3.0)
    ops = [Operation("rough", small, raster(small, -2.5, 2.5), leave=0.5, info={"cusp_mm": 0.0})]
    job = verify_job(Slot(), ops, 0.01, spacing=0.25)
    assert not job.ok and "where the tool reaches" in job.failures[0]


# ----------------------------------------------------------------------------
# tool changes read back
# ----------------------------------------------------------------------------
TWO_TOOLS = """G17 G21 G90 G94 G54
T1 M6
G43 H1
G0 Z5
M3 S10000
X-6 Y10.03
G1 Z-2 F300
X46 F1000
Y16.03
X-6
G0 Z5
T2 M6
G43 H2
G0 Z5
X-4 Y10.5
G1 Z-2.5 F300
X44 F1000
Y13
X-4
G0 Z5
M5
M2
"""


def test_read_program_splits_tools():
    p = read_program(TWO_TOOLS)
    assert p.tool_changes == [(0, 1, 2), (7, 2, 12)]
    assert p.tools() == [1, 2]
    assert list(p.tool) == [1] * 7 + [2] * 7
    assert list(p.offset) == [1] * 7 + [2] * 7
    runs = p.split()
    assert [t for t, _ in runs] == [1, 2]
    assert len(runs[0][1]) == 7 and len(runs[1][1]) == 7
    assert np.all(np.isnan(runs[1][1].start))
    # after the change the tip's Z is unknown until the program sets it
    a, _ = p.segments()
    assert np.isnan(a[7, 2]) and runs[1][1].points[0, 2] == 5.0
    # every move before any M6 is tool -1; M6 with no T loads T0 (LinuxCNC's selection
    # before any T); G49 cancels the offset; a T word that is not a tool number is refused
    q = read_program("G0 Z5\nT3\nM6\nG43\nG1 X1 F100\nG49\nG0 Z5\nM2\n")
    assert list(q.tool) == [-1, 3, 3] and list(q.offset) == [-1, 3, -1]
    assert list(read_program("G0 Z5\nM6\nG0 Z4\n").tool) == [-1, 0]
    with pytest.raises(DesignError, match="line 2"):
        read_program("G0 Z5\nT1.5 M6\n")


def test_split_program_simulates_each_tool():
    p = read_program(TWO_TOOLS)
    tools = {1: Tool("flat", 6.0), 2: Tool.ball(3.0)}
    s = make_stock(40.0, 20.0, 0.1)
    for t, run in p.split():
        res = cut(s, tools[t], run.points, run.kinds, start=run.start)
        assert res.rapids_into_stock == 0 and res.unlocated_low == 0
    X, Y = s.grid()
    # the flat mill's two passes clear 7.03 <= y <= 19.03 to -2 (y = 10.03 and 16.03, R = 3)
    col = s.z[200]
    inside = (s.y >= 7.03) & (s.y <= 19.03)
    expect = np.where(inside, -2.0, 0.0)
    for yc in (10.5, 13.0):
        d = np.abs(s.y - yc)
        groove = np.where(d <= 1.5, -2.5 + 1.5 - np.sqrt(np.clip(2.25 - d ** 2, 0, None)), 0.0)
        expect = np.minimum(expect, groove)
    np.testing.assert_allclose(col, expect, atol=1e-12)


_CANON = re.compile(r"(STRAIGHT_FEED|STRAIGHT_TRAVERSE)\(([-0-9.]+), ([-0-9.]+), ([-0-9.]+)|CHANGE_TOOL\((\d+)\)")


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
def test_rs274_two_tool_program_agrees(tmp_path):
    """LinuxCNC's interpreter reads the two-tool program (M6, G43); the stock cut along
    its canonical moves, each run with the tool CHANGE_TOOL loaded, equals the stock cut
    along read_program's moves split by tool."""
    path = tmp_path / "two.ngc"
    path.write_text(TWO_TOOLS)
    run = subprocess.run([RS274, "-g", str(path)], stdin=subprocess.DEVNULL, capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert run.stderr.strip() in ("", "executing"), run.stderr
    tools = {1: Tool("flat", 6.0), 2: Tool.ball(3.0)}
    runs, cur = [], None
    for kind, x, y, z, change in _CANON.findall(run.stdout):
        if change:
            cur = int(change)
            runs.append((cur, [], []))
            continue
        assert cur is not None
        runs[-1][1].append([float(x), float(y), float(z)])
        runs[-1][2].append(CUT if kind == "STRAIGHT_FEED" else RAPID)
    assert [t for t, _, _ in runs] == [1, 2]
    ours = make_stock(40.0, 20.0, 0.2)
    for t, prog in read_program(TWO_TOOLS).split():
        cut(ours, tools[t], prog.points, prog.kinds, start=prog.start)
    theirs = make_stock(40.0, 20.0, 0.2)
    for t, pts, kinds in runs:
        pts = np.array(pts)
        # rs274's first move after a change starts from the old tool's position (Z in
        # the new offset); start it from straight above its end point like ours
        res = cut(theirs, tools[t], pts, np.array(kinds), start=np.array([pts[0, 0], pts[0, 1], np.nan]))
        assert res.rapids_into_stock == 0
    np.testing.assert_allclose(theirs.z, ours.z, atol=1e-12)
    assert ours.z.min() < -2.4


def test_operations_from_program_and_picture():
    p = read_program(TWO_TOOLS)
    ops = operations_from_program(p, {1: Tool("flat", 6.0), 2: Tool.ball(3.0)},
                                  info={1: {"leave": 0.5, "cusp_mm": 0.0}})
    assert [o.kind for o in ops] == ["rough", "finish"] and ops[0].leave == 0.5

    class Floor(FlatFloor):
        stock_size_mm = (40.0, 20.0)
        y_range = (0.0, 20.0)
        depth = 2.5

    job = verify_job(Floor(), ops, 0.01, spacing=0.2)
    pics = job.pictures()
    assert sorted(pics) == ["finish", "rough"]
    from io import BytesIO

    from PIL import Image

    for png in list(pics.values()) + [stock_png(job.snapshots[0], job.design)]:
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        im = Image.open(BytesIO(png))
        assert im.size[0] >= 600 and im.mode == "RGB"
    # the picture is coloured by the deviation: the cut floor 2.5 deep (the design) is
    # white-grey where the ball went to -2.5, the uncut top face orange (material left)
    im = np.asarray(Image.open(BytesIO(pics["rough"])))
    assert im[40:-100, 70:-40, 0].astype(int).max() > im[40:-100, 70:-40, 2].astype(int).max()


def test_reach_of_a_ball_in_a_narrow_groove():
    """The lowest a ball of radius 3 reaches in a V groove of half-angle 45 degrees (walls
    z = |y - 10| - 4, clipped at the top face 0): the ball rests on both walls, its
    centre sqrt(2) R above the apex, its tip (sqrt(2) - 1) R above the apex. Sampled
    (every 2nd node, the rest by the nearest) and computed at every node agree with it."""
    from fabkit.toolpath.cut.stock import reach_height

    s = make_stock(20.0, 20.0, 0.1)
    X, Y = s.grid()
    target = np.minimum(np.abs(Y - 10.0) - 4.0, 0.0)
    ball = Tool.ball(6.0)
    apex = (np.abs(s.y - 10.0) < 1e-9)
    mask = np.zeros(s.shape, bool)
    mask[40:160, :] = np.abs(Y[40:160, :] - 10.0) < 0.5
    full = reach_height(target, s, ball, mask)
    expect = -4.0 + (np.sqrt(2.0) - 1.0) * 3.0
    # centres and contacts on the nodes: within the grid's chordal error
    # (0.1^2 / (8 * 3) ~ 4e-4 mm, x sqrt(2) on the 45-degree walls)
    got = full[100, apex][0]
    assert abs(got - expect) < 1e-3
    sampled = reach_height(target, s, ball, mask, max_nodes=int(mask.sum()) // 3)
    both = np.isfinite(full) & np.isfinite(sampled)
    assert both.sum() == mask.sum()
    assert np.max(np.abs(sampled[both] - full[both])) < 0.1


def test_rest_pass_keeps_the_finishing_ball_within_its_depth_of_cut():
    """The closed slot again (4 mm wide, 2 mm below the 3 mm floor, 30 mm long): the 10 mm
    flat end mill leaves it full (2.5 mm above its floor); a ball 3 mm across finishing its
    floor at -5 would remove 2.5 mm there. A rest operation with a 3 mm flat end mill
    (two passes, leave 0.5) first: the ball removes at most 0.5 mm (its centre line), and
    the slot's corners, which the rest tool's round end cannot reach, are reported as
    unreachable, not as a failure."""

    class Slot(FlatFloor):
        def height(self, x, y):
            x, y = np.asarray(x), np.asarray(y)
            return np.where((np.abs(y - 15.0) < 2.0) & (np.abs(x - 20.0) < 15.0), -5.0, -3.0)

    rough, rest, ball = Tool("flat", 10.0, number=1), Tool("flat", 3.0, number=2), Tool.ball(3.0, number=3)

    def passes(ys, z, x0, x1):
        pts, kinds = [], []
        for y in ys:
            pts += [[x0, y, 5.0], [x0, y, z], [x1, y, z], [x1, y, 5.0]]
            kinds += [RAPID, PLUNGE, CUT, RAPID]
        return Toolpath(np.array(pts), np.array(kinds), 1.5, 5.0)

    ops = [Operation("rough", rough, raster(rough, -2.5, 8.0), leave=0.5, info={"cusp_mm": 0.0}),
           Operation("rest", rest, passes([14.51, 15.49], -4.5, 6.51, 33.49), leave=0.5, info={"cusp_mm": 0.0}),
           Operation("finish", ball, passes([15.0], -5.0, 6.6, 33.4), info={"scallop": 0.05})]
    limit = {"finish": 1.0}
    with_rest = verify_job(Slot(), ops, 0.01, spacing=0.25, depth_of_cut=limit)
    r, rs, f = with_rest.operations
    assert r.unreachable_area > 100 and not any("operation 1" in x or "operation 2" in x for x in with_rest.failures)
    assert rs.max_removed == 2.0 and rs.max_gouge == 0.0
    assert 0 < rs.unreachable_area < 4 * (0.25 * 0.25) * 20      # the four corners, a few nodes each
    assert f.max_removed == 0.5 and f.max_gouge == 0.0
    assert not any("depth of cut" in x for x in with_rest.failures)
    without = verify_job(Slot(), [ops[0], ops[2]], 0.01, spacing=0.25, depth_of_cut=limit)
    assert without.operations[1].max_removed == 2.5
    assert any("removes 2.500 mm" in x and "depth of cut 1 mm" in x for x in without.failures)


@pytest.mark.parametrize("size", [(3, 3), (7, 5), (1, 9), (9, 1), (13, 13)])
def test_window_filters_equal_scipy_ndimage_to_the_bit(size):
    """The pictures' and the rest roughing's window filters are scipy.ndimage's, to the
    last bit (min, max and the running-sum mean, edges repeated), and the min/max agree
    with a brute-force window over the edge-padded array."""
    from scipy.ndimage import maximum_filter, minimum_filter, uniform_filter

    from fabkit.toolpath.cut.stock_kernels import window_max, window_mean, window_minmax

    rng = np.random.default_rng(7)
    for a in (rng.normal(size=(41, 23)).cumsum(axis=0) * 0.37, -np.abs(rng.normal(size=(5, 4))) * 1e3):
        lo, hi = window_minmax(a, size)
        assert np.array_equal(lo, minimum_filter(a, size=size, mode="nearest"))
        assert np.array_equal(hi, maximum_filter(a, size=size, mode="nearest"))
        assert np.array_equal(hi, maximum_filter(a, size=size, mode="constant", cval=-np.inf))
        assert np.array_equal(window_max(a, size), hi)
        b = a.copy()
        assert window_max(b, size, out=b) is b and np.array_equal(b, hi)
        assert np.array_equal(window_mean(a, size), uniform_filter(a, size=size, mode="nearest"))
        s0, s1 = size[0] // 2, size[1] // 2
        p = np.pad(a, ((s0, s0), (s1, s1)), mode="edge")
        ref = np.array([[p[i:i + size[0], j:j + size[1]].max() for j in range(a.shape[1])]
                        for i in range(a.shape[0])])
        assert np.array_equal(hi, ref)


@pytest.mark.parametrize("tool", [Tool("flat", 4.0, 0.0), Tool("bull", 4.0, 0.7), Tool.ball(4.0)])
def test_cut_skipping_nodes_a_move_cannot_change_equals_every_node_visited(tool):
    """The sweep skips the nodes a move cannot lower (within the flat of the last level
    feed, for a move no lower than it; beyond the move's capsule). The stock, each
    move's engagement and the rapids' depths equal, to the bit, those of every move
    evaluated at every node (the kernel's closed-form lowest point, node by node):
    level loops at two depths, ramps, a diagonal, a plunge, rapids across the cut."""
    from fabkit.toolpath.cut.stock_kernels import lowest

    rng = np.random.default_rng(11)
    pts, kinds = [[2.0, 2.0, 3.0]], [RAPID]
    for z in (-1.0, -2.5):
        ring = np.array([[2, 2], [11, 2.3], [12.4, 8], [7, 9.7], [2.2, 8.8], [2, 2]], float)
        ring += rng.normal(scale=0.05, size=ring.shape)
        pts += [[ring[0, 0], ring[0, 1], z + 1.0], [ring[0, 0], ring[0, 1], z]]
        kinds += [RAPID, PLUNGE]
        for q in ring[1:]:
            pts.append([q[0], q[1], z])
            kinds.append(CUT)
        pts += [[6.0, 6.0, z], [6.5, 6.2, z - 0.1], [8.0, 4.0, z - 0.8], [3.0, 5.5, z - 0.8], [3.0, 5.5, 1.0]]
        kinds += [CUT, CUT, CUT, CUT, RAPID]
    pts += [[13.0, 9.0, -0.5], [1.0, 1.0, -0.2], [5.0, 5.0, -3.0]]
    kinds += [RAPID, RAPID, PLUNGE]
    P, K = np.array(pts), np.array(kinds)
    stock = make_stock(14.0, 10.0, 0.25)
    res = cut(stock, tool, P, K, start=P[0])
    # every node, every move
    Z = np.zeros(stock.z.shape)
    X, Y = stock.grid()
    R, r = tool.radius, tool.corner_radius
    eng, rap = np.zeros(len(P)), np.zeros(len(P))
    for m in range(len(P)):
        a, b = (P[0] if m == 0 else P[m - 1]), P[m]
        g = np.array([lowest(x, y, *a, *b, R, r, R - r) for x, y in zip(X.ravel(), Y.ravel())]).reshape(Z.shape)
        d = np.where(g < Z, Z - g, 0.0)
        if K[m] == RAPID:
            rap[m] = d.max() if d.max() > 1e-6 else 0.0
        else:
            eng[m] = d.max()
            Z = np.minimum(Z, g)
    assert np.array_equal(stock.z, Z)
    assert np.array_equal(res.engagement, eng)
    assert res.rapid_depth == rap.max() and res.rapids_into_stock == int((rap > 1e-6).sum())
    assert res.rapids_into_stock >= 1 and eng.max() > 0.5


def test_picture_pooling_equals_numpy_block_reductions():
    """The picture's k x k pooling: the envelope of largest magnitude of each block and
    the block means, against numpy's reductions over the blocks (the extremes to the
    bit, a nan propagated; the means to 1e-13)."""
    from fabkit.toolpath.cut.stock_kernels import pool_envelope, pool_mean

    rng = np.random.default_rng(2)
    for k, shape in ((2, (9, 7)), (3, (40, 31)), (4, (13, 26))):
        lo = rng.normal(size=shape)
        hi = lo + np.abs(rng.normal(size=shape))
        hi[3, 2] = np.nan
        env = np.where(-lo > hi, lo, hi)
        mx, my = shape[0] // k * k, shape[1] // k * k
        b = env[:mx, :my].reshape(mx // k, k, my // k, k)
        bmax, bmin = b.max(axis=(1, 3)), b.min(axis=(1, 3))
        want = np.where(-bmin > bmax, bmin, bmax)
        got = np.empty((shape[0] // k, shape[1] // k))
        pool_envelope(lo, hi, k, got)
        assert np.array_equal(got, want, equal_nan=True) and np.isnan(got[3 // k, 2 // k])
        a = rng.normal(size=shape) * 10.0 ** rng.uniform(-3, 3, size=shape)
        mean = np.empty_like(got)
        pool_mean(a, k, mean)
        np.testing.assert_allclose(mean, a[:mx, :my].reshape(mx // k, k, my // k, k).mean(axis=(1, 3)),
                                   rtol=1e-13, atol=1e-13 * np.abs(a).max())


def test_slope_grids_are_numpys_gradient_expressions_to_the_bit():
    """stock_kernels.slope_grids (verify_job's normal measure and slope) against the numpy
    expressions it replaces: numpy.gradient, 1 / sqrt((1 + gx^2) + gy^2) in place, and
    hypot, on rough random grids with non-finite nodes, unequal spacings, down to 2 x 2;
    either output alone."""
    from fabkit.toolpath.cut.stock_kernels import slope_grids

    rng = np.random.default_rng(5)
    for shape in [(2, 2), (2, 7), (5, 3), (301, 170)]:
        f = np.cumsum(rng.normal(size=shape) * rng.choice([1e-3, 1.0, 50.0], size=shape), axis=0)
        f[rng.random(shape) < 0.02] = np.nan
        h0, h1 = 0.2498, 0.3117
        gx, gy = np.gradient(f, h0, h1)
        ns = gx * gx
        np.add(1.0, ns, out=ns)
        ns += gy * gy
        np.sqrt(ns, out=ns)
        np.divide(1.0, ns, out=ns)
        hp = np.hypot(gx, gy)
        N, S, none = np.empty_like(f), np.empty_like(f), np.empty((0, 0))
        slope_grids(f, h0, h1, N, S)
        assert np.array_equal(N, ns, equal_nan=True) and np.array_equal(S, hp, equal_nan=True)
        N2, S2 = np.empty_like(f), np.empty_like(f)
        slope_grids(f, h0, h1, N2, none)
        slope_grids(f, h0, h1, none, S2)
        assert np.array_equal(N2, ns, equal_nan=True) and np.array_equal(S2, hp, equal_nan=True)


def test_shaded_rgb_is_the_pictures_numpy_expression_to_the_byte():
    """stock_kernels.shaded_rgb (stock_png's colouring) against the array expression it
    replaces: colour(dv) x shade, rint, clip, uint8, rows +Y up; deviations on both sides
    of the scale, beyond its ends and exactly 0, shades 0.5-1."""
    from fabkit.toolpath.cut.stock import _GOUGE, _LEFT, _ZERO
    from fabkit.toolpath.cut.stock_kernels import shaded_rgb

    rng = np.random.default_rng(11)
    dv = rng.normal(scale=0.05, size=(233, 117))
    dv[::7, ::5] = 0.0
    dv[3, :] = 1.0
    dv[:, 4] = -1.0
    shade = rng.uniform(0.5, 1.0, size=dv.shape)
    gmax, lmax = 0.02, 0.07

    def colour(d):
        tg = np.clip(-d / gmax, 0.0, 1.0)[..., None]
        tl = np.clip(d / lmax, 0.0, 1.0)[..., None]
        return np.where(d[..., None] < 0, _ZERO + (_GOUGE - _ZERO) * tg, _ZERO + (_LEFT - _ZERO) * tl)

    want = np.clip(np.rint(colour(dv) * shade[..., None]), 0, 255).astype(np.uint8).transpose(1, 0, 2)[::-1]
    got = np.empty_like(want)
    shaded_rgb(dv, shade, gmax, lmax, _ZERO, _GOUGE, _LEFT, got)
    assert np.array_equal(got, want)


def test_pooled_window_envelope_is_the_windows_pooled():
    """stock_kernels.pool_window_envelope (the stock picture's colour per pixel) against
    pool_envelope of window_minmax, the two passes it replaces: random deviations with
    infinite nodes, blocks of 2-5 nodes, windows of 1-9 (wider than a small grid too),
    partial last blocks dropped. (stock_png takes the two passes where a node is nan.)"""
    from fabkit.toolpath.cut.stock_kernels import pool_envelope, pool_window_envelope, window_minmax

    rng = np.random.default_rng(13)
    for n0, n1, k, w in [(40, 31, 3, (7, 7)), (9, 8, 2, (9, 9)), (50, 50, 5, (3, 5)), (23, 61, 4, (1, 3)),
                         (6, 6, 2, (5, 1))]:
        a = rng.normal(scale=0.05, size=(n0, n1))
        a[rng.random(a.shape) < 0.02] = np.inf
        a[rng.random(a.shape) < 0.02] = -np.inf
        lo, hi = window_minmax(a, w)
        want = np.empty((n0 // k, n1 // k))
        pool_envelope(np.ascontiguousarray(lo), np.ascontiguousarray(hi), k, want)
        got = np.empty_like(want)
        pool_window_envelope(a, k, w[0], w[1], got)
        assert np.array_equal(got, want, equal_nan=True)
