"""The batched surface callback of the drop cutter's kernel (codegen's ``heights(n, X, Y,
OUT, P)``, one call for many points) against the scalar ``height`` it batches, bit for
bit, including the points where the formula overflows or is undefined, and against the
formula evaluated here in numpy, independently of the code generator (within 1e-12 of
the size of its terms). (tests/test_drop_kernel.py compares the kernel, which calls it,
with the numpy drop cutter.)"""

from __future__ import annotations

import ctypes

import numpy as np
import pytest

numba = pytest.importorskip("numba")

from fabkit.expr import compile_surface  # noqa: E402
from fabkit.physics.engine import codegen  # noqa: E402
from fabkit.physics.engine.batch import _formula  # noqa: E402
from fabkit.toolpath.finish import kernels  # noqa: E402

PAPER_PARAMS = {"a": 0.389, "b": 0.306, "c": 0.0764, "d": 0.306, "eta": 3.27, "eps": 0.25}


def _paper(x, y, p):
    ea, eb, ed = np.exp(p["a"] * x), np.exp(p["b"] * x), np.exp(p["d"] * x)
    h = p["eta"] * (ea - eb) + p["c"] * y ** 2 + p["eps"] * y * ed
    return h, p["eta"] * (ea + eb) + p["c"] * y ** 2 + np.abs(p["eps"] * y * ed)


def _waves(x, y, p):
    return np.sin(x) * np.cos(y) + 0.1 * x ** 2 - 8, np.abs(np.sin(x) * np.cos(y)) + 0.1 * x ** 2 + 8


def _vee(x, y, p):
    return 3 * np.abs(x) - 10 + np.abs(y - 0.5 * x), 3 * np.abs(x) + 10 + np.abs(y) + 0.5 * np.abs(x)


def _poly(x, y, p):
    t = [1.0 + 0 * x, x, -2 * x * y, 0.5 * x ** 3, -y ** 4 / 7, x ** 2 * y ** 2]
    return sum(t), sum(np.abs(u) for u in t)


def _roots(x, y, p):
    s = p["k"] * np.sqrt(x) + np.log(y + 2)
    return s, np.abs(p["k"] * np.sqrt(x)) + np.abs(np.log(y + 2))


FORMULAS = [
    ("eta*(exp(a*x) - exp(b*x)) + c*y**2 + eps*y*exp(d*x)", PAPER_PARAMS, _paper, (-44, 6), (-12.5, 12.5)),
    ("sin(x)*cos(y) + 0.1*x**2 - 8", {}, _waves, (-30, 30), (-30, 30)),
    ("3*abs(x) - 10 + abs(y - 0.5*x)", {}, _vee, (-5, 5), (-8, 8)),
    ("1 + x - 2*x*y + 0.5*x**3 - y**4/7 + x**2*y**2", {}, _poly, (-20, 20), (-20, 20)),
    ("k*sqrt(x) + log(y + 2)", {"k": 1.7}, _roots, (-1, 9), (-3, 5)),   # NaN off its domain
]
IDS = ["exp", "sin", "abs", "poly", "sqrt-log"]


def _module(text, params):
    fns = compile_surface(text, params)
    f, path = _formula(fns, kernels._template())
    return f, kernels._load(path)


@numba.njit
def _scalar(fn, X, Y, OUT, Pa):
    p = Pa.ctypes
    for i in range(X.size):
        OUT[i] = fn(X[i], Y[i], p)[0]


def _ptr(a):
    return a.ctypes.data_as(ctypes.POINTER(ctypes.c_double))


def _batched(fn, X, Y, OUT, Pa, n=None):
    fn.ctypes(X.size if n is None else n, _ptr(X), _ptr(Y), _ptr(OUT), _ptr(Pa))


def _points(xr, yr, n=4000):
    rng = np.random.default_rng(7)
    x = rng.uniform(*xr, n)
    y = rng.uniform(*yr, n)
    # overflow, underflow, the undefined, signed zeros and the infinities
    special = np.array([2000.0, -2000.0, 709.0, 1e300, -1e300, np.nan, np.inf, -np.inf, 0.0, -0.0, 5e-324])
    xs, ys = np.meshgrid(special, special)
    return np.concatenate([x, xs.ravel()]), np.concatenate([y, ys.ravel()])


def _same_bits(a, b):
    """The same bits, NaN for NaN: a NaN's sign and payload are the compiler's choice of
    operand order in a commutative operation (a * b or b * a: the same number
    otherwise), and no caller reads them (NaN tests are x != x)."""
    nan = np.isnan(a)
    return np.array_equal(nan, np.isnan(b)) and np.array_equal(a[~nan].view(np.int64), b[~nan].view(np.int64))


@pytest.mark.parametrize("text,params,ref,xr,yr", FORMULAS, ids=IDS)
def test_batched_equals_scalar_bit_for_bit(text, params, ref, xr, yr):
    f, mod = _module(text, params)
    Pa = np.array(f.values, dtype=float)
    X, Y = _points(xr, yr)
    want = np.empty_like(X)
    with np.errstate(all="ignore"):
        _scalar(mod.height, X, Y, want, Pa)
    got = np.full_like(X, 7.0)
    _batched(mod.heights, X, Y, got, Pa)
    assert _same_bits(got, want)
    assert np.isnan(want).any() or text.startswith(("1 +", "3*abs"))   # the undefined points are there
    # n = 1 and n = 0: one point; none (nothing written)
    one = np.full(3, 7.0)
    _batched(mod.heights, X[5:], Y[5:], one, Pa, n=1)
    assert _same_bits(one[:1], want[5:6]) and (one[1:] == 7.0).all()
    none = np.full(3, 7.0)
    _batched(mod.heights, X, Y, none, Pa, n=0)
    assert (none == 7.0).all()


@pytest.mark.parametrize("text,params,ref,xr,yr", FORMULAS, ids=IDS)
def test_batched_against_numpy(text, params, ref, xr, yr):
    f, mod = _module(text, params)
    Pa = np.array(f.values, dtype=float)
    rng = np.random.default_rng(11)
    X, Y = rng.uniform(*xr, 20000), rng.uniform(*yr, 20000)
    got = np.empty_like(X)
    _batched(mod.heights, X, Y, got, Pa)
    with np.errstate(all="ignore"):
        want, scale = ref(X, Y, params)
    fin = np.isfinite(want)
    assert fin.sum() > 10000
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.all(np.abs(got[fin] - want[fin]) <= 1e-12 * scale[fin])


def test_batched_several_outputs_bit_for_bit():
    """A batched function of several derivatives (OUT[m i + k]) equals the scalar one."""
    wanted = ((), ("x",), ("y",), ("x", "x"), ("x", "y"), ("y", "y"))
    tpl = codegen.Template("heights-test", "", (("jet", wanted),), 0, (("jets", wanted),))
    fns = compile_surface(FORMULAS[0][0], PAPER_PARAMS)
    f, path = _formula(fns, tpl)
    mod = kernels._load(path)
    Pa = np.array(f.values, dtype=float)
    X, Y = _points((-44, 6), (-12.5, 12.5), 500)
    got = np.empty(6 * X.size)
    mod.jets.ctypes(X.size, _ptr(X), _ptr(Y), _ptr(got), _ptr(Pa))

    @numba.njit
    def scalar(fn, X, Y, OUT, Pa):
        p = Pa.ctypes
        for i in range(X.size):
            h, hx, hy, hxx, hxy, hyy = fn(X[i], Y[i], p)
            OUT[6 * i], OUT[6 * i + 1], OUT[6 * i + 2] = h, hx, hy
            OUT[6 * i + 3], OUT[6 * i + 4], OUT[6 * i + 5] = hxx, hxy, hyy

    want = np.empty_like(got)
    scalar(mod.jet, X, Y, want, Pa)
    assert _same_bits(got, want)
