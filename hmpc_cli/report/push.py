"""The biped's push study on the results page: where the walker starts to fail.

Reads the push sweep's results.csv only (``sweeps/biped_push.toml``: torso push
magnitude x walking-MPC rate, seeds): success per cell with Wilson 95 % intervals, the
boundary (per rate, the largest push at which every run succeeded and the smallest at
which none did), a Cochran-Armitage trend of success across push sizes per rate and
across rates per push size, and a figure (success vs push, one line per rate). Figure 4
is drawn again from the log of a run at the boundary: the largest push the default rate
still walked through.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from hmpc_cli.analysis.tables import FigureInputError, parse_bool, read_table, resolve_table
from hmpc_cli.figures.robustness import Cell, wilson
from hmpc_cli.figures.common import page_link
from hmpc_cli.report.robustness import trend_text, wall_text

__all__ = ["PUSH", "RATE", "push_cells", "push_section"]

PUSH, RATE = "disturbance.magnitude", "mpc.rate_hz"


#: the columns that make two rows of one cell the same run (the seed drew nothing)
SAME_RUN = ("success", "final_error", "contacts", "solves", "solver_failures", "reason")


def push_cells(rows: list[dict], where: str) -> list[Cell]:
    """Cells (panel "", series: the rate in Hz, x: the push [N]) of the push sweep's runs.

    A cell whose seeds all gave the same run (every :data:`SAME_RUN` column alike, e.g. no
    push: the seed draws nothing) counts it once (:func:`repeated_cells` names them).
    """
    out = []
    for (rate, push), sel in sorted(_by_cell(rows, where).items()):
        runs = sel[:1] if _one_run(sel) else sel
        out.append(Cell("", f"{rate:g}", push, len(runs),
                        sum(parse_bool(r.get("success"), where) for r in runs)))
    return out


def _by_cell(rows: list[dict], where: str) -> dict[tuple[float, float], list[dict]]:
    """The rows by (rate [Hz], push [N]).

    Raises:
        FigureInputError: a rate or push that is not a number, a success that is no bool.
    """
    by: dict[tuple[float, float], list[dict]] = {}
    for i, row in enumerate(rows, start=2):
        try:
            key = (float(row[RATE]), float(row[PUSH]))
        except (KeyError, ValueError):
            raise FigureInputError(f"{where}:{i}: columns {RATE} and {PUSH} must be numbers "
                                   "(is this the push sweep's results.csv?)") from None
        parse_bool(row.get("success"), f"{where}:{i}: column success")
        by.setdefault(key, []).append(row)
    return by


def _one_run(rows: list[dict]) -> bool:
    """Whether a cell's rows (two or more) are one run repeated (see :data:`SAME_RUN`).

    A table without final errors cannot tell: never.
    """
    first = tuple(rows[0].get(k) for k in SAME_RUN)
    return len(rows) > 1 and rows[0].get("final_error") not in (None, "") and \
        all(tuple(r.get(k) for k in SAME_RUN) == first for r in rows)


def _distinct(rows: list[dict], where: str) -> list[dict]:
    """The rows with each cell that is one run repeated (:func:`_one_run`) kept once."""
    return [r for sel in _by_cell(rows, where).values()
            for r in (sel[:1] if _one_run(sel) else sel)]


def _count(row: dict, key: str) -> int | None:
    try:
        return int(row[key])
    except (KeyError, TypeError, ValueError):
        return None


def _outcomes(rows: list[dict], where: str) -> list[str]:
    """How the distinct runs ended (:func:`_distinct`), in sentences.

    Falls before the first touchdown, solver failures, and how far from the goal the
    successes end (what a success asks).
    """
    runs = _distinct(rows, where)
    good = [parse_bool(r.get("success"), where) for r in runs]
    ok = [r for r, g in zip(runs, good, strict=True) if g]
    failed = [r for r, g in zip(runs, good, strict=True) if not g]
    out = []
    if failed and all(_count(r, "contacts") is not None for r in failed):
        early = {rate: sum(_count(r, "contacts") == 0 for r in failed if r[RATE] == rate)
                 for rate in dict.fromkeys(r[RATE] for r in failed)}
        out.append(f"{sum(early.values())} of the {len(failed)} failures fall before the first "
                   "touchdown (no contact: in the first swing; "
                   + ", ".join(f"{float(k):g} Hz {v} of "
                               f"{sum(r[RATE] == k for r in failed)}" for k, v in early.items())
                   + ").")
    if all(_count(r, "solver_failures") is not None for r in runs):
        hit = [g for r, g in zip(runs, good, strict=True) if _count(r, "solver_failures")]
        out.append(f"{len(hit)} of the {len(runs)} runs had a solver failure "
                   f"({sum(hit)} of the {len(ok)} successes).")
    errors = sorted(float(r["final_error"]) for r in ok if r.get("final_error"))
    if errors:
        out.append("A success is the stance foot on the top segment at the run's end: the "
                   f"successes end a median {statistics.median(errors):.2f} m from the goal "
                   f"(at most {errors[-1]:.2f} m).")
    return out


def repeated_cells(rows: list[dict], where: str = "results.csv") -> list[str]:
    """``±P N at F Hz`` for each cell whose seeds all gave the same run."""
    return [f"±{push:g} N at {rate:g} Hz" for (rate, push), sel in sorted(
        _by_cell(rows, where).items(), key=lambda kv: (kv[0][1], kv[0][0])) if _one_run(sel)]


def _boundary(cells: list[Cell]) -> list[str]:
    """Per rate: the largest push with no failure and the smallest with no success."""
    out = []
    for rate in dict.fromkeys(c.series for c in cells):
        sel = [c for c in cells if c.series == rate]
        safe = [c.x for c in sel if c.successes == c.runs]
        lost = [c.x for c in sel if c.successes == 0]
        first_fail = min((c.x for c in sel if c.successes < c.runs), default=None)
        if not safe:
            line = f"- {rate} Hz: failures at every push size"
        elif max(safe) == 0.0:
            line = f"- {rate} Hz: every run without a push walked"
        else:
            line = f"- {rate} Hz: every run walked up to ±{max(safe):g} N"
        line += (f"; the first failure at ±{first_fail:g} N" if first_fail is not None
                 else "; no failure up to the largest push")
        out.append(line + (f"; none walked at ±{min(lost):g} N." if lost else "."))
    return out


def _table(cells: list[Cell]) -> list[str]:
    rates = list(dict.fromkeys(c.series for c in cells))
    pushes = sorted({c.x for c in cells})
    by = {(c.series, c.x): c for c in cells}
    lines = ["| push | " + " | ".join(f"{r} Hz" for r in rates) + " |",
             "| --- | " + " | ".join("---" for _ in rates) + " |"]
    for p in pushes:
        parts = []
        for r in rates:
            c = by.get((r, p))
            lo, hi = wilson(c.successes, c.runs) if c else (0.0, 1.0)
            parts.append("-" if c is None else
                         f"{c.successes}/{c.runs} ({100 * lo:.0f}-{100 * hi:.0f} %)")
        lines.append(f"| ±{p:g} N | " + " | ".join(parts) + " |")
    return lines


def _draw(cells: list[Cell], out: Path) -> None:
    """Success rate vs push [N], one line per rate, Wilson bars: ``out`` (png, pdf)."""
    from matplotlib.figure import Figure

    from hmpc_cli.figures.common import (
        COLUMN_WIDTH_IN, figure_style, make_out_dir, save_figure)
    from hmpc_cli.figures.robustness import SERIES_STYLE

    with figure_style():
        fig = Figure(figsize=(COLUMN_WIDTH_IN, 2.0), layout="constrained")
        ax = fig.add_subplot()
        for k, rate in enumerate(dict.fromkeys(c.series for c in cells)):
            sel = [c for c in cells if c.series == rate]
            xs = [c.x for c in sel]
            ys = [c.rate for c in sel]
            lo = [c.rate - c.interval[0] for c in sel]
            hi = [c.interval[1] - c.rate for c in sel]
            ax.errorbar(xs, ys, yerr=[lo, hi], capsize=2, lw=1.0, ms=3.5,
                        label=f"{rate} Hz", **SERIES_STYLE[k % len(SERIES_STYLE)])
        ax.set_xlabel("torso push magnitude (N)")
        ax.set_ylabel("success rate (Wilson 95 %)")
        ax.set_ylim(-0.05, 1.05)
        ax.legend(loc="lower left", title="walking MPC")
        save_figure(fig, make_out_dir(out.parent), out.name, ("pdf", "png"))


def _boundary_run(rows: list[dict], rate: str) -> dict | None:
    """The run of ``rate`` [Hz] at the largest push any of its seeds walked through."""
    ok = [r for r in rows if r.get(RATE) and f"{float(r[RATE]):g}" == rate
          and parse_bool(r.get("success"), "results.csv: success") and r.get("log")]
    return max(ok, key=lambda r: (float(r[PUSH]), -int(r.get("seed") or 0)), default=None)


def push_section(directory: Path, fig_dir: Path, base: Path, default_rate: str = "10"
                 ) -> list[str]:
    """The page's push-study section (markdown lines); figures into ``fig_dir``.

    Raises:
        FigureInputError: no such table, or not the push sweep's.
    """
    table = resolve_table(directory)
    rows = read_table(table, [PUSH, RATE, "success"])
    cells = push_cells(rows, str(table))
    if not cells:
        raise FigureInputError(f"{table}: no finished run")
    _draw(cells, fig_dir / "biped_push")
    seeds = len({r.get("seed") for r in rows})
    repeated = repeated_cells(rows, str(table))
    once = ([f"Counted once: {', '.join(repeated)} (its {seeds} seeds gave one run, row for "
             "row alike: no push, nothing for the seed to draw)."] if repeated else [])
    lines = ["## The biped under pushes that matter", "",
             f"![biped push study]({page_link(fig_dir / 'biped_push.png', base)})", "",
             f"{len(rows)} finished runs of `sweeps/biped_push.toml`, {seeds} seeds (each its "
             "own push sequence: uniform in ±magnitude, held 0.1 s, at the torso) per cell; "
             "the Figure 4 stairs and 1.1x heavier robot; Wilson 95 % intervals. The "
             "paper gives no push size for its Figure 4; `scenarios/biped_stairs.toml` "
             "pushes with ±25 N (the reference notes' example); this robot's joints may "
             "give 3 kN m, and its stance foot is pinned (no friction or unilateral contact "
             "limit is modelled), so the pushes it withstands here are the model's, not a "
             f"real foot's; {wall_text(rows)}.", "", *_table(cells), "", *once,
             *_outcomes(rows, str(table)), "", "Where it starts to fail:", "",
             *_boundary(cells), "", "Trends (Cochran-Armitage):", ""]
    for rate in dict.fromkeys(c.series for c in cells):
        sel = [c for c in cells if c.series == rate]
        if len(sel) >= 2:
            lines.append("- " + trend_text(sel, [c.x for c in sel],
                                           f"{rate} Hz, across push sizes (scores: push [N])",
                                           "with the push") + ".")
    for push in sorted({c.x for c in cells}):
        sel = [c for c in cells if c.x == push]
        if len(sel) >= 2:
            lines.append("- " + trend_text(sel, [math.log(float(c.series)) for c in sel],
                                           f"±{push:g} N, across MPC rates (scores: log f)")
                         + ".")
    run = _boundary_run(rows, default_rate)
    if run is not None:
        lines += _boundary_walk(run, table, default_rate, fig_dir, base)
    return lines + [""]


def _boundary_walk(run: dict, table: Path, rate: str, fig_dir: Path, base: Path) -> list[str]:
    """Figure 4 drawn again from the boundary run's log (or why it is not drawn)."""
    from hmpc_cli.analysis.tables import resolve_run_log
    from hmpc_cli.figures.fig4 import fig4
    from hmpc_cli.report.traces import keep_traces

    what = (f"Figure 4 at the boundary: a {rate} Hz walk at the largest push size it walked "
            f"through (±{float(run[PUSH]):g} N, seed {run['seed']}, run "
            f"{run.get('run_id', '?')})")
    keep_traces([table.parent / Path(run["log"])])
    log = resolve_run_log(table.parent / Path(run["log"]))
    if not log.is_file():
        return ["", f"{what}: its log is not here (`hmpc sweep sweeps/biped_push.toml` "
                "writes it), so it is not drawn."]
    walk = fig4(log, fig_dir / "fig4_push", "pdf,png")
    return ["", f"{what}; F_x to the run's end ({walk.t[-1]:.2f} s):", "",
            f"![Figure 4 at ±{float(run[PUSH]):g} N]"
            f"({page_link(fig_dir / 'fig4_push' / 'fig4.png', base)})"]
