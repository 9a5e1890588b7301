"""``hmpc plot``: the paper's figures from recorded runs (heavy imports inside the command)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from hmpc_cli.cli.common import checked_output, complete_figure, is_quiet
from hmpc_cli.core.paths import path_option

__all__ = ["plot_command"]

EXIT_BAD_INPUT = 2
TEXT_WIDTH_IN = 7.16  # as hmpc_cli.figures.common (not imported: --help stays light)
COLUMN_WIDTH_IN = 3.5


def _wrote(names: list[str], out_dir: Path) -> None:
    """The last line: the files written (with -q: the output directory only)."""
    typer.echo(str(out_dir) if is_quiet() else f"wrote {', '.join(names)} to {out_dir}")


def _partial(log: Path, note: str) -> None:
    """A warning when the figure's log was not read whole (``note``: its damage or cut)."""
    if note:
        typer.echo(f"warning: {log}: the figure shows what the log holds{note}", err=True)


def _fail(message: str) -> None:
    """Prints one error line and exits with the bad-input code."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def _print_counts(counts: dict, reference: dict) -> None:
    """Prints the counts per panel; adds the paper's counts when the labels are the paper's.

    The paper's column only for runs of the paper's system and geometry (the ball with its
    default geometry); else a caption says why it is left out.
    """
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    named = any(label in reference for label in counts)
    why = next((c.not_paper for c in counts.values() if c.not_paper), "")
    with_ref = named and not why
    caption = escape(f"paper column left out: {why}") if named and why else None
    table = Table(title="Figure 3: stable runs per panel", caption=caption)
    for col in ("panel", "runs", "stable", "failed") + (("paper",) if with_ref else ()):
        table.add_column(col, justify="right" if col in ("runs", "stable", "paper") else "left")
    for c in counts.values():
        row = [c.label, str(c.runs), str(c.successes), ", ".join(c.failed) or "-"]
        if with_ref:
            ref = reference.get(c.label)
            row.append(f"{ref[0]}/{ref[1]}" if ref else "-")
        table.add_row(*row)
    Console().print(table)


def _fig3(table: Path, out: Path | None, formats: str, options: dict) -> None:
    """Draws Figure 3, prints the counts and the written files."""
    from hmpc_cli.analysis.tables import FigureInputError, resolve_table
    from hmpc_cli.figures.common import parse_formats
    from hmpc_cli.figures.fig3 import REFERENCE_COUNTS, fig3

    out_dir = out if out is not None else checked_output(resolve_table(table).parent,
                                                         "output directory")
    try:
        counts = fig3(table, out_dir, formats, **options)
    except FigureInputError as exc:
        _fail(str(exc))
    for note in (n for c in counts.values() for n in c.notes):
        typer.echo(f"warning: {note}", err=True)
    _warn_unfinished(table)
    if not is_quiet():
        _print_counts(counts, REFERENCE_COUNTS)
    names = [f"fig3.{f}" for f in parse_formats(formats)] + ["fig3_counts.csv"]
    _wrote(names, out_dir)


def _fig4(log: Path, out: Path | None, formats: str, every: float, gif: bool,
          width: float, height: float) -> None:
    """Draws Figure 4 (and the GIF) from a biped run log."""
    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.figures.common import check_outputs, parse_formats
    from hmpc_cli.figures.fig4 import animate_walk, fig4
    from hmpc_cli.analysis.tables import resolve_run_log

    if not every > 0.0:
        _fail(f"--every: the time between snapshots must be > 0 s (got {every:g})")
    log = resolve_run_log(log)
    out_dir = out if out is not None else checked_output(log.parent, "output directory")
    try:
        check_outputs(out_dir, [*(f"fig4.{f}" for f in parse_formats(formats)),
                                *(["walk.gif"] if gif else [])])  # the GIF comes last
        walk = fig4(log, out_dir, formats, every=every, width=width, height=height)
        if gif:
            animate_walk(walk, out_dir / "walk.gif")
    except FigureInputError as exc:
        _fail(str(exc))
    _partial(log, walk.log_note)
    names = [f"fig4.{f}" for f in parse_formats(formats)] + (["walk.gif"] if gif else [])
    if is_quiet():
        return _wrote(names, out_dir)
    for t, guard, fx, fy in walk.contacts:
        typer.echo(f"contact t = {t:.3f} s  {guard:<8} foot ({fx:.3f}, {fy:.3f}) m")
    verdict = {True: "success", False: "failed", None: "unfinished"}[walk.success]
    why = f" ({walk.reason})" if walk.reason not in ("", verdict) else ""
    typer.echo(f"{verdict}{why}; hip ends at ({walk.hip[-1, 0]:.3f}, "
               f"{walk.hip[-1, 1]:.3f}) m")
    _wrote(names, out_dir)


def _timing(log: Path, out: Path | None, formats: str, width: float, height: float) -> None:
    """The run's solve times against its MPC period; prints the counts of its title."""
    from hmpc_cli.analysis.tables import FigureInputError, resolve_run_log
    from hmpc_cli.figures.common import check_size, parse_formats
    from hmpc_cli.figures.timing import count_text, solve_times, timing

    try:
        check_size(width, height)
        names = [f"timing.{f}" for f in parse_formats(formats)]
        log = resolve_run_log(log)
        st = solve_times(log)
        out_dir = out if out is not None else checked_output(log.parent, "output directory")
        timing(st, out_dir, formats, width=width, height=height)
    except FigureInputError as exc:
        _fail(str(exc))
    _partial(log, st.log_note)
    if not is_quiet():
        typer.echo(count_text(st))
    _wrote(names, out_dir)


def _fig2(log: Path, out: Path | None, formats: str, options: dict) -> None:
    """Figure 2 from a run log: the pass-through computed, drawn; prints its checks."""
    from hmpc_cli.analysis.tables import FigureInputError, resolve_run_log
    from hmpc_cli.figures.common import parse_formats
    from hmpc_cli.figures.fig2 import check_request, fig2
    from hmpc_cli.analysis.passthrough import PassThroughError, pass_through_geometry

    size = {k: options.pop(k) for k in ("width", "height", "dpi") if k in options}
    try:
        check_request(formats, size["width"], size["height"])
        out_dir = out if out is not None else checked_output(resolve_run_log(log).parent,
                                                             "output directory")
        geo = pass_through_geometry(log, **options)
        fig2(geo, out_dir, formats, **size)
    except (FigureInputError, PassThroughError) as exc:
        _fail(str(exc))
    _partial(geo.log, geo.log_note)
    names = [f"fig2.{f}" for f in parse_formats(formats)]
    if is_quiet():
        return _wrote(names, out_dir)
    typer.echo(f"solve {geo.solve} at t = {geo.t:.3f} s crosses guard {geo.guard_name} "
               f"({geo.source_mode} -> {geo.target_mode}); tube radius d = {geo.radius:.4g} "
               f"({geo.radius_source}); solve slack {geo.slack:.2g}")
    typer.echo(f"guard node gap {geo.guard_node_gap:.3g}; virtual node gap "
               f"{geo.virtual_gap:.4g}; disc's nearest point gap {geo.disc_gap:.4g}: "
               + ("past the guard" if geo.disc_past else "NOT entirely past the guard"))
    typer.echo(f"NLP row q(x_v) <= -kappa(d): {geo.virtual_q:.4g} vs {-geo.kappa:.4g}: "
               + ("holds" if geo.nlp_row >= -1e-6 else "violated")
               + f"; |post-reset - R(guard node)| = "
               f"{float(abs(geo.post_reset - geo.reset_of_guard_node).max()):.2g}")
    _wrote(names, out_dir)


def _robustness(table: Path, out: Path | None, formats: str, options: dict) -> None:
    """Draws the robustness curves, prints the cell table and the written files."""
    from rich.console import Console
    from rich.table import Table

    from hmpc_cli.analysis.tables import FigureInputError, resolve_table
    from hmpc_cli.figures.common import parse_formats
    from hmpc_cli.figures.robustness import default_axes, robustness

    out_dir = out if out is not None else checked_output(resolve_table(table).parent,
                                                         "output directory")
    try:
        axes = default_axes(table, options["panel_axis"], options["x_axis"],
                            options["series_axis"])
        options = {**options, **dict(zip(("panel_axis", "x_axis", "series_axis"), axes,
                                         strict=True))}
        data = robustness(table, out_dir, formats, **options)
    except FigureInputError as exc:
        _fail(str(exc))
    _warn_unfinished(table)
    names = [f"robustness.{f}" for f in parse_formats(formats)] + ["robustness_table.csv"]
    if is_quiet():
        return _wrote(names, out_dir)
    t = Table(title="success rate per cell (Wilson 95 % interval)")
    for col in (options["panel_axis"] or "panel", options["series_axis"], options["x_axis"],
                "runs",
                "success", "95 % interval"):
        t.add_column(col, justify="right")
    for c in data:
        lo, hi = c.interval
        t.add_row(c.panel, c.series, f"{c.x:g}", str(c.runs),
                  f"{100 * c.rate:.0f} %", f"{100 * lo:.0f}-{100 * hi:.0f} %")
    Console().print(t)
    _wrote(names, out_dir)


def _warn_unfinished(table: Path) -> None:
    """Warns when the table holds fewer runs than its sweep (its ``sweep.toml``) plans."""
    from hmpc_cli.analysis.tables import read_table, resolve_table
    from hmpc_cli.sweep.plan import planned_runs

    path = resolve_table(table)
    stored = path.parent / "sweep.toml"
    planned = planned_runs(stored) if stored.is_file() else None
    held = len({row.get("run_id") for row in read_table(path, ["success"])})
    if planned is not None and held < planned:
        typer.echo(f"warning: {path} holds {held} of the {planned} runs its sweep plans "
                   f"({stored}): the figure shows those; `hmpc sweep` on the sweep "
                   "file resumes the rest", err=True)


def plot_command(
    figure: Annotated[str, typer.Argument(
        metavar="FIGURE", help="figure to draw: fig2, fig3, robustness, fig4 or timing",
        autocompletion=complete_figure)],
    table: Annotated[Path, typer.Argument(
        metavar="TABLE|RUN", help="fig3, robustness: sweep table (results.csv, or the sweep "
        "directory holding it); fig2, timing: a run log, fig4: a biped run log (run.mcap, or "
        "the run directory holding it)")],
    out: Annotated[Path | None, typer.Option(
        "--out", metavar="DIR", help="output directory (default: the table's directory)",
        parser=path_option)] = None,
    formats: Annotated[str, typer.Option(
        "--formats", help="comma-separated output formats: pdf,svg,png")] = "pdf,svg,png",
    panel_axis: Annotated[str | None, typer.Option(
        "--panel-axis", help="table column with one panel per value (fig3: controller, "
        "robustness: disturbance.magnitude, else set.disturbance.magnitude, else one "
        "panel)")] = None,
    x_axis: Annotated[str | None, typer.Option(
        "--x-axis", help="robustness: numeric column on the x axis (mpc.rate_hz, else "
        "set.mpc.rate_hz)")] = None,
    series_axis: Annotated[str | None, typer.Option(
        "--series-axis", help="robustness: column with one line per value "
        "(replanning.policy, else set.replanning.policy)")] = None,
    trace_axis: Annotated[str, typer.Option(
        "--trace-axis", help="fig3: column naming a panel's trajectories")] = "disturbance",
    nominal: Annotated[str, typer.Option(
        "--nominal", help="fig3: trace-axis value of the undisturbed run")] = "nominal",
    panels: Annotated[str | None, typer.Option(
        "--panels", help='fig3: panels in order (all), e.g. "10 Hz fixed,20 Hz fixed"')] = None,
    width: Annotated[float | None, typer.Option(
        "--width", help="figure width (in; fig3, fig4 3.5 = one column; fig2, robustness, "
        "timing 7.16 = text width)")] = None,
    height: Annotated[float | None, typer.Option(
        "--height", help="figure height (in; fig3 2.1, fig4 4.2, fig2 2.8, robustness 1.9, "
        "timing 2.4)")] = None,
    view: Annotated[str | None, typer.Option(
        "--view", help='fig3: axis limits "x0,x1,y0,y1" in m (default: the data)')] = None,
    every: Annotated[float, typer.Option(
        "--every", help="fig4: time between stick-figure snapshots (s)")] = 0.1,
    gif: Annotated[bool, typer.Option(
        "--gif/--no-gif", help="fig4: also write the animation walk.gif")] = True,
    solve: Annotated[int | None, typer.Option(
        "--solve", help="fig2: draw the K-th logged MPC solve (from 1; default: the "
        "first whose plan crosses a guard)")] = None,
    radius: Annotated[float | None, typer.Option(
        "--radius", help="fig2: tube radius d (default: the one the run's NLP used, "
        "mpc.tube_margin or the guard's in its mpc.margins)")] = None,
    from_tube: Annotated[bool, typer.Option(
        "--from-tube", help="fig2: d = the guard's tube radius at the run's MPC rate, "
        "as its margins use it (hmpc tube: the kinematic tube for a guard of positions, "
        "else diam T(dt))")
    ] = False,
) -> None:
    """Draw a paper figure from recorded runs (a sweep table and the logs it points to)."""
    if out is not None:  # before any input is read: a bad path writes nothing
        checked_output(out, "--out")
    _draw(figure, table, out, formats, dict(
        panel_axis=panel_axis, x_axis=x_axis, series_axis=series_axis, trace_axis=trace_axis,
        nominal=nominal, panels=panels, width=width, height=height, view=view, every=every,
        gif=gif, solve=solve, radius=radius, from_tube=from_tube))


def _draw(figure: str, table: Path, out: Path | None, formats: str, o: dict) -> None:
    """Dispatches ``hmpc plot FIGURE``; a damaged or foreign log is reported as such."""
    from hmpc_cli.log.damage import DamagedLogError, reading

    try:
        with reading(table):
            _dispatch(figure, table, out, formats, o)
    except DamagedLogError as exc:
        _fail(str(exc))


def _dispatch(figure: str, table: Path, out: Path | None, formats: str, o: dict) -> None:
    """Dispatches ``hmpc plot FIGURE`` with the command's options ``o`` (by name)."""
    from hmpc_cli.figures import FIGURES

    if figure not in FIGURES:
        _fail(f"unknown figure {figure!r} (choose from {', '.join(FIGURES)})")
    _refuse_other_figures_options(figure, o)
    height = o["height"]
    # fig3 and fig4 fit one IEEE column; fig2 and the robustness curves span the text width
    width = o["width"] if o["width"] is not None else \
        COLUMN_WIDTH_IN if figure in ("fig3", "fig4") else TEXT_WIDTH_IN
    if figure == "fig2":
        return _fig2(table, out, formats, {"solve": o["solve"], "radius": o["radius"],
                                           "width": width, "from_tube": o["from_tube"],
                                           "height": height or 2.8})
    if figure == "fig4":
        return _fig4(table, out, formats, o["every"], o["gif"], width, height or 4.2)
    if figure == "timing":
        return _timing(table, out, formats, width, height or 2.4)
    if figure == "robustness":
        return _robustness(table, out, formats, {
            "x_axis": o["x_axis"], "series_axis": o["series_axis"], "width": width,
            "panel_axis": o["panel_axis"],
            "height": height or 1.9})
    return _fig3(table, out, formats, {
        "panel_axis": o["panel_axis"] or "controller", "trace_axis": o["trace_axis"],
        "nominal": o["nominal"], "panels": _panels(o["panels"]), "width": width,
        "height": height or 2.1, "view": _limits(o["view"])})


#: the options only some figures read: option -> (its flag, those figures)
FIGURE_OPTIONS = {
    "panel_axis": ("--panel-axis", ("fig3", "robustness")),
    "x_axis": ("--x-axis", ("robustness",)), "series_axis": ("--series-axis", ("robustness",)),
    "trace_axis": ("--trace-axis", ("fig3",)), "nominal": ("--nominal", ("fig3",)),
    "panels": ("--panels", ("fig3",)), "view": ("--view", ("fig3",)),
    "every": ("--every", ("fig4",)), "gif": ("--no-gif", ("fig4",)),
    "solve": ("--solve", ("fig2",)), "radius": ("--radius", ("fig2",)),
    "from_tube": ("--from-tube", ("fig2",))}


def _refuse_other_figures_options(figure: str, o: dict) -> None:
    """Exits 2 when an option another figure reads is given (it would be ignored)."""
    import inspect

    defaults = {name: p.default for name, p in inspect.signature(plot_command).parameters.items()}
    for key, (flag, figures) in FIGURE_OPTIONS.items():
        if figure not in figures and o[key] != defaults[key]:
            _fail(f"{flag} is {' and '.join(figures)}'s option, not {figure}'s (it would "
                  "be ignored): leave it out")


def _panels(panels: str | None) -> list[str] | None:
    """The --panels list (None: all); an empty list is bad input (exit 2)."""
    chosen = [p.strip() for p in panels.split(",") if p.strip()] if panels is not None else None
    if chosen == []:
        _fail("--panels is empty")
    return chosen


def _limits(view: str | None) -> list[float] | None:
    """The --view limits as numbers (None: from the data); bad input exits 2."""
    if view is None:
        return None
    try:
        limits = [float(v) for v in view.split(",")]
    except ValueError:
        limits = []
    if len(limits) != 4 or not all(map(math.isfinite, limits)) or not (
            limits[0] < limits[1] and limits[2] < limits[3]):
        _fail(f"--view must be four finite numbers x0,x1,y0,y1 with x0 < x1 and y0 < y1, "
              f"got {view!r}")
    return limits
