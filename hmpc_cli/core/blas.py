"""NumPy's BLAS kernels pinned, so that x86-64 machines compute the same bits.

NumPy's OpenBLAS is built for many CPUs at once (``DYNAMIC_ARCH``) and picks its kernels by
the CPU it runs on: an AVX-512 machine and an AVX2 one multiply and solve the same small
matrices with different instruction sequences, and their results differ in the last
bits. A closed loop near a failure (a biped's, above all with its compute time charged)
then goes another way, whole runs of a committed table with it. :func:`pin_kernels` asks
OpenBLAS for its Haswell kernels (AVX2 and FMA) on every x86-64 CPU that has them, before
NumPy loads them; :func:`kernels` says what the process runs. CasADi's own OpenBLAS (under
MUMPS) is built for one CPU target and needs no pin.

Standard library only: this module runs when ``hmpc_cli`` is imported, before NumPy is.
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys

#: the OpenBLAS kernels hmpc pins on an x86-64 CPU with AVX2 and FMA
PINNED = "Haswell"
#: the CPU flags (Linux /proc/cpuinfo) those kernels need
NEEDS = frozenset({"avx", "avx2", "fma"})
#: the environment variable OpenBLAS reads its kernels from when it loads
VARIABLE = "OPENBLAS_CORETYPE"

#: whether NumPy was loaded when this process set the variable (empty: it did not set it)
_late: list[bool] = []

def _cpu_flags() -> frozenset[str]:
    """The CPU's flags from /proc/cpuinfo (empty where there is none)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "flags":
                    return frozenset(value.split())
    except OSError:
        pass
    return frozenset()


def pin_kernels() -> None:
    """Sets ``OPENBLAS_CORETYPE=Haswell`` for this process and its children.

    Only on an x86-64 Linux CPU with AVX2 and FMA, and only when the variable is unset (a
    user's own choice stands). NumPy imported before this call has loaded its kernels
    already: the pin then reaches only the child processes (sweep workers), and
    :func:`kernels` says so.
    """
    if VARIABLE in os.environ or platform.machine().lower() not in ("x86_64", "amd64"):
        return
    if not _cpu_flags() >= NEEDS:
        return
    os.environ[VARIABLE] = PINNED
    _late.append("numpy" in sys.modules)


def _core_names() -> list[str]:
    """The kernel names of the OpenBLAS libraries NumPy loaded ([] if none is found)."""
    try:
        with open("/proc/self/maps", encoding="utf-8", errors="replace") as f:
            paths = {line.split(maxsplit=5)[-1].strip() for line in f if "openblas" in line}
    except OSError:
        return []
    names = []
    for path in sorted(p for p in paths if p.startswith("/") and "numpy" in p):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for symbol in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename",
                       "openblas_get_corename"):
            get = getattr(lib, symbol, None)
            if get is not None:
                get.restype = ctypes.c_char_p
                names.append(get().decode("ascii", "replace"))
                break
    return names


def kernels() -> str:
    """NumPy's OpenBLAS kernels in this process, with ``OPENBLAS_CORETYPE`` if set.

    E.g. ``"Haswell (OPENBLAS_CORETYPE=Haswell)"``, ``"SkylakeX"`` (unset: OpenBLAS chose
    by the CPU), ``"SkylakeX (OPENBLAS_CORETYPE=Haswell not applied: NumPy loaded its
    kernels before hmpc set it)"``, or ``""`` where NumPy's BLAS does not say (not
    OpenBLAS, or no /proc). OpenBLAS names some kernel sets after others (``Zen`` runs
    ``Haswell``'s).
    """
    import numpy  # noqa: F401  (loads its BLAS)

    names = _core_names()
    if not names:
        return ""
    name, wanted = names[0], os.environ.get(VARIABLE, "")
    if not wanted:
        return name
    if _late and _late[-1]:
        return (f"{name} ({VARIABLE}={wanted} not applied: NumPy loaded its kernels before "
                "hmpc set it)")
    return f"{name} ({VARIABLE}={wanted})"
