"""A cart docking on a line: a small hmpc system plug-in, registered by an entry point.

State x = (p, v) [m, m/s], input u [N], disturbance w [m/s^2] added to the acceleration.
Two modes: ``free`` (p'' = u/m + w, |u| <= u_free) and ``docked``, the final domain
(p'' = u/m - damping v + w, |u| <= u_docked). Guards of ``free``: ``dock`` at p = dock_at
crossed rightwards (the dock's latch catches the cart: velocity x catch) and ``bumper``
at p = 0 crossed leftwards (velocity reversed x restitution). Task: reach (goal, 0) in
the (p, v) plane within success_radius.

The cart starts moving left fast enough that it cannot stop before the bumper, so every
plan bounces once and then docks: free -bumper-> free -dock-> docked.

Registered by ``hmpc_dock-0.1.dist-info/entry_points.txt`` next to this file
(``[hmpc.systems] dock = hmpc_dock:SYSTEM``); a pip-installed package writes the same file
from its ``[project.entry-points."hmpc.systems"]`` table.
"""

from __future__ import annotations

from typing import Literal

import casadi as ca
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from hmpc_cli.plugin import Guard, HybridSystem, Mode, ReachGoal, SystemSpec


class DockParams(BaseModel):
    """Parameters of the docking cart (SI units)."""

    model_config = ConfigDict(extra="forbid")
    name: Literal["dock"] = "dock"
    mass: float = Field(1.0, gt=0.0, description="cart mass [kg]")
    u_free: float = Field(5.0, gt=0.0, description="input bound |u| in mode free [N]")
    u_docked: float = Field(20.0, gt=0.0, description="input bound |u| in mode docked [N]")
    damping: float = Field(2.0, ge=0.0, description="damping in the dock [1/s]")
    dock_at: float = Field(2.0, gt=0.0, description="position of the dock's entry [m]")
    catch: float = Field(0.5, ge=0.0, le=1.0, description="velocity kept through the "
                         "dock's latch")
    restitution: float = Field(0.8, ge=0.0, le=1.0, description="bumper restitution")
    x0: tuple[float, float] = (1.0, -4.0)
    goal: float = Field(2.5, description="target position in the dock [m]")
    q_position: float = Field(20.0, ge=0.0, description="stage cost weight on (p - goal)^2")
    q_velocity: float = Field(1.0, ge=0.0, description="stage cost weight on v^2")
    r_input: float = Field(0.01, ge=0.0, description="stage cost weight on u^2")
    success_radius: float = Field(0.2, gt=0.0, description="|(p, v) - (goal, 0)| at the end")


def build_dock(p: DockParams) -> HybridSystem:
    """The cart's hybrid system from validated parameters."""
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 1)
    w = ca.SX.sym("w", 1)
    pos, vel = x[0], x[1]

    def fn(name: str, expr: ca.SX) -> ca.Function:
        return ca.Function(name, [x], [expr])

    free = Mode("free", ca.Function("f_free", [x, u, w], [ca.vertcat(vel, u / p.mass + w)]),
                (-p.u_free,), (p.u_free,))
    docked = Mode("docked", ca.Function(
        "f_docked", [x, u, w], [ca.vertcat(vel, u / p.mass - p.damping * vel + w)]),
        (-p.u_docked,), (p.u_docked,))
    dock = Guard("dock", "free", "docked", fn("h_dock", pos), p.dock_at, +1,
                 reset=fn("R_dock", ca.vertcat(pos, p.catch * vel)))
    bumper = Guard("bumper", "free", "free", fn("h_bumper", pos), 0.0, -1,
                   reset=fn("R_bumper", ca.vertcat(pos, -p.restitution * vel)))
    goal = ca.DM([p.goal, 0.0])
    cost = (p.q_position * (pos - p.goal) ** 2 + p.q_velocity * vel**2
            + p.r_input * ca.sumsqr(u))
    return HybridSystem(
        name="dock", state_names=("p", "v"), input_names=("u",), disturbance_names=("w",),
        modes=(free, docked), guards=(dock, bumper),
        initial_mode="free", final_mode="docked",
        x0=np.array(p.x0, dtype=float), goal=np.array(goal).ravel(),
        goal_map=ca.Function("goal_map", [x], [x]),
        stage_cost=ca.Function("L_dock", [x, u], [cost]),
        terminal_set=None,
        tracking_gain=lambda kp, kd: np.array([[kp, kd]]),
        params=p.model_dump(), plane=("p", "v"),
    )


def dock_task(p: DockParams, system: HybridSystem) -> ReachGoal:
    """Reach (goal, 0) within the success radius."""
    return ReachGoal(system, p.success_radius)


SYSTEM = SystemSpec(
    name="dock", params=DockParams, build=build_dock, task=dock_task,
    planner="cem", mpc="fixed_mode",
    defaults={"planner.cem": {"horizon": 2.0, "knots": 10, "init_mean": 0.0,
                              "init_cov": 4.0, "samples": 30, "iterations": 8}},
)
