"""Sweep tables and run traces as the figures and the analyses read them.

A sweep's ``results.csv`` and its own ``sweep.toml``, table cells, log paths relative to a
table, and a run's positions in its drawing plane (:class:`RunTrace`). Every bad input is a
:class:`FigureInputError` with a one-line message.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["FigureInputError", "RunTrace", "blamed_on", "count_cell", "load_trace",
           "not_run_yet", "parse_bool", "pooled_counts", "read_table", "resolve_log",
           "resolve_run_log", "resolve_table", "sweep_spec", "trace_of"]

_TRUE = {"true", "1", "yes"}
_FALSE = {"false", "0", "no"}


class FigureInputError(ValueError):
    """Bad figure input (table, columns, logs, options); the message is one line.

    ``source``: the input directory it came from, once known (:func:`blamed_on`), so that
    the command can name the option that gave it; None until then.
    """

    source: Path | None = None


@contextmanager
def blamed_on(directory: str | Path) -> Iterator[None]:
    """Records ``directory`` as the ``source`` of a :class:`FigureInputError` raised inside.

    An error that already has a source (an inner input) keeps it.
    """
    try:
        yield
    except FigureInputError as exc:
        if exc.source is None:
            exc.source = Path(directory)
        raise


def resolve_run_log(path: str | Path) -> Path:
    """The log itself, or run.mcap when ``path`` is a run directory holding one.

    A run.mcap that is not there is its trajectory log (``trace.mcap`` beside it) if there
    is one (:func:`hmpc_cli.log.rundata.resolve_log`).
    """
    from hmpc_cli.log.rundata import resolve_log

    try:
        return resolve_log(Path(path))
    except ValueError:
        return Path(path)


def sweep_spec(directory: str | Path) -> dict:
    """The sweep's own file as it ran (its output directory's ``sweep.toml``; {} if none)."""
    import tomllib

    try:
        return tomllib.loads((Path(directory) / "sweep.toml").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def resolve_table(path: str | Path) -> Path:
    """The table itself, or results.csv when `path` is a sweep directory holding one."""
    path = Path(path)
    if path.is_dir() and (path / "results.csv").is_file():
        return path / "results.csv"
    return path


def read_table(path: Path, required: Iterable[str]) -> list[dict[str, str]]:
    """Reads a CSV table with a header; checks it exists, has rows and the `required` columns."""
    path = Path(path)
    if not path.is_file():
        run = path.is_dir() and any((path / f).is_file() for f in ("run.mcap", "trace.mcap"))
        raise FigureInputError(f"{path}: " + (
            "a run's directory, not a table: give a sweep's output directory or its "
            "results.csv (a run's figures: hmpc plot fig2, timing)" if run
            else "no such table"))
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            columns = list(reader.fieldnames or [])
            rows = [dict(r) for r in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise FigureInputError(f"{path}: cannot read table ({exc})") from None
    missing = [c for c in required if c not in columns]
    if missing:
        have = ", ".join(columns) if columns else "none"
        named = ", ".join(c + _column_hint(c, columns) for c in missing)
        raise FigureInputError(f"{path}: missing column(s) {named} (has: {have})")
    if not rows:
        raise FigureInputError(f"{path}: table has no rows")
    seen: dict[str, int] = {}
    for line, row in enumerate(rows, start=2):  # a sweep's table holds each run once
        rid = row.get("run_id")
        if rid and seen.setdefault(rid, line) != line:
            raise FigureInputError(f"{path}:{line}: run_id {rid!r} again (line "
                                   f"{seen[rid]}): a sweep's table holds each run once; "
                                   f"keep one of the two rows")
    return rows


def _column_hint(name: str, columns: list[str]) -> str:
    """`` (did you mean 'set.x'?)`` for a column the table has under another name, else ''.

    A sweep's fixed settings are its ``set.<key>`` columns; else a near spelling.
    """
    from hmpc_cli.core.text import did_you_mean

    return f" (did you mean 'set.{name}'?)" if f"set.{name}" in columns else \
        did_you_mean(name, columns)


def pooled_counts(table: Path, rows: list[dict[str, str]], key, columns: tuple[str, ...]
                  ) -> dict[Any, list[int]]:
    """Per ``key(row)``: the sums of the count ``columns`` over its rows that hold them.

    A row whose first column is empty (e.g. flown before hmpc recorded it) is left out;
    ``key(row)`` None leaves a row out too.

    Raises:
        FigureInputError: a counted cell that is not a whole number (file:line: column).
    """
    out: dict[Any, list[int]] = {}
    for line, row in enumerate(rows, start=2):
        k = key(row)
        if k is None or not (row.get(columns[0]) or "").strip():
            continue
        sums = out.setdefault(k, [0] * len(columns))
        for i, col in enumerate(columns):
            sums[i] += count_cell(row.get(col), f"{table}:{line}: {col}")
    return out


def count_cell(text: str | None, where: str) -> int:
    """A table cell that holds a count.

    Raises:
        FigureInputError: it does not (``where`` names the cell: file:line: column).
    """
    try:
        return int(text)
    except (TypeError, ValueError):
        raise FigureInputError(f"{where}: expected a count, got {text!r}") from None


def not_run_yet(directory: str | Path) -> bool:
    """Whether a sweep directory holds no run yet: no results.csv, or its header alone.

    A sweep writes its table's header before its first run ends; a table that is there
    but cannot be read counts as holding runs (reading it says what is wrong).
    """
    path = Path(directory) / "results.csv"
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            next(reader, None)
            return next(reader, None) is None
    except FileNotFoundError:
        return True
    except (OSError, UnicodeDecodeError, csv.Error):
        return False


def parse_bool(value: str | None, where: str) -> bool:
    """Parses a table cell like True/False (also true/1/yes, false/0/no)."""
    text = (value or "").strip().lower()
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise FigureInputError(f"{where}: expected True or False, got {value!r}")


def resolve_log(table_path: Path, log: str | None, where: str) -> Path:
    """Resolves a log path relative to the table's directory; checks that the file exists."""
    text = (log or "").strip()
    if not text:
        raise FigureInputError(f"{where}: empty log path")
    path = Path(text)
    if not path.is_absolute():
        path = Path(table_path).parent / path
    path = resolve_run_log(path)
    if not path.is_file():
        raise FigureInputError(f"{where}: log {path} does not exist")
    return path


@dataclass
class RunTrace:
    """Positions of one recorded run: `t` (s), `xy` (n x 2, NaN where not finite), run info."""

    path: Path
    t: np.ndarray
    xy: np.ndarray
    scenario: dict = field(default_factory=dict)
    logged_success: bool | None = None  # the log's own /run/summary verdict, if any
    complete: bool = True
    damage: str = ""  # why reading stopped at a damaged chunk ('' if it did not)
    geometry: Any = None  # the log's GeometryRec (None: none logged)

    @property
    def system(self) -> dict:
        """The scenario's system parameters (radius, guards, goal, ...)."""
        return dict(self.scenario.get("system") or {})


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else math.nan


def load_trace(path: Path) -> RunTrace:
    """Reads a run log's positions in its drawing plane from /sim/state, events spliced in.

    The plane is the log geometry's ``plane`` (two state names; default the first two
    states). The exact pre- and post-reset positions of /sim/event are inserted at the
    event times, so drawn bounces touch the guard instead of cutting the corner between
    logged samples.
    """
    from hmpc_cli.log.rundata import read_run

    try:
        run = read_run(path, with_plans=False)
    except ValueError as exc:
        raise FigureInputError(f"{path}: cannot read log ({exc})") from None
    return trace_of(run, Path(path))


def trace_of(run: Any, path: Path) -> RunTrace:
    """The positions of a run already read by ``read_run``, as :func:`load_trace` gives them."""
    plane = list(run.geometry.plane) if run.geometry is not None else []
    i, j = (run.state_names.index(plane[0]), run.state_names.index(plane[1])) \
        if len(plane) == 2 and set(plane) <= set(run.state_names) else (0, 1)
    points: list[tuple[float, int, int, float, float]] = []  # (t, kind, seq, a, b)
    if run.x.shape[1] > max(i, j):
        points += [(float(t), 1, k, _num(x[i]), _num(x[j]))
                   for k, (t, x) in enumerate(zip(run.t, run.x, strict=True))]
    if not points:
        raise FigureInputError(f"{path}: log has no /sim/state positions")
    for k, ev in enumerate(run.events):
        for m, x in enumerate((ev.x_before, ev.x_after)):
            if len(x) > max(i, j) and math.isfinite(ev.t):
                points.append((ev.t, 0, 2 * k + m, _num(x[i]), _num(x[j])))
    points.sort(key=lambda p: (p[0], p[1], p[2]))
    arr = np.array([(p[0], p[3], p[4]) for p in points], dtype=float)
    ok = run.summary.success if run.summary is not None else None
    return RunTrace(Path(path), arr[:, 0], arr[:, 1:3], run.scenario, ok, run.complete,
                    run.damage, run.geometry)
