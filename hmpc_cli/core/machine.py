"""The machine a run computes on: its CPU model, which can move a result's last bits.

NumPy and the BLAS under IPOPT choose their kernels by the CPU, so two machines with the
same versions can give runs that differ in the last digits (docs/running.md).
"""

from __future__ import annotations

import functools
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
