"""The run log's held messages: written later, but in order and as they were logged."""

from __future__ import annotations

import dataclasses
import subprocess

import numpy as np
import pytest

from conftest import SCENARIOS
from hmpc_cli.log import runlog
from hmpc_cli.mpc.chain.kind import ChainDetail
from hmpc_cli.core.messages import ModeSchedule, Plan, SolveStats, Trajectory
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.reader import read_log
from hmpc_cli.core.registry import build_system
from hmpc_cli.analysis.replay import _ignored
from hmpc_cli.log.runlog import RunIdentity, TopicWriter
from hmpc_cli.run.runner import execute_run, prepare
from hmpc_cli.run.scenario import load_scenario
from hmpc_cli.systems.ball import BallParams


def _untimed(value):
    """A JSON value without its measured times and command line (what verify skips)."""
    if isinstance(value, dict):
        return {k: _untimed(v) for k, v in value.items() if not _ignored(k)}
    return [_untimed(v) for v in value] if isinstance(value, list) else value


def _messages(path):
    """Every message of a log, JSON (untimed) and protobuf: (topic, log time [ns], data)."""
    log = read_log(path)
    return ([(m.topic, m.log_time_ns, _untimed(m.data)) for m in log.messages],
            [(m.topic, m.log_time_ns, m.data) for m in log.raw])


def test_held_messages_are_the_messages_written_at_once(tmp_path, monkeypatch):
    """A disturbed ball run (states, disturbances, solves, contacts, the scene) logs the
    same messages in the same order whether each is written at once or held."""
    sc, text = load_scenario(SCENARIOS / "ball_disturbed.toml", ["sim.duration=0.8"])
    logs = {}
    for held in (1, runlog.HELD):
        monkeypatch.setattr(runlog, "HELD", held)
        execute_run(prepare(sc), text, tmp_path / str(held))
        logs[held] = _messages(tmp_path / str(held) / "run.mcap")
    at_once, held = logs[1], logs[runlog.HELD]
    topics = {m[0] for m in at_once[0]}
    assert {"/sim/state", "/disturbance", "/mpc/solve", "/sim/event"} <= topics
    assert len(at_once[0]) > runlog.HELD
    assert held == at_once


def _plan(model) -> Plan:
    n = 5
    traj = Trajectory(t=np.linspace(0.0, 0.4, n), x=np.ones((n, 4)), u=np.zeros((n, 2)),
                      mode=np.zeros(n, dtype=int), seg=np.zeros(n, dtype=int))
    return Plan(0.3, traj, SolveStats("Solve_Succeeded", True, 2, 0.01, 1.5, 0.0),
                ModeSchedule((0,), (), (), 0.0), ChainDetail(1, (5,)))


def test_a_held_solve_is_logged_as_it_was_when_solved(tmp_path):
    """The plan's arrays may change after solve(): the log keeps the solve (its detail is
    a frozen record)."""
    model = build_system(BallParams())
    rec = Recorder(tmp_path / "run.mcap")
    log = TopicWriter(rec, RunIdentity("ball", 0, kinds=("none", "fixed_mode"),
                                       details={"mpc": ChainDetail}))
    log.open(model)
    plan = _plan(model)
    log.mpc_solve(0.3, plan, "test", model)
    assert log._held  # not written yet
    plan.traj.x[:] = -7.0
    plan.traj.t[:] = 9.0
    log.flush_held()
    rec.close()
    solve = read_log(tmp_path / "run.mcap").topic("/mpc/solve")[0].data
    assert [node["px"] for node in solve["plan"]] == [1.0] * 5
    assert solve["plan"][-1]["t"] == 0.3 + 0.4
    assert solve["detail"] == {"shifted": 1, "counts": [5]}
    assert dataclasses.asdict(_plan(model).stats)["iterations"] == solve["iterations"]


def test_the_null_writer_answers_every_call_of_the_topic_writer():
    """A run without a log (benchmarks) calls the same methods: none may be missing."""
    from hmpc_cli.log.runlog import NullWriter, TopicWriter

    def public(cls):
        return {n for n in dir(cls) if not n.startswith("_") and callable(getattr(cls, n))}

    assert public(TopicWriter) == public(NullWriter)


def _no_git_env() -> dict[str, str]:
    """This environment without GIT_* (a git hook's would point git at another repo)."""
    import os

    return {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}


def test_a_run_records_the_git_commit_it_ran_from(tmp_path):
    """/run/info's versions and the metadata record name the checkout's commit, as git
    gives it (this test runs from a checkout: CI's fresh clone); replay --verify skips
    it (another commit is no divergence)."""
    import shutil

    from hmpc_cli.core.source import ROOT, source_commit

    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not run from a git checkout")
    sc, text = load_scenario(SCENARIOS / "ball.toml", ["sim.duration=0.05"])
    execute_run(prepare(sc), text, tmp_path / "run")
    log = read_log(tmp_path / "run" / "run.mcap")
    head = subprocess.run(["git", f"--git-dir={ROOT / '.git'}", "rev-parse", "HEAD"],
                          capture_output=True, text=True, check=True, env=_no_git_env()
                          ).stdout.strip()
    source = log.topic("/run/info")[0].data["versions"]["source"]
    assert source in (head, f"{head} (modified)") and source == source_commit()
    assert log.metadata["run"]["version.source"] == source
    assert _ignored("versions")


def test_the_source_commit_and_whether_tracked_files_differ(tmp_path, monkeypatch):
    """A clean checkout gives its commit; an untracked file changes nothing; a tracked
    file changed appends " (modified)"; a folder without .git gives "" even inside a
    repository (only the folder hmpc runs from counts); so does a repository without a
    commit."""
    import shutil

    from hmpc_cli.core.source import source_commit

    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    repo = tmp_path / "repo"
    (repo / "inner").mkdir(parents=True)

    def git(*args):
        return subprocess.run(["git", "-C", str(repo), "-c", "user.name=t",
                               "-c", "user.email=t@t", *args], env=_no_git_env(),
                              capture_output=True, text=True, check=True).stdout.strip()

    git("init", "-q")
    assert source_commit.__wrapped__(repo) == ""  # no commit yet
    (repo / "a.txt").write_text("a\n")
    git("add", "a.txt")
    git("commit", "-q", "-m", "a")
    head = git("rev-parse", "HEAD")
    assert len(head) == 40
    (repo / "untracked.txt").write_text("u\n")
    assert source_commit.__wrapped__(repo) == head
    monkeypatch.setenv("GIT_DIR", str(tmp_path / "elsewhere"))  # a git hook's environment
    assert source_commit.__wrapped__(repo) == head
    monkeypatch.delenv("GIT_DIR")
    (repo / "a.txt").write_text("b\n")
    assert source_commit.__wrapped__(repo) == f"{head} (modified)"
    assert source_commit.__wrapped__(repo / "inner") == ""
    assert source_commit.__wrapped__(tmp_path / "nowhere") == ""


def test_a_run_records_the_cpu_it_ran_on(tmp_path):
    """The CPU can move a run's last bits (docs/running.md): /run/info's versions, the
    summary and summary.json name it; replay --verify skips it (another machine is no
    divergence)."""
    import json

    from hmpc_cli.core.machine import cpu_model

    sc, text = load_scenario(SCENARIOS / "ball.toml", ["sim.duration=0.05"])
    execute_run(prepare(sc), text, tmp_path / "run")
    log = read_log(tmp_path / "run" / "run.mcap")
    cpu = cpu_model()
    assert cpu and cpu != "unknown"
    assert log.topic("/run/info")[0].data["versions"]["cpu"] == cpu
    assert log.topic("/run/summary")[0].data["cpu"] == cpu
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["cpu"] == cpu
    assert _ignored("cpu")
