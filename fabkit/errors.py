"""The error hierarchy. Exit codes are assigned here and nowhere else.

Library code raises these; only :func:`fabkit.cli.main` turns them into
exit codes and one printed line. Nothing in the library calls ``sys.exit``
or prints.
"""

from __future__ import annotations


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
