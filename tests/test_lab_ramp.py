"""fabkit ramp: one watertight body meeting the block curvature-continuously, marks at the
heights `fabkit calibrate` gives, measured back from the written mesh."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from conftest import mutated, write_spec


@pytest.fixture(scope="module")
def ramp_run(tmp_path_factory):
    from fabkit.cli import main
    import contextlib
    import io

    d = tmp_path_factory.mktemp("ramp")
    # a quick check (the marks need v_critical and the windows, not their last digits)
    spec = write_spec(d, mutated({"ramp.samples": 60, "simulation.rtol": 1e-7, "simulation.atol": 1e-9,
                                  "simulation.t_max": 20}))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["ramp", str(spec), "-o", str(d / "r.stl"), "--json"])
    assert code == 0
    return spec, d / "r.stl", json.loads(out.getvalue())


def test_one_watertight_body(ramp_run):
    trimesh = pytest.importorskip("trimesh")
    _, stl, res = ramp_run
    m = trimesh.load(stl)
    assert m.is_watertight and m.is_volume and len(m.split(only_watertight=False)) == 1
    assert m.body_count == 1 and int((m.area_faces < 1e-9).sum()) == 0
    assert res["bodies"] == 1 and res["genus"] == 0 and res["degenerate_triangles"] == 0
    assert m.volume == pytest.approx(res["volume_mm3"], rel=1e-5)
    # it meets the block at the launch point (work X = (start - x0) * 10 = 140 mm) and rests
    # on the table (Z = -thickness) beyond the block's end (X < 0)
    assert res["extent_mm"]["X"][1] == pytest.approx(140.0, abs=1e-6)
    assert res["extent_mm"]["Z"][0] == pytest.approx(-76.2, abs=1e-4)
    assert res["extent_mm"]["X"][0] < 0


def test_marks_agree_with_calibrate_and_with_the_mesh(ramp_run, cli):
    trimesh = pytest.importorskip("trimesh")
    spec, stl, res = ramp_run
    marks = res["marks"]
    assert any(m["label"] == "v_critical" for m in marks) and len(marks) >= 2
    code, out, _ = cli("calibrate", spec, "--v-in", *[m["v_in"] for m in marks], "--json")
    assert code == 0
    cal = json.loads(out)["inverse"]["heights"]
    for m, h in zip(marks, cal):
        assert abs(m["height"] - h) < 1e-3
    # measured on the mesh: the running surface under each mark (vertical rays on the launch
    # line, beside the grooves, which leave the ball's path alone) and a ball of radius
    # 1.25 cm resting there: its centre stands H above its centre at the launch point
    mesh = trimesh.load(stl)
    r = 12.5  # mm
    T = mesh.triangles
    up = mesh.face_normals[:, 2] > 0

    def surface(X, Y):
        """Highest upward face over (X, Y): its height there (barycentric) and normal."""
        a, b, c = T[:, 0, :2], T[:, 1, :2], T[:, 2, :2]
        d = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
        with np.errstate(all="ignore"):
            l1 = ((b[:, 1] - c[:, 1]) * (X - c[:, 0]) + (c[:, 0] - b[:, 0]) * (Y - c[:, 1])) / d
            l2 = ((c[:, 1] - a[:, 1]) * (X - c[:, 0]) + (a[:, 0] - c[:, 0]) * (Y - c[:, 1])) / d
            l3 = 1 - l1 - l2
            inside = up & (l1 >= -1e-9) & (l2 >= -1e-9) & (l3 >= -1e-9) & (d != 0)
            z = l1 * T[:, 0, 2] + l2 * T[:, 1, 2] + l3 * T[:, 2, 2]
        i = np.flatnonzero(inside)[np.argmax(z[inside])]
        return z[i], mesh.face_normals[i]

    Y = marks[0]["Y"]
    z0, n0 = surface(140.0 - 1e-6, Y)
    for m in marks:
        z, n = surface(m["X"], Y)
        H = ((z + r * n[2]) - (z0 + r * n0[2])) / 10.0   # cm
        assert abs(H - m["height"]) < 1e-3, (m, H)


def test_curvature_continuous_join():
    from fabkit.lab.ramp import design_profile
    from fabkit.spec import load_spec
    from conftest import PAPER

    prof = design_profile(load_spec(PAPER), 4.5)
    e = 1e-6
    assert float(prof.lift(0.0)) == 0 and float(prof.dlift(0.0)) == 0 and float(prof.ddlift(0.0)) == 0
    # at the end of the transition: slope and curvature continuous
    L = prof.L
    assert float(prof.dlift(L - e)) == pytest.approx(float(prof.dlift(L + e)), abs=1e-9)
    assert float(prof.ddlift(L - e)) == pytest.approx(float(prof.ddlift(L + e)), abs=1e-5)
    # the lift's own derivative matches its closed form (central differences)
    u = np.linspace(0.1, 1.4 * L, 7)
    num = (prof.lift(u + 1e-5) - prof.lift(u - 1e-5)) / 2e-5
    np.testing.assert_allclose(num, prof.dlift(u), atol=1e-8)


def test_marks_agree_with_an_independent_descent(ramp_run):
    """Each mark's height, descended by the reference integration of tests/test_calibrate.py
    (time domain, its own line and release point) with the spec's damping, enters at the
    mark's v_in (1e-3 asked)."""
    from test_calibrate import _reference_descent

    from fabkit.spec import load_spec

    spec_path, _, res = ramp_run
    spec = load_spec(spec_path)
    mu = float(spec.simulation.damping)
    assert mu > 0
    for m in res["marks"]:
        v = _reference_descent(spec, m["height"], mu, 0.0)
        assert v == pytest.approx(m["v_in"], rel=1e-6), m


@pytest.mark.parametrize("changes,words", [
    ({"simulation.damping": 1e9}, "simulation.t_max"),
    ({"ball.rolling_resistance": 0.7}, "stops on the ramp"),
])
def test_a_ball_that_cannot_reach_the_block_is_refused(cli, tmp_path, changes, words):
    """Damping 1e9 1/s (the ball crawls at 3.5e-7 cm/s: issue 29's hang) or a rolling
    resistance above tan(30 deg): exit 1, one line naming why, nothing written, before
    the block is simulated."""
    spec = write_spec(tmp_path, mutated(changes))
    code, out, err = cli("ramp", spec, "-o", tmp_path / "r.stl", "--json")
    assert code == 1 and out == "" and err.count("\n") == 1 and words in err, err
    assert not (tmp_path / "r.stl").exists()
    code, out, err = cli("calibrate", spec)
    assert code == 1 and err.count("\n") == 1 and words in err


def test_straight_profile_is_not_built(cli, tmp_path):
    spec = write_spec(tmp_path, mutated({"ramp.profile": "straight", "ramp.angle": 20, "ramp.length": 12}))
    code, out, err = cli("ramp", spec, "-o", tmp_path / "r.stl")
    assert code == 2 and "ramp.profile" in err and err.count("\n") == 1
    code, out, err = cli("calibrate", spec, "--v-in", "50")
    assert code == 0 and "straight" in out


def test_marks_closer_than_a_groove_are_set_apart_into_one_watertight_body():
    """The grooves of marks 0.43 mm apart (narrower than a 0.6 mm groove) overlapped
    and left 26 zero-area triangles and a stray body. Marks at 0.43, 0.1 and 0.0 mm from
    each other and from v_critical's double groove: each keeps its place along the ramp,
    crowded ones go to separate lanes, and trimesh reads the STL as one watertight body."""
    trimesh = pytest.importorskip("trimesh")
    import io

    from fabkit.lab.ramp import GROOVE_CLEAR_MM, GROOVE_WIDTH_MM, build_ramp, mesh_verdict, place_marks
    from fabkit.physics.ramp_profile import design_profile
    from fabkit.solid import stl_bytes
    from fabkit.spec import load_spec
    from conftest import PAPER

    spec = load_spec(PAPER)
    prof = design_profile(spec, 4.5)
    s = float(spec.scale)
    u0 = prof.u_for_height(2.55)
    # along the launch line: window marks 0.43 mm, 0.1 mm and 0 mm apart, and one on v_critical's groove
    us = [u0, u0 + 0.43 / s, u0 + 0.53 / s, u0 + 0.53 / s, u0 + 1.0 / s + 1.5 / s]
    targets = [{"height": float(prof.drop(u)), "v_in": 0.0, "label": f"m{i}", "double": False}
               for i, u in enumerate(us[:4])]
    targets.append({"height": float(prof.drop(us[4])), "v_in": 0.0, "label": "v_critical", "double": True})
    # and a mark near the launch point, where the ramp is 0.6 mm thick: its groove must not cut through
    u_thin = float(__import__("scipy.optimize").optimize.brentq(lambda u: float(prof.lift(u)) * s - 0.6, 1e-6,
                                                                 prof.L))
    targets.append({"height": float(prof.drop(u_thin + 0.3 / s)), "v_in": 0.0, "label": "thin", "double": False})
    targets.sort(key=lambda t: t["height"])
    marks = place_marks(spec, prof, targets)
    for m in marks:                                      # each where its height puts it
        assert m["drop_check"] == pytest.approx(m["height"], abs=1e-9)
    # no two grooves of one side and lane closer than a width plus the clearance
    lines = [(side, m["lane"][side], x) for m in marks if m["engraved"] for side in m["grooves"]
             for x in ([m["X"] - 1.0, m["X"] + 1.0] if m["double"] else [m["X"]])]
    for i, (sa, la, xa) in enumerate(lines):
        for sb, lb, xb in lines[i + 1:]:
            if (sa, la) == (sb, lb):
                assert abs(xa - xb) >= GROOVE_WIDTH_MM + GROOVE_CLEAR_MM - 1e-9
    assert all(m["engraved"] for m in marks) and sum(m["crowded"] for m in marks) >= 2
    thin = next(m for m in marks if m["label"] == "thin")
    assert 0.05 <= thin["groove_depth_mm"] <= 0.3 + 1e-9          # half the ramp's 0.6 mm there
    data = stl_bytes(*(lambda r: (r.vertices, r.faces))(build_ramp(spec, prof, marks)))
    mesh = trimesh.load(io.BytesIO(data), file_type="stl")
    assert mesh.is_watertight and mesh.body_count == 1 and len(mesh.split(only_watertight=False)) == 1
    assert mesh.volume > 0 and int((mesh.area_faces < 1e-9).sum()) == 0
    assert mesh_verdict(data, "stl").ok


def test_mesh_verdict_refuses_a_stray_body_and_slivers():
    """The read-back check the command runs before writing: a cube is one watertight body; a
    cube with a zero-volume sliver beside it (the issue's stray body) or a duplicated
    degenerate face is not."""
    from fabkit.lab.ramp import mesh_verdict
    from fabkit.solid import stl_bytes

    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                  [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    good = mesh_verdict(stl_bytes(V, F), "stl")
    assert good.ok and good.bodies == 1 and good.volume_mm3 == pytest.approx(1.0)
    # a flat, zero-volume "body": two coincident triangles, back to back
    Vs = np.vstack([V, [[3, 0, 0], [4, 0, 0], [3, 1, 0]]])
    stray = mesh_verdict(stl_bytes(Vs, np.vstack([F, [[8, 9, 10], [8, 10, 9]]])), "stl")
    assert not stray.ok and stray.bodies == 2
    sliver = mesh_verdict(stl_bytes(Vs, np.vstack([F, [[8, 9, 9]]])), "stl")
    assert not sliver.ok
