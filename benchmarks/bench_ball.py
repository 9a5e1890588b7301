"""Ball benchmarks: fixed-mode MPC solve time in closed loop, CEM plan time.

Run on demand:  python benchmarks/bench_ball.py [--runs N]
Prints medians, p95 and ratios to the step targets (MPC median <= 20 ms, CEM <= 500 ms).
Timing is measured, never asserted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

import numpy as np

from hmpc_cli.planner.cem import CrossEntropyPlanner
from hmpc_cli.log.reader import read_log
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.runner import prepare, run_to_log
from hmpc_cli.run.scenario import load_scenario

HERE = os.path.dirname(os.path.abspath(__file__))
SCENARIO = os.path.join(HERE, "..", "scenarios", "ball.toml")


def closed_loop_solves(overrides: list[str], runs: int) -> dict[str, np.ndarray]:
    """Wall times of the MPC solves over runs: all, warm-started periodic ones, and those
    with switches left (the switching NLP) or none (the final domain's NLP)."""
    out: dict[str, list[float]] = {"all": [], "warm": [], "switching": [], "final": []}
    for r in range(runs):
        sc, _ = load_scenario(SCENARIO, overrides + [f"disturbance.trial={r % 10 + 1}"])
        with tempfile.TemporaryDirectory() as tmp:
            run_to_log(prepare(sc), os.path.join(tmp, "run.mcap"))
            for m in read_log(os.path.join(tmp, "run.mcap")).topic("/mpc/solve"):
                t = m.data["wall_time"]
                out["all"].append(t)
                if m.data["reason"] == "period":
                    out["warm"].append(t)
                out["final" if len(m.data["detail"]["counts"]) == 1 else "switching"].append(t)
    return {k: np.array(v) for k, v in out.items()}


def cem_plan_times(repeats: int) -> np.ndarray:
    sc, _ = load_scenario(SCENARIO)
    system = build_system(sc.system)
    planner = CrossEntropyPlanner(system, sc.planner)
    print(f"CEM rollout backend: {planner.backend}")
    out = []
    for i in range(repeats):
        start = time.perf_counter()
        planner.plan(0.01 * i, system.x0, 0)
        out.append(time.perf_counter() - start)
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--runs", type=int, default=5, help="closed-loop runs (paper trials)")
    ap.add_argument("--plans", type=int, default=5, help="CEM plans")
    args = ap.parse_args()
    dist = ["disturbance.kind=\"paper_fig3\""]
    solves = closed_loop_solves(dist, args.runs)
    plans = cem_plan_times(args.plans)
    ms = 1e3
    print(f"fixed-mode MPC, ball, 10 Hz, horizon 3 s (180 nodes), {args.runs} disturbed runs")
    labels = {"all": "all solves", "warm": "warm (periodic)",
              "switching": "switches left", "final": "final domain"}
    for key, label in labels.items():
        t = solves[key]
        if t.size:
            print(f"  {label:16s} n={len(t):4d}  median {ms * np.median(t):7.2f} ms  "
                  f"p95 {ms * np.percentile(t, 95):7.2f} ms  max {ms * t.max():7.2f} ms")
    print(f"  median / target (20 ms): {ms * np.median(solves['all']) / 20.0:.2f}")
    print(f"CEM plan (50 samples + mean, 15 iterations, 60 Hz rollouts), {args.plans} plans")
    print(f"  median {ms * statistics.median(plans):7.1f} ms  max {ms * plans.max():7.1f} ms  "
          f"median / target (500 ms): {statistics.median(plans) / 0.5:.2f}")


if __name__ == "__main__":
    main()
