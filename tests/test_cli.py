"""``hmpc run`` end to end: run directory, MCAP log contents, reproducibility, help."""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
from pathlib import Path

import casadi
import numpy as np
import pytest
from typer.testing import CliRunner

import hmpc_cli
from hmpc_cli.cli.app import app
from hmpc_cli.log.reader import Log, read_log
from hmpc_cli.run.scenario import Scenario, load_scenario

REPO = Path(__file__).resolve().parents[1]
BALL = REPO / "scenarios" / "ball.toml"
GOAL = (3.0, 3.0)


# ------------------------------------------------------------------- the full default run
@pytest.fixture(scope="module")
def full(full_run):
    assert full_run.proc.returncode == 0, full_run.proc.stderr
    return full_run


@pytest.fixture(scope="module")
def summary(full) -> dict:
    return json.loads((full.out / "summary.json").read_text())


@pytest.fixture(scope="module")
def log(full) -> Log:
    return read_log(full.out / "run.mcap")


@pytest.mark.slow
def test_run_writes_the_run_directory(full) -> None:
    assert sorted(p.name for p in full.out.iterdir()) == ["run.mcap", "scenario.toml",
                                                          "summary.json"]
    assert "Traceback" not in full.proc.stderr
    assert full.proc.stdout == f"{full.out / 'run.mcap'}\n"  # --quiet: the log's path only


def test_summary_reports_success_at_the_goal(summary) -> None:
    assert summary["success"] is True
    assert summary["diverged"] is False and summary["reason"] == "success"
    assert summary["scenario"] == "ball" and summary["seed"] == 0
    # the run is deterministic: 2.4e-11 m (its last digits may differ across CPUs)
    assert summary["final_error"] < 1e-9
    assert summary["t_end"] == pytest.approx(3.0)
    x_end = summary["x_end"]
    assert math.hypot(x_end[0] - GOAL[0], x_end[1] - GOAL[1]) == pytest.approx(
        summary["final_error"], abs=1e-9)
    assert summary["solves"] == 32 and summary["planner_calls"] == 1
    assert summary["contacts"] == 3
    assert summary["contacts_by_guard"] == {"floor": 1, "wall": 1, "circle_in": 1,
                                            "circle_out": 0}


def test_written_scenario_reloads_equal(full) -> None:
    written, _ = load_scenario(full.out / "scenario.toml")
    original, text = load_scenario(BALL)
    assert written == original
    assert (full.out / "scenario.toml").read_text(encoding="utf-8") == text


def test_log_is_complete(log) -> None:
    assert log.complete
    assert {m.topic for m in log.messages} >= {
        "/run/info", "/sim/state", "/sim/event", "/mpc/solve", "/planner/plan", "/run/summary"}


def test_run_info(log, full) -> None:
    (info,) = log.topic("/run/info")
    assert info.t == 0.0
    d = info.data
    assert d["seed"] == 0 and d["scenario_name"] == "ball"
    v = d["versions"]
    assert v["casadi"] == casadi.__version__
    assert v["numpy"] == np.__version__
    assert v["python"] == platform.python_version()
    assert v["hmpc"] == hmpc_cli.__version__
    written, _ = load_scenario(full.out / "scenario.toml")
    assert Scenario.model_validate(json.loads(d["scenario_json"])) == written
    assert log.metadata["run"]["seed"] == "0"
    m = d["margins"]  # hand-set: tube_margin = 0.025 of the scenario
    assert m["source"] == "hand" and m["radius"] == 0.025
    assert [g["guard"] for g in m["guards"]] == d["guard_names"]


def test_solves_contacts_and_plans_match_summary(log, summary) -> None:
    assert len(log.topic("/mpc/solve")) == summary["solves"]
    assert len(log.topic("/planner/plan")) == summary["planner_calls"]
    events = log.topic("/sim/event")
    assert len(events) == summary["contacts"]
    # the wall at 0.15 s, the floor at 0.2017 s, into the circle at 0.5517 s
    assert [ev.data["guard_name"] for ev in events] == ["wall", "floor", "circle_in"]
    by_guard: dict[str, int] = {}
    for ev in events:
        for key in ("x_before", "x_after"):
            x = list(ev.data[key].values())
            assert len(x) == 4 and all(isinstance(v, float) and math.isfinite(v) for v in x)
        xb, xa = list(ev.data["x_before"].values()), list(ev.data["x_after"].values())
        expected = {"floor": [xb[0], xb[1], xb[2], -xb[3]],  # the ball's reset maps
                    "wall": [xb[0], xb[1], -xb[2], xb[3]]}.get(ev.data["guard_name"], xb)
        assert xa == expected, ev.data
        assert ev.data["t"] == pytest.approx(ev.t, abs=1e-9)
        by_guard[ev.data["guard_name"]] = by_guard.get(ev.data["guard_name"], 0) + 1
    assert by_guard == {k: n for k, n in summary["contacts_by_guard"].items() if n}
    (last,) = log.topic("/run/summary")
    typed = ("x_end", "contacts_by_guard", "failure_statuses", "wall_time")
    assert {k: v for k, v in last.data.items() if k not in typed} == \
        {k: v for k, v in summary.items() if k not in typed}
    assert list(last.data["x_end"].values()) == summary["x_end"]
    # every guard in both, zeros included, in the model's order
    assert list(summary["contacts_by_guard"]) == ["floor", "wall", "circle_in", "circle_out"]
    assert last.data["contacts_by_guard"] == summary["contacts_by_guard"]


def test_state_at_the_log_rate(log) -> None:
    sc, _ = load_scenario(BALL)
    rate, n = sc.sim.log_rate_hz, round(sc.sim.duration * sc.sim.log_rate_hz)
    states = log.topic("/sim/state")
    assert len(states) == n + 1
    for k, m in enumerate(states):
        assert abs(m.log_time_ns - k * 1_000_000_000 // rate) <= 1, (k, m.log_time_ns)
        assert m.data["t"] == pytest.approx(k / rate, abs=1e-12)
        assert list(m.data["x"]) == ["px", "py", "vx", "vy"]
    assert list(states[0].data["x"].values()) == list(sc.system.x0)


def test_log_times_non_decreasing_per_topic(log) -> None:
    by_topic: dict[str, list[int]] = {}
    for m in log.messages:
        by_topic.setdefault(m.topic, []).append(m.log_time_ns)
    assert len(by_topic) >= 6
    for topic, times in by_topic.items():
        assert all(a <= b for a, b in zip(times, times[1:], strict=False)), topic


def test_scenario_attachment(log, full) -> None:
    assert log.attachments["scenario.toml"] == (full.out / "scenario.toml").read_bytes()


# ---------------------------------------------------------------------- reproducibility
SHORT = ["--set", "sim.duration=0.6", "-q"]


@pytest.fixture(scope="module")
def twin_logs(tmp_path_factory, start_hmpc) -> tuple[Log, Log]:
    """Two short runs of the same scenario and seed, in two processes at once."""
    base = tmp_path_factory.mktemp("twins")
    procs = [start_hmpc(["run", str(BALL), "--out", str(base / name), *SHORT], cwd=base)
             for name in ("a", "b")]
    for p in procs:
        _, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
    return read_log(base / "a" / "run.mcap"), read_log(base / "b" / "run.mcap")


def _data(log: Log, topic: str, key: str) -> list:
    return [m.data[key] for m in log.topic(topic)]


@pytest.mark.slow
def test_runs_are_bit_for_bit_reproducible(twin_logs) -> None:
    a, b = twin_logs
    xs = _data(a, "/sim/state", "x")
    assert len(xs) == 61
    assert xs == _data(b, "/sim/state", "x")
    ev_a = _data(a, "/sim/event", "t")
    assert len(ev_a) > 0, "the short run should already hit a guard"
    assert ev_a == _data(b, "/sim/event", "t")
    assert [m.log_time_ns for m in a.topic("/sim/event")] == \
        [m.log_time_ns for m in b.topic("/sim/event")]
    assert _data(a, "/sim/event", "x_after") == _data(b, "/sim/event", "x_after")
    plans = _data(a, "/mpc/solve", "plan")
    assert len(plans) > 1
    assert plans == _data(b, "/mpc/solve", "plan")
    assert _data(a, "/planner/plan", "rollout") == _data(b, "/planner/plan", "rollout")
    # ... while the wall clock differs: the comparison above is not of one file with itself
    assert _data(a, "/mpc/solve", "wall_time") != _data(b, "/mpc/solve", "wall_time")


def test_short_run_is_a_prefix_of_the_full_run(twin_logs, log) -> None:
    short, _ = twin_logs
    xs_short = _data(short, "/sim/state", "x")[:-1]  # the last one is the final state
    assert xs_short == _data(log, "/sim/state", "x")[:len(xs_short)]
    ev_short = _data(short, "/sim/event", "t")
    assert ev_short == _data(log, "/sim/event", "t")[:len(ev_short)]


# ------------------------------------------------------------------------ existing run
def test_refuses_a_directory_holding_a_run(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "old"
    out.mkdir()
    mcap = out / "run.mcap"
    mcap.write_bytes(b"precious earlier run")
    stat = mcap.stat()
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(out), "-q",
                                   "--set", "sim.duration=0.1"])
    assert res.exit_code == 2, res.output
    assert isinstance(res.exception, SystemExit)
    assert "Traceback" not in res.output
    assert res.stderr.splitlines() == [
        f"error: --out {out}: already holds a run (choose another --out)"]
    assert [p.name for p in out.iterdir()] == ["run.mcap"]
    assert mcap.read_bytes() == b"precious earlier run"
    assert mcap.stat().st_mtime_ns == stat.st_mtime_ns
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]


# -------------------------------------------------------------------------------- help
def test_help(run_hmpc, tmp_path: Path) -> None:
    top = run_hmpc(["--help"], cwd=tmp_path)
    assert top.returncode == 0, top.stderr
    for word in ("Usage", "run", "schema", "--help"):
        assert word in top.stdout, word
    sub = run_hmpc(["run", "--help"], cwd=tmp_path)
    assert sub.returncode == 0, sub.stderr
    for word in ("SCENARIO", "--out", "--set", "--seed", "--quiet", "-q"):
        assert word.lower() in sub.stdout.lower(), word
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("code, status, err", [("3", 3, ""), ("None", 0, ""),
                                               ("'stopped'", 1, "stopped\n")])
def test_the_process_ends_like_sys_exit_after_its_atexit_handlers(tmp_path, code, status,
                                                                   err) -> None:
    """``end_process`` (the console script's last step): the status, the atexit handlers
    and both streams' buffered text, as ``sys.exit`` would give them."""
    script = ("import atexit, sys\n"
              "from hmpc_cli.cli.app import end_process\n"
              "atexit.register(lambda: print('atexit ran'))\n"
              "sys.stdout.write('partial line')\n"
              f"end_process({code})\n"
              "print('never')\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert (proc.returncode, proc.stdout, proc.stderr) == (status, "partial lineatexit ran\n",
                                                           err)


def test_output_that_cannot_be_written_is_an_error_not_a_silent_success() -> None:
    """stdout on a full device: said on stderr, status 120 (as CPython's own exit)."""
    script = ("import sys\n"
              "from hmpc_cli.cli.app import end_process\n"
              "sys.stdout.write('result')\n"
              "end_process(0)\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    with open("/dev/full", "w") as full:
        proc = subprocess.run([sys.executable, "-c", script], stdout=full, env=env,
                              stderr=subprocess.PIPE, text=True, timeout=60)
    assert proc.returncode == 120
    assert "the output could not be written" in proc.stderr and "No space" in proc.stderr


def test_a_live_non_daemon_thread_is_waited_for(tmp_path) -> None:
    done = tmp_path / "done"
    script = ("import threading, time\n"
              "from hmpc_cli.cli.app import end_process\n"
              f"t = threading.Thread(target=lambda: (time.sleep(0.3), open({str(done)!r}, 'w')"
              ".write('x')))\n"
              "t.start()\n"
              "end_process(4)\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 4 and done.read_text() == "x", proc.stderr
