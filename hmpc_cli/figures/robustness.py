"""The robustness study: success rate versus MPC rate, per replanning policy and disturbance size.

Drawn from a sweep table (results.csv) only: every finished run is one Bernoulli trial
(success by the scenario's criterion; a crashed or diverged run counts as a failure). Each
cell (x value, series, panel) gets its success rate with a Wilson score interval.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from hmpc_cli.figures.common import (
    TEXT_WIDTH_IN,
    check_outputs,
    check_size,
    figure_style,
    make_out_dir,
    parse_formats,
    save_figure,
    write_csv)
from hmpc_cli.analysis.tables import (
    FigureInputError,
    parse_bool,
    read_table,
    resolve_table,
    sweep_spec)

__all__ = ["Cell", "cells", "robustness", "wilson"]

Z95 = 1.959963984540054  # standard normal 97.5 % quantile
SERIES_STYLE = ({"color": "#1f4e8c", "marker": "o", "linestyle": "-"},
                {"color": "#d2691e", "marker": "s", "linestyle": "--"},
                {"color": "#2e8b57", "marker": "^", "linestyle": ":"},
                {"color": "#7b3f99", "marker": "D", "linestyle": "-."})


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval (lo, hi) of a binomial proportion with k successes in n trials."""
    if n <= 0:
        return (0.0, 1.0)
    p = k / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1.0 - p) / n + z * z / (4 * n * n)) / denom
    lo = 0.0 if k == 0 else max(0.0, centre - half)  # exact ends (no round-off past p)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return (lo, hi)


@dataclass(frozen=True)
class Cell:
    """Success statistics of one (x, series, panel) cell over its seeds.

    ``not_set_up``: of its ``runs``, those whose controller was never set up (counted as
    failed; which runs is the caller's test, e.g. margins that do not fit the NLP).
    """

    panel: str
    series: str
    x: float
    runs: int
    successes: int
    not_set_up: int = 0

    @property
    def ran(self) -> bool:
        """Whether any of its runs got a controller (not every one failed at set-up)."""
        return self.not_set_up < self.runs

    @property
    def rate(self) -> float:
        """Success rate successes / runs in [0, 1]; NaN for a cell without runs."""
        return self.successes / self.runs if self.runs else math.nan

    @property
    def interval(self) -> tuple[float, float]:
        """95 % Wilson score interval (lo, hi) of the success rate; (0, 1) without runs."""
        return wilson(self.successes, self.runs)


def _number(text: str, where: str) -> float:
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise FigureInputError(f"{where}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise FigureInputError(f"{where}: expected a finite number, got {text!r}")
    return v


def grid_order(table: Path, axis: str) -> list[str]:
    """The values of ``axis`` in the order its sweep lists them, as text.

    From ``[grid]`` of the ``sweep.toml`` beside the table; [] without one.
    """
    spec = sweep_spec(Path(table).parent)
    values = spec.get("grid", {}).get(axis) if isinstance(spec.get("grid"), dict) else None
    return [str(v) for v in values] if isinstance(values, list) else []


def _order(values: list[str], listed: Sequence[str] = ()) -> list[str]:
    """Numeric order when every value is a number, else the sweep's order (``listed``).

    Values the sweep does not list come after, in order of first appearance (a sweep's
    results.csv is sorted by run id: its first row's values say nothing).
    """
    try:
        return sorted(values, key=float)
    except ValueError:
        rank = {v: i for i, v in enumerate(listed)}
        return sorted(values, key=lambda v: rank.get(v, len(rank)))


#: the panel of every run when the table has no panel column (:func:`default_axes`)
ONE_PANEL = "all runs"
#: the column a robustness figure's panels follow by default, in order of preference: the
#: disturbance size as a grid axis, else as a fixed setting of the sweep (``[set]``)
PANEL_AXES = ("disturbance.magnitude", "set.disturbance.magnitude")


#: the x axis's and the series' default columns, in order of preference: a grid axis, else
#: the value a table axis's entries (or ``[set]``) give (``set.`` columns)
X_AXES = ("mpc.rate_hz", "set.mpc.rate_hz")
SERIES_AXES = ("replanning.policy", "set.replanning.policy")


def default_axes(table: str | Path, panel: str | None = None, x: str | None = None,
                 series: str | None = None) -> tuple[str | None, str, str]:
    """The (panel, x, series) axes: those given, else the table's defaults (one read).

    A default is the first of :data:`PANEL_AXES`, :data:`X_AXES` and :data:`SERIES_AXES`
    the table has. No panel column: None (one panel, :data:`ONE_PANEL`); no x or series column: the
    first name (the error names it).
    """
    present = read_table(resolve_table(table), ["success"])[0].keys()

    def first(columns: Sequence[str]) -> str | None:
        return next((c for c in columns if c in present), None)

    return (panel if panel is not None else first(PANEL_AXES),
            x if x is not None else first(X_AXES) or X_AXES[0],
            series if series is not None else first(SERIES_AXES) or SERIES_AXES[0])


def cells(table: str | Path, x_axis: str, series_axis: str, panel_axis: str | None,
          not_set_up: Callable[[dict], bool] | None = None) -> list[Cell]:
    """Pools the table's runs into cells, ordered by panel, series, x.

    ``panel_axis`` None puts every run in one panel, :data:`ONE_PANEL`.
    ``not_set_up(row)``: whether a row's run never got a controller (default: none).
    """
    path = resolve_table(table)
    rows = read_table(path, [x_axis, series_axis, *([panel_axis] if panel_axis else []),
                             "success"])
    counts: dict[tuple[str, str, float], list[int]] = {}
    panels: list[str] = []
    series: list[str] = []
    for i, row in enumerate(rows, start=2):
        where = f"{path}:{i}"
        x = _number(row[x_axis], f"{where}: column {x_axis}")
        ok = parse_bool(row["success"], f"{where}: column success")
        key = (row[panel_axis] if panel_axis else ONE_PANEL, row[series_axis], x)
        panels += [key[0]] if key[0] not in panels else []
        series += [key[1]] if key[1] not in series else []
        c = counts.setdefault(key, [0, 0, 0])
        c[0] += 1
        c[1] += ok
        c[2] += bool(not_set_up and not_set_up(row))
    out = []
    for p in _order(panels, grid_order(path, panel_axis)):
        for s in _order(series, grid_order(path, series_axis)):
            for x in sorted({k[2] for k in counts if k[0] == p and k[1] == s}):
                out.append(Cell(p, s, x, *counts[(p, s, x)]))
    return out


def _write_table(path: Path, data: list[Cell], names: tuple[str, str, str]) -> None:
    write_csv(path, [*names, "runs", "successes", "success_rate", "wilson95_lo",
                     "wilson95_hi", "not_set_up"],
              ([c.panel, c.series, f"{c.x:g}", c.runs, c.successes, f"{c.rate:.4f}",
                f"{c.interval[0]:.4f}", f"{c.interval[1]:.4f}", c.not_set_up]
               for c in data))


#: axis labels of the bundled study's columns (others: the key's last part)
AXIS_LABELS = {"mpc.rate_hz": "MPC rate [Hz]", "replanning.policy": "replanning",
               "disturbance.magnitude": "disturbance"}


def _axis_label(axis: str) -> str:
    axis = axis.removeprefix("set.")  # a value the sweep's table entries or [set] give
    return AXIS_LABELS.get(axis, axis.rsplit(".", 1)[-1].replace("_", " "))


def _panel_title(axis: str | None, value: str) -> str:
    if axis is None:
        return value
    axis = axis.removeprefix("set.")  # a sweep's fixed setting as a column
    try:
        if axis == "disturbance.magnitude":
            return f"$|w_i| \\leq {float(value):g}$"
    except ValueError:
        pass
    return f"{_axis_label(axis)} {value}"


#: the curves' legend entries, by bound name: what each bounds, and in what
TUBE_LABEL = {"trivial": "trivial: diam $T(1/f)$, state norm",
              "kinematic": r"kinematic: $\int_0^{1/f}$ diam $T$, positions"}
#: line styles of the tube-diameter curves, by bound name (others: grey)
TUBE_STYLE = {"trivial": {"color": "#0072B2", "linestyle": "-", "marker": "v"},
              "kinematic": {"color": "#CC79A7", "linestyle": "-.", "marker": "x"}}


def robustness(table: str | Path, out_dir: str | Path | None = None,
               formats: str | Sequence[str] = "pdf,svg,png", *,
               x_axis: str = "mpc.rate_hz", series_axis: str = "replanning.policy",
               panel_axis: str | None = "disturbance.magnitude",
               width: float = TEXT_WIDTH_IN,
               height: float = 1.9, name: str = "robustness",
               diameters: Mapping[float, Mapping[str, Sequence[tuple[float, float]]]]
               | None = None,
               not_set_up: Callable[[dict], bool] | None = None) -> list[Cell]:
    """Draws success rate vs ``x_axis`` (log scale) with Wilson 95 % intervals.

    One panel per ``panel_axis`` value (None: one panel, :data:`ONE_PANEL`; see
    :func:`default_axes`), one line per ``series_axis`` value; a cell none of
    whose runs was set up (``not_set_up``, see :func:`cells`) is a cross at 0, off the
    line. With ``diameters`` (panel value -> bound name -> [(x, diam T(1/x))]) a second
    row draws the tube diameters on the same x axis (log y). Writes ``<name>.<fmt>`` and
    ``<name>_table.csv`` to ``out_dir`` (default: the table's directory) and returns the
    cells.
    """
    fmts = parse_formats(formats)
    rows = 2 if diameters else 1
    check_size(width, height * (1.0 + 0.75 * (rows - 1)))
    data = cells(table, x_axis, series_axis, panel_axis, not_set_up)
    out = Path(out_dir) if out_dir is not None else resolve_table(table).parent
    make_out_dir(out)
    import matplotlib.pyplot as plt

    panels = list(dict.fromkeys(c.panel for c in data))
    with figure_style():
        fig, axes = plt.subplots(rows, len(panels), sharex="col", squeeze=False,
                                 figsize=(width, height * (1.0 + 0.75 * (rows - 1))),
                                 gridspec_kw={"height_ratios": [1.0, 0.75][:rows]})
        for ax, p in zip(axes[0], panels, strict=True):
            _success_panel(ax, data, p, panel_axis, series_axis)
        axes[0][0].set_ylabel("success rate (Wilson 95 %)")
        _success_legend(axes[0], data, series_axis)
        if diameters:
            for ax, p in zip(axes[1], panels, strict=True):
                if ax is not axes[1][0]:
                    ax.sharey(axes[1][0])
                _diameter_panel(ax, diameters, p)
            axes[1][0].set_ylabel("tube bound at $1/f$")
            found = _handles(axes[1])
            if found:
                axes[1][-1].legend(found.values(), found.keys(), loc="lower left",
                                   title="tube bound")
        _rate_axes(axes, sorted({c.x for c in data}), x_axis)
        fig.tight_layout(pad=0.3, w_pad=0.4, h_pad=0.3)
        check_outputs(out, [f"{name}_table.csv", *(f"{name}.{f}" for f in fmts)])
        save_figure(fig, out, name, fmts)
    _write_table(out / f"{name}_table.csv", data,
                 (panel_axis or "panel", series_axis, x_axis))
    return data


def _rate_axes(axes, xs: list[float], x_axis: str) -> None:
    """Every panel's log x axis ticked at the table's values ``xs``; the bottom row labelled."""
    for ax in axes[-1]:
        ax.set_xlabel(_axis_label(x_axis))
    for ax in axes.ravel():
        ax.set_xscale("log")
        ax.set_xticks(xs)
        ax.set_xticklabels([f"{x:g}" for x in xs])
        ax.minorticks_off()
        ax.grid(True, linewidth=0.3, alpha=0.5)


def _handles(row) -> dict:
    """Legend handles of a row of axes by label (one per label, the last one drawn)."""
    return {lb: h for ax in row for h, lb in zip(*ax.get_legend_handles_labels(), strict=True)}


def _success_legend(row, data: list[Cell], series_axis: str) -> None:
    """The series legend on the row's last panel, a cross for cells never set up if any."""
    marks = _handles(row)
    if not all(c.ran for c in data):
        from matplotlib.lines import Line2D

        marks["not set up (no run)"] = Line2D([], [], color="0.25", marker="x",
                                              linestyle="none", markersize=4)
    row[-1].legend(marks.values(), marks.keys(), loc="best", title=_axis_label(series_axis))


def _success_panel(ax, data: list[Cell], panel: str, panel_axis: str,
                   series_axis: str) -> None:
    """One panel's success rates per series with Wilson bars (series dodged on log x)."""
    series = list(dict.fromkeys(c.series for c in data))
    for j, s in enumerate(series):
        sel = [c for c in data if c.panel == panel and c.series == s]
        lo = [c.rate - c.interval[0] for c in sel if c.ran]
        hi = [c.interval[1] - c.rate for c in sel if c.ran]
        style = SERIES_STYLE[j % len(SERIES_STYLE)]
        dodge = 1.06 ** (j - (len(series) - 1) / 2)  # keep the bars apart (log x)
        ax.errorbar([c.x * dodge for c in sel if c.ran], [c.rate for c in sel if c.ran],
                    yerr=[lo, hi], capsize=1.5, elinewidth=0.6, markersize=2.5, label=s,
                    **style)
        unset = [c.x * dodge for c in sel if not c.ran]
        if unset:
            ax.plot(unset, [0.0] * len(unset), linestyle="none", marker="x", markersize=4,
                    color=style["color"])
    n = sorted({c.runs for c in data if c.panel == panel})
    runs = f"{n[0]}" if len(n) == 1 else f"{n[0]}-{n[-1]}"
    ax.set_title(f"{_panel_title(panel_axis, panel)}  (n = {runs})")
    ax.set_ylim(-0.03, 1.03)
    if ax is not ax.figure.axes[0]:
        ax.tick_params(labelleft=False)


def _diameter_panel(ax, diameters: Mapping[float, Mapping[str, Sequence[tuple[float, float]]]],
                    panel: str) -> None:
    """Tube diameters vs x for the panel's value (log y); 'no tube' if none given."""
    curves = next((v for k, v in diameters.items() if _same(k, panel)), None)
    if not curves:
        ax.text(0.5, 0.5, "no tube", transform=ax.transAxes, ha="center", va="center")
        return
    for bound, points in curves.items():
        pts = sorted((x, d) for x, d in points if math.isfinite(d) and d > 0)
        if pts:
            style = TUBE_STYLE.get(bound, {"color": "0.4", "linestyle": ":", "marker": "."})
            ax.plot([x for x, _ in pts], [d for _, d in pts], markersize=3,
                    label=TUBE_LABEL.get(bound, bound), **style)
    ax.set_yscale("log")


def _same(key: float, panel: str) -> bool:
    """Whether a diameters key names the panel value (numerically)."""
    try:
        return math.isclose(float(key), float(panel))
    except (TypeError, ValueError):
        return str(key) == panel
