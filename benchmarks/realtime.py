"""The paper's yardstick in real time: does the layered controller keep up?

Runs the nominal ball and the 10 Figure 3 trials at 10, 20, 60 and 100 Hz (100 Hz on
``mpc.nodes_per_second = 100``), plan-once and replanning on contact, with the compute time
``paused`` (the paper's runs), charged by the deterministic ``model`` and ``measured``
(machine dependent), each with delay compensation and the first plan paused, through
``hmpc sweep``'s machinery (resumable: ``--out`` keeps finished runs). Prints and writes
success counts per cell, the solves past the MPC period (from the runs' ``real_time``), and
the MPC solve percentiles (all solves, and those with a switch left), measured wall time
and charged delay.

    python benchmarks/realtime.py --write results/bench/realtime.md
    python benchmarks/realtime.py --latency paused,model --rates 20,60 --workers 2
    python benchmarks/realtime.py --scenario scenarios/ball_realtime.toml --no-compensation \
        --workers 1 --out rti_runs

``--scenario`` picks the MPC configuration (default: scenarios/ball.toml, IPOPT to
convergence; scenarios/ball_realtime.toml: real-time iterations with its fitted latency
model); the grid overrides its rate, replanning, latency and disturbance. ``--sweep``
runs and reports a sweep file with the same axes instead (its ``latency`` entries may set
more than the latency, e.g. the low level past the guard):

    python benchmarks/realtime.py --sweep sweeps/realtime_ipopt.toml --workers 2 \
        --out results/sweeps/realtime_ipopt --write results/bench/realtime_ipopt.md

``--out`` must be free or the same sweep's directory (``hmpc sweep``'s rule), and
``--write`` needs every run's log in it: a committed table's rows have none, so a
report over them is printed, not written.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import platform
import tomllib
from pathlib import Path

import numpy as np

from hmpc_cli.log.reader import read_log
from hmpc_cli.run.sections import SimSettings
from hmpc_cli.sweep.execute import execute_sweep
from hmpc_cli.sweep.plan import plan_sweep

ROOT = Path(__file__).resolve().parents[1]
RATES = (10, 20, 60, 100)
POLICIES = ("once", "on_contact")
LATENCIES = ("paused", "model", "measured")
TRIALS = 10
GRID_NAME = "realtime"  #: the sweep name of the yardstick's own grid (without --sweep)


def sweep_text(latencies, rates, policies, trials: int, compensate: bool,
               scenario: Path = ROOT / "scenarios" / "ball.toml") -> str:
    """The sweep file of the yardstick's grid over ``scenario``."""
    lines = [f'name = "{GRID_NAME}"', f'scenario = "{Path(scenario).resolve().as_posix()}"',
             "seeds = [0]", "[set]", '"sim.latency_first" = "paused"',
             f'"sim.delay_compensation" = {str(compensate).lower()}', "[grid]", "latency = ["]
    lines += [f'  {{ label = "{lat}", "sim.latency" = "{lat}" }},' for lat in latencies]
    lines += ["]", "controller = ["]
    for rate in rates:
        nps = 100 if rate == 100 else 60
        for pol in policies:
            lines.append(f'  {{ label = "{rate} Hz {pol}", "mpc.rate_hz" = {rate}, '
                         f'"mpc.nodes_per_second" = {nps}, "replanning.policy" = "{pol}" }},')
    lines += ["]", "disturbance = [", '  { label = "nominal", "disturbance.kind" = "none" },']
    lines += [f'  {{ label = "trial {k}", "disturbance.kind" = "paper_fig3", '
              f'"disturbance.trial" = {k} }},' for k in range(1, trials + 1)]
    lines.append("]")
    return "\n".join(lines) + "\n"


def solves_of(log: Path) -> list[tuple[float, float, bool]]:
    """(measured wall [s], charged delay [s], a switch left) of every MPC solve of a log."""
    out = []
    for m in read_log(log).messages:
        if m.topic == "/mpc/solve":
            d = m.data
            sched = d.get("schedule") or {}
            out.append((float(d.get("wall_time") or math.nan), float(d.get("latency") or 0.0),
                        bool(sched.get("guards"))))
    return out


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(values, q)) * 1e3 if values else math.nan


def summarise(out: Path) -> tuple[dict, dict, float, int, list[str]]:
    """Success counts and solves per (latency, controller); the runs' summed wall time [s];
    how many rows have no run directory in ``out`` (a committed table's rows); the CPUs the
    rows name (their ``cpu`` column, where the table has one)."""
    with open(out / "results.csv", newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    counts: dict[tuple[str, str], list[int]] = {}
    solves: dict[tuple[str, str], list[tuple[float, float, bool]]] = {}
    no_log = 0
    for row in rows:
        key = (row["latency"], row["controller"])
        ok = row["success"].strip().lower() == "true"
        c = counts.setdefault(key, [0, 0])
        c[0] += ok
        c[1] += 1
        log = out / row["log"] if row.get("log") else None
        if log is not None and log.is_file():
            solves.setdefault(key, []).extend(solves_of(log))
        elif not (out / "runs" / row.get("run_id", "")).is_dir():
            no_log += 1  # a table's row (a run that raised before its log has its directory)
    walls = [float(r["wall_time"]) for r in rows if r.get("wall_time")]
    cpus = sorted({r["cpu"] for r in rows if r.get("cpu")})
    return counts, solves, sum(walls), no_log, cpus


def past_period(out: Path) -> dict[tuple[str, str], list[int]]:
    """Per (latency, controller): the table's charged, late, dropped and stopped solves,
    pooled over its runs that recorded them (the summary's ``real_time``; a row flown
    before hmpc recorded it has none)."""
    from hmpc_cli.analysis.tables import pooled_counts
    from hmpc_cli.sweep.table import POOLED

    table = out / "results.csv"
    with open(table, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    return pooled_counts(table, rows, lambda r: (r["latency"], r["controller"]), POOLED)


def _past_period_lines(late: dict, lats: list[str], ctrls: list[str]) -> list[str]:
    """The report's table of :func:`past_period` (none when no run recorded it)."""
    from hmpc_cli.report.robustness import past_period_table

    shown = [lat for lat in lats if any(k[0] == lat for k in late)]
    if not shown:
        return []
    return ["", "Solves past the MPC period (`late_solves` of `charged_solves` of the "
            "runs' `real_time`, pooled; then those the budget dropped and a contact stopped; "
            "`-`: not recorded):", "",
            *past_period_table({(c, lat): v for (lat, c), v in late.items()}, "controller",
                               ctrls, shown)]


def machine(cpus: list[str] = ()) -> str:
    """The runs' CPUs when the table names them, else this machine (marked so)."""
    if cpus:
        return f"{', '.join(cpus)} (the runs' own, from the table)"
    cpu = platform.processor() or "?"
    info = Path("/proc/cpuinfo")
    if info.is_file():
        cpu = next((ln.split(":", 1)[1].strip() for ln in info.read_text().splitlines()
                    if ln.startswith("model name")), cpu)
    return (f"{cpu}, {os.cpu_count()} logical CPUs, load {os.getloadavg()[0]:.1f} (the "
            "machine that wrote this report; the table does not name the runs')")


def _solve_row(label: str, s: list[tuple[float, float, bool]]) -> str:
    wall = [w for w, _, _ in s if math.isfinite(w)]
    sw = [w for w, _, sw_ in s if sw_ and math.isfinite(w)]
    ch = [c for _, c, _ in s if c > 0]
    return (f"| {label} | {len(s)} | {_pct(wall, 50):.1f} | {_pct(wall, 95):.1f} | "
            f"{_pct(sw, 50):.1f} | {_pct(sw, 95):.1f} | {_pct(ch, 50):.1f} | "
            f"{_pct(ch, 95):.1f} |")


SOLVE_HEAD = ["| {} | solves | all median | all p95 | switching median | switching p95 "
              "| charged median | charged p95 |", "|---|---|---|---|---|---|---|---|"]


def run_settings(plan) -> str:
    """What the planned runs' effective scenarios say of delay compensation and the first
    plan: one value for all, or the values found (the controllers' labels say which)."""
    found: dict[str, set] = {"sim.delay_compensation": set(), "sim.latency_first": set()}
    for run in plan.runs:
        sim = tomllib.loads(run.toml).get("sim", {})
        for key, values in found.items():
            name = key.split(".", 1)[1]
            values.add(sim.get(name, SimSettings.model_fields[name].default))
    comp = found["sim.delay_compensation"]
    first = found["sim.latency_first"]
    comp_text = (f"Delay compensation {'on' if comp.pop() else 'off'}" if len(comp) == 1
                 else "Delay compensation on in some runs, off in others")
    first_text = (f"first plan {first.pop()}" if len(first) == 1
                  else f"first plan {' or '.join(sorted(first))} (as each controller's "
                  "label says)")
    return f"{comp_text}, {first_text}"


def report(counts: dict, solves: dict, args, cpu: float, cpus: list[str] = (),
           late: dict | None = None) -> str:
    """The Markdown report: success per controller and latency, solves past the period
    (``late``: :func:`past_period`), solve percentiles."""
    lats = [lat for lat in args.latency if any(k[0] == lat for k in counts)]
    ctrls = list(dict.fromkeys(k[1] for k in counts))
    lines = [f"# Real time: {args.title}", "",
             f"Generated by `{args.command}`.", "",
             f"MPC configuration: `{args.scenario_name}` (its solver"
             f"{'' if args.own_model else ' and latency model'}; "
             f"{args.grid_says}).", "",
             f"Machine: {machine(cpus)}. `measured` rows are machine (and load) dependent; "
             "`model` charges `sim.latency_model` (deterministic); `paused` is the paper's "
             "setting.", "",
             f"{args.settings}; the runs' wall times sum to {cpu / 60:.1f} min (summed over "
             "the runs, not elapsed).", "",
             "| controller | " + " | ".join(lats) + " |",
             "|---|" + "---|" * len(lats)]
    for c in ctrls:
        cells = [f"{counts[(lat, c)][0]}/{counts[(lat, c)][1]}" if (lat, c) in counts else "-"
                 for lat in lats]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    lines += _past_period_lines(late or {}, lats, ctrls)
    lines += ["", "MPC solves [ms] (measured wall time; charged delay for model/measured), "
              "all controllers:", "", SOLVE_HEAD[0].format("latency"), SOLVE_HEAD[1]]
    for lat in lats:
        lines.append(_solve_row(lat, [x for c in ctrls for x in solves.get((lat, c), [])]))
    for lat in lats:
        lines += ["", f"By controller, `{lat}`:", "", SOLVE_HEAD[0].format("controller"),
                  SOLVE_HEAD[1]]
        lines += [_solve_row(c, solves.get((lat, c), [])) for c in ctrls]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--latency", default=",".join(LATENCIES))
    ap.add_argument("--rates", default=",".join(map(str, RATES)))
    ap.add_argument("--policies", default=",".join(POLICIES))
    ap.add_argument("--trials", type=int, default=TRIALS, help="disturbed trials (0..10)")
    ap.add_argument("--no-compensation", dest="compensate", action="store_false")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "ball.toml",
                    help="the MPC configuration (default: scenarios/ball.toml)")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "bench" / "realtime_runs")
    ap.add_argument("--write", type=Path, help="write the Markdown report here")
    ap.add_argument("--sweep", type=Path, help="a sweep file with axes latency, controller "
                    "and disturbance: run (resumable) and report it instead of the grid")
    args = ap.parse_args()
    args.latency = args.latency.split(",")
    import shlex
    import sys

    from hmpc_cli.report.paths import portable_command

    args.command = portable_command(shlex.join(["python", "benchmarks/realtime.py",
                                                *sys.argv[1:]]), ROOT)
    plan = _plan(args)
    args.settings = run_settings(plan)
    args.scenario_name = args.scenario.resolve().relative_to(ROOT).as_posix() \
        if args.scenario.resolve().is_relative_to(ROOT) else args.scenario.name
    args.out.mkdir(parents=True, exist_ok=True)
    execute_sweep(plan, args.out, workers=args.workers)
    counts, solves, cpu, no_log, cpus = summarise(args.out)
    out = report(counts, solves, args, cpu, cpus, past_period(args.out))
    print(out)
    if no_log and args.write:
        _refuse(f"--write {args.write}: {no_log} of {sum(c[1] for c in counts.values())} "
                f"runs in {args.out} have no log (their rows came from a committed table), "
                "so the solve percentiles above leave them out; nothing written: run into a "
                "new --out to measure every run on this machine")
    if args.write:
        args.write.write_text(out, encoding="utf-8")


def _plan(args):
    """The sweep to run: ``--sweep``'s, or the yardstick's grid written into ``--out``.

    Sets the report's ``title`` and ``grid_says`` (and, for ``--sweep``, its ``latency``
    and ``scenario``) on ``args``; exit 2 when ``--out`` is another sweep's directory.
    """
    from hmpc_cli.sweep.lock import owner_problem

    plan = plan_sweep(args.sweep) if args.sweep is not None else None
    problem = owner_problem(args.out, plan.spec.name if plan is not None else GRID_NAME)
    if problem is not None:
        _refuse(f"--out {args.out}: {problem}")
    if plan is not None:
        axes = {a.name: a for a in plan.axes}
        args.latency = [str(label) for label in axes["latency"].labels]
        args.scenario = plan.scenario
        args.title = plan.spec.description or plan.spec.name
        args.own_model = any(k.startswith("sim.latency_model") for ov in
                             axes["latency"].overrides for k in ov)
        args.grid_says = f"the grid of `{args.sweep.as_posix()}` sets the rest" + (
            ", its latency entries their own latency model" if args.own_model else "")
        return plan
    args.title = "the nominal ball and the 10 Figure 3 trials"
    args.own_model = False  # the grid's latencies set no model
    args.grid_says = "the grid sets rate, replanning, latency and disturbance"
    text = sweep_text(args.latency, [int(r) for r in args.rates.split(",")],
                      args.policies.split(","), args.trials, args.compensate, args.scenario)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:  # planned before anything is written
        (Path(tmp) / "realtime.toml").write_text(text, encoding="utf-8")
        plan_sweep(Path(tmp) / "realtime.toml")
    args.out.mkdir(parents=True, exist_ok=True)
    spec = args.out / "realtime.toml"
    spec.write_text(text, encoding="utf-8")
    return plan_sweep(spec)


def _refuse(line: str) -> None:
    """``error: line`` on stderr, exit 2 (bad input; nothing written)."""
    import sys

    print(f"error: {line}", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
    main()
