"""The compiled drop cutter and swept cut (toolpath/finish/dropcut.py) against the numpy code
they transcribe (compensate.py's candidates, verify.capsule_lower): the same heights
within 1e-9 mm on smooth ground, creases, ridges, walls and the footprint's edges.
(tests/test_compensate.py checks the same drop cutter, compiled, against closed forms
and an independent optimizer.)"""

from __future__ import annotations

import numpy as np
import pytest

from fabkit.spec import validate
from fabkit.surface import Surface
from fabkit.toolpath.finish import compensate as C
from fabkit.toolpath.cut.verify import SegmentGrid

R = 1.6


def _ws(height, x=(-5, 5), y=(-8, 8), top=0.0):
    raw = {"name": "t", "units": "mm",
           "surface": {"height": height, "x": list(x), "y": list(y), "top": top},
           "stock": {"thickness": 50}, "tool": {"diameter": 2 * R},
           "machining": {"scallop": 0.05, "tolerance": 0.01}}
    return C.WorkSurface(Surface.from_spec(validate(raw, "t.yaml")))


@pytest.mark.parametrize("height,top", [
    ("3*abs(x) - 10", 0.0),                                  # a V crease, the top face
    ("4 - 2*abs(x - 0.3*y) - 0.05*y**2", 3.0),              # a ridge: candidate (v)
    ("-8 + 0.1*x**2 + 3*sin(x)*cos(y)", -6.0),              # waves, valleys tighter than the ball
    ("4*x - 30", 0.0),                                       # a wall of slope 4 at the edges
    ("-exp(-(x**2 + y**2)/4) * 5", -1.0),                   # a dimple meeting the top face
    ("3.27*(exp(0.389*x) - exp(0.306*x)) + 0.0764*y**2 + 0.25*y*exp(0.306*x)", 0.5),  # the paper's
])
def test_kernel_matches_numpy(height, top):
    ws = _ws(height, top=top)
    if ws.kernel() is None:
        pytest.skip("numba kernels off")
    rng = np.random.default_rng(3)
    X = rng.uniform(-R, ws.L + R, 3000)
    Y = rng.uniform(-R, ws.W + R, 3000)
    X[:300] = rng.uniform(-R, R, 300)                        # the edges and corners
    Zk, ik = C.compensate(ws, X, Y, R, return_info=True)
    wn = _ws(height, top=top)
    wn._kernel = None                                        # the numpy candidates
    Zn, inn = C.compensate(wn, X, Y, R, return_info=True)
    fin = np.isfinite(Zn)
    assert np.array_equal(np.isfinite(Zk), fin)
    assert np.max(np.abs(Zk[fin] - Zn[fin])) < 1e-9
    assert np.array_equal(ik.bridged, inn.bridged)
    # the contact point may differ only where two candidates tie in value
    with np.errstate(invalid="ignore"):
        same = (ik.kind == inn.kind) | (np.abs(Zk - Zn) < 1e-12) | ~fin
    assert same.all()


def test_lowest_matches_numpy(monkeypatch):
    rng = np.random.default_rng(0)
    n = 800
    a = rng.uniform(0, 20, (n, 3))
    a[:, 2] = rng.uniform(-5, 0, n)
    b = a + rng.normal(0, 1, (n, 3))
    b[::7] = a[::7]                                          # zero-length moves
    b[::11, :2] = a[::11, :2]                                # plunges
    g = SegmentGrid(a, b, 1.5, 2.0, np.array([0.0, 0.0]), (12, 12), 10 ** 8)
    px, py = rng.uniform(0, 20, 5000), rng.uniform(0, 20, 5000)
    before = rng.integers(0, n, 5000)
    k1, k2 = g.lowest(px, py), g.lowest(px, py, before=before)
    monkeypatch.setenv("FABKIT_NO_KERNELS", "1")
    n1, n2 = g.lowest(px, py), g.lowest(px, py, before=before)
    for k, m in ((k1, n1), (k2, n2)):
        fin = np.isfinite(m)
        assert np.array_equal(np.isfinite(k), fin) and fin.any()
        assert np.max(np.abs(k[fin] - m[fin])) < 1e-12
