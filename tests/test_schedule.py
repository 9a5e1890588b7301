"""The schedule planner: a given mode schedule, validated by name, flown by the MPC."""

import math
from pathlib import Path

import pytest

from conftest import run_loop
from hmpc_cli.run.setup_checks import setup_problems
from hmpc_cli.planner.schedule import SchedulePlanner, ScheduleSettings
from hmpc_cli.log.reader import read_log
from hmpc_cli.run.scenario import ScenarioError, load_scenario
from hmpc_cli.systems.ball import BallParams, build_ball

ROOT = Path(__file__).resolve().parents[1]
BALL = ROOT / "scenarios" / "ball.toml"


def _schedule_toml(tmp_path, modes, guards, durations, extra=""):
    text = BALL.read_text().replace("[planner]\niterations = 15\nsamples = 50\n", "")
    text += (f'\n[planner]\nkind = "schedule"\nmodes = {modes!r}\nguards = {guards!r}\n'
             f"durations = {list(durations)!r}\n{extra}")
    path = tmp_path / "schedule.toml"
    path.write_text(text.replace("'", '"'))
    return path


def test_names_are_checked_against_the_system(tmp_path):
    path = _schedule_toml(tmp_path, ["outside", "inside", "nowhere"], ["circle_in", "floor"],
                          [0.5, 0.2])
    sc, _ = load_scenario(path)
    problems = setup_problems(sc)
    assert any(p.startswith("planner.modes[2]: unknown mode 'nowhere'") for p in problems)
    assert any(p.startswith("planner.guards[1]: guard 'floor' leads from 'outside'")
               for p in problems)
    # a schedule runs from where the plant starts to the final domain (6 of 6 solves
    # failed, no warning, when it never reached it)
    for modes, line in ((["outside"], "planner.modes[0]: 'outside' is not the system's "
                                      "final mode 'inside'"),
                        (["inside"], "planner.modes[0]: 'inside' is not the system's "
                                     "initial mode 'outside'")):
        sc, _ = load_scenario(_schedule_toml(tmp_path, modes, [], []))
        assert [p.split(" (")[0] for p in setup_problems(sc)] == [line]
    with pytest.raises(ScenarioError) as exc:  # lengths and signs: when the file is read
        load_scenario(_schedule_toml(tmp_path, ["outside", "inside"], ["circle_in"], [-1.0]))
    assert any("planner.durations" in line for line in exc.value.lines)


def test_a_later_call_drops_the_passed_domains():
    ball = build_ball(BallParams())
    planner = SchedulePlanner(ball, ScheduleSettings(
        modes=["outside", "outside", "inside"], guards=["floor", "circle_in"],
        durations=[0.25, 0.5]))
    first = planner.plan(0.0, ball.x0, 0).schedule
    assert first.durations == (0.25, 0.5) and first.t0 == 0.0
    later = planner.plan(0.3, ball.x0, 0).schedule
    assert later.guards == (ball.guard_index("circle_in"),)
    assert later.durations == pytest.approx((0.45,)) and later.t0 == 0.3
    early = planner.plan(0.7, ball.x0, 1)  # the circle came early: the final domain
    assert early.schedule.modes == (1,) and early.reached_final
    wrong = planner.plan(0.1, ball.x0, 1)  # in the circle while the floor is due
    assert wrong.schedule is None and "mode 1" in wrong.note


def test_the_ball_flies_the_cem_schedule_fed_back(tmp_path):
    """The CEM's plan for scenarios/ball.toml, given as a schedule, is flown exactly.

    Tolerance: the MPC rounds each planned duration up to whole node steps
    (dt = 1/60 s) and, after a real contact, re-solves at the end of the simulator step
    holding it (up to h = 1/600 s later), counting the next domain's nodes from there.
    So contact j must come ceil(d_j / dt) * dt after that re-solve (after t = 0 for
    the first), up to the event time tolerance (1e-10 s) and the MPC's forward-Euler
    model against the plant's RK4 (microseconds here): asserted to 1e-4 s. Against the
    schedule's own times (the durations summed) each contact may lag by one node step
    plus one simulator step per contact so far.
    """
    sc, _ = load_scenario(BALL, ["sim.duration=1.0"])
    run_loop(sc, tmp_path / "cem.mcap")
    plan = read_log(tmp_path / "cem.mcap").topic("/planner/plan")[0].data["schedule"]
    (tmp_path / "fed").mkdir()
    path = _schedule_toml(tmp_path / "fed", plan["mode_names"], plan["guard_names"],
                          plan["durations"])
    sc, _ = load_scenario(path, ["sim.duration=1.0"])
    run_loop(sc, tmp_path / "schedule.mcap")
    log = read_log(tmp_path / "schedule.mcap")
    events = [m.data for m in log.topic("/sim/event")]
    assert [e["guard_name"] for e in events] == plan["guard_names"]
    assert all(e["scheduled"] for e in events)
    dt, h, tol = 1.0 / 60, 1.0 / 600, sc.sim.event_time_tol
    impact_solves = [m.data["t"] for m in log.topic("/mpc/solve")
                     if m.data["reason"] == "impact"]
    start, planned = 0.0, 0.0
    for j, (e, d) in enumerate(zip(events, plan["durations"], strict=True)):
        expected = start + math.ceil(d / dt - 1e-6) * dt
        assert abs(e["t"] - expected) <= 1e-4, (j, e["t"], expected)
        planned += d
        assert planned - tol <= e["t"] <= planned + (j + 1) * (dt + h) + tol
        start = impact_solves[j]
        assert e["t"] <= start <= e["t"] + h + tol


def test_the_reference_six_contact_schedule_is_flown_in_order(tmp_path):
    sc, _ = load_scenario(ROOT / "scenarios" / "ball_reference_schedule.toml")
    result = run_loop(sc, tmp_path / "run.mcap")
    events = [m.data for m in read_log(tmp_path / "run.mcap").topic("/sim/event")]
    assert [e["guard_name"] for e in events] == sc.planner.guards
    planned, dt, h = 0.0, 1.0 / 60, 1.0 / 600
    for j, (e, d) in enumerate(zip(events, sc.planner.durations, strict=True)):
        planned += d  # late by at most one node step + one simulator step per contact
        assert planned <= e["t"] <= planned + (j + 1) * (dt + h)
    assert result.success
