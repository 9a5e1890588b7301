"""``hmpc sweep`` under faults: signals, a killed parent, killed workers, two sweeps at once."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from test_sweep import REGISTER, sweep, table, write_sweep

from conftest import cli_env


def _spec(name: str, seeds: int, duration: float) -> str:
    return (f'name = "{name}"\nscenario = "{{scenario}}"\nseeds = {seeds}\n[set]\n'
            f'"sim.duration" = {duration}\n"mpc.horizon" = 1.0\n"planner.iterations" = 6\n'
            '"planner.samples" = 20\n"planner.knots" = 10\n')


def _start(path: Path, out: Path, cwd: Path, workers: int = 2) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", REGISTER, "sweep", str(path), "--workers",
                             str(workers), "--out", str(out)], cwd=cwd, env=cli_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _workers(parent: int) -> list[int]:
    """Pids of the sweep's worker processes (children running multiprocessing's spawn)."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmd = (stat.parent / "cmdline").read_bytes()
        except OSError:
            continue
        if int(fields[1]) == parent and b"spawn_main" in cmd:
            pids.append(int(stat.parent.name))
    return pids


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _run_of(pid: int) -> str | None:
    """The run id whose run.mcap worker ``pid`` has open, if any."""
    try:
        for fd in Path(f"/proc/{pid}/fd").iterdir():
            target = os.readlink(fd)
            if target.endswith("/run.mcap"):
                return Path(target).parent.name
    except OSError:
        return None
    return None


def _wait(cond, timeout: float = 60.0, what: str = "") -> object:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = cond()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _busy_workers(proc: subprocess.Popen, n: int) -> dict[int, str]:
    """Waits until ``n`` workers each hold a run: worker pid -> run id."""
    def busy():
        runs = {pid: _run_of(pid) for pid in _workers(proc.pid)}
        runs = {p: r for p, r in runs.items() if r}
        return runs if len(runs) >= n else None
    return _wait(busy, what=f"{n} busy workers")


def _finish(proc: subprocess.Popen, timeout: float = 90) -> tuple[str, str]:
    try:
        return proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow
def test_sigterm_stops_the_sweep_and_resume_redoes_interrupted_runs(tmp_path):
    path = write_sweep(tmp_path, _spec("stop", 4, 20.0))
    out = tmp_path / "out"
    proc = _start(path, out, tmp_path)
    busy = _busy_workers(proc, 2)
    time.sleep(1.0)
    os.kill(proc.pid, signal.SIGTERM)
    _, err = _finish(proc)
    assert proc.returncode == 143, err
    assert "Traceback" not in err and "interrupted:" in err
    assert (out / "results.csv").exists() and table(out) == []
    for run in busy.values():  # the runs in flight stopped cleanly, marked interrupted
        summary = json.loads((out / "runs" / run / "summary.json").read_text())
        assert summary["reason"] == "interrupted (SIGTERM)" and summary["t_end"] > 0
    assert not any(_alive(p) for p in busy), "the workers stopped"
    path.write_text(path.read_text().replace("20.0", "0.3"))  # same ids, short runs
    # a changed duration changes the effective scenario: resume redoes them anyway
    again = sweep([str(path), "--workers", "2", "--out", str(out)], tmp_path)
    assert again.returncode == 0, again.stderr
    assert len(table(out)) == 4


def _wait_for_signal(report) -> None:  # a busy worker: says which stop signal reached it
    got = []
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, lambda signum, frame: got.append(signum))
    report.send("ready")
    while not got:
        time.sleep(0.01)
    report.send(got[0])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP])
def test_the_busy_workers_get_the_sweeps_own_stop_signal(sig):
    """A sweep stopped by SIGINT (or SIGHUP) stops its busy workers with that signal, so
    their runs are marked interrupted by it (they were sent SIGTERM)."""
    import multiprocessing
    from types import SimpleNamespace

    from hmpc_cli.sweep.pool import _stop_all

    ctx = multiprocessing.get_context("fork")
    report, child = ctx.Pipe()
    task, _ = ctx.Pipe()  # the worker's task pipe, which _stop_all closes
    proc = ctx.Process(target=_wait_for_signal, args=(child,), daemon=True)
    proc.start()
    assert report.poll(10) and report.recv() == "ready"
    _stop_all([SimpleNamespace(run="busy", proc=proc, conn=task)], sig)
    assert not proc.is_alive() and report.poll(1) and report.recv() == sig


def test_a_stopped_pool_stops_its_workers_with_the_sweeps_own_signal(monkeypatch, tmp_path):
    """run_pool stopped by SIGHUP (raised where it waits for its workers) hands SIGHUP to
    the workers' stop, not SIGTERM."""
    import multiprocessing.connection
    from types import SimpleNamespace

    from hmpc_cli.core.signals import Interrupted
    from hmpc_cli.sweep import pool

    class Idle:  # a worker that starts no process
        def __init__(self, ctx):
            self.run, self.conn, self.proc = None, object(), SimpleNamespace(sentinel=0)

        def give(self, run, out, provenance):
            self.run = run

    def stopped(*args, **kwargs):
        raise Interrupted(signal.SIGHUP)

    got = []
    monkeypatch.setattr(pool, "_Worker", Idle)
    monkeypatch.setattr(multiprocessing.connection, "wait", stopped)
    monkeypatch.setattr(pool, "_stop_all", lambda workers, stop=None: got.append(stop))
    with pytest.raises(Interrupted):
        pool.run_pool(1, ["run"], tmp_path, lambda *a: None, lambda *a: None)
    assert got == [signal.SIGHUP]


def test_interrupted_summary_is_never_kept_as_finished(tmp_path):
    from hmpc_cli.sweep.table import finished_in

    from conftest import write_finished_log

    (tmp_path / "scenario.toml").write_text("x")
    write_finished_log(tmp_path)
    for reason, kept in [("interrupted", False), ("interrupted (SIGTERM)", False),
                         ("interrupted (SIGHUP)", False), ("diverged", True)]:
        (tmp_path / "summary.json").write_text(json.dumps({"reason": reason}))
        assert (finished_in(tmp_path, "x") is not None) == kept, reason


def test_parent_sigkill_leaves_no_orphans(tmp_path):
    path = write_sweep(tmp_path, _spec("orphans", 4, 20.0))
    proc = _start(path, tmp_path / "out", tmp_path)
    workers = list(_busy_workers(proc, 2))
    os.kill(proc.pid, signal.SIGKILL)
    _finish(proc)
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline and any(_alive(p) for p in workers):
        time.sleep(0.1)
    left = [p for p in workers if _alive(p)]
    for p in left:
        os.kill(p, signal.SIGKILL)
    assert not left, "workers outlived their parent"


@pytest.mark.slow
def test_a_killed_worker_loses_only_its_run_which_is_retried(tmp_path):
    path = write_sweep(tmp_path, _spec("kill1", 2, 5.0))
    out = tmp_path / "out"
    proc = _start(path, out, tmp_path)
    busy = _busy_workers(proc, 1)  # (the other worker may be building its NLPs)
    victim = next(iter(busy))
    os.kill(victim, signal.SIGKILL)
    stdout, err = _finish(proc)
    assert proc.returncode == 0, err
    rows = table(out)
    assert len(rows) == 2
    assert not any("BrokenProcessPool" in r["reason"] or "died" in r["reason"] for r in rows)


@pytest.mark.slow
def test_a_run_that_kills_its_worker_twice_is_lost_work_and_runs_again(tmp_path):
    """Killed from outside (or out of memory) twice: no result of the controller's, so
    not tabled as a failed run; the sweep exits 1 naming it, its directory keeps why and
    the partial log, and the next sweep runs it again."""
    path = write_sweep(tmp_path, _spec("kill2", 2, 6.0))
    out = tmp_path / "out"
    proc = _start(path, out, tmp_path)
    busy = _busy_workers(proc, 1)
    victim, run = next(iter(busy.items()))
    os.kill(victim, signal.SIGKILL)

    def holder():  # the fresh worker that took the run again
        return next((p for p in _workers(proc.pid) if p != victim and _run_of(p) == run), None)
    os.kill(_wait(holder, what="the retried run"), signal.SIGKILL)
    _, err = _finish(proc)
    assert proc.returncode == 1, err
    assert f"run not recorded (rerun to retry): {run}: worker died (signal 9) twice" in err
    rows = {r["run_id"]: r for r in table(out)}
    assert list(rows) != [] and run not in rows and len(rows) == 1
    assert "died" not in next(iter(rows.values()))["reason"]
    kept = out / "runs" / run
    assert (kept / "worker-died.txt").is_file() and not (kept / "summary.json").exists()
    again = sweep([str(path), "--workers", "2", "--out", str(out)], tmp_path)
    assert again.returncode == 0, again.stderr
    rows = {r["run_id"]: r for r in table(out)}
    assert len(rows) == 2 and "died" not in rows[run]["reason"]
    assert not (kept / "worker-died.txt").exists()


@pytest.mark.slow
def test_two_sweeps_on_one_directory(tmp_path):
    path = write_sweep(tmp_path, _spec("lock", 4, 20.0))
    out = tmp_path / "out"
    first = _start(path, out, tmp_path)
    try:
        _busy_workers(first, 1)
        stamp = (out / "sweep.toml").stat().st_mtime_ns
        second = sweep([str(path), "--workers", "2", "--out", str(out)], tmp_path)
        assert second.returncode == 2, second.stderr
        assert f"error: {out}: another sweep is writing here (pid {first.pid})" in second.stderr
        # the second wrote nothing (the first is still running its 20 s runs)
        assert (out / "sweep.toml").stat().st_mtime_ns == stamp
        assert not (out / "results.csv").exists() and "results" not in second.stdout
    finally:
        os.kill(first.pid, signal.SIGINT)
        _finish(first)
    assert first.returncode == 130


def test_a_stop_while_a_worker_imports_is_recorded_not_a_traceback():
    """Ctrl-C in the first second of a sweep reached workers still importing hmpc (before
    their handlers): each printed 'Process SpawnProcess-1: Traceback ... KeyboardInterrupt'.
    The worker records a stop from its first line on and ends cleanly."""
    import subprocess
    import sys

    code = """
import importlib.abc, multiprocessing, os, signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)

class StopDuringImport(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "hmpc_cli.run.runner":
            os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the worker imports
        return None

sys.meta_path.insert(0, StopDuringImport())
from hmpc_cli.sweep.pool import worker_main
parent, child = multiprocessing.Pipe()
parent.send(None)
worker_main(child, os.getppid())
print("ended cleanly")
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert (res.returncode, res.stdout, res.stderr) == (0, "ended cleanly\n", ""), res.stderr


#: a ``sitecustomize`` whose processes (the sweep's and its spawned workers) find the disk
#: full under every sweep's runs/ directory: each atomic write there fails (ENOSPC)
FULL_RUNS = ("import errno\n"
             "from hmpc_cli.core import paths\n"
             "real = paths.write_atomic\n"
             "def write_atomic(path, data):\n"
             "    if '/runs/' in str(path):\n"
             "        raise OSError(errno.ENOSPC, 'No space left on device', str(path))\n"
             "    return real(path, data)\n"
             "paths.write_atomic = write_atomic\n")


def test_a_full_disk_in_the_workers_stops_the_pool_with_one_line(tmp_path):
    """Workers whose run files cannot be written (a full disk): the worker's disk error
    comes back to the parent, which stops with its one line (it printed each worker's
    traceback and retried every run first); no run directory holds an empty file."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(FULL_RUNS)
    path = write_sweep(tmp_path, _spec("full", 2, 0.2))
    out = tmp_path / "out"
    env = cli_env() | {"PYTHONPATH": os.pathsep.join(
        [str(site), *filter(None, [os.environ.get("PYTHONPATH")])])}
    proc = subprocess.run([sys.executable, "-c", REGISTER, "sweep", str(path), "--workers",
                           "2", "--out", str(out)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    (line,) = proc.stderr.splitlines()
    assert line.startswith(f"error: cannot write: {out / 'runs'}/"), line
    assert line.endswith(f"/scenario.toml: No space left on device; 0 of 2 runs kept in {out} "
                         "(finished runs stay; free space and run the same command to "
                         "resume)"), line
    assert [p for p in (out / "runs").rglob("*") if p.is_file()] == []
