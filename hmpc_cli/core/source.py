"""The hmpc source a run computes with: the git commit of the checkout it runs from.

``hmpc_cli.__version__`` names a release, not the code between two releases; a run made
from a git checkout (``pip install -e .``) also records the commit, and whether tracked
files differed from it (docs/running.md).
"""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

#: the checkout hmpc runs from, if it runs from one (an installed wheel's is site-packages)
ROOT = Path(__file__).resolve().parents[2]


@functools.cache
def source_commit(root: Path = ROOT) -> str:
    """The commit of the git checkout at ``root``, ``" (modified)"`` appended if need be.

    The commit is 40 hex digits; `` (modified)`` follows when a tracked file differs from
    it, `` (modified: unknown)`` when git names the commit but cannot compare the files.
    ``""``: ``root`` holds no ``.git``, or git cannot tell the commit (git missing or
    timing out, not a repository, no commit yet).

    Untracked files (a virtual environment, run outputs) do not count as modified. Only
    ``root`` itself is looked at, never a repository around it, and ``GIT_*`` variables
    of the environment (a git hook's) are not followed.
    """
    import os

    if not (root / ".git").exists():
        return ""
    # no optional locks: a status beside the user's own git commands (or another run's)
    # neither waits for nor takes the index lock
    git = ["git", "--no-optional-locks", f"--git-dir={root / '.git'}", f"--work-tree={root}"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    try:
        head = subprocess.run([*git, "rev-parse", "--verify", "-q", "HEAD"],
                              capture_output=True, text=True, timeout=10, env=env)
        if head.returncode != 0:
            return ""
        status = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=10, env=env)
    except (OSError, subprocess.SubprocessError):
        return ""
    commit = head.stdout.strip()
    if status.returncode != 0:
        return f"{commit} (modified: unknown)"
    return f"{commit} (modified)" if status.stdout.strip() else commit
