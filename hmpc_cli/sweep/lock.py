"""The exclusive lock of a sweep's output directory (two sweeps never write one directory)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

__all__ = ["SweepLockedError", "output_lock"]


class SweepLockedError(Exception):
    """Another sweep holds the output directory's lock.

    Attributes:
        out: the directory; pid: the holder's process id (0 if unknown).
    """

    def __init__(self, out: Path, pid: int) -> None:
        super().__init__(f"{out}: another sweep is writing here (pid {pid})")
        self.out, self.pid = out, pid


@contextlib.contextmanager
def output_lock(out: Path) -> Iterator[None]:
    """Holds ``<out>/.lock`` (``fcntl.flock``, holding the pid) while a sweep writes there.

    Raises:
        SweepLockedError: another process holds the lock (nothing is written).
    """
    import fcntl

    out.mkdir(parents=True, exist_ok=True)
    fd = os.open(out / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
        os.close(fd)
        raise SweepLockedError(out, int(text) if text.isdigit() else 0) from None
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock
