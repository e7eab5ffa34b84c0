"""Streaming launches: memory bounded by one chunk, results equal to the batch."""

from __future__ import annotations

import tracemalloc

import numpy as np

from fabkit.expr import compile_surface
from fabkit.physics.integrate import launch_batch, launch_stream
from fabkit.physics.models import CAPTURED, Problem

G = 980.665


def tilted_plane():
    """h = 0.1 x on [-10, 10]^2: every launch from x = -9 rolls off the far end, or stops
    and rolls back through x = start (escaped), in a few steps."""
    return Problem(fns=compile_surface("s*x", {"s": 0.1}), g=G, k=0.4, model="full", start=-9.0,
                   x_range=(-10.0, 10.0), y_range=(-10.0, 10.0), top=1e3, margin=0.0, t_max=60.0)


def peak_bytes(p, n, chunk):
    v = np.tile(np.linspace(1.0, 400.0, chunk), n // chunk)   # every chunk alike
    launch_batch(p, v[:16])          # warm up: the generated right-hand side is cached
    tracemalloc.start()
    tracemalloc.reset_peak()
    base = tracemalloc.get_traced_memory()[0]
    ended = 0
    for part in launch_stream(p, v, chunk=chunk):
        ended += int((part.outcome != CAPTURED).sum())
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    return peak, ended


def test_stream_equals_batch():
    p = tilted_plane()
    v = np.linspace(1.0, 400.0, 1000)
    a = launch_batch(p, v)
    parts = list(launch_stream(p, v, chunk=128))
    assert len(parts) == 8
    for f in ("outcome", "bounces", "v_out", "t_end", "x_end", "vx_end", "energy_error"):
        assert np.array_equal(getattr(a, f), np.concatenate([getattr(q, f) for q in parts]), equal_nan=True)


def test_stream_memory_does_not_grow_with_the_number_of_launches():
    p = tilted_plane()
    small, n_small = peak_bytes(p, 8_192, 2048)
    large, n_large = peak_bytes(p, 131_072, 2048)
    assert n_small == 8_192 and n_large == 131_072       # none left running: the runs were real
    # 16 times the launches: only the validated input lanes grow (v, y0, vy0: 24 bytes a
    # launch, 3 MB here); the per-chunk working set does not
    assert large < small + 131_072 * 24 + 500_000, (small, large)
    # a batch of the same launches holds every summary: far more
    tracemalloc.start()
    launch_batch(p, np.linspace(1.0, 400.0, 131_072), chunk=2048)
    whole = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert whole > 2 * large
