"""One run on disk: ``<out>/{scenario.toml, run.mcap, summary.json}``.

Shared by ``hmpc run``, ``hmpc report`` and the sweep workers. The loop is built first
(:func:`prepare`: bad plug-ins and settings fail before anything is written); the MPC's
NLPs are built once per process per (system, MPC settings) by :func:`hmpc_cli.loop.build`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

from hmpc_cli import signals
from hmpc_cli.loop import ClosedLoop, RunResult, build
from hmpc_cli.recorder import Recorder
from hmpc_cli.runlog import RunLog

INTERRUPTED = "interrupted"  # a summary reason's prefix: the run was stopped

__all__ = ["execute_run", "jsonable", "out_problem", "prepare", "run_scenario"]


def prepare(scenario) -> ClosedLoop:
    """The scenario's closed loop, with a run log not yet attached to a file.

    Raises:
        hmpc_cli.registry.PluginError: a plug-in fails to build.
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
    from hmpc_cli.jsonio import finite

    return finite(value)


def execute_run(loop: ClosedLoop, toml_text: str, out: Path,
                progress: Callable[[int, int, str], None] | None = None,
                mirror=None) -> RunResult:
    """Runs ``loop`` into directory ``out``.

    The log is closed and the summary written even when the run is interrupted or
    crashes (``reason``: ``interrupted (SIGTERM)``, or the exception's type and message;
    the exception propagates after that: :class:`hmpc_cli.signals.Interrupted` for a stop
    signal). ``mirror`` (e.g. a
    :class:`hmpc_cli.live.LiveSink`) also gets every topic and message of the log.
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
    from hmpc_cli.scene import open_scene

    return open_scene(rec, loop.plant.system, loop.log.info.get("margins"))


def run_scenario(scenario, toml_text: str, out: Path,
                 progress: Callable[[int, int, str], None] | None = None) -> RunResult:
    """:func:`prepare` then :func:`execute_run`."""
    return execute_run(prepare(scenario), toml_text, out, progress)
