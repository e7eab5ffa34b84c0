"""Cut verification against exact answers: the swept-ball formula against dense
sampling, flat-plane scallops in closed form, a known gouge, rapids through
material, and the whole verification against an independent brute-force sweep of
LinuxCNC's own reading of the program."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from fabkit.errors import DesignError
from fabkit.expr import compile_surface
from fabkit.surface import Surface
from fabkit.toolpath.program.gcode import MachineProfile, write_program
from fabkit.toolpath.path import CUT, PLUNGE, RAPID, Toolpath
from fabkit.toolpath.cut.verify import capsule_lower, verify_cut
from fabkit.toolpath.program.reader import read_program

RS274 = shutil.which("rs274")


def brute_lower(px, py, a, b, R, n=4001):
    """Lowest point of the balls centred at tip + (0, 0, R) for n tip positions
    evenly spaced from a to b, above each (px, py): a direct sampling of the sweep."""
    t = np.linspace(0.0, 1.0, n)
    out = np.full(len(px), np.inf)
    for i in range(len(px)):
        c = a[i] + t[:, None] * (b[i] - a[i])
        r2 = (px[i] - c[:, 0]) ** 2 + (py[i] - c[:, 1]) ** 2
        ok = r2 <= R * R
        if ok.any():
            out[i] = np.min(c[ok, 2] + R - np.sqrt(R * R - r2[ok]))
    return out


def test_capsule_lower_matches_dense_sphere_sampling():
    rng = np.random.default_rng(1)
    R = 3.0
    m = 400
    a = rng.uniform(-5, 5, (m, 3))
    b = a + rng.normal(0, 4, (m, 3))
    b[:40, :2] = a[:40, :2]                    # vertical segments (plunges)
    b[40:80, 2] = a[40:80, 2]                  # horizontal segments
    b[80:100] = a[80:100]                      # zero length
    b[100:120, :2] = a[100:120, :2] + 1e-7     # nearly vertical
    c = 0.5 * (a + b)
    px = c[:, 0] + rng.uniform(-R * 1.3, R * 1.3, m)
    py = c[:, 1] + rng.uniform(-R * 1.3, R * 1.3, m)
    exact = capsule_lower(px, py, a, b, R)
    brute = brute_lower(px, py, a, b, R)
    both = np.isfinite(brute)
    # the sampled sweep is never below the exact one, and converges to it
    assert np.all(exact[both] <= brute[both] + 1e-12)
    np.testing.assert_allclose(exact[both], brute[both], atol=2e-4)
    # lines the dense sampling misses lie outside (or on the rim of) the capsule
    miss = ~both
    assert np.all(~np.isfinite(exact[miss]) | (exact[miss] > np.minimum(a[miss, 2], b[miss, 2]) + R - 0.05))
    assert both.sum() > 250


def _flat(depth=2.0, L=60.0, W=40.0):
    return Surface(compile_surface(f"0*x - {depth}", {}), (0, L), (0, W), top=0.0, scale=1.0)


def raster(z, s, R, L=60.0, W=40.0, y_end=None):
    """Zigzag passes along x at height z, stepover s, overhanging the edges by R + 1."""
    ys = np.arange(0.0, (W if y_end is None else y_end) + 1e-9, s)
    pts, kinds = [], []
    for i, y in enumerate(ys):
        xs = (-R - 1, L + R + 1) if i % 2 == 0 else (L + R + 1, -R - 1)
        if i == 0:
            pts += [(xs[0], y, 2.0), (xs[0], y, z)]
            kinds += [RAPID, PLUNGE]
        else:
            pts.append((xs[0], y, z))
            kinds.append(CUT)
        pts.append((xs[1], y, z))
        kinds.append(CUT)
    pts.append((pts[-1][0], pts[-1][1], 5.0))
    kinds.append(RAPID)
    return Toolpath(np.array(pts), np.array(kinds), tool_radius=R, safe_z=5.0, passes=len(ys),
                    stepover=s, stepover_min=s), ys


@pytest.mark.parametrize("units", ["mm", "in"])
def test_flat_raster_scallop_closed_form(units):
    R, s, depth = 3.0, 1.0, 2.0
    tp, ys = raster(-depth, s, R)
    text = write_program(tp, MachineProfile(units=units))
    prog = read_program(text)
    res = verify_cut(_flat(depth), prog, R, points=6000, detail=True)
    # exact cut at each sample point: the nearest pass leaves R - sqrt(R^2 - dy^2)
    dy = np.min(np.abs(res["Y"][:, None] - ys[None, :]), axis=1)
    expected_left = R - np.sqrt(R * R - dy * dy)
    rnd = MachineProfile(units=units).rounding_mm
    np.testing.assert_allclose(res["cut"] - res["design"], expected_left, atol=2 * rnd + 1e-12)
    scallop = R - np.sqrt(R * R - (s / 2) ** 2)
    assert res["max_material_left"] <= scallop + 2 * rnd
    assert res["max_material_left"] >= scallop - 1e-3       # a sample lies near a cusp
    assert res["max_gouge"] <= 2 * rnd
    assert res["rapid_clearance"] == np.inf                  # no rapid below the top face
    assert res["deepest_cut"] == pytest.approx(depth, abs=rnd)
    assert res["first_move_ok"] and res["depth_ok"]


def test_tilted_plane_scallop_closed_form_both_measures():
    """Passes along x on the plane z = m y - 20 (slope m across them), each at the exact
    offset height: the cusp between two passes s apart is R - sqrt(R^2 - (s / 2c)^2)
    along the plane's normal (c = cos atan m) and 1 / c times that vertically."""
    R, s, m = 3.0, 0.6, 2.0
    c = 1.0 / np.sqrt(1.0 + m * m)
    surf = Surface(compile_surface(f"{m}*y - 90", {}), (0, 60), (0, 40), top=0.0, scale=1.0)
    ys = np.arange(-4.0, 42.0, s)             # contacts R m c = 2.7 mm uphill of each pass
    pts, kinds = [(-R - 1, ys[0], 5.0)], [RAPID]
    for i, y in enumerate(ys):
        z = m * y - 90 + R / c - R              # the tip of a ball touching the plane
        xs = (-R - 1, 60 + R + 1) if i % 2 == 0 else (60 + R + 1, -R - 1)
        pts += [(xs[0], y, z), (xs[1], y, z)]
        kinds += [PLUNGE if i == 0 else CUT, CUT]
    pts.append((pts[-1][0], pts[-1][1], 5.0))
    kinds.append(RAPID)
    tp = Toolpath(np.array(pts), np.array(kinds), tool_radius=R, safe_z=5.0)
    prog = read_program(write_program(tp, MachineProfile(tolerance=0.001)))
    normal = R - np.sqrt(R * R - (s / (2 * c)) ** 2)
    res = verify_cut(surf, prog, R, points=20000)
    assert res["material_left_measure"] == "normal"
    assert res["max_material_left"] == res["max_material_left_normal"]
    assert res["max_material_left_normal"] == pytest.approx(normal, rel=0.02)
    assert res["max_material_left_normal"] <= normal + 1e-4
    assert res["max_material_left_vertical"] == pytest.approx(normal / c, rel=0.02)
    vert = verify_cut(surf, prog, R, points=20000, normal=False)
    assert vert["max_material_left"] == vert["max_material_left_vertical"]
    assert vert["material_left_measure"] == "vertical"


def test_program_cut_too_deep_reports_the_gouge():
    R, s, depth = 3.0, 0.5, 2.0
    tp, ys = raster(-depth - 0.1, s, R)
    res = verify_cut(_flat(depth), read_program(write_program(tp, MachineProfile())), R, points=6000,
                     detail=True)
    dy = np.min(np.abs(res["Y"][:, None] - ys[None, :]), axis=1)
    np.testing.assert_allclose(res["design"] - res["cut"], 0.1 - (R - np.sqrt(R * R - dy * dy)), atol=1e-9)
    assert res["max_gouge"] == pytest.approx(0.1, abs=1e-3)
    assert res["max_gouge"] <= 0.1 + 1e-12


def test_uncut_strip_at_the_edge_is_material_left():
    # passes stop 3 mm short of the far edge: the strip above y = 37 + R stays at the top face
    R, s, depth = 3.0, 1.0, 2.0
    tp, _ = raster(-depth, s, R, y_end=37.0)
    res = verify_cut(_flat(depth), read_program(write_program(tp, MachineProfile())), R, points=4000)
    assert res["max_material_left"] == pytest.approx(depth, abs=1e-12)
    assert res["material_at"][1] > 37.0 + R - 1e-9


def test_rapid_through_material_is_caught():
    R = 3.0
    pts = np.array([(5, 5, 1.0), (5, 5, -1.0), (50, 5, -1.0), (50, 35, 1.0), (50, 35, 5.0)])
    kinds = np.array([RAPID, PLUNGE, RAPID, CUT, RAPID])    # a G0 through the uncut stock at Z-1
    tp = Toolpath(pts, kinds, tool_radius=R, safe_z=5.0)
    res = verify_cut(_flat(2.0), read_program(write_program(tp, MachineProfile())), R, points=2000)
    assert res["rapids_checked"] == 1
    assert res["rapid_clearance"] == pytest.approx(-1.0, abs=1e-9)
    # the same rapid over a region already cut deeper is safe
    pts2 = np.array([(5, 5, 1.0), (5, 5, -1.5), (50, 5, -1.5), (50, 5, -1.0), (5, 5, -1.0), (5, 5, 5.0)])
    kinds2 = np.array([RAPID, PLUNGE, CUT, CUT, RAPID, RAPID])
    tp2 = Toolpath(pts2, kinds2, tool_radius=R, safe_z=5.0)
    res2 = verify_cut(_flat(2.0), read_program(write_program(tp2, MachineProfile())), R, points=2000)
    assert res2["rapids_checked"] == 2      # along the cut, then straight up
    assert res2["rapid_clearance"] == pytest.approx(0.5, abs=1e-9)


@pytest.mark.parametrize("text, message", [
    ("G91\nG0 X1\n", "G91"),
    ("G0 X1 (a (b))\n", "nested"),
    ("G2 X1 Y1 I1\n", "G2"),
    ("G0 X1 Q3\n", "Q3"),
    ("X1\n", "before any G0/G1"),
    ("G21\nG1 X1\n", "feed"),
])
def test_reader_refuses_what_it_cannot_follow(text, message):
    with pytest.raises(DesignError, match=re.escape(message)):
        read_program(text)


def test_reader_units_modal_feed_and_end():
    prog = read_program("(x)\nG20 G90\nG0 Z1\nX1 Y2\nG1 Z-0.5 F10 ; plunge\nX2\nG21 X60\nM2\nG0 X99\n")
    np.testing.assert_allclose(prog.points, [[np.nan, np.nan, 25.4], [25.4, 50.8, 25.4],
                                             [25.4, 50.8, -12.7], [50.8, 50.8, -12.7], [60, 50.8, -12.7]])
    np.testing.assert_array_equal(prog.kinds, [0, 0, 1, 1, 1])
    np.testing.assert_allclose(prog.feed[2:], 254.0)


# ----------------------------------------------------------------------------
# independent check: LinuxCNC's canonical moves, swept by brute force
# ----------------------------------------------------------------------------
_CANON = re.compile(r"(STRAIGHT_FEED|STRAIGHT_TRAVERSE)\(([-0-9.]+), ([-0-9.]+), ([-0-9.]+)")


def rs274_moves(path):
    """End points (mm) and feed flags of the canonical moves LinuxCNC's interpreter makes."""
    run = subprocess.run([RS274, "-g", str(path)], stdin=subprocess.DEVNULL, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stderr.strip() in ("", "executing"), run.stderr
    m = _CANON.findall(run.stdout)
    pts = np.array([[float(x), float(y), float(z)] for _, x, y, z in m])
    feed = np.array([k == "STRAIGHT_FEED" for k, *_ in m])
    return pts, feed


def brute_cut(px, py, a, b, R, step):
    """Material height after the sweep, by placing the ball every ``step`` mm along
    each segment (brute force, no closed form), clipped at the top face 0."""
    out = np.zeros(len(px))
    for sa, sb in zip(a, b):
        n = max(2, int(np.ceil(np.linalg.norm(sb - sa) / step)) + 1)
        c = sa + np.linspace(0, 1, n)[:, None] * (sb - sa)
        c = c[c[:, 2] < 0]
        if not len(c):
            continue
        near = (px > c[:, 0].min() - R) & (px < c[:, 0].max() + R) & \
               (py > c[:, 1].min() - R) & (py < c[:, 1].max() + R)
        if not near.any():
            continue
        r2 = (px[near, None] - c[None, :, 0]) ** 2 + (py[near, None] - c[None, :, 1]) ** 2
        z = np.where(r2 <= R * R, c[None, :, 2] + R - np.sqrt(np.maximum(R * R - r2, 0)), np.inf)
        out[near] = np.minimum(out[near], z.min(axis=1))
    return out


@pytest.mark.skipif(RS274 is None, reason="LinuxCNC rs274 not installed")
def test_verification_agrees_with_independent_sweep_of_rs274_moves(tmp_path):
    from test_gcode_cli import bowl_surface, simple_plan

    surface, R = bowl_surface(), 3.0
    tp = simple_plan(surface, R, scallop=0.1)
    text = write_program(tp, MachineProfile(tolerance=0.02))
    prog_path = tmp_path / "p.ngc"
    prog_path.write_text(text)
    pts, feed = rs274_moves(prog_path)
    res = verify_cut(surface, read_program(text), R, points=3000, detail=True, normal=False)
    # an independent subset of points plus the two reported extremes
    rng = np.random.default_rng(7)
    pick = rng.choice(len(res["X"]), 400, replace=False)
    px = np.r_[res["X"][pick], res["gouge_at"][0], res["material_at"][0]]
    py = np.r_[res["Y"][pick], res["gouge_at"][1], res["material_at"][1]]
    a, b = pts[:-1], pts[1:]
    cut = brute_cut(px, py, a, b, R, step=0.01)
    design = np.minimum(surface.scale * (surface.height(px / surface.scale + surface.x_range[0],
                                                         py / surface.scale + surface.y_range[0])
                                         - surface.top), 0.0)
    n = len(pick)
    np.testing.assert_allclose(cut[:n], res["cut"][pick], atol=2e-4)
    np.testing.assert_allclose(design[:n], res["design"][pick], atol=1e-9)
    assert design[n] - cut[n] == pytest.approx(res["max_gouge"], abs=2e-4)
    assert cut[n + 1] - design[n + 1] == pytest.approx(res["max_material_left"], abs=2e-4)
    assert np.max(design - cut) <= res["max_gouge"] + 2e-4
    assert np.max(cut - design) <= res["max_material_left"] + 2e-4
