"""The stack contract: what the paper's three layers promise each other.

hybrid MPC (a :class:`Planner`) -> :class:`~hmpc_cli.core.messages.ModeSchedule` ->
fixed-mode MPC (a :class:`FixedModeMPC`) -> :class:`~hmpc_cli.core.messages.Plan` -> low level.
The :class:`Task` says what the run is for (goal, success, failure); it belongs to the
system plug-in, not to the loop. Planner, MPC, low level, tube and run log meet only here
and in :mod:`hmpc_cli.core.messages`; only the closed loop knows the whole stack.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hmpc_cli.core.messages import GuardEvent, ModeSchedule, Plan, PlannerResult, Trajectory

#: ``solve(schedule) -> Plan``: the fixed-mode MPC solved from the planner's state; a
#: planner that ranks candidate schedules by their MPC solution calls it.
SolveFn = Callable[[ModeSchedule], Plan]


class Planner(Protocol):
    """The hybrid MPC: picks the domain/guard sequence (a mode schedule).

    Optional: ``within(result, finished) -> PlannerResult``, called when
    ``sim.solve_budget`` stopped some of a call's own MPC solves (``result.mpc_solves``;
    ``finished[i]``: whether the i-th finished in time): the result the call would have
    returned with only those (``result.iterations``: those they ran within the budget).
    Its schedule, if it is one of the finished solves' and the MPC can solve it,
    replaces the call's; otherwise, as without it, the schedule before the call is kept
    and the planner runs again.
    """

    def plan(self, t: float, x: np.ndarray, mode: int, solve: SolveFn) -> PlannerResult:
        """Plans from state x (n,) in mode ``mode`` at simulated time t [s].

        ``solve`` solves the fixed-mode MPC for a candidate schedule from the same
        (t, x, mode); planners that do not rank by the MPC ignore it. Never raises for
        an unreachable target: returns a result with no schedule and a note.
        """
        ...


class FixedModeMPC(Protocol):
    """The fixed-mode MPC: solves the state-constrained NLP over a mode schedule.

    It owns its transcription's node schedule: it computes the elapsed nodes from
    time, applies the paper's impact rule for the events it is given (once each,
    however often they are passed again) and moves to the final domain's problem
    itself.

    Optional: ``stop_at(stops) -> list[tuple[Plan, int]]``, called right after a
    ``solve`` whose plan is dropped over ``sim.solve_budget``, and when a contact stops
    the solver in flight (``sim.preempt_at_contact``; then possibly again, earlier, for
    a solve stopped at its budget before), with (a plan it returned, the iterations its
    solver had finished then) per solve the plan was charged for: the iterate it held
    there, not its whole solution, must warm-start the next solve. Returns (plan,
    iterations kept) of the solves it stopped; an MPC without it keeps its whole
    solution.
    """

    rate_hz: int

    def check(self, schedule: ModeSchedule) -> str:
        """Why this MPC cannot solve ``schedule`` ('' if it can); never raises."""
        ...

    def solve(self, t: float, x: np.ndarray, mode: int, schedule: ModeSchedule,
              events: Sequence[GuardEvent] = (), guess: Trajectory | None = None) -> Plan:
        """Solves from state x (n,) in mode ``mode`` at time t [s] over ``schedule``.

        Args:
            t: simulated time [s].
            x: measured state, shape (n,).
            mode: the plant's mode.
            schedule: the latest schedule (a new plan, or one advanced by events).
            events: the guard events since the previous solve (older ones are ignored).
            guess: an initial guess for a newly planned schedule (e.g. the rollout).

        Returns:
            The plan. Solver failures, NaN and a schedule the NLP cannot hold are
            reported in ``plan.stats`` (never raised).
        """
        ...


@dataclass(frozen=True)
class Verdict:
    """The task's judgement of a run's end state.

    Attributes:
        success: the task was achieved.
        error: the scalar error a summary and a figure report (e.g. distance to goal).
        reason: 'success' or why not.
    """

    success: bool
    error: float
    reason: str


class Task(Protocol):
    """What a run is for: goal, success and failure (owned by the system plug-in)."""

    goal: np.ndarray

    def failure(self, x: np.ndarray, mode: int) -> str:
        """Why the run must stop now as failed ('' to go on); called every step."""
        ...

    def verdict(self, x: np.ndarray, mode: int) -> Verdict:
        """The run's outcome at its end state x (n,) in mode ``mode``."""
        ...
