"""Atomic output files.

Every file fabkit writes goes through :func:`atomic_outputs`: the content is
written to a temporary file beside the target, flushed and fsynced, and only
then renamed over the target (``os.replace`` is atomic on POSIX). Several
outputs of one command (a program and its setup sheet) are renamed together
at the end, so an error, Ctrl-C or crash before that leaves every existing
output intact and no temporary file behind.

Modes: a new file gets ``0666`` less the umask, as ``open()`` would give it; a
replaced file keeps its mode (a program another user's machine controller reads
stays readable). :func:`check_outputs` refuses, before any work, an output that
is one of the inputs, is not a regular file, names a folder, or lies under a
path that cannot become a folder.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import stat
import tempfile
import threading
from pathlib import Path

from .errors import OutputError, SpecError, outputs_written, pause_at


#: characters of the target's name kept in the temporary name (at most 4 bytes each; the rest is
#: ".", 8 random characters and ".tmp"): a temporary name stays within NAME_MAX
#: (255 bytes) whatever the target's name
_TMP_NAME_KEEP = 48


def _umask() -> int:
    """The process umask, read without changing it where the kernel tells it."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def _mode_for(target: Path) -> int:
    """Permission bits for ``target``: those of the file it replaces, else 0666 less the umask."""
    try:
        st = os.stat(target)
    except OSError:
        return 0o666 & ~_umask()
    return stat.S_IMODE(st.st_mode)


def _real_target(target: Path) -> Path:
    """A symlink is written through (the link stays, its file is replaced)."""
    return Path(os.path.realpath(target)) if target.is_symlink() else target


def check_outputs(outputs: dict, inputs=()) -> None:
    """Refuse bad output paths before any work (SpecError, exit 2, nothing written).

    ``outputs``: {option or description: path or None}; ``inputs``: paths read by the
    command. An output is refused when it is one of the inputs or another output,
    exists and is not a regular file (folder, device, pipe, socket), its folder
    cannot be created (a file in the way) or written, or its name is too long.
    """
    seen: dict = {}
    ins = [Path(p) for p in inputs if p is not None]
    for key, path in outputs.items():
        if path is None:
            continue
        target = Path(path)
        shown = str(target)
        real = os.path.realpath(target)
        for src in ins:
            same = os.path.realpath(src) == real
            with contextlib.suppress(OSError):
                same = same or os.path.samefile(src, target)
            if same:
                raise SpecError(f"output {shown} is the input {src}: choose another output path", key=key)
        if real in seen:
            raise SpecError(f"output {shown} is also given for {seen[real]}", key=key)
        seen[real] = key
        try:
            st = os.stat(target)
        except (FileNotFoundError, NotADirectoryError):
            st = None
        except OSError as exc:
            if exc.errno == errno.ENAMETOOLONG:
                raise SpecError("file name too long for the file system (at most 255 bytes per name)",
                                file=shown, key=key) from None
            raise SpecError(f"cannot use output {shown}: {exc.strerror}", key=key) from None
        if st is not None:
            if stat.S_ISDIR(st.st_mode):
                raise SpecError("output path is a folder", file=shown, key=key)
            if not stat.S_ISREG(st.st_mode):
                raise SpecError("output path exists and is not a regular file (a device, pipe or socket); "
                                "fabkit replaces only regular files", file=shown, key=key)
        directory = Path(real).parent
        existing = directory
        while not existing.exists() and existing != existing.parent:
            existing = existing.parent
        if not existing.is_dir():
            raise SpecError(f"cannot create output folder {directory}: {existing} is not a folder",
                            file=shown, key=key)
        if not os.access(existing, os.W_OK | os.X_OK):
            raise SpecError(f"cannot write in {existing}: permission denied", file=shown, key=key)
        try:
            limit = os.pathconf(existing, "PC_NAME_MAX")
        except (OSError, ValueError):
            limit = 255
        for part in Path(real).relative_to(existing).parts:
            if len(os.fsencode(part)) > limit:
                raise SpecError(f"file name longer than {limit} bytes", file=shown, key=key)


class _Outputs:
    def __init__(self) -> None:
        self._pending: list[tuple[str, Path]] = []

    def write(self, path: str | os.PathLike, data: bytes | str) -> Path:
        """Stage ``data`` for ``path``; it appears there when the block exits cleanly."""
        target = _real_target(Path(path))
        if isinstance(data, str):
            data = data.encode("utf-8")
        directory = target.parent if str(target.parent) else Path(".")
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise SpecError(f"cannot create output folder: {exc.strerror}", file=str(directory)) from None
        if target.is_dir():
            raise SpecError("output path is a folder", file=str(target))
        if target.exists() and not target.is_file():
            raise SpecError("output path exists and is not a regular file", file=str(target))
        try:
            fd, tmp = tempfile.mkstemp(prefix=f".{target.name[:_TMP_NAME_KEEP]}.", suffix=".tmp", dir=directory)
        except OSError as exc:
            raise SpecError(f"cannot write output: {exc.strerror}", file=str(target)) from None
        self._pending.append((tmp, target))
        try:
            with os.fdopen(fd, "wb") as fh:
                os.fchmod(fh.fileno(), _mode_for(target))   # mkstemp gives 0600
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
        except OSError as exc:  # a full disk, a quota, an I/O error: the temporary is discarded
            raise OutputError(f"cannot write output: {exc.strerror or exc}", file=str(target)) from None
        return target

    def _commit(self) -> None:
        # Ctrl-C between two renames would leave a new program beside an old setup sheet:
        # SIGINT/SIGTERM are held for the microseconds of the renames and delivered after.
        # Once renamed, the outputs are recorded before the held signal is delivered: a Ctrl-C
        # from then on reports them written (fabkit.errors.interrupted_line), never "intact".
        with _signals_held():
            done = []
            try:
                for tmp, target in self._pending:
                    try:
                        os.replace(tmp, target)
                    except OSError as exc:
                        raise OutputError(f"cannot write output: {exc.strerror or exc}", file=str(target)) from None
                    done.append(target)
            finally:
                outputs_written(done)
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
        pause_at("staged")            # every output made, none renamed into place yet
        outputs._commit()
    except BaseException:
        outputs._discard()
        raise
    pause_at("written")


def text_of(data: bytes, path, limit: int) -> str:
    """``data`` (the bytes :func:`read_regular` read from ``path``) as text: SpecError (exit
    2, naming the file) for more than ``limit`` bytes, invalid UTF-8 or NUL bytes."""
    from .errors import SpecError

    p = str(path)
    if len(data) > limit:
        raise SpecError(f"file too large (limit {limit} bytes)", file=p)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise SpecError("not a text file (invalid UTF-8)", file=p) from None
    if "\x00" in text:
        raise SpecError("not a text file (NUL bytes)", file=p)
    return text


def read_regular(path, limit: int, noun: str = "input") -> bytes:
    """The first ``limit + 1`` bytes of the regular file ``path`` (the caller refuses more).

    Opened without blocking and checked with fstat on the open descriptor (no race
    between the check and the read): a named pipe, a device or a socket is refused
    (SpecError, exit 2) instead of blocking forever or reading without end. ``noun``
    names what the file should be in the messages ("spec", "track export")."""
    p = str(path)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        raise SpecError("file not found", file=p) from None
    except IsADirectoryError:
        raise SpecError(f"is a folder, not a {noun} file", file=p) from None
    except OSError as exc:
        raise SpecError(f"cannot read: {exc.strerror or exc}", file=p) from None
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise SpecError(f"is a folder, not a {noun} file", file=p)
        if not stat.S_ISREG(mode):
            kind = ("a named pipe (FIFO)" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
                    else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
            raise SpecError(f"is {kind}, not a regular file: give the {noun} as a file", file=p)
        with os.fdopen(fd, "rb", closefd=False) as fh:
            return fh.read(limit + 1)
    except OSError as exc:
        raise SpecError(f"cannot read: {exc.strerror or exc}", file=p) from None
    finally:
        os.close(fd)


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write one file atomically."""
    with atomic_outputs() as out:
        return out.write(path, data)
