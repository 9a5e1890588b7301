"""Real-time machinery: the latency model, the per-solve budget and delay compensation."""

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import hmpc_cli.run.layers as layers_module
from hmpc_cli.analysis.replay import _settings_added_since, compare_logs
from hmpc_cli.core.messages import ModeSchedule, Plan, PlannerResult, SolveStats, Trajectory
from hmpc_cli.log.reader import LogMessage, read_log
from hmpc_cli.run.realtime import Latency, SolverClock
from hmpc_cli.run.runner import prepare, run_to_log
from hmpc_cli.run.scenario import load_scenario
from hmpc_cli.run.sections import SimSettings

ROOT = Path(__file__).resolve().parents[1]
BALL = ROOT / "scenarios" / "ball.toml"


def _run(tmp_path, name, overrides, spy_predict=None):
    """Runs the ball; returns the result, the log, the MPC's solve calls (t, x, mode, plan)
    and the plant's state and tracked plan at each step (t -> (x, mode, plan))."""
    sc, _ = load_scenario(BALL, overrides)
    loop = prepare(sc)
    solves, steps = [], {}
    solve, command = loop.mpc.solve, loop.plant.command

    def spy_solve(t, x, mode, *args, **kw):
        plan = solve(t, x, mode, *args, **kw)
        solves.append((t, np.array(x), mode, plan))
        return plan

    def spy_command(t, x, mode, plan, span):
        steps.setdefault(round(t * 600), (np.array(x), mode, plan))
        return command(t, x, mode, plan, span)

    loop.mpc.solve, loop.plant.command = spy_solve, spy_command
    result = run_to_log(loop, tmp_path / f"{name}.mcap")
    return result, tmp_path / f"{name}.mcap", solves, steps


def _plan(iterations: int, wall: float, switches: int = 0, t0: float = 0.0,
          nodes: int = 1) -> Plan:
    """A plan of ``nodes`` nodes with these solve statistics over a schedule with
    ``switches`` switches."""
    traj = Trajectory(np.zeros(nodes), np.zeros((nodes, 1)), np.zeros((nodes, 1)),
                      np.zeros(nodes, int), np.zeros(nodes, int))
    sched = ModeSchedule((0,) * (switches + 1), (0,) * switches, (0.1,) * switches, t0)
    return Plan(t0, traj, SolveStats("Solve_Succeeded", True, iterations, wall, 1.0, 0.0),
                sched)


def _planned(wall: float, *solves: Plan) -> PlannerResult:
    """A planner call of measured ``wall`` [s] that made these MPC solves itself."""
    return PlannerResult(None, None, 0.0, True, wall, 0, mpc_solves=solves)


def test_the_latency_kinds_charge_what_they_say():
    model = Latency("model", overhead=0.002, per_iteration=0.008, planner=0.01)
    assert model.charge(_plan(12, 5.0)) == pytest.approx(0.002 + 12 * 0.008)
    assert model.charge(_plan(3, 5.0), _planned(7.0)) == pytest.approx(0.01 + 0.002 + 0.024)
    assert Latency("fixed", 0.02).charge(_plan(40, 5.0), _planned(7.0)) == 0.02
    assert Latency("measured").charge(_plan(40, 0.05), _planned(0.03)) == pytest.approx(0.08)
    assert Latency("paused").charge(_plan(40, 0.05), _planned(0.03)) == 0.0
    assert not Latency("paused").charged("period")
    assert not Latency("fixed", 0.02, first="paused").charged("initial")
    assert Latency("fixed", 0.02, first="paused").charged("period")
    budget = Latency("model", per_iteration=0.01, budget=0.05)
    assert budget.over_budget(0.06) and not budget.over_budget(0.05)
    assert Latency("fixed", 0.02).expected(0.3) == 0.02
    assert Latency("model").expected(0.3) == 0.3
    # a solve with a switch left is charged its own cost per iteration (its NLP is larger)
    two = Latency("model", overhead=0.001, per_iteration=0.002, per_switching_iteration=0.009)
    assert two.charge(_plan(1, 5.0, switches=1)) == pytest.approx(0.010)
    assert two.charge(_plan(5, 5.0)) == pytest.approx(0.011)
    assert model.charge(_plan(2, 5.0, switches=1)) == pytest.approx(0.018)


def test_a_model_with_nodes_charges_a_plan_by_its_size():
    """sim.latency_model.nodes: a plan of n nodes is charged n / nodes times the model (a
    301-node plan 301/181 of a 181-node one's, per its own iterations); without nodes, or
    for a rejected schedule's one-node plan (nothing solved), the charge is the unscaled
    one."""
    from hmpc_cli.mpc.chain.kind import rejected_plan

    kw = {"overhead": 0.005, "per_iteration": 0.002, "per_switching_iteration": 0.004}
    scaled, flat = Latency("model", nodes=181, **kw), Latency("model", **kw)
    assert scaled.charge(_plan(2, 5.0, nodes=181)) == flat.charge(_plan(2, 5.0, nodes=301)) \
        == pytest.approx(0.009)
    assert scaled.charge(_plan(2, 5.0, nodes=301)) == pytest.approx(0.009 * 301 / 181)
    assert scaled.charge(_plan(3, 5.0, switches=1, nodes=191)) == pytest.approx(
        0.017 * 191 / 181)
    rejected = rejected_plan(0.2, np.zeros(4), 0, ModeSchedule((0,), (), (), 0.2), "why")
    assert len(rejected.traj.t) == 1 and scaled.charge(rejected) == flat.charge(rejected) \
        == pytest.approx(0.005)
    planned = _planned(0.3, _plan(4, 0.1, switches=1, nodes=362))
    assert Latency("model", nodes=181, planner=0.01, **kw).planner_cost(planned) == \
        pytest.approx(0.01 + 2 * 0.021)
    sim = SimSettings.model_validate({"latency": "model", "latency_model": {
        "overhead": 0.005, "per_iteration": 0.002, "nodes": 181}})
    assert Latency.of(sim.latency, model=sim.latency_model).nodes == 181
    assert Latency.of("model", model=SimSettings().latency_model).nodes is None


def test_a_planner_that_solves_mpc_problems_is_charged_them_once():
    """A foothold planner's candidate solves are its cost; the loop's solve of the chosen
    candidate returns that plan again and adds nothing (not twice, not never)."""
    model = Latency("model", overhead=0.002, per_iteration=0.008, planner=0.01)
    a, b = _plan(30, 0.2, switches=1, t0=0.3), _plan(12, 0.1, switches=1, t0=0.3)
    call = _planned(0.31, a, b)
    assert model.planner_cost(call) == pytest.approx(0.01 + 0.002 + 0.24 + 0.002 + 0.096)
    assert model.charge(replace(a, adopt=False), call) == pytest.approx(model.planner_cost(call))
    other = _plan(7, 0.05, switches=1, t0=0.3)  # a solve the planner did not make
    assert model.charge(other, call) == pytest.approx(model.planner_cost(call) + 0.058)
    measured = Latency("measured")
    assert measured.charge(a, call) == pytest.approx(0.31)  # the candidate's 0.2 s is in it
    assert measured.charge(other, call) == pytest.approx(0.36)


def test_a_prediction_after_a_foothold_replan_expects_the_candidates_solve_time():
    """``measured``: the loop's solve of the chosen foothold candidate returns the plan the
    planner solved (a lookup of microseconds); the next prediction expects that plan's own
    solve time, not the lookup's (it expected about 0 s), nor the planner call's."""
    clock = SolverClock(Latency("measured", compensate=True))
    chosen = _plan(39, 0.2, switches=1, t0=0.3)
    clock.planner = _planned(0.35, chosen, _plan(20, 0.1, switches=1, t0=0.3))
    clock.solved(chosen, 1.5e-5)
    assert clock.last_solve == 0.2
    clock.planner = None
    clock.solved(_plan(5, 0.01, t0=0.4), 0.012)  # a period solve: its whole call
    assert clock.last_solve == 0.012
    clock.solved(replace(_plan(0, 0.0, t0=0.5), adopt=False), 1e-4)  # rejected: no NLP
    assert clock.last_solve == 0.012


def test_rebase_keeps_what_is_left_of_the_current_domain():
    """A schedule planned anew at t: the current domain, entered at start, keeps its
    planned time less what has elapsed (none when overdue; all of it when start is later
    than t, a domain entered at a predicted time the solve came before: it gained time)."""
    from hmpc_cli.run.realtime import rebase

    sched = ModeSchedule((0, 1, 2), (0, 1), (0.1, 0.2), t0=0.0)
    assert rebase(sched, 0.25, 0.2).durations == pytest.approx((0.05, 0.2))
    assert rebase(sched, 0.25, 0.2).t0 == 0.25
    assert rebase(sched, 0.5, 0.2).durations == (0.0, 0.2)
    assert rebase(sched, 0.3, 0.35).durations == (0.1, 0.2)
    final = ModeSchedule((2,), (), (), t0=0.0)
    assert rebase(final, 0.4, 0.1) == ModeSchedule((2,), (), (), t0=0.4)


def test_delay_compensation_solves_from_the_state_at_the_plans_arrival(tmp_path, monkeypatch):
    """Undisturbed ball, 0.02 s charged: every compensated solve starts from exactly the
    plant's state at the step its plan reaches the plant, a contact inside the delay
    included (the prediction flies the same simulator through the reset)."""
    predictions = []
    real_predict = layers_module.predict

    def spy(plant, t, x, mode, delay, plan_at, contacts):
        pred = real_predict(plant, t, x, mode, delay, plan_at, contacts)
        predictions.append((t, delay, pred))
        return pred

    monkeypatch.setattr(layers_module, "predict", spy)
    res, log, solves, steps = _run(tmp_path, "comp", [
        "sim.duration=1.5", "sim.latency=0.02", 'sim.latency_first="paused"',
        "sim.delay_compensation=true", "mpc.rate_hz=20"])
    assert not res.diverged, res.reason
    made = [(t, p) for t, d, p in predictions if p is not None]
    # every solve but the first (the replan at t = 0, from the measured state) compensated
    assert len(made) == len(predictions) == len(solves) - 1 == 31
    for t, pred in made:
        assert pred.t == pytest.approx(t + 0.02, abs=1e-9)  # 12 steps of 1/600 s
        x_real, mode_real, _ = steps[round(pred.t * 600)]
        assert np.array_equal(pred.x, x_real) and pred.mode == mode_real
        solved = [s for s in solves if s[0] == pred.t]
        assert solved and np.array_equal(solved[0][1], pred.x)
    across = [pred for _, pred in made if pred.events]
    assert len(across) == 2, "the two predictions across a contact: not exercised"
    # the log stamps each plan from where it starts: the predicted arrival, not t
    logged = {round(m.log_time_ns / 1e9, 9): m.data for m in read_log(log).messages
              if m.topic == "/mpc/solve"}
    for t, pred in made:
        assert logged[round(t, 9)]["plan"][0]["t"] == pytest.approx(pred.t, abs=1e-12)


def test_a_prediction_expects_the_last_solves_own_time_at_most_the_budget(tmp_path,
                                                                         monkeypatch):
    """Modelled latency (2 ms per iteration, 30 ms per planner call), a 0.1 s budget, the
    first plan charged: each compensated solve predicts as far ahead as the last charged
    solve took itself, never its planner call's time (a period solve follows none) and
    never past the budget (a slower solve is dropped: no plan arrives later)."""
    delays = []
    real_predict = layers_module.predict

    def spy(plant, t, x, mode, delay, plan_at, contacts):
        delays.append((t, delay))
        return real_predict(plant, t, x, mode, delay, plan_at, contacts)

    monkeypatch.setattr(layers_module, "predict", spy)
    res, log, solves, _ = _run(tmp_path, "expect", [
        "sim.duration=1.5", 'sim.latency="model"', "sim.latency_model.overhead=0.0",
        "sim.latency_model.per_iteration=0.002",
        "sim.latency_model.per_switching_iteration=0.002", "sim.latency_model.planner=0.03",
        "sim.solve_budget=0.1", "sim.delay_compensation=true"])
    msgs = [m.data for m in read_log(log).topic("/mpc/solve")]
    expected, last = {}, 0.0
    for m in msgs:
        expected[round(m["t"], 9)] = min(last, 0.1)
        if m["iterations"] > 0:
            last = 0.002 * m["iterations"]
    assert len(delays) > 5 and all(d == pytest.approx(expected[round(t, 9)], abs=1e-12)
                                   for t, d in delays)
    # the first plan's charge held the planner's 30 ms; its successor expects its solve's
    assert msgs[0]["reason"] == "initial" and delays[0][0] == msgs[1]["t"]
    assert delays[0][1] == pytest.approx(msgs[0]["latency"] - 0.03, abs=1e-12)
    assert any(d == 0.1 for _, d in delays), "no prediction capped: not exercised"


def _force_one_longer_prediction(monkeypatch, late: float | None = None) -> list:
    """Makes the first compensated prediction that sees no contact fly 0.1 s longer, to
    one it sees (with ``late``: that contact placed at ``late`` s, the prediction ending
    0.01 s after it); returns the list that gets that prediction."""
    real_predict, forced = layers_module.predict, []

    def spy(plant, t, x, mode, delay, plan_at, contacts):
        pred = real_predict(plant, t, x, mode, delay, plan_at, contacts)
        if not forced and pred is not None and not pred.events:
            longer = real_predict(plant, t, x, mode, delay + 0.1, plan_at, contacts)
            if longer is not None and longer.events:
                if late is not None:
                    moved = replace(longer.events[0], t=late)
                    longer = replace(longer, events=(moved,), t=late + 0.01)
                forced.append(longer)
                return longer
        return pred

    monkeypatch.setattr(layers_module, "predict", spy)
    return forced


def test_a_predicted_contact_not_predicted_again_replans_the_schedule_on_time(
        tmp_path, monkeypatch):
    """Ball, 0.02 s charged, compensated: one prediction (forced 0.1 s longer) tells the
    MPC of a wall contact at 0.15 s that the next prediction, to 0.12 s, does not reach.
    The MPC then holds a schedule the plant has not reached: the loop plans its schedule
    anew at 0.12 s, the current domain keeping what is left of its planned time, so the
    MPC's first domain has 2 intervals of 1/60 s (it had 9 from the planner's whole 0.139 s
    when the contact was just forgotten); the real contact is applied when it comes."""
    forced = _force_one_longer_prediction(monkeypatch)
    res, log, solves, _ = _run(tmp_path, "told", [
        "sim.duration=0.3", "sim.latency=0.02", 'sim.latency_first="paused"',
        "sim.delay_compensation=true", "mpc.rate_hz=20"])
    (pred,) = forced
    assert [round(ev.t, 4) for ev in pred.events] == [0.15] and pred.t == pytest.approx(0.17)
    planned = solves[0][3].schedule
    at = {round(t, 4): plan for t, _, _, plan in solves}
    replanned = at[0.12]  # solved at 0.1 s from the state predicted at 0.12 s
    assert replanned.schedule.t0 == pytest.approx(0.12)
    assert replanned.schedule.durations[0] == pytest.approx(planned.durations[0] - 0.12)
    assert replanned.schedule.durations[1:] == planned.durations[1:]
    assert replanned.detail.counts[:2] == (2, 3)
    (wall, *_) = [m.t for m in read_log(log).topic("/sim/event")]
    after = [plan for t, _, _, plan in solves if t > wall]
    assert after and len(after[0].detail.counts) == len(replanned.detail.counts) - 1


def test_a_real_contact_before_a_withdrawn_prediction_of_it_is_applied(tmp_path,
                                                                       monkeypatch):
    """As above, but the forced prediction places the wall contact at 0.19 s, after the
    plant's real one at 0.176 s: the MPC had kept the predicted time as the newest event
    it applied, skipped the real contact as old and reinstalled its schedule cold. Now a
    schedule planned anew forgets the withdrawn time: the real contact drops the wall
    domain, with no reinstall."""
    _force_one_longer_prediction(monkeypatch, late=0.19)
    _, log, solves, _ = _run(tmp_path, "late", [
        "sim.duration=0.3", "sim.latency=0.02", 'sim.latency_first="paused"',
        "sim.delay_compensation=true", "mpc.rate_hz=20"])
    (wall, *_) = [m.t for m in read_log(log).topic("/sim/event")]
    assert wall == pytest.approx(0.1761, abs=1e-4) and wall < 0.19
    at = {round(t, 4): plan for t, _, _, plan in solves}
    before, after = at[0.17], at[0.1967]  # the solves either side of the real contact
    assert len(after.detail.counts) == len(before.detail.counts) - 1  # the wall dropped
    # one node moved since the contact: no schedule reinstalled (it was: 0 moved, the
    # first domain 3 intervals from 0.1967 s)
    assert after.detail.shifted == 1 and after.detail.counts[0] == 2


def test_measured_latency_charges_the_prediction_and_the_whole_solve_call(tmp_path,
                                                                        monkeypatch):
    """``measured``: a solve is charged the controller's whole work for it, the prediction
    (made to take 30 ms here) and the MPC's set-up around its NLP included, not only the
    NLP solver's own wall time."""
    import time

    real_predict = layers_module.predict

    def slow(*args):
        time.sleep(0.03)
        return real_predict(*args)

    monkeypatch.setattr(layers_module, "predict", slow)
    _, log, _, _ = _run(tmp_path, "measured", [
        "sim.duration=0.5", 'sim.latency="measured"', 'sim.latency_first="paused"',
        "sim.delay_compensation=true", "mpc.rate_hz=20"])
    msgs = [m.data for m in read_log(log).topic("/mpc/solve")][1:]
    assert msgs and all(m["reason"] in ("period", "impact") for m in msgs)
    assert all(m["latency"] >= m["wall_time"] + 0.03 for m in msgs)
    assert all(m["latency"] == m["call_wall_time"] for m in msgs)  # logged as charged


def test_a_solve_over_its_budget_is_dropped_and_the_previous_plan_tracked_on(tmp_path):
    res, log, solves, steps = _run(tmp_path, "budget", [
        "sim.duration=0.5", 'sim.latency="model"', 'sim.latency_first="paused"',
        "sim.latency_model.overhead=0.0", "sim.latency_model.per_iteration=0.01",
        "sim.latency_model.planner=0.0", "sim.solve_budget=0.05"])
    msgs = [m.data for m in read_log(log).messages if m.topic == "/mpc/solve"]
    dropped = [m for m in msgs if "over budget" in m["reason"]]
    kept = [m for m in msgs if "over budget" not in m["reason"]]
    assert dropped and kept
    assert all(m["iterations"] * 0.01 > 0.05 for m in dropped)
    # logged not adopted, with the compute time they were charged (not the budget)
    assert all(m["adopted"] is False for m in dropped)
    assert all(m["latency"] == pytest.approx(m["iterations"] * 0.01) for m in dropped)
    assert all(m["reason"].endswith(" (over budget: dropped)") for m in dropped)
    used = {id(p) for _, _, p in steps.values() if p is not None}
    plans = {round(t, 9): plan for t, _, _, plan in solves}
    for m in dropped:
        assert id(plans[round(m["t"], 9)]) not in used  # never reached the plant
        # the plant tracks the plan it had, over the budget's window
        k0, k1 = round(m["t"] * 600), round((m["t"] + 0.05) * 600)
        before = steps[k0][2]
        assert all(steps[k][2] is before for k in range(k0, k1) if k in steps)
    assert any("solve_budget" in w for w in res.warnings)
    assert res.real_time["dropped_solves"] == len(dropped)
    assert res.real_time["charged_solves"] == len(msgs) - 1  # the first plan paused
    # a dropped solve keeps the solver busy for the budget (0.05 s), under the 0.1 s
    # period, however much it was charged: late are kept solves charged over the period
    assert any(m["latency"] > 0.1 for m in dropped)
    assert res.real_time["late_solves"] == sum(m["latency"] > 0.1 for m in kept[1:])
    assert res.real_time["delay_max"] == max(m["latency"] for m in msgs[1:])


def test_a_contact_counts_and_names_only_the_plans_it_stops():
    """A plan due after the contact is dropped and named; one already due is kept; work
    that had no plan for the plant (a planner call that found nothing) is no preemption."""
    clock = SolverClock(Latency("fixed", 0.05, preempt=True))
    assert clock.charge(0.10, _plan(3, 0.0)) == (False, 0.05)  # due at 0.15
    assert clock.charge(0.20, _plan(3, 0.0)) == (False, 0.05)  # due at 0.25
    assert clock.preempt(0.22) == [0.20] and clock.preempted == 1
    # the stopped solve kept the solver busy until the contact, its charge stays
    assert np.allclose(clock.charges, [[0.10, 0.05, 0.05], [0.20, 0.05, 0.02]])
    assert [due for due, _, _ in clock.pending] == [0.15000000000000002]
    clock.busy(0.30, 0.04)
    assert clock.preempt(0.32) == [] and clock.preempted == 1
    assert clock.free(0.32)
    assert clock.warnings() == ["1 solve in flight was stopped by a contact "
                                "(sim.preempt_at_contact; their plans dropped)"]


def test_real_time_settings_with_time_paused_are_named_in_a_warning(tmp_path):
    res, log, _, _ = _run(tmp_path, "paused", [
        "sim.duration=0.1", "sim.solve_budget=0.001", "sim.delay_compensation=true"])
    assert res.warnings == [
        "sim.solve_budget, sim.delay_compensation: no effect with sim.latency = \"paused\" "
        "(no compute time is charged); set sim.latency to \"model\", \"measured\" or a "
        "delay [s]"]
    assert res.real_time is None
    assert "real_time" not in read_log(log).topic("/run/summary")[0].data
    assert all(m.data["latency"] == 0.0 and "over budget" not in m.data["reason"]
               for m in read_log(log).messages if m.topic == "/mpc/solve")


def test_the_model_latency_is_deterministic(tmp_path):
    args = ["sim.duration=1.0", 'sim.latency="model"', "sim.delay_compensation=true",
            "sim.latency_model.overhead=0.002", "sim.latency_model.per_iteration=0.008"]
    _, a, _, _ = _run(tmp_path, "a", args)
    _, b, _, _ = _run(tmp_path, "b", args)
    assert compare_logs(read_log(a).messages, read_log(b).messages) is None
    charged = [m.data["latency"] for m in read_log(a).messages if m.topic == "/mpc/solve"]
    iters = [m.data["iterations"] for m in read_log(a).messages if m.topic == "/mpc/solve"]
    assert charged[1:] == pytest.approx([0.002 + 0.008 * k for k in iters[1:]])


def test_the_summary_says_how_the_charged_compute_time_met_the_mpc_period(tmp_path):
    """real_time: the compute time charged to each solve as /mpc/solve logs it (the
    first plan's, paused, left out), the late solves those charged more than the 50 ms
    period of a 20 Hz MPC (some are, some are not); the same object in summary.json and
    /run/summary."""
    import json

    from hmpc_cli.run.runner import summary_text

    res, log, _, _ = _run(tmp_path, "rt", [
        "sim.duration=1.0", "mpc.rate_hz=20", 'sim.latency="model"',
        'sim.latency_first="paused"', "sim.latency_model.overhead=0.002",
        "sim.latency_model.per_iteration=0.008", "sim.latency_model.planner=0.0"])
    solves = [m.data for m in read_log(log).messages if m.topic == "/mpc/solve"]
    assert solves[0]["latency"] == 0.0
    charged = np.array([s["latency"] for s in solves[1:]])
    late = charged > 0.05
    assert 0 < late.sum() < len(charged)
    assert res.real_time == {
        "latency": "model", "period": 0.05, "delay_median": float(np.median(charged)),
        "delay_p95": float(np.percentile(charged, 95)), "delay_max": float(charged.max()),
        "charged_solves": len(charged), "late_solves": int(late.sum()),
        "dropped_solves": 0, "preempted_solves": 0}
    assert read_log(log).topic("/run/summary")[0].data["real_time"] == res.real_time
    assert json.loads(summary_text(res))["real_time"] == res.real_time
    # hmpc replay says it as hmpc run does
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app
    from hmpc_cli.cli.run import real_time_text

    shown = CliRunner().invoke(app, ["replay", "-q", str(log)], env={"COLUMNS": "400"})
    assert shown.exit_code == 0, shown.output
    assert f"model: {real_time_text(res.real_time)}" in " ".join(shown.output.split())


def test_the_model_charges_a_solve_with_a_switch_left_its_own_cost(tmp_path):
    """scenarios/ball_realtime.toml (real-time iterations) with the model latency: every
    charged solve costs overhead + its iterations x the per-iteration cost of its NLP (the
    switching one while the schedule has a switch left); the first plan is paused; two
    runs are identical."""
    sets = ["sim.duration=1.0", 'sim.latency="model"']
    logs = []
    for name in ("a", "b"):
        sc, _ = load_scenario(ROOT / "scenarios" / "ball_realtime.toml", sets)
        run_to_log(prepare(sc), tmp_path / f"{name}.mcap")
        logs.append(read_log(tmp_path / f"{name}.mcap"))
    assert compare_logs(logs[0].messages, logs[1].messages) is None
    m = load_scenario(ROOT / "scenarios" / "ball_realtime.toml", sets)[0].sim.latency_model
    solves = [d.data for d in logs[0].messages if d.topic == "/mpc/solve"]
    assert solves[0]["reason"] == "initial" and solves[0]["latency"] == 0.0
    want = [m.overhead + k * (m.per_switching_iteration if sw else m.per_iteration)
            for k, sw in ((s["iterations"], bool((s.get("schedule") or {}).get("guards")))
                          for s in solves[1:])]
    assert [s["latency"] for s in solves[1:]] == pytest.approx(want)
    kinds = {bool((s.get("schedule") or {}).get("guards")) for s in solves[1:]}
    assert kinds == {True, False}  # both costs were charged
    assert {s["iterations"] for s in solves[1:] if s["reason"] == "period"} == {1}


def test_verify_forgives_a_setting_added_since_the_run_and_nothing_else():
    old = LogMessage("/run/info", 0.0, {"scenario_json": '{"sim": {"rate_hz": 600}}'}, 0)
    added = '{"sim": {"rate_hz": 600, "delay_compensation": false}}'
    new = LogMessage("/run/info", 0.0, {"scenario_json": added}, 0)
    (same,) = _settings_added_since([old], [new])
    assert same.data == old.data
    changed = LogMessage("/run/info", 0.0, {"scenario_json":
                                            '{"sim": {"rate_hz": 500, "new": 1}}'}, 0)
    (kept,) = _settings_added_since([old], [changed])
    assert kept.data == changed.data


@pytest.mark.parametrize("topic, field, value, since", [
    ("/mpc/solve", "nodes", 181, 5), ("/run/summary", "real_time", {"late_solves": 2}, 6)])
def test_verify_forgives_a_field_added_since_the_logs_version_and_nothing_else(
        topic, field, value, since):
    """/mpc/solve's nodes (log version 5) and /run/summary's real_time (6) are left out of
    a re-run compared with an older log, kept against one of their version; other fields
    stay either way."""
    new = LogMessage(topic, 0.1, {"iterations": 3, field: value}, 0)
    recorded = LogMessage(topic, 0.1, {"iterations": 3}, 0)  # written without it
    for version, want in [(since - 1, {"iterations": 3}),
                          (since, {"iterations": 3, field: value})]:
        info = LogMessage("/run/info", 0.0, {"log_version": version}, 0)
        rerun = _settings_added_since([info, recorded], [info, new])
        assert rerun[1].data == want
        found = compare_logs([info, recorded], rerun)
        assert (found is None) if version < since else (found.path, found.recorded) == (
            field, "(missing)")


def test_a_compensated_walking_solve_past_the_touchdown_solves_from_the_measured_state(
        tmp_path):
    """Biped, modelled latency (8 ms per iteration, the first plan paused), delay
    compensation: a period solve whose prediction crosses the touchdown leaves no
    foothold in the schedule, which the walking MPC cannot solve; the solve starts from
    the measured state instead (it was given the predicted one, rejected, and charged
    while the plant waited) and the MPC is not told the touchdown the plant has not had."""
    from hmpc_cli.log.schema import validate

    sc, _ = load_scenario(ROOT / "scenarios" / "biped_stairs.toml", [
        "sim.duration=0.3", 'sim.latency="model"', "sim.delay_compensation=true",
        'sim.latency_first="paused"', "sim.latency_model.per_iteration=0.008"])
    told: list = []
    prepared = prepare(sc)
    solve = prepared.mpc.solve

    def spy(t, x, mode, schedule, events=(), guess=None):
        told.append((round(t, 4), [round(ev.t, 4) for ev in events]))
        return solve(t, x, mode, schedule, events, guess)

    prepared.mpc.solve = spy
    result = run_to_log(prepared, tmp_path / "biped.mcap")
    assert result.t_end == pytest.approx(0.3), result.reason
    log = read_log(tmp_path / "biped.mcap")
    solves = log.topic("/mpc/solve")
    assert not [m for m in solves if m.data["status"].startswith("schedule rejected")]
    (at,) = [m for m in solves if round(m.t, 3) == 0.214]
    assert at.data["iterations"] > 0 and at.data["plan"][0]["t"] == pytest.approx(at.t)
    # the touchdown (after the run's end) was never told the MPC
    assert not log.topic("/sim/event") and told and not any(ts for _, ts in told)
    for m in log.messages:
        assert validate(log.schemas[m.topic], m.data) == [], (m.topic, m.t)


def test_the_foothold_planners_candidates_are_charged_once(tmp_path):
    """Biped, modelled latency, the first plan charged: its planning step solves two
    candidates cold; the first plan reaches the plant after the planner's constant and
    both candidates' solves, each charged as a solve, and the loop's solve of the chosen
    candidate (the same plan returned) adds nothing."""
    sc, _ = load_scenario(ROOT / "scenarios" / "biped_stairs.toml",
                          ["sim.duration=0.05", 'sim.latency="model"'])
    run_to_log(prepare(sc), tmp_path / "biped.mcap")
    log, m = read_log(tmp_path / "biped.mcap"), sc.sim.latency_model
    (call,) = log.topic("/planner/plan")
    iters = [c["iterations"] for c in call.data["detail"]["candidates"]]
    assert len(iters) == 2 and min(iters) > 0
    (solve,) = log.topic("/mpc/solve")
    assert solve.data["reason"] == "initial" and solve.data["iterations"] in iters
    assert solve.data["latency"] == pytest.approx(
        m.planner + sum(m.overhead + m.per_iteration * k for k in iters))


def test_a_planner_call_that_finds_no_schedule_keeps_the_solver_busy(tmp_path):
    """Ball, modelled latency with a planner call charged 0.25 s: when the first call
    returns no schedule (injected), the retry waits for the solver: at 0.25 s, not at the
    next MPC period (0.1 s)."""
    sc, _ = load_scenario(BALL, ["sim.duration=0.4", 'sim.latency="model"',
                                 "sim.latency_model.planner=0.25"])
    run = prepare(sc)
    plan, calls = run.planner.plan, []

    def first_finds_nothing(t, *args):
        result = plan(t, *args)
        calls.append(t)
        return replace(result, schedule=None, note="injected") if len(calls) == 1 else result

    run.planner.plan = first_finds_nothing
    run_to_log(run, tmp_path / "ball.mcap")
    log = read_log(tmp_path / "ball.mcap")
    assert [round(p.t, 6) for p in log.topic("/planner/plan")] == [0.0, 0.25]
    assert not log.topic("/planner/plan")[0].data["accepted"]
    assert [round(s.t, 6) for s in log.topic("/mpc/solve")][:1] == [0.25]


def test_a_prediction_that_chatters_falls_back_to_the_measured_state(tmp_path, monkeypatch):
    """Ball, 0.02 s charged, delay compensation, the model's flight allowed no guard event
    in a step (so every prediction across a contact chatters by the simulator's own Zeno
    check): the run goes on (it crashed once, on a biped whose model chattered where the
    plant did not), and each solve whose prediction chattered starts from the measured
    state at its own time."""
    real_predict, chattered = layers_module.predict, []

    def strict(plant, t, x, mode, delay, plan_at, contacts):
        pred = real_predict(replace(plant, max_events=0), t, x, mode, delay, plan_at,
                            contacts)
        if pred is None:
            chattered.append((t, np.array(x)))
        return pred

    monkeypatch.setattr(layers_module, "predict", strict)
    res, _, solves, _ = _run(tmp_path, "chatter", [
        "sim.duration=1.5", "sim.latency=0.02", 'sim.latency_first="paused"',
        "sim.delay_compensation=true", "mpc.rate_hz=20"])
    assert res.t_end == pytest.approx(1.5) and not res.diverged, res.reason
    assert chattered, "no prediction crossed a contact: the case is not exercised"
    for t, x in chattered:
        (solve,) = [s for s in solves if s[0] == t and np.array_equal(s[1], x)]
        assert solve[3] is not None


def test_the_models_flight_into_a_resting_contact_is_no_prediction():
    """A ball dropped 1 nm onto the floor bounces elastically about 60 times in one
    1/600 s step (more than sim.max_events_per_step): the model's step raises Zeno, and
    a prediction through it is None (no state to predict)."""
    from hmpc_cli.run.realtime import predict, prediction_plant
    from hmpc_cli.sim.simulator import ZenoError

    sc, _ = load_scenario(BALL, [])
    plant = prediction_plant(prepare(sc).plant)
    x = np.array([1.0, 0.1 + 1e-9, 0.0, 0.0])  # the centre 1 nm above the floor guard
    with pytest.raises(ZenoError):
        plant.step(0.0, x, 0, np.zeros(2), np.zeros(2), lambda ev: None, lambda: None)
    assert predict(plant, 0.0, x, 0, 0.02, lambda s: None) is None


def test_the_low_level_following_the_plan_across_impacts_keeps_the_ball_up(tmp_path):
    """The default controller (IPOPT, 10 Hz) with its compute time charged by the model
    and the first plan paused: holding the plan's pre-impact guard node until the next
    plan arrives loses the ball; following the plan's next domain from the contact keeps
    it on the plan (every later solve is warm and short)."""
    sets = ["sim.duration=3.0", 'sim.latency="model"', 'sim.latency_first="paused"']
    results = {}
    for past in ("hold", "next_domain"):
        results[past], log, _, _ = _run(tmp_path, past, [*sets, f'lowlevel.past_guard="{past}"'])
    assert not results["hold"].success and results["hold"].reason.startswith("final error 3.5")
    assert results["next_domain"].success and results["next_domain"].final_error < 1e-3
    assert results["next_domain"].solver_failures == 0
    # the summary says when holding mattered, and how to follow the plan instead
    assert results["hold"].warnings == [
        "after 10 of 10 contacts the low level held the plan's pre-impact guard node until "
        "a new plan arrived (lowlevel.past_guard = \"hold\"); \"next_domain\" follows the "
        "plan across the impact"]
    assert results["next_domain"].warnings == []


def test_a_contact_stops_the_solve_in_flight(tmp_path):
    """Biped, modelled latency, first plan paused: the MPC period's solve at 0.3 s is in
    flight when the swing foot lands at 0.3002 s. Without ``sim.preempt_at_contact`` the
    contact's foothold planning waits until that solve is done (0.372 s); with it the
    planning starts at the contact, the solve in flight is dropped and counted."""
    planned = {}
    for preempt in (False, True):
        sc, _ = load_scenario(ROOT / "scenarios" / "biped_stairs.toml", [
            "sim.duration=0.4", 'sim.latency="model"', 'sim.latency_first="paused"',
            f"sim.preempt_at_contact={str(preempt).lower()}"])
        result = run_to_log(prepare(sc), tmp_path / f"{preempt}.mcap")
        log = read_log(tmp_path / f"{preempt}.mcap")
        (contact,) = log.topic("/sim/event")
        assert contact.t == pytest.approx(0.3002, abs=1e-4)
        planned[preempt] = [p.t for p in log.topic("/planner/plan")][1]
        stopped = [w for w in result.warnings if "stopped by a contact" in w]
        assert stopped == (["1 solve in flight was stopped by a contact "
                            "(sim.preempt_at_contact; their plans dropped)"] if preempt else [])
        noted = [(s.t, s.data["reason"]) for s in log.topic("/mpc/solve")
                 if "stopped" in s.data["reason"]]
        # the solver had run 0.2 ms, under the model's overhead: no iteration of the solve in
        # flight was done, so its start is the next warm start, not its solution
        assert noted == ([(contact.t, "replan (after a contact stopped the solve of "
                           "t = 0.3000 s: dropped) (stopped at the contact: the solve of "
                           "t = 0.3000 s after 0 of 17 iterations, that iterate warm-starts "
                           "this one)")]
                         if preempt else [])
        assert result.real_time["preempted_solves"] == int(preempt)
    assert planned[True] == contact.t
    assert planned[False] == pytest.approx(0.372)


def test_ipopts_walking_mpc_does_not_climb_with_its_modelled_compute_time(tmp_path):
    """scenarios/biped_realtime.toml with the fitted model charged (IPOPT at 10 Hz, a budget
    of one period): from the second contact on each foothold replan (two or three
    candidates of 8-96 iterations) overruns the 0.1 s budget before its candidates
    finish: 5 of its 11 planner calls choose among the candidates that finished in time,
    4 find none finished and keep the schedule before them, and the walker trips at the
    top stair's riser; holding the guard node it scuffs the ground it lifted off from at
    the first step. The real-time iterations climb (tests/test_walking_stagewise.py)."""
    from hmpc_cli.run.layers import REVOKED_NOTE

    for past in ("next_domain", "hold"):
        sc, _ = load_scenario(ROOT / "scenarios" / "biped_realtime.toml", [
            'sim.latency="model"', f'lowlevel.past_guard="{past}"'])
        log = tmp_path / f"{past}.mcap"
        result = run_to_log(prepare(sc), log)
        assert result.success is False, result.reason
        if past == "hold":
            assert result.reason == ("fall: the swing foot is 10.32 mm inside the terrain "
                                     "at x = 0.734 m (driven into the ground it lifted off "
                                     "from before clearing it, deeper than 10 mm: it "
                                     "tripped)")
        if past == "next_domain":
            assert result.reason == ("fall: the swing foot is 14.60 mm inside the terrain "
                                     "at x = 1.600 m (no guard there, deeper than 1 mm: "
                                     "it tripped)")
            plans = [m.data for m in read_log(log).topic("/planner/plan")]
            assert [p["accepted"] for p in plans] == [True] * 3 + [False] + [True] * 3 + \
                [False, False, True, False]
            assert sum("chosen among those" in p["note"] for p in plans) == 5
            assert [p["note"] for p in plans if not p["accepted"]] == [REVOKED_NOTE] * 4
            assert result.planner_rejected == 4


def test_a_solve_never_started_within_the_budget_did_not_finish_whatever_its_iterations():
    """A replan's own solves finished in time only if their whole charge fitted: one the
    budget never started did not, even with 0 iterations (a warm start already optimal;
    a review found such a candidate chosen as finished)."""
    model = Latency("model", overhead=0.001, per_iteration=0.01, planner=0.02, budget=0.05)
    a, b, c = _plan(3, 9.0, t0=0.5), _plan(0, 9.0, t0=0.5), _plan(2, 9.0, t0=0.5)
    # the planner's 0.02 s, a's 0.031 s (over by 0.001 s), b's 0.001 s never started
    assert model.finished_in_time(b, _planned(7.0, a, b)) == [False, False]
    assert [k for _, k in model.stopped_solves(b, _planned(7.0, a, b))] == [2, 0]
    assert model.finished_in_time(a, _planned(7.0, c, a)) == [True, False]  # c: 0.021 s
    assert Latency("model", per_iteration=0.01).finished_in_time(
        a, _planned(7.0, c, a)) == [True, True]  # no budget


def test_the_budget_stops_each_charged_solve_where_it_ran_out():
    """The iterations each solve had finished when the budget ran out: the model's exact
    count, the solve's mean time per iteration otherwise; a replan's own solves in the
    order they ran after the planner's work, those after the budget never started."""
    model = Latency("model", overhead=0.001, per_iteration=0.01, planner=0.02, budget=0.05)
    plan = _plan(10, 9.0)
    assert [k for _, k in model.stopped_solves(plan)] == [4]  # 0.041 fits, 0.051 not
    a, b = _plan(3, 9.0, t0=0.5), _plan(5, 9.0, t0=0.5)
    # the planner's 0.02 s, then a (0.031 s: over by 0.001 s, 2 iterations fit), then b
    stops = model.stopped_solves(b, _planned(7.0, a, b))  # b is the planner's: not again
    assert [(p is a or p is b, k) for p, k in stops] == [(True, 2), (True, 0)]
    assert [k for _, k in model.stopped_solves(_plan(1, 9.0), _planned(7.0, a))] == [2, 0]
    measured = Latency("measured", budget=0.05)
    assert [k for _, k in measured.stopped_solves(_plan(10, 0.2), None, 0.125)] == [4]
    # a planner call of 0.03 s whose solve took 0.02 s: 0.01 s of its own, then its
    # solve (all 4 iterations fit: 0.03 s), then 0.04 s of the loop's own: 0.02 s left
    c = _plan(4, 0.02, t0=1.0)
    assert [k for _, k in measured.stopped_solves(_plan(8, 0.04, t0=1.0), _planned(0.03, c),
                                                  0.04)] == [4, 4]
    assert Latency("model", per_iteration=0.01).stopped_solves(plan) == []  # no budget


def test_a_solve_dropped_over_its_budget_warm_starts_the_next_from_its_iterate_there(
        tmp_path, monkeypatch):
    """A real solver stopped at its budget hands over the iterate it reached: the chain
    keeps the dropped solve's iterate after the iterations the budget let it finish
    (IPOPT's own iterate there) as the next warm start, not its whole solution; the
    model latency keeps the runs deterministic."""
    from hmpc_cli.mpc.chain.controller import ChainSolver
    from hmpc_cli.mpc.solver import SolverSession

    kept, stopped, stop_at = [], SolverSession.stopped, ChainSolver.stop_at

    def spy_stopped(self, k, *call):
        res = stopped(self, k, *call)
        kept.append([k, res])
        return res

    def spy_stop_at(self, plan, k):
        out = stop_at(self, plan, k)
        kept[-1].append((self._w.copy(), self._lam_g.copy(), plan))
        return out

    monkeypatch.setattr(SolverSession, "stopped", spy_stopped)
    monkeypatch.setattr(ChainSolver, "stop_at", spy_stop_at)
    overrides = ["sim.duration=0.35", 'sim.latency="model"', 'sim.latency_first="paused"',
                 "sim.latency_model.overhead=0.0", "sim.latency_model.per_iteration=0.01",
                 "sim.latency_model.planner=0.0", "sim.solve_budget=0.05"]
    _, log, _, _ = _run(tmp_path, "stopped", overrides)
    msgs = [m.data for m in read_log(log).topic("/mpc/solve")]
    dropped = [m for m in msgs if "over budget" in m["reason"]]
    assert len(dropped) >= 2 and len(kept) == len(dropped)
    assert {m["reason"].split()[0] for m in dropped} == {"period", "impact"}
    for m, (k, res, (w, lam_g, _)) in zip(dropped, kept, strict=True):
        assert k == 5 and res.stats.iterations == 5  # 5 x 0.01 s fit the 0.05 s budget
        assert res.stats.status == "User_Requested_Stop" and m["iterations"] > 5
        assert np.array_equal(w, res.x) and np.array_equal(lam_g, res.lam_g)
        why = m["reason"].split()[0]
        assert m["reason"] == (f"{why} (stopped at the budget: its solve after 5 of "
                               f"{m['iterations']} iterations, that iterate warm-starts the "
                               f"next solve) (over budget: dropped)")
    _, again, _, _ = _run(tmp_path, "stopped_again", overrides)

    def timeless(log):
        return [{k: v for k, v in m.data.items() if not k.endswith("wall_time")}
                for m in read_log(log).topic("/mpc/solve")]

    assert timeless(again) == timeless(log)


def test_the_stopped_iterate_is_ipopts_own_after_that_many_iterations():
    """SolverSession.stopped(k) hands over the iterate IPOPT reaches after k iterations
    from the same start: a session limited to k iterations reaches the same one, bit for
    bit, cold and warm."""
    import casadi as ca

    from hmpc_cli.mpc.solver import SolverSession, WarmStart

    x, p = ca.SX.sym("x", 3), ca.SX.sym("p")
    nlp = {"x": x, "p": p, "f": (x[0] - p) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2 +
           (1 - x[2]) ** 4, "g": ca.vertcat(x[0] + x[1] + x[2], x[0] * x[1])}
    call = (np.array([-1.2, 1.0, 0.0]), 1.0, np.full(3, -np.inf), np.full(3, np.inf),
            np.array([-10.0, -5.0]), np.array([2.0, 5.0]))
    warm = WarmStart(mu_init=1e-3, bound_push=1e-6)
    session = SolverSession("t", nlp, max_iter=100, warm=warm)
    full = session.run(*call)
    assert full.stats.success and full.stats.iterations > 6
    duals = (full.lam_x, full.lam_g)
    for start in ((), duals):
        n = session.run(*call, *start).stats.iterations
        for k in range(n):
            got = session.stopped(k, *call, *start)
            ref = SolverSession("m", nlp, max_iter=k, warm=warm).run(*call, *start)
            assert got.stats.iterations == k == ref.stats.iterations
            for a, b in ((got.x, ref.x), (got.lam_x, ref.lam_x), (got.lam_g, ref.lam_g)):
                assert np.array_equal(a, b)
    assert SolverSession("s", nlp, "sqpmethod", max_iter=5).stopped(2, *call) is None
    # Waechter and Biegler's example: IPOPT's restoration phase (iterations 5r-14r), where
    # CasADi calls the iteration callback more than once an iteration
    x = ca.SX.sym("x", 3)
    resto = {"x": x, "p": p, "f": x[0],
             "g": ca.vertcat(x[0] ** 2 - x[1] - 1, x[0] - x[2] - 0.5)}
    call = (np.array([-2.0, 1.0, 1.0]), 0.0, np.array([-np.inf, 0.0, 0.0]),
            np.full(3, np.inf), np.zeros(2), np.zeros(2))
    session = SolverSession("r", resto, max_iter=100)
    n = session.run(*call).stats.iterations
    assert n == 14
    for k in range(n + 1):
        got = session.stopped(k, *call)
        ref = SolverSession("m", resto, max_iter=k).run(*call)
        assert got.stats.iterations == k == ref.stats.iterations
        for a, b in ((got.x, ref.x), (got.lam_x, ref.lam_x), (got.lam_g, ref.lam_g)):
            assert np.array_equal(a, b)


def test_a_contact_before_the_budget_ran_out_stops_the_dropped_solve_earlier(tmp_path):
    """biped_realtime.toml, seed 4, modelled: the period solve of 0.594 s (34 iterations)
    is dropped over its 0.1 s budget (23 iterations fit), but the swing foot lands at
    0.5962 s and the contact stops the solver after 2.2 ms: no iteration (8.3 ms + 3.9
    ms would be 12.2 ms). That iterate (its start), not the budget's, warm-starts the
    contact's solve, and the solver was busy until the contact only. (The numbers are
    NumPy's Haswell kernels', which hmpc pins: with another machine's own kernels the
    solve took 128 iterations and the foot landed at 0.6051 s; tests/test_blas.py.)"""
    sc, _ = load_scenario(ROOT / "scenarios" / "biped_realtime.toml",
                          ['sim.latency="model"', "seed=4", "sim.duration=0.7"])
    loop = prepare(sc)
    run_to_log(loop, tmp_path / "r.mcap")
    reasons = {round(m.t, 4): m.data["reason"] for m in read_log(tmp_path / "r.mcap").topic(
        "/mpc/solve")}
    assert reasons[0.594] == ("period (stopped at the budget: its solve after 23 of 34 "
                              "iterations, that iterate warm-starts the next solve) (over "
                              "budget: dropped)")
    contact = next(t for t in reasons if 0.594 < t < 0.61)
    assert contact == 0.5962
    assert reasons[contact].startswith(
        "replan (stopped at the contact: the solve of t = 0.5940 s after 0 of 34 "
        "iterations, that iterate warm-starts this one)")


def test_a_planner_call_that_found_nothing_is_stopped_at_the_budget():
    """A planner call that finds no schedule keeps the solver busy for its charge, but no
    longer than sim.solve_budget, as a solve is stopped there (it was charged 0.26 s with a
    budget of 0.1 s, the next contact handled only then)."""
    clock = SolverClock(Latency("model", planner=0.01, budget=0.1))
    clock.busy(0.5, 0.26)
    assert not clock.free(0.599) and clock.free(0.6)
    unbounded = SolverClock(Latency("model", planner=0.01))
    unbounded.busy(0.5, 0.26)
    assert not unbounded.free(0.6) and unbounded.free(0.76)


def _budget_cut_replans(tmp_path: Path) -> tuple[list, dict, int]:
    """The /mpc/solve reasons of replans cut by a 0.01 s budget (biped_rti, 1.2 s), the
    run's summary and its adopted period solves; every one of those flies a schedule an
    accepted planner call chose."""
    sc, _ = load_scenario(ROOT / "scenarios" / "biped_rti.toml",
                          ["sim.solve_budget=0.01", "sim.duration=1.2"])
    log = tmp_path / "run.mcap"
    run_to_log(prepare(sc), log)
    chosen, cut, flown, planner = [], [], 0, {}
    for m in read_log(log).messages:
        d = m.data
        if m.topic == "/planner/plan":
            planner[d["t"]] = d
            if d["accepted"]:
                chosen.append(tuple(d["schedule"]["guards"]))
        elif m.topic == "/mpc/solve" and "budget)" in d["reason"]:
            assert not d["adopted"]
            cut.append((d["reason"], planner[d["t"]]))
        elif m.topic == "/mpc/solve" and d["adopted"] and d["reason"].startswith("period"):
            flown += 1
            guards = tuple(d["schedule"]["guards"])
            assert any(c[len(c) - len(guards):] == guards for c in chosen), (d["t"], guards)
        elif m.topic == "/run/summary":
            summary = d
    return cut, summary, flown


def test_a_replan_dropped_before_its_planner_finished_chooses_among_its_finished_solves(
        tmp_path):
    """The biped's foothold planner chooses by solving the walking MPC per candidate: a
    replan dropped over the budget before those solves finished never made its choice.
    The planner chooses again among the candidates that finished in time (``within``):
    its schedule, logged as the call's, is what the period solves after it fly (before
    2026-12-01 they flew the unfinished choice)."""
    from hmpc_cli.run.layers import OVER_BUDGET, WITHIN, WITHIN_NOTE

    cut, summary, flown = _budget_cut_replans(tmp_path)
    assert len(cut) == 3 and flown > 0
    for reason, call in cut:
        n, m, which = re.match(r"(\d+) of its (\d+) .*order they ran: ([\d, ]+)\)",
                               call["note"]).groups()
        done = [int(i) - 1 for i in which.split(", ")]
        assert 1 <= int(n) == len(done) < int(m) and call["accepted"] is True
        assert call["note"] == WITHIN_NOTE.format(n, m, which)
        assert reason.endswith(WITHIN.format(n, m) + OVER_BUDGET)
        # the logged choice is a finished candidate's
        segments = [c["segment"] for c in call["detail"]["candidates"]]
        assert len(segments) == int(m)
        assert call["schedule"]["guards"][0] in [segments[i] for i in done]
    assert summary["planner_rejected"] == 0


@pytest.mark.parametrize("within", ["none", "not among the finished"])
def test_a_replan_dropped_before_its_planner_finished_keeps_the_schedule_before_it(
        tmp_path, monkeypatch, within):
    """A planner that cannot choose among its finished solves (no ``within``), or whose
    ``within`` returns a schedule none of them had: the cut replan's schedule is dropped
    with it (the one before kept, the planner run again, the call rejected in the log and
    the summary)."""
    from hmpc_cli.planner.footholds import FootholdPlanner
    from hmpc_cli.run.layers import OVER_BUDGET, REVOKED, REVOKED_NOTE

    if within == "none":
        monkeypatch.delattr(FootholdPlanner, "within")
    else:  # its choice re-timed: the MPC can solve it, but no finished solve had it
        monkeypatch.setattr(FootholdPlanner, "within", lambda self, result, finished: replace(
            result, schedule=replace(result.schedule, durations=(0.123,))))
    cut, summary, flown = _budget_cut_replans(tmp_path)
    assert len(cut) > 10 and flown > 0
    for reason, call in cut:
        assert reason.endswith(REVOKED + OVER_BUDGET)
        assert call["accepted"] is False and call["note"] == REVOKED_NOTE
    assert summary["planner_rejected"] == len(cut)
