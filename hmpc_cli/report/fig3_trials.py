"""Figure 3 trial by trial from a sweep table alone: which of the authors' failures appear.

For a Figure 3 sweep (grid axes ``controller`` and ``disturbance``, e.g.
``sweeps/fig3_reference_rule.toml``) the section lists, per controller, hmpc's count
beside the paper's and the authors' (their data: :data:`AUTHORS_FAILED`), the trials that
failed on each side, and per authors' failure whether hmpc's run failed too. It reads the
table only (no log), so a committed table regenerates it.
"""

from __future__ import annotations

from pathlib import Path

from hmpc_cli.analysis.tables import FigureInputError, parse_bool, read_table, resolve_table
from hmpc_cli.analysis.tables import sweep_spec
from hmpc_cli.report.paths import repository_file
from hmpc_cli.report.robustness import settings_text, wall_text

__all__ = ["AUTHORS_FAILED", "PAPER_COUNTS", "fig3_trials_section"]

#: the trials that ended outside the circle in the authors' own Figure 3 data (their
#: reference CSVs: end more than the circle's radius from its centre at t = 3 s; checked
#: against the CSVs by tests/test_report.py where they are present)
AUTHORS_FAILED: dict[str, tuple[str, ...]] = {
    "10 Hz fixed": ("trial 5", "trial 7"), "20 Hz fixed": (), "10 Hz replan": (),
    "100 Hz fixed": ("trial 3", "trial 4", "trial 5", "trial 6", "trial 7", "trial 9",
                     "trial 10")}
#: how many runs each of the authors' Figure 3 panels has (nominal + 10 disturbances)
AUTHORS_TRIALS = 11
#: the paper's Figure 3 counts (stable / runs), its three panels; the reference code's
#: 100 Hz panel is not in the paper (its count: the authors' data, :data:`AUTHORS_FAILED`)
PAPER_COUNTS: dict[str, str] = {"10 Hz fixed": "9/11", "20 Hz fixed": "11/11",
                                "10 Hz replan": "11/11"}


def _names(trials: list[str]) -> str:
    return ", ".join(trials) if trials else "none"


def fig3_trials_section(directory: Path) -> list[str]:
    """The section's markdown lines for one Figure 3 sweep's table.

    Raises:
        FigureInputError: no such table, or not a Figure 3 sweep's (no controller and
            disturbance columns).
    """
    table = resolve_table(directory)
    rows = read_table(table, ["controller", "disturbance", "success"])
    spec = sweep_spec(table.parent)
    name = str(spec.get("name") or table.parent.name)
    by: dict[str, dict[str, bool]] = {}
    for i, r in enumerate(rows, start=2):
        by.setdefault(r["controller"], {})[r["disturbance"]] = parse_bool(
            r["success"], f"{table}:{i}: column success")
    if not by:
        raise FigureInputError(f"{table}: no finished run")
    lines = [f"## Figure 3 trial by trial: {spec.get('description', name)}", "",
             f"From {repository_file('sweeps', name + '.toml')}'s per-run table "
             f"({len(rows)} runs; settings of every "
             f"run: {settings_text(spec)}; {wall_text(rows)}). The authors' "
             "failures: their own data (the trials that end outside the circle at t = 3 s).",
             "",
             "| controller | hmpc | paper | authors' failures | hmpc's failures | "
             "the authors' failures in hmpc |", "| --- | --- | --- | --- | --- | --- |"]
    verdicts = []
    for controller, trials in by.items():
        ok = sum(trials.values())
        ours = [t for t, s in trials.items() if not s]
        theirs = list(AUTHORS_FAILED.get(controller, ()))
        shared = [t for t in theirs if t in trials and not trials[t]]
        missed = [t for t in theirs if t in trials and trials[t]]
        seen = ("-" if not theirs else
                f"{len(shared)} of {len(theirs)}" + (f" (not: {_names(missed)})" if missed
                                                     else ""))
        lines.append(f"| {controller} | {ok}/{len(trials)} | "
                     f"{PAPER_COUNTS.get(controller, '-')} | {_names(theirs)} | "
                     f"{_names(ours)} | {seen} |")
        paper, source = PAPER_COUNTS.get(controller), "the paper's"
        if paper is None and controller in AUTHORS_FAILED:
            paper = f"{AUTHORS_TRIALS - len(theirs)}/{AUTHORS_TRIALS}"
            source = "the authors' data's (not in the paper)"
        if paper is not None:
            same = paper == f"{ok}/{len(trials)}" and set(ours) == set(theirs)
            verdicts.append(
                f"- {controller}: "
                f"{'count and failing trials reproduced' if same else 'not reproduced'} "
                f"({ok}/{len(trials)} vs {source} {paper}; of the authors' "
                f"{len(theirs)} failures {len(shared)} fail here"
                + (f", and {len(ours) - len(shared)} more" if len(ours) > len(shared) else "")
                + ").")
    return lines + ["", *verdicts, ""]

