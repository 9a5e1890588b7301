"""Figure 3 campaign benchmark: wall time of the 33 runs with 1 and 2 workers.

Run on demand:  python benchmarks/bench_campaign.py [--workers 1,2] [--sweep FILE]
Each measurement starts from an empty output directory (nothing skipped) and includes the
worker start-up (each worker builds its own solvers). Prints the wall times, their ratio,
the target (2 workers <= 20 s, Step 8) and whether the result tables agree. Measured,
never asserted.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from hmpc_cli.sweep.execute import execute_sweep
from hmpc_cli.sweep.plan import plan_sweep

HERE = Path(__file__).resolve().parent
TARGET_S = 20.0


def _table(out: Path) -> list[str]:
    """results.csv without the wall-time columns and log paths (the rest must agree)."""
    import csv

    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    drop = {"wall_time", "solve_time_median", "solve_time_p95", "solve_time_max",
            "plan_time_median", "log"}
    return [",".join(f"{k}={v}" for k, v in r.items() if k not in drop) for r in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts")
    ap.add_argument("--sweep", default=str(HERE.parent / "sweeps" / "fig3.toml"))
    args = ap.parse_args()
    plan = plan_sweep(args.sweep)
    times, tables = {}, {}
    for n in (int(v) for v in args.workers.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            outcome = execute_sweep(plan, Path(tmp), workers=n)
            times[n] = time.perf_counter() - start
            tables[n] = _table(Path(tmp))
        ok = sum(r.count("success=true") for r in tables[n])
        print(f"{plan.spec.name}: {outcome.total} runs, {n} worker(s): {times[n]:7.1f} s "
              f"({ok} successes, {len(outcome.lost)} lost)")
    first = min(times)
    for n, t in times.items():
        if n != first:
            print(f"  speed-up {first} -> {n} workers: {times[first] / t:.2f}x; tables "
                  f"{'identical' if tables[n] == tables[first] else 'DIFFER'}")
    if 2 in times:
        print(f"  2 workers / target ({TARGET_S:.0f} s): {times[2] / TARGET_S:.2f}")
    print(f"machine: {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
