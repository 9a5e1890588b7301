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
