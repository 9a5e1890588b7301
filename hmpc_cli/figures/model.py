"""The controllers' model of a recorded run, rebuilt from its log through the registry."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hmpc_cli.figures.common import FigureInputError


def system_from_params(system: dict, where: str) -> Any:
    """Builds the registered system a logged ``[system]`` section names.

    Raises:
        FigureInputError: no system section, an unknown or broken plug-in, or
            parameters its plug-in rejects.
    """
    from pydantic import ValidationError

    from hmpc_cli.registry import PluginError, build_system, registry

    if not system or not isinstance(system.get("name"), str):
        raise FigureInputError(f"{where}: the log names no system")
    try:
        params = registry().system(system["name"]).params.model_validate(system)
        return build_system(params)
    except PluginError as exc:
        raise FigureInputError(f"{where}: {exc}") from None
    except ValidationError as exc:
        raise FigureInputError(f"{where}: bad {system['name']} parameters in the log "
                               f"({exc.error_count()} errors)") from None


def system_from_log(path: Path, log) -> Any:
    """The system of a read log (its /run/info scenario's ``[system]`` section)."""
    infos = log.topic("/run/info")
    scenario = (infos[0].data.get("scenario") or {}) if infos else {}
    return system_from_params(dict(scenario.get("system") or {}), str(path))


def read_logged_system(path: Path, what: str = "log") -> tuple[Any, Any]:
    """(log, system) of the run log ``path``: its messages and its rebuilt system.

    Raises:
        FigureInputError: "no such <what>", an unreadable log, or no buildable system.
    """
    from hmpc_cli.recorder import read_log

    if not path.is_file():
        raise FigureInputError(f"{path}: no such {what}")
    try:
        log = read_log(path)
    except (OSError, ValueError) as exc:
        raise FigureInputError(f"{path}: cannot read log ({exc})") from None
    return log, system_from_log(path, log)
