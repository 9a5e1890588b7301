"""Hybrid MPC by foothold choice: which contact surface the next swing lands on.

The hybrid problem of a walking system is a choice among few footholds: at the start and
after each contact the fixed-mode MPC is solved once per candidate surface (through the
``solve`` callback the loop hands the planner, so this module never imports an MPC) and
the best solution is kept (the reference: the largest final hip x). A candidate is a
guard with a contact surface (``HybridSystem.guard_surfaces``: (start, end, height) [m]);
its schedule is one switch through that guard. Needs the system's
:class:`~hmpc_cli.core.walker.WalkerModel`: the stance foot x[stance_index] and, for
``max_hip_x``, ``hip_world``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from pydantic import ConfigDict, Field

from hmpc_cli.core.kinds import PlannerSettings
from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import ModeSchedule, Plan, PlannerResult
from hmpc_cli.core.numeric import compile_numpy
from hmpc_cli.core.registry import PlannerSpec, Requirement
from hmpc_cli.core.settings_types import FiniteFloat, StrictBool
from hmpc_cli.core.stack import SolveFn
from hmpc_cli.core.walker import WalkerModel

Segment = tuple[float, float, float]


class FootholdSettings(PlannerSettings):
    """Candidate enumeration and selection settings."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["footholds"] = Field("footholds", description="foothold candidates "
                                       "ranked by the fixed-mode MPC (walking systems)")
    reach: FiniteFloat = Field(0.45, gt=0.0, description="a segment is a candidate if one of "
                         "its ends lies within this of the stance foot [m]")
    include_current: StrictBool = Field(True, description="the segment under the stance foot "
                                  "is always a candidate")
    ahead_only: StrictBool = Field(True, description="drop segments that end at or behind "
                             "the stance foot")
    criterion: Literal["max_hip_x", "min_cost"] = Field(
        "max_hip_x", description="max_hip_x: largest final hip x (reference); min_cost: "
                                 "lowest MPC cost")


def candidates(stance_x: float, segments: Sequence[Segment],
               settings: FootholdSettings | None = None) -> list[int]:
    """Indices of the candidate segments for a swing from stance-foot x, ascending.

    A segment qualifies if min(|x - start|, |x - end|) <= reach (the reference rule), or
    if it holds the stance foot (``include_current``); with ``ahead_only`` a segment
    ending at or behind x never qualifies.

    Raises:
        ValueError: no segment qualifies (e.g. the foot is beyond the stairs' end).
    """
    s = settings or FootholdSettings()
    out = []
    for i, (start, end, _) in enumerate(segments):
        if s.ahead_only and end <= stance_x:
            continue
        near = min(abs(stance_x - start), abs(stance_x - end)) <= s.reach
        under = s.include_current and start <= stance_x <= end
        if near or under:
            out.append(i)
    if not out:
        ends = f"[{segments[0][0]:g}, {segments[-1][1]:g}]" if segments else "(none)"
        raise ValueError(f"no foothold candidate within reach {s.reach:g} m of the stance "
                         f"foot at x = {stance_x:.4f} m (stairs span {ends})")
    return out


def choose(plans: Sequence[Plan | None], settings: FootholdSettings | None = None,
           hip_x=None) -> int | None:
    """Index of the best successful plan in ``plans``, or None if every one failed.

    Args:
        plans: candidate plans (None: not solved).
        settings: the selection criterion.
        hip_x: plan -> its last hip x in the world [m] (needed for ``max_hip_x``).

    ``min_cost`` reads ``plan.stats.cost``. Ties keep the first. None tells the caller
    to keep its previous plan.

    Raises:
        ValueError: ``max_hip_x`` without ``hip_x``.
    """
    s = settings or FootholdSettings()
    if s.criterion == "max_hip_x" and hip_x is None:
        raise ValueError("choose: the max_hip_x criterion needs hip_x (plan -> hip x [m])")
    best, best_score = None, None
    for i, plan in enumerate(plans):
        if plan is None or not plan.stats.success:
            continue
        score = hip_x(plan) if s.criterion == "max_hip_x" else -float(plan.stats.cost)
        if best_score is None or score > best_score:
            best, best_score = i, score
    return best


class FootholdPlanner:
    """Ranks the contact surfaces within reach by the fixed-mode MPC's solutions.

    Args:
        system: the controllers' model (``guard_surfaces`` and ``walker``).
        settings: candidate enumeration and selection.

    Raises:
        ValueError: the system has no :class:`~hmpc_cli.core.walker.WalkerModel`.
    """

    def __init__(self, system: HybridSystem, settings: FootholdSettings) -> None:
        if not isinstance(system.walker, WalkerModel):
            raise ValueError(f"the footholds planner needs a WalkerModel: system "
                             f"{system.name!r} has none (HybridSystem.walker)")
        self.system, self.s = system, settings
        self.guards = sorted(system.guard_surfaces)
        self.surfaces = [system.guard_surfaces[g] for g in self.guards]
        self.walker = system.walker
        self._stance_x = system.walker.stance_index.start
        self._hip = compile_numpy(system.walker.hip_world) \
            if settings.criterion == "max_hip_x" else None

    def _hip_x(self, plan: Plan) -> float:
        return float(self._hip(plan.traj.x[-1])[0][0])

    def plan(self, t: float, x: np.ndarray, mode: int, solve: SolveFn) -> PlannerResult:
        """Solves every candidate from (t, x, mode) and keeps the best plan's schedule.

        The result's schedule is the chosen plan's (one switch through the chosen guard,
        planned at t); its detail (:class:`FootholdsDetail`) lists every candidate's
        solve, with the planned touchdown and final hip from the plan's trajectory.
        """
        start = time.perf_counter()
        stance_x = float(np.asarray(x, dtype=float)[self._stance_x])
        try:
            cand = [self.guards[i] for i in candidates(stance_x, self.surfaces, self.s)]
        except ValueError as exc:
            return PlannerResult(None, None, math.nan, False, time.perf_counter() - start, 0,
                                 str(exc), FootholdsDetail(()))
        plans = [solve(ModeSchedule((mode, mode), (g,), (math.nan,), t)) for g in cand]
        best = choose(plans, self.s, self._hip_x)
        detail = FootholdsDetail(tuple(self._candidate(g, p)
                                       for g, p in zip(cand, plans, strict=True)))
        solved = tuple(plans)
        chosen = plans[best] if best is not None else None
        iters = int(sum(p.stats.iterations for p in plans))
        wall = time.perf_counter() - start
        if chosen is None:
            return PlannerResult(None, None, math.nan, False, wall, iters,
                                 "every candidate failed", detail, solved)
        return PlannerResult(chosen.schedule, chosen.traj, chosen.stats.cost, True, wall,
                             iters, "", detail, solved)

    def within(self, result: PlannerResult, finished: Sequence[bool]) -> PlannerResult:
        """``result`` had the call stopped with only some candidates solved.

        ``finished[i]``: whether ``result.mpc_solves[i]`` finished in time (a solve time
        budget stopped the others): the best of those keeps its schedule, the detail
        still lists every candidate.
        """
        plans = [p if done else None
                 for p, done in zip(result.mpc_solves, finished, strict=True)]
        best = choose(plans, self.s, self._hip_x)
        if best is None:
            return replace(
                result, schedule=None, trajectory=None, cost=math.nan,
                reached_final=False, note=f"no candidate solved in time ({sum(finished)} of "
                                          f"{len(plans)} finished)")
        chosen = plans[best]
        return replace(result, schedule=chosen.schedule, trajectory=chosen.traj,
                       cost=chosen.stats.cost, reached_final=True, note="")

    def _candidate(self, guard: int, plan: Plan) -> Candidate:
        """One candidate's row: its solve, planned touchdown and final hip (x, y) [m].

        The touchdown is the swing foot at the last node before the impact (segment 0).
        """
        st, x = plan.stats, plan.traj.x
        pre = int(np.flatnonzero(np.asarray(plan.traj.seg) == 0)[-1])
        touchdown = np.asarray(self.walker.swing_foot_world(x[pre])).ravel()
        hip = np.asarray(self.walker.hip_world(x[-1])).ravel()
        return Candidate(guard, self.system.guards[guard].name, st.status, st.success,
                         st.iterations, st.wall_time, st.cost,
                         tuple(float(v) for v in hip), tuple(float(v) for v in touchdown))


@dataclass(frozen=True)
class Candidate:
    """One foothold candidate's solve (the /planner/plan detail).

    Attributes:
        segment: the candidate's guard index (/run/info ``guard_names``), whose contact
            surface the swing lands on.
        guard_name: that guard's name.
        status: the fixed-mode MPC's solver status.
        success: the walking MPC's solve succeeded, as /mpc/solve ``success`` says
            (per ``mpc.solver``: "rti" counts a finite point at its iteration limit).
        iterations: solver iterations.
        wall_time: measured solve time [s].
        cost: the solve's optimal cost (absent: none).
        final_hip: the hip's (x, y) in the world at the plan's last node [m] (absent
            only in older logs).
        touchdown: the swing foot's (x, y) in the world at the plan's last node before
            the impact [m] (absent only in older logs).
    """

    segment: int
    guard_name: str
    status: str
    success: bool
    iterations: int
    wall_time: float
    cost: float
    final_hip: tuple[float, ...] | None = None
    touchdown: tuple[float, ...] | None = None


@dataclass(frozen=True)
class FootholdsDetail:
    """/planner/plan detail: every candidate's solve.

    Attributes:
        candidates: one per candidate surface within reach, in guard order (empty: none
            within reach, the call's ``note`` says why).
    """

    candidates: tuple[Candidate, ...]


PLANNER = PlannerSpec(
    kind="footholds", settings=FootholdSettings,
    make=lambda system, settings, seed: FootholdPlanner(system, settings),
    needs=frozenset({"guard_surfaces", WalkerModel}), detail=FootholdsDetail,
    requires=(Requirement("replanning.policy", "on_contact",
                          "the foothold of every swing is chosen at its contact"),),
)
