"""The structured-NLP builder and the solver session."""

import json

import casadi as ca
import numpy as np
import pytest

from hmpc_cli.mpc.builder import NLPBuilder, NLPLayout
from hmpc_cli.mpc.solver import (INTERRUPTED, SolverSession, WarmStart, plugin_options,
                                  without_nlp_grad)


def _chain(links=3, n=2, m=1):
    """Chain NLP: per stage k z (n), u (m, k < L); p: a (L, 2), c (scalar); rows."""
    L = links
    b = NLPBuilder()
    a = b.parameter("a", (L, 2))
    c = b.parameter("c")
    z, u = [], []
    for k in range(L + 1):
        with b.stage(k):
            z.append(b.variable("z", n))
            if k < L:
                u.append(b.variable("u", m))
    for k in range(L):
        with b.stage(k):
            b.rows("dynamics", z[k + 1] - a[k, 0] * z[k] - a[k, 1] * u[k])
            b.rows("box", z[k][0] - c, shape=())
    b.rows("terminal", z[L])
    return b.build(ca.sumsqr(ca.vertcat(*z)))


def test_index_arrays_are_named_shaped_and_interleaved_per_stage():
    nlp, lay = _chain()
    assert lay.x.size == nlp["x"].size1() == 4 * 2 + 3
    assert lay.x["z"].shape == (4, 2) and lay.x["u"].shape == (3, 1)
    # stage-wise interleaving: z0 u0 z1 u1 z2 u2 z3
    assert lay.x["z"].tolist() == [[0, 1], [3, 4], [6, 7], [9, 10]]
    assert lay.x["u"].ravel().tolist() == [2, 5, 8]
    assert lay.x.stages("u") == (0, 1, 2) and lay.x.at(1).tolist() == [3, 4, 5]
    assert lay.g.names == ("dynamics", "box", "terminal")
    assert lay.g["dynamics"].shape == (3, 2) and lay.g["box"].shape == (3,)
    assert lay.g["box"].tolist() == [2, 5, 8] and lay.g["terminal"].tolist() == [9, 10]
    # parameters: column-major matrix (as casadi.vec), scalar block
    assert lay.p["a"].shape == (3, 2) and lay.p["a"][:, 0].tolist() == [0, 1, 2]
    assert lay.p["c"].shape == () and int(lay.p["c"]) == 6
    with pytest.raises(ValueError):
        lay.x["z"][0, 0] = 5  # index arrays are read-only


def test_pack_unpack_round_trip_matches_casadi_order():
    nlp, lay = _chain()
    values = {"a": np.arange(6.0).reshape(3, 2), "c": 7.5}
    p = lay.p.pack(values)
    assert p.tolist() == [0.0, 2.0, 4.0, 1.0, 3.0, 5.0, 7.5]  # vec(a), c
    back = lay.p.unpack(p)
    np.testing.assert_array_equal(back["a"], values["a"])
    assert back["c"] == 7.5
    par = lay.p.zeros()
    assert par["a"].shape == (3, 2) and par["c"].shape == ()
    with pytest.raises(KeyError):
        lay.p.pack({"a": values["a"]})
    w = np.arange(lay.x.size, dtype=float)
    parts = lay.x.unpack(w)
    np.testing.assert_array_equal(lay.x.pack(parts), w)
    # the symbols sit where the layout says
    f = ca.Function("f", [nlp["x"], nlp["p"]], [nlp["g"]])
    g = np.asarray(f(w, p)).ravel()
    z, u = parts["z"], parts["u"][:, 0]
    np.testing.assert_allclose(g[lay.g["dynamics"][1]], z[2] - 2.0 * z[1] - 3.0 * u[1])
    np.testing.assert_allclose(g[lay.g["box"]], z[:3, 0] - 7.5)


def test_bounds_by_name():
    _, lay = _chain()
    bd = lay.bounds()
    bd.lbg["dynamics"][:] = bd.ubg["dynamics"][:] = 0.0
    bd.lbg["box"][1] = -1.0
    bd.lbx["z"][0] = bd.ubx["z"][0] = [1.0, 2.0]
    bd.ubx["u"][2, 0] = 4.0
    lbx, ubx, lbg, ubg = bd.arrays()
    assert lbx[[0, 1]].tolist() == [1.0, 2.0] and ubx[[0, 1]].tolist() == [1.0, 2.0]
    assert ubx[8] == 4.0 and np.isinf(lbx[2:]).all() and np.isinf(ubx[2:8]).all()
    assert lbg[lay.g["dynamics"]].tolist() == [[0.0, 0.0]] * 3
    assert lbg[5] == -1.0 and np.isinf(lbg[[2, 8, 9, 10]]).all() and np.isinf(ubg[2])
    assert bd.lbg["box"][1] == -1.0


def test_staged_grid_and_registration_errors():
    b = NLPBuilder()
    for j in range(2):
        for k in range(3):
            if (j, k) != (0, 0):
                with b.stage((j, k)):
                    b.variable("x", 2)
    _, lay = b.build(0)
    grid = lay.x.grid("x")
    assert grid.shape == (2, 3, 2) and grid[0, 0].tolist() == [-1, -1]
    assert grid[1, 0].tolist() == [4, 5]
    b = NLPBuilder()
    with b.stage(0):
        b.variable("x", 2)
        with pytest.raises(ValueError, match="twice"):
            b.variable("x", 2)
    with b.stage(1), pytest.raises(ValueError, match="shape"):
        b.variable("x", 3)
    with pytest.raises(ValueError, match="twice"):
        b.variable("x", 2)


def test_rows_placed_give_the_layout_of_rows_made():
    """Rows registered by place only lay g out as the same rows registered by expression;
    such an NLP has no build (its g is made elsewhere, in the layout's order)."""
    _, made = _chain()
    L, n = 3, 2
    b = NLPBuilder()
    b.parameter("a", (L, 2))
    b.parameter("c")
    for k in range(L + 1):
        with b.stage(k):
            b.variable("z", n)
            if k < L:
                b.variable("u", 1)
    for k in range(L):
        with b.stage(k):
            b.place_rows("dynamics", n)
            b.place_rows("box", ())
    b.place_rows("terminal", n)
    assert b.layout().to_dict() == made.to_dict()
    x, p = b.symbols()
    assert (x.numel(), p.numel()) == (made.x.size, made.p.size) and x.is_symbolic()
    with pytest.raises(ValueError, match="place_rows"):
        b.build(0)
    with b.stage(L), pytest.raises(ValueError, match="shape"):
        b.place_rows("dynamics", n + 1)
    with pytest.raises(ValueError, match="made and rows placed"):
        b.rows("extra", x[0])


def test_staged_matrix_blocks_index_their_symbols_in_casadi_order():
    """A matrix block registered per stage: its index array (stages, rows, columns) holds
    each entry's place in the flat x, and the layout survives the build cache's JSON."""
    b = NLPBuilder()
    syms = []
    for k in range(3):
        with b.stage(k):
            syms.append(b.variable("M", (2, 3)))
            b.variable("s")
    nlp, lay = b.build(0)
    idx = lay.x["M"]
    assert idx.shape == (3, 2, 3) and lay.x["s"].tolist() == [6, 13, 20]
    for k in range(3):
        for i in range(2):
            for j in range(3):
                assert ca.is_equal(nlp["x"][int(idx[k, i, j])], syms[k][i, j])
        assert lay.x.at(k).tolist() == list(range(7 * k, 7 * k + 7))
    back = NLPLayout.from_dict(json.loads(json.dumps(lay.to_dict())))
    for name in ("M", "s"):
        assert back.x[name].tolist() == lay.x[name].tolist()
        assert back.x.stages(name) == (0, 1, 2) and not back.x[name].flags.writeable
    assert back.x.at(2).tolist() == lay.x.at(2).tolist()
    data = lay.to_dict()
    data["x"]["entries"]["M"][1][2] = [3, 2]  # a stage of another shape: refused
    with pytest.raises(ValueError, match="shapes differ"):
        NLPLayout.from_dict(data)


def _scalar_session(**kw):
    b = NLPBuilder()
    x = b.variable("x")
    b.rows("lower", x, shape=())
    nlp, lay = b.build((x - 1) ** 2)
    return SolverSession("tiny", nlp, "ipopt", max_iter=50, **kw), lay


def test_tiny_nlp_solved_by_the_session():
    session, lay = _scalar_session(warm=WarmStart(1e-6, 1e-9))
    bd = lay.bounds()
    bd.lbg["lower"][()] = 2.0  # x >= 2 as a row
    res = session.run(np.zeros(1), np.zeros(0), *bd.arrays())
    assert res.stats.success and res.stats.status == "Solve_Succeeded"
    assert res.x[lay.x["x"]] == pytest.approx(2.0, abs=1e-7)
    assert res.stats.cost == pytest.approx(1.0, abs=1e-6)
    assert res.stats.max_violation <= 1e-8 and res.stats.iterations > 0
    assert res.lam_g[lay.g["lower"]] == pytest.approx(-2.0, abs=1e-6)  # df/dx = 2
    warm = session.run(res.x, np.zeros(0), *bd.arrays(), res.lam_x, res.lam_g)
    assert warm.stats.success and warm.x[0] == pytest.approx(2.0, abs=1e-7)
    assert session.warm is not session.cold
    # as a bound instead of a row; violation is measured on rows and bounds
    bd = lay.bounds()
    bd.lbx["x"][()] = 2.0
    res = session.run(np.zeros(1), np.zeros(0), *bd.arrays())
    assert res.x[0] == pytest.approx(2.0, abs=1e-7)
    assert session.violation(np.array([1.5]), np.zeros(0), *bd.arrays()) == 0.5


def test_sessions_skip_nlpsols_post_solve_gradient_and_solve_alike():
    """No instance generates ``nlp_grad`` (a reverse sweep of the whole graph, used only
    for post-solve quantities hmpc does not ask for); the iterates are those of an
    instance that has it, bit for bit; asking for such a quantity keeps it."""
    session, lay = _scalar_session(warm=WarmStart(1e-6, 1e-9))
    other = SolverSession("tiny", session._nlp, "sqpmethod", max_iter=50)
    for inst in (session.cold, session.warm, other.cold):
        assert "nlp_grad" not in inst.get_function()
        assert "nlp_hess_l" in inst.get_function()
    bd = lay.bounds()
    bd.lbg["lower"][()] = 2.0
    args = (np.zeros(1), np.zeros(0), *bd.arrays())
    with_grad = ca.nlpsol("with", "ipopt", session._nlp,
                          {**session.options, "no_nlp_grad": False})
    assert "nlp_grad" in with_grad.get_function()
    ours = session.cold(x0=args[0], p=args[1], lbx=args[2], ubx=args[3], lbg=args[4],
                        ubg=args[5])
    theirs = with_grad(x0=args[0], p=args[1], lbx=args[2], ubx=args[3], lbg=args[4],
                       ubg=args[5])
    for key in ("x", "f", "g", "lam_x", "lam_g"):
        assert np.array_equal(np.ravel(ours[key]), theirs[key].full().ravel()), key
    assert without_nlp_grad({"calc_lam_x": True}) == {"calc_lam_x": True}
    assert without_nlp_grad({}, "fatrop") == {}  # fatrop calls it
    assert without_nlp_grad({"no_nlp_grad": False}) == {"no_nlp_grad": False}  # the user's
    # a compiled library has no nlp_grad: a calc_* option is refused before it is loaded
    # (the chain and walking NLPs then build in SX, with a warning naming the reason)
    with pytest.raises(RuntimeError, match=r"\['calc_lam_x'\] need nlp_grad"):
        SolverSession("lib", "/nonexistent/nlp.so", "ipopt", max_iter=5,
                      extra={"calc_lam_x": True})
    with pytest.raises(RuntimeError, match=r"\['no_nlp_grad=False'\] need nlp_grad"):
        SolverSession("lib", "/nonexistent/nlp.so", "ipopt", max_iter=5,
                      extra={"no_nlp_grad": False})
    assert without_nlp_grad({"calc_lam_p": False}) == {"calc_lam_p": False,
                                                       "no_nlp_grad": True}


def test_warm_instance_with_a_limited_memory_hessian():
    """IPOPT generates no Hessian under L-BFGS: the warm instance is built without one."""
    session, lay = _scalar_session(warm=WarmStart(1e-6, 1e-9), extra={
        "ipopt": {"hessian_approximation": "limited-memory"}})
    bd = lay.bounds()
    bd.lbg["lower"][()] = 2.0
    res = session.run(np.zeros(1), np.zeros(0), *bd.arrays())
    warm = session.run(res.x, np.zeros(0), *bd.arrays(), res.lam_x, res.lam_g)
    assert res.stats.success and warm.stats.success
    assert warm.x[0] == pytest.approx(2.0, abs=1e-7)
    assert not session.cold.has_function("nlp_hess_l")


def test_interrupt_inside_ipopt_is_re_raised_not_a_failed_solve():
    session, lay = _scalar_session()

    class Interrupted:  # CasADi's behaviour on Ctrl-C inside IPOPT: a status, no raise
        def __init__(self, solver):
            self.solver = solver

        def __call__(self, **args):
            return self.solver(**args)

        def stats(self):
            return {**self.solver.stats(), "return_status": INTERRUPTED, "success": False}

    session.cold = Interrupted(session.cold)
    with pytest.raises(KeyboardInterrupt):
        session.run(np.zeros(1), np.zeros(0), *lay.bounds().arrays())


def test_solver_errors_become_failed_solves():
    session, lay = _scalar_session()

    def raising(**args):
        raise RuntimeError("Error in Function::call\n  .../x.cpp:12: NaN detected for output f")

    session.cold = raising
    res = session.run(np.array([3.0]), np.zeros(0), *lay.bounds().arrays())
    assert not res.stats.success and res.stats.status == "error: .../x.cpp:12: NaN detected " \
                                                         "for output f"
    assert res.x.tolist() == [3.0] and res.lam_x is None and res.stats.max_violation == np.inf


def test_plugin_options_table():
    ipopt = plugin_options("ipopt", 50, 1e-6, 2.0, extra={"ipopt": {"tol": 1e-7},
                                                          "ipopt_warm": {"mu_init": 1.0},
                                                          "error_on_fail": False})
    assert ipopt["ipopt"]["tol"] == 1e-7 and ipopt["ipopt"]["max_wall_time"] == 2.0
    assert ipopt["error_on_fail"] is False and "ipopt_warm" not in ipopt
    assert plugin_options("sqpmethod", 5)["qpsol"] == "qrqp"
    assert plugin_options("fatrop", 5, equality=[True, False])["equality"] == [True, False]
    with pytest.raises(ValueError):
        plugin_options("snopt", 5)


# ------------------------------------------------------------ fixed-mode NLP row groups


def test_fixed_mode_row_groups_by_name_and_size():
    from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule
    from hmpc_cli.mpc.chain.nlp import FixedModeNLPs, MPCSettings
    from hmpc_cli.systems.ball import BallParams, build_ball

    ball = build_ball(BallParams(terminal_radius=0.5))
    nlps = FixedModeNLPs(ball, MPCSettings(horizon=0.5, max_switches=2))
    nlp, n, G = nlps.switching, ball.n_x, len(ball.guards)
    L, g = nlp.L, nlp.layout.g
    assert L == 30 + 2 and nlp.R == 2 and nlp.T == 1
    assert g.names == ("dynamics", "guard_avoid", "guard_hit", "virtual_node", "region",
                       "terminal")
    sizes = {name: g[name].shape for name in g.names}
    assert sizes == {"dynamics": (L, n), "guard_avoid": (L + 1, G), "guard_hit": (L + 1,),
                     "virtual_node": (L + 1,), "region": (L + 1, 2), "terminal": (1,)}
    # rows interleave per link: dynamics then node k's path rows; terminal last
    per_link = n + G + 2 + 2
    assert nlp.ng == L * per_link + per_link - n + 1
    for k in (0, 1, L - 1):
        assert g.at(k).tolist() == list(range(k * per_link, (k + 1) * per_link))
    assert g["terminal"].tolist() == [nlp.ng - 1]
    x = nlp.layout.x
    assert x["z"].shape == (L + 1, n) and x["u"].shape == (L, 2) and x["sigma"].shape == (L + 1,)
    assert x.at(1).tolist() == list(range(n + 2 + 1, 2 * (n + 2 + 1)))
    # the final domain's NLP: no switching rows
    final = nlps.final
    assert final.layout.g.names == ("dynamics", "guard_avoid", "terminal")
    inside = ball.guards_of(ball.mode_index(ball.final_mode))
    assert final.S == 0 and final.layout.g["guard_avoid"].shape == (31, len(inside))
    # problem data switches the rows of a guard node on by name
    ns = NodeSchedule((0, 1), (1,), (5, 25))
    lay = ChainLayout.build(ns, L)
    p, lbx, ubx, lbg, ubg = nlp.problem_data(ns, lay, ball.x0)
    assert np.all(lbg[g["dynamics"]] == 0.0) and np.all(ubg[g["dynamics"]] == 0.0)
    assert ubg[g["guard_hit"][5]] == 0.0 and lbg[g["virtual_node"][5]] == 0.0
    assert np.all(lbg[g["region"][5]] == 0.0) and lbg[g["guard_avoid"][5, 1]] == 0.0
    assert np.isinf(ubg[g["guard_hit"]]).sum() == L and lbg[g["terminal"][0]] == 0.0
    par = nlp.layout.p.unpack(p)
    assert par["hit"][5, 1] == 1.0 and par["beta"][5, 1] == 1.0 and par["b"][5, 1] == 1.0
    assert np.all(lbx[x["z"][0]] == ball.x0) and np.all(ubx[x["sigma"]] == np.inf)


def test_without_the_virtual_node_the_input_before_a_guard_is_free_in_its_box():
    """mpc.robust = false: the reset link's input, the end of the first-order hold of the
    interval before the guard node, had bounds [0, 0], so that interval's input ramped to
    0 (outside the ball's [-100, 0] box tightened by an input margin). It takes the
    source mode's box either way; only the virtual node's row differs."""
    from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule, RESET
    from hmpc_cli.mpc.chain.nlp import FixedModeNLPs, MPCSettings
    from hmpc_cli.systems.ball import BallParams, build_ball

    ball = build_ball(BallParams())
    ns = NodeSchedule((0, 0, 1), (0, 2), (10, 20, 150))
    made = {}
    for robust in (True, False):
        nlp = FixedModeNLPs(ball, MPCSettings(robust=robust, input_margin=5.0)).switching
        lay = ChainLayout.build(ns, nlp.L)
        _, lbx, ubx, lbg, _ = nlp.problem_data(ns, lay, ball.x0)
        reset = np.nonzero(lay.link_type == RESET)[0]
        u = nlp.layout.x["u"]
        made[robust] = lbx[u[reset]], ubx[u[reset]]
        assert np.all(lbx[u[reset]] == -95.0) and np.all(ubx[u[reset]] == -5.0)
        virtual = lbg[nlp.layout.g["virtual_node"]]
        assert np.isfinite(virtual).sum() == (2 if robust else 0)
    assert all(np.array_equal(a, b) for a, b in zip(made[True], made[False], strict=True))


def test_walking_row_groups_by_name_and_size():
    from hmpc_cli.mpc.walking.nlp import WalkingMPCSettings, WalkingNLP
    from hmpc_cli.systems.biped import BipedParams, build_biped

    N = 6
    nlp = WalkingNLP(build_biped(BipedParams()),
                     WalkingMPCSettings(nodes_per_swing=N, apex_node=3))
    NX = nlp.nx
    assert (nlp.nq, NX) == (5, 10)  # the biped's five joints: (q, qd) per node
    g, x = nlp.layout.g, nlp.layout.x
    assert g.names == ("dynamics", "torque", "guard_avoid", "knees", "touchdown", "reset",
                       "liftoff")
    assert {name: g[name].shape for name in g.names} == {
        "dynamics": (2 * N, NX), "torque": (2 * N, 5), "guard_avoid": (2 * N,),
        "knees": (2 * N, 2), "touchdown": (2,), "reset": (NX,), "liftoff": ()}
    # per interval 18 rows; swing 0's intervals, touchdown + reset, swing 1's, liftoff
    assert nlp.interval_rows.shape == (2, N, 18)
    assert nlp.interval_rows[0].ravel().tolist() == list(range(18 * N))
    assert g["touchdown"].tolist() == [18 * N, 18 * N + 1] and nlp.row(1, 0) == 18 * N + 12
    assert int(g["liftoff"]) == nlp.ng - 1 == 2 * 18 * N + 12
    assert x["x"].shape == (2 * N + 1, NX) and x["a"].shape == (2 * N, 5)
    assert nlp.x_idx[0, 0].tolist() == [-1] * NX and nlp.x_idx[1, 0].tolist() == \
        list(range(15 * N, 15 * N + NX))
    p, lbx, ubx, lbg, ubg = nlp.problem_data(build_biped(BipedParams()).x0, (1.0, 1.5, 0.1),
                                             0.0)
    assert float(p[nlp.layout.p["dt0"]]) == pytest.approx(nlp.s.dt)
    assert lbg[g["touchdown"][0]] == pytest.approx(1.0 + nlp.s.segment_margin)
    assert lbg[g["touchdown"][1]] == ubg[g["touchdown"][1]] == pytest.approx(0.095)
    assert np.isinf(lbg[g["guard_avoid"][N - 1]]) and lbg[g["guard_avoid"][N]] == 0.0
    assert lbg[g["liftoff"]] == nlp.s.liftoff_accel


def test_the_cost_is_the_objective_inside_the_bounds():
    """Soft-constraint slacks s >= 0 with weight 1e4 that need no relaxation: IPOPT returns
    them 1e-8 below 0 (its bound relaxation), the objective there is negative; the
    session reports the (nonnegative) objective at the solution projected onto its bounds."""
    b = NLPBuilder()
    x, s = b.variable("x"), b.variable("s", 181)
    nlp, lay = b.build((x - 1) ** 2 + 1e4 * ca.sum1(s))
    bd = lay.bounds()
    bd.lbx["s"][:] = 0.0
    res = SolverSession("slack", nlp, "ipopt", max_iter=50).run(
        np.zeros(182), np.zeros(0), *bd.arrays())
    slack = res.x[lay.x["s"]]
    assert res.stats.success and slack.min() < 0.0  # IPOPT's relaxed bound, as returned
    inside = np.clip(res.x, *bd.arrays()[:2])
    objective = ca.Function("f", [nlp["x"], nlp["p"]], [nlp["f"]])
    assert res.stats.cost == float(objective(inside, np.zeros(0)))
    assert 0.0 <= res.stats.cost < 1e-12


def test_given_derivatives_are_checked_and_an_assembled_nlp_is_not_expanded():
    """``derivatives`` are IPOPT's derivative options only (a typo is an error, not a
    silently generated function); an MX NLP given them is solved as assembled (no
    ``expand``: its kernels may be C libraries), one given none is expanded as before."""
    x, p = ca.MX.sym("x"), ca.MX.sym("p", 0)
    nlp = {"x": x, "p": p, "f": (x - 1) ** 2, "g": x}
    grad = ca.Function("nlp_grad_f", [x, p], [(x - 1) ** 2, 2 * (x - 1)], ["x", "p"],
                       ["f", "grad_f_x"])
    with pytest.raises(ValueError, match=r"not derivative options of ipopt: \['grad'\]"):
        SolverSession("typo", nlp, "ipopt", max_iter=10, derivatives={"grad": grad})
    given = SolverSession("given", nlp, "ipopt", max_iter=10, derivatives={"grad_f": grad})
    assert "expand" not in given.options and given.derivatives == {"grad_f": grad}
    assert given.cold.get_function("nlp_grad_f").serialize() == grad.serialize()  # used
    plain = SolverSession("plain", nlp, "ipopt", max_iter=10)
    assert plain.options["expand"] is True
    assert plain.cold.get_function("nlp_grad_f").is_a("SXFunction")  # generated, expanded


def test_which_options_take_the_nlp_assembled_from_compiled_kernels():
    """Only IPOPT, and only options that cannot make nlpsol differentiate the NLP itself."""
    from hmpc_cli.mpc.solver import takes_assembled

    assert takes_assembled("ipopt", None)
    assert takes_assembled("ipopt", {"ipopt": {"max_cpu_time": 1.0}, "record_time": True})
    assert not takes_assembled("ipopt", {"calc_lam_p": True})  # needs nlp_grad
    assert not takes_assembled("ipopt", {"detect_simple_bounds": True})  # not known safe
    assert not takes_assembled("sqp_hpipm", None)  # its own derivatives, from SX
    assert not takes_assembled("fatrop", None)
