"""One run on disk: ``<out>/{scenario.toml, run.mcap, summary.json}``.

Shared by ``hmpc run``, ``hmpc report`` and the sweep workers. The loop is built first
(:func:`prepare`: bad plug-ins and settings fail before anything is written); the MPC's
NLPs are built once per process per (system, MPC settings) by :func:`hmpc_cli.run.loop.build`.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import tomllib
import traceback
from collections.abc import Callable
from pathlib import Path

from hmpc_cli.core import signals
from hmpc_cli.run.loop import ClosedLoop, build
from hmpc_cli.log.runlog import RunResult
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.runlog import RunLog

INTERRUPTED = "interrupted"  # a summary reason's prefix: the run was stopped

__all__ = ["execute_run", "jsonable", "out_problem", "prepare", "run_one", "run_scenario"]


def prepare(scenario) -> ClosedLoop:
    """The scenario's closed loop, with a run log not yet attached to a file.

    Raises:
        hmpc_cli.core.registry.PluginError: a plug-in fails to build.
        ValueError: settings that do not fit the built system.
        RuntimeError: CasADi rejects the solver settings.
    """
    return build(scenario, RunLog(None))


def out_problem(out: Path) -> str | None:
    """Why ``out`` cannot become a run directory, or None; creates and removes nothing.

    Checked before anything is built: an existing run, a file in the way, a name the
    file system refuses, or a directory that cannot be created or written.
    """
    import os

    try:
        for part in out.absolute().parts:
            if len(os.fsencode(part)) > 255:
                return f"name too long: {part[:40]}... ({len(os.fsencode(part))} bytes, max 255)"
        if (out / "run.mcap").exists():
            return "already holds a run (choose another --out)"
        if out.exists() and not out.is_dir():
            return "exists and is not a directory"
    except (OSError, RuntimeError, ValueError) as exc:
        return f"not a usable path: {exc}"
    parent = out
    while not parent.exists():  # the nearest existing ancestor must be a writable directory
        if parent.parent == parent:
            break
        parent = parent.parent
    if not parent.is_dir():
        return f"cannot create it: {parent} is not a directory"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot create or write it: {parent} is not writable"
    return None


def jsonable(value):
    """Replaces NaN and +-inf by None recursively (strict JSON has neither)."""
    from hmpc_cli.core.jsonio import finite

    return finite(value)


def execute_run(loop: ClosedLoop, toml_text: str, out: Path,
                progress: Callable[[int, int, str], None] | None = None,
                mirror=None) -> RunResult:
    """Runs ``loop`` into directory ``out``.

    The log is closed and the summary written even when the run is interrupted or
    crashes (``reason``: ``interrupted (SIGTERM)``, or the exception's type and message;
    the exception propagates after that: :class:`hmpc_cli.core.signals.Interrupted` for a stop
    signal). ``mirror`` (e.g. a
    :class:`hmpc_cli.log.live.LiveSink`) also gets every topic and message of the log.
    """
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenario.toml").write_text(toml_text, encoding="utf-8")
    with signals.deferred():  # a signal stops the loop at its next check, not the writes
        rec = Recorder(out / "run.mcap", mirror=mirror)
        loop.log.rec = rec
        loop.log.scene = None
        loop.progress = progress
        result = None
        try:
            rec.add_attachment("scenario.toml", toml_text.encode(), "application/toml")
            loop.log.scene = _open_scene(loop, rec)
            signals.check()
            result = loop.run()
        except KeyboardInterrupt as exc:
            if not loop.res.reason.startswith(INTERRUPTED):
                loop.res.reason = f"{INTERRUPTED} ({signals.as_interrupted(exc).name})"
            raise
        except Exception as exc:
            if not loop.res.reason:
                loop.res.reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
            raise
        finally:
            try:
                loop.log.flush_held()
            finally:
                try:
                    rec.close()
                finally:  # the summary also when the last writes fail (e.g. a full disk)
                    _write_summary(out, result if result is not None else loop.res)
    return result


def _write_summary(out: Path, res: RunResult) -> None:
    """Writes ``summary.json`` atomically (a reader never sees half of it)."""
    tmp = out / "summary.json.tmp"
    tmp.write_text(json.dumps(jsonable(res.__dict__), indent=2, allow_nan=False) + "\n")
    os.replace(tmp, out / "summary.json")


def _open_scene(loop: ClosedLoop, rec: Recorder):
    """The run's 3D scene writer (the simulated system's drawing), or None."""
    from hmpc_cli.log.scene import open_scene

    return open_scene(rec, loop.plant.system, loop.log.info.get("margins"))


def run_scenario(scenario, toml_text: str, out: Path,
                 progress: Callable[[int, int, str], None] | None = None) -> RunResult:
    """:func:`prepare` then :func:`execute_run`."""
    return execute_run(prepare(scenario), toml_text, out, progress)


# ------------------------------------------------------------------ a sweep's run
_LOCK = threading.Lock()


def run_one(toml_text: str, run_dir: str, provenance=None) -> dict:
    """Runs one effective scenario into ``run_dir`` (replacing it); returns its summary.

    An exception becomes a failed run: ``reason`` is the exception type and message and
    ``error.txt`` holds the traceback. Runs in one process are serialized (IPOPT is not
    thread-safe); NLPs are cached per process (:func:`hmpc_cli.run.loop.build`).
    ``provenance`` (:class:`hmpc_cli.log.runlog.Provenance`, see :func:`run_provenance`) is
    recorded in the run's log; None records this process's command line only.
    """
    from hmpc_cli.run.scenario import scenario_model

    out = Path(run_dir)
    with _LOCK:
        if out.exists():
            shutil.rmtree(out)
        loop, sc = None, None
        try:
            sc = scenario_model().model_validate(tomllib.loads(toml_text))
            loop = prepare(sc)
            if provenance is not None:
                loop.log.provenance = provenance
            execute_run(loop, toml_text, out)
        except Exception as exc:  # broad on purpose: a failed run is a result
            res = loop.res if loop is not None else RunResult(
                sc.name if sc else "?", sc.seed if sc else -1)
            res.success = False
            res.reason = f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:500]
            out.mkdir(parents=True, exist_ok=True)
            (out / "scenario.toml").write_text(toml_text, encoding="utf-8")
            (out / "error.txt").write_text(traceback.format_exc(), encoding="utf-8")
            (out / "summary.json").write_text(
                json.dumps(jsonable(res.__dict__), indent=2, allow_nan=False) + "\n")
        return json.loads((out / "summary.json").read_text())
