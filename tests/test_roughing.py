"""Roughing with its own tool and rest passes (fabkit/toolpath/rough/roughing.py), against
closed forms and an independent cut simulation written here.

- A paraboloid bowl H = a rho^2 - d: at level z a flat end mill's tip may stand
  within rho_z - R of the axis, rho_z = sqrt((z - leave + d) / a) (the region
  {H + leave > z} dilated by R is the outside of that circle); the levels are the
  multiples of the stepdown above the bowl's floor + leave; a closed pocket is
  entered by a helix.
- A bull nose in the same bowl: the largest allowed radius solved here by bisection
  on the exact constraint a (rho + t)^2 - d + leave <= z + lift(t), t in [0, R].
- Every tip position checked by brute force over the disc under the tool.
- A groove narrower than the flat end mill in the bowl's floor gets rest passes, and
  an independent height-field simulation of rough + rest shows the finishing ball
  never engages more than its depth of cut.
- Spec errors: one line naming the file and key, exit 2, via the CLI.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from fabkit.errors import SpecError
from fabkit.spec import load_spec, validate
from fabkit.surface import Surface
from fabkit.toolpath.path import CUT, PLUNGE, RAPID
from fabkit.toolpath.rough.roughing import (finish_tool, plan_operations, plan_rough, spec_tools)
from fabkit.toolpath.tools import Tool

from conftest import SPECS, run_cli

A, DEPTH, HALF = 0.01, 30.0, 50.0   # bowl: H = A rho^2 - DEPTH (mm, top 0), footprint 100 x 100 mm


def bowl_raw(height=f"{A}*(x**2 + y**2) - {DEPTH}", tools=None, roughing=None, **machining):
    raw = {
        "name": "bowl", "units": "mm",
        "surface": {"height": height, "x": [-HALF, HALF], "y": [-HALF, HALF], "top": 0.0},
        "stock": {"thickness": 50.0},
        "tool": {"shape": "ball", "diameter": 6.35, "number": 2},
        "tools": tools or [{"number": 1, "shape": "flat", "diameter": 12.7, "reach": 60}],
        "roughing": roughing or {"tool": 1, "stepdown": 5, "stepover": 6, "leave": 0.5},
        "machining": {"scallop": 0.1, "tolerance": 0.01, **machining},
    }
    return raw


def load(tmp_path, raw):
    p = tmp_path / "spec.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    spec = load_spec(p)
    return spec, Surface.from_spec(spec)


def feed_points(tp, step=0.25):
    """Tip positions along every feed move (CUT and PLUNGE), every ``step`` mm, work mm."""
    P, K = tp.points, tp.kinds
    out = []
    for i in range(1, len(P)):
        if K[i] not in (CUT, PLUNGE):
            continue
        a, b = P[i - 1], P[i]
        n = max(1, int(math.ceil(np.linalg.norm(b - a) / step)))
        t = np.linspace(0.0, 1.0, n + 1)[:, None]
        out.append(a + t * (b - a))
    return np.vstack(out)


def worst_allowance(points, tool: Tool, design, L, W, leave, rings=24, angles=72):
    """min over tip positions c and stock points q under the tool of
    z + lift(|q - c|) - (design(q) + leave): >= 0 where the allowance holds. q on
    rings of the disc (and its centre), inside the footprint only."""
    R = tool.radius
    rho = np.r_[0.0, R * np.sqrt(np.linspace(0, 1, rings + 1)[1:])]
    ang = 2 * np.pi * np.arange(angles) / angles
    ox = (rho[:, None] * np.cos(ang)[None, :]).ravel()
    oy = (rho[:, None] * np.sin(ang)[None, :]).ravel()
    lift = tool.lift(np.hypot(ox, oy))
    worst = np.inf
    for a in range(0, len(points), 2000):
        c = points[a:a + 2000]
        qx, qy = c[:, :1] + ox, c[:, 1:2] + oy
        inside = (qx >= 0) & (qx <= L) & (qy >= 0) & (qy <= W)
        gap = c[:, 2:3] + lift - (np.minimum(design(qx, qy), 0.0) + leave)
        worst = min(worst, float(np.where(inside, gap, np.inf).min()))
    return worst


def bowl_design(X, Y):
    """The bowl in work mm (origin at the footprint corner), written here."""
    return A * ((X - HALF) ** 2 + (Y - HALF) ** 2) - DEPTH


def levels_of(tp):
    z = tp.points[tp.kinds == CUT, 2]
    return np.unique(np.round(z[z < -1e-9], 6))


def test_flat_bowl_levels_region_and_allowance(tmp_path):
    spec, surf = load(tmp_path, bowl_raw())
    op = plan_rough(spec, surf)
    leave, R, step = 0.5, 6.35, 5.0
    # levels: every stepdown above the floor + leave (-29.5): -5 ... -25
    expect = [-step * k for k in range(1, 6)]
    assert op.levels == 5 and op.info["level_z_mm"] == expect
    assert list(levels_of(op.toolpath)) == sorted(expect)
    pts = feed_points(op.toolpath)
    # the allowed region at each level: the disc of radius rho_z - R about the axis
    for z in expect:
        at = pts[np.abs(pts[:, 2] - z) < 1e-9]
        r = np.hypot(at[:, 0] - HALF, at[:, 1] - HALF)
        rho_z = math.sqrt((z - leave + DEPTH) / A)
        # the outermost loop on the boundary, short of it by at most the stated vertical
        # excess over the slope there, the dilation's circumscribed chord and 1 um
        slack = (op.info["allowance_excess_mm"] / (2 * A * rho_z) + R * (1 / math.cos(math.pi / 64) - 1)
                 + op.info["loop_inset_mm"] + 1e-3)
        assert rho_z - R - slack <= r.max() <= rho_z - R + 1e-6, (z, r.max(), rho_z - R)
    # no tip position leaves less than the allowance; the walls' contacts leave it exactly
    worst = worst_allowance(pts, op.tool, bowl_design, 2 * HALF, 2 * HALF, leave)
    chord = R * (1 / math.cos(math.pi / 64) - 1) + op.info["loop_inset_mm"]
    assert -1e-9 <= worst <= op.info["allowance_excess_mm"] + 2 * A * (HALF + R) * chord + 1e-3
    # a closed pocket per level: entered by a helix, and the allowance excess stated
    assert op.info["entries"]["helix"] == 5 and op.info["entries"]["plunge_entries"] == 0
    assert op.info["allowance_excess_mm"] <= spec.machining.tolerance + 1e-12
    assert op.info["cusp_mm"] == step
    # cut length, time by length / feed: recomputed here
    P, K = op.toolpath.points, op.toolpath.kinds
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    cut, plg = seg[K[1:] == CUT].sum(), seg[K[1:] == PLUNGE].sum()
    assert op.info["cutting_length_mm"] == pytest.approx(cut + plg)
    assert op.info["time_by_length_feed_s"] == pytest.approx(60 * (cut / 2500 + plg / 600))


@pytest.mark.parametrize("strategy,entry", [("offset", "ramp"), ("offset", "plunge"), ("raster", "helix")])
def test_strategies_and_entries_keep_the_allowance(tmp_path, strategy, entry):
    rg = {"tool": 1, "stepdown": 5, "stepover": 6, "leave": 0.5, "strategy": strategy, "entry": entry}
    spec, surf = load(tmp_path, bowl_raw(roughing=rg))
    op = plan_rough(spec, surf)
    assert op.levels == 5 and op.info["strategy"] == strategy
    e = op.info["entries"]
    if strategy == "offset":
        # one closed pocket per level, entered as asked
        assert e["helix"] == 0 and e[{"ramp": "ramp", "plunge": "plunge_entries"}[entry]] == 5
    else:
        # rows: a helix has no room at a row's end; the rows not over cleared ground are ramped into
        assert e["helix"] == 0 and e["ramp"] >= 5
    pts = feed_points(op.toolpath)
    assert worst_allowance(pts, op.tool, bowl_design, 2 * HALF, 2 * HALF, 0.5) >= -1e-9
    # ramps descend at 5 degrees at most
    P, K = op.toolpath.points, op.toolpath.kinds
    d = np.diff(P, axis=0)
    run = np.hypot(d[:, 0], d[:, 1])
    down = (K[1:] == 2) | ((K[1:] == 1) & (run > 1e-9))
    slope = -d[down, 2] / np.maximum(run[down], 1e-12)
    assert slope.max() <= math.tan(math.radians(5.0)) + 1e-6


def test_levels_stop_at_the_depth_limit(tmp_path):
    # the bowl is 30 mm deep; with stock.depth_limit 17 mm the levels stop at -15 and -17
    raw = bowl_raw()
    raw["stock"]["depth_limit"] = 17.0
    spec, surf = load(tmp_path, raw)
    op = plan_rough(spec, surf)
    assert op.info["level_z_mm"] == [-5.0, -10.0, -15.0, -17.0] and op.info["stopped_at_limit"]
    assert op.toolpath.points[:, 2].min() == pytest.approx(-17.0)
    # the tool's reach binds the same way
    raw = bowl_raw(tools=[{"number": 1, "shape": "flat", "diameter": 12.7, "reach": 12}])
    spec, surf = load(tmp_path, raw)
    assert plan_rough(spec, surf).info["level_z_mm"] == [-5.0, -10.0, -12.0]


def bull_radius(z, leave, R, r):
    """Largest tip radius about the bowl's axis where a bull nose (R, corner r) at level
    z leaves the allowance: a (rho + t)^2 - d + leave <= z + lift(t) for t in [0, R]
    (the worst q lies outward along the radius), by bisection on a dense t."""
    tool = Tool("bull", 2 * R, r)
    t = np.linspace(0.0, R, 20001)
    lift = tool.lift(t)

    def ok(rho):
        return bool(np.all(A * (rho + t) ** 2 - DEPTH + leave <= z + lift))

    lo, hi = 0.0, HALF
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo


def test_bull_nose_bowl_against_bisection(tmp_path):
    tools = [{"number": 1, "shape": "bull", "diameter": 12.7, "corner_radius": 3.0, "reach": 60}]
    spec, surf = load(tmp_path, bowl_raw(tools=tools))
    op = plan_rough(spec, surf)
    pts = feed_points(op.toolpath)
    excess = op.info["allowance_excess_mm"]
    assert excess <= 3.0 / 24 + spec.machining.tolerance + 1e-12
    # the levels a step of 5 mm less Delta apart (the allowance's bound held strictly)
    assert op.info["level_step_mm"] == pytest.approx(5.0 - 3.0 / 24, abs=2e-3)
    for z in levels_of(op.toolpath):
        at = pts[np.abs(pts[:, 2] - z) < 1e-6]
        # over the footprint (beyond its edges the corner may stand over the stock's edge,
        # lifted above the allowance there: the brute force below checks those)
        at = at[(at[:, 0] >= 0) & (at[:, 0] <= 2 * HALF) & (at[:, 1] >= 0) & (at[:, 1] <= 2 * HALF)]
        r = np.hypot(at[:, 0] - HALF, at[:, 1] - HALF).max()
        exact = bull_radius(z, 0.5, 6.35, 3.0)
        # never beyond the exact radius; and the tool standing there leaves at most the
        # stated excess (plus the dilation's chord on the slope) above the allowance
        assert r <= exact + 1e-6, (z, r, exact)
        t = np.linspace(0.0, 6.35, 20001)
        gap = float(np.min(z + Tool("bull", 12.7, 3.0).lift(t) - (A * (r + t) ** 2 - DEPTH + 0.5)))
        chord = 2 * A * (r + 6.35) * (6.35 * (1 / math.cos(math.pi / 64) - 1) + op.info["loop_inset_mm"])
        assert -1e-9 <= gap <= excess + chord + 1e-3, (z, gap, excess)
    assert worst_allowance(pts, op.tool, bowl_design, 2 * HALF, 2 * HALF, 0.5) >= -1e-9
    # a bull nose leaves a cusp between loops when the stepover exceeds its flat: 6 > 2 x 3.35: none
    assert op.info["cusp_mm"] == pytest.approx(op.info["level_step_mm"])


def test_open_pocket_entered_from_outside(tmp_path):
    # a plane falling to the x = 0 edge: the pocket opens beyond the stock; no helix
    spec, surf = load(tmp_path, bowl_raw(height="-0.2*(50 - x)"))
    op = plan_rough(spec, surf)
    assert op.info["entries"]["helix"] == 0 and op.info["entries"]["from_outside"] == op.levels
    # H = -0.2 (100 - X) - ... in work mm: H(X) = -0.2 (100 - X); allowed X <= X_z - R,
    # X_z where H + leave = z: X_z = 100 + (z - leave) / 0.2
    pts = feed_points(op.toolpath)
    for z in op.info["level_z_mm"]:
        at = pts[np.abs(pts[:, 2] - z) < 1e-9]
        at = at[(at[:, 1] >= 0) & (at[:, 1] <= 100)]    # beyond, the disc overhangs the side
        xz = 100 + (z - 0.5) / 0.2
        slack = (op.info["allowance_excess_mm"] / 0.2 + 6.35 * (1 / math.cos(math.pi / 64) - 1)
                 + op.info["loop_inset_mm"] + 1e-3)
        assert xz - 6.35 - slack <= at[:, 0].max() <= xz - 6.35 + 1e-6
    design = lambda X, Y: -0.2 * (100 - X)
    assert worst_allowance(pts, op.tool, design, 100, 100, 0.5) >= -1e-9
    # the levels: 20 mm deep at X = 0, floor + leave at -19.5: -5, -10, -15
    assert op.levels == 3


def _under(pts, h, n, R):
    """Grid nodes (step h, n x n) within R of each tip: (ii, jj, rho), exact distances."""
    m = int(math.ceil(R / h)) + 1
    di, dj = np.meshgrid(np.arange(-m, m + 1), np.arange(-m, m + 1), indexing="ij")
    ii = np.rint(pts[:, 1:2] / h).astype(int) + di.ravel()
    jj = np.rint(pts[:, 0:1] / h).astype(int) + dj.ravel()
    rho = np.hypot(jj * h - pts[:, 0:1], ii * h - pts[:, 1:2])
    ok = (rho <= R) & (ii >= 0) & (ii < n) & (jj >= 0) & (jj < n)
    return ii, jj, rho, ok


def simulate(ops, n, h, rapid_hits=None):
    """Independent height-field cut simulation: the stock's top at the nodes of a grid
    of step h after the operations' feed moves (sampled every h/2), each tool's own
    shape (tip + lift at the exact distance), in the program's order. ``rapid_hits``
    (a list): the most material (mm) any rapid move's tool meets, per operation."""
    S = np.zeros((n, n))
    for op in ops:
        P, K = op.toolpath.points, op.toolpath.kinds
        rapid = K == RAPID
        # batches of consecutive moves of one class (feed or rapid), in order
        cuts = np.nonzero(np.diff(np.r_[-1, rapid[1:].astype(int)]))[0] + 1
        bounds = list(cuts) + [len(P)]
        worst = 0.0
        R = op.tool.radius
        for a, b in zip(bounds[:-1], bounds[1:]):
            segs = []
            for i in range(a, b):
                p0, p1 = P[i - 1], P[i]
                k = max(1, int(math.ceil(np.linalg.norm(p1 - p0) / (h / 2))))
                t = np.linspace(0.0, 1.0, k + 1)[:, None]
                segs.append(p0 + t * (p1 - p0))
            c = np.vstack(segs)
            for lo in range(0, len(c), 2000):
                cc = c[lo:lo + 2000]
                ii, jj, rho, ok = _under(cc, h, n, R)
                z = cc[:, 2:3] + op.tool.lift(np.minimum(rho, R))
                if rapid[a]:
                    top = S[np.clip(ii, 0, n - 1), np.clip(jj, 0, n - 1)]
                    worst = max(worst, float(np.where(ok, top - z, 0.0).max()))
                else:
                    np.minimum.at(S, (ii[ok], jj[ok]), z[ok])
        if rapid_hits is not None:
            rapid_hits.append(worst)
    return S


def engagement(S, h, tp, tool):
    """The most material (mm, vertical) the tool removes at any node under it along the
    toolpath ``tp`` from the stock S: max of S(q) - (tip + lift(|q - c|)), the stock's
    thickness it cuts through (0 where it cuts nothing). The stock is updated as it goes."""
    S = S.copy()
    n = len(S)
    pts = feed_points(tp, step=h / 2)
    worst = 0.0
    for a in range(0, len(pts), 500):
        c = pts[a:a + 500]
        ii, jj, rho, ok = _under(c, h, n, tool.radius)
        z = c[:, 2:3] + tool.lift(np.minimum(rho, tool.radius))
        top = S[np.clip(ii, 0, n - 1), np.clip(jj, 0, n - 1)]
        worst = max(worst, float(np.where(ok, top - z, 0.0).max()))
        np.minimum.at(S, (ii[ok], jj[ok]), z[ok])
    return worst


def test_groove_narrower_than_the_tool_gets_rest_passes(tmp_path):
    from fabkit.toolpath.finish.raster import plan_toolpath

    # the bowl with a groove 4 mm wide (1/e half width 2 mm) and 12 mm deep along y in its floor
    height = f"{A}*(x**2 + y**2) - {DEPTH} - 12*exp(-(x/2)**2)"
    # a coarse finish (scallop 0.3 mm): the rest passes, not the finish, are under test
    spec, surf = load(tmp_path, bowl_raw(height=height, scallop=0.3))
    finish = plan_toolpath(spec, surf)
    ops = plan_operations(spec, surf, finish)
    assert [o.kind for o in ops] == ["rough", "rest"]
    rough, rest = ops
    assert rest.tool == finish_tool(spec)
    # the rest passes cut in the groove, below everything the roughing reached there
    rp = feed_points(rest.toolpath)
    groove = np.abs(rp[:, 0] - HALF) < 2.0
    assert groove.any()
    rough_pts = feed_points(rough.toolpath)
    near = np.abs(rough_pts[:, 0] - HALF) < 2.0
    assert rp[groove, 2].min() < rough_pts[near, 2].min() - 5.0
    # the rest ball leaves the allowance too (brute force over its disc)
    design = lambda X, Y: bowl_design(X, Y) - 12 * np.exp(-((X - HALF) / 2) ** 2)
    assert worst_allowance(rp, rest.tool, design, 100, 100, 0.5) >= -spec.machining.tolerance
    assert worst_allowance(rough_pts, rough.tool, design, 100, 100, 0.5) >= -1e-9
    # independent simulation: after rough + rest the finishing ball cuts through at most
    # its depth of cut of stock anywhere; after the rough alone it would cut more
    h = 0.5      # grid of the independent simulation (tests/test_roughing_job.py cuts rs274's moves too)
    n = int(round(100 / h)) + 1
    fb = finish_tool(spec)
    hits = []
    S = simulate(ops, n, h, hits)
    assert engagement(S, h, finish, fb) <= spec.tool.depth_of_cut + 0.05
    # no rapid move of the rough or the rest meets material (links above the level
    # above or the roughed stock's drop)
    assert max(hits) <= 1e-9, hits
    S1 = simulate([rough], n, h)
    assert engagement(S1, h, finish, fb) > spec.tool.depth_of_cut + 1.0


def test_spec_tools_and_finish_tool(tmp_path):
    tools = [{"number": 1, "shape": "flat", "diameter": "1/2 in", "reach": 70, "feed": 3000},
             {"number": 3, "shape": "bull", "diameter": 6, "corner_radius": 1, "depth_of_cut": 4}]
    spec, _ = load(tmp_path, bowl_raw(tools=tools))
    t = spec_tools(spec)
    assert set(t) == {1, 2, 3}
    assert t[1] == Tool("flat", 12.7, 0.0, reach=70.0, number=1, feed=3000.0)
    assert t[3].corner_radius == 1.0 and spec.tools[1].depth_of_cut == 4.0
    assert spec.tools[0].depth_of_cut == pytest.approx(12.7)       # default: the diameter
    assert spec.tool.depth_of_cut == pytest.approx(6.35)
    assert finish_tool(spec) == Tool.ball(6.35, reach=math.inf, number=2)
    assert spec.roughing.stepover == 6.0 and spec.roughing.rest is None
    raw = bowl_raw(roughing={"tool": 1, "stepdown": 5})
    spec2, _ = load(tmp_path, raw)
    assert spec2.roughing.stepover == pytest.approx(0.45 * 12.7)
    assert spec2.roughing.entry == "helix" and spec2.roughing.strategy == "offset"


def test_list_keys_cannot_be_overridden(tmp_path):
    spec, _ = load(tmp_path, bowl_raw())
    with pytest.raises(SpecError) as e:
        spec.with_overrides({"tools.diameter": 10})
    assert e.value.key == "tools.diameter"
    assert spec.with_overrides({"roughing.stepdown": 4}).roughing.stepdown == 4.0


def test_spec_without_roughing_is_unchanged():
    raw = yaml.safe_load((SPECS / "surface.yaml").read_text())
    spec = validate(raw, "surface.yaml")
    assert not spec.has("roughing") and not spec.has("tools")
    assert spec.tool.depth_of_cut == pytest.approx(6.35)


BAD = [
    ({"tools": [{"number": 1, "shape": "flat", "diameter": -1}]}, "tools[0].diameter", "must be > 0"),
    ({"tools": [{"number": 1, "shape": "flat", "diameter": 12}, {"number": 1, "shape": "ball", "diameter": 3}]},
     "tools[1].number", "already tools[0].number"),
    ({"tools": [{"number": 2, "shape": "flat", "diameter": 12}]}, "tools[0].number", "already tool.number"),
    ({"tools": [{"number": 1, "shape": "bull", "diameter": 6, "corner_radius": 4}]},
     "tools[0].corner_radius", "<= diameter/2"),
    ({"tools": [{"number": 1, "shape": "bull", "diameter": 6}]}, "tools[0].corner_radius", "needs"),
    ({"tools": [{"number": 1, "shape": "flat", "diameter": 12, "colour": "red"}]}, "tools[0].colour", "unknown key"),
    ({"tools": ["flat"]}, "tools[0]", "must be a mapping"),
    ({"tools": {"number": 1}}, "tools", "list of mappings"),
    ({"roughing": {"tool": 7, "stepdown": 5}}, "roughing.tool", "not in `tools`"),
    ({"roughing": {"tool": 1, "stepdown": 5, "rest": [9]}}, "roughing.rest[0]", "not in `tools`"),
    ({"roughing": {"tool": 1, "stepdown": 13}}, "roughing.stepdown", "depth_of_cut"),
    ({"roughing": {"tool": 1, "stepdown": 5, "entry": "dive"}}, "roughing.entry", "helix | ramp | plunge"),
    ({"machining": {"stepdown": 3}}, "roughing", "exclusive"),
]


@pytest.mark.parametrize("change,key,words", BAD, ids=[b[1] for b in BAD])
def test_spec_errors_one_line_exit_2(tmp_path, change, key, words):
    raw = bowl_raw()
    for sec, body in change.items():
        if isinstance(body, dict) and isinstance(raw.get(sec), dict):
            raw[sec] = {**raw[sec], **body}
        else:
            raw[sec] = body
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    with pytest.raises(SpecError) as e:
        load_spec(p)
    assert e.value.key == key and words in e.value.detail
    out_dir = tmp_path / "out"
    code, out, err = run_cli(["gcode", p, "--out", out_dir])
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and f"{p}: {key}: " in lines[0], err
    assert not out_dir.exists() or not any(out_dir.iterdir())


# ----------------------------------------------------------------------------
# every input bounded (issue 37, item 4): refused up front, naming the key
# ----------------------------------------------------------------------------
HOSTILE = [
    ({"tools": [{"number": 1, "shape": "flat", "diameter": 12.7, "spindle": 0.4}]}, "tools[0].spindle", "S0"),
    ({"tools": [{"number": 1, "shape": "flat", "diameter": 12.7, "feed": 1e-6}]}, "tools[0].feed", "F0"),
    ({"tools": [{"number": 1, "shape": "flat", "diameter": 12.7, "plunge": 1e-6}]}, "tools[0].plunge", "F0"),
    ({"roughing": {"tool": 1, "stepdown": 5, "leave": 7}}, "roughing.leave", "depth_of_cut"),
    ({"roughing": {"tool": 1, "stepdown": 5, "stepover": 1e-6}}, "roughing.stepover", "finer than"),
    ({"tool": {"shape": "ball", "diameter": 6.35}}, "tool.number", "M6"),   # no number, LinuxCNC
]


@pytest.mark.parametrize("change,key,words", HOSTILE, ids=[h[1] for h in HOSTILE])
def test_tool_and_roughing_keys_refused_up_front(tmp_path, change, key, words):
    raw = bowl_raw()
    for sec, body in change.items():
        raw[sec] = body if sec == "tool" else {**raw[sec], **body} if isinstance(body, dict) else body
    with pytest.raises(SpecError) as e:
        load(tmp_path, raw)
    assert e.value.key == key and words in e.value.detail, e.value


def _refusal(tmp_path, raw):
    from fabkit.toolpath.finish.raster import plan_estimate

    spec, surface = load(tmp_path, raw)
    with pytest.raises(SpecError) as e:
        plan_estimate(spec, surface)
    return e.value


def test_loops_beyond_the_guards_refused_before_planning(tmp_path):
    # stepover 0.001 mm on a 100 x 100 mm bowl 30 mm deep: ~1e8 mm of loops (the planner's
    # offset tree once overflowed Python's recursion on it)
    e = _refusal(tmp_path, bowl_raw(roughing={"tool": 1, "stepdown": 5, "stepover": 0.001, "leave": 0.5}))
    assert e.key == "roughing.stepover" and "mm of loops" in e.detail
    # a 0.05 mm end mill at stepover 0.02: the loops' vertices on a fine design grid (memory)
    e = _refusal(tmp_path, bowl_raw(tools=[{"number": 1, "shape": "flat", "diameter": 0.05, "depth_of_cut": 5}],
                                    roughing={"tool": 1, "stepdown": 5, "stepover": 0.02, "leave": 0.5}))
    assert e.key == "roughing.stepover", e


def test_tool_too_large_for_the_reach_search_and_too_short(tmp_path):
    e = _refusal(tmp_path, bowl_raw(tools=[{"number": 1, "shape": "flat", "diameter": 190, "depth_of_cut": 20}],
                                    roughing={"tool": 1, "stepdown": 5, "stepover": 80, "leave": 0.5}))
    assert e.key == "tools[0].diameter" and "centre-offset pairs" in e.detail
    # the bowl is 30 mm deep: a 20 mm reach cannot come within one 5 mm stepdown of 29.5 mm
    e = _refusal(tmp_path, bowl_raw(tools=[{"number": 1, "shape": "flat", "diameter": 12.7, "reach": 20}]))
    assert e.key == "tools[0].reach" and "24.5" in e.detail
    from fabkit.toolpath.finish.raster import plan_estimate

    spec, surface = load(tmp_path, bowl_raw(tools=[{"number": 1, "shape": "flat", "diameter": 12.7, "reach": 25}]))
    est = plan_estimate(spec, surface)
    # the levels' length: per level the area below it over the stepover, closed form on the
    # paraboloid (area pi (z + D - leave) / A, plus the band beyond the edges: none here)
    exact = sum(math.pi * (DEPTH - 0.5 - 5 * k) / A for k in range(1, 6)) / 6
    assert est["rough_levels"] == 5 and est["rough_length_mm"] == pytest.approx(exact, rel=0.03)


def test_offset_tree_walked_without_recursion():
    from fabkit.toolpath.rough.roughing import _post_order, _pre_order

    class N:
        def __init__(self, i):
            self.i, self.children = i, []

    root = N(0)
    node = root
    for i in range(1, 20000):        # deeper than Python's recursion limit
        ch = N(i)
        node.children.append(ch)
        node.children.append(N(-i))
        node = ch
    post = [n.i for n in _post_order(root)]
    pre = [n.i for n in _pre_order(root)]
    assert len(post) == len(pre) == 39999
    assert pre[:4] == [0, 1, 2, 3] and post[0] == 19999 and post[-1] == 0
    assert post.index(-1) > post.index(1) and pre.index(-1) > pre.index(19999)


def test_level_cleared_region_by_pocket_fill_equals_the_discs():
    """_Level's region from the loops' bounded region (stepover well inside the disc) is the
    union of every loop's disc (shapely's own buffer of all the lines)."""
    import shapely
    from shapely.geometry import Polygon, box
    from fabkit.toolpath.rough.roughing import _erosion_tree, _Level, _pre_order, _ring_region

    P = Polygon([(0, 0), (40, 0), (40, 25), (22, 25), (22, 12), (16, 12), (16, 25), (0, 25)]).difference(
        box(5, 5, 9, 9))
    s, simp = 2.0, 0.01
    tree = _erosion_tree(P, s, simp)
    lines = [r for n in _pre_order(tree) for r in n.rings]
    tool = Tool("flat", 12.7)
    out = box(-100, -100, 200, 200).difference(box(0, 0, 40, 25))
    fast = _Level(-1.0, [], tool, out, 0.01, 1.0, [(_ring_region(P, simp), lines)], s, simp)
    slow = shapely.multilinestrings([shapely.linestrings(r) for r in lines]).buffer(6.35, quad_segs=32)
    assert fast.cleared.symmetric_difference(slow).area < 1e-3 * slow.area


def test_kernels_in_chunks_give_the_same_stock(monkeypatch):
    from fabkit.toolpath.cut import stock as st

    s0 = st.make_stock(20.0, 12.0, 0.25)
    X, Y = s0.grid()
    target = -0.05 * (X - 10) ** 2 - 2.0
    tool = Tool("bull", 6.0, 1.5)
    pts = np.array([[1, 1, 1], [1, 1, -2], [18, 3, -2.5], [18, 9, -1], [3, 10, -3], [3, 10, 5]], float)
    kinds = np.array([RAPID, PLUNGE, CUT, CUT, CUT, RAPID], np.int8)
    a, b = s0.copy(), s0.copy()
    ra = st.cut(a, tool, pts, kinds)
    mask = target < -2.5
    ha = st.reach_height(target, a, tool, mask)
    monkeypatch.setattr(st, "KERNEL_CHUNK_WORK", 500.0)       # many small calls
    rb = st.cut(b, tool, pts, kinds)
    hb = st.reach_height(target, b, tool, mask)
    assert np.array_equal(a.z, b.z) and np.array_equal(ra.engagement, rb.engagement)
    assert np.array_equal(ha, hb, equal_nan=True)


@pytest.mark.parametrize("dialect", ["linuxcnc", "grbl"])
def test_sheet_names_each_tool_its_number_offset_and_touch_off(dialect):
    from types import SimpleNamespace

    from fabkit.toolpath.program.setup_sheet import _operations_keys, _tool_line

    def fig(kind, n, shape, d, prog):
        js = {"kind": kind, "tool": {"number": n, "shape": shape, "diameter": d}}
        return SimpleNamespace(program=prog, to_json=lambda k, js=js: dict(js))

    progs = ("", "", "") if dialect == "linuxcnc" else (".1-rough.nc", ".2-rest.nc", ".3-finish.nc")
    figs = [fig("rough", 1, "flat", 12.7, progs[0]), fig("rest", 2, "ball", 6.35, progs[1]),
            fig("finish", 2, "ball", 6.35, progs[2])]
    keys = _operations_keys(figs, "job.ngc", dialect, 1.0, None)
    first, second = keys["tools_loaded"]
    assert (first["number"], first["operations"]) == (1, ["rough"])
    assert (second["number"], second["operations"]) == (2, ["rest", "finish"])
    if dialect == "linuxcnc":
        assert _tool_line(first, dialect).endswith("the program calls T1 M6 G43 H1 (tool change and length offset)")
        assert "T2 M6 G43 H2" in _tool_line(second, dialect) and "H2" in keys["steps"][1]
    else:
        assert first["programs"] == ["job.1-rough.nc"] and "before running job.1-rough.nc" in _tool_line(first, dialect)
        assert second["programs"] == ["job.2-rest.nc", "job.3-finish.nc"]
        assert "touch off Z0" in _tool_line(second, dialect) and first["tool_call"] is None


def test_wall_meeting_the_stock_edge_is_roughed_from_beyond_it(tmp_path):
    """A 90-degree V trench along x, 8 mm deep, under an 8 mm flat end mill (stepdown 3,
    leave 0.4): inside the block the tool reaches only -3 (its disc touches the walls
    + leave there); at the block's ends it stands beyond the stock, where the level -6
    lets its centre within R of the trench's bottom: exactly where hypot(x, 1.6) >= 4
    (K(-6) = {|y - 10| > 1.6}), so the end faces are cut to -6 within 1.59 mm of y = 10."""
    raw = bowl_raw(height="-8 + abs(y - 10)",
                   tools=[{"number": 1, "shape": "flat", "diameter": 8, "reach": 40, "depth_of_cut": 8}],
                   roughing={"tool": 1, "stepdown": 3, "stepover": 3.5, "leave": 0.4})
    raw["surface"].update(x=[0, 20], y=[0, 20])
    spec, surf = load(tmp_path, raw)
    op = plan_rough(spec, surf)
    # the kink's interpolation bound takes the level step down a little (the bound held strictly)
    z1, z2 = op.info["level_z_mm"]
    assert z2 == pytest.approx(2 * z1, abs=1e-3) and -3.0 <= z1 <= -2.9
    h, n = 0.5, 41
    S = simulate([op], n, h)
    y = np.arange(n) * h
    D = np.minimum(-8 + np.abs(y - 10), 0.0)
    # the allowance kept everywhere (tolerance 0.01)
    assert (S - np.minimum(D[:, None] + 0.4, 0.0) >= -0.01 - 1e-9).all()
    mid = np.abs(y - 10) <= 1.5
    for j in (0, n - 1):                     # the two end faces, x = 0 and x = 20
        assert np.allclose(S[mid, j], z2, atol=1e-4), S[mid, j]
    assert np.allclose(S[mid, 4], z1, atol=1e-4)        # 2 mm in: the first level


def test_finish_reach_only_as_far_beyond_the_edge_as_its_passes():
    """A ball of R 3 mm over a 90-degree V's bottom at the block's end: standing wholly
    beyond the end (up to R out) it reaches the bottom; up to 2.9 mm out (a grid node:
    centres stand on nodes) its section at the end face has radius sqrt(9 - 2.9^2) =
    0.768 mm and stays 0.768 (sqrt(2) - 1) = 0.318 mm above the bottom."""
    from fabkit.toolpath.cut import stock as st

    s0 = st.make_stock(6.0, 6.0, 0.1)
    X, Y = s0.grid()
    target = -3.0 + np.abs(Y - 3.0)
    mask = np.zeros(target.shape, bool)
    mask[0, 30] = True                       # x = 0, y = 3: the bottom at the end face
    ball = Tool.ball(6.0)
    full = st.reach_height(target, s0, ball, mask)[0, 30] + 3.0
    part = st.reach_height(target, s0, ball, mask, beyond=2.9 + 1e-9)[0, 30] + 3.0
    assert full == pytest.approx(0.0, abs=1e-9)
    assert part == pytest.approx(math.sqrt(9 - 2.9 ** 2) * (math.sqrt(2) - 1), abs=0.005), part


def test_flat_rest_tool_stands_on_the_design_from_above(tmp_path):
    """A rest flat end mill's tip on the bowl H = A rho^2 - D: exactly A (rho + r)^2 - D
    (its disc's highest point, on its rim away from the axis); the grid bound is never
    below it and at most the slope x a cell's diagonal + 2 e above it."""
    from fabkit.toolpath.rough.roughing_rest import _tool_on_design

    spec, surf = load(tmp_path, bowl_raw())
    op = plan_rough(spec, surf)
    r = 2.0
    rho = np.linspace(0.0, 40.0, 41)
    X, Y = HALF + rho * math.cos(0.3), HALF + rho * math.sin(0.3)
    got = _tool_on_design(op, X, Y, Tool("flat", 2 * r))
    exact = np.minimum(A * (rho + r) ** 2 - DEPTH, 0.0)
    sets = op.sets
    diag = math.hypot(sets.hx, sets.hy)
    slope = 2 * A * (rho + r + 2 * diag)
    assert (got >= exact - 1e-9).all()
    assert (got - exact <= slope * 2 * diag + 2 * sets.err + 1e-9).all(), float((got - exact).max())


def test_last_rest_tool_larger_than_the_finish_refused(tmp_path):
    raw = bowl_raw(tools=[{"number": 1, "shape": "flat", "diameter": 12.7, "reach": 60},
                          {"number": 3, "shape": "bull", "diameter": 8, "corner_radius": 1}],
                   roughing={"tool": 1, "stepdown": 5, "rest": [3]})
    with pytest.raises(SpecError) as e:
        load(tmp_path, raw)
    assert e.value.key == "roughing.rest[0]" and "larger than the finishing" in e.value.detail
    raw["roughing"]["rest"] = [3, 2]
    spec, _ = load(tmp_path, raw)
    assert spec.roughing.rest == (3, 2)


def test_rest_drop_distance_near_the_levels_equals_shapely_to_the_bit():
    """The rest passes' drop onto the levels takes the distance to the uncut region from
    a compiled kernel over the edges near each point: it equals shapely's (GEOS's)
    distance to the bit wherever that is within the cap, and is +inf beyond, on a
    polygon with a hole and a second part, points inside, outside, on edges and
    vertices, at the cap exactly, and on a fine polygon of many edges."""
    import shapely
    from shapely.geometry import MultiPolygon, Point, Polygon

    from fabkit.toolpath.rough.roughing_rest import _distance_near

    rng = np.random.default_rng(3)
    U1 = MultiPolygon([Polygon([(0, 0), (10, 0), (10, 6), (0, 6)], [[(3, 2), (7, 2), (7, 4), (3, 4)]]),
                       Polygon([(20, 0), (24, 3), (20, 6)])])
    U2 = Point(5.3, 4.1).buffer(3.7, quad_segs=64).difference(Point(6.1, 4.4).buffer(1.2, quad_segs=32))
    cap = 1.5
    for U in (U1, U2):
        lo, hi = np.array(U.bounds[:2]) - 4, np.array(U.bounds[2:]) + 4
        xy = np.vstack([rng.uniform(lo, hi, size=(4000, 2)), np.asarray(U.boundary.geoms[0].coords)[:5],
                        [[5, 3], [5, 2], [-cap, 3], [10 + cap, 3], [5, 2 + cap], [22, 3]]])
        ref = shapely.distance(shapely.points(xy), U)
        got = _distance_near(U, xy[:, 0], xy[:, 1], cap)
        near = ref <= cap
        assert near.sum() > 500 and (~near).sum() > 500
        assert np.array_equal(got[near], ref[near])
        assert np.isinf(got[~near]).all()


def test_cut_lines_added_at_once_equal_point_by_point():
    """A level's cut lines added as arrays give the points and kinds that adding them
    one by one gives (a point repeating the one before it within 1e-9 mm dropped)."""
    from fabkit.toolpath.rough.roughing_loops import _Path

    rng = np.random.default_rng(5)
    lines = [rng.normal(size=(7, 2)), np.array([[0.0, 0.0], [0.0, 5e-10], [1.0, 1.0]]),
             np.array([[1.0, 1.0], [2.0, 2.0]]), np.array([[2.0, 2.0 + 1e-10]]), rng.normal(size=(3, 2))]
    a, b = _Path(), _Path()
    a.add((9.0, 9.0, -1.0), RAPID)
    b.add((9.0, 9.0, -1.0), RAPID)
    for ln in lines:
        a.cut_xy(ln, -1.0)
        for q in ln:
            b.add((q[0], q[1], -1.0), CUT)
    assert a.pts == b.pts and a.kinds == b.kinds
    assert len(a.level_lines) == 4


# --------------------------------------------------------------------------
# the loops' simplification (roughing_loops._simplify): GEOS's plain Douglas-Peucker
# where it keeps every ring valid, else the topology-preserving one
# --------------------------------------------------------------------------
def _blobs(rng):
    from shapely.geometry import Point
    from shapely.ops import unary_union

    disks = [Point(rng.uniform(0, 50, 2)).buffer(rng.uniform(2, 12), quad_segs=int(rng.integers(4, 40)))
             for _ in range(int(rng.integers(2, 9)))]
    holes = [Point(rng.uniform(0, 50, 2)).buffer(rng.uniform(0.5, 5), quad_segs=int(rng.integers(4, 40)))
             for _ in range(int(rng.integers(0, 6)))]
    P = unary_union(disks)
    return P.difference(unary_union(holes)) if holes else P


def test_loop_simplification_is_the_topology_preserving_one_to_the_bit():
    """On 120 random unions of discs less discs (islands), eroded as the loops are and
    simplified within 0.99 x the erosion (0.001-0.3 mm): the fast path gives GEOS's
    topology-preserving result exactly (every coordinate, every ring's start), valid,
    with every ring."""
    from fabkit.toolpath.rough.roughing_loops import QUAD_SEGS, _polys, _simplify

    rng = np.random.default_rng(7)
    n = 0
    for _ in range(120):
        P = _blobs(rng)
        s = float(rng.choice([0.001, 0.01, 0.05, 0.3]))
        for q in _polys(P.buffer(-s, quad_segs=QUAD_SEGS)):
            a = q.simplify(0.99 * s, preserve_topology=True)
            b = _simplify(q, 0.99 * s)
            assert b.is_valid and len(b.interiors) == len(q.interiors)
            assert a.equals_exact(b, 0.0)
            n += 1
    assert n > 300


def test_loop_simplification_falls_back_where_a_chord_would_cross_an_island():
    """A hole 0.2 mm inside a finely drawn circle's edge, simplified within 0.5 mm: the
    plain simplifier's chords cut across the hole (an invalid polygon); the result is the
    topology-preserving one, valid, with the hole."""
    from shapely.geometry import Point, Polygon

    from fabkit.toolpath.rough.roughing_loops import _simplify

    outer = Point(0, 0).buffer(10.0, quad_segs=256)
    hole = Point(9.5, 0.0).buffer(0.3, quad_segs=16)
    q = Polygon(outer.exterior.coords, [hole.exterior.coords])
    assert q.is_valid
    plain = q.simplify(0.5, preserve_topology=False)
    assert not (plain.is_valid and len(plain.interiors) == 1)       # the case is a real one
    b = _simplify(q, 0.5)
    assert b.is_valid and len(b.interiors) == 1
    assert b.equals_exact(q.simplify(0.5, preserve_topology=True), 0.0)


def test_band_slope_is_numpys_gradient_to_the_bit():
    """roughing._band_slope's compiled pass against numpy.gradient + hypot over the band
    (the expression it replaces), on rough random grids with non-finite nodes, both
    spacings unequal, grids down to 2 x 2."""
    from types import SimpleNamespace

    from fabkit.toolpath.rough.roughing import _band_slope

    rng = np.random.default_rng(3)
    seen = set()
    for shape, scale in [((2, 2), 1.0), ((2, 9), 0.1), ((7, 3), 1.0), ((301, 173), 1.0), ((301, 173), 0.01)]:
        H = scale * np.cumsum(rng.normal(size=shape) * rng.choice([1e-3, 1.0, 30.0], size=shape), axis=0) - 5.0
        H[rng.random(shape) < 0.02] = np.nan
        hy, hx = 0.2498, 0.3117
        gy, gx = np.gradient(H, hy, hx)
        for low in (-1e9, -8.0, -2.0):
            band = (H >= low) & (H <= 0.0) & np.isfinite(gx) & np.isfinite(gy)
            want = float(min(20.0, np.hypot(gx, gy)[band].max())) if band.any() else 0.0
            assert _band_slope(SimpleNamespace(H=H, hx=hx, hy=hy), low) == want
            seen.add(want == 20.0)
    assert seen == {True, False}          # both the cap and slopes under it


def test_drop_grid_stops_early_with_the_same_maximum():
    """stock_kernels.drop_grid with the blocks' bound (offsets by rising lift, the search
    stopped once no block can beat the best) against the full search, on rough random
    stocks (terraces, spikes, nan and inf nodes) and positions inside, at the edges and
    beyond the grid, for a ball's, a bull nose's and a flat end's lifts."""
    from fabkit.toolpath.cut.stock_kernels import drop_grid

    rng = np.random.default_rng(17)
    for trial in range(12):
        ny, nx = int(rng.integers(5, 90)), int(rng.integers(5, 90))
        S = -np.round(rng.uniform(0, 4, (ny, nx))) * 5.0 + rng.normal(scale=0.3, size=(ny, nx))
        S[rng.random(S.shape) < 0.01] = 8.0
        if trial % 4 == 1:
            S[rng.random(S.shape) < 0.01] = np.nan
        if trial % 4 == 2:
            S[rng.random(S.shape) < 0.01] = np.inf
        h = 0.25
        ni = nj = int(rng.integers(2, 14))
        di, dj = np.meshgrid(np.arange(-ni, ni + 1), np.arange(-nj, nj + 1), indexing="ij")
        rho = np.hypot(di * h, dj * h)
        R = ni * h
        ok = rho <= R
        shape = trial % 3
        r = R if shape == 0 else (0.4 * R if shape == 1 else 0.0)
        f = R - r
        u = np.clip(rho[ok] - f, 0.0, None)
        lift = np.where(u > 0, r - np.sqrt(np.maximum(r * r - u * u, 0.0)), 0.0) if r > 0 else np.zeros(ok.sum())
        di, dj = di[ok], dj[ok]
        order = np.argsort(lift, kind="stable")
        di, dj, lift = (np.ascontiguousarray(di[order], np.int64), np.ascontiguousarray(dj[order], np.int64),
                        np.ascontiguousarray(lift[order]))
        X = rng.uniform(-3 * R, nx * h + 3 * R, 400)
        Y = rng.uniform(-3 * R, ny * h + 3 * R, 400)
        bs = max(1, ni)
        pad = np.full((-(-ny // bs) * bs, -(-nx // bs) * bs), -np.inf)
        pad[:ny, :nx] = np.where(np.isnan(S), -np.inf, S)
        bmax = np.ascontiguousarray(pad.reshape(pad.shape[0] // bs, bs, pad.shape[1] // bs, bs).max(axis=(1, 3)))
        fast, full = np.full(400, -np.inf), np.full(400, -np.inf)
        drop_grid(S, h, h, X, Y, di, dj, lift, fast, bmax, bs, ni, nj)
        drop_grid(S, h, h, X, Y, di, dj, lift, full, np.empty((0, 0)), 1, 0, 0)
        assert np.array_equal(fast, full, equal_nan=True)


def test_block_max_leaves_nan_out():
    """stock_kernels.block_max against numpy's block reduction (nan as -inf), partial
    last blocks included."""
    from fabkit.toolpath.cut.stock_kernels import block_max

    rng = np.random.default_rng(2)
    for ny, nx, bs in [(5, 7, 2), (40, 33, 6), (12, 12, 12), (3, 50, 7)]:
        S = rng.normal(size=(ny, nx))
        S[rng.random(S.shape) < 0.1] = np.nan
        pad = np.full((-(-ny // bs) * bs, -(-nx // bs) * bs), -np.inf)
        pad[:ny, :nx] = np.where(np.isnan(S), -np.inf, S)
        want = pad.reshape(pad.shape[0] // bs, bs, pad.shape[1] // bs, bs).max(axis=(1, 3))
        assert np.array_equal(block_max(S, bs), want)


def test_curvature_bounds_are_the_array_expressions_to_the_bit():
    """stock_kernels.curvature_bounds (roughing.LevelSets' second differences) against the
    whole-grid numpy expressions it replaces, on rough random designs with nodes in and out
    of the band, unequal spacings, grids down to 3 x 3, and a band no node lies in."""
    from fabkit.toolpath.cut.stock_kernels import curvature_bounds

    rng = np.random.default_rng(23)
    for ny, nx in [(3, 3), (4, 9), (57, 31), (200, 150)]:
        H = np.cumsum(rng.normal(size=(ny, nx)) * rng.choice([0.01, 1.0, 20.0], size=(ny, nx)), axis=1) - 10.0
        hx, hy = 0.3117, 0.2498
        for lo, hi in [(-12.0, 0.0), (-1e9, 1e9), (1e5, 2e5)]:
            rel = (H >= lo) & (H <= hi)
            hxx = np.abs(H[:, 2:] - 2 * H[:, 1:-1] + H[:, :-2]) / hx ** 2
            hyy = np.abs(H[2:, :] - 2 * H[1:-1, :] + H[:-2, :]) / hy ** 2
            hxy = np.abs(H[1:, 1:] - H[1:, :-1] - H[:-1, 1:] + H[:-1, :-1]) / (hx * hy)
            want = [float(a[m].max()) if m.any() else -1.0
                    for a, m in ((hxx, rel[:, 1:-1]), (hyy, rel[1:-1, :]), (hxy, rel[1:, 1:]))]
            assert list(curvature_bounds(H, lo, hi, hx ** 2, hy ** 2, hx * hy)) == want
