"""What a walking MPC and a foothold planner need of a planar walker: one typed object.

A walker's state is x = (q[n_q], qd[n_q], p_st[2]): joint coordinates, their rates and the
stance-foot position in the world [m] (constant along the flow, moved by the contact
reset). Its swings all happen in one mode, the stance mode, named by the walker. A system
plug-in builds one :class:`WalkerModel` and hands it to its
:class:`~hmpc_cli.core.hybrid.HybridSystem` (``walker=``), which checks it when built
(:meth:`WalkerModel.check`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

#: the columns of ``points`` the walking MPC uses (knee clearance, posture, the swing foot)
WALKER_POINTS = ("stance_knee", "torso_top", "swing_knee", "swing_foot")


@dataclass(frozen=True)
class WalkerModel:
    """A planar walker's model for walking MPCs and foothold planners (CasADi SX, SI units).

    State x = (q, qd, p_st), n_x = 2 n_q + 2 (see :attr:`q_index`, :attr:`qd_index`,
    :attr:`stance_index`); n_u inputs, n_w disturbances: the system's. Shapes are CasADi's
    (rows, columns); a vector of n entries is (n, 1).

    Attributes:
        n_q: number of joint coordinates q [rad].
        stance_mode: name of the mode every swing happens in.
        point_names: names of the P columns of ``points``; they include
            :data:`WALKER_POINTS`.
        points: q -> (2, P) joint points relative to the stance foot [m].
        inverse_dynamics: (q, qd [rad/s], qdd [rad/s^2], w) -> u, (n_u, 1): the inputs
            [N m] that give qdd under the disturbance w.
        swing_foot_world: x -> (2, 1) swing-foot position in the world [m].
        swing_foot_velocity: (q, qd) -> (2, 1) swing-foot velocity [m/s].
        swing_foot_jacobian: q -> (2, n_q) d(swing foot)/dq [m/rad].
        contact_reset: x -> x+, (n_x, 1): the touchdown's reset (impact, then the legs
            swapped: the new stance foot is the old swing foot).
        hip_world: x -> (2, 1) hip position in the world [m].
    """

    n_q: int
    stance_mode: str
    point_names: tuple[str, ...]
    points: ca.Function
    inverse_dynamics: ca.Function
    swing_foot_world: ca.Function
    swing_foot_velocity: ca.Function
    swing_foot_jacobian: ca.Function
    contact_reset: ca.Function
    hip_world: ca.Function

    @property
    def n_x(self) -> int:
        """State dimension 2 n_q + 2."""
        return 2 * self.n_q + 2

    @property
    def q_index(self) -> slice:
        """x[q_index] = q, (n_q,) [rad]."""
        return slice(0, self.n_q)

    @property
    def qd_index(self) -> slice:
        """x[qd_index] = qd, (n_q,) [rad/s]."""
        return slice(self.n_q, 2 * self.n_q)

    @property
    def stance_index(self) -> slice:
        """x[stance_index] = p_st, (2,): the stance foot in the world [m]."""
        return slice(2 * self.n_q, 2 * self.n_q + 2)

    def point(self, name: str) -> int:
        """Column of the point ``name`` in ``points``."""
        return self.point_names.index(name)

    def check(self, x0: np.ndarray, n_u: int, n_w: int, modes: Sequence[str]) -> None:
        """Checks the layout and every function's shapes, each evaluated once at x0.

        Args:
            x0: the system's initial state, (n_x,).
            n_u: the system's input dimension.
            n_w: the system's disturbance dimension.
            modes: the system's mode names.

        Raises:
            ValueError: the message names the function, the expected and the actual shape.
        """
        x0 = np.asarray(x0, dtype=float).ravel()
        nq, nx = self.n_q, self.n_x
        if x0.size != nx:
            raise ValueError(f"WalkerModel: the state (q[{nq}], qd[{nq}], p_st[2]) has {nx} "
                             f"entries, the system's x0 has {x0.size}")
        if self.stance_mode not in modes:
            raise ValueError(f"WalkerModel: stance_mode {self.stance_mode!r} is not a mode "
                             f"of the system ({', '.join(map(repr, modes))})")
        missing = [p for p in WALKER_POINTS if p not in self.point_names]
        if missing:
            raise ValueError(f"WalkerModel: point_names {self.point_names} lack {missing}")
        q, qd, zq = x0[self.q_index], x0[self.qd_index], np.zeros(nq)
        x, w = (x0, (nx, 1)), (np.zeros(n_w), (n_w, 1))
        vq, vqd = (q, (nq, 1)), (qd, (nq, 1))
        calls = {
            "points": ((vq,), (2, len(self.point_names))),
            "inverse_dynamics": ((vq, vqd, (zq, (nq, 1)), w), (n_u, 1)),
            "swing_foot_world": ((x,), (2, 1)),
            "swing_foot_velocity": ((vq, vqd), (2, 1)),
            "swing_foot_jacobian": ((vq,), (2, nq)),
            "contact_reset": ((x,), (nx, 1)),
            "hip_world": ((x,), (2, 1)),
        }
        for name, (args, out) in calls.items():
            _check_function(name, getattr(self, name), args, out)


def _check_function(name: str, fn, args: tuple, out: tuple[int, int]) -> None:
    """Raises ValueError unless fn takes ``args`` ((value, shape) each) and returns ``out``."""
    where = f"WalkerModel.{name}"
    if not isinstance(fn, ca.Function):
        raise ValueError(f"{where} must be a casadi.Function, not {type(fn).__name__}")
    if fn.n_in() != len(args) or fn.n_out() < 1:
        raise ValueError(f"{where} takes {fn.n_in()} inputs and returns {fn.n_out()}, "
                         f"expected {len(args)} inputs and one output")
    for i, (_, shape) in enumerate(args):
        actual = (fn.size1_in(i), fn.size2_in(i))
        if actual != shape:
            raise ValueError(f"{where}: input {i} ({fn.name_in(i)}) has shape {actual}, "
                             f"expected {shape}")
    value = fn.call([ca.DM(v) for v, _ in args])[0]
    actual = (value.size1(), value.size2())
    if actual != out:
        raise ValueError(f"{where} returns shape {actual}, expected {out}")
