"""NumPy's BLAS kernels pinned (hmpc_cli.core.blas): the same bits on x86-64 machines.

An AVX-512 machine's OpenBLAS kernels and an AVX2 one's differ in the last bits, and the
biped's closed loops near a failure then go another way: ``realtime_biped_rti``'s seed-13
``model`` run of "hold, first plan charged" climbs with the Haswell kernels and trips at
the second stair's riser with the Sandybridge ones.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hmpc_cli.core import blas

REPO = Path(__file__).resolve().parents[1]
PINNABLE = blas._cpu_flags() >= blas.NEEDS and os.uname().machine == "x86_64"


def _python(code: str, **env: str) -> str:
    """``code``'s stdout in a fresh interpreter, OPENBLAS_CORETYPE unset unless given."""
    environ = {k: v for k, v in os.environ.items() if k != blas.VARIABLE}
    out = subprocess.run([sys.executable, "-c", code], env={**environ, **env}, cwd=REPO,
                         capture_output=True, text=True, check=True)
    return out.stdout.strip()


@pytest.mark.skipif(not PINNABLE, reason="an x86-64 Linux CPU with AVX2 and FMA")
def test_importing_hmpc_pins_numpys_kernels_for_the_process_and_its_children():
    assert _python("import hmpc_cli, numpy, os\n"
                   "from hmpc_cli.core.blas import kernels\n"
                   "print(os.environ['OPENBLAS_CORETYPE'], '|', kernels())") == \
        "Haswell | Haswell (OPENBLAS_CORETYPE=Haswell)"
    # this test process too: conftest imports hmpc_cli before any test module's NumPy
    assert blas.kernels() == "Haswell (OPENBLAS_CORETYPE=Haswell)"


@pytest.mark.skipif(not PINNABLE, reason="an x86-64 Linux CPU with AVX2 and FMA")
def test_a_users_own_kernel_choice_stands():
    assert _python("import hmpc_cli, numpy\nfrom hmpc_cli.core.blas import kernels\n"
                   "print(kernels())", OPENBLAS_CORETYPE="Sandybridge") == \
        "Sandybridge (OPENBLAS_CORETYPE=Sandybridge)"


@pytest.mark.skipif(not PINNABLE, reason="an x86-64 Linux CPU with AVX2 and FMA")
def test_kernels_say_when_numpy_loaded_them_before_the_pin():
    """NumPy imported first (a script's own import order) keeps the kernels it loaded:
    OpenBLAS's own choice for the CPU; the children the script starts get the pin."""
    own = _python("import numpy\nfrom hmpc_cli.core import blas\n"
                  "print(blas._core_names()[0])")
    late = _python("import numpy, hmpc_cli, os, subprocess, sys\n"
                   "from hmpc_cli.core.blas import kernels\nprint(kernels())\n"
                   "sys.stdout.flush()\n"
                   "subprocess.run([sys.executable, '-c', 'import hmpc_cli\\n"
                   "from hmpc_cli.core.blas import kernels\\nprint(kernels())'])")
    assert late.splitlines() == [
        f"{own} (OPENBLAS_CORETYPE=Haswell not applied: NumPy loaded its kernels before "
        "hmpc set it)", "Haswell (OPENBLAS_CORETYPE=Haswell)"]


def test_the_run_log_records_the_kernels(tmp_path, run_hmpc):
    out = tmp_path / "run"
    proc = run_hmpc(["run", "scenarios/ball.toml", "--set", "sim.duration=0.05", "--out",
                     str(out), "-q"], REPO)
    assert proc.returncode == 0, proc.stderr
    from hmpc_cli.log.reader import read_log

    versions = read_log(out / "run.mcap").topic("/run/info")[0].data["versions"]
    expected = "Haswell (OPENBLAS_CORETYPE=Haswell)" if PINNABLE else blas.kernels()
    assert versions["blas"] == expected
    assert json.loads((out / "summary.json").read_text())["cpu"] == versions["cpu"]
