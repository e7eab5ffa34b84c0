"""The error hierarchy. Exit codes are assigned here and nowhere else.

Library code raises these; only :func:`fabkit.cli.main` turns them into
exit codes and one printed line. Nothing in the library calls ``sys.exit``
or prints.
"""

from __future__ import annotations

import os


class FabkitError(Exception):
    """Base class of every error fabkit reports to a user."""

    exit_code = 2


class SpecError(FabkitError):
    """Bad input: unreadable file, bad YAML, unknown/missing key, bad value,
    unsafe expression, a design the machine cannot cut (depth over a limit),
    or a request whose size would exceed a guard. Exit 2.

    The message is one line: ``<file>: <key>: <what is wrong>``.
    """

    exit_code = 2

    def __init__(self, message: str, *, file: str | None = None, key: str | None = None):
        self.file = file
        self.key = key
        self.detail = message
        super().__init__(message)

    def with_location(self, file: str | None = None, key: str | None = None) -> "SpecError":
        """A copy of this error that names ``file`` (and ``key`` if not set yet)."""
        err = type(self)(self.detail, file=self.file or file, key=self.key or key)
        return err

    def __str__(self) -> str:
        parts = [one_line(p, 200) for p in (self.file, self.key) if p]
        parts.append(one_line(self.detail, 2000))
        return ": ".join(parts)


class OutputError(SpecError):
    """An output cannot be written (a full disk, a quota, a read-only or missing
    folder, an I/O error). Exit 2, like bad input: nothing is written or replaced,
    and the line names the output: ``<path>: cannot write output: No space left on device``."""


def one_line(text: object, limit: int) -> str:
    """``text`` as one printable line of at most ``limit`` characters: line breaks
    and control characters (from keys and file names in a hostile spec) escaped."""
    s = str(text)
    if any(not ch.isprintable() and ch != " " for ch in s):
        s = "".join(ch if ch.isprintable() or ch == " " else repr(ch)[1:-1] for ch in s)
    return s if len(s) <= limit else s[: limit - 3] + "..."


class DesignError(FabkitError):
    """A check failed: the design is unsafe, or the verified cut is out of
    tolerance. Exit 1. The command may still have written its outputs."""

    exit_code = 1


EXIT_OK = 0
EXIT_CHECK_FAILED = DesignError.exit_code
EXIT_BAD_INPUT = SpecError.exit_code
EXIT_INTERRUPTED = 130
EXIT_INTERNAL = 3
#: interrupted (Ctrl-C) after outputs were renamed into place: each output named is complete
EXIT_INTERRUPTED_WRITTEN = 4


# ----------------------------------------------------------------------------
# what a Ctrl-C means at each point of a run
# ----------------------------------------------------------------------------
class RunState:
    """Where the command line's run is, for the Ctrl-C handler :func:`fabkit.cli.entry`
    installs: ``phase`` "start" (parsing, importing), "run" (the command's work),
    "exit" (the command returned ``code``); ``written`` the outputs renamed into place
    so far (set by :mod:`fabkit.io` as it commits them); ``interrupted`` once a SIGINT
    has come (an error after it is the interrupt's doing, not a bug)."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.phase = "start"
        self.command: str | None = None
        self.code = 0
        self.written: list[str] = []
        self.interrupted = False         # a SIGINT has come (set by the handler)


RUN = RunState()


def outputs_written(paths) -> None:
    """Record outputs renamed into place (called by :mod:`fabkit.io` once they are)."""
    RUN.written.extend(str(p) for p in paths)


def interrupted_line() -> tuple[str, int]:
    """The line and exit code for a Ctrl-C now: after outputs were written, code
    EXIT_INTERRUPTED_WRITTEN naming them; before, EXIT_INTERRUPTED (nothing written)."""
    who = f"fabkit {RUN.command}" if RUN.command else "fabkit"
    if RUN.written:
        names = ", ".join(RUN.written[:6]) + (f" and {len(RUN.written) - 6} more" if len(RUN.written) > 6 else "")
        return (f"{who}: interrupted after writing {one_line(names, 2000)} (complete); any other output of this run "
                "was not written", EXIT_INTERRUPTED_WRITTEN)
    if RUN.phase == "start":
        return f"{who}: interrupted while starting; nothing written", EXIT_INTERRUPTED
    return f"{who}: interrupted; existing outputs left intact", EXIT_INTERRUPTED


def pause_at(point: str) -> None:
    """A hook for testing Ctrl-C at the edges of a run: with ``FABKIT_PAUSE_AT=point``
    (start, staged, written, exit) the process says ``fabkit: paused at <point>`` on stderr and
    waits up to 60 s for a signal there. Without it, nothing."""
    if os.environ.get("FABKIT_PAUSE_AT") != point:
        return
    import time

    os.write(2, f"fabkit: paused at {point}\n".encode())
    time.sleep(60)
