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
  ``liftoff_time`` of a swing c_k = min(0, gap of the lifting foot at the swing start),
  so a foot starting on (or, near an edge, below) the inflated floor may not sink. Off
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
(hip in the world, torso top relative to the stance foot; weights from
:class:`BipedParams` and the settings).
"""

from __future__ import annotations

from typing import Literal

import casadi as ca
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from hmpc_cli.hybrid import HybridSystem

INF = np.inf
NX = 10  # (q, qd) per node; p_st is a parameter (swing 0) or an expression (swing 1)
ROWS = 18  # per interval: dynamics 10, torque 5, floor 1, knees 2
TD_ROWS = 2 + NX  # touchdown x, y; reset


class WalkingMPCSettings(BaseModel):
    """Fixed-mode walking MPC settings (reference values)."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["walking"] = Field("walking", description="two-swing walking MPC "
                                     "(walkers with a stance foot: the biped)")
    rate_hz: int = Field(10, gt=0, description="re-solve rate [Hz] (also after contacts)")
    swing_time: float = Field(0.3, gt=0.0, description="duration of a swing [s]")
    nodes_per_swing: int = Field(25, ge=4, description="intervals per swing")
    min_swing_time: float = Field(0.03, gt=0.0, description="lower bound on swing 0's "
                                  "remaining time [s]")
    touchdown_depth: float = Field(0.005, ge=0.0, description="touchdown node this far "
                                   "below the target surface [m]")
    segment_margin: float = Field(0.075, ge=0.0, description="touchdown at least this far "
                                  "inside the segment's ends (tube tightening) [m]")
    apex_node: int = Field(20, ge=1, description="node of a swing with the apex row")
    apex_clearance: float = Field(0.05, ge=0.0, description="foot above the terrain at the "
                                  "apex node [m]")
    liftoff_time: float = Field(0.024, ge=0.0, description="liftoff window: guard-avoid "
                                "row relaxed to the start height [s]")
    liftoff_accel: float = Field(3.0, description="upward swing-foot acceleration at "
                                 "node 0 when the swing starts within the liftoff window "
                                 "[m/s^2]")
    terrain_margin: float = Field(0.025, ge=0.0, description="edge inflation of the "
                                  "guard-avoid terrain [m]")
    terrain_smoothing: float = Field(0.005, gt=0.0, description="logistic width of the "
                                     "terrain steps [m]")
    swing2_end_clearance: float | None = Field(0.05, gt=0.0, description="swing 1's last "
                                               "node at most this above the terrain [m]; "
                                               "None: free")
    swing_height_cap: float | None = Field(0.25, gt=0.0, description="swing foot at most "
                                           "this above the terrain at every node [m]; "
                                           "None: no cap")
    knee_clearance: float = Field(0.2, description="knees above the stance foot [m]")
    torque_margin: float = Field(300.0, ge=0.0, description="torque limit tightening "
                                 "(the low-level controller's share) [N m]")
    torso_top_target: tuple[float, float] = Field((0.2, 1.6), description="torso top "
                                                  "relative to the stance foot [m]")
    torso_top_weights: tuple[float, float] = Field((50.0, 5.0), description="cost weights "
                                                   "on the torso-top error [1/(m^2 s)]")
    max_iter: int = Field(200, gt=0, description="IPOPT iterations")
    tol: float = Field(1e-6, gt=0.0, description="IPOPT tol")
    max_wall_time: float | None = Field(None, gt=0.0, description="IPOPT wall-time cap [s]")
    warm_start: bool = Field(True, description="primal-dual warm start from the previous "
                             "solution of the same candidate")
    impact_duals: bool = Field(True, description="after a contact, also shift the "
                               "executed plan's multipliers (warm IPOPT instance)")
    solver_options: dict = Field(default_factory=dict, description="extra IPOPT options")

    @model_validator(mode="after")
    def _apex_inside(self) -> WalkingMPCSettings:
        if self.apex_node >= self.nodes_per_swing:
            raise ValueError(f"apex_node {self.apex_node} must be below nodes_per_swing "
                             f"{self.nodes_per_swing}")
        return self

    @property
    def dt(self) -> float:
        """Node step of a full swing [s]."""
        return self.swing_time / self.nodes_per_swing


def _smooth_step(z):
    return 0.5 * (1.0 + ca.tanh(0.5 * z))


class WalkingNLP:
    """The parametric two-swing NLP (built once per parameters and settings).

    Vector layouts (N = nodes_per_swing):
        w: per swing j, per interval k: a_{j,k} (5) then (q, qd)_{j,k+1} (10); swing 1's
           node 0 (10) precedes its first interval. ``x_idx[j, k]`` (10 indices, -1 for
           the parameter node (0, 0)) and ``a_idx[j, k]`` index it.
        g: per swing, per interval: ROWS rows (``row(j, k)`` = first row); after swing 0
           the touchdown rows (x, y) then the reset rows (``td_row``); last the liftoff
           acceleration row (``lift_row``).
        p: x0 (12), dt_0, h0, shifted edges (E), jumps (E), clearances c (2, N + 1).
    """

    def __init__(self, system: HybridSystem, settings: WalkingMPCSettings) -> None:
        self.system, self.s = system, settings
        self.model = _Outputs(system)
        self.N = settings.nodes_per_swing
        self.E = len(system.terrain.segments)
        self._build()

    # ------------------------------------------------------------------ build
    def _layout(self) -> None:
        N = self.N
        self.x_idx = -np.ones((2, N + 1, NX), dtype=int)
        self.a_idx = np.zeros((2, N, 5), dtype=int)
        i = 0
        for j in range(2):
            if j == 1:
                self.x_idx[1, 0] = np.arange(i, i + NX)
                i += NX
            for k in range(N):
                self.a_idx[j, k] = np.arange(i, i + 5)
                self.x_idx[j, k + 1] = np.arange(i + 5, i + 5 + NX)
                i += 5 + NX
        self.nw = i
        self.td_row = N * ROWS
        self.ng = 2 * N * ROWS + TD_ROWS + 1
        self.lift_row = self.ng - 1

    def row(self, j: int, k: int) -> int:
        """First row of interval k of swing j."""
        return j * (self.N * ROWS + TD_ROWS) + k * ROWS

    def _build(self) -> None:
        self._layout()
        N, E, s, mdl = self.N, self.E, self.s, self.model
        w = ca.SX.sym("w", self.nw)
        x0 = ca.SX.sym("x0", 12)
        dt0 = ca.SX.sym("dt0")
        h0 = ca.SX.sym("h0")
        edges = ca.SX.sym("edges", E)
        jumps = ca.SX.sym("jumps", E)
        clear = ca.SX.sym("clear", 2, N + 1)
        p = ca.vertcat(x0, dt0, h0, edges, jumps, ca.vec(clear))
        self.n_par = p.size1()

        fx = ca.SX.sym("fx")
        floor = h0 + sum(jumps[i] * _smooth_step((fx - edges[i]) / s.terrain_smoothing)
                         for i in range(E))
        floor_fn = ca.Function("floor", [fx, h0, edges, jumps], [floor])
        top_t, top_w = ca.DM(s.torso_top_target), ca.DM(s.torso_top_weights)

        def var_x(j, k):
            if j == 0 and k == 0:
                return x0[:NX]
            return w[self.x_idx[j, k].tolist()]

        def stage(xq, pst, u):
            """The system's stage cost plus the torso-top posture term."""
            pts = mdl.points(xq[:5])
            return (self.system.stage_cost(ca.vertcat(xq, pst), u)
                    + ca.dot(top_w, (pts[:, mdl.torso_top] - top_t) ** 2))

        g = []
        J = 0
        xs_out, us_out = [], []
        pst = x0[10:12]
        for j in range(2):
            dt = dt0 if j == 0 else s.dt
            if j == 1:
                xs_out.append(ca.vertcat(var_x(1, 0), pst))
            else:
                xs_out.append(x0)
            for k in range(N):
                xk, xn = var_x(j, k), var_x(j, k + 1)
                a = w[self.a_idx[j, k].tolist()]
                q, qd, qn, qdn = xk[:5], xk[5:], xn[:5], xn[5:]
                u = mdl.inverse_dynamics(q, qd, a, 0)
                pts = mdl.points(qn)
                foot = pts[:, mdl.swing_foot] + pst
                g += [qdn - qd - dt * a, qn - q - dt * qdn, u,
                      foot[1] - floor_fn(foot[0], h0, edges, jumps) - clear[j, k + 1],
                      pts[1, mdl.stance_knee], pts[1, mdl.swing_knee]]
                J += dt * stage(xn, pst, u)
                xs_out.append(ca.vertcat(xn, pst))
                us_out.append(u)
            if j == 0:
                x_td = ca.vertcat(var_x(0, N), pst)
                foot = mdl.swing_foot_world(x_td)
                x_plus = mdl.reset(x_td)
                g += [foot[0], foot[1], var_x(1, 0) - x_plus[:NX]]
                pst = x_plus[10:12]
        q0, qd0 = x0[:5], x0[5:NX]
        vel = mdl.swing_foot_velocity(q0, qd0)
        acc = ca.jtimes(vel, q0, qd0) + ca.mtimes(mdl.swing_foot_jacobian(q0),
                                                 w[self.a_idx[0, 0].tolist()])
        g.append(acc[1])
        g = ca.vertcat(*g)
        assert g.size1() == self.ng
        self._g_fun = ca.Function("g", [w, p], [g])
        self._traj_fun = ca.Function("traj", [w, p], [ca.horzcat(*xs_out).T,
                                                      ca.horzcat(*us_out).T])
        self._f_fun = ca.Function("f", [w, p], [J])
        nlp = {"x": w, "p": p, "f": J, "g": g}
        ipopt = {"print_level": 0, "sb": "yes", "max_iter": s.max_iter, "tol": s.tol,
                 "constr_viol_tol": 1e-8, "mu_strategy": "adaptive"}
        if s.max_wall_time is not None:
            ipopt["max_wall_time"] = s.max_wall_time
        extra = dict(s.solver_options)
        ipopt.update(extra.pop("ipopt", {}))
        warm_extra = extra.pop("ipopt_warm", {})
        opts = {"expand": True, "print_time": False, "ipopt": ipopt, **extra}
        self.solver = ca.nlpsol("walking_mpc", "ipopt", nlp, opts)
        warm = dict(opts)
        warm["ipopt"] = {**ipopt, "warm_start_init_point": "yes", "mu_init": 1e-4,
                         "warm_start_bound_push": 1e-6, "warm_start_mult_bound_push": 1e-6,
                         "warm_start_slack_bound_push": 1e-6, **warm_extra}
        self.warm_solver = ca.nlpsol("walking_mpc_warm", "ipopt", nlp, warm)

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
        terrain, m = self.system.terrain, self.s.terrain_margin
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
        return h0 + (d * 0.5 * (1.0 + np.tanh(0.5 * z))).sum(axis=-1)

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
        s, N = self.s, self.N
        clear = np.zeros((2, N + 1))
        tau = self.swing_times(elapsed)
        foot0 = np.asarray(self.model.swing_foot_world(x0)).ravel()
        starts = (foot0, x0[10:12])  # swing 1 lifts the current stance foot
        for j in range(2):
            lift = tau[j] < s.liftoff_time - 1e-12
            clear[j, lift] = min(0.0, starts[j][1] - float(self.floor(starts[j][0])))
        ap0, ap1 = self.apex_nodes(elapsed)
        if ap0 is not None:
            clear[0, ap0] = s.apex_clearance
        clear[1, ap1] = s.apex_clearance
        h0, e, d = self.terrain()
        p = np.concatenate([x0, [self.dt0(elapsed), h0], e, d, clear.ravel(order="F")])
        lo_x, hi_x = (b[:NX] for b in self.system.state_box)
        lbx, ubx = np.full(self.nw, -INF), np.full(self.nw, INF)
        for j in range(2):
            for k in range(N + 1):
                if self.x_idx[j, k, 0] >= 0:
                    lbx[self.x_idx[j, k]], ubx[self.x_idx[j, k]] = lo_x, hi_x
        lbg, ubg = np.full(self.ng, -INF), np.full(self.ng, INF)
        umax = np.maximum(np.asarray(self.system.modes[0].u_upper) - s.torque_margin, 0.0)
        for j in range(2):
            for k in range(N):
                r = self.row(j, k)
                lbg[r:r + NX] = ubg[r:r + NX] = 0.0
                lbg[r + 10:r + 15], ubg[r + 10:r + 15] = -umax, umax
                if not (j == 0 and k == N - 1):  # the touchdown node has its own rows
                    lbg[r + 15] = 0.0
                if s.swing_height_cap is not None and not (j == 0 and k == N - 1):
                    ubg[r + 15] = s.swing_height_cap - clear[j, k + 1]
                lbg[r + 16:r + 18] = s.knee_clearance
        if s.swing2_end_clearance is not None:
            r = self.row(1, N - 1) + 15
            ubg[r] = min(s.swing2_end_clearance, ubg[r])
        start, end, height = segment
        r = self.td_row
        lbg[r], ubg[r] = start + s.segment_margin, end - s.segment_margin
        lbg[r + 1] = ubg[r + 1] = height - s.touchdown_depth
        lbg[r + 2:r + TD_ROWS] = ubg[r + 2:r + TD_ROWS] = 0.0
        if elapsed < s.liftoff_time:
            lbg[self.lift_row] = s.liftoff_accel
        return p, lbx, ubx, lbg, ubg

    # ------------------------------------------------------------- evaluation
    def constraints(self, w: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Constraint values g(w, p), shape (ng,)."""
        return np.asarray(self._g_fun(w, p)).ravel()

    def violation(self, w, p, lbx, ubx, lbg, ubg) -> float:
        """Largest constraint or bound violation at primal point w."""
        g = self.constraints(w, p)
        v = [np.maximum(lbg - g, 0.0), np.maximum(g - ubg, 0.0),
             np.maximum(lbx - w, 0.0), np.maximum(w - ubx, 0.0)]
        return float(max(np.max(a, initial=0.0) for a in v))

    def cost(self, w: np.ndarray, p: np.ndarray) -> float:
        """Objective value at w."""
        return float(self._f_fun(w, p))

    def states_inputs(self, w: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Node states (2 (N + 1), 12) and interval torques (2 N, 5) of a primal point.

        Rows: swing 0 nodes 0..N (pre-impact last), swing 1 nodes 0..N (post-reset first);
        p_st of swing 1 is the touchdown point.
        """
        xs, us = self._traj_fun(w, p)
        return np.asarray(xs), np.asarray(us)

    def solve(self, w0, p, lbx, ubx, lbg, ubg, lam_x0=None, lam_g0=None):
        """One IPOPT solve: (solution dict, status, iterations, success).

        With both multiplier guesses the warm instance runs (multipliers of unbounded
        rows and variables zeroed), else the cold one.
        """
        args = {"x0": w0, "p": p, "lbx": lbx, "ubx": ubx, "lbg": lbg, "ubg": ubg}
        solver = self.solver
        if lam_x0 is not None and lam_g0 is not None:
            lam_g0 = np.where(np.isfinite(lbg) | np.isfinite(ubg), lam_g0, 0.0)
            lam_x0 = np.where(np.isfinite(lbx) | np.isfinite(ubx), lam_x0, 0.0)
            args.update(lam_x0=lam_x0, lam_g0=lam_g0)
            solver = self.warm_solver
        sol = solver(**args)
        st = solver.stats()
        return (sol, str(st.get("return_status", "?")), int(st.get("iter_count", 0)),
                bool(st.get("success", False)))


class _Outputs:
    """The system outputs the transcription uses, with the joint-point columns by name."""

    def __init__(self, system: HybridSystem) -> None:
        names = system.point_names
        self.points = system.output("points")
        self.inverse_dynamics = system.output("inverse_dynamics")
        self.swing_foot_world = system.output("swing_foot_world")
        self.swing_foot_velocity = system.output("swing_foot_velocity")
        self.swing_foot_jacobian = system.output("swing_foot_jacobian")
        self.reset = system.output("contact_reset")
        self.hip_world = system.output("hip_world")
        self.stance_knee, self.hip = names.index("stance_knee"), names.index("hip")
        self.torso_top, self.swing_knee = names.index("torso_top"), names.index("swing_knee")
        self.swing_foot = names.index("swing_foot")
