"""Build cache of the MPC's NLPs: compiled once per problem structure, loaded after.

Where a process spends its start-up (``hmpc run scenarios/ball.toml``): transcribing
each NLP into an SX graph and its ``ca.nlpsol`` (the symbolic gradient, Jacobian and
Hessian and their sparsity): most of a short run (results/bench/), but for the chain NLP
on IPOPT, whose functions are assembled from stage kernels in a fraction of that
(:mod:`hmpc_cli.mpc.staged`). A serialized
``nlpsol`` does not help (tens of MB for the switching NLP, slower to read than to rebuild), so
the cache keeps what IPOPT calls, compiled: the C that ``nlpsol.generate_dependencies``
writes (``nlp_f``, ``nlp_g``, ``nlp_grad_f``, ``nlp_jac_g``, ``nlp_hess_l``; no ``nlp_grad``;
a Hessian ``nlpsol`` was given written with them: :func:`_generate_c`),
built into a shared library that ``ca.nlpsol(name, "ipopt", library)`` loads in
milliseconds, with the NLP's block layout beside it. Compiled this way the solves are the
SX virtual machine's bit for bit (same operations, ``-ffp-contract=off``).

One *entry* per problem structure, keyed by :func:`structure_key` (what determines the
graph: the system's CasADi functions and numbers, the structural MPC settings, the chain
length S, the sources that build the graph (:data:`GRAPH_SOURCES`), and the hmpc, CasADi
and Python versions; not the solver options, rates, margins or iteration limits, which are applied
when the library is loaded), in the directory of the C rollouts
(:func:`hmpc_cli.core.cbuild.cache_dir`):

* ``nlp-<key>.json``: the layout (block names, stages, offsets, shapes);
* ``nlp-<key>.casadi``: the NLP's ``(x, p) -> (f, g)`` function, serialized (the
  transcription);
* ``nlp-<key>-hess.casadi``: the Hessian of the Lagrangian the NLP gives IPOPT instead of
  the one ``nlpsol`` generates (``hess_lag``; the chain NLP's, assembled stage by stage),
  serialized, if it has one (its layout file says);
* ``nlp-<key>-<compiler>.so``: the library, its name also keyed by the compiler's identity
  and the flags.

Each file is written atomically with its sha256 beside it and used only when its bytes
match; a damaged file is reported, removed and rebuilt. A miss in the modes that compile
transcribes the NLP in SX, stores the layout and the function, and compiles the library
in a detached background process started when the process exits (``python -m
hmpc_cli.mpc.cache``; one entry is compiled by one process at a time: a lock file), so a
run never waits for the compiler nor competes with it; the next run loads it. The compile
is the price: for the ball's switching NLP minutes of CPU and GBs of memory at -O1.

Until its library is made a later run loads the stored function and calls it on fresh
symbols (:func:`load_transcription`), the graph the compiler is given too, and ``nlpsol``
derives the same functions from it (the chain NLP on IPOPT assembles them from its stage
kernels instead: the same numbers): the solves are the transcribed NLP's bit for bit
(``tests/test_build_cache.py``). The cache is still a miss (no compiled library); its
reason says the transcription was loaded (or, assembled from stage kernels, only
verified). The default mode stores nothing of the NLP: transcribing costs what loading
does (the stage kernels, small, are compiled in every mode but ``off``:
:mod:`hmpc_cli.mpc.kernels`).

``HMPC_BUILD_CACHE`` (:func:`mode`): ``off`` (or ``0``) disables the cache; ``use`` (the
default) loads compiled NLPs but never compiles (the user asks for the cost, once);
``background`` compiles a missing one at exit, ``sync`` in the foreground. No
compiler, a cache directory writable by others, a solver the table does not mark
``compilable`` (:mod:`hmpc_cli.mpc.solver_table`; IPOPT only) or a failed
compilation: the NLP is built without a library, and :class:`BuildInfo` says why (it goes
to the run log's ``/run/info``).
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import functools
import hashlib
import json
import logging
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from hmpc_cli import __version__
from hmpc_cli.core import cbuild
from hmpc_cli.core.messages import BuildInfo
from hmpc_cli.core.machine import process_exists
from hmpc_cli.mpc.builder import NLPLayout
from hmpc_cli.mpc.solver import without_nlp_grad
from hmpc_cli.mpc.solver_table import SOLVERS, backend_of

ENV = "HMPC_BUILD_CACHE"
CFLAGS = ("-O1", "-shared", "-fPIC", "-ffp-contract=off", "-fno-fast-math")
FORMAT = 2  # of the entry files (2: the Hessian file)
#: [s] a compile lock older than this is taken over (one of a dead process at once)
LOCK_STALE = 3600.0
#: MPC settings applied at solve time (bounds, parameters, options): not in the key
NON_STRUCTURAL = frozenset({"rate_hz", "tube_margin", "input_margin", "margins", "robust",
                            "solver", "solver_options", "max_iter", "warm_start",
                            "resolve_on_impact", "final_domain_nlp", "node_shift"})
_LOG = logging.getLogger(__name__)
_QUEUE: list[Entry] = []  # entries this process compiles in the background at exit


@dataclass(frozen=True)
class Hit:
    """A lookup: the library and layout on a hit (else None), and the build info.

    ``transcription``: on a miss whose function and layout are stored, the NLP
    ``{"x", "p", "f", "g"}`` loaded from them (with ``layout``), else None. ``stored``:
    they are stored (and verified), loaded or not (:func:`lookup`'s ``load``).
    """

    library: str | None
    layout: NLPLayout | None
    info: BuildInfo
    transcription: dict | None = None
    stored: bool = False


#: ``$HMPC_BUILD_CACHE`` values: off, use (default), background, sync
MODES = ("off", "use", "background", "sync")


def mode() -> str:
    """The cache mode from ``$HMPC_BUILD_CACHE`` (default ``"use"``).

    ``off``: no cache; ``use``: load compiled NLPs (else a transcription the other modes
    stored), never store or compile (a compile costs minutes of CPU and GBs of memory
    once per problem structure: the user asks for it);
    ``background``: also compile a missing one in a detached process at exit; ``sync``:
    compile it in the foreground.
    """
    value = os.environ.get(ENV, "").strip().lower()
    if value in ("off", "0", "no", "false", "disabled"):
        return "off"
    return value if value in ("background", "sync") else "use"


#: why a miss is not compiled in the default mode
NOT_COMPILED = (f"not compiled: {ENV}=background (at exit) or {ENV}=sync (now) compiles it, "
                "once per problem structure (minutes of CPU, ~2 GB for the ball)")


#: the reason of a miss whose transcription was loaded (before what happens to the library)
TRANSCRIPTION_LOADED = "transcription loaded from the cache"
#: the reason's clause of a stored transcription a build verified but did not load
TRANSCRIPTION_STORED = "transcription stored in the cache"


#: the sources that turn a system and settings into the NLP's graph and code
GRAPH_SOURCES = ("mpc/**/*.py", "core/hybrid.py", "core/numeric.py", "core/cbuild.py")


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """sha256 of the :data:`GRAPH_SOURCES` of ``hmpc_cli`` (names and bytes).

    The system's own code needs no entry: its CasADi functions are in the key.
    """
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(p for pattern in GRAPH_SOURCES for p in root.glob(pattern)):
        h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def _fingerprint(value) -> object:
    """A JSON-ready fingerprint of a system's field (functions by their serialization)."""
    if isinstance(value, ca.Function):
        return hashlib.sha256(value.serialize().encode()).hexdigest()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _fingerprint(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {str(k): _fingerprint(v) for k, v in sorted(value.items(), key=str)}
    if isinstance(value, list | tuple):
        return [_fingerprint(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, str | int | float | bool) or value is None:
        return value
    # callables (margins, gains: parameters, not graph) and other objects: by type only
    return f"<{type(value).__module__}.{type(value).__qualname__}>"


def structure_key(system, settings, switches: int, variant: dict | None = None) -> str:
    """sha256 of everything that determines the NLP's graph (see the module docstring).

    Args:
        system: the controllers' hybrid system.
        settings: the MPC settings (a pydantic model).
        switches: S, the guard events of the chain.
        variant: another NLP than the chain (its kind and the numbers its graph holds
            beyond the settings, JSON-ready), e.g. ``{"kind": "walking", ...}``.
    """
    fields = {k: v for k, v in settings.model_dump(mode="json").items()
              if k not in NON_STRUCTURAL}
    material = {"format": FORMAT, "hmpc": __version__, "casadi": ca.__version__,
                "python": sys.version, "machine": platform.machine(),
                "source": source_digest(), "system": _fingerprint(system),
                "settings": fields, "switches": int(switches)}
    if variant is not None:  # absent for the chain: its keys (and compiled entries) stay
        material["variant"] = variant
    return hashlib.sha256(json.dumps(material, sort_keys=True).encode()).hexdigest()


class Entry:
    """The files of one cache entry (see the module docstring).

    Args:
        folder: the cache directory.
        key: the structure key.
        identity: the compiler's identity (:func:`hmpc_cli.core.cbuild.compiler_identity`).
    """

    def __init__(self, folder: Path, key: str, identity: str) -> None:
        """The entry's paths."""
        stem = f"nlp-{key[:32]}"
        cc = hashlib.sha256("\0".join([identity, *CFLAGS]).encode()).hexdigest()[:16]
        self.key, self.folder = key, folder
        self.meta = folder / f"{stem}.json"
        self.function = folder / f"{stem}.casadi"
        self.hessian = folder / f"{stem}-hess.casadi"
        self.library = folder / f"{stem}-{cc}.so"
        self.lock = folder / f"{stem}-{cc}.lock"
        self.failed = folder / f"{stem}-{cc}.failed"

    def check(self, path: Path, note: str = "") -> bool:
        """True if ``path`` is verified (and recorded with ``note``); else it is removed.

        A damaged or foreign file (bytes not matching its sha256, or recorded for another
        key) is reported as a warning.
        """
        if cbuild.verified(path) and (not note or cbuild.recorded(path)[2:3] == [note]):
            return True
        if path.exists():
            _LOG.warning("%s does not match its recorded sha256%s: rebuilding it", path,
                         f" and key {note[:16]}" if note else "")
            for p in (path, cbuild.hash_path(path)):
                with contextlib.suppress(OSError):
                    p.unlink()
        return False


def _disabled(reason: str) -> Hit:
    return Hit(None, None, BuildInfo("disabled", False, reason))


def open_entry(key: str, plugin: str) -> tuple[Entry | None, Hit | None]:
    """The entry of ``key``, or None and why the cache is not used."""
    if mode() == "off":
        return None, _disabled(f"{ENV}=off: no NLP is compiled")
    if not backend_of(plugin).compilable:
        able = " or ".join(b.name for b in SOLVERS.values() if b.compilable)
        return None, _disabled(f"solver {plugin!r}: compiled NLPs are for {able} only")
    cc = cbuild.compiler()
    if cc is None:
        why = cbuild.compiler_problem() or "no C compiler found (set CC or install cc/gcc)"
        return None, _disabled(f"{why}: no NLP is compiled")
    try:
        identity = cbuild.compiler_identity(cc)
    except cbuild.CBuildError as e:
        return None, _disabled(f"{e}: no NLP is compiled")
    folder, unsafe = cbuild.checked_cache_dir()
    if unsafe:
        return None, _disabled(f"cache directory {folder} is not used ({unsafe})")
    return Entry(folder, key, identity), None


def _meta(entry: Entry) -> dict:
    """The entry's (verified) layout file: ``format``, ``key``, ``layout``, ``hess_lag``.

    Raises:
        ValueError: the file is missing, damaged, unreadable or another entry's.
    """
    if not entry.check(entry.meta):
        raise ValueError(f"{entry.meta} is missing or damaged")
    try:
        meta = json.loads(entry.meta.read_text())
    except (OSError, ValueError) as e:
        raise ValueError(f"{entry.meta}: {e}") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or \
            meta.get("key") != entry.key:
        raise ValueError(f"{entry.meta} belongs to another entry")
    return meta


def _load_function(entry: Entry, path: Path, n_in: int, n_out: int,
                   what: str) -> ca.Function:
    """The CasADi function stored in the entry's file ``path`` (``what``: its signature).

    Raises:
        ValueError: the file is missing or damaged, or not such a function.
    """
    if not entry.check(path, entry.key):
        raise ValueError(f"{path} is missing or damaged")
    try:
        fun = ca.Function.deserialize(path.read_bytes().decode())
    except (OSError, RuntimeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: {e}") from e
    if fun.n_in() != n_in or fun.n_out() != n_out:
        raise ValueError(f"{path} is not {what}")
    return fun


def load_transcription(entry: Entry) -> dict:
    """The entry's NLP ``{"x", "p", "f", "g"}``: its stored function called on new symbols.

    Raises:
        ValueError: the function is missing, damaged or not a CasADi function.
    """
    fun = _load_function(entry, entry.function, 2, 2, "an NLP's (x, p) -> (f, g)")
    x = ca.SX.sym("x", fun.size1_in(0))
    p = ca.SX.sym("p", fun.size1_in(1))
    f, g = fun(x, p)
    return {"x": x, "p": p, "f": f, "g": g}


def load_hessian(entry: Entry) -> ca.Function | None:
    """The entry's stored ``hess_lag``, or None if its layout file records none.

    Raises:
        ValueError: the layout file or the Hessian's is missing or damaged, or the
            Hessian is not a function of (x, p, lam_f, lam_g).
    """
    if not _meta(entry).get("hess_lag"):
        return None
    return _load_function(entry, entry.hessian, 4, 1, "a Hessian's (x, p, lam_f, lam_g) -> H")


def lookup(key: str, plugin: str, load: bool = True) -> Hit:
    """The compiled library and layout of ``key`` if cached and verified, else why not.

    On a miss, the stored transcription and layout if they are verified; ``load=False``:
    the transcription's file verified, not loaded (a build that does not use it).
    """
    entry, off = open_entry(key, plugin)
    if entry is None:
        return off
    if not entry.check(entry.meta):
        return Hit(None, None, BuildInfo("miss", False, "not in the cache"))
    try:
        meta = _meta(entry)
        layout = NLPLayout.from_dict(meta["layout"])
    except (ValueError, KeyError, TypeError) as e:
        _LOG.warning("%s is unusable (%s): rebuilding it", entry.meta, e)
        return Hit(None, None, BuildInfo("miss", False, f"unusable entry: {e}"))
    if entry.check(entry.library, entry.key):
        return Hit(str(entry.library), layout,
                   BuildInfo("hit", True, f"loaded {entry.library.name}"))
    if not entry.function.exists():  # removed as damaged, or by hand: nothing to report
        return Hit(None, None, BuildInfo("miss", False, "not in the cache"))
    try:
        nlp = None
        if load:
            nlp = load_transcription(entry)
            sizes = (nlp["x"].numel(), nlp["p"].numel(), nlp["g"].numel())
            if sizes != (layout.x.size, layout.p.size, layout.g.size):
                raise ValueError(f"{entry.function}: sizes {sizes} are not its layout's")
        elif not entry.check(entry.function, entry.key):
            raise ValueError(f"{entry.function} is damaged")
        if meta.get("hess_lag") and not entry.check(entry.hessian, entry.key):
            raise ValueError(f"{entry.hessian} is missing or damaged")
    except ValueError as e:
        _LOG.warning("%s: transcribing the NLP again", e)
        return Hit(None, None, BuildInfo("miss", False, "not in the cache"))
    return Hit(None, layout, BuildInfo("miss", False, TRANSCRIPTION_LOADED if load
                                       else TRANSCRIPTION_STORED), nlp, stored=True)


def store(key: str, plugin: str, nlp: dict | None, layout: NLPLayout, *,
          stored: bool = False, hess_lag: ca.Function | None = None) -> BuildInfo:
    """Stores a freshly built NLP's layout and function, and starts its compilation.

    In the default mode (``use``) nothing is stored: transcribing the NLP again costs
    what loading its function does.

    Args:
        key: the entry's structure key.
        plugin: the solver back-end's name.
        nlp: the NLP ``{"x", "p", "f", "g"}`` in SX (None: in the default mode, which
            stores nothing, or ``stored`` and not loaded).
        layout: its layout.
        stored: they are stored already (the NLP loaded from them, or ``nlp`` None:
            verified only).
        hess_lag: the Hessian of the Lagrangian the NLP gives IPOPT (None: ``nlpsol``'s);
            the library is compiled with it.

    Returns:
        The build info of this (SX) build: ``miss``, whether the transcription was loaded,
        and what happens to the library.
    """
    entry, off = open_entry(key, plugin)
    if entry is None:
        return off.info
    fate = _library_fate(entry, nlp, layout, stored, hess_lag)
    said = TRANSCRIPTION_LOADED if nlp is not None else TRANSCRIPTION_STORED
    return BuildInfo("miss", False, f"{said}; {fate}" if stored else fate)


def _library_fate(entry: Entry, nlp: dict | None, layout: NLPLayout, stored: bool,
                  hess_lag: ca.Function | None) -> str:
    """What happens to the entry's library.

    ``sync`` compiles it now and ``background`` queues it, after storing the function and
    layout (unless ``stored``); ``use`` does neither.
    """
    if mode() == "use":
        return NOT_COMPILED
    if not stored:
        fun = ca.Function("nlp", [nlp["x"], nlp["p"]], [nlp["f"], nlp["g"]],
                          ["x", "p"], ["f", "g"])
        try:
            cbuild.write_verified(entry.function, fun.serialize(), entry.key)
            if hess_lag is not None:
                cbuild.write_verified(entry.hessian, hess_lag.serialize(), entry.key)
            cbuild.write_verified(entry.meta, json.dumps(
                {"format": FORMAT, "key": entry.key, "layout": layout.to_dict(),
                 "hess_lag": hess_lag is not None}, sort_keys=True))
        except OSError as e:
            return f"cannot write the cache: {e}"
    if entry.failed.exists():
        return f"compilation failed before (see {entry.failed})"
    if mode() == "sync":
        try:
            seconds = compile_entry(entry)
        except cbuild.CBuildError as e:
            return f"compilation failed: {e}"
        return f"compiled {entry.library.name} in {seconds:.1f} s"
    return _spawn(entry)


#: [s] a lock file without a readable owner is taken over after this (its creator
#: writes its owner right after creating it)
LOCK_GRACE = 5.0


def _start_time(pid: int) -> str:
    """The start time of process ``pid`` (clock ticks since boot; '' if unknown).

    With the pid it names one process: a pid reused after its process died has another
    start time.
    """
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat[stat.rindex(")") + 2:].split()[19]
    except (OSError, ValueError, IndexError):
        return ""


def lock_owner(pid: int | None = None) -> str:
    """A compile lock's content: ``<pid> <start time>`` of the process holding it."""
    pid = os.getpid() if pid is None else int(pid)
    return f"{pid} {_start_time(pid)}".rstrip()


def _stale(lock: Path) -> bool:
    """True if ``lock`` may be taken over: its owner process is gone, or it is too old.

    Gone: the recorded pid runs no process, or runs another process than the one that
    took the lock (its start time differs: the pid was reused). A lock without a readable
    owner (empty, garbage) is stale after :data:`LOCK_GRACE` seconds, any lock after
    :data:`LOCK_STALE`.
    """
    try:
        age = time.time() - lock.stat().st_mtime
        fields = lock.read_text().split()
    except OSError:
        return False  # no lock (taken below), or unreadable: not ours to remove
    if age > LOCK_STALE:
        return True
    try:
        pid = int(fields[0])
        if pid <= 0:
            raise ValueError(pid)
    except (IndexError, ValueError):
        return age > LOCK_GRACE
    if not process_exists(pid):
        return True
    started, now = (fields[1] if len(fields) > 1 else ""), _start_time(pid)
    return bool(started and now and started != now)


def _take_lock(entry: Entry) -> bool:
    """Creates the entry's lock file (False if another live compile holds it).

    The lock records this process (:func:`lock_owner`); one whose owner died is taken
    over at once.
    """
    if _stale(entry.lock):
        _LOG.info("taking over the stale compile lock %s", entry.lock)
        entry.lock.unlink(missing_ok=True)
    try:
        fd = os.open(entry.lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except OSError:  # held by a live compile (FileExistsError), or not writable
        return False
    os.write(fd, lock_owner().encode())
    os.close(fd)
    return True


def _spawn(entry: Entry) -> str:
    """Queues ``entry`` for the background compile started at exit; returns what was done.

    The lock is taken now; one detached process compiles this process's entries one after
    the other once it exits (never competing with its run, one compiler's memory at a
    time).
    """
    if not _take_lock(entry):
        return f"being compiled by another process ({entry.lock.name})"
    if not _QUEUE:
        atexit.register(_start_queue)
    _QUEUE.append(entry)
    return f"{entry.library.name} is compiled in the background when this process exits"


def _start_queue() -> None:
    """Starts the detached compile of the queued entries (at exit)."""
    entries, _QUEUE[:] = list(_QUEUE), []
    root = str(Path(__file__).resolve().parents[2])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (root, os.environ.get("PYTHONPATH", "")) if p)}
    args = [a for e in entries for a in (str(e.folder), e.key)]
    try:
        proc = subprocess.Popen([sys.executable, "-m", "hmpc_cli.mpc.cache", *args], env=env,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)
    except OSError:
        for e in entries:
            e.lock.unlink(missing_ok=True)
        return
    for e in entries:  # the compiling process owns the locks before this one exits
        with contextlib.suppress(OSError):
            cbuild.atomic_write(e.lock, lock_owner(proc.pid))


def generate(entry: Entry, folder: Path) -> Path:
    """Writes the C of the entry's ``nlpsol`` functions into ``folder``; returns its path.

    Raises:
        cbuild.CBuildError: the stored function is damaged or the code cannot be made.
    """
    try:
        nlp = load_transcription(entry)
        hess = load_hessian(entry)
    except ValueError as e:
        raise cbuild.CBuildError(str(e)) from e
    try:
        solver = ca.nlpsol("nlp", "ipopt", nlp, without_nlp_grad(
            {"expand": True, "calc_lam_p": False, **({"hess_lag": hess} if hess else {})}))
        with contextlib.chdir(folder):
            _generate_c(solver, "nlp.c")
    except RuntimeError as e:
        raise cbuild.CBuildError(f"code generation failed: {e}") from e
    return folder / "nlp.c"


def _generate_c(solver: ca.Function, name: str) -> None:
    """``solver.generate_dependencies(name)``, the functions given as options included.

    ``generate_dependencies`` writes the oracle and the functions ``nlpsol`` generated,
    sorted by name, but not one it was given (``hess_lag``); the same C for the rest.
    """
    gen = ca.CodeGenerator(name, {"with_header": False})
    gen.add(solver.oracle())
    for fn in solver.get_function():  # sorted by name
        gen.add(solver.get_function(fn))
    gen.generate()


def compile_entry(entry: Entry) -> float:
    """Generates and compiles the entry's library (verified on disk); returns seconds.

    Raises:
        cbuild.CBuildError: no compiler, generation or compilation failed.
    """
    cc = cbuild.compiler()
    if cc is None:
        raise cbuild.CBuildError("no C compiler found")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="hmpc-nlp-") as work:
        source = generate(entry, Path(work))
        cbuild.compile_shared(cc, CFLAGS, source, entry.library, note=entry.key)
    seconds = time.perf_counter() - start
    _LOG.info("compiled %s in %.1f s", entry.library, seconds)
    return seconds


def _main(args: list[str]) -> int:
    """The background compile: ``python -m hmpc_cli.mpc.cache (<folder> <key>)...``."""
    with contextlib.suppress(OSError, AttributeError):
        os.nice(10)
    cc = cbuild.compiler()
    identity = cbuild.compiler_identity(cc) if cc else ""
    entries = [Entry(Path(f), k, identity) for f, k in zip(args[::2], args[1::2], strict=True)]
    for entry in entries:  # the locks are this process's now
        cbuild.atomic_write(entry.lock, lock_owner())
    for folder in {e.folder for e in entries}:  # left by compiles killed midway
        cbuild.remove_stale_temporaries(folder)
    failures = 0
    for entry in entries:
        try:
            compile_entry(entry)
        except cbuild.CBuildError as e:
            cbuild.atomic_write(entry.failed, f"{e}\n")
            failures += 1
        finally:
            entry.lock.unlink(missing_ok=True)
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
