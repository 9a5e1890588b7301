"""Fixed-mode MPC: constraint satisfaction, reset nodes, node shifting."""

import numpy as np
import pytest

from hmpc_cli.core.messages import ModeSchedule
from hmpc_cli.mpc.chain.controller import ChainSolver
from hmpc_cli.mpc.chain.layout import FLOW, HOLD, RESET, ChainLayout, NodeSchedule
from hmpc_cli.mpc.chain.nlp import MPCSettings
from hmpc_cli.planner.cem import CEMSettings, CrossEntropyPlanner
from hmpc_cli.systems.ball import BallParams, build_ball

BALL_MEAN = -20.0  # the ball plug-in's CEM initial mean (its default)


@pytest.fixture(scope="module")
def ball():
    return build_ball(BallParams())


@pytest.fixture(scope="module")
def planned(ball):
    planner = CrossEntropyPlanner(ball, CEMSettings(init_mean=BALL_MEAN, iterations=6))
    result = planner.plan(0.0, ball.x0, 0)
    assert result.reached_final
    return result


@pytest.fixture(scope="module")
def mpc(ball):
    return ChainSolver(ball, MPCSettings(horizon=1.5, max_switches=6))


def test_solved_plan_satisfies_every_constraint_and_reset_map(ball, planned, mpc):
    ns = NodeSchedule.from_schedule(planned.schedule, mpc.nlp.N, mpc.nlp.dt)
    mpc.set_schedule(ns, planned.trajectory)
    plan = mpc.reoptimize(0.0, ball.x0)
    assert plan.stats.success, plan.stats.status
    nlp, lay = mpc.nlp, mpc.layout
    p, lbx, ubx, lbg, ubg = nlp.problem_data(ns, lay, ball.x0)
    w = mpc.solution
    g = nlp.constraints(w, p)
    assert np.all(g >= lbg - 1e-6) and np.all(g <= ubg + 1e-6)
    assert np.all(w >= lbx - 1e-6) and np.all(w <= ubx + 1e-6)
    num = ball.numeric
    for k in np.nonzero(lay.link_type == RESET)[0]:
        gi = int(lay.link_guard[k])
        z_guard, z_next = w[nlp.z_idx[k]], w[nlp.z_idx[k + 1]]
        assert abs(num.gap(gi, z_guard[None])[0]) < 1e-6, "guard node on its guard"
        assert num.active(gi, z_guard[None])[0]
        np.testing.assert_allclose(z_next, num.reset(gi, z_guard[None])[0], atol=1e-6)
        # virtual pass-through node: one more interval of the source flow is past the guard
        # by the whole tube margin
        u_virtual = w[nlp.u_idx[k]]
        mode = int(lay.link_mode[k])
        x_v = ball.numeric.rk4[mode](z_guard[None], u_virtual[None],
                                     np.zeros((1, 2)), np.array([[nlp.dt]]))[0]
        assert num.gap(gi, x_v)[0] <= -mpc.s.tube_margin + 1e-6
    # tightened guard-avoid on every regular node before its guard
    for k in range(1, lay.last + 1):
        if lay.first_after_reset[k] or lay.link_type[min(k, nlp.L - 1)] == RESET:
            continue
        j = lay.seg[k]
        for gi in ball.guards_of(ns.modes[j]):
            margin = 0.0 if j > 0 and gi == ns.guards[j - 1] else mpc.s.tube_margin
            assert num.gap(gi, w[nlp.z_idx[k]][None])[0] >= margin - 1e-6


def test_layout_roles(mpc):
    ns = NodeSchedule((0, 0, 1), (1, 2), (5, 4, mpc.nlp.N - 9))
    lay = ChainLayout.build(ns, mpc.nlp.L)
    assert list(lay.link_type[:5]) == [FLOW] * 5 and lay.link_type[5] == RESET
    assert lay.link_guard[5] == 1 and lay.link_type[10] == RESET and lay.link_guard[10] == 2
    assert lay.last == mpc.nlp.N + 2
    assert np.all(lay.link_type[lay.last:] == HOLD)
    assert lay.first_after_reset[6] and lay.first_after_reset[11]


@pytest.mark.parametrize("rate, nodes_per_second, moved", [(10, 60, 6), (20, 60, 3),
                                                           (100, 100, 1)])
def test_node_shifting_moves_the_elapsed_nodes(rate, nodes_per_second, moved):
    s = MPCSettings(rate_hz=rate, nodes_per_second=nodes_per_second)
    assert s.nodes_per_period == moved
    n = s.n_intervals
    ns = NodeSchedule((0, 0, 1), (0, 2), (20, 15, n - 35))
    shifted, k = ns.shift(s.nodes_per_period)
    assert k == moved
    assert shifted.counts == (20 - moved, 15, n - 35 + moved)
    assert shifted.n_intervals == n
    # a domain whose guard is overdue keeps one node before its guard
    late = NodeSchedule((0, 1), (2,), (2, n - 2)).shift(6)[0]
    assert late.counts == (1, n - 1)
    # in the final domain nothing moves (receding horizon)
    assert NodeSchedule((1,), (), (n,)).shift(6)[0].counts == (n,)


def test_node_shifting_on_impact():
    ns = NodeSchedule((0, 0, 1), (0, 2), (7, 15, 158))
    after = ns.on_impact()
    assert after.modes == (0, 1) and after.guards == (2,)
    assert after.counts == (15, 165)
    assert after.on_impact().counts == (180,)
    with pytest.raises(ValueError):
        after.on_impact().on_impact()


def test_schedule_rounding_and_horizon_check():
    sched = ModeSchedule((0, 0, 1), (0, 2), (0.1, 0.2505))
    ns = NodeSchedule.from_schedule(sched, 180, 1 / 60)
    assert ns.counts == (6, 16, 158)
    with pytest.raises(ValueError, match="horizon"):
        NodeSchedule.from_schedule(ModeSchedule((0, 1), (2,), (3.5,)), 180, 1 / 60)


def test_warm_start_resolve_after_shift_is_fast_and_feasible(ball, planned, mpc):
    ns = NodeSchedule.from_schedule(planned.schedule, mpc.nlp.N, mpc.nlp.dt)
    mpc.set_schedule(ns, planned.trajectory)
    first = mpc.reoptimize(0.0, ball.x0)
    assert first.stats.success
    moved = mpc.shift(3)
    assert moved == 3
    second = mpc.reoptimize(0.05, first.traj.x[3])
    assert second.stats.success
    assert second.stats.iterations <= first.stats.iterations
    np.testing.assert_allclose(second.traj.x[0], first.traj.x[3])
