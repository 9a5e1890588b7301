"""One solver session of a parametric NLP: options, cold and warm instances, solves.

Both MPC NLPs solve through a :class:`SolverSession`: it builds the plugin's options
(:func:`plugin_options`), a cold instance and, for IPOPT, a warm-start instance
(:class:`WarmStart`), and turns every solve into a :class:`SolveResult` with the
:class:`~hmpc_cli.core.messages.SolveStats` of the closed loop. The back-end ``sqp_hpipm``
(:mod:`hmpc_cli.mpc.backends`: SQP, Gauss-Newton Hessian, HPIPM on the NLP's stage
structure) runs a bounded number of iterations from the primal-dual warm start; a solve
it fails is solved again by IPOPT (built on first use) and marked ``fallback``. A solve
never raises on a solver failure (CasADi's ``RuntimeError`` on NaN evaluations becomes a
failed solve with status ``"error: ..."``); it does raise ``KeyboardInterrupt`` when the
user interrupted IPOPT: CasADi catches the interrupt inside IPOPT's callbacks and returns
the status ``NonIpopt_Exception_Thrown``, which the session turns back into the interrupt.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.core.messages import SolveStats
from hmpc_cli.mpc.backends import OCPStructure, rti_success, sqp_options

INTERRUPTED = "NonIpopt_Exception_Thrown"


@dataclass(frozen=True)
class WarmStart:
    """Options of the warm IPOPT instance (primal-dual warm starts).

    Attributes:
        mu_init: initial barrier parameter.
        bound_push: ``warm_start_{bound,mult_bound,slack_bound}_push``.
    """

    mu_init: float
    bound_push: float


@dataclass(frozen=True)
class SolveResult:
    """One solve.

    Attributes:
        x: primal point, shape (nx,) (the initial guess if the solver raised).
        lam_x: bound multipliers, shape (nx,) (None if the solver raised).
        lam_g: row multipliers, shape (ng,) (None if the solver raised).
        stats: status, success, iterations, wall time, cost, max violation (slack 0).
    """

    x: np.ndarray
    lam_x: np.ndarray | None
    lam_g: np.ndarray | None
    stats: SolveStats


def failed(w0: np.ndarray, message: str, wall: float = 0.0) -> SolveResult:
    """A failed solve at ``w0`` with status ``"error: "`` + the message's last line."""
    lines = [ln.strip() for ln in message.splitlines() if ln.strip()]
    status = "error: " + (lines[-1] if lines else "RuntimeError")[:160]
    return SolveResult(w0, None, None, SolveStats(status, False, 0, wall, np.nan, np.inf))


def plugin_options(plugin: str, max_iter: int, tol: float = 1e-8,
                   max_wall_time: float | None = None, equality: list[bool] | None = None,
                   extra: dict | None = None) -> dict:
    """CasADi ``nlpsol`` options of the cold instance.

    Args:
        plugin: "ipopt", "sqpmethod" or "fatrop" ("sqp_hpipm": see
            :func:`hmpc_cli.mpc.backends.sqp_options`).
        max_iter: iteration limit.
        tol: IPOPT ``tol``.
        max_wall_time: IPOPT ``max_wall_time`` [s] (None: none).
        equality: fatrop: per row, True for equality rows, shape (ng,).
        extra: user options: ``"ipopt"`` (IPOPT options), ``"ipopt_warm"`` (warm
            instance only), ``"hpipm"`` (``sqp_hpipm`` only, dropped here), the rest
            ``nlpsol`` options.
    """
    opts: dict = {"expand": True}
    extra = dict(extra or {})
    extra.pop("ipopt_warm", None)
    extra.pop("hpipm", None)  # the sqp_hpipm back-end's (shared settings)
    if plugin == "ipopt":
        ipopt = {"print_level": 0, "sb": "yes", "max_iter": max_iter, "tol": tol,
                 "constr_viol_tol": 1e-8, "mu_strategy": "adaptive"}
        if max_wall_time is not None:
            ipopt["max_wall_time"] = max_wall_time
        ipopt.update(extra.pop("ipopt", {}))
        opts.update({"ipopt": ipopt, "print_time": False})
    elif plugin == "sqpmethod":
        opts.update({"max_iter": max_iter, "print_time": False, "print_header": False,
                     "print_iteration": False, "qpsol": "qrqp",
                     "qpsol_options": {"print_iter": False, "print_header": False,
                                       "error_on_fail": False}})
    elif plugin == "fatrop":
        opts.update({"structure_detection": "auto", "print_time": False})
        if equality is not None:
            opts["equality"] = list(equality)
        opts["fatrop"] = {"print_level": 0, "max_iter": max_iter}
    else:
        raise ValueError(f"unknown NLP solver plugin {plugin!r}")
    opts.update(extra)
    return opts


def warm_options(cold: dict, warm: WarmStart, extra: dict | None = None) -> dict:
    """Options of the warm IPOPT instance.

    Returns:
        ``cold`` with the warm-start IPOPT options and the user's ``extra["ipopt_warm"]``.
    """
    push = warm.bound_push
    ipopt = {**cold["ipopt"], "warm_start_init_point": "yes", "mu_init": warm.mu_init,
             "warm_start_bound_push": push, "warm_start_mult_bound_push": push,
             "warm_start_slack_bound_push": push, **(extra or {}).get("ipopt_warm", {})}
    return {**cold, "ipopt": ipopt}


#: IPOPT's derivative options -> the functions nlpsol generates for them
DERIVATIVES = {"grad_f": "nlp_grad_f", "jac_g": "nlp_jac_g", "hess_lag": "nlp_hess_l"}


def derivatives_of(solver: ca.Function) -> dict:
    """The gradient, Jacobian and Hessian functions an IPOPT instance generated, as options.

    Another instance of the same NLP given them skips their symbolic generation (a large
    part of an instance's start-up); they are the same SX graphs, so its iterates
    are the same bit for bit.
    """
    return {opt: solver.get_function(fn) for opt, fn in DERIVATIVES.items()}


def _run(instances: tuple, w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0,
         rti: bool = False) -> SolveResult:
    """One solve on the (cold, warm) instances (see :meth:`SolverSession.solve`).

    ``rti``: a bounded SQP run (success by :func:`~hmpc_cli.mpc.backends.rti_success`).
    """
    start = time.perf_counter()
    args = {"x0": w0, "p": p, "lbx": lbx, "ubx": ubx, "lbg": lbg, "ubg": ubg}
    solver = instances[0]
    if lam_x0 is not None and lam_g0 is not None:
        args["lam_g0"] = np.where(np.isfinite(lbg) | np.isfinite(ubg), lam_g0, 0.0)
        args["lam_x0"] = np.where(np.isfinite(lbx) | np.isfinite(ubx), lam_x0, 0.0)
        solver = instances[1]
    with signals.abortable():  # a stop signal cuts the solve (checked after it too)
        try:
            sol = solver(**args)
        except RuntimeError as exc:  # CasADi raises on NaN evaluations
            return failed(w0, str(exc), time.perf_counter() - start)
        st = solver.stats()
        status = str(st.get("return_status", st.get("success")))
        if status == INTERRUPTED:  # CasADi swallowed the interrupt
            signals.check()
            raise KeyboardInterrupt(f"solver interrupted ({status})")
    w = np.asarray(sol["x"]).ravel()
    finite = bool(np.all(np.isfinite(w)))
    cost = float(sol["f"]) if finite else np.nan
    # the rows at w come with the solution (no second evaluation)
    viol = _violation(w, np.asarray(sol["g"]).ravel(), lbx, ubx, lbg, ubg) if finite else np.inf
    ok = bool(st.get("success", False))
    if rti:
        ok = rti_success(status, ok, viol)
    stats = SolveStats(status, ok and finite, _iterations(st), time.perf_counter() - start,
                       cost, float(viol))
    return SolveResult(w, np.asarray(sol["lam_x"]).ravel(), np.asarray(sol["lam_g"]).ravel(),
                       stats)


def _iterations(stats: dict) -> int:
    if "iter_count" in stats:
        return int(stats["iter_count"])
    its = stats.get("iterations")
    return int(its.get("iter", [0])[-1]) if isinstance(its, dict) else 0


class SolverSession:
    """The solver instances of one NLP and its solve, violation and constraint calls.

    Args:
        name: instance name (the warm one gets ``_warm`` appended).
        nlp: ``{"x", "p", "f", "g"}`` (e.g. from :meth:`NLPBuilder.build`), or (IPOPT,
            fatrop, sqpmethod) the path of a shared library of the functions an
            ``nlpsol`` of that NLP generates (``generate_dependencies``; see
            :mod:`hmpc_cli.mpc.cache`).
        plugin: "ipopt", "sqpmethod", "fatrop" or "sqp_hpipm".
        max_iter, tol, max_wall_time, equality, extra: see :func:`plugin_options`
            (``sqp_hpipm``: ``max_iter`` and ``tol`` are those of the IPOPT fallback,
            ``extra["hpipm"]`` HPIPM options, ``extra["ipopt"]`` the fallback's).
        warm: warm IPOPT instance options (None, or another plugin: warm starts run on
            the cold instance).
        structure: ``sqp_hpipm``: the NLP's stage structure (required).
        sqp_iter: ``sqp_hpipm``: SQP iterations per solve (real-time iterations).
        residuals: ``sqp_hpipm``: least-squares residuals of the cost (see
            :func:`hmpc_cli.mpc.backends.gauss_newton_hessian`).
    """

    def __init__(self, name: str, nlp: dict, plugin: str = "ipopt", *, max_iter: int,
                 tol: float = 1e-8, max_wall_time: float | None = None,
                 equality: list[bool] | None = None, extra: dict | None = None,
                 warm: WarmStart | None = None, structure: OCPStructure | None = None,
                 sqp_iter: int = 10, residuals=None) -> None:
        """Builds the cold and (IPOPT with ``warm``) the warm instance."""
        self.plugin, self._nlp, self._name = plugin, nlp, name
        ipopt_extra = {k: v for k, v in (extra or {}).items() if k in ("ipopt", "ipopt_warm")}
        self._ipopt_args = (max_iter, tol, max_wall_time, ipopt_extra, warm)
        self._fallback: tuple | None = None
        compiled = isinstance(nlp, str)  # a library of nlpsol's generated functions
        if plugin == "sqp_hpipm":
            if structure is None or compiled:
                raise ValueError("solver sqp_hpipm needs the NLP's expressions and its stage "
                                 "structure")
            extra = dict(extra or {})
            hpipm = extra.pop("hpipm", {})
            extra.pop("ipopt", None)
            extra.pop("ipopt_warm", None)
            self.options = {**sqp_options(nlp, structure, sqp_iter, tol, residuals, hpipm),
                            **extra}
            self.cold = self.warm = ca.nlpsol(name, "sqpmethod", nlp, self.options)
        else:
            self.options = plugin_options(plugin, max_iter, tol, max_wall_time, equality,
                                          extra)
            load = {k: v for k, v in self.options.items() if k != "expand"} if compiled \
                else self.options
            self.cold = self.warm = ca.nlpsol(name, plugin, nlp, load)
            if plugin == "ipopt" and warm is not None:
                self.warm = ca.nlpsol(f"{name}_warm", plugin, nlp, {
                    **warm_options(load, warm, extra),
                    **({} if compiled else derivatives_of(self.cold))})
        self._g = ca.external("nlp_g", nlp) if compiled else \
            ca.Function("g", [nlp["x"], nlp["p"]], [nlp["g"]])

    def solve(self, w0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None) -> SolveResult:
        """One solve from ``w0``; never raises on a solver failure.

        With both multiplier guesses the warm instance runs (multipliers of rows and
        variables without finite bounds zeroed), else the cold one. ``sqp_hpipm``: a
        failed solve is solved again by IPOPT (``stats.fallback`` True).

        Raises:
            KeyboardInterrupt: the solve was interrupted (Ctrl-C inside IPOPT);
                :class:`hmpc_cli.core.signals.Interrupted` when a stop signal is pending.
        """
        args = (w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0)
        res = _run((self.cold, self.warm), *args, rti=self.plugin == "sqp_hpipm")
        if self.plugin != "sqp_hpipm" or res.stats.success:
            return res
        again = _run(self.fallback_instances(), *args)
        st = again.stats
        status = f"{st.status} (fallback; sqp_hpipm: {res.stats.status})"
        stats = SolveStats(status, st.success, res.stats.iterations + st.iterations,
                           res.stats.wall_time + st.wall_time, st.cost, st.max_violation,
                           fallback=True)
        return SolveResult(again.x, again.lam_x, again.lam_g, stats)

    def fallback_instances(self) -> tuple:
        """The (cold, warm) IPOPT instances of the fallback (built on first use)."""
        if self._fallback is None:
            max_iter, tol, wall, extra, warm = self._ipopt_args
            cold = plugin_options("ipopt", max_iter, tol, wall, extra=extra)
            first = ca.nlpsol(f"{self._name}_ipopt", "ipopt", self._nlp, cold)
            self._fallback = (first, ca.nlpsol(
                f"{self._name}_ipopt_warm", "ipopt", self._nlp,
                {**warm_options(cold, warm or WarmStart(1e-6, 1e-9), extra),
                 **derivatives_of(first)}))
        return self._fallback

    def constraints(self, w, p) -> np.ndarray:
        """Constraint values g(w, p), shape (ng,)."""
        return np.asarray(self._g(w, p)).ravel()

    def violation(self, w, p, lbx, ubx, lbg, ubg) -> float:
        """Largest constraint or bound violation at primal point w (0 if none)."""
        return _violation(w, self.constraints(w, p), lbx, ubx, lbg, ubg)


def _violation(w, g, lbx, ubx, lbg, ubg) -> float:
    """Largest violation of rows g (ng,) and bounds at w (nx,) (0 if none)."""
    v = [np.maximum(lbg - g, 0.0), np.maximum(g - ubg, 0.0),
         np.maximum(lbx - w, 0.0), np.maximum(w - ubx, 0.0)]
    return float(max(np.max(a, initial=0.0) for a in v))


#: IPOPT linear solvers a build may provide (HSL's, Pardiso, SPRAL, WSMP, MUMPS)
LINEAR_SOLVERS = ("mumps", "ma27", "ma57", "ma77", "ma86", "ma97", "pardiso", "spral", "wsmp")


def option_problems(plugin: str, extra: dict, key: str = "mpc.solver_options") -> list[str]:
    """Solver options tried once on a tiny NLP: ``key.path: reason`` lines (none: usable).

    CasADi rejects unknown ``nlpsol`` options when the solver is built; IPOPT reports an
    unknown option or an unavailable linear solver only when it solves (status
    ``Invalid_Option``), so one tiny problem is solved with the same options.
    """
    import json

    if plugin == "sqp_hpipm":  # its IPOPT fallback's options (the rest fail at build)
        plugin, extra = "ipopt", {k: v for k, v in extra.items()
                                  if k in ("ipopt", "ipopt_warm")}
    if plugin != "ipopt":  # their options fail when the NLP is built (a PluginError)
        return []
    return list(_option_problems(plugin, json.dumps(extra, sort_keys=True), key))


@lru_cache(maxsize=64)
def _option_problems(plugin: str, extra_json: str, key: str) -> tuple[str, ...]:
    import json

    extra = json.loads(extra_json)
    for instance, opts in _probe_options(plugin, extra):
        solver = opts.get("ipopt", {}).get("linear_solver")
        # a linear solver is tried in a child process: some HSL stubs crash the process
        status = _probe(plugin, opts) if solver is None else _probe_isolated([(plugin, opts)])[0]
        if status is None:
            continue
        section = "ipopt_warm" if "linear_solver" in extra.get("ipopt_warm", {}) else "ipopt"
        if solver is not None and _probe(plugin, _with_solver(opts, "mumps")) is None:
            found = _probe_isolated([(plugin, _with_solver(opts, s)) for s in LINEAR_SOLVERS])
            available = [s for s, st in zip(LINEAR_SOLVERS, found, strict=True) if st is None]
            return (f"{key}.{section}.linear_solver: {solver!r} is not available "
                    f"(available: {', '.join(available) or 'none'})",)
        return (f"{key}: the solver rejects these options ({instance} instance): {status}",)
    return ()


def _with_solver(opts: dict, solver: str) -> dict:
    return {**opts, "ipopt": {**opts["ipopt"], "linear_solver": solver}}


_CHILD = """
import json, sys
from hmpc_cli.mpc.solver import _probe
plugin, opts = json.loads(sys.argv[1])
print(json.dumps(_probe(plugin, opts)))
"""


def _probe_isolated(cases: list[tuple[str, dict]]) -> list[str | None]:
    """:func:`_probe` of each case in its own child process (in parallel)."""
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")])}
    procs = [subprocess.Popen([sys.executable, "-c", _CHILD, json.dumps(case)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
             for case in cases]
    out = []
    for proc in procs:
        stdout, _ = proc.communicate()
        if proc.returncode:
            out.append(f"the solver process crashed (exit {proc.returncode})")
        else:
            out.append(json.loads(stdout.strip().splitlines()[-1]))
    return out


def _probe_options(plugin: str, extra: dict) -> list[tuple[str, dict]]:
    """(instance, nlpsol options) of the cold and (IPOPT) warm instances."""
    cold = plugin_options(plugin, 5, extra=extra)
    if plugin != "ipopt":
        return [("cold", cold)]
    return [("cold", cold), ("warm", warm_options(cold, WarmStart(1e-4, 1e-6), extra))]


def _probe(plugin: str, opts: dict) -> str | None:
    """None if ``min (x - 1)^2`` solves with ``opts``; else the status or error."""
    from hmpc_cli.core.registry import one_line

    x = ca.SX.sym("x")
    try:
        solver = ca.nlpsol("probe", plugin, {"x": x, "f": (x - 1) ** 2, "g": x}, opts)
        solver(x0=0.0, lbg=-10.0, ubg=10.0)
    except RuntimeError as exc:
        return one_line(exc)
    stats = solver.stats()
    status = str(stats.get("return_status", ""))
    if plugin == "ipopt" and status in ("Invalid_Option", "Invalid_Problem_Definition",
                                        "Unrecoverable_Exception", "NonIpopt_Exception_Thrown",
                                        "Internal_Error", "Insufficient_Memory"):
        return status
    return None
