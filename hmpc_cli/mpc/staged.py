"""An NLP's functions assembled from stage kernels: its cost, rows and IPOPT's derivatives.

An NLP made of stages of a few kinds (the chain NLP's links and last node:
:meth:`~hmpc_cli.mpc.chain.nlp.FixedModeNLP._stage_kinds`) has one SX function per kind,
(stage variables, stage parameters) -> (rows[, cost]). From it come small SX *kernels*
(its rows, its cost, their Jacobian and gradient in the stage's variables, the Hessian of
its Lagrangian), each mapped over its stages in MX on gathers of x and p; a constant 0/1
matrix puts each entry of a derivative at its place, summing where a variable is in two
stages. The functions are ``nlpsol``'s from the whole SX graph (the stages' operations
written out) bit for bit, the same instructions on the same numbers, with one exception:
the Hessian where a variable is in two stages' rows (u_k with a first-order hold), whose
two sums are associated otherwise (equal to rounding). They are made in a fraction of the
time ``nlpsol`` takes to differentiate the whole graph (docs/performance.md), and each
kernel can run as its compiled C (:func:`hmpc_cli.mpc.kernels.compiled`: the same
numbers, several times faster).
"""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np

from hmpc_cli.mpc import kernels


@dataclasses.dataclass(frozen=True)
class StageKind:
    """One kind of stage, in the order of the NLP's rows.

    Attributes:
        fn: its SX function (stage variables..., parameters) -> (rows, cost), or -> rows
            (a stage without cost).
        count: its stages, whose rows follow each other in g, stage by stage.
        variables: per variable argument of ``fn``, its entries of x (shape (width,
            count), one column per stage) and their indices into x (shape (count, width)).
        parameters: the stages' parameters, shape (parameter width, count).
    """

    fn: ca.Function
    count: int
    variables: list[tuple[ca.MX, np.ndarray]]
    parameters: ca.MX

    @property
    def has_cost(self) -> bool:
        """Whether ``fn`` returns a stage cost."""
        return self.fn.n_out() == 2

    @property
    def n_rows(self) -> int:
        """Rows per stage."""
        return self.fn.size1_out(0)

    def columns(self) -> np.ndarray:
        """The stage variables' indices into x, shape (count, stage variables)."""
        return np.hstack([idx for _, idx in self.variables])


class StagedNLP:
    """The cost, rows and derivatives of an NLP of :class:`StageKind` s, as MX functions.

    Args:
        kinds: the NLP's kinds of stage, in the order of its rows (built on ``x`` and ``p``).
        x: the NLP's variables, an MX symbol of shape (nx, 1).
        p: its parameters, an MX symbol.
        slack: (indices into x, weight w): the cost's exact penalty w * sum of those
            entries of x, added after the stages' costs.
        compiled: each kernel as its C library where the cache holds one (else its compile
            is started for a later run; :func:`hmpc_cli.mpc.kernels.compiled`).
    """

    def __init__(self, kinds: list[StageKind], x: ca.MX, p: ca.MX,
                 slack: tuple[np.ndarray, float], compiled: bool = False) -> None:
        """Keeps the stage kinds; the functions are made on request."""
        self.kinds, self.x, self.p = kinds, x, p
        self.slack, self.compiled = slack, compiled
        self.nx = x.size1()
        sizes = [k.n_rows * k.count for k in kinds]
        self.ng = sum(sizes)
        #: per kind, the index of its first row in g
        self.first_rows = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)
        #: the kernels made so far, as evaluated: SX functions or their C libraries
        self.made: list[ca.Function] = []

    # ---------------------------------------------------------------- kernels
    def _mapped(self, kind: StageKind, what: str, outputs, extra=()) -> tuple[list, object]:
        """The kernel ``<fn>_<what>`` mapped over the kind's stages.

        ``outputs(kind, symbols, stage_variables)`` gives the kernel's SX outputs from
        ``fn``'s argument symbols (and those of its variables stacked) and what the caller
        keeps of them (a derivative's sparsity); ``extra``: (SX symbol, its MX argument)
        pairs of further inputs after them. Returns the map's outputs, one column per
        stage, and what ``outputs`` kept.
        """
        fn = kind.fn
        sym = [ca.SX.sym(f"v{i}", fn.size1_in(i)) for i in range(fn.n_in())]
        out, kept = outputs(kind, sym, ca.vertcat(*sym[:len(kind.variables)]))
        kernel = ca.Function(f"{fn.name()}_{what}", [*sym, *(s for s, _ in extra)], out)
        kernel = kernels.compiled(kernel) if self.compiled else kernel
        self.made.append(kernel)
        mapped = kernel.map(kind.count).call([*(c for c, _ in kind.variables),
                                              kind.parameters, *(a for _, a in extra)])
        return mapped, kept

    # -------------------------------------------------------------- functions
    def nlp(self) -> dict:
        """The NLP ``{"x", "p", "f", "g"}`` in MX, f and g from the cost and rows kernels."""
        rows = [ca.vec(self._mapped(k, "rows", _rows)[0][0]) for k in self.kinds]
        costs = [self._mapped(k, "cost", _cost)[0][0] for k in self.kinds if k.has_cost]
        return {"x": self.x, "p": self.p, "f": self._cost(costs), "g": ca.vertcat(*rows)}

    def gradient(self) -> ca.Function:
        """(x, p) -> (f, df/dx), named as ``nlpsol``'s ``nlp_grad_f``."""
        costs, values, columns = [], [], []
        for k in self.kinds:
            if k.has_cost:
                (cost, grad), entries = self._mapped(k, "grad", _gradient)
                costs.append(cost)
                values.append(ca.vec(grad))
                columns.append(k.columns()[:, entries].ravel())
        idx, weight = self.slack  # d(w sum sigma)/d sigma = w
        values.append(ca.DM.ones(idx.size) * weight)
        c = np.concatenate([*columns, idx])
        grad = _assembled(ca.vertcat(*values), np.arange(c.size), c, np.zeros_like(c),
                          (self.nx, 1))
        return ca.Function("nlp_grad_f", [self.x, self.p], [self._cost(costs), grad],
                           ["x", "p"], ["f", "grad_f_x"])

    def jacobian(self) -> ca.Function:
        """(x, p) -> (g, dg/dx), named as ``nlpsol``'s ``nlp_jac_g``.

        Every row is one stage's, so no entry is a sum.
        """
        rows, values, r_all, c_all = [], [], [], []
        for k, first in zip(self.kinds, self.first_rows, strict=True):
            (g, jac), (r, c) = self._mapped(k, "jac", _jacobian)
            rows.append(ca.vec(g))
            values.append(ca.vec(jac))
            stage_rows = first + np.arange(k.count)[:, None] * k.n_rows
            r_all.append((stage_rows + np.asarray(r, dtype=int)[None, :]).ravel())
            c_all.append(k.columns()[:, c].ravel())
        r, c = np.concatenate(r_all), np.concatenate(c_all)
        jac = _assembled(ca.vertcat(*values), np.arange(r.size), r, c, (self.ng, self.nx))
        return ca.Function("nlp_jac_g", [self.x, self.p], [ca.vertcat(*rows), jac],
                           ["x", "p"], ["g", "jac_g_x"])

    def hessian(self) -> ca.Function:
        """(x, p, lam_f, lam_g) -> triu(H), named as ``nlpsol``'s ``nlp_hess_l``.

        H, shape (nx, nx), is the Hessian of lam_f f + lam_g^T g in x. Each kind's
        kernel is the Hessian of lam_f cost + lam^T rows (the cost first, as ``nlpsol``
        forms the Lagrangian) in its stage variables; the assembled sparsity is the whole
        graph's Hessian's.
        """
        lam_f, lam_g = ca.MX.sym("lam_f"), ca.MX.sym("lam_g", self.ng)
        values, r_all, c_all = [], [], []
        for k, first in zip(self.kinds, self.first_rows, strict=True):
            lam, lf = ca.SX.sym("lam", k.n_rows), ca.SX.sym("lam_f")

            def outputs(kind, s, v, lam=lam, lf=lf):
                out = _outputs(kind, s)
                lag = lf * out[1] + ca.dot(lam, out[0]) if kind.has_cost else \
                    ca.dot(lam, out[0])
                h = ca.hessian(lag, v)[0]
                return [h.nz[:]], h.sparsity().get_triplet()

            span = lam_g[int(first):int(first) + k.n_rows * k.count]
            (h,), (r, c) = self._mapped(k, "hess", outputs, extra=(
                (lam, ca.reshape(span, k.n_rows, k.count)), (lf, ca.repmat(lam_f, 1, k.count))))
            values.append(ca.vec(h))
            r_all.append(k.columns()[:, r].ravel())
            c_all.append(k.columns()[:, c].ravel())
        r, c = np.concatenate(r_all), np.concatenate(c_all)
        upper = np.flatnonzero(r <= c)
        hess = _assembled(ca.vertcat(*values), upper, r[upper], c[upper], (self.nx, self.nx))
        return ca.Function("nlp_hess_l", [self.x, self.p, lam_f, lam_g], [hess],
                           ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])

    def derivatives(self) -> dict[str, ca.Function]:
        """IPOPT's derivative functions, by ``nlpsol`` option."""
        return {"grad_f": self.gradient(), "jac_g": self.jacobian(), "hess_lag": self.hessian()}

    def _cost(self, costs: list[ca.MX]) -> ca.MX:
        """The cost f from the kinds' per-stage costs (:func:`total_cost`)."""
        return total_cost(costs, self.x, self.slack)


def total_cost(costs: list[ca.MX], x: ca.MX, slack: tuple[np.ndarray, float]) -> ca.MX:
    """The NLP's cost f from its kinds' stage costs (one row each, a column per stage).

    Summed in the one order every form of the NLP shares (so they are equal bit for bit):
    each kind's stages, the kinds in order, then the slack penalty (``slack``: indices
    into x, weight).
    """
    total = ca.sum2(costs[0])
    for cost in costs[1:]:
        total = total + ca.sum2(cost)
    idx, weight = slack
    return total + weight * ca.sum1(x[idx.tolist()])


def _outputs(kind: StageKind, sym: list[ca.SX]) -> list[ca.SX]:
    """``kind.fn`` on ``sym``: [rows, cost], or [rows] for a kind without cost."""
    out = kind.fn(*sym)
    return list(out) if kind.has_cost else [out]


# Kernel outputs (for StagedNLP._mapped): (SX outputs, what the caller keeps of them).
def _rows(kind: StageKind, sym: list[ca.SX], _v: ca.SX) -> tuple[list, None]:
    return [_outputs(kind, sym)[0]], None


def _cost(kind: StageKind, sym: list[ca.SX], _v: ca.SX) -> tuple[list, None]:
    return [_outputs(kind, sym)[1]], None


def _gradient(kind: StageKind, sym: list[ca.SX], v: ca.SX) -> tuple[list, list]:
    """The cost and its gradient's nonzeros; kept: their rows in the stage variables."""
    cost = _outputs(kind, sym)[1]
    grad = ca.gradient(cost, v)
    return [cost, grad.nz[:]], grad.sparsity().row()


def _jacobian(kind: StageKind, sym: list[ca.SX], v: ca.SX) -> tuple[list, tuple]:
    """The rows and their Jacobian's nonzeros; kept: its (rows, columns) triplet."""
    g = _outputs(kind, sym)[0]
    jac = ca.jacobian(g, v)
    return [g, jac.nz[:]], jac.sparsity().get_triplet()


def _assembled(values: ca.MX, at: np.ndarray, r: np.ndarray, c: np.ndarray,
               shape: tuple[int, int]) -> ca.MX:
    """The sparse matrix of ``shape`` whose entry (r[i], c[i]) sums ``values[at[i]]``.

    A constant 0/1 matrix times ``values``; the nonzeros in column-major order.
    """
    n_rows = shape[0]
    entry, which = np.unique(c * n_rows + r, return_inverse=True)
    total = ca.DM(ca.Sparsity.triplet(entry.size, values.size1(), which.tolist(),
                                      at.tolist()), 1.0)
    sparsity = ca.Sparsity.triplet(*shape, (entry % n_rows).tolist(),
                                   (entry // n_rows).tolist())
    return ca.MX(sparsity, ca.mtimes(total, values))
