"""The public plug-in API: everything a system, planner or fixed-mode MPC plug-in needs.

Import from here only (``from hmpc_cli.plugin import HybridSystem, SystemSpec, ...``): the
names below keep their meaning across releases, wherever hmpc keeps them inside. A plug-in
registers an object under an entry-point group of ``pyproject.toml``:

* ``hmpc.systems``: a :class:`SystemSpec` (settings model, ``build`` -> :class:`HybridSystem`,
  its :class:`Task`, a :class:`Drawing` for the log's 3D scene; a walker's
  :class:`WalkerModel`);
* ``hmpc.planners``: a :class:`PlannerSpec` (settings: a :class:`PlannerSettings`,
  ``make`` -> a :class:`Planner` returning :class:`PlannerResult` with a
  :class:`ModeSchedule`);
* ``hmpc.mpcs``: an :class:`MPCSpec` (settings: an :class:`MPCKindSettings`, ``make`` -> a
  :class:`FixedModeMPC` returning a :class:`Plan` with its :class:`SolveStats` and
  :class:`Trajectory`).

See ``docs/plugins.md`` for one screen per kind.
"""

from __future__ import annotations

from hmpc_cli.core.drawing import Ball, Drawing, Polyline, Rgba, circle
from hmpc_cli.core.kinds import KindSettings, MarginsSettings, MPCKindSettings, PlannerSettings
from hmpc_cli.core.hybrid import (
    RESERVED_NAMES, Guard, HybridSystem, Mode, NumericSystem, Terrain, rk4_expr)
from hmpc_cli.core.messages import (
    ConstraintMargins, GuardEvent, ModeSchedule, Plan, PlannerResult, SolveStats, Trajectory)
from hmpc_cli.core.numeric import compile_numpy
from hmpc_cli.core.registry import (
    CAPABILITIES, MPCSpec, PlannerSpec, PluginError, Requirement, SystemSpec)
from hmpc_cli.core.settings_types import BoundedInt, FiniteFloat, LargeFloat, StrictBool
from hmpc_cli.core.stack import FixedModeMPC, Planner, SolveFn, Task, Verdict
from hmpc_cli.core.tasks import ReachGoal
from hmpc_cli.core.walker import WalkerModel

__all__ = [
    "CAPABILITIES", "RESERVED_NAMES", "Ball", "BoundedInt", "ConstraintMargins", "Drawing",
    "FiniteFloat", "FixedModeMPC", "Guard", "GuardEvent", "HybridSystem", "KindSettings",
    "LargeFloat", "MPCKindSettings", "MPCSpec", "MarginsSettings", "Mode", "ModeSchedule",
    "NumericSystem", "Plan", "Planner", "PlannerResult", "PlannerSettings", "PlannerSpec",
    "PluginError", "Polyline", "ReachGoal", "Requirement", "Rgba", "SolveFn", "SolveStats",
    "StrictBool", "SystemSpec", "Task", "Terrain", "Trajectory", "Verdict", "WalkerModel",
    "circle", "compile_numpy", "rk4_expr",
]
