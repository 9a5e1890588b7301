"""Step 14, "nothing hangs, nothing lies": stop signals, sizes that hang, inputs that lie.

Table-driven: each table row is one fault with the exit code, the message and the files
it must (not) leave. No wall-clock asserts: subprocess timeouts only guard against hangs.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import (
    BALL, bad_input, cli_env, forbid_prepare, hmpc_command, signal_handlers_installed,
    stop_process)
from hmpc_cli.core import cbuild, signals
from hmpc_cli.run.scenario import ScenarioError, load_scenario

CODES = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGHUP: 129}
#: a CEM plan of ~100 s that passes the work limit (250 x 20001 x 180 = 9e8 steps)
HUGE_PLAN = ["--set", "planner.samples=20000", "--set", "planner.iterations=250"]


@pytest.fixture
def work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A scratch current directory with ball.toml; building a loop fails the test."""
    shutil.copy(BALL, tmp_path / "ball.toml")
    monkeypatch.chdir(tmp_path)
    forbid_prepare(monkeypatch)
    return tmp_path


def _bad(work: Path, args: list[str]) -> list[str]:
    return bad_input(work, args)


# ------------------------------------------------------------------ 2. sizes that hang
def _deep_file(work: Path) -> list[str]:
    (work / "deep.toml").write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    return ["run", "deep.toml"]


def _deep_ok_syntax(work: Path) -> list[str]:
    (work / "deep.toml").write_text("a = " + "[" * 100 + "]" * 100 + "\n")
    return ["run", "deep.toml"]


def _sweep(work: Path, grid: str) -> list[str]:
    (work / "x.toml").write_text(f'name = "x"\nscenario = "ball.toml"\n[grid]\n{grid}\n')
    return ["sweep", "x.toml", "--dry-run"]


SIZES = [
    # (id, args or a function of the work directory, the line's start, text in the line)
    ("iterations", ["run", "ball.toml", "--set", "planner.iterations=100000000"],
     "error: --set planner.iterations=100000000: planner.iterations x planner.samples: "
     "100000000 iterations x (50 + 1) samples = 5.1e+09 rollouts of 180 steps",
     "limit 1e+09 (about 1.27 days per planner call"),
    ("samples", ["run", "ball.toml", "--set", "planner.samples=20000000"],
     "error: --set planner.samples=20000000: planner.iterations x planner.samples: 15 "
     "iterations x (20000000 + 1) samples", "rollout steps per planner call, limit 1e+09"),
    ("rollout rate", ["run", "ball.toml", "--set", "planner.rollout_rate_hz=100000000"],
     "error: --set planner.rollout_rate_hz=100000000: planner.iterations x planner.samples:",
     "(planner.horizon x planner.rollout_rate_hz)"),
    ("planner horizon", ["run", "ball.toml", "--set", "planner.horizon=0.001"],
     "error: --set planner.horizon=0.001: planner.horizon: 0.001 s x 60 Hz "
     "(planner.rollout_rate_hz) = 0.06 rollout steps: a rollout needs at least one",
     "lengthen planner.horizon to 0.0166667 s or more"),
    ("switches", ["run", "ball.toml", "--set", "mpc.max_switches=20000"],
     "error: --set mpc.max_switches=20000: mpc.max_switches: 180 nodes (mpc.horizon x "
     "mpc.nodes_per_second) + 20000 switches = 2.02e+04 links of the switching NLP exceeds "
     "the limit 20000", "min to build, at 0.3 MiB and 10 ms per switch"),
    ("switches 1e8", ["run", "ball.toml", "--set", "mpc.max_switches=100000000"],
     "error: --set mpc.max_switches=100000000: mpc.max_switches:", "h to build"),
    ("sweep dry-run", lambda w: _sweep(w, '"mpc.max_switches" = [10, 20000]'),
     "error: x.toml: grid.mpc.max_switches[1]: mpc.max_switches: 180 nodes", "per switch"),
    ("tube samples", ["tube", "ball.toml", "--samples", "1000000000"],
     "error: --samples: 1e+09 samples per constant exceeds the limit 1e+07", "of memory"),
    ("deep TOML", _deep_file,
     "error: deep.toml: tables or arrays nested too deeply (more than 32 levels)", ""),
    ("deep TOML parsed", _deep_ok_syntax,
     "error: deep.toml: tables or arrays nested too deeply (more than 32 levels)", ""),
    ("deep --set", ["run", "ball.toml", "--set", "a=" + "[" * 5000 + "]" * 5000],
     "error: --set 'a=[[[[", "...: the value is nested too deeply (more than 32 levels)"),
]


@pytest.mark.parametrize("args,start,within", [row[1:] for row in SIZES],
                         ids=[row[0] for row in SIZES])
def test_sizes_are_refused_before_anything_is_built(work: Path, args, start: str, within: str):
    args = args(work) if callable(args) else args
    lines = _bad(work, args)
    hit = [line for line in lines if line.startswith(start)]
    assert hit and within in hit[0], lines
    assert all(len(line) < 500 for line in lines), "a message is one readable line"


def test_a_plan_within_the_limits_is_accepted(work: Path):
    sc, _ = load_scenario("ball.toml", ["planner.samples=20000", "planner.iterations=250",
                                        "mpc.max_switches=19000"])
    assert (sc.planner.samples, sc.planner.iterations, sc.mpc.max_switches) == (20000, 250,
                                                                                  19000)


# ----------------------------------------------------------- 3. counts/inputs that lie
def _directory(work: Path, mp: pytest.MonkeyPatch) -> list[str]:
    (work / "adir.toml").mkdir()
    return ["run", "adir.toml"]


def _unreadable(work: Path, mp: pytest.MonkeyPatch) -> list[str]:
    shutil.copy(BALL, work / "locked.toml")
    if os.geteuid() != 0:
        (work / "locked.toml").chmod(0)
        return ["run", "locked.toml"]
    real = Path.read_text  # root reads anything: make reading fail as it would

    def read_text(self, *args, **kwargs):
        if self.name == "locked.toml":
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    mp.setattr(Path, "read_text", read_text)
    return ["run", "locked.toml"]


BLAME = [
    # (id, args, the expected lines (each a prefix))
    ("directory", _directory, ["error: adir.toml: is a directory, not a scenario file"]),
    ("unreadable", _unreadable, ["error: locked.toml: cannot read it: Permission denied"]),
    ("through a value", ["run", "ball.toml", "--set", "mpc.rate_hz.x=1"],
     ["error: --set 'mpc.rate_hz.x=1': mpc.rate_hz is a value (10), not a table, so "
      "mpc.rate_hz.x names no key: set mpc.rate_hz itself"]),
    ("a horizon shorter than the period", ["run", "ball.toml", "--set", "mpc.horizon=0.05",
                                           "--set", "mpc.rate_hz=5"],
     ["error: --set mpc.horizon=0.05: mpc.horizon: 0.05 s is shorter than the MPC period "
      "1 / mpc.rate_hz = 0.2 s: each plan would run out before the next one"]),
    ("an event tolerance of a step", ["run", "ball.toml", "--set", "sim.event_time_tol=1e9"],
     ["error: --set sim.event_time_tol=1e9: sim.event_time_tol: 1e+09 s brackets an event "
      "time to more than 1e-3 of a simulator step (1/sim.rate_hz = 0.001667 s): events would "
      "be placed anywhere in the step; use at most 1.67e-06 s (default 1e-10)"]),
    ("a system that is not a table", ["run", "ball.toml", "--set", "system=ball"],
     ["error: --set system=ball: system: Input should be a valid dictionary"]),  # only
    ("no =", ["run", "ball.toml", "--set", "nokey"],
     ["error: --set 'nokey': expected key.path=value"]),
    ("a rate named in the reason", ["run", "ball.toml", "--set", "sim.rate_hz=7"],
     ["error: --set sim.rate_hz=7: mpc.rate_hz: 10 must divide sim.rate_hz = 7",
      "error: --set sim.rate_hz=7: sim.log_rate_hz: 100 must divide sim.rate_hz = 7"]),
    ("a union tag", ["run", "ball.toml", "--set", "planner.kind=xxx"],
     ["error: --set planner.kind=xxx: planner: unknown kind 'xxx'; choose from 'cem', "
      "'footholds', 'schedule'"]),
    ("a section check", ["run", "ball.toml", "--set", "mpc.solver=fatrop"],
     ['error: --set mpc.solver=fatrop: mpc: solver "fatrop" needs stage-wise dynamics']),
    ("a margins file", ["run", "ball.toml", "--set", "mpc.margins=nope.toml"],
     ["error: --set mpc.margins=nope.toml: mpc.margins: file not found:"]),
    ("a merged table", ["run", "ball.toml", "--set", "mpc={rate_hz=7}"],
     ["error: --set mpc={rate_hz=7}: mpc.rate_hz: 7 must divide mpc.nodes_per_second = 60"]),
    ("tube, a merged table", ["tube", "ball.toml", "--set", "mpc={rate_hz=7}"],
     ["error: --set mpc={rate_hz=7}: mpc.rate_hz: 7 must divide mpc.nodes_per_second = 60"]),
]


@pytest.mark.parametrize("args,expected", [row[1:] for row in BLAME],
                         ids=[row[0] for row in BLAME])
def test_errors_blame_what_is_at_fault(work: Path, args, expected: list[str]):
    with pytest.MonkeyPatch.context() as mp:
        lines = _bad(work, args(work, mp) if callable(args) else args)
    assert len(lines) == len(expected), lines
    for line, start in zip(lines, expected, strict=True):
        assert line.startswith(start), lines


MERGES = [
    # (id, --set items, expected values of [mpc] (the file's kept where not set))
    ("a table keeps the other keys", ["mpc={rate_hz=20}"],
     {"rate_hz": 20, "nodes_per_second": 60, "horizon": 3.0, "tube_margin": 0.025}),
    ("a key, then a table", ["mpc.horizon=2.0", "mpc={rate_hz=20}"],
     {"rate_hz": 20, "horizon": 2.0, "tube_margin": 0.025}),
    ("nested tables merge", ["mpc.solver_options={ipopt={tol=1e-6}}",
                             "mpc={solver_options={ipopt={max_cpu_time=5.0}}}"],
     {"solver_options": {"ipopt": {"tol": 1e-6, "max_cpu_time": 5.0}}, "rate_hz": 10}),
    ("a scalar replaces", ["mpc.solver_options={ipopt={tol=1e-6}}", "mpc.rate_hz=20"],
     {"solver_options": {"ipopt": {"tol": 1e-6}}, "rate_hz": 20}),
]


@pytest.mark.parametrize("sets,expected", [row[1:] for row in MERGES],
                         ids=[row[0] for row in MERGES])
def test_set_tables_are_merged(sets: list[str], expected: dict):
    sc, text = load_scenario(BALL, sets)
    mpc = sc.mpc.model_dump()
    assert {k: mpc[k] for k in expected} == expected


def test_set_does_not_change_the_file_data_of_other_sections():
    with pytest.raises(ScenarioError) as exc:
        load_scenario(BALL, ["sim={rate_hz=7}"])
    assert all(line.startswith("--set sim={rate_hz=7}: ") for line in exc.value.lines)
    sc, _ = load_scenario(BALL, ["sim={duration=1.0}"])
    assert (sc.sim.duration, sc.sim.rate_hz) == (1.0, 600)  # rate_hz from the file


# ------------------------------------------------------ CC that cannot be parsed
CC_VALUES = [
    # (CC, parsed command or None, the problem's text)
    ("gcc '", None, "CC=\"gcc '\" cannot be parsed (No closing quotation)"),
    ('cc "-O2', None, "cannot be parsed (No closing quotation)"),
    ("   ", None, "names no command"),
    ("cc -O2", ["cc", "-O2"], ""),
]


@pytest.mark.parametrize("cc,command,problem", CC_VALUES)
def test_an_unparsable_cc_means_no_compiler_with_one_warning(monkeypatch, cc, command,
                                                             problem):
    monkeypatch.setenv("CC", cc)
    monkeypatch.setattr(cbuild, "_CC_WARNED", set())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert cbuild.compiler() == command
        assert cbuild.compiler() == command  # warned once, not twice
    assert problem in cbuild.compiler_problem()
    assert len(caught) == (1 if command is None else 0), [str(w.message) for w in caught]
    if command is None:
        assert "no C compiler is used" in str(caught[0].message)


def test_a_run_with_an_unparsable_cc_runs(tmp_path: Path):
    env = {**cli_env(), "CC": "gcc '", "HMPC_BUILD_CACHE": "background"}
    proc = subprocess.run([*hmpc_command(), "run", str(BALL), "--set", "sim.duration=0.1",
                           "--out", str(tmp_path / "r"), "-q"], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.splitlines()
    assert lines == [lines[0]] and lines[0].startswith("warning: CC=\"gcc '\" cannot be "
                                                       "parsed"), lines
    info = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert info["solves"] > 0


# ---------------------------------------------------------------- stale compile locks
def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


LOCKS = [
    # (id, lock content (a function of nothing), its age [s], taken over)
    ("dead owner", lambda: f"{_dead_pid()}", 1.0, True),
    ("dead owner, fresh", lambda: f"{_dead_pid()} 12345", 0.0, True),
    ("pid reused", lambda: f"{os.getpid()} 1", 1.0, True),
    ("empty, old", lambda: "", 60.0, True),
    ("garbage, old", lambda: "not a pid", 60.0, True),
    ("empty, being written", lambda: "", 0.0, False),
    ("live owner", lambda: None, 1.0, False),
    ("live owner, older than an hour", lambda: None, 7200.0, True),
]


@pytest.mark.parametrize("content,age,taken", [row[1:] for row in LOCKS],
                         ids=[row[0] for row in LOCKS])
def test_a_lock_whose_owner_is_dead_is_taken_over(tmp_path: Path, content, age: float,
                                                  taken: bool):
    from hmpc_cli.mpc import cache

    entry = cache.Entry(tmp_path, "k" * 64, "identity")
    text = content()
    entry.lock.write_text(cache.lock_owner() if text is None else text)
    then = time.time() - age
    os.utime(entry.lock, (then, then))
    before = entry.lock.read_text()
    assert cache._take_lock(entry) is taken
    if taken:
        assert entry.lock.read_text() == cache.lock_owner()
    else:
        assert entry.lock.read_text() == before


def test_the_background_compile_owns_its_locks(tmp_path: Path, monkeypatch):
    from hmpc_cli.mpc import cache

    entry = cache.Entry(tmp_path, "k" * 64, "identity")
    assert cache._take_lock(entry)
    started = []

    class Proc:
        pid = _dead_pid()

    def popen(*args, **kwargs):
        started.append(args)
        return Proc()

    monkeypatch.setattr(cache.subprocess, "Popen", popen)
    monkeypatch.setattr(cache, "_QUEUE", [entry])
    cache._start_queue()
    assert started and entry.lock.read_text().split()[0] == str(Proc.pid)
    assert cache._take_lock(entry), "its process is gone: taken over at once"


# --------------------------------------------------------- 1. stop signals, in-process
@pytest.fixture
def planner():
    from hmpc_cli.planner.cem import CEMSettings, CrossEntropyPlanner
    from hmpc_cli.systems.ball import BallParams, build_ball

    system = build_ball(BallParams())
    settings = CEMSettings(samples=10, iterations=3, rollout_backend="numpy")
    yield CrossEntropyPlanner(system, settings), system
    signals.reset()


def test_a_pending_signal_stops_the_planner(planner):
    cem, system = planner
    signals._STATE.signum = int(signal.SIGTERM)  # as the handler records it
    with pytest.raises(signals.Interrupted) as exc:
        cem.plan(0.0, np.array(system.x0, dtype=float), 0)
    assert exc.value.exit_code == 143


def test_rollouts_stop_between_batches(planner, monkeypatch):
    from hmpc_cli.planner import cem as cem_module

    cem, system = planner
    monkeypatch.setattr(cem_module, "ROLLOUT_BATCH", 4)
    done = []

    def batch(x0, mode0, knots, bound):
        done.append(len(knots))
        signals._STATE.signum = int(signal.SIGINT)  # arrives during the first batch
        return np.zeros(len(knots)), np.zeros(len(knots), dtype=bool)

    monkeypatch.setattr(cem, "_batch_cost", batch)
    knots = np.zeros((10, cem.s.knots, system.n_u))
    with pytest.raises(signals.Interrupted):
        cem.rollout_cost(np.array(system.x0, dtype=float), 0, knots)
    assert done == [4]


def test_batched_rollouts_are_the_whole_batch_cut_in_pieces(planner, monkeypatch):
    from hmpc_cli.planner import cem as cem_module

    cem, system = planner
    rng = np.random.default_rng(3)
    knots = -20.0 + 15.0 * rng.standard_normal((9, cem.s.knots, system.n_u))
    x0 = np.array(system.x0, dtype=float)
    parts = [cem.rollout_cost(x0, 0, knots[i:i + 4]) for i in range(0, 9, 4)]
    monkeypatch.setattr(cem_module, "ROLLOUT_BATCH", 4)
    cost, reached = cem.rollout_cost(x0, 0, knots)
    assert np.array_equal(cost, np.concatenate([p[0] for p in parts]))
    assert np.array_equal(reached, np.concatenate([p[1] for p in parts]))


# ------------------------------------------------------- 1. stop signals, subprocesses
def _start(args: list[str], cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([*hmpc_command(), *args], cwd=cwd, env=cli_env(), text=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _wait(proc: subprocess.Popen, ready, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if ready():
            return
        time.sleep(0.02)
    proc.kill()
    raise AssertionError(f"never ready (exit {proc.wait()}): {proc.stderr.read()}")


def _stop(proc: subprocess.Popen, sig: int) -> str:
    """Sends ``sig``; returns stderr (hang guard: the process must end within 60 s)."""
    return stop_process(proc, sig, 60)[1]


def test_sigterm_while_the_cem_plans_a_huge_plan(tmp_path: Path):
    out = tmp_path / "run"
    proc = _start(["run", str(BALL), "--out", str(out), "-q", *HUGE_PLAN], tmp_path)
    mcap = out / "run.mcap"
    _wait(proc, lambda: mcap.exists() and mcap.stat().st_size > 0)
    time.sleep(0.5)  # in the initial plan (~100 s of rollouts)
    err = _stop(proc, signal.SIGTERM)
    assert proc.returncode == 143, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("interrupted (SIGTERM)"), err
    assert str(mcap) in lines[0]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reason"] == "interrupted (SIGTERM)" and summary["success"] is False
    assert summary["t_end"] == 0.0 and summary["solves"] == 0


def _ball_run(tmp_path: Path) -> Path:
    run = tmp_path / "r"
    proc = subprocess.run([*hmpc_command(), "run", str(BALL), "--set", "sim.duration=0.5",
                           "--out", str(run), "-q"], cwd=tmp_path, env=cli_env(),
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return run


COMMANDS = [
    # (id, arguments (a function of a ball run's directory), signal, needs a run (slow))
    ("tube SIGTERM", lambda run: ["tube", str(BALL), "--samples", "2000000", "-q"],
     signal.SIGTERM, False),
    ("tube SIGHUP", lambda run: ["tube", str(BALL), "--samples", "2000000", "-q"],
     signal.SIGHUP, False),
    ("plot SIGTERM", lambda run: ["plot", "fig2", str(run), "--out", "figs"],
     signal.SIGTERM, True),
    ("replay SIGTERM", lambda run: ["replay", str(run), "--figures", "figs"],
     signal.SIGTERM, True),
    ("replay SIGINT", lambda run: ["replay", str(run), "--figures", "figs"],
     signal.SIGINT, True),
]


@pytest.mark.parametrize("args,sig,needs_run", [
    pytest.param(*row[1:], id=row[0], marks=[pytest.mark.slow] if row[3] else [])
    for row in COMMANDS])
def test_other_commands_keep_the_exit_contract(tmp_path: Path, args, sig: int,
                                               needs_run: bool):
    proc = _start(args(_ball_run(tmp_path) if needs_run else None), tmp_path)
    _wait(proc, lambda: signal_handlers_installed(proc.pid))
    err = _stop(proc, sig)
    name = signal.Signals(sig).name
    assert proc.returncode == CODES[sig], err
    assert err.splitlines() == [f"interrupted ({name})"], err
    assert not list(tmp_path.rglob("*.tmp*")), "no temporary left behind"


def test_a_run_started_without_a_stdout_runs_and_exits_0(tmp_path):
    """``hmpc run ... >&-`` (no file descriptor 1, as under some schedulers): the option
    probe's silencer and the exit's flush do without it; the run ends with status 0,
    nothing on stderr, and its log whole."""
    import json

    out = tmp_path / "run"
    proc = subprocess.run([*hmpc_command(), "run", str(BALL), "--set", "sim.duration=0.2",
                           "--out", str(out), "-q"], env=cli_env(), cwd=tmp_path,
                          stderr=subprocess.PIPE, text=True, preexec_fn=lambda: os.close(1),
                          timeout=120)
    assert (proc.returncode, proc.stderr) == (0, "")
    assert json.loads((out / "summary.json").read_text())["t_end"] == 0.2
