"""The walking MPC's IPOPT levers, side by side on the same recorded problems.

One run of scenarios/biped_stairs.toml records every walking-NLP solve (its start point,
parameters, bounds and multiplier guesses) and whether the foothold planner made it
(a candidate) or the period re-solve did. Each lever is a value of the walking MPC's
``mpc.solver_options``; it solves every recorded problem again in this process, on a
session built as the walking MPC builds its own (SX, cold and warm IPOPT instances), so
the levers compare like with like. Then each lever flies the scenario in closed loop.
The shipped session's solves are split into IPOPT's own time and its function
evaluations (CasADi's per-function statistics). With ``--compiled DIR`` every lever also
solves on the walking NLP's compiled library. Last, the scenario flies on each NLP
back-end of the walking MPC (``mpc.solver``; the stage-wise ones on their own
transcription, so not on the recorded problems): period re-solves, foothold candidates,
planning steps and the footholds against IPOPT's.

    python benchmarks/walking_levers.py --write results/bench/walking_levers.md
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from hmpc_cli.log.reader import read_log
from hmpc_cli.mpc import solver as solver_mod
from hmpc_cli.mpc.solver import SolverSession
from hmpc_cli.mpc.walking import nlp as walking_nlp
from hmpc_cli.run.runner import prepare, run_to_log, run_unlogged
from hmpc_cli.run.scenario import load_scenario
from hmpc_cli.sweep.table import toml_value
from bench_targets import EVALS, planning_flag, shown_command  # this script's directory
from realtime import machine

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "scenarios" / "biped_stairs.toml"
#: (lever, what it changes, the walking MPC's mpc.solver_options)
LEVERS: list[tuple[str, str, dict]] = [
    ("shipped", "IPOPT as the walking MPC builds it (adaptive barrier, MUMPS)", {}),
    ("monotone barrier", 'mu_strategy = "monotone"', {"ipopt": {"mu_strategy": "monotone"}}),
    ("warm mu 1e-6", "the warm instance's mu_init 1e-6 (shipped 1e-4)",
     {"ipopt_warm": {"mu_init": 1e-6}}),
    ("MUMPS unscaled", "mumps_permuting_scaling = 0, mumps_scaling = 0",
     {"ipopt": {"mumps_permuting_scaling": 0, "mumps_scaling": 0}}),
    ("SPRAL", 'linear_solver = "spral"', {"ipopt": {"linear_solver": "spral"}}),
    ("L-BFGS Hessian", 'hessian_approximation = "limited-memory"',
     {"ipopt": {"hessian_approximation": "limited-memory"}}),
    ("3 iterations", "max_iter = 3 (what 15 ms allows at the shipped cost per iteration)",
     {"ipopt": {"max_iter": 3}}),
    ("MUMPS without matching", "mumps_permuting_scaling = 0 (MUMPS's scaling kept)",
     {"ipopt": {"mumps_permuting_scaling": 0}}),
    ("probing barrier", 'mu_oracle = "probing" (adaptive barrier)',
     {"ipopt": {"mu_oracle": "probing"}}),
    ("both", "mumps_permuting_scaling = 0 and mu_oracle = \"probing\"",
     {"ipopt": {"mumps_permuting_scaling": 0, "mu_oracle": "probing"}}),
]
def record(duration: float) -> tuple[dict, list[tuple[bool, tuple]], dict]:
    """(the NLP in SX, [(a candidate, solve arguments)], the run's outcome)."""
    keep: dict = {}
    session = walking_nlp.WalkingNLP._session
    state = {"planning": False}

    def kept_session(self, nlp):
        keep["nlp"], keep["settings"] = nlp, self.s
        built = session(self, nlp)
        source = built[0]._nlp  # the library's path when the build cache held it compiled
        keep["library"] = source if isinstance(source, str) else None
        return built

    walking_nlp.WalkingNLP._session = kept_session
    try:
        sc, _ = load_scenario(SCENARIO, [f"sim.duration={duration}"])
        run = prepare(sc)
        problems: list[tuple[bool, tuple]] = []
        call = run.mpc.nlp.session.run

        def traced_run(*args):
            problems.append((state["planning"], tuple(
                None if a is None else np.array(a, dtype=float) for a in args)))
            return call(*args)

        run.mpc.nlp.session.run = traced_run
        try:
            with planning_flag(state):
                result = run_unlogged(run)
        finally:  # the NLP is shared by later runs of these settings in this process
            del run.mpc.nlp.session.run
    finally:
        walking_nlp.WalkingNLP._session = session
    return keep, problems, {"success": result.success, "t_end": result.t_end}


def session_of(keep: dict, extra: dict, compiled: bool = False) -> SolverSession:
    """A session built as the walking MPC builds its own, with ``extra`` options.

    ``compiled``: on the compiled library the recorded run loaded, else in SX.
    """
    s = keep["settings"]
    source = keep["library"] if compiled else keep["nlp"]
    return SolverSession("walking_lever", source, "ipopt", max_iter=s.max_iter,
                         tol=s.tol, max_wall_time=s.max_wall_time,
                         extra={**s.solver_options, **extra}, warm=walking_nlp.WARM_START)


def replay(sessions: dict[str, SolverSession], problems: list, reps: int
           ) -> dict[str, list[dict]]:
    """Every recorded problem solved ``reps`` times by every session, interleaved (one
    problem by each session in turn): per session, the fastest wall time of each."""
    out: dict[str, list[dict]] = {name: [] for name in sessions}
    evals: list[float] = []
    call = solver_mod._call_instance

    def traced(instances, *args, **kw):
        res = call(instances, *args, **kw)
        st = instances[1 if args[6] is not None and args[7] is not None else 0].stats()
        evals.append(sum(st.get(k, 0.0) for k in EVALS))
        return res

    solver_mod._call_instance = traced
    try:
        for rep in range(reps):
            for i, (cand, args) in enumerate(problems):
                for name, session in sessions.items():
                    evals.clear()
                    res = session.run(*args)
                    row = {"candidate": cand, "wall": res.stats.wall_time,
                           "iterations": res.stats.iterations,
                           "success": res.stats.success, "evals": sum(evals), "x": res.x}
                    if rep == 0:
                        out[name].append(row)
                    elif row["wall"] < out[name][i]["wall"]:
                        out[name][i] = row
    finally:
        solver_mod._call_instance = call
    return out


def closed_loop(extra: dict, duration: float) -> dict:
    """The scenario flown with the lever's options: outcome and footholds (its log)."""
    sets = [f"mpc.solver_options={toml_value(extra)}"] if extra else []
    with tempfile.TemporaryDirectory() as tmp:
        return backend_run(sets, duration, Path(tmp))


#: (back-end, the walking MPC's overrides): the same scenario on each NLP back-end
BACKENDS: list[tuple[str, list[str]]] = [
    ("ipopt (shipped)", []),
    ("fatrop", ['mpc.solver="fatrop"']),
    ("sqp_hpipm, 10 SQP steps", ['mpc.solver="sqp_hpipm"', "mpc.max_sqp_iter=10"]),
    ("rti (1 SQP step)", ['mpc.solver="rti"']),
    ("rti, 2 SQP steps", ['mpc.solver="rti"', "mpc.max_sqp_iter=2"]),
]


def backend_run(sets: list[str], duration: float, work: Path) -> dict:
    """One closed-loop run on a back-end, read back from its log (time paused)."""
    sc, _ = load_scenario(SCENARIO, [f"sim.duration={duration}", *sets])
    result = run_to_log(prepare(sc), work / "run.mcap")
    log = read_log(work / "run.mcap")
    solves = [m.data for m in log.topic("/mpc/solve")]
    plans = [m.data for m in log.topic("/planner/plan")]
    return {"success": result.success, "reason": result.reason, "t_end": result.t_end,
            "period": [(d["wall_time"], d["iterations"]) for d in solves
                       if d["reason"] == "period"],
            "fallbacks": sum("fallback" in str(d["status"]) for d in solves),
            "candidates": [c["wall_time"] for d in plans
                           for c in (d.get("detail") or {}).get("candidates", [])],
            "steps": [d["wall_time"] for d in plans],
            "footholds": [(m.data["guard"], m.data["x_after"]["stance_x"])
                          for m in log.topic("/sim/event")]}


def backend_lines(duration: float) -> list[str]:
    """The back-ends table: period re-solves, candidates, planning steps, footholds."""
    rows = {}
    for name, sets in BACKENDS:
        with tempfile.TemporaryDirectory() as tmp:
            rows[name] = backend_run(sets, duration, Path(tmp))
    ref = rows[BACKENDS[0][0]]["footholds"]
    lines = ["", "## The walking NLP's back-ends, closed loop", "",
             f"`scenarios/biped_stairs.toml` ({duration:g} s, time paused) with "
             "`mpc.solver` set; fatrop, sqp_hpipm and rti solve the stage-wise "
             "transcription (sqp_hpipm and rti with the Gauss-Newton Hessian of the "
             "system's `stage_residuals`). Targets: period re-solves' median <= 15 ms, "
             "every foothold planning step <= 100 ms.", "",
             "| back-end | outcome | period median ms | period p95 ms | period median iter "
             "| IPOPT fallbacks | candidate median ms | planning steps | first step ms | "
             "slowest step ms | footholds (contact surfaces in order) |",
             "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|---|"]
    for name, r in rows.items():
        walls = [w for w, _ in r["period"]]
        its = [i for _, i in r["period"]]
        steps = r["steps"]
        same = [g for g, _ in r["footholds"]] == [g for g, _ in ref]
        feet = f"surfaces {' '.join(str(g) for g, _ in r['footholds'])}" + (
            f" (ipopt's; touchdowns within "
            f"{max(abs(a[1] - b[1]) for a, b in zip(r['footholds'], ref, strict=True)):.4f} m)"
            if same and r is not rows[BACKENDS[0][0]] else "")
        outcome = "climbs" if r["success"] else f"{r['reason']} (t = {r['t_end']:.2f} s)"
        lines.append(f"| {name} | {outcome} | {_ms(walls, 50)} | {_ms(walls, 95)} | "
                     f"{np.median(its) if its else float('nan'):.0f} | {r['fallbacks']} | "
                     f"{_ms(r['candidates'], 50)} | {len(steps)} | "
                     f"{steps[0] * 1e3 if steps else float('nan'):.1f} | "
                     f"{max(steps, default=float('nan')) * 1e3:.1f} | {feet} |")
    return lines


def _ms(values, q: float) -> str:
    return f"{np.percentile(values, q) * 1e3:.1f}" if len(values) else "-"


def _loop_text(loop: dict, shipped: dict) -> str:
    """A closed loop's outcome and its footholds against the shipped options' flight."""
    if not loop["success"]:
        return f"{loop['reason']} (t = {loop['t_end']:.2f} s)"
    feet, ref = loop["footholds"], shipped["footholds"]
    if loop is shipped:
        return f"climbs: surfaces {' '.join(str(g) for g, _ in feet)}"
    if [g for g, _ in feet] != [g for g, _ in ref]:
        return f"climbs, other footholds: surfaces {' '.join(str(g) for g, _ in feet)}"
    gap = max(abs(a[1] - b[1]) for a, b in zip(feet, ref, strict=True))
    return f"climbs, the shipped surfaces (touchdowns within {gap:.1e} m)"


def lever_row(name: str, what: str, rows: list[dict], ref: list[dict], loop: str) -> str:
    period = [r for r in rows if not r["candidate"]]
    cands = [r for r in rows if r["candidate"]]
    pw = [r["wall"] for r in period]
    cw = [r["wall"] for r in cands]
    its = [r["iterations"] for r in period]
    per = sum(pw) / max(1, sum(its))
    ok = sum(r["success"] for r in rows)
    both = [(r, s) for r, s in zip(rows, ref, strict=True) if r["success"] and s["success"]]
    dev = max((float(np.abs(r["x"] - s["x"]).max()) for r, s in both), default=float("nan"))
    return (f"| {name} | {what} | {ok}/{len(rows)} | {_ms(pw, 50)} | {_ms(pw, 95)} | "
            f"{np.median(its):g} | {per * 1e3:.2f} | {_ms(cw, 50)} | {_ms(cw, 95)} | "
            f"{dev:.1e} | {loop} |")


def _where_time_goes(label: str, rows: list[dict]) -> str:
    period = [r for r in rows if not r["candidate"]]
    wall = sum(r["wall"] for r in period)
    ev = sum(r["evals"] for r in period)
    its = sum(r["iterations"] for r in period)
    return (f"Where the {label} period re-solves' time goes: {wall * 1e3:.0f} ms over "
            f"{len(period)} solves and {its} iterations; function evaluations "
            f"{ev * 1e3:.0f} ms ({ev / wall * 100:.0f} %), IPOPT's own work (MUMPS, the "
            f"barrier update, the line search) and CasADi's call {(wall - ev) * 1e3:.0f} ms "
            f"({(wall - ev) / wall * 100:.0f} %): {(wall - ev) / max(its, 1) * 1e3:.2f} ms "
            "per iteration before any evaluation.")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=2.5, help="simulated time [s]")
    ap.add_argument("--reps", type=int, default=2, help="solves per problem (fastest kept)")
    ap.add_argument("--levers", default="", help="comma-separated lever names (default: all)")
    ap.add_argument("--no-backends", action="store_true",
                    help="leave out the closed-loop runs on the other NLP back-ends")
    ap.add_argument("--compiled", metavar="DIR", help="a cache directory holding the "
                    "walking NLP compiled (HMPC_BUILD_CACHE=sync once): every lever solves "
                    "on it too, and the closed loops fly on it (the same numbers as SX)")
    ap.add_argument("--write", type=Path, help="write the Markdown report here")
    args = ap.parse_args()
    if args.compiled:
        os.environ["HMPC_CACHE_DIR"] = str(Path(args.compiled).resolve())
    chosen = [lv for lv in LEVERS if not args.levers or lv[0] in args.levers.split(",")]
    keep, problems, outcome = record(args.duration)
    if args.compiled and keep["library"] is None:
        ap.error(f"--compiled {args.compiled}: no compiled walking NLP there for these "
                 "sources (make it with HMPC_BUILD_CACHE=sync hmpc run "
                 "scenarios/biped_stairs.toml)")
    sources = [("", False)] + ([(", compiled", True)] if args.compiled else [])
    sessions = {name + tag: session_of(keep, extra, comp)
                for name, _, extra in chosen for tag, comp in sources}
    results = replay(sessions, problems, args.reps)
    loops = {name: closed_loop(extra, args.duration) for name, _, extra in chosen}
    shipped = chosen[0][0]
    n_period = sum(not c for c, _ in problems)
    lines = ["# The walking MPC's IPOPT levers, side by side", "",
             "Generated by "
             f"`{shown_command('walking_levers.py', sys.argv[1:])}` "
             f"on {machine()} (solve times are machine dependent).", "",
             f"`scenarios/biped_stairs.toml`, {args.duration:g} s, recorded once "
             f"({'climbs' if outcome['success'] else 'fails'}): {len(problems)} walking-NLP "
             f"solves, {n_period} period re-solves and {len(problems) - n_period} foothold "
             "candidates. Every lever solves the same recorded problems (NLP in SX"
             + (", and on its compiled library: the rows marked compiled" if args.compiled
                else "") + f"; the fastest of {args.reps}, the levers taking turns on each "
             "problem), then flies the scenario in closed loop (the footholds compared "
             "with the shipped options' flight). Target: the period re-solves' median "
             "<= 15 ms.", "",
             "| lever | what | solved | period median ms | period p95 ms | period median "
             "iter | ms / iter | candidate median ms | candidate p95 ms | max abs(x - "
             "shipped x) | closed loop |",
             "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|---|"]
    lines += [lever_row(name + tag, what, results[name + tag], results[shipped + tag],
                        _loop_text(loops[name], loops[shipped]))
              for tag, _ in sources for name, what, _ in chosen]
    lines += ["", _where_time_goes("shipped", results[shipped])]
    if args.compiled:
        lines += ["", _where_time_goes("compiled shipped", results[shipped + ", compiled"])]
    if not args.no_backends:
        lines += backend_lines(args.duration)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.write:
        args.write.write_text(text)


if __name__ == "__main__":
    main()
