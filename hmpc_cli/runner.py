"""One run on disk: ``<out>/{scenario.toml, run.mcap, summary.json}``.

Shared by ``hmpc run`` and the sweep workers. The MPC's NLP can be passed in so a worker
builds each NLP once and reuses it across runs with the same system and MPC settings.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

from hmpc_cli.loop_core import LoopCore, RunResult
from hmpc_cli.mpc.controller import FixedModeMPC
from hmpc_cli.mpc.nlp import FixedModeNLPs
from hmpc_cli.mpc.walking import WalkingMPC, WalkingNLP
from hmpc_cli.recorder import Recorder
from hmpc_cli.scenario import Scenario
from hmpc_cli.systems import build_system

_NLP_CACHE: dict[str, FixedModeNLPs | WalkingNLP] = {}


def cached_mpc(sc: Scenario) -> FixedModeMPC | WalkingMPC:
    """The scenario's fixed-mode MPC with its NLP built once per process per (system, MPC
    settings); a fresh controller (no memory of earlier runs) around the cached NLP."""
    key = json.dumps([sc.system.model_dump(mode="json"), sc.mpc.model_dump(mode="json")],
                     sort_keys=True)
    if sc.system.name == "biped":
        if key not in _NLP_CACHE:
            _NLP_CACHE[key] = WalkingNLP(sc.system, sc.mpc)
        return WalkingMPC(sc.system, sc.mpc, _NLP_CACHE[key])
    system = build_system(sc.system)
    if key not in _NLP_CACHE:
        _NLP_CACHE[key] = FixedModeNLPs(system, sc.mpc)
    return FixedModeMPC(system, sc.mpc, _NLP_CACHE[key])


def jsonable(value):
    """Replaces NaN by None recursively (JSON has no NaN)."""
    if isinstance(value, float) and value != value:
        return None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value


def execute_run(loop: LoopCore, toml_text: str, out: Path,
                progress: Callable[[int, int], None] | None = None) -> RunResult:
    """Runs ``loop`` into directory ``out``; the log is closed and the summary written
    even when the run is interrupted (KeyboardInterrupt propagates after that)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "scenario.toml").write_text(toml_text, encoding="utf-8")
    rec = Recorder(out / "run.mcap")
    loop.rec = rec
    loop.progress = progress
    result = None
    try:
        rec.add_attachment("scenario.toml", toml_text.encode(), "application/toml")
        result = loop.run()
    except KeyboardInterrupt:
        loop.res.reason = "interrupted"
        raise
    finally:
        rec.close()
        res = result if result is not None else loop.res
        (out / "summary.json").write_text(json.dumps(jsonable(res.__dict__), indent=2) + "\n")
    return result
