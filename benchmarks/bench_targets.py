"""Step 11's targets beyond the ball's MPC solves, measured and profiled in one command.

Run on demand:  python benchmarks/bench_targets.py [--runs N] [--no-campaign]
                [--compiled DIR] [--out DIR]

Measures, on this machine, what the issue's targets name and where the time goes, for a
fresh install (an empty cache directory: the NLPs built in SX, the CEM's C rollout
compiled on the first run) and, with ``--compiled DIR``, for a cache directory that holds
the ball's and the biped's NLPs compiled (made once with ``HMPC_BUILD_CACHE=sync``):

* ``hmpc run scenarios/ball.toml`` (targets: fresh <= 2.0 s, warm <= 1.0 s): the
  command's wall time in fresh processes, each with a new empty cache (fresh), then again
  in one cache holding the stage kernels (warm, the default ``HMPC_BUILD_CACHE=use``: no
  NLP compiled), and in the compiled cache; one run split into its phases (imports,
  scenario, the NLPs' build: SX transcription, assembly from stage kernels, ``nlpsol``
  set-up; the loop's MPC solves, planner, the rest);
* the biped (targets: walking MPC <= 15 ms median, every foothold planning step <= 100 ms
  the first included, the walker climbs with ``sim.latency = "model"`` at its default
  rate): every IPOPT call's wall time, iterations and its split into function
  evaluations and IPOPT's own work, the planning steps, and the runs with the modelled
  compute time charged (``scenarios/biped_realtime.toml``, and ``biped_stairs.toml``
  with the paper's settings); the same for the walking MPC on real-time iterations
  (``mpc.solver = "rti"``; charged run ``scenarios/biped_rti.toml``);
* the Figure 3 campaign (``sweeps/fig3.toml``, 33 runs, 2 workers, time paused; target
  <= 15 s): wall time and how much of it the runs themselves account for;
* the ball's CEM plan (Step 8's target <= 5 ms): plan time, the rollout kernel's share.

Prints a report and writes it to ``<out>/targets.md`` (default ``results/bench``) with
the machine's description. Measured, never asserted.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import suite_report

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BALL, BIPED, FIG3 = "scenarios/ball.toml", "scenarios/biped_stairs.toml", "sweeps/fig3.toml"
BIPED_RT = "scenarios/biped_realtime.toml"
BIPED_RTI = "scenarios/biped_rti.toml"
#: the walking MPC's configurations: (overrides of BIPED, the charged runs, its steps)
BIPED_VARIANTS = {
    "ipopt": ([], (("stairs", BIPED), ("realtime", BIPED_RT)), "IPOPT iterations"),
    "rti": (['mpc.solver="rti"'], (("rti", BIPED_RTI),), "SQP steps"),
}
#: IPOPT's timing statistics of the function evaluations (CasADi's ``stats()`` keys)
EVALS = ("t_wall_nlp_f", "t_wall_nlp_g", "t_wall_nlp_grad_f", "t_wall_nlp_jac_g",
         "t_wall_nlp_hess_l", "t_wall_nlp_grad",
         "t_wall_nlp_fg", "t_wall_nlp_jac_fg")  # the last two: sqpmethod's (rti)


def shown_command(script: str, argv: Sequence[str]) -> str:
    """``python benchmarks/<script> <argv>`` as a report shows it: ``--compiled``'s
    directory as DIR."""
    out = list(argv)
    for i, a in enumerate(out):
        if a == "--compiled" and i + 1 < len(out):
            out[i + 1] = "DIR"
        elif a.startswith("--compiled="):
            out[i] = "--compiled=DIR"
    return shlex.join(["python", f"benchmarks/{script}", *out])


def _median(xs) -> float:
    xs = list(xs)
    return statistics.median(xs) if xs else float("nan")


def _p95(xs) -> float:
    xs = sorted(xs)
    return xs[min(len(xs) - 1, round(0.95 * (len(xs) - 1)))] if xs else float("nan")


# ----------------------------------------------------------------- hmpc run, ball
#: the build step of the CEM's C rollout kernel, as :func:`phases` names it
KERNEL = "CEM's C rollout kernel"
#: the kernel's compile, in a thread beside the NLP build (not a phase of the command)
BACKGROUND = f"beside the build: {KERNEL} compiled in the background"
#: the first plan's wait for a kernel still compiling (part of the run's loop)
WAIT = f"run: the first plan's wait for the {KERNEL}"


def _env(cache: str) -> dict:
    """This process's environment with ``HMPC_CACHE_DIR`` = cache (default cache mode)."""
    # without PYTHONDONTWRITEBYTECODE: imports from cached bytecode, as a user's run has them
    env = {k: v for k, v in os.environ.items()
           if k not in ("HMPC_BUILD_CACHE", "PYTHONDONTWRITEBYTECODE")}
    return {**env, "HMPC_CACHE_DIR": cache}


def command_walls(runs: int, cache: str | None) -> list[float]:
    """Wall times [s] of ``hmpc run scenarios/ball.toml`` in fresh processes.

    ``cache``: the cache directory every process uses (None: a new empty one each).
    """
    walls = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(runs):
            env = _env(cache or tempfile.mkdtemp(dir=tmp))
            start = time.perf_counter()
            subprocess.run([sys.executable, "-m", "hmpc_cli", "run", BALL, "--out",
                            f"{tmp}/{k}", "-q"], cwd=ROOT, check=True, env=env,
                           stdout=subprocess.DEVNULL)
            walls.append(time.perf_counter() - start)
    return walls


def phases(sets: Sequence[str] = ()) -> dict[str, float]:
    """One ``hmpc run`` of the ball in this (fresh) process, split into phases [s].

    ``sets``: scenario overrides (``key=value``, as ``--set``). The timers wrapped around
    CasADi's and hmpc's functions are taken off again before it returns.
    """
    t0 = time.perf_counter()
    import casadi as ca

    from hmpc_cli import cli  # noqa: F401  (what the command imports first)
    from hmpc_cli.mpc.chain import nlp as nlp_mod
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.mpc.staged import StagedNLP
    from hmpc_cli.sim import rollout
    out = {"imports": time.perf_counter() - t0}
    spent = {"nlpsol": 0.0, "transcription": 0.0, ASSEMBLY: 0.0, KERNEL: 0.0}

    def timed(fn, key):
        def wrapper(*a, **kw):
            start = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                spent[key] += time.perf_counter() - start
        return wrapper

    cls = nlp_mod.FixedModeNLP
    # the command's own time for the kernel: starting its compile (and loading a cached
    # one) in the build, waiting for it at the first plan in the run
    wrapped = [(ca, "nlpsol", "nlpsol"), (cls, "_transcription", "transcription"),
               (StagedNLP, "nlp", ASSEMBLY), (StagedNLP, "derivatives", ASSEMBLY),
               (rollout, "start_library", KERNEL), (rollout.LibraryBuild, "result", KERNEL)]
    originals = [(owner, name, getattr(owner, name)) for owner, name, _ in wrapped]
    for owner, name, key in wrapped:
        setattr(owner, name, timed(getattr(owner, name), key))
    try:
        t = time.perf_counter()
        sc, text = load_scenario(str(ROOT / BALL), list(sets))
        out["scenario"] = time.perf_counter() - t
        t = time.perf_counter()
        loop = prepare(sc)
        out["build"] = time.perf_counter() - t
        out.update({f"build: {k}": v for k, v in spent.items()})
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            execute_run(loop, text, Path(tmp))
            out["run"] = time.perf_counter() - t
    finally:
        for owner, name, original in originals:
            setattr(owner, name, original)
    out["run: MPC solves"] = float(sum(loop.books.solve_times))
    out["run: planner"] = float(sum(loop.books.plan_times))
    # the first plan waits for a kernel still compiling (outside its own timer)
    out[WAIT] = spent[KERNEL] - out[ROLLOUT]
    c_rollout = getattr(loop.planner, "_c", None)
    out[BACKGROUND] = float(getattr(c_rollout, "compile_seconds", None) or 0.0)
    build = loop.identity.build
    out["build cache"] = json.dumps(dataclasses.asdict(build) if build is not None else None)
    return out


def prime() -> None:
    """Compiles the ball's NLPs' stage kernels into this process's cache, waiting for each
    (a sweep's process does the same: :func:`hmpc_cli.mpc.kernels.wait_for_compiles`)."""
    from hmpc_cli.mpc import kernels
    from hmpc_cli.run.runner import prepare
    from hmpc_cli.run.scenario import load_scenario

    kernels.wait_for_compiles()
    prepare(load_scenario(str(ROOT / BALL))[0])


def _child(flag: str, cache: str) -> dict:
    """This script's ``flag`` section in a fresh process with ``cache``; its JSON."""
    child = subprocess.run([sys.executable, str(HERE / "bench_targets.py"), flag],
                           cwd=ROOT, check=True, capture_output=True, text=True,
                           env=_env(cache))
    return json.loads(child.stdout.strip().splitlines()[-1])


def _phases(runs: int, cache: str | None, command: list[float]) -> dict:
    """Per phase, the median over ``runs`` fresh processes of :func:`phases` [s].

    ``cache``: the cache directory of every process (None: a new empty one each). The
    phases' sum is subtracted from the median of ``command`` (the command's walls) for
    what the interpreter, the CLI and the exit take.
    """
    with tempfile.TemporaryDirectory() as tmp:
        each = [_child("--phases", cache or tempfile.mkdtemp(dir=tmp)) for _ in range(runs)]
    ph = {k: (_median(p[k] for p in each) if isinstance(v, float) else v)
          for k, v in each[0].items()}
    ph[REST] = _median(command) - sum(ph[k] for k in ("imports", "scenario", "build", "run"))
    return ph


#: the build's phase of IPOPT's functions assembled from stage kernels (their SX, or their
#: C libraries loaded)
ASSEMBLY = "cost, rows and derivatives from stage kernels"
#: the phase left when the measured ones are taken from the command's wall time
REST = "interpreter, CLI and exit (command median - the phases)"


def _walls_text(walls: list[float]) -> str:
    return (f"median **{_median(walls):.2f} s** (min {min(walls):.2f}, max "
            f"{max(walls):.2f}, {len(walls)} processes)")


#: the phase of the CEM's C rollout kernel build (a fresh cache compiles it): the
#: command's own time in the build (starting the compile, or loading a cached library)
ROLLOUT = f"build: {KERNEL}"
_COLUMNS = ("fresh install", "warm", "NLPs compiled")


def _phase_table(phs: list[dict], totals: list[float]) -> list[str]:
    """Phases [s] and shares of the command's median, one column pair per case."""
    cols = _COLUMNS[:len(phs)]
    lines = ["| phase | " + " | ".join(f"{c} s | share" for c in cols) + " |",
             "|---|" + "--:|--:|" * len(cols)]
    lines += [f"| {k} | " + " | ".join(f"{ph[k]:.3f} | {ph[k] / t * 100:.0f} %"
                                       for ph, t in zip(phs, totals, strict=True)) + " |"
              for k, v in phs[0].items() if isinstance(v, float)]
    lines += ["| the command (median) | " + " | ".join(f"{t:.3f} | 100 %" for t in totals)
              + " |", ""]
    return lines + [f"How the NLPs were built ({c}): `{ph.get('build cache')}`."
                    for c, ph in zip(cols, phs, strict=True)]


def _verdict(value: float, target: float, unit: str = "s") -> str:
    """Whether a lower bound of a time (``unit``) leaves the target reachable."""
    return ("above the target" if value > target
            else f"under the target by {target - value:.2f} {unit}")


def run_section(runs: int, compiled: str | None) -> tuple[list[str], dict]:
    """The ``hmpc run`` section: fresh, warm and compiled walls, phases, target lines."""
    fresh = command_walls(runs, None)
    fph = _phases(runs, None, fresh)
    with tempfile.TemporaryDirectory() as cache:
        command_walls(1, cache)  # the first run: the CEM's C rollout compiled
        subprocess.run([sys.executable, str(HERE / "bench_targets.py"), "--prime"], cwd=ROOT,
                       check=True, env=_env(cache))  # the kernels that run had no time for
        warm = command_walls(runs, cache)
        ph = _phases(runs, cache, warm)
    lines = ["## `hmpc run scenarios/ball.toml` (targets: fresh install <= 2.0 s, warm "
             "<= 1.0 s)", "",
             f"* Fresh install (each process a new, empty cache directory): {_walls_text(fresh)}.",
             f"* Warm (one cache directory holding the CEM's C rollout kernel and the "
             f"NLPs' stage kernels: a first run compiled the rollout and the kernels it had "
             f"time for, a process waiting for them the rest, as a third run finds them; "
             f"the default `HMPC_BUILD_CACHE=use` compiles no NLP and stores no "
             f"transcription): {_walls_text(warm)}."]
    out = {"fresh": fresh, "warm": warm, "fresh_phases": fph, "phases": ph}
    if compiled:
        comp = command_walls(runs, compiled)
        out.update(compiled=comp, compiled_phases=_phases(runs, compiled, comp))
        lines.append(f"* The NLPs compiled (`--compiled`: made once with "
                     f"`HMPC_BUILD_CACHE=sync`, minutes of CPU and GBs of memory): "
                     f"{_walls_text(comp)}.")
    lines += ["", f"By phase, medians of {runs} processes each (a fresh install, warm"
              + (", the NLPs compiled" if compiled else "") + "):", "",
              *_phase_table([fph, ph] + ([out["compiled_phases"]] if compiled else []),
                            [_median(fresh), _median(warm)]
                            + ([_median(out["compiled"])] if compiled else []))]
    best = out["compiled_phases"] if compiled else ph
    floor = sum(best[k] for k in ("imports", "scenario", "run")) + best[REST]
    rest = best["run"] - best["run: MPC solves"] - best["run: planner"]
    lines += ["", f"* fresh <= 2.0 s: {'met' if _median(fresh) <= 2.0 else 'NOT met'} "
              f"({_median(fresh):.2f} s; its build: {fph['build']:.2f} s, of which the "
              f"transcription {fph['build: transcription']:.2f} s, the assembly from stage "
              f"kernels {fph['build: ' + ASSEMBLY]:.2f} s, `nlpsol` "
              f"{fph['build: nlpsol']:.2f} s and the CEM's C rollout kernel "
              f"{fph[ROLLOUT]:.2f} s: compiled in {fph[BACKGROUND]:.2f} s beside the NLP "
              f"build, the first plan waiting {fph[WAIT]:.2f} s for it).",
              f"* warm <= 1.0 s: {'met' if _median(warm) <= 1.0 else 'NOT met'} by default "
              f"({_median(warm):.2f} s)"
              + (f"; {'met' if _median(out['compiled']) <= 1.0 else 'NOT met'} with the NLPs "
                 f"compiled ({_median(out['compiled']):.2f} s)" if compiled else "")
              + f". The run's own MPC solves ({ph['run: MPC solves']:.2f} s, IPOPT's "
              f"iterates fixed by the committed tables) and the build "
              f"({ph['build']:.2f} s) add up to "
              f"{ph['run: MPC solves'] + ph['build']:.2f} s: "
              f"{_verdict(ph['run: MPC solves'] + ph['build'], 1.0)}, before "
              f"anything else runs. "
              f"With no NLP build at all a run still takes {floor:.2f} s here: imports "
              f"{best['imports']:.2f} s, the scenario {best['scenario']:.2f} s, the loop "
              f"{best['run']:.2f} s (MPC solves "
              f"{best['run: MPC solves']:.2f} s, planner {best['run: planner']:.2f} s, "
              f"simulator, low level and log {rest:.2f} s), "
              f"interpreter, CLI and exit {best[REST]:.2f} s."]
    return lines, out


# ------------------------------------------------------------------ biped
@contextlib.contextmanager
def planning_flag(state: dict) -> Iterator[None]:
    """Inside, the foothold planner sets ``state["planning"]`` while it plans (restored)."""
    from hmpc_cli.planner.footholds import FootholdPlanner

    plan = FootholdPlanner.plan

    def traced_plan(self, *a, **kw):
        state["planning"] = True
        try:
            return plan(self, *a, **kw)
        finally:
            state["planning"] = False

    FootholdPlanner.plan = traced_plan
    try:
        yield
    finally:
        FootholdPlanner.plan = plan


def biped_calls(variant: str = "ipopt", sets: Sequence[str] = ()) -> dict:
    """Every NLP solver call of one biped_stairs run, the build time and the NLP's size.

    ``variant``: a key of :data:`BIPED_VARIANTS` (the walking MPC's back-end). Each call:
    ``planning`` (inside the foothold planner) or not, wall [s], iterations, and the time
    the solver's statistics give its function evaluations [s]. Then the variant's charged
    runs (``model`` latency), whose calls are not recorded. ``sets``: scenario overrides
    (``key=value``) of every run, after the variant's.
    """
    from hmpc_cli.mpc import solver as solver_mod
    from hmpc_cli.run.runner import prepare, run_unlogged
    from hmpc_cli.run.scenario import load_scenario

    calls: list[dict] = []
    state = {"planning": False}
    call = solver_mod._call_instance

    def traced_call(instances, *args, **kw):
        res = call(instances, *args, **kw)
        warm = args[6] is not None and args[7] is not None
        st = instances[1 if warm else 0].stats()
        calls.append({"planning": state["planning"], "wall": res.stats.wall_time,
                      "iterations": res.stats.iterations,
                      "evals": sum(st.get(k, 0.0) for k in EVALS)})
        return res

    variant_sets, charged_runs, unit = BIPED_VARIANTS[variant]
    sc, _ = load_scenario(str(ROOT / BIPED), [*variant_sets, *sets])
    start = time.perf_counter()
    loop = prepare(sc)
    build = time.perf_counter() - start
    solver_mod._call_instance = traced_call
    try:
        with planning_flag(state):
            run_unlogged(loop)
    finally:
        solver_mod._call_instance = call
    nlp = getattr(loop.mpc, "nlp", None)
    charged = {}
    for key, scenario in charged_runs:
        model, _ = load_scenario(str(ROOT / scenario), ['sim.latency="model"', *sets])
        r = run_unlogged(prepare(model))
        charged[key] = {"success": r.success, "reason": r.reason, "t_end": r.t_end}
    info = loop.identity.build
    return {"calls": calls, "build": build, "plan_times": list(loop.books.plan_times),
            "variables": getattr(nlp, "nw", None), "constraints": getattr(nlp, "ng", None),
            "build cache": dataclasses.asdict(info) if info is not None else None,
            "model": charged, "unit": unit}


def _split(calls: list[dict]) -> str:
    ms = [c["wall"] * 1e3 for c in calls]
    it = [c["iterations"] for c in calls]
    per = [c["wall"] * 1e3 / max(1, c["iterations"]) for c in calls]
    ev = sum(c["evals"] for c in calls) / max(1e-12, sum(c["wall"] for c in calls))
    return (f"| {len(calls)} | {_median(ms):.1f} | {_p95(ms):.1f} | {max(ms, default=0):.1f} "
            f"| {_median(it):.0f} | {_median(per):.2f} | {ev * 100:.0f} % |")


def _biped_lines(label: str, info: dict) -> list[str]:
    calls = info["calls"]
    periodic = [c for c in calls if not c["planning"]]
    cands = [c for c in calls if c["planning"]]
    steps = [t * 1e3 for t in info["plan_times"]]
    med = _median(c["wall"] * 1e3 for c in periodic)
    per = _median(c["wall"] * 1e3 / max(1, c["iterations"]) for c in periodic)
    iters = _median(c["iterations"] for c in periodic)
    own = _median((c["wall"] - c["evals"]) * 1e3 / max(1, c["iterations"]) for c in periodic)
    own_call = _median((c["wall"] - c["evals"]) * 1e3 for c in periodic)  # <= med, call by call
    model, unit = info["model"], info.get("unit", "IPOPT iterations")
    if "rti" in model:
        climbs = (f"{'met' if model['rti']['success'] else 'NOT met'} with `{BIPED_RTI}` "
                  f"(ends at t = {model['rti']['t_end']:.3f} s: {model['rti']['reason']}).")
    else:
        climbs = (f"{'met' if model['realtime']['success'] else 'NOT met'} with `{BIPED_RT}` "
                  f"(ends at t = {model['realtime']['t_end']:.3f} s: "
                  f"{model['realtime']['reason']}; `{BIPED}`, the first plan charged and the "
                  f"guard node held after impacts: ends at t = {model['stairs']['t_end']:.3f} "
                  f"s: {model['stairs']['reason']}).")
    return [f"### {label}", "",
            f"Walking NLP: {info['variables']} variables, {info['constraints']} "
            f"constraints; built in {info['build']:.2f} s (`{info['build cache']}`). Solver "
            "calls of one run:", "",
            "| calls | n | median ms | p95 ms | max ms | median iter | ms / iter | "
            "evaluations share |", "|---|--:|--:|--:|--:|--:|--:|--:|",
            f"| walking MPC (not planning) {_split(periodic)}",
            f"| foothold candidates {_split(cands)}", "",
            f"Foothold planning steps: {len(steps)}, median {_median(steps):.0f} ms, max "
            f"{max(steps, default=float('nan')):.0f} ms (the first, at t = 0: "
            f"{steps[0] if steps else float('nan'):.0f} ms).", "",
            f"* walking MPC <= 15 ms median: {'met' if med <= 15 else 'NOT met'} "
            f"({med:.1f} ms: {iters:g} {unit[:-1] if iters == 1 else unit} x {per:.1f} "
            f"ms; 15 ms needs "
            f"{15 / max(iters, 1):.1f} ms per iteration at that count, or "
            f"{15 / per:.1f} iterations at this cost). The solver's own work, without the "
            f"function evaluations: median {own_call:.1f} ms per call ({own:.2f} ms per "
            f"iteration), {_verdict(own_call, 15.0, 'ms')} with evaluations that cost "
            f"nothing.",
            f"* every foothold planning step <= 100 ms, the first included: "
            f"{'met' if max(steps, default=1e9) <= 100 else 'NOT met'} "
            f"({sum(x <= 100 for x in steps)} of {len(steps)} steps within it; a step "
            f"solves the walking NLP once per candidate surface in reach).",
            f"* climbs with `sim.latency = \"model\"` at its default rate: {climbs}"]


def biped_section(compiled: str | None) -> tuple[list[str], dict]:
    """The biped section: walking MPC re-solves, planning steps, the charged run."""
    with tempfile.TemporaryDirectory() as cache:
        runs = {"Fresh install (NLP in SX)": _child("--biped", cache)}
    if compiled:
        runs["The walking NLP compiled"] = _child("--biped", compiled)
    with tempfile.TemporaryDirectory() as cache:
        runs['The walking MPC on real-time iterations (`mpc.solver = "rti"`, NLP in SX)'] = \
            _child("--biped-rti", cache)
    lines = ["## Biped (`scenarios/biped_stairs.toml`; targets: walking MPC <= 15 ms median, "
             "every foothold planning step <= 100 ms, climbs with modelled latency)", ""]
    for label, info in runs.items():
        lines += [*_biped_lines(label, info), ""]
    return lines[:-1], runs


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

    lines = ["## Ball CEM plan from x0 (Step 8's target <= 5 ms, the reference's parameters)",
             "",
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


def _campaign(cache: str) -> dict:
    """One Figure 3 campaign with 2 workers in ``cache``: wall and the runs' own time."""
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "hmpc_cli", "sweep", FIG3, "--workers", "2",
                        "--out", tmp, "-q"], cwd=ROOT, check=True, env=_env(cache),
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - start
        runs = [json.loads(p.read_text()) for p in Path(tmp).glob("runs/*/summary.json")]
        solves, plans = _logged_times(Path(tmp).glob("runs/*/run.mcap"))
    return {"wall": wall, "runs": len(runs), "inside": sum(r["wall_time"] for r in runs),
            "solves": solves, "plans": plans}


def campaign_section(compiled: str | None) -> tuple[list[str], dict]:
    """The Figure 3 campaign with 2 workers: warm default cache, and compiled NLPs."""
    with tempfile.TemporaryDirectory() as cache:
        command_walls(1, cache)  # the CEM's C rollout compiled, as after a first run
        out = {"the default (the chain NLPs assembled from their stage kernels, in C: those "
               "a first run left compiled by the sweep's workers, each waiting once)":
               _campaign(cache)}
    if compiled:
        out["the NLPs compiled"] = _campaign(compiled)
    lines = ["## Figure 3 campaign (`sweeps/fig3.toml`, 2 workers, time paused; target "
             "<= 15 s)", ""]
    for label, c in out.items():
        lines.append(
            f"* {label}: {c['runs']} runs in **{c['wall']:.1f} s** wall "
            f"({'met' if c['wall'] <= 15 else 'NOT met'}). The runs' own loops: "
            f"{c['inside']:.1f} s in all ({c['inside'] / 2:.1f} s per worker), of which MPC "
            f"solves {c['solves']:.1f} s and CEM plans {c['plans']:.1f} s (their logged "
            f"times); the rest of the wall time ({c['wall'] - c['inside'] / 2:.1f} s) is "
            "process start-up, the NLP builds in each worker and the sweep's bookkeeping. "
            f"The MPC solves alone take {c['solves'] / 2:.1f} s per worker (a lower bound "
            f"of the wall time on 2 cores, with IPOPT's iterates those of the committed "
            f"tables): {_verdict(c['solves'] / 2, 15.0)}.")
    return lines, out


def main(argv: Sequence[str] | None = None) -> None:
    """Runs the sections and writes ``targets.md`` (``argv``: the arguments; None: the
    command line's)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="`hmpc run` processes per case")
    ap.add_argument("--no-campaign", action="store_true", help="skip the Figure 3 campaign")
    ap.add_argument("--compiled", help="a cache directory holding the ball's and the "
                    "biped's NLPs compiled (HMPC_BUILD_CACHE=sync once): measured beside")
    ap.add_argument("--out", default=str(ROOT / "results" / "bench"))
    ap.add_argument("--phases", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--prime", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--biped", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--biped-rti", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    argv = [sys.argv[0], *(sys.argv[1:] if argv is None else argv)]
    if args.prime:  # a child: the ball's stage kernels compiled into its cache
        prime()
        return
    if args.phases or args.biped or args.biped_rti:  # a child: one section's measurements
        print(json.dumps(phases() if args.phases else
                         biped_calls("rti" if args.biped_rti else "ipopt")))
        return
    compiled = str(Path(args.compiled).resolve()) if args.compiled else None
    git, load0, start = suite_report.git_describe(), os.getloadavg(), time.perf_counter()
    sections = [run_section(args.runs, compiled), biped_section(compiled), cem_section()]
    if not args.no_campaign:
        sections.append(campaign_section(compiled))
    desc = suite_report.machine(argv, load0, time.perf_counter() - start, (), (), git)
    head = ["# Step 11 targets beyond the ball's MPC solves: measured and profiled", "",
            f"Generated by `{shown_command('bench_targets.py', argv[1:])}` on "
            f"{desc['date_utc']} "
            f"(hmpc {desc['hmpc']}, git {git}); {desc['cpu']}, {desc['cores']} cores, "
            f"CasADi {desc['casadi']}; load average {desc['load_average_start']} at start, "
            f"{desc['load_average_end']} at end; {desc['suite_seconds']} s. The ball's MPC "
            "solves themselves: `backends.md` and `realtime_rti.md`.", ""]
    text = "\n".join(head + [ln for lines, _ in sections for ln in [*lines, ""]])
    print(text)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    (Path(args.out) / "targets.md").write_text(text, encoding="utf-8")
    print(f"written: {Path(args.out) / 'targets.md'}")


if __name__ == "__main__":
    main()
