"""The results page's real-time section: does the controller keep up, from a sweep table alone.

For a sweep with grid axes ``latency`` (entries setting ``sim.latency``: paused, model,
measured, and possibly more, e.g. ``lowlevel.past_guard``) and ``controller`` (e.g. MPC
rate and replanning; ``sweeps/realtime_rti.toml``, ``realtime_biped.toml``) it tables the
successes per controller and latency entry, the solves each controller made against its
time-paused twin (whether it keeps up with its rate), and the per-run solve times of the
runs whose compute time was measured (machine dependent). It reads the table and the sweep file only
(no log), so a committed table regenerates it.
"""

from __future__ import annotations

import statistics
from pathlib import Path

from hmpc_cli.analysis.tables import (
    FigureInputError, count_cell, parse_bool, pooled_counts, read_table, resolve_table,
    sweep_spec)
from hmpc_cli.report.paths import repository_file
from hmpc_cli.report.robustness import (
    FLOWN_BEFORE, PAST_PERIOD, past_period_table, settings_text, wall_text)

__all__ = ["realtime_section"]

#: what each latency kind means, as the page says it
KINDS = {"paused": "time paused while the controllers compute (the paper's runs)",
         "model": "each solve charged by the {whose} fitted solve-time model "
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


def _sim_settings(table: Path, spec: dict, entry: dict | None = None) -> dict:
    """The runs' ``[sim]``: the base scenario beside the table, ``[set]``, a grid ``entry``.

    The sweep's ``[set]`` ``sim.*`` keys go over the base scenario's ({} when that cannot
    be read), the entry's over both (e.g. a latency entry's own ``sim.latency_model.*``).
    """
    import tomllib

    try:
        sim = dict(tomllib.loads((table.parent / "base_scenario.toml").read_text())["sim"])
    except (OSError, KeyError, TypeError, ValueError, tomllib.TOMLDecodeError):
        sim = {}
    for key, value in [*(spec.get("set") or {}).items(), *(entry or {}).items()]:
        if not key.startswith("sim."):
            continue
        head, _, rest = key.removeprefix("sim.").partition(".")
        sim[head] = {**dict(sim.get(head) or {}), rest: value} if rest else value
    return sim


def _model_costs(sim: dict) -> str:
    """The runs' ``sim.latency_model`` in words ('' when the settings cannot say)."""
    try:
        model = dict(sim["latency_model"])
        nodes = model.pop("nodes", None)  # plan nodes, not seconds
        ms = {k: 1e3 * float(v) for k, v in model.items() if v is not None}
        size = (f"at {int(nodes)} plan nodes, a plan of n nodes charged n / {int(nodes)} "
                "times them" if nodes else "not scaled to the NLP's size")
    except (KeyError, TypeError, ValueError):
        return ""
    switching = (f" ({ms['per_switching_iteration']:g} ms with a switch left)"
                 if "per_switching_iteration" in ms else "")
    return (f": {ms.get('overhead', 0.0):g} ms per solve + {ms.get('per_iteration', 0.0):g} ms "
            f"per iteration{switching}, the costs of the solves they were fitted to (on one "
            f"machine; {size}) whatever the controller's own, and "
            f"{ms.get('planner', 0.0):g} ms per planner call")


def _meaning(label: str, entries: dict[str, dict], costs: str = "") -> str:
    entry, kind = entries.get(label, {}), _kind(label, entries)
    own = any(k.startswith("sim.latency_model.") for k in entry)  # the entry sets it
    text = KINDS.get(kind, kind).format(whose="sweep's" if own else "scenario's") + \
        (costs if kind == "model" else "")
    past = entry.get("lowlevel.past_guard")
    return f"{text}; {PAST_GUARD.get(past, past)}" if past else text


def _ms(rows: list[dict], key: str, how) -> str:
    values = [float(v) * 1e3 for r in rows if (v := (r.get(key) or "").strip())
              and v.lower() != "nan"]
    return f"{how(values):.1f}" if values else "-"


#: a controller solves as often as with time paused when it makes at least this share of
#: its time-paused twin's solves
KEEPS_UP = 0.95


def _duration(sim: dict) -> float | None:
    """The runs' ``sim.duration`` [s] (None: the settings cannot say)."""
    try:
        return float(sim["duration"])
    except (KeyError, TypeError, ValueError):
        return None


def _keep_up_lines(solves: dict[tuple[str, str], list[int]], lats: list[str],
                   ctrls: list[str], entries: dict[str, dict],
                   duration: float | None) -> list[str]:
    """The solves each controller made per latency entry, against its time-paused twin.

    ``solves``: (latency, controller) -> the MPC solves of its successful runs (each flew
    the scenario's whole duration).
    """
    paused = next((lat for lat in lats if _kind(lat, entries) == "paused"), None)
    med = {key: statistics.median(v) for key, v in solves.items() if v}
    span = f"the whole {duration:g} s" if duration is not None else \
        "the scenario's whole duration"
    lines = ["", f"Does it keep up: MPC solves per successful run (median; a successful run "
             f"flies {span}). There is one solver: a solve that falls due (a period, "
             "a contact) while it still computes waits for it, so a controller whose "
             "charged compute time exceeds its period solves less often than its rate"
             + (f" (in brackets: the share of the `{paused}` runs' count)." if paused is not
                None else " (in brackets: solves per second of simulated time)."), "",
             "| controller | " + " | ".join(lats) + " |", "|---|" + "---|" * len(lats)]
    short: dict[str, list[str]] = {lat: [] for lat in lats if lat != paused}
    for c in ctrls:
        cells = []
        for lat in lats:
            if (lat, c) not in med:
                cells.append("-")
            elif paused is None or lat == paused:
                rate = f" ({med[(lat, c)] / duration:.0f}/s)" if duration and paused is None \
                    else ""
                cells.append(f"{med[(lat, c)]:g}{rate}")
            elif med.get((paused, c)):
                share = med[(lat, c)] / med[(paused, c)]
                cells.append(f"{med[(lat, c)]:g} ({100 * share:.0f} %)")
                if share < KEEPS_UP:
                    short[lat].append(f"{c} {100 * share:.0f} %")
            else:
                cells.append(f"{med[(lat, c)]:g}")
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    if paused is not None:
        lines.append("")
        for lat, slow in short.items():
            n = sum((lat, c) in med and bool(med.get((paused, c))) for c in ctrls)
            lines.append(f"- `{lat}`: as many solves as with time paused (at least "
                         f"{100 * KEEPS_UP:.0f} %) for {n - len(slow)} of the {n} controllers "
                         "with successful runs both ways"
                         + (f"; fewer: {', '.join(slow)}." if slow else "."))
    return lines


def _late_lines(table: Path, rows: list[dict], lats: list[str], ctrls: list[str],
                entries: dict[str, dict]) -> list[str]:
    """Per controller and charged latency entry: its solves past the MPC period.

    Pooled over the cell's runs that recorded ``real_time`` (the table's ``late_solves``,
    ``dropped_solves``, ``preempted_solves`` of ``charged_solves``; empty in a row flown
    before hmpc recorded them).
    """
    from hmpc_cli.sweep.table import POOLED

    charged = [lat for lat in lats if _kind(lat, entries) != "paused"]
    if not charged:
        return []
    pooled = pooled_counts(table, rows, lambda r: (r["controller"], r["latency"])
                           if r["latency"] in charged else None, POOLED)
    shown = [lat for lat in charged if any((c, lat) in pooled for c in ctrls)]
    unrecorded = ", ".join(f"`{lat}`" for lat in charged if lat not in shown)
    before = FLOWN_BEFORE.format(f"the {unrecorded}") if unrecorded else ""
    if not shown:
        return ["", f"Solves past the MPC period: not in this table; {before}."]
    return ["", PAST_PERIOD.format(pooled="every run of the cell that recorded them pooled")
            + "; `-`: no run of the cell recorded them" + (f"; {before}" if before else "")
            + "):", "", *past_period_table(pooled, "controller", ctrls, shown)]


def realtime_section(directory: Path) -> list[str]:
    """The markdown lines of one real-time sweep's table (a sub-section of :data:`HEADING`).

    Raises:
        FigureInputError: no such table, or not a real-time sweep's (no latency,
            controller and success columns).
    """
    table = resolve_table(directory)
    rows = read_table(table, ["latency", "controller", "success", "solves"])
    spec = sweep_spec(table.parent)
    lats = list(dict.fromkeys(r["latency"] for r in rows))
    ctrls = list(dict.fromkeys(r["controller"] for r in rows))
    ok: dict[tuple[str, str], list[bool]] = {}
    solves: dict[tuple[str, str], list[int]] = {}
    for line, r in enumerate(rows, start=2):
        key = (r["latency"], r["controller"])
        ok.setdefault(key, []).append(parse_bool(r["success"], f"{table}:{line}: success"))
        if ok[key][-1]:
            solves.setdefault(key, []).append(count_cell(r["solves"], f"{table}:{line}: solves"))
    if not ok:
        raise FigureInputError(f"{table}: no finished run")
    scenario = Path(str(spec.get("scenario", "?"))).name
    name = spec.get("name", table.parent.name)
    entries = _latency_entries(spec)
    lines = [f"### {repository_file('sweeps', name + '.toml')}: "
             f"{spec.get('description', name)}", "",
             f"From its per-run table ({len(rows)} runs of "
             f"{repository_file('scenarios', scenario)}; "
             f"settings of every run: {settings_text(spec)}; "
             f"{wall_text(rows)}). A plan reaches the plant its charged compute time after "
             "the state it was solved from; until then the previous plan is tracked. "
             "Latency:", ""]
    sim = _sim_settings(table, spec)
    for lat in lats:  # a latency entry may set its own model
        costs = _model_costs(_sim_settings(table, spec, entries.get(lat)))
        lines.append(f"- `{lat}`: {_meaning(lat, entries, costs)}.")
    lines += ["", "| controller | " + " | ".join(lats) + " |", "|---|" + "---|" * len(lats)]
    for c in ctrls:
        cells = [f"{sum(v)}/{len(v)}" if (v := ok.get((lat, c))) else "-" for lat in lats]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    lines += _keep_up_lines(solves, lats, ctrls, entries, _duration(sim))
    lines += _late_lines(table, rows, lats, ctrls, entries)
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
