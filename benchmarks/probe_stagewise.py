"""Probe: the fixed-mode NLP's stage functions mapped over the links, kept in MX or expanded.

Run on demand:  python benchmarks/probe_stagewise.py [scenario.toml]

hmpc transcribes the chain NLP as one SX function per kind of stage, mapped over the
links in MX and expanded to SX (``FixedModeNLP._staged_nlp``): the graph the operations
written out at every node give, instruction for instruction. This probe builds the
scenario's switching NLP (default scenarios/ball.toml) both ways in one process and
prints their set-up time (transcription and ``nlpsol``) and the evaluation time of the
Hessian of the Lagrangian and the constraint Jacobian that IPOPT calls every iteration:

* expanded to SX, as hmpc builds it;
* the map kept in MX (a faster set-up, slower evaluations in the MX virtual machine,
  and other derivative graphs: other iterates).

Measured, never asserted; the findings are in docs/performance.md.
"""

from __future__ import annotations

import os
import sys
import time

import casadi as ca
import numpy as np

from hmpc_cli.core.registry import build_system
from hmpc_cli.mpc.chain.nlp import FixedModeNLP
from hmpc_cli.run.scenario import load_scenario


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
    nlp = FixedModeNLP(build_system(sc.system), sc.mpc)
    opts = {"print_time": False}
    start = time.perf_counter()
    whole, layout = nlp._transcription()
    t_tr = time.perf_counter() - start
    start = time.perf_counter()
    sx = ca.nlpsol("whole", "ipopt", whole, {**opts, "expand": True})
    t_sx = time.perf_counter() - start
    start = time.perf_counter()
    fn = nlp._staged_nlp(layout, expand=False)
    x, p = ca.MX.sym("x", fn.size1_in(0)), ca.MX.sym("p", fn.size1_in(1))
    f, g = fn.call([x, p])
    t_map = time.perf_counter() - start
    start = time.perf_counter()
    mx = ca.nlpsol("mapped", "ipopt", {"x": x, "p": p, "f": f, "g": g}, opts)
    t_mx = time.perf_counter() - start
    print(f"switching NLP: L = {nlp.L} intervals, {whole['x'].numel()} variables, "
          f"{whole['g'].numel()} rows")
    for label, setup, solver in (
            (f"expanded to SX, hmpc's (transcription {t_tr:.3f} s + nlpsol {t_sx:.3f} s)",
             t_tr + t_sx, sx),
            (f"kept in MX (map {t_map:.3f} s + nlpsol {t_mx:.3f} s)", t_map + t_mx, mx)):
        ev = evaluation_ms(solver)
        print(f"{label}: set-up {setup:.3f} s; Hessian {ev['nlp_hess_l']:.2f} ms, "
              f"Jacobian {ev['nlp_jac_g']:.2f} ms")


if __name__ == "__main__":
    main()
