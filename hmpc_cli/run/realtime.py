"""Real time: what the controllers' compute time costs the plant, and how the loop copes.

:class:`Latency` charges each solve a delay before its plan reaches the plant:

* ``paused``: none (simulated time stops while the controllers compute; the paper's runs);
* ``fixed``: a constant delay L [s];
* ``measured``: the measured wall time of the planner call it follows plus the
  controller's whole work for the solve (the prediction, the NLP's set-up, the solve and
  the plan built from it; machine dependent: runs are not reproducible);
* ``model``: ``overhead + per_iteration x iterations`` of the MPC solve (a solve with a
  switch left: ``per_switching_iteration``, its NLP being larger, if set; with ``nodes``
  set, times the plan's nodes / ``nodes``: a larger NLP costs more), plus, for the
  planner call it follows, ``planner`` and each fixed-mode MPC solve the planner made
  itself (a foothold candidate) charged as a solve: a deterministic charge from a
  calibrated cost per iteration (``benchmarks/calibrate_latency.py`` fits the constants
  to measured solves).

A solve that returns a plan the planner has just solved (the foothold planner's chosen
candidate) costs nothing more: its compute time is the planner's.

A ``budget`` [s] bounds a solve: a solve charged more is stopped at t + budget, its
plan dropped and the previous plan (time-indexed, hence shifted) tracked on; the MPC
keeps the iterate its solver had reached then (:meth:`Latency.stopped_solves`). With
``preempt`` a contact that makes the stack work stops the solve in flight (solved from
the state before the contact): its plan is dropped and the stack works at the contact.

Delay compensation (:func:`predict`) solves from the state predicted at the time the
plan will reach the plant: the model (never the true plant) flown with w = 0 through
its resets under the plans the plant will track until then, on the simulator's grid.
The delay it expects is the last charged MPC solve's own compute time (a planner call's
is not a period solve's; none before the first), at most the budget (a solve charged more
never reaches the plant).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from hmpc_cli.core.messages import OFF_SCHEDULE, GuardEvent, ModeSchedule, Plan, PlannerResult

__all__ = ["Latency", "Prediction", "SolverClock", "advance", "predict", "prediction_plant",
           "rebase"]

GRID_TOL = 1e-9  #: a time within this of a simulator step [s] is on the grid


@dataclass(frozen=True)
class Latency:
    """How a solve's compute time is charged to simulated time.

    Attributes:
        kind: ``paused``, ``fixed``, ``measured`` or ``model``.
        delay: the fixed delay [s] (kind ``fixed``).
        overhead: per MPC solve [s] (kind ``model``).
        per_iteration: per NLP iteration [s] (kind ``model``).
        per_switching_iteration: per NLP iteration of a solve with a switch left [s]
            (kind ``model``; None: ``per_iteration``).
        planner: per planner call [s] (kind ``model``).
        nodes: the plan nodes the model's constants hold at; a solve whose plan has n
            nodes is charged n / nodes times them (kind ``model``; None: no scaling).
        first: ``charged`` (the first plan waits its delay too) or ``paused``.
        budget: a solve charged more than this [s] is dropped (None: no budget).
        compensate: solve from the state predicted at the plan's arrival.
        preempt: a contact that makes the stack work stops the solve in flight.
    """

    kind: str = "paused"
    delay: float = 0.0
    overhead: float = 0.0
    per_iteration: float = 0.0
    planner: float = 0.0
    first: str = "charged"
    budget: float | None = None
    compensate: bool = False
    per_switching_iteration: float | None = None
    preempt: bool = False
    nodes: int | None = None

    @classmethod
    def of(cls, latency: str | float, first: str = "charged", model=None,
           budget: float | None = None, compensate: bool = False,
           preempt: bool = False) -> Latency:
        """From the scenario's ``sim.latency`` (a kind or a delay [s]) and its model."""
        if not isinstance(latency, str):
            return cls("fixed", float(latency), first=first, budget=budget,
                       compensate=compensate, preempt=preempt)
        m = model if latency == "model" else None
        return cls(latency, overhead=m.overhead if m else 0.0,
                   per_iteration=m.per_iteration if m else 0.0,
                   planner=m.planner if m else 0.0, first=first, budget=budget,
                   compensate=compensate,
                   per_switching_iteration=m.per_switching_iteration if m else None,
                   preempt=preempt, nodes=m.nodes if m else None)

    def charged(self, reason: str) -> bool:
        """Whether a solve for ``reason`` is charged (``initial`` may be paused)."""
        return self.kind != "paused" and not (reason == "initial" and self.first == "paused")

    def solve_cost(self, plan: Plan, compute: float | None = None) -> float:
        """The compute time [s] one fixed-mode MPC solve is charged (``measured``, ``model``).

        ``measured``: ``compute``, the loop's measured wall time of the whole solve call
        [s] (None: the NLP solver's own, ``plan.stats.wall_time``). ``model``: a schedule
        with a switch left is charged ``per_switching_iteration`` per iteration, if set;
        with ``nodes`` set the charge is scaled by the plan's nodes / ``nodes`` (a plan of
        one node, a rejected schedule's, which solved nothing: unscaled).
        """
        st = plan.stats
        if self.kind == "measured":
            return st.wall_time if compute is None else compute
        if self.kind != "model":
            return 0.0
        switching = plan.schedule is not None and plan.schedule.n_switches > 0
        per = self.per_switching_iteration if switching and \
            self.per_switching_iteration is not None else self.per_iteration
        cost = self.overhead + per * max(int(st.iterations), 0)
        n = plan.nodes
        return cost * (n / self.nodes) if self.nodes and n else cost

    def planner_cost(self, result: PlannerResult) -> float:
        """The compute time [s] one planner call is charged (``measured``, ``model``).

        ``measured``: its wall time (the MPC solves it made included); ``model``:
        ``planner`` plus each of its own MPC solves (``result.mpc_solves``) as a solve.
        """
        if self.kind == "measured":
            return result.wall_time
        if self.kind != "model":
            return 0.0
        return self.planner + sum(self.solve_cost(p) for p in result.mpc_solves)

    def charge(self, plan: Plan, planner: PlannerResult | None = None,
               compute: float | None = None) -> float:
        """The delay [s] of one solve's plan, and of the planner call it follows, if any.

        A plan the planner has already solved (one of ``planner.mpc_solves``: same start
        time and statistics) adds no solve cost: it was returned, not computed again.
        ``compute``: see :meth:`solve_cost`.
        """
        if self.kind == "fixed":
            return self.delay
        if planner is None:
            return self.solve_cost(plan, compute)
        reused = _solved_by(plan, planner)
        return self.planner_cost(planner) + (0.0 if reused else self.solve_cost(plan, compute))

    def expected(self, last_solve: float) -> float:
        """The delay [s] a prediction assumes.

        The fixed delay; else ``last_solve``, the last MPC solve's own compute time [s]
        (no planner call's), at most the budget: a solve charged more is dropped, so no
        plan reaches the plant later than t + budget.
        """
        if self.kind == "fixed":
            return self.delay
        return last_solve if self.budget is None else min(last_solve, self.budget)

    def over_budget(self, delay: float) -> bool:
        """Whether a solve charged ``delay`` [s] is dropped."""
        return self.budget is not None and delay > self.budget + GRID_TOL

    def stopped_solves(self, plan: Plan, planner: PlannerResult | None = None,
                       compute: float | None = None, available: float | None = None
                       ) -> list[tuple[Plan, int]]:
        """Where the budget, or a contact, stopped the solves a plan was charged for.

        ``available`` [s]: the time the solver had instead of the budget (a contact
        stopped it in flight, that long after it started).

        The solves in the order they ran: the planner call's own MPC solves, then
        ``plan``'s unless the planner solved it (:meth:`charge`), after the planner's own
        work. Each gets the iterations it finished within the budget: all of them while
        the charge so far fits, then the iterations of the solve the budget ran out in
        (``model``: the most whose charge, :meth:`solve_cost` of that many, fits what is
        left; else its iterations times what is left / its charge, every iteration
        taking the solve's mean time), and 0 for those after it (never started).

        Returns:
            (solve's plan, iterations finished) pairs; empty without a budget or
            ``available``.
        """
        return [(p, k) for p, k, _ in self._budget_walk(plan, planner, compute, available)]

    def finished_in_time(self, plan: Plan, planner: PlannerResult,
                         compute: float | None = None) -> list[bool]:
        """Whether each of ``planner.mpc_solves`` finished within the budget.

        Its whole charge fitted (:meth:`stopped_solves`' order): a solve never started
        did not finish, whatever its iteration count (0 for a warm start already
        optimal). All True without a budget.
        """
        walk = {id(p): fit for p, _, fit in self._budget_walk(plan, planner, compute)}
        return [walk.get(id(p), True) for p in planner.mpc_solves]

    def _budget_walk(self, plan: Plan, planner: PlannerResult | None,
                     compute: float | None, available: float | None = None
                     ) -> list[tuple[Plan, int, bool]]:
        """Per charged solve, in the order they ran (:meth:`stopped_solves`).

        (solve's plan, iterations finished, its whole charge fitted).
        """
        budget = self.budget if available is None else available
        if budget is None:
            return []
        solves = list(planner.mpc_solves) if planner is not None else []
        if not _solved_by(plan, planner):
            solves.append(plan)
        if self.kind == "fixed":
            costs, used = [self.delay / len(solves)] * len(solves), 0.0
        else:
            costs = [self.solve_cost(p, compute if p is plan else None) for p in solves]
            used = 0.0 if planner is None else (
                self.planner if self.kind == "model" else
                max(planner.wall_time - sum(c for p, c in zip(solves, costs, strict=True)
                                            if p is not plan), 0.0))
        out = []
        for p, cost in zip(solves, costs, strict=True):
            n = max(int(p.stats.iterations), 0)
            left = budget + GRID_TOL - used
            if cost <= left:
                out.append((p, n, True))
            elif self.kind == "model":
                fit = [k for k in range(n + 1)
                       if self.solve_cost(_with_iterations(p, k)) <= left]
                out.append((p, fit[-1] if fit else 0, False))
            else:
                out.append((p, min(int(math.floor(n * max(left, 0.0) / cost + 1e-9)), n)
                            if cost > 0 else 0, False))
            used += cost
        return out


def _with_iterations(plan: Plan, k: int) -> Plan:
    """``plan`` with its statistics' iterations set to k."""
    return replace(plan, stats=replace(plan.stats, iterations=k))


@dataclass
class SolverClock:
    """The one solver's time line when compute time is charged (:class:`Latency`).

    Attributes:
        latency: how compute time is charged.
        pending: plans computed but not yet at the plant: (due [s], solve time [s], plan),
            in order.
        free_at: sim time [s] the solver is free again.
        last_solve: the last charged MPC solve's own compute time [s] (what a prediction
            expects: :meth:`Latency.expected`; 0 before the first).
        planner: the planner call the next solve follows (None: none).
        told: guards of predicted events told the MPC that the plant has not had yet,
            in order.
        over_budget: solves dropped for their budget.
        preempted: solves in flight stopped by a contact with their plan not yet at the
            plant (a solve over budget, or a planner call that found nothing, is not one).
        charges: per charged solve, in order: [solve time [s], charged delay [s], the
            time it kept the solver busy [s]: the delay, the budget if dropped for it, or
            until the contact that stopped it].
        last_charged: the last charged solve's (solve time [s], plan, the planner call
            it followed or None, its measured compute time [s]), or None.
        in_flight: after :meth:`preempt`, how long [s] the solver had run on the last
            charged solve when the contact stopped it (None: it was done).
    """

    latency: Latency = field(default_factory=Latency)
    pending: list[tuple[float, float, Plan]] = field(default_factory=list)
    free_at: float = 0.0
    last_solve: float = 0.0
    planner: PlannerResult | None = None
    told: list[int] = field(default_factory=list)
    over_budget: int = 0
    preempted: int = 0
    charges: list[list[float]] = field(default_factory=list)
    last_charged: tuple | None = None
    in_flight: float | None = None

    def free(self, t: float) -> bool:
        """Whether the solver is done with its last solve at sim time t [s]."""
        return t >= self.free_at - GRID_TOL

    def solved(self, plan: Plan, compute: float) -> None:
        """Notes a solve's own compute time (``compute``: its measured wall time [s]).

        A rejected schedule's plan (no NLP solved) tells nothing of the next solve's; a
        plan the planner solved (a foothold candidate, returned, not solved again) counts
        its own solve's time, not the lookup's.
        """
        if plan.stats.iterations <= 0:
            return
        reused = _solved_by(plan, self.planner)
        self.last_solve = self.latency.solve_cost(plan, None if reused else compute)

    def charge(self, t: float, plan: Plan, compute: float | None = None
               ) -> tuple[bool, float]:
        """Charges a plan solved at t [s]: it waits for the plant, or is dropped.

        ``compute``: the measured wall time of the solve call [s] (:meth:`Latency.charge`).

        Returns:
            (whether it is dropped for its budget: the solver stops at t + budget, the
            compute time it was charged [s]).
        """
        lat = self.latency
        delay = lat.charge(plan, self.planner, compute)
        self.last_charged = (t, plan, self.planner, compute)
        if lat.over_budget(delay):
            self.over_budget += 1
            self.free_at = t + lat.budget
            self.charges.append([t, delay, lat.budget])
            return True, delay
        self.free_at = t + delay
        self.charges.append([t, delay, delay])
        if plan.adopt:
            self.pending.append((t + delay, t, plan))
        return False, delay

    def preempt(self, t: float) -> list[float]:
        """A contact at t [s] stops the solve in flight: its plan (due after t) is dropped.

        The last charged solve, if the solver was still busy with it (its plan pending,
        dropped over the budget or not adopted), is busy until the contact only:
        :attr:`in_flight` says how long it had run (None: it was done).

        Returns:
            The solve times [s] of the plans dropped (empty: the solver was busy with
            work that had no plan for the plant).
        """
        self.in_flight = None
        if self.charges and self.last_charged is not None:
            entry = self.charges[-1]
            if entry[0] == self.last_charged[0] and t < entry[0] + entry[2] - GRID_TOL:
                self.in_flight = max(t - entry[0], 0.0)
        dropped = [t_solve for due, t_solve, _ in self.pending if due > t + GRID_TOL]
        self.pending = [p for p in self.pending if p[0] <= t + GRID_TOL]
        self.free_at = t
        self.preempted += len(dropped)
        for t_solve in dropped:  # busy until the contact
            entry = next(c for c in reversed(self.charges) if c[0] == t_solve)
            entry[2] = min(entry[2], t - t_solve)
        if self.in_flight is not None:  # also dropped over its budget, or not adopted
            self.charges[-1][2] = min(self.charges[-1][2], self.in_flight)
        return dropped

    def busy(self, t: float, cost: float) -> None:
        """Work at t [s] that yields no plan (a planner call that found no schedule).

        It is charged ``cost`` [s], stopped at the budget as a solve is.
        """
        budget = self.latency.budget
        self.free_at = t + (cost if budget is None else min(cost, budget + GRID_TOL))

    def plan_at(self, t: float, current: Plan | None) -> Plan | None:
        """The plan the plant tracks over the step at t [s] (``current`` or a due one)."""
        due = [p for t_due, _, p in self.pending if t_due <= t + GRID_TOL]
        return due[-1] if due else current

    def due(self, t: float) -> Plan | None:
        """The newest pending plan due at step time t [s], taken; older ones dropped.

        A plan is due at the first simulator step at or after its solve time + latency
        (:data:`GRID_TOL` of rounding allowed: t is a step count times the step).
        """
        due = [k for k, (t_due, _, _) in enumerate(self.pending) if t_due <= t + GRID_TOL]
        if not due:
            return None
        plan = self.pending[due[-1]][2]
        del self.pending[: due[-1] + 1]
        return plan

    def heard(self, guard: int) -> bool:
        """Whether the plant's event of ``guard`` was predicted and told the MPC (forgotten)."""
        if self.told and self.told[0] == guard:
            self.told.pop(0)
            return True
        return False

    def warnings(self) -> list[str]:
        """The summary's warnings: dropped solves, and real-time settings time paused ignores."""
        lat, out = self.latency, []
        if self.over_budget:
            out.append(f"{_solves(self.over_budget)} charged more than the budget "
                       f"sim.solve_budget = {lat.budget:g} s {_were(self.over_budget)} "
                       "dropped (the previous plan tracked on)")
        if self.preempted:
            out.append(f"{_solves(self.preempted)} in flight {_were(self.preempted)} stopped "
                       "by a contact (sim.preempt_at_contact; their plans dropped)")
        unused = [key for key, on in (("sim.solve_budget", lat.budget is not None),
                                      ("sim.delay_compensation", lat.compensate),
                                      ("sim.preempt_at_contact", lat.preempt)) if on]
        if lat.kind == "paused" and unused:
            out.append(f"{', '.join(unused)}: no effect with sim.latency = \"paused\" (no "
                       "compute time is charged); set sim.latency to \"model\", "
                       "\"measured\" or a delay [s]")
        return out


def _solved_by(plan: Plan, planner: PlannerResult | None) -> bool:
    """Whether the planner call solved ``plan`` itself (same start time and statistics)."""
    return planner is not None and any(
        p.t0 == plan.t0 and p.stats == plan.stats for p in planner.mpc_solves)


def _solves(n: int) -> str:
    return f"{n} solve" if n == 1 else f"{n} solves"


def _were(n: int) -> str:
    return "was" if n == 1 else "were"


@dataclass(frozen=True)
class Prediction:
    """The model's state at the time a plan will reach the plant.

    Attributes:
        t: that time [s], on the simulator's grid.
        x: the predicted state (n,).
        mode: the predicted mode.
        events: the guard events predicted on the way, in time order.
    """

    t: float
    x: np.ndarray
    mode: int
    events: tuple[GuardEvent, ...]


def predict(plant, t: float, x: np.ndarray, mode: int, delay: float,
            plan_at: Callable[[float], Plan | None],
            contacts: tuple[Sequence[float], Sequence[int]] = ((), ())) -> Prediction | None:
    """Flies ``plant`` (the model's plant: w = 0) from (t, x, mode) to the plan's arrival.

    The arrival is the first simulator step at or after t + ``delay``, where the loop
    adopts a plan; each step tracks ``plan_at(step time)`` as the loop would.

    Args:
        plant: a :class:`~hmpc_cli.run.plant.Plant` of the controllers' model, w = 0.
        t: the solve time [s] (on the grid).
        x: the state (n,) at t.
        mode: the mode at t.
        delay: the delay [s] the plan is expected to take.
        plan_at: step time [s] -> the plan the plant tracks over that step.
        contacts: the plant's guard events up to t, (times [s], guards), for the
            prediction's low level (``lowlevel.past_guard``).

    Returns:
        The prediction, or None when t is not on the grid (a solve at an event time
        inside a step: nothing to predict on the grid from there) or when the model's
        flight chatters (more guard events in a step than ``sim.max_events_per_step``:
        no state to predict).
    """
    from hmpc_cli.sim.simulator import ZenoError

    h = plant.h
    plant.lowlevel.contact_times = list(contacts[0])
    plant.lowlevel.contact_guards = list(contacts[1])
    i0 = round(t / h)
    if abs(i0 * h - t) > GRID_TOL:
        return None
    end = max(i0, math.ceil((t + delay) / h - GRID_TOL))
    events: list[GuardEvent] = []
    w = np.zeros(plant.model.n_w)
    xs, m = np.array(x, dtype=float), int(mode)
    for i in range(i0, end):
        s = i * h
        plan = plan_at(s)
        u, _ = plant.command(s, xs, m, plan, h)
        try:
            xs, m, _ = plant.step(s, xs, m, u, w, events.append, lambda p=plan: p)
        except ZenoError:
            return None
    return Prediction(end * h, xs, m, tuple(events))


def advance(schedule: ModeSchedule, events: Sequence[GuardEvent]) -> ModeSchedule | None:
    """``schedule`` after predicted ``events`` by the impact rule (None: off schedule)."""
    for ev in events:
        schedule, outcome = schedule.after_event(ev.guard, ev.mode_after)
        if outcome == OFF_SCHEDULE:
            return None
    return schedule


def rebase(schedule: ModeSchedule, t: float, start: float) -> ModeSchedule:
    """``schedule`` as planned anew at t [s].

    Its current domain, entered at ``start`` [s], keeps what is left of its planned time
    (none when overdue); the later domains keep theirs.
    """
    durations = schedule.durations
    if durations:
        durations = (max(0.0, durations[0] - max(0.0, t - start)), *durations[1:])
    return ModeSchedule(schedule.modes, schedule.guards, durations, t)


def prediction_plant(plant):
    """The plant a prediction flies: the controllers' model, no disturbance."""
    from hmpc_cli.lowlevel import LowLevelController
    from hmpc_cli.sim.simulator import HybridSimulator

    sim = plant.sim if plant.system is plant.model else HybridSimulator(
        plant.model, plant.sim.max_events, plant.sim.time_tol)
    zeros = np.zeros(plant.model.n_w)
    return replace(plant, system=plant.model, sim=sim, disturbance=lambda t: zeros,
                   lowlevel=LowLevelController(plant.model, plant.lowlevel.settings))
