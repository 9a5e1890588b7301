"""Figure 3 of the paper: the bouncing ball under the same disturbances, one panel per controller.

Drawn from a sweep table (results.csv) and the run logs it points to; never runs a controller
and never rebuilds a model. Each panel's guards are the static polylines its logs' geometry
records (what the system's drawing declares, :mod:`hmpc_cli.log.geometry`), in the plane of
the logged ``plane`` states: any system, with its own geometry.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hmpc_cli.analysis.tables import (
    FigureInputError, RunTrace, load_trace, parse_bool, read_table, resolve_log, resolve_table)
from hmpc_cli.figures.common import (
    COLUMN_WIDTH_IN, OKABE_ITO, check_outputs, check_size, figure_style, make_out_dir,
    parse_formats, save_figure, static_polylines, write_csv)

__all__ = ["PAPER_GEOMETRY", "REFERENCE_COUNTS", "PanelCounts", "fig3", "not_the_paper"]

# The paper's Figure 3 outcome (stable runs / runs, 10 disturbed trials + nominal): of the
# ball with the paper's geometry only (see PAPER_GEOMETRY and not_the_paper).
REFERENCE_COUNTS: dict[str, tuple[int, int]] = {
    "10 Hz fixed": (9, 11), "20 Hz fixed": (11, 11), "10 Hz replan": (11, 11)}
#: the paper's ball geometry: the defaults of the ball's parameters (figures read logs and
#: import no system; tests/test_newcomer.py checks these against BallParams)
PAPER_SYSTEM = "ball"
PAPER_GEOMETRY: dict[str, object] = {
    "radius": 0.1, "circle_center": [3.0, 3.0], "circle_radius": 1.0,
    "floor_extent": [0.0, 8.0], "wall_extent": [0.0, 8.0], "x0": [1.0, 1.0, 0.0, 0.0],
    "goal": None}

# Okabe-Ito colours; each kind also differs without colour: nominal a thick solid line,
# disturbed thin dashed lines, end points small dots, failed ends large crosses, the start a
# square, the goal a plus.
TRACE_COLOR = OKABE_ITO["blue"]  # disturbed runs
NOMINAL_COLOR = OKABE_ITO["orange"]  # the paper's orange
START_COLOR = OKABE_ITO["purple"]
FAIL_COLOR = OKABE_ITO["vermillion"]
HEIGHT_IN = 2.1  # default height at one-column width: three square panels + legend below


@dataclass
class PanelCounts:
    """Outcome of one panel: number of runs, stable runs, trace labels of the failed runs.

    ``notes`` names the logs left out (unreadable) or drawn only up to a damaged chunk.
    """

    label: str
    runs: int = 0
    successes: int = 0
    failed: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: why the paper's counts do not apply to these runs ('' : they are the paper's system
    #: and geometry, see :func:`not_the_paper`)
    not_paper: str = ""


def _same(a: object, b: object) -> bool:
    """Whether two logged parameter values are equal (lists and tuples alike, floats exact)."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return a == b


def not_the_paper(scenarios: Iterable[dict]) -> str:
    """Why runs of these scenarios are not the paper's Figure 3 setting, or '' if they are.

    The paper's counts (:data:`REFERENCE_COUNTS`) are of the ball with its default geometry
    (:data:`PAPER_GEOMETRY`); the simulated plant's parameters (``plant``) count too.
    """
    for sc in scenarios:
        system = dict(sc.get("system") or {})
        name = system.get("name", PAPER_SYSTEM)
        if name != PAPER_SYSTEM:
            return f"runs of system {name!r}, not the paper's {PAPER_SYSTEM!r}"
        for where, params in (("system", system), ("plant", dict(sc.get("plant") or {}))):
            for key, paper in PAPER_GEOMETRY.items():  # a key not logged: the default
                if not _same(params.get(key, paper), paper):
                    return (f"{where}.{key} = {params.get(key)!r}, not the paper's "
                            f"{paper!r}")
    return ""


@dataclass
class _Run:
    trace_label: str
    success: bool
    nominal: bool
    trace: RunTrace


def _natural(text: str) -> list:
    """Sort key that puts "trial 2" before "trial 10"."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", text)]


def _group(rows: list[dict[str, str]], panel_axis: str, panels: Sequence[str] | None,
           table: Path) -> dict[str, list[tuple[int, dict[str, str]]]]:
    """Groups rows (with their table line numbers) by panel, in order of first appearance.

    The paper's Figure 3 controllers keep the paper's left-to-right order, a variant of one
    ("10 Hz fixed, floor shift") right after it, any other panel after them (a table's
    order need not be the paper's).
    """
    groups: dict[str, list[tuple[int, dict[str, str]]]] = {}
    for i, row in enumerate(rows):
        groups.setdefault((row.get(panel_axis) or "").strip(), []).append((i + 2, row))
    if panels is None:
        paper = list(REFERENCE_COUNTS)

        def key(p: str) -> int:
            return next((k for k, q in enumerate(paper) if p == q or p.startswith(q + ",")),
                        len(paper))

        return {p: groups[p] for p in sorted(groups, key=key)}
    unknown = [p for p in panels if p not in groups]
    if unknown:
        have = ", ".join(repr(g) for g in groups)
        raise FigureInputError(f"{table}: no {panel_axis} {', '.join(map(repr, unknown))} "
                               f"(has: {have})")
    if len(set(panels)) != len(panels):
        raise FigureInputError(f"--panels lists a panel twice: {', '.join(panels)}")
    return {p: groups[p] for p in panels}


def _load_runs(table: Path, groups: dict, trace_axis: str, nominal: str | None,
               notes: dict[str, list[str]]) -> dict[str, list[_Run]]:
    """Loads every run of every panel (all checks happen here, before anything is written).

    An unreadable log is left out and a damaged one kept as read (its intact chunks), each
    with a line in ``notes[label]``; a panel left without runs is dropped
    (FigureInputError if all are).
    """
    out: dict[str, list[_Run]] = {}
    for label, rows in groups.items():
        runs, notes[label] = [], []
        for line, row in rows:
            where = f"{table}:{line}"
            ok = parse_bool(row.get("success"), f"{where}: success")
            try:
                trace = load_trace(resolve_log(table, row.get("log"), where))
            except FigureInputError as exc:  # its text may start with the row's place
                notes[label].append(f"{where}: skipped: {str(exc).removeprefix(where + ': ')}")
                continue
            if trace.damage:
                notes[label].append(f"{trace.path}: damaged log, its intact chunks drawn "
                                    f"({trace.damage})")
            tl = (row.get(trace_axis) or "").strip()
            runs.append(_Run(tl, ok, nominal is not None and tl == nominal, trace))
        if runs:
            out[label] = runs
        else:
            notes[label].append(f"panel {label!r}: no readable log, panel left out")
    if not out:
        said = [n for ns in notes.values() for n in ns if not n.startswith("panel ")]
        more = f"; ... ({len(said)} rows in all)" if len(said) > 3 else ""
        raise FigureInputError(f"{table}: no readable run log: " + "; ".join(said[:3]) + more)
    return out


def _geometry(runs: list[_Run]):
    """The logged GeometryRec of the first run that has one (None: none, e.g. an old log)."""
    return next((r.trace.geometry for r in runs if r.trace.geometry is not None), None)


def _goal(geo) -> np.ndarray | None:
    """The goal point if it lives in the drawing plane (two coordinates), else None."""
    goal = np.asarray(geo.goal if geo is not None else (), dtype=float).ravel()
    return goal if goal.size == 2 else None


def _polylines(geo) -> list[tuple[np.ndarray, np.ndarray]]:
    """The drawing's static polylines as (a (K,), b (K,)) [m], closed ones closed."""
    return static_polylines(geo)


def _view(runs: dict[str, list[_Run]], geos) -> tuple[tuple[float, float], ...]:
    """Common (x, y) limits: every trajectory, goal, the origin and closed guards nearby."""
    xs, ys = [0.0], [0.0]
    for geo in geos:
        goal = _goal(geo)
        if goal is not None:
            xs.append(float(goal[0]))
            ys.append(float(goal[1]))
    for rs in runs.values():
        for r in rs:
            xy = r.trace.xy[np.isfinite(r.trace.xy).all(axis=1)]
            if len(xy):
                xs += [float(xy[:, 0].min()), float(xy[:, 0].max())]
                ys += [float(xy[:, 1].min()), float(xy[:, 1].max())]
    span = max(max(xs) - min(xs), max(ys) - min(ys), 1e-6)
    box = ((min(xs) - 0.6 * span, max(xs) + 0.6 * span),
           (min(ys) - 0.6 * span, max(ys) + 0.6 * span))
    for geo in geos:  # closed guard curves near the data (a circle) are shown whole
        for line in geo.static if geo is not None else ():
            a, b = np.asarray(line.a or [0.0]), np.asarray(line.b or [0.0])
            if line.closed and box[0][0] <= a.min() and a.max() <= box[0][1] \
                    and box[1][0] <= b.min() and b.max() <= box[1][1]:
                xs += [float(a.min()), float(a.max())]
                ys += [float(b.min()), float(b.max())]
    span = max(max(xs) - min(xs), max(ys) - min(ys))
    pad = 0.04 * span
    return (min(xs) - pad, max(xs) + pad), (min(ys) - pad, max(ys) + pad)


def _draw_guards(ax, geo: dict) -> None:
    """The guards as the system's drawing declares them (its static polylines)."""
    lines = _polylines(geo)
    for a, b in lines:
        ax.plot(a, b, color="black", lw=0.8, zorder=2)
    if lines:
        ax.plot([], [], color="black", lw=0.8, label="guards")


def _end(xy: np.ndarray) -> np.ndarray | None:
    """The last finite position of a trajectory."""
    good = np.flatnonzero(np.isfinite(xy).all(axis=1))
    return xy[good[-1]] if len(good) else None


def _draw_panel(ax, label: str, runs: list[_Run], geo: dict, view) -> None:
    """One panel: guards, trajectories, nominal on top, start/end/failed markers, goal, title."""
    from matplotlib.ticker import MaxNLocator

    _draw_guards(ax, geo)
    for r in runs:
        if not r.nominal:
            ax.plot(r.trace.xy[:, 0], r.trace.xy[:, 1], color=TRACE_COLOR, lw=0.5, alpha=0.85,
                    ls=(0, (3.0, 1.2)), zorder=3, label="disturbed")
    for r in runs:
        if r.nominal:
            ax.plot(r.trace.xy[:, 0], r.trace.xy[:, 1], color=NOMINAL_COLOR, lw=1.3, zorder=4,
                    label="nominal")
    # End points outside a user-set view sit on its border, so no failure goes unseen.
    lo, hi = np.array([view[0][0], view[1][0]]), np.array([view[0][1], view[1][1]])
    ends = [(np.clip(e, lo, hi), r.success) for r in runs if (e := _end(r.trace.xy)) is not None]
    mark = {"ls": "none", "marker": "o", "clip_on": False}
    ok = np.array([e for e, s in ends])
    if len(ok):
        ax.plot(ok[:, 0], ok[:, 1], ms=2.0, mew=0, color="black", zorder=6, label="end point",
                **mark)
    bad = np.array([e for e, s in ends if not s])
    if len(bad):
        ax.plot(bad[:, 0], bad[:, 1], ms=5.5, mew=1.0, color=FAIL_COLOR, zorder=7,
                label="unstable", **{**mark, "marker": "x"})
    starts = {tuple(np.round(r.trace.xy[0], 9)) for r in runs if np.isfinite(r.trace.xy[0]).all()}
    if starts:
        s = np.array(sorted(starts))
        ax.plot(s[:, 0], s[:, 1], ls="none", marker="s", ms=4.5, mew=0, color=START_COLOR,
                zorder=8, label="start")
    goal = _goal(geo)
    if goal is not None:
        ax.plot([goal[0]], [goal[1]], ls="none", marker="+", ms=7.0, mew=0.8, color="black",
                zorder=9, label="goal")
    n_ok = sum(r.success for r in runs)
    ax.set_title(f"{label}\n{n_ok}/{len(runs)} stable", linespacing=1.1)
    ax.xaxis.set_major_locator(MaxNLocator(3))
    ax.yaxis.set_major_locator(MaxNLocator(4))
    ax.set_xlim(*view[0])
    ax.set_ylim(*view[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(r"$x$ (m)")


def _legend(fig, axes) -> None:
    """One legend for the figure, below the panels, one entry per kind of mark."""
    seen: dict[str, object] = {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(lab, h)
    order = ["guards", "nominal", "disturbed", "start", "end point", "unstable", "goal"]
    labels = [k for k in order if k in seen]
    fig.legend([seen[k] for k in labels], labels, loc="outside lower center",
               ncol=min(4, len(labels)), handlelength=1.8, columnspacing=1.0,
               labelspacing=0.3, handletextpad=0.4)


def _figure(runs: dict[str, list[_Run]], width: float, height: float,
            view: Sequence[float] | None):
    """Builds the matplotlib Figure (no pyplot state); guards from each panel's own logs."""
    from matplotlib.figure import Figure

    geos = {label: _geometry(rs) for label, rs in runs.items()}
    lims = _view(runs, list(geos.values())) if view is None else \
        ((view[0], view[1]), (view[2], view[3]))
    fig = Figure(figsize=(width, height), layout="constrained")
    fig.get_layout_engine().set(w_pad=0.02, h_pad=0.02, wspace=0.02)
    axes = fig.subplots(1, len(runs), sharex=True, sharey=True, squeeze=False)[0]
    for ax, (label, rs) in zip(axes, runs.items(), strict=True):
        _draw_panel(ax, label, rs, geos[label], lims)
    axes[0].set_ylabel(r"$y$ (m)")
    _legend(fig, axes)
    return fig


def _write_counts(path: Path, counts: dict[str, PanelCounts]) -> None:
    """Writes panel, runs, successes, failed (trace labels joined by ';')."""
    write_csv(path, ["panel", "runs", "successes", "failed"],
              ([c.label, c.runs, c.successes, ";".join(c.failed)] for c in counts.values()))


def fig3(table_path: str | Path, out_dir: str | Path | None = None,
         formats: str | Iterable[str] = ("pdf", "svg", "png"), *,
         panel_axis: str = "controller", trace_axis: str = "disturbance",
         nominal: str | None = "nominal", panels: Sequence[str] | None = None,
         width: float = COLUMN_WIDTH_IN, height: float = HEIGHT_IN,
         view: Sequence[float] | None = None, dpi: int = 300) -> dict[str, PanelCounts]:
    """Draws Figure 3 from a sweep table into out_dir/fig3.<fmt> and out_dir/fig3_counts.csv.

    `table_path` may also be a sweep directory holding results.csv; `out_dir` defaults to the
    table's directory; sizes in inches; `view` = (x0, x1, y0, y1) overrides the limits taken
    from the data. Returns the counts per panel label; raises FigureInputError on bad input,
    before anything is written.
    """
    table = resolve_table(table_path)
    check_size(width, height)
    if view is not None:
        try:
            view = tuple(float(v) for v in view)
        except (TypeError, ValueError):
            view = ()
        if len(view) != 4 or not all(map(math.isfinite, view)) or not (
                view[0] < view[1] and view[2] < view[3]):
            raise FigureInputError(f"view must be x0 < x1, y0 < y1 (4 finite numbers), got {view}")
    fmts = parse_formats(formats)
    rows = read_table(table, [panel_axis, trace_axis, "success", "log"])
    traces = sorted({(r.get(trace_axis) or "").strip() for r in rows}, key=_natural)
    if nominal and nominal != "nominal" and nominal not in traces:  # the default may be absent
        raise FigureInputError(f"{table}: --nominal {nominal!r}: no run has it as its "
                               f"{trace_axis} (has: {', '.join(map(repr, traces))})")
    groups = _group(rows, panel_axis, list(panels) if panels is not None else None, table)
    notes: dict[str, list[str]] = {}
    runs = _load_runs(table, groups, trace_axis, nominal or None, notes)
    counts = {label: PanelCounts(label, len(rs), sum(r.success for r in rs),
                                 sorted((r.trace_label for r in rs if not r.success),
                                        key=_natural), notes[label],
                                 not_the_paper(r.trace.scenario for r in rs))
              for label, rs in runs.items()}
    dropped = [n for label, ns in notes.items() if label not in runs for n in ns]
    if dropped:
        next(iter(counts.values())).notes.extend(dropped)
    out = Path(out_dir) if out_dir is not None else table.parent
    make_out_dir(out)
    check_outputs(out, ["fig3_counts.csv", *(f"fig3.{f}" for f in fmts)])
    with figure_style():  # nothing from the user's matplotlibrc leaks in
        save_figure(_figure(runs, width, height, view), out, "fig3", fmts, dpi=dpi)
    _write_counts(out / "fig3_counts.csv", counts)
    return counts
