"""Fits sim.latency_model to measured MPC solves of one MPC configuration.

Runs the given scenarios with time paused (with ``--set`` overrides: the configuration
to fit, e.g. the real-time iterations), reads each /mpc/solve's iterations, measured
wall time and whether its schedule has a switch left, and fits by least squares
(non-negative) either

* wall = overhead + per_iteration x iterations (default), or
* with ``--switching``: per_iteration for the final-domain NLP and per_switching_iteration
  for a solve with a switch left (the larger NLP),

each term scaled by the solve's plan nodes / ``nodes`` with ``--scale-nodes`` (``nodes`` the
fitted solves' median; one model for several node grids),

side by side with the medians per (switching, iterations). Prints the TOML to paste under
[sim.latency_model] and, with --write, a Markdown report. With --sweep it runs nothing and
fits the solves its runs logged (e.g. a real-time sweep's time-paused cells, run under the
same load as its measured ones).

    python benchmarks/calibrate_latency.py --write results/bench/latency_model.md
    python benchmarks/calibrate_latency.py --switching --scenario scenarios/ball_realtime.toml \
        --write results/bench/latency_model_rti.md
    python benchmarks/calibrate_latency.py --scenario scenarios/biped_stairs.toml \
        --set 'mpc.solver="rti"' --candidates --write results/bench/latency_model_biped_rti.md
    python benchmarks/calibrate_latency.py --switching --scale-nodes \
        --sweep results/sweeps/realtime_ipopt --where latency=paused \
        --write results/bench/latency_model_ipopt.md

``--time call`` fits the controller's whole solve call (/mpc/solve ``call_wall_time``:
the NLP's set-up and the plan too, what ``sim.latency = "measured"`` charges) instead of
the NLP solver's own call (``wall_time``). A foothold planner's candidates (``--candidates``)
are fitted by their NLP solver's call either way: their set-up is in the planner call's
own time, which ``planner`` fits, as "measured" charges a replan.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np

from hmpc_cli.log.reader import read_log
from hmpc_cli.log.rundata import plan_stride
from hmpc_cli.run.runner import execute_run, prepare
from hmpc_cli.run.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ["scenarios/ball.toml", "scenarios/ball_disturbed.toml"]


def solves_of(scenario: Path, runs: int, work: Path, sets: list[str],
              candidates: bool = False) -> list[tuple[int, float, bool, int]]:
    """(iterations, wall time [s], a switch left, plan nodes) of every MPC solve of ``runs``
    paused runs.

    ``candidates``: also the foothold planner's candidate solves (each has its guard); the
    loop's solve that returns a candidate's stored plan (its stats) is counted once.
    """
    out = []
    for k in range(runs):
        sc, text = load_scenario(scenario, [f"seed={k}", 'sim.latency="paused"', *sets])
        run_dir = work / f"{scenario.stem}-{k}"
        execute_run(prepare(sc), text, run_dir)
        out += solves_in(run_dir / "run.mcap", candidates)
    return out


def solves_in(log: Path, candidates: bool = False) -> list[tuple[int, float, bool, int]]:
    """(iterations, wall time [s], a switch left, plan nodes) of every MPC solve logged in
    ``log``.

    Plan nodes: /mpc/solve's ``nodes``; in a log written before it had them (log version
    4), the logged plan's nodes when the run logged every one (``sim.log_plan_stride =
    1``), else 0 (unknown), as for a foothold candidate's solve.
    """
    return logged_solves(read_log(log).messages, candidates)


def logged_solves(messages, candidates: bool = False) -> list[tuple[int, float, bool, int]]:
    """:func:`solves_in` of a log's decoded messages.

    A replan's /mpc/solve that returns a foothold candidate's stored plan (its statistics)
    is left out with ``candidates`` (the candidate is the point) and with ``--time call``
    (its call only returned the plan: the planner call holds the solve's time); it is
    counted in :data:`REUSED`.
    """
    out = []
    chosen: set[float] = set()  # the candidates' wall times: a replan reuses one
    stride = 0  # the run's sim.log_plan_stride (0: unknown)
    skip_reused = candidates or TIME[0] != "wall_time"
    for m in messages:
        if m.topic == "/run/info":
            try:
                stride = plan_stride(json.loads(m.data["scenario_json"]))
            except (KeyError, TypeError, ValueError, AttributeError):
                stride = 0
        elif m.topic == "/mpc/solve" and m.data.get("iterations", 0) > 0 \
                and skip_reused and float(m.data["wall_time"]) in chosen:
            REUSED[0] += 1
        elif m.topic == "/mpc/solve" and m.data.get("iterations", 0) > 0:
            guards = (m.data.get("schedule") or {}).get("guards") or ()
            nodes = m.data.get("nodes", len(m.data.get("plan") or ()) if stride == 1 else 0)
            if TIME[0] not in m.data:
                raise SystemExit(f"--time call: a solve at t = {m.data.get('t')} has no "
                                 f"{TIME[0]} (a log written before hmpc logged it, version "
                                 f"7): run the runs again")
            out.append((int(m.data["iterations"]), float(m.data[TIME[0]]),
                        len(guards) > 0, int(nodes)))
        elif m.topic == "/planner/plan":
            cands = (m.data.get("detail") or {}).get("candidates", [])
            chosen |= {float(c["wall_time"]) for c in cands}
            if candidates:  # each the NLP solver's call: its set-up is the planner's own
                out += [(int(c["iterations"]), float(c["wall_time"]), True, 0)
                        for c in cands if c.get("iterations", 0) > 0]
                OWN.append(float(m.data["wall_time"]) - sum(c["wall_time"] for c in cands))
    return out


def sweep_logs(sweep: Path, where: list[str]) -> list[Path]:
    """The run logs of the sweep directory ``sweep`` whose results.csv row matches every
    ``COLUMN=VALUE`` of ``where`` (its time-paused runs: ``latency=paused``).

    Raises:
        SystemExit: no results.csv, an unknown column, no row matching or a log missing.
    """
    table = sweep / "results.csv"
    if not table.is_file():
        raise SystemExit(f"{table}: no such file (a sweep's output directory has one)")
    with table.open(newline="") as f:
        rows = list(csv.DictReader(f))
    pairs = [w.split("=", 1) for w in where]
    for pair in pairs:
        if len(pair) != 2 or (rows and pair[0] not in rows[0]):
            raise SystemExit(f"--where {'='.join(pair)}: want COLUMN=VALUE with a column of "
                             f"{table} ({', '.join(rows[0]) if rows else 'empty'})")
    picked = [r for r in rows if all(r[k] == v for k, v in pairs)]
    if not picked:
        raise SystemExit(f"{table}: no run matches {' and '.join(where) or 'anything'}")
    unlogged = [r.get("run_id", "?") for r in picked if not (r.get("log") or "").strip()]
    if unlogged:
        raise SystemExit(f"{table}: {len(unlogged)} matching runs have no log (first: run "
                         f"{unlogged[0]}, which did not finish): narrow --where or run the "
                         f"sweep again")
    logs = [sweep / r["log"] for r in picked]
    missing = [str(p) for p in logs if not p.is_file()]
    if missing:
        raise SystemExit(f"{len(missing)} run logs missing (first: {missing[0]}): run "
                         f"the sweep again to make them")
    return logs


#: per planner call, its wall time beyond its candidate solves [s] (``--candidates``)
OWN: list[float] = []
#: the /mpc/solve field fitted: ``wall_time`` (the NLP solver's call) or, with ``--time
#: call``, ``call_wall_time`` (the controller's whole solve call, what "measured" charges)
TIME = ["wall_time"]
#: replan solves left out: each returned a foothold candidate's plan (:func:`logged_solves`)
REUSED = [0]


def _columns(points) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(iterations, wall time [s], a switch left, plan nodes: 0 unknown) of ``points``."""
    it = np.array([p[0] for p in points], dtype=float)
    wall = np.array([p[1] for p in points], dtype=float)
    sw = np.array([p[2] for p in points], dtype=bool)
    nodes = np.array([p[3] if len(p) > 3 else 0 for p in points], dtype=float)
    return it, wall, sw, nodes


def fit(points, switching: bool, nodes: int | None = None) -> dict[str, float]:
    """The model's constants [s]: least squares, each clipped at 0 (refit without it).

    ``points``: (iterations, wall time [s], a switch left[, plan nodes]) per solve.
    ``nodes``: fit the constants at that many plan nodes, every solve's charge scaled by
    its plan's nodes / ``nodes`` (each point needs its nodes; the result has ``nodes``).
    """
    it, wall, sw, n = _columns(points)
    if nodes is not None and not (n > 0).all():
        raise SystemExit(f"{int((n <= 0).sum())} of {len(n)} solves have no plan nodes "
                         f"(logs written before /mpc/solve had them, or foothold "
                         f"candidates): fit them without --scale-nodes")
    scale = n / nodes if nodes is not None else np.ones_like(it)
    names = ["overhead", "per_iteration"] + (["per_switching_iteration"] if switching else [])
    cols = [scale, scale * (np.where(sw, 0.0, it) if switching else it)] + \
        ([scale * np.where(sw, it, 0.0)] if switching else [])
    keep = list(range(len(names)))
    while True:
        coef, *_ = np.linalg.lstsq(np.column_stack([cols[i] for i in keep]), wall, rcond=None)
        if (coef >= 0).all():
            break
        keep.pop(int(np.argmin(coef)))
    out = dict.fromkeys(names, 0.0)
    out.update({names[i]: float(c) for i, c in zip(keep, coef, strict=True)})
    if nodes is not None:
        out["nodes"] = nodes
    return out


#: decimals [s] the constants are printed and charged with
PLACES = 4


def predict(model: dict[str, float], it: np.ndarray, sw: np.ndarray,
            nodes: np.ndarray | None = None) -> np.ndarray:
    """The model's charge [s] of solves with ``it`` iterations, ``sw`` a switch left and
    ``nodes`` plan nodes (scaled as ``sim.latency = "model"`` does when the model has
    ``nodes``)."""
    per = np.where(sw, model.get("per_switching_iteration", model["per_iteration"]),
                   model["per_iteration"])
    charge = model["overhead"] + per * it
    if model.get("nodes") and nodes is not None:
        charge = np.where(nodes > 0, charge * nodes / model["nodes"], charge)
    return charge


def _constant(key: str, value: float) -> str:
    """One TOML line of the model: seconds at :data:`PLACES` decimals, nodes whole."""
    return f"{key} = {int(value)}" if key == "nodes" else f"{key} = {value:.{PLACES}f}"


def machine() -> str:
    """The CPU model, logical CPUs and OS of this machine."""
    cpuinfo = Path("/proc/cpuinfo")
    model = next((line.split(":", 1)[1].strip() for line in cpuinfo.read_text().splitlines()
                  if line.startswith("model name")), platform.processor() or "?") \
        if cpuinfo.is_file() else platform.processor()
    return f"{model}, {os.cpu_count()} logical CPUs, {platform.system()}"


def report(points, model: dict[str, float], scenarios: list[str], sets: list[str],
           candidates: bool = False, source: str | None = None, reused: int = 0) -> str:
    """The Markdown report: the TOML, medians per iteration count beside the model.

    The constants are rounded to :data:`PLACES` decimals as printed, so the model column
    is what ``sim.latency = "model"`` charges with the constants a scenario copies.
    ``source``: where the solves come from, instead of ``scenarios`` run with ``sets``;
    ``reused``: replan solves left out, each a foothold candidate's plan returned.
    """
    model = {k: v if k == "nodes" else round(v, PLACES) for k, v in model.items()}
    it, wall, sw, n = _columns(points)
    it = it.astype(int)
    pred = predict(model, it, sw, n)
    scaled = bool(model.get("nodes"))
    config = f" with `{'`, `'.join(sets)}`" if sets else ""
    lines = ["# The latency model, fitted to measured MPC solves", "",
             f"Machine: {machine()} (machine dependent: re-fit on yours).", "",
             f"{len(points)} solves of "
             + (source or f"{', '.join(scenarios)}{config}, time paused")
             + (" (with the foothold planner's candidate solves)" if candidates else "")
             + (f"; {reused} replan solves left out: each returned a foothold candidate's "
                f"plan, whose time is the planner call's (`--candidates` fits the "
                f"candidates)" if reused else "")
             + ".", "",
             "```toml", "[sim.latency_model]",
             *(_constant(k, v) for k, v in model.items()), "```", ""]
    if scaled:
        lines += [f"Each solve is charged its plan's nodes / {int(model['nodes'])} times the "
                  "constants; the model column is the median charge of the row's solves.", ""]
    lines += ["| switch left | iterations | solves | measured median [ms] | measured p95 [ms] "
              "| model [ms] |", "|---|---|---|---|---|---|"]
    for s in sorted(set(sw.tolist())):
        for k in sorted(set(it[sw == s].tolist())):
            sel = (it == k) & (sw == s)
            w = wall[sel] * 1e3
            lines.append(f"| {'yes' if s else 'no'} | {k} | {len(w)} | {np.median(w):.1f} | "
                         f"{np.percentile(w, 95):.1f} | {np.median(pred[sel]) * 1e3:.1f} |")
    if scaled:
        lines += ["", "By plan nodes:", "", "| plan nodes | solves | measured median [ms] | "
                  "measured p95 [ms] | model median [ms] |", "|---|---|---|---|---|"]
        for k in sorted(set(n.astype(int).tolist())):
            sel = n == k
            w = wall[sel] * 1e3
            lines.append(f"| {k} | {len(w)} | {np.median(w):.1f} | "
                         f"{np.percentile(w, 95):.1f} | {np.median(pred[sel]) * 1e3:.1f} |")
    err = np.abs(pred - wall) * 1e3
    lines += ["", f"Absolute error of the model: median {np.median(err):.1f} ms, "
              f"p95 {np.percentile(err, 95):.1f} ms.", ""]
    if "planner" in model:
        lines[-1:] = ["", f"`planner`: the median of a planner call's wall time beyond its "
                      f"candidate solves, {len(OWN)} calls (max "
                      f"{max(OWN) * 1e3:.1f} ms).", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="seeds per scenario")
    ap.add_argument("--scenario", action="append", help="scenario (repeatable; default: "
                    + ", ".join(SCENARIOS) + ")")
    ap.add_argument("--set", action="append", default=[], dest="sets",
                    help="KEY=VALUE override of every run (repeatable)")
    ap.add_argument("--trials", default="", help="also Figure 3 trials K,K,... of each "
                    "scenario (disturbance.trial, paper_fig3)")
    ap.add_argument("--switching", action="store_true",
                    help="fit per_switching_iteration for solves with a switch left")
    ap.add_argument("--scale-nodes", action="store_true",
                    help="charges scale with the plan's nodes (sim.latency_model.nodes, set "
                    "to the fitted solves' median): one model for several node grids")
    ap.add_argument("--candidates", action="store_true",
                    help="also the foothold planner's candidate solves (the model charges "
                    "each as a solve)")
    ap.add_argument("--sweep", type=Path, help="run nothing: fit the solves logged by "
                    "the runs of this sweep output directory (its results.csv and logs), "
                    "e.g. results/sweeps/realtime_ipopt with --where latency=paused")
    ap.add_argument("--where", action="append", default=[], metavar="COLUMN=VALUE",
                    help="with --sweep: only the runs whose results.csv row has this "
                    "value (repeatable)")
    ap.add_argument("--time", choices=("solver", "call"), default="solver",
                    help="fit the NLP solver's call (wall_time, default) or the controller's "
                    "whole solve call (call_wall_time: the set-up and the plan too, what "
                    "sim.latency = \"measured\" charges)")
    ap.add_argument("--write", type=Path, help="write the Markdown report here")
    args = ap.parse_args()
    if args.time == "call":
        TIME[0] = "call_wall_time"
    if args.where and not args.sweep:
        ap.error("--where needs --sweep")
    if args.sweep and (args.scenario or args.sets or args.trials):
        ap.error("--sweep fits logged runs: --scenario, --set and --trials run new ones")
    scenarios = args.scenario or SCENARIOS
    source = None
    if args.sweep:
        logs = sweep_logs(args.sweep, args.where)
        points = [p for log in logs for p in solves_in(log, args.candidates)]
        source = (f"the {len(logs)} runs of `{args.sweep}`"
                  + (f" with {' and '.join(f'`{w}`' for w in args.where)}" if args.where
                     else "") + f" (their logged `{TIME[0]}`)")
    else:
        cases = [(s, []) for s in scenarios]
        cases += [(s, ['disturbance.kind="paper_fig3"', f"disturbance.trial={k}"])
                  for s in scenarios for k in (int(x) for x in args.trials.split(",") if x)]
        with tempfile.TemporaryDirectory() as tmp:
            points = [p for n, (s, extra) in enumerate(cases) for p in solves_of(
                ROOT / s, args.runs, Path(tmp) / str(n), [*args.sets, *extra],
                args.candidates)]
    ref = None
    if args.scale_nodes:
        counts = [p[3] for p in points if len(p) > 3 and p[3] > 0]
        ref = int(np.median(counts)) if counts else 0
    model = fit(points, args.switching, ref)
    if args.candidates and OWN:
        model["planner"] = float(np.median(OWN))  # the planner's own time, median
    text = report(points, model, scenarios, args.sets, args.candidates, source,
                  0 if args.candidates else REUSED[0])
    print(text)
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(text)


if __name__ == "__main__":
    main()
