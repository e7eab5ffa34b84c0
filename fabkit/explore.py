"""Design studies: grids of designs over spec keys, and Monte Carlo over the launch.

Pure library code (no printing, no files): the commands ``fabkit explore`` and
``fabkit robustness`` are the edge.

Engine
------
Every launch goes through an :class:`Engine`. Without a scheduler address it
runs the compiled engine (:func:`integrate.launch_batch`) in this process.
With ``scheduler='tcp://host:port'`` it splits each batch of launches into
chunks and submits one Dask task per chunk (task names ``fabkit-launch-<id>``)
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

Explore
-------
:func:`explore` evaluates every design of a grid (:func:`parse_vary`,
:func:`design_grid`): the spec with the grid's keys replaced and fully
re-validated (an invalid combination becomes that design's ``error``). Per
design: ``v_critical`` (± ``v_critical_error``, the half-width of its bracket,
1e-6 relative) and the n-bounce ``windows`` by :func:`sweep.sweep`, and the
pre-fabrication check: with a ramp, all of it is :func:`physics.check.check`
itself, run through the engine (``launcher``): the ramp's release heights
launched (with the ``--v-in`` speeds in the same batch), the highest safe
release height (1e-4 relative) and the first failing height, and the machining
feasibility (depth of the cut against the stock and tool, tool radius against
the smallest concave radius). ``safe`` is the check's verdict: no ramp height
flies off, loses contact, bridges or slips, and the cut is machinable (without
a ``ramp`` section, judged over the ``--v-in`` launches instead). ``model``:
the model that made the design's results (the spec's: the finite ball unless
it names another).

Robustness
----------
:func:`robustness` launches, for each entry speed, ``samples`` launches with
the transverse offset and velocity drawn from normal distributions around the
spec's ``simulation.y0`` / ``vy0`` (standard deviations ``sigma_y``,
``sigma_vy``), plus the nominal (zero-scatter) launch. The draws come from
``numpy.random.default_rng(seed)`` all at once, before any launch, so they do
not depend on chunking or on the scheduler. Per entry speed it reports the
probability of each bounce count (escaped launches) and of each outcome; the
probabilities sum to 1 and each has the binomial standard error
sqrt(p (1 - p) / samples).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import threading
import time
import uuid
from dataclasses import dataclass

import numpy as np

from .errors import SpecError
from .spec import suggest
from .tolerances import DEFAULT

MIN_CHUNK = 64         # smallest automatic chunk (lanes per Dask task)
MAX_CHUNK = 16384      # largest chunk (memory bound, as the integrator's own chunks)
MAX_DESIGNS = 10_000   # designs in one grid
MAX_CACHED = 32        # compiled problems kept per process
TASK_PREFIX = "fabkit-launch"


# ----------------------------------------------------------------------------
# --vary KEY=LO:HI:N
# ----------------------------------------------------------------------------
@dataclass(frozen=True)
class Vary:
    """One axis of a design grid: a dotted spec key and its values."""

    key: str
    values: tuple


def variable_keys(spec) -> list[str]:
    """The dotted keys a grid may vary in ``spec``: every number or choice field
    of the sections the spec has, and ``surface.params.<name>`` for its params."""
    from .spec import SCHEMA, Choice, Inertia, Num

    keys = []
    for sec, fields in SCHEMA.items():
        if not spec.has(sec):
            continue
        for name, f in fields.items():
            if isinstance(f, (Num, Choice, Inertia)):
                keys.append(f"{sec}.{name}")
        if sec == "surface":
            keys.extend(f"surface.params.{p}" for p in spec.surface.params)
    return keys


def _all_keys() -> list[str]:
    from .spec import SCHEMA

    return [f"{sec}.{name}" for sec, fields in SCHEMA.items() for name in fields]


def _num(text: str, what: str, flag: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise SpecError(f"{what} must be a number, got {text.strip()!r}", key=flag) from None
    if not math.isfinite(x):
        raise SpecError(f"{what} must be finite, got {text.strip()!r}", key=flag)
    return x


#: the narrowest searchable or sampled interval LO:HI, relative to its ends' magnitude (the
#: values must stay distinct floats, and a search's step, 1/1000 of the interval, too)
MIN_SPAN_REL = 1e-9
#: and in absolute terms (a step far above the smallest normal float)
MIN_SPAN_ABS = 1e-100


def check_value(key: str, value, spec, flag: str, what: str = "a value"):
    """The value ``value`` of ``key`` (one end of a ``--vary`` interval or one listed value)
    checked by the spec's own rules for that key (range, whole number, choice), as if it
    were written in the spec; returns it as the spec would read it. SpecError naming
    ``flag`` and the key."""
    from .spec import SCHEMA, Params, read_field

    sec, _, rest = key.partition(".")
    try:
        if key.startswith("surface.params."):
            return read_field(Params(), {rest.split(".", 1)[1]: value}, "surface.params", "", spec.units)[
                rest.split(".", 1)[1]]
        if rest.count(".") == 1:          # an end of a footprint interval (surface.x.lo)
            if not abs(value) <= 1e9:
                raise SpecError(f"out of range (|value| <= 1e9), got {value:g}")
            return value
        return read_field(SCHEMA[sec][rest], value, key, "", spec.units)
    except SpecError as exc:
        raise SpecError(f"{key}: {what}: {exc.detail}", key=flag) from None


def check_interval(key: str, lo: float, hi: float, spec, flag: str) -> None:
    """Both ends of ``key=LO:HI`` inside the key's range (:func:`check_value`), LO < HI,
    and the interval wide enough to be divided (:data:`MIN_SPAN_REL`, :data:`MIN_SPAN_ABS`)
    and not so wide that HI - LO overflows. SpecError naming ``flag``."""
    from .spec import SCHEMA

    sec, _, rest = key.partition(".")
    if getattr(SCHEMA.get(sec, {}).get(rest), "integer", False):     # whole-number key: its whole numbers
        first, last = math.ceil(lo), math.floor(hi)
        if last < first:
            raise SpecError(f"{key}: no whole number in {lo:g}:{hi:g}", key=flag)
        check_value(key, float(first), spec, flag, "LO")
        check_value(key, float(last), spec, flag, "HI")
        return
    check_value(key, lo, spec, flag, "LO")
    check_value(key, hi, spec, flag, "HI")
    if not hi > lo:
        raise SpecError(f"{key}: need LO < HI, got {lo:g}:{hi:g}", key=flag)
    span = hi - lo
    if not math.isfinite(span):
        raise SpecError(f"{key}: the interval {lo:g}:{hi:g} is too wide (HI - LO overflows)", key=flag)
    need = max(MIN_SPAN_ABS, MIN_SPAN_REL * max(abs(lo), abs(hi)))
    if span < need:
        raise SpecError(f"{key}: the interval {lo:.17g}:{hi:.17g} is too narrow to divide (HI - LO = {span:g}, "
                        f"need >= {need:g})", key=flag)


def refuse_key(key: str, allowed, spec, flag: str, not_variable: str):
    """Raise the SpecError for a ``--vary`` key outside ``allowed``: a section the
    spec lacks, a key that exists but cannot be varied (``not_variable`` says why),
    an unknown surface parameter or an unknown key, with a did-you-mean."""
    section = key.split(".")[0]
    if key in _all_keys() and not spec.has(section):
        raise SpecError(f"{key}: the spec has no {section} section", key=flag)
    if key in _all_keys():
        raise SpecError(f"{key}: {not_variable}", key=flag)
    if key.startswith("surface.params."):
        names = list(spec.surface.params) if spec.has("surface") else []
        raise SpecError(f"{key}: no such parameter in surface.params"
                        f"{suggest(key, [f'surface.params.{n}' for n in names])}", key=flag)
    raise SpecError(f"unknown key {key!r}{suggest(key, allowed)}", key=flag)


def parse_vary(text: str, spec, flag: str = "--vary") -> Vary:
    """``KEY=LO:HI:N`` (N evenly spaced values, both ends included) or
    ``KEY=V1,V2,...`` (values as given; words for choice keys such as
    ``simulation.model=full,simplified``). The key must be a number or choice
    key of a section the spec has (did-you-mean otherwise); values of whole-number
    keys must be whole. Raises SpecError naming ``--vary``."""
    from .spec import SCHEMA, Choice, Inertia, Num

    text = str(text)
    if "=" not in text:
        raise SpecError(f"expected KEY=LO:HI:N (or KEY=V1,V2,...), got {text!r}", key=flag)
    key, _, rhs = text.partition("=")
    key, rhs = key.strip(), rhs.strip()
    allowed = variable_keys(spec)
    if key not in allowed:
        refuse_key(key, allowed, spec, flag, "not a number or choice key (it cannot be varied on a grid)")
    field = None
    if not key.startswith("surface.params."):
        sec, name = key.split(".")
        field = SCHEMA[sec][name]
    if not rhs:
        raise SpecError(f"{key}: no values (expected {key}=LO:HI:N)", key=flag)
    if ":" in rhs:
        parts = rhs.split(":")
        if len(parts) != 3:
            raise SpecError(f"{key}: expected LO:HI:N, got {rhs!r}", key=flag)
        lo, hi = _num(parts[0], "LO", flag), _num(parts[1], "HI", flag)
        n = _num(parts[2], "N", flag)
        if n != int(n) or n < 1:
            raise SpecError(f"{key}: N must be a whole number >= 1, got {parts[2].strip()}", key=flag)
        if n > MAX_DESIGNS:
            raise SpecError(f"{key}: N = {n:.6g} exceeds the limit of {MAX_DESIGNS} designs", key=flag)
        if n == 1 and lo != hi:
            raise SpecError(f"{key}: N = 1 needs LO = HI, got {lo:g}:{hi:g}", key=flag)
        if isinstance(field, Choice):
            raise SpecError(f"{key}: a choice key takes a list of words, e.g. {key}="
                            f"{','.join(field.options)}", key=flag)
        if n >= 2:
            check_interval(key, lo, hi, spec, flag)
        values = [float(x) for x in np.linspace(lo, hi, int(n))]
        if n >= 2 and len(set(values)) != len(values):
            raise SpecError(f"{key}: {int(n)} values between {lo:g} and {hi:g} are not distinct numbers "
                            "(a smaller N or a wider interval)", key=flag)
    else:
        values = []
        for item in rhs.split(","):
            item = item.strip()
            if not item:
                raise SpecError(f"{key}: empty value in {rhs!r}", key=flag)
            if isinstance(field, Choice) or (isinstance(field, Inertia) and item in ("solid", "hollow")):
                values.append(item)
            else:
                values.append(_num(item, "a value", flag))
        if len(values) > MAX_DESIGNS:
            raise SpecError(f"{key}: {len(values)} values exceed the limit of {MAX_DESIGNS} designs", key=flag)
    if isinstance(field, Num) and field.integer:
        for x in values:
            if x != int(x):
                raise SpecError(f"{key}: must be a whole number, got {x:g}", key=flag)
        values = [int(x) for x in values]
    if len(set(map(repr, values))) != len(values):
        raise SpecError(f"{key}: repeated values", key=flag)
    for x in values:
        check_value(key, x, spec, flag, f"the value {x:g}" if isinstance(x, float) else f"the value {x}")
    return Vary(key, tuple(values))


def design_grid(varies: list[Vary]) -> list[dict]:
    """Every combination of the axes' values as ``{key: value}``, in the order of
    the axes (the last axis varies fastest). One empty design for no axes."""
    keys = [v.key for v in varies]
    if len(set(keys)) != len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise SpecError(f"{dup} is varied twice", key="--vary")
    n = 1
    for v in varies:
        n *= len(v.values)
    if n > MAX_DESIGNS:
        raise SpecError(f"the grid has {n} designs (limit {MAX_DESIGNS})", key="--vary")
    return [dict(zip(keys, combo)) for combo in itertools.product(*(v.values for v in varies))]


# ----------------------------------------------------------------------------
# the engine
# ----------------------------------------------------------------------------
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
    try:
        from distributed import get_worker

        where = get_worker().address
    except (ImportError, ValueError):
        where = None
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
        self.client = None
        self.launches = 0
        self.tasks = 0
        self.workers: dict = {}
        self._lock = threading.Lock()
        if scheduler:
            self.client = _connect(scheduler, timeout)
            try:
                self.threads = max(1, sum(w.get("nthreads", 1)
                                          for w in self.client.scheduler_info()["workers"].values()))
            except Exception:  # noqa: BLE001 - the count only sizes the chunks
                self.threads = 1

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            finally:
                self.client = None

    def _done(self, n: int, worker=None) -> None:
        with self._lock:
            self.launches += n
            if worker is not None:
                self.tasks += 1
                self.workers[worker] = self.workers.get(worker, 0) + 1
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
        from distributed import as_completed

        pieces = _pieces(v.size, self.chunk_for(v.size))
        futures = []
        for a, b in pieces:
            futures.append(self.client.submit(
                run_chunk, design, v[a:b], None if y0 is None else y0[a:b], None if vy0 is None else vy0[a:b],
                key=f"{TASK_PREFIX}-{uuid.uuid4().hex}", pure=False, retries=1))
        sizes = {f.key: b - a for f, (a, b) in zip(futures, pieces)}
        results = {}
        try:
            for fut in as_completed(futures, loop=self.client.loop):
                r = fut.result()
                results[fut.key] = r
                self._done(sizes[fut.key], r.get("worker") or "unknown")
        finally:
            for f in futures:
                f.release()
        return [results[f.key] for f in futures]

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

    def info(self) -> dict:
        return {"scheduler": self.address,
                "chunk": None if not self.address else (self.chunk if self.chunk is not None else "auto"),
                "threads": self.threads if self.address else None,
                "tasks": self.tasks, "workers": dict(sorted(self.workers.items())), "launches": self.launches}


def _probe_scheduler(address: str, timeout: float) -> None:
    """Refuse at once (SpecError naming --scheduler) an address Dask cannot use: an
    unknown scheme, a host that does not resolve, a TCP port nobody listens on."""
    import socket

    from distributed.comm import parse_address
    from distributed.comm.registry import backends

    try:
        scheme, loc = parse_address(address, strict=False)
    except (ValueError, TypeError) as exc:
        raise SpecError(f"not a scheduler address: {address!r} ({exc}; e.g. tcp://127.0.0.1:8786)",
                        key="--scheduler") from None
    if scheme not in backends:
        raise SpecError(f"unknown scheme {scheme!r} in {address!r} (known: {', '.join(sorted(backends))}; "
                        "e.g. tcp://127.0.0.1:8786)", key="--scheduler")
    if scheme != "tcp":
        return
    host, _, port = loc.rpartition(":")
    host = host.strip("[]")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise SpecError(f"not a scheduler address: {address!r} (host:port expected, e.g. tcp://127.0.0.1:8786)",
                        key="--scheduler")
    try:
        socket.create_connection((host, int(port)), timeout=timeout).close()
    except socket.gaierror:
        raise SpecError(f"cannot connect to the Dask scheduler at {address}: unknown host {host!r}",
                        key="--scheduler") from None
    except OSError as exc:
        why = "timed out" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise SpecError(f"cannot connect to the Dask scheduler at {address}: {why}", key="--scheduler") from None


def _connect(address: str, timeout: float):
    address = str(address).strip()
    if not address or any(ch.isspace() for ch in address):
        raise SpecError(f"not a scheduler address: {address!r} (e.g. tcp://127.0.0.1:8786)", key="--scheduler")
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - a dependency
        raise SpecError("Dask distributed is not installed (pip install 'dask[distributed]')",
                        key="--scheduler") from None
    _probe_scheduler(address, min(timeout, 3.0))

    class _Client(Client):
        # a Client whose constructor failed closes itself at garbage collection, waits
        # 20 s for a loop that never ran and prints a traceback: fabkit closes its clients
        def __del__(self):
            pass

    try:
        client = _Client(address, timeout=timeout, set_as_default=False)
    except MemoryError:   # something listens there but does not speak Dask's protocol
        raise SpecError(f"cannot connect to the Dask scheduler at {address}: the service there does not answer "
                        "as a Dask scheduler", key="--scheduler") from None
    except Exception as exc:  # noqa: BLE001 - any failure of the remote end is the address's fault
        raise SpecError(f"cannot connect to the Dask scheduler at {address}: {type(exc).__name__}: {exc}",
                        key="--scheduler") from None
    try:
        client.wait_for_workers(1, timeout=timeout)
    except (OSError, TimeoutError) as exc:
        client.close()
        raise SpecError(f"the Dask scheduler at {address} has no workers ({type(exc).__name__})",
                        key="--scheduler") from None
    return client


# ----------------------------------------------------------------------------
# explore
# ----------------------------------------------------------------------------
def _counts(outcome) -> dict:
    from .physics.models import OUTCOMES

    out = {}
    for o in np.asarray(outcome).tolist():
        out[OUTCOMES[int(o)]] = out.get(OUTCOMES[int(o)], 0) + 1
    return out


def evaluate_design(spec, v_grid, engine: Engine, *, rel_tol: float = 1e-6, height_rel_tol: float = 1e-4,
                    tol=DEFAULT) -> dict:
    """One design (a validated spec): v_critical, windows, ramp safety, machining.

    With a ramp, this is the pre-fabrication check itself (:func:`physics.check.check`)
    run through the engine, its sweep over ``v_grid`` (sorted entry speeds) or, for
    None, the ramp's calibrated speeds; ``safe`` is the check's verdict. Without a
    ramp, the sweep over ``v_grid`` and safety judged over those launches.
    Returns the design's entry without ``params``, plus ``grid`` (the grid launches:
    v_in, outcome, bounces, v_out arrays) for the per-launch table."""
    from .physics.check import check, machining
    from .physics.models import OUTCOMES
    from .physics.models import unsafe as unsafe_mask
    from .physics.sweep import sweep

    t0 = time.perf_counter()
    design = design_of(spec)
    problem = problem_of(design)
    counted = {"n": 0}

    def launch(v):
        counted["n"] += len(v)
        return engine.launch(design, v)

    has_ramp = spec.has("ramp") and spec.has("ball")
    if v_grid is None and not has_ramp:
        raise SpecError("missing section (needed by explore without --v-in)", file=spec.path, key="ramp")
    if has_ramp:
        if v_grid is not None and np.size(v_grid) * 2 > tol.max_launches:
            raise SpecError(f"{np.size(v_grid)} launches exceed the limit {tol.max_launches}", key="--v-in")
        sweep_v = None if v_grid is None else np.sort(np.asarray(v_grid, dtype=float))
        rep = check(spec, launcher=launch, sweep_v=sweep_v, problem=problem, rel_tol=height_rel_tol,
                    v_rel_tol=rel_tol, edge_rel_tol=rel_tol, tol=tol, window_bounces=None)   # every n-bounce window
        out: dict = {"v_critical": rep.v_critical, "v_critical_error": rep.v_critical_error,
                     "v_critical_reason": rep.v_critical_reason, "windows": rep.windows, "safe_over": "ramp",
                     "highest_safe_height": rep.highest_safe_height, "first_failure": rep.first_failure}
        m, grid, safe, v = rep.machining, rep.grid, rep.safe, rep.grid.v_in
    else:
        v = np.sort(np.asarray(v_grid, dtype=float))
        if v.size > tol.max_launches:
            raise SpecError(f"{v.size} launches exceed the limit {tol.max_launches}", key="--v-in")
        grid = launch(v)
        sw = sweep(problem, v, launcher=launch, initial=grid, rel_tol=rel_tol, error_samples=0, tn=False,
                   tol=tol)
        unsafe = unsafe_mask(grid.outcome)
        first_failure = None
        if unsafe.any():
            i = int(np.flatnonzero(unsafe)[0])
            first_failure = {"height": None, "v_in": float(v[i]), "outcome": OUTCOMES[int(grid.outcome[i])]}
        out = {"v_critical": sw["v_critical"], "v_critical_error": sw["v_critical_error"],
               "v_critical_reason": sw["v_critical_reason"], "windows": sw["windows"], "safe_over": "v_in",
               "highest_safe_height": None, "first_failure": first_failure}
        m = machining(spec)
        safe = not bool(unsafe.any()) and (m is None or bool(m["feasible"]))
    out["model"] = problem.model
    out["depth_mm"] = None if m is None else m["depth_mm"]
    out["depth_ok"] = None if m is None else m["depth_ok"]
    out["machining"] = m
    out["safe"] = bool(safe)
    out["outcomes"] = _counts(grid.outcome)
    out["launches"] = counted["n"]
    out["seconds"] = time.perf_counter() - t0
    out["grid"] = {"v_in": v, "outcome": [OUTCOMES[int(o)] for o in grid.outcome], "bounces": grid.bounces,
                   "v_out": grid.v_out}
    return out


def explore(spec, varies: list[Vary], v_grid=None, *, engine: Engine, rel_tol: float = 1e-6,
            tol=DEFAULT) -> dict:
    """Evaluate every design of the grid. Returns ``{"designs": [...], "launches",
    "seconds", "engine"}``; each design ``{"params", "v_critical", "windows", "safe",
    ...}`` (see :func:`evaluate_design`) or ``{"params", "error", "safe": None, ...}``
    when its spec is invalid."""
    t0 = time.perf_counter()
    grid = design_grid(varies)
    if v_grid is not None and len(grid) * len(v_grid) > tol.max_launches:
        raise SpecError(f"{len(grid)} designs x {len(v_grid)} speeds exceed the limit of {tol.max_launches} "
                        "launches", key="--v-in")

    def one(params: dict) -> dict:
        entry: dict = {"params": params}
        try:
            dspec = spec.with_overrides(params) if params else spec
            entry.update(evaluate_design(dspec, v_grid, engine, rel_tol=rel_tol, tol=tol))
        except SpecError as exc:
            entry.update({"error": str(exc), "v_critical": None, "v_critical_error": None, "windows": [],
                          "highest_safe_height": None, "safe": None})
        return entry

    designs = engine.map(one, grid)
    return {"designs": designs, "launches": engine.launches, "seconds": time.perf_counter() - t0,
            "engine": engine.info()}


# ----------------------------------------------------------------------------
# robustness
# ----------------------------------------------------------------------------
def draw_scatter(n_v: int, samples: int, sigma_y: float, sigma_vy: float, y0: float, vy0: float,
                 seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(y0, vy0), each (n_v, samples): normal draws around the nominal launch,
    from ``default_rng(seed)``, drawn all at once (chunking cannot change them)."""
    z = np.random.default_rng(seed).standard_normal((2, n_v, samples))
    return y0 + sigma_y * z[0], vy0 + sigma_vy * z[1]


def check_scatter(sigma_y: float, sigma_vy: float, samples: int, n_v: int, tol=DEFAULT, seed: int = 0) -> None:
    """SpecError (naming the flag) for a bad sigma, sample count, launch count or seed."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**63:
        raise SpecError(f"must be a whole number in 0..2**63-1, got {seed}", key="--seed")
    for flag, s in (("--sigma-y", sigma_y), ("--sigma-vy", sigma_vy)):
        if not (isinstance(s, (int, float)) and math.isfinite(s) and s >= 0):
            raise SpecError(f"must be finite and >= 0, got {s}", key=flag)
    if not (isinstance(samples, int) and samples >= 1):
        raise SpecError(f"must be a whole number >= 1, got {samples}", key="--samples")
    total = n_v * (samples + 1)
    if total > tol.max_launches:
        raise SpecError(f"{n_v} speeds x ({samples} samples + 1 nominal) = {total} launches exceed the limit "
                        f"{tol.max_launches}", key="--samples")


#: the largest transverse velocity scatter, design units/s: far beyond any launch, and far
#: below the numbers whose draws overflow
MAX_SIGMA_VY = 1e6


def check_scatter_size(spec, sigma_y, sigma_vy) -> None:
    """SpecError (naming the flag) for a launch scatter too large to mean anything: a
    transverse offset spread wider than the footprint (most launches would start off the
    block), or a velocity spread above :data:`MAX_SIGMA_VY`. Finite, >= 0 is checked by
    the callers."""
    width = float(spec.surface.y[1] - spec.surface.y[0])
    u = spec.units
    if isinstance(sigma_y, (int, float)) and math.isfinite(sigma_y) and sigma_y > width:
        raise SpecError(f"{sigma_y:g} {u} is wider than the footprint ({width:g} {u} across): most launches "
                        "would start off the block", key="--sigma-y")
    if isinstance(sigma_vy, (int, float)) and math.isfinite(sigma_vy) and sigma_vy > MAX_SIGMA_VY:
        raise SpecError(f"must be at most {MAX_SIGMA_VY:g} {u}/s, got {sigma_vy:g}", key="--sigma-vy")


def robustness(spec, v, *, sigma_y: float, sigma_vy: float, samples: int, seed: int = 0,
               engine: Engine, tol=DEFAULT) -> dict:
    """Monte Carlo over the launch's transverse offset and velocity (module doc).

    Returns ``v_in`` (N,), ``rows`` (one per v_in: ``v_in``, ``nominal_outcome``,
    ``nominal_bounces``, ``p_bounces`` {n: P(escaped after n bounces)}, ``p_outcome``
    {outcome: P}, ``p_nominal`` (P(same outcome and bounce count as the nominal
    launch)), ``most_likely``, ``standard_error`` (largest over the row)), ``summary``,
    ``launches`` (arrays over all sampled launches, for the table), ``seconds``."""
    from .physics.models import OUTCOMES
    from .physics.sweep import ESCAPED

    t0 = time.perf_counter()
    v = np.asarray(v, dtype=float).ravel()
    check_scatter(sigma_y, sigma_vy, samples, v.size, tol, seed=seed)
    design = design_of(spec)
    problem = problem_of(design)
    Y, VY = draw_scatter(v.size, samples, float(sigma_y), float(sigma_vy), problem.y0, problem.vy0, seed)
    V = np.repeat(v, samples)
    allv = np.concatenate([v, V])
    ally = np.concatenate([np.full(v.size, problem.y0), Y.ravel()])
    allvy = np.concatenate([np.full(v.size, problem.vy0), VY.ravel()])
    r = engine.launch(design, allv, ally, allvy)
    n = v.size
    nom_o, nom_b = r.outcome[:n], r.bounces[:n]
    O = r.outcome[n:].reshape(n, samples)
    B = r.bounces[n:].reshape(n, samples)
    rows = []
    for i in range(n):
        esc = O[i] == ESCAPED
        pb = {}
        for b in sorted(set(B[i][esc].tolist())):
            pb[str(int(b))] = float(np.count_nonzero(esc & (B[i] == b)) / samples)
        po = {name: float(np.count_nonzero(O[i] == j) / samples) for j, name in enumerate(OUTCOMES)}
        same = (O[i] == nom_o[i]) & ((B[i] == nom_b[i]) | (nom_o[i] != ESCAPED))
        p_nom = float(np.count_nonzero(same) / samples)
        cands = {f"escaped_{b}": p for b, p in pb.items()}
        cands.update({name: p for name, p in po.items() if name != "escaped"})
        most = max(cands.items(), key=lambda kv: kv[1])[0] if cands else None
        ps = list(pb.values()) + [p for name, p in po.items() if name != "escaped"]
        se = max((math.sqrt(p * (1 - p) / samples) for p in ps), default=0.0)
        nominal_name = (f"escaped_{int(nom_b[i])}" if nom_o[i] == ESCAPED else OUTCOMES[int(nom_o[i])])
        rows.append({"v_in": float(v[i]), "nominal_outcome": OUTCOMES[int(nom_o[i])],
                     "nominal_bounces": int(nom_b[i]), "p_bounces": pb, "p_outcome": po, "p_nominal": p_nom,
                     "most_likely": most, "most_likely_is_nominal": most == nominal_name, "standard_error": se})
    p_nom = np.array([row["p_nominal"] for row in rows])
    two_nom = np.array([row["nominal_outcome"] == "escaped" and row["nominal_bounces"] == 2 for row in rows])
    p_two = np.array([row["p_bounces"].get("2", 0.0) for row in rows])
    summary = {
        "mean_p_nominal": float(p_nom.mean()), "min_p_nominal": float(p_nom.min()),
        "v_in_min_p_nominal": float(v[int(np.argmin(p_nom))]),
        "most_likely_differs": int(sum(not row["most_likely_is_nominal"] for row in rows)),
        "nominal_two_bounce": int(two_nom.sum()),
        "mean_p_two_where_nominal_two": float(p_two[two_nom].mean()) if two_nom.any() else None,
        "mean_p_two_elsewhere": float(p_two[~two_nom].mean()) if (~two_nom).any() else None,
        "max_standard_error": float(max(row["standard_error"] for row in rows)),
        "bound_standard_error": 0.5 / math.sqrt(samples),
    }
    launches = {"v_in": V, "sample": np.tile(np.arange(samples), n), "y0": Y.ravel(), "vy0": VY.ravel(),
                "outcome": [OUTCOMES[int(o)] for o in r.outcome[n:]], "bounces": r.bounces[n:],
                "v_out": r.v_out[n:]}
    return {"v_in": v, "rows": rows, "summary": summary, "sigma_y": float(sigma_y), "sigma_vy": float(sigma_vy),
            "samples": int(samples), "seed": int(seed), "y0": problem.y0, "vy0": problem.vy0,
            "model": problem.model, "damping": problem.damping, "launches": launches,
            "launch_count": int(allv.size), "seconds": time.perf_counter() - t0, "engine": engine.info()}


# ----------------------------------------------------------------------------
# per-launch tables
# ----------------------------------------------------------------------------
def table_format(path: str | None) -> str | None:
    """'csv' | 'parquet' from ``--out``'s extension (None without --out); SpecError
    for another extension, or for Parquet without pyarrow."""
    if path is None:
        return None
    p = str(path).lower()
    if p.endswith(".csv"):
        return "csv"
    if p.endswith(".parquet") or p.endswith(".pq"):
        try:
            import pyarrow  # noqa: F401
        except ImportError:
            raise SpecError("Parquet needs pyarrow (pip install 'fabkit[parquet]'); or give a .csv file",
                            key="--out") from None
        return "parquet"
    raise SpecError(f"must end in .csv or .parquet, got {str(path)!r}", key="--out")


def table_bytes(columns: dict, fmt: str) -> bytes:
    """The columns (equal lengths) as CSV (floats written exactly, nan empty) or Parquet."""
    names = list(columns)
    cols = [list(np.asarray(c).tolist()) if not isinstance(c, list) else c for c in columns.values()]
    if fmt == "parquet":
        import io

        import pyarrow as pa
        import pyarrow.parquet as pq

        buf = io.BytesIO()
        pq.write_table(pa.table({k: c for k, c in zip(names, cols)}), buf)
        return buf.getvalue()
    import csv
    import io

    def cell(x):
        if isinstance(x, float):
            return repr(x) if math.isfinite(x) else ""
        return "" if x is None else x

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(names)
    for row in zip(*cols):
        w.writerow([cell(x) for x in row])
    return buf.getvalue().encode()
