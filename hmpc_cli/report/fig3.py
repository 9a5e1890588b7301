"""The results page's Figure 3 section: as published (reference mode) and as improved (hmpc).

Each campaign's Figure 3 side by side, with the paper's counts; with the authors' data
(:mod:`hmpc_cli.analysis.authors`) also the authors' own counts, every trial's contacts, circle
entry, end point and success beside theirs, overlays of our paths on theirs, and, where
the outcomes differ, why (:mod:`hmpc_cli.analysis.fig3compare`): all computed from the logs and the
data when the page is written.
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from hmpc_cli.figures.common import page_link
from hmpc_cli.report.fig3_trials import PAPER_COUNTS as PAPER

__all__ = ["PAPER", "Fig3Mode", "fig3_section"]


#: how the reference code's fixed-mode MPC followed its plan in closed loop (read from its
#: published code, BouncingBallNoHybrid.m and BouncingBallMPC.m; a fact about that code,
#: not a result of ours), to read the "off their undisturbed run" lines below against
REFERENCE_RULES = (
    "Reading the lines below: the reference code (its published MATLAB, not computed "
    "here) gives each planned domain ceil(60 x its duration) nodes spread over that "
    "duration, moves floor(60 x elapsed) nodes per period, drops the first domain when "
    "its planned time has passed, and drops it at every floor or wall contact, whichever "
    "guard that domain planned: a contact that comes more than one MPC period late costs "
    "the plan one domain more than the ball used. Whether this rule explains the authors' "
    "failures is run, not assumed: the section on the reference rule emulated "
    "(`mpc.schedule_rule = \"reference\"`) below gives its counts trial by trial, flown "
    "on the reference mode's own plans (not on the authors' six-contact plan).")


@dataclass(frozen=True)
class Fig3Mode:
    """One campaign: name, file stem, sweep directories (main, extra panel), settings text."""

    name: str
    stem: str
    main: Path | None
    extra: Path | None
    settings: str = ""


def _paper(panel: str) -> str:
    from hmpc_cli.analysis.fig3compare import authors_panel

    key = authors_panel(panel, list(PAPER))
    return PAPER[key] if key else "-"


def _count(successes: int, runs: int, failed: Sequence[str]) -> str:
    return f"{successes}/{runs}" + (f" ({', '.join(failed)})" if failed else "")


def _draw(mode: Fig3Mode, fig_dir: Path) -> tuple[dict, list[str]]:
    """Figure 3 of one mode (and its extra panel): counts by panel, notes on the logs."""
    from hmpc_cli.analysis.tables import blamed_on
    from hmpc_cli.figures.fig3 import fig3
    from hmpc_cli.report.traces import keep_traces, sweep_logs

    main_dir = fig_dir / (f"fig3_{mode.stem}" if mode.stem != "hmpc" else "")
    extra_dir = fig_dir / ("fig3_extra" if mode.stem == "hmpc" else f"fig3_{mode.stem}_extra")
    counts = {}
    for directory, out, formats in ((mode.main, main_dir, "pdf,svg,png"),
                                    (mode.extra, extra_dir, "png")):
        if directory is not None:
            with blamed_on(directory):
                keep_traces(sweep_logs(directory))
                counts.update(fig3(directory, out, formats))
    return counts, [n for c in counts.values() for n in c.notes]


def _compared(directory: Path, authors: dict) -> list:
    """One sweep's trials beside the authors' (:func:`compare_sweep`), errors blamed on it."""
    from hmpc_cli.analysis.fig3compare import compare_sweep
    from hmpc_cli.analysis.tables import blamed_on

    with blamed_on(directory):
        return compare_sweep(directory / "results.csv" if directory.is_dir() else directory,
                             authors)


def _image(mode: Fig3Mode, fig_dir: Path, base: Path, extra: bool) -> str:
    sub = ("fig3_extra" if extra else "") if mode.stem == "hmpc" else \
        f"fig3_{mode.stem}{'_extra' if extra else ''}"
    path = fig_dir / sub / "fig3.png"
    return f"![{mode.name}{' extra' if extra else ''}]({page_link(path, base)})"


def _counts_table(modes: Sequence[Fig3Mode], counts: dict, authors: dict) -> list[str]:
    """Panels x (paper, authors' data, each mode)."""
    panels = list(dict.fromkeys(p for m in modes for p in counts[m.name]))
    head = "| controller | paper | authors' data |" + "".join(f" {m.name} |" for m in modes)
    lines = [head, "|" + " --- |" * (3 + len(modes))]
    for p in panels:
        theirs = authors.get(p)
        cells = [_count(c.successes, c.runs, c.failed) if (c := counts[m.name].get(p)) else "-"
                 for m in modes]
        lines.append(f"| {p} | {_paper(p)} | {theirs or '-'} | " + " | ".join(cells) + " |")
    return lines


def _authors_counts(rows: dict) -> dict[str, str]:
    """The authors' counts by our panel label, from their end points (first mode's rows)."""
    out: dict[str, str] = {}
    for mode_rows in rows.values():
        for panel in dict.fromkeys(r.panel for r in mode_rows):
            mine = [r for r in mode_rows if r.panel == panel and r.theirs is not None]
            if panel in out or not mine:
                continue
            failed = [r.trial for r in mine if not r.theirs.success]
            out[panel] = _count(len(mine) - len(failed), len(mine), failed)
    return out


def _fmt_t(t: float | None) -> str:
    return "never" if t is None else f"{t:.2f}"


def _side_cells(side) -> list[str]:
    from hmpc_cli.analysis.fig3compare import sequence_text

    if side is None:
        return ["-"] * 4
    return [sequence_text(side.contacts), _fmt_t(side.entry),
            f"({side.end[0]:.2f}, {side.end[1]:.2f})", "yes" if side.success else "**no**"]


def _trial_table(rows: Sequence) -> list[str]:
    """One row per trial: ours beside theirs, same sequence, end-point gap."""
    lines = ["| controller | trial | hmpc contacts | entry [s] | end [m] | ok | authors' "
             "contacts | entry [s] | end [m] | ok | same contacts | same contacts, ±30 ms "
             "| path deviation max / RMS [m] | end gap [m] |",
             "|" + " --- |" * 14]
    yes = {None: "-", True: "yes", False: "no"}
    for r in rows:
        gap = "-" if r.end_gap is None else f"{r.end_gap:.3f}"
        dev = r.path_deviation
        dev = "-" if dev is None else f"{dev[0]:.2f} / {dev[1]:.2f}"
        cells = [r.panel, r.trial, *_side_cells(r.ours), *_side_cells(r.theirs),
                 yes[r.same_sequence], yes[r.same_timed_sequence], dev, gap]
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _agreement(rows: Sequence) -> list[str]:
    """Per panel: same outcome, same contacts, end gaps where both are stable, entries."""
    lines = ["| controller | same outcome | same contacts | same contacts, ±30 ms | path "
             "deviation, median of max / RMS [m] | end gap, both stable: median / max [m] | "
             "circle entry, median of the runs that entered: hmpc / authors [s] |",
             "|" + " --- |" * 7]
    for panel in dict.fromkeys(r.panel for r in rows):
        rs = [r for r in rows if r.panel == panel and r.ours and r.theirs]
        if not rs:
            continue
        gaps = [r.end_gap for r in rs if r.ours.success and r.theirs.success]
        gap = f"{statistics.median(gaps):.3f} / {max(gaps):.3f}" if gaps else "-"
        ent = [_entry_text([s.entry for s in sides], who) for sides, who in
               (([r.ours for r in rs], "hmpc"), ([r.theirs for r in rs], "authors"))]
        devs = [d for r in rs if (d := r.path_deviation) is not None]
        dev = (f"{statistics.median(d[0] for d in devs):.2f} / "
               f"{statistics.median(d[1] for d in devs):.2f}") if devs else "-"
        lines.append(f"| {panel} | {sum(r.ours.success == r.theirs.success for r in rs)}/"
                     f"{len(rs)} | {sum(bool(r.same_sequence) for r in rs)}/{len(rs)} | "
                     f"{sum(bool(r.same_timed_sequence) for r in rs)}/{len(rs)} | {dev} | "
                     f"{gap} | {ent[0]} / {ent[1]} |")
    return lines


def _entry_text(entries: list[float | None], who: str) -> str:
    """Median circle entry [s] of ``who``'s runs that entered, and how many did if not all."""
    inside = [e for e in entries if e is not None]
    if not inside:
        return "never"
    text = f"{statistics.median(inside):.2f}"
    return text if len(inside) == len(entries) else \
        f"{text} ({who}: {len(inside)} of {len(entries)} entered)"


def _plans(rows: Sequence) -> list[str]:
    """Per panel: our initial plan and the authors' undisturbed run, contact by contact."""
    out = []
    for r in rows:
        if r.trial != "nominal" or r.facts is None:
            continue
        ours = ", ".join(f"{c.guard} {c.t:.2f}" for c in r.facts.plan) or "none"
        theirs = ", ".join(f"{c.guard} {c.t:.2f}" for c in r.their_plan) or "-"
        out.append(f"- {r.panel}: hmpc plans {ours} s; the authors' undisturbed run: "
                   f"{theirs} s.")
    return out


def _floor_finding(rows: Sequence) -> list[str]:
    """Per floor-shift panel: outcome and nodes moved per periodic re-solve (from the logs).

    Beside it the same controller with the exact shift and the authors' failures.
    """
    from collections import Counter

    out = []
    for panel in dict.fromkeys(r.panel for r in rows if r.panel.endswith(", floor shift")):
        floor = [r for r in rows if r.panel == panel and r.ours is not None]
        exact = [r for r in rows if r.panel == panel.removesuffix(", floor shift")
                 and r.ours is not None]
        moves = Counter(s for r in floor for s in r.facts.period_shifts)
        fail = [r.trial for r in floor if not r.ours.success]
        theirs = [r.trial for r in floor if r.theirs is not None and not r.theirs.success]
        text = (f"{panel}: {len(floor) - len(fail)}/{len(floor)} stable (failed: "
                f"{', '.join(fail) or 'none'}); nodes moved per periodic re-solve: "
                + ", ".join(f"{k} in {n}" for k, n in sorted(moves.items())) + ".")
        if exact:
            text += (f" The same controller with the exact shift: "
                     f"{sum(r.ours.success for r in exact)}/{len(exact)} stable.")
        if theirs or any(r.theirs is not None for r in floor):
            both = [t for t in fail if t in theirs]
            text += (f" The authors' failures: {', '.join(theirs) or 'none'}; failing in "
                     f"both: {', '.join(both) or 'none'}.")
        out += ["", text]
    return out


def _compare_mode(mode: Fig3Mode, fig_dir: Path, base: Path, rows: list) -> list[str]:
    """A mode's agreement, plans, differing outcomes, overlays and every trial."""
    from hmpc_cli.figures.fig3overlay import fig3_overlay

    lines = [f"### {mode.name}: trial by trial", "", *_agreement(rows), "",
             "Initial plans (contact, planned time):", "", *_plans(rows)]
    lines += _floor_finding(rows)
    differ = [r for r in rows if r.why]
    lines += ["", f"Outcomes that differ from the authors' ({len(differ)}), and where the runs "
              "part (computed from the logs and the data: differences, not tested causes):",
              ""]
    lines += [f"- **{r.panel}, {r.trial}**: {r.why}." for r in differ] or ["- none"]
    lines += ["", "Our paths (solid) over the authors' (dashed):", ""]
    for panel in dict.fromkeys(r.panel for r in rows):
        stem = f"overlay_{mode.stem}_" + "".join(ch if ch.isalnum() else "_" for ch in panel)
        mine = [r for r in rows if r.panel == panel]
        fig3_overlay(mine, fig_dir / "overlay", stem, "png", title=f"{mode.name}, {panel}")
        link = page_link(fig_dir / "overlay" / f"{stem}.png", base)
        lines.append(f"![{mode.name}, {panel}]({link})")
    return lines + ["", "Every trial (contacts in order, repeats folded; entry: the first time "
                    "|p - (3, 3)| <= 1, ours the logged circle_in event, theirs the first of "
                    "their samples; their contacts found in their sampled positions, "
                    "`hmpc_cli/analysis/authors.py`):", "", *_trial_table(rows), ""]


def _settings_line(modes: Sequence[Fig3Mode]) -> list[str]:
    def sweeps(m: Fig3Mode) -> str:
        names = [f"`{d.name}`" for d in (m.main, m.extra) if d is not None]
        return f" (sweep{'s' if len(names) > 1 else ''} {' and '.join(names)})"

    return [f"- **{m.name}**{sweeps(m)}: {m.settings or 'the defaults'}." for m in modes]


def _verdicts(modes: Sequence[Fig3Mode], counts: dict, authors: dict) -> list[str]:
    """Per panel: the paper's count reproduced by which modes (exactly), or by none.

    A panel the paper has not is judged against the authors' data's count when they have
    it. The count only: which trials fail is the trial-by-trial sections' (the paper names
    none; the authors' data do).
    """
    out = []
    for p in dict.fromkeys(p for m in modes for p in counts[m.name]):
        got = {m.name: f"{c.successes}/{c.runs}" for m in modes
               if (c := counts[m.name].get(p)) is not None}
        paper, theirs = _paper(p), authors.get(p)
        if paper == "-" and not theirs:
            out.append(f"- {p}: not in the paper (" + ", ".join(
                f"{name} {c}" for name, c in got.items()) + ").")
            continue
        # a panel the paper has not: judged against the authors' data's count
        ref = paper if paper != "-" else theirs.split(" ")[0]
        said = (f"the paper: {paper}" if paper != "-" else
                f"not in the paper; the authors' data: {ref}")
        total = int(ref.split("/")[1])  # the reference's runs in that panel
        whole = {m.name: c for m in modes if (c := counts[m.name].get(p)) is not None
                 and c.runs == total}  # a panel with runs missing is not judged
        same = [name for name, c in whole.items() if f"{c.successes}/{c.runs}" == ref]
        verdict = (f"count reproduced by {', '.join(same)}" if same else
                   "**not reproduced** by any mode" if whole else
                   f"not judged: no mode holds its {total} runs yet")
        out.append(f"- {p} ({said}): {verdict} (" + ", ".join(
            f"{name} {c}{_runs_note(int(c.split('/')[1]), total)}"
            for name, c in got.items()) + ").")
    return out


def _runs_note(runs: int, total: int) -> str:
    """``, 6 runs missing`` (or ``, 22 runs against the paper's 11``) unless ``runs`` is it."""
    if runs == total:
        return ""
    return f", {total - runs} runs missing" if runs < total else \
        f", {runs} runs against the paper's {total}"


def fig3_section(modes: Sequence[Fig3Mode], authors_dir: Path | None, fig_dir: Path,
                 base: Path, authors_note: str = "") -> list[str]:
    """The page's Figure 3 lines; figures into ``fig_dir``, links relative to ``base``.

    Raises:
        FigureInputError: a sweep table or the authors' data is unusable.
    """
    from hmpc_cli.analysis.authors import PANEL_FILES, read_panels
    from hmpc_cli.analysis.tables import FigureInputError, blamed_on

    modes = [m for m in modes if m.main is not None or m.extra is not None]
    authors, rows = {}, {}
    if authors_dir is not None:  # read first: a bad directory fails before any drawing
        with blamed_on(authors_dir):
            try:
                authors = read_panels(authors_dir)
            except ValueError as exc:
                raise FigureInputError(str(exc)) from None
            if not authors:
                raise FigureInputError(f"{authors_dir}: none of the authors' Figure 3 files "
                                       f"is there ({', '.join(PANEL_FILES.values())})")
    drawn = {m.name: _draw(m, fig_dir) for m in modes}
    counts = {name: c for name, (c, _) in drawn.items()}
    if authors:
        rows = {m.name: [r for d in (m.main, m.extra) if d is not None
                         for r in _compared(d, authors)] for m in modes}
    lines = ["## Figure 3 as published and as improved", "",
             "The paper's Figure 3 campaign (nominal + the 10 paper disturbances per "
             "controller; success: within 1 m of (3, 3) at t = 3 s), run by hmpc in "
             f"{len(modes)} mode{'s' if len(modes) != 1 else ''}:", "",
             *_settings_line(modes), "",
             "| " + " | ".join(m.name for m in modes) + " |", "|" + " --- |" * len(modes),
             "| " + " | ".join(_image(m, fig_dir, base, m.main is None) for m in modes) + " |",
             "",
             *_counts_table(modes, counts, _authors_counts(rows)), "",
             "The paper's counts, exactly:", "",
             *_verdicts(modes, counts, _authors_counts(rows)), ""]
    extras = [_image(m, fig_dir, base, True) for m in modes
              if m.extra is not None and m.main is not None]  # else drawn above
    if extras:
        lines += ["The 100 Hz panels: " + " ".join(extras), ""]
    notes = [n for _, ns in drawn.values() for n in ns]
    if notes:
        from hmpc_cli.report.paths import portable_text

        lines += ["Logs left out or drawn only in part:", "",
                  *(f"- {portable_text(n)}" for n in notes), ""]
    if authors_note:
        lines += [authors_note, ""]
    if any(rows.values()):
        lines += [REFERENCE_RULES, ""]
    for m in modes:
        if rows.get(m.name):
            lines += _compare_mode(m, fig_dir, base, rows[m.name])
    return lines
