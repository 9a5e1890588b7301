"""``hmpc report`` under faults: stop signals, a section that fails, inputs that are not sweeps."""

from __future__ import annotations

import signal
import time

import pytest

from conftest import BALL, signal_handlers_installed, stop_process

#: every section left out (a test gives back the one it needs)
NONE = {"--fig3": "", "--fig3-extra": "", "--fig3-reference": "", "--fig3-reference-extra": "",
        "--fig3-schedule": "", "--biped": "", "--biped-push": "", "--fig3-trials": "",
        "--realtime": "", "--robustness": ""}


def _args(**given: str) -> list[str]:
    """``report`` with every section left out but ``given`` (``fig3_extra=`` for --fig3-extra)."""
    options = NONE | {"--" + k.replace("_", "-"): v for k, v in given.items()}
    return ["report", *(x for kv in options.items() for x in kv)]


def _wait_for(cond, what: str, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_stopped_report_run_exits_128_plus_the_signal_and_says_what_finished(
        tmp_path, start_hmpc, sig):
    """A stop signal to ``hmpc report --run`` in its first run: exit 128 + the signal, one
    line saying how many of the missing runs finished (none), no page, no figures."""
    sweep = tmp_path / "slow_study.toml"
    sweep.write_text(f'name = "slow_study"\nscenario = "{BALL.as_posix()}"\nseeds = 2\n'
                     '[set]\n"sim.duration" = 30.0\n"mpc.horizon" = 1.0\n')
    res = tmp_path / "results"
    proc = start_hmpc([*_args(robustness=str(sweep)), "--run", "--results", str(res),
                       "--workers", "1"], tmp_path)
    runs = res / "sweeps" / "slow_study" / "runs"
    _wait_for(lambda: proc.poll() is not None or (
        signal_handlers_installed(proc.pid) and any(runs.glob("*/run.mcap"))), "a run")
    assert proc.poll() is None, proc.communicate()
    _, err = stop_process(proc, sig, timeout=120)
    assert proc.returncode == 128 + sig, err
    assert err.splitlines()[-1] == ("interrupted: 0 of 2 missing runs done; run the same "
                                    "command again to resume"), err
    assert "Traceback" not in err
    assert not (res / "README.md").exists() and not (res / "report").exists()
