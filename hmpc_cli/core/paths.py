"""Where hmpc writes: one output-path check for every command, files written whole or not at all.

:func:`output_problem` says why a path cannot take a command's output (an empty name, a
name longer than the file system allows, a dangling symbolic link or a loop, a virtual file
system such as /proc, a file where a directory is needed, a directory that cannot be
written); it creates and removes nothing. Every writing option (``run --out``, ``sweep
--out``, ``plot --out``, ``tube --out/--write``, ``report --results``, ``replay
--export/--figures``) is checked with it before any work starts (:func:`check_output`,
:class:`OutputPathError`: exit 2). :func:`atomic_file` writes a file under a temporary name
and renames it: a failed write (a full disk) leaves neither a temporary nor a half file.
:func:`file_digest` says what an input file held, for a later run to compare.

Light on purpose (the standard library only): ``hmpc --help`` imports it.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from pathlib import Path, PosixPath

__all__ = ["DISK_ERRNOS", "EmptyPath", "OutputPathError", "atomic_file", "check_output",
           "disk_error", "file_digest", "first_names", "output_problem", "path_option",
           "write_atomic"]

#: errors of a full or read-only disk: bad environment (exit 2), not a bug
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG})
#: virtual file systems: no place for a command's files
VIRTUAL = ("/proc", "/sys", "/dev")
NAME_MAX, PATH_MAX = 255, 4096


class OutputPathError(ValueError):
    """A path that cannot take a command's output; the message is one line (exit 2)."""


class EmptyPath(PosixPath):
    """An option given as the empty string (a plain ``Path("")`` would be ``.``)."""


def path_option(value: str) -> Path:
    """Typer ``parser`` of a writing option: ``""`` becomes :class:`EmptyPath` (refused)."""
    return EmptyPath(".") if not str(value).strip() else Path(value)


def _prefixes(path: Path) -> list[Path]:
    """The absolute path's prefixes, root first (``/a``, ``/a/b``, ...)."""
    parts = path.parts
    return [Path(*parts[:k]) for k in range(2, len(parts) + 1)]


def _link_problem(path: Path) -> str | None:
    """A dangling symbolic link or a loop on the way to ``path``, else None."""
    for prefix in _prefixes(path):
        if not prefix.is_symlink():
            continue
        try:
            os.stat(prefix)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                return f"{prefix} is a symbolic link loop"
            if exc.errno == errno.ENOENT:
                return f"{prefix} is a dangling symbolic link (to {os.readlink(prefix)})"
            return f"{prefix}: {exc.strerror or exc}"
    return None


def _writable(directory: Path) -> str | None:
    """Why files cannot be created in the existing directory ``directory``, or None."""
    try:
        if os.statvfs(directory).f_flag & os.ST_RDONLY:
            return f"{directory} is on a read-only file system"
    except OSError as exc:
        return f"{directory}: {exc.strerror or exc}"
    if not os.access(directory, os.W_OK | os.X_OK):
        return f"{directory} is not writable"
    return None


def output_problem(path: Path | str, kind: str = "dir") -> str | None:
    """Why ``path`` cannot take a command's output, or None; creates and removes nothing.

    Args:
        path: the output.
        kind: ``dir`` (a directory, created if missing) or ``file`` (a file, replaced).
    """
    if isinstance(path, EmptyPath) or not str(path).strip():
        return "an empty path (name a directory or file)"
    p = Path(path)
    try:
        absolute = Path(os.path.abspath(p))
        if len(os.fsencode(str(absolute))) >= PATH_MAX:
            return f"path too long ({len(os.fsencode(str(absolute)))} bytes, max {PATH_MAX - 1})"
        for part in absolute.parts:
            if len(os.fsencode(part)) > NAME_MAX:
                return (f"name too long: {part[:40]}... ({len(os.fsencode(part))} bytes, the "
                        f"file system allows {NAME_MAX})")
        link = _link_problem(absolute)
        if link is not None:
            return link
        real = os.path.realpath(absolute)
        for root in VIRTUAL:
            if real == root or real.startswith(root + "/"):
                return f"{real} is in {root}, a virtual file system"
        return _place_problem(absolute, kind, not p.is_absolute())
    except (OSError, RuntimeError, ValueError) as exc:
        return f"not a usable path: {exc}"


def _place_problem(absolute: Path, kind: str, relative: bool) -> str | None:
    """:func:`output_problem` of a well-formed absolute path: what is there, writable.

    ``relative``: name the directories in the way relative to the working directory.
    """
    if absolute.exists():
        if kind == "dir" and not absolute.is_dir():
            return "exists and is not a directory"
        if kind == "file" and absolute.is_dir():
            return "is a directory (name a file)"
        if kind == "file" and not os.access(absolute, os.W_OK):
            return "is not writable"
        return _writable(absolute if kind == "dir" else absolute.parent)
    parent = absolute.parent
    while not parent.exists() and parent.parent != parent:
        parent = parent.parent
    shown = os.path.relpath(parent) if relative else str(parent)
    if not parent.is_dir():
        return f"cannot create it: {shown} is not a directory (a file is in the way)"
    problem = _writable(parent)
    return f"cannot create it: {problem}" if problem else None


def check_output(path: Path, option: str, kind: str = "dir") -> Path:
    """``path`` when :func:`output_problem` finds nothing.

    Raises:
        OutputPathError: ``<option> <path>: <problem>``.
    """
    problem = output_problem(path, kind)
    if problem is not None:
        shown = '""' if isinstance(path, EmptyPath) else str(path)
        raise OutputPathError(f"{option} {shown}: {problem}")
    return Path(path)


@contextlib.contextmanager
def atomic_file(path: Path) -> Iterator[Path]:
    """Yields a temporary name next to ``path``; renamed to ``path`` when the block ends.

    When the block raises, the temporary is deleted and ``path`` is left as it was: a
    reader never finds half a file, nor a file that was claimed but not written.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_atomic(path: Path, data: str | bytes) -> Path:
    """Writes ``data`` (text as UTF-8) to ``path`` through :func:`atomic_file`."""
    with atomic_file(path) as tmp:
        if isinstance(data, str):
            tmp.write_text(data, encoding="utf-8")
        else:
            tmp.write_bytes(data)
    return Path(path)


def disk_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a full or read-only disk (:data:`DISK_ERRNOS`)."""
    return isinstance(exc, OSError) and exc.errno in DISK_ERRNOS


def disk_error_text(exc: OSError) -> str:
    """One line for a disk error: the file and the reason."""
    where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
    return f"{where}{exc.strerror or exc}"


def first_names(names: list[str]) -> str:
    """The first three of a directory's entries for a message: ``a, b, c, ...``."""
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


def file_digest(path: str | Path) -> str | None:
    """``sha256:<hex>`` of a file's bytes (None: it cannot be read)."""
    import hashlib

    try:
        return "sha256:" + hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None
