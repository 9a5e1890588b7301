"""The trajectory logs a results page keeps beside the run logs it draws.

A committed page cannot hold every run log (about 0.5 MB each), so the report writes each
drawn run's trajectory log (:mod:`hmpc_cli.log.trace`, about 40 kB) beside it; a fresh
clone draws the same figures from those alone.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator
from pathlib import Path

from hmpc_cli.analysis.tables import read_table, resolve_table

__all__ = ["deferred_traces", "keep_traces", "sweep_logs"]

#: the logs :func:`keep_traces` noted inside :func:`deferred_traces` (innermost last)
_NOTED: list[list[Path]] = []


@contextlib.contextmanager
def deferred_traces() -> Iterator[list[Path]]:
    """:func:`keep_traces` inside only notes its logs, in the list yielded (written later).

    The figures read a run log itself when it is here, never its trajectory log.
    """
    _NOTED.append([])
    try:
        yield _NOTED[-1]
    finally:
        _NOTED.pop()


def sweep_logs(directory: Path) -> list[Path]:
    """The run logs a sweep's table lists (whether or not they are here)."""
    table = resolve_table(directory)
    return [table.parent / row["log"] for row in read_table(table, ["log"])
            if (row.get("log") or "").strip()]


def keep_traces(logs: Iterable[Path]) -> None:
    """Writes the trajectory log beside each run log that is here (unless it is up to date).

    Inside :func:`deferred_traces`: only notes the logs.

    A log that cannot be copied (damaged) gets none: the figures read it themselves and
    name what they leave out.
    """
    from hmpc_cli.log.trace import TRACE_NAME, write_trace

    if _NOTED:
        _NOTED[-1].extend(Path(log) for log in logs)
        return
    for log in logs:
        log = Path(log)
        if log.is_dir():
            log = log / "run.mcap"
        if not log.is_file():
            continue
        trace = log.with_name(TRACE_NAME)
        if trace.is_file() and trace.stat().st_mtime >= log.stat().st_mtime:
            continue
        try:
            write_trace(log, trace)
        except ValueError:
            continue
