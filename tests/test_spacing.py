"""The point spacing's simplification: the compiled rounds (spacing_kernels) drop the
same nodes as the numpy rounds, and what survives keeps every sample within the
tolerance of its chord."""

import numpy as np
import pytest

from fabkit.toolpath.finish import spacing
from fabkit.toolpath.finish.passes import AIR_EPS

kern = pytest.importorskip("fabkit.toolpath.finish.spacing_kernels")
# the numpy rounds on NaN and -inf tips (as they meet them) warn; the comparisons hold
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")


def _samples(rng, passes=7, n=400, air_frac=0.1, bad=False):
    """Sorted samples of several passes: smooth profiles with kinks and steps (nodes at
    the pass ends and at random), some in air; with ``bad`` also -inf and NaN tips."""
    sp, su, sz, sn = [], [], [], []
    for p in range(passes):
        u = np.sort(rng.uniform(0.0, 50.0, n))
        z = -2.0 - 0.5 * np.sin(u / (1.0 + p)) - 0.3 * np.abs(u - 25.0) / 25.0 + 1e-3 * rng.standard_normal(n)
        z[rng.uniform(size=n) < air_frac] = 0.0                   # at the top face: air
        if bad:
            z[rng.integers(0, n, 3)] = -np.inf
            z[rng.integers(0, n, 2)] = np.nan
        node = rng.uniform(size=n) < 0.6
        node[0] = node[-1] = True
        sp.append(np.full(n, p))
        su.append(u)
        sz.append(z)
        sn.append(node)
    return (np.concatenate(sp).astype(np.int64), np.concatenate(su), np.concatenate(sz),
            np.concatenate(sn))


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("etol", [1e-4, 2e-3, 0.05])
def test_compiled_rounds_drop_the_same_nodes(seed, etol):
    rng = np.random.default_rng(seed)
    sp, su, sz, sn = _samples(rng, bad=seed % 2 == 1)
    no_tent = np.zeros(len(su))
    ref = spacing._simplify_numpy(sp, su, sz, sn, etol)
    got = kern.simplify(sp, su, sz, sn.copy(), sz >= -AIR_EPS, etol, 64, no_tent, np.inf)
    assert got.sum() < sn.sum()                                  # something was dropped
    np.testing.assert_array_equal(got, ref)
    for rounds in (1, 2, 5):                                     # round by round too
        np.testing.assert_array_equal(
            kern.simplify(sp, su, sz, sn.copy(), sz >= -AIR_EPS, etol, rounds, no_tent, np.inf),
            spacing._simplify_numpy(sp, su, sz, sn, etol, rounds))
    # with tent bounds (a concave tip path's rise above a chord, spacing.tent_bound): the
    # compiled rounds keep the same nodes as numpy's
    tent = rng.uniform(0.0, 3.0 * etol, len(su))
    bound = 2.5 * etol
    np.testing.assert_array_equal(
        kern.simplify(sp, su, sz, sn.copy(), sz >= -AIR_EPS, etol, 64, tent, bound),
        spacing._simplify_numpy(sp, su, sz, sn, etol, 64, tent, bound))


def test_survivors_hold_every_sample_within_tolerance():
    """Independent of both implementations: between consecutive surviving nodes of a
    pass every sample lies within etol of their chord, and the pass ends survive."""
    rng = np.random.default_rng(11)
    sp, su, sz, sn = _samples(rng, air_frac=0.0)
    sn[:] = True                          # every sample a node: the invariant holds at the start
    etol = 2e-3
    nodes = spacing._simplify(sp, su, sz, sn, etol)
    assert nodes.sum() < 0.5 * sn.sum()
    for p in np.unique(sp):
        idx = np.nonzero(sp == p)[0]
        keep = idx[nodes[idx]]
        assert keep[0] == idx[0] and keep[-1] == idx[-1]
        for a, b in zip(keep[:-1], keep[1:]):
            i = np.arange(a, b + 1)
            chord = sz[a] + (su[i] - su[a]) / (su[b] - su[a]) * (sz[b] - sz[a])
            assert np.abs(sz[i] - chord).max() <= etol * (1 + 1e-12)


def test_without_kernels_the_numpy_rounds_run(monkeypatch):
    monkeypatch.setenv("FABKIT_NO_KERNELS", "1")
    assert spacing._kernel() is None
    rng = np.random.default_rng(3)
    sp, su, sz, sn = _samples(rng, passes=2, n=100)
    np.testing.assert_array_equal(spacing._simplify(sp, su, sz, sn, 1e-3),
                                  spacing._simplify_numpy(sp, su, sz, sn, 1e-3))
