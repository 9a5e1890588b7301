"""The fixed-mode MPC behind the stack contract on the chain transcription.

The MPC kind ``fixed_mode`` owns its node schedule.

Given the latest :class:`~hmpc_cli.core.messages.ModeSchedule` and the guard events since its
previous solve, it

* installs a newly planned schedule (durations rounded up to whole nodes, the planner's
  rollout as the initial guess), or reports one its chain cannot hold as a rejected plan;
* applies the paper's impact rule to each new event (:meth:`ModeSchedule.after_event`):
  a scheduled impact drops the current domain, virtual node included, and its remaining
  nodes move to the final domain (:meth:`~hmpc_cli.mpc.chain.layout.NodeSchedule.on_impact`);
* shifts the nodes elapsed since its previous solve (or since the last such impact) from
  the current domain to the final domain, the part of an interval not moved carried to
  the next solve (node shifting, paper Sec. III);
* solves on the NLP that fits the node schedule (the final domain's own once no switch
  is left).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import (
    AHEAD, SCHEDULED, ConstraintMargins, GuardEvent, ModeSchedule, Plan, SolveStats,
    Trajectory)
from hmpc_cli.mpc.chain.controller import ChainSolver
from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule
from hmpc_cli.mpc.chain.nlp import FixedModeNLPs, MPCSettings
from hmpc_cli.core.registry import MPCSpec


def rejected_plan(t: float, x: np.ndarray, mode: int, schedule: ModeSchedule,
                  reason: str) -> Plan:
    """The plan an MPC returns for a schedule it cannot solve: not solved, not adopted."""
    x = np.asarray(x, dtype=float)
    traj = Trajectory(np.zeros(1), x[None], np.zeros((1, 0)), np.array([mode]),
                      np.zeros(1, dtype=int))
    stats = SolveStats(f"schedule rejected: {reason}", False, 0, 0.0, math.nan, math.inf)
    return Plan(t, traj, stats, schedule, adopt=False)


class ChainMPC:
    """Fixed-mode MPC over mode schedules on the chain transcription.

    Args:
        system: the controllers' model.
        settings: MPC settings (``rate_hz`` is the re-solve rate the loop keeps).
        nlps: the NLPs, built once per (system, settings) and shared (default: built).
    """

    def __init__(self, system: HybridSystem, settings: MPCSettings,
                 nlps: FixedModeNLPs | None = None) -> None:
        self.system, self.s = system, settings
        self.rate_hz = settings.rate_hz
        self.chain = ChainSolver(system, settings, nlps)
        self._schedule: ModeSchedule | None = None  # what the node schedule follows
        self._installed: ModeSchedule | None = None  # the plan as installed
        self._t_shift = 0.0  # nodes are shifted by the time elapsed since this [s]
        self._t_event = -math.inf  # the newest event applied [s]

    def check(self, schedule: ModeSchedule) -> str:
        """Why the chain cannot hold ``schedule`` ('' if it can)."""
        sysm = self.system
        for j, g in enumerate(schedule.guards):
            guard = sysm.guards[g]
            if (sysm.mode_index(guard.source), sysm.mode_index(guard.target)) != \
                    (schedule.modes[j], schedule.modes[j + 1]):
                return f"guard {guard.name} does not lead from domain {j} to domain {j + 1}"
        try:
            ns = NodeSchedule.from_schedule(schedule, self.chain.N, self.chain.dt)
            ChainLayout.build(ns, self.chain.nlps.for_schedule(ns).L)
        except ValueError as exc:
            return str(exc)
        return ""

    def solve(self, t: float, x: np.ndarray, mode: int, schedule: ModeSchedule,
              events: Sequence[GuardEvent] = (), guess: Trajectory | None = None) -> Plan:
        """Solves over ``schedule`` from x (n,) at time t [s] (see the module docstring).

        Returns:
            The plan; its detail a :class:`ChainDetail` (nodes moved by time, flow
            intervals per domain). A schedule the chain cannot hold gives a rejected,
            unsolved plan (``adopt`` False) and leaves the previous one in place.
        """
        dropped = self._apply(events)
        if self._new_plan(schedule):
            reason = self.check(schedule)
            if reason:
                return rejected_plan(t, x, mode, schedule, reason)
            ns = NodeSchedule.from_schedule(schedule, self.chain.N, self.chain.dt)
            self.chain.set_schedule(ns, guess)
            self._schedule, self._installed, shifted = schedule, schedule, 0
            # an event after t is new to this schedule, also one at or before a predicted
            # event told before (the loop withdrew it and planned this schedule anew)
            self._t_shift, self._t_event = t, min(self._t_event, t)
        else:
            n = self.s.shifted_nodes(t - self._t_shift)
            # after an impact (its domain started at the event, not at t) only a move
            shifted = 0 if dropped and not n else self._shift(n)
            self._t_shift = self._shift_clock(t, n)
        plan = self.chain.reoptimize(t, x)
        return replace(plan, schedule=self._schedule, detail=ChainDetail(
            int(shifted), tuple(int(c) for c in self.chain.node_schedule.counts)))

    def stop_at(self, stops: Sequence[tuple[Plan, int]]) -> list[tuple[Plan, int]]:
        """Solves stopped by the solve budget or a contact, each where its time ran out.

        ``stops``: (a plan this MPC returned, the iterations its solver had finished when
        its time ran out). The chain keeps one warm start: only its last solve's counts, whose
        iterate there warm-starts the next solve (the nodes it moved stay moved: time
        passed; see :meth:`ChainSolver.stop_at`).

        Returns:
            (plan, iterations kept) of the solves stopped; the others keep their whole
            solution.
        """
        out = []
        for plan, k in stops:
            kept = self.chain.stop_at(plan, k)
            if kept is not None:
                out.append((plan, kept))
        return out

    def _shift_clock(self, t: float, n: int) -> float:
        """The time [s] the next solve's shift counts from, after n intervals moved at t.

        ``elapsed``: the clock advances by the n whole intervals moved, so the part of an
        interval not moved counts at the next solve (solves at the solver's own pace, not
        one period apart, moved 1 node per 1.2 elapsed and planned the guard later at
        each solve). A solve from before the clock (a compensated solve expecting a
        shorter delay) moves no node and keeps it: no interval moves twice. ``floor``
        (the reference code's rule) drops the rest at every solve, as the reference does.
        """
        if self.s.node_shift == "floor":
            return max(self._t_shift, t)
        return self._t_shift + n * self.s.dt if t > self._t_shift else self._t_shift

    def _new_plan(self, schedule: ModeSchedule) -> bool:
        """Whether ``schedule`` is a newly planned one (else the one the nodes follow).

        Under the reference rule the MPC's own schedule runs ahead of the loop's impact
        rule: a schedule is new only if it is not the installed plan with domains dropped.
        """
        if self.s.schedule_rule == "impact" or self._installed is None:
            return schedule != self._schedule
        plan, k = self._installed, len(self._installed.modes) - len(schedule.modes)
        return not (k >= 0 and schedule.t0 == plan.t0 and schedule.modes == plan.modes[k:]
                    and schedule.guards == plan.guards[k:])

    def _apply(self, events: Sequence[GuardEvent]) -> bool:
        """Applies the schedule rule to the events newer than the last applied one.

        Returns:
            Whether a domain was dropped.
        """
        dropped = False
        for ev in events:
            if ev.t <= self._t_event:
                continue
            self._t_event = ev.t
            if self._schedule is None:
                continue
            after = self._after(ev)
            if after is not None:
                for _ in range(len(self._schedule.modes) - len(after.modes)):
                    self.chain.on_impact()
                self._schedule, dropped = after, True
                self._t_shift = ev.t
        return dropped

    def _after(self, ev: GuardEvent) -> ModeSchedule | None:
        """The schedule after a real event by the rule (None: unchanged)."""
        sched = self._schedule
        if self.s.schedule_rule == "impact":
            after, outcome = sched.after_event(ev.guard, ev.mode_after)
            return after if outcome in (SCHEDULED, AHEAD) else None
        if not sched.guards:
            return None
        final = self.system.mode_index(self.system.final_mode)
        return sched.drop(len(sched.guards) if ev.mode_after == final else 1)

    def _shift(self, n: int) -> int:
        """Moves n elapsed intervals to the final domain; returns how many moved.

        The reference rule first drops every domain whose planned intervals have all
        elapsed (the impact rule keeps one interval while the guard is pending).
        """
        moved = 0
        if self.s.schedule_rule == "reference":
            while self._schedule.guards and n >= self.chain.node_schedule.counts[0]:
                k = self.chain.node_schedule.counts[0]
                self.chain.on_impact()
                self._schedule = self._schedule.drop(1)
                n, moved = n - k, moved + k
        return moved + self.chain.shift(n)


def _problem(system: HybridSystem, settings: MPCSettings,
             margins: ConstraintMargins | None = None) -> FixedModeNLPs:
    return FixedModeNLPs(system, settings, margins)


@dataclass(frozen=True)
class ChainDetail:
    """/mpc/solve detail of the chain MPC: nodes shifted by time, flow intervals per domain.

    Attributes:
        shifted: flow intervals this solve moved from the current domain to the final
            one for the time elapsed (node shifting: since the previous solve or impact,
            the part of an interval not moved then included;
            under ``mpc.schedule_rule = "reference"`` the intervals of the domains it
            dropped too; 0: a newly installed schedule).
        counts: flow intervals per domain D_0..D_S of the node schedule solved on (final
            domain last; their sum is the horizon's N).
    """

    shifted: int
    counts: tuple[int, ...]


def _hand_margins(system: HybridSystem, settings: MPCSettings) -> ConstraintMargins:
    """The hand-set margins of ``mpc.tube_margin`` and ``mpc.input_margin``.

    Raises:
        ValueError: ``mpc.tube_margin: ...`` when a guard-avoid row tightened by it fails
            at x0 already (the NLP's first node: every solve would be softened).
    """
    margins = ConstraintMargins.hand(system, settings.tube_margin, settings.input_margin)
    violated = system.initial_avoid_violations(margins.avoid)
    if violated:
        name, q, kappa = violated[0]
        raise ValueError(
            f"mpc.tube_margin: {settings.tube_margin:g} tightens the guard-avoid row of "
            f"{name} by kappa = {kappa:.4g}, more than its gap at x0 ({q:.4g}): the tightened "
            "problem is infeasible at the initial state (choose a smaller mpc.tube_margin)")
    return margins


MPC = MPCSpec(kind="fixed_mode", settings=MPCSettings, problem=_problem, make=ChainMPC,
              hand_margins=_hand_margins, detail=ChainDetail)
