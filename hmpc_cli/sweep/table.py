"""A sweep's results table: finished runs -> ``<out>/results.csv``.

A run is finished when its run directory says so (:func:`finished`), or when it is a
*tabled* run: a row of the existing results.csv whose run id is planned, written beside
``<out>/base_scenario.toml`` (the sweep's scenario as its runs read it) that is the planned
scenario (:func:`tabled_rows`). Committed tables carry no run directories; their rows still
count, so a campaign resumes from the table alone (a fresh clone, another machine).
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

TIMING = ("solve_time_median", "solve_time_p95", "solve_time_max", "plan_time_median",
          "wall_time")
METRICS = ("success", "final_error", "contacts", "solves", "solver_failures", "softened_solves",
           "planner_calls", "planner_rejected", "diverged", "reason", *TIMING, "cpu")
#: the summary's ``real_time`` (:class:`hmpc_cli.log.topics.RealTime`), columns of a sweep
#: that charges compute time (:attr:`hmpc_cli.sweep.plan.SweepPlan.columns`); a run whose
#: summary has none (time paused, or flown before hmpc recorded it) leaves them empty
REAL_TIME = ("charged_solves", "late_solves", "dropped_solves", "preempted_solves",
             "delay_median", "delay_p95", "delay_max")
INTERRUPTED = "interrupted"
#: beside results.csv: the sweep's scenario file as its runs read it (no override, seed 0)
BASE_SCENARIO = "base_scenario.toml"


def is_interrupted(summary: dict) -> bool:
    """Whether a run summary is of a run stopped by a signal (``interrupted (SIGTERM)``)."""
    return str(summary.get("reason", "")).startswith(INTERRUPTED)


def finished(out: Path, run) -> dict | None:
    """The run's summary if it finished with the same effective scenario, else None."""
    return finished_in(out / "runs" / run.run_id, run.toml)


def made_otherwise(out: Path, runs) -> list[str]:
    """The ids of ``runs`` whose directory holds a run finished with another scenario.

    Its scenario.toml differs from the run's effective scenario now, or its margins file
    changed since (:func:`margins_changed`): a resume runs it again and replaces its files.
    """
    ids = []
    for run in runs:
        d = out / "runs" / run.run_id
        try:
            stored = (d / "scenario.toml").read_text(encoding="utf-8")
            summary = json.loads((d / "summary.json").read_text())
        except (OSError, ValueError):
            continue
        if isinstance(summary, dict) and not is_interrupted(summary) and \
                (not same_scenario(stored, run.toml) or margins_changed(d, stored)) and \
                log_done(d):
            ids.append(run.run_id)
    return ids


def finished_in(d: Path, toml_text: str) -> dict | None:
    """The summary of the run in directory ``d``, if it finished there; else None.

    Finished means: its log ``run.mcap`` reads back complete with its /run/summary
    (:func:`hmpc_cli.log.reader.log_finished`: a missing, empty, cut-short or damaged log
    is not finished, whatever summary.json says; a run that raised, recorded with its
    ``error.txt``, finished with no log or a complete one), summary.json holds a JSON
    object whose reason is not ``interrupted...``, and scenario.toml is the effective
    scenario ``toml_text`` (:func:`same_scenario`) with its margins file unchanged
    (:func:`margins_changed`). Anything else is redone on resume.
    """
    try:
        summary = json.loads((d / "summary.json").read_text())
        stored = (d / "scenario.toml").read_text(encoding="utf-8")
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict) or is_interrupted(summary):
        return None
    if not same_scenario(stored, toml_text) or not log_done(d) or margins_changed(d, stored):
        return None
    return summary


def margins_file_of(toml_text: str) -> str | None:
    """The margins file a run's scenario text reads (``mpc.margins`` as a path), or None."""
    if 'margins = "' not in toml_text:
        return None
    import tomllib

    try:
        source = (tomllib.loads(toml_text).get("mpc") or {}).get("margins")
    except tomllib.TOMLDecodeError:
        return None
    return None if not isinstance(source, str) or source in ("hand", "tube") else source


def margins_changed(d: Path, stored: str) -> bool:
    """Whether the run in ``d`` read a margins file whose contents changed since.

    Its /run/info records the file's digest (``margins.sha256``); a log without one (an
    older hmpc's, or a run that raised before its log) is trusted.

    Args:
        d: the run directory.
        stored: its scenario.toml.
    """
    source = margins_file_of(stored)
    if source is None:
        return False
    from hmpc_cli.log.reader import first_message
    from hmpc_cli.core.paths import file_digest

    recorded = ((first_message(d / "run.mcap", "/run/info") or {}).get("margins") or {}
                ).get("sha256")
    return recorded is not None and recorded != file_digest(Path(source))


def log_done(d: Path) -> bool:
    """Whether run directory ``d`` holds the log a finished run leaves (:func:`finished_in`)."""
    from hmpc_cli.log.reader import log_finished

    log = d / "run.mcap"
    if log_finished(log):
        return True
    if not (d / "error.txt").is_file():  # no log of a run that raised: a crash is a result
        return False
    return not (log.exists() or log.is_symlink()) or log_finished(log, summary=False)


def same_scenario(stored: str, planned: str) -> bool:
    """Whether a run's stored effective scenario is the planned one.

    Equal text, or equal once the stored text is read by today's scenario model: a setting
    added to hmpc since the run takes its default (every other setting is written out in
    full in a run's scenario.toml, so a changed default or value still differs). A run
    of an older hmpc thus stays finished unless something it ran with changed.
    """
    if stored == planned:
        return True
    import tomllib

    from hmpc_cli.core.registry import PluginError
    from hmpc_cli.run.scenario import effective_toml, scenario_model

    try:
        scenario = scenario_model().model_validate(tomllib.loads(stored))
    except (ValueError, TypeError, KeyError, PluginError):  # not a scenario today: differs
        return False
    return effective_toml(scenario) == planned


def cell_text(v: Any) -> str:
    """A value as a results.csv cell."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float, str)):
        return repr(v) if isinstance(v, float) else str(v)
    from hmpc_cli.core.jsonio import dumps

    return dumps(v, sort_keys=True)  # strict JSON: non-finite numbers as null


def grid_order(plan) -> list:
    """The plan's runs in grid order: cells as the grid lists them, seeds ascending."""
    cells: dict[tuple, int] = {}
    for run in plan.runs:  # the plan expands the grid cell by cell
        cells.setdefault(tuple(map(repr, run.cell)), len(cells))
    return sorted(plan.runs, key=lambda r: (cells[tuple(map(repr, r.cell))], r.seed))


def tabled_rows(plan, out: Path) -> dict[str, dict[str, str]]:
    """The rows of ``<out>/results.csv`` that stand for finished runs of ``plan``, by run id.

    A row counts when ``<out>/base_scenario.toml`` is the plan's base scenario
    (``plan.base_toml``, compared by :func:`same_scenario`), its run id is one of the
    plan's (the id hashes the run's overrides and seed, so the run's effective scenario is
    the planned one), its ``success`` is ``true`` or ``false`` and its reason is not
    ``interrupted...``. A table written without ``base_scenario.toml`` (before hmpc
    recorded it), unreadable, or of another scenario counts for nothing: its runs are
    redone. Not seen: defaults that only a run's overrides bring in (a plug-in kind chosen
    by a grid axis) changed since the row was written; the run directory's check sees them.
    """
    if not plan.base_toml:
        return {}
    try:
        stored = (out / BASE_SCENARIO).read_text(encoding="utf-8")
        with open(out / "results.csv", newline="", encoding="utf-8-sig") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error):
        return {}
    if not same_scenario(stored, plan.base_toml):
        return {}
    planned = {r.run_id for r in plan.runs}
    return {r["run_id"]: r for r in rows
            if r.get("run_id") in planned and not str(r.get("reason", "")).startswith(
                INTERRUPTED) and r.get("success") in ("true", "false")}


def stale_table(plan, out: Path) -> str | None:
    """Why ``<out>/results.csv`` is not a table of ``plan``'s runs, or None if it is one.

    Not one: rows hold run ids the plan does not have (the grid, ``[set]`` or seeds changed
    since); finished run directories of the plan hold runs it lacks (the sweep stopped
    before it rewrote the table); or a row no finished run directory vouches for (its
    effective scenario is the planned one) while the table was written for another base
    scenario (``base_scenario.toml`` differs from ``plan.base_toml``, :func:`same_scenario`)
    or for none to check against. No table, or an unreadable one: None.
    """
    try:
        with open(out / "results.csv", newline="", encoding="utf-8-sig") as f:
            ids = [r.get("run_id") or "" for r in csv.DictReader(f)]
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    runs = {r.run_id: r for r in plan.runs}
    foreign = [i for i in ids if i not in runs]
    if foreign:
        return (f"{len(foreign)} of its {len(ids)} rows are runs this sweep file does not "
                f"plan (run ids {', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}"
                "): the grid, [set] or seeds changed since it was written")
    behind = _untabled_finished(plan, out, set(ids))
    if behind:
        return (f"it is behind its finished runs: {behind} finished run "
                f"director{'y is' if behind == 1 else 'ies are'} not in it (the sweep "
                "stopped before it rewrote its table)")
    if not ids:
        return None
    try:
        stored = (out / BASE_SCENARIO).read_text(encoding="utf-8") if plan.base_toml else None
    except FileNotFoundError:
        stored = None
    except (OSError, UnicodeDecodeError):
        return None
    if stored is not None and same_scenario(stored, plan.base_toml):
        return None
    unfinished = sum(finished(out, runs[i]) is None for i in ids)
    if not unfinished:  # every row vouched for by its run directory
        return None
    if stored is not None:
        return (f"it was written for another base scenario: {plan.scenario} changed since (the "
                f"one it ran: {out / BASE_SCENARIO})")
    return (f"{unfinished} of its {len(ids)} rows have no finished run directory to vouch for "
            f"them, and no base scenario ({BASE_SCENARIO}) they could be checked against")


def _untabled_finished(plan, out: Path, tabled: set[str]) -> int:
    """How many of ``plan``'s runs not in ``tabled`` have a finished run directory."""
    return sum(r.run_id not in tabled and (out / "runs" / r.run_id / "summary.json").is_file()
               and finished(out, r) is not None for r in plan.runs)


def started(d: Path) -> bool:
    """Whether run directory ``d`` holds a run started here: its log or its summary.

    A directory with neither is a committed one (at most the trajectory extract
    ``trace.mcap`` the page draws) or none at all.
    """
    return any((d / f).exists() or (d / f).is_symlink() for f in ("run.mcap", "summary.json"))


def _standing_row(tabled: dict, out: Path, run) -> dict[str, str] | None:
    """The tabled row of ``run`` if it stands for the run: the run was never started here."""
    row = tabled.get(run.run_id)
    return row if row is not None and not started(out / "runs" / run.run_id) else None


def finished_runs(plan, out: Path, runs=None) -> dict[str, dict | None]:
    """Per run of ``runs`` (default: the plan's selected ones): what shows it finished.

    The run directory's summary (:func:`finished`); else, for a run never started here
    (:func:`started`), its tabled row's values as a summary (``success`` a bool, the
    other values as tabled, ``real_time`` when its columns hold it; :func:`tabled_rows`);
    else None. A run started here and not finished (a log deleted,
    a run killed) is redone whatever the table says.
    """
    tabled = tabled_rows(plan, out)
    done = {}
    for run in plan.selected if runs is None else runs:
        summary = finished(out, run)
        row = _standing_row(tabled, out, run) if summary is None else None
        if row is not None:
            summary = {**{k: row.get(k, "") for k in METRICS}, "success": row["success"] ==
                       "true"}
            if (row.get("charged_solves") or "").strip():  # tabled since hmpc records it
                summary["real_time"] = {k: row.get(k, "") for k in REAL_TIME}
        done[run.run_id] = summary
    return done


def result_rows(plan, out: Path) -> list[dict[str, str]]:
    """One row per finished run, in grid order (:func:`grid_order`), however they finished.

    A run whose directory is finished gets its row from its summary; a tabled run never
    started here (:func:`finished_runs`) keeps its outcome (the metrics, the real-time
    columns and ``log``) as tabled. The run id, labels, seed and ``set.*`` columns come
    from the plan (an axis or a label renamed since is renamed in the table too).
    Columns: :attr:`SweepPlan.columns`.
    """
    rows = []
    tabled = tabled_rows(plan, out)
    for run in grid_order(plan):
        summary = finished(out, run)
        row = {"run_id": run.run_id, "seed": str(run.seed)}
        cell = zip(plan.axes, run.cell, strict=True)  # one label per axis
        row |= {a.name: cell_text(v) for a, v in cell}
        row |= {f"set.{k}": cell_text(run.overrides.get(k)) for k in plan.keys}
        if summary is None:
            was = _standing_row(tabled, out, run)
            if was is not None:
                row |= {k: was.get(k, "") for k in (*METRICS, *REAL_TIME, "log")}
                rows.append({c: row[c] for c in plan.columns})
            continue
        row |= {k: cell_text(summary.get(k)) for k in METRICS}
        real_time = summary.get("real_time") or {}
        row |= {k: cell_text(real_time.get(k)) for k in REAL_TIME}
        log = out / "runs" / run.run_id / "run.mcap"
        row["log"] = log.relative_to(out).as_posix() if log.exists() else ""
        rows.append({c: row[c] for c in plan.columns})
    return rows


def write_results(plan, out: Path) -> list[str]:
    """Rewrites ``<out>/results.csv`` (:func:`result_rows`) and ``<out>/base_scenario.toml``.

    Returns:
        The run ids of the table's rows (every seed's, not only ``--seeds``'s).
    """
    buf, rows = io.StringIO(), result_rows(plan, out)
    writer = csv.DictWriter(buf, plan.columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    from hmpc_cli.core.paths import write_atomic

    write_atomic(out / "results.csv", buf.getvalue())
    if plan.base_toml:
        write_atomic(out / BASE_SCENARIO, plan.base_toml)
    else:  # no base to record: a sidecar of an earlier plan would vouch for these rows
        (out / BASE_SCENARIO).unlink(missing_ok=True)
    return [row["run_id"] for row in rows]


def toml_value(v: Any) -> str:
    """A value as TOML text (what :func:`apply_overrides` parses back)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{toml_value(str(k))} = {toml_value(x)}"
                               for k, x in v.items()) + "}"
    raise TypeError(f"unsupported value type {type(v).__name__}")


@dataclass(frozen=True)
class CellStats:
    """A grid cell's finished runs (seeds pooled).

    ``late``, ``dropped``, ``preempted`` of ``charged``: the charged solves that kept the
    solver busy past the MPC period, whose plans a budget dropped, and that a contact
    stopped, over the ``recorded`` runs (those that recorded ``real_time``).
    """

    cell: tuple[str, ...]
    runs: int = 0
    successes: int = 0
    recorded: int = 0
    charged: int = 0
    late: int = 0
    dropped: int = 0
    preempted: int = 0

    def columns(self, charged: bool) -> list[str]:
        """The cell's counts as table cells (its solves past the period when ``charged``)."""
        rate = f"{100 * self.successes / self.runs:.0f} %" if self.runs else "-"
        late = late_text(self.charged, self.late, self.dropped, self.preempted) \
            if self.recorded else "-"
        return [str(self.runs), str(self.successes), rate, *([late] if charged else [])]


#: the real_time counts a cell pools, in :class:`CellStats`' order and :func:`late_text`'s
POOLED = ("charged_solves", "late_solves", "dropped_solves", "preempted_solves")


def late_text(charged: int, late: int, dropped: int = 0, preempted: int = 0) -> str:
    """Charged solves past the MPC period as a table cell; ``0/0`` without one.

    E.g. ``12 % (3/25)`` (late of charged) or ``0 % (0/9); 4 dropped, 1 stopped`` (plans
    dropped by the budget, solves stopped by a contact).
    """
    if not charged:
        return "0/0"
    more = [f"{n} {what}" for n, what in ((dropped, "dropped"), (preempted, "stopped")) if n]
    return f"{100 * late / charged:.0f} % ({late}/{charged})" + \
        (f"; {', '.join(more)}" if more else "")


def cell_stats(plan, out: Path) -> list[CellStats]:
    """Per grid cell (all axes, seeds pooled): runs, successes, solves past the period."""
    stats: dict[tuple[str, ...], list[int]] = {}
    done = finished_runs(plan, out.resolve(), plan.runs)
    for run in plan.runs:
        s = stats.setdefault(tuple(cell_text(v) for v in run.cell), [0] * (3 + len(POOLED)))
        summary = done[run.run_id]
        if summary is not None:
            s[0] += 1
            s[1] += bool(summary.get("success"))
            counts = _pooled(summary.get("real_time") or {})
            if counts is not None:
                s[2:] = [a + b for a, b in zip(s[2:], [1, *counts], strict=True)]
    return [CellStats(c, *v) for c, v in stats.items()]


def _pooled(real_time: dict) -> list[int] | None:
    """A run's :data:`POOLED` counts; None: not recorded, or a tabled cell not a count.

    The table printed at a sweep's end leaves such a run out rather than fail; the
    results page names the cell.
    """
    try:
        return [int(real_time[k]) for k in POOLED]
    except (KeyError, TypeError, ValueError):
        return None
