"""The milled block against exact answers: volumes by closed form and quadrature,
watertightness by edge counting, the crease on h = top, the deviation by random
sampling independent of the mesher's own sample points."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.optimize import brentq

from fabkit.errors import SpecError
from fabkit.solid import build_solid, stl_bytes
from fabkit.spec import load_spec, validate
from fabkit.surface import Surface

from conftest import PAPER, SPECS


def surface_of(height, x, y, top, units="mm", params=None, thickness=50.0):
    raw = {"name": "t", "units": units,
           "surface": {"height": height, "params": params or {}, "x": list(x), "y": list(y), "top": top},
           "stock": {"thickness": thickness}}
    spec = validate(raw)
    return Surface.from_spec(spec), thickness


@pytest.fixture(scope="module")
def paper():
    spec = load_spec(PAPER)
    surface = Surface.from_spec(spec)
    return spec, surface, build_solid(surface, spec.stock.thickness, 0.01)


def paper_removed_integral() -> float:
    """Integral over the footprint of top - min(h, top) for the paper's surface
    (design units^3): h is quadratic in y at fixed x, so the inner integral is
    exact between the roots; the outer one is adaptive quadrature to 1e-12."""
    a, b, c, d, eta, eps = 0.389, 0.306, 0.0764, 0.306, 3.27, 0.25
    top, (y0, y1), (x0, x1) = 5.0, (-12.5, 12.5), (-44.0, 6.0)

    def inner(x):
        A = eta * (math.exp(a * x) - math.exp(b * x))
        B = eps * math.exp(d * x)
        disc = B * B - 4 * c * (A - top)
        if disc <= 0:
            return 0.0
        r = math.sqrt(disc)
        lo, hi = max(y0, (-B - r) / (2 * c)), min(y1, (-B + r) / (2 * c))
        if hi <= lo:
            return 0.0
        F = lambda y: (top - A) * y - B * y * y / 2 - c * y ** 3 / 3  # noqa: E731
        return F(hi) - F(lo)

    val, err = quad(inner, x0, x1, limit=500, epsabs=1e-12, epsrel=1e-13)
    assert err < 1e-8
    return val


def edge_check(faces):
    """Every directed edge appears once and its reverse once: closed, consistently
    oriented 2-manifold (independent of manifold3d and trimesh)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    key = e[:, 0].astype(np.int64) * (faces.max() + 1) + e[:, 1]
    rkey = e[:, 1].astype(np.int64) * (faces.max() + 1) + e[:, 0]
    assert len(np.unique(key)) == len(key), "a directed edge is used twice"
    assert np.isin(rkey, key).all(), "an edge has no opposite partner"


def signed_volume(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def sample_deviation(solid, surface, n=200_000, seed=1):
    """Largest |mesh z - min(h, top)| (mm) at random points in random skin triangles."""
    rng = np.random.default_rng(seed)
    F = solid.faces[: solid.surface_triangles]
    pick = rng.integers(0, len(F), n)
    r = rng.random((n, 2))
    flip = r.sum(axis=1) > 1
    r[flip] = 1 - r[flip]
    w = np.column_stack([1 - r.sum(axis=1), r])
    P = np.einsum("nk,nkd->nd", w, solid.vertices[F[pick]])
    x, y, z = surface.from_work(P[:, 0], P[:, 1], P[:, 2])
    return float(np.max(np.abs(z - surface.clipped(x, y))) * surface.scale)


# ----------------------------------------------------------------------------
# the paper's block
# ----------------------------------------------------------------------------
def test_paper_volume_against_quadrature(paper):
    spec, surface, solid = paper
    L, W = surface.stock_size_mm
    exact = L * W * spec.stock.thickness - surface.scale ** 3 * paper_removed_integral()
    # a piecewise-linear skin within 0.01 mm of the surface: |dV| <= dev * area
    assert abs(solid.volume_mm3 - exact) <= solid.max_deviation_mm * L * W
    assert abs(solid.volume_mm3 / exact - 1) < 1e-4            # acceptance: 0.1 %
    assert signed_volume(solid.vertices, solid.faces) == pytest.approx(exact, rel=1e-4)


def test_paper_is_closed_oriented_single_body(paper):
    import trimesh

    _, _, solid = paper
    edge_check(solid.faces)
    assert solid.bodies == 1
    mesh = trimesh.load(io.BytesIO(stl_bytes(solid.vertices, solid.faces)), file_type="stl")
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0                                    # outward normals
    assert mesh.body_count == 1


def test_paper_work_coordinates(paper):
    spec, surface, solid = paper
    lo, hi = solid.vertices.min(axis=0), solid.vertices.max(axis=0)
    np.testing.assert_allclose(lo, [0, 0, -spec.stock.thickness], atol=1e-9)
    np.testing.assert_allclose(hi, [500, 250, 0], atol=1e-9)
    # the deepest skin vertex is no deeper than the surface's lowest point
    assert solid.vertices[:, 2][solid.faces[: solid.surface_triangles]].min() >= -surface.depth_mm() - 1e-9


def test_paper_crease_on_its_curve(paper):
    _, surface, solid = paper
    assert len(solid.crease) > 100
    x, y = solid.crease.T
    assert np.max(np.abs(surface.height(x, y) - surface.top)) < 1e-9


def test_paper_deviation_by_random_sampling(paper):
    _, surface, solid = paper
    measured = sample_deviation(solid, surface)
    assert measured <= solid.tolerance_mm
    assert solid.max_deviation_mm <= solid.tolerance_mm
    assert measured <= solid.max_deviation_mm * 1.05 + 1e-6   # the report is not an underestimate


def test_coarser_tolerance_fewer_triangles_still_within(paper):
    spec, surface, fine = paper
    coarse = build_solid(surface, spec.stock.thickness, 0.1)
    assert coarse.triangles < fine.triangles / 5
    assert sample_deviation(coarse, surface, n=50_000) <= 0.1


# ----------------------------------------------------------------------------
# flat and planar surfaces: exact volumes
# ----------------------------------------------------------------------------
def test_flat_above_top_is_the_stock_box():
    surface, T = surface_of("3", (-10, 30), (0, 20), top=2.0)
    solid = build_solid(surface, T, 0.01)
    assert solid.volume_mm3 == pytest.approx(40 * 20 * T, rel=1e-12)
    assert 2 <= solid.surface_triangles <= 1200
    assert solid.max_deviation_mm < 1e-12
    edge_check(solid.faces)


def test_flat_pocket_below_top():
    surface, T = surface_of("-4", (0, 40), (0, 20), top=0.0, units="cm", thickness=60.0)
    solid = build_solid(surface, T, 0.01)
    assert solid.volume_mm3 == pytest.approx(400 * 200 * (60 - 40), rel=1e-12)
    assert solid.triangles <= 2000
    edge_check(solid.faces)


@pytest.mark.parametrize("top", [0.25, 0.0])   # 0.0: the crease passes through grid vertices (x = 3)
def test_tilted_plane_crease_is_exact(top):
    """h = 0.1 (x - 3) meets top on the line x = 3 + 10 top; every piece is planar,
    so the volume is exact to rounding: removed = W * 0.5 * d * (d / 0.1) with d the
    depth at x = x0."""
    surface, T = surface_of("0.1*(x - 3)", (-13, 19), (0, 10), top=top, thickness=20.0)
    solid = build_solid(surface, T, 0.01)
    depth = top - 0.1 * (-13 - 3)
    removed = 10 * 0.5 * depth * (depth / 0.1)
    assert solid.volume_mm3 == pytest.approx(32 * 10 * T - removed, rel=1e-12)
    assert np.allclose(solid.crease[:, 0], 3 + 10 * top, atol=1e-12)
    assert solid.max_deviation_mm < 1e-9
    edge_check(solid.faces)


def test_paraboloid_bowl_closed_form():
    """h = (x^2 + y^2) / (2 R) clipped at t: removed volume = pi R t^2 (the disk of
    radius sqrt(2 R t) lies inside the footprint)."""
    R, t = 40.0, 5.0
    surface, T = surface_of("(x**2 + y**2)/(2*R)", (-30, 30), (-25, 25), top=t, params={"R": R})
    solid = build_solid(surface, T, 0.01)
    exact = 60 * 50 * T - math.pi * R * t * t
    rim = math.pi * 2 * R * t                                     # area of the cut disk, mm^2
    assert abs(solid.volume_mm3 - exact) <= solid.max_deviation_mm * rim
    assert solid.volume_mm3 == pytest.approx(exact, rel=1e-4)
    x, y = solid.crease.T
    np.testing.assert_allclose(np.hypot(x, y), math.sqrt(2 * R * t), rtol=1e-11)
    assert sample_deviation(solid, surface, n=50_000) <= 0.01
    edge_check(solid.faces)


# ----------------------------------------------------------------------------
# the mm example spec against nested quadrature
# ----------------------------------------------------------------------------
def bowl_removed_integral(surface) -> float:
    """Integral of top - min(h, top) over the footprint: at each x the y-intervals
    where h < top are bracketed on a fine grid and their ends found by brentq
    (xtol 1e-14), integrated by quad; the outer integral is quad as well."""
    (x0, x1), (y0, y1), top = surface.x_range, surface.y_range, surface.top
    ys = np.linspace(y0, y1, 801)

    def inner(x):
        f = lambda y: top - float(surface.height(x, y))  # noqa: E731
        v = top - surface.height(np.full_like(ys, x), ys)
        ends = [y0] if v[0] > 0 else []
        for i in np.nonzero(np.sign(v[:-1]) != np.sign(v[1:]))[0]:
            ends.append(brentq(f, ys[i], ys[i + 1], xtol=1e-14))
        if v[-1] > 0:
            ends.append(y1)
        return sum(quad(f, ends[k], ends[k + 1], epsabs=1e-12, epsrel=1e-12)[0]
                   for k in range(0, len(ends) - 1, 2))

    val, _ = quad(inner, x0, x1, limit=200, epsabs=1e-8, epsrel=1e-11)
    return val


def test_bowl_spec_volume_against_quadrature():
    spec = load_spec(SPECS / "bowl.yaml")
    surface = Surface.from_spec(spec)
    solid = build_solid(surface, spec.stock.thickness, 0.01)
    L, W = surface.stock_size_mm
    exact = L * W * spec.stock.thickness - bowl_removed_integral(surface)
    assert abs(solid.volume_mm3 - exact) <= solid.max_deviation_mm * L * W
    assert solid.volume_mm3 == pytest.approx(exact, rel=1e-4)
    assert sample_deviation(solid, surface, n=50_000) <= 0.01
    x, y = solid.crease.T
    assert np.max(np.abs(surface.height(x, y) - surface.top)) < 1e-9
    edge_check(solid.faces)


# ----------------------------------------------------------------------------
# guards
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_bad_tolerance_refused(bad):
    surface, T = surface_of("0.01*x*x", (0, 10), (0, 10), top=0.5)
    with pytest.raises(SpecError, match="--tolerance"):
        build_solid(surface, T, bad)


def test_tiny_tolerance_refused_before_allocating():
    spec = load_spec(PAPER)
    surface = Surface.from_spec(spec)
    with pytest.raises(SpecError, match="--tolerance.*limit"):
        build_solid(surface, spec.stock.thickness, 1e-9)


def test_not_finite_inside_footprint_is_bad_input():
    """log(x - 0.0001) is finite on the loader's check grid but not on the whole footprint."""
    raw = {"units": "mm", "surface": {"height": "log(x - 0.0001)", "x": [0, 10], "y": [0, 10], "top": 5.0},
           "stock": {"thickness": 50}}
    spec = validate(raw)
    surface = Surface(spec.surface_functions(), (0, 10), (0, 10), 5.0, 1.0)   # loader check skipped
    with pytest.raises(SpecError, match="surface.height.*not finite"):
        build_solid(surface, 50.0, 0.01)


def test_mesh_precision_rows():
    from fabkit.solid import mesh_precision

    rows = mesh_precision(load_spec(SPECS / "bowl.yaml"), tolerances=(0.1, 0.03))
    assert [r["tolerance"] for r in rows] == [0.1, 0.03]
    for r in rows:
        assert 0 < r["max_deviation"] <= r["tolerance"] and r["seconds"] > 0
    assert rows[1]["triangles"] > rows[0]["triangles"]
    assert rows[1]["max_deviation"] < rows[0]["max_deviation"]


def test_narrow_dimple_between_initial_samples_is_found():
    """A Gaussian pit of width 0.08 mm in a 100 x 50 mm footprint falls between the
    first triangles' sample points; the first-round probe lattice must find it.
    Removed volume: 2 * 2 pi sigma^2 (tails outside the footprint negligible)."""
    surface, T = surface_of("-2*exp(-((x-3.3)**2+(y-1.7)**2)/(2*0.08**2))", (-50, 50), (-25, 25), top=0.0,
                            thickness=20.0)
    solid = build_solid(surface, T, 0.01)
    skin = solid.faces[: solid.surface_triangles]
    assert solid.vertices[skin, 2].min() < -2 + 0.01
    removed = 100 * 50 * 20 - solid.volume_mm3
    assert removed == pytest.approx(2 * 2 * math.pi * 0.08 ** 2, rel=0.02)
    edge_check(solid.faces)
