"""One solver session of a parametric NLP: options, cold and warm instances, solves.

Both MPC NLPs solve through a :class:`SolverSession` of one back-end of the table
:data:`~hmpc_cli.mpc.solver_table.SOLVERS`: it builds the entry's options, a cold
instance and, if the entry has one, a warm-start instance (IPOPT's: :class:`WarmStart`),
and turns every solve into a :class:`SolveResult` with the
:class:`~hmpc_cli.core.messages.SolveStats` of the closed loop. A back-end with a
fallback (``sqp_hpipm``: SQP, Gauss-Newton Hessian, HPIPM on the NLP's stage structure,
a bounded number of iterations from the primal-dual warm start) has a solve it fails
solved again by the fallback (IPOPT, built on first use), marked ``fallback``. A solve
never raises on a solver failure (CasADi's ``RuntimeError`` on NaN evaluations becomes a
failed solve with status ``"error: ..."``); it does raise ``KeyboardInterrupt`` when the
user interrupted IPOPT: CasADi catches the interrupt inside IPOPT's callbacks and returns
the status ``NonIpopt_Exception_Thrown``, which the session turns back into the interrupt.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.core.messages import SolveStats
from hmpc_cli.mpc.backends import OCPStructure
from hmpc_cli.mpc import ipopt_options
from hmpc_cli.mpc.buffered import BufferedSolver
from hmpc_cli.mpc.solver_table import (
    SolverArgs, WarmStart, backend_of, split_options, warm_options)

__all__ = ["DERIVATIVES", "FALLBACK_WARM", "INTERRUPTED", "LINEAR_SOLVERS", "SolveResult",
           "SolverSession", "WarmStart", "derivatives_of", "failed", "iterate_at",
           "option_problems", "plugin_options", "warm_options"]

INTERRUPTED = "NonIpopt_Exception_Thrown"
#: the fallback's warm start when its session was given none
FALLBACK_WARM = WarmStart(mu_init=1e-6, bound_push=1e-9)


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
    """CasADi ``nlpsol`` options of the cold instance of back-end ``plugin``.

    Args:
        plugin: a back-end of :data:`~hmpc_cli.mpc.solver_table.SOLVERS` that needs no
            NLP to build its options ("ipopt", "sqpmethod", "fatrop").
        max_iter: iteration limit.
        tol: IPOPT ``tol``.
        max_wall_time: IPOPT ``max_wall_time`` [s] (None: none).
        equality: fatrop: per row, True for equality rows, shape (ng,).
        extra: user options: the back-ends' sections (``"ipopt"``, ``"ipopt_warm"``
            (warm instance only), ``"hpipm"``), the rest ``nlpsol`` options.

    Raises:
        ValueError: an unknown back-end.
    """
    backend = backend_of(plugin)
    nlpsol, sections = split_options(backend, extra)
    return backend.options(SolverArgs(max_iter, tol, max_wall_time, equality, nlpsol,
                                      sections))


#: per nlpsol plugin, its derivative options -> the functions it generates for them
DERIVATIVES = {
    "ipopt": {"grad_f": "nlp_grad_f", "jac_g": "nlp_jac_g", "hess_lag": "nlp_hess_l"},
    "sqpmethod": {"jac_fg": "nlp_jac_fg", "hess_lag": "nlp_hess_l"},
}


#: ``nlpsol`` options whose post-solve quantities need its ``nlp_grad`` function
NLP_GRAD_USERS = ("calc_lam_p", "calc_lam_x", "calc_f", "calc_g", "calc_multipliers")
#: plug-ins that never call ``nlp_grad`` themselves (fatrop does: it aborts without it)
NLP_GRAD_FREE = ("ipopt", "sqpmethod")


def without_nlp_grad(options: dict, plugin: str = "ipopt") -> dict:
    """``options`` with ``no_nlp_grad`` for a plug-in of :data:`NLP_GRAD_FREE`.

    Not set when one of :data:`NLP_GRAD_USERS` is on or ``no_nlp_grad`` is given.
    ``nlpsol`` otherwise generates ``nlp_grad`` (f, g and the Lagrangian's gradient in x
    and p: a reverse sweep of the whole graph) in every instance, only to compute those
    quantities after the solve. No iteration of these plug-ins calls it, so leaving it
    out changes no iterate.
    """
    if plugin not in NLP_GRAD_FREE or "no_nlp_grad" in options or \
            any(options.get(k) for k in NLP_GRAD_USERS):
        return options
    return {**options, "no_nlp_grad": True}


#: ``nlpsol`` options an NLP whose derivatives are given, assembled from compiled kernels,
#: takes: none of them makes ``nlpsol`` differentiate the NLP itself (but those that ask
#: for ``nlp_grad``: :func:`takes_assembled`). Any other (``detect_simple_bounds``, say)
#: might, which C kernels cannot be.
ASSEMBLED_OPTIONS = frozenset({
    "print_time", "record_time", "error_on_fail", "verbose_init", "warn_initial_bounds",
    "bound_consistency", "min_lam", "expand", "no_nlp_grad", *NLP_GRAD_USERS})


def takes_assembled(plugin: str, extra: dict | None) -> bool:
    """Whether back-end ``plugin`` can solve an NLP assembled from compiled kernels.

    With user options ``extra``, the NLP's derivatives given
    (:class:`~hmpc_cli.mpc.staged.StagedNLP`): IPOPT only, with only
    :data:`ASSEMBLED_OPTIONS` among the ``nlpsol`` options and none that needs
    ``nlp_grad`` (:func:`without_nlp_grad`): else ``nlpsol`` differentiates the NLP
    itself, which needs it in SX.
    """
    backend = backend_of(plugin)
    nlpsol = split_options(backend, extra)[0]
    return backend.plugin == "ipopt" and set(nlpsol) <= ASSEMBLED_OPTIONS and \
        bool(without_nlp_grad(nlpsol, backend.plugin).get("no_nlp_grad"))


def derivatives_of(solver: ca.Function, plugin: str = "ipopt") -> dict:
    """The derivative functions an ``nlpsol`` instance of ``plugin`` generated, as options.

    Another instance of the same NLP given them skips their symbolic generation (a large
    part of an instance's start-up); they are the same functions (those the first was
    given, if any), so its iterates are the same bit for bit. A function the instance
    did not generate (no Hessian with ``hessian_approximation = "limited-memory"``) is
    left out; a plugin without an entry in :data:`DERIVATIVES` gets none.
    """
    return {opt: solver.get_function(fn) for opt, fn in DERIVATIVES.get(plugin, {}).items()
            if solver.has_function(fn)}


def _call_instance(instances: tuple, w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0,
                   judge=None) -> SolveResult:
    """Calls the cold or (with both multiplier guesses) the warm instance once.

    See :meth:`SolverSession.run`. ``judge``: a bounded SQP run's success from (status,
    converged, max violation) (:attr:`~hmpc_cli.mpc.solver_table.Backend.judge`).
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
    # the rows at w come with the solution (no second evaluation)
    viol = _violation(w, np.asarray(sol["g"]).ravel(), lbx, ubx, lbg, ubg) if finite else np.inf
    wall = time.perf_counter() - start  # the cost's evaluation below is not the solve's
    cost = _cost_in_bounds(solver, w, p, lbx, ubx, float(np.ravel(sol["f"])[0])) \
        if finite else np.nan
    ok = bool(st.get("success", False))
    if judge is not None:
        ok = judge(status, ok, viol)
    stats = SolveStats(status, ok and finite, _iterations(st), wall, cost, float(viol))
    return SolveResult(w, np.asarray(sol["lam_x"]).ravel(), np.asarray(sol["lam_g"]).ravel(),
                       stats)


def _cost_in_bounds(solver: ca.Function, w: np.ndarray, p, lbx, ubx, f: float) -> float:
    """The objective at ``w`` projected onto its bounds (``f``, the solver's, if inside).

    IPOPT's bound relaxation (1e-8) returns a variable up to that far outside its bound:
    a soft constraint's slack at -1e-8 times its weight (1e4), over every node, made the
    reported cost of a plan at rest at the goal negative. The plan itself is unchanged.
    """
    inside = np.clip(w, lbx, ubx)
    has = getattr(solver, "has_function", None)  # a wrapper without it keeps the solver's
    if np.array_equal(inside, w) or has is None or not has("nlp_f"):
        return f
    objective = getattr(solver, "objective", None)  # a BufferedSolver's, buffered
    if objective is not None:
        return objective(inside, p)
    return float(solver.get_function("nlp_f")(inside, p))


def _iterations(stats: dict) -> int:
    if "iter_count" in stats:
        return int(stats["iter_count"])
    its = stats.get("iterations")
    return int(its.get("iter", [0])[-1]) if isinstance(its, dict) else 0


class SolverSession:
    """The solver instances of one NLP and its run, violation and constraint calls.

    Args:
        name: instance name (the warm one gets ``_warm`` appended).
        nlp: ``{"x", "p", "f", "g"}`` (e.g. from :meth:`NLPBuilder.build`), or (a
            compilable back-end) the path of a shared library of the functions an
            ``nlpsol`` of that NLP generates (``generate_dependencies``; see
            :mod:`hmpc_cli.mpc.cache`).
        plugin: the back-end's name in :data:`~hmpc_cli.mpc.solver_table.SOLVERS`.
        max_iter, tol, max_wall_time, equality: see
            :class:`~hmpc_cli.mpc.solver_table.SolverArgs` (``sqp_hpipm``: ``max_iter``
            is its fallback's; it runs ``sqp_iter``).
        extra: user options: the back-ends' sections (``"ipopt"``, ``"ipopt_warm"``,
            ``"hpipm"``; a fallback gets its own), the rest ``nlpsol`` options.
        warm: warm instance options (None, or a back-end without a warm instance: warm
            starts run on the cold instance).
        structure: stage-wise back-ends: the NLP's stage structure.
        sqp_iter: ``sqp_hpipm``: SQP iterations per solve (real-time iterations).
        residuals: ``sqp_hpipm``: least-squares residuals of the cost (see
            :func:`hmpc_cli.mpc.backends.gauss_newton_hessian`).
        derivatives: IPOPT's derivative functions by ``nlpsol`` option (``grad_f``,
            ``jac_g``, ``hess_lag``: :data:`DERIVATIVES`) instead of those ``nlpsol``
            generates from the whole graph (e.g.
            :meth:`~hmpc_cli.mpc.staged.StagedNLP.derivatives`); other plug-ins, and a
            compiled library (whose own they are), leave them out (:attr:`derivatives`:
            those given). An NLP in MX given them is not expanded (its functions are
            assembled already; its kernels may be C libraries, which do not expand):
            ``options``, what the cold instance gets, then has no ``expand``.

    Raises:
        ValueError: an unknown back-end, a compiled library for a back-end that cannot
            load one, or a derivative that is not one of IPOPT's options.
    """

    def __init__(self, name: str, nlp: dict, plugin: str = "ipopt", *, max_iter: int,
                 tol: float = 1e-8, max_wall_time: float | None = None,
                 equality: list[bool] | None = None, extra: dict | None = None,
                 warm: WarmStart | None = None, structure: OCPStructure | None = None,
                 sqp_iter: int = 10, residuals=None,
                 derivatives: dict[str, ca.Function] | None = None) -> None:
        """Builds the cold and (a back-end with a warm instance, ``warm``) the warm one."""
        self.backend = backend = backend_of(plugin)
        self.plugin, self._nlp, self._name = plugin, nlp, name
        self._args = dict(max_iter=max_iter, tol=tol, max_wall_time=max_wall_time,
                          equality=equality, extra=extra, warm=warm, structure=structure,
                          sqp_iter=sqp_iter, residuals=residuals,
                          derivatives=derivatives)
        self._fallback: SolverSession | None = None
        compiled = isinstance(nlp, str)  # a library of nlpsol's generated functions
        if compiled and not backend.compilable:
            raise ValueError(f"solver {plugin!r} cannot load a compiled NLP")
        nlpsol, sections = split_options(backend, extra)
        args = SolverArgs(max_iter, tol, max_wall_time, equality, nlpsol, sections, nlp,
                          structure, sqp_iter, residuals)
        self.options = without_nlp_grad({"calc_lam_p": False, **backend.options(args)},
                                         backend.plugin)
        #: the derivative functions given to ``nlpsol`` (by option; empty: its own)
        self.derivatives = dict(derivatives or {}) \
            if backend.plugin == "ipopt" and not compiled else {}
        unknown = set(self.derivatives) - set(DERIVATIVES["ipopt"])
        if unknown:
            raise ValueError(f"not derivative options of ipopt: {sorted(unknown)}")
        self.options = {**self.derivatives, **self.options}
        if compiled and not self.options.get("no_nlp_grad"):
            asked = [k for k in NLP_GRAD_USERS if self.options.get(k)] or ["no_nlp_grad=False"]
            raise RuntimeError(f"options {asked} need nlp_grad, which a compiled NLP leaves out")
        if compiled or (self.derivatives and isinstance(nlp["x"], ca.MX)):
            self.options.pop("expand", None)  # nothing to expand, or assembled already
        self.cold = self.warm = BufferedSolver(ca.nlpsol(name, backend.plugin, nlp,
                                                         self.options))
        #: the warm instance's options (None: warm starts run on the cold instance)
        self._warm_options: dict | None = None
        if backend.warm is not None and warm is not None:
            self._warm_options = {
                **backend.warm(self.options, warm, sections, args),
                **({} if compiled else derivatives_of(self.cold, backend.plugin))}
            self.warm = BufferedSolver(ca.nlpsol(f"{name}_warm", backend.plugin, nlp,
                                                 self._warm_options))
        self._stopping: tuple[_IterationStop, tuple] | None = None  # :meth:`stopped`'s
        self._g = ca.external("nlp_g", nlp) if compiled else \
            ca.Function("g", [nlp["x"], nlp["p"]], [nlp["g"]])

    def run(self, w0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None) -> SolveResult:
        """Runs the solver once from ``w0``; never raises on a solver failure.

        With both multiplier guesses the warm instance runs (multipliers of rows and
        variables without finite bounds zeroed), else the cold one. A back-end with a
        fallback: a failed solve is solved again by the fallback (``stats.fallback``).

        Raises:
            KeyboardInterrupt: the solve was interrupted (Ctrl-C inside IPOPT);
                :class:`hmpc_cli.core.signals.Interrupted` when a stop signal is pending.
        """
        args = (w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0)
        res = _call_instance((self.cold, self.warm), *args, judge=self.backend.judge)
        if self.backend.fallback is None or res.stats.success:
            return res
        again = self.fallback_session().run(*args)
        st = again.stats
        status = f"{st.status} (fallback; {self.plugin}: {res.stats.status})"
        stats = SolveStats(status, st.success, res.stats.iterations + st.iterations,
                           res.stats.wall_time + st.wall_time, st.cost, st.max_violation,
                           fallback=True)
        return SolveResult(again.x, again.lam_x, again.lam_g, stats)

    def stopped(self, iterations: int, w0, p, lbx, ubx, lbg, ubg, lam_x0=None,
                lam_g0=None) -> SolveResult | None:
        """The iterate :meth:`run` from the same arguments reaches after ``iterations``.

        IPOPT is deterministic: the same instance's options (cold, or warm with both
        multiplier guesses) stopped by an iteration callback after ``iterations``
        iterations (0: the start) hand over the very iterate its full run passed there,
        as IPOPT's own ``max_iter`` would (status ``User_Requested_Stop``). In IPOPT's
        restoration phase the callback comes more than once an iteration: a run that
        stopped short is run again with the calls it lacked added. Its instances are
        built on first use. Never raises on a solver failure.

        Returns:
            That iterate, or None for a back-end other than IPOPT (its iterates are not
            recorded).
        """
        if self.backend.plugin != "ipopt":
            return None
        if self._stopping is None:
            stop = _IterationStop(self.cold.function)
            made = []
            for name, options in ((self._name, self.options),
                                  (f"{self._name}_warm", self._warm_options)):
                if options is None:
                    made.append(made[0])
                    continue
                extra = {} if isinstance(self._nlp, str) or name == self._name + "_warm" \
                    else derivatives_of(self.cold, "ipopt")
                made.append(BufferedSolver(ca.nlpsol(
                    f"{name}_stopped", "ipopt", self._nlp,
                    {**options, **extra, "iteration_callback": stop})))
            self._stopping = (stop, tuple(made))
        stop, instances = self._stopping
        want = max(int(iterations), 0)
        calls = want
        for _ in range(_STOP_TRIES):
            stop.after = calls
            res = _call_instance(instances, w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0)
            short = want - res.stats.iterations
            if short <= 0 or res.stats.status != "User_Requested_Stop":
                return res
            calls += short  # restoration: CasADi calls back more than once an iteration
        return res

    def fallback_session(self) -> SolverSession:
        """The session of the back-end's fallback (built on first use).

        It gets the fallback's own option sections and, if this session has none, the
        warm start :data:`FALLBACK_WARM`.
        """
        if self._fallback is None:
            fallback = backend_of(self.backend.fallback)
            args = {**self._args, "warm": self._args["warm"] or FALLBACK_WARM,
                    "extra": split_options(fallback, self._args["extra"])[1]}
            self._fallback = SolverSession(f"{self._name}_{fallback.name}", self._nlp,
                                           fallback.name, **args)
        return self._fallback

    def constraints(self, w, p) -> np.ndarray:
        """Constraint values g(w, p), shape (ng,)."""
        return np.asarray(self._g(w, p)).ravel()

    def violation(self, w, p, lbx, ubx, lbg, ubg) -> float:
        """Largest constraint or bound violation at primal point w (0 if none)."""
        return _violation(w, self.constraints(w, p), lbx, ubx, lbg, ubg)


def iterate_at(session: SolverSession, iterations: int, total: int, call: tuple
               ) -> tuple[int, SolveResult | None] | None:
    """The warm start a solve of ``total`` iterations leaves when stopped after ``iterations``.

    ``call``: the solve's arguments (:meth:`SolverSession.run`'s, in order).

    Returns:
        (``total``, None): not stopped short, its whole solution stays; (0, None): the
        warm start it started from (stopped before its first iteration, or at a
        non-finite iterate); (k, iterate): IPOPT's iterate after k iterations
        (:meth:`SolverSession.stopped`); None: the back-end cannot stop at an iteration
        (its whole solution stays).
    """
    k = min(max(int(iterations), 0), total)
    if k >= total or k == 0:
        return k, None
    res = session.stopped(k, *call)
    if res is None:
        return None
    if bool(np.all(np.isfinite(res.x))) and res.lam_g is not None:
        return res.stats.iterations, res
    return 0, None


#: runs of :meth:`SolverSession.stopped` to reach its iteration count
_STOP_TRIES = 8


class _IterationStop(ca.Callback):
    """IPOPT's iteration callback that stops the solve after :attr:`after` calls.

    CasADi calls it once per iterate, the start (iteration 0) included, and in IPOPT's
    restoration phase more than once an iteration; a nonzero return stops IPOPT there.
    A solve resets its count by setting :attr:`after`.
    """

    def __init__(self, solver: ca.Function) -> None:
        """The callback of ``solver``'s NLP (its outputs are the callback's inputs)."""
        ca.Callback.__init__(self)
        self._after, self._calls = 0, 0
        self._sparsity = [solver.sparsity_out(i) for i in range(solver.n_out())]
        self.construct("iteration_stop", {})

    @property
    def after(self) -> int:
        """Iterations to let run before stopping."""
        return self._after

    @after.setter
    def after(self, iterations: int) -> None:
        self._after, self._calls = iterations, 0

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "stop"

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return self._sparsity[i]

    def eval(self, arg):
        self._calls += 1
        return [1 if self._calls > self._after else 0]


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
    Only back-ends with ``probe`` are solved; the others' ``nlpsol`` options (the keys
    outside every section) are checked by a build on a tiny NLP, each unknown one named
    with CasADi's nearest. A back-end's fallback is tried with its own sections. Each
    option of an ``hpipm`` section is tried alone on a tiny QP (HPIPM's error does not
    name it).
    """
    import json

    backend = backend_of(plugin)
    checks = [(backend, extra)]
    if backend.fallback is not None:
        fallback = backend_of(backend.fallback)
        checks.append((fallback, split_options(fallback, extra)[1]))
    lines = [line for b, opts in checks if b.probe
             for line in _option_problems(b.name, json.dumps(opts, sort_keys=True), key)]
    nlpsol = split_options(backend, extra)[0]
    if not backend.probe and nlpsol:
        lines += _unknown_options(backend.name, json.dumps(nlpsol, sort_keys=True), key)
    section = extra.get("hpipm") if "hpipm" in backend.sections else None
    if isinstance(section, dict):
        lines += [line for name, value in section.items()
                  for line in _hpipm_problem(name, json.dumps(value), key)]
    return lines


@lru_cache(maxsize=64)
def _unknown_options(name: str, nlpsol_json: str, key: str) -> tuple[str, ...]:
    """``key.option: ...`` for each ``nlpsol`` option back-end ``name``'s plugin lacks.

    Found by building it on a tiny NLP: CasADi names one unknown option per build and
    suggests the nearest. Only the user's options are given: an error of another kind
    (the tiny NLP has no stage structure, a value of the wrong type) is left to the MPC's
    own build.
    """
    import json
    import re

    plugin, left, out = backend_of(name).plugin, json.loads(nlpsol_json), []
    x = ca.SX.sym("x", 2)
    tiny = {"x": x, "f": ca.sumsqr(x), "g": x[0] + x[1]}
    while left:
        try:
            with _c_stdout_silenced():
                ca.nlpsol("probe", plugin, tiny, {**left, "print_time": False})
            break
        except RuntimeError as exc:
            text = str(exc)
            found = re.search(r"Unknown option: (\S+)", text)
            if found is None or found.group(1) not in left:
                break
            option = found.group(1)
            near = re.search(r'Did you mean one of the following\?\s*> "([^"]+)"', text)
            hint = f"did you mean {near.group(1)!r}?" if near else \
                f"casadi.nlpsol_options({plugin!r}) lists the plugin's own"
            out.append(f"{key}.{option}: {plugin} (back-end {name!r}) has no option "
                       f"{option!r} ({hint})")
            del left[option]
    return tuple(out)


#: HPIPM options CasADi's interface accepts (named in the error of a misspelt one)
HPIPM_EXAMPLES = ("iter_max", "mu0", "alpha_min", "res_g_max", "res_b_max", "res_d_max",
                  "res_m_max", "warm_start", "pred_corr", "reg_prim", "lam_min", "t_min",
                  "mode")


@lru_cache(maxsize=64)
def _hpipm_problem(name: str, value_json: str, key: str) -> tuple[str, ...]:
    """``key.hpipm.name: reason`` if HPIPM refuses the option alone on a tiny QP, else ().

    CasADi's HPIPM interface says "Unknown option." without the name; one QP per option
    names it.
    """
    import difflib
    import json

    from hmpc_cli.core.registry import one_line

    x = ca.SX.sym("x", 2)
    qp = {"x": x, "f": ca.sumsqr(x), "g": x[0] + x[1]}
    try:
        ca.qpsol("probe", "hpipm", qp, {"hpipm": {name: json.loads(value_json)},
                                        "print_problem": False})
    except RuntimeError as exc:
        text = one_line(exc)
        if "Unknown option" not in text:
            return (f"{key}.hpipm.{name}: HPIPM refuses {value_json}: {text}",)
        near = difflib.get_close_matches(name, HPIPM_EXAMPLES, n=1)
        hint = f"did you mean {near[0]!r}?" if near else \
            f"HPIPM's options are e.g. {', '.join(HPIPM_EXAMPLES)}"
        return (f"{key}.hpipm.{name}: HPIPM has no option {name!r} ({hint})",)
    return ()


@lru_cache(maxsize=64)
def _option_problems(name: str, extra_json: str, key: str) -> tuple[str, ...]:
    import json

    extra, plugin = json.loads(extra_json), backend_of(name).plugin
    for instance, opts in _probe_options(name, extra):
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
        named = [line for sec in ("ipopt", "ipopt_warm") if isinstance(extra.get(sec), dict)
                 for line in ipopt_options.problems(extra[sec], f"{key}.{sec}")
                 ] if plugin == "ipopt" else []
        if named:
            return tuple(named)
        return (f"{key}: the solver rejects these options ({instance} instance): {status}",)
    return ()


def _with_solver(opts: dict, solver: str) -> dict:
    return {**opts, "ipopt": {**opts["ipopt"], "linear_solver": solver}}


_CHILD = """
import json, sys
from hmpc_cli.mpc.solver import _probe
for plugin, opts in json.loads(sys.argv[1]):
    print("probe:", json.dumps(_probe(plugin, opts)), flush=True)
"""


def _probe_isolated(cases: list[tuple[str, dict]]) -> list[str | None]:
    """:func:`_probe` of each case, in order, in child processes.

    One child probes them all; a case that crashes its process (some HSL stubs do) is
    reported so and the cases after it go to a new one.
    """
    import json
    import os
    import subprocess
    import sys

    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")])}
    out: list[str | None] = []
    while len(out) < len(cases):
        proc = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(cases[len(out):])],
                              env=env, capture_output=True, text=True, check=False)
        out += [json.loads(line.removeprefix("probe:")) for line in proc.stdout.splitlines()
                if line.startswith("probe:")][: len(cases) - len(out)]
        if len(out) < len(cases) and proc.returncode:  # the next case took the process down
            out.append(f"the solver process crashed (exit {proc.returncode})")
        elif len(out) < len(cases):
            raise RuntimeError(f"the solver probe process ended early: {proc.stderr[-500:]}")
    return out


def _probe_options(name: str, extra: dict) -> list[tuple[str, dict]]:
    """(instance, nlpsol options) of back-end ``name``'s cold and (if any) warm instances."""
    backend, cold = backend_of(name), plugin_options(name, 5, extra=extra)
    if backend.warm is None:
        return [("cold", cold)]
    warm = backend.warm(cold, WarmStart(1e-4, 1e-6), split_options(backend, extra)[1],
                        SolverArgs(5))
    return [("cold", cold), ("warm", warm)]


_SILENCE = threading.Lock()  # fd 1 and sys.stdout are the process's: one silencer at a time


def _c_flush() -> None:
    """Flushes the C library's stdio buffers (nothing where there is no C library handle)."""
    import contextlib
    import ctypes

    with contextlib.suppress(OSError, TypeError, AttributeError):
        ctypes.CDLL(None).fflush(None)


@contextmanager
def _c_stdout_silenced() -> Iterator[None]:
    """Prints inside go nowhere: CasADi's (Python's ``sys.stdout``) and C libraries' (fd 1).

    Without a file descriptor 1 (stdout closed) only Python's are held back.
    """
    import contextlib
    import io
    import os
    import sys

    with _SILENCE:
        if sys.stdout is not None:
            sys.stdout.flush()
        _c_flush()  # what was printed before goes out before fd 1 moves
        try:
            kept = os.dup(1)
        except OSError:
            kept = None
        if kept is not None:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)
        try:
            with contextlib.redirect_stdout(io.StringIO()):
                yield
        finally:
            if kept is not None:
                _c_flush()  # what the C library still holds: to /dev/null
                os.dup2(kept, 1)
                os.close(kept)
                os.close(null)


def _probe(plugin: str, opts: dict) -> str | None:
    """None if ``min (x - 1)^2`` solves with ``opts``; else the status or error."""
    from hmpc_cli.core.registry import one_line

    x = ca.SX.sym("x")
    try:
        with _c_stdout_silenced():  # IPOPT prints a refused option's documentation there
            solver = ca.nlpsol("probe", plugin, {"x": x, "f": (x - 1) ** 2, "g": x}, opts)
            solver(x0=0.0, lbg=-10.0, ubg=10.0)
    except RuntimeError as exc:  # CasADi's own suggestion for an unknown option, if any
        near = re.search(r'Did you mean one of the following\?\s*> "(\w+)"', str(exc))
        return one_line(exc) + (f" (did you mean {near.group(1)!r}?)" if near else "")
    stats = solver.stats()
    status = str(stats.get("return_status", ""))
    if plugin == "ipopt" and status in ("Invalid_Option", "Invalid_Problem_Definition",
                                        "Unrecoverable_Exception", "NonIpopt_Exception_Thrown",
                                        "Internal_Error", "Insufficient_Memory"):
        return status
    return None
