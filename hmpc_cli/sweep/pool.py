"""The local worker pool of ``hmpc sweep``: one run at a time per spawned worker process.

Each worker gets its runs through its own pipe, so the parent always knows which run a
worker holds:

* a worker that dies (killed, out of memory) loses only its run: the run is retried once
  on a fresh worker; a run that kills its worker twice is lost work (``died``: not
  recorded, the sweep exits 1, a resume runs it again); the other workers go on;
* on SIGINT/SIGTERM/SIGHUP the parent asks its busy workers to stop (the same signal:
  they stop their run within one simulator step, its summary marked interrupted by it,
  see :mod:`hmpc_cli.core.signals`) and waits for them;
* a disk error in a worker (a full or read-only disk) comes back as such: the parent
  raises it (no retry), stopping the sweep;
* workers exit when their parent dies (``PR_SET_PDEATHSIG`` on Linux, and a watchdog
  thread polling the parent pid).
"""

from __future__ import annotations

import ctypes
import os
import signal
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from pathlib import Path

from hmpc_cli.core import signals
from hmpc_cli.core.paths import disk_error

__all__ = ["WORKER_STOP_GRACE", "run_pool"]

WORKER_STOP_GRACE = 20.0  # [s] a stopping worker's time to close its run before SIGKILL
_PR_SET_PDEATHSIG = 1
_WATCH_PERIOD = 0.5  # [s] parent-pid watchdog period
_DISK = "disk error"  # a reply's mark: (_DISK, errno, strerror, filename)


# ------------------------------------------------------------------ the worker side
def _die_with_parent(parent: int) -> None:
    """SIGTERM when the parent dies (Linux prctl) and a watchdog thread as a fallback."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):  # not Linux: the watchdog alone
        pass

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(_WATCH_PERIOD)
        os.kill(os.getpid(), signal.SIGTERM)  # stop the run (its summary: interrupted)
        time.sleep(WORKER_STOP_GRACE)
        os._exit(128 + signal.SIGTERM)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()
    if os.getppid() != parent:  # the parent died before prctl
        os._exit(128 + signal.SIGTERM)


def worker_main(conn, parent: int) -> None:
    """A worker: runs ``(toml_text, run_dir, provenance)`` tasks from ``conn``.

    Stops at a None task or a signal. Replies with each run's summary, None when the
    run was stopped by a signal, or ``(_DISK, errno, strerror, filename)`` for a disk
    error (the worker then exits).
    """
    signals.install_deferred()  # first: a stop during the imports below is recorded
    _die_with_parent(parent)
    from hmpc_cli.run.runner import run_one

    while True:
        try:
            task = conn.recv()
        except (EOFError, OSError):
            return
        if task is None or signals.pending() is not None:
            return
        try:
            summary = run_one(*task)
        except KeyboardInterrupt:
            summary = None
        except OSError as exc:
            if not disk_error(exc):
                raise
            summary = (_DISK, exc.errno, exc.strerror, exc.filename)
        try:
            conn.send(summary)
        except (BrokenPipeError, OSError):
            return
        if not isinstance(summary, dict) or signals.pending() is not None:
            return


# ------------------------------------------------------------------ the parent side
class _Worker:
    """One worker process, its pipe and the run it holds."""

    def __init__(self, ctx) -> None:
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=worker_main, args=(child, os.getpid()), daemon=True)
        self.proc.start()
        child.close()
        self.run = None

    def give(self, run, out: Path, provenance) -> None:
        self.run = run
        self.conn.send((run.toml, str(out / "runs" / run.run_id), provenance))


def run_pool(n: int, pending: list, out: Path, record: Callable, died: Callable,
             provenance: Callable = lambda run: None) -> None:
    """Runs ``pending`` on ``n`` worker processes; returns when all are done.

    Args:
        n: worker processes.
        pending: the runs (:class:`hmpc_cli.sweep.plan.Run`).
        out: the sweep's output directory.
        record: ``record(run, summary)``; summary None for a run stopped by a signal.
        died: ``died(run, signum)`` for a run whose worker died twice (lost work).
        provenance: ``provenance(run)``, the :class:`hmpc_cli.log.runlog.Provenance` the run's
            log records (None: the worker's own command line).

    Raises:
        KeyboardInterrupt: a stop signal (the workers are stopped first).
        OSError: a disk error in a worker (the workers are stopped first).
    """
    import multiprocessing
    from multiprocessing.connection import wait

    ctx = multiprocessing.get_context("spawn")
    todo, deaths = deque(pending), Counter()
    workers: list[_Worker] = []
    stop = int(signal.SIGTERM)  # passed on to the busy workers: the sweep's own signal
    try:
        while todo or any(w.run is not None for w in workers):
            while todo and len(workers) < n:
                workers.append(_Worker(ctx))
            for w in workers:
                if w.run is None and todo:
                    run = todo.popleft()
                    w.give(run, out, provenance(run))
            busy = [w for w in workers if w.run is not None]
            ready = wait([w.conn for w in busy] + [w.proc.sentinel for w in busy])
            for w in busy:
                if w.conn in ready and _answered(w, record):
                    continue
                if w.conn in ready or w.proc.sentinel in ready:
                    _dead(w, workers, todo, deaths, died)
    except KeyboardInterrupt as exc:
        stop = signals.as_interrupted(exc).signum
        raise
    finally:
        with signals.deferred():
            _stop_all(workers, stop)


def _answered(w: _Worker, record: Callable) -> bool:
    """Records the worker's answer; False if the worker died instead.

    Raises:
        OSError: the worker's disk error (its run is not recorded).
    """
    try:
        summary = w.conn.recv()
    except (EOFError, OSError):
        return False
    if summary is None:  # the worker was stopped by a signal not from us: as if it died
        return False
    if isinstance(summary, tuple) and summary[:1] == (_DISK,):
        w.run = None  # the worker exits; its run resumes later
        raise OSError(*summary[1:])
    run, w.run = w.run, None
    record(run, summary)
    return True


def _dead(w: _Worker, workers: list, todo: deque, deaths: Counter, died: Callable) -> None:
    """A worker died holding a run: retry the run once, then hand it to ``died``."""
    w.proc.join(timeout=5.0)
    code = w.proc.exitcode
    signum = -code if code is not None and code < 0 else int(signal.SIGTERM)
    workers.remove(w)
    w.conn.close()
    run = w.run
    deaths[run.run_id] += 1
    if deaths[run.run_id] >= 2:
        died(run, signum)
    else:
        todo.appendleft(run)


def _stop_all(workers: list[_Worker], stop: int = signal.SIGTERM) -> None:
    """Stops every worker: None to the idle ones, signal ``stop`` to the busy ones; joins."""
    for w in workers:
        try:
            if w.run is None:
                w.conn.send(None)
            elif w.proc.is_alive():
                os.kill(w.proc.pid, stop)
        except (OSError, ValueError):
            pass
    deadline = time.monotonic() + WORKER_STOP_GRACE
    for w in workers:
        w.proc.join(timeout=max(0.0, deadline - time.monotonic()))
        if w.proc.is_alive():
            w.proc.kill()
            w.proc.join(timeout=5.0)
        w.conn.close()
