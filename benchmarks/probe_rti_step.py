"""Probe: a hand-rolled real-time iteration beside CasADi's ``sqpmethod`` (one process).

Run:  python benchmarks/probe_rti_step.py        (trial 1's recorded problems, ~1 min)

``mpc.solver = "rti"`` runs ``sqpmethod`` for one full SQP step. After its last step
``sqpmethod`` evaluates the gradient and the constraint Jacobian (``nlp_jac_fg``) once
more, for a convergence test whose verdict a real-time iteration does not use. The probe
takes the functions ``sqpmethod`` generated (``nlp_jac_fg``, ``nlp_hess_l``) and the NLP's
own ``(x, p) -> (f, g)``, runs the same step in Python around them (convergence and step
tests before the step, the QP from dx = 0 with the current multipliers, step and QP
multipliers taken in full, f and g of the new iterate from the NLP's function) and
prints, per NLP, how many of the warm-started problems give ``sqpmethod``'s iterate and
multipliers bit for bit, and both median wall times.

CasADi's HPIPM conic is called on a fresh ``FunctionBuffer`` (and so fresh memory) per
QP: on one buffer reused, its second call with the same inputs returns another step (the
probe prints whether it does). Inside hmpc's solver session (branch
``exp/rti-python-steps``) the Python around the calls spends what the evaluation saves:
docs/performance.md, "Real time: the real-time iterations".
Timing is measured, never asserted.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

import bench_backends as bb
import suite
from hmpc_cli.mpc.chain.nlp import FixedModeNLP
from hmpc_cli.run.runner import prepare
from hmpc_cli.run.scenario import load_scenario

OUTPUTS = ("x", "f", "g", "lam_x", "lam_g")


def _buffer(fn: ca.Function) -> tuple:
    """(evaluate, input arrays, output arrays, the buffer) of ``fn`` on one ``FunctionBuffer``
    (the buffer must outlive the calls of ``evaluate``)."""
    buf, evaluate = fn.buffer()
    ins = [np.zeros(fn.nnz_in(k)) for k in range(fn.n_in())]
    outs = [np.zeros(fn.nnz_out(k)) for k in range(fn.n_out())]
    for k, a in enumerate(ins):
        buf.set_arg(k, memoryview(a))
    for k, a in enumerate(outs):
        buf.set_res(k, memoryview(a))
    return evaluate, ins, outs, buf


class HandRolledStep:
    """One full Gauss-Newton SQP step on ``sqpmethod``'s own functions (see the module)."""

    def __init__(self, sqp: ca.Function, qp_options: dict, tol: float = 1e-8) -> None:
        jac_fg = sqp.get_function("nlp_jac_fg")
        self.jac = _buffer(jac_fg)
        self.hess = _buffer(sqp.get_function("nlp_hess_l"))
        self.fg = _buffer(sqp.oracle())
        q = sqp.find_function("qpsol")
        self.conic = ca.conic("rti_qp", "hpipm", {"h": q.sparsity_in(0),
                                                  "a": q.sparsity_in(2)}, qp_options)
        jac = jac_fg.sparsity_out(3)
        self.col = np.repeat(np.arange(jac.size2()), np.diff(jac.colind()))
        self.row = np.asarray(jac.row())
        self.tol = tol
        self.last_qp: list[np.ndarray] = []  # the last QP's input arrays (its own buffer's)

    def qp(self, ins: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(dx, lam_x, lam_a) of the QP with inputs ``ins`` (conic's order), fresh memory."""
        evaluate, arr_in, out, _buf = _buffer(self.conic)
        for a, v in zip(arr_in, ins, strict=True):
            a[:] = v
        evaluate()
        self.last_qp = arr_in  # a fresh buffer's arrays: kept without a copy in the timing
        return out[0].copy(), out[3].copy(), out[2].copy()

    def __call__(self, x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0) -> dict:
        """The step from (x0, lam_x0, lam_g0); outputs as ``sqpmethod``'s (1 iteration)."""
        nx = x0.size
        (jev, jin, jout, _), (hev, hin, hout, _) = self.jac, self.hess
        z, lam = np.concatenate([x0, np.zeros(lbg.size)]), np.concatenate([lam_x0, lam_g0])
        lbz, ubz = np.concatenate([lbx, lbg]), np.concatenate([ubx, ubg])
        jin[0][:], jin[1][:] = x0, p
        jev()
        z[nx:] = jout[2]
        glag = jout[1].copy()
        np.add.at(glag, self.col, jout[3] * lam[nx:][self.row])
        glag += lam[:nx]
        if max(0.0, np.max(z - ubz), np.max(lbz - z)) < self.tol and \
                np.max(np.abs(glag)) < self.tol:
            return {"x": x0.copy(), "f": jout[0][0], "g": z[nx:].copy(), "lam_x": lam[:nx],
                    "lam_g": lam[nx:], "iter": 0}
        hin[0][:], hin[1][:], hin[2][:], hin[3][:] = x0, p, 1.0, lam[nx:]
        hev()
        lbd, ubd = lbz - z, ubz - z
        dx, lam_x, lam_a = self.qp([hout[0], jout[1], jout[3], lbd[nx:], ubd[nx:], lbd[:nx],
                                    ubd[:nx], np.zeros(nx), lam[:nx], lam[nx:], [], []])
        x = x0 + dx
        fev, fin, fout, _ = self.fg
        fin[0][:], fin[1][:] = x, p
        fev()
        return {"x": x, "f": fout[0][0], "g": fout[1].copy(), "lam_x": lam_x, "lam_g": lam_a,
                "iter": 1}


def _median_ms(times: list[float]) -> float:
    return 1e3 * float(np.median(times))


def compare(trial: int = 1) -> list[dict]:
    """Per NLP: problems, bit-identical steps, both median times [ms], buffer reuse."""
    problems, _ = suite.record(trial, [])
    sc, _ = load_scenario(bb.SCENARIO, [*bb.ZOH, f"disturbance.trial={trial}"])
    final = prepare(sc).mpc.chain.nlps.final
    settings = final.s.model_copy(update={"solver": "rti", "switching_solver": "rti",
                                          "max_sqp_iter": 1})
    rows = []
    for which, switches in (("final", 0), ("switching", None)):
        nlp = FixedModeNLP(final.system, settings, switches=switches)
        solver = nlp.session.warm
        step = HandRolledStep(solver.function, nlp.session.options["qpsol_options"])
        same, t_sqp, t_hand = 0, [], []
        chosen = [q for q in problems if q.nlp == which and q.args[6] is not None]
        for prob in chosen:
            w0, p, lbx, ubx, lbg, ubg, lx, lg = prob.args
            lx = np.where(np.isfinite(lbx) | np.isfinite(ubx), lx, 0.0)
            lg = np.where(np.isfinite(lbg) | np.isfinite(ubg), lg, 0.0)
            start = time.perf_counter()
            a = solver(x0=w0, p=p, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg, lam_x0=lx, lam_g0=lg)
            t_sqp.append(time.perf_counter() - start)
            start = time.perf_counter()
            b = step(w0, p, lbx, ubx, lbg, ubg, lx, lg)
            t_hand.append(time.perf_counter() - start)
            same += all(np.array_equal(np.ravel(a[k]), np.ravel(b[k])) for k in OUTPUTS) \
                and int(solver.stats()["iter_count"]) == b["iter"]
        rows.append({"nlp": which, "problems": len(chosen), "identical": same,
                     "sqpmethod_ms": _median_ms(t_sqp), "hand_ms": _median_ms(t_hand),
                     "reused_buffer_same": _reuse_gives_same_step(step)})
    return rows


def _reuse_gives_same_step(step: HandRolledStep) -> bool:
    """Whether the conic on one reused buffer gives the last QP's step twice."""
    evaluate, ins, outs, _buf = _buffer(step.conic)
    for a, v in zip(ins, step.last_qp, strict=True):
        a[:] = v
    evaluate()
    first = outs[0].copy()
    for a in outs:
        a[:] = 0.0
    evaluate()
    return bool(np.array_equal(first, outs[0]))


def main() -> None:
    """Prints :func:`compare` as a Markdown table."""
    print("| NLP | problems | bit-identical | sqpmethod median ms | hand-rolled median ms |")
    print("|---|--:|--:|--:|--:|")
    for r in compare():
        print(f"| {r['nlp']} | {r['problems']} | {r['identical']} | {r['sqpmethod_ms']:.2f} | "
              f"{r['hand_ms']:.2f} |")
        print(f"  {r['nlp']}: the conic on one reused buffer, same inputs twice: "
              f"{'the same step' if r['reused_buffer_same'] else 'another step'}")


if __name__ == "__main__":
    main()
