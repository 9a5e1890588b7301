"""Damaged or foreign log content: one error class, what counts as damage, one guard.

A log is read from bytes another program, a full disk or a flipped bit may have written:
any exception its content raises while it is decoded or interpreted (a length past the
file's end, a huge length that exhausts memory, a field of the wrong type, a missing key)
is damage of that log, not a bug of hmpc. :func:`reading` turns those exceptions into
:class:`DamagedLogError` (a ``ValueError``; the command line exits 2 with its one line).

Light on purpose (the standard library only).
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator
from pathlib import Path

__all__ = ["CONTENT_ERRORS", "DamagedLogError", "reading"]

#: what damaged or foreign content raises while it is decoded or interpreted
CONTENT_ERRORS = (ValueError, TypeError, KeyError, IndexError, AttributeError, LookupError,
                  ArithmeticError, MemoryError, RecursionError, struct.error, EOFError,
                  UnicodeError, AssertionError, RuntimeError, NotImplementedError)


class DamagedLogError(ValueError):
    """A log whose content cannot be interpreted; the message is one line naming the file."""


def describe(exc: BaseException) -> str:
    """``Type: first line`` of an exception, at most 160 characters."""
    text = " ".join(str(exc).split())[:160]
    return type(exc).__name__ + (f": {text}" if text else "")


def _deliberate(exc: BaseException) -> bool:
    """Whether ``exc`` was raised on purpose: hmpc's own errors, the CLI framework's exits."""
    module = type(exc).__module__ or ""
    return module.split(".")[0] in ("hmpc_cli", "click", "typer")


@contextlib.contextmanager
def reading(path: Path | str, what: str = "") -> Iterator[None]:
    """Turns :data:`CONTENT_ERRORS` raised in the block into :class:`DamagedLogError`.

    ``what``: the part being read (e.g. ``/mpc/solve``), for the message. hmpc's own
    errors (a :class:`DamagedLogError`, a figure's input error: they already say what is
    wrong) and the command line's exits pass unchanged; OSError (the disk, not the
    content) and KeyboardInterrupt are not caught.
    """
    try:
        yield
    except CONTENT_ERRORS as exc:
        if _deliberate(exc):
            raise
        part = f" ({what})" if what else ""
        raise DamagedLogError(f"{path}: damaged log: its content cannot be read{part}: "
                              f"{describe(exc)}") from None
