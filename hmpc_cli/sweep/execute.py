"""Executing a sweep's plan: every unfinished run, in-process, on a local pool or on Dask.

Runs go to ``<out>/runs/<run_id>/`` (see :mod:`hmpc_cli.run.runner`), in-process, in spawned
worker processes (:mod:`hmpc_cli.sweep.pool`) or on a Dask cluster whose workers return
their files through the futures (:mod:`hmpc_cli.sweep.dask`); ``<out>/results.csv`` is
rebuilt from their ``summary.json`` files and the committed table's rows that still stand
for runs (:mod:`hmpc_cli.sweep.table`).
"""

from __future__ import annotations

import dataclasses
import shlex
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from hmpc_cli.core import signals
from hmpc_cli.core.paths import write_atomic
from hmpc_cli.run.runner import run_one, runs_in_this_process
from hmpc_cli.sweep.plan import Run, SweepPlan
from hmpc_cli.sweep.pool import run_pool
from hmpc_cli.sweep.table import (finished_runs, is_interrupted, made_otherwise, toml_value,
                                  write_results)


def run_provenance(plan: SweepPlan, run: Run, command: str | None = None):
    """What started ``run``: the sweep's command line, the run's overrides and sweep file.

    Args:
        plan: the sweep.
        run: one of its runs.
        command: the command line (default: this process's ``sys.argv``).

    Returns:
        A :class:`hmpc_cli.log.runlog.Provenance` whose overrides are the run's ``[set]`` and
        grid overrides (``key=value``, TOML values, sorted) and ``seed=N``.
    """
    from hmpc_cli.log.runlog import Provenance

    overrides = [f"{k}={toml_value(v)}" for k, v in run.overrides.items()]
    prov = Provenance(overrides=(*overrides, f"seed={run.seed}"), sweep=str(plan.path))
    return prov if command is None else dataclasses.replace(prov, command=command)


# ---------------------------------------------------------------------- the sweep
@dataclass
class Outcome:
    """What :func:`execute_sweep` did."""

    total: int
    skipped: int = 0
    ran: int = 0
    done: int = 0
    lost: list[str] = field(default_factory=list)
    interrupted: bool = False
    signum: int = int(signal.SIGINT)


def execute_sweep(plan: SweepPlan, out: Path, workers: int = 1, client=None,
                  on_start: Callable[[int, int, int, list[str]], None] | None = None,
                  on_done: Callable[[Run, dict], None] | None = None) -> Outcome:
    """Runs every unfinished run (in-process, process pool or Dask ``client``).

    Finished: a finished run directory or a tabled run (:mod:`hmpc_cli.sweep.table`).

    ``on_start(total, skipped, successes_skipped, replaced)`` and ``on_done(run, summary)``
    report progress; ``replaced``: the ids of the pending runs whose directory holds a run
    finished with another scenario (run again, its files replaced). Ctrl-C stops cleanly
    (``Outcome.interrupted``); results.csv is always rewritten (``Outcome.done``: the
    selected runs it holds, a ``--seeds`` selection's only).
    ``lost`` lists runs whose worker failed or whose results did not arrive from Dask (not
    recorded, retried on resume). Every run's log records its provenance
    (:func:`run_provenance`, this process's command line).
    """
    out = out.resolve()
    (out / "runs").mkdir(parents=True, exist_ok=True)
    write_atomic(out / "sweep.toml", plan.stored_text)
    selected = plan.selected
    done = finished_runs(plan, out, selected)  # run directories and tabled runs
    pending = [r for r in selected if done[r.run_id] is None]
    for r in pending:  # what a run that killed its workers left: it runs again now
        for name in WORKER_DIED:
            (out / "runs" / r.run_id / name).unlink(missing_ok=True)
    res = Outcome(len(selected), skipped=len(selected) - len(pending))
    if on_start:
        on_start(res.total, res.skipped, sum(bool(s and s.get("success")) for s in done.values()),
                 made_otherwise(out, pending))

    def record(run: Run, summary: dict | None) -> None:
        if summary is not None and not is_interrupted(summary):
            res.ran += 1
            if on_done:
                on_done(run, summary)

    command = shlex.join(sys.argv)  # this process's, not a worker's

    def prov(run: Run):
        return run_provenance(plan, run, command)

    try:
        _dispatch(pending, out, workers, client, record, res.lost, prov)
    except KeyboardInterrupt as exc:
        res.interrupted = True
        res.signum = signals.as_interrupted(exc).signum
    finally:
        tabled = set(write_results(plan, out))
        res.done = sum(r.run_id in tabled for r in selected)
    return res


def _dispatch(pending: list[Run], out: Path, workers: int, client,
              record: Callable[[Run, dict | None], None], lost: list[str],
              prov: Callable) -> None:
    """Runs ``pending`` on Dask ``client``, in this process, or in a pool of ``workers``.

    ``record(run, summary)`` takes each result; ``lost`` gets the runs whose worker died.
    """
    if client is not None:
        from hmpc_cli.sweep.dask import run_on_dask

        run_on_dask(client, pending, out, record, lost, prov)
    elif workers <= 1 or len(pending) <= 1:
        with runs_in_this_process():
            for run in pending:
                record(run, run_one(run.toml, str(out / "runs" / run.run_id), prov(run)))
    else:
        run_pool(min(workers, len(pending)), pending, out, record,
                 lambda run, signum: lost.append(_worker_died(run, out, signum)), prov)


#: the files a run that killed its worker twice leaves in its directory
WORKER_DIED = ("worker-died.txt", "run.killed.mcap")


def _worker_died(run: Run, out: Path, signum: int) -> str:
    """A run that killed its worker twice: lost work, not a result; returns its line.

    Its partial log is kept aside as ``run.killed.mcap`` beside ``worker-died.txt``;
    nothing marks it finished (no summary), so the sweep exits 1 and a resume runs it
    again (a worker death, an out-of-memory kill, say, is not the controller's failure).
    """
    d = out / "runs" / run.run_id
    d.mkdir(parents=True, exist_ok=True)
    write_atomic(d / "scenario.toml", run.toml)
    for stale in ("summary.json", "error.txt"):  # of an earlier try: not this one's
        (d / stale).unlink(missing_ok=True)
    log = d / "run.mcap"
    if log.exists():
        log.replace(d / "run.killed.mcap")
    why = f"worker died (signal {signum}) twice"
    write_atomic(d / "worker-died.txt", f"{why}: the run was tried twice and each time its "
                 "worker process was killed; run.killed.mcap is the second try's log so far "
                 "(if any); the run is not recorded and runs again when the sweep does\n")
    kept = f" (its partial log: {d / 'run.killed.mcap'})" if (d / "run.killed.mcap").exists() \
        else ""
    return f"{run.run_id}: {why}{kept}"
