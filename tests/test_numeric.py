"""NumPy evaluation of CasADi graphs equals CasADi's own evaluation."""

import casadi as ca
import numpy as np
import pytest

from hmpc_cli.core.hybrid import rk4_expr
from hmpc_cli.core.numeric import compile_numpy, compile_one
from hmpc_cli.sim.simulator import HybridSimulator
from hmpc_cli.systems.ball import BallParams, build_ball
from hmpc_cli.systems.biped import build_biped
from hmpc_cli.systems.biped.params import BipedParams


def test_numpy_matches_casadi_on_every_ball_function():
    ball = build_ball(BallParams())
    rng = np.random.default_rng(0)
    x = rng.normal(2.0, 1.5, size=(50, 4))
    u = rng.uniform(-100, 100, size=(50, 2))
    w = rng.uniform(-10, 10, size=(50, 2))
    for mode in ball.modes:
        f = compile_numpy(mode.flow)
        ref = np.array(mode.flow.map(50)(x.T, u.T, w.T)).T
        np.testing.assert_allclose(f(x, u, w)[0], ref, rtol=1e-14, atol=1e-12)
    for g in ball.guards:
        for fun in [g.h, g.reset] + ([g.region] if g.region is not None else []):
            ref = np.array(fun.map(50)(x.T)).T
            np.testing.assert_allclose(compile_numpy(fun)(x)[0], ref, rtol=1e-14, atol=1e-12)


def test_sparse_outputs_constants_and_branches():
    a = ca.SX.sym("a", 2)
    out = ca.vertcat(0, a[0] * 3, ca.if_else(a[1] > 0, a[0], -a[1]), 7.5, ca.fmax(a[0], a[1]))
    f = ca.Function("f", [a], [out])
    pts = np.array([[1.0, 2.0], [-1.0, -3.0], [0.5, 0.0]])
    ref = np.array(f.map(3)(pts.T)).T
    np.testing.assert_allclose(compile_numpy(f)(pts)[0], ref)
    np.testing.assert_allclose(compile_numpy(f)(pts[0])[0], ref[0])


def test_tanh_is_the_c_librarys_bit_for_bit_on_any_cpu():
    """NumPy's SIMD tanh differs from the C library's (CasADi's) in the last bit for about
    a quarter of arguments on AVX2 CPUs: the evaluator and the walking MPC's floor use the
    C library's, so no result depends on the machine's vector unit."""
    z = ca.SX.sym("z")
    f = ca.Function("f", [z], [ca.tanh(z)])
    a = np.random.default_rng(1).uniform(-10.0, 10.0, 20_000)
    ref = np.array(f.map(a.size)(a)).ravel()
    assert np.array_equal(compile_numpy(f)(a[:, None])[0][:, 0], ref)


def _simulator_functions(system):
    """(name, SX function) of what the simulator evaluates per step: RK4 and the gaps."""
    x, u = ca.SX.sym("x", system.n_x), ca.SX.sym("u", system.n_u)
    w, h = ca.SX.sym("w", system.n_w), ca.SX.sym("h")
    out = []
    for i, mode in enumerate(system.modes):
        out.append((f"rk4_{mode.name}", ca.Function("rk4", [x, u, w, h],
                                                    [rk4_expr(mode, x, u, w, h)])))
        gaps = [system.guards[g].gap_expr(x) for g in system.guards_of(i)]
        out.append((f"gaps_{mode.name}", ca.Function("gaps", [x], [ca.vertcat(*gaps)])))
    return out


@pytest.mark.parametrize("which", ["ball", "biped"])
def test_single_sample_evaluator_equals_the_batch_one_bit_for_bit(which):
    """compile_one on Python floats gives compile_numpy's numbers on a batch of one, also
    at signed zeros, NaN and infinite inputs (fmin and fmax as NumPy's, sin and cos
    NumPy's own)."""
    system = build_ball(BallParams()) if which == "ball" else build_biped(BipedParams())
    rng = np.random.default_rng(7)
    x0 = np.asarray(system.x0, dtype=float)
    for name, fun in _simulator_functions(system):
        batch, one = compile_numpy(fun), compile_one(fun)
        assert one is not None, name
        sizes = [fun.size1_in(i) for i in range(fun.n_in())]
        for k in range(400):
            args = [x0 + rng.normal(0.0, 0.5, sizes[0])]
            args += [rng.normal(0.0, 80.0, n) for n in sizes[1:3]]
            args += [np.array([1e-3])] * (len(sizes) - 3)
            if k % 5 == 0:  # an input exactly at a bound's sign change, and a signed zero
                args[min(1, len(args) - 1)][0] = -0.0 if k % 10 else 0.0
            if k == 7:
                args[-1][0] = np.nan
            if k == 11:
                args[0][0] = np.inf
            args = [a[None] for a in args]
            with np.errstate(all="ignore"):
                ref = batch(*args)
                got = one(*args)
            for r, g in zip(ref, got, strict=True):
                assert r.shape == g.shape and np.array_equal(r, g, equal_nan=True), (name, k)
                assert np.array_equal(np.signbit(r), np.signbit(g)), (name, k)


def test_single_sample_evaluator_falls_back_where_python_floats_raise():
    """Division by zero and the square root of a negative number give NumPy's inf and NaN
    (the batch evaluator runs instead); fmin and fmax are NumPy's at signed zeros and NaN;
    an operation outside the exact set: no evaluator."""
    a = ca.SX.sym("a", 2)
    f = ca.Function("f", [a], [ca.vertcat(1.0 / a[0], ca.sqrt(a[1]), ca.fmin(a[0], a[1]),
                                          ca.fmax(a[0], a[1]), ca.fmin(a[1], a[0]))])
    one = compile_one(f)
    nan, inf = np.nan, np.inf
    with np.errstate(all="ignore"):
        for point in ([0.0, 4.0], [-0.0, -1.0], [2.0, 9.0], [0.0, -0.0], [-0.0, 0.0],
                      [nan, 1.0], [1.0, nan], [inf, -inf], [-inf, nan]):
            arg = np.array([point])
            got, ref = one(arg)[0], compile_numpy(f)(arg)[0]
            assert np.array_equal(got, ref, equal_nan=True), point
            assert np.array_equal(np.signbit(got), np.signbit(ref)), point
    assert compile_one(ca.Function("g", [a], [ca.exp(a[0])])) is None


def test_the_biped_steps_alone_as_in_a_batch():
    """The plant steps one sample (single-sample evaluators); the same states in a batch
    (NumPy evaluators) reach the same states, modes and event times, touchdowns included."""
    system = build_biped(BipedParams())
    sim = HybridSimulator(system)
    rng = np.random.default_rng(3)
    x = np.asarray(system.x0, dtype=float) + rng.normal(0.0, 0.05, (12, system.n_x))
    x[:, system.n_x // 2:] += rng.normal(0.0, 1.0, (12, system.n_x - system.n_x // 2))
    u = rng.normal(0.0, 20.0, (12, system.n_u))
    w = np.zeros((12, system.n_w))
    mode = np.zeros(12, dtype=int)
    batch = sim.step(x, mode, u, w, 0.2, raise_zeno=False)
    assert batch.events  # some samples touch down within the step
    for b in range(12):
        single = sim.step(x[b:b + 1], mode[b:b + 1], u[b:b + 1], w[b:b + 1], 0.2,
                          raise_zeno=False)
        assert np.array_equal(single.x[0], batch.x[b], equal_nan=True)
        assert single.mode[0] == batch.mode[b]
        assert [e.tau for e in single.events] == [e.tau for e in batch.events if e.sample == b]


def test_single_sample_evaluator_hands_other_arguments_to_numpy():
    """Integers are floats, another batch shape gets the batch evaluator's answer, an
    output that overflows is NumPy's with its warning, and infinite constants evaluate."""
    a = ca.SX.sym("a", 2)
    f = ca.Function("f", [a], [ca.vertcat(a[0] * a[1], ca.fmin(a[0], ca.inf),
                                          ca.fmax(a[1], -ca.inf))])
    one, batch = compile_one(f), compile_numpy(f)
    for arg in (np.array([[2, 3]]), np.array([[1.5, -2.0], [0.5, 4.0]]), np.array([1.0, 2.0])):
        got, ref = one(arg)[0], batch(arg)[0]
        assert got.dtype == ref.dtype == float and got.shape == ref.shape
        assert np.array_equal(got, ref)
    with pytest.warns(RuntimeWarning, match="overflow"):
        got = one(np.array([[1e308, 10.0]]))[0]
    assert np.array_equal(got, [[np.inf, 1e308, 10.0]])
