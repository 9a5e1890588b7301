"""Parameters of the five-link biped and its stairs (validated, SI units)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from hmpc_cli.core.settings_types import FiniteFloat
from hmpc_cli.systems.biped.kinematics import swing_foot_numeric
from hmpc_cli.systems.biped.terrain import stair_terrain

Five = tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]
Pair = tuple[FiniteFloat, FiniteFloat]
Q0: Five = (-0.78, 0.9, 0.0133, 0.51, -1.0951)


class Stair(BaseModel):
    """A flat segment of the course; segments follow each other from x = 0."""

    model_config = ConfigDict(extra="forbid")
    length: FiniteFloat = Field(gt=0.0, description="segment length along x [m]")
    height: FiniteFloat = Field(description="segment height [m]")


def _fig4_stairs() -> list[Stair]:
    return [Stair(length=a, height=b)
            for a, b in ((0.4, 0.0), (1.0, 0.075), (0.2, 0.125), (1.25, 0.175))]


class BipedParams(BaseModel):
    """Parameters of the five-link biped and its task (SI units, reference values)."""

    model_config = ConfigDict(extra="forbid")
    name: Literal["biped"] = "biped"
    torso_length: FiniteFloat = Field(0.625, gt=0.0, description="hip to torso top [m]")
    thigh_length: FiniteFloat = Field(0.4, gt=0.0, description="hip to knee [m]")
    calf_length: FiniteFloat = Field(0.4, gt=0.0, description="knee to foot [m]")
    torso_mass: FiniteFloat = Field(10.0, gt=0.0, description="[kg]")
    thigh_mass: FiniteFloat = Field(3.0, gt=0.0, description="[kg]")
    calf_mass: FiniteFloat = Field(1.0, gt=0.0, description="[kg]")
    torso_inertia: FiniteFloat = Field(2.22, ge=0.0, description="about the CoM [kg m^2]")
    thigh_inertia: FiniteFloat = Field(1.08, ge=0.0, description="about the CoM [kg m^2]")
    calf_inertia: FiniteFloat = Field(0.93, ge=0.0, description="about the CoM [kg m^2]")
    torso_com: FiniteFloat = Field(0.2, ge=0.0, description="CoM distance from the hip [m]")
    thigh_com: FiniteFloat = Field(0.163, ge=0.0, description="CoM distance from the hip [m]")
    calf_com: FiniteFloat = Field(0.128, ge=0.0, description="CoM distance from the knee [m]")
    gravity: FiniteFloat = Field(9.81, ge=0.0, description="[m/s^2]")
    mass_scale: FiniteFloat = Field(1.0, gt=0.0, description="factor on every mass and inertia "
                                                       "(1.1: the paper's heavier robot)")
    torque_limit: FiniteFloat = Field(3000.0, gt=0.0, description="|u_i| <= this [N m]")
    rate_limit: FiniteFloat = Field(35.0, gt=0.0, description="|qdot_i| <= this [rad/s]")
    stance_knee_range: Pair = Field((0.0, math.pi / 2), description="q2 bounds [rad]")
    torso_range: Pair = Field((-math.pi / 2, math.pi / 2),
                              description="q3 (torso relative to stance thigh) bounds [rad]")
    q0: Five = Field(Q0, description="initial angles [rad]")
    qdot0: Five = Field((0.0,) * 5, description="initial rates [rad/s]")
    stance_foot0: Pair = Field((0.0, 0.0), description="initial stance foot [m]")
    stairs: list[Stair] = Field(default_factory=_fig4_stairs, min_length=1,
                                description="consecutive flat segments from x = 0")
    ground_height: FiniteFloat = Field(0.0, description="terrain height for x <= 0 [m]")
    goal: Pair = Field((2.0, 0.8), description="hip target in the world [m]")
    q_hip: FiniteFloat = Field(10.0, ge=0.0, description="stage cost weight on |hip - goal|^2")
    q_nominal: Five = Field(Q0, description="nominal pose of the stage cost [rad]")
    pose_weights: Five = Field((0.0, 1.0, 1.0, 1.0, 1.0),
                               description="stage cost weights on (q - q_nominal)^2")
    r_torque: FiniteFloat = Field(1e-4, ge=0.0, description="stage cost weight on |u|^2")
    fall_hip_height: FiniteFloat = Field(0.35, ge=0.0, description="a fall: the hip less than "
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
        ground = stair_terrain(self).heights(fx)
        if not ground:
            out.append((("stance_foot0",), f"x = {fx} lies beyond the stairs' end "
                        f"{stair_terrain(self).end:g}", [fx, fy]))
            return out  # the swing foot is placed from it: its checks would blame q0
        if min(abs(fy - h) for h in ground) > 1e-9:
            out.append((("stance_foot0",), f"must be on the ground: y = {fy}, terrain height "
                        f"{_fmt(ground)} at x = {fx}", [fx, fy]))
            return out
        else:
            start, end, top = stair_terrain(self).segments[-1]
            if start <= fx <= end and abs(fy - top) <= 1e-9:
                out.append((("stance_foot0",), f"({fx:g}, {fy:g}) is on the top segment "
                            f"[{start:g}, {end:g}] at height {top:g} already: nothing to "
                            "climb (add a stair, or start before the top)", [fx, fy]))
        sx, sy = swing_foot_numeric(self, q)
        sx, sy = sx + fx, sy + fy
        ground = stair_terrain(self).heights(sx)
        if not ground:
            out.append((("q0",), f"initial swing foot x = {sx:.4f} lies beyond the stairs' "
                        f"end {stair_terrain(self).end:g}", list(q)))
        elif sy < min(ground) - 1e-9:
            out.append((("q0",), f"initial swing foot ({sx:.4f}, {sy:.4f}) is below the "
                        f"terrain (height {_fmt(ground)})", list(q)))
        return out


def _fmt(heights: list[float]) -> str:
    return " / ".join(f"{h:g}" for h in heights)


