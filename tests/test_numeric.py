"""NumPy evaluation of CasADi graphs equals CasADi's own evaluation."""

import casadi as ca
import numpy as np

from hmpc_cli.core.numeric import compile_numpy
from hmpc_cli.systems.ball import BallParams, build_ball


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
