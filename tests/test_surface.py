"""Surface: lowest point, depth, curvature, coordinates, against closed forms."""

import math

import numpy as np
import pytest

from fabkit.expr import compile_surface
from fabkit.spec import load_spec
from fabkit.surface import Surface, check_depth
from fabkit.errors import SpecError

from conftest import PAPER, mutated, write_spec


def test_paraboloid_lowest_and_curvature():
    # h = (x-1)^2/(2R) + (y+2)^2/(2R): lowest at (1, -2), concave radius R at the bottom.
    R = 7.0
    f = compile_surface("((x-1)**2 + (y+2)**2)/(2*R)", {"R": R})
    s = Surface(f, (-5, 5), (-5, 5), top=1.0, scale=10.0)
    low = s.lowest()
    assert low.x == pytest.approx(1.0, abs=1e-6) and low.y == pytest.approx(-2.0, abs=1e-6)
    assert low.z == pytest.approx(0.0, abs=1e-12)
    assert s.depth_mm() == pytest.approx(10.0, rel=1e-10)
    k1, k2 = s.principal_curvatures(np.array(1.0), np.array(-2.0))
    assert float(k1) == pytest.approx(1 / R, rel=1e-12) and float(k2) == pytest.approx(1 / R, rel=1e-12)
    # on a paraboloid the curvature is largest at the vertex
    assert s.min_concave_radius().z == pytest.approx(R, rel=1e-6)


def test_sphere_cap_principal_curvatures():
    # lower half of a sphere of radius 5: k1 = k2 = 1/5 everywhere
    f = compile_surface("5 - sqrt(25 - x**2 - y**2)", {})
    s = Surface(f, (-3, 3), (-3, 3), top=10.0)
    x, y = np.array([0.0, 1.5, -2.0]), np.array([0.0, 1.0, 2.0])
    k1, k2 = s.principal_curvatures(x, y)
    np.testing.assert_allclose(k1, 0.2, rtol=1e-12)
    np.testing.assert_allclose(k2, 0.2, rtol=1e-12)


def test_flat_surface_has_no_concave_radius():
    s = Surface(compile_surface("0*x - 2", {}), (0, 1), (0, 1), top=0.0)
    assert math.isinf(s.min_concave_radius().z)
    assert s.depth_mm() == pytest.approx(2.0)


def test_paper_surface_lowest_point_closed_form():
    spec = load_spec(PAPER)
    s = Surface.from_spec(spec)
    p = spec.surface.params
    # at the minimum: h_y = 0 -> y = -eps e^{dx}/(2c); then h_x = 0 in x alone
    from scipy.optimize import brentq

    def hx_on_valley(x):
        y = -p["eps"] * math.exp(p["d"] * x) / (2 * p["c"])
        return p["eta"] * (p["a"] * math.exp(p["a"] * x) - p["b"] * math.exp(p["b"] * x)) + p["eps"] * p["d"] * y * math.exp(p["d"] * x)

    x = brentq(hx_on_valley, -10, 0, xtol=1e-14)
    y = -p["eps"] * math.exp(p["d"] * x) / (2 * p["c"])
    z = float(s.height(x, y))
    low = s.lowest()
    assert low.z == pytest.approx(z, abs=1e-12)
    assert low.x == pytest.approx(x, abs=1e-5) and low.y == pytest.approx(y, abs=1e-5)
    assert check_depth(spec, s) == pytest.approx((5.0 - z) * 10, rel=1e-12)


def test_work_coordinates_roundtrip():
    spec = load_spec(PAPER)
    s = Surface.from_spec(spec)
    X, Y, Z = s.to_work(-44.0, -12.5, 5.0)
    assert (X, Y, Z) == (0.0, 0.0, 0.0)
    X, Y, Z = s.to_work(6.0, 12.5, 0.0)
    assert (float(X), float(Y), float(Z)) == (500.0, 250.0, -50.0)
    x, y, z = s.from_work(X, Y, Z)
    assert (float(x), float(y), float(z)) == (6.0, 12.5, 0.0)


@pytest.mark.parametrize("key,limit", [("stock.depth_limit", 40), ("tool.reach", 30)])
def test_depth_over_limit_names_key_and_amount(tmp_path, key, limit):
    spec = load_spec(write_spec(tmp_path, mutated({key: limit})))
    with pytest.raises(SpecError) as info:
        check_depth(spec, Surface.from_spec(spec))
    assert info.value.key == key
    assert f"{53.31671 - limit:.3f}" in str(info.value)


def test_non_finite_surface_is_refused(tmp_path):
    spec = load_spec(write_spec(tmp_path, mutated({"surface.height": "log(x)"})))
    with pytest.raises(SpecError, match="not finite"):
        Surface.from_spec(spec)


@pytest.mark.parametrize("height, ok", [
    ("3*sqrt((x - 10)**2 + y**2)", True),     # a cone's apex on the check grid: slope 3 all round
    ("sqrt((x - 10)**2)", True),              # abs written as a square root: a crease
    ("sqrt(sqrt((x - 10)**2 + y**2))", False),  # a vertical tangent at the apex
    ("abs(x - 10)**0.5", False),              # a vertical tangent along a line
])
def test_undefined_derivative_at_a_kink_is_accepted_a_vertical_tangent_refused(tmp_path, height, ok):
    """At a kink of the formula a derivative is 0/0 (nan) while h is finite: a cone's apex
    is millable like abs's crease. Where the slope beside the point grows without bound
    the surface has a vertical tangent there: refused naming surface.height."""
    raw = mutated({"surface.height": height, "surface.x": [0, 20], "surface.y": [-5, 5],
                   "simulation.start": 5})
    spec = load_spec(write_spec(tmp_path, raw))
    if ok:
        s = Surface.from_spec(spec)
        assert s.height(10.0, 0.0) == 0.0
    else:
        with pytest.raises(SpecError, match="not finite") as info:
            Surface.from_spec(spec)
        assert info.value.key == "surface.height"
