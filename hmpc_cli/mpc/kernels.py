"""Stage kernels compiled to C: the small SX functions a staged NLP maps over its stages.

The chain NLP's Hessian of the Lagrangian is assembled from one SX function per kind of
stage (:meth:`~hmpc_cli.mpc.chain.nlp.FixedModeNLP._staged_hessian`): a few thousand
instructions each, evaluated once per stage and IPOPT iteration in CasADi's SX virtual
machine. Compiled to C, each takes a fraction of a second to build (the whole NLP's
functions take minutes: :mod:`hmpc_cli.mpc.cache`) and evaluates several times faster,
with the same numbers bit for bit (CasADi's C of the same operations, ``-ffp-contract=off``).

:func:`compiled` returns a kernel's library from the cache directory if a verified copy is
there (``kernel-<key>.so``, keyed by the function's serialization, CasADi's version, the
compiler's identity and the flags), else the SX function itself, and compiles the library
in a thread, the compiler a child process at the lowest priority: a run never waits for
it (at exit neither: a compile still running then is abandoned, and a later run starts it
again), the next run loads it. A process that runs many runs (a sweep's worker) calls
:func:`wait_for_compiles` first: it then waits for each kernel's compile (at normal
priority) once, so its later runs evaluate the kernels in C.
``HMPC_BUILD_CACHE=off``, no usable compiler or a cache directory others may write
leave every kernel in SX.
"""

from __future__ import annotations

import hashlib
import logging
import shutil
import tempfile
import threading
import time
from pathlib import Path

import casadi as ca

from hmpc_cli.core import cbuild
from hmpc_cli.mpc.cache import CFLAGS

#: the compiler runs at the lowest priority beside a run, never in its way (where
#: ``nice`` is found)
NICE = ("nice", "-n", "19")
_STARTED: dict[Path, threading.Thread] = {}  # this process's compiles, by library
_FAILED: list[str] = []  # this process's failed compiles: their first lines
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
        thread = _start(cc, fn, path, k)
        if not _WAIT:
            return fn
        thread.join()
        if not _ready(path, k):
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


def _ready(path: Path, k: str) -> bool:
    """Whether ``path`` is a verified library recorded for key ``k``."""
    return cbuild.verified(path) and cbuild.recorded(path)[2:3] == [k]


def _start(cc: list[str], fn: ca.Function, path: Path, k: str) -> threading.Thread:
    """Compiles ``fn``'s C (generated here: CasADi is not thread-safe) in a thread.

    Returns the thread (the one started before for ``path`` in this process, if any).
    """
    with _LOCK:
        if path in _STARTED:
            return _STARTED[path]
        if not _STARTED:  # once per process: what killed compiles left
            cbuild.remove_stale_temporaries(path.parent)
        gen = ca.CodeGenerator(f"{fn.name()}.c", {"with_header": False})
        gen.add(fn)
        source = gen.dump()
        nice = () if _WAIT or not NICE or shutil.which(NICE[0]) is None else NICE
        thread = threading.Thread(target=_compile, args=([*nice, *cc], source, fn.name(),
                                                         path, k),
                                  name=f"hmpc-kernel-{k[:8]}", daemon=True)
        _STARTED[path] = thread
    thread.start()
    return thread


def _compile(cc: list[str], source: str, name: str, path: Path, k: str) -> None:
    """Compiles ``source`` to ``path`` (recorded ``k``); a failure is kept for :func:`describe`.

    The source gets a fixed name (``<name>.c``) in a scratch directory, so processes that
    compile the same kernel at once write the same library bytes (the source's name is in
    its symbol table). If the process exits first, the compiler's partial output is a
    ``.hmpc-*`` file of the cache directory, removed a day later by
    :func:`~hmpc_cli.core.cbuild.remove_stale_temporaries` (called before the first
    compile). No logging here: this thread may outlive the handlers' streams.
    """
    try:
        with tempfile.TemporaryDirectory(prefix="hmpc-kernel-") as work:
            c_file = Path(work) / f"{name}.c"
            c_file.write_text(source)
            cbuild.compile_shared(cc, CFLAGS, c_file, path, timeout=600.0, note=k)
    except (cbuild.CBuildError, OSError) as e:
        with _LOCK:
            _FAILED.append(f"{name}: {(str(e).splitlines() or [type(e).__name__])[0]}")


def describe(fn: ca.Function) -> str:
    """Where the stage kernels ``fn`` maps run, as a clause of a build's reason.

    ``fn``: a function assembled from kernels (e.g. the staged Hessian). Names the
    kernels in SX and, if any, this process's last failed kernel compile.
    """
    kernels = {f.name(): f.class_name() for f in fn.find_functions()
               if f.class_name() != "Map"}
    in_c = sum(kind == "External" for kind in kernels.values())
    if in_c == len(kernels):
        return f"stage kernels in C ({in_c})"
    with _LOCK:
        failed = f"; a kernel compile of this process failed: {_FAILED[-1]}" if _FAILED else ""
    return f"stage kernels in SX ({len(kernels) - in_c} of {len(kernels)}){failed}"


def wait(timeout: float = 60.0) -> bool:
    """Waits for this process's kernel compiles, at most ``timeout`` seconds in all.

    Returns whether they all ended.
    """
    with _LOCK:
        threads = list(_STARTED.values())
    end = time.monotonic() + timeout
    for thread in threads:
        thread.join(max(0.0, end - time.monotonic()))
    return not any(thread.is_alive() for thread in threads)
