"""``hmpc run`` stopped by SIGINT, SIGTERM and SIGHUP: clean log, true summary, exit code."""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from types import SimpleNamespace

import pytest

from conftest import BALL, cli_env, stop_process
from hmpc_cli.log.reader import read_log

CODES = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGHUP: 129}


def _start(tmp_path: Path, out: Path, extra: list[str]) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "hmpc_cli", "run", str(BALL), "--out", str(out), "-q",
           *extra]
    return subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)


def _wait_for_log(proc: subprocess.Popen, mcap: Path, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if mcap.exists() and mcap.stat().st_size > 0:
            return
        time.sleep(0.05)
    raise AssertionError("the run did not start its log")


def _main_thread_cpu(pid: int) -> float:
    """CPU time [s] the process's main thread has used (utime + stime)."""
    import os

    fields = Path(f"/proc/{pid}/task/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _wait_for_cpu(proc: subprocess.Popen, seconds: float, timeout: float = 300.0) -> None:
    """Waits until the run's main thread has used ``seconds`` more of CPU time: its
    progress, whatever the machine's load (a fixed sleep on a busy machine stopped it
    before its first solve; other threads, e.g. a BLAS pool's, are not counted)."""
    start, deadline = _main_thread_cpu(proc.pid), time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if _main_thread_cpu(proc.pid) - start >= seconds:
            return
        time.sleep(0.05)
    raise AssertionError(f"the run did not use {seconds} s of CPU in {timeout} s")


def _stop(proc: subprocess.Popen, sig: int) -> tuple[float, str]:
    """Sends ``sig``; returns (seconds until the process exited, its stderr)."""
    return stop_process(proc, sig, 30)


def _check_interrupted(out: Path, sig: int, proc: subprocess.Popen, err: str) -> dict:
    name = signal.Signals(sig).name
    assert proc.returncode == CODES[sig], err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if ln.startswith("interrupted")]
    assert len(lines) == 1 and str(out / "run.mcap") in lines[0] and name in lines[0], err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reason"] == f"interrupted ({name})"
    assert summary["success"] is False
    log = read_log(out / "run.mcap")
    assert log.complete, "the log is closed with its footer"
    assert log.topic("/run/info") and log.topic("/run/summary")
    states = log.topic("/sim/state")
    assert summary["t_end"] > 0.0
    assert abs(states[-1].t - summary["t_end"]) <= 1.0 / 600 + 1e-9
    assert len(summary["x_end"]) == 4 and summary["mode_end"]
    assert summary["solves"] == len(log.topic("/mpc/solve")) > 0
    assert math.isfinite(summary["solve_time_median"])
    assert summary["planner_calls"] >= 1
    return summary


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=lambda s: signal.Signals(s).name)
def test_signal_stops_run_cleanly(tmp_path, sig):
    out = tmp_path / "run"
    proc = _start(tmp_path, out, ["--set", "sim.duration=60.0"])
    _wait_for_log(proc, out / "run.mcap")
    _wait_for_cpu(proc, 2.0)
    _, err = _stop(proc, sig)
    _check_interrupted(out, sig, proc, err)


def _ipopt_tables(lines: list[str]) -> list[dict]:
    """The MPC solves IPOPT printed (print_level 5; not its 1-variable problems): per
    solve its iteration numbers, its "Number of Iterations" and its EXIT line (None: the
    solve did not end)."""
    tables: list[dict] = []
    for line in lines:
        if line.startswith("Total number of variables"):
            tables.append({"nvar": int(line.split()[-1]), "iters": [], "count": None,
                           "exit": None})
        elif tables and (m := re.match(r"\s*(\d+)r?\s+[-+\d]", line)):
            tables[-1]["iters"].append(int(m.group(1)))
        elif tables and line.startswith("Number of Iterations"):
            tables[-1]["count"] = int(line.split()[-1])
        elif tables and line.startswith("EXIT:"):
            tables[-1]["exit"] = line.strip()
    return [t for t in tables if t["nvar"] > 100]


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=lambda s: signal.Signals(s).name)
def test_signal_inside_an_ipopt_solve_stops_it(tmp_path, sig):
    """The signal is sent at iteration 20 of the 4th MPC solve (of up to 150 iterations,
    IPOPT's own output read as it prints): that solve is cut there, before its maximum
    and without its EXIT line, and is not logged; every solve before it is, as printed."""
    out = tmp_path / "run"
    # long solves: IPOPT cannot converge (tol 1e-300), most run to 150 iterations
    cmd = [sys.executable, "-m", "hmpc_cli", "run", str(BALL), "--out", str(out), "-q",
           "--set", "sim.duration=20.0", "--set", "mpc.max_iter=150", "--set",
           "mpc.solver_options={ipopt = {tol = 1e-300, acceptable_iter = 0, "
           "dual_inf_tol = 1e-300, compl_inf_tol = 1e-300, print_level = 5}}"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env={**cli_env(), "PYTHONUNBUFFERED": "1"},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    printed: list[str] = []
    big = 0  # MPC solves started
    try:
        for line in proc.stdout:  # the run ends by itself after 20 s of sim time
            printed.append(line)
            if line.startswith("Total number of variables") and int(line.split()[-1]) > 100:
                big += 1
            if big == 4 and re.match(r"\s*20r?\s", line):
                break
        os.kill(proc.pid, sig)
        rest, err = proc.communicate(timeout=60)  # a hang guard
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    printed += rest.splitlines(keepends=True)
    summary = _check_interrupted(out, sig, proc, err)
    # the one line, not CasADi's warning about the interrupt it caught inside IPOPT too
    assert len(err.strip().splitlines()) == 1, err
    tables = _ipopt_tables(printed)
    *done, cut = tables
    assert len(done) == summary["solves"] >= 3
    assert cut["exit"] is None and cut["count"] is None, cut
    assert 20 <= cut["iters"][-1] < 150, cut["iters"]
    assert cut["iters"] == list(range(cut["iters"][-1] + 1))
    logged = [m.data["iterations"] for m in read_log(out / "run.mcap").topic("/mpc/solve")]
    assert logged == [t["count"] for t in done]
    assert all(t["exit"] for t in done)


class _Frozen(datetime):
    @classmethod
    def now(cls, tz=None):
        return datetime(2026, 1, 2, 3, 4, 5, tzinfo=tz)


def test_default_run_dirs_are_unique_within_a_second(tmp_path, monkeypatch):
    from hmpc_cli.cli import run as cli

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(cli, "datetime", _Frozen)
    sc = SimpleNamespace(name="ball", seed=3)
    dirs = [cli._run_dir(None, sc) for _ in range(3)]
    assert [d.name for d in dirs] == ["20260102-030405-seed3", "20260102-030405-seed3-2",
                                      "20260102-030405-seed3-3"]
    assert all((tmp_path / d).is_dir() for d in dirs)


@pytest.mark.slow
def test_two_default_runs_at_once_get_two_directories(tmp_path):
    cmd = [sys.executable, "-m", "hmpc_cli", "run", str(BALL), "-q", "--set",
           "sim.duration=0.05"]
    procs = [subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    errs = [p.communicate(timeout=120)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    runs = sorted((tmp_path / "results" / "ball").iterdir())
    assert len(runs) == 2 and all((d / "summary.json").exists() for d in runs)
    assert all(read_log(d / "run.mcap").complete for d in runs)


def test_explicit_out_holding_a_run_is_refused(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "run.mcap").write_bytes(b"x")
    r = subprocess.run([sys.executable, "-m", "hmpc_cli", "run", str(BALL), "--out",
                        str(out), "-q"], cwd=tmp_path, env=cli_env(), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and "already holds a run" in r.stderr


def test_a_crashed_run_summary_has_the_exception_and_the_state_reached(tmp_path):
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(BALL, ["sim.duration=0.5"], None)
    loop = prepare(sc)
    step, calls = loop.plant.step, []

    def failing(*args, **kw):
        calls.append(1)
        if len(calls) == 100:
            raise RuntimeError("boom  in\nthe plant")
        return step(*args, **kw)

    loop.plant.step = failing
    with pytest.raises(RuntimeError):
        execute_run(loop, text, tmp_path / "run")
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["reason"] == "RuntimeError: boom in the plant"
    assert summary["t_end"] == pytest.approx(99 / 600) and summary["solves"] > 0
    assert len(summary["x_end"]) == 4 and math.isfinite(summary["solve_time_median"])
    assert read_log(tmp_path / "run" / "run.mcap").complete


def test_a_signal_after_the_run_finished_says_so(tmp_path, monkeypatch):
    """A stop signal while the summary is printed: the run and its log are complete, and
    the one stderr line says that (not "while setting up; no run was started")."""
    from typer.testing import CliRunner

    import hmpc_cli.cli.run
    from hmpc_cli.cli.app import app
    from hmpc_cli.core.signals import Interrupted

    def stopped(result, out):
        raise Interrupted(signal.SIGTERM)

    monkeypatch.setattr(hmpc_cli.cli.run, "_print_summary", stopped)
    out = tmp_path / "r"
    res = CliRunner().invoke(app, ["run", str(BALL), "--set", "sim.duration=0.05",
                                   "--out", str(out)])
    assert res.exit_code == 143, res.output
    assert res.stderr.splitlines() == [
        f"interrupted (SIGTERM) after the run finished; its log is complete: {out / 'run.mcap'}"]
    assert json.loads((out / "summary.json").read_text())["t_end"] == pytest.approx(0.05)
    assert read_log(out / "run.mcap").complete


def test_casadis_interrupt_warning_is_left_out_of_stderr_inside_a_solve(monkeypatch):
    """A stop signal inside an abortable section (an IPOPT solve) filters stderr until the
    section ends: the line CasADi writes in pieces about the interrupt it caught is
    dropped, every other line reaches stderr whole. Without a signal, or with one outside
    a solve, stderr is left as it is."""
    import contextlib
    import io

    from hmpc_cli.core import signals

    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    signals.reset()
    with signals.abortable():
        assert sys.stderr is err
        sys.stderr.write("before the signal\n")
    warning = ["CasADi - ", "2026", "-", "11", " WARNING(\"", "KeyboardInterruptException",
               "\") [", ".../ipopt_nlp.cpp:114", "]", "\n"]
    with pytest.raises(signals.Interrupted), signals.abortable():
        with contextlib.suppress(signals.Interrupted):  # CasADi catches it in IPOPT
            signals._handler(signal.SIGINT, None)
        assert sys.stderr is not err
        for piece in ["another ", "line\n", *warning, "a partial", " line"]:
            sys.stderr.write(piece)
    signals.reset()
    assert sys.stderr is err
    assert err.getvalue() == "before the signal\nanother line\na partial line"
    with pytest.raises(signals.Interrupted):
        signals._handler(signal.SIGINT, None)  # outside a solve: nothing to filter
    signals.reset()
    assert sys.stderr is err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_where_python_drops_exceptions_is_raised_after_it(sig):
    """The handler's raise inside a finaliser or a weakref callback (importlib's module-lock
    callback, in CI: a SIGINT to `hmpc replay --figures` printed "Exception ignored in:
    <function _get_module_lock.<locals>.cb>" and a traceback) is not lost nor reported:
    the stop is raised in the code around it, or on the way out of a body that ends
    first; the hooks are restored after."""
    import gc

    from hmpc_cli.core import signals

    dropped: list = []
    hook, sys.unraisablehook = sys.unraisablehook, dropped.append

    class Dying:
        def __del__(self):
            signal.raise_signal(sig)
            sum(range(1000))  # the handler runs in here; Python drops what it raises

    try:
        with pytest.raises(signals.Interrupted) as exc, signals.handle_signals():
            Dying()
            gc.collect()
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline:  # the signal sent again lands in here
                pass
        assert exc.value.signum == sig and dropped == []
        assert sys.unraisablehook == dropped.append  # handle_signals' own hook undone
        # a body that ends before the handler is called again: the stop on its way out
        with pytest.raises(signals.Interrupted) as exc, signals.handle_signals():
            Dying()
            gc.collect()
        assert exc.value.signum == sig and dropped == []
        time.sleep(0.01)  # the stale call asked for is not made: nothing raises here
        Dying.__del__ = lambda self: (_ for _ in ()).throw(ValueError("mine"))
        Dying()
        gc.collect()
        assert [type(u.exc_value) for u in dropped] == [ValueError]  # others as before
    finally:
        sys.unraisablehook = hook
        signals.reset()


def test_a_dropped_stop_is_asked_for_again_only_while_nothing_raised_it():
    """check() raising the stop first, no second raise cuts the cleanup after it; check()'s
    own Interrupted dropped in a finaliser inside a deferred section keeps the section
    deferred (the signal stays recorded); a nested handle_signals leaves the outer one in
    place, so a stop dropped after the inner one ended is still raised (review of the
    change: each reproduced)."""
    import gc

    from hmpc_cli.core import signals

    hook, sys.unraisablehook = sys.unraisablehook, lambda info: None
    raise_in_del = {"fn": lambda: signal.raise_signal(signal.SIGTERM)}

    class Dying:
        def __del__(self):
            raise_in_del["fn"]()
            sum(range(1000))

    def spin(seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            pass

    cleaned: list[bool] = []
    try:
        with pytest.raises(signals.Interrupted), signals.handle_signals():
            Dying()
            gc.collect()  # dropped: asked for again in 1 ms
            try:
                signals.check()  # raises it first
            except signals.Interrupted:
                spin(0.05)  # cleanup: not cut by a second raise
                cleaned.append(True)
                raise
        assert cleaned == [True]
        signals.reset()
        with pytest.raises(signals.Interrupted), signals.handle_signals():
            with signals.deferred():
                with contextlib.suppress(signals.Interrupted):
                    signal.raise_signal(signal.SIGTERM)  # recorded only
                raise_in_del["fn"] = signals.check
                Dying()
                gc.collect()  # check()'s Interrupted dropped: the section stays deferred
                assert signals._STATE.raise_now is False
                spin(0.02)
            signals.check()
        signals.reset()
        raise_in_del["fn"] = lambda: signal.raise_signal(signal.SIGINT)
        with pytest.raises(signals.Interrupted) as exc, signals.handle_signals():
            with signals.handle_signals():  # nested: the outer one stays
                pass
            Dying()
            gc.collect()
            spin(5)
        assert exc.value.signum == signal.SIGINT
    finally:
        sys.unraisablehook = hook
        signals.reset()


@pytest.mark.parametrize("verbose", [0, 1])
def test_an_exception_after_a_stop_signal_is_the_stop(capsys, verbose):
    """The handler's KeyboardInterrupt raised where C code runs Python can come out as
    another exception (a SIGINT to `hmpc replay` in CI ended in ``TypeError: expected a
    message argument``, CPython 3.11.2's import machinery): with a stop signal received, the
    command reports the stop, exit 128 + signal, not an internal error; the exception's
    traceback with -v. Without a signal the same exception is an internal error."""
    import os

    import typer

    from hmpc_cli.cli.common import EXIT_INTERNAL, with_verbosity
    from hmpc_cli.core.signals import deferred

    def body(signalled: bool):
        if signalled:
            with deferred():  # the handler only records the signal
                os.kill(os.getpid(), signal.SIGTERM)
        raise TypeError("expected a message argument")

    command = with_verbosity(body)
    with pytest.raises(typer.Exit) as stop:
        command(signalled=True, verbose=verbose)
    assert stop.value.exit_code == 143
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "interrupted (SIGTERM)"
    if verbose:
        assert err[-1] == "TypeError: expected a message argument"
    else:
        assert err[1:] == []
    with pytest.raises(typer.Exit) as failed:
        command(signalled=False)
    assert failed.value.exit_code == EXIT_INTERNAL
    assert capsys.readouterr().err.startswith("error: internal error: TypeError: expected a")


def _run_stopped_after(step: str, tmp_path, monkeypatch):
    """``hmpc run`` of a 0.05 s ball run with a SIGTERM sent as ``runner.<step>`` returns;
    (the CliRunner result, the run directory)."""
    from typer.testing import CliRunner

    import hmpc_cli.run.runner as runner
    from hmpc_cli.cli.app import app

    real = getattr(runner, step)

    def then_stopped(*args, **kwargs):
        result = real(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)
        return result

    monkeypatch.setattr(runner, step, then_stopped)
    out = tmp_path / "r"
    return CliRunner().invoke(app, ["run", str(BALL), "--set", "sim.duration=0.05",
                                    "--out", str(out), "-q"]), out


def test_a_stop_right_after_the_run_directory_is_claimed_ends_a_readable_run_at_t0(
        tmp_path, monkeypatch):
    """A stop between claiming --out and the loop (it once left an empty run.mcap, said
    "no run was started" and refused the same --out again; a moment later, a log without
    /run/info that replay refused): the run ends at t = 0 with its log readable."""
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app

    res, out = _run_stopped_after("claim_run_dir", tmp_path, monkeypatch)
    assert res.exit_code == 143, res.output
    assert res.stderr.splitlines() == [
        f"interrupted (SIGTERM) at t = 0.000 s; partial log in {out / 'run.mcap'}"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reason"] == "interrupted (SIGTERM)" and summary["t_end"] == 0.0
    log = read_log(out / "run.mcap")
    assert log.complete and log.topic("/run/info") and log.topic("/run/summary")
    assert [m.t for m in log.topic("/sim/state")] == [0.0]
    monkeypatch.undo()
    shown = CliRunner().invoke(app, ["replay", str(out)])
    assert shown.exit_code == 0 and "interrupted (SIGTERM)" in shown.stdout, shown.output


def test_a_stop_after_the_runs_last_check_says_the_run_finished(tmp_path, monkeypatch):
    """A stop once the run has closed its log and written its summary (it was reported as
    "interrupted at t = 0.050 s; partial log" beside a summary saying success)."""
    res, out = _run_stopped_after("execute_run", tmp_path, monkeypatch)
    assert res.exit_code == 143, res.output
    assert res.stderr.splitlines() == [
        f"interrupted (SIGTERM) after the run finished; its log is complete: {out / 'run.mcap'}"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["t_end"] == pytest.approx(0.05) and not summary["reason"].startswith(
        "interrupted")
    assert read_log(out / "run.mcap").complete


def test_a_stop_signal_the_process_ignores_stays_ignored_and_the_others_are_handled():
    """The stop handlers took SIGHUP from ``nohup`` and SIGINT from a background job: such
    a run or sweep stopped when its terminal closed. Both stay ignored, in a command and in
    a sweep's worker; the handlers take the others and give them back."""
    from hmpc_cli.core import signals

    code = ("import signal\n"
            "signal.signal(signal.SIGHUP, signal.SIG_IGN)\n"
            "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
            "from hmpc_cli.core import signals\n"
            "names = lambda: [signal.getsignal(s) is signal.SIG_IGN for s in "
            "signals.STOP_SIGNALS]\n"
            "with signals.handle_signals():\n"
            "    print(names(), signals.stoppable())\n"
            "print(names(), signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)\n"
            "signals.install_deferred()\n"
            "print(names(), signal.getsignal(signal.SIGTERM) is signals._handler)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, env=cli_env())
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines() == [
        "[True, False, True] (<Signals.SIGTERM: 15>,)", "[True, False, True] True",
        "[True, False, True] True"]
    assert signals.STOP_SIGNALS == (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@pytest.mark.slow
def test_a_run_under_nohup_in_the_background_survives_its_terminal_closing(tmp_path):
    """``nohup hmpc run ... &``: SIGHUP (the terminal closing) and SIGINT (Ctrl-C in the
    terminal) reach a process that ignores them; the run went on to its end."""
    import os

    out = tmp_path / "run"

    def ignore() -> None:
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
        signal.signal(signal.SIGINT, signal.SIG_IGN)

    cmd = [sys.executable, "-m", "hmpc_cli", "run", str(BALL), "--out", str(out), "-q",
           "--set", "sim.duration=1.0"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=cli_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, preexec_fn=ignore)
    _wait_for_log(proc, out / "run.mcap")
    _wait_for_cpu(proc, 0.3)
    for sig in (signal.SIGHUP, signal.SIGINT):
        os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["reason"], summary["t_end"]) == ("success", 1.0)


@pytest.mark.parametrize("ignored", [False, True], ids=["handled", "ignored"])
def test_a_stop_while_the_process_exits_is_one_line_not_a_traceback(ignored):
    """Ctrl-C while the atexit handlers run (the command's handlers already taken off)
    printed a KeyboardInterrupt traceback from inside one; it is held to the exit: one
    line, 130. A SIGINT the process ignores (a background job) stays ignored."""
    code = ("import atexit, os, signal\n"  # the child's SIGINT as Python's own, or ignored
            + ("signal.signal(signal.SIGINT, signal.SIG_IGN)\n" if ignored else
               "signal.signal(signal.SIGINT, signal.default_int_handler)\n")
            + "from hmpc_cli.cli.app import end_process\n"
            "atexit.register(lambda: os.kill(os.getpid(), signal.SIGINT))\n"
            "end_process(0)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, env=cli_env())
    if ignored:
        assert (res.returncode, res.stderr) == (0, "")
    else:
        assert res.returncode == 130 and res.stderr.splitlines() == [
            "interrupted (SIGINT) while exiting; the command had finished"]


def test_a_second_stop_while_the_process_exits_ends_it_at_once():
    """An atexit handler that hangs: the first stop is held, the second ends the process
    (128 + its number), the rest of the handlers not run."""
    code = ("import atexit, os, signal, time\n"
            "signal.signal(signal.SIGINT, signal.default_int_handler)\n"  # a CI may ignore it
            "from hmpc_cli.cli.app import end_process\n"
            "atexit.register(lambda: print('not reached', flush=True))\n"
            "def hang():\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    os.kill(os.getpid(), signal.SIGTERM)\n"
            "    time.sleep(60)\n"
            "atexit.register(hang)\n"
            "end_process(0)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, env=cli_env())
    assert (res.returncode, res.stdout, res.stderr) == (143, "", "")


def test_a_solve_stopped_after_its_planner_call_leaves_that_call_in_the_log(tmp_path):
    """The planner call's /planner/plan is written with the solve that follows it (a
    dropped replan revokes its schedule there): a run stopped inside that solve still
    logs the call, before the log ends."""
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(BALL, ["sim.duration=0.5"], None)
    loop = prepare(sc)

    def stopped(*args, **kw):
        raise KeyboardInterrupt

    loop.mpc.solve = stopped
    with pytest.raises(KeyboardInterrupt):
        execute_run(loop, text, tmp_path / "run")
    log = read_log(tmp_path / "run" / "run.mcap")
    assert [m.topic for m in log.messages if m.topic.startswith(("/planner", "/mpc"))] == \
        ["/planner/plan"]


def test_a_stop_while_a_dropped_replan_is_stopped_at_its_budget_keeps_its_planner_call(
        tmp_path, monkeypatch):
    """The stop can come while the MPC replays a dropped solve to its budget's iterate
    (an IPOPT re-solve): the planner call before it is in the log all the same, as the
    books counted it."""
    from hmpc_cli.core import signals
    from hmpc_cli.mpc.walking.kind import WalkingMPC
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    root = Path(__file__).resolve().parents[1]
    sc, text = load_scenario(root / "scenarios" / "biped_rti.toml",
                             ["sim.solve_budget=0.01", "sim.duration=0.6"], None)

    def stop(self, stops):
        raise signals.Interrupted()

    monkeypatch.setattr(WalkingMPC, "stop_at", stop)
    with pytest.raises(KeyboardInterrupt):
        execute_run(prepare(sc), text, tmp_path / "run")
    log = read_log(tmp_path / "run" / "run.mcap")
    planner = [m for m in log.messages if m.topic == "/planner/plan"]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert len(planner) == summary["planner_calls"] >= 2
