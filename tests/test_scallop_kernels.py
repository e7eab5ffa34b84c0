"""The material bound's compiled loops (fabkit/toolpath/finish/scallop_kernels.py) against the
numpy code they transcribe (the same bits), and against the tilted plane's closed-form
cusp."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fabkit.spec import validate
from fabkit.surface import Surface
from fabkit.toolpath.finish import scallop
from fabkit.toolpath.finish.compensate import WorkSurface
from fabkit.toolpath.finish.passes import Frame, compensate_passes, fine_grid, u_grid
from fabkit.toolpath.finish.scallop import (hermite_profile, stack_profiles, sweep_material,
                                            tilted_plane_cusp)

pytest.importorskip("numba")
from fabkit.toolpath.finish import scallop_kernels  # noqa: E402

R = 3.175


def _ws(height, x=(0, 30), y=(0, 20)):
    raw = {"name": "t", "units": "mm",
           "surface": {"height": height, "x": list(x), "y": list(y), "top": 0.0},
           "stock": {"thickness": 120},
           "tool": {"diameter": 2 * R},
           "machining": {"scallop": 0.05, "tolerance": 0.01}}
    return WorkSurface(Surface.from_spec(validate(raw, "t.yaml")))


class _Cutter:
    """A pass as sweep_material reads it: v, the fine profile, the Hermite nodes."""

    def __init__(self, v, ug, uf, Z, dZ, bridged, lo, hi, fine):
        self.v, self._ug, self.Z, self.dZ, self.bridged = v, ug, Z, dZ, bridged
        self._lo, self._hi, self.fine = lo, hi, fine


def _random_cutters(rng, ws, fr, ug, uf, n):
    """n passes with random tip profiles near the design's (some nodes unmachined, some
    kinks, random machined spans, one empty pass)."""
    out = []
    for k in range(n):
        v = float(rng.uniform(-0.5 * R, fr.Lv + 0.5 * R))
        X, Y = fr.xy(ug, np.full(ug.shape, v))
        Z = np.minimum(ws.H(X, Y), 0.0) + rng.uniform(-0.3, 0.6, ug.shape)
        Z[rng.random(ug.shape) < 0.05] = np.inf
        dZ = rng.uniform(-20.0, 20.0, ug.shape)
        bridged = rng.random(ug.shape) < 0.2
        fine = hermite_profile(ug, Z, dZ, uf, bridged)
        fine[rng.random(uf.shape) < 0.03] = np.inf
        lo, hi = sorted(rng.uniform(ug[0], ug[-1], 2))
        if k == n - 1:
            lo, hi, fine = math.inf, -math.inf, np.full(uf.shape, np.inf)
        out.append(_Cutter(v, ug, uf, Z, dZ, bridged, float(lo), float(hi), fine))
    return out


def _same_bits(a, b):
    a, b = np.ascontiguousarray(a, float), np.ascontiguousarray(b, float)
    return a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("normal", [True, False])
def test_kernel_bound_is_the_numpy_bound_bit_for_bit(monkeypatch, seed, normal):
    """Random passes over a design steep along the passes (slope 2.5: stage 3 runs) and
    random sample rows: the compiled bound equals the numpy bound in every bit."""
    rng = np.random.default_rng(seed)
    ws = _ws("2.5*x + 0.3*sin(y) - 80")
    fr = Frame("x", ws.L, ws.W)
    ug = u_grid(fr, R)
    uf = fine_grid(ug, R, 0.05)
    uq = ug[(ug >= 0) & (ug <= fr.Lu)]
    cutters = _random_cutters(rng, ws, fr, ug, uf, 5)
    vs = np.sort(rng.uniform(0.0, fr.Lv, (9, uq.size)), axis=0)
    for threshold, chord in ((0.0, 0.0), (0.02, 0.004), (0.5, 0.0)):
        got = sweep_material(ws, fr, R, uq, vs, cutters, uf, threshold, chord, normal)
        with monkeypatch.context() as m:
            m.setattr(scallop, "_kernels", lambda: None)
            ref = sweep_material(ws, fr, R, uq, vs, cutters, uf, threshold, chord, normal)
        assert np.isfinite(ref).any() and (ref > 0).any()
        assert _same_bits(got, ref)


def test_rim_search_is_the_numpy_search_bit_for_bit():
    """The stage-3 kernel alone on random profiles and points, against the numpy
    golden-section search written out here (the same steps as sweep_material's)."""
    rng = np.random.default_rng(7)
    ws = _ws("3*x - 90")
    fr = Frame("x", ws.L, ws.W)
    ug = u_grid(fr, R)
    uf = fine_grid(ug, R, 0.05)
    cutters = _random_cutters(rng, ws, fr, ug, uf, 4)
    u0 = rng.uniform(0.0, fr.Lu, 40)
    Zs, dZs, lo, hi, kink = stack_profiles(cutters)
    pv = np.array([p.v for p in cutters])
    vs = pv[rng.integers(0, 3, (6, 40))] + rng.uniform(-R, R, (6, 40))    # near the passes
    o = np.linspace(-R, R, 65)
    h = o[1] - o[0]
    gr = 0.5 * (math.sqrt(5.0) - 1.0)
    got = scallop_kernels.rim_cut(u0, vs, ug, Zs, dZs, kink, lo, hi, pv, R, o, h, gr, 24)

    def ball(p, uc, dv2, oo):
        r2 = R * R - oo * oo - dv2
        if not r2 >= 0:
            return math.inf
        u = uc + oo
        if not lo[p] <= u <= hi[p]:
            return math.inf
        z = float(hermite_profile(ug, Zs[p], dZs[p], np.array([u]), kink[p])[0])
        return z + R - math.sqrt(r2)

    ref = np.empty_like(got)
    for c in range(u0.size):
        for i in range(vs.shape[0]):
            best = math.inf
            for p in range(len(cutters)):
                dv2 = (vs[i, c] - pv[p]) ** 2
                g = [ball(p, u0[c], dv2, ok) for ok in o]
                a = o[int(np.argmin(g))] - h
                b = a + 2 * h
                cc, d = b - gr * (b - a), a + gr * (b - a)
                gc, gd = ball(p, u0[c], dv2, cc), ball(p, u0[c], dv2, d)
                for _ in range(24):
                    if gc <= gd:
                        b, d = d, cc
                        cc = b - gr * (b - a)
                        gc, gd = ball(p, u0[c], dv2, cc), gc
                    else:
                        a, cc = cc, d
                        d = a + gr * (b - a)
                        gc, gd = gd, ball(p, u0[c], dv2, d)
                best = min(best, min(g), gc, gd)
            ref[i, c] = best
    assert np.isfinite(ref).sum() > ref.size // 2
    assert _same_bits(got, ref)


@pytest.mark.parametrize("measure_normal", [True, False])
def test_bound_on_a_tilted_plane_is_the_closed_form_cusp(monkeypatch, measure_normal):
    """Two passes s apart across a plane of slope 0.7 across them (nothing along): the
    largest material the bound finds between them is the closed-form cusp between the
    lowest balls, those on the fine grid nearest the cross-section (du along the pass
    from it: a circle of radius sqrt(R^2 - du^2) in the cross-section), i.e.
    tilted_plane_cusp with R^2 - du^2 for R^2 (the exact cusp where du = 0); sampled
    across every 5e-5 mm (1e-5 mm below the crest at most), with and without the
    kernels. The columns on the edges along the pass are left out (balls beyond the
    edges drop lower)."""
    m = 0.7
    ws = _ws(f"{m}*y - 32", x=(0, 12), y=(0, 20))
    fr = Frame("x", ws.L, ws.W)
    ug = u_grid(fr, R)
    uf = fine_grid(ug, R, 0.05)
    uq = ug[(ug > 0) & (ug < fr.Lu)]
    s = 1.1
    passes = compensate_passes(ws, fr, R, ug, uf, [8.0, 8.0 + s], 60.0, 0.05)
    theta = math.atan(m)
    du = np.abs(uq[:, None] - uf[None, :]).min(axis=1)
    half = s / (2.0 * math.cos(theta))
    exact = R - np.sqrt(R * R - du * du - half * half)
    if not measure_normal:
        exact = exact / math.cos(theta)
    assert du.min() < 1e-12 and exact.min() == pytest.approx(tilted_plane_cusp(R, s, theta, measure_normal),
                                                            abs=1e-12)
    # the crest lies within 0.1 mm of midway between the contacts, R sin(theta) uphill of the passes' middle
    mid = 8.0 + 0.5 * s + R * math.sin(theta)
    vs = np.repeat(np.linspace(mid - 0.1, mid + 0.1, 4001)[:, None], uq.size, axis=1)
    for kernels in (True, False):
        with monkeypatch.context() as mp:
            if not kernels:
                mp.setattr(scallop, "_kernels", lambda: None)
            ml = sweep_material(ws, fr, R, uq, vs, passes, uf, 0.0, 0.0, measure_normal)
        top = ml.max(axis=0)
        assert np.all(top <= exact + 1e-12)
        assert np.all(top >= exact - 1e-5)
