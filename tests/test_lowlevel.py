"""The low level's feed-forward: the held input gives the plant the plan's impulse."""

from __future__ import annotations

import numpy as np
import pytest

from hmpc_cli.lowlevel import LowLevelController, LowLevelSettings
from hmpc_cli.core.messages import ModeSchedule, Plan, SolveStats, Trajectory
from hmpc_cli.core.registry import build_system
from hmpc_cli.systems.ball import BallParams


def _plan(t0: float, seed: int, hold: str) -> Plan:
    """A two-domain plan of the ball: 12 nodes in mode 0, then 5 after a reset."""
    rng = np.random.default_rng(seed)
    t = np.concatenate([np.linspace(0.0, 0.55, 12), np.linspace(0.55, 0.8, 5)])
    return Plan(t0, Trajectory(t, rng.normal(size=(17, 4)), rng.normal(size=(17, 2)) * 10,
                               np.r_[np.zeros(12, int), np.ones(5, int)],
                               np.r_[np.zeros(12, int), np.ones(5, int)], (0,), hold),
                SolveStats("ok", True, 1, 0.0, 0.0, 0.0), ModeSchedule((0, 1), (0,), (0.55,), t0))


def _mean_input(plan: Plan, a: float, b: float) -> np.ndarray:
    """Mean over [a, b] (plan time) of the first domain's input, by dense quadrature."""
    tr = plan.traj
    ts, us = tr.t[:12], tr.u[:12]
    grid = np.linspace(a, b, 20001)
    if tr.input_hold == "zoh":
        k = np.clip(np.searchsorted(ts, grid, side="right") - 1, 0, 11)
        vals = us[k]
    else:
        vals = np.column_stack([np.interp(grid, ts, us[:, j]) for j in range(2)])
    return np.trapezoid(vals, grid, axis=0) / (b - a)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_held_input_is_the_plan_input_mean_over_the_step(hold):
    ctl = LowLevelController(build_system(BallParams()), LowLevelSettings())
    plans = [_plan(1.0, 0, hold), _plan(1.0, 1, hold)]
    for t in (1.0, 1.013, 1.2501, 1.53, 1.6):  # alternating plans: each gets its own numbers
        for plan in (plans[0], plans[1], plans[0]):
            span = min(1 / 600, 1.55 - t) if t < 1.55 else 1 / 600
            _, u_ff = ctl.reference(t, plan, span)
            a = t - plan.t0
            if a + span <= 0.55:
                np.testing.assert_allclose(u_ff, _mean_input(plan, a, a + span), rtol=1e-6,
                                           atol=1e-6)
            else:  # past the domain's last node: its last input is held
                assert np.all(np.isfinite(u_ff))
    x_ref, _ = ctl.reference(1.3, plans[1], 0.0)
    k = np.searchsorted(plans[1].traj.t[:12], 0.3) - 1
    w = (0.3 - plans[1].traj.t[k]) / (plans[1].traj.t[k + 1] - plans[1].traj.t[k])
    np.testing.assert_allclose(x_ref, (1 - w) * plans[1].traj.x[k] + w * plans[1].traj.x[k + 1])


def _x_at(plan: Plan, nodes: slice, tau: float) -> np.ndarray:
    """The plan's state at plan time tau, interpolated over the given nodes."""
    tr = plan.traj
    return np.array([np.interp(tau, tr.t[nodes], tr.x[nodes, j]) for j in range(4)])


def test_past_the_guard_the_reference_holds_or_follows_the_plans_next_domain():
    """``past_guard``: 'hold' keeps to the plan's first domain after a contact (its guard
    node held past the planned 0.55 s); 'next_domain' tracks the
    plan's domain after its guard, re-timed to start at the contact (0.04 s before the
    planned 0.55 s here); contacts at or before the plan's start and contacts through a
    guard the plan does not schedule next leave the reference on its first domain."""
    system = build_system(BallParams())
    plan = _plan(1.0, 2, "foh")
    hold = LowLevelController(system, LowLevelSettings())
    follow = LowLevelController(system, LowLevelSettings(past_guard="next_domain"))
    for ctl in (hold, follow):
        ctl.contact(0.7, 1)  # before the plan started: not its guard event
        ctl.contact(1.0, 0)  # at its start: the plan was solved after it
        ctl.contact(1.51, 0)  # the plan's guard, planned at 1.55
    for t in (1.2, 1.5099):  # before the contact both track domain 0
        for ctl in (hold, follow):
            np.testing.assert_allclose(ctl.reference(t, plan)[0],
                                       _x_at(plan, slice(0, 12), t - 1.0))
    for t in (1.51, 1.6, 1.75):
        np.testing.assert_allclose(hold.reference(t, plan)[0],  # on time, then held
                                   _x_at(plan, slice(0, 12), t - 1.0))
        x_ref, u_ff = follow.reference(t, plan)
        tau = 0.55 + (t - 1.51)
        np.testing.assert_allclose(x_ref, _x_at(plan, slice(12, 17), tau))
        np.testing.assert_allclose(
            u_ff, [np.interp(tau, plan.traj.t[12:], plan.traj.u[12:, j]) for j in range(2)])
    other = LowLevelController(system, LowLevelSettings(past_guard="next_domain"))
    other.contact(1.51, 1)  # a guard the plan does not schedule: held as with 'hold'
    np.testing.assert_allclose(other.reference(1.6, plan)[0], plan.traj.x[11])
    assert hold.reference(1.75, plan)[0].tolist() == plan.traj.x[11].tolist()


def test_at_a_node_time_the_reference_is_that_node_and_the_held_input_switches_to_it():
    """Node times are exact: the reference state is the node's, bit for bit; a zero-order
    hold is continuous from the right (the node's input at its time, the one before
    just ahead of it); before the first node and after the last the ends are held."""
    ctl = LowLevelController(build_system(BallParams()), LowLevelSettings())
    for hold in ("zoh", "foh"):
        plan = _plan(0.0, 3, hold)
        tr = plan.traj
        for k in (1, 5, 10):
            x_ref, u_ff = ctl.reference(float(tr.t[k]), plan)
            assert x_ref.tolist() == tr.x[k].tolist() and u_ff.tolist() == tr.u[k].tolist()
            _, u_before = ctl.reference(float(np.nextafter(tr.t[k], 0.0)), plan)
            if hold == "zoh":
                assert u_before.tolist() == tr.u[k - 1].tolist()
        assert ctl.reference(-0.1, plan)[0].tolist() == tr.x[0].tolist()
        x_end, u_end = ctl.reference(0.6, plan)  # past domain 0's last node (0.55 s)
        assert x_end.tolist() == tr.x[11].tolist() and u_end.tolist() == tr.u[11].tolist()
        # a step over the last node (0.54 to 0.56 s): half of it before, half held after
        before = tr.u[10] if hold == "zoh" else tr.u[10] + 0.9 * (tr.u[11] - tr.u[10])
        np.testing.assert_allclose(ctl.reference(0.54, plan, 0.02)[1],
                                   0.5 * (before + tr.u[11]), rtol=1e-12)


def test_a_float32_plan_is_tracked_in_float64_as_the_same_plan_cast():
    """A plug-in may hand over a float32 plan: the low level computes in float64."""
    ctl = LowLevelController(build_system(BallParams()), LowLevelSettings())
    plan = _plan(0.0, 4, "foh")
    tr = plan.traj
    narrow = Plan(0.0, Trajectory(tr.t.astype(np.float32), tr.x.astype(np.float32),
                                  tr.u.astype(np.float32), tr.mode, tr.seg, tr.guards,
                                  tr.input_hold), plan.stats, plan.schedule)
    wide = Plan(0.0, Trajectory(*(a.astype(np.float32).astype(float)
                                  for a in (tr.t, tr.x, tr.u)), tr.mode, tr.seg, tr.guards,
                                tr.input_hold), plan.stats, plan.schedule)
    for t, span in ((0.123, 0.01), (0.3, 0.0), (0.549, 0.002)):
        got, want = ctl.reference(t, narrow, span), ctl.reference(t, wide, span)
        assert [g.dtype for g in got] == [np.float64, np.float64]
        assert [g.tolist() for g in got] == [w.tolist() for w in want]
