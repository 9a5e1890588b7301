"""A hybrid system's parts of the wrong size are named when it is built."""

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

from hmpc_cli.core.registry import build_system
from hmpc_cli.systems.ball import BallParams


@pytest.fixture(scope="module")
def ball():
    return build_system(BallParams())


def _error(system, **changes) -> str:
    with pytest.raises(ValueError) as info:
        replace(system, **changes)
    return str(info.value)


def test_the_bundled_systems_have_the_shapes_they_need(ball):
    from hmpc_cli.core.shapes import shape_problems
    from hmpc_cli.systems.biped import BipedParams

    assert shape_problems(ball) == [] and shape_problems(build_system(BipedParams())) == []


def test_each_part_of_the_wrong_size_is_named(ball):
    x, u, w = ca.SX.sym("x", 4), ca.SX.sym("u", 2), ca.SX.sym("w", 2)
    air = replace(ball.modes[0], flow=ca.Function("f", [x, u, w], [ca.vertcat(x, 0.0)]))
    assert _error(ball, modes=(air, ball.modes[1])) == (
        "ball: mode 'outside': flow must map (x[4], u[2], w[2]) -> dx/dt[4], not "
        "(i0[4x1], i1[2x1], i2[2x1]) -> [5x1]")
    wide = replace(ball.modes[1], u_lower=(-1.0, -1.0, -1.0))
    assert _error(ball, modes=(ball.modes[0], wide)) == (
        "ball: mode 'inside': u_lower and u_upper need 2 entries each (one per input "
        "['ux', 'uy']), not 3 and 2")
    floor = replace(ball.guards[0], reset=ca.Function("R", [x], [x[:3]]))
    assert _error(ball, guards=(floor, *ball.guards[1:])) == (
        "ball: guard 'floor': reset must map x[4] -> [4], not (i0[4x1]) -> [3x1]")
    assert _error(ball, x0=np.zeros(3), tracking_gain=lambda kp, kd: np.zeros((2, 3)),
                  stage_cost=ca.Function("L", [x, u], [ca.vertcat(x[0], u[0])])) == (
        "ball: x0 has shape (3,), expected (4,) (one entry per state ['px', 'py', 'vx', "
        "'vy']); stage_cost must map (x[4], u[2]) -> a scalar, not (i0[4x1], i1[2x1]) -> "
        "[2x1]; tracking_gain(kp, kd) must be 2 x 4 (inputs x states), not 2 x 3")
