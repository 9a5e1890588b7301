"""The results page's robustness study: success rate vs MPC rate, with real statistics.

One section per study sweep (paper geometry, a moved geometry, solve latency charged): the
success rates with Wilson 95 % intervals and, on the same rate axis, the tube diameter
diam T(1/f) of Step 5 computed for the sweep's own scenario and disturbance size; the
table; findings computed from the intervals; the runs' summed wall time and how to
resume. Then the latency comparison and a reading computed from all of it: a pairwise
claim is made only where intervals separate; a trend only at the 5 % level, tested again
without the slowest rate, and tallied both ways.
"""

from __future__ import annotations

import functools
import math
import re
import statistics
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from hmpc_cli.analysis.tables import (
    FigureInputError,
    blamed_on,
    not_run_yet,
    parse_bool,
    pooled_counts,
    read_table,
    resolve_table,
    sweep_spec)
from hmpc_cli.figures.common import page_link
from hmpc_cli.tube.margins_file import REFUSED

if TYPE_CHECKING:
    from hmpc_cli.tube.report import TubeReport

__all__ = ["Study", "past_period_table", "robustness_sections"]

RATE, POLICY, SIZE = "mpc.rate_hz", "replanning.policy", "disturbance.magnitude"
#: the page's words for a table of charged solves past the period (``pooled``: over what)
PAST_PERIOD = ("Solves that kept the one solver busy past the MPC period, so that the next "
               "period's solve waited (`late_solves` of `charged_solves`, {pooled}, failed "
               "ones too; then the solves whose plans the budget dropped and those a contact "
               "stopped")
#: ... when a table's runs do not record them (``{}``: whose runs)
FLOWN_BEFORE = "{} runs were flown before hmpc recorded `real_time`"


def margins_refused(row: dict) -> bool:
    """Whether a table row's run was refused at set-up for its margins: never controlled."""
    return str(row.get("reason") or "").startswith(f"ValueError: {REFUSED}")


@dataclass(frozen=True)
class Study:
    """One robustness sweep on the page.

    Attributes:
        directory: the sweep's output directory (results.csv, sweep.toml, runs/).
        sweep_file: the sweep file (how to resume), or None.
        planned_seeds: the sweep's seeds (None: its ``sweep.toml``'s).
    """

    directory: Path
    sweep_file: Path | None = None
    planned_seeds: int | None = None


def settings_text(spec: dict) -> str:
    """A sweep's ``[set]`` overrides as text, values as TOML writes them ("-" if none)."""
    from hmpc_cli.sweep.table import toml_value

    return ", ".join(f"`{k} = {toml_value(v)}`"
                     for k, v in spec.get("set", {}).items()) or "-"


def fixed_settings(directory: Path) -> str:
    """A sweep output directory's ``[set]`` overrides as text ("-" if none)."""
    return settings_text(sweep_spec(directory))


def _effective(table: Path, row: dict, sweep_file: Path | None, scratch: Path) -> Path:
    """A run's effective ``scenario.toml``: in its run directory, else from its sweep file.

    A committed sweep table has no run directories: the sweep file (which made the
    table) gives every run's scenario again, by run id.
    """
    path = table.parent / "runs" / row.get("run_id", "") / "scenario.toml"
    if path.is_file() or sweep_file is None:
        return path
    run = _planned(Path(sweep_file).resolve()).get(row.get("run_id"))
    if run is None or not run.toml:
        return path
    out = scratch / f"{run.run_id}.toml"
    out.write_text(run.toml, encoding="utf-8")
    return out


@functools.lru_cache(maxsize=16)
def _planned(sweep_file: Path) -> dict:
    """The runs of a sweep file by run id (planned once per file and process)."""
    from hmpc_cli.sweep.plan import plan_sweep

    return {r.run_id: r for r in plan_sweep(sweep_file).runs}


def tube_reports(table: Path, rows: list[dict], size_column: str = SIZE,
                 sweep_file: Path | None = None) -> dict[float, TubeReport]:
    """Step 5's tube analysis per disturbance size of a sweep: size -> its ``TubeReport``.

    ``hmpc tube``'s (its default region and samples, eta with the ``[plant]``'s flow
    mismatch) for the effective scenario of the first finished run of each size (its
    ``scenario.toml``, or the ``sweep_file``'s for a table without run directories), at
    the sweep's rates; a size whose scenario cannot be read or analysed is left out.
    """
    from hmpc_cli.core.registry import PluginError, build_system
    from hmpc_cli.run.tube_margins import scenario_tube
    from hmpc_cli.tube import TubeError

    rates = sorted({float(r[RATE]) for r in rows if r.get(RATE)})
    out: dict[float, TubeReport] = {}
    for size in sorted({float(r[size_column]) for r in rows if r.get(size_column)}):
        first = next(r for r in rows if r.get(size_column) and float(r[size_column]) == size)
        sc = _effective_scenario(table, first, sweep_file)
        if sc is None:
            continue
        try:
            out[size] = scenario_tube(sc, build_system(sc.system), rates=rates)
        except (OSError, PluginError, TubeError, ValueError):
            continue
    return out


def tube_diameters(reports: dict[float, TubeReport], rows: list[dict]
                   ) -> dict[float, dict[str, list]]:
    """Diam T(1/f) per disturbance size: size -> bound -> [(rate, diam)].

    From :func:`tube_reports`, at the rates of ``rows``; bounds ``trivial`` (Prop. 2) and
    ``kinematic``.
    """
    rates = sorted({float(r[RATE]) for r in rows if r.get(RATE)})
    out: dict[float, dict[str, list]] = {}
    for size, rep in reports.items():
        picked = [r for r in rep.rows if any(math.isclose(r.rate_hz, x) for x in rates)]
        out[size] = {"trivial": [(r.rate_hz, r.trivial) for r in picked],
                     "kinematic": [(r.rate_hz, r.kinematic) for r in picked
                                   if r.kinematic is not None]}
    return out


def region_text(reports: dict[float, TubeReport]) -> str:
    """The constants' region in words: the largest L_x found and the box, per state.

    Empty without a report. The sizes share one region (the scenario's default).
    """
    if not reports:
        return ""
    rep = next(iter(reports.values()))
    box = ", ".join(f"{name} [{lo:.3g}, {hi:.3g}]" for name, lo, hi in zip(
        rep.state_names, rep.region.lower, rep.region.upper, strict=True))
    return (f"L_x = {max(r.lipschitz.L_x for r in reports.values()):.4g} 1/s, the largest "
            f"||df/dx|| sampled on `hmpc tube`'s default region, the box {box}: a Lipschitz "
            "constant inside that box only, so these tubes do not cover a run's states "
            "outside it (docs/tubes.md, \"The region\", measures how far the ball's runs "
            "leave it)")


def _effective_scenario(table: Path, row: dict, sweep_file: Path | None):
    """The run's effective scenario (see :func:`_effective`), or None if it cannot be read."""
    import tempfile

    from hmpc_cli.run.scenario import ScenarioError, load_scenario

    try:
        with tempfile.TemporaryDirectory() as scratch:
            return load_scenario(_effective(table, row, sweep_file, Path(scratch)),
                                 check_margins=False)[0]
    except (OSError, ScenarioError, ValueError):
        return None


def _pivot(cells) -> list[str]:
    """Markdown table: one row per (size, policy), one column per rate."""
    xs = sorted({c.x for c in cells})
    lines = ["| disturbance | policy | " + " | ".join(f"{x:g} Hz" for x in xs) + " |",
             "| --- | --- | " + " | ".join("---" for _ in xs) + " |"]
    rows: dict[tuple[str, str], dict[float, object]] = {}
    for c in cells:
        rows.setdefault((c.panel, c.series), {})[c.x] = c
    for (panel, series), by_x in rows.items():
        parts = []
        for x in xs:
            c = by_x.get(x)
            parts.append("-" if c is None else
                         f"{c.successes}/{c.runs}, margins refused" if not c.ran else
                         f"{c.successes}/{c.runs} ({100 * c.interval[0]:.0f}-"
                         f"{100 * c.interval[1]:.0f} %)")
        lines.append(f"| ±{panel} | {series} | " + " | ".join(parts) + " |")
    return lines


def _diam_lines(diameters: dict[float, dict[str, list]]) -> list[str]:
    """Markdown table of diam T(1/f) per size and bound."""
    if not diameters:
        return []
    xs = sorted({x for d in diameters.values() for pts in d.values() for x, _ in pts})
    lines = ["| tube | " + " | ".join(f"{x:g} Hz" for x in xs) + " |",
             "| --- | " + " | ".join("---" for _ in xs) + " |"]
    for size, curves in diameters.items():
        for bound, pts in curves.items():
            by = dict(pts)
            lines.append(f"| ±{size:g}, {bound} | " + " | ".join(
                f"{by[x]:.3g}" if x in by else "-" for x in xs) + " |")
    return lines


def separated(a, b) -> bool:
    """Whether two cells' Wilson intervals do not overlap."""
    return a.interval[1] < b.interval[0] or b.interval[1] < a.interval[0]


def _compare(hi, lo, what_hi: str, what_lo: str) -> str:
    """How two cells' success rates compare, a direction only where intervals separate.

    '<hi> is higher / lower than <lo> (rates; intervals separate)', else '<hi> vs <lo>:
    rates, intervals overlap'.
    """
    digits = 0  # as many decimals as it takes to show a difference (up to 3)
    while (digits < 3 and hi.rate != lo.rate
           and f"{100 * hi.rate:.{digits}f}" == f"{100 * lo.rate:.{digits}f}"):
        digits += 1
    rates = f"{100 * hi.rate:.{digits}f} % vs {100 * lo.rate:.{digits}f} %"
    if not separated(hi, lo):
        return f"{what_hi} vs {what_lo}: {rates}, intervals overlap"
    verdict = "higher than" if hi.rate > lo.rate else "lower than"
    return f"{what_hi} is {verdict} {what_lo} ({rates}; intervals separate)"


def _trend(cells, scores=None):
    """The Cochran-Armitage trend of cells (default scores: log of the rate)."""
    from hmpc_cli.analysis.trend import cochran_armitage

    scores = [math.log(c.x) for c in cells] if scores is None else scores
    return cochran_armitage([c.runs for c in cells], [c.successes for c in cells], scores)


def _significant(cells) -> str | None:
    """'rises' or 'falls' where the trend across rates holds at the 5 % level, else None."""
    tr = _trend(cells)
    return tr.direction if math.isfinite(tr.p) and tr.p < 0.05 else None


def trend_text(cells, scores=None,
               what: str = "trend across rates (Cochran-Armitage, scores log f)",
               along: str = "with the MPC rate") -> str:
    """The Cochran-Armitage trend of cells (default: one series across rates, log f)."""
    tr = _trend(cells, scores)
    if not math.isfinite(tr.p):
        return f"{what}: undefined (every run alike)"
    verdict = (f"success {tr.direction} {along} at the 5 % level" if tr.p < 0.05
               else f"no trend at the 5 % level (direction: {tr.direction})")
    return f"{what}: z = {tr.z:+.2f}, p = {tr.p:.3g}: {verdict}"


def findings(cells) -> list[str]:
    """Per (size, policy): fastest vs slowest rate, the trend across rates.

    Per (size, rate): replanning vs once, where both ran and their intervals separate.
    """
    out = []
    panels = list(dict.fromkeys(c.panel for c in cells))
    series = list(dict.fromkeys(c.series for c in cells))
    for p in panels:
        for s in series:
            sel = sorted((c for c in cells if c.panel == p and c.series == s), key=lambda c: c.x)
            if len(sel) >= 2:
                out.append(f"- ±{p}, {s}: " + _series_finding(sel) + ".")
        if len(series) == 2:
            a, b = series
            for x in sorted({c.x for c in cells if c.panel == p}):
                ca = [c for c in cells if (c.panel, c.series, c.x) == (p, a, x) and c.ran]
                cb = [c for c in cells if (c.panel, c.series, c.x) == (p, b, x) and c.ran]
                if ca and cb and separated(ca[0], cb[0]):
                    out.append(f"- ±{p}, {x:g} Hz: " + _compare(cb[0], ca[0], b, a) + ".")
    return out


def _series_finding(sel: list) -> str:
    """One series (cells by ascending rate): fastest vs slowest rate and the trend.

    Rates whose runs were all refused at set-up (their margins) are named; the comparison
    is then between the rates set up, and the trend is given over all rates (a refused run
    counts as failed) and over the rates set up.
    """
    def fastest_vs_slowest(cells: list) -> str:
        return _compare(cells[-1], cells[0], f"{cells[-1].x:g} Hz", f"{cells[0].x:g} Hz")

    ran = [c for c in sel if c.ran]
    if len(ran) == len(sel):
        return fastest_vs_slowest(sel) + "; " + trend_text(sel) + _without_slowest(sel)
    refused = [f"{c.x:g}" for c in sel if not c.ran]
    where = (f"{refused[0]} Hz" if len(refused) == 1
             else f"{', '.join(refused[:-1])} and {refused[-1]} Hz")
    text = f"at {where} every run's margins were refused at set-up (none ran)"
    if len(ran) >= 2:
        text += "; of the rates set up, " + fastest_vs_slowest(ran)
    text += "; " + trend_text(sel, what="trend across all rates (a refused run counts as "
                              "failed; Cochran-Armitage, scores log f)")
    if len(ran) >= 2:
        text += "; " + trend_text(ran, what=f"across the rates set up ({ran[0].x:g}-"
                                  f"{ran[-1].x:g} Hz)") + _without_slowest(ran)
    return text


def _without_slowest(cells: list) -> str:
    """A trend that holds over >= 3 rates, tested again without its slowest rate."""
    if len(cells) < 3 or _significant(cells) is None:
        return ""
    rest = cells[1:]
    return "; " + trend_text(rest, what=f"without the slowest rate ({rest[0].x:g}-"
                             f"{rest[-1].x:g} Hz)")


def wall_text(rows: list[dict]) -> str:
    """The runs' summed wall time (core hours), mean per run and the machines' CPUs."""
    walls = [float(r["wall_time"]) for r in rows if r.get("wall_time") not in (None, "")]
    if not walls:
        return "wall time not recorded" + machines_text(rows)
    return (f"the runs took {sum(walls) / 3600:.1f} core-hours ({sum(walls) / len(walls):.1f} s "
            "per run on average; divide by the worker processes for the elapsed time)"
            + machines_text(rows))


def machines_text(rows: list[dict]) -> str:
    """``; run on CPU (n runs), ...``; ``; its CPU not recorded`` when no row records it.

    Rows of a table written before hmpc recorded the CPU count as not recorded (wall
    times of two tables compare only on one machine).
    """
    cpus = Counter(r.get("cpu") or "" for r in rows)
    if not any(cpus):
        return "; its CPU not recorded" if rows else ""
    parts = [f"{cpu or 'a CPU not recorded'} ({n} run{'' if n == 1 else 's'})"
             for cpu, n in sorted(cpus.items(), key=lambda kv: (not kv[0], -kv[1], kv[0]))]
    return "; run on " + ", ".join(parts)


def _number(value) -> float:
    """A results.csv cell as a float (nan: empty or not a number)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _median(rows: list[dict], key: str) -> float:
    """The median of a numeric column over rows (finite cells only; nan if none)."""
    vals = [v for v in (_number(r.get(key)) for r in rows) if math.isfinite(v)]
    return statistics.median(vals) if vals else math.nan


def failure_lines(rows: list[dict], size: str) -> list[str]:
    """How the failed runs failed, and how much the disturbance draw alone decides.

    From results.csv rows: the failed runs' final distance to the goal and solver failures
    beside the successful runs', their reasons (numbers elided), and over the draws (seed
    and ``size``) run in more than one cell how many succeed everywhere, fail everywhere
    or differ between cells.
    """
    ok = [parse_bool(r.get("success"), "results.csv: success") for r in rows]
    failed = [r for r, good in zip(rows, ok, strict=True) if not good]
    if not failed:
        return [f"- Failed runs: none of {len(rows)}."]
    good = [r for r, g in zip(rows, ok, strict=True) if g]
    has = set(rows[0])
    parts = [f"- Failed runs: {len(failed)} of {len(rows)}"]
    refused = [r for r in failed if margins_refused(r)]
    if refused:  # no controller ran: their distance and solver failures say nothing
        failed = [r for r in failed if not margins_refused(r)]
        parts[0] += (f" ({len(refused)} never ran: margins refused at set-up"
                     + (f"; the numbers below are the {len(failed)} that ran)" if failed
                        else ")"))
    if "final_error" in has and failed:
        parts.append("they end " + _stat(failed, good, "final_error", "{:.2f} m",
                                         " from the goal"))
    if "solver_failures" in has and failed:
        parts.append("with " + _stat(failed, good, "solver_failures", "{:g}",
                                     " solver failures per run"))
    if "reason" in has and failed:
        why = Counter(_NUMBER.sub("…", r.get("reason") or "?") for r in failed)
        parts.append("reasons: " + ", ".join(f"`{k}` ({v})" for k, v in why.most_common(4)))
    return ["; ".join(parts) + "."] + _draw_lines(rows, ok, size)


#: a number in a failure reason (not digits inside a name such as ``wall2``)
_NUMBER = re.compile(r"(?<![\w.])-?\d+(\.\d+)?([eE][-+]?\d+)?")


def _stat(failed: list[dict], good: list[dict], key: str, fmt: str, what: str) -> str:
    """"a median X<what>" of the failed runs' ``key``, beside the successful runs' median.

    ``fmt`` formats a value (its unit included, e.g. ``"{:.2f} m"``). Non-finite values (a
    diverged run's distance) are left out and counted; "n/a" when none is finite.
    """
    def med(rows: list[dict]) -> str:
        m = _median(rows, key)
        return fmt.format(m) if math.isfinite(m) else "n/a"

    notes = [f"successful runs: {med(good)}"] if good else []
    gone = sum(not math.isfinite(_number(r.get(key))) for r in failed)
    if gone:
        notes.append(f"{gone} failed run{'s' * (gone > 1)} without a finite value")
    return f"a median {med(failed)}{what}" + (f" ({'; '.join(notes)})" if notes else "")


def _draw_lines(rows: list[dict], ok: list[bool], size: str) -> list[str]:
    """How the draws (seed and ``size``) run in every cell of their size fare across cells.

    A draw run in fewer cells than the most any draw of its size was run in (a campaign
    under way) is left out.
    """
    draws: dict[tuple, list[bool]] = defaultdict(list)
    for r, g in zip(rows, ok, strict=True):
        draws[(r.get("seed"), r.get(size))].append(g)
    width: dict[object, int] = defaultdict(int)
    for (_, z), v in draws.items():
        width[z] = max(width[z], len(v))
    full = [v for (_, z), v in draws.items() if len(v) == width[z] > 1]
    if not full:
        return []
    everywhere, nowhere = sum(all(v) for v in full), sum(not any(v) for v in full)
    return [f"- The same disturbance draw (seed and size) in every rate and policy: succeeds "
            f"in all its cells for {everywhere} of {len(full)} draws, fails in all for "
            f"{nowhere}, differs between cells for {len(full) - everywhere - nowhere}."]


def _drawn(study: Study, table: Path, rows: list[dict], spec: dict, name: str,
           fig_dir: Path) -> tuple[list[dict], str, dict, str, list]:
    """The study's figure and cells.

    Returns:
        (rows with the study's columns, the size column, the tube diameters, their
        constants' region in words (:func:`region_text`), the cells).
    """
    import tempfile

    from hmpc_cli.figures.common import TEXT_WIDTH_IN
    from hmpc_cli.figures.robustness import robustness

    _refuse_pooled_axes(spec)
    with tempfile.TemporaryDirectory() as scratch:
        drawn, rows = _with_study_columns(table, rows, spec, study.sweep_file, Path(scratch))
        size = _size_column(rows)
        reports = tube_reports(table, rows, size, study.sweep_file)
        diam = tube_diameters(reports, rows)
        cells = robustness(drawn, fig_dir, "pdf,svg,png", name=name, diameters=diam,
                           panel_axis=size, width=min(TEXT_WIDTH_IN, 3.5 * max(1, len(diam))),
                           not_set_up=margins_refused)
    return rows, size, diam, region_text(reports), cells


def _draws(entries: object) -> bool:
    """A grid axis of tables that set only the disturbance's draw (``disturbance.*``)."""
    return isinstance(entries, list) and all(
        isinstance(e, dict) and all(k == "label" or k == "disturbance"
                                    or k.startswith("disturbance.") for k in e)
        for e in entries)


def _refuse_pooled_axes(spec: dict) -> None:
    """Refuses a grid axis whose entries would be pooled into one cell of the study.

    The cells are (MPC rate, policy, disturbance size); two entries of an axis that set
    the same ones but differ otherwise would be pooled. Entries that set only the
    disturbance's draw (``disturbance.*``) are pooled like seeds.

    Raises:
        FigureInputError: such an axis (named).
    """
    for axis, entries in (spec.get("grid") or {}).items():
        if axis in (RATE, POLICY, SIZE) or not isinstance(entries, list) or len(entries) < 2 \
                or _draws(entries):
            continue
        if all(isinstance(e, dict) for e in entries):
            cells = [tuple(str(_entry_value(e, k)) for k in (RATE, POLICY, SIZE))
                     for e in entries]
            if len(set(cells)) == len(cells):
                continue
        raise FigureInputError(
            f"grid.{axis}: a robustness section tells runs apart by MPC rate, replanning "
            f"policy and disturbance size only, so entries of this axis would be pooled "
            f"into one cell: report each as a study of its own (a sweep per entry, one "
            f"--robustness each), or draw it with hmpc plot robustness DIR --series-axis "
            f"{axis}")


def _with_study_columns(table: Path, rows: list[dict], spec: dict, sweep_file: Path | None,
                        scratch: Path) -> tuple[Path, list[dict]]:
    """The table with a column for the MPC rate, the policy and the disturbance size.

    A sweep names each by its key (a grid axis of values) or ``set.<key>`` (its
    ``[set]``); otherwise the value comes from a grid axis of tables whose entries set
    it (by the run's label on that axis), else from each run's effective scenario.
    Returns ``table`` itself when nothing is missing, else a completed copy in
    ``scratch`` (with the sweep's ``sweep.toml`` beside it, for the grid's order).
    """
    import csv
    import shutil

    have = set(rows[0]) if rows else set()
    fills = {}
    for key in (RATE, POLICY, SIZE):
        if key in have or (key == SIZE and f"set.{key}" in have):
            continue
        fills[key] = _column_source(key, have, spec, table, sweep_file)
    if not fills or not rows:
        return table, rows
    done = [{**r, **{k: f(r) for k, f in fills.items()}} for r in rows]
    out = scratch / "results.csv"
    with open(out, "w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=[*rows[0], *fills])
        writer.writeheader()
        writer.writerows(done)
    if (table.parent / "sweep.toml").is_file():
        shutil.copyfile(table.parent / "sweep.toml", scratch / "sweep.toml")
    return out, done


def _column_source(key: str, have: set, spec: dict, table: Path, sweep_file: Path | None):
    """``row -> value`` of ``key`` for a table without its column (see above).

    Raises:
        FigureInputError: an axis of tables sets the key in some entries only, or a run's
            scenario cannot be read (no run directory and no sweep file).
    """
    if f"set.{key}" in have:
        return lambda row: row[f"set.{key}"]
    for axis, entries in (spec.get("grid") or {}).items():
        sets = [_entry_value(e, key) for e in entries] \
            if isinstance(entries, list) and all(isinstance(e, dict) for e in entries) else []
        if not any(v is not None for v in sets):
            continue
        labels = [e.get("label") for e in entries]
        if axis not in have or None in sets or not all(isinstance(b, str) for b in labels):
            raise FigureInputError(f"grid.{axis}: its entries set {key}, but not every entry "
                                   f"does, under a label of its own (label = \"...\")")
        by_label = dict(zip(labels, (str(v) for v in sets), strict=True))
        return lambda row: by_label.get(row[axis], "")
    section, _, field = key.partition(".")

    def of_run(row: dict) -> str:
        sc = _effective_scenario(table, row, sweep_file)
        if sc is None:
            raise FigureInputError(f"{table}: no {key} column, and the scenario of run "
                                   f"{row.get('run_id')!r} cannot be read (no run directory; "
                                   "pass the sweep file)")
        return str(getattr(getattr(sc, section), field))

    return of_run


def _entry_value(entry: dict, key: str):
    """A grid table entry's value of a dotted key (quoted or nested), or None."""
    if key in entry:
        return entry[key]
    node = entry
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _size_column(rows: list[dict]) -> str:
    """The table's disturbance-size column: the grid's, else the sweep's fixed ``[set]``."""
    return SIZE if rows and SIZE in rows[0] else f"set.{SIZE}"


def study_section(study: Study, fig_dir: Path, base: Path) -> tuple[list[str], list, dict]:
    """One sweep's section: figure with tubes, tables, findings, wall time, resume.

    Returns:
        (markdown lines, the cells, the sweep's ``sweep.toml`` as it ran).
    """
    table = resolve_table(study.directory)
    rows = read_table(table, ["seed"])
    spec = sweep_spec(study.directory)
    name = str(spec.get("name") or study.directory.name)
    sc = _effective_scenario(table, rows[0], study.sweep_file) if rows else None
    if sc is not None:  # a setting the runs take from their scenario file
        spec = {**spec, "effective": {"sim.latency_first": sc.sim.latency_first,
                                      "lowlevel.past_guard": sc.lowlevel.past_guard,
                                      "sim.latency": sc.sim.latency}}
    rows, size, diam, region, cells = _drawn(study, table, rows, spec, name, fig_dir)
    seeds = len({r["seed"] for r in rows})
    n = sorted({c.runs for c in cells})
    seeds_spec = spec.get("seeds")
    planned = study.planned_seeds or (seeds_spec if isinstance(seeds_spec, int) else len(
        seeds_spec) if isinstance(seeds_spec, list) else None)
    partial = (f" (a prefix: {seeds} of the sweep's {planned} seeds)"
               if planned and seeds < planned else "")
    grid = spec.get("grid", {})
    planned_cells = math.prod(len(v) for v in grid.values()
                              if isinstance(v, list) and not _draws(v))
    if grid and len(cells) < planned_cells:
        partial += f"; {len(cells)} of its {planned_cells} cells have runs so far"
    from hmpc_cli.report.paths import portable_command

    guess = Path("sweeps") / f"{name}.toml"  # the repository's layout, where it holds
    if study.sweep_file or guess.is_file():
        resume = portable_command(f"hmpc sweep {study.sweep_file}" if study.sweep_file else
                                  f"hmpc sweep {guess.as_posix()} --out {study.directory}")
        resume = f" Resume or complete: `{resume}` (finished runs are skipped)."
    else:
        resume = (f" Resume or complete: `hmpc sweep` on the sweep file of `{name}` with "
                  f"`--out {portable_command(str(study.directory))}` (finished runs are "
                  "skipped).")
    png = page_link(fig_dir / f"{name}.png", base)
    csv = page_link(fig_dir / f"{name}_table.csv", base)
    return ([f"### {spec.get('description', name)}", "", f"![{name}]({png})", "",
             f"{len(rows)} finished runs, {seeds} seeds{partial}, {n[0]}"
             f"{'' if len(n) == 1 else f'-{n[-1]}'} runs per cell; settings of every run: "
             f"{settings_text(spec)}; Wilson 95 % intervals; {wall_text(rows)}. "
             f"Table: [{csv}]({csv})."
             + resume, "", *_pivot(cells), "",
             *([f"Tube bounds at each rate (Step 5, sampled constants: {region}; the "
                f"lower panels): trivial, diam T(1/f), a bound on the state's norm; "
                f"kinematic, its integral over the period, a bound on the positions:", "",
                *_diam_lines(diam), ""]
               if diam else []),
             *_past_period_lines(table, rows, charged(spec) is not None),
             "Computed findings (a pairwise claim only where the intervals separate; a "
             "trend at the 5 % level, uncorrected for this page's many tests, and again "
             "without the slowest rate where it holds):", "",
             *(findings(cells) or ["- none: no cell has runs at two rates"]), "",
             "How the runs failed (each run's summary):", "", *failure_lines(rows, size), ""],
            cells, spec)


def _past_period_lines(table: Path, rows: list[dict], charges: bool) -> list[str]:
    """Per policy and rate, the charged solves past the MPC period.

    ``charges``: the study charges compute time. No line with time paused; one sentence
    for runs flown before hmpc recorded ``real_time``.
    """
    from hmpc_cli.sweep.table import POOLED

    def key(row: dict) -> tuple[str, float] | None:
        rate = _number(row.get(RATE))
        return (row.get(POLICY, ""), rate) if math.isfinite(rate) else None

    pooled = pooled_counts(table, rows, key, POOLED)
    if not pooled:
        return [f"Solves past the MPC period: not in this table; {FLOWN_BEFORE.format('its')}.",
                ""] if charges else []
    policies = list(dict.fromkeys(p for p, _ in pooled))
    rates = sorted({x for _, x in pooled})
    return [PAST_PERIOD.format(pooled="every disturbance size and run that recorded them "
                               "pooled") + "): a rate whose solves fit its period runs at "
            "that rate.", "",
            *past_period_table(pooled, "replanning", policies, rates, lambda x: f"{x:g} Hz"),
            ""]


def past_period_table(pooled: dict, head: str, rows: list, columns: list,
                      label=str) -> list[str]:
    """A Markdown table of pooled charged solves past the period (:func:`late_text`).

    ``pooled``: (row, column) -> the :data:`~hmpc_cli.sweep.table.POOLED` counts; a cell
    without them is ``-``. ``label(column)``: its heading.
    """
    from hmpc_cli.sweep.table import late_text

    return ["| " + head + " | " + " | ".join(map(label, columns)) + " |",
            "|---|" + "---|" * len(columns),
            *(f"| {r} | " + " | ".join(late_text(*pooled[(r, c)]) if (r, c) in pooled
                                        else "-" for c in columns) + " |" for r in rows)]


def twin_pairs(paused: list, charged: list) -> list[tuple]:
    """(charged cell, the same cell with time paused) for every charged cell with a twin."""
    by = {(p.panel, p.series, p.x): p for p in paused}
    return [(c, by[(c.panel, c.series, c.x)]) for c in charged
            if (c.panel, c.series, c.x) in by]


def latency_lines(pairs: list[tuple], latency: object) -> list[str]:
    """The cells run with latency charged beside the same cells with time paused."""
    return [f"- ±{c.panel}, {c.series}, {c.x:g} Hz: "
            + _compare(c, twin, latency_text(latency), "time paused") + "." for c, twin in pairs]


def latency_text(latency: object) -> str:
    """``sim.latency`` in words: "0.05 s latency", "measured latency" or "modelled latency".

    Measured: the solve's own time; modelled: charged from the solver's iterations
    (``sim.latency_model``).
    """
    if latency in ("measured", "model"):
        return "measured latency" if latency == "measured" else "modelled latency"
    return f"{latency} s latency"


def charged(spec: dict) -> object | None:
    """A sweep's charged ``sim.latency`` (None: time paused).

    Its ``[set]``'s, else its runs' scenario's (``effective``, see :func:`study_section`).
    """
    lat = spec.get("set", {}).get("sim.latency", spec.get("effective", {}).get("sim.latency"))
    return None if lat in (None, "paused") else lat


def _tally(pairs: list[tuple]) -> tuple[int, int, int]:
    """(first higher with separated intervals, first lower so, unresolved) over pairs."""
    up = sum(separated(a, b) and a.rate > b.rate for a, b in pairs)
    down = sum(separated(a, b) and a.rate < b.rate for a, b in pairs)
    return up, down, len(pairs) - up - down


def _pairs(cells) -> tuple[list, list]:
    """(fastest vs slowest rate per size and policy, replanning vs once per size and rate).

    Of the cells whose runs were set up (not every run refused for its margins).
    """
    by: dict[tuple, object] = {(c.panel, c.series, c.x): c for c in cells if c.ran}
    rate_pairs, plan_pairs = [], []
    for p, s in dict.fromkeys((c.panel, c.series) for c in cells):
        xs = sorted(x for (pp, ss, x) in by if (pp, ss) == (p, s))
        if len(xs) >= 2:
            rate_pairs.append((by[(p, s, xs[-1])], by[(p, s, xs[0])]))
    for p, x in dict.fromkeys((c.panel, c.x) for c in cells):
        if (p, "once", x) in by and (p, "on_contact", x) in by:
            plan_pairs.append((by[(p, "on_contact", x)], by[(p, "once", x)]))
    return rate_pairs, plan_pairs


def _series_set_up(cells) -> list[list]:
    """Each (size, policy) series' cells set up, by ascending rate (>= 2 rates)."""
    out = []
    for p, s in dict.fromkeys((c.panel, c.series) for c in cells):
        sel = sorted((c for c in cells if (c.panel, c.series) == (p, s) and c.ran),
                     key=lambda c: c.x)
        if len(sel) >= 2:
            out.append(sel)
    return out


def _trend_counts(series: list[list], level: float = 0.05) -> tuple[int, int]:
    """(rising, falling) trends across the rates set up that hold at ``level``."""
    trs = [_trend(sel) for sel in series]
    hold = [t for t in trs if math.isfinite(t.p) and t.p < level]
    return (sum(t.direction == "rises" for t in hold),
            sum(t.direction == "falls" for t in hold))


def _trend_tally(series: list[list]) -> str:
    """How many series' trends across the rates set up rise or fall.

    At the 5 % level, and at the Bonferroni level 0.05 / (the number of series).
    """
    n = len(series)
    up, down = _trend_counts(series)
    up_b, down_b = _trend_counts(series, 0.05 / n)
    rest = [sel[1:] for sel in series if len(sel) >= 3]
    up_r, down_r = _trend_counts(rest)
    return (f" Trend tests across the rates set up (Cochran-Armitage, scores log f): "
            f"success rises with the rate in {up} of these {n} series and falls in {down} "
            f"at the 5 % level; at the Bonferroni level 0.05/{n} = {0.05 / n:.2g}, it rises "
            f"in {up_b} and falls in {down_b}"
            + (f"; without each series' slowest rate ({len(rest)} series of 3 rates or "
               f"more), it rises in {up_r} and falls in {down_r} at the 5 % level." if rest
               else "."))


def _pace(latency: object) -> float | None:
    """1/L [Hz]: the most solves per second one solver makes at a fixed latency L [s]."""
    try:
        return 1.0 / float(latency)
    except (TypeError, ValueError, ZeroDivisionError):
        return None


def _paced(cells, latency: object) -> str:
    """Which tested rates a fixed latency L holds to 1/L ('' for none, or no fixed L)."""
    pace = _pace(latency)
    above = sorted({c.x for c in cells if pace is not None and c.x > pace})
    if not above:
        return ""
    return (f" One solver at {latency} s per solve runs at most {pace:.3g} Hz: the "
            f"{', '.join(f'{x:g}' for x in above)} Hz cells solve at most that often, so "
            "their differences are not those of their nominal rates.")


def _refused_series(cells) -> int:
    """How many compared (size, policy) series hold a rate none of whose runs was set up.

    Compared: two rates or more set up (a series with fewer is not in the rate reading).
    """
    refused = {(c.panel, c.series) for c in cells if not c.ran}
    return sum(sum(c.ran for c in cells if (c.panel, c.series) == key) >= 2
               for key in refused)


def reading(results: list[tuple[dict, list]],
            latency: list[tuple[tuple[str, ...], list, list[tuple], object]],
            margins: list[tuple[dict, list[tuple]]] = ()) -> list[str]:
    """What the evidence does and does not support, counted from the intervals.

    Args:
        results: every study's (``sweep.toml``, cells).
        latency: per latency study compared with its paused twin: (its latency in words,
            :func:`_latency_words`; its cells; :func:`twin_pairs` with the paused twin; its
            ``sim.latency``).
        margins: per tube-margins study, (its ``sweep.toml``, :func:`twin_pairs` with its
            hand-margin twin).
    """
    paused, series = _paused_reading(results)
    lines = ["### Reading", "", *paused]
    for spec, pairs in margins:
        better, worse, tie = _tally(pairs)
        unset = sum(not c.ran and separated(c, h) and c.rate < h.rate for c, h in pairs)
        lines.append(f"- Each rate's tube margins vs one hand margin (`{spec.get('name')}`): "
                     f"better in {better} of {len(pairs)} cells with separated intervals, "
                     f"worse in {worse}" + (f" ({unset} of them cells whose tube margins "
                                             "were refused at set-up)" if unset else "")
                     + f"; {tie} unresolved.")
    for words, cells, twins, lat in latency:
        better, worse, _ = _tally(twins)
        lines.append(f"- Solve time charged ({', '.join(words)}): {worse} of {len(twins)} "
                     f"cells succeed less often than with time paused, {better} more often "
                     "(separated intervals); the rest unresolved.")
        rates = _pairs(cells)[0]
        if rates:
            what = ", ".join([f"{words[0]} charged", *words[1:]])
            lines.append(_rate_reading(f"Faster MPC ({what})", rates, "policy")
                         + _trend_tally(_series_set_up(cells)) + _paced(cells, lat))
    return lines + [_limits(series), ""]


def _paused_reading(results: list[tuple[dict, list]]) -> tuple[list[str], list[list]]:
    """The reading's time-paused lines and the series set up whose trends they tally.

    Faster MPC (fastest vs slowest rate, the trend tally); replanning vs planning once.
    """
    rate_pairs, plan_pairs, refused, series = [], [], 0, []
    for spec, cells in results:
        if charged(spec) is None:
            r, p = _pairs(cells)
            rate_pairs += r
            plan_pairs += p
            refused += _refused_series(cells)
            series += _series_set_up(cells)
    lines = []
    if rate_pairs:
        lines.append(_rate_reading("Faster MPC (time paused)", rate_pairs, "study x "
                                   "disturbance size x policy"))
        if refused:
            lines[-1] += (f" In {refused} of these series a slower rate's margins were "
                          "refused at set-up, so none of its runs ran: the slowest rate "
                          "compared is the slowest set up (each study's findings give the "
                          "trend both ways).")
        lines[-1] += _trend_tally(series)
    if plan_pairs:
        up, down, tie = _tally(plan_pairs)
        lines.append(f"- Replanning at contacts vs planning once (time paused): better in {up} "
                     f"of {len(plan_pairs)} cells with separated intervals, worse in {down}; "
                     f"{tie} unresolved.")
    return lines, series


def _limits(series: list[list]) -> str:
    """The reading's last line: what the studies do not support."""
    up, down = _trend_counts(series) if series else (0, 0)
    return ("- Not supported by this study: rates outside the tested grid, other systems, "
            "other disturbance shapes than a held uniform box, and real-time behaviour "
            "beyond a charged latency (fixed, or modelled from the solver's iterations); "
            "the tube diameters are bounds from sampled constants (Step 5): the paper's "
            "mechanism for a trend, not a certificate of one"
            + (", and the trends above (time paused) point both ways." if up and down
               else "."))


def _rate_reading(what: str, pairs: list[tuple], series: str) -> str:
    """The fastest-vs-slowest-rate tally of ``pairs`` as a reading line."""
    up, down, tie = _tally(pairs)
    return (f"- {what}: in {up} of {len(pairs)} series ({series}) the fastest rate succeeds "
            f"more often than the slowest with separated intervals, in {down} less often; "
            f"{tie} unresolved at this sample size.")


def side_by_side(pairs: list[tuple]) -> list[str]:
    """Markdown table of (cell, twin) pairs: one row per (size, policy), a column per rate."""
    xs = sorted({c.x for c, _ in pairs})
    rows: dict[tuple[str, str], dict[float, tuple]] = {}
    for c, t in pairs:
        rows.setdefault((c.panel, c.series), {})[c.x] = (c, t)
    lines = ["| disturbance | policy | " + " | ".join(f"{x:g} Hz" for x in xs) + " |",
             "| --- | --- | " + " | ".join("---" for _ in xs) + " |"]
    for (panel, series), by_x in rows.items():
        parts = ["-" if x not in by_x else " \\| ".join(
            f"{c.successes}/{c.runs}" + ("" if c.ran else " refused") for c in by_x[x])
            for x in xs]
        lines.append(f"| ±{panel} | {series} | " + " | ".join(parts) + " |")
    return lines


def _margins_line(tube, hand) -> str:
    """A cell with tube margins against its hand-margin twin, for the list under the table."""
    where = f"- ±{tube.panel}, {tube.series}, {tube.x:g} Hz: "
    if not tube.ran:
        return (where + f"the tube margins were refused at set-up (none of its {tube.runs} "
                f"runs ran); with the hand margin {100 * hand.rate:.0f} % "
                f"({hand.successes}/{hand.runs}).")
    return where + _compare(tube, hand, "success with tube margins", "with the hand margin") + "."


def _hand_twin(spec: dict, paused: list[tuple[dict, list]]) -> tuple[dict, list] | None:
    """The hand-margin study with a tube-margins study's settings, else None."""
    if spec.get("set", {}).get("mpc.margins") != "tube":
        return None

    def key(s: dict) -> dict:
        return {k: v for k, v in s.get("set", {}).items() if k != "mpc.margins"}

    return next((p for p in paused if p[0].get("set", {}).get("mpc.margins", "hand") == "hand"
                 and key(p[0]) == key(spec)), None)


#: the [set] keys in which a latency study and its time-paused twin may differ (the low
#: level past the guard acts with time paused only where an impact's re-solve fails)
_LATENCY_KEYS = ("sim.latency", "sim.latency_first", "lowlevel.past_guard", SIZE)


def _twin(spec: dict, paused: list[tuple[dict, list]]) -> tuple[dict, list] | None:
    """The paused study with the latency study's settings but the latency (and size)."""
    def key(s: dict) -> tuple:
        return s.get("scenario"), {k: v for k, v in s.get("set", {}).items()
                                   if k not in _LATENCY_KEYS}

    return next((p for p in paused if key(p[0]) == key(spec)), None)


def _first_paused(spec: dict) -> bool:
    """Whether a study computes the first plan with time paused.

    Its ``[set]`` says, else the effective scenario of its runs (``spec["effective"]``,
    see :func:`study_section`).
    """
    value = spec.get("set", {}).get("sim.latency_first",
                                    spec.get("effective", {}).get("sim.latency_first"))
    return value == "paused"


def _follows(spec: dict) -> bool:
    """Whether a study's low level follows the plan across impacts.

    Its ``[set]`` says, else the effective scenario of its runs (as :func:`_first_paused`).
    """
    value = spec.get("set", {}).get("lowlevel.past_guard",
                                    spec.get("effective", {}).get("lowlevel.past_guard"))
    return value == "next_domain"


def _first_plan(spec: dict, latency: object) -> str:
    """A latency study's first plan and low level past the guard, in a sentence or two.

    ``sim.latency_first`` and ``lowlevel.past_guard``.
    """
    follow = (" After an impact the low level follows the plan's next domain until the "
              "next plan arrives (`lowlevel.past_guard = \"next_domain\"`; the paused "
              "study holds the guard node, which differs only where an impact's re-solve "
              "fails).") if _follows(spec) else ""
    if _first_paused(spec):
        return ("The first plan is computed with time paused at t = 0 "
                "(`sim.latency_first = \"paused\"`); every later plan is charged." + follow)
    wait = {"measured": "its solve time", "model": "its modelled compute time"}.get(
        str(latency), f"{latency} s")
    return (f"The first plan, too, reaches the plant {wait} after the state it was computed "
            "from: until then the input is zero (`sim.latency_first = \"paused\"` would "
            "compute it with time paused)." + follow)


def _latency_words(spec: dict, latency: object) -> tuple[str, ...]:
    """A latency study in a few words: ("0.03 s latency", "first plan paused")."""
    return (latency_text(latency), *(["first plan paused"] if _first_paused(spec) else []),
            *(["low level following the plan"] if _follows(spec) else []))


def _solver_pace(latency: object) -> str:
    """The rate above which a fixed latency L makes the MPC run at the solver's pace."""
    pace = _pace(latency)
    if pace is None:
        return ""
    return (f" There is one solver: a solve that falls due while it still computes waits "
            f"for it, so rates above 1/L = {pace:.3g} Hz solve at most {pace:.3g} times a "
            "second.")


def _tube_vs_hand(spec: dict, hand: dict, pairs: list[tuple]) -> list[str]:
    """A tube-margins study's cells beside its hand-margin twin's (``sweep.toml``s)."""
    return [f"### Each rate's tube margins vs one hand margin: `{spec.get('name')}` beside "
            f"`{hand.get('name')}`", "",
            "The same grid cells with the paper's mechanism, every MPC rate tightening its "
            "constraints by the margins of its own tube (for a guard whose gap sees positions "
            "only, as the ball's guards do, the kinematic tube, the integral of diam T(s) "
            "over one period 1/f: hmpc's refinement of the paper's diam T(1/f), "
            "docs/tubes.md; its constants those of the tube table above, on `hmpc tube`'s "
            "default region), and with one hand margin at every rate; each cell: tube k/n | "
            "hand k/n (each the first n seeds of its sweep, so the smaller count's seeds and "
            "disturbance draws are shared; `refused`: the tube margins were refused at "
            "set-up, no run ran).", "", *side_by_side(pairs), "",
            *[_margins_line(c, h) for c, h in pairs if separated(c, h) or not c.ran], ""]


def robustness_sections(studies: list[Study], fig_dir: Path, base: Path) -> list[str]:
    """The page's robustness part: every study, the latency comparison, the reading."""
    lines = ["## Robustness study: success rate vs MPC rate", "",
             "Each run draws its disturbance from its seed (each study lists the settings "
             "of its runs); success = the task's verdict at the run's end (the ball: ending "
             "inside the circle). Lower panels: the tube diameter diam T(1/f) of the same "
             "scenario and disturbance size at each MPC rate f.", ""]
    results: list[tuple[dict, list]] = []
    for study in studies:
        try:
            with blamed_on(study.directory):
                section, cells, spec = study_section(study, fig_dir, base)
        except FigureInputError as exc:
            if not not_run_yet(study.directory):
                raise  # a table of runs that is unusable: the command names its option
            from hmpc_cli.report.paths import portable_path, portable_text

            why = (f"Not run yet: no run of `{portable_path(study.sweep_file)}` is in this "
                   f"repository (`hmpc sweep {portable_path(study.sweep_file)}` runs it, "
                   "resumably)." if study.sweep_file else
                   f"Not drawn: {portable_text(str(exc))}")
            lines += [f"### {study.directory.name}", "", why, ""]
            continue
        lines += section
        results.append((spec, cells))
    paused = [r for r in results if charged(r[0]) is None]
    margins: list[tuple[dict, list[tuple]]] = []
    for spec, cells in paused:
        twin = _hand_twin(spec, paused)
        if twin is not None:
            pairs = twin_pairs(twin[1], cells)
            margins.append((spec, pairs))
            lines += _tube_vs_hand(spec, twin[0], pairs)
    latency: list[tuple[tuple[str, ...], list, list[tuple], object]] = []
    for spec, cells in results:
        lat = charged(spec)
        if lat is None:
            continue
        twin = _twin(spec, paused)
        if twin is None:
            lines += [f"### {latency_text(lat)} charged", "",
                      f"`{spec.get('name')}`: no study on this page has its settings with "
                      "time paused, so its cells are not compared.", ""]
            continue
        pairs = twin_pairs(twin[1], cells)
        mine = latency_lines(pairs, lat)
        latency.append((_latency_words(spec, lat), cells, pairs, lat))
        lines += [f"### {latency_text(lat)} charged vs time paused", "",
                  f"`{spec.get('name')}` beside the same cells of `{twin[0].get('name')}`. "
                  + _first_plan(spec, lat) + _solver_pace(lat), "", *mine, ""]
    return lines + reading(results, latency, margins)
