"""Raster planning: slope-aware stepover, chord tolerance, air, edges, links, guards."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fabkit.errors import SpecError
from fabkit.spec import load_spec, validate
from fabkit.surface import Surface
from fabkit.toolpath.finish.compensate import compensate
from fabkit.toolpath.path import CUT, PLUNGE, RAPID
from fabkit.toolpath.finish.raster import (LINK_CLEARANCE, flat_stepover, plan_toolpath,
                                           tilted_plane_cusp)

from conftest import PAPER, mutated

R = 3.175
DIMPLE = "0.004*(x-30)**2 + 0.006*(y-20)**2 - 6"     # a bowl reaching the top near the corners


def _spec(height, machining=None, tool=None, stock=None, x=(0, 60), y=(0, 40)):
    raw = {"name": "t", "units": "mm",
           "surface": {"height": height, "x": list(x), "y": list(y), "top": 0.0},
           "stock": {"thickness": 40, **(stock or {})},
           "tool": {"diameter": 2 * R, **(tool or {})},
           "machining": {"scallop": 0.05, "tolerance": 0.01, **(machining or {})}}
    spec = validate(raw, "t.yaml")
    return spec, Surface.from_spec(spec)


@pytest.fixture(scope="module")
def dimple():
    spec, surf = _spec(DIMPLE)
    return spec, surf, plan_toolpath(spec, surf)


def _cut_runs(tp):
    """Consecutive CUT moves as polylines (n, 3)."""
    runs, cur = [], []
    for i in range(1, len(tp)):
        if tp.kinds[i] == CUT:
            if not cur:
                cur = [tp.points[i - 1]]
            cur.append(tp.points[i])
        elif cur:
            runs.append(np.array(cur))
            cur = []
    if cur:
        runs.append(np.array(cur))
    return runs


@pytest.mark.parametrize("measure", ["vertical", "normal"])
def test_tilted_plane_stepover_matches_closed_form(measure):
    m = 0.7                                   # slope across the passes (direction x: across = y)
    spec, surf = _spec(f"{m}*y - 32", y=(0, 40), machining={"scallop_measure": measure})
    normal = measure == "normal"
    tp = plan_toolpath(spec, surf)
    theta = math.atan(m)
    v = np.array(tp.info["pass_positions"])
    # the cusp between two passes lies midway between their contacts, R sin(theta) uphill;
    # those inside the stock count (beyond the edge there is nothing to leave)
    cusp_at = 0.5 * (v[1:] + v[:-1]) + R * math.sin(theta)
    steps = np.diff(v)[(cusp_at > 0) & (cusp_at < 40)]
    # largest stepover allowed by the closed-form vertical cusp (bisection)
    lo, hi = 0.0, 2 * R * math.cos(theta)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if tilted_plane_cusp(R, mid, theta, normal) <= 0.05 else (lo, mid)
    s_max = lo
    assert steps.size > 5
    for s in steps:
        assert tilted_plane_cusp(R, s, theta, normal) <= 0.05 + 1e-9
        assert s >= 0.8 * s_max
    assert steps.max() < flat_stepover(R, 0.05)   # the wall needs a smaller stepover than flat ground


def test_tilted_plane_cusp_closed_forms():
    """Normal cusp: two balls whose centres are s / cos(theta) apart along the offset
    plane; the vertical one is 1 / cos(theta) times that (flat: the same)."""
    s, theta = 1.2, math.atan(3.0)
    d = s / math.cos(theta)
    normal = R - math.sqrt(R * R - d * d / 4)
    assert tilted_plane_cusp(R, s, theta, True) == pytest.approx(normal, rel=1e-12)
    assert tilted_plane_cusp(R, s, theta) == pytest.approx(normal * math.sqrt(10.0), rel=1e-12)
    assert tilted_plane_cusp(R, s, 0.0) == pytest.approx(R - math.sqrt(R * R - s * s / 4), rel=1e-12)


@pytest.mark.parametrize("slope", [4.0, 8.0])
def test_passes_along_a_steep_plane_need_no_more_than_flat_ground(slope):
    """Passes running up a plane of slope 4 or 8 (direction x, the slope along x): the
    cross-section across the passes is flat, so the scallop measured on the slope (normal
    to it) needs the flat stepover; measured vertically it would need sqrt(1 + slope^2)
    times the cusp, about 2.9x the passes at slope 8."""
    y = (0, 30)
    spec, surf = _spec(f"{slope}*x - 30", x=(0, 12), y=y)
    flat_spec, flat_surf = _spec("0*x - 5", x=(0, 12), y=y)
    tp, flat = plan_toolpath(spec, surf), plan_toolpath(flat_spec, flat_surf)
    # the flat-ground count: the width over the flat stepover at 0.95 scallop, plus the edges
    s_flat = flat_stepover(R, 0.95 * 0.05)
    assert flat.passes <= math.ceil(30 / s_flat) + 3
    assert tp.passes <= flat.passes
    vspec, vsurf = _spec(f"{slope}*x - 30", x=(0, 12), y=y, machining={"scallop_measure": "vertical"})
    assert plan_toolpath(vspec, vsurf).passes >= 1.5 * tp.passes


def test_chord_error_within_tolerance(dimple):
    spec, surf, tp = dimple
    worst = 0.0
    for run in _cut_runs(tp):
        a, b = run[:-1], run[1:]
        # program segments between points on the path (links at clearance left out)
        za = compensate(surf, a[:, 0], a[:, 1], R)
        zb = compensate(surf, b[:, 0], b[:, 1], R)
        on = (np.abs(a[:, 2] - za) < 1e-9) & (np.abs(b[:, 2] - zb) < 1e-9)
        a, b = a[on], b[on]
        t = np.linspace(0, 1, 9)[1:-1]
        P = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
        Z = compensate(surf, P[..., 0], P[..., 1], R)
        worst = max(worst, float(np.abs(P[..., 2] - Z).max(initial=0.0)))
    assert worst <= spec.machining.tolerance


def test_no_air_segments_and_safe_rapids(dimple):
    spec, surf, tp = dimple
    P, K = tp.points, tp.kinds
    for i in range(1, len(P)):
        a, b = P[i - 1], P[i]
        if K[i] == CUT and abs(a[2] - b[2]) < 1e-12 and np.hypot(*(b - a)[:2]) > 1e-9:
            # a horizontal feed at one height: either below the top face (cutting) or a link
            # above the material checked along its length
            z = compensate(surf, np.linspace(a[0], b[0], 20), np.linspace(a[1], b[1], 20), R)
            assert a[2] < -1e-9 or np.all(a[2] >= z + 0.5)
        if K[i] == RAPID:
            moved = np.hypot(*(b - a)[:2]) > 1e-9
            if moved:
                # across at the safe height, or a short lift over the top face (at least
                # the link clearance above it: no material above the top face)
                assert min(a[2], b[2]) >= min(tp.safe_z, LINK_CLEARANCE) - 1e-9
            elif b[2] < a[2]:
                assert b[2] > 0                       # rapids down stop above the top face
        if K[i] == PLUNGE:
            assert b[2] <= a[2]
    # every cut run touches material: some point strictly below the top face
    for run in _cut_runs(tp):
        assert run[:, 2].min() < -1e-7


def test_passes_reach_the_footprint_edges(dimple):
    spec, surf, tp = dimple
    L, W = surf.stock_size_mm
    v = np.array(tp.info["pass_positions"])
    assert v.min() <= 0 and v.max() >= W
    cut = tp.points[tp.kinds == CUT]
    for vv in v:
        on = np.abs(cut[:, 1] - vv) < 1e-9
        x0, y0 = surf.from_work(0.0, vv)
        # (where the design at the edge lies within the scallop of the top face, the ball
        # there cuts air within the program's resolution and the run may end short of it:
        # at most that much material is left, which the scallop allows)
        if on.any() and 0 <= vv <= W and surf.height(x0, y0) < surf.top - spec.machining.scallop:
            assert cut[on, 0].min() <= 0 and cut[on, 0].max() >= L


def test_deterministic_and_direction_y_one_way():
    spec, surf = _spec(DIMPLE, machining={"direction": "y", "pattern": "climb", "scallop": 0.2,
                                          "tolerance": 0.03})
    a, b = plan_toolpath(spec, surf), plan_toolpath(spec, surf)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.kinds, b.kinds)
    # one-way: every cut run moves the same way along y (climb with M3, passes stepping +x)
    runs = [r for r in _cut_runs(a) if np.ptp(r[:, 1]) > 1e-6]    # cutting runs along y
    assert len(runs) > 10
    for run in runs:
        assert np.all(np.diff(run[:, 1]) <= 1e-9)


def test_guards_name_the_keys():
    spec, surf = _spec(DIMPLE, machining={"scallop": 1e-9}, x=(0, 5000), y=(0, 4000))
    with pytest.raises(SpecError) as e:
        plan_toolpath(spec, surf)
    assert "machining.scallop" in str(e.value)
    spec, surf = _spec(DIMPLE, machining={"tolerance": 2e-5, "scallop": 2.0}, x=(0, 3000))
    with pytest.raises(SpecError) as e:
        plan_toolpath(spec, surf)
    assert "machining.tolerance" in str(e.value)
    spec, surf = _spec(DIMPLE, machining={"scallop": 0.5, "tolerance": 0.05}, tool={"reach": 4})
    with pytest.raises(SpecError) as e:
        plan_toolpath(spec, surf)
    assert "tool.reach" in str(e.value)


@pytest.mark.parametrize("machining", [{"scallop": 1e-6}, {"scallop": 1e-4},
                                       {"stepdown": 0.001, "scallop": 0.5}])
def test_tiny_scallop_or_stepdown_refused_before_any_planning(monkeypatch, machining):
    """The guards refuse from the spec's estimates alone: no pass is placed and no tip
    height computed (either would fail here), so the refusal costs what the estimate does."""
    from fabkit.toolpath.finish import passes, raster

    def never(*a, **k):
        raise AssertionError("planning started before the guards refused")

    monkeypatch.setattr(raster, "place_passes", never)
    monkeypatch.setattr(passes, "compensate", never)
    monkeypatch.setattr(raster, "rough_runs", never)
    with pytest.raises(SpecError) as e:      # by the spec's own check or the planner's guards
        spec, surf = _spec(DIMPLE, machining=machining, x=(0, 300), y=(0, 200))
        plan_toolpath(spec, surf)
    key = "machining.stepdown" if "stepdown" in machining else "machining.scallop"
    assert key in str(e.value) and ("limit" in str(e.value) or ">=" in str(e.value))


def test_paper_surface_coarse_scallop():
    spec = load_spec(PAPER).with_overrides({"machining.scallop": 0.4, "machining.tolerance": 0.05})
    surf = Surface.from_spec(spec)
    tp = plan_toolpath(spec, surf)
    L, W = surf.stock_size_mm
    assert tp.passes > 0
    assert tp.stepover <= flat_stepover(R, 0.4) + 1e-12
    assert tp.stepover_min < tp.stepover            # steeper walls: smaller stepover
    assert -tp.points[:, 2].min() <= spec.stock.depth_limit
    cut = tp.points[tp.kinds == CUT]
    # the open end (x = -44, the channel below the top face) is milled to the edge and from
    # beyond it; the far end (x = 6) lies above the top face everywhere: no move goes there
    assert cut[:, 0].min() <= 0
    far = surf.height(np.full(101, 6.0), np.linspace(-12.5, 12.5, 101)) - surf.top
    assert (far > 0).all() and cut[:, 0].max() < L


def test_roughing_levels_leave_stock_above_the_finish_path():
    spec, surf = _spec(DIMPLE, machining={"stepdown": 2.0, "leave": 0.5, "scallop": 0.2,
                                          "tolerance": 0.03})
    tp = plan_toolpath(spec, surf)
    assert tp.info["roughing_runs"] > 0
    P = tp.points[tp.kinds == CUT]
    Z = compensate(surf, P[:, 0], P[:, 1], R)
    assert np.all(P[:, 2] >= Z - spec.machining.tolerance)       # nothing below the finish path
    for level in (-2.0, -4.0):
        at = np.abs(P[:, 2] - level) < 1e-12
        assert at.sum() > 10
        assert np.all(P[at, 2] - Z[at] >= 0.5 - 1e-9)             # the stock to leave


def test_open_edges_do_not_gouge_at_a_fine_tolerance():
    """Beyond the stock the tip height has a vertical tangent where the ball's equator
    touches the edge (u = -R); a pass node there gouged the edge by ~7 um whatever the
    tolerance. Now the verified gouge of the paper's open end stays within 0.004 mm."""
    from fabkit.toolpath.program.gcode import profile_from_spec, write_program
    from fabkit.toolpath.program.reader import read_program
    from fabkit.toolpath.cut.verify import verify_cut

    spec = load_spec(PAPER).with_overrides({"machining.tolerance": 0.004, "machining.scallop": 0.1,
                                            "surface.x": [-44, -36], "surface.y": [-4, 4],
                                            "simulation.start": -40})
    surf = Surface.from_spec(spec)
    tp = plan_toolpath(spec, surf)
    prog = read_program(write_program(tp, profile_from_spec(spec, surf)))
    c = verify_cut(surf, prog, R, 40000)
    assert c["max_gouge"] <= 0.004
    assert c["max_material_left"] <= 0.1 + 0.004
    # the pass nodes beyond the stock stay short of the equator contact (at most 0.99 R out:
    # a steep foot at the edge is reached only from there)
    cut = tp.points[tp.kinds == CUT]
    assert cut[:, 0].min() >= -R * 0.99 - 1e-9


BOWL = "0.1*x + 0.004*y**2 - 18*exp(-(x**2 + y**2)/(2*25**2))"


def test_estimated_passes_match_the_closed_form_on_flat_ground_and_the_planner():
    """Flat ground: the estimate is Lv / flat stepover (+2 for the edge passes), and the
    planner places about as many. On a plane of slope 4 along the passes and on a V
    crease the passes cross, the estimate is within x2 of the planner's count."""
    from fabkit.toolpath.finish.raster import plan_estimate
    spec, surf = _spec("-2 + 0*x", machining={"direction": "x"}, x=(0, 12), y=(0, 9))
    s = flat_stepover(R, 0.95 * 0.05)
    est = plan_estimate(spec, surf)
    assert est["passes"] == pytest.approx(9.0 / s + 2.0, rel=1e-9)
    tp = plan_toolpath(spec, surf)
    assert 0.5 <= est["passes"] / tp.passes <= 2.0
    for height, x in (("4*x - 12", (0, 4)), ("3*abs(x) - 9", (-4, 4))):
        spec, surf = _spec(height, machining={"direction": "x"}, tool={"diameter": 3.175},
                           x=x, y=(0, 6))
        tp = plan_toolpath(spec, surf)
        # the estimate is of the passes placed across; the comb hanging off the edges where
        # the V crease runs off them (80 short passes per edge) comes on top
        placed = tp.passes - tp.info["edge_comb_passes"]
        assert 0.5 <= tp.info["estimate"]["passes"] / placed <= 2.0, height
        assert tp.info["edge_comb_passes"] <= (160 if "abs" in height else 0)


def test_near_flat_bowl_plans_close_to_the_flat_pass_count():
    """A near-flat bowl rising toward the stock edge the passes run off (y = 10): every
    ball beyond that edge touches it, and the contact curve once took the ball a radius
    out (its equator) for the pass's, so the material bound sampled the edge column
    ahead of the next pass (~0.01 mm whatever the stepover): 334 passes at the smallest
    stepover instead of ~40."""
    spec, surf = _spec(BOWL, machining={"scallop": 0.005, "direction": "y"},
                       tool={"diameter": 3.175}, x=(-30, -22), y=(4, 10))
    tp = plan_toolpath(spec, surf)
    flat = 8.0 / flat_stepover(1.5875, 0.95 * 0.005)
    assert tp.passes <= 1.5 * flat
    assert tp.info["stepover_min"] >= 0.5 * tp.info["stepover_flat"]
    assert tp.info.get("unreachable_bound_mm", 0.0) < 0.25 * 0.005


def test_tiny_scallop_refused_by_the_cli_before_planning(cli, tmp_path, monkeypatch):
    """A scallop of 0.1 um (the finest the guards take) on a 160 x 200 mm bowl (~4800
    passes, about 80 s of CPU estimated: over the 60 s budget) is refused from the
    estimate: exit 2, one line naming machining.scallop and the estimate, nothing
    planned, nothing written. (On 160 x 100 mm it is estimated at 53 s and runs; at
    0.5 um there it is 1 826 passes and 24 s.)"""
    from conftest import write_spec
    from fabkit.toolpath.finish import passes, raster

    def never(*a, **k):
        raise AssertionError("planning started before the guards refused")

    monkeypatch.setattr(raster, "place_passes", never)
    monkeypatch.setattr(passes, "compensate", never)
    raw = {"name": "b", "units": "mm",
           "surface": {"height": BOWL, "x": [-80, 80], "y": [-100, 100], "top": 0.0},
           "stock": {"thickness": 50, "depth_limit": 40},
           "tool": {"shape": "ball", "diameter": 3.175, "reach": 30},
           "machining": {"scallop": 0.0001, "tolerance": 0.01, "direction": "y"}}
    spec = write_spec(tmp_path, raw)
    code, out, err = cli("gcode", spec, "-o", tmp_path / "p.ngc")
    assert code == 2
    assert "machining.scallop" in err and "passes" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "p.ngc").exists()


def test_dome_above_the_top_face_cuts_no_air():
    """A dome rising 4 mm above the top face (x^2 + y^2 < 8 clipped away): the ball
    touches nothing over it, so no feed move with any XY travel lies at or above the
    top face, every cut run is entered by exactly one plunge, links over the dome are
    rapids, and each pass that crosses the dome is two runs."""
    spec, surf = _spec("4 - (x**2 + y**2)/2", x=(-4, 4), y=(-4, 4),
                       machining={"scallop": 0.2, "tolerance": 0.03, "direction": "y"})
    tp = plan_toolpath(spec, surf)
    P, K = tp.points, tp.kinds
    a, b = P[:-1], P[1:]
    feed = K[1:] != RAPID
    xy = np.hypot(*(b - a)[:, :2].T)
    in_air = feed & (a[:, 2] >= 0) & (b[:, 2] >= 0) & (xy > 1e-9)
    assert not in_air.any()
    runs = _cut_runs(tp)
    assert int((K == PLUNGE).sum()) == len(runs)
    # a pass (fixed x) whose ball clears the dome's rim circle r = sqrt(8) cuts one
    # run; one whose ball centre crosses the disc is split in two by the dome
    xs = np.array(tp.info["pass_positions"]) - 4.0
    split = np.abs(xs) < math.sqrt(8.0)
    per_pass = {}
    for r in runs:
        k = int(np.argmin(np.abs(np.array(tp.info["pass_positions"]) - r[0, 0])))
        per_pass[k] = per_pass.get(k, 0) + 1
    # (tips shallower than the air depth tolerance/20 cut air: within sqrt(2 R eps) of
    # the rim either count is right, so those passes are not asserted)
    band = math.sqrt(2 * R * 0.05 * 0.03)
    for k, n in per_pass.items():
        if not math.sqrt(8.0) <= abs(xs[k]) <= math.sqrt(8.0) + band:
            assert n == (2 if split[k] else 1), (xs[k], n)


def test_pass_gaps_split_stepovers_over_the_stock_from_gaps_beyond_its_edges():
    """Passes at -2.997 (beyond the edge 0), 0, 1, 2.05 and 4.75 (beyond the edge 2.1):
    stepovers 1 and 1.05 over the stock, gaps 2.997 and 2.7 to the passes beyond."""
    from fabkit.toolpath.finish.raster import pass_gaps

    steps, beyond = pass_gaps([-2.997, 0.0, 1.0, 2.05, 4.75], 2.1)
    np.testing.assert_allclose(steps, [1.0, 1.05])
    np.testing.assert_allclose(beyond, [2.997, 2.7])
    # every pass beyond the edges (a block narrower than the tool): all are stepovers
    steps, beyond = pass_gaps([-1.0, 2.0], 1.0)
    np.testing.assert_allclose(steps, [3.0])
    assert beyond.size == 0
