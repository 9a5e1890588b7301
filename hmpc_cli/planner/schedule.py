"""A given mode schedule as the plan (any system).

The scenario names the domain sequence D_0..D_S, the guards G_1..G_S between them and
the time spent in D_0..D_{S-1}; the planner hands that schedule to the fixed-mode MPC
unchanged. The schedule's clock starts at the first plan: a later call (a replanning
policy) drops the domains whose scheduled end has passed and shortens the current one,
and lets a contact that came early count when it changed the mode (the plant already in
the next scheduled domain's mode). The planner sees the mode, not the contacts: an early
contact through a guard into the same mode (the ball's floor and wall) is not seen, and
its domain is kept until its scheduled end. It plans nothing and rolls nothing out: no
initial guess (the MPC starts from the held current state).
"""

from __future__ import annotations

import time
from typing import Literal

from pydantic import ConfigDict, Field, field_validator, model_validator

from hmpc_cli.core.kinds import PlannerSettings
from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import ModeSchedule, PlannerResult
from hmpc_cli.core.registry import PlannerSpec
from hmpc_cli.core.settings_types import FiniteFloat


class ScheduleSettings(PlannerSettings):
    """A given domain/guard schedule with durations, by name."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["schedule"] = Field("schedule", description="fly a given mode schedule")
    modes: list[str] = Field(min_length=1, description="domain sequence D_0..D_S by mode "
                             "name (D_0: the system's initial mode, where the plant starts; "
                             "D_S: its final mode)")
    guards: list[str] = Field(default_factory=list, description="guards G_1..G_S by name "
                              "(G_j leads from D_{j-1} to D_j)")
    durations: list[FiniteFloat] = Field(
        default_factory=list, description="time spent in D_0..D_{S-1} [s] (D_S: the rest)")

    @field_validator("durations")
    @classmethod
    def _positive(cls, v: list[float]) -> list[float]:
        bad = [i for i, d in enumerate(v) if d <= 0.0]
        if bad:
            raise ValueError(f"durations must be > 0 s (index {bad[0]}: {v[bad[0]]:g})")
        return v

    @model_validator(mode="after")
    def _lengths(self) -> ScheduleSettings:
        s = len(self.guards)
        if len(self.modes) != s + 1 or len(self.durations) != s:
            raise ValueError(f"a schedule of {s} guards needs {s + 1} modes and {s} "
                             f"durations (got {len(self.modes)} modes, "
                             f"{len(self.durations)} durations)")
        return self

    def system_problems(self, system: HybridSystem) -> list[str]:
        """``planner.key: reason`` lines where the schedule does not fit ``system``.

        Unknown mode or guard names, a guard that does not lead from the domain before it
        to the domain after it, and a schedule that does not start in the system's initial
        mode (where the plant starts) or end in its final mode.
        """
        modes = [m.name for m in system.modes]
        guards = {g.name: g for g in system.guards}
        out = [f"planner.modes[{i}]: unknown mode {m!r} (the system has {modes})"
               for i, m in enumerate(self.modes) if m not in modes]
        for i, end, mode in ((0, "initial", system.initial_mode),
                             (len(self.modes) - 1, "final", system.final_mode)):
            if self.modes[i] in modes and self.modes[i] != mode:
                out.append(f"planner.modes[{i}]: {self.modes[i]!r} is not the system's {end} "
                           f"mode {mode!r} (a schedule runs from the initial mode, where the "
                           "plant starts, to the final one)")
        for j, name in enumerate(self.guards):
            g = guards.get(name)
            if g is None:
                out.append(f"planner.guards[{j}]: unknown guard {name!r} (the system has "
                           f"{sorted(guards)})")
            elif (g.source, g.target) != (self.modes[j], self.modes[j + 1]):
                out.append(f"planner.guards[{j}]: guard {name!r} leads from {g.source!r} to "
                           f"{g.target!r}, not from {self.modes[j]!r} to "
                           f"{self.modes[j + 1]!r}")
        return out


class SchedulePlanner:
    """Hands the scenario's mode schedule to the fixed-mode MPC.

    Args:
        system: the hybrid system (the names are resolved against it).
        settings: the schedule by name.

    Raises:
        ValueError: the schedule does not fit the system (``planner.key: reason`` lines).
    """

    def __init__(self, system: HybridSystem, settings: ScheduleSettings):
        problems = settings.system_problems(system)
        if problems:
            raise ValueError("\n".join(problems))
        self.modes = tuple(system.mode_index(m) for m in settings.modes)
        self.guards = tuple(system.guard_index(g) for g in settings.guards)
        self.durations = tuple(float(d) for d in settings.durations)
        self.final = system.mode_index(system.final_mode)
        self.start: float | None = None  # simulated time of the first plan [s]

    def schedule_at(self, t: float, mode: int) -> tuple[ModeSchedule | None, str]:
        """The rest of the schedule at time t [s] with the plant in ``mode``.

        Returns:
            (schedule, note): the schedule stamped t (None if the plant is not where the
            schedule is at t; the note says why).
        """
        if self.start is None:
            self.start = t
        end, k = self.start, 0
        for d in self.durations:  # drop the domains whose scheduled end has passed
            if end + d > t:
                break
            end, k = end + d, k + 1
        if k < len(self.durations) and self.modes[k] != mode and self.modes[k + 1] == mode:
            end, k = end + self.durations[k], k + 1  # the contact came early
        if self.modes[k] != mode:
            return None, (f"the plant is in mode {mode}, the schedule has mode "
                          f"{self.modes[k]} at t = {t:.4g} s")
        durations = list(self.durations[k:])
        if durations:
            durations[0] = max(end + durations[0] - t, 0.0)
        return ModeSchedule(self.modes[k:], self.guards[k:], tuple(durations), float(t)), ""

    def plan(self, t: float, x, mode: int, solve=None) -> PlannerResult:
        """The given schedule from time t [s] (x and ``solve`` are not used)."""
        start = time.perf_counter()
        schedule, note = self.schedule_at(t, int(mode))
        reached = schedule is not None and schedule.modes[-1] == self.final
        return PlannerResult(schedule, None, float("nan"), reached,
                             time.perf_counter() - start, 0, note)


PLANNER = PlannerSpec(kind="schedule", settings=ScheduleSettings,
                      make=lambda system, settings, seed: SchedulePlanner(system, settings))
