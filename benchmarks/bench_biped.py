"""Biped benchmarks: walking-MPC solve times and the foothold planning step, in closed loop.

Run on demand:  python benchmarks/bench_biped.py [--duration S] [--runs N]

Runs the bundled scenario (scenarios/biped_stairs.toml: 1.1x heavier robot, +-25 N torso
pushes, MPC at 10 Hz and at each contact) through the real closed loop and reads the
timings back from its logs: the NLP build time, the periodic (warm) MPC re-solves, the
planning step at t = 0 (every candidate, cold) and after each contact (every candidate,
warm-started from the executed plan). Prints medians, p95 and the ratio to the target
(MPC median <= 100 ms, so that 10 Hz holds in real time). Measured, never asserted.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from hmpc_cli.log.reader import read_log
from hmpc_cli.run.runner import prepare, run_to_log
from hmpc_cli.run.scenario import load_scenario

SCENARIO = Path(__file__).resolve().parent.parent / "scenarios" / "biped_stairs.toml"
TARGET = 0.100


def stats(name: str, v: list[float], target: float | None = None) -> None:
    a = np.asarray(v) * 1e3
    if a.size == 0:
        print(f"{name:<36} (none)")
        return
    line = (f"{name:<36} n={a.size:3d}  median {np.median(a):7.1f} ms  "
            f"p95 {np.percentile(a, 95):7.1f} ms  max {a.max():7.1f} ms")
    if target is not None:
        line += f"  median/target {np.median(a) / (1e3 * target):.2f}"
    print(line)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=2.5, help="simulated time [s]")
    ap.add_argument("--runs", type=int, default=1, help="runs (seeds 0..N-1)")
    args = ap.parse_args()
    period, first, contact, iters, outcomes = [], [], [], [], []
    for seed in range(args.runs):
        sc, _ = load_scenario(SCENARIO, [f"sim.duration={args.duration}"], seed=seed)
        start = time.perf_counter()
        loop = prepare(sc)  # the NLP is built once per process (seed 0 pays it)
        build = time.perf_counter() - start
        with tempfile.TemporaryDirectory() as tmp:
            res = run_to_log(loop, Path(tmp) / "run.mcap")
            log = read_log(Path(tmp) / "run.mcap")
        for m in log.topic("/mpc/solve"):
            if m.data["reason"] == "period":
                period.append(m.data["wall_time"])
                iters.append(m.data["iterations"])
        for m in log.topic("/planner/plan"):
            (first if m.data["reason"] == "initial" else contact).append(m.data["wall_time"])
        outcomes.append(f"seed {seed}: {'success' if res.success else 'failed'} "
                        f"({res.reason}), contacts {res.contacts_by_guard}, "
                        f"solver failures {res.solver_failures}, wall {res.wall_time:.1f} s")
        print(f"system + NLP build {build:.2f} s; " + outcomes[-1])
    print()
    stats("MPC re-solve (10 Hz, warm)", period, TARGET)
    if iters:
        print(f"{'':<36} iterations median {np.median(iters):.0f}, max {max(iters)}")
    stats("planning step at t = 0 (cold)", first)
    stats("planning step after a contact", contact)


if __name__ == "__main__":
    main()
