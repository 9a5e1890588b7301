"""The machine a run computes on: its CPU model, and whether a process of it exists.

The CPU model can move a result's last bits; a process that no longer exists leaves a
lock or a staging folder to take over.

NumPy and the BLAS under IPOPT choose their kernels by the CPU, so two machines with the
same versions can give runs that differ in the last digits (docs/running.md).
"""

from __future__ import annotations

import functools
import os
import platform


@functools.cache
def cpu_model() -> str:
    """The CPU's model name, e.g. ``AMD EPYC``.

    Linux: /proc/cpuinfo's first ``model name``; elsewhere the platform's processor or
    machine type.
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return " ".join(value.split())
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def process_exists(pid: int) -> bool:
    """Whether process ``pid`` exists on this machine (another user's too)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # it exists, another user's
        return True
    return True
