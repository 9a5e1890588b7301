"""One run on disk: ``<out>/{scenario.toml, run.mcap, summary.json}``.

Shared by ``hmpc run``, ``hmpc report`` and the sweep workers. The loop is built first
(:func:`prepare`: bad plug-ins and settings fail before anything is written); the MPC's
NLPs are built once per process per (system, MPC settings) by :func:`hmpc_cli.run.compose.build`.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import threading
import tomllib
import traceback
from collections.abc import Callable
from pathlib import Path

from hmpc_cli.core import signals
from hmpc_cli.core.paths import disk_error, first_names, write_atomic
from hmpc_cli.log.books import RunResult
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.runlog import NullWriter, Provenance, TopicWriter
from hmpc_cli.run.compose import PreparedRun, build
from hmpc_cli.run.loop import ClosedLoop

INTERRUPTED = "interrupted"  # a summary reason's prefix: the run was stopped

__all__ = ["RunDirTakenError", "claim_run_dir", "execute_run", "jsonable", "out_problem",
           "prepare", "run_one", "run_scenario", "run_to_log", "run_unlogged", "summary_text"]


def prepare(scenario) -> PreparedRun:
    """The scenario's run, built and checked; nothing is written yet.

    Raises:
        hmpc_cli.core.registry.PluginError: a plug-in fails to build.
        ValueError: settings that do not fit the built system.
        RuntimeError: CasADi rejects the solver settings.
    """
    return build(scenario)


def run_unlogged(prepared: PreparedRun) -> RunResult:
    """Runs a prepared run without a log (benchmarks); returns its result."""
    return ClosedLoop(prepared, NullWriter()).run()


def run_to_log(prepared: PreparedRun, path: Path) -> RunResult:
    """Runs a prepared run into the one MCAP file ``path`` (no run directory, no scene)."""
    rec = Recorder(path)
    log = TopicWriter(rec, prepared.identity)
    try:
        return ClosedLoop(prepared, log).run()
    finally:
        try:
            log.flush_held()
        finally:
            rec.close()


def out_problem(out: Path) -> str | None:
    """Why ``out`` cannot become a run directory, or None; creates and removes nothing.

    Checked before anything is built: the shared output-path check
    (:func:`hmpc_cli.core.paths.output_problem`: an empty or too long name, a file in the
    way, a dangling link, /proc, a directory that cannot be created or written), an
    existing run and a directory that holds anything else (the run would overwrite or mix
    with it).
    """
    from hmpc_cli.core.paths import output_problem

    problem = output_problem(out, "dir")
    if problem is not None:
        return problem
    try:
        if (out / "run.mcap").exists() or (out / "run.mcap").is_symlink():
            return "already holds a run (choose another --out)"
        if out.is_dir():
            names = sorted(entry.name for entry in os.scandir(out))
            if names:
                shown = first_names(names)
                return (f"is not empty ({shown}): a run writes run.mcap, scenario.toml and "
                        "summary.json into a directory of its own (choose a new or empty "
                        "--out)")
    except OSError as exc:
        return f"not a usable path: {exc}"
    return None


class RunDirTakenError(Exception):
    """Another run has claimed the directory (its run.mcap exists)."""


def claim_run_dir(out: Path) -> Path:
    """Creates ``out`` (and parents) and claims it for one run: its run.mcap, exclusively.

    Two runs started into one directory at once never share it: the second finds the
    log created (``O_EXCL``) and raises :class:`RunDirTakenError`; nothing of it is written.
    The claimed log is empty until :func:`execute_run` writes it.
    """
    out.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(out / "run.mcap", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    except FileExistsError:
        raise RunDirTakenError(f"{out}: already holds a run (choose another --out)") from None
    os.close(fd)
    return out


def jsonable(value):
    """Replaces NaN and +-inf by None recursively (strict JSON has neither)."""
    from hmpc_cli.core.jsonio import finite

    return finite(value)


def summary_text(res: RunResult) -> str:
    """``summary.json``'s text: the result's fields, NaN and inf as null.

    ``real_time`` is left out when there is none (time paused, or a set-up that failed).
    """
    from hmpc_cli.core.jsonio import dumps

    fields = {k: v for k, v in res.__dict__.items() if not (k == "real_time" and v is None)}
    return dumps(fields, indent=2) + "\n"


def execute_run(prepared: PreparedRun, toml_text: str, out: Path,
                progress: Callable[[int, int, str], None] | None = None,
                mirror=None, provenance: Provenance | None = None) -> RunResult:
    """Runs ``prepared`` into directory ``out``: its recorder opened here, and closed.

    The log is closed and the summary written even when the run is interrupted or
    crashes (``reason``: ``interrupted (SIGTERM)``, or the exception's type and message;
    the exception propagates after that: :class:`hmpc_cli.core.signals.Interrupted` for a stop
    signal; ``prepared.result`` holds the run's result then). ``mirror`` (e.g. a
    :class:`hmpc_cli.log.live.LiveSink`) also gets every topic and message of the log;
    ``provenance``: the command line and overrides recorded (default: this process's).
    """
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "scenario.toml", toml_text)  # a full disk leaves no empty file
    with signals.deferred():  # a signal stops the loop at its next check, not the writes
        rec = Recorder(out / "run.mcap", mirror=mirror)
        res, log = prepared.result, None
        try:
            rec.add_attachment("scenario.toml", toml_text.encode(), "application/toml")
            log = TopicWriter(rec, prepared.identity, provenance, _open_scene(prepared, rec))
            res = ClosedLoop(prepared, log, progress).run()
        except KeyboardInterrupt as exc:
            if not res.reason.startswith(INTERRUPTED):
                res.reason = f"{INTERRUPTED} ({signals.as_interrupted(exc).name})"
            raise
        except Exception as exc:
            if not res.reason:
                res.reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
            raise
        finally:
            try:
                if log is not None:
                    log.flush_held()
            finally:
                try:
                    rec.close()
                finally:  # the summary also when the last writes fail (e.g. a full disk)
                    _write_summary(out, res)
    return res


def _write_summary(out: Path, res: RunResult) -> None:
    """Writes ``summary.json`` atomically (a reader never sees half of it, nor a temporary)."""
    write_atomic(out / "summary.json", summary_text(res))


def _open_scene(prepared: PreparedRun, rec: Recorder):
    """The run's 3D scene writer (the simulated system's drawing), or None."""
    from hmpc_cli.log.scene import open_scene

    margins = prepared.identity.margins
    return open_scene(rec, prepared.plant.system, dict(margins) if margins else None)


def run_scenario(scenario, toml_text: str, out: Path,
                 progress: Callable[[int, int, str], None] | None = None) -> RunResult:
    """:func:`prepare` then :func:`execute_run`."""
    return execute_run(prepare(scenario), toml_text, out, progress)


# ------------------------------------------------------------------ a sweep's run
_LOCK = threading.Lock()


@contextlib.contextmanager
def runs_in_this_process():
    """Where :func:`run_one` runs in a process that goes on after its runs.

    A sweep's runs in the caller's own process: within, they wait for their kernels'
    compiles; after, the process's NLP builds compile them in the background again.
    """
    from hmpc_cli.mpc import kernels

    with kernels.waits_restored():
        yield


def run_one(toml_text: str, run_dir: str, provenance=None) -> dict:
    """Runs one effective scenario into ``run_dir`` (replacing it); returns its summary.

    An exception becomes a failed run: ``reason`` is the exception type and message and
    ``error.txt`` holds the traceback; a disk error (a full or read-only disk,
    :func:`hmpc_cli.core.paths.disk_error`) is no run's result: it is raised. Runs in one
    process are serialized (IPOPT is not thread-safe); NLPs are cached per process
    (:func:`hmpc_cli.run.compose.build`).
    ``provenance`` (:class:`hmpc_cli.log.runlog.Provenance`, see :func:`run_provenance`) is
    recorded in the run's log; None records this process's command line only. A sweep's
    process runs many runs, so it waits for its NLPs' stage kernels to compile (once,
    :func:`hmpc_cli.mpc.kernels.wait_for_compiles`): its later runs evaluate them in C.
    """
    from hmpc_cli.mpc import kernels
    from hmpc_cli.run.scenario import scenario_model

    kernels.wait_for_compiles()

    out = Path(run_dir)
    with _LOCK:
        if out.exists():
            shutil.rmtree(out)
        prepared, sc = None, None
        try:
            sc = scenario_model().model_validate(tomllib.loads(toml_text))
            prepared = prepare(sc)
            execute_run(prepared, toml_text, out, provenance=provenance)
        except Exception as exc:  # broad on purpose: a failed run is a result
            if disk_error(exc):  # the sweep stops (its files could not be written either)
                raise
            res = prepared.result if prepared is not None else RunResult(
                sc.name if sc else "?", sc.seed if sc else -1)
            res.success = False
            res.reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:500]
            out.mkdir(parents=True, exist_ok=True)
            write_atomic(out / "scenario.toml", toml_text)
            write_atomic(out / "error.txt", traceback.format_exc())
            write_atomic(out / "summary.json", summary_text(res))
        return json.loads((out / "summary.json").read_text())
