r"""Paths as the results page shows them: repository-relative, never a machine's absolute path.

The page is committed; an absolute path (``/home/me/...``, ``C:\...``) names one machine's
file system. A path inside the repository (the working directory ``hmpc report`` runs in) is
written relative to it; one outside as ``<...>/`` and its last two components, a
placeholder for the reader's own directory.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path, PureWindowsPath

__all__ = ["PLACEHOLDER", "portable_command", "portable_path", "portable_text",
           "repository_file"]

PLACEHOLDER = "<...>"
#: an absolute POSIX path (two components at least) or a Windows drive path in text
_ABSOLUTE = re.compile(r"(?<![\w.~/<>-])(?:/[\w.+~-]+(?:/[\w.+~@%=,-]*)+|[A-Za-z]:\\[^\s`'\"|):]*)")


def _is_absolute(text: str) -> bool:
    return text.startswith(("/", "~")) or PureWindowsPath(text).drive != ""


def portable_path(path: str | Path, root: str | Path | None = None) -> str:
    """``path`` relative to ``root`` (default: the working directory) or a placeholder.

    A relative path is kept as it is (POSIX separators).
    """
    text = str(path)
    if not _is_absolute(text):
        return Path(text).as_posix()
    root = Path.cwd() if root is None else Path(root)
    if not PureWindowsPath(text).drive:
        p = Path(text).expanduser()
        for a, b in ((p, root), (p.resolve(), root.resolve())):
            try:
                rel = a.relative_to(b).as_posix()
                return rel if rel != "." else "."
            except ValueError:
                continue
    parts = [q for q in re.split(r"[\\/]", text) if q and not q.endswith(":")][-2:]
    return "/".join([PLACEHOLDER, *parts])


def portable_command(command: str, root: str | Path | None = None) -> str:
    """A command line with every absolute path argument (also ``--opt=PATH``) made portable."""
    try:
        args = shlex.split(command)
    except ValueError:
        return portable_text(command, root)
    out = []
    for arg in args:
        opt, eq, value = arg.partition("=") if arg.startswith("--") else ("", "", arg)
        if value and _is_absolute(value):
            value = portable_path(value, root)
        out.append(f"{opt}{eq}{value}")
    return " ".join(a if PLACEHOLDER in a and shlex.quote(a.replace(PLACEHOLDER, "x")) ==
                    a.replace(PLACEHOLDER, "x") else shlex.quote(a) for a in out)


#: the first components of the log's topic names (``/run/summary`` is not a path)
_TOPICS = {"run", "sim", "mpc", "planner", "scene", "disturbance"}


def portable_text(text: str, root: str | Path | None = None) -> str:
    """``text`` with every absolute path in it made portable (see :func:`portable_path`).

    A log topic's name (``/run/summary``, ``/sim/event``...) is left as it is.
    """
    def sub(m: re.Match) -> str:
        found = m.group(0)
        if found.startswith("/") and found.split("/")[1] in _TOPICS:
            return found
        return portable_path(found, root)

    return _ABSOLUTE.sub(sub, text)


def repository_file(folder: str, name: str) -> str:
    """```folder/name``` in Markdown when the repository holds it, else ```name```.

    A section made from a sweep outside the repository's layout (an output directory of
    the user's own sweep) names no file the reader cannot find.
    """
    path = Path(folder) / name
    return f"`{path.as_posix()}`" if path.is_file() else f"`{name}`"
