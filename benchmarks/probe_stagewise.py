"""Probe: the fixed-mode NLP's stage functions mapped over the links, kept in MX or expanded.

Run on demand:  python benchmarks/probe_stagewise.py [scenario.toml]

hmpc has one SX function per kind of the chain NLP's stages. This probe builds the
scenario's switching NLP (default scenarios/ball.toml) three ways in one process and
prints their set-up time (transcription and ``nlpsol``) and the evaluation time of the
Hessian of the Lagrangian and the constraint Jacobian that IPOPT calls every iteration:

* mapped over the links in MX and expanded to SX (``FixedModeNLP._staged_nlp``: the graph
  the operations written out at every node give, instruction for instruction), with
  ``nlpsol``'s derivatives of the whole graph: what the other back-ends and the build
  cache's compiled library start from;
* the map kept in MX, ``nlpsol`` differentiating it (a faster set-up, slower evaluations
  in the MX virtual machine, and other derivative graphs: other iterates);
* assembled from stage kernels (``FixedModeNLP._staged``: hmpc's for IPOPT), its
  derivatives given to ``nlpsol``, the kernels in SX.

Then, for either input hold, both NLPs' Hessian of the Lagrangian assembled stage by stage
(:func:`staged_hessian`, given to IPOPT as ``hess_lag``) against the one ``nlpsol``
generates from the whole graph: set-up, evaluation, and how many of its entries differ
bit for bit at random points (:func:`hessian_rows`). Last, the constraint Jacobian
assembled the same way (``jac_g``) against ``nlpsol``'s (:func:`jacobian_rows`).

Measured, never asserted; the findings are in docs/performance.md.
"""

from __future__ import annotations

import os
import sys
import time

import casadi as ca
import numpy as np

from hmpc_cli.core.registry import build_system
from hmpc_cli.mpc.builder import NLPLayout
from hmpc_cli.mpc.chain.nlp import FixedModeNLP, MPCSettings
from hmpc_cli.run.scenario import load_scenario

#: nlpsol options of every build here: hmpc's (no ``nlp_grad``, no ``lam_p``), silent
QUIET = {"print_time": False, "no_nlp_grad": True, "calc_lam_p": False,
         "ipopt.print_level": 0}


def evaluation_ms(solver: ca.Function, reps: int = 30) -> dict[str, float]:
    """Mean time [ms] of one call of the solver's Hessian and Jacobian at random points."""
    out = {}
    for fn in ("nlp_hess_l", "nlp_jac_g"):
        f = solver.get_function(fn)
        rng = np.random.default_rng(0)
        args = [ca.DM(f.sparsity_in(i), rng.standard_normal(f.sparsity_in(i).nnz()))
                for i in range(f.n_in())]
        out[fn] = call_ms(f, args, reps)
    return out


def call_ms(f: ca.Function, args: list, reps: int = 30) -> float:
    """Mean time [ms] of one call of f on args (after one call)."""
    f(*args)
    start = time.perf_counter()
    for _ in range(reps):
        f(*args)
    return (time.perf_counter() - start) / reps * 1e3


def staged_hessian(nlp: FixedModeNLP, layout: NLPLayout, expand: bool = False) -> ca.Function:
    """hmpc's Hessian of the Lagrangian assembled stage by stage (``_staged_hessian``).

    The map kept in MX, as hmpc gives it to IPOPT; ``expand`` makes the whole of it SX.
    """
    fn = nlp._staged_hessian(layout)
    return fn.expand() if expand else fn


def hessian_rows(system, settings: MPCSettings, points: int = 3,
                 reps: int = 30) -> list[dict]:
    """Per NLP (switching, final domain): ``nlpsol``'s Hessian against :func:`staged_hessian`.

    Keys: ``nlp``; ``nnz`` (upper triangle) and ``same_sparsity``; ``differing`` (the most
    entries not equal bit for bit at one of ``points`` random points (x, p, lam_f, lam_g),
    either staged Hessian), ``max_diff`` and ``max_abs`` (the largest |difference| and
    |entry| at any of them; a NaN difference counts as inf), ``blocks`` (the pairs of
    variable blocks, sorted names of z, u, sigma, of the entries that differ); set-up [s]:
    ``nlpsol`` (all of it, its own Hessian included), ``staged_mx`` and ``staged_sx`` (the
    Hessian, then ``nlpsol`` given it); one Hessian call [ms], mean of ``reps``:
    ``eval_nlpsol``, ``eval_mx``, ``eval_sx``.
    """
    out = []
    for label, switches in (("switching", None), ("final", 0)):
        nlp = FixedModeNLP(system, settings, switches=switches)
        whole, layout = nlp._transcription()
        row: dict = {"nlp": label}
        start = time.perf_counter()
        reference = ca.nlpsol("whole", "ipopt", whole, QUIET).get_function("nlp_hess_l")
        row["nlpsol"] = time.perf_counter() - start
        staged = {}
        for kind in ("mx", "sx"):
            start = time.perf_counter()
            staged[kind] = staged_hessian(nlp, layout, expand=kind == "sx")
            ca.nlpsol("staged", "ipopt", whole, {**QUIET, "hess_lag": staged[kind]})
            row[f"staged_{kind}"] = time.perf_counter() - start
        row["nnz"] = reference.sparsity_out(0).nnz()
        row["same_sparsity"] = all(reference.sparsity_out(0) == f.sparsity_out(0)
                                   for f in staged.values())
        rng = np.random.default_rng(0)
        row.update(differing=0, max_diff=0.0, max_abs=0.0, blocks=set())
        block = np.empty(layout.x.size, dtype=object)
        for name in ("z", "u", "sigma"):
            block[layout.x[name].ravel()] = name
        for _ in range(points):
            args = [rng.standard_normal(whole["x"].numel()), rng.uniform(size=whole["p"].numel()),
                    rng.standard_normal(), rng.standard_normal(whole["g"].numel())]
            ref = reference(*args).full()
            for f in staged.values():
                diff = np.nan_to_num(np.abs(f(*args).full() - ref), nan=np.inf)
                row["differing"] = max(row["differing"], int(np.count_nonzero(diff)))
                row["max_diff"] = max(row["max_diff"], float(diff.max()))
                row["blocks"] |= {tuple(sorted(block[[i, j]]))
                                  for i, j in np.argwhere(diff)}
            row["max_abs"] = max(row["max_abs"], float(np.abs(ref).max()))
        for key, f in (("eval_nlpsol", reference), ("eval_mx", staged["mx"]),
                       ("eval_sx", staged["sx"])):
            row[key] = call_ms(f, args, reps)
        out.append(row)
    return out


def jacobian_rows(system, settings: MPCSettings, points: int = 3) -> list[dict]:
    """Per NLP (switching, final domain): ``nlpsol``'s constraint Jacobian against hmpc's
    assembled stage by stage: ``nnz``, ``same_sparsity``, ``differing`` (the most entries
    of g and the Jacobian not equal bit for bit at one of ``points`` random points (x, p));
    set-up [s]: ``staged`` (the staged Jacobian) and ``nlpsol`` (its Jacobian and
    gradient, the staged Hessian given)."""
    out = []
    for label, switches in (("switching", None), ("final", 0)):
        nlp = FixedModeNLP(system, settings, switches=switches)
        whole, layout = nlp._transcription()
        start = time.perf_counter()
        staged = nlp._staged(layout).jacobian()
        row: dict = {"nlp": label, "staged": time.perf_counter() - start}
        start = time.perf_counter()
        solver = ca.nlpsol("whole", "ipopt", whole, {
            **QUIET, "hess_lag": nlp._staged_hessian(layout)})
        row["nlpsol"] = time.perf_counter() - start
        reference = solver.get_function("nlp_jac_g")  # (x, p) -> (g, dg/dx)
        rng = np.random.default_rng(0)
        row["differing"] = 0
        for _ in range(points):
            args = [rng.standard_normal(nlp.nx_var), rng.uniform(size=nlp.np)]
            (g_ref, ref), (g, got) = reference(*args), staged(*args)
            row["same_sparsity"] = ref.sparsity() == got.sparsity()
            row["nnz"] = ref.nnz()
            row["differing"] = max(row["differing"], int(
                np.count_nonzero(np.asarray(ref.nonzeros()) != np.asarray(got.nonzeros()))
                + np.count_nonzero(g_ref.full() != g.full())))
        out.append(row)
    return out


def main() -> None:
    os.environ["HMPC_BUILD_CACHE"] = "off"  # the kernels in SX, whatever the cache holds
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
    start = time.perf_counter()
    staged = nlp._staged(layout)  # hmpc's options: no nlp_grad (it would differentiate it)
    kernels = ca.nlpsol("kernels", "ipopt", staged.nlp(), {**QUIET, **staged.derivatives()})
    t_kernels = time.perf_counter() - start
    print(f"switching NLP: L = {nlp.L} intervals, {whole['x'].numel()} variables, "
          f"{whole['g'].numel()} rows")
    for label, setup, solver in (
            (f"expanded to SX (transcription {t_tr:.3f} s + nlpsol {t_sx:.3f} s)",
             t_tr + t_sx, sx),
            (f"kept in MX (map {t_map:.3f} s + nlpsol {t_mx:.3f} s)", t_map + t_mx, mx),
            ("assembled from stage kernels in SX, hmpc's for IPOPT", t_kernels, kernels)):
        ev = evaluation_ms(solver)
        print(f"{label}: set-up {setup:.3f} s; Hessian {ev['nlp_hess_l']:.2f} ms, "
              f"Jacobian {ev['nlp_jac_g']:.2f} ms")
    system = build_system(sc.system)
    print("\nthe Hessian of the Lagrangian, nlpsol's (whole graph) against the stage by stage "
          "one (nlpsol given it; stage Hessians mapped in MX / expanded to SX):")
    for hold, r in _by_hold(sc.mpc, system, hessian_rows):
        print(f"{hold} {r['nlp']:9s}: set-up {r['nlpsol']:.3f} s / {r['staged_mx']:.3f} s / "
              f"{r['staged_sx']:.3f} s; one call {r['eval_nlpsol']:.2f} / "
              f"{r['eval_mx']:.2f} / {r['eval_sx']:.2f} ms; up to {r['differing']} of "
              f"{r['nnz']} entries differ bit for bit at a random point, by up to "
              f"{r['max_diff']:.1e} (largest entry {r['max_abs']:.1e}), in the "
              f"blocks {sorted(r['blocks'])}")
    print("\nthe constraint Jacobian, nlpsol's (whole graph) against the stage by stage one:")
    for hold, r in _by_hold(sc.mpc, system, jacobian_rows):
        print(f"{hold} {r['nlp']:9s}: set-up {r['staged']:.3f} s staged, "
              f"{r['nlpsol']:.3f} s nlpsol's Jacobian and gradient; same sparsity "
              f"{r['same_sparsity']}; {r['differing']} of {r['nnz']} entries differ bit "
              "for bit at a random point")


def _by_hold(settings: MPCSettings, system, rows):
    """(input hold, row) of ``rows(system, settings)`` with each input hold, foh first."""
    for hold in ("foh", "zoh"):
        for r in rows(system, settings.model_copy(update={"input_hold": hold})):
            yield hold, r


if __name__ == "__main__":
    main()
