"""Probe: the switching NLP's rows as one SX stage function mapped over the nodes.

Run on demand:  python benchmarks/probe_stagewise.py [scenario.toml]

Builds the fixed-mode MPC's switching NLP of the scenario (default scenarios/ball.toml)
three ways in one process and prints their set-up time and the evaluation time of the
Hessian of the Lagrangian and the constraint Jacobian that IPOPT calls every iteration:

* the whole NLP in SX, as hmpc builds it (transcription, then ``nlpsol``);
* one stage (interval k: dynamics and node k's path rows, its cost) as an SX function,
  mapped over the L intervals in MX, left in MX;
* the same, expanded to SX by ``nlpsol``.

The mapped NLP leaves out the last node's rows and the terminal set (a few rows) and
orders rows and variables by stage: it is for timing, not solving. Measured, never
asserted; the findings are in docs/performance.md ("Why the last three rows are not met").
"""

from __future__ import annotations

import contextlib
import os
import sys
import time

import casadi as ca
import numpy as np

from hmpc_cli.core.registry import build_system
from hmpc_cli.mpc.chain.nlp import FixedModeNLP
from hmpc_cli.run.scenario import load_scenario


class _Rows:
    """Collects the rows :meth:`FixedModeNLP._path_rows` registers (a builder stand-in)."""

    def __init__(self) -> None:
        self.rows_: list = []

    def rows(self, name: str, expr, shape=None) -> None:
        self.rows_.append(ca.vertcat(*expr) if isinstance(expr, list) else ca.vec(expr))

    @contextlib.contextmanager
    def stage(self, k):
        yield


def stage_nlp(nlp: FixedModeNLP, system, penalty: float) -> dict:
    """The NLP ``{"x", "p", "f", "g"}`` in MX: one SX stage function mapped over L."""
    n, m, L = nlp.n, nlp.m, nlp.L
    z, u, un, zn = (ca.SX.sym(k, d) for k, d in (("z", n), ("u", m), ("un", m), ("zn", n)))
    sig = ca.SX.sym("sig")
    shapes = {"a": nlp.M, "b": nlp.G, "e": 1, "w": 1, "v": 1, "foh": 1, "s": nlp.Gr,
              "kappa": nlp.Gr, "beta": nlp.G, "kappa_v": 1, "hit": nlp.G}
    par = {k: ca.SX.sym(k, 1, d) for k, d in shapes.items()}
    pvec = ca.vertcat(*[ca.vec(par[k]) for k in shapes])
    nlp._par = par  # _path_rows reads the parameters of "stage 0": this stage's
    flows = [nlp._interval(i, z, u, u + par["foh"][0] * (un - u)) for i in nlp.modes_in]
    nxt = par["e"][0] * z
    for c in range(nlp.M):
        nxt += par["a"][0, c] * flows[c]
    for i, g in enumerate(system.guards):
        nxt += par["b"][0, i] * g.reset(z)
    rows = _Rows()
    rows.rows("dynamics", zn - nxt)
    nlp._path_rows(rows, 0, z, flows, sig)
    cost = par["w"][0] * system.stage_cost(z, u) + par["v"][0] * ca.sumsqr(u)
    stage = ca.Function("stage", [z, u, un, sig, zn, pvec], [ca.vertcat(*rows.rows_), cost])
    Z, U = ca.MX.sym("Z", n, L + 1), ca.MX.sym("U", m, L)
    S, P = ca.MX.sym("S", 1, L + 1), ca.MX.sym("P", pvec.numel(), L)
    g, f = stage.map(L)(Z[:, :L], U, ca.horzcat(U[:, 1:], U[:, -1:]), S[:, :L], Z[:, 1:], P)
    return {"x": ca.vertcat(ca.vec(Z), ca.vec(U), ca.vec(S)), "p": ca.vec(P),
            "f": ca.sum2(f) + penalty * ca.sum2(S), "g": ca.vec(g)}


def evaluation_ms(solver: ca.Function, reps: int = 30) -> dict[str, float]:
    """Mean time [ms] of one call of the solver's Hessian and Jacobian at random points."""
    out = {}
    for fn in ("nlp_hess_l", "nlp_jac_g"):
        f = solver.get_function(fn)
        rng = np.random.default_rng(0)
        args = [ca.DM(f.sparsity_in(i), rng.standard_normal(f.sparsity_in(i).nnz()))
                for i in range(f.n_in())]
        f(*args)
        start = time.perf_counter()
        for _ in range(reps):
            f(*args)
        out[fn] = (time.perf_counter() - start) / reps * 1e3
    return out


def main() -> None:
    os.environ["HMPC_BUILD_CACHE"] = "off"  # the SX build, whatever the cache holds
    sc = load_scenario(sys.argv[1] if len(sys.argv) > 1 else "scenarios/ball.toml")[0]
    system = build_system(sc.system)
    nlp = FixedModeNLP(system, sc.mpc)
    opts = {"print_time": False}
    start = time.perf_counter()
    whole, _ = nlp._transcription()
    t_tr = time.perf_counter() - start
    start = time.perf_counter()
    sx = ca.nlpsol("whole", "ipopt", whole, {**opts, "expand": True})
    t_sx = time.perf_counter() - start
    start = time.perf_counter()
    mapped = stage_nlp(nlp, system, sc.mpc.soft_penalty)
    t_map = time.perf_counter() - start
    start = time.perf_counter()
    mx = ca.nlpsol("mapped", "ipopt", mapped, opts)
    t_mx = time.perf_counter() - start
    start = time.perf_counter()
    mxe = ca.nlpsol("mapped_sx", "ipopt", mapped, {**opts, "expand": True})
    t_mxe = time.perf_counter() - start
    print(f"switching NLP: L = {nlp.L} intervals, {whole['x'].numel()} variables, "
          f"{whole['g'].numel()} rows")
    for label, setup, solver in (
            (f"whole SX (transcription {t_tr:.3f} s + nlpsol {t_sx:.3f} s)", t_tr + t_sx, sx),
            (f"stage map, MX (stage {t_map:.3f} s + nlpsol {t_mx:.3f} s)", t_map + t_mx, mx),
            (f"stage map, expanded (stage {t_map:.3f} s + nlpsol {t_mxe:.3f} s)",
             t_map + t_mxe, mxe)):
        ev = evaluation_ms(solver)
        print(f"{label}: set-up {setup:.3f} s; Hessian {ev['nlp_hess_l']:.2f} ms, "
              f"Jacobian {ev['nlp_jac_g']:.2f} ms")


if __name__ == "__main__":
    main()
