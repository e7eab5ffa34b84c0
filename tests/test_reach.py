"""The verification's reachable height (:func:`fabkit.toolpath.cut.reach.reachable_height`)
on creases and valleys tighter than the ball, against independent answers: the closed
form of the ball bridging a V crease (straight and oblique to the axes) and a brute-force
zooming search over ball centres written here (exact drop-cutter heights, no model)."""

from __future__ import annotations

import math

import numpy as np
import pytest

R = 1.5875                              # 1/8 in ball


def _ws(formula, x, y):
    from fabkit.expr import compile_surface
    from fabkit.surface import Surface
    from fabkit.toolpath.finish.compensate import WorkSurface

    return WorkSurface(Surface(compile_surface(formula, {}), x, y, 0.0))


@pytest.mark.parametrize("k, m", [(3.0, 0.0), (2.0, 0.3), (1.0, -0.7)])
def test_v_crease_closed_form(k, m):
    """h = k |y - m x| - D: a V crease along y = m x, flank slope K = k sqrt(1 + m^2)
    across it. A ball centred above the crease rests on both flanks, its centre
    R sqrt(1 + K^2) above the crease (each flank is a plane of slope K; the centre is R
    along that plane's normal); a ball centred u off the crease rests on the far flank
    only, K u higher. The lowest ball surface above a point at distance u from the crease
    is therefore the centred ball's, -D + R sqrt(1 + K^2) - sqrt(R^2 - u^2), for
    |u| < R K / sqrt(1 + K^2) (beyond, the ball touches the design: it reaches)."""
    from fabkit.toolpath.cut.reach import reachable_height

    D = 12.0
    # the crease crosses the block's middle; the points stay more than R from the edges
    ws = _ws(f"{k}*abs(y - {m}*x) - {D}", (-6.0, 6.0), (-6.0, 6.0))
    K = k * math.sqrt(1 + m * m)
    umax = R * K / math.sqrt(1 + K * K)
    rng = np.random.default_rng(1)
    t = rng.uniform(-2.5, 2.5, 300)                       # along the crease
    u = rng.uniform(-1.2 * umax, 1.2 * umax, 300)         # across it
    nrm = np.array([-m, 1.0]) / math.hypot(m, 1.0)
    tan = np.array([1.0, m]) / math.hypot(m, 1.0)
    X = 6.0 + t * tan[0] + u * nrm[0]
    Y = 6.0 + t * tan[1] + u * nrm[1]
    z, ok = reachable_height(ws, X, Y, R)
    inside = np.abs(u) < umax - 1e-6
    assert not ok[inside].any() and ok[np.abs(u) > umax + 1e-6].all()
    exact = -D + R * math.sqrt(1 + K * K) - np.sqrt(R * R - u[inside] ** 2)
    # an upper bound of the lowest ball (every centre tried is a real ball) ...
    assert np.all(z[inside] >= exact - 1e-9)
    # ... and the lowest one, to 1e-6 mm
    assert np.max(z[inside] - exact) < 1e-6
    design = K * np.abs(u) - D
    assert np.allclose(z[~inside], design[~inside], atol=1e-9)


def _brute(ws, px, py, R, overhang):
    """The lowest ball surface above (px, py) over ball centres within R of it and not
    farther than ``overhang`` beyond the footprint: exact drops on a 121 x 121 grid of
    centres over the disk, then on grids about 4 times finer around the best, eight
    times (each 61 x 61 spanning 16 of the previous cells), and the lowest of all found."""
    from fabkit.toolpath.finish.compensate import compensate

    def g(ux, uy):
        qx, qy = px + ux, py + uy
        ex = np.maximum(np.maximum(-qx, qx - ws.L), 0.0)
        ey = np.maximum(np.maximum(-qy, qy - ws.W), 0.0)
        allowed = (ux * ux + uy * uy <= R * R) & (ex <= overhang) & (ey <= overhang) \
            & (ex * ex + ey * ey <= overhang * overhang)
        out = np.full(ux.shape, np.inf)
        if allowed.any():
            z = compensate(ws, qx[allowed], qy[allowed], R)
            with np.errstate(invalid="ignore"):
                v = z + R - np.sqrt(R * R - ux[allowed] ** 2 - uy[allowed] ** 2)
            out[allowed] = np.where(np.isfinite(v), v, np.inf)
        return out

    s = np.linspace(-R, R, 121)
    UX, UY = (a.ravel() for a in np.meshgrid(s, s))
    G = g(UX, UY)
    i = int(np.argmin(G))
    best, bx, by = G[i], UX[i], UY[i]
    h = s[1] - s[0]
    for _ in range(8):
        s = np.linspace(-8 * h, 8 * h, 61)
        UX, UY = (a.ravel() for a in np.meshgrid(bx + s, by + s))
        G = g(UX, UY)
        i = int(np.argmin(G))
        if G[i] < best:
            best, bx, by = G[i], UX[i], UY[i]
        h = s[1] - s[0]
    return best


@pytest.mark.parametrize("formula, x, y, pts", [
    # a curved crease (a parabola in plan), walls of slope 3
    ("3*abs(x - 0.15*y**2) - 10", (-4.0, 4.0), (-3.0, 3.0), [(4.0, 3.0), (4.3, 1.7), (4.9, 4.4), (3.6, 2.2)]),
    # a valley tighter than the ball with a slope along it
    ("1.5*x**2 + 0.3*y - 10", (-3.0, 3.0), (0.0, 6.0), [(3.0, 3.0), (2.6, 2.0), (3.4, 4.1)]),
    # the V crease running off the stock edge y = 0, a ball hanging off it
    ("3*abs(x) - 10", (-4.0, 4.0), (0.0, 6.0), [(4.0, 0.4), (4.2, 0.05), (3.5, 0.8)]),
])
def test_reachable_height_against_brute_force_search(formula, x, y, pts):
    """Against a brute-force zooming search over ball centres (exact drops): never more
    than 2e-5 mm above it, and not below it by more than the brute search's own
    resolution (both are real balls: the reachable height is a valid upper bound)."""
    from fabkit.toolpath.cut.reach import OVERHANG, reachable_height

    ws = _ws(formula, x, y)
    px, py = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
    z, ok = reachable_height(ws, px, py, R, overhang=OVERHANG * R)
    assert not ok.any()
    ref = np.array([_brute(ws, a, b, R, OVERHANG * R) for a, b in zip(px, py)])
    assert np.all(z <= ref + 2e-5), (z - ref)
    assert np.all(z >= ref - 1e-4), (z - ref)


def test_compiled_loops_match_the_numpy_code(monkeypatch):
    """The reachable height's grid minimum and shared balls run compiled (dropcut.py's
    reach_grid_best, reach_share) or in numpy (FABKIT_NO_KERNELS=1, the drop cutter too):
    the same heights and normal scales, to the drop cutter's own agreement (1e-9 mm)."""
    from fabkit.toolpath.cut.reach import OVERHANG, reachable_height

    rng = np.random.default_rng(5)
    X, Y = rng.uniform(2.5, 5.5, 400), rng.uniform(0.0, 6.0, 400)
    out = []
    for off in ("0", "1"):
        monkeypatch.setenv("FABKIT_NO_KERNELS", off)
        ws = _ws("3*abs(x) - 10", (-4.0, 4.0), (0.0, 6.0))
        out.append(reachable_height(ws, X, Y, R, overhang=OVERHANG * R, return_scale=True))
    (z1, ok1, s1), (z2, ok2, s2) = out
    assert (ok1 == ok2).all() and (~ok1).sum() > 100
    np.testing.assert_allclose(z1, z2, rtol=0, atol=1e-9)
    np.testing.assert_allclose(s1, s2, rtol=0, atol=1e-9)
