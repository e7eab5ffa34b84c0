"""Launches for the design studies: an :class:`Engine` that runs batches of launches
of one design in this process or, as chunk tasks, on a Dask cluster
(:class:`fabkit.cluster.Cluster`). Used by ``fabkit explore`` and ``fabkit robustness``.

Without a scheduler address it runs the compiled engine (:func:`integrate.launch_batch`)
in this process. With ``scheduler='tcp://host:port'`` it splits each batch of launches
into chunks and submits one Dask task per chunk (task names ``fabkit-launch-<id>``)
to an existing cluster. A task has a fixed cost besides its launches, so
chunks are as large as the cluster allows: by default each batch is
split evenly over the cluster's threads not already kept busy by other designs
(at least :data:`MIN_CHUNK` lanes a chunk); ``chunk`` fixes the size instead. The
compiled right-hand sides of a design do not pickle, so a task carries the
design's validated spec as its raw mapping and the worker rebuilds the
:class:`models.Problem` once per design (cached per worker process by a hash of
the mapping). The integrator's arithmetic is elementwise over lanes, so a
launch's result does not depend on the batch it shares: the cluster's results
are bit-identical to the in-process ones (the tests check it). In the Dask case
the designs of a grid are driven concurrently from client threads (each
refinement round of a design is one set of chunk tasks), so the workers are
kept busy by several designs at once.
"""

from __future__ import annotations

import hashlib
import json
import math
import threading
from dataclasses import dataclass

import numpy as np

from .cluster import Cluster, worker_address
from .errors import SpecError

MIN_CHUNK = 64         # smallest automatic chunk (lanes per Dask task)
MAX_CHUNK = 16384      # largest chunk (memory bound, as the integrator's own chunks)
MAX_CACHED = 32        # compiled problems kept per process
TASK_PREFIX = "fabkit-launch"


@dataclass(frozen=True)
class Design:
    """A validated spec as it travels to a worker: its raw mapping and file name."""

    key: str
    raw: dict
    path: str


def design_of(spec) -> Design:
    text = json.dumps([spec.path, spec.raw], sort_keys=True, default=repr)
    return Design(hashlib.sha256(text.encode()).hexdigest()[:24], spec.raw, spec.path)


_CACHE: dict = {}
_CACHE_LOCK = threading.Lock()


def problem_of(design: Design):
    """The design's Problem, built once per process (the spec re-validated from its
    raw mapping, the surface compiled)."""
    with _CACHE_LOCK:
        hit = _CACHE.get(design.key)
        if hit is not None:
            return hit
        from .physics.models import problem_from_spec
        from .spec import validate

        # captured launches stop once their energy is below every exit (physics/trap.py):
        # no other outcome changes, and a study is mostly captured launches near v_critical
        problem = problem_from_spec(validate(design.raw, design.path)).with_(stop_trapped=True)
        if len(_CACHE) >= MAX_CACHED:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[design.key] = problem
        return problem


def run_chunk(design: Design, v, y0=None, vy0=None) -> dict:
    """One task: launch ``v`` (with per-lane ``y0``, ``vy0`` or the spec's) for the
    design; returns the per-launch summaries and where it ran (the Dask worker's
    address, None in-process)."""
    from .physics.integrate import launch_batch

    r = launch_batch(problem_of(design), v, y0, vy0, workers=1)
    where = worker_address()
    return {"outcome": np.asarray(r.outcome, dtype=np.int8), "bounces": np.asarray(r.bounces, dtype=int),
            "v_out": np.asarray(r.v_out, dtype=float), "bounce_times": np.asarray(r.bounce_times, dtype=float),
            "worker": where}


def _pieces(n: int, chunk: int) -> list[tuple[int, int]]:
    k = max(1, math.ceil(n / max(1, chunk)))
    b = np.linspace(0, n, k + 1).round().astype(int)
    return [(int(x), int(y)) for x, y in zip(b[:-1], b[1:]) if y > x]


class Engine:
    """Runs launches in-process (``scheduler`` None) or as chunk tasks on a Dask
    cluster. ``progress(done)``: called with the running count of launches done.
    Use as a context manager (closes the Dask client, not the cluster)."""

    def __init__(self, scheduler: str | None = None, *, chunk: int | None = None, progress=None,
                 timeout: float = 10.0):
        if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, int)
                                  or not 1 <= chunk <= MAX_CHUNK):
            raise SpecError(f"must be a whole number in 1..{MAX_CHUNK}, got {chunk}", key="--chunk")
        self.address = scheduler
        self.chunk = chunk
        self.threads = 1
        self.streams = 1
        self.progress = progress
        self.cluster = None
        self.launches = 0
        self._lock = threading.Lock()
        if scheduler:
            self.cluster = Cluster(scheduler, timeout)
            self.threads = self.cluster.threads

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def client(self):
        """The Dask client (None in-process)."""
        return None if self.cluster is None else self.cluster.client

    def close(self) -> None:
        if self.cluster is not None:
            self.cluster.close()

    def _done(self, n: int) -> None:
        with self._lock:
            self.launches += n
            done = self.launches
        if self.progress is not None:
            self.progress(done)

    def launch(self, design: Design, v, y0=None, vy0=None):
        """Launch ``v`` (M,) for ``design``; returns a :class:`sweep.Launches`."""
        from .physics.sweep import Launches

        v = np.atleast_1d(np.asarray(v, dtype=float)).ravel()
        n = v.size
        lanes = [None if a is None else np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=float), (n,)))
                 for a in (y0, vy0)]
        if n == 0:
            return Launches(v, np.zeros(0, np.int8), np.zeros(0, int), np.zeros(0), np.zeros((0, 8)))
        if self.client is None:
            with self._lock:
                base = self.launches
            cb = (lambda d, _t: self.progress(base + int(d))) if self.progress is not None else None
            from .physics.integrate import launch_batch

            r = launch_batch(problem_of(design), v, lanes[0], lanes[1], workers=1,
                             **({"progress": cb} if cb else {}))
            with self._lock:
                self.launches += n
            parts = [{"outcome": r.outcome, "bounces": r.bounces, "v_out": r.v_out,
                      "bounce_times": r.bounce_times}]
        else:
            parts = self._on_cluster(design, v, lanes[0], lanes[1])
        k = max(p["bounce_times"].shape[1] for p in parts)
        bt = np.concatenate([np.pad(np.asarray(p["bounce_times"], dtype=float),
                                    ((0, 0), (0, k - p["bounce_times"].shape[1])), constant_values=np.nan)
                             for p in parts])
        return Launches(v, np.concatenate([np.asarray(p["outcome"], dtype=np.int8) for p in parts]),
                        np.concatenate([np.asarray(p["bounces"], dtype=int) for p in parts]),
                        np.concatenate([np.asarray(p["v_out"], dtype=float) for p in parts]), bt)

    def _on_cluster(self, design, v, y0, vy0) -> list[dict]:
        pieces = _pieces(v.size, self.chunk_for(v.size))
        calls = [(design, v[a:b], None if y0 is None else y0[a:b], None if vy0 is None else vy0[a:b])
                 for a, b in pieces]
        return self.cluster.run(run_chunk, calls, TASK_PREFIX,
                                on_done=lambda i, _r: self._done(pieces[i][1] - pieces[i][0]))

    def chunk_for(self, n: int) -> int:
        """Lanes per task for a batch of ``n`` (results do not depend on it)."""
        if self.chunk is not None:
            return self.chunk
        share = max(1, math.ceil(self.threads / max(1, self.streams)))
        return min(MAX_CHUNK, max(MIN_CHUNK, math.ceil(n / share)))

    def map(self, fn, items: list) -> list:
        """``[fn(x) for x in items]``: serially in-process; from client threads on a
        cluster (each thread's launches become tasks, so designs run side by side)."""
        if self.client is None or len(items) <= 1:
            return [fn(x) for x in items]
        from concurrent.futures import ThreadPoolExecutor

        n = max(2, min(len(items), 2 * self.threads, 32))
        self.streams = n
        pool = ThreadPoolExecutor(max_workers=n)
        try:
            futures = [pool.submit(fn, x) for x in items]
            out = [f.result() for f in futures]
        except BaseException:
            # Ctrl-C or an error: do not wait for the other designs; closing the client
            # (the engine's exit) cancels their tasks and ends their threads
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        finally:
            self.streams = 1
        pool.shutdown(wait=True)
        return out

    @property
    def tasks(self) -> int:
        return 0 if self.cluster is None else self.cluster.tasks

    @property
    def workers(self) -> dict:
        return {} if self.cluster is None else self.cluster.workers

    def info(self) -> dict:
        return {"scheduler": self.address,
                "chunk": None if not self.address else (self.chunk if self.chunk is not None else "auto"),
                "threads": self.threads if self.address else None,
                "tasks": self.tasks, "workers": dict(sorted(self.workers.items())), "launches": self.launches}
