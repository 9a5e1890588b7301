"""The settings of a planner or MPC kind: every hook hmpc calls on them, declared here.

A plug-in's ``[planner]`` settings subclass :class:`PlannerSettings`, its ``[mpc]``
settings :class:`MPCKindSettings` (the registry refuses other models). A kind overrides the
hooks it needs; every default means "nothing to check" or "not applicable". hmpc calls
these methods only, never probes a settings object for attributes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, field_validator

__all__ = ["KindSettings", "MPCKindSettings", "MarginsSettings", "PlannerSettings"]


class KindSettings(BaseModel):
    """Base of a kind's settings section; validated by pydantic, unknown keys refused."""

    model_config = ConfigDict(extra="forbid")

    def scenario_problems(self) -> list[str]:
        """``section.key: reason`` lines for settings that do not fit together."""
        return []

    def size_problems(self) -> list[str]:
        """``section.key: reason`` lines for work beyond hmpc's limits, with its estimate.

        Called before anything is built; say what the setting would cost.
        """
        return []


class PlannerSettings(KindSettings):
    """Base of a planner's settings (``[planner]``, field ``kind: Literal[...]``)."""

    def system_problems(self, system: Any) -> list[str]:
        """``planner.key: reason`` lines only the built system can tell (its guards, ...)."""
        return []


class MPCKindSettings(KindSettings):
    """Base of a fixed-mode MPC's settings.

    The ``[mpc]`` section declares ``kind: Literal[...]`` and ``rate_hz``, the re-solve rate
    [Hz] the loop keeps.
    """

    def period_steps(self) -> list[tuple[str, int]]:
        """(key path, rate [Hz]) of step grids the MPC period must be a whole number of."""
        return []

    def margins_source(self) -> str | None:
        """Where the constraint margins come from.

        ``"hand"`` (the kind's hand-set ones, ``MPCSpec.hand_margins``), ``"tube"`` (the
        scenario's own tube at ``rate_hz``), a margins file's path, or None (no margins).
        """
        return None

    def margins_file(self) -> str | None:
        """The margins file :meth:`margins_source` names (None: hand, the tube or none)."""
        source = self.margins_source()
        return None if source in (None, "hand", "tube") else source

    def resolve_margins_file(self, base: Path) -> Path | None:
        """Makes a margins file named relative to ``base`` absolute; returns it (None: none)."""
        return None

    def input_margin_key(self) -> str:
        """The key path of the hand-set input margin (named in its problems)."""
        return "mpc.margins"

    def solver_choice(self) -> tuple[str, dict] | None:
        """(back-end, options) the set-up checks try on a tiny NLP; None: nothing to try."""
        return None

    def solver_choices(self) -> list[tuple[str, dict]]:
        """Every (back-end, options) the kind builds, for the set-up checks.

        Default: :meth:`solver_choice`'s.
        """
        choice = self.solver_choice()
        return [] if choice is None else [choice]

    def resolves_on_impact(self) -> bool:
        """Whether the loop re-solves right after a guard event."""
        return True


class MarginsSettings(MPCKindSettings):
    """An MPC kind with a ``margins`` field: ``"hand"``, ``"tube"`` or a margins file.

    The kind declares the field (its default and description are its own).
    """

    @field_validator("margins", check_fields=False)
    @classmethod
    def _named(cls, value: Any) -> Any:
        """An empty ``margins``: no file (it would name the scenario's directory)."""
        if isinstance(value, str) and not value.strip():
            raise ValueError('empty: give "hand", "tube" or a margins file\'s path')
        return value

    def margins_source(self) -> str:
        """``mpc.margins``: "hand", "tube" or a margins file."""
        return self.margins

    def resolve_margins_file(self, base: Path) -> Path | None:
        """A margins file named relative to ``base`` made absolute (None: hand or tube)."""
        if self.margins in ("hand", "tube"):
            return None
        file = Path(self.margins).expanduser()
        file = (file if file.is_absolute() else base / file).resolve()
        self.margins = str(file)
        return file
