"""Our Figure 3 runs drawn over the authors' trajectories: one small panel per trial.

Drawn from :class:`~hmpc_cli.analysis.fig3compare.TrialComparison` rows: our positions as the run
logs hold them (read by :func:`hmpc_cli.log.rundata.read_run`, bounces spliced in at the
logged events), theirs from the authors' CSV (:mod:`hmpc_cli.analysis.authors`), the guards from
the logs' static polylines. Never runs a controller and never builds a model.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from hmpc_cli.figures.common import (
    OKABE_ITO,
    TEXT_WIDTH_IN,
    check_size,
    figure_style,
    make_out_dir,
    parse_formats,
    save_figure,
    static_polylines)
from hmpc_cli.analysis.tables import FigureInputError

__all__ = ["COLUMNS", "HEIGHT_PER_ROW_IN", "fig3_overlay", "overlay_figure"]

COLUMNS = 4  # trials per row; the last cell of the grid holds the legend
HEIGHT_PER_ROW_IN = 1.95  # [in] one row of square panels at text width, with its titles
OURS = OKABE_ITO["blue"]
THEIRS = OKABE_ITO["vermillion"]


def _polylines(rows) -> list[tuple[np.ndarray, np.ndarray]]:
    """The first logged geometry's static polylines (closed ones closed) [m]."""
    return static_polylines(next((r.geometry for r in rows if r.geometry is not None), None))


def _limits(rows, closed: list[np.ndarray]) -> tuple[tuple[float, float], tuple[float, float]]:
    """Common square (x, y) limits [m]: both sides' paths, the origin, closed guards (K, 2)."""
    pts = [np.zeros((1, 2)), *closed]
    for r in rows:
        for side in (r.ours, r.theirs):
            if side is not None:
                pts.append(side.xy[np.isfinite(side.xy).all(axis=1)])
    xy = np.vstack(pts)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = float(max(hi - lo)) * 1.08 or 1.0
    mid = 0.5 * (lo + hi)
    return ((mid[0] - span / 2, mid[0] + span / 2), (mid[1] - span / 2, mid[1] + span / 2))


def _word(side) -> str:
    return "-" if side is None else ("ok" if side.success else "failed")


def _draw_trial(ax, row, lines, lims) -> None:
    """One trial: guards, their path (dashed), ours (solid), end points, outcome title."""
    for a, b in lines:
        ax.plot(a, b, color="black", lw=0.6, zorder=1, label="guards")
    for side, color, style, mark, label in (
            (row.theirs, THEIRS, (0, (3.0, 1.5)), "s", "authors"),
            (row.ours, OURS, "-", "o", "hmpc")):
        if side is None:
            continue
        ax.plot(side.xy[:, 0], side.xy[:, 1], color=color, lw=0.7, ls=style, zorder=3,
                label=label)
        ax.plot(*side.end, ls="none", marker=mark if side.success else "x", ms=3.5,
                mew=0.8, mfc="none", color=color, zorder=4)
    ax.set_title(f"{row.trial}\nhmpc {_word(row.ours)}, authors {_word(row.theirs)}",
                 linespacing=1.05)
    ax.set_xlim(*lims[0])
    ax.set_ylim(*lims[1])
    ax.set_aspect("equal", adjustable="box")


def overlay_figure(rows: Sequence, title: str = "", width: float = TEXT_WIDTH_IN,
                   height: float | None = None):
    """The overlay of one panel's trials as a Matplotlib Figure (no pyplot state).

    Args:
        rows: :class:`~hmpc_cli.analysis.fig3compare.TrialComparison` of one panel, drawn in order.
        title: the figure's title ('' for none).
        width: figure width [in].
        height: figure height [in] (None: :data:`HEIGHT_PER_ROW_IN` per row of panels).
    """
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    nrows = len(rows) // COLUMNS + 1
    height = HEIGHT_PER_ROW_IN * nrows + (0.2 if title else 0.0) if height is None else height
    fig = Figure(figsize=(width, height), layout="constrained")
    fig.get_layout_engine().set(w_pad=0.02, h_pad=0.02, wspace=0.02, hspace=0.02)
    axes = fig.subplots(nrows, COLUMNS, sharex=True, sharey=True, squeeze=False).ravel()
    lines = _polylines(rows)
    lims = _limits(rows, [np.column_stack([a, b]) for a, b in lines
                          if len(a) > 2 and a[0] == a[-1] and b[0] == b[-1]])
    for ax, row in zip(axes, rows, strict=False):
        _draw_trial(ax, row, lines, lims)
        ax.xaxis.set_major_locator(MaxNLocator(3))
        ax.yaxis.set_major_locator(MaxNLocator(3))
    for k, ax in enumerate(axes[: len(rows)]):
        if k % COLUMNS == 0:
            ax.set_ylabel(r"$y$ (m)")
        if k >= COLUMNS * (nrows - 1):
            ax.set_xlabel(r"$x$ (m)")
    legend_ax = axes[len(rows)]
    for ax in axes[len(rows):]:
        ax.axis("off")
    handles = [Line2D([], [], color=OURS, lw=0.9, marker="o", ms=3.5, mfc="none"),
               Line2D([], [], color=THEIRS, lw=0.9, ls=(0, (3.0, 1.5)), marker="s", ms=3.5,
                      mfc="none"),
               Line2D([], [], color="black", lw=0.6),
               Line2D([], [], color="gray", ls="none", marker="x", ms=4.0)]
    legend_ax.legend(handles, ["hmpc (end: circle)", "authors (end: square)", "guards",
                               "failed end"], loc="center", handlelength=2.2)
    if title:
        fig.suptitle(title)
    return fig


def fig3_overlay(rows: Sequence, out_dir: str | Path, stem: str,
                 formats: str | Iterable[str] = ("png",), *, title: str = "",
                 width: float = TEXT_WIDTH_IN, height: float | None = None,
                 dpi: int = 120) -> list[Path]:
    """Draws :func:`overlay_figure` into out_dir/stem.<fmt>; returns the written paths.

    Raises:
        FigureInputError: no rows, a size out of range or an unwritable directory.
    """
    if not rows:
        raise FigureInputError(f"{stem}: no trials to draw")
    fmts = parse_formats(formats)
    nrows = len(rows) // COLUMNS + 1
    check_size(width, height if height is not None else HEIGHT_PER_ROW_IN * nrows)
    out = make_out_dir(Path(out_dir))
    with figure_style():
        return save_figure(overlay_figure(rows, title, width, height), out, stem, fmts, dpi=dpi)
