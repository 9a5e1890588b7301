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


def read_logged_system(path: Path, what: str = "log") -> tuple[Any, Any]:
    """(run, system) of the run log ``path``: its arrays (:class:`RunData`) and its system.

    Raises:
        FigureInputError: "no such <what>", an unreadable log, or no buildable system.
    """
    from hmpc_cli.rundata import read_run

    if not path.is_file():
        raise FigureInputError(f"{path}: no such {what}")
    try:
        run = read_run(path)
    except ValueError as exc:
        raise FigureInputError(f"{path}: cannot read log ({exc})") from None
    return run, system_from_params(run.system, str(path))
