"""The fixed-mode NLP's transcription against the plant, its soft constraints, and the
final domain's own NLP."""

import numpy as np
import pytest

from hmpc_cli.lowlevel import LowLevelController, LowLevelSettings
from hmpc_cli.core.messages import Plan
from hmpc_cli.mpc.chain.controller import ChainSolver
from hmpc_cli.mpc.chain.layout import NodeSchedule
from hmpc_cli.mpc.chain.nlp import MPCSettings
from hmpc_cli.planner.cem import CEMSettings, CrossEntropyPlanner
from hmpc_cli.sim.simulator import HybridSimulator
from hmpc_cli.systems.ball import BallParams, build_ball
from conftest import nlp_function_calls

BALL_MEAN = -20.0  # the ball plug-in's CEM initial mean (its default)

SIM_RATE = 600


@pytest.fixture(scope="module")
def ball():
    return build_ball(BallParams())


@pytest.fixture(scope="module")
def planned(ball):
    planner = CrossEntropyPlanner(ball, CEMSettings(init_mean=BALL_MEAN, horizon=1.5))
    return planner.plan(0.0, ball.x0, 0)


def _solve(ball, planned, **settings) -> tuple[ChainSolver, Plan]:
    mpc = ChainSolver(ball, MPCSettings(horizon=1.5, max_switches=6, **settings))
    ns = NodeSchedule.from_schedule(planned.schedule, mpc.N, mpc.dt)
    mpc.set_schedule(ns, planned.trajectory)
    plan = mpc.reoptimize(0.0, ball.x0)
    assert plan.stats.success, plan.stats.status
    return mpc, plan


def _plant_error(ball, plan: Plan, feedforward: str) -> float:
    """Largest distance between the undisturbed plant, fed forward the plan's inputs by
    the low level (no feedback), and the plan's nodes before its first guard node."""
    sim = HybridSimulator(ball)
    low = LowLevelController(ball, LowLevelSettings(feedforward=feedforward))
    tr = plan.traj
    guard_node = int(np.nonzero(tr.seg == 0)[0][-1])
    steps = int(round(tr.t[guard_node] * SIM_RATE)) - 1  # stop just before the guard
    h = 1.0 / SIM_RATE
    x, mode, err = ball.x0.copy(), np.array([0]), 0.0
    for i in range(steps):
        u, _ = low.command(i * h, x, plan, h)
        res = sim.step(x[None], mode, u[None], np.zeros((1, 2)), h)
        x, mode = res.x[0], res.mode
        t = (i + 1) * h
        k = np.nonzero(np.isclose(tr.t[: guard_node], t, atol=1e-12))[0]
        if k.size:
            err = max(err, float(np.max(np.abs(x - tr.x[k[0]]))))
    return err


def test_undisturbed_plant_follows_the_first_order_hold_plan(ball, planned):
    _, plan = _solve(ball, planned)
    assert plan.traj.input_hold == "foh"
    # what is left is RK4 at the node step (60 Hz) against RK4 at the simulator's 600 Hz
    assert _plant_error(ball, plan, "plan") < 2e-4
    # the same plan fed forward with a zero-order hold drifts away: the test can fail
    assert _plant_error(ball, plan, "zoh") > 1e-2


def test_zero_order_hold_transcription_matches_a_zoh_low_level(ball, planned):
    _, plan = _solve(ball, planned, input_hold="zoh")
    assert plan.traj.input_hold == "zoh"
    assert _plant_error(ball, plan, "plan") < 2e-4


def test_soft_constraints_change_nothing_when_the_hard_problem_is_feasible(ball, planned):
    _, soft = _solve(ball, planned)
    _, hard = _solve(ball, planned, soft_penalty=0.0)
    assert soft.stats.slack < 1e-6 and hard.stats.slack == 0.0
    # same optimum up to the solver's tolerance (and the barrier's ~1e-10 slacks x penalty)
    np.testing.assert_allclose(soft.traj.x, hard.traj.x, atol=1e-3)
    np.testing.assert_allclose(soft.stats.cost, hard.stats.cost, rtol=1e-3)


@pytest.mark.slow
def test_an_unreachable_guard_time_is_softened_not_failed(ball, planned):
    # the wall 0.05 s after rest at (1, 1): 0.9 m away, unreachable with |u| <= 100
    ns = NodeSchedule((0, 0, 1), (1, 2), (3, 40, 47))
    results = {}
    for penalty in (0.0, 1e4):
        mpc = ChainSolver(ball, MPCSettings(horizon=1.5, max_switches=6,
                                            soft_penalty=penalty, max_iter=300))
        mpc.set_schedule(ns)
        results[penalty] = mpc.reoptimize(0.0, ball.x0).stats
    assert not results[0.0].success
    soft = results[1e4]
    assert soft.success, soft.status
    assert soft.slack > 0.1  # the wall node is far from the wall: reported, not hidden
    assert soft.max_violation < 1e-6


def test_final_domain_nlp_solves_the_same_problem(ball):
    x0 = np.array([3.5, 3.2, 1.0, -0.5])
    plans = []
    for own in (True, False):
        mpc = ChainSolver(ball, MPCSettings(horizon=1.5, max_switches=6,
                                            final_domain_nlp=own))
        mpc.set_schedule(NodeSchedule((1,), (), (mpc.N,)))
        assert (mpc.nlp.S == 0) is own
        plan = mpc.reoptimize(0.0, x0)
        assert plan.stats.success, plan.stats.status
        plans.append(plan)
    assert plans[0].traj.x.shape == plans[1].traj.x.shape
    np.testing.assert_allclose(plans[0].traj.x, plans[1].traj.x, atol=1e-3)
    np.testing.assert_allclose(plans[0].stats.cost, plans[1].stats.cost, rtol=1e-3)


def test_switching_to_the_final_domain_nlp_keeps_the_plan_as_warm_start(ball, planned):
    mpc, plan = _solve(ball, planned)
    for _ in range(len(mpc.node_schedule.guards)):
        mpc.on_impact()
    assert mpc.nlp is mpc.nlps.final
    # the primal guess carried over is the old plan's final-domain part
    last = plan.traj.x[-1]
    guess = mpc.solution[mpc.nlp.z_idx[0]]
    assert np.all(np.isfinite(guess))
    np.testing.assert_allclose(mpc.solution[mpc.nlp.z_idx[-1]], last, atol=1e-9)


def test_fatrop_solves_the_zero_order_hold_problem_like_ipopt(ball, planned):
    _, ipopt = _solve(ball, planned, input_hold="zoh")
    _, fatrop = _solve(ball, planned, input_hold="zoh", solver="fatrop")
    np.testing.assert_allclose(fatrop.traj.x, ipopt.traj.x, atol=1e-3)
    with pytest.raises(ValueError, match="zoh"):
        MPCSettings(solver="fatrop")


def _path_rows_written_out(nlp, b, k, z, flows, sk):
    """Node k's path rows written out from the parameter vector, as the NLP's docstring
    states them."""
    import casadi as ca

    P, q, G, switching = nlp._par, nlp._q, nlp.G, nlp.S > 0
    qz = {i: q[i](z) for i in (range(G) if switching else nlp.row_guards)}
    b.rows("guard_avoid", [P["s"][k, c] * qz[i] - P["kappa"][k, c] + sk
                           for c, i in enumerate(nlp.row_guards)])
    if not switching:
        return
    b.rows("guard_hit", sum(P["hit"][k, i] * qz[i] for i in range(G)) - sk, shape=())
    virt = 0
    for i in range(G):
        virt += P["beta"][k, i] * (-q[i](flows[nlp._src[i]]))
    b.rows("virtual_node", virt - P["kappa_v"][k] + sk, shape=())
    reg = ca.SX.zeros(nlp.R)
    for i in range(G):
        reg += P["beta"][k, i] * nlp._regions[i](z)
    if nlp.R:
        b.rows("region", reg + sk)


def _transcription_written_out(nlp):
    """The NLP and its layout with every operation written out at each node, as the
    NLP's module docstring states it (the reference the staged transcription must
    reproduce instruction for instruction)."""
    import casadi as ca

    from hmpc_cli.mpc.builder import NLPBuilder

    b, zs, us, sigmas = NLPBuilder(), [], [], []
    L, m, sysm, switching = nlp.L, nlp.m, nlp.system, nlp.S > 0
    for k in range(L + 1):
        with b.stage(k):
            zs.append(b.variable("z", nlp.n))
            if k < L:
                us.append(b.variable("u", m))
            sigmas.append(b.variable("sigma"))
    nlp._par = P = nlp._parameters(b)
    nlp._guard_functions()
    J = 0
    for k in range(L):
        foh = nlp.s.input_hold == "foh" and k + 1 < L
        u_end = us[k] + P["foh"][k] * (us[k + 1] - us[k]) if foh else us[k]
        flows = [nlp._interval_expr(i, zs[k], us[k], u_end) for i in nlp.modes_in]
        nxt = P["e"][k] * zs[k]
        for c in range(nlp.M):
            nxt += P["a"][k, c] * flows[c]
        for i, g in enumerate(sysm.guards if switching else ()):
            nxt += P["b"][k, i] * g.reset(zs[k])
        with b.stage(k):
            b.rows("dynamics", zs[k + 1] - nxt)
            _path_rows_written_out(nlp, b, k, zs[k], flows, sigmas[k])
        J += P["w"][k] * sysm.stage_cost(zs[k], us[k]) + P["v"][k] * ca.sumsqr(us[k])
    last_flows = [nlp._interval_expr(i, zs[L], ca.DM.zeros(m), ca.DM.zeros(m))
                  for i in nlp.modes_in] if switching else []
    with b.stage(L):
        _path_rows_written_out(nlp, b, L, zs[L], last_flows, sigmas[L])
    if nlp.T:
        b.rows("terminal", sysm.terminal_set(zs[L]) + sigmas[L])
    return b.build(J + nlp.s.soft_penalty * ca.sum1(ca.vertcat(*sigmas)))


def _graphs(nlp) -> list:
    """The serialized (x, p) -> (f, g) and the layout of the staged transcription and of
    the written-out one."""
    import casadi as ca

    out = []
    for transcribe in (type(nlp)._transcription, _transcription_written_out):
        x, layout = transcribe(nlp)
        out.append((ca.Function("nlp", [x["x"], x["p"]], [x["f"], x["g"]]).serialize(),
                    layout.to_dict()))
    return out


def _lag_system():
    """Two modes of a first-order lag (time constant 0.1 s) whose Euler step at 10 nodes/s
    cancels the state: flows of negated terms, which CasADi simplifies (-(-a) = a)."""
    import casadi as ca

    from hmpc_cli.core.hybrid import Guard, HybridSystem, Mode

    x, u, w = ca.SX.sym("x", 2), ca.SX.sym("u", 1), ca.SX.sym("w", 0)
    f = ca.Function("f", [x, u, w], [ca.vertcat(x[1], (-u[0] - x[1]) / 0.1)])

    def fn(name, e):
        return ca.Function(name, [x], [e])

    return HybridSystem(
        name="lag", state_names=("p", "a"), input_names=("u",), disturbance_names=(),
        modes=(Mode("A", f, (-1.0,), (1.0,)), Mode("B", f, (-1.0,), (1.0,))),
        guards=(Guard("g0", "A", "B", fn("h0", x[1]), 0.0, -1, reset=fn("R", x)),
                Guard("g1", "A", "B", fn("h1", x[0]), 1.0, +1, reset=fn("R", x))),
        initial_mode="A", final_mode="B", x0=np.zeros(2), goal=np.zeros(2),
        goal_map=fn("gm", x), stage_cost=ca.Function("L", [x, u], [ca.sumsqr(x) + ca.sumsqr(u)]),
        terminal_set=None, tracking_gain=lambda kp, kd: np.zeros((1, 2)))


@pytest.mark.parametrize("system, hold, integrator", [
    ("ball", "foh", "rk4"), ("ball", "zoh", "rk4"), ("ball", "foh", "euler"),
    ("ball, final outside", "foh", "rk4"), ("ball, mass 0.5", "zoh", "rk4"),
    ("ball, mass 0.5", "foh", "rk4"), ("lag", "foh", "euler")])
def test_the_staged_transcription_gives_the_graph_written_out_node_by_node(ball, system, hold,
                                                                          integrator):
    """The links' and the last node's rows and costs are SX functions mapped over the
    stages in MX and expanded: the NLP's graph and layout are the ones the operations
    written out at each node give, byte for byte (so no iterate depends on how the NLP
    was transcribed). Cases CasADi could simplify differently: a final domain of 3
    guard-avoid rows (the ball's final mode moved to the free flight), a held input
    (u_end the same node as u) in a flow that scales its input by 2 (mass 0.5), and
    flows of negated terms (the lag's Euler step)."""
    import dataclasses

    from hmpc_cli.mpc.chain.nlp import FixedModeNLPs

    model = {"ball": ball, "ball, final outside": dataclasses.replace(ball, final_mode="outside"),
             "ball, mass 0.5": build_ball(BallParams(mass=0.5)), "lag": _lag_system()}[system]
    fast = {"nodes_per_second": 10} if system == "lag" else {}
    nlps = FixedModeNLPs(model, MPCSettings(horizon=0.5, max_switches=2 if system == "lag"
                                            else 3, input_hold=hold, integrator=integrator,
                                            **fast))
    if system == "ball, final outside":
        assert len(nlps.final.row_guards) == 3
    for nlp in (nlps.switching, nlps.final):
        staged, written_out = _graphs(nlp)
        assert staged == written_out


def _random_expr(rng, leaves, depth):
    """A random SX expression of ``leaves``: sums, differences, products, quotients by
    constants, negations, squares and sines, and constants CasADi simplifies (0, 1, -1)."""
    import casadi as ca

    if depth == 0 or rng.random() < 0.3:
        return rng.choice(leaves) if rng.random() < 0.8 else ca.SX(
            rng.choice([0.0, 1.0, -1.0, 0.5, 2.0, 10.0, 0.1, 3.0]))
    op = rng.choice(["+", "-", "*", "/", "neg", "neg", "sq", "sin"])
    a = _random_expr(rng, leaves, depth - 1)
    if op == "neg":
        return -a
    if op == "sq":
        return a * a
    if op == "sin":
        return ca.sin(a)
    b = ca.SX(rng.choice([0.5, 2.0, 10.0, 0.1])) if op == "/" else \
        _random_expr(rng, leaves, depth - 1)
    return {"+": a + b, "-": a - b, "*": a * b, "/": a / b}[op]


@pytest.fixture
def no_kernel_compiles(monkeypatch):
    """The stage kernels of a random system stay in SX: each system's are its own, and
    compiling them (in this process's background) serves no later build; the C kernels
    are tested in tests/test_kernels.py."""
    monkeypatch.setenv("HMPC_BUILD_CACHE", "off")


def _random_system(seed):
    """A random hybrid system: 1-3 states, 0-2 inputs, 1-3 modes, 1-3 guards with random
    gaps, optional regions, identity or negating resets, an optional terminal set."""
    import random

    import casadi as ca

    from hmpc_cli.core.hybrid import Guard, HybridSystem, Mode

    rng = random.Random(seed)
    n, m, nm = rng.choice([1, 2, 3]), rng.choice([0, 1, 2]), rng.choice([1, 2, 3])
    x, u, w = ca.SX.sym("x", n), ca.SX.sym("u", m), ca.SX.sym("w", 0)
    leaves = [x[i] for i in range(n)] + [u[i] for i in range(m)]
    names = [f"M{i}" for i in range(nm)]
    modes = tuple(Mode(name, ca.Function("f", [x, u, w], [ca.vertcat(
        *(_random_expr(rng, leaves, 3) for _ in range(n)))]), (-1.0,) * m, (1.0,) * m)
        for name in names)
    guards = []
    for i in range(rng.choice([1, 2, 3])):
        h = _random_expr(rng, [x[j] for j in range(n)], 2)
        region = ca.Function("r", [x], [_random_expr(rng, [x[j] for j in range(n)], 2)]) \
            if rng.random() < 0.5 else None
        guards.append(Guard(f"g{i}", rng.choice(names), rng.choice(names),
                            ca.Function("h", [x], [h]), rng.choice([0.0, 1.0, -0.5]),
                            rng.choice([-1, 1]), reset=ca.Function(
                                "R", [x], [x if rng.random() < 0.5 else -x]), region=region))
    terminal = ca.Function("T", [x], [1 - x[0] ** 2]) if rng.random() < 0.3 else None
    return HybridSystem(
        name=f"random{seed}", state_names=tuple(f"s{i}" for i in range(n)),
        input_names=tuple(f"i{i}" for i in range(m)), disturbance_names=(), modes=modes,
        guards=tuple(guards), initial_mode=names[0], final_mode=rng.choice(names),
        x0=np.zeros(n), goal=np.zeros(n), goal_map=ca.Function("gm", [x], [x]),
        stage_cost=ca.Function("L", [x, u], [ca.sumsqr(x) + ca.sumsqr(u)]),
        terminal_set=terminal, tracking_gain=lambda kp, kd: np.zeros((m, n))), rng


@pytest.mark.parametrize("seed", range(40))
def test_random_systems_transcribe_to_the_graph_written_out(seed, no_kernel_compiles):
    """Random flows, guards, regions, resets, holds, integrators, switch counts and
    penalties: the staged transcription gives the graph and layout the operations
    written out at each node give."""
    from hmpc_cli.mpc.chain.nlp import FixedModeNLP

    system, rng = _random_system(seed)
    settings = MPCSettings(horizon=0.3, nodes_per_second=rng.choice([10, 20]),
                           max_switches=rng.choice([1, 2, 3]),
                           integrator=rng.choice(["rk4", "euler"]),
                           input_hold=rng.choice(["foh", "zoh"]),
                           soft_penalty=rng.choice([0.0, 1e4]))
    for switches in (settings.max_switches, 0):
        nlp = FixedModeNLP(system, settings, switches=switches)
        staged, written_out = _graphs(nlp)
        assert staged == written_out, (seed, switches, settings)


@pytest.mark.parametrize("seed", range(0, 40, 4))
def test_random_systems_give_ipopt_the_functions_of_the_whole_graph(seed, no_kernel_compiles):
    """IPOPT's NLP assembled from stage kernels (hmpc_cli/mpc/staged.py) has the functions
    ``nlpsol`` derives from the whole SX graph: cost, rows, gradient and constraint
    Jacobian bit for bit with either hold; the Hessian of the Lagrangian with its sparsity,
    bit for bit with a zero-order hold, to rounding with a first-order hold (u_k in two
    links)."""
    import casadi as ca

    from hmpc_cli.mpc.chain.nlp import FixedModeNLP

    system, rng = _random_system(seed)
    settings = MPCSettings(horizon=0.3, nodes_per_second=rng.choice([10, 20]),
                           max_switches=rng.choice([1, 2, 3]),
                           integrator=rng.choice(["rk4", "euler"]),
                           soft_penalty=rng.choice([0.0, 1e4]))
    points = np.random.default_rng(seed)
    for hold in ("zoh", "foh"):
        for switches in (settings.max_switches, 0):
            nlp = FixedModeNLP(system, settings.model_copy(update={"input_hold": hold}),
                               switches=switches)
            assert nlp.session.cold.oracle().is_a("MXFunction")  # assembled, not expanded
            whole, _ = nlp._transcription()
            derived = ca.nlpsol("whole", "ipopt", whole, {"no_nlp_grad": True,
                                                          "calc_lam_p": False})
            for name, args in nlp_function_calls(points, nlp.nx_var, nlp.np, nlp.ng):
                given, whole_graph = (s.get_function(name) for s in (nlp.session.cold, derived))
                for i in range(given.n_out()):
                    where = (seed, hold, switches, name, i)
                    assert given.sparsity_out(i) == whole_graph.sparsity_out(i), where
                    a = given.call(args)[i].full()
                    b = whole_graph.call(args)[i].full()
                    if name != "nlp_hess_l" or hold == "zoh":
                        np.testing.assert_array_equal(a, b, err_msg=str(where))
                    else:
                        np.testing.assert_allclose(a, b, rtol=0,
                                                   atol=1e-14 * max(1.0, np.abs(b).max()))
