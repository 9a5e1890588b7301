"""The paper's planar five-link, fully actuated biped on stairs (Sec. IV, Fig. 4).

Links, in chain order: stance calf, stance thigh, torso, swing thigh, swing calf; the
robot is pinned at the stance foot (a point foot) and every joint carries a torque.

Coordinate convention (angles in rad, counter-clockwise positive, x forward, y up)
---------------------------------------------------------------------------------
Every link k has an *absolute* angle theta_k from the upward vertical, taken along the
link's "upward" unit vector e(theta) = (-sin theta, cos theta): for the legs it points from
the foot end to the hip end (stance AND swing leg alike), for the torso from the hip to the
top. The generalised coordinates are

    q1 = theta_1                    absolute stance-calf angle (q1 < 0: leaning forward)
    q2 = theta_2 - theta_1          stance knee (flexion, > 0 with the knee forward)
    q3 = theta_3 - theta_2          torso relative to the stance thigh
    q4 = theta_4 - theta_3          swing thigh relative to the torso
    q5 = theta_5 - theta_4          swing knee (< 0 with the knee forward)

i.e. theta = S q with S the lower-triangular matrix of ones, and u_i is the joint torque
conjugate to q_i (ankle, stance knee, stance hip, swing hip, swing knee) [N m]. Points
relative to the stance foot: knee = Lc e1, hip = knee + Lt e2, torso top = hip + LT e3,
swing knee = hip - Lt e4, swing foot = swing knee - Lc e5. For the reference q0 this gives
the hip at (0.2334, 0.6815), the swing foot at (0.2987, 0.0016) and the torso top at
(0.1504, 1.3009) (Fig. 4 data, snapshot 0). The leg swap is then the *reversal* of the
absolute angles, theta' = (theta5, theta4, theta3, theta2, theta1), i.e.
q1' = q1 + ... + q5, (q2', q3', q4', q5') = (-q5, -q4, -q3, -q2), and the same for the
rates; it is an involution and leaves every joint where it is in the world.

Centres of mass sit on the links: torso ``torso_com`` from the hip, thighs ``thigh_com``
from the hip, calves ``calf_com`` from the knee (the same physical points on both legs;
on the stance leg, traversed foot -> knee -> hip, that is Lc - calf_com from the foot and
Lt - thigh_com from the knee).

State x = (q[5], qdot[5], p_st[2]) [rad, rad/s, m], p_st the stance-foot position in the
world (constant along the flow). Input u = joint torques [N m] (5,). Disturbance w = a
horizontal force on the torso at the hip joint [N] (1,), generalised force J_hip,x^T w.

Dynamics (Lagrangian, derived in closed form in the absolute angles): every CoM is
sum_k C[b, k] e(theta_k) with constant C, so T = 1/2 thd^T M_th(theta) thd with
M_th[i, j] = A_ij cos(theta_i - theta_j), A = C^T diag(m) C + diag(I), and
V = g sum_k beta_k cos(theta_k), beta = C^T m. Euler-Lagrange gives
M_th thdd + h_th = S^-T (u + J_hip,x^T w), h_th,i = sum_j A_ij sin(th_i - th_j) thd_j^2
- g beta_i sin(th_i); in q: M = S^T M_th S, bias = C(q, qd) qd + G(q) = S^T h_th.
tests/test_biped.py checks these against CasADi AD of the Lagrangian built from the CoMs.

Hybrid structure: one mode ``single_support``; one guard per stair segment i (swing-foot
height falls through the segment height while the foot is above the segment) plus
``ground`` (height ``ground_height`` for x <= 0); every reset is the plastic impact of the
point foot followed by the leg swap. The impact is the paper's formula with the pinned
5 x 5 M: the old stance foot stays pinned through it, so both feet are at rest right after
it; the momenta M v along motions that keep the landing foot still are conserved, but the
angular momentum about the impact point is not (the pin takes an impulse too).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import casadi as ca
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from hmpc_cli.hybrid import Guard, HybridSystem, Mode

Five = tuple[float, float, float, float, float]
Pair = tuple[float, float]
MODE = "single_support"
N_Q = 5
STANCE_X = 2 * N_Q  #: index of the stance-foot x in the state (the stance-foot y follows)
#: names of the points returned by :attr:`BipedModel.points` (columns, in this order)
POINT_NAMES = ("stance_foot", "stance_knee", "hip", "torso_top", "swing_knee", "swing_foot")

Q0: Five = (-0.78, 0.9, 0.0133, 0.51, -1.0951)


class Stair(BaseModel):
    """A flat segment of the course; segments follow each other from x = 0."""

    model_config = ConfigDict(extra="forbid")
    length: float = Field(gt=0.0, description="segment length along x [m]")
    height: float = Field(description="segment height [m]")


def _fig4_stairs() -> list[Stair]:
    return [Stair(length=a, height=b)
            for a, b in ((0.4, 0.0), (1.0, 0.075), (0.2, 0.125), (1.25, 0.175))]


class BipedParams(BaseModel):
    """Parameters of the five-link biped and its task (SI units, reference values)."""

    model_config = ConfigDict(extra="forbid")
    name: Literal["biped"] = "biped"
    torso_length: float = Field(0.625, gt=0.0, description="hip to torso top [m]")
    thigh_length: float = Field(0.4, gt=0.0, description="hip to knee [m]")
    calf_length: float = Field(0.4, gt=0.0, description="knee to foot [m]")
    torso_mass: float = Field(10.0, gt=0.0, description="[kg]")
    thigh_mass: float = Field(3.0, gt=0.0, description="[kg]")
    calf_mass: float = Field(1.0, gt=0.0, description="[kg]")
    torso_inertia: float = Field(2.22, ge=0.0, description="about the CoM [kg m^2]")
    thigh_inertia: float = Field(1.08, ge=0.0, description="about the CoM [kg m^2]")
    calf_inertia: float = Field(0.93, ge=0.0, description="about the CoM [kg m^2]")
    torso_com: float = Field(0.2, ge=0.0, description="CoM distance from the hip [m]")
    thigh_com: float = Field(0.163, ge=0.0, description="CoM distance from the hip [m]")
    calf_com: float = Field(0.128, ge=0.0, description="CoM distance from the knee [m]")
    gravity: float = Field(9.81, ge=0.0, description="[m/s^2]")
    mass_scale: float = Field(1.0, gt=0.0, description="factor on every mass and inertia "
                                                       "(1.1: the paper's heavier robot)")
    torque_limit: float = Field(3000.0, gt=0.0, description="|u_i| <= this [N m]")
    rate_limit: float = Field(35.0, gt=0.0, description="|qdot_i| <= this [rad/s]")
    stance_knee_range: Pair = Field((0.0, math.pi / 2), description="q2 bounds [rad]")
    torso_range: Pair = Field((-math.pi / 2, math.pi / 2),
                              description="q3 (torso relative to stance thigh) bounds [rad]")
    q0: Five = Field(Q0, description="initial angles [rad]")
    qdot0: Five = Field((0.0,) * 5, description="initial rates [rad/s]")
    stance_foot0: Pair = Field((0.0, 0.0), description="initial stance foot [m]")
    stairs: list[Stair] = Field(default_factory=_fig4_stairs, min_length=1,
                                description="consecutive flat segments from x = 0")
    ground_height: float = Field(0.0, description="terrain height for x <= 0 [m]")
    goal: Pair = Field((2.0, 0.8), description="hip target in the world [m]")
    q_hip: float = Field(10.0, ge=0.0, description="stage cost weight on |hip - goal|^2")
    q_nominal: Five = Field(Q0, description="nominal pose of the stage cost [rad]")
    pose_weights: Five = Field((0.0, 1.0, 1.0, 1.0, 1.0),
                               description="stage cost weights on (q - q_nominal)^2")
    r_torque: float = Field(1e-4, ge=0.0, description="stage cost weight on |u|^2")
    success_radius: float = Field(0.3, gt=0.0, description="unused by the walking "
                                  "success test (no fall, ends on the top segment); the "
                                  "final error is |hip - goal| [m]")
    fall_hip_height: float = Field(0.35, ge=0.0, description="a fall: the hip less than "
                                   "this above the terrain under it [m]")

    @model_validator(mode="after")
    def _consistent(self) -> BipedParams:
        problems: list[tuple[tuple, str, object]] = []
        for key, (lo, hi) in (("stance_knee_range", self.stance_knee_range),
                              ("torso_range", self.torso_range)):
            if not lo < hi:
                problems.append(((key,), f"lower bound {lo} must be below upper bound {hi}",
                                 [lo, hi]))
        for key, com, length in (("torso_com", self.torso_com, self.torso_length),
                                 ("thigh_com", self.thigh_com, self.thigh_length),
                                 ("calf_com", self.calf_com, self.calf_length)):
            if com > length:
                problems.append(((key,), f"{com} m lies beyond the link ({length} m)", com))
        if not problems:
            problems += self._initial_problems()
        if problems:
            raise ValidationError.from_exception_data("BipedParams", [
                InitErrorDetails(type=PydanticCustomError("value_error", msg), loc=loc,
                                 input=value) for loc, msg, value in problems])
        return self

    def _initial_problems(self) -> list[tuple[tuple, str, object]]:
        out = []
        q = self.q0
        for i, key, (lo, hi) in ((1, "stance knee q2", self.stance_knee_range),
                                 (2, "torso q3", self.torso_range)):
            if not lo <= q[i] <= hi:
                out.append((("q0",), f"{key} = {q[i]} outside [{lo}, {hi}]", list(q)))
        if any(abs(v) > self.rate_limit for v in self.qdot0):
            out.append((("qdot0",), f"a rate exceeds rate_limit = {self.rate_limit}",
                        list(self.qdot0)))
        fx, fy = self.stance_foot0
        ground = terrain_heights(self, fx)
        if not ground:
            out.append((("stance_foot0",), f"x = {fx} lies beyond the stairs' end "
                        f"{stairs_end(self)}", [fx, fy]))
        elif min(abs(fy - h) for h in ground) > 1e-9:
            out.append((("stance_foot0",), f"must be on the ground: y = {fy}, terrain height "
                        f"{_fmt(ground)} at x = {fx}", [fx, fy]))
        sx, sy = swing_foot_numeric(self, q)
        sx, sy = sx + fx, sy + fy
        ground = terrain_heights(self, sx)
        if not ground:
            out.append((("q0",), f"initial swing foot x = {sx:.4f} lies beyond the stairs' "
                        f"end {stairs_end(self)}", list(q)))
        elif sy < min(ground) - 1e-9:
            out.append((("q0",), f"initial swing foot ({sx:.4f}, {sy:.4f}) is below the "
                        f"terrain (height {_fmt(ground)})", list(q)))
        return out


def _fmt(heights: list[float]) -> str:
    return " / ".join(f"{h:g}" for h in heights)


def stair_edges(p: BipedParams) -> list[tuple[float, float, float]]:
    """(start, end, height) of each stair segment, consecutive from x = 0 [m]."""
    out, x = [], 0.0
    for s in p.stairs:
        out.append((x, x + s.length, s.height))
        x += s.length
    return out


def stairs_end(p: BipedParams) -> float:
    """x where the last segment ends [m]."""
    return stair_edges(p)[-1][1]


def terrain_heights(p: BipedParams, x: float) -> list[float]:
    """Terrain heights at x: one, two on a segment boundary, none beyond the end."""
    out = [p.ground_height] if x <= 0.0 else []
    out += [h for a, b, h in stair_edges(p) if a <= x <= b and h not in out]
    return out


def terrain_profile(p: BipedParams, x) -> np.ndarray:
    """Terrain height under each x [m] (vectorised): the higher side on a boundary, the
    ground height for x <= 0, the last segment's height past the stairs' end."""
    x, edges = np.asarray(x, dtype=float), stair_edges(p)
    out = np.where(x <= 0.0, p.ground_height, -np.inf)
    for a, b, h in edges:
        out = np.where((x >= a) & (x <= b), np.maximum(out, h), out)
    return np.where(x > edges[-1][1], edges[-1][2], out)


def _geometry(p: BipedParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients D (points x links), C (bodies x links), masses and inertias."""
    lc, lt, lT = p.calf_length, p.thigh_length, p.torso_length
    d = np.array([[0, 0, 0, 0, 0], [lc, 0, 0, 0, 0], [lc, lt, 0, 0, 0], [lc, lt, lT, 0, 0],
                  [lc, lt, 0, -lt, 0], [lc, lt, 0, -lt, -lc]], dtype=float)
    c = np.array([[lc - p.calf_com, 0, 0, 0, 0],           # stance calf: calf_com from knee
                  [lc, lt - p.thigh_com, 0, 0, 0],         # stance thigh: thigh_com from hip
                  [lc, lt, p.torso_com, 0, 0],             # torso
                  [lc, lt, 0, -p.thigh_com, 0],            # swing thigh
                  [lc, lt, 0, -lt, -p.calf_com]], dtype=float)  # swing calf
    s = p.mass_scale
    mass = s * np.array([p.calf_mass, p.thigh_mass, p.torso_mass, p.thigh_mass, p.calf_mass])
    inertia = s * np.array([p.calf_inertia, p.thigh_inertia, p.torso_inertia,
                            p.thigh_inertia, p.calf_inertia])
    return d, c, mass, inertia


def swing_foot_numeric(p: BipedParams, q) -> np.ndarray:
    """Swing foot relative to the stance foot for angles q (NumPy, used by validation)."""
    d = _geometry(p)[0]
    theta = np.cumsum(np.asarray(q, dtype=float))
    return np.array([-d[-1] @ np.sin(theta), d[-1] @ np.cos(theta)])


@dataclass(frozen=True)
class BipedModel:
    """The biped's symbolic pieces as CasADi SX functions (SI units).

    q[5] angles [rad], qd[5] rates [rad/s], qdd[5] [rad/s^2], u[5] torques [N m],
    w[1] horizontal hip force [N], x[12] the state (q, qd, p_st). Points are relative to
    the stance foot unless named ``*_world``; 2 x 6 point matrices hold the columns
    :data:`POINT_NAMES` (NumPy evaluation flattens them to (x0, y0, x1, y1, ...)).

    Attributes:
        mass_matrix: q -> M(q), 5 x 5 [kg m^2].
        bias: (q, qd) -> C(q, qd) qd + G(q), (5,) [N m].
        coriolis: (q, qd) -> C(q, qd) qd, (5,) [N m].
        gravity: q -> G(q) = dV/dq, (5,) [N m].
        hip_force_map: q -> J_hip,x(q)^T, (5,) [m]: generalised force per newton of w.
        forward_dynamics: (q, qd, u, w) -> qdd, (5,).
        inverse_dynamics: (q, qd, qdd, w) -> u = M qdd + bias - J_hip,x^T w, (5,).
        flow: (x, u, w) -> dx/dt, (12,) (the mode's flow; p_st is constant).
        link_angles: q -> absolute link angles theta = S q, (5,) [rad].
        points: q -> 2 x 6 joint points [m]. points_world: x -> 2 x 6 [m].
        coms: q -> 2 x 5 link centres of mass (chain order) [m].
        hip: q -> (2,); hip_jacobian: q -> 2 x 5 [m].
        hip_world: x -> (2,) [m] (the goal map).
        swing_foot: q -> (2,); swing_foot_jacobian: q -> 2 x 5 [m].
        swing_foot_world: x -> (2,) [m]; swing_foot_velocity: (q, qd) -> (2,) [m/s].
        kinetic, potential, energy: x -> scalar [J] (potential and energy include the
            stance foot's height, so they are continuous across a leg swap).
        impact: x -> x with the post-impact rates (plastic impact of the swing foot,
            no relabelling). impulse: x -> Lambda (2,) [N s], M (v+ - v-) = J^T Lambda.
        swap: x -> x with the legs relabelled (new stance foot = old swing foot).
        reset: x -> swap(impact(x)), the guards' reset map.
        total_mass: [kg]. state_lower, state_upper: (12,) box on x (inf: unbounded).
        u_max: torque limit [N m].
    """

    mass_matrix: ca.Function
    bias: ca.Function
    coriolis: ca.Function
    gravity: ca.Function
    hip_force_map: ca.Function
    forward_dynamics: ca.Function
    inverse_dynamics: ca.Function
    flow: ca.Function
    link_angles: ca.Function
    points: ca.Function
    points_world: ca.Function
    coms: ca.Function
    hip: ca.Function
    hip_jacobian: ca.Function
    hip_world: ca.Function
    swing_foot: ca.Function
    swing_foot_jacobian: ca.Function
    swing_foot_world: ca.Function
    swing_foot_velocity: ca.Function
    kinetic: ca.Function
    potential: ca.Function
    energy: ca.Function
    impact: ca.Function
    impulse: ca.Function
    swap: ca.Function
    reset: ca.Function
    total_mass: float
    state_lower: np.ndarray
    state_upper: np.ndarray
    u_max: float


class _Terms:
    """Closed-form Lagrangian terms in the absolute angles for symbolic q, qd."""

    def __init__(self, p: BipedParams, q: ca.SX, qd: ca.SX) -> None:
        d, c, mass, inertia = _geometry(p)
        self.S = np.tril(np.ones((N_Q, N_Q)))
        self.Sinv = np.linalg.inv(self.S)  # bidiagonal: exact differences
        self.a = c.T @ np.diag(mass) @ c + np.diag(inertia)
        self.beta = c.T @ mass
        self.d, self.c, self.g = d, c, p.gravity
        self.theta = ca.mtimes(ca.DM(self.S), q)
        self.thd = ca.mtimes(ca.DM(self.S), qd)
        self.sin = [ca.sin(self.theta[k]) for k in range(N_Q)]
        self.cos = [ca.cos(self.theta[k]) for k in range(N_Q)]

    def cos_diff(self, i: int, j: int):
        return self.cos[i] * self.cos[j] + self.sin[i] * self.sin[j]

    def sin_diff(self, i: int, j: int):
        return self.sin[i] * self.cos[j] - self.cos[i] * self.sin[j]

    def m_theta(self) -> ca.SX:
        m = ca.SX(N_Q, N_Q)
        for i in range(N_Q):
            m[i, i] = self.a[i, i]
            for j in range(i):
                m[i, j] = self.a[i, j] * self.cos_diff(i, j)
                m[j, i] = m[i, j]
        return m

    def coriolis_theta(self) -> ca.SX:
        sq = self.thd**2
        return ca.vertcat(*[sum(self.a[i, j] * self.sin_diff(i, j) * sq[j]
                                for j in range(N_Q) if j != i) for i in range(N_Q)])

    def gravity_theta(self) -> ca.SX:
        return ca.vertcat(*[-self.g * self.beta[k] * self.sin[k] for k in range(N_Q)])

    def point(self, coeff: np.ndarray) -> ca.SX:
        """sum_k coeff_k e(theta_k)."""
        return ca.vertcat(-sum(coeff[k] * self.sin[k] for k in range(N_Q) if coeff[k]),
                          sum(coeff[k] * self.cos[k] for k in range(N_Q) if coeff[k]))

    def jac_theta(self, coeff: np.ndarray) -> ca.SX:
        """d point / d theta, 2 x 5 (columns coeff_k e'(theta_k), e' = (-cos, -sin))."""
        return ca.horzcat(*[coeff[k] * ca.vertcat(-self.cos[k], -self.sin[k])
                            for k in range(N_Q)])

    def to_q(self, row_theta: ca.SX) -> ca.SX:
        """Right-multiplies a d/dtheta row block by S (chain rule to q)."""
        return ca.mtimes(row_theta, ca.DM(self.S))


def make_biped_model(p: BipedParams) -> BipedModel:
    """Derives the biped's dynamics, kinematics, impact and swap maps symbolically."""
    q = ca.SX.sym("q", N_Q)
    qd = ca.SX.sym("qd", N_Q)
    qdd = ca.SX.sym("qdd", N_Q)
    u = ca.SX.sym("u", N_Q)
    w = ca.SX.sym("w", 1)
    x = ca.SX.sym("x", 2 * N_Q + 2)
    t = _Terms(p, q, qd)
    S, St, Sinv = ca.DM(t.S), ca.DM(t.S.T), ca.DM(t.Sinv)
    m_th = t.m_theta()
    cor_th, grav_th = t.coriolis_theta(), t.gravity_theta()
    m_q = ca.mtimes([St, m_th, S])
    hip_coeff, foot_coeff = t.d[2], t.d[5]
    jh_th = t.jac_theta(hip_coeff)
    force_map = ca.mtimes(St, jh_th[0, :].T)  # J_hip,x^T in q
    # forward dynamics in theta: M_th thdd = S^-T (u + J^T w) - h_th; qdd = S^-1 thdd
    rhs_th = ca.mtimes(Sinv.T, u) + jh_th[0, :].T * w - cor_th - grav_th
    qdd_expr = ca.mtimes(Sinv, ca.solve(m_th, rhs_th))
    # inverse dynamics
    tau_expr = (ca.mtimes(m_q, qdd) + ca.mtimes(St, cor_th + grav_th) - force_map * w)

    def q_fn(name, expr, extra=(), names=("q",)):
        return ca.Function(name, [q, *extra], [expr], [*names], [name])

    pts = ca.horzcat(*[t.point(t.d[i]) for i in range(len(POINT_NAMES))])
    coms = ca.horzcat(*[t.point(t.c[b]) for b in range(N_Q)])
    jf_th = t.jac_theta(foot_coeff)
    kin = 0.5 * ca.dot(t.thd, ca.mtimes(m_th, t.thd))
    pot_rel = p.gravity * sum(t.beta[k] * t.cos[k] for k in range(N_Q))
    total_mass = float(_geometry(p)[2].sum())

    model = dict(
        mass_matrix=q_fn("M", m_q),
        bias=q_fn("bias", ca.mtimes(St, cor_th + grav_th), [qd], ["q", "qd"]),
        coriolis=q_fn("coriolis", ca.mtimes(St, cor_th), [qd], ["q", "qd"]),
        gravity=q_fn("G", ca.mtimes(St, grav_th)),
        hip_force_map=q_fn("hip_force_map", force_map),
        forward_dynamics=q_fn("qdd", ca.cse(qdd_expr), [qd, u, w], ["q", "qd", "u", "w"]),
        inverse_dynamics=q_fn("tau", tau_expr, [qd, qdd, w], ["q", "qd", "qdd", "w"]),
        link_angles=q_fn("theta", t.theta),
        points=q_fn("points", pts),
        coms=q_fn("coms", coms),
        hip=q_fn("hip", t.point(hip_coeff)),
        hip_jacobian=q_fn("hip_jacobian", t.to_q(jh_th)),
        swing_foot=q_fn("swing_foot", t.point(foot_coeff)),
        swing_foot_jacobian=q_fn("swing_foot_jacobian", t.to_q(jf_th)),
        swing_foot_velocity=q_fn("swing_foot_velocity", ca.mtimes(jf_th, t.thd), [qd],
                                 ["q", "qd"]),
    )
    # state-level functions: substitute (q, qd) = x[0:5], x[5:10]
    xq, xv, pst = x[0:N_Q], x[N_Q:2 * N_Q], x[2 * N_Q:]

    def x_fn(name, expr):
        expr = ca.substitute(expr, ca.vertcat(q, qd), x[0:2 * N_Q])
        return ca.Function(name, [x], [expr], ["x"], [name])

    flow = ca.vertcat(xv, model["forward_dynamics"](xq, xv, u, w), ca.SX.zeros(2))
    model["flow"] = ca.Function("f_biped", [x, u, w], [flow], ["x", "u", "w"], ["xdot"])
    model["points_world"] = x_fn("points_world", pts + ca.repmat(pst, 1, len(POINT_NAMES)))
    model["hip_world"] = x_fn("hip_world", t.point(hip_coeff) + pst)
    model["swing_foot_world"] = x_fn("swing_foot_world", t.point(foot_coeff) + pst)
    model["kinetic"] = x_fn("kinetic", kin)
    model["potential"] = x_fn("potential", pot_rel + total_mass * p.gravity * pst[1])
    model["energy"] = x_fn("energy", kin + pot_rel + total_mass * p.gravity * pst[1])
    # plastic impact (coordinate-free, evaluated in theta): J M^-1 J^T is the same in q
    minv_jt = ca.solve(m_th, jf_th.T)                       # 5 x 2
    lam = -ca.solve(ca.mtimes(jf_th, minv_jt), ca.mtimes(jf_th, t.thd))
    thd_plus = t.thd + ca.mtimes(minv_jt, lam)
    qd_plus = ca.mtimes(Sinv, thd_plus)
    model["impulse"] = x_fn("impulse", lam)
    model["impact"] = x_fn("impact", ca.cse(ca.vertcat(q, qd_plus, pst)))
    # leg swap: reverse the absolute angles and rates; new stance foot = old swing foot
    rev = ca.DM(t.Sinv @ np.eye(N_Q)[::-1] @ t.S)
    swapped = ca.vertcat(ca.mtimes(rev, q), ca.mtimes(rev, qd), pst + t.point(foot_coeff))
    model["swap"] = x_fn("swap", swapped)
    x_imp = model["impact"](x)
    model["reset"] = ca.Function("R_biped", [x], [ca.cse(model["swap"](x_imp))], ["x"],
                                 ["x_plus"])
    inf = np.inf
    lower = np.full(2 * N_Q + 2, -inf)
    upper = np.full(2 * N_Q + 2, inf)
    lower[1], upper[1] = p.stance_knee_range
    lower[2], upper[2] = p.torso_range
    lower[N_Q:2 * N_Q], upper[N_Q:2 * N_Q] = -p.rate_limit, p.rate_limit
    return BipedModel(**model, total_mass=total_mass, state_lower=lower, state_upper=upper,
                      u_max=p.torque_limit)


def build_biped(p: BipedParams) -> HybridSystem:
    """Builds the biped's hybrid system from validated parameters."""
    model = make_biped_model(p)
    x = ca.SX.sym("x", 2 * N_Q + 2)
    u = ca.SX.sym("u", N_Q)
    foot = model.swing_foot_world(x)
    h = ca.Function("h_swing_foot_y", [x], [foot[1]])
    mode = Mode(MODE, model.flow, (-p.torque_limit,) * N_Q, (p.torque_limit,) * N_Q)
    guards = []
    for i, (start, end, height) in enumerate(stair_edges(p), start=1):
        region = ca.Function(f"A_stair_{i}", [x], [ca.vertcat(foot[0] - start, end - foot[0])])
        guards.append(Guard(f"stair_{i}", MODE, MODE, h, height, -1, reset=model.reset,
                            region=region))
    guards.append(Guard("ground", MODE, MODE, h, p.ground_height, -1, reset=model.reset,
                        region=ca.Function("A_ground", [x], [-foot[0]])))
    goal = ca.DM(p.goal)
    hip = model.hip_world(x)
    pose_err = x[0:N_Q] - ca.DM(p.q_nominal)
    cost = (p.q_hip * ca.sumsqr(hip - goal)
            + ca.dot(ca.DM(p.pose_weights), pose_err**2) + p.r_torque * ca.sumsqr(u))

    def gain(kp: float, kd: float) -> np.ndarray:
        return np.hstack([kp * np.eye(N_Q), kd * np.eye(N_Q), np.zeros((N_Q, 2))])

    x0 = np.array([*p.q0, *p.qdot0, *p.stance_foot0], dtype=float)
    return HybridSystem(
        name="biped",
        state_names=(*(f"q{i}" for i in range(1, 6)), *(f"dq{i}" for i in range(1, 6)),
                     "stance_x", "stance_y"),
        input_names=("tau_ankle", "tau_stance_knee", "tau_stance_hip", "tau_swing_hip",
                     "tau_swing_knee"),
        disturbance_names=("force_x_torso",),
        modes=(mode,),
        guards=tuple(guards),
        initial_mode=MODE,
        final_mode=MODE,
        x0=x0,
        goal=np.array(p.goal, dtype=float),
        goal_map=model.hip_world,
        stage_cost=ca.Function("L_biped", [x, u], [cost]),
        terminal_set=None,
        success_radius=p.success_radius,
        tracking_gain=gain,
        params=p.model_dump(),
    )
