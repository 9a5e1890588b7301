"""Would IPOPT's own counters make a better latency model? Measured, not built.

Flies the time-paused cells of a real-time sweep (default ``sweeps/realtime_ipopt.toml``)
with every IPOPT call's counters recorded: iterations, the evaluations of the constraints,
their Jacobian and the Hessian of the Lagrangian, and the iterations IPOPT regularised for
inertia; then fits, by non-negative least squares with every solve scaled by its NLP's size
(its variables / 7 / 301, the plan nodes the shipped model holds at), the shipped form

    wall = overhead + per_iteration x iterations (final domain) + per_switching_iteration x
           iterations (a switch left)

and that form plus the regularised iterations and plus the three evaluation counts. Each
run's solves are predicted by a fit without that run (leave one run out). Prints, and with
--write writes, the error on the switching solves over 50 ms (the long ones a real-time
trajectory turns on), and the named solves of one run with each model's charge.

    python benchmarks/latency_counts.py --workers 2 --write results/bench/latency_counts.md

The run listed solve by solve (``--show``) is flown ``--again`` more times: the same
problems' measured times in one sitting, against which any model's error is read.

Measured, never asserted: the times are this machine's (run it on an idle one).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import statistics
import sys
import tempfile
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EVALUATIONS = ("nlp_g", "nlp_jac_g", "nlp_hess_l")
#: the models compared: name -> the counts beside the shipped form's columns
MODELS = {"shipped form": (), "+ regularised iterations": ("regularised",),
          "+ regularised iterations and evaluations": ("regularised", *EVALUATIONS)}
LONG = 0.05  #: a long switching solve [s]


def _cells(sweep: Path, axis: str, label: str) -> list[list[str]]:
    """The ``--set`` overrides of the sweep's runs whose ``axis`` entry is ``label``."""
    spec = tomllib.loads(sweep.read_text())

    def sets(entry: dict) -> list[str]:
        return [f"{k}={json.dumps(v)}" for k, v in entry.items() if k != "label"]

    grid = spec.get("grid", {})
    fixed = [f"{k}={json.dumps(v)}" for k, v in spec.get("set", {}).items()]
    chosen = [e for e in grid[axis] if e.get("label") == label]
    if not chosen:
        raise SystemExit(f"{sweep}: no {axis} entry labelled {label!r}")
    axes = [[(name, e) for e in grid[name]] for name in grid if name != axis]
    runs = [[]]
    for entries in axes:
        runs = [r + [e] for r in runs for e in entries]
    return [fixed + sets(chosen[0]) + [s for _, e in r for s in sets(e)]
            + [f"#{e['label']}" for _, e in r] for r in runs]


def fly(args: tuple[str, list[str]]) -> list[dict]:
    """One run of ``scenario`` with ``sets`` (time paused); every IPOPT call's counters."""
    scenario, sets = args
    from hmpc_cli.mpc import solver
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    calls, original = [], solver._call_instance
    name = " ".join(s[1:] for s in sets if s.startswith("#"))

    def counted(instances, w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0, judge=None):
        res = original(instances, w0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0, judge)
        warm = lam_x0 is not None and lam_g0 is not None
        st = (instances[1] if warm else instances[0]).stats()
        its = st.get("iterations") if isinstance(st.get("iterations"), dict) else {}
        calls.append({"run": name, "variables": len(w0), "rows": len(lbg),
                      "iterations": res.stats.iterations, "wall": res.stats.wall_time,
                      "regularised": sum(1 for r in its.get("regularization_size", [])
                                         if r > 0),
                      **{e: int(st.get(f"n_call_{e}", 0)) for e in EVALUATIONS}})
        return res

    solver._call_instance = counted
    try:
        sc, text = load_scenario(str(ROOT / scenario), [s for s in sets
                                                         if not s.startswith("#")])
        with tempfile.TemporaryDirectory() as tmp:
            execute_run(prepare(sc), text, Path(tmp))
    finally:
        solver._call_instance = original
    return calls


def fit_nonnegative(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares with every coefficient >= 0 (a negative one is dropped and refitted)."""
    keep = list(range(x.shape[1]))
    while True:
        coef, *_ = np.linalg.lstsq(x[:, keep], y, rcond=None)
        if (coef >= 0).all() or len(keep) == 1:
            break
        keep.pop(int(np.argmin(coef)))
    out = np.zeros(x.shape[1])
    out[keep] = np.clip(coef, 0.0, None)
    return out


def columns(calls: list[dict], counts: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(the model's columns per solve, a switch left): each scaled by the NLP's size."""
    n = np.array([c["variables"] for c in calls], dtype=float)
    switching = np.array([c["rows"] > 1.2 * c["variables"] for c in calls])
    it = np.array([c["iterations"] for c in calls], dtype=float)
    scale = n / (7 * 301)
    cols = [scale, scale * np.where(switching, 0.0, it), scale * np.where(switching, it, 0.0)]
    cols += [scale * np.array([c[k] for c in calls], dtype=float) for k in counts]
    return np.column_stack(cols), switching


def cross_validated(calls: list[dict], counts: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Each solve's charge by a fit without its run, and the fit on every solve [s]."""
    x, _ = columns(calls, counts)
    wall = np.array([c["wall"] for c in calls])
    runs = np.array([c["run"] for c in calls])
    charge = np.empty_like(wall)
    for run in np.unique(runs):
        out = runs == run
        charge[out] = x[out] @ fit_nonnegative(x[~out], wall[~out])
    return charge, fit_nonnegative(x, wall)


def report(calls: list[dict], shown: str, head: str, again: list[list[dict]] = ()) -> str:
    """The Markdown report: the models' errors on long switching solves, one run's solves.

    ``again``: the shown run flown again (its calls each time): the range of each long
    solve's measured times there.
    """
    wall = np.array([c["wall"] for c in calls])
    _, switching = columns(calls, ())
    long = switching & (wall > LONG)
    lines = [head, "", f"{len(calls)} IPOPT calls; {int(long.sum())} switching solves over "
             f"{LONG * 1e3:.0f} ms. Error of each solve's charge by a fit without its run:", "",
             "| model | median error | p95 error | median miss [ms] | p95 miss [ms] | fitted "
             "constants [ms] |", "|---|--:|--:|--:|--:|---|"]
    charges = {}
    for name, counts in MODELS.items():
        charge, coef = cross_validated(calls, counts)
        charges[name] = charge
        rel, miss = np.abs(charge - wall)[long] / wall[long], np.abs(charge - wall)[long]
        names = ["overhead", "per iteration", "per switching iteration", *counts]
        fitted = ", ".join(f"{k} {v * 1e3:.3g}" for k, v in zip(names, coef, strict=True))
        lines.append(f"| {name} | {100 * np.median(rel):.1f} % | "
                     f"{100 * np.percentile(rel, 95):.1f} % | {1e3 * np.median(miss):.1f} | "
                     f"{1e3 * np.percentile(miss, 95):.1f} | {fitted} |")
    picked = [i for i, c in enumerate(calls) if c["run"] == shown and c["iterations"] >= 20]
    if picked:
        first = [i for i, c in enumerate(calls) if c["run"] == shown]
        lines += ["", f"The solves of 20 or more iterations of run {shown!r}"
                  + (f", and their measured times in {len(again)} more flights of it the "
                     "same sitting" if again else "") + ":", "",
                  "| iterations | regularised | constraint evaluations | Jacobians | "
                  "measured [ms] | " + ("again [ms] | " if again else "")
                  + " | ".join(f"{n} [ms]" for n in MODELS) + " |",
                  "|--:|--:|--:|--:|--:|" + ("---|" if again else "") + "--:|" * len(MODELS)]
        for i in picked:
            c, k = calls[i], first.index(i)
            more = [1e3 * run[k]["wall"] for run in again if len(run) > k]
            lines.append(f"| {c['iterations']} | {c['regularised']} | {c['nlp_g']} | "
                         f"{c['nlp_jac_g']} | {1e3 * c['wall']:.1f} | "
                         + (f"{min(more):.1f}-{max(more):.1f} | " if more else "")
                         + " | ".join(f"{1e3 * charges[n][i]:.1f}" for n in MODELS) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sweep", default="sweeps/realtime_ipopt.toml")
    ap.add_argument("--axis", default="latency", help="the grid axis of the paused entry")
    ap.add_argument("--label", default="paused", help="its label")
    ap.add_argument("--limit", type=int, default=None, help="only the first N runs")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--show", default="100 Hz on_contact trial 1",
                    help="the run whose long solves are listed")
    ap.add_argument("--again", type=int, default=4,
                    help="fly the --show run this many more times (one process)")
    ap.add_argument("--write", type=Path, default=None)
    args = ap.parse_args(argv)
    sweep = ROOT / args.sweep
    scenario = tomllib.loads(sweep.read_text())["scenario"]
    scenario = str((sweep.parent / scenario).resolve().relative_to(ROOT))
    runs = _cells(sweep, args.axis, args.label)[:args.limit]
    jobs = [(scenario, sets) for sets in runs]
    if args.workers > 1:
        with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
            flown = pool.map(fly, jobs, chunksize=1)
    else:
        flown = [fly(j) for j in jobs]
    calls = [c for run in flown for c in run]
    shown = [j for j, run in zip(jobs, flown, strict=True) if run and run[0]["run"] == args.show]
    again = [fly(shown[0]) for _ in range(args.again)] if shown else []
    from hmpc_cli.core.machine import cpu_model

    head = (f"# IPOPT's counters in the latency model (measured, not built)\n\n"
            f"Written by `python benchmarks/latency_counts.py --workers {args.workers}"
            f"{'' if args.limit is None else f' --limit {args.limit}'}` on {cpu_model()}, "
            f"{multiprocessing.cpu_count()} logical CPUs, Python "
            f"{sys.version.split()[0]}: the {args.label} cells of `{args.sweep}` "
            f"({len(runs)} runs, median {statistics.median(len(r) for r in flown)} IPOPT "
            "calls each). Times are this machine's.")
    text = report(calls, args.show, head, again)
    print(text)
    if args.write is not None:
        args.write.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
