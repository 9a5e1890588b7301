"""A run killed mid-way leaves a log whose completed chunks read back."""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hmpc_cli.log.reader import read_log

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_sigkilled_run_leaves_a_readable_log(tmp_path):
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "hmpc_cli", "run", str(ROOT / "scenarios" / "ball.toml"),
           "--out", str(out), "-q", "--set", "sim.duration=30.0", "--set", "sim.log_rate_hz=600"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        mcap = out / "run.mcap"
        while time.time() < deadline:  # wait until a few flushes have reached the disk
            if mcap.exists() and mcap.stat().st_size > 60_000:
                break
            time.sleep(0.2)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    log = read_log(out / "run.mcap")
    assert not log.complete
    info = log.topic("/run/info")
    assert len(info) == 1 and info[0].data["seed"] == 0
    states = log.topic("/sim/state")
    assert len(states) > 100
    times = [m.t for m in states]
    assert times == sorted(times)
    assert log.topic("/mpc/solve"), "solves before the kill are in the log"
    # hmpc replay reads it up to its last completed chunk and says where it was cut
    rp = subprocess.run([sys.executable, "-m", "hmpc_cli", "replay", str(out), "--topic",
                         "summary"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert rp.returncode == 0, rp.stderr
    text = " ".join(rp.stdout.split())
    cut = re.search(r"cut short at t = ([0-9.]+) s", text)
    assert cut and float(cut.group(1)) >= round(times[-1], 3) - 1e-3
    assert "no summary (the run did not finish)" in text and "Traceback" not in rp.stderr
