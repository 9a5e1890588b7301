"""Fits sim.latency_model (overhead + per_iteration x iterations) to measured MPC solves.

Runs the given scenarios with time paused, reads each /mpc/solve's IPOPT iterations and
measured wall time, and fits wall = overhead + per_iteration x iterations by least squares
(non-negative), side by side with the medians per iteration count. Prints the TOML to
paste under [sim.latency_model] and, with --write, a Markdown report.

    python benchmarks/calibrate_latency.py --write results/bench/latency_model.md
"""

from __future__ import annotations

import argparse
import platform
import tempfile
from pathlib import Path

import numpy as np

from hmpc_cli.log.reader import read_log
from hmpc_cli.run.runner import execute_run, prepare
from hmpc_cli.run.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ["scenarios/ball.toml", "scenarios/ball_disturbed.toml"]


def solves_of(scenario: Path, runs: int, work: Path) -> list[tuple[int, float]]:
    """(iterations, wall time [s]) of every MPC solve of ``runs`` paused runs."""
    out = []
    for k in range(runs):
        sc, text = load_scenario(scenario, [f"seed={k}"])
        run_dir = work / f"{scenario.stem}-{k}"
        execute_run(prepare(sc), text, run_dir)
        for m in read_log(run_dir / "run.mcap").messages:
            if m.topic == "/mpc/solve" and m.data.get("iterations", 0) > 0:
                out.append((int(m.data["iterations"]), float(m.data["wall_time"])))
    return out


def fit(points: list[tuple[int, float]]) -> tuple[float, float]:
    """(overhead, per_iteration) [s] of the least-squares line, both clipped at 0."""
    it = np.array([p[0] for p in points], dtype=float)
    wall = np.array([p[1] for p in points])
    A = np.column_stack([np.ones_like(it), it])
    (a, b), *_ = np.linalg.lstsq(A, wall, rcond=None)
    if a < 0:
        a, b = 0.0, float(wall @ it / (it @ it))
    return max(float(a), 0.0), max(float(b), 0.0)


def machine() -> str:
    model = next((line.split(":", 1)[1].strip() for line in
                  Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("model name")), platform.processor() or "?") \
        if Path("/proc/cpuinfo").is_file() else platform.processor()
    import os
    return f"{model}, {os.cpu_count()} logical CPUs, {platform.system()}"


def report(points, overhead, per_it) -> str:
    it = np.array([p[0] for p in points])
    wall = np.array([p[1] for p in points])
    pred = overhead + per_it * it
    lines = ["# The latency model, fitted to measured MPC solves", "",
             f"Machine: {machine()} (machine dependent: re-fit on yours).", "",
             f"{len(points)} solves of {', '.join(SCENARIOS)} with time paused.", "",
             "```toml", "[sim.latency_model]", f"overhead = {overhead:.4f}",
             f"per_iteration = {per_it:.4f}", "```", "",
             "| iterations | solves | measured median [ms] | measured p95 [ms] | model [ms] |",
             "|---|---|---|---|---|"]
    for k in sorted(set(it.tolist())):
        w = wall[it == k] * 1e3
        lines.append(f"| {k} | {len(w)} | {np.median(w):.1f} | {np.percentile(w, 95):.1f} | "
                     f"{(overhead + per_it * k) * 1e3:.1f} |")
    err = np.abs(pred - wall) * 1e3
    lines += ["", f"Absolute error of the model: median {np.median(err):.1f} ms, "
              f"p95 {np.percentile(err, 95):.1f} ms.", ""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="seeds per scenario")
    ap.add_argument("--write", type=Path, help="write the Markdown report here")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        points = [p for s in SCENARIOS for p in solves_of(ROOT / s, args.runs, Path(tmp))]
    overhead, per_it = fit(points)
    text = report(points, overhead, per_it)
    print(text)
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(text)


if __name__ == "__main__":
    main()
