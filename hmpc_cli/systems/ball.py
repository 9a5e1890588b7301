"""The paper's controlled bouncing ball (Sec. IV, Fig. 3), reference parameters by default.

State x = (px, py, vx, vy) [m, m, m/s, m/s], input u = (ux, uy) [N], disturbance
w = (wx, wy) [m/s^2] added to the accelerations (eq. (1)). Two domains: ``outside`` the
circle (gravity, pushes only towards the walls: u in [-100, 0]^2) and ``inside`` (no
gravity, u in [-100, 100]^2). Guards: floor (py - r = 0 falling, px in [0, 8], vy -> -vy),
wall (px - r = 0 moving left, py in [0, 8], vx -> -vx) and the circle |p - c| = R, crossed
inwards (outside -> inside) or outwards (inside -> outside), with identity reset.

Task: reach the circle. The goal (also the stage cost's target) is the circle's centre
and the success radius its radius unless ``goal`` / ``success_radius`` are set; the
reference's criterion (within 1 of (3, 3) at t = 3 s) is the default geometry's.
"""

from __future__ import annotations

from typing import Literal

import casadi as ca
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from hmpc_cli.plugin import (
    Ball, Drawing, FiniteFloat, Guard, HybridSystem, Mode, Polyline, ReachGoal, SystemSpec, circle)


Pair = tuple[FiniteFloat, FiniteFloat]


class BallParams(BaseModel):
    """Parameters of the bouncing ball (SI units)."""

    model_config = ConfigDict(extra="forbid")
    name: Literal["ball"] = "ball"
    radius: FiniteFloat = Field(0.1, ge=0.0, description="ball radius r [m]; shifts the wall "
                                                     "guards")
    mass: FiniteFloat = Field(1.0, gt=0.0, description="mass [kg]")
    drag: FiniteFloat = Field(0.02, ge=0.0, description="drag gamma: acceleration -gamma |v|^2 v")
    gravity: FiniteFloat = Field(9.81, ge=0.0, description="gravity outside the circle [m/s^2]")
    circle_center: Pair = Field((3.0, 3.0), description="centre c (x, y) of the circle "
                                "guard, the final domain [m]; the circle must not reach the "
                                "floor's or the wall's guard")
    circle_radius: FiniteFloat = Field(1.0, gt=0.0)
    floor_extent: Pair = Field((0.0, 8.0), description="x range where the floor is active")
    wall_extent: Pair = Field((0.0, 8.0), description="y range where the wall is active")
    u_outside: Pair = Field((-100.0, 0.0), description="input bounds per axis outside")
    u_inside: Pair = Field((-100.0, 100.0), description="input bounds per axis inside")
    x0: tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat] = Field(
        (1.0, 1.0, 0.0, 0.0), description="initial state (px, py, vx, vy) [m, m, m/s, m/s]")
    goal: Pair | None = Field(None, description="target position of the stage cost and "
                              "the success test [m] (default: the circle's centre)")
    q_position: FiniteFloat = Field(50.0, ge=0.0, description="stage cost weight on |p - goal|^2")
    q_velocity: FiniteFloat = Field(0.001, ge=0.0, description="stage cost weight on |v|^2")
    r_input: FiniteFloat = Field(0.001, ge=0.0, description="stage cost weight on |u|^2")
    terminal_radius: FiniteFloat | None = Field(
        None, gt=0.0, description="terminal set |p - goal| <= this (None: the final domain)")
    success_radius: FiniteFloat | None = Field(
        None, gt=0.0, description="success: |p_end - goal| <= this [m] (default: the "
                                  "circle's radius)")

    @property
    def target(self) -> Pair:
        """The goal position [m]: ``goal``, else the circle's centre."""
        return self.goal if self.goal is not None else self.circle_center

    @field_validator("floor_extent", "wall_extent", "u_outside", "u_inside")
    @classmethod
    def _ordered(cls, v: Pair) -> Pair:
        if not v[0] < v[1]:
            raise ValueError(f"lower bound {v[0]} must be below upper bound {v[1]}")
        return v

    @model_validator(mode="after")
    def _circle_clear_of_bounces(self) -> BallParams:
        # floor and wall are guards of ``outside`` only: inside the circle the ball would
        # pass through them, and leave the circle beyond them with their gaps negative
        (cx, cy), rad, r = self.circle_center, self.circle_radius, self.radius
        for surface, line, across, along, extent in (
                ("floor", "y", cy, cx, self.floor_extent),
                ("wall", "x", cx, cy, self.wall_extent)):
            if abs(across - r) < rad:
                half = (rad**2 - (across - r) ** 2) ** 0.5
                lo, hi = max(along - half, extent[0]), min(along + half, extent[1])
                if lo < hi:
                    raise ValueError(
                        f"the circle (centre {self.circle_center}, radius {rad:g}) reaches "
                        f"the {surface}'s guard {line} = radius = {r:g} over [{lo:.4g}, "
                        f"{hi:.4g}]: inside the circle the ball does not bounce on it; move "
                        f"circle_center at least circle_radius + radius from the {surface}")
        return self


def _modes(p: BallParams, x: ca.SX, u: ca.SX, w: ca.SX) -> tuple[Mode, Mode]:
    """The domains ``outside`` (gravity, pushes towards the walls) and ``inside``."""
    vel = x[2:4]
    drag = -p.drag * ca.sumsqr(vel) * vel
    acc_in = drag + u / p.mass + w
    acc_out = acc_in - ca.vertcat(0.0, p.gravity)
    outside = Mode("outside", ca.Function("f_outside", [x, u, w], [ca.vertcat(vel, acc_out)]),
                   (p.u_outside[0],) * 2, (p.u_outside[1],) * 2)
    inside = Mode("inside", ca.Function("f_inside", [x, u, w], [ca.vertcat(vel, acc_in)]),
                  (p.u_inside[0],) * 2, (p.u_inside[1],) * 2)
    return outside, inside


def _guards(p: BallParams, x: ca.SX) -> tuple[Guard, ...]:
    """Floor, wall (bounces) and the circle crossed inwards and outwards."""

    def fn(name: str, expr: ca.SX) -> ca.Function:
        return ca.Function(name, [x], [expr])

    dist2 = ca.sumsqr(x[0:2] - ca.DM(p.circle_center))
    rad = p.circle_radius
    floor = Guard(
        "floor", "outside", "outside", fn("h_floor", x[1]), p.radius, -1,
        reset=fn("R_floor", ca.vertcat(x[0], x[1], x[2], -x[3])),
        region=fn("A_floor", ca.vertcat(x[0] - p.floor_extent[0], p.floor_extent[1] - x[0])),
    )
    wall = Guard(
        "wall", "outside", "outside", fn("h_wall", x[0]), p.radius, -1,
        reset=fn("R_wall", ca.vertcat(x[0], x[1], -x[2], x[3])),
        region=fn("A_wall", ca.vertcat(x[1] - p.wall_extent[0], p.wall_extent[1] - x[1])),
    )
    identity = fn("R_circle", x)
    circle_in = Guard(
        "circle_in", "outside", "inside", fn("h_circle", ca.sqrt(dist2)), rad, -1,
        reset=identity, nlp_gap=fn("q_circle_in", dist2 - rad**2),
        margin=lambda d, past: rad**2 - (rad - d) ** 2 if past else (rad + d) ** 2 - rad**2,
    )
    circle_out = Guard(
        "circle_out", "inside", "outside", fn("h_circle", ca.sqrt(dist2)), rad, +1,
        reset=identity, nlp_gap=fn("q_circle_out", rad**2 - dist2),
        margin=lambda d, past: (rad + d) ** 2 - rad**2 if past else rad**2 - (rad - d) ** 2,
    )
    return floor, wall, circle_in, circle_out


def ball_drawing(p: BallParams) -> Drawing:
    """The ball's 3D scene: floor, wall and circle where the parameters put them.

    The floor (y = 0 over ``floor_extent``) and the wall (x = 0 over ``wall_extent``) are
    the surfaces the ball bounces on (their guards act on its centre, ``radius`` away);
    the circle is the guard |p - c| = R of the centre. The body is a sphere of the
    ball's radius (at least 2 cm, so a point ball stays visible) at (px, py), which also
    traces plans and rollouts.
    """
    fx, wy = p.floor_extent, p.wall_extent
    brown, teal = (0.55, 0.4, 0.25, 1.0), (0.1, 0.7, 0.6, 1.0)
    static = (Polyline("floor", ((fx[0], 0.0), (fx[1], 0.0)), brown, 0.04),
              Polyline("wall", ((0.0, wy[0]), (0.0, wy[1])), brown, 0.04),
              circle("circle", p.circle_center, p.circle_radius, teal, 0.03))
    return Drawing(points=lambda x: x[0:2].reshape(2, 1), point_names=("ball",),
                   points_many=lambda xs: xs[:, 0:2, None],
                   balls=(Ball("ball", max(p.radius, 0.02)),), trace=("ball",),
                   static=static)


def build_ball(p: BallParams) -> HybridSystem:
    """Builds the ball's hybrid system from validated parameters."""
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 2)
    w = ca.SX.sym("w", 2)
    pos, vel = x[0:2], x[2:4]
    goal = ca.DM(p.target)
    cost = (p.q_position * ca.sumsqr(pos - goal) + p.q_velocity * ca.sumsqr(vel)
            + p.r_input * ca.sumsqr(u))
    terminal = None
    if p.terminal_radius is not None:
        terminal = ca.Function("E_ball", [x], [p.terminal_radius**2 - ca.sumsqr(pos - goal)])

    def gain(kp: float, kd: float) -> np.ndarray:
        return np.hstack([kp * np.eye(2), kd * np.eye(2)])

    return HybridSystem(
        name="ball",
        state_names=("px", "py", "vx", "vy"),
        input_names=("ux", "uy"),
        disturbance_names=("wx", "wy"),
        modes=_modes(p, x, u, w),
        guards=_guards(p, x),
        initial_mode="outside",
        final_mode="inside",
        x0=np.array(p.x0, dtype=float),
        goal=np.array(p.target, dtype=float),
        goal_map=ca.Function("goal_map", [x], [pos]),
        stage_cost=ca.Function("L_ball", [x, u], [cost]),
        terminal_set=terminal,
        tracking_gain=gain,
        params=p.model_dump(),
        plane=("px", "py"),
        drawing=ball_drawing(p),
    )


def ball_task(p: BallParams, system: HybridSystem) -> ReachGoal:
    """Reach the goal (the circle's centre by default) within the success radius."""
    radius = p.success_radius if p.success_radius is not None else p.circle_radius
    return ReachGoal(system, radius)


SYSTEM = SystemSpec(
    name="ball", params=BallParams, build=build_ball, task=ball_task,
    planner="cem", mpc="fixed_mode",
    defaults={"planner.cem": {"init_mean": -20.0}},
)
