"""Physics of the hybrid simulator: exact event times, energy, guard penetration, Zeno."""

import numpy as np
import pytest

from hmpc_cli.sim.simulator import HybridSimulator, ZenoError
from hmpc_cli.systems.ball import BallParams, build_ball

G = 9.81
R = 0.1


def free_ball(**kw):
    return build_ball(BallParams(drag=0.0, **kw))


def simulate(system, x0, mode, duration, rate, u=None, w=None):
    sim = HybridSimulator(system)
    x, m = np.array([x0], dtype=float), np.array([mode])
    u = np.zeros((1, 2)) if u is None else np.asarray(u, dtype=float)[None]
    w = np.zeros((1, 2)) if w is None else np.asarray(w, dtype=float)[None]
    h = 1.0 / rate
    events, states = [], [x[0].copy()]
    for i in range(int(round(duration * rate))):
        res = sim.step(x, m, u, w, h)
        events += [(i * h + e.tau, e) for e in res.events]
        x, m = res.x, res.mode
        states.append(x[0].copy())
    return np.array(states), events, m[0]


@pytest.mark.parametrize("rate", [600, 100, 37])
def test_free_bounce_event_times_match_closed_form(rate):
    y0 = 2.0
    states, events, _ = simulate(free_ball(), [0.5, y0, 0.0, 0.0], 0, 4.0, rate)
    t_fall = np.sqrt(2.0 * (y0 - R) / G)
    expected = t_fall + 2.0 * t_fall * np.arange(len(events))
    times = np.array([t for t, _ in events])
    assert len(events) == int((4.0 - t_fall) // (2 * t_fall)) + 1
    assert np.max(np.abs(times - expected)) < 1e-9
    for _, e in events:
        assert e.x_before[1] == pytest.approx(R, abs=1e-9)
        assert e.x_after[3] == pytest.approx(-e.x_before[3])


def test_energy_preserved_across_elastic_resets():
    # oblique bounces on floor and wall, no drag, no input: E = |v|^2 / 2 + g y
    states, events, _ = simulate(free_ball(), [1.5, 1.5, -4.0, 1.0], 0, 3.0, 600)
    kinds = {e.guard for _, e in events}
    assert kinds == {0, 1}, "both floor and wall must be hit"
    energy = 0.5 * np.sum(states[:, 2:] ** 2, axis=1) + G * states[:, 1]
    assert np.max(np.abs(energy - energy[0])) < 1e-8 * abs(energy[0])
    for _, e in events:
        assert np.linalg.norm(e.x_after[2:]) == pytest.approx(np.linalg.norm(e.x_before[2:]),
                                                              rel=1e-14)


def test_no_state_past_an_active_guard():
    system = build_ball(BallParams())
    rng = np.random.default_rng(3)
    num = system.numeric
    for _ in range(5):
        u = rng.uniform(-100, 0, size=2)
        w = rng.uniform(-10, 10, size=2)
        states, events, _ = simulate(system, [1.0, 1.0, 0.0, 0.0], 0, 1.0, 600, u=u, w=w)
        assert events, "the pushed ball must hit something"
        outside = np.linalg.norm(states[:, :2] - 3.0, axis=1) > 1.0
        for g in (0, 1):
            gaps = num.gap(g, states[outside])
            act = num.active(g, states[outside])
            assert np.all(gaps[act] > -1e-9)


def test_guard_at_level_does_not_refire_after_reset():
    # start exactly on the floor moving up: the floor must not fire
    states, events, _ = simulate(free_ball(), [0.5, R, 0.0, 3.0], 0, 0.1, 600)
    assert events == []
    assert states[-1][1] > R


def test_inactive_region_lets_the_ball_pass():
    # the floor only exists for x in [0, 8]: beyond it the ball falls through
    states, events, _ = simulate(free_ball(), [9.0, 0.5, 0.0, 0.0], 0, 1.0, 600)
    assert events == []
    assert states[-1][1] < 0.0


def test_circle_crossing_switches_mode_with_identity_reset():
    system = free_ball(gravity=0.0)
    states, events, mode = simulate(system, [1.5, 3.0, 2.0, 0.0], 0, 0.5, 600)
    assert [e.guard for _, e in events] == [system.guard_index("circle_in")]
    t, e = events[0]
    assert t == pytest.approx(0.25, abs=1e-9)
    assert np.array_equal(e.x_before, e.x_after)
    assert system.modes[mode].name == "inside"


def test_several_events_in_one_step_and_zeno_cap():
    system = free_ball(gravity=0.0)
    sim = HybridSimulator(system, max_events=10)
    # corner shot: wall then floor inside one coarse step
    x = np.array([[0.12, 0.13, -2.0, -2.0]])
    res = sim.step(x, np.array([0]), np.zeros((1, 2)), np.zeros((1, 2)), 0.05)
    assert [e.guard for e in res.events] == [1, 0]
    assert res.events[0].tau == pytest.approx(0.01, abs=1e-10)
    assert res.events[1].tau == pytest.approx(0.015, abs=1e-10)
    assert res.x[0, 2] > 0 and res.x[0, 3] > 0
    # a ball pinned to the floor by a huge push: Zeno chattering is an error
    sim = HybridSimulator(build_ball(BallParams(drag=0.0, u_outside=(-1e6, 0.0))), max_events=3)
    with pytest.raises(ZenoError):
        for _ in range(50):
            x0 = np.array([[4.0, R + 1e-4, 0.0, -1e-3]])
            sim.step(x0, np.array([0]), np.array([[0.0, -1e6]]), np.zeros((1, 2)), 0.1)


def test_batch_matches_single_samples():
    system = build_ball(BallParams())
    sim = HybridSimulator(system)
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(0.3, 2, 8), rng.uniform(0.3, 2, 8), rng.normal(0, 3, (8, 2))])
    u = rng.uniform(-100, 0, (8, 2))
    w = np.zeros((8, 2))
    mode = np.zeros(8, dtype=int)
    batch = sim.step(x, mode, u, w, 0.05)
    for b in range(8):
        single = sim.step(x[b:b + 1], mode[b:b + 1], u[b:b + 1], w[b:b + 1], 0.05)
        assert np.array_equal(single.x[0], batch.x[b])
