"""Start-up benchmark: ``hmpc run`` with the NLP build cache off (SX build) and warm.

Run on demand:  python benchmarks/bench_startup.py [--repeats 5] [--scenario FILE] [--no-compile]
Uses its own cache directory (``--cache``, default a directory under the system temp
dir, kept between calls so the compile is paid once). First fills it in the foreground
(``HMPC_BUILD_CACHE=sync``, the compile time is printed), then times ``hmpc run`` in fresh
processes, cache off and warm interleaved, and prints the medians, the build-time split
measured in this process (transcription, ``nlpsol``, cache lookup and load), the median
MPC solve time of both runs, and one run's solve calls replayed in this process on the SX
and the compiled NLPs, interleaved (compiled vs SX virtual machine, and whether the
solutions are bit-identical). ``--no-compile``: the default mode on a new cache directory,
where it compiles and stores no NLP (only the CEM's C rollout kernel, made by the first
run: every run builds its NLPs in SX); no compiled replay. Measured, never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
TARGET_S = 1.0  # [s] Step 11: a warm `hmpc run scenarios/ball.toml`


def _run(scenario: str, cache: Path, mode: str, out: Path) -> tuple[float, dict]:
    """Wall time [s] of one ``hmpc run`` in a fresh process and its summary."""
    env = {**os.environ, "HMPC_CACHE_DIR": str(cache), "HMPC_BUILD_CACHE": mode,
           "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    start = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "hmpc_cli", "run", scenario, "--out", str(out),
                          "--quiet"], env=env, capture_output=True, text=True, check=False)
    wall = time.perf_counter() - start
    if res.returncode not in (0, 1):
        raise RuntimeError(f"hmpc run failed ({res.returncode}): {res.stderr[-2000:]}")
    return wall, json.loads((out / "summary.json").read_text())


def _build_info(run_dir: Path) -> dict:
    from hmpc_cli.log.rundata import read_run

    import dataclasses

    build = read_run(run_dir / "run.mcap").info.build
    return dataclasses.asdict(build) if build is not None else {}


def split(scenario: str, cache: Path, warm_mode: str = "background") -> dict[str, float]:
    """Build-time split [s] in this process: SX (transcription, nlpsol) and warm load."""
    from hmpc_cli.mpc import cache as nlp_cache
    from hmpc_cli.mpc.chain.nlp import FixedModeNLP
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario

    sc, _ = load_scenario(scenario)
    system = build_system(sc.system)
    os.environ["HMPC_CACHE_DIR"] = str(cache)
    out: dict[str, float] = {}
    for label, switches in (("switching", None), ("final", 0)):
        os.environ["HMPC_BUILD_CACHE"] = "off"
        t0 = time.perf_counter()
        sx = FixedModeNLP(system, sc.mpc, switches=switches)
        t1 = time.perf_counter()
        sx._transcription()
        t2 = time.perf_counter()
        os.environ["HMPC_BUILD_CACHE"] = warm_mode
        key = nlp_cache.structure_key(system, sc.mpc, sx.S)
        t3 = time.perf_counter()
        nlp_cache.lookup(key, sc.mpc.solver)
        t4 = time.perf_counter()
        warm = FixedModeNLP(system, sc.mpc, switches=switches)
        t5 = time.perf_counter()
        out[f"{label}: SX build total"] = t1 - t0
        out[f"{label}:   transcription"] = t2 - t1
        out[f"{label}:   nlpsol cold + warm"] = (t1 - t0) - (t2 - t1)
        out[f"{label}: key"] = t3 - t2
        out[f"{label}: lookup (sha256 checks)"] = t4 - t3
        out[f"{label}: warm build total ({warm.build_info.cache})"] = t5 - t4
    return out


def solve_split(scenario: str, cache: Path, passes: int = 5) -> dict[str, tuple]:
    """One closed loop's solve calls replayed on SX and compiled NLPs, interleaved.

    Returns:
        Per NLP ("switching", "final"): (solves per pass, median pass time SX [s], median
        pass time compiled [s], primal solutions bit-identical).
    """
    import numpy as np

    from hmpc_cli.run.compose import build
    from hmpc_cli.run.runner import run_unlogged
    from hmpc_cli.mpc.chain.nlp import FixedModeNLPs
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario

    os.environ["HMPC_CACHE_DIR"] = str(cache)
    sc, _ = load_scenario(scenario)
    system = build_system(sc.system)
    os.environ["HMPC_BUILD_CACHE"] = "off"
    sx = FixedModeNLPs(system, sc.mpc)
    os.environ["HMPC_BUILD_CACHE"] = "background"
    compiled = FixedModeNLPs(system, sc.mpc)
    loop = build(sc)  # records the solve calls of one run
    calls: list[tuple[str, tuple]] = []
    for label in ("switching", "final"):
        nlp = getattr(loop.mpc.chain.nlps, label)
        if nlp is None:
            continue
        run = nlp.session.run
        nlp.session.run = (lambda *a, _s=run, _l=label: calls.append((_l, a)) or _s(*a))
    run_unlogged(loop)
    out = {}
    for label in ("switching", "final"):
        args = [a for lab, a in calls if lab == label]
        times: dict[str, list[float]] = {"sx": [], "compiled": []}
        xs: dict[str, list] = {"sx": [], "compiled": []}
        for i in range(passes):
            order = (("sx", sx), ("compiled", compiled))
            for name, nlps in order if i % 2 == 0 else order[::-1]:
                start = time.perf_counter()
                res = [getattr(nlps, label).optimize(*a) for a in args]
                times[name].append(time.perf_counter() - start)
                xs[name] = [r.x for r in res]
        same = all(np.array_equal(a, b) for a, b in zip(xs["sx"], xs["compiled"], strict=True))
        out[label] = (len(args), statistics.median(times["sx"]),
                      statistics.median(times["compiled"]), same)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--scenario", default=str(REPO / "scenarios" / "ball.toml"))
    ap.add_argument("--cache", default=None, help="cache directory (default: under the "
                    "system temp dir; with --no-compile a new one)")
    ap.add_argument("--no-compile", action="store_true",
                    help="warm = the default mode on a new cache: no NLP compiled or stored")
    args = ap.parse_args()
    fill, warm = ("use", "use") if args.no_compile else ("sync", "background")
    cache = Path(args.cache or (tempfile.mkdtemp(prefix="hmpc-bench-cache-") if args.no_compile
                                else Path(tempfile.gettempdir()) / "hmpc-bench-cache"))
    cache.mkdir(mode=0o700, parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        wall, _ = _run(args.scenario, cache, fill, Path(tmp) / "fill")
        print(f"fill ({'nothing to store' if args.no_compile else 'compile'} if not "
              f"cached): {wall:.1f} s; {_build_info(Path(tmp) / 'fill').get('reason', '?')}")
        walls: dict[str, list[float]] = {"off": [], warm: []}
        solves: dict[str, list[float]] = {"off": [], warm: []}
        for i in range(args.repeats):
            for mode in walls:
                out = Path(tmp) / f"{mode}-{i}"
                wall, summary = _run(args.scenario, cache, mode, out)
                walls[mode].append(wall)
                solves[mode].append(summary.get("solve_time_median", float("nan")))
        info = _build_info(Path(tmp) / f"{warm}-0")
    for mode, label in (("off", "cache off (SX build)"), (warm, "warm cache")):
        print(f"{label:22s}: median {statistics.median(walls[mode]):5.2f} s  "
              f"(runs {', '.join(f'{w:.2f}' for w in walls[mode])}); median solve "
              f"{1e3 * statistics.median(solves[mode]):.1f} ms")
    print(f"warm run's build: {info}")
    print(f"warm / target ({TARGET_S} s): {statistics.median(walls[warm]) / TARGET_S:.2f}")
    for name, seconds in split(args.scenario, cache, warm).items():
        print(f"  {name:40s} {seconds:6.3f} s")
    replays = {} if args.no_compile else solve_split(args.scenario, cache)
    for label, (n, t_sx, t_c, same) in replays.items():
        print(f"{label} NLP, {n} solves of one run replayed: SX {t_sx:.3f} s, compiled "
              f"{t_c:.3f} s ({t_c / t_sx:.2f}x); {'bit-identical' if same else 'DIFFERENT'}")
    print(f"machine: {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
