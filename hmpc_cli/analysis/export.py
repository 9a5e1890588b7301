"""``hmpc replay --export``: one flat table per topic (CSV, or Parquet with pyarrow).

Flattening of a message (a JSON object):

* nested objects become dotted columns (``schedule.t0``, ``x.px``);
* lists of scalars become indexed columns (``w[0]``, ``w[1]``, ...);
* lists holding objects or lists (``x_plan``, ``candidates``, the ``plan`` array of named
  nodes) go to a separate table ``<topic>_<field>`` with one row per element, keyed by
  ``msg`` and ``index`` (the element's position); inside such a row a further list of
  objects is one JSON-string column.

A container's cells are its elements': an empty object or list writes no cell (and no
row in a list's table), so it reads as an absent field does (e.g. ``body`` of a system
without a skeleton, a final schedule's ``schedule.guards``, ``warnings`` of a run
without any).

Each topic's table has one row per message. Every row of every table starts with
``msg``, its message's position among its topic's exported messages (0, 1, ...: a child
row joins its message's row on ``msg``), and ``msg_t``, the message's log time [s]
(``LogMessage.t``, the same float in the topic's table and its child tables; two messages
of one topic may share it), then the message's (or the element's) fields; ``t`` is a
message's own field, where it has one.
``info.json`` holds the run info, the metadata,
the attached scenario text, the filters and the tables written (``files``). A directory
takes an export when it is new, empty or an earlier export's: that export's tables are
replaced, those this one does not write removed (no stale topic is left beside it).
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path
from typing import Any

from hmpc_cli.core.jsonio import dumps
from hmpc_cli.core.paths import first_names

__all__ = ["ExportError", "check_format", "earlier_export", "flatten", "tables",
           "write_export"]

FORMATS = ("csv", "parquet")


class ExportError(Exception):
    """The export cannot be written (unknown format, missing pyarrow, unwritable directory)."""


def _scalar(v: Any) -> bool:
    """Whether ``v`` is a JSON scalar."""
    return v is None or isinstance(v, (str, bool, int, float))


def _into(value: Any, key: str, row: dict, nested: dict | None) -> None:
    """Flattens ``value`` under column ``key`` into ``row``; lists of objects to ``nested``."""
    if isinstance(value, dict):
        for k, v in value.items():
            _into(v, f"{key}.{k}" if key else str(k), row, nested)
    elif isinstance(value, list) and all(_scalar(v) for v in value):  # [] too: no cell
        for i, v in enumerate(value):
            row[f"{key}[{i}]"] = v
    elif isinstance(value, list):
        if nested is None:
            row[key] = dumps(value, separators=(",", ":"))
        else:
            nested[key] = value
    else:
        row[key] = value


def flatten(data: dict, nested: dict | None = None) -> dict:
    """One flat row of a message (see the module docstring).

    Args:
        data: the message.
        nested: receives ``{field: list}`` for lists holding objects or lists; None
            writes them as JSON-string columns instead.
    """
    row: dict = {}
    _into(data, "", row, nested)
    return row


def _table_name(topic: str) -> str:
    """``/mpc/solve`` -> ``mpc_solve``."""
    return topic.strip("/").replace("/", "_").replace(".", "_") or "root"


def tables(messages: list) -> dict[str, list[dict]]:
    """Rows per table name: one table per topic, one per (topic, list-of-objects field).

    Every row starts with ``msg``, its message's position among the topic's exported
    messages (0, 1, ...: a child row joins its message's row on it), and ``msg_t``, the
    message's log time [s] (the same float in both tables; two messages of a topic may
    share it).
    """
    out: dict[str, list[dict]] = {}
    for m in messages:
        name = _table_name(m.topic)
        nested: dict[str, list] = {}
        rows = out.setdefault(name, [])
        key0 = {"msg": len(rows), "msg_t": m.t}
        rows.append({**key0, **flatten(m.data, nested)})
        for key, items in nested.items():
            child = out.setdefault(f"{name}_{_table_name(key)}", [])
            for i, item in enumerate(items):
                row = flatten(item if isinstance(item, dict) else {key: item}, None)
                child.append({**key0, "index": i, **row})
    return out


def _columns(rows: list[dict]) -> list[str]:
    """The union of the rows' columns in first-seen order."""
    seen: dict[str, None] = {}
    for r in rows:
        for k in r:
            seen.setdefault(k, None)
    return list(seen)


def _write_csv(path: Path, rows: list[dict]) -> None:
    """Writes rows as CSV (missing cells and None empty)."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=_columns(rows), restval="")
        writer.writeheader()
        for r in rows:
            writer.writerow({k: "" if v is None else v for k, v in r.items()})


def _arrow_column(values: list) -> tuple[list, str]:
    """A column's values and arrow type name: bool, int64, float64 or string."""
    kinds = {type(v) for v in values if v is not None}
    if kinds <= {bool} and kinds:
        return values, "bool_"
    if kinds <= {int} and kinds:
        return values, "int64"
    if kinds <= {int, float} and kinds:
        return [None if v is None else float(v) for v in values], "float64"
    return [None if v is None else (v if isinstance(v, str) else dumps(v))
            for v in values], "string"


def _write_parquet(path: Path, rows: list[dict]) -> None:
    """Writes rows as a Parquet file (one typed column per flattened field)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    arrays, names = [], []
    for col in _columns(rows):
        values, kind = _arrow_column([r.get(col) for r in rows])
        arrays.append(pa.array(values, type=getattr(pa, kind)()))
        names.append(col)
    pq.write_table(pa.Table.from_arrays(arrays, names=names), path)


def check_format(fmt: str) -> None:
    """Checks an export format and, for Parquet, that pyarrow is installed.

    Raises:
        ExportError: unknown format or pyarrow missing.
    """
    if fmt not in FORMATS:
        raise ExportError(f"--format: unknown format {fmt!r} (choose from {', '.join(FORMATS)})")
    if fmt == "parquet":
        try:
            import pyarrow.parquet  # noqa: F401
        except ImportError:
            raise ExportError("--format parquet needs pyarrow: pip install pyarrow "
                              "(or pip install -e '.[parquet]')") from None


def write_export(out: Path, messages: list, info: dict, fmt: str = "csv") -> list[Path]:
    """Writes the tables of ``messages`` and ``info.json`` into directory ``out``, whole.

    Everything is written into a staging directory inside ``out`` (the same file system)
    and then moved in, ``info.json`` last, an earlier export's other tables removed: a
    failure while writing (a full disk) leaves ``out`` as it was, or none if it was new.

    Args:
        out: output directory (created).
        messages: the (filtered) log messages.
        info: what ``info.json`` holds (run info, scenario text, filters, ...).
        fmt: ``csv`` or ``parquet``.

    Returns:
        The written files.

    Raises:
        ExportError: unknown format, pyarrow missing for Parquet, or ``out`` unwritable.
    """
    import shutil
    import tempfile

    from hmpc_cli.core import signals

    check_format(fmt)
    earlier = earlier_export(out)
    made = next((d for d in [*reversed(out.absolute().parents), out.absolute()]
                 if not d.exists()), None)  # the first directory this export creates
    stage = None
    try:
        out.mkdir(parents=True, exist_ok=True)
        _remove_dead_stages(out)
        stage = Path(tempfile.mkdtemp(prefix=f".hmpc-export-{os.getpid()}-", dir=out))
        names = []
        for name, rows in tables(messages).items():
            (_write_csv if fmt == "csv" else _write_parquet)(stage / f"{name}.{fmt}", rows)
            names.append(f"{name}.{fmt}")
        (stage / "info.json").write_text(dumps({**info, "files": names}, indent=2,
                                               ensure_ascii=False) + "\n", encoding="utf-8")
        with signals.deferred():  # moved in whole: a stop meanwhile acts after
            for name in [*names, "info.json"]:
                (stage / name).replace(out / name)
            for name in set(earlier) - set(names):  # the earlier export's own
                (out / name).unlink(missing_ok=True)
    except BaseException as exc:  # a full disk, a stop, unwritable content: as it was
        if made is not None:
            shutil.rmtree(made, ignore_errors=True)
        if isinstance(exc, OSError):
            raise ExportError(f"{out}: cannot write ({exc.strerror or exc})") from None
        raise
    finally:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
    signals.check()  # a stop held while the files were moved in acts now
    return [out / n for n in [*names, "info.json"]]


def _remove_dead_stages(out: Path) -> None:
    """Removes the staging directories in ``out`` of exports whose process is gone."""
    import shutil

    from hmpc_cli.core.machine import process_exists

    for d in out.glob(".hmpc-export-*"):
        pid = d.name.split("-")[2]
        if not pid.isdigit() or not process_exists(int(pid)):
            shutil.rmtree(d, ignore_errors=True)


def earlier_export(out: Path) -> list[str]:
    """The tables an earlier export wrote into ``out`` (none when it is new or empty).

    Raises:
        ExportError: ``out`` holds files but no export's ``info.json`` (they would be
            written over or mixed with the export's).
    """
    try:  # a staging directory an export killed while writing left is not content
        entries = sorted(p.name for p in Path(out).iterdir()
                         if not p.name.startswith(".hmpc-export-"))
    except OSError:  # none there (or no directory: writing it says why)
        return []
    if not entries:
        return []
    try:
        info = json.loads((Path(out) / "info.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        info = None
    if not isinstance(info, dict) or not {"log", "filters"} <= set(info):
        shown = first_names(entries)
        raise ExportError(f"{out}: is not empty ({shown}) and holds no earlier export "
                          "(its info.json): choose a new or empty directory")
    files = info.get("files")
    if isinstance(files, list):  # the names it wrote; an older export's: its tables
        return [f for f in files if isinstance(f, str) and f in entries]
    return [f for f in entries if f.endswith(tuple(f".{x}" for x in FORMATS))]
