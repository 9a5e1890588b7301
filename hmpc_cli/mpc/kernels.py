"""Stage kernels compiled to C: the small SX functions a staged NLP maps over its stages.

The chain NLP's cost, rows and derivatives are assembled from SX kernels, a few per kind
of stage (:class:`~hmpc_cli.mpc.staged.StagedNLP`): up to a few thousand instructions
each, evaluated once per stage and IPOPT call in CasADi's SX virtual machine. Compiled to
C, each takes a fraction of a second to build (the whole NLP's functions take minutes:
:mod:`hmpc_cli.mpc.cache`) and evaluates several times faster, with the same numbers bit
for bit (CasADi's C of the same operations, ``-ffp-contract=off``).

:func:`compiled` returns a kernel's library from the cache directory if a verified copy is
there (``kernel-<key>.so``, keyed by the function's serialization, CasADi's version, the
compiler's identity and the flags), else the SX function itself, and queues the library's
compile for one worker thread, which runs the compiler (a child process at the lowest
priority) on one kernel after the other: a run never waits for it, the next run loads
what was compiled. At exit neither: the compiler running then is stopped and its output
removed, and a later run compiles what was left (no process outlives the run, nothing is
written into the cache directory after it). One compile at a time: a run of many kernels
would otherwise start as many compilers at once, which even at the lowest priority take a
share of the run's core.
A process that runs many runs (a sweep's worker) calls :func:`wait_for_compiles` first:
it then waits for each kernel's compile (at normal priority) once, so its later runs
evaluate the kernels in C. ``HMPC_BUILD_CACHE=off``, no usable compiler or a cache
directory others may write leave every kernel in SX.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import logging
import os
import queue
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import casadi as ca

from hmpc_cli.core import cbuild
from hmpc_cli.mpc.cache import CFLAGS

#: the compiler runs at the lowest priority beside a run, never in its way (where
#: ``nice`` is found)
NICE = ("nice", "-n", "19")
_STARTED: dict[Path, threading.Event] = {}  # this process's compiles (set: ended), by library
_JOBS: queue.SimpleQueue = queue.SimpleQueue()  # compiles for the worker, in order
_WORKER: list[threading.Thread] = []  # the worker thread, once started
_RUNNING: list[subprocess.Popen] = []  # the compiler the worker runs now
_EXITING = threading.Event()  # set at exit: the worker takes no more jobs
_FAILED: dict[str, str] = {}  # this process's failed compiles by key: their first lines
_SX_KEYS: dict[int, tuple[ca.Function, str]] = {}  # kernels returned in SX: their keys
#: [s] the longest a compile may take (a kernel's takes a fraction of a second)
TIMEOUT = 600.0
#: how :func:`describe` says that every kernel of a build runs in C, or that some run in
#: SX (a run's build reason joins its NLPs': :func:`hmpc_cli.cli.sweep.not_compiled_note`
#: reads both there)
IN_C = "stage kernels in C"
IN_SX = "stage kernels in SX"
_WAIT = False  # set by wait_for_compiles
_LOCK = threading.Lock()
_LOG = logging.getLogger(__name__)


def key(fn: ca.Function, identity: str) -> str:
    """sha256 of what determines a kernel's library: ``fn``, CasADi, compiler, flags."""
    material = "\0".join([fn.serialize(), ca.__version__, identity, *CFLAGS])
    return hashlib.sha256(material.encode()).hexdigest()


def compiled(fn: ca.Function) -> ca.Function:
    """``fn`` compiled to C if its library is cached, else ``fn`` (its compile started).

    ``fn``: an SX function (a stage kernel). Returns a function with ``fn``'s inputs,
    outputs and numbers: the cached library's, or ``fn``.
    """
    cc = cbuild.compiler()
    if cc is None:
        return fn
    try:
        identity = cbuild.compiler_identity(cc)
    except cbuild.CBuildError:
        return fn
    folder, unsafe = cbuild.checked_cache_dir()
    if unsafe:
        return fn
    k = key(fn, identity)
    path = folder / f"kernel-{k[:32]}.so"
    if not _ready(path, k):
        ended = _start(cc, fn, path, k)
        if _WAIT:
            ended.wait(TIMEOUT + 60.0)
        if not _ready(path, k):
            with _LOCK:
                _SX_KEYS[id(fn)] = (fn, k)
            return fn
    try:
        return ca.external(fn.name(), str(path))
    except RuntimeError as e:
        _LOG.warning("cannot load %s (%s): the kernel runs in SX", path, e)
        return fn


def wait_for_compiles() -> None:
    """From now on this process waits for its kernels' compiles (many runs follow)."""
    global _WAIT
    _WAIT = True


@contextlib.contextmanager
def waits_restored():
    """Within: :func:`wait_for_compiles` holds; after: the process waits as it did before.

    For a sweep run in a process that goes on after it (``hmpc sweep --workers 1``, a
    script's or a test's :func:`~hmpc_cli.sweep.execute.execute_sweep`): its later NLP
    builds compile their kernels in the background again, not waiting for the compiler.
    """
    global _WAIT
    before = _WAIT
    try:
        yield
    finally:
        _WAIT = before


def _ready(path: Path, k: str) -> bool:
    """Whether ``path`` is a verified library recorded for key ``k``."""
    return cbuild.verified(path) and cbuild.recorded(path)[2:3] == [k]


def _start(cc: list[str], fn: ca.Function, path: Path, k: str) -> threading.Event:
    """Queues the compile of ``fn``'s C (generated here: CasADi is not thread-safe).

    Returns the event set when it has ended (the one of an earlier call for ``path`` in
    this process, if any).
    """
    with _LOCK:
        if path in _STARTED:
            return _STARTED[path]
        if not _STARTED:  # once per process: what killed compiles left
            cbuild.remove_stale_temporaries(path.parent)
        gen = ca.CodeGenerator(f"{fn.name()}.c", {"with_header": False})
        gen.add(fn)
        nice = () if _WAIT or not NICE or shutil.which(NICE[0]) is None else NICE
        ended = _STARTED[path] = threading.Event()
        _JOBS.put(([*nice, *cc], gen.dump(), fn.name(), path, k, ended))
        if not _WORKER:
            atexit.register(_stop)
        if not _WORKER or not _WORKER[-1].is_alive():
            _WORKER.append(threading.Thread(target=_work, name="hmpc-kernels", daemon=True))
            _WORKER[-1].start()
    return ended


def _work() -> None:
    """The worker thread: compiles the queued kernels one after the other, until exit."""
    while not _EXITING.is_set():
        *job, ended = _JOBS.get()
        try:
            if not _EXITING.is_set():
                _compile(*job)
        finally:
            ended.set()


def _stop() -> None:
    """At exit: the worker takes no more jobs; the compiler it runs is stopped.

    Its partial output is removed as the worker ends that compile (waited for a moment).
    """
    _EXITING.set()
    _JOBS.put(([], "", "", Path(), "", threading.Event()))  # wakes an idle worker
    with _LOCK:
        running = list(_RUNNING)
    for proc in running:
        _terminate(proc)
    for worker in _WORKER:
        worker.join(2.0)


def _terminate(proc: subprocess.Popen) -> None:
    """Stops a compiler and the programs it runs (its process group).

    On SIGTERM the compiler driver removes its own temporary files.
    """
    with contextlib.suppress(OSError):
        os.killpg(proc.pid, signal.SIGTERM)


def _compile(cc: list[str], source: str, name: str, path: Path, k: str) -> None:
    """Compiles ``source`` to ``path`` (recorded ``k``); a failure is kept for :func:`describe`.

    The source gets a fixed name (``<name>.c``) in a scratch directory, so processes that
    compile the same kernel at once write the same library bytes (the source's name is in
    its symbol table). A compile stopped at exit (:func:`_stop`) is not a failure; a
    process killed mid-compile leaves a ``.hmpc-*`` file of the cache directory, removed
    a day later by :func:`~hmpc_cli.core.cbuild.remove_stale_temporaries` (called before
    the first compile). No logging here: this thread may outlive the handlers' streams.
    """

    def started(proc: subprocess.Popen) -> None:
        with _LOCK:
            _RUNNING[:] = [proc]
        if _EXITING.is_set():  # exit began while it was starting
            _terminate(proc)

    try:
        with tempfile.TemporaryDirectory(prefix="hmpc-kernel-") as work:
            c_file = Path(work) / f"{name}.c"
            c_file.write_text(source)
            cbuild.compile_shared(cc, CFLAGS, c_file, path, timeout=TIMEOUT, note=k,
                                  started=started)
    except Exception as e:  # the worker must go on: recorded, reported
        if not _EXITING.is_set():
            with _LOCK:
                _FAILED[k] = f"{name}: {(str(e).splitlines() or [type(e).__name__])[0]}"
    finally:
        with _LOCK:
            _RUNNING.clear()


def describe(made: Iterable[ca.Function]) -> str:
    """Where the stage kernels ``made`` run, as a clause of a build's reason.

    ``made``: kernels as :func:`compiled` returned them. Counts those in SX and names, if
    any, the last failed compile of one of them in this process.
    """
    made = list(made)
    in_c = sum(fn.class_name() == "External" for fn in made)
    if in_c == len(made):
        return f"{IN_C} ({in_c})"
    with _LOCK:
        keys = [_SX_KEYS[id(fn)][1] for fn in made if id(fn) in _SX_KEYS]
        errors = [_FAILED[k] for k in keys if k in _FAILED]
    failed = f"; a kernel compile of this process failed: {errors[-1]}" if errors else ""
    return f"{IN_SX} ({len(made) - in_c} of {len(made)}){failed}"


def wait(timeout: float = 60.0) -> bool:
    """Waits for this process's kernel compiles, at most ``timeout`` seconds in all.

    Returns whether they all ended.
    """
    with _LOCK:
        events = list(_STARTED.values())
    end = time.monotonic() + timeout
    return all(ended.wait(max(0.0, end - time.monotonic())) for ended in events)
