"""The solvers' buffered calls: the plain call's results and stats, errors, interrupts."""

import signal

import casadi as ca
import numpy as np
import pytest

from hmpc_cli.mpc.buffered import BufferedSolver

QUIET = {"print_time": False}
SOLVERS = {
    "ipopt": {**QUIET, "ipopt": {"print_level": 0, "sb": "yes"}},
    "sqpmethod": {**QUIET, "print_header": False, "print_iteration": False,
                  "print_status": False, "qpsol": "qrqp",
                  "qpsol_options": {"print_iter": False, "print_header": False,
                                    "error_on_fail": False}},
}


def _nlp(n: int = 12) -> dict:
    x, p = ca.SX.sym("x", n), ca.SX.sym("p", 2)
    f = ca.sumsqr(x - p[0]) + ca.sum1((x + 2) ** 4) * p[1]
    g = ca.vertcat(*[x[i] * x[i + 1] for i in range(n - 1)], ca.sum1(x))
    return {"x": x, "p": p, "f": f, "g": g}


def _inputs(n: int = 12) -> dict:
    return {"x0": np.linspace(0.2, 0.7, n), "p": np.array([0.3, 0.01]),
            "lbx": np.full(n, -1.0), "ubx": np.full(n, 1.0),
            "lbg": np.r_[np.full(n - 1, -0.5), 1.0], "ubg": np.r_[np.full(n - 1, 0.5), 1.0]}


@pytest.mark.parametrize("plugin", sorted(SOLVERS))
def test_buffered_calls_return_the_plain_calls_results_bit_for_bit(plugin):
    plain = ca.nlpsol("s", plugin, _nlp(), SOLVERS[plugin])
    buffered = BufferedSolver(ca.nlpsol("s", plugin, _nlp(), SOLVERS[plugin]))
    cold = _inputs()
    first = plain(**cold)
    warm = {**cold, "x0": np.asarray(first["x"]).ravel() + 1e-3,
            "lam_x0": np.asarray(first["lam_x"]).ravel(),
            "lam_g0": np.asarray(first["lam_g"]).ravel()}
    for args in (cold, warm, cold):  # the second cold call: multipliers back to defaults
        want, got = plain(**args), buffered(**args)
        assert set(got) == set(plain.name_out())
        for name, value in got.items():
            assert value.shape == (plain.nnz_out(name),)
            np.testing.assert_array_equal(value, np.asarray(want[name]).ravel())
        want_st, got_st = plain.stats(), buffered.stats()
        assert got_st["return_status"] == want_st["return_status"]
        assert got_st["iter_count"] == want_st["iter_count"]
        calls = {k: v for k, v in want_st.items() if k.startswith("n_call_")}
        assert calls and {k: got_st[k] for k in calls} == calls  # this call's, not a sum


def test_buffered_outputs_are_copies_and_attributes_are_the_functions():
    solver = BufferedSolver(ca.nlpsol("s", "ipopt", _nlp(), SOLVERS["ipopt"]))
    first = solver(**_inputs())
    kept = first["x"].copy()
    solver(**{**_inputs(), "p": np.array([-0.4, 0.01])})
    np.testing.assert_array_equal(first["x"], kept)
    assert solver.name() == "s" and solver.has_function("nlp_jac_g")


def test_buffered_inputs_are_checked_by_name_and_size():
    solver = BufferedSolver(ca.nlpsol("s", "ipopt", _nlp(), SOLVERS["ipopt"]))
    with pytest.raises(ValueError, match="input 'x0' has 3 entries, expected 12"):
        solver(**{**_inputs(), "x0": np.zeros(3)})
    with pytest.raises(ValueError, match="no input 'lam_z0'"):
        solver(**_inputs(), lam_z0=np.zeros(12))
    out = solver(**{**_inputs(), "lbx": -1.0})  # a scalar fills the input, as CasADi does
    assert np.all(out["x"] >= -1.0 - 1e-9)


class Stop(KeyboardInterrupt):
    pass


def test_a_signal_handlers_exception_inside_a_buffered_ipopt_solve_comes_out_as_raised():
    """CasADi hands a Python exception raised inside the solve (a stop signal's handler)
    back as a SystemError; the buffered call raises the handler's own exception."""
    n = 2000  # Rosenbrock's chain from -1.2: thousands of IPOPT iterations, seconds
    x = ca.SX.sym("x", n)
    f = ca.sum1(100 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2)
    solver = BufferedSolver(ca.nlpsol("s", "ipopt", {"x": x, "f": f},
                                      {**QUIET, "ipopt": {"print_level": 0, "sb": "yes"}}))

    def handler(signum, frame):
        raise Stop("stop")

    old = signal.signal(signal.SIGALRM, handler)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.05)
        with pytest.raises(Stop, match="stop"):
            solver(x0=np.full(n, -1.2))
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert solver.stats() == {}  # no call finished
    out = solver(x0=np.full(n, 0.9))  # the solver is usable after it
    assert solver.stats()["return_status"] == "Solve_Succeeded"
    np.testing.assert_allclose(out["x"], 1.0, atol=1e-6)


def test_with_record_time_a_buffered_call_has_its_own_total_timer():
    opts = {**SOLVERS["ipopt"], "record_time": True}
    plain = ca.nlpsol("s", "ipopt", _nlp(), opts)
    buffered = BufferedSolver(ca.nlpsol("s", "ipopt", _nlp(), opts))
    plain(**_inputs())
    for _ in range(2):
        buffered(**_inputs())
        st = buffered.stats()
        assert st["n_call_total"] == plain.stats()["n_call_total"] == 1
        assert st["t_wall_total"] >= st["t_wall_nlp_hess_l"] + st["t_wall_nlp_jac_g"] > 0
        assert st["t_proc_total"] > 0


def test_the_buffered_objective_is_nlp_f_bit_for_bit():
    """The cost at the bounds after each solve (hmpc_cli.mpc.solver) calls nlp_f through a
    buffer: the same values as a plain call of the solver's nlp_f."""
    plain = ca.nlpsol("s", "ipopt", _nlp(), SOLVERS["ipopt"])
    buffered = BufferedSolver(ca.nlpsol("s", "ipopt", _nlp(), SOLVERS["ipopt"]))
    f = plain.get_function("nlp_f")
    rng = np.random.default_rng(0)
    for _ in range(5):
        w, p = rng.normal(size=12), rng.normal(size=2)
        assert buffered.objective(w, p) == float(f(w, p))
