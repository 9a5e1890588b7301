"""Shared pieces of hmpc's compiled-code caches.

Where they live, who may write there, which compiler builds, and how a built file is
verified before it is loaded.

Used by the planner's C rollouts (:mod:`hmpc_cli.sim.rollout`) and the MPC's
compiled NLPs (:mod:`hmpc_cli.mpc.cache`). The rules, the same for both:

* the cache is ``$HMPC_CACHE_DIR`` (default ``~/.cache/hmpc``), created with mode 0700;
* a directory writable by group or others, or owned by another user, is never used for
  files that get executed or loaded (:func:`unsafe_reason`);
* every built file is written atomically (temporary file + ``os.replace``) with its sha256
  next to it (``<file>.sha256``), and is loaded only when its bytes match (:func:`verified`);
* a cache key covers the compiler's identity (resolved path and a hash of its ``--version``
  output, :func:`compiler_identity`) and the flags.

No CasADi here: this module is cheap to import.
"""

from __future__ import annotations

import atexit
import contextlib
import hashlib
import os
import shlex
import shutil
import subprocess
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path

_IDENTITY: dict[tuple[str, ...], str] = {}  # compiler identity by command
_PRIVATE: list[Path] = []  # this process's private build directory, once made


class CBuildError(RuntimeError):
    """Code could not be compiled, or the compiler cannot be run."""


_CC_WARNED: set[str] = set()  # unparsable $CC values already warned about


def compiler_problem() -> str:
    """Why ``$CC`` cannot be used as a command ('' if it can, or is not set)."""
    cc = os.environ.get("CC")
    if not cc:
        return ""
    try:
        words = shlex.split(cc)
    except ValueError as e:
        return f"CC={cc!r} cannot be parsed ({e})"
    return "" if words else f"CC={cc!r} names no command"


def compiler() -> list[str] | None:
    """The C compiler command: ``$CC`` if set, else ``cc`` or ``gcc`` on the PATH.

    A ``$CC`` that cannot be parsed as a shell command (an unbalanced quote) means no
    compiler: compiled NLPs and C rollouts are not used, and one warning says why (once
    per process); it never fails a run.
    """
    cc = os.environ.get("CC")
    if cc:
        problem = compiler_problem()
        if problem:
            if cc not in _CC_WARNED:
                _CC_WARNED.add(cc)
                warnings.warn(f"{problem}: no C compiler is used (the NLPs stay uncompiled, "
                              "the planner's rollouts run in NumPy)", RuntimeWarning,
                              stacklevel=2)
            return None
        return shlex.split(cc)
    found = shutil.which("cc") or shutil.which("gcc")
    return [found] if found else None


def cache_dir() -> Path:
    """Where compiled code is kept: ``$HMPC_CACHE_DIR`` or ``~/.cache/hmpc``."""
    return Path(os.environ.get("HMPC_CACHE_DIR") or Path.home() / ".cache" / "hmpc")


def unsafe_reason(folder: Path) -> str:
    """Why ``folder`` must not hold files that get executed ('' if it may).

    Unsafe: not a directory, owned by another user, or writable by group or others.
    """
    try:
        st = folder.stat()
    except OSError as e:
        return f"cannot stat it: {e}"
    if not folder.is_dir():
        return "not a directory"
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        return f"owned by uid {st.st_uid}, not by this user"
    if st.st_mode & 0o022:
        return f"writable by group or others (mode {st.st_mode & 0o777:o})"
    return ""


def checked_cache_dir() -> tuple[Path, str]:
    """The cache directory (created 0700 if missing) and why it is unsafe ('' if safe)."""
    folder = cache_dir()
    with contextlib.suppress(OSError):  # reported as unsafe below
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    return folder, unsafe_reason(folder)


def private_dir(what: str, folder: Path, reason: str) -> Path:
    """This process's private temporary build directory (removed at exit), once made.

    Warns once that ``folder`` is not used for ``what`` because of ``reason``.
    """
    if not _PRIVATE:
        _PRIVATE.append(Path(tempfile.mkdtemp(prefix="hmpc-build-")))
        atexit.register(shutil.rmtree, _PRIVATE[0], ignore_errors=True)
        warnings.warn(f"{what} cache {folder} is not used ({reason}); building in "
                      f"{_PRIVATE[0]}", RuntimeWarning, stacklevel=3)
    return _PRIVATE[0]


def compiler_identity(cc: list[str]) -> str:
    """The compiler's resolved path, its extra arguments and a hash of ``--version``.

    Raises:
        CBuildError: the compiler cannot be run.
    """
    key = tuple(cc)
    if key not in _IDENTITY:
        exe = shutil.which(cc[0]) or cc[0]
        try:
            out = subprocess.run([*cc, "--version"], capture_output=True, text=True,
                                 timeout=60, check=False)
        except (OSError, subprocess.SubprocessError) as e:
            raise CBuildError(f"cannot run {shlex.join(cc)}: {e}") from e
        digest = hashlib.sha256((out.stdout + out.stderr).encode()).hexdigest()
        _IDENTITY[key] = f"{os.path.realpath(exe)} {shlex.join(cc[1:])} {digest}"
    return _IDENTITY[key]


def file_sha256(path: Path) -> str:
    """sha256 hex digest of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def hash_path(path: Path) -> Path:
    """Where the recorded sha256 of ``path`` is kept (``<name>.sha256``)."""
    return path.with_name(path.name + ".sha256")


def verified(path: Path) -> bool:
    """True if ``path`` exists and its bytes match the recorded sha256."""
    try:
        recorded = hash_path(path).read_text().split()[0]
        return file_sha256(path) == recorded
    except (OSError, IndexError):
        return False


def atomic_write(path: Path, data: str | bytes) -> None:
    """Writes ``data`` to ``path`` through a temporary file in the same directory."""
    fd, tmp = tempfile.mkstemp(prefix=".hmpc-", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_verified(path: Path, data: str | bytes, note: str = "") -> None:
    """Writes ``data``'s sha256 next to ``path``, then ``data`` (both atomically).

    ``note`` (one word, e.g. a cache key) follows the sha256 in its record.
    """
    raw = data.encode() if isinstance(data, str) else data
    record = f"{hashlib.sha256(raw).hexdigest()}  {path.name}  {note}".rstrip() + "\n"
    atomic_write(hash_path(path), record)
    atomic_write(path, raw)


def remove_stale_temporaries(folder: Path, age: float = 86400.0) -> int:
    """Removes this module's temporary files older than ``age`` [s] (of killed builds).

    Returns:
        How many were removed.
    """
    removed = 0
    for tmp in folder.glob(".hmpc-*"):
        with contextlib.suppress(OSError):
            if time.time() - tmp.stat().st_mtime > age:
                tmp.unlink()
                removed += 1
    return removed


def recorded(path: Path) -> list[str]:
    """The fields of the sha256 record of ``path`` (digest, name, notes; [] if none)."""
    try:
        return hash_path(path).read_text().split()
    except OSError:
        return []


def compile_shared(cc: list[str], flags: tuple[str, ...], source: Path, path: Path,
                   timeout: float = 1800.0, note: str = "",
                   started: Callable[[subprocess.Popen], None] | None = None) -> float:
    """Compiles C file ``source`` to shared library ``path``; returns the seconds taken.

    The library is compiled to a temporary file beside ``path`` and moved in place
    (``os.replace``) after its sha256 is written next to it (atomically), followed by
    ``note`` (one word, e.g. the cache key the library was built for). ``started`` gets
    the compiler's process as soon as it runs, its own process group then (a caller that
    may have to stop it and the programs it runs: ``os.killpg``).

    Raises:
        CBuildError: the directory is not writable, the compiler cannot be run or fails.
    """
    start = time.perf_counter()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".hmpc-", suffix=".so", dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise CBuildError(f"cache directory {path.parent} is not writable: {e}") from e
    try:
        cmd = [*cc, *flags, "-o", tmp, str(source), "-lm"]
        try:
            with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, errors="replace",
                                  process_group=0 if started is not None else None) as proc:
                if started is not None:
                    started(proc)
                try:
                    _, stderr = proc.communicate(timeout=timeout)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.communicate()
                    raise
        except (OSError, subprocess.SubprocessError) as e:
            raise CBuildError(f"cannot run {shlex.join(cc)}: {e}") from e
        if proc.returncode != 0:
            raise CBuildError(f"{shlex.join(cmd)} failed:\n{stderr[-2000:]}")
        digest = file_sha256(Path(tmp))
        # the record first: a reader never sees the new library without it
        atomic_write(hash_path(path), f"{digest}  {path.name}  {note}".rstrip() + "\n")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return time.perf_counter() - start
