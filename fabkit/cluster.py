"""Where the design studies run: one driver for a Dask cluster, shared by ``fabkit
explore`` and ``fabkit robustness`` (chunks of launches, :mod:`fabkit.launches`) and
``fabkit design`` (one evaluation per design, :mod:`fabkit.design`).

:class:`Cluster` connects to an existing scheduler (``tcp://host:port``): an address
Dask cannot use is refused at once (SpecError naming ``--scheduler``), and so is a
scheduler without workers. :meth:`Cluster.run` submits one task per argument tuple
(task names ``<prefix>-<id>``, retried once), collects the results in the order given
whatever order they finish in, and counts the tasks each worker ran (:meth:`Cluster.info`).
The client is closed at the end, never the cluster.
"""

from __future__ import annotations

import threading
import uuid


def worker_address() -> str | None:
    """The address of the Dask worker running the caller, None outside a worker."""
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return None


def _traced(fn, *args):
    """A task: ``fn(*args)`` and where it ran."""
    return fn(*args), worker_address()


def probe_scheduler(address: str, timeout: float) -> None:
    """Refuse at once (SpecError naming --scheduler) an address Dask cannot use: an
    unknown scheme, a host that does not resolve, a TCP port nobody listens on."""
    import socket

    from distributed.comm import parse_address
    from distributed.comm.registry import backends

    from .errors import SpecError

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


def connect(address: str, timeout: float):
    """A Dask client of the scheduler at ``address`` that has at least one worker
    (SpecError naming --scheduler otherwise)."""
    from .errors import SpecError

    address = str(address).strip()
    if not address or any(ch.isspace() for ch in address):
        raise SpecError(f"not a scheduler address: {address!r} (e.g. tcp://127.0.0.1:8786)", key="--scheduler")
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - a dependency
        raise SpecError("Dask distributed is not installed (pip install 'dask[distributed]')",
                        key="--scheduler") from None
    probe_scheduler(address, min(timeout, 3.0))

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


class Cluster:
    """A connection to a Dask cluster and the tasks run on it (module doc). Use as a
    context manager: closes the client, not the cluster."""

    def __init__(self, address: str, timeout: float = 10.0):
        self.address = address
        self.client = connect(address, timeout)
        self.tasks = 0
        self.workers: dict = {}
        self._lock = threading.Lock()

    @property
    def threads(self) -> int:
        """The cluster's worker threads (1 if the scheduler does not say)."""
        try:
            return max(1, sum(w.get("nthreads", 1) for w in self.client.scheduler_info()["workers"].values()))
        except Exception:  # noqa: BLE001 - the count only sizes the chunks
            return 1

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

    def run(self, fn, calls: list[tuple], prefix: str, on_done=None) -> list:
        """``[fn(*args) for args in calls]``, one task per call named ``<prefix>-<id>``.
        ``on_done(i, result)``: called as call ``i`` completes, after its task is counted."""
        from distributed import as_completed

        futures = [self.client.submit(_traced, fn, *args, key=f"{prefix}-{uuid.uuid4().hex}", pure=False,
                                      retries=1) for args in calls]
        index = {f.key: i for i, f in enumerate(futures)}
        results: dict = {}
        try:
            for fut in as_completed(futures, loop=self.client.loop):
                value, where = fut.result()
                results[fut.key] = value
                with self._lock:
                    self.tasks += 1
                    where = where or "unknown"
                    self.workers[where] = self.workers.get(where, 0) + 1
                if on_done is not None:
                    on_done(index[fut.key], value)
        finally:
            for f in futures:
                f.release()
        return [results[f.key] for f in futures]

    def info(self) -> dict:
        return {"scheduler": self.address, "tasks": self.tasks, "workers": dict(sorted(self.workers.items()))}
