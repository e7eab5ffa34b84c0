"""Atomic output files.

Every file fabkit writes goes through :func:`atomic_outputs`: the content is
written to a temporary file beside the target, flushed and fsynced, and only
then renamed over the target (``os.replace`` is atomic on POSIX). Several
outputs of one command (a program and its setup sheet) are renamed together
at the end, so an error, Ctrl-C or crash before that leaves every existing
output intact and no temporary file behind.
"""

from __future__ import annotations

import contextlib
import os
import signal
import tempfile
import threading
from pathlib import Path

from .errors import SpecError


class _Outputs:
    def __init__(self) -> None:
        self._pending: list[tuple[str, Path]] = []

    def write(self, path: str | os.PathLike, data: bytes | str) -> Path:
        """Stage ``data`` for ``path``; it appears there when the block exits cleanly."""
        target = Path(path)
        if isinstance(data, str):
            data = data.encode("utf-8")
        directory = target.parent if str(target.parent) else Path(".")
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SpecError(f"cannot create output folder: {exc.strerror}", file=str(directory)) from None
        if target.is_dir():
            raise SpecError("output path is a folder", file=str(target))
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
        except OSError as exc:
            raise SpecError(f"cannot write output: {exc.strerror}", file=str(target)) from None
        self._pending.append((tmp, target))
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        return target

    def _commit(self) -> None:
        # Ctrl-C between two renames would leave a new program beside an old setup sheet:
        # SIGINT/SIGTERM are held for the microseconds of the renames and delivered after.
        with _signals_held():
            for tmp, target in self._pending:
                os.replace(tmp, target)
            self._pending.clear()

    def _discard(self) -> None:
        for tmp, _ in self._pending:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        self._pending.clear()


@contextlib.contextmanager
def _signals_held():
    """Defer SIGINT and SIGTERM for the duration of the block, then deliver them.

    A Python-level handler records the signal instead of raising; on exit the
    previous handlers come back and a recorded signal is raised again. (Masking
    with pthread_sigmask is not enough: the kernel hands a process-directed signal
    to any thread that does not block it, and Python then raises it in the main
    thread at once.) Handlers can only be changed from the main thread; elsewhere
    the block runs unprotected, as KeyboardInterrupt never reaches such threads.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held = (signal.SIGINT, signal.SIGTERM)
    received: list[int] = []
    previous = {}
    try:
        for s in held:
            old = signal.getsignal(s)
            if old is None:          # installed outside Python: leave it alone
                continue
            previous[s] = signal.signal(s, lambda signum, frame: received.append(signum))
        yield
    finally:
        for s, old in previous.items():
            signal.signal(s, old)
        if received:
            signal.raise_signal(received[0])


@contextlib.contextmanager
def atomic_outputs():
    """Context manager staging output files; all are renamed into place on success.

    >>> with atomic_outputs() as out:            # doctest: +SKIP
    ...     out.write("toolpaths/a.ngc", program)
    ...     out.write("toolpaths/a.setup.json", sheet)
    """
    outputs = _Outputs()
    try:
        yield outputs
    except BaseException:
        outputs._discard()
        raise
    try:
        outputs._commit()
    except BaseException:
        outputs._discard()
        raise


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write one file atomically."""
    with atomic_outputs() as out:
        return out.write(path, data)
