"""The results page's real-time section: does the controller keep up, from a sweep table alone.

For a sweep with grid axes ``latency`` (entries setting ``sim.latency``: paused, model,
measured, and possibly more, e.g. ``lowlevel.past_guard``) and ``controller`` (e.g. MPC
rate and replanning; ``sweeps/realtime_rti.toml``, ``realtime_biped.toml``) it tables the
successes per controller and latency entry and the per-run solve times of the runs whose
compute time was measured (machine dependent). It reads the table and the sweep file only
(no log), so a committed table regenerates it.
"""

from __future__ import annotations

import statistics
from pathlib import Path

from hmpc_cli.analysis.tables import (
    FigureInputError, parse_bool, read_table, resolve_table, sweep_spec)
from hmpc_cli.report.robustness import settings_text, wall_text

__all__ = ["realtime_section"]

#: what each latency kind means, as the page says it
KINDS = {"paused": "time paused while the controllers compute (the paper's runs)",
         "model": "each solve charged by the scenario's fitted solve-time model "
                  "(deterministic)",
         "measured": "each solve charged its measured wall time on the machine that ran "
                     "the table (not reproducible elsewhere)"}


#: what each ``lowlevel.past_guard`` means, as the page says it
PAST_GUARD = {"hold": "the low level holds the plan's guard node after an impact until the "
                      "next plan arrives",
              "next_domain": "the low level follows the plan's next domain from the "
                             "contact's time"}

HEADING = "## Real time: does the controller keep up?"


def _latency_entries(spec: dict) -> dict[str, dict]:
    """The sweep's latency axis: label -> the settings of that entry (empty if unknown)."""
    axis = (spec.get("grid") or {}).get("latency") or []
    return {str(e.get("label", e.get("sim.latency"))): e for e in axis if isinstance(e, dict)}


def _kind(label: str, entries: dict[str, dict]) -> str:
    """The ``sim.latency`` kind of a latency label (the label itself when unknown)."""
    return str(entries.get(label, {}).get("sim.latency", label))


def _meaning(label: str, entries: dict[str, dict]) -> str:
    entry, kind = entries.get(label, {}), _kind(label, entries)
    text = KINDS.get(kind, kind)
    past = entry.get("lowlevel.past_guard")
    return f"{text}; {PAST_GUARD.get(past, past)}" if past else text


def _ms(rows: list[dict], key: str, how) -> str:
    values = [float(v) * 1e3 for r in rows if (v := (r.get(key) or "").strip())
              and v.lower() != "nan"]
    return f"{how(values):.1f}" if values else "-"


def realtime_section(directory: Path) -> list[str]:
    """The markdown lines of one real-time sweep's table (a sub-section of :data:`HEADING`).

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
    name = spec.get("name", table.parent.name)
    entries = _latency_entries(spec)
    lines = [f"### `sweeps/{name}.toml`: {spec.get('description', name)}", "",
             f"From its per-run table ({len(rows)} runs of `scenarios/{scenario}`; "
             f"settings of every run: {settings_text(spec)}; "
             f"{wall_text(rows)}). A plan reaches the plant its charged compute time after "
             "the state it was solved from; until then the previous plan is tracked. "
             "Latency:", ""]
    lines += [f"- `{lat}`: {_meaning(lat, entries)}." for lat in lats]
    lines += ["", "| controller | " + " | ".join(lats) + " |", "|---|" + "---|" * len(lats)]
    for c in ctrls:
        cells = [f"{sum(v)}/{len(v)}" if (v := ok.get((lat, c))) else "-" for lat in lats]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    measured = [lat for lat in lats if _kind(lat, entries) == "measured"]
    if measured:
        lines += ["", "MPC solve times of the measured runs (per run: its median and p95 "
                  "over all its solves; machine dependent, pooled percentiles and the "
                  f"machine: `results/bench/{name}.md`):", "",
                  "| controller | " + " | ".join(
                      f"`{lat}`: median of the runs' medians [ms] | largest p95 [ms]"
                      for lat in measured) + " |", "|---|" + "---|---|" * len(measured)]
        for c in ctrls:
            cells = []
            for lat in measured:
                sel = [r for r in rows if r["latency"] == lat and r["controller"] == c]
                cells += [_ms(sel, "solve_time_median", statistics.median),
                          _ms(sel, "solve_time_p95", max)]
            lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return lines + [""]
