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

from dataclasses import dataclass

import casadi as ca
import numpy as np

from hmpc_cli.systems.biped.kinematics import N_Q, POINT_NAMES, link_geometry
from hmpc_cli.systems.biped.params import BipedParams

__all__ = ["BipedModel", "make_biped_model", "state_box"]

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
        d, c, mass, inertia = link_geometry(p)
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
        """D point / d theta, 2 x 5 (columns coeff_k e'(theta_k), e' = (-cos, -sin))."""
        return ca.horzcat(*[coeff[k] * ca.vertcat(-self.cos[k], -self.sin[k])
                            for k in range(N_Q)])

    def to_q(self, row_theta: ca.SX) -> ca.SX:
        """Right-multiplies a d/dtheta row block by S (chain rule to q)."""
        return ca.mtimes(row_theta, ca.DM(self.S))


def make_biped_model(p: BipedParams) -> BipedModel:
    """Derives the biped's dynamics, kinematics, impact and swap maps symbolically."""
    q = ca.SX.sym("q", N_Q)
    qd = ca.SX.sym("qd", N_Q)
    t = _Terms(p, q, qd)
    model = _joint_space(t, q, qd)
    model.update(_state_space(p, t, model, q, qd))
    lower, upper = state_box(p)
    return BipedModel(**model, total_mass=float(link_geometry(p)[2].sum()), state_lower=lower,
                      state_upper=upper, u_max=p.torque_limit)


def _joint_space(t: _Terms, q: ca.SX, qd: ca.SX) -> dict[str, ca.Function]:
    """Functions of the joint coordinates: dynamics, kinematics and Jacobians."""
    qdd = ca.SX.sym("qdd", N_Q)
    u = ca.SX.sym("u", N_Q)
    w = ca.SX.sym("w", 1)
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
    return dict(
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


def _state_space(p: BipedParams, t: _Terms, model: dict, q: ca.SX, qd: ca.SX
                 ) -> dict[str, ca.Function]:
    """Functions of the state x = (q, qd, p_st): flow, world points, energy, reset."""
    u = ca.SX.sym("u", N_Q)
    w = ca.SX.sym("w", 1)
    x = ca.SX.sym("x", 2 * N_Q + 2)
    Sinv = ca.DM(t.Sinv)
    m_th = t.m_theta()
    hip_coeff, foot_coeff = t.d[2], t.d[5]
    pts = ca.horzcat(*[t.point(t.d[i]) for i in range(len(POINT_NAMES))])
    jf_th = t.jac_theta(foot_coeff)
    kin = 0.5 * ca.dot(t.thd, ca.mtimes(m_th, t.thd))
    pot = (p.gravity * sum(t.beta[k] * t.cos[k] for k in range(N_Q))
           + float(link_geometry(p)[2].sum()) * p.gravity * x[2 * N_Q + 1])
    # state-level functions: substitute (q, qd) = x[0:5], x[5:10]
    xq, xv, pst = x[0:N_Q], x[N_Q:2 * N_Q], x[2 * N_Q:]

    def x_fn(name, expr):
        expr = ca.substitute(expr, ca.vertcat(q, qd), x[0:2 * N_Q])
        return ca.Function(name, [x], [expr], ["x"], [name])

    out = {}
    flow = ca.vertcat(xv, model["forward_dynamics"](xq, xv, u, w), ca.SX.zeros(2))
    out["flow"] = ca.Function("f_biped", [x, u, w], [flow], ["x", "u", "w"], ["xdot"])
    out["points_world"] = x_fn("points_world", pts + ca.repmat(pst, 1, len(POINT_NAMES)))
    out["hip_world"] = x_fn("hip_world", t.point(hip_coeff) + pst)
    out["swing_foot_world"] = x_fn("swing_foot_world", t.point(foot_coeff) + pst)
    out["kinetic"] = x_fn("kinetic", kin)
    out["potential"] = x_fn("potential", pot)
    out["energy"] = x_fn("energy", kin + pot)
    # plastic impact (coordinate-free, evaluated in theta): J M^-1 J^T is the same in q
    minv_jt = ca.solve(m_th, jf_th.T)                       # 5 x 2
    lam = -ca.solve(ca.mtimes(jf_th, minv_jt), ca.mtimes(jf_th, t.thd))
    qd_plus = ca.mtimes(Sinv, t.thd + ca.mtimes(minv_jt, lam))
    out["impulse"] = x_fn("impulse", lam)
    out["impact"] = x_fn("impact", ca.cse(ca.vertcat(q, qd_plus, pst)))
    # leg swap: reverse the absolute angles and rates; new stance foot = old swing foot
    rev = ca.DM(t.Sinv @ np.eye(N_Q)[::-1] @ t.S)
    swapped = ca.vertcat(ca.mtimes(rev, q), ca.mtimes(rev, qd), pst + t.point(foot_coeff))
    out["swap"] = x_fn("swap", swapped)
    x_imp = out["impact"](x)
    out["reset"] = ca.Function("R_biped", [x], [ca.cse(out["swap"](x_imp))], ["x"],
                               ["x_plus"])
    return out


def state_box(p: BipedParams) -> tuple[np.ndarray, np.ndarray]:
    """Bounds (lower, upper) on x = (q, qd, p_st), shape (12,) each (inf: unbounded)."""
    lower = np.full(2 * N_Q + 2, -np.inf)
    upper = np.full(2 * N_Q + 2, np.inf)
    lower[1], upper[1] = p.stance_knee_range
    lower[2], upper[2] = p.torso_range
    lower[N_Q:2 * N_Q], upper[N_Q:2 * N_Q] = -p.rate_limit, p.rate_limit
    return lower, upper
