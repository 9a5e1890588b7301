"""The run's books: what a closed-loop run counts, and nothing it writes.

:class:`RunBooks` is the only producer of a run's :class:`RunResult` (``summary.json``
and /run/summary): contacts per guard, MPC solves and their failures, softened solves,
planner calls and their verdicts, solve and planning times, and, when compute time is
charged, the solves' charges against the MPC period. It does no I/O; the topic
writer (:mod:`hmpc_cli.log.runlog`) writes the log beside it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hmpc_cli.core.machine import cpu_model
from hmpc_cli.core.messages import Plan, PlannerResult
from hmpc_cli.log.topics import RealTime

__all__ = ["SOFTENED_TOL", "RunBooks", "RunResult"]

SOFTENED_TOL = 1e-6  # a solve whose hybrid-constraint slack exceeds this is "softened"
PERIOD_TOL = 1e-9  # a solve busy within this of the MPC period [s] is not late


@dataclass
class RunResult:
    """Outcome of one closed-loop run (what summary.json holds)."""

    scenario: str
    seed: int
    success: bool = False
    final_error: float = float("nan")
    t_end: float = 0.0
    x_end: list = field(default_factory=list)
    mode_end: str = ""
    contacts: int = 0
    contacts_by_guard: dict = field(default_factory=dict)
    solves: int = 0
    solver_failures: int = 0
    failure_statuses: dict = field(default_factory=dict)
    softened_solves: int = 0
    max_slack: float = 0.0
    fallbacks: int = 0
    solve_time_median: float = float("nan")
    solve_time_p95: float = float("nan")
    solve_time_max: float = float("nan")
    planner_calls: int = 0
    planner_rejected: int = 0
    plan_time_median: float = float("nan")
    diverged: bool = False
    reason: str = ""
    wall_time: float = 0.0
    warnings: list = field(default_factory=list)
    cpu: str = field(default_factory=cpu_model)  # the machine's (hmpc_cli.core.machine)
    #: how the charged compute time met the MPC period (None: time paused, or a set-up
    #: that failed; the fields of :class:`hmpc_cli.log.topics.RealTime`)
    real_time: dict | None = None


class RunBooks:
    """The counts of one run.

    Args:
        scenario: the scenario's name; seed: the run's seed.
        guards: the model's guard names (every one in ``contacts_by_guard``, zeros
            included, in this order; a guard of the plant only is added when hit).
    """

    def __init__(self, scenario: str, seed: int, guards: Sequence[str] = ()) -> None:
        self.result = RunResult(scenario, seed, contacts_by_guard={g: 0 for g in guards})
        self.solve_times: list[float] = []
        self.plan_times: list[float] = []
        self.accepted_plans = 0
        self.last_note = ""  # the last planner call's note
        #: failed solves counted from a planner call's own MPC solves (:func:`_solve_key`)
        self._counted: set[tuple] = set()

    def charge_time(self, latency: str, period: float) -> None:
        """Compute time is charged at an MPC period of ``period`` [s].

        ``latency``: ``fixed``, ``measured`` or ``model``. The result gets ``real_time``
        (no solve yet, until :meth:`time_charged`).
        """
        self.result.real_time = _real_time(latency, period, [], 0, 0)

    def time_charged(self, charges: Sequence[tuple[float, float]], dropped: int,
                     preempted: int) -> None:
        """The run's charged solves in ``real_time`` (none without :meth:`charge_time`).

        Args:
            charges: per charged solve, (the compute time charged [s], the time it kept
                the solver busy [s]).
            dropped: solves dropped for their budget.
            preempted: solves in flight a contact stopped.
        """
        rt = self.result.real_time
        if rt is not None:
            self.result.real_time = _real_time(rt["latency"], rt["period"], charges,
                                               dropped, preempted)

    def contact(self, guard: str) -> None:
        """Counts a guard event of the simulated system."""
        r = self.result
        r.contacts += 1
        r.contacts_by_guard[guard] = r.contacts_by_guard.get(guard, 0) + 1

    def planner_call(self, t: float, result: PlannerResult, accepted: bool,
                     note: str) -> None:
        """Counts a planner call, its verdict and the failed MPC solves it reports.

        A planner that solves the MPC itself (the biped's foothold planner solves the
        walking MPC per candidate) returns those solves (``result.mpc_solves``): the
        failed ones count as solver failures, as a failed /mpc/solve does
        (:meth:`count_solve`), once each.
        """
        r = self.result
        r.planner_calls += 1
        r.planner_rejected += not accepted
        self.accepted_plans += bool(accepted)
        self.last_note = note
        self.plan_times.append(result.wall_time)
        for plan in result.mpc_solves:
            if plan is not None and not plan.stats.success:
                self._fail(plan.stats.status)
                self._counted.add(_solve_key(t, plan))

    def planner_revoked(self, note: str) -> None:
        """The last planner call's accepted schedule was dropped with its replan.

        Its MPC solves did not finish within the budget: it counts as rejected after all.
        """
        self.result.planner_rejected += 1
        self.accepted_plans -= 1
        self.last_note = note

    def planner_chosen_within(self, note: str) -> None:
        """The last planner call chose again among its MPC solves finished in time.

        Still accepted, with ``note``.
        """
        self.last_note = note

    def count_solve(self, t: float, plan: Plan) -> None:
        """Counts one fixed-mode MPC solve (a planner's candidate solve only once)."""
        st, r = plan.stats, self.result
        r.solves += 1
        self.solve_times.append(st.wall_time)
        r.fallbacks += bool(st.fallback)
        if not st.success:
            key = _solve_key(t, plan)
            if key in self._counted:  # the planner's candidate solve, counted there
                self._counted.discard(key)
            else:
                self._fail(st.status)
        elif st.slack > SOFTENED_TOL:
            r.softened_solves += 1
            r.max_slack = max(r.max_slack, st.slack)

    def _fail(self, status: str) -> None:
        r = self.result
        r.solver_failures += 1
        r.failure_statuses[status] = r.failure_statuses.get(status, 0) + 1

    def warn(self, message: str) -> None:
        """A warning for the summary."""
        self.result.warnings.append(message)

    def fail(self, t: float, reason: str, diverged: bool) -> None:
        """The run ends early at t [s] (``diverged``: numerically, else by the task)."""
        r = self.result
        r.diverged, r.reason, r.t_end = diverged, reason, t

    def close(self, x_end: Sequence[float], mode_end: str, verdict, stopped: bool,
              wall_time: float) -> RunResult:
        """The run's result: its end, the task's ``verdict`` and the time statistics.

        Args:
            x_end: the final state (n,).
            mode_end: the final mode's name.
            verdict: the task's verdict (``success``, ``error``, ``reason``).
            stopped: the run ended early (a failure or a stop): never a success.
            wall_time: the run's wall time [s].
        """
        r = self.result
        r.x_end = [float(v) for v in x_end]
        r.mode_end = mode_end
        r.final_error = verdict.error
        r.success = not stopped and verdict.success
        if not r.reason:
            r.reason = verdict.reason
        if r.planner_calls and not self.accepted_plans:
            self.warn(f"the planner never found a schedule ({r.planner_calls} calls; last: "
                      f"{self.last_note})")
        r.wall_time = wall_time
        if self.solve_times:
            r.solve_time_median, r.solve_time_p95, r.solve_time_max = _spread(self.solve_times)
        if self.plan_times:
            r.plan_time_median = float(np.median(self.plan_times))
        return r


def _real_time(latency: str, period: float, charges: Sequence[tuple[float, float]],
               dropped: int, preempted: int) -> dict:
    """The fields of :class:`~hmpc_cli.log.topics.RealTime` as a dict (see there)."""
    delays = _spread([c[0] for c in charges]) if len(charges) else (np.nan,) * 3
    late = sum(busy > period + PERIOD_TOL for _, busy in charges)
    return dataclasses.asdict(RealTime(latency, float(period), *delays, len(charges),
                                       int(late), int(dropped), int(preempted)))


def _spread(values: Sequence[float]) -> tuple[float, float, float]:
    """(median, 95th percentile, max) of non-empty ``values``."""
    v = np.asarray(values, dtype=float)
    return float(np.median(v)), float(np.percentile(v, 95)), float(v.max())


def _solve_key(t: float, plan: Plan) -> tuple:
    """What identifies a failed solve: (t [s], the schedule's guards, the status)."""
    guards = tuple(plan.schedule.guards) if plan.schedule is not None else None
    return float(t), guards, plan.stats.status
