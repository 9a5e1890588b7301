"""One run on disk: ``<out>/{scenario.toml, run.mcap, summary.json}``.

Shared by ``hmpc run``, ``hmpc report`` and the sweep workers. The loop is built first
(:func:`prepare`: bad plug-ins and settings fail before anything is written); the MPC's
NLPs are built once per process per (system, MPC settings) by :func:`hmpc_cli.loop.build`.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from hmpc_cli.loop import ClosedLoop, RunResult, build
from hmpc_cli.recorder import Recorder
from hmpc_cli.runlog import RunLog

__all__ = ["execute_run", "jsonable", "prepare", "run_scenario"]


def prepare(scenario) -> ClosedLoop:
    """The scenario's closed loop, with a run log not yet attached to a file.

    Raises:
        hmpc_cli.registry.PluginError: a plug-in fails to build.
        ValueError: settings that do not fit the built system.
        RuntimeError: CasADi rejects the solver settings.
    """
    return build(scenario, RunLog(None))


def jsonable(value):
    """Replaces NaN and +-inf by None recursively (strict JSON has neither)."""
    from hmpc_cli.jsonio import finite

    return finite(value)


def execute_run(loop: ClosedLoop, toml_text: str, out: Path,
                progress: Callable[[int, int, str], None] | None = None,
                mirror=None) -> RunResult:
    """Runs ``loop`` into directory ``out``.

    The log is closed and the summary written even when the run is interrupted
    (KeyboardInterrupt propagates after that). ``mirror`` (e.g. a
    :class:`hmpc_cli.live.LiveSink`) also gets every topic and message of the log.
    """
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenario.toml").write_text(toml_text, encoding="utf-8")
    rec = Recorder(out / "run.mcap", mirror=mirror)
    loop.log.rec = rec
    loop.log.scene = None
    loop.progress = progress
    result = None
    try:
        rec.add_attachment("scenario.toml", toml_text.encode(), "application/toml")
        loop.log.scene = _open_scene(loop, rec)
        result = loop.run()
    except KeyboardInterrupt:
        loop.res.reason = "interrupted"
        raise
    finally:
        rec.close()
        res = result if result is not None else loop.res
        (out / "summary.json").write_text(
            json.dumps(jsonable(res.__dict__), indent=2, allow_nan=False) + "\n")
    return result


def _open_scene(loop: ClosedLoop, rec: Recorder):
    """The run's 3D scene writer (the simulated system's drawing), or None."""
    from hmpc_cli.scene import open_scene

    return open_scene(rec, loop.plant.system, loop.log.info.get("margins"))


def run_scenario(scenario, toml_text: str, out: Path,
                 progress: Callable[[int, int, str], None] | None = None) -> RunResult:
    """:func:`prepare` then :func:`execute_run`."""
    return execute_run(prepare(scenario), toml_text, out, progress)
