"""Fixed-mode MPC (the paper's problems (12) and (14)) as one parametric NLP.

Multiple shooting on a chain of ``L = N + S`` links (see :mod:`hmpc_cli.mpc.chain.layout`).
Link k maps node z_k to z_{k+1}:

    z_{k+1} = sum_m a_km Phi_m(z_k, u_k) + sum_g b_kg R_g(z_k) + e_k z_k

with Phi_m one RK4 (or Euler) interval of mode m, R_g the reset map of guard g and the
one-hot link type (a, b, e) a *parameter*. With ``input_hold = "foh"`` the input of a flow
interval goes linearly from u_k to u_{k+1} (the low level's first-order-hold feed-forward,
so an undisturbed plant follows the plan); the last interval before a guard node ends at
the virtual input, the horizon's last interval holds its input.

Path rows of node k, with bounds chosen per solve (an inactive row gets infinite bounds),
by row group (the named blocks of :class:`FixedModeNLP`; link k's ``dynamics`` rows come
first):

* ``guard_avoid``, one row per guard g: s_kg q_g(z_k) - kappa_kg + sigma_k. Guard-avoid
  (>= 0, s = +1, kappa from the tube margin), the lower side of the guard-hit at the
  switching node (>= 0 with kappa = 0), or off;
* ``guard_hit``: q_G(z_k) - sigma_k <= 0 at the switching node (with the row above:
  |q_G| <= sigma_k);
* ``virtual_node``: -q_G(Phi(z_k, u_k)) - kappa + sigma_k >= 0 at each guard node, i.e.
  one more interval of the source flow with the virtual input u_k puts the whole tube
  past the guard (problem (14));
* ``region``: the guard's activity-region rows at the switching node (+ sigma_k >= 0);
* ``terminal``: terminal-set rows at the last node (+ sigma_L >= 0).

sigma_k >= 0 is one slack per node with an exact L1 penalty ``soft_penalty * sum sigma_k``
in the cost: whenever the hybrid constraints can be met, the solution meets them exactly
(sigma = 0); when a disturbance has made them infeasible (the planned guard time can no
longer be reached, say) the solve returns the least-relaxed plan instead of failing, and
the relaxation max sigma_k is reported with every solve. ``soft_penalty = 0`` fixes
sigma = 0: the hard constraints of the paper.

Inputs are bounded by the (tightened) box of each link's mode through the variable
bounds; reset-link inputs are the virtual inputs. Built once per (system, horizon,
S_max) and re-solved with parameters, bounds and a primal-dual warm start.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Literal

import casadi as ca
import numpy as np
from pydantic import ConfigDict, Field, model_validator

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.kinds import MarginsSettings
from hmpc_cli.core.messages import ConstraintMargins, Trajectory
from hmpc_cli.mpc import cache, kernels
from hmpc_cli.mpc.backends import OCPStructure
from hmpc_cli.mpc.builder import Blocks, NLPBuilder, NLPLayout
from hmpc_cli.mpc.chain.layout import FLOW, ChainLayout, NodeSchedule
from hmpc_cli.mpc.chain.problem_data import INF, ChainShape, problem_data
from hmpc_cli.mpc.solver import SolveResult, SolverSession, WarmStart, takes_assembled
from hmpc_cli.mpc.staged import StageKind, StagedNLP, total_cost
from hmpc_cli.mpc.solver_table import (SOLVERS, SolverName, SolverOptions, describe,
                                       split_options)
from hmpc_cli.core.settings_types import (
    MAX_NLP_NODES, BoundedInt, FiniteFloat, StrictBool, nlp_estimate)

__all__ = ["INF", "FixedModeNLP", "FixedModeNLPs", "MPCSettings"]

WARM_START = WarmStart(mu_init=1e-6, bound_push=1e-9)  # the warm IPOPT instance
_LOG = logging.getLogger(__name__)

#: measured cost of one chain-NLP node (both NLPs, cold and warm solvers; ball, 2 cores)
NODE_MIB, NODE_MS = 0.85, 18.0
#: measured cost of one guard event of the switching chain NLP (ball, 2 cores): a link
#: with its guard, virtual-node and region rows, in one NLP (cold and warm solvers)
SWITCH_MIB, SWITCH_MS = 0.3, 10.0


class MPCSettings(MarginsSettings):
    """Fixed-mode MPC settings."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["fixed_mode"] = Field("fixed_mode", description="mode-schedule MPC on "
                                        "the chain transcription (any system)")
    rate_hz: BoundedInt = Field(10, gt=0, description="MPC re-solve rate [Hz]")
    nodes_per_second: BoundedInt = Field(60, gt=0, description="NLP node rate: node step = 1/this")
    horizon: FiniteFloat = Field(3.0, gt=0.0, description="receding horizon [s]: a whole "
                                 "number (>= 2) of node steps 1 / mpc.nodes_per_second")
    max_switches: BoundedInt = Field(10, ge=0, description="guard events the NLP chain can hold")
    integrator: Literal["rk4", "euler"] = "rk4"
    input_hold: Literal["foh", "zoh"] = Field(
        "foh", description="input between nodes: first-order hold (linear from u_k to "
                           "u_k+1, as the low level feeds it forward) or zero-order hold")
    robust: StrictBool = Field(True, description="virtual pass-through node (problem (14))")
    soft_penalty: FiniteFloat = Field(
        1e4, ge=0.0, description="L1 penalty on relaxing guard, virtual-node, region and "
                                 "terminal rows (0: hard constraints, as in the paper)")
    tube_margin: FiniteFloat = Field(0.025, ge=0.0, description="tube radius diam T(dt) [state "
                               "norm] (hand-set margins: mpc.margins = \"hand\")")
    input_margin: FiniteFloat = Field(0.0, ge=0.0, description="input-box tightening per side "
                                "(hand-set margins: mpc.margins = \"hand\")")
    margins: Literal["hand", "tube"] | str = Field(
        "hand", description='"hand": the margins of tube_margin and input_margin; "tube": '
        "those of the scenario's own tube diam T(1 / mpc.rate_hz) under its disturbance, "
        "plant and low level (as hmpc tube computes them; cached), so each MPC rate gets "
        "its own; else a margins file of hmpc tube --write (relative to the scenario file's "
        "directory): its guard-avoid, pass-through and input margins at mpc.rate_hz replace "
        "them")
    solver: SolverName = Field("ipopt", description=f"NLP back-end: {describe()}")
    solver_options: SolverOptions = Field(default_factory=dict, description="extra solver options: "
        "sections ipopt, ipopt_warm (IPOPT), hpipm (the SQP back-ends' QP) and fatrop (fatrop's "
        "own options over hmpc's, passed unchecked); other keys nlpsol options of mpc.solver's "
        "back-end, checked before the run (a switching NLP on another back-end gets its own "
        "sections only)")
    max_iter: BoundedInt = Field(200, gt=0, description="iteration limit (sqp_hpipm: of "
                                 "its IPOPT fallback; fatrop can run past it: its watchdog "
                                 "steps)")
    max_sqp_iter: BoundedInt = Field(3, gt=0, description="sqp_hpipm and rti: SQP "
                                     "iterations per solve (sqp_hpipm accepts a feasible "
                                     "point at the limit, rti any finite one)")
    switching_solver: SolverName | None = Field(
        None, description="back-end of the switching chain NLP (None: mpc.solver, but "
        '"ipopt" when mpc.solver is "sqp_hpipm": the SQP converges only linearly on its '
        "degenerate guard-hit rows)")
    warm_start: StrictBool = True
    resolve_on_impact: StrictBool = True
    node_shift: Literal["elapsed", "floor"] = Field(
        "elapsed", description='nodes moved to the final domain at each re-solve: "elapsed" '
        "(the time since the previous re-solve or scheduled contact [s] in whole node steps, "
        "rounded, the rest carried to the next re-solve; the MPC period must then be a whole "
        "number of node steps) or \"floor\" (the "
        "reference code's floor(nodes_per_second x elapsed), computed in floating point: "
        "0 at 100 Hz with 60 nodes/s, so the nodes never move, and 5 instead of 6 in some 10 "
        "Hz periods; any nodes_per_second)")
    schedule_rule: Literal["impact", "reference"] = Field(
        "impact", description='how the MPC keeps its schedule in closed loop: "impact" (the '
        "paper's impact rule: a domain is dropped when its scheduled guard fires; its node "
        'count never shifts below one) or "reference" (the reference code\'s bookkeeping, to '
        "emulate it: every contact that does not enter the final domain drops the first "
        "domain, whichever guard fired; a contact into the final domain drops every domain "
        "before it; a domain whose planned nodes have all shifted away is dropped without a "
        'contact). Pair it with node_shift = "floor" to fly the reference code\'s rule whole')
    final_domain_nlp: StrictBool = Field(
        True, description="solve schedules with no switch left on the final domain's own, "
                          "smaller NLP (same problem, no switching rows)")

    @model_validator(mode="after")
    def _stagewise_for_fatrop(self) -> MPCSettings:
        for solver in (self.solver, self.switching_solver):
            if solver is not None and SOLVERS[solver].stagewise and self.input_hold == "foh":
                raise ValueError(f'solver "{solver}" needs stage-wise dynamics: set '
                                 'input_hold = "zoh" (a first-order hold couples each '
                                 'interval to the next input)')
        return self

    def input_margin_key(self) -> str:
        """The hand-set input margin's key path."""
        return "mpc.input_margin"

    def solver_choice(self) -> tuple[str, dict]:
        """(``mpc.solver``, ``mpc.solver_options``) for the set-up checks."""
        return self.solver, self.solver_options

    def solver_choices(self) -> list[tuple[str, dict]]:
        """(back-end, options) of the final-domain and (if another) the switching NLP."""
        choices = [(self.solver, self.solver_options)]
        if self.solver_of(1) != self.solver:
            choices.append((self.solver_of(1), self.options_of(1)))
        return choices

    def options_of(self, switches: int) -> dict:
        """``mpc.solver_options`` as the NLP with ``switches`` guard events takes them.

        All of them on ``mpc.solver``'s back-end; another back-end (the switching NLP's
        ``mpc.switching_solver``, or sqp_hpipm's IPOPT) takes the sections only (its own
        and its fallback's are picked from them): the other keys are ``mpc.solver``'s
        ``nlpsol`` options.
        """
        name = self.solver_of(switches)
        if name == self.solver:
            return self.solver_options
        nlpsol = split_options(SOLVERS[name], self.solver_options)[0]
        return {k: v for k, v in self.solver_options.items() if k not in nlpsol}

    def resolves_on_impact(self) -> bool:
        """``mpc.resolve_on_impact``."""
        return self.resolve_on_impact

    def solver_of(self, switches: int) -> str:
        """The back-end of the NLP with ``switches`` guard events (0: final domain's)."""
        if switches == 0:
            return self.solver
        if self.switching_solver is not None:
            return self.switching_solver
        return SOLVERS[self.solver].switching or self.solver

    def period_steps(self) -> list[tuple[str, int]]:
        """Step rates the MPC period must be a whole number of (key path, rate [Hz])."""
        if self.node_shift == "floor":  # the reference's rule needs no whole number
            return []
        return [("mpc.nodes_per_second", self.nodes_per_second)]

    def shifted_nodes(self, elapsed: float) -> int:
        """Intervals to move after ``elapsed`` seconds, by ``node_shift`` (>= 0)."""
        if self.node_shift == "floor":
            return max(0, math.floor(self.nodes_per_second * elapsed))
        return max(0, int(round(elapsed / self.dt)))

    def size_problems(self) -> list[str]:
        """Horizon nodes, or nodes + switches, beyond :data:`MAX_NLP_NODES`.

        Checked before anything is built. The switching chain NLP has one link per node
        interval and one per guard event it can hold.
        """
        n = self.horizon * self.nodes_per_second
        if n > MAX_NLP_NODES:
            return [f"mpc.horizon: {self.horizon:g} s x {self.nodes_per_second} nodes/s "
                    f"(mpc.nodes_per_second) = "
                    f"{n:.3g} NLP nodes exceeds the limit {MAX_NLP_NODES} (it would need "
                    f"{nlp_estimate(n, NODE_MIB, NODE_MS)})"]
        S = self.max_switches
        if n + S <= MAX_NLP_NODES:
            return []
        return [f"mpc.max_switches: {n:.3g} nodes (mpc.horizon x mpc.nodes_per_second) + "
                f"{S} switches = {n + S:.3g} links of the switching NLP exceeds the limit "
                f"{MAX_NLP_NODES} (the switches alone would need "
                f"{nlp_estimate(S, SWITCH_MIB, SWITCH_MS, per='switch')})"]

    def scenario_problems(self) -> list[str]:
        """``mpc.key: reason`` lines for settings that do not fit together."""
        n = self.horizon * self.nodes_per_second
        if n < 2 or abs(n - round(n)) > 1e-9 * max(1.0, n):
            return ["mpc.horizon: must be a whole number (>= 2) of node steps"]
        if self.horizon < 1.0 / self.rate_hz - 1e-12:
            return [f"mpc.horizon: {self.horizon:g} s is shorter than the MPC period "
                    f"1 / mpc.rate_hz = {1.0 / self.rate_hz:g} s: each plan would run out "
                    "before the next one; lengthen mpc.horizon or raise mpc.rate_hz"]
        return []

    @property
    def dt(self) -> float:
        """Node step [s]."""
        return 1.0 / self.nodes_per_second

    @property
    def n_intervals(self) -> int:
        """Flow intervals over the horizon, N."""
        return round(self.horizon * self.nodes_per_second)

    @property
    def nodes_per_period(self) -> int:
        """Intervals elapsed per MPC period."""
        return self.nodes_per_second // self.rate_hz


class FixedModeNLP:
    """The parametric fixed-mode NLP on a chain of N + S links (built once).

    Named blocks (see :mod:`hmpc_cli.mpc.builder`; stage k = node k and link k), in the
    order of the flat vectors:

    * x, per stage k: ``z`` (n), ``u`` (m, links only), ``sigma`` (scalar slack);
    * g, per stage k: ``dynamics`` (n, links only), ``guard_avoid`` (one row per guard
      with rows), and with S > 0 ``guard_hit`` (scalar), ``virtual_node`` (scalar),
      ``region`` (R, if any guard has a region); after the last stage ``terminal`` (T);
    * p: ``a`` (L, M), ``b`` (L, G), ``e``, ``w``, ``v``, ``foh`` (L each), ``s``,
      ``kappa`` (L + 1, Gr), ``beta`` (L + 1, G), ``kappa_v`` (L + 1), ``hit``
      (L + 1, G) (the last three with no rows when S = 0).

    Args:
        system: the hybrid system (the controllers' model).
        settings: MPC settings.
        switches: S, the guard events the chain holds (default ``settings.max_switches``).
            With S = 0 the NLP is the final domain's plain MPC: only that mode's flow and
            guard-avoid rows, no reset, virtual-node or region rows (a much smaller KKT
            system for the solves after the last scheduled switch).
        margins: the guard, virtual-node and input tightenings (parameters and bounds
            only); default the hand-set ones of ``settings.tube_margin`` and
            ``settings.input_margin``.
    """

    def __init__(self, system: HybridSystem, settings: MPCSettings,
                 switches: int | None = None,
                 margins: ConstraintMargins | None = None) -> None:
        """Builds the NLP and its solver session (see the class docstring)."""
        self.system = system
        self.s = settings
        self.S = settings.max_switches if switches is None else switches
        self.N = settings.n_intervals
        self.L = self.N + self.S
        self.dt = settings.dt
        self.n, self.m = system.n_x, system.n_u
        self.G = len(system.guards)
        final = system.mode_index(system.final_mode)
        # modes with a flow in the chain, guards with rows (local column order)
        self.modes_in = list(range(len(system.modes))) if self.S else [final]
        self.row_guards = list(range(self.G)) if self.S else system.guards_of(final)
        self.mode_col = {mode: c for c, mode in enumerate(self.modes_in)}
        self.guard_col = {g: c for c, g in enumerate(self.row_guards)}
        self.M, self.Gr = len(self.modes_in), len(self.row_guards)
        self.R = max([g.region.size1_out(0) for g in system.guards if g.region is not None]
                     or [0]) if self.S else 0
        self.T = system.terminal_set.size1_out(0) if system.terminal_set is not None else 0
        self.guards_of = [system.guards_of(i) for i in range(len(system.modes))]
        self.margins = margins or ConstraintMargins.hand(system, settings.tube_margin,
                                                         settings.input_margin)
        # guard-avoid offsets: margin 0 for the guard just crossed, else the tube margin
        self.avoid_offsets = list(zip(self.margins.entered, self.margins.avoid, strict=True))
        #: per mode: its column in the link-type parameter a (-1: no flow in this NLP)
        self.mode_cols = np.array([self.mode_col.get(i, -1) for i in range(len(system.modes))])
        #: per mode: its tightened input box (lower, upper), shape (modes, 2, m)
        self.input_boxes = np.array([self.input_box(i) for i in range(len(system.modes))])
        self._guard_functions()
        self._stage_fns: tuple[ca.Function, ...] | None = None  # of _stage_kinds, made once
        self._build()
        self.shape = ChainShape(
            system=system, s=settings, layout=self.layout, L=self.L, m=self.m, dt=self.dt,
            margins=self.margins, input_boxes=self.input_boxes, mode_cols=self.mode_cols,
            guards_of=self.guards_of, guard_col=self.guard_col,
            avoid_offsets=self.avoid_offsets)

    # ------------------------------------------------------------------ build
    def _interval_expr(self, mode: int, z, u, u_end):
        """One interval of ``mode`` from z, the input going linearly from u to u_end."""
        f = self.system.modes[mode].flow
        w = ca.DM.zeros(self.system.n_w)
        h = self.dt
        if self.s.integrator == "euler":
            return z + h * f(z, u, w)
        u_mid = 0.5 * (u + u_end)
        k1 = f(z, u, w)
        k2 = f(z + h / 2 * k1, u_mid, w)
        k3 = f(z + h / 2 * k2, u_mid, w)
        k4 = f(z + h * k3, u_end, w)
        return z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    def _build(self) -> None:
        """The NLP from the build cache if compiled there, else built (and cached).

        Built, IPOPT gets the cost, rows and derivatives assembled from the stage kernels
        (:meth:`_staged`); another back-end, or IPOPT with options that may make ``nlpsol``
        differentiate the NLP itself (:func:`~hmpc_cli.mpc.solver.takes_assembled`), the SX
        transcription, IPOPT (or the fallback) with the staged derivatives.
        """
        key = cache.structure_key(self.system, self.s, self.S)
        # options that may make nlpsol differentiate the NLP itself need it in SX
        mx = takes_assembled(self.s.solver_of(self.S), self.s.options_of(self.S))
        hit = cache.lookup(key, self.s.solver_of(self.S), load=not mx)
        self.session = None
        if hit.library is not None:
            self.layout, self.build_info = hit.layout, hit.info
            try:
                self.session = self._session(hit.library)
            except RuntimeError as exc:  # a library CasADi refuses: build in SX
                _LOG.warning("cannot load %s (%s): building the NLP in SX", hit.library,
                             str(exc).strip().splitlines()[-1:])
                hit = cache.Hit(None, None, cache.BuildInfo("miss", False, "unloadable"))
        if self.session is None:
            self.build_info = self._built(key, hit, mx)
        X, g = self.layout.x, self.layout.g
        self.nx_var, self.ng, self.np = X.size, g.size, self.layout.p.size
        self.z_idx, self.u_idx, self.s_idx = X["z"], X["u"], X["sigma"]
        self.link_rows = np.stack([g.at(k) for k in range(self.L)])  # (L, rows per link)

    def _built(self, key: str, hit: cache.Hit, mx: bool) -> cache.BuildInfo:
        """Builds the session of an NLP the cache holds no library of; its build info.

        The info is the cache's, with where the stage kernels run. ``mx``: IPOPT gets the
        NLP assembled from stage kernels; else (another back-end, options that may make
        ``nlpsol`` differentiate the NLP itself) the SX transcription, which the cache's
        modes that compile also store when they hold none (with the staged Hessian of SX
        kernels: the library's C).
        """
        solver = self.s.solver_of(self.S)
        backend = SOLVERS[solver]
        fallback = SOLVERS[backend.fallback].plugin if backend.fallback else None
        stores = hit.info.cache != "disabled" and not hit.stored and \
            cache.mode() in ("background", "sync")
        if hit.stored:  # loaded unless mx
            sx, self.layout = hit.transcription, hit.layout
        elif not mx or stores:
            sx, self.layout = self._transcription()
        else:
            sx, self.layout = None, self._builder().layout()
        staged = self._staged(self.layout, compiled=cache.mode() != "off") \
            if "ipopt" in (backend.plugin, fallback) else None
        nlp = staged.nlp() if mx else sx
        self.session = self._session(nlp, staged.derivatives() if staged else None)
        info = hit.info if hit.info.cache == "disabled" else cache.store(
            key, solver, sx, self.layout, stored=hit.stored,
            hess_lag=self._staged_hessian(self.layout) if staged and stores else None)
        if staged is None:
            return info
        what = "cost, rows and derivatives" if mx else "derivatives" if \
            backend.plugin == "ipopt" else f"derivatives of {backend.fallback}, the fallback,"
        return dataclasses.replace(info, reason=f"{info.reason}; {what} assembled stage by "
                                                f"stage: {kernels.describe(staged.made)}")

    def _session(self, nlp: dict | str,
                 derivatives: dict[str, ca.Function] | None = None) -> SolverSession:
        """The solver session of the NLP (a dict of MX or SX, or a compiled library's path).

        ``derivatives``: IPOPT's derivative functions by ``nlpsol`` option
        (:meth:`~hmpc_cli.mpc.staged.StagedNLP.derivatives`).
        """
        equality, structure, solver = None, None, self.s.solver_of(self.S)
        if SOLVERS[solver].stagewise:
            eq = np.zeros(self.layout.g.size, dtype=bool)
            eq[self.layout.g["dynamics"]] = True
            equality, structure = eq.tolist(), self.structure()
        return SolverSession(
            "fixed_mode_mpc", nlp, solver, max_iter=self.s.max_iter, tol=1e-8,
            equality=equality, extra=self.s.options_of(self.S), warm=WARM_START,
            structure=structure, sqp_iter=self.s.max_sqp_iter, derivatives=derivatives)

    def _builder(self) -> NLPBuilder:
        """The builder with x, p and g laid out stage by stage (the rows by place only)."""
        b = NLPBuilder()
        for k in range(self.L + 1):
            with b.stage(k):
                b.variable("z", self.n)
                if k < self.L:
                    b.variable("u", self.m)
                b.variable("sigma")
        self._parameters(b)
        for k in range(self.L + 1):
            with b.stage(k):
                for name, shape in self._row_blocks(link=k < self.L):
                    b.place_rows(name, shape)
        if self.T:
            b.place_rows("terminal", self.T)
        return b

    def _transcription(self) -> tuple[dict, NLPLayout]:
        """The NLP ``{"x", "p", "f", "g"}`` in SX and its layout.

        :meth:`_staged_nlp` makes the cost and the rows, evaluated on the builder's
        symbols (:meth:`_builder`).
        """
        b = self._builder()
        (x, p), layout = b.symbols(), b.layout()
        f, g = self._staged_nlp(layout).call([x, p])
        return {"x": x, "p": p, "f": f, "g": g}, layout

    def _row_blocks(self, link: bool) -> list[tuple[str, int | tuple]]:
        """(row group, shape) of a stage's rows in registration order.

        A link's, or the last node's; shape () is a scalar row.
        """
        blocks = [("dynamics", self.n)] if link else []
        blocks.append(("guard_avoid", self.Gr))
        if self.S:
            blocks += [("guard_hit", ()), ("virtual_node", ())] + \
                ([("region", self.R)] if self.R else [])
        return blocks

    def _staged_nlp(self, layout: NLPLayout, expand: bool = True) -> ca.Function:
        """(x, p) -> (f, g) in SX: each kind of stage one SX function, mapped over its stages.

        The stage functions (:meth:`_stage_functions`) take a stage's variables and its
        parameters as symbols; mapped over the links in MX on gathers of the flat x and p,
        then expanded, their instructions are replayed on every stage's entries. As x, p
        and g keep the builder's order, the result is the graph the operations written
        out stage by stage give, instruction for instruction (so no iterate depends on
        how the NLP was transcribed; tests compare the graphs, random systems included),
        in a fraction of the Python calls. ``expand=False`` keeps the map in MX
        (``benchmarks/probe_stagewise.py`` measures both).
        """
        x, p = ca.MX.sym("x", layout.x.size), ca.MX.sym("p", layout.p.size)
        rows, costs = [], []
        for kind in self._stage_kinds(layout, x, p):
            args = [c for c, _ in kind.variables]
            if not kind.has_cost:  # the last node
                rows.append(kind.fn(*args, kind.parameters))
                continue
            r, j = kind.fn.map(kind.count)(*args, kind.parameters)
            rows.append(ca.vec(r))
            costs.append(j)
        f = total_cost(costs, x, (layout.x["sigma"].ravel(), self.s.soft_penalty))
        fn = ca.Function("nlp", [x, p], [f, ca.vertcat(*rows)])
        return fn.expand() if expand else fn

    def _stage_kinds(self, layout: NLPLayout, x: ca.MX, p: ca.MX) -> list[StageKind]:
        """Each kind of stage in the order of g, on the MX symbols x and p.

        The kinds are :meth:`_stage_functions`' (links with a first-order hold, held links,
        the last node), those with no stage left out; a kind's parameters are its stages'
        parameter blocks stacked.
        """
        X, P, L = layout.x, layout.p, self.L
        link_par, node_par = self._stage_parameters()
        widths = {name: math.prod(P[name].shape[1:]) for name in link_par}
        if self._stage_fns is None:
            self._stage_fns = self._stage_functions(link_par, node_par, widths)
        link, held, last = self._stage_fns
        n_foh = L - 1 if self.s.input_hold == "foh" else 0  # the rest hold their input
        out = []
        for fn, ks, names in ((link, slice(0, n_foh), link_par), (held, slice(n_foh, L),
                              link_par), (last, slice(L, L + 1), node_par)):
            if ks.stop == ks.start:
                continue
            zn = slice(ks.start + 1, ks.stop + 1)
            blocks = [(X["z"], ks), (X["sigma"], ks)] if fn is last else \
                [(X["z"], ks), (X["u"], ks), (X["sigma"], ks), (X["z"], zn)] + \
                ([(X["u"], zn)] if fn is link else [])
            pars = ca.vertcat(*[_stage_columns(p, P[name], ks)[0] for name in names])
            out.append(StageKind(fn, ks.stop - ks.start,
                                 [_stage_columns(x, idx, stages) for idx, stages in blocks],
                                 pars))
        return out

    def _staged(self, layout: NLPLayout, compiled: bool = False) -> StagedNLP:
        """The NLP's cost, rows and derivatives assembled from its stage kernels.

        See :class:`~hmpc_cli.mpc.staged.StagedNLP`; ``compiled``: the kernels' C libraries
        where the cache holds them (:func:`hmpc_cli.mpc.kernels.compiled`).
        """
        x, p = ca.MX.sym("x", layout.x.size), ca.MX.sym("p", layout.p.size)
        slack = (layout.x["sigma"].ravel(), self.s.soft_penalty)
        return StagedNLP(self._stage_kinds(layout, x, p), x, p, slack, compiled)

    def _staged_hessian(self, layout: NLPLayout, compiled: bool = False) -> ca.Function:
        """IPOPT's Hessian of the Lagrangian assembled stage by stage.

        (x, p, lam_f, lam_g) -> triu(H) (:meth:`~hmpc_cli.mpc.staged.StagedNLP.hessian`).
        Equal to ``nlpsol``'s bit for bit with a zero-order hold, to rounding with a
        first-order hold (u_k's entries sum links k-1 and k in another order).
        """
        return self._staged(layout, compiled).hessian()

    def _stage_parameters(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """The parameter blocks a link's and a node's rows read (see :meth:`_parameters`)."""
        node = ("s", "kappa") + (("hit", "beta", "kappa_v") if self.S else ())
        return ("a", "b", "e", "w", "v", "foh") + node, node

    def _stage_functions(self, link_par, node_par, widths) -> tuple[ca.Function, ...]:
        """SX functions of one stage: (link with a first-order hold, held link, last node).

        Links: (z_k, u_k, sigma_k, z_k+1[, u_k+1], p_k) -> (rows, cost): link k's dynamics
        rows then node k's path rows, and its stage cost; the held link's interval holds u_k
        (its u_end the same symbol as u_k: CasADi simplifies 0.5 (u + u) to u as it does
        written out). The last node: (z_L, sigma_L, p_L) -> its path rows, then the terminal
        rows. p_k holds the blocks of ``link_par`` (``node_par``) at stage k, in order, each
        of its ``widths`` entry's size.
        """
        n, m, sysm, switching = self.n, self.m, self.system, self.S > 0
        z, z1, sk = ca.SX.sym("z", n), ca.SX.sym("z_next", n), ca.SX.sym("sigma")
        u, u1 = ca.SX.sym("u", m), ca.SX.sym("u_next", m)

        def split(names):
            pk = ca.SX.sym("p", sum(widths[name] for name in names))
            out, at = {}, 0
            for name in names:
                out[name] = pk[at:at + widths[name]]
                at += widths[name]
            return pk, out

        def node_rows(zk, sig, flows, par) -> list:
            if not switching:
                return self._path_exprs(zk, sig, par["s"], par["kappa"])
            vq = ca.vertcat(*(-self._q[i](flows[self._src[i]]) for i in range(self.G)))
            rows = self._path_exprs(zk, sig, par["s"], par["kappa"], par["hit"],
                                    par["beta"], par["kappa_v"], vq)
            return rows if self.R else rows[:3]

        def link_function(name, u_end, ins):
            pk, par = split(link_par)
            end = u_end(par)  # one expression for every mode's interval, as written out
            flows = [self._interval_expr(i, z, u, end) for i in self.modes_in]
            nxt = par["e"] * z
            for c in range(self.M):
                nxt += par["a"][c] * flows[c]
            for i, g in enumerate(sysm.guards if switching else ()):
                nxt += par["b"][i] * g.reset(z)
            rows = ca.vertcat(z1 - nxt, *node_rows(z, sk, flows, par))
            cost = par["w"] * sysm.stage_cost(z, u) + par["v"] * ca.sumsqr(u)
            return ca.Function(name, [*ins, pk], [rows, cost])

        link = link_function("link_foh", lambda par: u + par["foh"] * (u1 - u),
                             [z, u, sk, z1, u1])
        held = link_function("link_held", lambda par: u, [z, u, sk, z1])
        pk, par = split(node_par)
        zero = ca.DM.zeros(m)
        flows = [self._interval_expr(i, z, zero, zero) for i in self.modes_in] \
            if switching else []
        rows = node_rows(z, sk, flows, par)
        if self.T:
            rows.append(sysm.terminal_set(z) + sk)
        return link, held, ca.Function("last_node", [z, sk, pk], [ca.vertcat(*rows)])

    def structure(self) -> OCPStructure:
        """The HPIPM stage structure (zero-order hold only).

        Per stage k the state z_k, the controls (u_k, sigma_k) (sigma_L alone at the
        last stage), the dynamics rows then the path rows.
        """
        g = self.layout.g
        ng = [g.at(k).size - self.n for k in range(self.L)]
        ng.append(g.size - sum(ng) - self.n * self.L)  # node L's rows and the terminal set
        return OCPStructure.chain(self.n, [self.m + 1] * self.L + [1], ng)

    def _parameters(self, b: NLPBuilder) -> dict:
        """The parameter blocks (link types, weights, path-row signs and offsets)."""
        L, G, Gr = self.L, self.G, self.Gr
        nsw = L + 1 if self.S else 0
        shapes = {"a": (L, self.M), "b": (L, G if self.S else 0), "e": L, "w": L, "v": L,
                  "foh": L,  # 1: the interval's input ends at the next link's input
                  "s": (L + 1, Gr), "kappa": (L + 1, Gr), "beta": (nsw, G),
                  "kappa_v": nsw, "hit": (nsw, G)}
        return {name: b.parameter(name, shape) for name, shape in shapes.items()}

    def _guard_functions(self) -> None:
        """Guard functions q_g, source-flow column of each guard, padded regions."""
        sysm, zs = self.system, ca.SX.sym("zs", self.n)
        self._src = [self.mode_col.get(sysm.mode_index(g.source), 0) for g in sysm.guards]
        self._q = [ca.Function(f"q_{g.name}", [zs], [g.q_expr(zs)]) for g in sysm.guards]
        self._regions = []
        for g in sysm.guards if self.S else ():
            r = g.region(zs) if g.region is not None else ca.SX.zeros(0)
            pad = ca.vertcat(r, ca.SX.zeros(self.R - r.size1()))
            self._regions.append(ca.Function(f"r_{g.name}", [zs], [pad]))

    def _path_exprs(self, z, sk, s, kappa, hit=None, beta=None, kappa_v=None,
                    vq=None) -> list:
        """Node rows written out in operations on the arguments.

        (z, sigma, s, kappa (C each), hit, beta (G each), kappa_v, vq (G)) -> [guard_avoid
        (C), guard_hit, virtual_node, region (R)], vq_i = -q_i(flow of guard i's source) at
        the node; without switches (z, sigma, s, kappa) -> [guard_avoid].
        """
        q, G = self._q, self.G
        qz = {i: q[i](z) for i in (range(G) if hit is not None else self.row_guards)}
        avoid = ca.vertcat(*[s[c] * qz[i] - kappa[c] + sk
                             for c, i in enumerate(self.row_guards)])
        if hit is None:
            return [avoid]
        hit_row = sum(hit[i] * qz[i] for i in range(G)) - sk
        virt = 0
        for i in range(G):
            virt += beta[i] * vq[i]
        reg = ca.SX.zeros(self.R)
        for i in range(G):
            reg += beta[i] * self._regions[i](z)
        return [avoid, hit_row, virt - kappa_v + sk, reg + sk]

    # ------------------------------------------------------------ problem data
    def problem_data(self, ns: NodeSchedule, lay: ChainLayout, x0: np.ndarray):
        """Parameters and bounds of one solve: (p, lbx, ubx, lbg, ubg)."""
        return problem_data(self.shape, ns, lay, x0)

    def input_box(self, mode: int) -> tuple[np.ndarray, np.ndarray]:
        """The mode's input box shrunk by its input margins per side (never past its centre)."""
        md, shrink = self.system.modes[mode], np.array(self.margins.inputs[mode])
        lo = np.array(md.u_lower) + shrink
        hi = np.array(md.u_upper) - shrink
        mid = 0.5 * (np.array(md.u_lower) + np.array(md.u_upper))
        return np.minimum(lo, mid), np.maximum(hi, mid)

    # --------------------------------------------------------------- optimize
    def optimize(self, w0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None) -> SolveResult:
        """One solve from ``w0`` (see :meth:`SolverSession.run`); never raises on solver failure."""
        return self.session.run(w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0)

    def violation(self, w, p, lbx, ubx, lbg, ubg) -> float:
        """Largest constraint or bound violation at primal point w."""
        return self.session.violation(w, p, lbx, ubx, lbg, ubg)

    def constraints(self, w, p) -> np.ndarray:
        """Constraint values g(w, p), shape (ng,)."""
        return self.session.constraints(w, p)

    # ------------------------------------------------------------- warm start
    def remap_vectors(self, node_map, w, lam_x, lam_g, source: FixedModeNLP | None = None):
        """Re-indexes primal/dual vectors of ``source`` (default: this NLP) node by node.

        See :func:`layout.remap` for ``node_map`` (shape (L + 1,)); a link takes the
        entries of its start node's link (the source's last link past its end). Duals
        only within one NLP (None else).
        """
        src = source or self
        link_map = np.minimum(node_map[: self.L], src.L - 1)
        maps = {"z": node_map, "u": link_map, "sigma": node_map}
        new_w = w.copy() if src is self else np.zeros(self.nx_var)
        _move(new_w, w, maps, self.layout.x, src.layout.x)
        if lam_x is None or lam_g is None or src is not self:
            return new_w, None, None
        new_lx = _move(lam_x.copy(), lam_x, maps, self.layout.x, self.layout.x)
        new_lg = lam_g.copy()
        new_lg[self.link_rows] = lam_g[self.link_rows[link_map]]
        return new_w, new_lx, new_lg

    # ------------------------------------------------------------- trajectory
    def trajectory(self, w: np.ndarray, ns: NodeSchedule, lay: ChainLayout) -> Trajectory:
        """The planned hybrid trajectory (real nodes only; resets as node pairs)."""
        k_last = lay.last
        x = w[self.z_idx[: k_last + 1]]
        u = w[self.u_idx[: max(k_last, 1)]]
        u = np.vstack([u, u[-1:]])[: k_last + 1]
        steps = np.where(lay.link_type[:k_last] == FLOW, self.dt, 0.0)
        t = np.concatenate([[0.0], np.cumsum(steps)])
        seg = lay.seg[: k_last + 1].copy()
        mode = np.array([ns.modes[j] for j in seg])
        return Trajectory(t, x, u, mode, seg, tuple(ns.guards), self.s.input_hold)


def _stage_columns(v: ca.MX, idx: np.ndarray, stages: slice) -> tuple[ca.MX, np.ndarray]:
    """Entries ``idx[stages]`` of v, one column per stage, and those indices.

    ``idx``: a staged block's indices, shape (stages,) or (stages, width). Returns the
    entries, shape (width, stages), and the indices, shape (stages, width).
    """
    idx = (idx[:, None] if idx.ndim == 1 else idx)[stages]
    return ca.reshape(v[idx.ravel().tolist()], idx.shape[1], idx.shape[0]), idx


def _move(dst: np.ndarray, src: np.ndarray, maps: dict, to: Blocks, frm: Blocks):
    """Sets stage i of each staged block ``name`` of dst to stage ``maps[name][i]`` of src."""
    for name, stage_map in maps.items():
        dst[to[name]] = src[frm[name][stage_map]]
    return dst


class FixedModeNLPs:
    """The fixed-mode NLPs of one (system, settings), each built once (or cache-loaded).

    The switching chain (S = ``max_switches``) and, with ``final_domain_nlp``, the final
    domain's (S = 0).
    """

    def __init__(self, system: HybridSystem, settings: MPCSettings,
                 margins: ConstraintMargins | None = None) -> None:
        """Builds the NLPs (``margins``: see :class:`FixedModeNLP`)."""
        self.switching = FixedModeNLP(system, settings, margins=margins)
        self.final = FixedModeNLP(system, settings, switches=0, margins=margins) \
            if settings.final_domain_nlp else None
        self._final_mode = system.mode_index(system.final_mode)
        self.N, self.dt = self.switching.N, self.switching.dt

    @property
    def build_info(self) -> cache.BuildInfo:
        """How the NLPs were built: a hit if all were loaded, a miss if any was built."""
        infos = [n.build_info for n in (self.switching, self.final) if n is not None]
        kinds = {i.cache for i in infos}
        kind = "miss" if "miss" in kinds else ("hit" if kinds == {"hit"} else "disabled")
        return cache.BuildInfo(kind, all(i.compiled for i in infos),
                               "; ".join(dict.fromkeys(i.reason for i in infos)))

    def for_schedule(self, ns: NodeSchedule) -> FixedModeNLP:
        """The NLP that solves node schedule ``ns``."""
        if self.final is not None and ns.modes == (self._final_mode,):
            return self.final
        return self.switching
