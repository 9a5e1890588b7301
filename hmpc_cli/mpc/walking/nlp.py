"""The biped's fixed-mode walking MPC (paper Step 3) as one parametric NLP.

Two swings j = 0, 1 of ``N = nodes_per_swing`` intervals each, linked by the touchdown of
swing 0 on a target stair segment (the guard) and the model's reset map (impact + leg swap).

Transcription (inverse dynamics, semi-implicit Euler), per swing j, interval k < N:

    qd_{k+1} = qd_k + dt_j a_k,   q_{k+1} = q_k + dt_j qd_{k+1},
    u_k = ID(q_k, qd_k, a_k, w=0),   |u_k,i| <= torque_limit - torque_margin,

decision variables (q, qd) per node (swing 0's node 0 is the parameter x0) and the
accelerations a_k per interval. Swing 0 has dt_0 = max(swing_time - elapsed,
min_swing_time) / N (a parameter: the *remaining* time of the current swing on a fixed
node count, so the NLP never changes shape); swing 1 has dt_1 = swing_time / N.

Path rows of node k >= 1 of each swing (belonging to interval k - 1):

* guard-avoid: 0 <= foot_y - floor(foot_x) - c_k <= swing_height_cap - c_k in the world,
  with floor the *inflated* smooth terrain h0 + sum_i dh_i sigma((x - e_i') / w): each
  edge e_i moved by ``terrain_margin`` towards the lower side (a step up starts that much
  earlier), sigma the logistic function of width ``terrain_smoothing``. c_k =
  ``apex_clearance`` at the apex node (swing time apex_node * dt); within the first
  ``liftoff_time`` of a swing c_k = min(0, gap of the lifting foot in the solve's x0),
  so a foot that is on (or, near an edge, below) the inflated floor when the solve starts
  may not sink further (it is the swing start's gap only when the solve starts there). Off
  at swing 0's touchdown node. Swing 1 has no touchdown: its last node's upper bound
  is min(cap, ``swing2_end_clearance``) (foot ready to land anywhere; None: the cap);
* knees: stance and swing knee at least ``knee_clearance`` above the stance foot.

Swing 0's touchdown node (the virtual pass-through node): foot_y = h - touchdown_depth
and s + segment_margin <= foot_x <= e - segment_margin for the target (s, e, h) (bounds
only, no parameters). Swing 1's node 0 equals reset(x_N) (q, qd); its stance foot is the
old swing foot, an expression. State boxes |qd| <= rate_limit, stance knee and torso
ranges bound every node variable. If the swing started less than ``liftoff_time`` ago,
the swing foot's continuous-time vertical acceleration at node 0, J(q0) a_0 +
Jdot(q0, qd0) qd0, is at least ``liftoff_accel`` (one last row): the foot at rest on the
ground after an impact leaves it at once instead of re-touching.

Cost: sum_j sum_k dt_j [l(x_{k+1}) + r_torque |u_k|^2] with l = q_hip |hip - goal|^2
+ sum pose_weights (q - q_nominal)^2 + sum torso_top_weights (top - torso_top_target)^2
(hip in the world, torso top relative to the stance foot): the system's own stage cost
(``HybridSystem.stage_cost`` at (x_{k+1}, u_k)) plus the torso-top posture term of the
settings.

The transcription needs the system's :class:`~hmpc_cli.core.walker.WalkerModel`
(``HybridSystem.walker``: the state layout x = (q[n_q], qd[n_q], p_st[2]), the functions
above, the stance mode whose input box and margins bound the torques), its ``terrain``
and ``state_box``.
"""

from __future__ import annotations

import logging
from typing import Literal

import casadi as ca
import numpy as np
from pydantic import ConfigDict, Field, model_validator

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.kinds import MarginsSettings
from hmpc_cli.core.messages import ConstraintMargins
from hmpc_cli.core.numeric import tanh
from hmpc_cli.core.walker import WalkerModel
from hmpc_cli.mpc import cache
from hmpc_cli.mpc.builder import Bounds, NLPBuilder
from hmpc_cli.mpc.backends import OCPStructure
from hmpc_cli.mpc.solver import SolveResult, SolverSession, WarmStart
from hmpc_cli.mpc.solver_table import SolverOptions, backend_of
from hmpc_cli.core.settings_types import (
    BoundedInt, FiniteFloat, Pair, StrictBool, nlp_estimate)

INF = np.inf
_LOG = logging.getLogger(__name__)
WARM_START = WarmStart(mu_init=1e-4, bound_push=1e-6)  # the warm IPOPT instance
#: back-ends whose Hessian is the Gauss-Newton one of the cost's residuals
GAUSS_NEWTON = ("sqp_hpipm", "rti")
#: SQP steps per solve when mpc.max_sqp_iter is unset (rti: per warm-started solve)
SQP_ITER = {"rti": 1, "sqp_hpipm": 10}

#: measured cost of one walking-NLP node (cold and warm solvers; biped, 2 cores)
NODE_MIB, NODE_MS = 2.2, 27.0
#: most walking-NLP nodes (two swings): its solves grow faster than its nodes (measured,
#: AMD EPYC, 2 cores: the first planning step takes 0.8 s at 50 nodes, 3.4 s at 200 and
#: 12 s at 400; a 2,000-node run had not made 0.03 s in 400 s)
MAX_WALKING_NODES = 1000


class WalkingMPCSettings(MarginsSettings):
    """Fixed-mode walking MPC settings (reference values)."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["walking"] = Field("walking", description="two-swing walking MPC (biped)")
    rate_hz: BoundedInt = Field(10, gt=0, description="re-solve rate [Hz] (also after contacts)")
    swing_time: FiniteFloat = Field(0.3, gt=0.0, description="duration of a swing [s]")
    nodes_per_swing: BoundedInt = Field(25, ge=4, description="intervals per swing")
    min_swing_time: FiniteFloat = Field(0.03, gt=0.0, description="lower bound on swing 0's "
                                  "remaining time [s]")
    touchdown_depth: FiniteFloat = Field(0.005, ge=0.0, description="touchdown node this far "
                                   "below the target surface [m]")
    segment_margin: FiniteFloat = Field(0.075, ge=0.0, description="touchdown at least this far "
                                  "inside the segment's ends (tube tightening) [m] (hand-set "
                                  "margins)")
    apex_node: BoundedInt = Field(20, ge=1, description="node of a swing with the apex row")
    apex_clearance: FiniteFloat = Field(0.05, ge=0.0, description="foot above the terrain at the "
                                  "apex node [m]")
    liftoff_time: FiniteFloat = Field(0.024, ge=0.0, description="liftoff window: guard-avoid "
                                "row relaxed to the lifting foot's height in the solve's "
                                "start state [s]")
    liftoff_accel: FiniteFloat = Field(3.0, description="upward swing-foot acceleration at "
                                 "node 0 when the swing starts within the liftoff window "
                                 "[m/s^2]")
    terrain_margin: FiniteFloat = Field(0.025, ge=0.0, description="edge inflation of the "
                                  "guard-avoid terrain [m] (hand-set margins)")
    terrain_smoothing: FiniteFloat = Field(0.005, gt=0.0, description="logistic width of the "
                                     "terrain steps [m]")
    swing2_end_clearance: FiniteFloat | None = Field(0.05, gt=0.0, description="swing 1's last "
                                               "node at most this above the terrain [m]; "
                                               "None: free")
    swing_height_cap: FiniteFloat | None = Field(0.25, gt=0.0, description="swing foot at most "
                                           "this above the terrain at every node [m]; "
                                           "None: no cap")
    knee_clearance: FiniteFloat = Field(0.2, description="knees above the stance foot [m]")
    torque_margin: FiniteFloat = Field(300.0, ge=0.0, description="torque limit tightening "
                                 "(the low-level controller's share) [N m] (hand-set "
                                 "margins: mpc.margins = \"hand\")")
    margins: Literal["hand", "tube"] | str = Field(
        "hand", description='"hand": terrain_margin, segment_margin and torque_margin; '
        '"tube": those of the scenario\'s own tube at mpc.rate_hz (cached); else '
        "a margins file of hmpc tube --write (relative to the scenario file's directory): "
        "at mpc.rate_hz its largest guard-avoid offset is the terrain margin, its largest "
        "pass-through offset of a contact surface the segment margin, its input shrink the "
        "torque margin per joint")
    torso_top_target: Pair = Field((0.2, 1.6), description="torso top "
                                                  "relative to the stance foot [m]")
    torso_top_weights: Pair = Field((50.0, 5.0), description="cost weights "
                                                   "on the torso-top error [1/(m^2 s)]")
    solver: Literal["ipopt", "fatrop", "sqp_hpipm", "rti"] = Field(
        "ipopt", description='NLP back-end: "ipopt" (interior point, MUMPS); on the '
        "stage-wise transcription (explicit stage dynamics, every row at the stage of the "
        "variables it reads, swing 1 carrying the stance foot as a state): \"fatrop\" "
        "(stage-wise interior point), \"sqp_hpipm\" (SQP, Gauss-Newton Hessian from the "
        "system's stage_residuals, HPIPM's Riccati QP, IPOPT fallback) and \"rti\" (real-"
        "time iterations: mpc.max_sqp_iter such SQP steps per warm-started solve, up to 3 "
        "from a cold start, each kept)")
    max_sqp_iter: BoundedInt | None = Field(
        None, gt=0, description="SQP steps per solve: rti: per warm-started solve (None: 1; "
        "a cold one takes up to 3); sqp_hpipm: per solve before its IPOPT fallback (None: "
        "10)")
    max_iter: BoundedInt = Field(200, gt=0, description="iteration limit of IPOPT and fatrop "
                                 "(sqp_hpipm: of its IPOPT fallback; rti: unused; fatrop can "
                                 "run past it: its watchdog steps)")
    tol: FiniteFloat = Field(1e-6, gt=0.0, description="convergence tolerance (IPOPT's and "
                             "fatrop's tol; sqp_hpipm: primal and dual)")
    max_wall_time: FiniteFloat | None = Field(None, gt=0.0, description="IPOPT's wall-time "
                                              "cap [s] (not applied by the other back-ends)")
    warm_start: StrictBool = Field(True, description="primal-dual warm start from the previous "
                             "solution of the same candidate")
    impact_duals: StrictBool = Field(True, description="after a contact, also shift the "
                               "executed plan's multipliers (warm IPOPT instance)")
    solver_options: SolverOptions = Field(default_factory=dict, description="extra solver options: "
        "sections ipopt, ipopt_warm (IPOPT), hpipm (the SQP back-ends' QP) and fatrop (fatrop's "
        "own options over hmpc's, passed unchecked); other keys nlpsol options of mpc.solver's "
        "back-end, checked before the run (its IPOPT fallback gets its own sections only)")

    @model_validator(mode="after")
    def _apex_inside(self) -> WalkingMPCSettings:
        if self.apex_node >= self.nodes_per_swing:
            raise ValueError(f"apex_node {self.apex_node} must be below nodes_per_swing "
                             f"{self.nodes_per_swing}")
        return self

    def input_margin_key(self) -> str:
        """The hand-set torque margin's key path."""
        return "mpc.torque_margin"

    def solver_choice(self) -> tuple[str, dict]:
        """(``mpc.solver``, ``mpc.solver_options``) for the set-up checks."""
        return self.solver, self.solver_options

    def size_problems(self) -> list[str]:
        """``mpc.nodes_per_swing`` beyond :data:`MAX_WALKING_NODES` nodes (two swings)."""
        n = 2 * self.nodes_per_swing
        if n <= MAX_WALKING_NODES:
            return []
        return [f"mpc.nodes_per_swing: 2 swings x {self.nodes_per_swing} = {n} NLP nodes "
                f"exceeds the walking MPC's limit {MAX_WALKING_NODES}: its solves grow "
                "faster than its nodes (the first planning step took 12 s at 400 nodes; "
                f"the build alone would need {nlp_estimate(n, NODE_MIB, NODE_MS)})"]

    @property
    def dt(self) -> float:
        """Node step of a full swing [s]."""
        return self.swing_time / self.nodes_per_swing


def hand_margins(system: HybridSystem, settings: WalkingMPCSettings) -> ConstraintMargins:
    """The hand-set margins as :class:`ConstraintMargins` (what ``margins = "hand"`` means).

    Every guard's avoid offset is ``terrain_margin`` and its pass-through offset
    ``segment_margin`` [m]; every joint's shrink ``torque_margin`` [N m]; the radius is the
    state-norm radius whose offset is ``terrain_margin`` (the guards' Lipschitz constant).
    """
    gs = system.guards
    lip = max((g.lipschitz for g in gs), default=1.0)
    return ConstraintMargins(
        "hand", settings.terrain_margin / lip, (settings.terrain_margin,) * len(gs),
        tuple(g.kappa(0.0, past=False) for g in gs), (settings.segment_margin,) * len(gs),
        tuple((settings.torque_margin,) * system.n_u for _ in system.modes))


def _smooth_step(z):
    return 0.5 * (1.0 + ca.tanh(0.5 * z))


class WalkingNLP:
    """The parametric two-swing NLP (built once per parameters and settings).

    Named blocks (see :mod:`hmpc_cli.mpc.builder`; N = nodes_per_swing, stage (j, k) =
    interval k of swing j for a and rows, node k of swing j for x), in flat order:
        x: per swing j, per interval k: ``a`` (5) at (j, k), then ``x`` = (q, qd) (10) at
           (j, k + 1); swing 1's node 0 (``x`` at (1, 0)) precedes its first interval.
           ``x_idx[j, k]`` (10 indices, -1 for the parameter node (0, 0)) and
           ``a_idx[j, k]`` index it.
        g: per swing, per interval: ``dynamics`` (10), ``torque`` (5), ``guard_avoid``
           (scalar), ``knees`` (2) (``interval_rows[j, k]``: all 18); after swing 0
           ``touchdown`` (x, y: the segment and the guard) and ``reset`` (10); last
           ``liftoff`` (scalar: the swing foot's vertical acceleration at node 0).
        p: ``x0`` (10) and ``stance`` (2) = the state x0 (12), ``dt0``, ``h0``,
           shifted ``edges`` (E), ``jumps`` (E), clearances ``clear`` (2, N + 1).

    The stage-wise transcription (``stagewise``: fatrop, sqp_hpipm, rti) adds a variable
    block ``stance`` (2) after each of swing 1's ``x`` and rows ``stance_foot`` (2) after
    each swing-1 interval's dynamics; its ``reset`` has 12 rows (with the stance foot).
    Its rows run stage by stage (see :meth:`_transcribe`); the blocks keep their names
    and stage labels, so ``interval_rows`` names the same 18 rows in both.
    """

    def __init__(self, system: HybridSystem, settings: WalkingMPCSettings,
                 margins: ConstraintMargins | None = None) -> None:
        """Builds the NLP and its solver session.

        ``margins``: the tightenings (default :func:`hand_margins` of the settings); the
        NLP uses the largest guard-avoid offset as ``terrain_margin``, the largest
        pass-through offset of a guard with a contact surface as ``segment_margin`` [m]
        and the stance mode's input shrink as ``torque_margin`` [N m] per joint.

        Raises:
            ValueError: the system has no :class:`~hmpc_cli.core.walker.WalkerModel`.
        """
        if not isinstance(system.walker, WalkerModel):
            raise ValueError(f"the walking MPC needs a WalkerModel: system {system.name!r} "
                             f"has none (HybridSystem.walker)")
        self.system, self.s, self.walker = system, settings, system.walker
        self.mode = system.mode_index(self.walker.stance_mode)  # the stance mode's index
        self.margins = margins or hand_margins(system, settings)
        surfaces = list(system.guard_surfaces) or range(len(system.guards))
        self.terrain_margin = max(self.margins.avoid, default=0.0)
        self.segment_margin = max((self.margins.pass_through[g] for g in surfaces),
                                  default=0.0)
        self.torque_margin = np.asarray(self.margins.inputs[self.mode], dtype=float)
        self.model = _Outputs(self.walker)
        self.nq = self.walker.n_q
        self.nx = 2 * self.nq  # (q, qd) per node; p_st is a parameter or an expression
        self.N = settings.nodes_per_swing
        self.E = len(system.terrain.segments)
        self.stagewise = backend_of(settings.solver).stagewise
        self.gauss_newton = settings.solver in GAUSS_NEWTON
        self.sqp_iter = settings.max_sqp_iter or SQP_ITER.get(settings.solver, 1)
        if self.gauss_newton and system.stage_residuals is None:
            raise ValueError(f"mpc.solver = {settings.solver!r} needs the system's "
                             f"stage_residuals (its stage cost as least squares): system "
                             f"{system.name!r} has none; use \"ipopt\" or \"fatrop\"")
        self._residuals: list = []
        self._build()

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        b, N, sw = NLPBuilder(), self.N, self.stagewise
        xs, acc, pst = {}, {}, {}
        for j in range(2):
            if j == 1:
                with b.stage((1, 0)):
                    xs[1, 0] = b.variable("x", self.nx)
                    if sw:
                        pst[0] = b.variable("stance", 2)
            for k in range(N):
                with b.stage((j, k)):
                    acc[j, k] = b.variable("a", self.nq)
                with b.stage((j, k + 1)):
                    xs[j, k + 1] = b.variable("x", self.nx)
                    if sw and j == 1:
                        pst[k + 1] = b.variable("stance", 2)
        shapes = {"x0": self.nx, "stance": 2, "dt0": (), "h0": (), "edges": self.E,
                  "jumps": self.E, "clear": (2, N + 1)}
        par = {name: b.parameter(name, shape) for name, shape in shapes.items()}
        xs[0, 0] = par["x0"]
        J, xs_out, us_out = self._transcribe(b, xs, acc, pst, par)
        nlp, self.layout = b.build(J)
        X, g = self.layout.x, self.layout.g
        self.nw, self.ng, self.n_par = X.size, g.size, self.layout.p.size
        self.x_idx, self.a_idx = X.grid("x"), X.grid("a")
        self.interval_rows = np.array([[self._interval(j, k) for k in range(N)]
                                       for j in range(2)])
        self.session, self.build_info = self._session(nlp)
        self._traj_fun = ca.Function("traj", [nlp["x"], nlp["p"]],
                                     [ca.horzcat(*xs_out).T, ca.horzcat(*us_out).T])
        self._f_fun = ca.Function("f", [nlp["x"], nlp["p"]], [J])

    def _interval(self, j: int, k: int) -> np.ndarray:
        """Rows of interval k of swing j: dynamics, torque, then node k + 1's rows (18)."""
        g = self.layout.g
        return np.concatenate([g[name][g.stages(name).index((j, k))].ravel()
                               for name in ("dynamics", "torque", "guard_avoid", "knees")])

    def _session(self, nlp: dict) -> tuple[SolverSession, cache.BuildInfo]:
        """The solver on the NLP's compiled functions if the build cache holds them, else SX.

        The graph is transcribed either way (the plan and cost functions need it); a
        cached library is used only if its layout is this NLP's.
        """
        s = self.s
        variant = {"kind": "walking", "terrain_margin": float(self.terrain_margin),
                   "segment_margin": float(self.segment_margin),
                   "torque_margin": self.torque_margin.tolist()}
        if self.stagewise:  # another graph than IPOPT's (its key stays as it was)
            variant["stagewise"] = True
        key = cache.structure_key(self.system, s, 0, variant)
        hit = cache.lookup(key, s.solver)
        equality, structure = (self.equality_rows().tolist(), self.structure()) \
            if self.stagewise else (None, None)

        residuals = ca.vertcat(*self._residuals) if self.gauss_newton else None

        def session(source: dict | str) -> SolverSession:
            return SolverSession("walking_mpc", source, s.solver, max_iter=s.max_iter,
                                 tol=s.tol, max_wall_time=s.max_wall_time,
                                 extra=s.solver_options, warm=WARM_START,
                                 equality=equality, structure=structure,
                                 sqp_iter=self.sqp_iter, residuals=residuals)

        if hit.library is not None:
            if hit.layout.to_dict() != self.layout.to_dict():
                _LOG.warning("%s: layout differs from the NLP's: building it in SX",
                             hit.library)
            else:
                try:
                    return session(hit.library), hit.info
                except RuntimeError as exc:  # a library CasADi refuses: SX
                    _LOG.warning("cannot load %s (%s): building the NLP in SX",
                                 hit.library, str(exc).strip().splitlines()[-1:])
            return session(nlp), cache.BuildInfo("miss", False, "unloadable")
        return session(nlp), hit.info if hit.info.cache == "disabled" else \
            cache.store(key, s.solver, nlp, self.layout)

    def equality_rows(self) -> np.ndarray:
        """Per row, True for the equality rows, shape (ng,).

        They are the dynamics, the stance foot kept, the reset and the touchdown height.
        """
        g = self.layout.g
        eq = np.zeros(g.size, dtype=bool)
        for name in ("dynamics", "stance_foot", "reset"):
            if name in g:
                eq[g[name].ravel()] = True
        eq[g["touchdown"][1]] = True
        return eq

    def structure(self) -> OCPStructure:
        """The stage structure of the stage-wise transcription.

        Stages: swing 0's nodes 0..N (node 0 the parameter x0: no state), then swing 1's
        nodes 0..N with the stance foot appended to (q, qd); controls a at every node
        but a swing's last; path rows per stage as :meth:`_transcribe` orders them.

        Raises:
            ValueError: the NLP is not the stage-wise transcription.
        """
        if not self.stagewise:
            raise ValueError("the walking NLP has a stage structure only with a stage-wise "
                             "back-end (mpc.solver = \"fatrop\", \"sqp_hpipm\" or \"rti\")")
        N, nx, nq = self.N, self.nx, self.nq
        node = 1 + 2  # guard-avoid, knees
        nxs = (0,) + (nx,) * N + (nx + 2,) * (N + 1)
        nus = ((nq,) * N + (0,)) * 2
        ngs = ((nq + 1,) + (nq + node,) * (N - 1) + (node + 2,)
               + (nq,) + (nq + node,) * (N - 1) + (node,))
        st = OCPStructure(nxs, nus, ngs)
        if st.sizes() != (self.nw, self.ng):
            raise ValueError(f"walking NLP: {st.sizes()} (variables, rows) in the stage "
                             f"structure, {(self.nw, self.ng)} in the NLP")
        return st

    def _transcribe(self, b: NLPBuilder, xs: dict, acc: dict, pst1: dict, par: dict):
        """Registers the rows; returns the cost and the plan's node states and torques.

        ``pst1``: swing 1's stance-foot variables per node (stage-wise transcription),
        else empty (swing 1's stance foot is the reset's expression). The stage-wise
        order puts, per stage, the rows closing the gap to the next stage first (the
        explicit dynamics; after swing 0 the reset), then the rows of the stage's own
        node (torque, liftoff; guard-avoid and knees of node k >= 1; swing 0's
        touchdown); node rows keep their interval's stage label either way.
        """
        N, s, mdl = self.N, self.s, self.model
        fx = ca.SX.sym("fx")
        h0, edges, jumps = par["h0"], par["edges"], par["jumps"]
        floor = h0 + sum(jumps[i] * _smooth_step((fx - edges[i]) / s.terrain_smoothing)
                         for i in range(self.E))
        floor_fn = ca.Function("floor", [fx, h0, edges, jumps], [floor])
        J, pst = 0, par["stance"]
        xs_out, us_out = [ca.vertcat(par["x0"], pst)], []
        pending: list = []  # stage-wise: a node's rows wait for its stage's gap rows

        def flush() -> None:  # the waiting rows of node k + 1 of swing j
            while pending:
                j, k, pts, foot = pending.pop()
                with b.stage((j, k)):
                    b.rows("guard_avoid", foot[1] - floor_fn(foot[0], h0, edges, jumps)
                           - par["clear"][j, k + 1], shape=())
                    b.rows("knees", [pts[1, mdl.stance_knee], pts[1, mdl.swing_knee]])

        for j in range(2):
            dt = par["dt0"] if j == 0 else s.dt
            for k in range(N):
                if self.stagewise and j == 1:
                    pst = pst1[k + 1]
                u = self._interval_rows(b, j, k, xs, acc, pst1, par, dt)
                flush()
                xn = xs[j, k + 1]
                pts = mdl.points(xn[:self.nq])
                pending.append((j, k, pts, pts[:, mdl.swing_foot] + pst))
                if not self.stagewise:
                    flush()
                J += dt * self._stage_cost(xn, pst, u)
                if self.gauss_newton:
                    self._residuals.append(ca.sqrt(dt) * self._stage_residual(xn, pst, u))
                xs_out.append(ca.vertcat(xn, pst))
                us_out.append(u)
            if j == 0:
                pst = self._junction(b, xs, pst1, pst, flush)
                xs_out.append(ca.vertcat(xs[1, 0], pst))
        flush()
        if not self.stagewise:
            self._liftoff_row(b, par, acc)
        return J, xs_out, us_out

    def _interval_rows(self, b: NLPBuilder, j: int, k: int, xs: dict, acc: dict,
                       pst1: dict, par: dict, dt):
        """Interval k of swing j's dynamics and torque rows; returns its torques u (nq,).

        Stage-wise: explicit dynamics (q first, then qd), swing 1's stance foot kept, and
        the liftoff row in the first stage.
        """
        nq = self.nq
        xk, xn, a = xs[j, k], xs[j, k + 1], acc[j, k]
        q, qd, qn, qdn = xk[:nq], xk[nq:], xn[:nq], xn[nq:]
        u = self.model.inverse_dynamics(q, qd, a, 0)
        with b.stage((j, k)):
            if self.stagewise:
                b.rows("dynamics", [qn - q - dt * (qd + dt * a), qdn - qd - dt * a])
                if j == 1:
                    b.rows("stance_foot", pst1[k + 1] - pst1[k])
            else:
                b.rows("dynamics", [qdn - qd - dt * a, qn - q - dt * qdn])
            b.rows("torque", u)
            if self.stagewise and (j, k) == (0, 0):
                self._liftoff_row(b, par, acc)
        return u

    def _junction(self, b: NLPBuilder, xs: dict, pst1: dict, pst, flush):
        """Swing 0's touchdown rows and the reset to swing 1's node 0.

        ``flush`` registers the waiting rows of swing 0's last node (stage-wise order).
        Returns swing 1's stance foot (2,).
        """
        mdl = self.model
        x_td = ca.vertcat(xs[0, self.N], pst)
        foot = mdl.swing_foot_world(x_td)
        x_plus = mdl.reset(x_td)
        if self.stagewise:
            b.rows("reset", ca.vertcat(xs[1, 0], pst1[0]) - x_plus)
            flush()
            b.rows("touchdown", [foot[0], foot[1]])
            return pst1[0]
        b.rows("touchdown", [foot[0], foot[1]])
        b.rows("reset", xs[1, 0] - x_plus[:self.nx])
        return x_plus[self.nx:]

    def _liftoff_row(self, b: NLPBuilder, par: dict, acc: dict) -> None:
        """The swing foot's vertical acceleration at node 0 (one row)."""
        mdl, nq = self.model, self.nq
        q0, qd0 = par["x0"][:nq], par["x0"][nq:]
        vel = mdl.swing_foot_velocity(q0, qd0)
        lift = ca.jtimes(vel, q0, qd0) + ca.mtimes(mdl.swing_foot_jacobian(q0), acc[0, 0])
        with b.stage(None):  # one row, unstaged in either order
            b.rows("liftoff", lift[1], shape=())

    def _stage_residual(self, xq, pst, u):
        """Residuals r with |r|^2 = :meth:`_stage_cost` (the system's stage_residuals)."""
        s, mdl = self.s, self.model
        pts = mdl.points(xq[:self.nq])
        top_t, top_w = ca.DM(s.torso_top_target), np.sqrt(np.asarray(s.torso_top_weights))
        return ca.vertcat(self.system.stage_residuals(ca.vertcat(xq, pst), u),
                          top_w * (pts[:, mdl.torso_top] - top_t))

    def _stage_cost(self, xq, pst, u):
        """The system's stage cost at (xq (nx), pst (2), u) plus the torso-top term."""
        s, mdl = self.s, self.model
        pts = mdl.points(xq[:self.nq])
        top_t, top_w = ca.DM(s.torso_top_target), ca.DM(s.torso_top_weights)
        return (self.system.stage_cost(ca.vertcat(xq, pst), u)
                + ca.dot(top_w, (pts[:, mdl.torso_top] - top_t) ** 2))

    def row(self, j: int, k: int) -> int:
        """First row of interval k of swing j."""
        return int(self.interval_rows[j, k, 0])

    # ------------------------------------------------------------ problem data
    def dt0(self, elapsed: float) -> float:
        """Swing 0's node step for ``elapsed`` seconds already spent in the swing [s]."""
        s = self.s
        return max(s.swing_time - elapsed, s.min_swing_time) / self.N

    def swing_times(self, elapsed: float) -> np.ndarray:
        """Time since liftoff of every node, shape (2, N + 1) [s]."""
        k = np.arange(self.N + 1)
        return np.vstack([elapsed + k * self.dt0(elapsed), k * self.s.dt])

    def terrain(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(h0, inflated edges (E,), jumps (E,)) of the guard-avoid floor."""
        terrain, m = self.system.terrain, self.terrain_margin
        h_prev, e, d = terrain.ground, [], []
        for start, _, h in terrain.segments:
            jump = h - h_prev
            e.append(start - np.sign(jump) * m)
            d.append(jump)
            h_prev = h
        return terrain.ground, np.array(e), np.array(d)

    def floor(self, x: np.ndarray) -> np.ndarray:
        """The guard-avoid floor (inflated smooth terrain) at world x [m]."""
        h0, e, d = self.terrain()
        z = (np.asarray(x, dtype=float)[..., None] - e) / self.s.terrain_smoothing
        return h0 + (d * 0.5 * (1.0 + tanh(0.5 * z))).sum(axis=-1)

    def apex_nodes(self, elapsed: float) -> tuple[int | None, int]:
        """Apex node of swing 0 (None if already past) and of swing 1."""
        s = self.s
        k = round((s.apex_node * s.dt - elapsed) / self.dt0(elapsed))
        return (k if 1 <= k <= self.N - 1 else None), s.apex_node

    def problem_data(self, x0: np.ndarray, segment: tuple[float, float, float],
                     elapsed: float):
        """Parameters and bounds of one solve: (p, lbx, ubx, lbg, ubg).

        Args:
            x0: state (q, qd, p_st), shape (12,).
            segment: target (start, end, height) of swing 0's touchdown [m].
            elapsed: time already spent in the current swing [s].
        """
        s = self.s
        clear = self._clearances(x0, elapsed)
        h0, e, d = self.terrain()
        p = self.layout.p.pack({"x0": x0[:self.nx], "stance": x0[self.walker.stance_index],
                                "dt0": self.dt0(elapsed), "h0": h0, "edges": e, "jumps": d,
                                "clear": clear})
        bounds = self.layout.bounds()
        self._interval_bounds(bounds, clear)
        lbg, ubg = bounds.lbg, bounds.ubg
        start, end, height = segment
        lbg["touchdown"][0], ubg["touchdown"][0] = start + self.segment_margin, \
            end - self.segment_margin
        lbg["touchdown"][1] = ubg["touchdown"][1] = height - s.touchdown_depth
        lbg["reset"][:] = ubg["reset"][:] = 0.0
        if elapsed < s.liftoff_time:
            lbg["liftoff"][()] = s.liftoff_accel
        return (p, *bounds.arrays())

    def _clearances(self, x0: np.ndarray, elapsed: float) -> np.ndarray:
        """Guard-avoid clearances c of every node, shape (2, N + 1) [m]."""
        s = self.s
        clear = np.zeros((2, self.N + 1))
        tau = self.swing_times(elapsed)
        foot0 = np.asarray(self.model.swing_foot_world(x0)).ravel()
        starts = (foot0, x0[self.walker.stance_index])  # swing 1 lifts the stance foot
        for j in range(2):
            lift = tau[j] < s.liftoff_time - 1e-12
            clear[j, lift] = min(0.0, starts[j][1] - float(self.floor(starts[j][0])))
        ap0, ap1 = self.apex_nodes(elapsed)
        if ap0 is not None:
            clear[0, ap0] = s.apex_clearance
        clear[1, ap1] = s.apex_clearance
        return clear

    def _interval_bounds(self, bounds: Bounds, clear: np.ndarray) -> None:
        """State boxes of the node variables and bounds of the interval rows."""
        s, N = self.s, self.N
        lower, upper = self.system.state_box
        bounds.lbx["x"][:], bounds.ubx["x"][:] = lower[:self.nx], upper[:self.nx]
        lbg, ubg = bounds.lbg, bounds.ubg
        umax = np.maximum(np.asarray(self.system.modes[self.mode].u_upper)
                          - self.torque_margin, 0.0)
        lbg["dynamics"][:] = ubg["dynamics"][:] = 0.0
        if "stance_foot" in self.layout.g:
            lbg["stance_foot"][:] = ubg["stance_foot"][:] = 0.0
        lbg["torque"][:], ubg["torque"][:] = -umax, umax
        lbg["knees"][:] = s.knee_clearance
        stages = self.layout.g.stages("guard_avoid")
        j, k = np.array(stages).T
        avoid = (j != 0) | (k != N - 1)  # swing 0's touchdown node has its own rows
        lbg["guard_avoid"][avoid] = 0.0
        if s.swing_height_cap is not None:
            ubg["guard_avoid"][avoid] = s.swing_height_cap - clear[j[avoid], k[avoid] + 1]
        if s.swing2_end_clearance is not None:
            last = stages.index((1, N - 1))
            ubg["guard_avoid"][last] = min(s.swing2_end_clearance, ubg["guard_avoid"][last])

    # ------------------------------------------------------------- evaluation
    def constraints(self, w: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Constraint values g(w, p), shape (ng,)."""
        return self.session.constraints(w, p)

    def violation(self, w, p, lbx, ubx, lbg, ubg) -> float:
        """Largest constraint or bound violation at primal point w."""
        return self.session.violation(w, p, lbx, ubx, lbg, ubg)

    def cost(self, w: np.ndarray, p: np.ndarray) -> float:
        """Objective value at w."""
        return float(self._f_fun(w, p))

    def states_inputs(self, w: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Node states (2 (N + 1), n) and interval torques (2 N, n_q) of a primal point.

        Rows: swing 0 nodes 0..N (pre-impact last), swing 1 nodes 0..N (post-reset first);
        p_st of swing 1 is the touchdown point.
        """
        xs, us = self._traj_fun(w, p)
        return np.asarray(xs), np.asarray(us)

    def optimize(self, w0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None) -> SolveResult:
        """One IPOPT solve from ``w0`` (see :meth:`SolverSession.run`); never raises on failure.

        With both multiplier guesses the warm instance runs, else the cold one.
        """
        return self.session.run(w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0)


class _Outputs:
    """The walker's functions the transcription uses, with the joint-point columns by name."""

    def __init__(self, walker: WalkerModel) -> None:
        self.points = walker.points
        self.inverse_dynamics = walker.inverse_dynamics
        self.swing_foot_world = walker.swing_foot_world
        self.swing_foot_velocity = walker.swing_foot_velocity
        self.swing_foot_jacobian = walker.swing_foot_jacobian
        self.reset = walker.contact_reset
        self.stance_knee, self.torso_top = walker.point("stance_knee"), walker.point("torso_top")
        self.swing_knee, self.swing_foot = walker.point("swing_knee"), walker.point("swing_foot")
