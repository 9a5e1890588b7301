"""The benchmark suite's peers of hmpc: the authors' baseline and do-mpc's default MPC.

* :class:`AuthorsBaseline`: what the reference code does on every MPC call (see
  ``shared/reference/README.md``): build the NLP from scratch (transcription + ``nlpsol``)
  and solve it cold with IPOPT's default options. The NLP is hmpc's own (same rows, same
  cost), transcribed anew each call; its primal guess is the recorded one (the reference
  took the plan's rollout, never the previous solution).
* :class:`DoMPCFinal`: do-mpc's default MPC (orthogonal collocation, Radau degree 2, one
  finite element per step, IPOPT with do-mpc's defaults, warm-started from its previous
  solution) on the final-domain problem: the final mode's flow, the same stage cost
  weighted by the node step, the same horizon, node step and input box, and the
  final domain's guard-avoid rows as soft constraints with the same L1 penalty.
  Built once per run from the system's CasADi functions; reset at each trial's first call.

Both return :class:`~hmpc_cli.core.messages.SolveStats` (``wall_time`` [s] of the whole call).
"""

from __future__ import annotations

import time
import warnings

import casadi as ca
import numpy as np

from hmpc_cli.core.messages import SolveStats
from hmpc_cli.mpc.chain.nlp import FixedModeNLP

#: IPOPT silent (printing is not part of any solve compared here)
SILENT = {"ipopt": {"print_level": 0, "sb": "yes"}, "print_time": False}


def _stats(status: str, ok: bool, iterations: int, wall: float, cost: float) -> SolveStats:
    return SolveStats(status, ok, iterations, wall, cost, float("nan"))


class AuthorsBaseline:
    """Rebuild + cold IPOPT (CasADi's default options) on every call.

    Args:
        template: the NLP to transcribe anew each call (its settings and schedule rows).

    Attributes:
        splits: per call, {"transcription", "nlpsol", "solve"} [s].
    """

    def __init__(self, template: FixedModeNLP) -> None:
        """Keeps the template (nothing is built until a call)."""
        self.template = template
        self.splits: list[dict[str, float]] = []

    def __call__(self, args: tuple) -> SolveStats:
        """Builds and solves one recorded problem ``(w0, p, lbx, ubx, lbg, ubg, lam_x, lam_g)``."""
        w0, p, lbx, ubx, lbg, ubg = args[:6]
        start = time.perf_counter()
        nlp, _ = self.template._transcription()
        built = time.perf_counter()
        solver = ca.nlpsol("authors", "ipopt", nlp, SILENT)
        made = time.perf_counter()
        try:
            sol = solver(x0=w0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        except RuntimeError as exc:  # NaN evaluations
            wall = time.perf_counter() - start
            return _stats(f"error: {str(exc).strip()[-80:]}", False, 0, wall, float("nan"))
        end = time.perf_counter()
        st = solver.stats()
        self.splits.append({"transcription": built - start, "nlpsol": made - built,
                            "solve": end - made})
        return _stats(str(st["return_status"]), bool(st["success"]), int(st["iter_count"]),
                      end - start, float(sol["f"]))


def import_do_mpc():
    """The ``do_mpc`` module, or None when it is not installed (its import warnings muted)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            import do_mpc
    except ImportError:
        return None
    return do_mpc


class DoMPCFinal:
    """do-mpc's default MPC of the final domain, built from the system's CasADi functions.

    Args:
        do_mpc: the imported module (see :func:`import_do_mpc`).
        nlp: hmpc's final-domain NLP (S = 0): its system, horizon, node step, input box,
            guard-avoid offsets and soft penalty.

    Attributes:
        build_time: seconds spent in do-mpc's model and MPC set-up.
    """

    def __init__(self, do_mpc, nlp: FixedModeNLP) -> None:
        """Builds do-mpc's model and MPC (not timed in the table)."""
        start = time.perf_counter()
        sysm, final = nlp.system, nlp.system.mode_index(nlp.system.final_mode)
        model = do_mpc.model.Model("continuous", "SX")
        x = model.set_variable("_x", "x", (sysm.n_x, 1))
        u = model.set_variable("_u", "u", (sysm.n_u, 1))
        model.set_rhs("x", sysm.modes[final].flow(x, u, ca.DM.zeros(sysm.n_w)))
        model.setup()
        mpc = do_mpc.controller.MPC(model)
        mpc.settings.n_horizon = nlp.N
        mpc.settings.t_step = nlp.dt
        mpc.settings.supress_ipopt_output()
        cost = nlp.dt * sysm.stage_cost(x, u)
        mpc.set_objective(lterm=cost, mterm=ca.DM(0.0))
        mpc.set_rterm(u=0.0)  # do-mpc's default (no input-rate penalty), set explicitly
        lo, hi = nlp.input_boxes[final]
        mpc.bounds["lower", "_u", "u"] = lo
        mpc.bounds["upper", "_u", "u"] = hi
        for gi in nlp.row_guards:  # s q(z) - kappa >= 0, relaxed by an L1-penalised slack
            guard, kappa = sysm.guards[gi], nlp.avoid_offsets[gi][1]
            mpc.set_nl_cons(f"avoid_{guard.name}", kappa - guard.q_expr(x), ub=0.0,
                            soft_constraint=True, penalty_term_cons=nlp.s.soft_penalty)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mpc.setup()
        self.mpc, self.n_x, self._trial = mpc, sysm.n_x, None
        self.build_time = time.perf_counter() - start

    def __call__(self, trial: int, x0: np.ndarray) -> SolveStats:
        """One ``make_step`` from state x0 (shape (n,)); a new trial resets the guess."""
        mpc = self.mpc
        x0 = np.asarray(x0, dtype=float).reshape(self.n_x, 1)
        if trial != self._trial:  # a new closed loop: do-mpc's initial guess from x0
            mpc.reset_history()
            mpc.x0 = x0
            mpc.set_initial_guess()
            mpc.flags["initial_run"] = False  # no dual warm start from another trial
            self._trial = trial
        start = time.perf_counter()
        try:
            mpc.make_step(x0)
        except RuntimeError as exc:
            wall = time.perf_counter() - start
            return _stats(f"error: {str(exc).strip()[-80:]}", False, 0, wall, float("nan"))
        wall = time.perf_counter() - start
        st = mpc.solver_stats  # do-mpc keeps no objective value: cost NaN
        return _stats(str(st["return_status"]), bool(st["success"]), int(st["iter_count"]),
                      wall, float("nan"))
