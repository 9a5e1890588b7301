"""NLP back-ends of the ball's fixed-mode MPC on the same recorded closed-loop problems.

Run on demand:  python benchmarks/bench_backends.py [--trials 1 2 3] [--closed-loop]

1. Runs disturbed Figure 3 trials (10 Hz, plan once, zero-order hold: the structured
   back-ends need stage-wise dynamics) with hmpc's IPOPT and records every MPC solve's
   problem (primal-dual warm start, parameters, bounds).
2. Replays each recorded problem with every back-end, interleaved problem by problem in
   this process: IPOPT with CasADi's defaults (cold), hmpc's IPOPT (warm instance),
   SQP + Gauss-Newton + HPIPM with 1 and 3 iterations (real-time iterations) and
   converged (50), fatrop, each on both NLPs. Prints median, p95, max wall time, mean
   iterations, failures (SQP: solves that fell back to IPOPT) and ratios to hmpc's IPOPT,
   per NLP.
3. ``--closed-loop``: the trials in closed loop with ``ipopt`` and ``sqp_hpipm``: success,
   final error, solves, fallbacks, median / p95 solve time.

Timing is measured, never asserted; the targets (issue): median <= 2 ms, p95 <= 10 ms.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from hmpc_cli.mpc.buffered import BufferedSolver
from hmpc_cli.mpc.chain.nlp import FixedModeNLP
from hmpc_cli.mpc.solver import SolverSession, plugin_options, without_nlp_grad
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.runner import prepare, run_unlogged
from hmpc_cli.run.scenario import load_scenario

HERE = os.path.dirname(os.path.abspath(__file__))
SCENARIO = os.path.join(HERE, "..", "scenarios", "ball_disturbed.toml")
ZOH = ['mpc.input_hold="zoh"']


def record(trial: int) -> list[tuple[str, tuple]]:
    """(NLP "final" or "switching", solve arguments) of every MPC solve of one trial."""
    sc, _ = load_scenario(SCENARIO, ZOH + [f"disturbance.trial={trial}"])
    loop = prepare(sc)
    nlps, out = loop.mpc.chain.nlps, []
    for label, nlp in (("switching", nlps.switching), ("final", nlps.final)):
        def optimize(*args, _nlp=nlp, _label=label):
            out.append((_label, args))
            return type(_nlp).optimize(_nlp, *args)
        nlp.optimize = optimize
    run_unlogged(loop)
    return out


def backends(system, settings) -> dict[str, dict[str, object]]:
    """Per back-end label, per NLP label, a callable ``(args) -> SolveStats``."""
    out: dict[str, dict[str, object]] = {}
    variants = {"ipopt_defaults": ("ipopt", {}), "hmpc_ipopt": ("ipopt", {}),
                "sqp_hpipm_rti1": ("sqp_hpipm", {"max_sqp_iter": 1}),
                "sqp_hpipm_rti3": ("sqp_hpipm", {"max_sqp_iter": 3}),
                "sqp_hpipm_conv": ("sqp_hpipm", {"max_sqp_iter": 50}),
                "fatrop": ("fatrop", {}),
                "rti": ("rti", {"max_sqp_iter": 1})}
    for label, (solver, extra) in variants.items():
        s = settings.model_copy(update={"solver": solver, "switching_solver": solver, **extra})
        nlps = {"switching": FixedModeNLP(system, s),
                "final": FixedModeNLP(system, s, switches=0)}
        if label == "ipopt_defaults":
            for nlp in nlps.values():
                nlp.session = _default_ipopt(nlp)
        out[label] = {k: _caller(nlp, label) for k, nlp in nlps.items()}
    return out


def _default_ipopt(nlp: FixedModeNLP) -> SolverSession:
    """IPOPT with CasADi's defaults (silent), no warm-start instance.

    On hmpc's NLP as its session holds it: assembled from stage kernels (MX, not expanded),
    its derivatives given, and no ``nlp_grad`` nor ``lam_p`` (post-solve quantities only;
    the kernels' C libraries have no derivatives to generate them from).
    """
    session = nlp.session
    opts = plugin_options("ipopt", 3000)
    opts["ipopt"] = {"print_level": 0, "sb": "yes"}
    import casadi as ca

    if isinstance(session._nlp, dict) and isinstance(session._nlp["x"], ca.MX):
        opts.pop("expand", None)
    opts = without_nlp_grad({"calc_lam_p": False, **opts, **session.derivatives})
    session.cold = session.warm = BufferedSolver(ca.nlpsol("ipopt_defaults", "ipopt",
                                                           session._nlp, opts))
    return session


#: (back-end, NLP) -> per solve: the solver's own timers [s] (CasADi ``t_wall_*``)
SPLITS: dict[tuple[str, str], list[dict]] = {}


def _caller(nlp: FixedModeNLP, label: str):
    which = "final" if nlp.S == 0 else "switching"

    def call(args):
        w0, p, lbx, ubx, lbg, ubg, lam_x, lam_g = args
        if label == "ipopt_defaults" or label == "fatrop":
            lam_x = lam_g = None  # cold (fatrop: no dual warm start through CasADi)
        start = time.perf_counter()
        stats = nlp.optimize(w0, p, lbx, ubx, lbg, ubg, lam_x, lam_g).stats
        total = time.perf_counter() - start
        inner = nlp.session.warm.stats() if lam_x is not None else nlp.session.cold.stats()
        split = {k[7:]: v for k, v in inner.items() if k.startswith("t_wall_") and v}
        split["call (hmpc + CasADi)"] = total
        SPLITS.setdefault((label, which), []).append(split)
        return stats
    call.nlp = nlp  # the NLP it solves (its session's solver instances)
    return call


def time_split(label: str = "sqp_hpipm_rti3", which: str = "final") -> None:
    """Prints where one back-end's solve time goes (median per part) [ms]."""
    rows = SPLITS.get((label, which), [])
    if not rows:
        return
    print(f"\nwhere the time goes: {label}, {which} NLP (median per solve, ms)")
    for key in sorted({k for r in rows for k in r}):
        print(f"  {key:24s} {1e3 * np.median([r.get(key, 0.0) for r in rows]):7.3f}")


def replay(problems, solvers) -> dict[tuple[str, str], list]:
    """Stats per (back-end, NLP), interleaved: every back-end on a problem, then the next."""
    out: dict[tuple[str, str], list] = {}
    for nlp_label, args in problems:
        for label, by_nlp in solvers.items():
            out.setdefault((label, nlp_label), []).append(by_nlp[nlp_label](args))
    return out


def table(stats: dict[tuple[str, str], list]) -> None:
    """Prints median / p95 / max [ms], mean iterations, failures, fallbacks, ratios."""
    ms = 1e3
    for nlp_label in ("final", "switching", "all"):
        rows = {}
        for (label, nl), st in stats.items():
            if nl == nlp_label or nlp_label == "all":
                rows.setdefault(label, []).extend(st)
        ref = np.median([s.wall_time for s in rows["hmpc_ipopt"]])
        print(f"\n{nlp_label} NLP ({len(rows['hmpc_ipopt'])} solves)")
        print(f"  {'back-end':16s} {'median':>8s} {'p95':>8s} {'max':>8s} {'iter':>5s} "
              f"{'failed':>6s} {'fallback':>8s} {'median/hmpc_ipopt':>18s}")
        for label, st in rows.items():
            t = np.array([s.wall_time for s in st])
            its = np.mean([s.iterations for s in st])
            fails = sum(not s.success for s in st)
            fb = sum(s.fallback for s in st)
            print(f"  {label:16s} {ms * np.median(t):7.2f}  {ms * np.percentile(t, 95):7.2f}  "
                  f"{ms * t.max():7.2f}  {its:5.1f} {fails:6d} {fb:8d} "
                  f"{np.median(t) / ref:18.2f}")


def closed_loop(trials: list[int]) -> None:
    """Closed-loop outcome of each trial with IPOPT and SQP + HPIPM."""
    print("\nclosed loop (10 Hz, plan once, zoh):")
    for trial in trials:
        for solver in ("ipopt", "sqp_hpipm"):
            sc, _ = load_scenario(SCENARIO, ZOH + [f"disturbance.trial={trial}",
                                                   f'mpc.solver="{solver}"'])
            start = time.perf_counter()
            r = run_unlogged(prepare(sc))
            print(f"  trial {trial:2d} {solver:10s} success {r.success!s:5s} final error "
                  f"{r.final_error:.4f} solves {r.solves} failures {r.solver_failures} "
                  f"fallbacks {r.fallbacks} median {1e3 * r.solve_time_median:.2f} ms "
                  f"p95 {1e3 * r.solve_time_p95:.2f} ms (run {time.perf_counter() - start:.1f} s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--trials", type=int, nargs="+", default=[1, 2, 5, 7])
    ap.add_argument("--closed-loop", action="store_true")
    args = ap.parse_args()
    sc, _ = load_scenario(SCENARIO, ZOH)
    problems = [rec for trial in args.trials for rec in record(trial)]
    solvers = backends(build_system(sc.system), sc.mpc)
    table(replay(problems, solvers))
    time_split()
    time_split("hmpc_ipopt")
    if args.closed_loop:
        closed_loop(args.trials)


if __name__ == "__main__":
    main()
