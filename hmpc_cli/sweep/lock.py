"""A sweep's output directory: its owner and its exclusive lock (two sweeps never share one).

A directory belongs to the sweep that made it (the name in its ``sweep.toml``,
:func:`owner_problem`); while a sweep writes there it holds the lock (:func:`output_lock`).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from hmpc_cli.core.paths import first_names

__all__ = ["SweepLockedError", "is_sweep_output", "owner_problem", "output_lock"]

#: the file that makes a directory a sweep's (its owner: :func:`owner_problem`)
SWEEP_FILE = "sweep.toml"
#: a sweep's table (:func:`hmpc_cli.sweep.table.write_results`)
TABLE_FILE = "results.csv"


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


def owner_problem(out: Path, name: str, option: str = "--out", text: str | None = None
                  ) -> str | None:
    """Why sweep ``name`` may not write into ``out``, or None; reads only.

    ``out`` is free when it does not exist or is empty (but for a lock); else it must be
    a sweep's directory (its ``sweep.toml``) of a sweep of the same name: resuming
    or extending it. A directory of another sweep, or one that is no sweep's, is refused.
    A stored ``sweep.toml`` without a name (an older hmpc's, of a file without ``name``)
    is this sweep's when it is ``text``, the sweep file's own text.
    ``option``: the option the reason advises to change.
    """
    import tomllib

    try:
        if not out.exists():
            return None
        entries = sorted(p.name for p in out.iterdir() if p.name != ".lock")
    except OSError as exc:
        return f"cannot read it ({exc.strerror or exc})"
    if not entries:
        return None
    stored = out / SWEEP_FILE
    if not stored.is_file():
        shown = first_names(entries)
        return (f"is not a sweep's directory (no sweep.toml; it holds {shown}): choose a new "
                f"or empty {option}")
    try:
        stored_text = stored.read_text(encoding="utf-8")
        owner = tomllib.loads(stored_text).get("name")
    except (OSError, ValueError) as exc:
        return f"its sweep.toml cannot be read ({exc}): choose another {option}"
    if owner is None and text is not None:
        return None if stored_text == text else (
            f"its sweep.toml names no sweep and is not this sweep file: choose another "
            f"{option} (the same sweep resumes in its own directory)")
    if owner != name:
        return (f"belongs to sweep {owner!r} (its sweep.toml), not {name!r}: choose another "
                f"{option} (the same sweep resumes in its own directory)")
    return None


def is_sweep_output(directory: Path) -> bool:
    """Whether ``directory`` is a sweep's output, to read.

    That is: its ``sweep.toml`` is there (the mark :func:`owner_problem` reads, ``hmpc
    sweep --out`` wrote it) or its table alone (a committed ``results.csv``, the run
    directories left out).
    """
    return (directory / SWEEP_FILE).is_file() or (directory / TABLE_FILE).is_file()
