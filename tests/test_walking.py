"""The biped's walking MPC (two swings, inverse dynamics) and the foothold candidates."""

import math
from dataclasses import replace

import numpy as np
import pytest

from hmpc_cli.lowlevel import LowLevelController, LowLevelSettings
from hmpc_cli.core.messages import ModeSchedule, Plan, SolveStats, Trajectory
from hmpc_cli.mpc.walking.kind import WalkingMPC
from hmpc_cli.mpc.walking.nlp import WalkingMPCSettings
from hmpc_cli.planner.footholds import FootholdPlanner, FootholdSettings, candidates, choose
from hmpc_cli.systems.biped import BipedParams, Stair, build_biped, make_biped_model, stair_edges

P = BipedParams()
SYS = build_biped(P)
MODEL = make_biped_model(P)
SEGMENT = 1  # the 1.0 m segment (guard stair_2)
TOL = 1e-6


def arr(v) -> np.ndarray:
    return np.asarray(v, dtype=float).ravel()


@pytest.fixture(scope="module")
def mpc() -> WalkingMPC:
    return WalkingMPC(SYS, WalkingMPCSettings())


@pytest.fixture(scope="module")
def plan(mpc) -> Plan:
    return mpc.solve_segment(0.0, build_biped(P).x0, SEGMENT, 0.0)


def terrain_under(x: float) -> float:
    """Highest true (unsmoothed) terrain height at x [m] (edges count both sides)."""
    heights = [P.ground_height] if x <= 0.0 else []
    heights += [h for a, b, h in stair_edges(P) if a <= x <= b]
    return max(heights)


# ------------------------------------------------------------ the fixed-mode plan


def test_plan_from_the_reference_state_solves(plan, mpc):
    st = plan.stats
    assert st.success, st.status
    assert st.max_violation <= TOL
    assert np.isfinite(st.cost) and st.iterations > 0 and st.wall_time > 0.0
    tr, n = plan.traj, mpc.nlp.N
    assert tr.x.shape == (2 * n + 2, 12) and tr.u.shape == (2 * n + 2, 5)
    assert tr.guards == (SEGMENT,) and plan.schedule.guards == (SEGMENT,)
    assert list(tr.seg) == [0] * (n + 1) + [1] * (n + 1)
    assert (tr.mode == 0).all()
    assert tr.t[n] == tr.t[n + 1] == pytest.approx(WalkingMPCSettings().swing_time)
    assert np.all(np.diff(tr.t) >= 0.0)
    assert tr.x[0] == pytest.approx(build_biped(P).x0, abs=1e-12)


def test_plan_satisfies_every_constraint_recomputed_from_the_trajectory(plan, mpc):
    s, m, n = mpc.s, MODEL, mpc.nlp.N
    tr = plan.traj
    umax = P.torque_limit - s.torque_margin
    start, end, height = stair_edges(P)[SEGMENT]
    for j in range(2):
        rows = np.arange(n + 1) + j * (n + 1)
        t, x, u = tr.t[rows], tr.x[rows], tr.u[rows]
        for k in range(n):
            dt = t[k + 1] - t[k]
            q, qd, qn, qdn = x[k, :5], x[k, 5:10], x[k + 1, :5], x[k + 1, 5:10]
            a = (qdn - qd) / dt
            # semi-implicit Euler and the inverse-dynamics torque
            assert np.abs(qn - q - dt * qdn).max() <= TOL
            assert arr(m.inverse_dynamics(q, qd, a, 0)) == pytest.approx(u[k], abs=1e-5)
            assert np.abs(u[k]).max() <= umax + TOL
            assert (x[k + 1, 10:] == x[0, 10:]).all()  # stance foot fixed in a swing
        for k in range(1, n + 1):
            knee_y = np.asarray(m.points(x[k, :5]))[1, [1, 4]]  # stance, swing knee
            assert knee_y.min() >= s.knee_clearance - TOL
        for k in range(n + 1):
            assert np.abs(x[k, 5:10]).max() <= P.rate_limit + TOL
            assert P.stance_knee_range[0] - TOL <= x[k, 1] <= P.stance_knee_range[1] + TOL
            assert P.torso_range[0] - TOL <= x[k, 2] <= P.torso_range[1] + TOL
            if j == 0 and k == n:
                continue
            fx, fy = arr(m.swing_foot_world(x[k]))
            assert fy >= terrain_under(fx) - TOL, (j, k, fx, fy)
        apex = s.apex_node
        fx, fy = arr(m.swing_foot_world(x[apex]))
        assert fy >= terrain_under(fx) + s.apex_clearance - TOL
    # touchdown: the virtual pass-through node, then the reset map
    fx, fy = arr(m.swing_foot_world(tr.x[n]))
    assert fy == pytest.approx(height - s.touchdown_depth, abs=TOL)
    assert start + s.segment_margin - TOL <= fx <= end - s.segment_margin + TOL
    assert tr.x[n + 1] == pytest.approx(arr(m.reset(tr.x[n])), abs=TOL)
    assert plan.detail.touchdown == pytest.approx((fx, fy))
    assert plan.detail.final_hip == pytest.approx(arr(m.hip_world(tr.x[-1])))
    # the robot moves towards the goal
    assert plan.detail.final_hip[0] > arr(m.hip_world(tr.x[0]))[0] + 0.5


def test_low_level_tracks_the_first_swing_only(plan, mpc):
    ll = LowLevelController(build_biped(P), LowLevelSettings(kp=700.0, kd=10.0))
    n = mpc.nlp.N
    x_ref, u_ff = ll.reference(0.0, plan)
    assert x_ref == pytest.approx(plan.traj.x[0]) and u_ff == pytest.approx(plan.traj.u[0])
    x_ref, u_ff = ll.reference(plan.traj.t[-1], plan)
    assert x_ref == pytest.approx(plan.traj.x[n])  # holds the pre-impact node


def test_warm_resolve_after_a_shift_needs_fewer_iterations(plan, mpc):
    k = 8
    t, x = float(plan.traj.t[k]), plan.traj.x[k]
    warm = mpc.solve_segment(t, x, SEGMENT, elapsed=t)
    cold = WalkingMPC(SYS, mpc.s, nlp=mpc.nlp).solve_segment(t, x, SEGMENT, elapsed=t)
    assert warm.stats.success and cold.stats.success
    assert warm.detail.warm == "primal-dual" and cold.detail.warm == "cold"
    assert warm.stats.iterations < cold.stats.iterations
    assert warm.stats.cost == pytest.approx(cold.stats.cost, rel=1e-4)
    assert warm.traj.t[mpc.nlp.N] == pytest.approx(mpc.s.swing_time - t)


def test_second_candidate_of_a_step_starts_from_the_first(mpc):
    """Cold candidates of one planning step: the second starts from the first's solution
    ("neighbour") and reaches the optimum a cold start reaches, in fewer iterations."""
    x0 = build_biped(P).x0
    fresh = WalkingMPC(SYS, mpc.s, nlp=mpc.nlp)
    first = fresh.solve_segment(0.0, x0, SEGMENT - 1)
    second = fresh.solve_segment(0.0, x0, SEGMENT)
    cold = WalkingMPC(SYS, mpc.s, nlp=mpc.nlp).solve_segment(0.0, x0, SEGMENT)
    assert first.detail.warm == "cold" and cold.detail.warm == "cold"
    assert second.detail.warm == "neighbour"
    assert second.stats.success and cold.stats.success
    assert second.stats.iterations < cold.stats.iterations / 2
    assert second.stats.cost == pytest.approx(cold.stats.cost, rel=1e-6)
    np.testing.assert_allclose(second.traj.x, cold.traj.x, atol=1e-5)
    # another state: no neighbour, a cold start
    other = fresh.solve_segment(0.0, x0 + 1e-3, SEGMENT + 1)
    assert other.detail.warm == "cold"


def test_next_swing_after_touchdown_starts_from_the_executed_plan(plan, mpc):
    n = mpc.nlp.N
    x_post = plan.traj.x[n + 1]
    cold = WalkingMPC(SYS, mpc.s, nlp=mpc.nlp).solve_segment(0.3, x_post, SEGMENT, 0.0)
    mpc.solve_segment(0.0, build_biped(P).x0, SEGMENT, 0.0)
    mpc.on_impact(SEGMENT)
    nxt = mpc.solve_segment(0.3, x_post, SEGMENT, 0.0)
    assert nxt.stats.success and cold.stats.success
    assert nxt.detail.warm == "primal-dual"
    assert nxt.stats.iterations < cold.stats.iterations
    assert nxt.detail.touchdown[0] > plan.detail.touchdown[0] + 0.2
    # liftoff: the new swing foot (old stance foot) accelerates upwards at once
    m = MODEL
    x0 = nxt.traj.x[0]
    qdd = arr(m.forward_dynamics(x0[:5], x0[5:10], nxt.traj.u[0], 0))
    jdot_qd = (arr(m.swing_foot_velocity(x0[:5] + 1e-7 * x0[5:10], x0[5:10]))
               - arr(m.swing_foot_velocity(x0[:5] - 1e-7 * x0[5:10], x0[5:10]))) / 2e-7
    acc = np.asarray(m.swing_foot_jacobian(x0[:5])) @ qdd + jdot_qd
    assert acc[1] >= mpc.s.liftoff_accel - 1e-3


# ----------------------------------------------------------------- failures


def test_failures_are_reported_not_raised():
    mpc = WalkingMPC(SYS, WalkingMPCSettings(max_iter=1, segment_margin=0.11))
    out = mpc.solve_segment(0.0, build_biped(P).x0, 3, 0.0)  # the top stair, 1.6 m away
    assert not out.stats.success
    assert out.stats.status == "Maximum_Iterations_Exceeded"
    assert out.stats.max_violation > 1e-3
    assert out.traj.x.shape == (2 * mpc.nlp.N + 2, 12)
    assert mpc._memory == {}  # nothing to warm-start from
    short = mpc.solve_segment(0.0, build_biped(P).x0, 2, 0.0)  # 0.2 m < 2 x 0.11 m
    assert not short.stats.success  # named by its guard, not its 0-based index
    assert short.stats.status == ("error: segment stair_3 (0.2 m) is shorter than 0.22 m, "
                                  "twice the segment margin")


def test_non_finite_state_fails_cleanly(mpc):
    x = build_biped(P).x0.copy()
    x[6] = np.nan
    out = mpc.solve_segment(0.0, x, SEGMENT, 0.0)
    assert not out.stats.success and out.stats.status.startswith("error")
    assert out.stats.max_violation == math.inf
    with pytest.raises(IndexError):
        mpc.solve_segment(0.0, build_biped(P).x0, 7, 0.0)


def test_settings_reject_unknown_keys_and_a_late_apex():
    with pytest.raises(ValueError):
        WalkingMPCSettings(apex_nodee=3)
    with pytest.raises(ValueError, match="apex_node"):
        WalkingMPCSettings(apex_node=25)


def test_floor_is_the_inflated_terrain(mpc):
    floor, m = mpc.nlp.floor, mpc.s.terrain_margin
    assert floor(0.2) == pytest.approx(0.0, abs=1e-9)
    assert floor(0.9) == pytest.approx(0.075, abs=1e-9)
    assert floor(0.4 - m - 0.03) == pytest.approx(0.0, abs=1e-3)
    assert floor(0.4 - m + 0.03) == pytest.approx(0.075, abs=1e-3)
    assert floor(np.array([0.2, 0.9])) == pytest.approx([0.0, 0.075], abs=1e-9)


# ---------------------------------------------------------------- footholds

EDGES = stair_edges(P)  # Figure 4: [0, .4] h 0, [.4, 1.4] .075, [1.4, 1.6] .125, [1.6, 2.85] .175


@pytest.mark.parametrize("x, expected", [
    (0.0, [0, 1]),          # start: the ground segment and the 1.0 m segment
    (0.716, [1]),           # first touchdown: segment 0 lies behind
    (1.21, [1, 2, 3]),      # second touchdown: the 0.2 m segment may be skipped
    (1.66, [3]),            # on the top segment
    (2.7, [3]),             # near the end
])
def test_candidates_on_the_figure_4_course(x, expected):
    assert candidates(x, EDGES) == expected


def test_candidates_reference_rule_and_errors():
    ref = FootholdSettings(ahead_only=False, include_current=False)
    assert candidates(0.716, EDGES, ref) == [0, 1]
    assert candidates(1.21, EDGES, ref) == [1, 2, 3]
    long = stair_edges(BipedParams(stairs=[Stair(length=3.0, height=0.0),
                                           Stair(length=1.0, height=0.1)]))
    assert candidates(1.5, long) == [0]  # the segment under the foot
    with pytest.raises(ValueError, match="no foothold candidate"):
        candidates(1.5, long, FootholdSettings(include_current=False))
    with pytest.raises(ValueError, match="stairs span"):
        candidates(3.5, EDGES)


def _fake(success: bool, hip_x: float, cost: float) -> Plan:
    tr = Trajectory(np.zeros(1), np.full((1, 12), hip_x), np.zeros((1, 5)), np.zeros(1, int),
                    np.zeros(1, int))  # its "hip x": every state entry, read by hip_x
    return Plan(0.0, tr, SolveStats("x", success, 1, 0.0, cost, 0.0),
                ModeSchedule((0, 0), (0,), (0.3,)))


def hip_x(plan: Plan) -> float:
    return float(plan.traj.x[-1, 0])


def test_choose_keeps_the_largest_final_hip_x_among_successes():
    plans = [_fake(True, 1.0, 5.0), _fake(False, 3.0, 1.0), None, _fake(True, 1.5, 9.0)]
    assert choose(plans, hip_x=hip_x) == 3
    assert choose(plans, FootholdSettings(criterion="min_cost")) == 0
    assert choose([_fake(False, 1.0, 1.0), None], hip_x=hip_x) is None
    assert choose([], hip_x=hip_x) is None
    assert choose([replace(plans[0]), plans[0]], hip_x=hip_x) == 0  # ties keep the first
    with pytest.raises(ValueError, match="max_hip_x criterion needs hip_x"):
        choose(plans)


def test_the_foothold_planner_chooses_within_the_candidates_that_finished():
    """A solve budget stopped some candidates: the best of the finished ones is kept
    (the budget's anytime choice); none finished: no schedule, and the note says so."""
    planner = FootholdPlanner(SYS, FootholdSettings(criterion="min_cost"))
    costs, plans = [5.0, 2.0, 3.0], []

    def solve(schedule):  # the candidates in the order the planner solves them
        plans.append(replace(_fake(True, 1.0, costs[len(plans)]), schedule=schedule))
        return plans[-1]

    x = SYS.x0.copy()
    x[10] = 1.3  # stance x: three candidate segments within reach
    full = planner.plan(0.2, x, 0, solve)
    assert len(plans) == 3 and full.schedule is plans[1].schedule
    cut = planner.within(full, [True, False, True])
    assert cut.schedule is plans[2].schedule and cut.cost == 3.0 and cut.note == ""
    assert cut.trajectory is plans[2].traj and cut.detail == full.detail
    assert cut.mpc_solves == full.mpc_solves
    none = planner.within(full, [False, False, False])
    assert none.schedule is None and none.trajectory is None
    assert none.note == "no candidate solved in time (0 of 3 finished)"


def test_walking_mpc_behind_the_contract(mpc):
    """A schedule without a target guard is rejected; the loop's solve of the schedule a
    foothold planner has just chosen reuses that solve; an event restarts the swing."""
    from hmpc_cli.core.messages import GuardEvent

    walker = WalkingMPC(SYS, mpc.s, nlp=mpc.nlp)
    x0 = SYS.x0
    empty = ModeSchedule.final(0)
    assert "no foothold target" in walker.check(empty)
    rejected = walker.solve(0.0, x0, 0, empty)
    assert not rejected.adopt and rejected.stats.status.startswith("schedule rejected")
    sched = ModeSchedule((0, 0), (SEGMENT,), (math.nan,), 0.0)
    first = walker.solve(0.0, x0, 0, sched)
    assert first.stats.success and first.adopt
    assert walker.solve(0.0, x0, 0, first.schedule).stats is first.stats  # not solved again
    later = walker.solve(0.1, first.traj.x[8], 0, first.schedule)
    assert later.detail.elapsed == pytest.approx(0.1)
    ev = GuardEvent(0.25, SEGMENT, 0, 0, first.traj.x[25], first.traj.x[26])
    after = walker.solve(0.25, ev.x_after, 0, sched, [ev])
    assert after.detail.elapsed == 0.0 and after.detail.warm == "primal-dual"
    again = walker.solve(0.35, ev.x_after, 0, sched, [ev])  # the event applies once
    assert again.detail.elapsed == pytest.approx(0.1)


def test_a_solve_stopped_at_its_budget_leaves_its_iterate_as_the_warm_start():
    """A solve dropped over the solve budget: its target's memory (the next warm start)
    is IPOPT's iterate after the iterations the budget let it finish (0: the memory
    before it), and the plant executes the plan it had."""
    mpc = WalkingMPC(SYS, WalkingMPCSettings())
    x0 = build_biped(P).x0
    sched = ModeSchedule((0, 0), (SEGMENT,), (0.4,), 0.0)
    first = mpc.solve(0.0, x0, 0, sched)
    assert first.adopt and mpc._executing == SEGMENT
    t1, x1 = first.traj.t[3], first.traj.x[3]
    second = mpc.solve(t1, x1, 0, sched)
    assert second.stats.iterations >= 2
    call = mpc._step[SEGMENT][0]
    ref = mpc.nlp.session.stopped(1, *call[:8])  # deterministic: the same iterate again
    assert mpc.stop_at([(first, 0)]) == []  # not a solve of this step
    assert mpc.stop_at([(second, 1)]) == [(second, 1)]
    assert np.array_equal(mpc._memory[SEGMENT].w, ref.x)
    assert np.array_equal(mpc._memory[SEGMENT].lam_g, ref.lam_g)
    assert not np.array_equal(ref.x, mpc.nlp.session.run(*call[:8]).x)
    assert mpc._executing == SEGMENT and mpc._memory[SEGMENT].x0 is call[8]
    stopped = mpc._memory[SEGMENT]
    third = mpc.solve(first.traj.t[4], first.traj.x[4], 0, sched)
    assert mpc.stop_at([(third, 0)]) == [(third, 0)]  # never started: the memory before
    assert mpc._memory[SEGMENT] is stopped
    fresh = WalkingMPC(SYS, WalkingMPCSettings())
    dropped = fresh.solve(0.0, x0, 0, sched)
    assert fresh.stop_at([(dropped, 0)]) == [(dropped, 0)]
    assert fresh._memory == {} and fresh._executing is None
