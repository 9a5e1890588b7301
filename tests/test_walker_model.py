"""The walker capability: one typed WalkerModel, checked when the system is built, needed by
the walking MPC and the foothold planner by type, its stance mode by name."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Literal

import casadi as ca
import numpy as np
import pytest

from conftest import BALL, SCENARIOS
from hmpc_cli.core import registry as reg
from hmpc_cli.core.messages import ConstraintMargins, ModeSchedule, Plan, SolveStats, Trajectory
from hmpc_cli.core.registry import PluginError, SystemSpec, build_system, missing_capabilities
from hmpc_cli.mpc.walking.kind import MPC, WalkingMPC
from hmpc_cli.mpc.walking.nlp import WalkingMPCSettings, WalkingNLP
from hmpc_cli.planner.footholds import (
    PLANNER, FootholdPlanner, FootholdSettings, candidates)
from hmpc_cli.plugin import HybridSystem, Mode, WalkerModel
from hmpc_cli.run.scenario import ScenarioError, load_scenario
from hmpc_cli.systems.ball import BallParams, build_ball
from hmpc_cli.systems.biped import MODE, BipedParams, build_biped

SYS = build_biped(BipedParams())
WALKER = SYS.walker
BALL_SYS = build_ball(BallParams())
Q = ca.SX.sym("q", 5)


def test_the_biped_provides_a_checked_walker_by_type():
    assert isinstance(WALKER, WalkerModel)
    assert (WALKER.n_q, WALKER.n_x, WALKER.stance_mode) == (5, 12, MODE)
    x = np.arange(12.0)
    assert list(x[WALKER.q_index]) == list(range(5))
    assert list(x[WALKER.qd_index]) == list(range(5, 10))
    assert list(x[WALKER.stance_index]) == [10.0, 11.0]
    assert "WalkerModel" in MPC.needs and "WalkerModel" in PLANNER.needs
    assert missing_capabilities(MPC.needs | PLANNER.needs, SYS) == []


# ------------------------------------------------------------- refused when built
@pytest.mark.parametrize("field, fn, message", [
    ("swing_foot_jacobian", ca.Function("J", [Q], [ca.SX.zeros(2, 4)]),
     "biped: WalkerModel.swing_foot_jacobian returns shape (2, 4), expected (2, 5)"),
    ("hip_world", ca.Function("hip", [ca.SX.sym("x", 12)], [ca.SX.zeros(3)]),
     "biped: WalkerModel.hip_world returns shape (3, 1), expected (2, 1)"),
    ("points", ca.Function("pts", [ca.SX.sym("x", 12)], [ca.SX.zeros(2, 6)]),
     "biped: WalkerModel.points: input 0 (i0) has shape (12, 1), expected (5, 1)"),
    ("inverse_dynamics", ca.Function("tau", [Q, ca.SX.sym("qd", 5)], [Q]),
     "biped: WalkerModel.inverse_dynamics takes 2 inputs and returns 1, expected 4 inputs "
     "and one output"),
])
def test_a_wrong_shaped_function_is_refused_at_build(field, fn, message):
    with pytest.raises(ValueError) as info:
        replace(SYS, walker=replace(WALKER, **{field: fn}))
    assert str(info.value) == message


def test_a_wrong_layout_or_stance_mode_is_refused_at_build():
    with pytest.raises(ValueError, match=r"^biped: WalkerModel: the state \(q\[4\], qd\[4\], "
                       r"p_st\[2\]\) has 10 entries, the system's x0 has 12$"):
        replace(SYS, walker=replace(WALKER, n_q=4))
    with pytest.raises(ValueError, match="^biped: WalkerModel: stance_mode 'double_support' "
                       "is not a mode of the system \\('single_support'\\)$"):
        replace(SYS, walker=replace(WALKER, stance_mode="double_support"))
    with pytest.raises(ValueError, match="point_names .* lack \\['torso_top'\\]"):
        names = tuple("head" if n == "torso_top" else n for n in WALKER.point_names)
        replace(SYS, walker=replace(WALKER, point_names=names))


class BadWalkerParams(BipedParams):
    name: Literal["badwalker"] = "badwalker"


class NoWalkerParams(BipedParams):
    name: Literal["nowalker"] = "nowalker"


def _registry(monkeypatch, spec: SystemSpec) -> None:
    table = reg.Registry({spec.name: spec}, {}, {}, {"system": {}, "planner": {}, "mpc": {}})
    monkeypatch.setattr(reg, "registry", lambda: table)


def test_the_registry_build_names_the_bad_function(monkeypatch):
    bad = replace(WALKER, contact_reset=ca.Function("R", [ca.SX.sym("x", 12)],
                                                    [ca.SX.zeros(10)]))
    spec = SystemSpec("badwalker", BadWalkerParams,
                      lambda p: replace(SYS, name="badwalker", walker=bad), lambda p, s: None,
                      "footholds", "walking", provides=frozenset({WalkerModel}))
    _registry(monkeypatch, spec)
    with pytest.raises(PluginError) as info:
        build_system(BadWalkerParams())
    assert str(info.value) == ("system: 'badwalker' failed to build: ValueError: badwalker: "
                               "WalkerModel.contact_reset returns shape (10, 1), expected "
                               "(12, 1)")


def test_a_system_declaring_a_walker_it_does_not_build_is_refused(monkeypatch):
    spec = SystemSpec("nowalker", NoWalkerParams,
                      lambda p: replace(SYS, name="nowalker", walker=None), lambda p, s: None,
                      "footholds", "walking", provides=frozenset({"terrain", WalkerModel}))
    _registry(monkeypatch, spec)
    with pytest.raises(PluginError) as info:
        build_system(NoWalkerParams())
    assert str(info.value) == ("system: 'nowalker' declares that it provides WalkerModel, "
                               "but its HybridSystem has none")


def test_a_capability_is_a_name_or_a_capability_type():
    assert reg.capability_names({"terrain", WalkerModel}) == {"terrain", "WalkerModel"}
    with pytest.raises(TypeError, match="a capability is a name or one of the types "
                       "WalkerModel, not <class 'int'>"):
        reg.capability_names({int})


# ------------------------------------------------ the walking MPC needs a WalkerModel
def test_the_walking_mpc_refuses_a_system_without_a_walker():
    assert missing_capabilities(MPC.needs, BALL_SYS) == ["WalkerModel", "guard_surfaces",
                                                         "terrain"]
    with pytest.raises(ScenarioError) as info:
        load_scenario(BALL, ['mpc.kind="walking"'])
    assert info.value.lines[0].endswith(
        "mpc.kind: 'walking' does not fit system 'ball': it needs WalkerModel, "
        "guard_surfaces, terrain (use 'fixed_mode')")
    with pytest.raises(ValueError, match="^the walking MPC needs a WalkerModel: system 'ball' "
                       "has none \\(HybridSystem.walker\\)$"):
        WalkingNLP(BALL_SYS, WalkingMPCSettings())
    with pytest.raises(ValueError, match="^the footholds planner needs a WalkerModel"):
        FootholdPlanner(BALL_SYS, FootholdSettings())
    sc, _ = load_scenario(SCENARIOS / "biped_stairs.toml")
    assert sc.mpc.kind == "walking"  # the biped fits


def test_the_walking_mpc_takes_the_stance_mode_and_its_margins_by_name():
    """A walker whose stance mode is not the first: its input box and shrink bound the
    torques, and its plans are in it."""
    idle = Mode("idle", SYS.modes[0].flow, (-1.0,) * 5, (1.0,) * 5)
    two = replace(SYS, modes=(idle, *SYS.modes))
    assert two.mode_index(WALKER.stance_mode) == 1
    n = len(two.guards)
    margins = ConstraintMargins("hand", 0.0, (0.025,) * n, (0.0,) * n, (0.075,) * n,
                                ((7.0,) * 5, (300.0,) * 5))
    settings = WalkingMPCSettings(nodes_per_swing=4, apex_node=2, max_iter=3)
    nlp = WalkingNLP(two, settings, margins)
    assert nlp.mode == 1 and list(nlp.torque_margin) == [300.0] * 5
    _, _, _, lbg, ubg = nlp.problem_data(two.x0, two.guard_surfaces[1], 0.0)
    rows = nlp.layout.g["torque"]
    limit = BipedParams().torque_limit - 300.0
    assert np.all(ubg[rows] == limit) and np.all(lbg[rows] == -limit)
    plan = WalkingMPC(two, settings, nlp).solve_segment(0.0, two.x0, 1)
    assert plan.schedule.modes == (1, 1) and np.all(plan.traj.mode == 1)


# ------------------------------------------------------- the biped's footholds unchanged
def _plan(x_end: np.ndarray, guard: int) -> Plan:
    traj = Trajectory(np.array([0.0, 0.1]), np.vstack([SYS.x0, x_end]), np.zeros((2, 5)),
                      np.zeros(2, dtype=int), np.zeros(2, dtype=int), (guard,), "zoh")
    stats = SolveStats("Solve_Succeeded", True, 3, 0.01, 1.0, 0.0)
    return Plan(0.0, traj, stats, ModeSchedule((0, 0), (guard,), (0.3,), 0.0), {})


def test_the_biped_footholds_are_unchanged():
    """The walker's stance foot and hip are the named outputs the planner read before."""
    planner = FootholdPlanner(SYS, FootholdSettings())
    stance, hip = SYS.numeric.output("stance_foot"), SYS.numeric.output("hip_world")
    rng = np.random.default_rng(3)
    xs = SYS.x0 + 0.1 * rng.standard_normal((20, 12))
    for x in xs:
        assert float(x[WALKER.stance_index][0]) == float(stance(x)[0][0])
        plan = _plan(x, 1)
        assert planner._hip_x(plan) == float(hip(plan.traj.x[-1])[0][0])
    # every candidate solved by a stand-in MPC whose final hip grows with the guard index
    ends = {g: SYS.x0 + np.r_[[0.0] * 10, 0.1 * g, 0.0] for g in SYS.guard_surfaces}
    seen = []

    def solve(schedule: ModeSchedule) -> Plan:
        seen.append(schedule.guards[0])
        assert schedule.modes == (0, 0) and math.isnan(schedule.durations[0])
        return _plan(ends[schedule.guards[0]], schedule.guards[0])

    res = planner.plan(0.0, SYS.x0, 0, solve)
    near = candidates(float(SYS.x0[WALKER.stance_index][0]), planner.surfaces, planner.s)
    assert res.reached_final and seen == [planner.guards[i] for i in near]
    assert res.schedule.guards == (max(seen),)


def test_a_toy_walker_builds():
    """A newcomer's walker writes one object: here a two-joint stand-in, checked at build."""
    q, qd, qdd = ca.SX.sym("q", 2), ca.SX.sym("qd", 2), ca.SX.sym("qdd", 2)
    x, u, w = ca.SX.sym("x", 6), ca.SX.sym("u", 2), ca.SX.sym("w", 0)
    pts = ca.horzcat(*[ca.vertcat(q[0] + i, q[1]) for i in range(4)])

    def f(name, args, expr):
        return ca.Function(name, args, [expr])

    walker = WalkerModel(
        n_q=2, stance_mode="walk", point_names=("stance_knee", "torso_top", "swing_knee",
                                                "swing_foot"),
        points=f("points", [q], pts), inverse_dynamics=f("id", [q, qd, qdd, w], qdd),
        swing_foot_world=f("foot", [x], x[4:6] + x[0:2]),
        swing_foot_velocity=f("v", [q, qd], qd), swing_foot_jacobian=f("J", [q], ca.SX.eye(2)),
        contact_reset=f("R", [x], x), hip_world=f("hip", [x], x[4:6]))
    flow = f("flow", [x, u, w], ca.vertcat(x[2:4], u, ca.SX.zeros(2)))
    system = HybridSystem(
        name="toy", state_names=("a", "b", "da", "db", "px", "py"), input_names=("ua", "ub"),
        disturbance_names=(), modes=(Mode("walk", flow, (-1.0, -1.0), (1.0, 1.0)),),
        guards=(), initial_mode="walk", final_mode="walk", x0=np.zeros(6),
        goal=np.zeros(2), goal_map=walker.hip_world,
        stage_cost=f("L", [x, u], ca.sumsqr(u)), terminal_set=None,
        tracking_gain=lambda kp, kd: np.zeros((2, 6)), walker=walker)
    assert system.walker is walker and missing_capabilities({"WalkerModel"}, system) == []
