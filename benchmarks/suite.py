"""The benchmark suite: every fixed-mode MPC configuration on the same recorded problems.

Run:  python benchmarks/suite.py            (trials 1 2 3 5 7: 160 problems, ~6 min)
      python benchmarks/suite.py --quick    (trial 1, 10 problems, ~1 min)

1. Records the MPC problems of disturbed Figure 3 trials in closed loop (10 Hz, plan once,
   zero-order hold: the structured back-ends need stage-wise dynamics) with hmpc's IPOPT:
   per solve the NLP ("final": no switch left; "switching"), the primal-dual warm start,
   parameters and bounds, and the time spent packing them (``problem_data``).
2. Replays each problem with every configuration, interleaved problem by problem in this
   process (the order rotates from one problem to the next):

   * ``authors``: rebuild the NLP (transcription + ``nlpsol``) and solve it cold with
     IPOPT's default options on every call, as the reference code does;
   * ``ipopt_defaults``: IPOPT with CasADi's defaults on the built NLP, cold, same guess;
   * ``hmpc_ipopt``: hmpc's IPOPT (warm instance, primal-dual warm start);
   * ``sqp_hpipm_rti1`` / ``_rti3`` / ``_conv``: SQP + Gauss-Newton + HPIPM with 1, 3 and
     50 iterations (a solve it fails falls back to IPOPT: counted);
   * ``fatrop`` (cold: no dual warm start through CasADi);
   * ``rti``: the real-time iterations, one SQP step from the warm start (kept as it is);
   * ``do_mpc``: do-mpc's default MPC (orthogonal collocation) on the final-domain
     problems only (optional: ``pip install -e '.[bench]'``).

   hmpc's ``sqpmethod`` back-end (exact Hessian, active-set QP) is left out
   (:data:`SQPMETHOD`).
3. Prints, per configuration and NLP, median / p95 / max wall time [ms], mean iterations,
   failures, fallbacks and ratios, the profile of the fastest back-end and the issue's
   targets; writes ``backends.md``, ``backends.csv`` and ``machine.json`` to ``--out``
   (default ``results/bench``, ``results/bench/quick`` with ``--quick``).

Every NLP is built in CasADi's SX (``HMPC_BUILD_CACHE=off`` unless set): a compiled build
cache would speed hmpc's IPOPT rows only. Timing is measured, never asserted.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np

import bench_backends as bb
import suite_peers as peers
import suite_report as report
from hmpc_cli.core.messages import SolveStats
from hmpc_cli.mpc.chain.nlp import FixedModeNLP
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.runner import prepare, run_unlogged
from hmpc_cli.run.scenario import load_scenario

TRIALS = (1, 2, 3, 5, 7)
QUICK_TRIALS, QUICK_PROBLEMS = (1,), 10
#: why hmpc's ``sqpmethod`` back-end has no row (measured on trial 1's problems, 180 nodes)
SQPMETHOD = ("sqpmethod (exact Hessian, qrqp active-set QP) left out: 3-8 s per solve on "
             "trial 1's problems, and 2 of its first 3 final-domain solves failed (one after "
             "200 iterations and 587 s)")


@dataclass(frozen=True)
class Problem:
    """One recorded MPC solve.

    Attributes:
        trial: the Figure 3 trial it comes from.
        nlp: "final" (no switch left) or "switching".
        args: (w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0) as the closed loop solved it.
        x0: the measured state the solve started from, shape (n,).
    """

    trial: int
    nlp: str
    args: tuple
    x0: np.ndarray


@dataclass
class SuiteRun:
    """What one suite run measured.

    Attributes:
        stats: per (configuration, NLP) the solves' stats, in problem order.
        splits: per (configuration, NLP) the solver's timers per solve [s]
            (:data:`bench_backends.SPLITS`; ``total`` with ``record_time``).
        packing: per recorded solve, the closed loop's ``problem_data`` time [s].
        notes: lines for the report (left-out rows and why).
        build: per configuration, seconds spent building it (not in the table).
        problems: the replayed problems' count per NLP.
    """

    stats: dict[tuple[str, str], list[SolveStats]] = field(default_factory=dict)
    splits: dict[tuple[str, str], list[dict]] = field(default_factory=dict)
    packing: list[float] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    build: dict[str, float] = field(default_factory=dict)
    problems: dict[str, int] = field(default_factory=dict)


def record(trial: int, overrides: list[str]) -> tuple[list[Problem], list[float]]:
    """The MPC problems of one closed-loop trial and the ``problem_data`` times [s]."""
    sc, _ = load_scenario(bb.SCENARIO, [*bb.ZOH, *overrides, f"disturbance.trial={trial}"])
    loop = prepare(sc)
    nlps, out, packing = loop.mpc.chain.nlps, [], []
    for label, nlp in (("switching", nlps.switching), ("final", nlps.final)):
        if nlp is None:
            continue

        def optimize(*args, _nlp=nlp, _label=label):
            out.append(Problem(trial, _label, args, args[0][_nlp.z_idx[0]].copy()))
            return type(_nlp).optimize(_nlp, *args)

        def pack(*args, _nlp=nlp):
            start = time.perf_counter()
            res = type(_nlp).problem_data(_nlp, *args)
            packing.append(time.perf_counter() - start)
            return res

        nlp.optimize, nlp.problem_data = optimize, pack
    run_unlogged(loop)
    return out, packing


def select(problems: list[Problem], limit: int | None) -> list[Problem]:
    """At most ``limit`` problems, spread evenly over each NLP's, in their recorded order."""
    if limit is None or len(problems) <= limit:
        return list(problems)
    kinds = {}
    for i, prob in enumerate(problems):
        kinds.setdefault(prob.nlp, []).append(i)
    keep: list[int] = []
    quota = {k: max(1, limit // len(kinds)) for k in kinds}
    quota[max(kinds, key=lambda k: len(kinds[k]))] += limit - sum(quota.values())
    for kind, idx in kinds.items():
        n = min(len(idx), max(quota[kind], 1))
        keep += [idx[j] for j in np.unique(np.linspace(0, len(idx) - 1, n).round().astype(int))]
    return [problems[i] for i in sorted(keep)]


class TimedSolver:
    """A CasADi solver whose stats add its last call's wall and process (CPU) time [s].

    ``t_wall_casadi_call``: the Python-to-CasADi call around the solver's own
    ``t_wall_total``; ``t_wall_cpu_casadi_call``: the process time of that call (wall
    above CPU time: the process waited for a core).
    """

    def __init__(self, solver) -> None:
        """Wraps ``solver`` (a ``casadi.Function`` from ``nlpsol``)."""
        self.solver, self.last = solver, (0.0, 0.0)

    def __call__(self, **kwargs):
        """Calls the solver, timing the call."""
        start, cpu = time.perf_counter(), time.process_time()
        out = self.solver(**kwargs)
        self.last = (time.perf_counter() - start, time.process_time() - cpu)
        return out

    def stats(self) -> dict:
        """The solver's stats, ``t_wall_casadi_call`` and ``t_wall_cpu_casadi_call``."""
        return {**self.solver.stats(), "t_wall_casadi_call": self.last[0],
                "t_wall_cpu_casadi_call": self.last[1]}

    def __getattr__(self, name: str):
        """Any other attribute is the solver's (``has_function``, ``get_function``, ...)."""
        return getattr(self.solver, name)


def configurations(system, settings, run: SuiteRun, with_dompc: bool = True) -> dict:
    """Per configuration label, a callable ``(Problem) -> SolveStats | None`` (None: n/a)."""
    configs: dict = {}
    start = time.perf_counter()
    templates = {"final": FixedModeNLP(system, settings, switches=0),
                 "switching": FixedModeNLP(system, settings)}
    authors = {k: peers.AuthorsBaseline(nlp) for k, nlp in templates.items()}
    configs["authors"] = lambda prob: authors[prob.nlp](prob.args)
    run.build["authors"] = time.perf_counter() - start
    start = time.perf_counter()
    timed = settings.model_copy(update={"solver_options": {"record_time": True}})
    for label, by_nlp in bb.backends(system, timed).items():
        for call in by_nlp.values():
            session = call.nlp.session
            cold = TimedSolver(session.cold)
            session.warm = cold if session.warm is session.cold else TimedSolver(session.warm)
            session.cold = cold
        configs[label] = lambda prob, _f=by_nlp: _f[prob.nlp](prob.args)
    run.build["hmpc back-ends (7 x 2 NLPs)"] = time.perf_counter() - start
    dm = dompc_config(templates["final"], run, with_dompc)
    if dm is not None:
        configs["do_mpc"] = dm
    return configs


def dompc_config(final: FixedModeNLP, run: SuiteRun, with_dompc: bool = True):
    """do-mpc's configuration (final-domain problems only), or None with one printed line
    and a note when do-mpc is not installed (or ``with_dompc`` is False)."""
    do_mpc = peers.import_do_mpc() if with_dompc else None
    if do_mpc is None:
        why = ("not installed (pip install -e '.[bench]')" if with_dompc
               else "not asked for (--no-do-mpc)")
        run.notes.append(f"do-mpc {why}: its row is left out")
        print(f"do-mpc {why}: its row is left out", flush=True)
        return None
    dm = peers.DoMPCFinal(do_mpc, final)
    run.build["do_mpc"] = dm.build_time
    return lambda prob: dm(prob.trial, prob.x0) if prob.nlp == "final" else None


def replay(problems: list[Problem], configs: dict, run: SuiteRun,
           progress: bool = False) -> None:
    """Every configuration on each problem in turn (rotating order); fills ``run.stats``."""
    labels = list(configs)
    for i, prob in enumerate(problems):
        r = i % len(labels)
        for label in labels[r:] + labels[:r]:
            start = time.perf_counter()
            try:
                st = configs[label](prob)
            except Exception as exc:  # a peer's own error: a failed solve, counted
                st = SolveStats(f"error: {type(exc).__name__}: {exc}"[:160], False, 0,
                                time.perf_counter() - start, float("nan"), float("inf"))
            if st is not None:
                run.stats.setdefault((label, prob.nlp), []).append(st)
        run.problems[prob.nlp] = run.problems.get(prob.nlp, 0) + 1
        if progress and (i + 1) % 10 == 0:
            print(f"  {i + 1}/{len(problems)} problems replayed", flush=True)


def run_suite(trials, overrides=(), limit=None, with_dompc=True, progress=False) -> SuiteRun:
    """Records the trials' problems and replays them with every configuration."""
    os.environ.setdefault("HMPC_BUILD_CACHE", "off")  # every row in SX (see the docstring)
    problems, packing = [], []
    for trial in trials:
        recorded, packed = record(trial, list(overrides))
        problems += recorded
        packing += packed
        if progress:
            print(f"trial {trial}: {len(recorded)} MPC problems recorded", flush=True)
    run = measure(select(problems, limit), overrides, with_dompc, progress)
    run.packing = packing
    return run


def measure(problems: list[Problem], overrides=(), with_dompc=True,
            progress=False) -> SuiteRun:
    """Builds every configuration (the recording's scenario overrides) and replays."""
    run = SuiteRun(notes=[SQPMETHOD])
    bb.SPLITS.clear()
    sc, _ = load_scenario(bb.SCENARIO, [*bb.ZOH, *overrides])
    configs = configurations(build_system(sc.system), sc.mpc, run, with_dompc)
    replay(problems, configs, run, progress)
    run.splits = {k: list(v) for k, v in bb.SPLITS.items()}
    return run


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, nargs="+", default=None,
                    help=f"Figure 3 trials to record (default {' '.join(map(str, TRIALS))})")
    ap.add_argument("--problems", type=int, default=None,
                    help="replay at most this many problems (spread over both NLPs)")
    ap.add_argument("--quick", action="store_true",
                    help=f"trial {QUICK_TRIALS[0]}, {QUICK_PROBLEMS} problems")
    ap.add_argument("--set", dest="overrides", action="append", default=[],
                    help="scenario override key.path=value (repeatable)")
    ap.add_argument("--no-do-mpc", action="store_true", help="leave do-mpc's row out")
    ap.add_argument("--out", default=None, help="output directory")
    args = ap.parse_args(argv)
    trials = args.trials or (QUICK_TRIALS if args.quick else TRIALS)
    limit = args.problems or (QUICK_PROBLEMS if args.quick else None)
    out = args.out or os.path.join("results", "bench", "quick" if args.quick else "")
    load0, start, git = os.getloadavg(), time.perf_counter(), report.git_describe()
    run = run_suite(trials, args.overrides, limit, not args.no_do_mpc, progress=True)
    machine = report.machine(["python", *sys.argv] if argv is None else argv, load0,
                             time.perf_counter() - start, trials, args.overrides, git)
    text, files = report.write(run, machine, out)
    print(text)
    print("\nwrote " + ", ".join(files))
    return 0


if __name__ == "__main__":
    sys.exit(main())
