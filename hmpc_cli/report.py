"""The results page: Figure 3 with its counts beside the paper's, and the robustness study.

Reads finished sweeps only (their results.csv and logs), draws the figures into
``<results>/report/`` and writes ``<results>/README.md``. Running the sweeps is the
caller's job (``hmpc report`` does it first, resumably).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from hmpc_cli.figures.common import FigureInputError, read_table, resolve_table

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
    robustness: Path | None
    biped: Path | None = None  # a biped run directory (Figure 4)
    fig3_reference: Path | None = None
    fig3_reference_extra: Path | None = None
    authors: Path | None = None
    authors_note: str = ""
    fig3_schedule: Path | None = None  # the authors' plan flown (schedule planner)


def _rel(path: Path, base: Path) -> str:
    try:
        return path.resolve().relative_to(base.resolve()).as_posix()
    except ValueError:
        return path.resolve().as_posix()


def _settings(*dirs: Path | None) -> str:
    """What the sweeps set beyond their scenario (their ``[set]``), as text."""
    parts = []
    for d in dirs:
        if d is not None:
            table = resolve_table(d)
            fixed, _ = _sweep_spec(table.parent / "sweep.toml")
            if fixed != "-" and fixed not in parts:
                parts.append(fixed)
    return ", ".join(parts)


def _fig3_section(inputs: ReportInputs, fig_dir: Path, base: Path) -> list[str]:
    from hmpc_cli.report_fig3 import Fig3Mode, fig3_section

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


def _pivot(cells) -> list[str]:
    xs = sorted({c.x for c in cells})
    head = "| disturbance | policy | " + " | ".join(f"{x:g} Hz" for x in xs) + " |"
    lines = [head, "| --- | --- | " + " | ".join("---" for _ in xs) + " |"]
    rows: dict[tuple[str, str], dict[float, object]] = {}
    for c in cells:
        rows.setdefault((c.panel, c.series), {})[c.x] = c
    for (panel, series), by_x in rows.items():
        parts = []
        for x in xs:
            c = by_x.get(x)
            if c is None:
                parts.append("-")
                continue
            lo, hi = c.interval
            parts.append(f"{c.successes}/{c.runs} ({100 * lo:.0f}-{100 * hi:.0f} %)")
        lines.append(f"| ±{panel} | {series} | " + " | ".join(parts) + " |")
    return lines


def _findings(cells) -> list[str]:
    """Plain statements computed from the cells (interval overlap = not resolved)."""
    out = []
    panels = list(dict.fromkeys(c.panel for c in cells))
    series = list(dict.fromkeys(c.series for c in cells))
    for p in panels:
        for s in series:
            sel = sorted((c for c in cells if c.panel == p and c.series == s), key=lambda c: c.x)
            if len(sel) < 2:
                continue
            lo, hi = sel[0], sel[-1]
            sep = lo.interval[1] < hi.interval[0] or hi.interval[1] < lo.interval[0]
            verdict = ("higher than" if hi.rate > lo.rate else "lower than"
                       if hi.rate < lo.rate else "the same as")
            out.append(f"- ±{p}, {s}: {hi.x:g} Hz is {verdict} {lo.x:g} Hz "
                       f"({100 * hi.rate:.0f} % vs {100 * lo.rate:.0f} %; "
                       f"{'intervals separate' if sep else 'intervals overlap'}).")
        if len(series) == 2:
            a, b = series
            diffs = []
            for x in sorted({c.x for c in cells if c.panel == p}):
                ca = [c for c in cells if c.panel == p and c.series == a and c.x == x]
                cb = [c for c in cells if c.panel == p and c.series == b and c.x == x]
                if ca and cb:
                    diffs.append(cb[0].rate - ca[0].rate)
            if diffs:
                mean = sum(diffs) / len(diffs)
                out.append(f"- ±{p}: {b} minus {a}, mean over rates: "
                           f"{100 * mean:+.0f} percentage points.")
    return out


def _sweep_spec(path: Path) -> tuple[str, int | None]:
    """The sweep file's ``[set]`` overrides as text ("-" if none) and its seed count."""
    import tomllib

    try:
        spec = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return "-", None
    seeds = spec.get("seeds")
    count = seeds if isinstance(seeds, int) else len(seeds) if isinstance(seeds, list) else None
    return ", ".join(f"`{k} = {v}`" for k, v in spec.get("set", {}).items()) or "-", count


def _robustness_section(inputs: ReportInputs, fig_dir: Path, base: Path) -> list[str]:
    from hmpc_cli.figures.robustness import robustness

    table = resolve_table(inputs.robustness)
    rows = read_table(table, ["seed"])
    cells = robustness(table, fig_dir, "pdf,svg,png")
    seeds = len({r["seed"] for r in rows})
    n = sorted({c.runs for c in cells})
    fixed, planned = _sweep_spec(table.parent / "sweep.toml")
    partial = (f" (a prefix: {seeds} of the sweep's {planned} seeds; `hmpc report` runs "
               "the rest, resuming)" if planned and seeds < planned else "")
    lines = ["## Robustness study: success rate vs MPC rate", "",
             f"![robustness]({_rel(fig_dir / 'robustness.png', base)})", "",
             f"{len(rows)} finished runs, {seeds} seeds{partial}, {n[0]}"
             f"{'' if len(n) == 1 else f'-{n[-1]}'} runs per cell; settings of every run: "
             f"{fixed}; Wilson 95 % intervals. Table: "
             f"[{_rel(fig_dir / 'robustness_table.csv', base)}]"
             f"({_rel(fig_dir / 'robustness_table.csv', base)}).", "", *_pivot(cells), "",
             "Computed findings (a claim holds only where the intervals separate):", "",
             *_findings(cells), ""]
    return lines


def _biped_section(inputs: ReportInputs, fig_dir: Path, base: Path) -> list[str]:
    import json

    from hmpc_cli.figures.fig4 import animate_walk, fig4

    run = Path(inputs.biped)
    walk = fig4(run, fig_dir, "pdf,png")
    animate_walk(walk, fig_dir / "walk.gif")
    import tomllib

    summary = json.loads((run / "summary.json").read_text()) if (
        run / "summary.json").is_file() else {}
    sc = tomllib.loads((run / "scenario.toml").read_text()) if (
        run / "scenario.toml").is_file() else {}
    d = sc.get("disturbance", {})
    setup = (f"plant vs model: {sc.get('plant') or 'identical'}; torso force: "
             + (f"{d.get('kind')} ±{d.get('magnitude')} N held {d.get('hold')} s"
                if d.get("kind", "none") != "none" else "none"))
    verdict = {True: "success", False: "failed", None: "unfinished"}[walk.success]
    lines = ["## Figure 4: the five-link biped on the stairs", "",
             f"![Figure 4]({_rel(fig_dir / 'fig4.png', base)})", "",
             f"Animation: [{_rel(fig_dir / 'walk.gif', base)}]"
             f"({_rel(fig_dir / 'walk.gif', base)}). {setup}; outcome: {verdict}"
             f"{f' ({walk.reason})' if walk.reason not in ('', verdict) else ''}; hip ends at "
             f"({walk.hip[-1, 0]:.3f}, {walk.hip[-1, 1]:.3f}) m.", "",
             "| contact | t [s] | segment | foot x [m] |", "| --- | --- | --- | --- |"]
    for k, (t, guard, fx, _) in enumerate(walk.contacts, start=1):
        lines.append(f"| {k} | {t:.3f} | {guard} | {fx:.3f} |")
    if summary:
        lines += ["", f"MPC re-solves: {summary.get('solves')} (median "
                  f"{1e3 * (summary.get('solve_time_median') or 0):.0f} ms), solver failures "
                  f"{summary.get('solver_failures')}; foothold planning steps: "
                  f"{summary.get('planner_calls')} (median "
                  f"{1e3 * (summary.get('plan_time_median') or 0):.0f} ms). Reference run: "
                  "touchdowns at x = 0.789, 1.214 (1.0 m segment), 1.720 (top segment)."]
    return lines + [""]


def write_report(results: Path, inputs: ReportInputs, command: str) -> Path:
    """Draws the figures into ``results/report`` and writes ``results/README.md``.

    Raises:
        FigureInputError: a sweep table or log is missing or malformed.
    """
    results = Path(results)
    fig_dir = results / "report"
    fig_dir.mkdir(parents=True, exist_ok=True)
    lines = ["# hmpc results", "",
             f"Generated by `{command}` from recorded runs (the sweeps' results.csv and MCAP "
             "logs); regenerate with the same command. Run outputs live beside this page and "
             "are not tracked by git, apart from this page and `report/`.", ""]
    if any(d is not None for d in (inputs.fig3, inputs.fig3_reference, inputs.fig3_schedule)):
        lines += _fig3_section(inputs, fig_dir, results)
    if inputs.robustness is not None:
        lines += _robustness_section(inputs, fig_dir, results)
    if inputs.biped is not None:
        lines += _biped_section(inputs, fig_dir, results)
    if inputs.fig3 is None and inputs.fig3_reference is None and inputs.robustness is None \
            and inputs.biped is None:
        raise FigureInputError("nothing to report: no Figure 3, robustness sweep or biped run")
    lines += ["## Layout", "",
              "* `<scenario>/<UTC time>-seed<N>/`: one `hmpc run` (`run.mcap`, `summary.json`, "
              "`scenario.toml`).",
              "* `sweeps/<name>/`: one `hmpc sweep` (`runs/<run id>/`, `results.csv`).",
              "* `report/`: the figures and tables of this page.", "",
              "Open an MCAP log in Foxglove or Lichtblick, or read it in Python with "
              "`hmpc_cli.rundata.read_run(path)` (arrays per topic).", ""]
    page = results / "README.md"
    tmp = page.with_name(".README.md.tmp")
    tmp.write_text("\n".join(lines), encoding="utf-8")
    tmp.replace(page)
    return page
