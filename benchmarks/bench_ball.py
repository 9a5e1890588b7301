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

from hmpc_cli.loop import LayeredLoop
from hmpc_cli.planner.cem import CrossEntropyPlanner
from hmpc_cli.recorder import Recorder, read_log
from hmpc_cli.scenario import load_scenario
from hmpc_cli.systems import build_system

HERE = os.path.dirname(os.path.abspath(__file__))
SCENARIO = os.path.join(HERE, "..", "scenarios", "ball.toml")


def closed_loop_solves(overrides: list[str], runs: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall times of every MPC solve (all, and warm-started periodic ones) over runs."""
    all_t, warm_t = [], []
    for r in range(runs):
        sc, _ = load_scenario(SCENARIO, overrides + [f"disturbance.trial={r % 10 + 1}"])
        with tempfile.TemporaryDirectory() as tmp:
            rec = Recorder(os.path.join(tmp, "run.mcap"))
            try:
                LayeredLoop(sc, rec).run()
            finally:
                rec.close()
            for m in read_log(os.path.join(tmp, "run.mcap")).topic("/mpc/solve"):
                all_t.append(m.data["wall_time"])
                if m.data["reason"] == "period":
                    warm_t.append(m.data["wall_time"])
    return np.array(all_t), np.array(warm_t)


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
    all_t, warm_t = closed_loop_solves(dist, args.runs)
    plans = cem_plan_times(args.plans)
    ms = 1e3
    print(f"fixed-mode MPC, ball, 10 Hz, horizon 3 s (180 nodes), {args.runs} disturbed runs")
    print(f"  all solves       n={len(all_t):4d}  median {ms * np.median(all_t):7.2f} ms  "
          f"p95 {ms * np.percentile(all_t, 95):7.2f} ms  max {ms * all_t.max():7.2f} ms")
    print(f"  warm (periodic)  n={len(warm_t):4d}  median {ms * np.median(warm_t):7.2f} ms  "
          f"p95 {ms * np.percentile(warm_t, 95):7.2f} ms")
    print(f"  median / target (20 ms): {ms * np.median(all_t) / 20.0:.2f}")
    print(f"CEM plan (50 samples + mean, 15 iterations, 60 Hz rollouts), {args.plans} plans")
    print(f"  median {ms * statistics.median(plans):7.1f} ms  max {ms * plans.max():7.1f} ms  "
          f"median / target (500 ms): {statistics.median(plans) / 0.5:.2f}")


if __name__ == "__main__":
    main()
