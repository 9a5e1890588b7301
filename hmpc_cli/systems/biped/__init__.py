"""The paper's planar five-link, fully actuated biped on stairs (Sec. IV, Fig. 4).

A plug-in in three parts: :mod:`.params` (validated parameters and the stairs),
:mod:`.model` (Lagrangian dynamics, kinematics, impact and leg swap, derived once in
CasADi), :mod:`.terrain` (the stairs as a terrain) and :mod:`.task` (falls, success).
:func:`build_biped` assembles the :class:`~hmpc_cli.core.hybrid.HybridSystem` with its
:class:`~hmpc_cli.core.walker.WalkerModel` (``walker``: what the walking MPC and the
foothold planner use; n_q = 5, stance mode ``single_support``) and the named outputs
tests and figures use: the walker's functions, ``points_world`` x -> (2, 6) (the joint
points ``POINT_NAMES`` in the world [m]) and ``stance_foot`` x -> (2,) [m].

State x = (q[5], qd[5], p_st[2]), one mode ``single_support``, one guard per stair
segment (``stair_1``..) plus ``ground``; each stair guard's contact surface is its
segment (the foothold candidates).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hmpc_cli.core.drawing import Ball, Drawing, Polyline
from hmpc_cli.core.numeric import compile_numpy
from hmpc_cli.core.hybrid import Guard, HybridSystem, Mode, Terrain
from hmpc_cli.core.registry import Requirement, SystemSpec
from hmpc_cli.core.walker import WalkerModel
from hmpc_cli.systems.biped.kinematics import N_Q, POINT_NAMES, STANCE_X
from hmpc_cli.systems.biped.model import BipedModel, make_biped_model, state_box
from hmpc_cli.systems.biped.params import BipedParams, Stair
from hmpc_cli.systems.biped.task import ClimbStairs
from hmpc_cli.systems.biped.terrain import stair_edges, stair_terrain

__all__ = ["MODE", "N_Q", "POINT_NAMES", "STANCE_X", "SYSTEM", "BipedModel", "BipedParams",
           "Stair", "build_biped", "make_biped_model", "stair_edges", "stair_terrain"]

MODE = "single_support"
#: polylines of the stick figure: stance leg, swing leg (from the hip), torso
SKELETON = (("stance_foot", "stance_knee", "hip", "swing_knee", "swing_foot"),
            ("hip", "torso_top"))


def _guards(p: BipedParams, model: BipedModel, x: ca.SX) -> tuple[Guard, ...]:
    """One guard per stair segment and ``ground`` (x <= 0).

    The swing foot falls through the segment's height over it; every reset is the
    impact followed by the leg swap.
    """
    foot = model.swing_foot_world(x)
    h = ca.Function("h_swing_foot_y", [x], [foot[1]])
    lip = _foot_height_lipschitz(p)
    guards = []
    for i, (start, end, height) in enumerate(stair_edges(p), start=1):
        region = ca.Function(f"A_stair_{i}", [x], [ca.vertcat(foot[0] - start, end - foot[0])])
        guards.append(Guard(f"stair_{i}", MODE, MODE, h, height, -1, reset=model.reset,
                            region=region, lipschitz=lip))
    guards.append(Guard("ground", MODE, MODE, h, p.ground_height, -1, reset=model.reset,
                        region=ca.Function("A_ground", [x], [-foot[0]]), lipschitz=lip))
    return tuple(guards)


def _foot_height_lipschitz(p: BipedParams) -> float:
    """A global Lipschitz constant of the swing-foot height in the state norm [m per unit].

    y = stance_y + Lc cos th1 + Lt cos th2 - Lt cos th4 - Lc cos th5 with th = S q, so
    dy/dq = S^T a with ||a|| <= sqrt(2 (Lc^2 + Lt^2)) and dy/dstance_y = 1.
    """
    S = np.tril(np.ones((N_Q, N_Q)))
    arm = np.linalg.norm(S, 2) * np.sqrt(2.0 * (p.calf_length**2 + p.thigh_length**2))
    return float(np.hypot(arm, 1.0))


def _walker(model: BipedModel) -> WalkerModel:
    """The biped as a walker: the walking MPC's and the foothold planner's view of it."""
    return WalkerModel(
        n_q=N_Q, stance_mode=MODE, point_names=POINT_NAMES, points=model.points,
        inverse_dynamics=model.inverse_dynamics, swing_foot_world=model.swing_foot_world,
        swing_foot_velocity=model.swing_foot_velocity,
        swing_foot_jacobian=model.swing_foot_jacobian, contact_reset=model.reset,
        hip_world=model.hip_world)


def _outputs(model: BipedModel, x: ca.SX) -> dict[str, ca.Function]:
    """The named outputs (see the module docstring)."""
    return {
        "points": model.points, "points_world": model.points_world,
        "hip_world": model.hip_world, "swing_foot_world": model.swing_foot_world,
        "stance_foot": ca.Function("stance_foot", [x], [x[STANCE_X:STANCE_X + 2]]),
        "inverse_dynamics": model.inverse_dynamics,
        "swing_foot_velocity": model.swing_foot_velocity,
        "swing_foot_jacobian": model.swing_foot_jacobian,
        "contact_reset": model.reset,
    }


def biped_drawing(model: BipedModel, terrain: Terrain) -> Drawing:
    """The biped's 3D scene: the stairs, the stick figure, hip and swing-foot traces.

    The stairs are one polyline from 1 m before x = 0 over every segment; the body is
    the ``points_world`` joints joined along :data:`SKELETON`, with spheres on the feet;
    plans and rollouts trace the hip and the swing foot.
    """
    pts = [(-1.0, terrain.ground), (0.0, terrain.ground)]
    for start, end, height in terrain.segments:
        pts += [(start, height), (end, height)]
    stairs = Polyline("stairs", tuple(pts), (0.55, 0.4, 0.25, 1.0), 0.03)
    points_world = model.points_world
    batched = compile_numpy(points_world)
    n_points = len(POINT_NAMES)

    def points(x: np.ndarray) -> np.ndarray:
        return np.asarray(points_world(x), dtype=float)

    def points_many(xs: np.ndarray) -> np.ndarray:  # column-major (2, P) nonzeros
        flat = batched(np.asarray(xs, dtype=float))[0]
        return flat.reshape(len(xs), n_points, 2).transpose(0, 2, 1)

    return Drawing(points=points, point_names=POINT_NAMES, links=SKELETON,
                   points_many=points_many,
                   balls=(Ball("stance_foot", 0.03, (0.2, 0.2, 0.2, 1.0)),
                          Ball("swing_foot", 0.03, (0.9, 0.4, 0.1, 1.0))),
                   trace=("hip", "swing_foot"), static=(stairs,))


def build_biped(p: BipedParams) -> HybridSystem:
    """Builds the biped's hybrid system from validated parameters."""
    model = make_biped_model(p)
    x = ca.SX.sym("x", 2 * N_Q + 2)
    u = ca.SX.sym("u", N_Q)
    hip = model.hip_world(x)
    pose_err = x[0:N_Q] - ca.DM(p.q_nominal)
    cost = (p.q_hip * ca.sumsqr(hip - ca.DM(p.goal))
            + ca.dot(ca.DM(p.pose_weights), pose_err**2) + p.r_torque * ca.sumsqr(u))
    residuals = ca.vertcat(np.sqrt(p.q_hip) * (hip - ca.DM(p.goal)),
                           np.sqrt(np.asarray(p.pose_weights)) * pose_err,
                           np.sqrt(p.r_torque) * u)

    def gain(kp: float, kd: float) -> np.ndarray:
        return np.hstack([kp * np.eye(N_Q), kd * np.eye(N_Q), np.zeros((N_Q, 2))])

    guards = _guards(p, model, x)
    terrain = stair_terrain(p)
    return HybridSystem(
        name="biped",
        state_names=(*(f"q{i}" for i in range(1, 6)), *(f"dq{i}" for i in range(1, 6)),
                     "stance_x", "stance_y"),
        input_names=("tau_ankle", "tau_stance_knee", "tau_stance_hip", "tau_swing_hip",
                     "tau_swing_knee"),
        disturbance_names=("force_x_torso",),
        modes=(Mode(MODE, model.flow, (-p.torque_limit,) * N_Q, (p.torque_limit,) * N_Q),),
        guards=guards,
        initial_mode=MODE,
        final_mode=MODE,
        x0=np.array([*p.q0, *p.qdot0, *p.stance_foot0], dtype=float),
        goal=np.array(p.goal, dtype=float),
        goal_map=model.hip_world,
        stage_cost=ca.Function("L_biped", [x, u], [cost]),
        terminal_set=None,
        tracking_gain=gain,
        params=p.model_dump(),
        outputs=_outputs(model, x),
        point_names=POINT_NAMES,
        skeleton=SKELETON,
        terrain=terrain,
        state_box=state_box(p),
        guard_surfaces={i: seg for i, seg in enumerate(stair_edges(p))},
        drawing=biped_drawing(model, terrain),
        walker=_walker(model),
        stage_residuals=ca.Function("r_biped", [x, u], [residuals]),
    )


def climb_task(p: BipedParams, system: HybridSystem) -> ClimbStairs:
    """The walking task on the simulated robot (``system``: the plant)."""
    return ClimbStairs(system, p.fall_hip_height)


SYSTEM = SystemSpec(
    name="biped", params=BipedParams, build=build_biped, task=climb_task,
    planner="footholds", mpc="walking",
    provides=frozenset({"terrain", "guard_surfaces", WalkerModel}),
    requires=(
        Requirement("sim.input_at_events", "recompute", "the biped's reset swaps the legs, "
                    "so the torque held before it would act on the other leg"),
        Requirement("mpc.kind", "walking", "the biped's swing needs the walking "
                    "transcription (stance-foot state, touchdown node, leg-swap reset)"),
        Requirement("planner.kind", "footholds", "the biped's hybrid problem is the choice "
                    "of the next foothold (its only mode is also its final domain)"),
    ),
)
