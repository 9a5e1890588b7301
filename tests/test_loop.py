"""Closed loop faults: solver failures, divergence; the log always closes cleanly."""

from pathlib import Path

import numpy as np
import pytest

from conftest import run_loop
from hmpc_cli.log.reader import read_log
from hmpc_cli.run.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]


def run(tmp_path, overrides):
    sc, _ = load_scenario(ROOT / "scenarios" / "ball.toml", overrides)
    result = run_loop(sc, tmp_path / "run.mcap")
    return result, read_log(tmp_path / "run.mcap")


@pytest.mark.slow
def test_solver_failures_are_counted_logged_and_survived(tmp_path):
    result, log = run(tmp_path, ["mpc.max_iter=2", "sim.duration=0.5"])
    solves = log.topic("/mpc/solve")
    failed = [m for m in solves if not m.data["success"]]
    assert result.t_end == 0.5 and not result.diverged
    assert result.solver_failures == len(failed) > 0
    assert sum(result.failure_statuses.values()) == len(failed)
    assert all(m.data["status"] for m in failed)
    # the loop kept commanding inputs from the shifted previous plan
    u = np.array([m.data["u"] for m in log.topic("/sim/state")])
    assert np.any(u != 0.0)
    assert log.complete


def test_divergence_ends_the_run_cleanly(tmp_path):
    result, log = run(tmp_path, ["sim.divergence_bound=3.0"])
    assert result.diverged and not result.success
    assert result.reason == ("diverged: |vx| 3.10059 > 3 (sim.divergence_bound) in mode "
                             "'outside'"), result.reason  # the largest state, its mode
    assert result.t_end < 3.0
    assert log.complete
    summary = log.topic("/run/summary")
    assert len(summary) == 1 and summary[0].data["diverged"] is True


def test_replanning_on_contact_replans_at_wall_and_floor_only(tmp_path):
    result, log = run(tmp_path, ["replanning.policy=\"on_contact\"", "sim.duration=1.0"])
    plans = log.topic("/planner/plan")
    events = log.topic("/sim/event")
    contacts = [e for e in events if e.data["guard_name"] in ("floor", "wall")]
    assert len(plans) == 1 + len(contacts)
    assert result.planner_calls == len(plans)
    for p in plans[1:]:
        assert p.data["reason"] == "contact"


def test_rejected_plans_are_retried_every_period_and_logged(tmp_path):
    # a planner that cannot reach the circle: one sample, zero mean, tiny variance
    result, log = run(tmp_path, ["planner.iterations=1", "planner.samples=1",
                                 "planner.init_mean=0.0", "planner.init_cov=1e-6",
                                 "sim.duration=0.5"])
    plans = log.topic("/planner/plan")
    events = log.topic("/sim/event")
    # t = 0, every MPC period (0.1 s) until the end, and after each contact
    assert result.planner_calls == len(plans) == 1 + 4 + len(events)
    assert result.planner_rejected == len(plans)
    retry_times = sorted(round(p.t, 6) for p in plans if p.data["reason"] == "retry")
    assert retry_times == [0.1, 0.2, 0.3, 0.4]
    assert all(not p.data["accepted"] and "no schedule yet" in p.data["note"] for p in plans)
    assert result.solves == 0 and not result.diverged


def test_the_plant_differs_from_the_model_only_where_the_scenario_says(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    same, log_a = run(tmp_path / "a", ["sim.duration=0.4"])
    heavy, log_b = run(tmp_path / "b", ["sim.duration=0.4", "plant.drag=0.2"])
    xa = np.array([list(m.data["x"].values()) for m in log_a.topic("/sim/state")])
    xb = np.array([list(m.data["x"].values()) for m in log_b.topic("/sim/state")])
    assert np.array_equal(xa[0], xb[0]) and not np.allclose(xa[-1], xb[-1])
    # the controllers keep the model: the first plans are identical
    pa, pb = log_a.topic("/mpc/solve")[0].data, log_b.topic("/mpc/solve")[0].data
    assert pa["plan"] == pb["plan"]


def test_the_logged_input_is_the_one_the_plant_applies(tmp_path):
    """A [plant] input box narrower than the model's: /sim/state.u is the input the plant
    applied (its box), not the model's saturation of the command (it logged -100 while the
    plant pushed with -50)."""
    result, log = run(tmp_path, ["sim.duration=0.3", "plant.u_outside=[-50.0, 0.0]"])
    ux = np.array([m.data["u"]["ux"] for m in log.topic("/sim/state")
                   if m.data["mode_name"] == "outside"])
    assert len(ux) > 10 and ux.min() == -50.0 and np.all(ux <= 0.0)


@pytest.mark.parametrize("react,contacts", [("hold", 0), ("recompute", 1)])
def test_zeno_ends_the_run_where_the_log_and_the_counts_do(tmp_path, react, contacts):
    """More events in a step than allowed: the run ends at the step's start (hold: none of
    its events happened) or after the last event handled (recompute: its contact is logged
    and counted, so the run ended after it, not at the step's start before the bounce);
    one /sim/state sample per time, the last one the run's end state."""
    result, log = run(tmp_path, ["sim.duration=0.2", "system.x0=[0.3, 0.3, -10.0, -10.0]",
                                 "sim.max_events_per_step=1", "planner.iterations=1",
                                 f'sim.input_at_events="{react}"'])
    assert result.reason == ("zeno: more than 1 guard event in one step of 0.00166667 s "
                             "(Zeno chattering)")
    events, states = log.topic("/sim/event"), log.topic("/sim/state")
    assert result.contacts == len(events) == contacts
    times = [m.data["t"] for m in states]
    assert len(set(times)) == len(times) and times[-1] == result.t_end
    assert list(states[-1].data["x"].values()) == list(result.x_end)
    if contacts:
        assert result.t_end == events[-1].data["t"] > 0.02
        assert list(result.x_end) == list(events[-1].data["x_after"].values())
    else:
        assert result.t_end == pytest.approx(0.02)


def test_a_schedule_the_nlp_cannot_hold_is_rejected_not_fatal(tmp_path):
    # the nominal plan crosses 3 guards; an NLP chain for 1 switch cannot hold it
    result, log = run(tmp_path, ["mpc.max_switches=1", "sim.duration=0.3"])
    assert result.t_end == pytest.approx(0.3) and not result.diverged
    assert result.planner_rejected == result.planner_calls >= 2
    notes = [m.data["note"] for m in log.topic("/planner/plan")]
    assert all("raise mpc.max_switches" in n and "no schedule yet" in n for n in notes)
    assert not log.topic("/mpc/solve")  # nothing to solve without a schedule


@pytest.mark.parametrize("duration", ["0.25", "0.255"])
def test_the_last_state_sample_holds_the_last_steps_input_reference_and_disturbance(
        tmp_path, duration):
    """The sample at the run's end (on the log grid or off it) repeats what was applied
    over the last simulator step: no zero input, no reference equal to the state, no
    disturbance that never acted."""
    from hmpc_cli.run.runner import prepare, run_to_log

    sc, _ = load_scenario(ROOT / "scenarios" / "ball_disturbed.toml",
                          [f"sim.duration={duration}", "disturbance.trial=7"])
    loop = prepare(sc)
    steps, command = [], loop.plant.command

    def spy(t, x, mode, plan, span):
        u, x_ref = command(t, x, mode, plan, span)
        steps.append((t, u, x_ref, loop.plant.disturbance(t)))
        return u, x_ref

    loop.plant.command = spy
    run_to_log(loop, tmp_path / "r.mcap")
    last = read_log(tmp_path / "r.mcap").topic("/sim/state")[-1].data
    t, u, x_ref, w = steps[-1]
    assert last["t"] == pytest.approx(float(duration)) and t < last["t"]
    assert list(last["u"].values()) == u.tolist() and np.any(u != 0.0)
    assert list(last["x_ref"].values()) == x_ref.tolist()
    assert list(last["w"].values()) == w.tolist()


@pytest.mark.parametrize("react", ["recompute", "hold"])
def test_a_stop_while_the_stack_handles_a_contact_ends_the_run_after_it(
        tmp_path, monkeypatch, react):
    """A stop signal that arrives as the first contact is handled (its re-solve at the
    event time with ``recompute``, the step's end with ``hold``): the summary counts that
    contact and ends at or after it, in the state after its reset, and is the log's last
    message (it ended before the contact, in the state before it, counting it)."""
    import signal

    from hmpc_cli.core import signals
    from hmpc_cli.run.layers import MPCLayers

    real = MPCLayers.on_event

    def on_event(self, ev):
        signals._STATE.signum = int(signal.SIGTERM)  # as the handler records it
        real(self, ev)

    monkeypatch.setattr(MPCLayers, "on_event", on_event)
    sc, _ = load_scenario(ROOT / "scenarios" / "ball.toml",
                          [f"sim.input_at_events={react!r}", "sim.duration=1.0"])
    try:
        with pytest.raises(signals.Interrupted):
            run_loop(sc, tmp_path / "run.mcap")
    finally:
        signals.reset()
    log = read_log(tmp_path / "run.mcap")
    events = log.topic("/sim/event")
    summary = log.topic("/run/summary")
    assert len(events) == 1 and len(summary) == 1
    event, end = events[0].data, summary[0].data
    assert end["reason"] == "interrupted (SIGTERM)"
    assert end["contacts"] == 1 and end["t_end"] >= event["t"]
    if react == "recompute":  # stopped at the event itself
        assert end["t_end"] == event["t"] and end["x_end"] == event["x_after"]
    assert max(m.log_time_ns for m in log.messages) == summary[0].log_time_ns
    assert log.topic("/sim/state")[-1].data["t"] == end["t_end"]
