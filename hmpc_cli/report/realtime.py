"""The results page's real-time section: does the controller keep up, from a sweep table alone.

For a sweep with grid axes ``latency`` (``sim.latency``: paused, model, measured),
``controller`` (MPC rate and replanning) and ``disturbance`` (e.g.
``sweeps/realtime_rti.toml``) it tables the successes per controller and latency and the
per-run solve times of the runs whose compute time was measured (machine dependent). It
reads the table only (no log), so a committed table regenerates it.
"""

from __future__ import annotations

import statistics
from pathlib import Path

from hmpc_cli.analysis.tables import (
    FigureInputError, parse_bool, read_table, resolve_table, sweep_spec)
from hmpc_cli.report.robustness import wall_text

__all__ = ["realtime_section"]

#: what each latency kind means, as the page says it
KINDS = {"paused": "time paused while the controllers compute (the paper's runs)",
         "model": "each solve charged by the scenario's fitted solve-time model "
                  "(deterministic)",
         "measured": "each solve charged its measured wall time on the machine that ran "
                     "the table (not reproducible elsewhere)"}


def _ms(rows: list[dict], key: str, how) -> str:
    values = [float(v) * 1e3 for r in rows if (v := (r.get(key) or "").strip())
              and v.lower() != "nan"]
    return f"{how(values):.1f}" if values else "-"


def realtime_section(directory: Path) -> list[str]:
    """The section's markdown lines for one real-time sweep's table.

    Raises:
        FigureInputError: no such table, or not a real-time sweep's (no latency,
            controller and success columns).
    """
    table = resolve_table(directory)
    rows = read_table(table, ["latency", "controller", "success"])
    spec = sweep_spec(table.parent)
    lats = list(dict.fromkeys(r["latency"] for r in rows))
    ctrls = list(dict.fromkeys(r["controller"] for r in rows))
    ok: dict[tuple[str, str], list[bool]] = {}
    for line, r in enumerate(rows, start=2):
        ok.setdefault((r["latency"], r["controller"]), []).append(
            parse_bool(r["success"], f"{table}:{line}: success"))
    if not ok:
        raise FigureInputError(f"{table}: no finished run")
    scenario = Path(str(spec.get("scenario", "?"))).name
    lines = ["## Real time: does the controller keep up?", "",
             f"From `sweeps/{spec.get('name', table.parent.name)}.toml`'s per-run table "
             f"({len(rows)} runs of `scenarios/{scenario}`: the nominal ball and the "
             f"Figure 3 trials; {wall_text(rows)}). A plan reaches the plant its charged "
             "compute time after the state it was solved from; until then the previous "
             "plan is tracked. Latency:", ""]
    lines += [f"- `{lat}`: {KINDS.get(lat, lat)}." for lat in lats]
    lines += ["", "| controller | " + " | ".join(lats) + " |", "|---|" + "---|" * len(lats)]
    for c in ctrls:
        cells = [f"{sum(v)}/{len(v)}" if (v := ok.get((lat, c))) else "-" for lat in lats]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    if "measured" in lats:
        lines += ["", "MPC solve times of the `measured` runs (per run: its median and p95 "
                  "over all its solves; machine dependent, pooled percentiles and the "
                  "machine: `results/bench/realtime_rti.md`):", "",
                  "| controller | median of the runs' medians [ms] | largest p95 [ms] |",
                  "|---|---|---|"]
        for c in ctrls:
            sel = [r for r in rows if r["latency"] == "measured" and r["controller"] == c]
            lines.append(f"| {c} | {_ms(sel, 'solve_time_median', statistics.median)} | "
                         f"{_ms(sel, 'solve_time_p95', max)} |")
    return lines + [""]
