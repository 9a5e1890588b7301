"""NLP back-ends of the fixed-mode MPC: SQP + Gauss-Newton + HPIPM and fatrop against
IPOPT on the same problems, the IPOPT fallback, and the closed loop."""

from dataclasses import replace

import numpy as np
import pytest

from hmpc_cli.core.messages import Plan
from hmpc_cli.mpc.backends import OCPStructure, rti_step_kept, rti_success
from hmpc_cli.mpc.chain.controller import ChainSolver
from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule
from hmpc_cli.mpc.chain.nlp import FixedModeNLP, MPCSettings
from hmpc_cli.planner.cem import CEMSettings, CrossEntropyPlanner
from hmpc_cli.log.books import RunBooks
from hmpc_cli.run.scenario import ScenarioError, load_scenario
from hmpc_cli.systems.ball import BallParams, build_ball

SMALL = {"horizon": 1.5, "max_switches": 6, "input_hold": "zoh"}


@pytest.fixture(scope="module")
def ball():
    return build_ball(BallParams())


@pytest.fixture(scope="module")
def problems(ball):
    """Recorded IPOPT problems and solutions: {"switching": ..., "final": ...}.

    Each: (solve arguments (w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0), IPOPT's
    SolveResult). The switching one is the warm re-solve one MPC period after the first
    solve; the final-domain one starts after the planned impacts (primal warm start).
    """
    planned = CrossEntropyPlanner(ball, CEMSettings(init_mean=-20.0, horizon=1.5)).plan(
        0.0, ball.x0, 0)
    mpc = ChainSolver(ball, MPCSettings(**SMALL))
    ns = NodeSchedule.from_schedule(planned.schedule, mpc.N, mpc.dt)
    mpc.set_schedule(ns, planned.trajectory)
    first = mpc.reoptimize(0.0, ball.x0)
    assert first.stats.success and len(ns.guards) > 0
    out = {}
    mpc.shift(6)
    x_next = first.traj.x[6]
    out["switching"] = _record(mpc, x_next, duals=True)
    while len(mpc.node_schedule.guards):
        mpc.on_impact()
    out["final"] = _record(mpc, mpc.solution[mpc.nlp.z_idx[0]], duals=False)
    return out


def _record(mpc: ChainSolver, x0: np.ndarray, duals: bool):
    nlp = mpc.nlp
    p, lbx, ubx, lbg, ubg = nlp.problem_data(mpc.node_schedule, mpc.layout, x0)
    w0 = mpc.solution.copy()
    w0[nlp.z_idx[0]] = x0
    lam = (mpc._lam_x, mpc._lam_g) if duals else (None, None)
    args = (w0, p, lbx, ubx, lbg, ubg, *lam)
    res = nlp.optimize(*args)
    assert res.stats.success, res.stats.status
    return args, res


def _nlp(ball, which: str, **settings) -> FixedModeNLP:
    s = MPCSettings(**SMALL, **settings)
    return FixedModeNLP(ball, s, switches=0 if which == "final" else None)


def test_ocp_structure_describes_both_nlps(ball):
    """The HPIPM stage structure counts every variable and row of either NLP."""
    for which in ("final", "switching"):
        nlp = _nlp(ball, which)
        st = nlp.structure()
        assert st.sizes() == (nlp.nx_var, nlp.ng)
        assert st.nu[-1] == 0 and st.nx[-1] == 0  # the trailing empty stage
    with pytest.raises(ValueError, match="nu"):
        OCPStructure((4, 4), (2, 1), (0, 0))


@pytest.mark.parametrize("which", ["final", "switching"])
@pytest.mark.parametrize("solver", ["sqp_hpipm", "fatrop"])
def test_backend_reaches_ipopts_optimum(ball, problems, which, solver):
    """Each back-end, converged, on IPOPT's recorded problem: same cost and plan."""
    args, ref = problems[which]
    nlp = _nlp(ball, which, solver=solver, switching_solver=solver, max_sqp_iter=200)
    lam = args[6:] if solver == "sqp_hpipm" else (None, None)
    res = nlp.optimize(*args[:6], *lam)
    assert res.stats.success and not res.stats.fallback, res.stats.status
    assert res.stats.max_violation < 1e-6
    # the back-ends' slacks differ in their last digits (x the 1e4 penalty per node):
    # compare the costs without the penalty term
    assert _unpenalized(nlp, res) == pytest.approx(_unpenalized(nlp, ref), rel=1e-6)
    np.testing.assert_allclose(res.x[nlp.z_idx], ref.x[nlp.z_idx], atol=2e-3)
    np.testing.assert_allclose(res.x[nlp.u_idx], ref.x[nlp.u_idx], atol=5e-2)


def _unpenalized(nlp: FixedModeNLP, res) -> float:
    """The cost without its slack penalty (the cost is taken with the slacks in bounds)."""
    return res.stats.cost - nlp.s.soft_penalty * float(np.sum(np.maximum(res.x[nlp.s_idx], 0.0)))


def test_real_time_iterations_accept_a_feasible_point_only():
    assert rti_success("Solve_Succeeded", True, 1.0)
    assert rti_success("Maximum_Iterations_Exceeded", False, 1e-9)
    assert not rti_success("Maximum_Iterations_Exceeded", False, 1e-3)
    assert not rti_success("Search_Direction_Becomes_Too_Small", False, 0.0)


def test_a_real_time_iteration_keeps_every_finite_step():
    assert rti_step_kept("Solve_Succeeded", True, 1.0)
    assert rti_step_kept("Maximum_Iterations_Exceeded", False, 1e-3)
    assert not rti_step_kept("Maximum_Iterations_Exceeded", False, float("inf"))
    assert not rti_step_kept("QP solver failed", False, 0.0)


@pytest.mark.parametrize("which", ["final", "switching"])
def test_one_real_time_iteration_is_one_full_step_kept(ball, problems, which):
    """rti on IPOPT's recorded problem: warm-started (multipliers given), one SQP step,
    kept although it has not converged, no fallback, and repeated from its own result it
    moves toward the optimum; cold (a new plan's first solve), up to RTI_COLD_ITER steps."""
    from hmpc_cli.mpc.solver_table import RTI_COLD_ITER

    args, ref = problems[which]
    nlp = _nlp(ball, which, solver="rti", switching_solver="rti", max_sqp_iter=1)
    lam = args[6:] if args[6] is not None else (np.zeros(len(args[2])), np.zeros(len(args[4])))
    first = nlp.optimize(*args[:6], *lam)
    assert first.stats.success and not first.stats.fallback
    assert first.stats.iterations == 1
    x, lam = first.x, (first.lam_x, first.lam_g)
    for _ in range(4):
        res = nlp.optimize(x, *args[1:6], *lam)
        assert res.stats.iterations <= 1  # 0: converged already (the final-domain QP)
        x, lam = res.x, (res.lam_x, res.lam_g)
    ref_z = ref.x[nlp.z_idx]
    assert np.abs(x[nlp.z_idx] - ref_z).max() < np.abs(args[0][nlp.z_idx] - ref_z).max()
    cold = nlp.optimize(*args[:6], None, None)
    assert cold.stats.success and 1 <= cold.stats.iterations <= RTI_COLD_ITER


@pytest.mark.parametrize("which", ["final", "switching"])
def test_the_warm_rti_instance_reuses_the_cold_ones_derivatives_bit_for_bit(ball, problems,
                                                                            which):
    """The warm instance is given the cold one's nlp_jac_fg and Hessian (no second
    symbolic generation at start-up): its steps equal those of a warm sqpmethod that
    generated its own, bit for bit."""
    import casadi as ca

    from hmpc_cli.mpc.buffered import BufferedSolver
    from hmpc_cli.mpc.solver import derivatives_of

    args, _ = problems[which]
    nlp = _nlp(ball, which, solver="rti", switching_solver="rti", max_sqp_iter=1)
    session = nlp.session
    shared = derivatives_of(session.cold, "sqpmethod")
    assert set(shared) == {"jac_fg", "hess_lag"}
    own = BufferedSolver(ca.nlpsol("own", "sqpmethod", session._nlp,
                                   {**session.options, "max_iter": 1}))
    lam_x = np.zeros(len(args[2])) if args[6] is None else args[6]
    lam_g = np.zeros(len(args[4])) if args[7] is None else args[7]
    inputs = dict(x0=args[0], p=args[1], lbx=args[2], ubx=args[3], lbg=args[4], ubg=args[5],
                  lam_x0=lam_x, lam_g0=lam_g)
    ours, ref = session.warm(**inputs), own(**inputs)
    assert all(np.array_equal(ours[k], ref[k]) for k in ("x", "f", "g", "lam_x", "lam_g"))


def test_failed_backend_solve_falls_back_to_ipopt_and_is_counted(ball, problems):
    """HPIPM cut to one iteration fails every QP: IPOPT solves instead, counted."""
    args, ref = problems["final"]
    nlp = _nlp(ball, "final", solver="sqp_hpipm",
               solver_options={"hpipm": {"iter_max": 1}})
    res = nlp.optimize(*args)
    assert res.stats.fallback and res.stats.success
    assert "fallback" in res.stats.status
    assert res.stats.cost == pytest.approx(ref.stats.cost, rel=1e-6)
    books = RunBooks("ball", 0)
    ns = NodeSchedule((ball.mode_index(ball.final_mode),), (), (nlp.N,))
    traj = nlp.trajectory(res.x, ns, ChainLayout.build(ns, nlp.L))
    for stats in (res.stats, replace(res.stats, fallback=False)):
        books.count_solve(0.0, Plan(0.0, traj, stats, None))
    assert books.result.fallbacks == 1 and books.result.solver_failures == 0


def test_sqp_backend_needs_stagewise_dynamics():
    with pytest.raises(ScenarioError, match=r'mpc: solver "sqp_hpipm" needs stage-wise'):
        load_scenario("scenarios/ball.toml", ['mpc.solver="sqp_hpipm"'])
    sc, _ = load_scenario("scenarios/ball.toml", ['mpc.solver="sqp_hpipm"',
                                                  'mpc.input_hold="zoh"'])
    assert sc.mpc.solver_of(0) == "sqp_hpipm" and sc.mpc.solver_of(10) == "ipopt"


@pytest.mark.slow
def test_sqp_closed_loop_matches_ipopt():
    """Figure 3, trial 5 (zero-order hold): same outcome with either back-end."""
    from hmpc_cli.run.runner import prepare, run_unlogged

    out = {}
    for solver in ("ipopt", "sqp_hpipm"):
        sc, _ = load_scenario("scenarios/ball_disturbed.toml", [
            'mpc.input_hold="zoh"', f'mpc.solver="{solver}"'])
        out[solver] = run_unlogged(prepare(sc))
    ipopt, sqp = out["ipopt"], out["sqp_hpipm"]
    assert sqp.success == ipopt.success
    assert (sqp.contacts, sqp.solves, sqp.solver_failures) == \
        (ipopt.contacts, ipopt.solves, ipopt.solver_failures)
    # both 0.0638601717 m; they differ by 4.8e-10 m
    assert ipopt.final_error == pytest.approx(0.0638601717, abs=1e-8)
    assert sqp.final_error == pytest.approx(ipopt.final_error, abs=1e-7)
    assert ipopt.fallbacks == 0
