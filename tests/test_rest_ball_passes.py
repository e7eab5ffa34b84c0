"""The rest ball's passes across a steep wall parallel to them (roughing_rest._ball_passes).

A plane of slope k falls across the passes, the stock untouched above it. The finishing
ball at pass v rests on the plane with its tip at -k v + R (sqrt(1 + k^2) - 1) (closed
form). What the finish must remove after the rest ball is measured here by brute force: at
4000 points across the wall, the lowest of every chosen ball's section (centre at its tip
+ R), lifted by the leave and capped by the top face, above the plane. It must stay within
the finish's depth of cut wherever the finishing passes themselves reach (one radius inside
the passes' ends), and the rest ball must skip passes where the wall allows it.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from fabkit.toolpath.finish.passes import Frame
from fabkit.toolpath.rough.roughing_rest import _ball_passes

R, LEAVE = 1.5875, 0.3


def _left_for_finish(Vs, tips, k, v):
    """Brute force: the rest-cut stock above the plane z = -k v (clipped at the top face 0)."""
    low = np.zeros(v.shape)                                   # the stock: the top face
    for ve, te in zip(Vs, tips):
        d = np.abs(v - ve)
        arc = np.where(d < R, te + R - np.sqrt(np.maximum(R * R - d * d, 0.0)) + LEAVE, np.inf)
        low = np.minimum(low, arc)
    return low - np.minimum(-k * v, 0.0)


@pytest.mark.parametrize("k", [0.5, 2.0, 4.0, 8.0])
def test_rest_ball_passes_hold_the_finish_depth_of_cut_on_a_steep_wall(k):
    V = np.round(np.arange(0.0, 12.0, 0.02), 10)
    tip = -k * V + R * (math.sqrt(1 + k * k) - 1)           # the ball on the plane, closed form
    plan = SimpleNamespace(ug=np.array([0.0, 1.0]),
                           passes=[SimpleNamespace(v=float(v), Z=np.full(2, t), keep=np.ones(2, bool))
                                   for v, t in zip(V, tip)])
    x = np.arange(-1.0, 14.0, 0.01)            # the level sets' grid: x along v, y along u
    y = np.array([-0.5, 0.5, 1.5])
    rough = SimpleNamespace(sets=SimpleNamespace(x=x, y=y))
    S = np.zeros((len(y), len(x)))             # the roughing left the top face
    ws = SimpleNamespace(H=lambda X, Y: -k * X)
    limit = 3.0 - 0.02
    sel = _ball_passes(plan, Frame("y", 14.0, 1.0), ws, V, R, R, LEAVE, limit, rough, S)
    assert sel[0] == 0 and sel[-1] == len(V) - 1 and all(b > a for a, b in zip(sel, sel[1:]))
    assert max(np.diff(V[sel])) <= R + 1e-9
    # the finish's removal where every pass around has its neighbours (one radius from the
    # last pass: beyond it no later ball cuts under the tips); 2 um for the code's sampling
    v = np.linspace(V[0], V[-1] - R, 4000)
    left = _left_for_finish(V[sel], tip[sel], k, v)
    assert left.max() <= limit + 2e-3
    # and all the passes would do no better than the limit allows: the choice is not the
    # whole set on any of these walls
    assert len(sel) < 0.5 * len(V)
    if k <= 0.5:
        assert max(np.diff(V[sel])) > R - 0.03          # gentle ground: one radius apart, as before
