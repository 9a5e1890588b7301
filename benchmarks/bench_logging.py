"""Logging overhead: the same closed-loop runs with the run log on and off, interleaved.

Run on demand:  python benchmarks/bench_logging.py [--runs N] [--scenario PATH]

Builds the scenario's loop once per variant and run (the NLPs are cached per process, so
both variants find the same process state), runs it as ``hmpc run`` does (run.mcap with
the typed topics and the 3D scene: "on") and with no recorder ("off"), alternating, and
prints the median and p95 of the run wall times, the overhead ratio (on / off - 1,
target < 5 %) and the log size. The
loop itself is identical; only the writing of the topics differs. On a busy machine the
wall-time ratio is noisy, so the log-on runs also time every RunLog call from inside
(perf_counter around each): their share of the run is the overhead without the noise.
Measured, never asserted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from hmpc_cli.runlog import RunLog
from hmpc_cli.runner import execute_run, prepare
from hmpc_cli.scenario import load_scenario

LOGGED = ("step", "state", "event", "planner", "solve", "summary")


class _Timed:
    """Times every call of RunLog's logging methods (class-wide, while active)."""

    def __init__(self) -> None:
        self.total = 0.0
        self._orig = {name: getattr(RunLog, name) for name in LOGGED}

    def __enter__(self) -> _Timed:
        for name, fn in self._orig.items():
            def timed(*args, _fn=fn, **kw):
                start = time.perf_counter()
                try:
                    return _fn(*args, **kw)
                finally:
                    self.total += time.perf_counter() - start
            setattr(RunLog, name, timed)
        return self

    def __exit__(self, *exc) -> None:
        for name, fn in self._orig.items():
            setattr(RunLog, name, fn)

HERE = os.path.dirname(os.path.abspath(__file__))


def one_run(scenario: str, log: bool) -> tuple[float, int]:
    """(wall time [s], log bytes) of one run with the log on (as ``hmpc run`` writes it:
    the typed topics and the 3D scene) or off (no recorder)."""
    sc, toml_text = load_scenario(scenario)
    loop = prepare(sc)
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        if log:
            execute_run(loop, toml_text, Path(tmp))
        else:
            loop.run()
        wall = time.perf_counter() - start
        return wall, os.path.getsize(Path(tmp) / "run.mcap") if log else 0


def main() -> None:
    """Interleaves runs with the log on and off and prints the comparison."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--scenario", default=os.path.join(HERE, "..", "scenarios", "ball.toml"))
    args = ap.parse_args()
    one_run(args.scenario, True)  # warm-up: NLPs built, caches filled
    times: dict[bool, list[float]] = {True: [], False: []}
    size = 0
    for _ in range(args.runs):
        for log in (False, True):
            wall, n = one_run(args.scenario, log)
            times[log].append(wall)
            size = n or size
    for log in (False, True):
        ts = sorted(times[log])
        p95 = ts[min(len(ts) - 1, round(0.95 * (len(ts) - 1)))]
        print(f"log {'on ' if log else 'off'}: median {statistics.median(ts) * 1e3:8.1f} ms"
              f"   p95 {p95 * 1e3:8.1f} ms   ({len(ts)} runs)")
    ratio = statistics.median(times[True]) / statistics.median(times[False]) - 1.0
    print(f"overhead (median on / median off - 1): {ratio * 100:+.1f} %   log size "
          f"{size / 1024:.0f} KiB")
    shares = []
    for _ in range(args.runs):
        with _Timed() as timer:
            wall, _ = one_run(args.scenario, True)
        shares.append(timer.total / wall)
    print(f"time inside RunLog calls, share of the run: median "
          f"{statistics.median(shares) * 100:.1f} %, max {max(shares) * 100:.1f} % "
          f"({len(shares)} runs)")


if __name__ == "__main__":
    main()
