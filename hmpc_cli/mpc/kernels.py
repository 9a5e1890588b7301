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
import tempfile
import threading
import time
from pathlib import Path

import casadi as ca

from hmpc_cli.core import cbuild

#: compiler flags: those of the compiled NLPs (:data:`hmpc_cli.mpc.cache.CFLAGS`)
CFLAGS = ("-O1", "-shared", "-fPIC", "-ffp-contract=off", "-fno-fast-math")
#: the compiler runs at the lowest priority beside a run, never in its way
NICE = ("nice", "-n", "19")
_STARTED: dict[Path, threading.Thread] = {}  # this process's compiles, by library
_FAILED: dict[str, str] = {}  # this process's failed compiles: kernel name -> first line
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
        nice = () if _WAIT else NICE
        thread = threading.Thread(target=_compile, args=([*nice, *cc], source, fn.name(),
                                                         path, k),
                                  name=f"hmpc-kernel-{k[:8]}", daemon=True)
        _STARTED[path] = thread
    thread.start()
    return thread


def _compile(cc: list[str], source: str, name: str, path: Path, k: str) -> None:
    """Writes ``source`` beside ``path`` and compiles it to ``path`` (recorded ``k``).

    The source is a ``.hmpc-*`` temporary file of the cache directory, removed after the
    compile (or, if the process exits first, a day later by
    :func:`~hmpc_cli.core.cbuild.remove_stale_temporaries`, called before the first compile).
    A failure is kept for :func:`describe` (no logging here: this thread may outlive the
    handlers' streams).
    """
    c_file = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=".hmpc-kernel-", suffix=".c", dir=path.parent)
        c_file = Path(tmp)
        with open(fd, "w") as f:
            f.write(source)
        cbuild.compile_shared(cc, CFLAGS, c_file, path, timeout=600.0, note=k)
    except (cbuild.CBuildError, OSError) as e:
        with _LOCK:
            _FAILED[name] = (str(e).splitlines() or [type(e).__name__])[0]
    finally:
        if c_file is not None:
            c_file.unlink(missing_ok=True)


def describe(fn: ca.Function) -> str:
    """Where the stage kernels ``fn`` maps run, as a clause of a build's reason.

    ``fn``: a function assembled from kernels (e.g. the staged Hessian). Names the
    kernels in SX and, if any, the last compile failure of this process.
    """
    kernels = {f.name(): f.class_name() for f in fn.find_functions()
               if f.class_name() != "Map"}
    in_c = sum(kind == "External" for kind in kernels.values())
    if in_c == len(kernels):
        return f"stage kernels in C ({in_c})"
    with _LOCK:
        failed = next((f"; {name} failed to compile: {why}" for name, why in _FAILED.items()
                       if name in kernels), "")
    return f"stage kernels in SX ({len(kernels) - in_c} of {len(kernels)}){failed}"


def wait(timeout: float = 60.0) -> None:
    """Waits for this process's kernel compiles, at most ``timeout`` seconds in all."""
    with _LOCK:
        threads = list(_STARTED.values())
    end = time.monotonic() + timeout
    for thread in threads:
        thread.join(max(0.0, end - time.monotonic()))
