"""Step 8's targets beyond the ball's MPC, measured and profiled in one command.

Run on demand:  python benchmarks/bench_targets.py [--runs N] [--no-campaign] [--out DIR]

Measures, on this machine, what the issue's targets name and where the time goes:

* ``hmpc run scenarios/ball.toml`` (target <= 1.5 s with a warm cache): the command's wall
  time in fresh processes, and the same run split into its phases in one fresh process
  (imports, scenario, NLP transcription, ``nlpsol`` set-up, the loop's MPC solves,
  planner, log writing and the rest);
* the biped's walking MPC (target <= 25 ms median) and foothold planning (target
  <= 100 ms per planning step) on ``scenarios/biped_stairs.toml``: every IPOPT call's
  wall time, iterations and its split into function evaluations and IPOPT's own work
  (linear algebra: MUMPS), periodic re-solves apart from the planner's candidate solves;
* the ball's CEM plan (target <= 5 ms with the reference's parameters): plan time and
  the compiled rollout kernel's share;
* the Figure 3 campaign (``sweeps/fig3.toml``, 33 runs, 2 workers; target <= 20 s): wall
  time and how much of it the runs themselves account for.

Prints a report and writes it to ``<out>/targets.md`` (default ``results/bench``) with
the machine's description. Measured, never asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import suite_report

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BALL, BIPED, FIG3 = "scenarios/ball.toml", "scenarios/biped_stairs.toml", "sweeps/fig3.toml"
#: IPOPT's timing statistics of the function evaluations (CasADi's ``stats()`` keys)
EVALS = ("t_wall_nlp_f", "t_wall_nlp_g", "t_wall_nlp_grad_f", "t_wall_nlp_jac_g",
         "t_wall_nlp_hess_l")


def _median(xs) -> float:
    xs = list(xs)
    return statistics.median(xs) if xs else float("nan")


def _p95(xs) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, round(0.95 * (len(xs) - 1)))] if xs else float("nan")


# ----------------------------------------------------------------- hmpc run, ball
def command_walls(runs: int) -> list[float]:
    """Wall times [s] of ``hmpc run scenarios/ball.toml`` in fresh processes."""
    walls = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(runs):
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "hmpc_cli", "run", BALL, "--out",
                            f"{tmp}/{k}", "-q"], cwd=ROOT, check=True,
                           stdout=subprocess.DEVNULL)
            walls.append(time.perf_counter() - start)
    return walls


def phases() -> dict[str, float]:
    """One ``hmpc run`` of the ball in this (fresh) process, split into phases [s]."""
    t0 = time.perf_counter()
    import casadi as ca

    from hmpc_cli import cli  # noqa: F401  (what the command imports first)
    from hmpc_cli.mpc.chain import nlp as nlp_mod
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario
    out = {"imports": time.perf_counter() - t0}
    spent = {"nlpsol": 0.0, "transcription": 0.0}

    def timed(fn, key):
        def wrapper(*a, **kw):
            start = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                spent[key] += time.perf_counter() - start
        return wrapper

    ca.nlpsol = timed(ca.nlpsol, "nlpsol")
    cls = nlp_mod.FixedModeNLP
    cls._transcription = timed(cls._transcription, "transcription")
    t = time.perf_counter()
    sc, text = load_scenario(str(ROOT / BALL))
    out["scenario"] = time.perf_counter() - t
    t = time.perf_counter()
    loop = prepare(sc)
    out["build"] = time.perf_counter() - t
    out.update({f"build: {k}": v for k, v in spent.items()})
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        execute_run(loop, text, Path(tmp))
        out["run"] = time.perf_counter() - t
    out["run: MPC solves"] = sum(loop.books.solve_times)
    out["run: planner"] = sum(loop.books.plan_times)
    build = loop.identity.build
    out["build cache"] = json.dumps(dataclasses.asdict(build) if build is not None else None)
    return out


def run_section(runs: int) -> tuple[list[str], dict]:
    """The ``hmpc run`` section: walls, phases and the target line."""
    walls = command_walls(runs)
    child = subprocess.run([sys.executable, str(HERE / "bench_targets.py"), "--phases"],
                           cwd=ROOT, check=True, capture_output=True, text=True)
    ph = json.loads(child.stdout.strip().splitlines()[-1])
    ph["interpreter, CLI and exit (command median - the phases)"] = _median(walls) - sum(
        ph[k] for k in ("imports", "scenario", "build", "run"))
    total = _median(walls)
    lines = ["## `hmpc run scenarios/ball.toml` (target <= 1.5 s, warm cache)", "",
             f"Wall time of the command, {runs} fresh processes: median "
             f"**{_median(walls):.2f} s** (min {min(walls):.2f}, max {max(walls):.2f}).", "",
             "One run in a fresh process, by phase:", "", "| phase | s | share |",
             "|---|--:|--:|"]
    for k, v in ph.items():
        if isinstance(v, float):
            lines.append(f"| {k} | {v:.3f} | {v / total * 100:.0f} % |")
    rest = ph["run"] - ph["run: MPC solves"] - ph["run: planner"]
    floor = total - ph["build"]
    lines += ["", f"How the NLPs were built: `{ph.get('build cache')}`.", "",
              f"* target <= 1.5 s: {'met' if _median(walls) <= 1.5 else 'NOT met'}. "
              f"With the NLPs loaded compiled in ~0 s the run would still take about "
              f"{floor:.2f} s here (of which imports {ph['imports']:.2f} s, the loop "
              f"{ph['run']:.2f} s: MPC solves {ph['run: MPC solves']:.2f} s, planner "
              f"{ph['run: planner']:.2f} s, simulator, low level and log "
              f"{rest:.2f} s)."]
    return lines, {"walls": walls, "phases": ph}


# ------------------------------------------------------------------ biped
def biped_calls() -> tuple[list[dict], float, dict]:
    """Every IPOPT call of one biped_stairs run: (calls, build time [s], NLP size).

    Each call: ``planning`` (inside the foothold planner) or not, wall [s], iterations,
    and the time IPOPT's statistics give its function evaluations [s].
    """
    from hmpc_cli.mpc import solver as solver_mod
    from hmpc_cli.planner.footholds import FootholdPlanner
    from hmpc_cli.run.runner import prepare, run_unlogged
    from hmpc_cli.run.scenario import load_scenario

    calls: list[dict] = []
    state = {"planning": False}
    call, plan = solver_mod._call_instance, FootholdPlanner.plan

    def traced_call(instances, *args, **kw):
        res = call(instances, *args, **kw)
        warm = args[6] is not None and args[7] is not None
        st = instances[1 if warm else 0].stats()
        calls.append({"planning": state["planning"], "wall": res.stats.wall_time,
                      "iterations": res.stats.iterations,
                      "evals": sum(st.get(k, 0.0) for k in EVALS)})
        return res

    def traced_plan(self, *a, **kw):
        state["planning"] = True
        try:
            return plan(self, *a, **kw)
        finally:
            state["planning"] = False

    solver_mod._call_instance, FootholdPlanner.plan = traced_call, traced_plan
    try:
        sc, _ = load_scenario(str(ROOT / BIPED))
        start = time.perf_counter()
        loop = prepare(sc)
        build = time.perf_counter() - start
        run_unlogged(loop)
    finally:
        solver_mod._call_instance, FootholdPlanner.plan = call, plan
    nlp = getattr(loop.mpc, "nlp", None)
    size = {"variables": getattr(nlp, "nw", None), "constraints": getattr(nlp, "ng", None)}
    return calls, build, {"plan_times": list(loop.books.plan_times), **size}


def _split(calls: list[dict]) -> str:
    ms = [c["wall"] * 1e3 for c in calls]
    it = [c["iterations"] for c in calls]
    per = [c["wall"] * 1e3 / max(1, c["iterations"]) for c in calls]
    ev = sum(c["evals"] for c in calls) / max(1e-12, sum(c["wall"] for c in calls))
    return (f"| {len(calls)} | {_median(ms):.1f} | {_p95(ms):.1f} | {max(ms, default=0):.1f} "
            f"| {_median(it):.0f} | {_median(per):.2f} | {ev * 100:.0f} % |")


def biped_section() -> tuple[list[str], dict]:
    """The biped section: walking MPC re-solves and foothold planning steps."""
    calls, build, info = biped_calls()
    periodic = [c for c in calls if not c["planning"]]
    cands = [c for c in calls if c["planning"]]
    steps = [t * 1e3 for t in info["plan_times"]]
    per = _median(c["wall"] * 1e3 / max(1, c["iterations"]) for c in periodic)
    iters = _median(c["iterations"] for c in periodic)
    lines = ["## Biped (`scenarios/biped_stairs.toml`)", "",
             f"Walking NLP: {info['variables']} variables, {info['constraints']} "
             f"constraints; built in {build:.2f} s. IPOPT calls of one run:", "",
             "| calls | n | median ms | p95 ms | max ms | median iter | ms / iter | "
             "evaluations share |", "|---|--:|--:|--:|--:|--:|--:|--:|",
             f"| walking MPC (not planning) {_split(periodic)}",
             f"| foothold candidates {_split(cands)}", "",
             f"Foothold planning steps: {len(steps)}, median {_median(steps):.0f} ms, max "
             f"{max(steps, default=float('nan')):.0f} ms (the first, at t = 0, "
             f"{steps[0] if steps else float('nan'):.0f} ms: cold solves).", "",
             f"* walking MPC <= 25 ms median: "
             f"{'met' if _median(c['wall'] * 1e3 for c in periodic) <= 25 else 'NOT met'}"
             f" ({iters:.0f} IPOPT iterations x {per:.1f} ms; 25 ms needs "
             f"{25 / max(iters, 1):.1f} ms per iteration at that count, or "
             f"{25 / per:.1f} iterations at this cost).",
             f"* one foothold planning step <= 100 ms: "
             f"{'met' if max(steps, default=1e9) <= 100 else 'NOT met'} "
             f"({sum(x <= 100 for x in steps)} of {len(steps)} steps within it, median "
             f"{_median(steps):.0f} ms; each step solves one walking NLP per candidate "
             f"surface in reach, the first cold: the cold candidate's IPOPT iterations "
             f"x {_median(c['wall'] * 1e3 / max(1, c['iterations']) for c in cands):.1f} "
             f"ms set it)."]
    return lines, {"calls": calls, "build": build, **info}


# ------------------------------------------------------------------ ball CEM
def cem_section(plans: int = 20) -> tuple[list[str], dict]:
    """The ball's CEM plan from x0 (target <= 5 ms with the reference's parameters)."""
    from hmpc_cli.sim import rollout as rollout_c
    from hmpc_cli.planner.cem import CrossEntropyPlanner
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario

    sc, _ = load_scenario(str(ROOT / BALL))
    system, x0 = build_system(sc.system), np.asarray(sc.system.x0, dtype=float)
    kernel, cost = {"s": 0.0}, rollout_c.CRollout.cost

    def timed(self, *a, **kw):
        start = time.perf_counter()
        try:
            return cost(self, *a, **kw)
        finally:
            kernel["s"] += time.perf_counter() - start

    lines = ["## Ball CEM plan from x0 (target <= 5 ms, the reference's parameters)", "",
             "| planner.cost | backend | median ms | min ms | rollout kernel share |",
             "|---|---|--:|--:|--:|"]
    rollout_c.CRollout.cost = timed
    try:
        for kind in ("reference", "hmpc"):
            planner = CrossEntropyPlanner(system, sc.planner.model_copy(
                update={"cost": kind}), sc.seed)
            planner.plan(0.0, x0, 0)
            kernel["s"], walls = 0.0, []
            for _ in range(plans):
                start = time.perf_counter()
                planner.plan(0.0, x0, 0)
                walls.append(time.perf_counter() - start)
            lines.append(f"| {kind} | {planner.backend} | {_median(walls) * 1e3:.1f} | "
                         f"{min(walls) * 1e3:.1f} | {kernel['s'] / sum(walls) * 100:.0f} % |")
    finally:
        rollout_c.CRollout.cost = cost
    s = sc.planner
    lines += ["", f"{s.iterations} iterations x {s.samples + 1} rollouts of "
              f"{s.horizon * s.rollout_rate_hz:.0f} steps per plan, in the compiled C "
              "kernel (bit-identical to the NumPy rollouts)."]
    return lines, {}


# ------------------------------------------------------------ Figure 3 campaign
def _logged_times(logs) -> tuple[float, float]:
    """Total logged MPC solve and planner call wall times [s] of run logs."""
    from mcap.reader import make_reader

    total = {"/mpc/solve": 0.0, "/planner/plan": 0.0}
    for path in logs:
        with open(path, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(topics=list(total)):
                total[channel.topic] += json.loads(message.data)["wall_time"]
    return total["/mpc/solve"], total["/planner/plan"]


def campaign_section() -> tuple[list[str], dict]:
    """The Figure 3 campaign with 2 workers: wall time and the runs' own time."""
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "hmpc_cli", "sweep", FIG3, "--workers", "2",
                        "--out", tmp, "-q"], cwd=ROOT, check=True,
                       stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        runs = [json.loads(p.read_text()) for p in Path(tmp).glob("runs/*/summary.json")]
        solves, plans = _logged_times(Path(tmp).glob("runs/*/run.mcap"))
    inside = sum(r["wall_time"] for r in runs)
    lines = ["## Figure 3 campaign (`sweeps/fig3.toml`, 2 workers; target <= 20 s)", "",
             f"{len(runs)} runs in **{wall:.1f} s** wall. The runs' own loops: "
             f"{inside:.1f} s of CPU in all ({inside / 2:.1f} s per worker), of which MPC "
             f"solves {solves:.1f} s and CEM plans {plans:.1f} s (their logged times), "
             f"the rest simulator, low level and log; the rest of the wall time "
             f"({wall - inside / 2:.1f} s) is process start-up, NLP builds in each worker "
             f"and the sweep's bookkeeping.", "",
             f"* <= 20 s: {'met' if wall <= 20 else 'NOT met'}; even with zero start-up "
             f"the loops alone need {inside / 2:.1f} s on 2 workers."]
    return lines, {"wall": wall, "runs": len(runs), "inside": inside}


def main() -> None:
    """Runs the sections and writes ``targets.md``."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="fresh `hmpc run` processes")
    ap.add_argument("--no-campaign", action="store_true", help="skip the Figure 3 campaign")
    ap.add_argument("--out", default=str(ROOT / "results" / "bench"))
    ap.add_argument("--phases", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.phases:  # the child of run_section: one run's phases as JSON
        print(json.dumps(phases()))
        return
    git, load0, start = suite_report.git_describe(), os.getloadavg(), time.perf_counter()
    sections = [run_section(args.runs), biped_section(), cem_section()]
    if not args.no_campaign:
        sections.append(campaign_section())
    desc = suite_report.machine(sys.argv, load0, time.perf_counter() - start, (), (), git)
    head = ["# Step 8 targets beyond the ball's MPC: measured and profiled", "",
            f"Generated by `python benchmarks/bench_targets.py` on {desc['date_utc']} "
            f"(hmpc {desc['hmpc']}, git {git}); {desc['cpu']}, {desc['cores']} cores, "
            f"CasADi {desc['casadi']}; load average {desc['load_average_start']} at start, "
            f"{desc['load_average_end']} at end; {desc['suite_seconds']} s. The ball's MPC "
            "solves themselves: `backends.md`.", ""]
    text = "\n".join(head + [ln for lines, _ in sections for ln in [*lines, ""]])
    print(text)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "targets.md").write_text(text, encoding="utf-8")
    print(f"written: {Path(args.out) / 'targets.md'}")


if __name__ == "__main__":
    main()
