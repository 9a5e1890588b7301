"""Structure-exploiting NLP back-ends: SQP with a Gauss-Newton Hessian and HPIPM.

The MPC NLPs have least-squares costs (plus linear slack penalties). The SQP back-end
``sqp_hpipm`` (CasADi ``sqpmethod``) takes the Gauss-Newton Hessian of the Lagrangian,

    H = lam_f * 2 J_r^T J_r         (f = |r|^2 + linear terms; no constraint curvature),

or, without an explicit residual vector r, the cost's own Hessian ``lam_f * d2f/dx2``
(equal to the Gauss-Newton one when the residuals are affine, as in the ball's
quadratic cost). Its QP subproblems are solved by HPIPM's Riccati-based interior point
method, which needs the optimal-control stage structure of the QP (:class:`OCPStructure`):
per stage k the state x_k (``nx[k]``) then the control u_k (``nu[k]``); per stage k < N
first the ``nx[k + 1]`` gap-closing rows ``x_{k+1} - F(x_k, u_k)`` then ``ng[k]`` path
rows of (x_k, u_k) only; the Hessian block diagonal per stage.

CasADi's HPIPM interface has no control at the last stage (the last stage's variables
are states only), so a last stage with a control (the fixed-mode NLP's slack sigma_L)
is given a trailing empty stage (nx = nu = ng = 0): the last real stage then has no gap
rows and keeps its control.

The back-ends of ``mpc.solver`` are the entries of :mod:`hmpc_cli.mpc.solver_table`.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

#: a bounded SQP run (real-time iterations) counts as a success below this violation
RTI_VIOLATION = 1e-6
#: added to the Gauss-Newton Hessian's diagonal (variables without cost curvature)
HESSIAN_REGULARIZATION = 1e-8


@dataclass(frozen=True)
class OCPStructure:
    """Stage dimensions of an OCP-structured NLP (HPIPM's ``N``, ``nx``, ``nu``, ``ng``).

    Attributes:
        nx: states per stage, length N + 1.
        nu: controls per stage, length N + 1 (the last one 0).
        ng: path rows per stage, length N + 1.
    """

    nx: tuple[int, ...]
    nu: tuple[int, ...]
    ng: tuple[int, ...]

    def __post_init__(self) -> None:
        if not len(self.nx) == len(self.nu) == len(self.ng) or self.nu[-1] != 0:
            raise ValueError(f"OCPStructure: nx, nu, ng of one length, nu[-1] = 0: {self}")

    @classmethod
    def chain(cls, nx: int, nu: list[int], ng: list[int]) -> OCPStructure:
        """The structure of a chain whose every stage has ``nx`` states.

        Args:
            nx: states per stage.
            nu: controls per stage, length N + 1 (the last stage may have controls: a
                trailing empty stage is added then).
            ng: path rows per stage (gap rows excluded), length N + 1.
        """
        n = len(nu)
        if nu[-1] == 0:
            return cls((nx,) * n, tuple(nu), tuple(ng))
        return cls((nx,) * n + (0,), (*nu, 0), (*ng, 0))

    @property
    def N(self) -> int:
        """Stages with gap rows (HPIPM's horizon)."""
        return len(self.nx) - 1

    def sizes(self) -> tuple[int, int]:
        """(variables, rows) the structure describes."""
        return sum(self.nx) + sum(self.nu), sum(self.nx[1:]) + sum(self.ng)

    def qpsol_options(self) -> dict:
        """The HPIPM ``conic`` options of this structure."""
        return {"N": self.N, "nx": list(self.nx), "nu": list(self.nu), "ng": list(self.ng)}


def gauss_newton_hessian(nlp: dict, residuals=None) -> ca.Function:
    """The Gauss-Newton Hessian of the Lagrangian as ``sqpmethod``'s ``hess_lag``.

    Args:
        nlp: ``{"x", "p", "f", "g"}`` (SX).
        residuals: r with f = |r|^2 + terms linear in x (None: the cost's own Hessian,
            the Gauss-Newton Hessian of affine residuals).

    Returns:
        (x, p, lam_f, lam_g) -> H, shape (nx, nx) (symmetric: ``sqpmethod`` wants the
        whole matrix).
    """
    x, p = nlp["x"], nlp["p"]
    lam_f = ca.SX.sym("lam_f")
    lam_g = ca.SX.sym("lam_g", nlp["g"].size1())
    if residuals is None:
        h = ca.hessian(nlp["f"], x)[0]
    else:
        jr = ca.jacobian(residuals, x)
        h = 2 * ca.mtimes(jr.T, jr)
    h = lam_f * h + HESSIAN_REGULARIZATION * ca.SX.eye(x.size1())
    return ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [h],
                       ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])


def sqp_options(nlp: dict, structure: OCPStructure, max_iter: int, tol: float = 1e-8,
                residuals=None, hpipm: dict | None = None) -> dict:
    """``sqpmethod`` options: Gauss-Newton Hessian, HPIPM on ``structure``.

    Args:
        nlp: the NLP (for the Hessian function).
        structure: its stage structure (sizes must match the NLP).
        max_iter: SQP iterations (a real-time iteration scheme bounds them).
        tol: primal and dual tolerance.
        residuals: see :func:`gauss_newton_hessian`.
        hpipm: HPIPM options (default: 50 iterations, mode "speed": relative
            tolerances; "speed_abs" stops too early for the SQP to converge).

    Raises:
        ValueError: the structure's sizes do not match the NLP's.
    """
    nv, nr = structure.sizes()
    if (nv, nr) != (nlp["x"].size1(), nlp["g"].size1()):
        raise ValueError(f"OCP structure of {nv} variables and {nr} rows for an NLP of "
                         f"{nlp['x'].size1()} variables and {nlp['g'].size1()} rows")
    qp = {**structure.qpsol_options(), "print_problem": False, "error_on_fail": False,
          "hpipm": {"iter_max": 50, "mode": "speed", **(hpipm or {})}}
    return {"expand": True, "print_time": False, "print_header": False,
            "print_iteration": False, "print_status": False, "max_iter": max_iter,
            "tol_pr": tol, "tol_du": tol, "hess_lag": gauss_newton_hessian(nlp, residuals),
            "qpsol": "hpipm", "qpsol_options": qp}


def rti_step_kept(status: str, converged: bool, violation: float) -> bool:
    """Whether a real-time iteration's result is kept as the plan.

    It is if it converged, or stopped at its iteration limit with a finite iterate: its
    remaining violation is what the next periods' steps reduce. A QP HPIPM failed to
    solve is not told apart: CasADi 3.8's ``sqpmethod`` (``error_on_fail`` off) reports
    its iteration limit then too and its statistics carry no QP status, so such a step is
    kept if its iterate is finite (its violation is logged in /mpc/solve).
    """
    if converged:
        return True
    return status == "Maximum_Iterations_Exceeded" and bool(np.isfinite(violation))


def rti_success(status: str, converged: bool, violation: float) -> bool:
    """Whether a bounded SQP run succeeded.

    It did if it converged, or stopped at its iteration limit at a point violating no
    row or bound by more than :data:`RTI_VIOLATION`.
    """
    if converged:
        return True
    return status == "Maximum_Iterations_Exceeded" and bool(np.isfinite(violation)) \
        and violation <= RTI_VIOLATION
