"""The kinematic part of the state: where a tube can be integrated once more.

A state x_i is *kinematic* when its flow has the same rate in every mode: exactly the
same other state x_j in every mode, or zero in every mode, free of the input and the
disturbance (positions of a mechanical system, p' = v; a held stance-foot position,
p' = 0; not a state that is p' = v in one mode and p' = 0 in another). Its tracking
error then starts at zero at every MPC solve (the plan starts at the measured state) and
is the integral of other components of the error: ||e_P(t)|| <= int_0^t ||e(s)|| ds <=
int_0^t diam(s) ds. A guard whose gap depends on kinematic states only sees that smaller
tube (:func:`hmpc_cli.tube.bounds.margins`).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hmpc_cli.core.hybrid import Guard, HybridSystem

__all__ = ["guard_states", "kinematic_rates", "kinematic_states"]


#: the rate of a kinematic state whose flow is zero
ZERO = -1


def _rate_of(f_i: ca.SX, i: int, x: ca.SX, u: ca.SX, w: ca.SX) -> int | None:
    """The rate of state i: j when its flow ``f_i`` is exactly x_j (j != i), ZERO when 0.

    None when the row is anything else.
    """
    if ca.depends_on(f_i, u) or (w.numel() and ca.depends_on(f_i, w)):
        return None
    jac = ca.jacobian(f_i, x)
    if not jac.is_constant():
        return None
    row = np.asarray(ca.DM(jac), dtype=float).ravel()
    if float(ca.Function("f0", [x], [f_i])(np.zeros(x.numel()))) != 0.0:
        return None
    nz = np.flatnonzero(row)
    if nz.size == 0:
        return ZERO
    return int(nz[0]) if nz.size == 1 and nz[0] != i and row[nz[0]] == 1.0 else None


def kinematic_rates(system: HybridSystem) -> dict[int, int]:
    """Kinematic state index -> the index of the state that is its rate (ZERO: none).

    A state is kinematic when its flow is the same state x_j (or zero) in every mode.
    """
    x = ca.SX.sym("x", system.n_x)
    u = ca.SX.sym("u", system.n_u)
    w = ca.SX.sym("w", system.n_w)
    rates: dict[int, int] | None = None
    for mode in system.modes:
        f = mode.flow(x, u, w)
        now = {i: r for i in range(system.n_x)
               if (r := _rate_of(f[i], i, x, u, w)) is not None}
        rates = now if rates is None else {i: r for i, r in rates.items() if now.get(i) == r}
    return dict(sorted((rates or {}).items()))


def kinematic_states(system: HybridSystem) -> tuple[int, ...]:
    """Indices of the kinematic states (see the module docstring), ascending."""
    return tuple(kinematic_rates(system))


def guard_states(guard: Guard, n_x: int) -> tuple[int, ...]:
    """Indices of the states the guard's NLP gap q(x) depends on, ascending."""
    x = ca.SX.sym("x", n_x)
    q = guard.q_expr(x)
    return tuple(i for i in range(n_x) if ca.depends_on(q, x[i]))
