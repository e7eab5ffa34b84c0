"""The per-formula cache of generated surface functions (fabkit/expr_cache.py), the
kernels' surface module found by the formula's text (codegen.known_surface), and the
depth check's own bounded search (surface.lowest_local).

References are independent: closed-form derivatives, sympy's own lambdify in the test,
the closed-form lowest point of a paraboloid and a plane."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fabkit import expr_cache
from fabkit.expr import compile_surface
from fabkit.physics.engine import codegen

FORMULA = "a*exp(-(x**2 + y**2)/s) + abs(x - 0.25) + sqrt(y**2 + 1) + atan2(y, x + 3) + c*sin(x)*cos(y)"
PARAMS = {"a": 2.0, "s": 3.0, "c": 0.7}


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    """A fresh cache folder for this test alone."""
    monkeypatch.setenv("FABKIT_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "engine" / "formulas"


def _points():
    rng = np.random.default_rng(7)
    return rng.uniform(-2.0, 2.0, 400), rng.uniform(-2.0, 2.0, 400)


def _reference(text, params):
    """(h, h_x, h_y, h_xx, h_xy, h_yy) by sympy in the test: diff and lambdify of the
    same formula, written out here (not through fabkit.expr)."""
    import sympy as sp

    x, y = sp.symbols("x y", real=True)
    a, s, c = (sp.Float(params[k], 17) for k in "asc")
    h = a * sp.exp(-(x**2 + y**2) / s) + sp.Abs(x - sp.Rational(1, 4)) + sp.sqrt(y**2 + 1) \
        + sp.atan2(y, x + 3) + c * sp.sin(x) * sp.cos(y)
    hx, hy = sp.diff(h, x), sp.diff(h, y)
    parts = [h, hx, hy, sp.diff(hx, x), sp.diff(hx, y), sp.diff(hy, y)]
    parts = [p.replace(sp.DiracDelta, lambda *q: sp.Integer(0)) for p in parts]
    return sp.lambdify((x, y), parts, modules="numpy")


def test_cached_functions_equal_an_independent_sympy_reference(cache):
    X, Y = _points()
    cold = compile_surface(FORMULA, PARAMS)
    entries = list(cache.glob("fk_formula_*.json"))
    assert len(entries) == 1
    warm = compile_surface(FORMULA, PARAMS)
    ref = [np.broadcast_to(v, X.shape) for v in _reference(FORMULA, PARAMS)(X, Y)]
    for got_cold, got_warm, want in zip(cold.all(X, Y), warm.all(X, Y), ref):
        np.testing.assert_array_equal(got_cold, got_warm)          # the same code, cold or warm
        np.testing.assert_allclose(got_warm, want, rtol=1e-13, atol=1e-13)
    np.testing.assert_array_equal(warm.h(X, Y), cold.h(X, Y))
    for a, b in zip(warm.grad(X, Y) + warm.hess(X, Y) + warm.accel(X, Y),
                    cold.grad(X, Y) + cold.hess(X, Y) + cold.accel(X, Y)):
        np.testing.assert_array_equal(a, b)
    # closed form of the smooth part's h_y at a point away from the kink x = 0.25
    x0, y0 = 1.1, -0.4
    hy = (-2 * y0 / 3.0 * 2.0 * np.exp(-(x0**2 + y0**2) / 3.0) + y0 / np.sqrt(y0**2 + 1)
          + (x0 + 3) / ((x0 + 3) ** 2 + y0**2) - 0.7 * np.sin(x0) * np.sin(y0))
    assert warm.grad(np.array(x0), np.array(y0))[1] == pytest.approx(hy, rel=1e-14)


def test_warm_run_imports_no_sympy(cache):
    code = ("import sys; from fabkit.expr import compile_surface; "
            f"f = compile_surface({FORMULA!r}, {PARAMS!r}); f.all(0.5, 0.5); "
            "print('sympy' in sys.modules)")
    env = {**os.environ, "FABKIT_CACHE_DIR": str(cache.parent.parent)}
    first = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    second = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert first.stdout.strip() == "True" and second.stdout.strip() == "False"


def test_symbolic_is_built_on_demand_and_equals_the_formula(cache):
    import sympy as sp

    compile_surface("c*(x**2 + y**2)", {"c": 0.5})
    f = compile_surface("c*(x**2 + y**2)", {"c": 0.5})
    assert f._symbolic is None
    x, y = sp.Symbol("x", real=True), sp.Symbol("y", real=True)
    assert sp.simplify(f.symbolic - sp.Rational(1, 2) * (x**2 + y**2)) == 0


def test_parameter_values_are_part_of_the_key(cache):
    X, Y = _points()
    f1 = compile_surface("c*x**2 + y", {"c": 0.5})
    f2 = compile_surface("c*x**2 + y", {"c": 0.25})
    assert len(list(cache.glob("fk_formula_*.json"))) == 2
    np.testing.assert_allclose(f1.h(X, Y), 0.5 * X**2 + Y, rtol=1e-15)
    np.testing.assert_allclose(f2.h(X, Y), 0.25 * X**2 + Y, rtol=1e-15)
    np.testing.assert_allclose(f2.hess(X, Y)[0], 0.5, rtol=1e-15)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "checksum", "other_text", "bad_origin"])
def test_a_damaged_entry_is_rebuilt(cache, damage):
    compile_surface("3*x**2 - y", {})
    (entry,) = cache.glob("fk_formula_*.json")
    data = json.loads(entry.read_text())
    if damage == "truncate":
        entry.write_text(entry.read_text()[:100])
    elif damage == "garbage":
        entry.write_bytes(b"\xff\xfe not json")
    elif damage == "checksum":       # the source changed, the checksum not: ignored
        data["body"]["source"]["h"] = data["body"]["source"]["h"].replace("3", "4")
        entry.write_text(json.dumps(data))
    elif damage == "other_text":     # a consistent entry of another formula under this key
        data["body"]["text"] = "4*x**2 - y"
        data["sha256"] = expr_cache._checksum(data["body"])
        entry.write_text(json.dumps(data))
    else:
        data["body"]["names"] = {"x0": ["os", "system"]}
        data["sha256"] = expr_cache._checksum(data["body"])
        entry.write_text(json.dumps(data))
    X, Y = _points()
    f = compile_surface("3*x**2 - y", {})
    np.testing.assert_allclose(f.h(X, Y), 3 * X**2 - Y, rtol=1e-15)
    np.testing.assert_allclose(f.grad(X, Y)[0], 6 * X, rtol=1e-15)
    rebuilt = json.loads(entry.read_text())       # written again, whole
    assert rebuilt["sha256"] == expr_cache._checksum(rebuilt["body"])
    assert rebuilt["body"]["text"] == "3*x**2 - y"


def test_an_unwritable_cache_falls_back_to_computing(tmp_path, monkeypatch):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("FABKIT_CACHE_DIR", str(blocker / "cache"))
    X, Y = _points()
    f = compile_surface("x*y + 2", {})
    np.testing.assert_allclose(f.all(X, Y)[0], X * Y + 2, rtol=1e-15)
    np.testing.assert_allclose(f.hess(X, Y)[1], 1.0)
    assert not (blocker / "cache").exists()


def test_refusals_are_the_same_cached_or_not(cache):
    from fabkit.errors import SpecError

    compile_surface("x + y", {"k": 1.0})
    with pytest.raises(SpecError, match="unknown name 'z'"):
        compile_surface("x + z", {})
    with pytest.raises(SpecError, match="division by zero"):
        compile_surface("x/k", {"k": 0.0})
    assert len(list(cache.glob("fk_formula_*.json"))) == 1


def test_derivative_size_kept_with_the_entry(cache):
    from fabkit.expr import check_derivative_size, derivative_size

    cold = compile_surface(FORMULA, PARAMS)
    warm = compile_surface(FORMULA, PARAMS)
    assert warm._symbolic is None
    for order in (2, 3):
        assert check_derivative_size(warm, order) == derivative_size(cold.symbolic, order)
    assert warm._symbolic is None


def test_the_surface_module_is_found_by_the_formula_text(cache):
    template = codegen.POINT
    f1 = compile_surface("a*x**2 + b*y**2", {"a": 0.5, "b": 0.25, "unused": 3.0})
    form = codegen.formula(f1)
    path = codegen.write_surface(form, template)
    assert codegen.known_surface(f1, template) is None       # not recorded yet
    codegen.remember_surface(f1, template, form, path)
    f2 = compile_surface("a*x**2 + b*y**2", {"a": 2.0, "b": 3.0, "unused": 1.0})   # other values
    known, kpath = codegen.known_surface(f2, template)
    assert kpath == path
    assert known.names == ("a", "b") and known.values == (2.0, 3.0)
    assert known._full is None                                # found without the expression
    assert str(known.h) == str(codegen.formula(f2).h)         # the expression when asked for
    other = compile_surface("a*x**2 + b*y**2", {"a": 2.0, "b": 3.0})   # other parameter names
    assert codegen.known_surface(other, template) is None
    alias = next((cache).glob("fk_surface_point_*.json"))
    alias.write_text("{")                                     # corrupt: rebuilt by the caller
    assert codegen.known_surface(f2, template) is None
    codegen.remember_surface(f1, template, form, path)
    path.unlink()                                             # the module removed: not known
    assert codegen.known_surface(f2, template) is None


def test_lowest_local_closed_forms():
    from fabkit.surface import Surface, check_depth, lowest_local

    bowl = Surface(compile_surface("(x - 1.3)**2 + 2*(y + 0.7)**2 + 0.5*(x - 1.3)*(y + 0.7) - 4", {}),
                   (-3, 3), (-2, 2), top=0.0)
    low = lowest_local(bowl)
    assert low.x == pytest.approx(1.3, abs=1e-7) and low.y == pytest.approx(-0.7, abs=1e-7)
    assert low.z == pytest.approx(-4.0, rel=1e-14)
    plane = Surface(compile_surface("4*x - 3*y", {}), (0, 5), (0, 40), top=20.0)
    low = lowest_local(plane)                                 # the corner x = 0, y = 40
    assert (low.x, low.y, low.z) == (0.0, 40.0, -120.0)
    outside = Surface(compile_surface("(x - 9)**2 + y**2", {}), (0, 5), (-1, 1), top=30.0)
    low = lowest_local(outside)                               # on the edge x = 5
    assert low.x == 5.0 and low.y == pytest.approx(0.0, abs=1e-9) and low.z == pytest.approx(16.0, rel=1e-14)

    class Spec:                                               # check_depth's view of a spec
        path = "<test>"

        def __init__(self, limit):
            self.stock = type("S", (), {"depth_limit": limit, "thickness": 100.0})()

        def has(self, name):
            return name == "stock"

    assert check_depth(Spec(10.0), bowl) == pytest.approx(4.0, rel=1e-14)
    from fabkit.errors import SpecError

    with pytest.raises(SpecError, match="4.000 mm deep"):
        check_depth(Spec(3.9), bowl)
    assert check_depth(Spec(4.0), bowl) == pytest.approx(4.0, rel=1e-14)   # a tie: scipy's search decides


def test_third_order_jet_cached_and_exact(cache):
    """The ball's jet (h to its third derivatives) against closed forms, the same
    numbers from the cache as computed, and a known formula's jet without sympy."""
    from fabkit.expr import jet_raw

    a, b = 0.389, 0.25
    text, params = "exp(a*x) + b*y**2*sin(x)", {"a": a, "b": b}
    X, Y = _points()
    cold = jet_raw(compile_surface(text, params))
    warm_fns = compile_surface(text, params)
    warm = jet_raw(warm_fns)
    assert warm_fns._symbolic is None
    e, s, c = np.exp(a * X), np.sin(X), np.cos(X)
    want = [e + b * Y**2 * s, a * e + b * Y**2 * c, 2 * b * Y * s, a * a * e - b * Y**2 * s, 2 * b * Y * c,
            2 * b * s, a**3 * e - b * Y**2 * c, -2 * b * Y * s, 2 * b * c, 0.0]
    for got_c, got_w, w in zip(cold(X, Y), warm(X, Y), want):
        np.testing.assert_array_equal(np.broadcast_to(got_c, X.shape), np.broadcast_to(got_w, X.shape))
        np.testing.assert_allclose(np.broadcast_to(got_w, X.shape), np.broadcast_to(w, X.shape),
                                   rtol=1e-13, atol=1e-13)
