"""The stack contract: the schedule's impact rule, the MPCs behind ``solve``, the registry."""

from __future__ import annotations

import dataclasses

import json
import math
from importlib.metadata import EntryPoint

import numpy as np
import pytest

from hmpc_cli.core.messages import (
    AHEAD, OFF_SCHEDULE, SCHEDULED, SELF_LOOP, GuardEvent, ModeSchedule)
from hmpc_cli.mpc.chain.kind import ChainMPC
from hmpc_cli.mpc.chain.nlp import MPCSettings
from hmpc_cli.planner.cem import CEMSettings, CrossEntropyPlanner
from hmpc_cli.core.registry import PluginError, SystemSpec, _load_one, registry
from hmpc_cli.systems.ball import BallParams, build_ball, ball_task

FLOOR, WALL, CIRCLE_IN, CIRCLE_OUT = range(4)
OUTSIDE, INSIDE = 0, 1


# ------------------------------------------------------------- the impact rule
def test_after_event_drops_the_scheduled_domain_and_keeps_t0():
    s = ModeSchedule((OUTSIDE, OUTSIDE, INSIDE), (FLOOR, CIRCLE_IN), (0.2, 0.3), t0=1.5)
    after, outcome = s.after_event(FLOOR, OUTSIDE)
    assert outcome == SCHEDULED
    assert after == ModeSchedule((OUTSIDE, INSIDE), (CIRCLE_IN,), (0.3,), t0=1.5)
    ahead, outcome = s.after_event(CIRCLE_IN, INSIDE)  # the floor bounce never happened
    assert outcome == AHEAD and ahead == ModeSchedule.final(INSIDE, 1.5)
    same, outcome = s.after_event(WALL, OUTSIDE)  # an extra bounce
    assert outcome == SELF_LOOP and same is s
    off, outcome = ModeSchedule.final(INSIDE).after_event(CIRCLE_OUT, OUTSIDE)
    assert outcome == OFF_SCHEDULE


# --------------------------------------------------------- the chain MPC contract
@pytest.fixture(scope="module")
def ball():
    return build_ball(BallParams())


@pytest.fixture(scope="module")
def chain(ball):
    return ChainMPC(ball, MPCSettings(horizon=1.5, max_switches=6))


@pytest.fixture(scope="module")
def planned(ball):
    planner = CrossEntropyPlanner(ball, CEMSettings(init_mean=-20.0, horizon=1.5))
    return planner.plan(0.0, ball.x0, OUTSIDE)


def _event(t, guard, before, after, x):
    return GuardEvent(t, guard, before, after, x, x)


def test_chain_mpc_owns_its_node_schedule(chain, ball, planned):
    sched = planned.schedule
    first = chain.solve(0.0, ball.x0, OUTSIDE, sched, (), planned.trajectory)
    assert first.stats.success and first.adopt and first.detail.shifted == 0
    counts = first.detail.counts
    # one MPC period later (6 nodes at 60 Hz): the elapsed nodes move to the final domain
    second = chain.solve(0.1, first.traj.x[6], OUTSIDE, sched)
    assert second.detail.shifted == 6
    assert second.detail.counts[0] == counts[0] - 6
    assert second.detail.counts[-1] == counts[-1] + 6
    # the scheduled guard fires: the MPC drops the domain itself, events apply once
    ev = _event(0.15, sched.guards[0], OUTSIDE, sched.modes[1], first.traj.x[9])
    advanced, _ = sched.after_event(ev.guard, ev.mode_after)
    third = chain.solve(0.16, first.traj.x[9], sched.modes[1], advanced, [ev])
    # the new domain began at the event: 0.01 s before this solve, round(0.6) = 1 node
    assert len(third.detail.counts) == len(counts) - 1 and third.detail.shifted == 1
    again = chain.solve(0.26, third.traj.x[6], sched.modes[1], advanced, [ev])
    assert len(again.detail.counts) == len(counts) - 1 and again.detail.shifted == 6


def test_a_solve_from_an_earlier_time_moves_no_node_twice(chain, ball, planned):
    """Delay compensation can hand the MPC a solve time before its previous one (a
    shorter delay expected): no node moves then, and the next shift counts from the
    latest time, so the nodes moved always match the latest time reached."""
    sched = dataclasses.replace(planned.schedule, t0=5.0)  # newly planned at t = 5 s
    counts = chain.solve(5.0, ball.x0, OUTSIDE, sched, (), planned.trajectory).detail.counts
    x = ball.x0
    moved = [chain.solve(t, x, OUTSIDE, sched).detail.shifted for t in (5.05, 5.0, 5.1)]
    assert counts[0] > 7 and moved == [3, 0, 3]  # 6 nodes at 60 /s: the latest 0.1 s
    assert chain.solve(5.1, x, OUTSIDE, sched).detail.counts[0] == counts[0] - 6


def test_a_schedule_the_chain_cannot_hold_is_a_rejected_plan_not_an_exception(chain, ball):
    too_many = ModeSchedule((OUTSIDE,) * 7 + (INSIDE,), (FLOOR, WALL) * 3 + (CIRCLE_IN,),
                            (0.05,) * 7, t0=3.0)
    assert "max_switches" in chain.check(too_many)
    plan = chain.solve(3.0, ball.x0, OUTSIDE, too_many)
    assert not plan.stats.success and not plan.adopt
    assert plan.stats.status.startswith("schedule rejected:")
    wrong = ModeSchedule((OUTSIDE, INSIDE), (FLOOR,), (0.1,))
    assert "does not lead" in chain.check(wrong)


# ---------------------------------------------------------------- the registry
def test_bundled_plugins_register_through_entry_points():
    reg = registry()
    assert {"ball", "biped"} <= set(reg.systems)
    assert {"cem", "footholds"} <= set(reg.planners) and {"fixed_mode", "walking"} <= set(reg.mpcs)
    with pytest.raises(PluginError, match="unknown system 'nope'"):
        reg.system("nope")


def test_a_broken_entry_point_is_reported_with_its_name_and_reason():
    bad = EntryPoint("box", "no_such_module_hmpc:SYSTEM", "hmpc.systems")
    with pytest.raises(PluginError, match=r"entry point 'box' = 'no_such_module_hmpc:SYSTEM'"
                       r".*ModuleNotFoundError"):
        _load_one(bad, "hmpc.systems", "name", SystemSpec)
    misnamed = EntryPoint("box", "hmpc_cli.systems.ball:SYSTEM", "hmpc.systems")
    with pytest.raises(PluginError, match="registers name 'ball'"):
        _load_one(misnamed, "hmpc.systems", "name", SystemSpec)


# -------------------------------------------------------------------- the task
def test_ball_task_follows_the_circle_unless_the_scenario_sets_goal_and_radius():
    p = BallParams(circle_center=(4.0, 2.5), circle_radius=0.8)
    system = build_ball(p)
    task = ball_task(p, system)
    assert task.goal.tolist() == [4.0, 2.5] and task.radius == 0.8
    near = task.verdict(np.array([4.5, 2.5, 0.0, 0.0]), INSIDE)
    far = task.verdict(np.array([4.9, 2.5, 0.0, 0.0]), INSIDE)
    assert near.success and near.error == pytest.approx(0.5)
    assert not far.success and "0.900 > 0.8" in far.reason
    nan = task.verdict(np.full(4, math.nan), INSIDE)
    assert not nan.success and math.isnan(nan.error)
    set_p = BallParams(goal=(3.0, 3.5), success_radius=0.1)
    assert ball_task(set_p, build_ball(set_p)).goal.tolist() == [3.0, 3.5]


@pytest.mark.slow
def test_a_planner_that_never_finds_a_schedule_says_so(tmp_path, invoke_hmpc):
    from conftest import BALL

    out = tmp_path / "run"
    proc = invoke_hmpc(["run", str(BALL), "--out", str(out), "--set", "planner.horizon=0.2",
                        "--set", "sim.duration=0.5"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert not summary["success"] and summary["planner_calls"] == summary["planner_rejected"]
    assert summary["warnings"] == [
        f"the planner never found a schedule ({summary['planner_calls']} calls; last: no "
        "rollout reached the final domain; no schedule yet)"]
    assert "never found a schedule" in proc.stdout


def test_the_progress_line_says_when_no_schedule_is_held(tmp_path):
    from conftest import BALL
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(BALL, ["planner.horizon=0.2", "sim.duration=0.2"])
    notes = []
    execute_run(prepare(sc), text, tmp_path / "run", lambda i, n, note: notes.append(note))
    assert notes and all(n.startswith("no schedule: no rollout reached") for n in notes)
