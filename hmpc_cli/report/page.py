"""The results page: Figure 3 with its counts beside the paper's, and the robustness study.

Reads finished sweeps only (their results.csv and logs), draws the figures into
``<results>/report/`` and writes ``<results>/README.md``. Running the sweeps is the
caller's job (``hmpc report`` does it first, resumably).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from hmpc_cli.analysis.tables import FigureInputError, resolve_table
from hmpc_cli.figures.common import page_link
from hmpc_cli.report.paths import portable_command, portable_text

__all__ = ["ReportInputs", "write_report"]

@dataclass(frozen=True)
class ReportInputs:
    """Sweep directories feeding the page (None: that section is left out).

    ``fig3``/``fig3_extra``: hmpc mode's Figure 3 (main panels, 100 Hz panel);
    ``fig3_reference``/``fig3_reference_extra``: the same in reference mode;
    ``fig3_schedule``: the authors' own plan flown by hmpc's MPC; ``authors``:
    the directory of the authors' Figure 3 CSVs (None: no comparison; ``authors_note``
    says why on the page).
    """

    fig3: Path | None
    fig3_extra: Path | None
    robustness: Path | tuple | None  # a sweep directory, or Study records (report_robustness)
    biped: Path | None = None  # a biped run directory (Figure 4)
    fig3_reference: Path | None = None
    fig3_reference_extra: Path | None = None
    authors: Path | None = None
    authors_note: str = ""
    fig3_schedule: Path | None = None  # the authors' plan flown (schedule planner)
    biped_push: Path | None = None  # the biped's push sweep (sweeps/biped_push.toml)
    fig3_trials: Path | None = None  # a Figure 3 sweep tabled trial by trial (table only)
    realtime: tuple[Path, ...] | None = None  # real-time sweeps (sweeps/realtime_*.toml)


def _settings(*dirs: Path | None) -> str:
    """What the sweeps set beyond their scenario (their ``[set]``), as text."""
    from hmpc_cli.report.robustness import fixed_settings

    parts = []
    for d in dirs:
        if d is not None:
            fixed = fixed_settings(resolve_table(d).parent)
            if fixed != "-" and fixed not in parts:
                parts.append(fixed)
    return ", ".join(parts)


def _fig3_section(inputs: ReportInputs, fig_dir: Path, base: Path) -> list[str]:
    from hmpc_cli.report.fig3 import Fig3Mode, fig3_section

    ref = _settings(inputs.fig3_reference, inputs.fig3_reference_extra)
    own = _settings(inputs.fig3, inputs.fig3_extra)
    modes = [Fig3Mode("reference mode", "reference", inputs.fig3_reference,
                      inputs.fig3_reference_extra,
                      f"the reference code's choices: {ref}" if ref else "the reference's"),
             Fig3Mode("hmpc mode", "hmpc", inputs.fig3, inputs.fig3_extra,
                      f"hmpc's own choices{': ' + own if own else ' (its defaults)'}"),
             Fig3Mode("authors' plan flown", "schedule", inputs.fig3_schedule, None,
                      "the authors' six-contact initial plan given to hmpc's MPC (planner "
                      "`schedule`, scenarios/ball_reference_schedule.toml), "
                      + (_settings(inputs.fig3_schedule) or "hmpc's MPC"))]
    return fig3_section(modes, inputs.authors, fig_dir, base, inputs.authors_note)


def _robustness_section(inputs: ReportInputs, fig_dir: Path, base: Path) -> list[str]:
    from hmpc_cli.report.robustness import Study, robustness_sections

    given = inputs.robustness
    studies = [s if isinstance(s, Study) else Study(Path(s))
               for s in ((given,) if isinstance(given, (str, Path)) else given)]
    return robustness_sections(studies, fig_dir, base)


def _biped_section(inputs: ReportInputs, fig_dir: Path, base: Path) -> list[str]:
    from hmpc_cli.analysis.tables import resolve_run_log
    from hmpc_cli.figures.fig4 import animate_walk, fig4
    from hmpc_cli.log.rundata import read_run
    from hmpc_cli.report.traces import keep_traces

    keep_traces([Path(inputs.biped)])
    log = resolve_run_log(Path(inputs.biped))
    walk = fig4(log, fig_dir, "pdf,png")
    animate_walk(walk, fig_dir / "walk.gif")
    try:
        run = read_run(log, with_plans=False)
    except ValueError as exc:
        raise FigureInputError(str(exc)) from None
    sc, summary = run.scenario, run.summary
    d = sc.get("disturbance", {})
    setup = (f"Run: scenario `{sc.get('name', '?')}`, seed {sc.get('seed', '?')}; "
             f"plant vs model: {sc.get('plant') or 'identical'}; torso force: "
             + (f"{d.get('kind')} ±{d.get('magnitude')} N held {d.get('hold')} s"
                if d.get("kind", "none") != "none" else "none"))
    verdict = {True: "success", False: "failed", None: "unfinished"}[walk.success]
    lines = ["## Figure 4: the five-link biped on the stairs", "",
             f"![Figure 4]({page_link(fig_dir / 'fig4.png', base)})", "",
             f"Animation: [{page_link(fig_dir / 'walk.gif', base)}]"
             f"({page_link(fig_dir / 'walk.gif', base)}). {setup}; outcome: {verdict}"
             f"{f' ({walk.reason})' if walk.reason not in ('', verdict) else ''}; hip ends at "
             f"({walk.hip[-1, 0]:.3f}, {walk.hip[-1, 1]:.3f}) m.", "",
             "| contact | t [s] | segment | foot x [m] |", "| --- | --- | --- | --- |"]
    for k, (t, guard, fx, _) in enumerate(walk.contacts, start=1):
        lines.append(f"| {k} | {t:.3f} | {guard} | {fx:.3f} |")
    if summary is not None:
        lines += ["", f"MPC re-solves: {summary.solves} (median "
                  f"{1e3 * (summary.solve_time_median or 0):.0f} ms), solver failures "
                  f"{summary.solver_failures}; foothold planning steps: "
                  f"{summary.planner_calls} (median "
                  f"{1e3 * (summary.plan_time_median or 0):.0f} ms). Reference run: "
                  "touchdowns at x = 0.789, 1.214 (1.0 m segment), 1.720 (top segment)."]
    return lines + [""]


def _or_not_drawn(title: str, directory: Path, section, level: str = "##") -> list[str]:
    """A table-only section, or its title and why it is not drawn (no table yet)."""
    try:
        return section()
    except FigureInputError as exc:
        if _no_table(directory):
            return [f"{level} {title}", "", f"Not drawn: {portable_text(str(exc))}", ""]
        raise


def _no_table(directory: Path) -> bool:
    """Whether a sweep directory has no results.csv yet (not run: not an error)."""
    return not (Path(directory) / "results.csv").is_file()


def write_report(results: Path, inputs: ReportInputs, command: str) -> Path:
    """Draws the figures into ``results/report`` and writes ``results/README.md``.

    Raises:
        FigureInputError: a sweep table or log is missing or malformed.
    """
    results = Path(results)
    fig_dir = results / "report"
    fig_dir.mkdir(parents=True, exist_ok=True)
    lines = ["# hmpc results", "",
             f"Generated by `{portable_command(command)}` from recorded runs: the sweeps' "
             "per-run tables (each section names its sweep; the repository's are "
             "`sweeps/<name>/results.csv` beside this page) and, for the "
             "figures that draw trajectories, the logs of the runs they show (a run's "
             "`run.mcap`, or where it is not there the trajectory log `trace.mcap` the report "
             "keeps beside it); regenerate with the same command.", ""]
    if any(d is not None for d in (inputs.fig3, inputs.fig3_reference, inputs.fig3_schedule)):
        lines += _fig3_section(inputs, fig_dir, results)
    if inputs.fig3_trials is not None:
        from hmpc_cli.report.fig3_trials import fig3_trials_section

        lines += _or_not_drawn("Figure 3 trial by trial", inputs.fig3_trials,
                               lambda: fig3_trials_section(inputs.fig3_trials))
    if inputs.realtime:
        from hmpc_cli.report.realtime import HEADING, realtime_section

        lines += [HEADING, ""]
        for d in inputs.realtime:
            lines += _or_not_drawn(f"`{Path(d).name}`", d, lambda d=d: realtime_section(d),
                                   level="###")
    if inputs.robustness is not None:
        lines += _robustness_section(inputs, fig_dir, results)
    if inputs.biped is not None:
        lines += _biped_section(inputs, fig_dir, results)
    if inputs.biped_push is not None:
        from hmpc_cli.report.push import push_section

        lines += _or_not_drawn("The biped under pushes that matter", inputs.biped_push,
                               lambda: push_section(inputs.biped_push, fig_dir, results))
    if inputs.fig3 is None and inputs.fig3_reference is None and inputs.robustness is None \
            and inputs.biped is None and inputs.biped_push is None \
            and inputs.fig3_trials is None and not inputs.realtime:
        raise FigureInputError("nothing to report: no Figure 3, robustness sweep or biped run")
    lines += ["## Layout", "",
              "* `<scenario>/<UTC time>-seed<N>/`: one `hmpc run` (`run.mcap`, `summary.json`, "
              "`scenario.toml`).",
              "* `sweeps/<name>/`: one `hmpc sweep` (`runs/<run id>/`, `results.csv`); "
              "`runs/<run id>/trace.mcap`: the trajectory log of a run this page draws.",
              "* `report/`: the figures and tables of this page.",
              *(["* `authors/`: the authors' Figure 3 data (their published trajectories)."]
                if (results / "authors").is_dir() else []), "",
              "Open an MCAP log in Foxglove or Lichtblick, or read it in Python with "
              "`hmpc_cli.log.rundata.read_run(path)` (arrays per topic).", ""]
    page = results / "README.md"
    from hmpc_cli.core.paths import write_atomic

    # no machine's absolute path on the committed page (repository-relative or <...>/)
    write_atomic(page, portable_text("\n".join(lines)))
    return page
