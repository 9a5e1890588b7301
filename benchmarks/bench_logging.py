"""Logging overhead: the same closed-loop runs with the run log on and off, interleaved.

Run on demand:  python benchmarks/bench_logging.py [--runs N] [--scenario PATH]
                [--set KEY=VALUE ...]   (e.g. --set sim.log_plan_stride=3)

Builds the scenario's loop once per variant and run (the NLPs are cached per process, so
both variants find the same process state), runs it as ``hmpc run`` does (run.mcap with
the typed topics and the 3D scene: "on") and with no recorder ("off"), in N
counterbalanced blocks off, on, on, off (the next block on, off, off, on), and prints the
run's wall time and its CPU time (this thread's) per variant, the overhead ratios
on / off - 1 (target < 5 %) of the medians, of the minima (the work is deterministic: the
minimum is the run least disturbed by the rest of the machine) and per block (the block's
two log-on runs against its two log-off runs: a drift of the machine that is linear
within the block cancels, and so does a cost of running second, which each variant pays
once per block), with a bootstrap 95 % interval of the blocks' median, and the log size.
The loop itself is identical; only the writing of the topics differs. The log-on runs
also time every logging call from inside (perf_counter around the outermost ones):
steadier than the on/off difference of two noisy medians, but blind to what logging
costs the rest of the run (e.g. caches refilled after it; the timer itself counts).
Measured, never asserted.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from hmpc_cli.log import scene
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.runlog import TopicWriter
from hmpc_cli.run.runner import execute_run, prepare, run_unlogged
from hmpc_cli.run.scenario import load_scenario

#: the calls that log: TopicWriter's topics, the recorder's open (header, attachment) and
#: close (the queued messages, the last chunk, summary and footer), the scene's set-up
LOGGED = ((TopicWriter, ("step", "state", "event", "planner", "mpc_solve", "summary", "open",
                    "flush_held")),
          (Recorder, ("__init__", "add_attachment", "close")), (scene, ("open_scene",)))


class _Timed:
    """Times the outermost logging calls of :data:`LOGGED` (class-wide, while active).

    ``step`` calls ``state``: only the outermost call is timed, so nothing counts twice.
    """

    def __init__(self) -> None:
        self.total = 0.0
        self._depth = 0
        self._orig = {(cls, name): getattr(cls, name) for cls, names in LOGGED
                      for name in names}

    def __enter__(self) -> _Timed:
        for (cls, name), fn in self._orig.items():
            def timed(*args, _fn=fn, **kw):
                self._depth += 1
                start = time.perf_counter()
                try:
                    return _fn(*args, **kw)
                finally:
                    self._depth -= 1
                    if self._depth == 0:
                        self.total += time.perf_counter() - start
            setattr(cls, name, timed)
        return self

    def __exit__(self, *exc) -> None:
        for (cls, name), fn in self._orig.items():
            setattr(cls, name, fn)

HERE = os.path.dirname(os.path.abspath(__file__))
#: the order of a block's runs (log on?), alternating between blocks
ABBA = ((False, True, True, False), (True, False, False, True))


def one_run(scenario: str, log: bool, sets: tuple[str, ...] = ()) -> tuple[float, float, int]:
    """(wall time [s], CPU time of this thread [s], log bytes) of one run with the log on
    (as ``hmpc run`` writes it: the typed topics and the 3D scene) or off (no recorder);
    ``sets``: ``key=value`` overrides of the scenario."""
    sc, toml_text = load_scenario(scenario, list(sets))
    loop = prepare(sc)
    with tempfile.TemporaryDirectory() as tmp:
        start, cpu = time.perf_counter(), time.thread_time()
        if log:
            execute_run(loop, toml_text, Path(tmp))
        else:
            run_unlogged(loop)
        wall, cpu = time.perf_counter() - start, time.thread_time() - cpu
        return wall, cpu, os.path.getsize(Path(tmp) / "run.mcap") if log else 0


def median_ci(values: list[float], level: float = 0.95, resamples: int = 4000,
              seed: int = 0) -> tuple[float, float]:
    """Percentile-bootstrap interval of the median of ``values`` (fixed seed: the same
    runs give the same interval)."""
    import numpy as np

    v = np.asarray(values, dtype=float)
    rng = np.random.default_rng(seed)
    meds = np.median(v[rng.integers(0, len(v), size=(resamples, len(v)))], axis=1)
    tail = (1.0 - level) / 2.0
    return float(np.quantile(meds, tail)), float(np.quantile(meds, 1.0 - tail))


def main() -> None:
    """Interleaves runs with the log on and off and prints the comparison."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="blocks of 4 runs (2 per variant)")
    ap.add_argument("--scenario", default=os.path.join(HERE, "..", "scenarios", "ball.toml"))
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a setting of the scenario (repeatable)")
    args = ap.parse_args()
    sets = tuple(args.set)
    one_run(args.scenario, True, sets)  # warm-up: NLPs built, caches filled
    times: dict[bool, list[tuple[float, float]]] = {True: [], False: []}
    blocks: list[tuple[float, float]] = []  # per block: on / off - 1 of (wall, CPU)
    size = 0
    for b in range(args.runs):
        block: dict[bool, list[tuple[float, float]]] = {True: [], False: []}
        for log in ABBA[b % 2]:
            wall, cpu, n = one_run(args.scenario, log, sets)
            block[log].append((wall, cpu))
            size = n or size
        blocks.append(tuple(sum(v[k] for v in block[True]) / sum(v[k] for v in block[False])
                            - 1.0 for k in (0, 1)))
        for log in (False, True):
            times[log] += block[log]
    for k, what in enumerate(("wall", "CPU ")):
        med = {log: statistics.median(v[k] for v in times[log]) for log in (False, True)}
        low = {log: min(v[k] for v in times[log]) for log in (False, True)}
        p95 = {log: sorted(v[k] for v in times[log])[
            round(0.95 * (len(times[log]) - 1))] for log in (False, True)}
        print(f"{what}: log off median {med[False] * 1e3:7.1f} ms (p95 {p95[False] * 1e3:7.1f},"
              f" min {low[False] * 1e3:7.1f})   on {med[True] * 1e3:7.1f} ms (p95 "
              f"{p95[True] * 1e3:7.1f}, min {low[True] * 1e3:7.1f})   overhead: medians "
              f"{(med[True] / med[False] - 1.0) * 100:+.1f} %, minima "
              f"{(low[True] / low[False] - 1.0) * 100:+.1f} %")
    for k, what in enumerate(("wall", "CPU ")):
        ratios = sorted(block[k] for block in blocks)
        q1, q3 = ratios[len(ratios) // 4], ratios[(3 * len(ratios)) // 4]
        lo, hi = median_ci(ratios)
        print(f"{what}: per block (its 2 on / its 2 off runs - 1): median "
              f"{statistics.median(ratios) * 100:+.1f} % (95 % CI {lo * 100:+.1f} .. "
              f"{hi * 100:+.1f}), quartiles {q1 * 100:+.1f} .. {q3 * 100:+.1f} % "
              f"({len(ratios)} blocks)")
    print(f"log size {size / 1024:.0f} KiB ({2 * args.runs} runs per variant)")
    shares = []
    for _ in range(args.runs):
        with _Timed() as timer:
            wall, _, _ = one_run(args.scenario, True, sets)
        shares.append(timer.total / wall)
    print(f"time inside the logging calls, share of the run: median "
          f"{statistics.median(shares) * 100:.1f} %, max {max(shares) * 100:.1f} % "
          f"({len(shares)} runs)")


if __name__ == "__main__":
    main()
