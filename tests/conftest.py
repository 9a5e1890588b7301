"""Shared fixtures: paths, the ``hmpc`` command line, and one full default run per session."""

from __future__ import annotations

import atexit
import csv
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import pytest
import typer.testing

# first: NumPy's BLAS kernels pinned before a test module loads NumPy (hmpc_cli.core.blas)
import hmpc_cli  # noqa: F401

REPO = Path(__file__).resolve().parents[1]


def _private_dir(variable: str, prefix: str) -> None:
    """Sets ``$variable`` to a new directory of this test session, removed at exit."""
    os.environ[variable] = tempfile.mkdtemp(prefix=prefix)
    atexit.register(shutil.rmtree, os.environ[variable], ignore_errors=True)


# compiled rollout kernels of this test session go to a private cache (inherited by the
# ``hmpc`` subprocesses), never to the user's ~/.cache/hmpc
if "HMPC_CACHE_DIR" not in os.environ:
    _private_dir("HMPC_CACHE_DIR", "hmpc-test-cache-")
# PYTHONDONTWRITEBYTECODE set (as on CI machines): the hundreds of processes the tests
# start would each compile every hmpc_cli module they import from source again (a fresh
# clone holds no bytecode: 0.35 s of a 2.9 s ball run). Their bytecode goes to a private
# cache of the session instead, removed at exit, never into the tree.
if os.environ.get("PYTHONDONTWRITEBYTECODE") and "PYTHONPYCACHEPREFIX" not in os.environ:
    del os.environ["PYTHONDONTWRITEBYTECODE"]
    _private_dir("PYTHONPYCACHEPREFIX", "hmpc-test-bytecode-")
# a stop signal this session was started ignoring (pytest under nohup, or in a background
# job: SIGHUP, SIGINT) would stay ignored in the processes the tests start and signal, as
# hmpc keeps it (hmpc_cli.core.signals.stoppable): the tests start them as a terminal does
for _sig, _default in ((signal.SIGHUP, signal.SIG_DFL),
                       (signal.SIGINT, signal.default_int_handler)):
    if signal.getsignal(_sig) is signal.SIG_IGN:
        signal.signal(_sig, _default)
# the build cache's default mode, in that private cache (in $HMPC_CACHE_DIR if the caller
# set it): every build transcribes its NLP, nothing is stored or compiled (minutes of CPU
# per structure: tests/test_build_cache.py compiles where it tests it)
os.environ.setdefault("HMPC_BUILD_CACHE", "use")
SCENARIOS = REPO / "scenarios"
BALL = SCENARIOS / "ball.toml"


def nlp_function_calls(rng, nx: int, n_p: int, ng: int) -> list[tuple[str, list]]:
    """(name, arguments) of the functions IPOPT calls (``nlpsol``'s names), at one random
    point (x, p, lam_f, lam_g) of ``rng`` for an NLP of those sizes."""
    x, p = rng.standard_normal(nx), rng.uniform(size=n_p)
    lam = [rng.standard_normal(), rng.standard_normal(ng)]
    return [("nlp_f", [x, p]), ("nlp_g", [x, p]), ("nlp_grad_f", [x, p]),
            ("nlp_jac_g", [x, p]), ("nlp_hess_l", [x, p, *lam])]


def _click_command_built_once(get_command):
    """Typer's ``get_command`` made once per app and its registered commands and groups:
    ``CliRunner.invoke`` otherwise builds the whole command tree, every option's parameter
    and its type adapter, on every call (most of an in-process bad-input test). A process
    of the real ``hmpc`` builds it once too."""
    built: dict = {}

    def command(app):
        parts = (app, *app.registered_commands, None, *app.registered_groups, None,
                 app.registered_callback)
        key = tuple(map(id, parts))
        if key not in built:  # the parts kept alive with it: their ids are not reused
            built[key] = (parts, get_command(app))
        return built[key][1]

    return command


typer.testing._get_command = _click_command_built_once(typer.testing._get_command)


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The files holding the most slow tests selected go to the workers first, then those
    holding the most tests, each file's tests in their own order.

    Under ``--dist loadfile --no-loadscope-reorder`` a worker takes whole files in this
    order. The slow files are the long ones, so a run with them (``pytest -m 'not
    campaign'``, CI) starts them early and does not end on one while the other cores idle;
    the fast suite alone is ordered by test count, as xdist would order it.
    """
    slow: Counter[str] = Counter()
    count: Counter[str] = Counter()
    for item in items:
        count[item.location[0]] += 1
        slow[item.location[0]] += item.get_closest_marker("slow") is not None
    first = {f: k for k, f in enumerate(dict.fromkeys(i.location[0] for i in items))}
    items.sort(key=lambda i: (-slow[i.location[0]], -count[i.location[0]],
                              first[i.location[0]]))


@pytest.fixture(autouse=True)
def _default_verbosity():
    """Each test starts at the default verbosity: an in-process command run with -q (the
    process-wide ``VERBOSITY``) does not make a later test's command quiet."""
    from hmpc_cli.cli.common import VERBOSITY

    VERBOSITY[0] = 0
    yield
    VERBOSITY[0] = 0


@pytest.fixture(autouse=True)
def _no_pending_stop_signal():
    """A stop signal a test sent to its own process is forgotten after it: else the next
    test's run in this worker stops at its first signal check (an xdist worker "crashed"
    with a KeyboardInterrupt)."""
    from hmpc_cli.core import signals

    yield
    signals.reset()


def hmpc_command() -> list[str]:
    """The installed ``hmpc`` console script next to this interpreter, else ``python -m``."""
    script = Path(sys.executable).with_name("hmpc")
    if script.is_file() and os.access(script, os.X_OK):
        return [str(script)]
    found = shutil.which("hmpc")
    return [found] if found else [sys.executable, "-m", "hmpc_cli"]


def cli_env() -> dict[str, str]:
    """A wide, colourless terminal so rich output is neither wrapped nor escaped."""
    return {**os.environ, "COLUMNS": "200", "NO_COLOR": "1", "TERM": "dumb"}


def _run_hmpc(args: list[str], cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    """Runs ``hmpc ARGS`` in a fresh process and captures its output."""
    return subprocess.run([*hmpc_command(), *args], cwd=cwd, env=cli_env(), capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="session")
def run_hmpc():
    """``run_hmpc(args, cwd)``: the real command line in a fresh process."""
    return _run_hmpc


def hmpc_in_process(args: list[str], cwd: Path,
                    timeout: float | None = None) -> subprocess.CompletedProcess:
    """Runs ``hmpc ARGS`` in this process from ``cwd`` (Typer's runner, the terminal of
    :func:`cli_env`); its exit code and output as a CompletedProcess. An exception the
    command does not turn into an exit code fails the test with its traceback."""
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app

    del timeout  # the signature of run_hmpc's
    here, argv = os.getcwd(), sys.argv
    os.chdir(cwd)
    sys.argv = [*hmpc_command()[-1:], *args]  # the command line the logs and pages record
    try:
        res = CliRunner().invoke(app, args, env={"COLUMNS": "200", "NO_COLOR": "1",
                                                 "TERM": "dumb"})
    finally:
        os.chdir(here)
        sys.argv = argv
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        raise res.exception
    return subprocess.CompletedProcess(args, res.exit_code, res.stdout, res.stderr)


@pytest.fixture(scope="session")
def invoke_hmpc():
    """``invoke_hmpc(args, cwd)``: the command line in this process, for tests of what a
    command writes and says, not of its process (exit by signal, a second process, the
    console script): it costs no interpreter start and no import, and shares this
    process's built NLPs."""
    return hmpc_in_process


@pytest.fixture(scope="session")
def start_hmpc():
    """``start_hmpc(args, cwd)``: like run_hmpc but returns the running Popen."""
    def start(args: list[str], cwd: Path) -> subprocess.Popen:
        return subprocess.Popen([*hmpc_command(), *args], cwd=cwd, env=cli_env(), text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)

    return start


@dataclass
class FullRun:
    """The full default ball scenario, run once through the real command line."""

    out: Path
    proc: subprocess.CompletedProcess


@pytest.fixture(scope="session")
def full_run(tmp_path_factory: pytest.TempPathFactory) -> FullRun:
    """``hmpc run scenarios/ball.toml --out DIR`` with nothing overridden (runs once)."""
    base = tmp_path_factory.mktemp("full_run")
    out = base / "run"
    proc = _run_hmpc(["run", str(BALL), "--out", str(out), "--quiet"], cwd=base)
    return FullRun(out, proc)


def run_loop(scenario, path: Path):
    """Runs a validated scenario's closed loop in this process into the log ``path``."""
    from hmpc_cli.run.runner import prepare, run_to_log

    return run_to_log(prepare(scenario), path)


def assert_runs_match_the_committed_table(results: Path, sweep: str,
                                          keep=lambda row: True) -> int:
    """The rows of ``results`` (a results.csv just made) against the committed
    ``results/sweeps/<sweep>/results.csv``, run by run: the same runs (those ``keep``
    selects), each with the same outcome, reason, contacts, solves and solver failures,
    and its final error to 1e-6 relative. Returns the number of runs compared."""
    def rows(path: Path) -> dict:
        with open(path, newline="") as f:
            return {r["run_id"]: r for r in csv.DictReader(f) if keep(r)}

    again, committed = rows(results), rows(REPO / "results" / "sweeps" / sweep / "results.csv")
    assert again.keys() == committed.keys(), (sweep, sorted(again.keys() ^ committed.keys()))
    same = ("success", "reason", "contacts", "solves", "solver_failures")
    for run_id, r in again.items():
        c = committed[run_id]
        assert [r[k] for k in same] == [c[k] for k in same], (sweep, run_id)
        assert float(r["final_error"]) == pytest.approx(float(c["final_error"]), rel=1e-6), \
            (sweep, run_id)
    return len(again)


def write_finished_log(run_dir: Path, summary: dict | None = None) -> Path:
    """A minimal complete run log (/run/summary only) in ``run_dir``: what a sweep's resume
    requires of a finished run besides summary.json (hmpc_cli.sweep.table.finished_in)."""
    import json

    from mcap.writer import Writer

    path = Path(run_dir) / "run.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="test")
        sid = w.register_schema("Summary", "jsonschema", b"{}")
        cid = w.register_channel("/run/summary", "json", sid)
        w.add_message(cid, 0, json.dumps(summary or {"success": True}).encode(), 0)
        w.finish()
    return path


def signal_handlers_installed(pid: int) -> bool:
    """Whether process ``pid`` catches SIGTERM and SIGHUP (hmpc's handlers are in place)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = int(next(ln.split()[1] for ln in status.splitlines()
                      if ln.startswith("SigCgt:")), 16)
    return all(caught & (1 << (int(s) - 1)) for s in (signal.SIGTERM, signal.SIGHUP))


def file_tree(root: Path) -> set[str]:
    """Every path under ``root``, relative to it."""
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def bad_input(work: Path, args: list[str]) -> list[str]:
    """``hmpc ARGS`` in-process expecting bad input: exit 2 by SystemExit, no traceback and
    no usage box, nothing written under ``work``, only ``error: `` lines (returned)."""
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app

    before = file_tree(work)
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2, (args, res.output, res.exception)
    assert isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output and "Usage:" not in res.output
    assert file_tree(work) == before, "bad input must not create any file or directory"
    lines = res.stderr.splitlines()
    assert lines and all(line.startswith("error: ") for line in lines), lines
    return lines


def standard_schema_errors(log) -> list[str]:
    """Every message of a read log (:func:`hmpc_cli.log.reader.read_log`) checked against
    its own channel's JSON schema by ``jsonschema`` (Draft 2020-12): one line per error."""
    import jsonschema

    checkers = {topic: jsonschema.Draft202012Validator(schema)
                for topic, schema in log.schemas.items()}
    return [f"{m.topic} t={m.t:.4f} {'/'.join(map(str, e.absolute_path))}: {e.message}"
            for m in log.messages for e in checkers[m.topic].iter_errors(m.data)]


def mounted_tmpfs(path: Path, options: str, why: str):
    """Mounts a tmpfs (``mount -o options``) on the new directory ``path``, yields it and
    unmounts it (a generator for a fixture); skips with ``why`` without root or mount."""
    path.mkdir()
    if os.geteuid() != 0 or subprocess.run(
            ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)],
            capture_output=True).returncode != 0:
        pytest.skip(f"needs root and a tmpfs mount for {why}")
    yield path
    subprocess.run(["umount", str(path)], check=False)


def forbid_prepare(monkeypatch: pytest.MonkeyPatch) -> None:
    """Makes building a loop fail the test: bad input must be refused before it."""
    import hmpc_cli.run.runner

    def prepare(scenario):
        raise AssertionError("invalid input reached prepare()")

    monkeypatch.setattr(hmpc_cli.run.runner, "prepare", prepare)


def stop_process(proc: subprocess.Popen, sig: int, timeout: float) -> tuple[float, str]:
    """Sends ``sig``; returns (seconds until the process exited, its stderr).

    Hang guard: a process still running after ``timeout`` s is killed (communicate raises).
    """
    import time

    sent = time.monotonic()
    os.kill(proc.pid, sig)
    try:
        _, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return time.monotonic() - sent, err


def load_benchmark(stem: str):
    """``benchmarks/<stem>.py`` as a module (the benchmarks are scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        f"benchmark_{stem}", Path(__file__).resolve().parents[1] / "benchmarks" / f"{stem}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
