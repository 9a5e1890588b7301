"""Profile of the switching MPC solve: where its iterations and its time go (measurement).

Run:  python benchmarks/profile_switching.py --write results/bench/profile_switching.md
      python benchmarks/profile_switching.py --quick      (nominal + trials 1 5, ~1 min)

1. Records, in this process, the MPC problems of the Figure 3 "10 Hz fixed" controller
   in closed loop (``scenarios/ball.toml``: the nominal ball and the disturbed trials
   1-10, as ``sweeps/fig3.toml`` runs them): per solve the NLP ("switching": at least one
   switch left; "final"), the primal-dual warm start, parameters and bounds, the node
   schedule, the time to the next planned switch and the previous solution (unshifted).
2. Re-solves the switching problems (interleaved problem by problem, the order rotating):

   * ``baseline``: the closed loop's solve (warm IPOPT instance, shifted primal-dual
     warm start), with IPOPT's per-function timers (``t_wall_nlp_*``, ``t_wall_total``);
   * row groups relaxed through their bounds (the same NLP; a relaxed row stays in the
     KKT system with infinite bounds): no virtual node (``robust = false``), hard
     constraints (``soft_penalty = 0``: slacks fixed at 0), no region rows, no
     guard-avoid rows, the guard hit as one equality row, every hybrid row off;
   * warm starts: primal only (cold instance), the previous solution unshifted, cold
     (state held, inputs 0);
   * IPOPT options on the same NLP: ``mu_strategy = monotone``, warm ``mu_init = 1e-4``,
     limited-memory Hessian, ``tol = 1e-6``, and IPOPT stopped after 3 iterations;
   * once more with IPOPT's ``print_timing_statistics`` (linear algebra vs the rest).

   The final-domain problems are re-solved once (baseline) for comparison.
3. Runs the closed loop again with structural settings changed (fewer nodes, Euler,
   zero-order hold, a shorter chain, hard constraints) and records its switching solves.
4. Writes a Markdown report (``--write``): machine, tables, what the profile says and
   the levers it points to, ranked by the saving measured or bounded here.

Every NLP is built in CasADi's SX (``HMPC_BUILD_CACHE=off`` unless set), as the closed
loop builds it without a compiled build cache. Timing is measured, never asserted; the
numbers depend on the machine and its load.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import suite_report  # noqa: E402

from hmpc_cli.core.messages import SolveStats  # noqa: E402
from hmpc_cli.core.registry import build_system  # noqa: E402
from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule  # noqa: E402
from hmpc_cli.mpc.chain.nlp import WARM_START, FixedModeNLP  # noqa: E402
from hmpc_cli.mpc.chain.problem_data import problem_data  # noqa: E402
from hmpc_cli.mpc.solver import SolverSession, WarmStart, warm_options  # noqa: E402
from hmpc_cli.run.runner import prepare, run_unlogged  # noqa: E402
from hmpc_cli.run.scenario import load_scenario  # noqa: E402

SCENARIO = str(HERE.parent / "scenarios" / "ball.toml")
TRIALS = tuple(range(1, 11))
QUICK_TRIALS = (1, 5)
DISTURBED = ['disturbance.kind="paper_fig3"']
MS = 1e3
#: IPOPT's function evaluations, as CasADi times them (``t_wall_<name>``)
EVALS = ("nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l")
#: row groups of the switching NLP (FixedModeNLP), in layout order
GROUPS = ("dynamics", "guard_avoid", "guard_hit", "virtual_node", "region", "terminal")
#: closed-loop settings variants (label, scenario overrides)
CLOSED_LOOP = (
    ("default (recorded)", ()),
    ("nodes_per_second = 30", ("mpc.nodes_per_second=30",)),
    ("nodes_per_second = 20", ("mpc.nodes_per_second=20",)),
    ('integrator = "euler"', ('mpc.integrator="euler"',)),
    ('input_hold = "zoh"', ('mpc.input_hold="zoh"',)),
    ("max_switches = 3", ("mpc.max_switches=3",)),
)
QUICK_CLOSED_LOOP = ("default (recorded)", "nodes_per_second = 30")
#: IPOPT timing statistics reported (name in IPOPT's output -> label)
IPOPT_TIMERS = (
    ("OverallAlgorithm", "whole IPOPT algorithm"),
    ("PDSystemSolverTotal", "linear algebra: KKT solves (MUMPS), residuals, refinement"),
    ("LinearSystemSymbolicFactorization", "  MUMPS symbolic factorization (analysis)"),
    ("LinearSystemFactorization", "  MUMPS numeric factorization"),
    ("LinearSystemBackSolve", "  MUMPS back-solves"),
    ("UpdateBarrierParameter", "barrier update (adaptive mu: probing solves)"),
    ("ComputeSearchDirection", "search direction"),
    ("ComputeAcceptableTrialPoint", "line search"),
    ("CheckConvergence", "convergence check"),
    ("UpdateHessian", "Hessian update (incl. nlp_hess_l)"),
)


# --------------------------------------------------------------------------- recording
@dataclass(frozen=True)
class Problem:
    """One recorded MPC solve of the closed loop.

    Attributes:
        run: "nominal" or "trial k".
        index: the solve's index in its run.
        t: simulated time of the solve [s].
        nlp: "switching" (at least one switch left) or "final".
        ns: the node schedule solved.
        lay: its layout on the NLP's chain.
        x0: the measured state the solve started from, shape (n,).
        args: (w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0) as the closed loop solved it.
        prev: the previous solve's solution on the same NLP (x, lam_x, lam_g), not
            shifted, or None (first solve of the NLP, or the previous solve failed).
        context: "cold (new plan)", "after impact" or "shifted".
        recorded: the closed loop's solve stats.
        to_switch: time to the next planned switch [s] (intervals left in the current
            domain x node step).
    """

    run: str
    index: int
    t: float
    nlp: str
    ns: NodeSchedule
    lay: ChainLayout
    x0: np.ndarray
    args: tuple
    prev: tuple | None
    context: str
    recorded: SolveStats
    to_switch: float


@dataclass
class RunInfo:
    """One closed-loop run: label, success, final error, solves per NLP."""

    label: str
    success: bool
    final_error: float
    solves: dict[str, int]


def _copy(args) -> tuple:
    return tuple(None if a is None else np.array(a, dtype=float, copy=True) for a in args)


def record(label: str, overrides=()) -> tuple[list[Problem], RunInfo]:
    """The MPC problems of one closed-loop run of ``scenarios/ball.toml`` + ``overrides``."""
    sc, _ = load_scenario(SCENARIO, list(overrides))
    loop = prepare(sc)
    chain, out = loop.mpc.chain, []
    nlps = chain.nlps
    ctx: dict = {"t": float("nan"), "prev": {}, "guards": None}
    reoptimize = chain.reoptimize

    def timed_reoptimize(t, x):
        ctx["t"] = t
        return reoptimize(t, x)

    chain.reoptimize = timed_reoptimize
    hooked = [(k, n) for k, n in (("switching", nlps.switching), ("final", nlps.final))
              if n is not None]
    for which, nlp in hooked:
        def optimize(*args, _nlp=nlp, _which=which):
            args = _copy(args)
            res = type(_nlp).optimize(_nlp, *args)
            ns = chain.node_schedule
            if args[6] is None:
                context = "cold (new plan)"
            elif ctx["guards"] is not None and len(ns.guards) < ctx["guards"]:
                context = "after impact"
            else:
                context = "shifted"
            ctx["guards"] = len(ns.guards)
            out.append(Problem(label, len(out), ctx["t"], _which, ns, chain.layout,
                               args[0][_nlp.z_idx[0]].copy(), args, ctx["prev"].get(_which),
                               context, res.stats, ns.counts[0] * _nlp.dt))
            ctx["prev"][_which] = (res.x.copy(), res.lam_x.copy(), res.lam_g.copy()) \
                if res.stats.success else None
            return res
        nlp.optimize = optimize
    try:
        result = run_unlogged(loop)
    finally:  # the NLPs are shared by the process's runs: unhook them
        for _, nlp in hooked:
            nlp.__dict__.pop("optimize", None)
    solves = {k: sum(p.nlp == k for p in out) for k in ("switching", "final")}
    return out, RunInfo(label, bool(result.success), float(result.final_error), solves)


def runs_of(trials, base=()) -> list[tuple[str, list[str]]]:
    """(label, overrides) of the nominal run and the disturbed trials."""
    return [("nominal", list(base))] + [
        (f"trial {k}", [*base, *DISTURBED, f"disturbance.trial={k}"]) for k in trials]


def record_all(trials, base=(), progress=False) -> tuple[list[Problem], list[RunInfo]]:
    """Every MPC problem of the nominal run and of the disturbed trials."""
    problems, infos = [], []
    for label, ov in runs_of(trials, base):
        recorded, info = record(label, ov)
        problems += recorded
        infos.append(info)
        if progress:
            print(f"  {label}: {info.solves['switching']} switching + "
                  f"{info.solves['final']} final solves", flush=True)
    return problems, infos


# ------------------------------------------------------------------------- measurement
@dataclass(frozen=True)
class Meas:
    """One re-solve: iterations, wall time of the call [s], IPOPT's timers [s], result."""

    iterations: int
    wall: float
    total: float
    evals: dict
    calls: dict
    success: bool
    status: str
    cost: float
    violation: float

    @property
    def eval_time(self) -> float:
        """All function evaluations [s]."""
        return float(sum(self.evals.values()))

    @property
    def rest(self) -> float:
        """IPOPT's time outside the evaluations: linear solver (MUMPS) + IPOPT [s]."""
        return max(self.total - self.eval_time, 0.0)


def measure(session: SolverSession, args: tuple) -> Meas:
    """Solves ``args`` on ``session`` and reads the instance's timers."""
    start = time.perf_counter()
    res = session.run(*args)
    wall = time.perf_counter() - start
    inst = session.warm if args[6] is not None and args[7] is not None else session.cold
    st = inst.stats()
    evals = {k: float(st.get(f"t_wall_{k}", 0.0)) for k in EVALS}
    calls = {k: int(st.get(f"n_call_{k}", 0)) for k in EVALS}
    s = res.stats
    return Meas(s.iterations, wall, float(st.get("t_wall_total", wall)), evals, calls,
                s.success, s.status, s.cost, s.max_violation)


def settings_of(overrides=()):
    """(system, MPC settings with IPOPT's ``record_time``) of the scenario + overrides."""
    sc, _ = load_scenario(SCENARIO, list(overrides))
    s = sc.mpc.model_copy(update={"solver_options": {**sc.mpc.solver_options,
                                                     "record_time": True}})
    return build_system(sc.system), s


def session(nlp: FixedModeNLP, ipopt: dict | None = None, warm: WarmStart = WARM_START,
            ipopt_warm: dict | None = None, max_iter: int | None = None) -> SolverSession:
    """An IPOPT session on ``nlp``'s expressions with other options (timers on).

    It gets the derivatives ``nlp``'s own session gives IPOPT (assembled stage by stage).
    """
    extra: dict = {"record_time": True, "ipopt": dict(ipopt or {})}
    if ipopt_warm:
        extra["ipopt_warm"] = ipopt_warm
    given = nlp.session.derivatives
    if (ipopt or {}).get("hessian_approximation") != "limited-memory":
        return SolverSession("profile", nlp.session._nlp, "ipopt",
                             max_iter=max_iter or nlp.s.max_iter, tol=1e-8, extra=extra,
                             warm=warm, derivatives=given)
    # no exact Hessian to share with the warm instance: build that one on its own
    out = SolverSession("profile", nlp.session._nlp, "ipopt",
                        max_iter=max_iter or nlp.s.max_iter, tol=1e-8, extra=extra,
                        derivatives={k: f for k, f in given.items() if k != "hess_lag"})
    out.warm = ca.nlpsol("profile_warm", "ipopt", nlp.session._nlp,
                         warm_options(out.options, warm, extra))
    return out


# --------------------------------------------------------------- problem transformations
def _relax(args, rows) -> tuple:
    w0, p, lbx, ubx, lbg, ubg, lx, lg = args
    lbg, ubg = lbg.copy(), ubg.copy()
    lbg[rows], ubg[rows] = -np.inf, np.inf
    return (w0, p, lbx, ubx, lbg, ubg, lx, lg)


def _hit_rows(nlp: FixedModeNLP, args) -> tuple[np.ndarray, np.ndarray]:
    """(guard_hit rows, guard_avoid rows of the hit guard) at the problem's guard nodes."""
    g, pl = nlp.layout.g, nlp.layout.p
    hit = g["guard_hit"]
    nodes = np.nonzero(np.isfinite(args[5][hit]))[0]
    hitp = args[1][pl["hit"]]  # (L + 1, G)
    cols = [nlp.guard_col[int(np.argmax(hitp[k]))] for k in nodes]
    return hit[nodes], np.array([g["guard_avoid"][k, c] for k, c in zip(nodes, cols,
                                                                        strict=True)], int)


def no_virtual_node(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """``robust = false``: the problem data without the virtual pass-through node."""
    shape = dataclasses.replace(nlp.shape, s=nlp.s.model_copy(update={"robust": False}))
    p, lbx, ubx, lbg, ubg = problem_data(shape, prob.ns, prob.lay, prob.x0)
    return (prob.args[0], p, lbx, ubx, lbg, ubg, prob.args[6], prob.args[7])


def hard(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """``soft_penalty = 0``: the slacks fixed at 0 (hard hybrid constraints)."""
    w0, p, lbx, ubx, lbg, ubg, lx, lg = prob.args
    ubx = ubx.copy()
    ubx[nlp.s_idx] = 0.0
    return (w0, p, lbx, ubx, lbg, ubg, lx, lg)


def no_region(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """The guards' activity-region rows relaxed."""
    return _relax(prob.args, nlp.layout.g["region"].ravel())


def no_guard_avoid(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """Guard-avoid rows relaxed (not the guard hit's lower side at the guard nodes)."""
    _, keep = _hit_rows(nlp, prob.args)
    rows = np.setdiff1d(nlp.layout.g["guard_avoid"].ravel(), keep)
    return _relax(prob.args, rows)


def hit_equality(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """The guard hit as one equality row q_G = sigma (its lower side relaxed)."""
    hit, low = _hit_rows(nlp, prob.args)
    w0, p, lbx, ubx, lbg, ubg, lx, lg = _relax(prob.args, low)
    lbg[hit] = ubg[hit] = 0.0
    return (w0, p, lbx, ubx, lbg, ubg, lx, lg)


def no_hybrid_rows(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """Every hybrid row relaxed, slacks fixed at 0: dynamics and input bounds only."""
    g = nlp.layout.g
    rows = np.concatenate([g[k].ravel() for k in GROUPS[1:] if k in g])
    w0, p, lbx, ubx, lbg, ubg, lx, lg = _relax(hard(nlp, prob), rows)
    return (w0, p, lbx, ubx, lbg, ubg, lx, lg)


def primal_only(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """The shifted primal warm start without multipliers (IPOPT's cold instance)."""
    return (*prob.args[:6], None, None)


def unshifted(nlp: FixedModeNLP, prob: Problem) -> tuple | None:
    """The previous solution as it was (not shifted), primal-dual; None if none."""
    if prob.prev is None or prob.args[6] is None:
        return None
    w, lx, lg = (a.copy() for a in prob.prev)
    w[nlp.z_idx[0]] = prob.x0
    return (w, *prob.args[1:6], lx, lg)


def cold(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """Cold: every node at the measured state, inputs and slacks 0 (cold instance)."""
    w = np.zeros(nlp.nx_var)
    w[nlp.z_idx] = prob.x0
    return (w, *prob.args[1:6], None, None)


def as_recorded(nlp: FixedModeNLP, prob: Problem) -> tuple:
    """The problem as the closed loop solved it."""
    return prob.args


@dataclass(frozen=True)
class Variant:
    """One way to re-solve the switching problems.

    Attributes:
        name: row label.
        section: "rows", "warm" or "ipopt".
        what: the problem (a function ``(nlp, Problem) -> args | None``; None: n/a).
        session: key of the solver session (:func:`sessions`).
        every: re-solve every ``every``-th problem only (the slow variants: run time).
    """

    name: str
    section: str
    what: object
    session: str = "base"
    every: int = 1


def _cold_of(transform):
    """The row-group transform from the cold start (state held, no multipliers)."""
    def what(nlp: FixedModeNLP, prob: Problem) -> tuple:
        args = transform(nlp, prob)
        return (cold(nlp, prob)[0], *args[1:6], None, None)
    return what


#: row-group transforms (label, function) relaxed from the warm and from the cold start
ROW_TRANSFORMS = (
    ("no virtual node (robust = false)", no_virtual_node),
    ("hard constraints (soft_penalty = 0)", hard),
    ("no region rows", no_region),
    ("no guard-avoid rows", no_guard_avoid),
    ("guard hit as one equality row", hit_equality),
    ("no hybrid rows, slacks 0 (dynamics only)", no_hybrid_rows),
)
BASELINE, COLD = "baseline (closed loop)", "cold: state held, inputs 0"
LBFGS_MAX_ITER = 60
VARIANTS = (
    Variant(BASELINE, "base", as_recorded),
    *(Variant(name, "rows", f) for name, f in ROW_TRANSFORMS),
    Variant("primal only (shifted), cold instance", "warm", primal_only),
    Variant("previous solution unshifted, primal-dual", "warm", unshifted),
    Variant(COLD, "warm", cold),
    *(Variant(f"{name} [cold]", "rows_cold", _cold_of(f), every=2)
      for name, f in ROW_TRANSFORMS),
    Variant("mu_strategy = monotone", "ipopt", as_recorded, "monotone"),
    Variant("warm mu_init = 1e-4 (default 1e-6)", "ipopt", as_recorded, "mu_init"),
    Variant("linear_solver = spral (default mumps)", "ipopt", as_recorded, "spral", every=4),
    Variant(f"limited-memory Hessian (L-BFGS, max {LBFGS_MAX_ITER} it.)", "ipopt",
            as_recorded, "lbfgs", every=4),
    Variant("tol = 1e-6 (default 1e-8)", "ipopt", as_recorded, "tol"),
    Variant("stopped after 3 iterations (RTI-like)", "ipopt", as_recorded, "max3"),
    Variant("timing statistics pass", "stats", as_recorded, "stats"),
)
LBFGS = VARIANTS[-4].name


def sessions(nlp: FixedModeNLP, folder: str, names) -> dict[str, SolverSession]:
    """The solver sessions the variants use (``base``: the NLP's own)."""
    files = {k: os.path.join(folder, f"ipopt_{k}.txt") for k in ("cold", "warm")}
    stats = {"print_timing_statistics": "yes", "file_print_level": 3}
    make = {
        "monotone": lambda: session(nlp, {"mu_strategy": "monotone"}),
        "mu_init": lambda: session(nlp, warm=WarmStart(1e-4, WARM_START.bound_push)),
        "lbfgs": lambda: session(nlp, {"hessian_approximation": "limited-memory"},
                                 max_iter=LBFGS_MAX_ITER),
        "spral": lambda: session(nlp, {"linear_solver": "spral"}),
        "tol": lambda: session(nlp, {"tol": 1e-6}),
        "max3": lambda: session(nlp, max_iter=3),
        "stats": lambda: session(nlp, {**stats, "output_file": files["cold"]},
                                 ipopt_warm={"output_file": files["warm"]}),
    }
    out = {"base": nlp.session}
    out.update({k: make[k]() for k in dict.fromkeys(names) if k != "base"})
    out["_files"] = files  # type: ignore[assignment]
    return out


def ipopt_timers(path: str) -> dict[str, float]:
    """IPOPT's timing statistics of the last solve written to ``path`` [s] (wall)."""
    try:
        text = Path(path).read_text()
    except OSError:
        return {}
    block = text.rsplit("Timing Statistics:", 1)[-1] if "Timing Statistics:" in text else ""
    out = {}
    for name, wall in re.findall(r"^\s*(\w+)\.+:\s+[\d.]+ \(sys:\s+[\d.]+ wall:\s+([\d.]+)\)",
                                 block, flags=re.M):
        out[name] = float(wall)
    return out


@dataclass
class Profile:
    """What :func:`replay` measured: per variant name, per problem a Meas (None: n/a)."""

    problems: list[Problem]
    meas: dict[str, list] = field(default_factory=dict)
    timers: list[dict] = field(default_factory=list)
    final: list[Meas] = field(default_factory=list)
    cpu_wall: float = float("nan")


def replay(problems: list[Problem], nlp: FixedModeNLP, variants=VARIANTS,
           progress: bool = False) -> Profile:
    """Every variant on each switching problem in turn (rotating order)."""
    prof = Profile(problems, {v.name: [] for v in variants})
    with tempfile.TemporaryDirectory() as tmp:
        sess = sessions(nlp, tmp, [v.session for v in variants])
        files = sess["_files"]
        start, cpu = time.perf_counter(), time.process_time()
        for i, prob in enumerate(problems):
            r = i % len(variants)
            for v in variants[r:] + variants[:r]:
                args = v.what(nlp, prob) if i % v.every == 0 else None
                m = None if args is None else measure(sess[v.session], args)
                prof.meas[v.name].append(m)
                if v.session == "stats" and m is not None:
                    prof.timers.append(ipopt_timers(files["warm" if args[6] is not None
                                                          else "cold"]))
            if progress and (i + 1) % 10 == 0:
                print(f"  {i + 1}/{len(problems)} switching problems re-solved", flush=True)
        wall = time.perf_counter() - start
        prof.cpu_wall = (time.process_time() - cpu) / wall if wall > 0 else float("nan")
    return prof


def replay_final(problems: list[Problem], nlp: FixedModeNLP, limit: int = 80) -> list[Meas]:
    """The baseline re-solve of (at most ``limit``, evenly spread) final-domain problems."""
    if len(problems) > limit:
        problems = [problems[i] for i in np.unique(
            np.linspace(0, len(problems) - 1, limit).round().astype(int))]
    return [measure(nlp.session, p.args) for p in problems]


# ------------------------------------------------------------------ closed-loop variants
@dataclass
class LoopVariant:
    """A closed-loop settings variant: its switching solves and runs."""

    label: str
    stats: list[SolveStats]
    runs: list[RunInfo]
    size: int


def closed_loop(label: str, overrides, trials) -> LoopVariant:
    """The nominal run and the trials with ``overrides``: their switching solves."""
    stats, infos = [], []
    for run, ov in runs_of(trials, overrides):
        problems, info = record(run, ov)
        stats += [p.recorded for p in problems if p.nlp == "switching"]
        infos.append(info)
    sysm, s = settings_of(overrides)
    return LoopVariant(label, stats, infos, _size_of(sysm, s))


def _size_of(sysm, s) -> int:
    """Variables of the switching NLP of settings ``s`` (from its chain length)."""
    links = s.n_intervals + s.max_switches
    return (links + 1) * (sysm.n_x + 1) + links * sysm.n_u


# ---------------------------------------------------------------------------- KKT size
def kkt_size(nlp: FixedModeNLP, problems: list[Problem]) -> dict:
    """Variables, rows and nonzeros of one NLP, and its rows with finite bounds per solve."""
    solver = nlp.session.cold
    jac = solver.get_function("nlp_jac_g").sparsity_out(1)
    hess = solver.get_function("nlp_hess_l").sparsity_out(0)
    g = nlp.layout.g
    groups = {}
    rows_nnz = np.bincount(jac.get_triplet()[0], minlength=nlp.ng)
    for name in GROUPS:
        if name not in g:
            continue
        idx = g[name].ravel()
        live = [int(np.sum(np.isfinite(p.args[4][idx]) | np.isfinite(p.args[5][idx])))
                for p in problems]
        groups[name] = {"rows": idx.size, "jac_nnz": int(rows_nnz[idx].sum()),
                        "live": float(np.median(live)) if live else float("nan")}
    eq = g["dynamics"].size
    fixed = [int(np.sum(p.args[2] == p.args[3])) for p in problems]
    ineq = nlp.ng - eq
    nfree = nlp.nx_var - (float(np.median(fixed)) if fixed else 0.0)
    return {"vars": nlp.nx_var, "rows": nlp.ng, "eq": eq, "ineq": ineq,
            "params": nlp.np, "fixed": float(np.median(fixed)) if fixed else float("nan"),
            "jac_nnz": jac.nnz(), "hess_nnz": hess.nnz(),
            "kkt_dim": nfree + eq + 2 * ineq,
            "kkt_nnz": hess.nnz() + jac.nnz() + nfree + 3 * ineq + eq,
            "groups": groups, "links": nlp.L}


# ---------------------------------------------------------------- compiled evaluations
@dataclass
class Compiled:
    """Per function (name, SX virtual machine ms, compiled C ms per call) on a short chain."""

    links: int
    rows: list = field(default_factory=list)
    compile_s: float = float("nan")
    note: str = ""

    def speedup(self, name: str) -> float:
        """SX time / compiled time of one function (NaN if not measured)."""
        for n, sx, c in self.rows:
            if n == name and c > 0:
                return sx / c
        return float("nan")


def compiled_evals(base=(), horizon: float = 0.5, calls: int = 200) -> Compiled:
    """IPOPT's evaluation functions of a short switching chain, SX vs compiled C.

    The functions ``nlpsol`` generates for the switching NLP with ``mpc.horizon =
    horizon``, generated as C and compiled with the build cache's flags
    (:data:`hmpc_cli.mpc.cache.CFLAGS`); per call, the mean of ``calls`` Python calls
    (the call overhead, the same for both, included).
    """
    from hmpc_cli.mpc import cache

    cc = shutil.which("gcc") or shutil.which("cc")
    sysm, s = settings_of([*base, f"mpc.horizon={horizon}"])
    nlp = FixedModeNLP(sysm, s)
    out = Compiled(nlp.L)
    if cc is None:
        out.note = "no C compiler: not measured"
        return out
    fns = {k: nlp.session.cold.get_function(k) for k in EVALS}
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        gen = ca.CodeGenerator("profile_evals.c")
        for f in fns.values():
            gen.add(f)
        gen.generate(tmp + os.sep)
        lib = os.path.join(tmp, "profile_evals.so")
        start = time.perf_counter()
        done = subprocess.run([cc, *cache.CFLAGS, os.path.join(tmp, "profile_evals.c"), "-o",
                               lib], capture_output=True, text=True)
        out.compile_s = time.perf_counter() - start
        if done.returncode:
            out.note = f"compilation failed: {done.stderr.strip()[-200:]}"
            return out
        for name, f in fns.items():
            ext = ca.external(name, lib)
            args = [ca.DM(0.1 * rng.standard_normal(f.sparsity_in(i).shape))
                    for i in range(f.n_in())]
            per = []
            for h in (f, ext):
                h.call(args)
                best = np.inf
                for _ in range(3):
                    start = time.perf_counter()
                    for _ in range(calls):
                        h.call(args)
                    best = min(best, (time.perf_counter() - start) / calls)
                per.append(MS * best)
            out.rows.append((name, per[0], per[1]))
    return out


# ---------------------------------------------------------------------------- statistics
def _q(xs, q: float) -> float:
    xs = [x for x in xs if x is not None and np.isfinite(x)]
    return float(np.percentile(xs, q)) if xs else float("nan")


def med(xs) -> float:
    """Median (NaN when empty)."""
    return _q(xs, 50)


def p95(xs) -> float:
    """95th percentile (NaN when empty)."""
    return _q(xs, 95)


def _f(x, fmt: str = ".1f") -> str:
    return format(x, fmt) if x is not None and np.isfinite(x) else "-"


def time_split(ms: list) -> list[tuple[str, list[float]]]:
    """Per quantity (label, values per solve) of the per-solve table."""
    ok = [m for m in ms if m is not None]
    its = [max(m.iterations, 1) for m in ok]
    rows = [("IPOPT iterations", [m.iterations for m in ok]),
            ("wall time of the call [ms]", [MS * m.wall for m in ok]),
            ("IPOPT total (t_wall_total) [ms]", [MS * m.total for m in ok])]
    rows += [(f"  {k} [ms]", [MS * m.evals[k] for m in ok]) for k in EVALS]
    rows += [("  all evaluations [ms]", [MS * m.eval_time for m in ok]),
             ("  rest: MUMPS + IPOPT internals [ms]", [MS * m.rest for m in ok]),
             ("per iteration: total [ms]",
              [MS * m.total / n for m, n in zip(ok, its, strict=True)]),
             ("per iteration: evaluations [ms]",
              [MS * m.eval_time / n for m, n in zip(ok, its, strict=True)]),
             ("per iteration: MUMPS + IPOPT [ms]",
              [MS * m.rest / n for m, n in zip(ok, its, strict=True)]),
             ("nlp_hess_l calls", [m.calls["nlp_hess_l"] for m in ok]),
             ("nlp_jac_g calls", [m.calls["nlp_jac_g"] for m in ok]),
             ("hmpc + CasADi around IPOPT [ms]", [MS * (m.wall - m.total) for m in ok])]
    return rows


def share(ms: list, part) -> float:
    """Share of the summed IPOPT total that ``part(m)`` accounts for."""
    ok = [m for m in ms if m is not None]
    total = sum(m.total for m in ok)
    return sum(part(m) for m in ok) / total if total > 0 else float("nan")


def variant_row(prof: Profile, name: str, base: str = BASELINE) -> dict:
    """A variant against ``base`` on the problems both solved (paired)."""
    pairs = [(b, v) for b, v in zip(prof.meas[base], prof.meas[name], strict=True)
             if b is not None and v is not None]
    vs = [v for _, v in pairs]
    sum_b = sum(b.iterations for b, _ in pairs)
    return {"n": len(vs), "failed": sum(not v.success for v in vs),
            "it_med": med([v.iterations for v in vs]), "it_p95": p95([v.iterations for v in vs]),
            "it_mean": float(np.mean([v.iterations for v in vs])) if vs else float("nan"),
            "dit": med([v.iterations - b.iterations for b, v in pairs]),
            "it_sum": sum(v.iterations for v in vs) / sum_b if sum_b else float("nan"),
            "t_med": med([MS * v.total for v in vs]), "t_p95": p95([MS * v.total for v in vs]),
            "ratio": med([v.total / b.total for b, v in pairs if b.total > 0]),
            "t_sum": (sum(v.total for v in vs) / sum(b.total for b, _ in pairs)
                      if pairs else float("nan")),
            "per_it": med([MS * v.total / max(v.iterations, 1) for v in vs]),
            "viol": med([v.violation for v in vs]),
            "dcost": med([abs(v.cost - b.cost) / max(abs(b.cost), 1e-9) for b, v in pairs
                          if np.isfinite(v.cost) and np.isfinite(b.cost)])}


#: time-to-switch buckets (upper bound [s], label); the first: 1 node left
BUCKETS = ((None, "1 node (at or past the planned guard time)"), (0.1, "2 nodes to 0.1 s"),
           (0.2, "0.1-0.2 s"), (0.4, "0.2-0.4 s"), (np.inf, "> 0.4 s"))


def bucket_of(prob: Problem) -> str:
    """The time-to-switch bucket label of a problem."""
    if prob.ns.counts[0] <= 1:
        return BUCKETS[0][1]
    return next(label for hi, label in BUCKETS[1:] if prob.to_switch <= hi + 1e-9)


# ------------------------------------------------------------------------------ report
@dataclass
class Inputs:
    """Everything the report is written from."""

    prof: Profile
    infos: list
    kkt: dict
    loops: list
    compiled: Compiled
    machine: dict


def _head(x: Inputs, add) -> None:
    m, prof = x.machine, x.prof
    add("# Profile of the switching MPC solve (ball, Figure 3 trials)\n")
    add("Written by `python benchmarks/profile_switching.py --write "
        "results/bench/profile_switching.md`. Measurement only: nothing in hmpc changed.\n")
    add("## Machine and load\n")
    add(f"- CPU: {m['cpu']}, {m['cores']} cores; Python {m['python']}, CasADi {m['casadi']} "
        f"(IPOPT with MUMPS), NLPs in SX (HMPC_BUILD_CACHE={m.get('hmpc_build_cache')}), "
        f"git {m.get('git')}")
    add(f"- date {m['date_utc']}, run time {m['suite_seconds']} s; load average (1/5/15 min) "
        f"{m['load_average_start']} at the start, {m['load_average_end']} at the end; "
        f"process CPU time / wall time during the re-solves {_f(prof.cpu_wall, '.2f')} "
        f"(below 1: the process waited for a core)")
    add("- **All times are machine dependent** and were measured while other processes "
        "(other helpers' tests) shared the cores: read medians and p95, not single solves. "
        "Iteration counts do not depend on the machine.\n")
    add("## Recorded problems\n")
    add("Closed loop of `scenarios/ball.toml` (10 Hz fixed-mode MPC, 60 nodes/s, 3 s "
        "horizon, max_switches 10, first-order hold, plan once), nominal and Figure 3 "
        "disturbance trials (`disturbance.kind = \"paper_fig3\"`), as `sweeps/fig3.toml`'s "
        "\"10 Hz fixed\" runs them. A switching problem is a solve with at least one switch "
        "left (the switching NLP); the rest are final-domain solves.\n")
    add("| run | success | final error | switching solves | final solves |")
    add("|---|---|--:|--:|--:|")
    for r in x.infos:
        add(f"| {r.label} | {r.success} | {_f(r.final_error, '.4f')} | "
            f"{r.solves['switching']} | {r.solves['final']} |")
    add(f"| **all** | {sum(r.success for r in x.infos)}/{len(x.infos)} | | "
        f"{sum(r.solves['switching'] for r in x.infos)} | "
        f"{sum(r.solves['final'] for r in x.infos)} |\n")
    rec = [p.recorded for p in prof.problems]
    add(f"In the closed loop itself the {len(rec)} switching solves took median "
        f"{_f(med([MS * s.wall_time for s in rec]))} ms, p95 "
        f"{_f(p95([MS * s.wall_time for s in rec]))} ms, median "
        f"{_f(med([s.iterations for s in rec]), '.0f')} iterations (p95 "
        f"{_f(p95([s.iterations for s in rec]), '.0f')}). Everything below re-solves the "
        f"recorded problems in this process (the final-domain column: {len(prof.final)} "
        f"of them).\n")


#: IPOPT's phases (they partition OverallAlgorithm) and its linear-algebra timers
PHASES = ("InitializeIterates", "UpdateHessian", "UpdateBarrierParameter",
          "ComputeSearchDirection", "ComputeAcceptableTrialPoint", "AcceptTrialPoint",
          "CheckConvergence", "OutputIteration")
LINALG = (("PDSystemSolverTotal", "linear algebra in any phase: KKT solves (MUMPS), "
           "residuals, iterative refinement"),
          ("LinearSystemSymbolicFactorization", "MUMPS analysis (once per solve)"),
          ("LinearSystemFactorization", "MUMPS numeric factorization, as timed apart by "
           "IPOPT (0: this build does not time it apart; it is in the total above)"),
          ("LinearSystemBackSolve", "MUMPS back-solves"))


def _timers(prof: Profile) -> dict[str, float]:
    keys = ("OverallAlgorithm", *PHASES, *(k for k, _ in LINALG))
    return {k: sum(t.get(k, 0.0) for t in prof.timers) for k in keys}


def _per_solve(x: Inputs, add) -> None:
    prof = x.prof
    base = prof.meas[BASELINE]
    add("## 1. Per solve: iterations and where IPOPT's time goes\n")
    add("Baseline re-solve (the closed loop's warm IPOPT instance and shifted primal-dual "
        "warm start). Evaluations are CasADi's `t_wall_nlp_*` timers inside IPOPT; "
        "\"rest\" is IPOPT's `t_wall_total` minus them: the linear solver (MUMPS) and "
        "IPOPT's own work. Share: of the summed `t_wall_total`.\n")
    add("| quantity | switching median | switching p95 | switching share | final median | "
        "final p95 | final share |")
    add("|---|--:|--:|--:|--:|--:|--:|")
    fi_rows = dict(time_split(prof.final))
    shares = {f"  {k} [ms]": (lambda m, _k=k: m.evals[_k]) for k in EVALS}
    shares["  all evaluations [ms]"] = lambda m: m.eval_time
    shares["  rest: MUMPS + IPOPT internals [ms]"] = lambda m: m.rest
    for label, xs in time_split(base):
        fx, sh = fi_rows.get(label, []), shares.get(label)
        s1 = f"{_f(100 * share(base, sh), '.0f')} %" if sh else ""
        s2 = f"{_f(100 * share(prof.final, sh), '.0f')} %" if sh and prof.final else ""
        fmt = ".0f" if "calls" in label or "iterations" in label else ".2f"
        name = "&nbsp;&nbsp;" + label.strip() if label.startswith("  ") else label
        add(f"| {name} | {_f(med(xs), fmt)} | {_f(p95(xs), fmt)} | {s1} | {_f(med(fx), fmt)} "
            f"| {_f(p95(fx), fmt)} | {s2} |")
    add("")
    add("### IPOPT's own timing statistics (switching problems, summed over the solves)\n")
    add("One more pass over the same problems with IPOPT's `print_timing_statistics` "
        "(1 ms resolution per solve, summed). The phases partition the algorithm; the "
        "linear-algebra timers cut across them (the adaptive barrier update solves extra "
        "KKT systems). Function evaluations: CasADi's timers of the same pass.\n")
    add("| part | summed [ms] | share of the algorithm |")
    add("|---|--:|--:|")
    t = _timers(prof)
    overall = t["OverallAlgorithm"]

    def pct(v):
        return f"{_f(100 * v / overall, '.0f')} %" if overall else "- %"

    add(f"| whole IPOPT algorithm (`OverallAlgorithm`) | {_f(MS * overall)} | {pct(overall)} |")
    for k in PHASES:
        add(f"| &nbsp;&nbsp;phase `{k}` | {_f(MS * t[k])} | {pct(t[k])} |")
    for k, label in LINALG:
        add(f"| {label} (`{k}`) | {_f(MS * t[k])} | {pct(t[k])} |")
    ev = sum(m.eval_time for m in prof.meas["timing statistics pass"] if m is not None)
    other = overall - t["PDSystemSolverTotal"] - ev
    add(f"| function evaluations (CasADi `t_wall_nlp_*`) | {_f(MS * ev)} | {pct(ev)} |")
    add(f"| rest of IPOPT (algorithm - linear algebra - evaluations) | {_f(MS * other)} | "
        f"{pct(other)} |\n")
    c = x.compiled
    add("### Evaluations compiled (short chain)\n")
    add(f"IPOPT's evaluation functions of the switching NLP with a 0.5 s horizon ({c.links} "
        f"links instead of {x.kkt['switching']['links']}: the full one is ~5 min of "
        f"compiler time), generated as C and compiled with the build cache's flags "
        f"(compile {_f(c.compile_s)} s); per call, best of 3 x 200 Python calls (call "
        f"overhead included in both). {c.note}\n")
    add("| function | SX virtual machine [ms/call] | compiled C [ms/call] | speed-up |")
    add("|---|--:|--:|--:|")
    for name in EVALS:
        row = next((r for r in c.rows if r[0] == name), None)
        add(f"| {name} | {_f(row[1], '.3f') if row else '-'} | "
            f"{_f(row[2], '.3f') if row else '-'} | {_f(c.speedup(name), '.1f')} |")
    add("")


def _kkt(x: Inputs, add) -> None:
    add("## 2. KKT size per NLP\n")
    add("Rows with infinite bounds (an inactive guard row, a hold link's) stay in IPOPT's "
        "KKT system as free inequality rows. KKT dimension: free variables + equality rows "
        "+ 2 x inequality rows (row + slack), as IPOPT's augmented system; its nonzeros are "
        "approximate (lower triangle: Hessian + Jacobian + diagonals). Hessian: one triangle, "
        "as IPOPT takes it.\n")
    add("| | switching NLP | final NLP |")
    add("|---|--:|--:|")
    sw, fi = x.kkt["switching"], x.kkt["final"]
    for key, label, fmt in (
            ("links", "chain links L (nodes L + 1)", "d"), ("vars", "variables", "d"),
            ("fixed", "fixed by bounds per solve (median)", ".0f"),
            ("rows", "constraint rows", "d"), ("eq", "&nbsp;&nbsp;equality (dynamics)", "d"),
            ("ineq", "&nbsp;&nbsp;inequality", "d"), ("params", "parameters", "d"),
            ("jac_nnz", "nonzeros of the Jacobian of g", "d"),
            ("hess_nnz", "nonzeros of the Hessian of the Lagrangian", "d"),
            ("kkt_dim", "KKT dimension (IPOPT)", ".0f"),
            ("kkt_nnz", "KKT nonzeros (approx.)", ".0f")):
        add(f"| {label} | {_f(sw[key], fmt)} | {_f(fi[key], fmt)} |")
    add("")
    add("Row groups (rows with finite bounds: median over the recorded problems of that "
        "NLP):\n")
    add("| row group | switching rows | Jacobian nonzeros | with finite bounds | final rows | "
        "final with finite bounds |")
    add("|---|--:|--:|--:|--:|--:|")
    empty = {"rows": 0, "jac_nnz": 0, "live": float("nan")}
    for name in GROUPS:
        a, b = sw["groups"].get(name, empty), fi["groups"].get(name, empty)
        add(f"| {name} | {a['rows']} | {a['jac_nnz']} | {_f(a['live'], '.0f')} | "
            f"{b['rows']} | {_f(b['live'], '.0f')} |")
    add("")


def _vtable(x: Inputs, add, names, base: str, extra: bool = False) -> None:
    head = ("| variant | solves | failed | iterations median | mean | p95 | median change | "
            "sum of iterations / base | time median [ms] | p95 [ms] | time / base (median) | "
            "per iteration [ms] |")
    sep = "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"
    if extra:
        head += " max violation (median) | cost gap (median) |"
        sep += "--:|--:|"
    add(head)
    add(sep)
    for name in names:
        r = variant_row(x.prof, name, base)
        line = (f"| {name} | {r['n']} | {r['failed']} | {_f(r['it_med'], '.0f')} | "
                f"{_f(r['it_mean'])} | {_f(r['it_p95'], '.0f')} | {_f(r['dit'], '+.0f')} | "
                f"{_f(r['it_sum'], '.2f')} | {_f(r['t_med'])} | {_f(r['t_p95'])} | "
                f"{_f(r['ratio'], '.2f')} | {_f(r['per_it'], '.2f')} |")
        if extra:
            line += f" {_f(r['viol'], '.1e')} | {_f(r['dcost'], '.1e')} |"
        add(line)
    add("")


def _variants(x: Inputs, add) -> None:
    of = {sec: [v.name for v in VARIANTS if v.section == sec]
          for sec in ("rows", "warm", "rows_cold", "ipopt")}
    add("## 3. Row groups relaxed (same problems)\n")
    add("Each group relaxed through its bounds on the same NLP; time is IPOPT's "
        "`t_wall_total`; \"median change\" and \"time / base\" are medians of the per-problem "
        "differences and ratios, \"sum of iterations / base\" the ratio of the sums (it "
        "weighs the long solves). \"no virtual node\" is `robust = false`'s problem data "
        "(virtual input fixed at 0); \"hard constraints\" is `soft_penalty = 0` (slacks fixed "
        "at 0); \"guard hit as one equality row\" replaces the pair |q_G| <= sigma by "
        "q_G = sigma. A relaxed problem has another solution, so from the closed loop's warm "
        "start (first table) the iterations include the way to it; the second table starts "
        "both the baseline and the relaxed problem cold (state held, inputs 0).\n")
    add("From the closed loop's warm start (base: the baseline):\n")
    _vtable(x, add, [BASELINE, *of["rows"]], BASELINE)
    add("From the cold start (base: the cold baseline):\n")
    _vtable(x, add, [COLD, *of["rows_cold"]], COLD)
    add("## 4. Warm start\n")
    add("The closed loop's warm start is the previous solution shifted by the elapsed nodes "
        "(primal and dual, warm IPOPT instance: mu_init 1e-6, bound push 1e-9). \"primal "
        "only\" runs IPOPT's cold instance (mu_init 0.1) from the same shifted primal point; "
        "\"previous solution unshifted\" is n/a for a run's first solve (cold in the closed "
        "loop).\n")
    _vtable(x, add, [BASELINE, *of["warm"]], BASELINE)
    add("## 5. IPOPT options (same NLP, same warm start)\n")
    add(f"The L-BFGS row is capped at {LBFGS_MAX_ITER} iterations (a capped solve counts as "
        f"failed). The last row stops IPOPT after 3 iterations (an interior-point stand-in "
        f"for a real-time iteration): its max violation and relative cost gap to the "
        f"baseline's solution.\n")
    _vtable(x, add, [BASELINE, *of["ipopt"]], BASELINE, extra=True)


def _loops(x: Inputs, add) -> None:
    add("## 6. Structural settings in closed loop\n")
    add("The closed loop run again (nominal + the same trials) with one setting changed: "
        "its own switching solves, different problems from the recorded ones (compare "
        "distributions; time is the closed loop's solve time). Variables of the switching "
        "NLP from its chain length. Each row ran at another moment on a shared machine: its "
        "time is noisier than the same-problem re-solves above (between two runs of this "
        "script a row's median moved by up to ~20 %); its iterations are not.\n")
    add("| setting | switching NLP variables | runs succeeded | median final error | "
        "switching solves | iterations median | p95 | time median [ms] | p95 [ms] |")
    add("|---|--:|--:|--:|--:|--:|--:|--:|--:|")
    for lv in x.loops:
        st = lv.stats
        add(f"| {lv.label} | {lv.size} | {sum(r.success for r in lv.runs)}/{len(lv.runs)} | "
            f"{_f(med([r.final_error for r in lv.runs]), '.4f')} | {len(st)} | "
            f"{_f(med([s.iterations for s in st]), '.0f')} | "
            f"{_f(p95([s.iterations for s in st]), '.0f')} | "
            f"{_f(med([MS * s.wall_time for s in st]))} | "
            f"{_f(p95([MS * s.wall_time for s in st]))} |")
    add("")


def _stat_row(label: str, ms: list) -> str:
    return (f"| {label} | {len(ms)} | {_f(med([m.iterations for m in ms]), '.0f')} | "
            f"{_f(p95([m.iterations for m in ms]), '.0f')} | "
            f"{max((m.iterations for m in ms), default='-')} | "
            f"{_f(med([MS * m.total for m in ms]))} | {_f(p95([MS * m.total for m in ms]))} |")


def _distance(x: Inputs, add) -> None:
    probs, base = x.prof.problems, x.prof.meas[BASELINE]
    pairs = [(p, m) for p, m in zip(probs, base, strict=True) if m is not None]
    add("## 7. Iterations vs the time to the next planned switch\n")
    add("Baseline re-solve of the warm-started problems (the runs' first, cold solves are "
        "in the context table only); time to the switch = intervals left in the current "
        "domain x node step (1 node: the planned guard time is now or has passed without "
        "an impact).\n")
    head = ("| {} | solves | iterations median | p95 | max | time median [ms] | p95 [ms] |\n"
            "|---|--:|--:|--:|--:|--:|--:|")
    add(head.format("time to the next switch"))
    for _, label in BUCKETS:
        add(_stat_row(label, [m for p, m in pairs if p.context != "cold (new plan)"
                              and bucket_of(p) == label]))
    add("")
    add(head.format("solve context"))
    for c in ("cold (new plan)", "after impact", "shifted"):
        add(_stat_row(c, [m for p, m in pairs if p.context == c]))
    for k in sorted({len(p.ns.guards) for p in probs}):
        add(_stat_row(f"{k} switch{'es' if k > 1 else ''} left (all contexts)",
                      [m for p, m in pairs if len(p.ns.guards) == k]))
    add("")


def report(x: Inputs) -> str:
    """The Markdown report (fixed structure; '-' where a number is not available)."""
    lines: list[str] = []
    for part in (_head, _per_solve, _kkt, _variants, _loops, _distance):
        part(x, lines.append)
    lines += findings(x)
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------- findings
def _facts(x: Inputs, rows: dict) -> list[str]:
    prof, sw, fi = x.prof, x.kkt["switching"], x.kkt["final"]
    base = [m for m in prof.meas[BASELINE] if m is not None]
    ev, rest = share(base, lambda m: m.eval_time), share(base, lambda m: m.rest)
    hess = share(base, lambda m: m.evals["nlp_hess_l"])
    jac = share(base, lambda m: m.evals["nlp_jac_g"])
    t = _timers(prof)
    overall = t["OverallAlgorithm"] or float("nan")
    b = rows[BASELINE]
    live = sum(g["live"] for n, g in sw["groups"].items() if n != "dynamics")
    out = ["## What the profile says\n", "Facts (this run):\n"]
    f_it = med([m.iterations for m in prof.final])
    f_per = med([MS * m.total / max(m.iterations, 1) for m in prof.final])
    it_x, per_x = b["it_med"] / f_it, b["per_it"] / f_per
    first, second = ("its iterations", "its cost per iteration") if it_x >= per_x else \
        ("its cost per iteration", "its iterations")
    out.append(
        f"- A switching solve takes median {_f(b['it_med'], '.0f')} iterations (mean "
        f"{_f(b['it_mean'])}, p95 {_f(b['it_p95'], '.0f')}) at {_f(b['per_it'], '.2f')} ms "
        f"per iteration, median {_f(b['t_med'])} ms (p95 {_f(b['t_p95'])} ms); a final-domain "
        f"solve {_f(f_it, '.0f')} iterations at {_f(f_per, '.2f')} ms. Against the final "
        f"solve it has x{_f(it_x, '.1f')} the iterations and x{_f(per_x, '.1f')} the cost per "
        f"iteration: slow by {first} first, {second} second.")
    out.append(
        f"- Where the time goes: function evaluations {_f(100 * ev, '.0f')} % of IPOPT's time "
        f"(Hessian of the Lagrangian {_f(100 * hess, '.0f')} %, constraint Jacobian "
        f"{_f(100 * jac, '.0f')} %), MUMPS + IPOPT {_f(100 * rest, '.0f')} %. IPOPT's "
        f"statistics: linear algebra {_f(100 * t['PDSystemSolverTotal'] / overall, '.0f')} % "
        f"of the algorithm (MUMPS's analysis, redone every solve, "
        f"{_f(100 * t['LinearSystemSymbolicFactorization'] / overall, '.0f')} %); the "
        f"adaptive barrier update {_f(100 * t['UpdateBarrierParameter'] / overall, '.0f')} %.")
    out.append(
        f"- KKT size: the switching NLP has {sw['vars']} variables and {sw['rows']} rows "
        f"({sw['jac_nnz']} Jacobian, {sw['hess_nnz']} Hessian nonzeros, KKT dimension "
        f"{sw['kkt_dim']:.0f}) against {fi['vars']}, {fi['rows']} and {fi['kkt_dim']:.0f} for "
        f"the final NLP; of its {sw['ineq']} inequality rows only ~{live:.0f} have a finite "
        f"bound in a solve: the rest are free rows IPOPT still carries.")
    parts = []
    for name, _ in ROW_TRANSFORMS:
        w, c = rows[name], rows[f"{name} [cold]"]
        parts.append(f"{name}: warm {_f(w['dit'], '+.0f')} it. (sum x{_f(w['it_sum'], '.2f')}, "
                     f"time x{_f(w['ratio'], '.2f')}), cold {_f(c['dit'], '+.0f')} it. (sum "
                     f"x{_f(c['it_sum'], '.2f')}, {c['failed']} failed)")
    cheapest = min((name for name, _ in ROW_TRANSFORMS[:-1]),
                   key=lambda k: rows[f"{k} [cold]"]["it_sum"]
                   if np.isfinite(rows[f"{k} [cold]"]["it_sum"]) else np.inf)
    every = rows[f"{ROW_TRANSFORMS[-1][0]} [cold]"]
    out.append("- Row groups relaxed (median change per problem; ratio of the iteration "
               "sums): " + "; ".join(parts) + f". From the cold start all hybrid rows "
               f"together cost x{_f(1 / every['it_sum'], '.2f')} the iterations of the "
               f"dynamics alone; the single group whose relaxation saves most is \"{cheapest}\" "
               f"(sum x{_f(rows[cheapest + ' [cold]']['it_sum'], '.2f')}). From the warm start "
               f"a relaxed problem has another solution, and the iterations mostly measure the "
               f"way to it.")
    w = {k: rows[name] for k, name in (("primal", "primal only (shifted), cold instance"),
                                       ("unshifted", "previous solution unshifted, "
                                                     "primal-dual"), ("cold", COLD))}
    out.append(
        f"- Warm start helps: shifted primal-dual median {_f(b['it_med'], '.0f')} iterations; "
        f"primal only {_f(w['primal']['it_med'], '.0f')} (time x{_f(w['primal']['ratio'], '.2f')})"
        f", the unshifted previous solution {_f(w['unshifted']['it_med'], '.0f')} "
        f"(x{_f(w['unshifted']['ratio'], '.2f')}), cold {_f(w['cold']['it_med'], '.0f')} "
        f"(x{_f(w['cold']['ratio'], '.2f')}, {w['cold']['failed']} failed).")
    pairs = [(p, m) for p, m in zip(prof.problems, prof.meas[BASELINE], strict=True)
             if m is not None and p.context != "cold (new plan)"]
    by = [(label, [m.iterations for p, m in pairs if bucket_of(p) == label])
          for _, label in BUCKETS]
    ctx = {c: [m.iterations for p, m in pairs if p.context == c]
           for c in ("after impact", "shifted")}
    cold_first = [m.iterations for p, m in zip(prof.problems, prof.meas[BASELINE], strict=True)
                  if m is not None and p.context == "cold (new plan)"]
    out.append(
        "- Distance to the guard (warm solves, median iterations): "
        + ", ".join(f"{label}: {_f(med(its), '.0f')} ({len(its)})" for label, its in by)
        + f". Contexts: the runs' first (cold) solves {_f(med(cold_first), '.0f')}, after an "
          f"impact {_f(med(ctx['after impact']), '.0f')}, shifted "
          f"{_f(med(ctx['shifted']), '.0f')}.\n")
    return out


def _saving(r: dict) -> float:
    return 1.0 - r["ratio"] if np.isfinite(r["ratio"]) else float("nan")


def _levers(x: Inputs, rows: dict) -> list[tuple[str, float, bool, str]]:
    """(lever, saving of the median switching solve, checked?, evidence).

    checked: the saving keeps the converged solution, or the closed loop ran with it; a
    lever that changes the solution without a closed-loop run here counts half in the
    ranking.
    """
    prof, sw = x.prof, x.kkt["switching"]
    base = [m for m in prof.meas[BASELINE] if m is not None]
    t = _timers(prof)
    overall = t["OverallAlgorithm"] or float("nan")
    la = t["PDSystemSolverTotal"] / overall
    loops = {lv.label: lv for lv in x.loops}
    ref = loops.get(CLOSED_LOOP[0][0])
    ref_t = med([MS * s.wall_time for s in ref.stats]) if ref else float("nan")

    def loop(label):
        lv = loops.get(label)
        if lv is None or not lv.stats:
            return float("nan"), "not run (--quick)"
        tm = med([MS * s.wall_time for s in lv.stats])
        its = med([s.iterations for s in lv.stats])
        ref_it = med([s.iterations for s in ref.stats])
        return 1 - tm / ref_t, (f"closed loop median {_f(tm)} vs {_f(ref_t)} ms, "
                                f"{_f(its, '.0f')} vs {_f(ref_it, '.0f')} iterations, "
                                f"{sum(r.success for r in lv.runs)}/{len(lv.runs)} runs "
                                f"succeeded, median final error "
                                f"{_f(med([r.final_error for r in lv.runs]), '.4f')}")

    c = x.compiled
    comp = sum(share(base, lambda m, _k=k: m.evals[_k]) * (1 - 1 / c.speedup(k))
               for k in EVALS if np.isfinite(c.speedup(k)))
    lb, tol, rti = rows[LBFGS], rows["tol = 1e-6 (default 1e-8)"], \
        rows["stopped after 3 iterations (RTI-like)"]
    mono, spral = rows["mu_strategy = monotone"], rows["linear_solver = spral (default mumps)"]
    hit = rows["guard hit as one equality row"]
    fewer, fewer_txt = loop("nodes_per_second = 30")
    fewer20, fewer20_txt = loop("nodes_per_second = 20")
    short, short_txt = loop("max_switches = 3")
    euler, euler_txt = loop('integrator = "euler"')
    ev = share(base, lambda m: m.eval_time)
    speedups = ", ".join(f"{k} x{_f(c.speedup(k), '.1f')}" for k in ("nlp_hess_l", "nlp_jac_g"))
    return [
        ("Fewer nodes (+ a higher-order integrator per interval to keep the accuracy)",
         fewer, True, f"nodes_per_second 60 -> 30 halves the chain: {fewer_txt}; 60 -> 20: "
         f"{fewer20_txt}. Both the KKT size and the per-iteration cost scale with the nodes"),
        ("Compiled evaluations (the build cache's compiled library instead of the SX "
         "virtual machine)", comp, bool(c.rows),
         f"evaluations are {_f(100 * ev, '.0f')} % of IPOPT's time; compiled, the short "
         f"chain's functions ran {speedups} faster: applied to each function's share. The "
         f"cache compiles the switching NLP once (~5 min of compiler time)"),
        ("RTI / a fixed small iteration budget per period (SQP-RTI with an exact, "
         "regularised Hessian and a structure-exploiting QP)", _saving(rti), False,
         f"IPOPT stopped after 3 iterations: time x{_f(rti['ratio'], '.2f')}, max violation "
         f"{_f(rti['viol'], '.1e')}, cost gap {_f(rti['dcost'], '.1e')} (not a closed-loop "
         f"test; SQP + HPIPM with a Gauss-Newton Hessian fell back to IPOPT on 26 of 35 "
         f"switching solves, and L-BFGS needs {_f(lb['it_med'], '.0f')} iterations with "
         f"{lb['failed']} of {lb['n']} solves capped: the exact Hessian is worth its cost)"),
        ("A linear solver without re-analysis per solve (SPRAL measured; HSL MA27/MA57 "
         "not in this build)", _saving(spral), True,
         f"linear algebra is {_f(100 * la, '.0f')} % of IPOPT's algorithm, MUMPS's analysis "
         f"{_f(100 * t['LinearSystemSymbolicFactorization'] / overall, '.0f')} %; SPRAL: "
         f"time x{_f(spral['ratio'], '.2f')}, {spral['failed']} failed"),
        ("A chain sized to the schedule (no free rows of unused switches)", short, True,
         f"{sw['ineq']} inequality rows, ~"
         f"{sum(g['live'] for n, g in sw['groups'].items() if n != 'dynamics'):.0f} bounded per"
         f" solve; max_switches 10 -> 3: {short_txt}"),
        ("Reformulate the guard hit (one equality row instead of |q_G| <= sigma)",
         _saving(hit), True, f"{_f(hit['dit'], '+.0f')} iterations (sum "
         f"x{_f(hit['it_sum'], '.2f')}), time x{_f(hit['ratio'], '.2f')} on the same problems "
         f"({hit['failed']} failed)"),
        ("Barrier strategy monotone", _saving(mono), True,
         f"{_f(mono['dit'], '+.0f')} iterations (sum x{_f(mono['it_sum'], '.2f')}), time "
         f"x{_f(mono['ratio'], '.2f')}"),
        ("Looser tolerance (tol 1e-6)", _saving(tol), True,
         f"{_f(tol['dit'], '+.0f')} iterations (sum x{_f(tol['it_sum'], '.2f')}), time "
         f"x{_f(tol['ratio'], '.2f')}" + (": the solves reach 1e-6 and 1e-8 in the same "
                                          "iteration" if tol["it_sum"] > 0.95 else "")),
        ("Euler instead of RK4", euler, True, f"{euler_txt} (cheaper evaluations, a less "
                                              f"accurate model)"),
        ("Quasi-Newton Hessian (L-BFGS)", _saving(lb), True,
         f"median {_f(lb['it_med'], '.0f')} iterations, {lb['failed']} of {lb['n']} capped at "
         f"{LBFGS_MAX_ITER}: a dead end"),
    ]


def findings(x: Inputs) -> list[str]:
    """The "what the profile says" section: facts and ranked levers, from the numbers."""
    rows = {v.name: variant_row(x.prof, v.name,
                                COLD if v.section == "rows_cold" else BASELINE)
            for v in VARIANTS}
    out = _facts(x, rows)
    def rank(lv):
        saving = lv[1] if np.isfinite(lv[1]) else -9.0
        return -(saving if lv[2] or saving < 0 else 0.5 * saving)

    levers = sorted(_levers(x, rows), key=rank)
    out.append("Levers, ranked by the saving of the median switching-solve time measured in "
               "this run (IPOPT's time on the same problems, or the closed loop's; compiled "
               "evaluations: measured per function on a short chain and applied to the "
               "evaluation shares). A lever that changes the solution and was not run in "
               "closed loop here (*unchecked*) counts half; negative: slower; '-': not run:\n")
    for i, (name, saving, checked, why) in enumerate(levers, 1):
        tag = "" if checked else " (*unchecked*)"
        out.append(f"{i}. **{name}**{tag}: {_f(100 * saving, '+.0f')} % time saved. {why}.")
    return out


# -------------------------------------------------------------------------------- main
def profile(trials, base=(), loop_variants=CLOSED_LOOP, progress=False,
            compile_evals=True) -> Inputs:
    """Records, re-solves and runs the closed-loop variants; returns the report's inputs."""
    os.environ.setdefault("HMPC_BUILD_CACHE", "off")
    if progress:
        print("recording the closed loop", flush=True)
    problems, infos = record_all(trials, base, progress)
    sysm, s = settings_of(base)
    nlps = {"switching": FixedModeNLP(sysm, s), "final": FixedModeNLP(sysm, s, switches=0)}
    switching = [p for p in problems if p.nlp == "switching"]
    final = [p for p in problems if p.nlp == "final"]
    kkt = {k: kkt_size(nlp, [p for p in problems if p.nlp == k]) for k, nlp in nlps.items()}
    if progress:
        print(f"re-solving {len(switching)} switching problems x {len(VARIANTS)} variants",
              flush=True)
    prof = replay(switching, nlps["switching"], progress=progress)
    prof.final = replay_final(final, nlps["final"])
    if progress:
        print("compiled evaluations (short chain)", flush=True)
    compiled = compiled_evals(base) if compile_evals else Compiled(0, note="not asked for")
    loops = []
    for label, ov in loop_variants:
        if progress:
            print(f"closed loop: {label}", flush=True)
        if not ov:
            loops.append(LoopVariant(label, [p.recorded for p in switching], infos,
                                     _size_of(sysm, s)))
        else:
            loops.append(closed_loop(label, [*base, *ov], trials))
    return Inputs(prof, infos, kkt, loops, compiled, {})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, nargs="+", default=None,
                    help=f"disturbed Figure 3 trials (default {TRIALS[0]}-{TRIALS[-1]})")
    ap.add_argument("--quick", action="store_true",
                    help=f"trials {' '.join(map(str, QUICK_TRIALS))}, two closed-loop variants")
    ap.add_argument("--no-compile", action="store_true",
                    help="skip the compiled-evaluation measurement (~10-20 s of compiling)")
    ap.add_argument("--write", default=None, help="write the Markdown report here")
    args = ap.parse_args(argv)
    trials = args.trials or (QUICK_TRIALS if args.quick else TRIALS)
    loops = [v for v in CLOSED_LOOP if not args.quick or v[0] in QUICK_CLOSED_LOOP]
    os.environ.setdefault("HMPC_BUILD_CACHE", "off")
    load0, start, git = os.getloadavg(), time.perf_counter(), suite_report.git_describe()
    x = profile(trials, loop_variants=loops, progress=True,
                compile_evals=not args.no_compile)
    argv_used = ["python", *sys.argv] if argv is None else ["profile_switching.py", *argv]
    x.machine = suite_report.machine(argv_used, load0, time.perf_counter() - start, trials,
                                     [], git)
    text = report(x)
    print(text)
    if args.write:
        Path(args.write).parent.mkdir(parents=True, exist_ok=True)
        Path(args.write).write_text(text)
        print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
