"""The paper's two MPC layers at run time: when each works, and what it costs.

:class:`MPCLayers` holds the hybrid MPC (the planner: the domain/guard schedule) and the
fixed-mode MPC (the plan over it) between simulator steps: the schedule's bookkeeping at
each guard event (the paper's impact rule,
:meth:`~hmpc_cli.core.messages.ModeSchedule.after_event`), the triggers (an off-schedule
event, a contact under ``replanning.policy = "on_contact"``, a replanning period, an
impact, an MPC period), and, when compute time is charged, the solver's time line
(:class:`~hmpc_cli.run.realtime.SolverClock`) with delay compensation. It counts in the
run's books and writes the planner's and the MPC's topics.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.core.messages import OFF_SCHEDULE, SCHEDULED, GuardEvent, ModeSchedule, Plan
from hmpc_cli.log.runlog import NullWriter, TopicWriter
from hmpc_cli.run.compose import PreparedRun
from hmpc_cli.run.realtime import SolverClock, advance, predict, prediction_plant, rebase

__all__ = ["MPCLayers"]


@dataclass
class _LayerState:
    """What the layers hold between steps."""

    schedule: ModeSchedule | None = None
    domain_start: float = 0.0  # when the plant entered ``schedule``'s current domain [s]
    usable: bool = False  # the MPC can solve ``schedule``
    guess: object = None
    plan: Plan | None = None
    events: list[GuardEvent] = field(default_factory=list)
    since_solve: int = 0
    need_replan: bool = False
    impact: bool = False
    preempted: list[float] = field(default_factory=list)  # solve times [s] a contact stopped
    stopped: str = ""  # where the contact stopped the solver in flight (a reason's note)
    planned: bool = False  # a planner call's schedule was accepted once
    lost_at: float | None = None  # when a contact used up the last usable schedule [s]
    rejected_since: int = 0  # planner calls that found none since then
    #: the schedule state the last accepted replan replaced (schedule, guess, usable,
    #: planned, lost_at, domain_start), for its solve's charge (None: none since the
    #: last planner call, or revoked)
    before_replan: tuple | None = None
    #: the last planner call's /planner/plan, written with its solve (t, reason, result,
    #: accepted, note)
    planner_record: tuple | None = None


#: appended to the reason of a solve dropped for its budget (``sim.solve_budget``)
OVER_BUDGET = " (over budget: dropped)"
#: appended to the reason of the solve a contact started after stopping solves in flight
PREEMPTED = " (after a contact stopped the solve of t = {} s: dropped)"
#: appended to the reason of a replan dropped for its budget whose planner's own MPC
#: solves did not all finish within it (the planner's choice was never made)
REVOKED = (" (its schedule dropped with it: the planner's solves did not finish within the "
           "budget)")
#: the /planner/plan note of such a replan
REVOKED_NOTE = ("its MPC solves did not finish within the budget (sim.solve_budget): the "
                "schedule before it, if any, is kept, the planner runs again")
#: appended to the reason of such a replan whose planner chose again among the solves that
#: finished (its optional ``within``)
WITHIN = (" (its schedule chosen again among the planner's {} of {} solves finished within "
          "the budget)")
#: the /planner/plan note of that replan
WITHIN_NOTE = ("{} of its {} MPC solves finished within the budget (sim.solve_budget; "
               "those in the order they ran: {}): chosen among those")


class MPCLayers:
    """The hybrid MPC and the fixed-mode MPC of one run, with their triggers.

    Args:
        run: the prepared run (planner, MPC, timing, the plant's model and system, books).
        log: the run's topic writer.
    """

    def __init__(self, run: PreparedRun, log: TopicWriter | NullWriter) -> None:
        self.planner, self.mpc, self.timing = run.planner, run.mpc, run.timing
        self.model, self.system = run.plant.model, run.plant.system
        self.at_events = run.plant.recompute_at_events  # react at the event time
        self.books, self.log = run.books, log
        self.final_mode = self.model.mode_index(self.model.final_mode)
        self.st, self.clock = _LayerState(), SolverClock(run.timing.latency)
        self._predictor = prediction_plant(run.plant) if run.timing.latency.compensate \
            else None
        self._lowlevel = run.plant.lowlevel

    @property
    def plan(self) -> Plan | None:
        """The plan the plant tracks."""
        return self.st.plan

    def arrive(self, t: float) -> None:
        """Step time t [s]: the newest pending plan due now reaches the plant."""
        due = self.clock.due(t)
        if due is not None:
            self.st.plan = due

    def warning(self, t_end: float) -> str:
        """The summary's warning when the run ended without a usable schedule ('' if not).

        A contact used up the last schedule at some time and no planner call found
        another until the end (t_end [s]): the low level tracked the last plan, the MPC
        no longer solved, whatever the run's outcome.
        """
        st = self.st
        if st.usable or st.lost_at is None or st.rejected_since == 0:
            return ""
        calls = "call" if st.rejected_since == 1 else "calls"
        return (f"no usable schedule from t = {st.lost_at:.4f} s to the end (t = {t_end:.4f} "
                f"s): {st.rejected_since} planner {calls} found none (the last: "
                f"{self.books.last_note.rsplit('; ', 1)[0]}); the low level tracked the "
                "last plan")

    def note(self) -> str:
        """Why the layers hold no schedule, if so (for the progress line)."""
        note = self.books.last_note
        if self.st.usable or self.books.result.planner_calls == 0:
            return ""
        return f"no schedule: {note}" if note else "no schedule"

    def start(self, x: np.ndarray, mode: int) -> None:
        """The first schedule (the planner's, unless x starts in the final domain) and plan."""
        final = ModeSchedule.final(mode, 0.0)
        if mode == self.final_mode and not self.mpc.check(final):
            self.st.schedule, self.st.usable = final, True
        else:
            self._replan(0.0, x, mode, "initial")
        self._solve(0.0, x, mode, "initial")

    def on_event(self, ev: GuardEvent) -> None:
        """Schedule bookkeeping and contact triggers at a guard event (time ev.t)."""
        st = self.st
        if not self.clock.heard(ev.guard):  # else predicted and told the MPC already
            st.events.append(ev)
        scheduled = False
        if st.schedule is None:
            st.need_replan |= ev.mode_after != self.final_mode
        else:
            after, outcome = st.schedule.after_event(ev.guard, ev.mode_after)
            scheduled = outcome == SCHEDULED
            final = ModeSchedule.final(ev.mode_after, ev.t)
            if outcome != OFF_SCHEDULE:
                if after != st.schedule:
                    st.domain_start = ev.t
                st.schedule = after
            elif ev.mode_after == self.final_mode and not self.mpc.check(final):
                st.schedule, st.domain_start = final, ev.t
            else:
                st.need_replan = True
            usable, st.usable = st.usable, not self.mpc.check(st.schedule)
            if usable and not st.usable:
                st.lost_at, st.rejected_since = ev.t, 0
        st.impact = True
        st.need_replan |= ev.guard in self.timing.on_contact
        self.books.contact(self.system.guards[ev.guard].name)
        self.log.event(ev, self.system, scheduled)
        if self.at_events:
            self.react(ev.t, ev.x_after, ev.mode_after)

    def after_step(self, i: int, t: float, x: np.ndarray, mode: int, last: bool) -> None:
        """After simulator step i (at t [s], state x in ``mode``): triggers and the period."""
        st, tm = self.st, self.timing
        st.since_solve += 1
        if tm.per_replan is not None and (i + 1) % tm.per_replan == 0:
            st.need_replan = True
        if not st.usable and st.since_solve >= tm.per_solve:
            st.need_replan = True  # no schedule the MPC can solve: retry every period
        if last:  # the run ends here: no more controller work
            return
        if (not self.react(t, x, mode) and st.since_solve >= tm.per_solve
                and self.clock.free(t)):
            self._solve(t, x, mode, "period")
            st.since_solve = 0

    def react(self, t: float, x: np.ndarray, mode: int) -> bool:
        """Replans and/or re-solves after events or a replanning trigger.

        Returns:
            Whether the stack worked (the MPC period restarts then).
        """
        st, clock = self.st, self.clock
        if not clock.free(t):
            if not (clock.latency.preempt and st.impact
                    and (st.need_replan or self.timing.resolve_on_impact)):
                return False  # the triggers wait for the solver
            # a contact: the solve in flight is from the state before it
            st.preempted = clock.preempt(t)
            st.stopped = self._stop_in_flight()
        need_replan, impact = st.need_replan, st.impact
        st.need_replan = st.impact = False
        if need_replan:
            why = "contact" if impact else ("periodic" if st.usable else "retry")
            self._replan(t, x, mode, why)
            self._solve(t, x, mode, "replan")
        elif impact and self.timing.resolve_on_impact:
            self._solve(t, x, mode, "impact")
        else:
            return False
        st.since_solve = 0
        return True

    def _replan(self, t: float, x: np.ndarray, mode: int, reason: str) -> None:
        st = self.st
        result = self.planner.plan(
            t, x, mode, lambda sched: self.mpc.solve(t, x, mode, sched, st.events))
        self.clock.planner = result
        note = result.note
        if result.schedule is not None:
            note = self.mpc.check(result.schedule)
        accepted = result.schedule is not None and not note
        st.before_replan = None
        if accepted:
            st.before_replan = (st.schedule, st.guess, st.usable, st.planned, st.lost_at,
                                st.domain_start)
            st.schedule, st.guess, st.usable = result.schedule, result.trajectory, True
            st.planned, st.lost_at = True, None
            st.domain_start = t
        else:
            st.rejected_since += not st.usable
            note += ("; previous schedule kept" if st.usable else
                     "; no usable schedule (the last one is used up)" if st.planned else
                     "; no schedule yet")
        self.books.planner_call(t, result, accepted, note)
        st.planner_record = (t, reason, result, accepted, note)

    def _write_planner(self) -> None:
        """Writes the last planner call's /planner/plan (held until its solve is charged)."""
        record, self.st.planner_record = self.st.planner_record, None
        if record is not None:
            self.log.planner(*record, self.model)

    def _revoke_replan(self, plan: Plan, compute: float,
                       stops: list[tuple[Plan, int]]) -> str:
        """A dropped replan whose planner's own MPC solves overran the budget.

        ``plan``: the replan's solve, ``compute`` its call [s]. The planner's choice was
        never made in time. A planner with the optional ``within`` chooses again among
        its solves that finished: that schedule, if it is one of theirs and the MPC can
        solve it, replaces the replan's (the plant keeps its plan until the next solve).
        Otherwise, or without it, the schedule state before the replan comes back, the
        planner runs again at the solver's next free step, and the call counts as
        rejected. Either way the call's record logs the iterations its solves ran within
        the budget (``stops``).

        Returns:
            The note for the dropped solve's reason ('' if the choice stands).
        """
        st, planner = self.st, self.clock.planner
        if planner is None or st.before_replan is None or not planner.mpc_solves:
            return ""
        finished = self.clock.latency.finished_in_time(plan, planner, compute)
        if all(finished):
            return ""
        own = {id(p) for p in planner.mpc_solves}
        ran = dataclasses.replace(
            planner, iterations=int(sum(k for p, k in stops if id(p) in own)))
        within = getattr(self.planner, "within", None)
        result = within(ran, finished) if within is not None else None
        kept = [p.schedule for p, done in zip(planner.mpc_solves, finished, strict=True)
                if done]
        if result is not None and result.schedule is not None and \
                any(result.schedule is k or result.schedule == k for k in kept) and \
                not self.mpc.check(result.schedule):
            st.schedule, st.guess = result.schedule, result.trajectory
            note = WITHIN_NOTE.format(len(kept), len(finished), ", ".join(
                str(i + 1) for i, done in enumerate(finished) if done))
            if st.planner_record is not None:
                st.planner_record = (*st.planner_record[:2], result, True, note)
            self.books.planner_chosen_within(note)
            return WITHIN.format(len(kept), len(finished))
        (st.schedule, st.guess, st.usable, st.planned, st.lost_at,
         st.domain_start) = st.before_replan
        st.before_replan, st.need_replan = None, True
        st.rejected_since += not st.usable
        if st.planner_record is not None:
            st.planner_record = (*st.planner_record[:2], ran, False, REVOKED_NOTE)
        self.books.planner_revoked(REVOKED_NOTE)
        return REVOKED

    def _solve(self, t: float, x: np.ndarray, mode: int, reason: str) -> None:
        st, clock = self.st, self.clock
        charged = clock.latency.charged(reason)
        note = (PREEMPTED.format(", ".join(f"{v:.4f}" for v in st.preempted))
                if st.preempted else "") + st.stopped
        # no schedule: a planner call that found none still took its time (a preemption's
        # note waits for the solve that logs it)
        if not st.usable:
            if charged and clock.planner is not None:
                clock.busy(t, clock.latency.planner_cost(clock.planner))
            clock.planner = None
            self._write_planner()
            return
        try:
            self._charge_and_log(t, x, mode, reason, charged, note)
        except BaseException:  # stopped (a signal): the planner call is in the log still
            self._write_planner()
            raise
        clock.planner = None
        signals.check()

    def _charge_and_log(self, t: float, x: np.ndarray, mode: int, reason: str,
                        charged: bool, note: str) -> None:
        """One solve: made, charged, counted, and logged after its planner call's record.

        Dropped over its budget, its solves are stopped there and a replan may be revoked
        (:meth:`_revoke_replan`).
        """
        st, clock = self.st, self.clock
        start = time.perf_counter()
        plan = self._solve_ahead(t, x, mode, reason) if charged else self.mpc.solve(
            t, x, mode, st.schedule, st.events, st.guess)
        compute = time.perf_counter() - start  # the prediction and the solve call
        st.events = []
        self.books.count_solve(t, plan)
        if charged:
            clock.solved(plan, compute)
            dropped, latency = clock.charge(t, plan, compute)
            if dropped:  # never reaches the plant: logged not adopted
                stops = clock.latency.stopped_solves(plan, clock.planner, compute)
                plan, note = dataclasses.replace(plan, adopt=False), \
                    note + self._stop_at_budget(stops) + \
                    self._revoke_replan(plan, compute, stops) + \
                    OVER_BUDGET
            self._write_planner()
            self.log.mpc_solve(t, plan, reason + note, self.model, latency, compute)
            st.preempted, st.stopped = [], ""
        else:
            self._write_planner()
            self.log.mpc_solve(t, plan, reason, self.model, call_time=compute)
            st.plan = plan if plan.adopt else st.plan

    def _stop_at_budget(self, stops: list[tuple[Plan, int]]) -> str:
        """Stops the solves of a plan dropped over its budget where the budget ran out.

        The MPC keeps, of each solve the plan was charged for (a replan's: the planner's
        own MPC solves too), the iterate its solver held when the budget ran out as the
        warm start (``stop_at``); ``stops``:
        :meth:`~hmpc_cli.run.realtime.Latency.stopped_solves`.

        Returns:
            The note for its /mpc/solve reason ('' if every solve keeps its solution).
        """
        return self._stop(stops, "the budget", "warm-starts the next solve")

    def _stop_in_flight(self) -> str:
        """A contact stopped the solver in flight: the MPC keeps its iterate then.

        The last charged solve, if the solver was still busy with it (its plan pending,
        dropped over the budget, whose budget stop this one supersedes, or not adopted),
        stopped after the time it had run (``SolverClock.in_flight``).

        Returns:
            The note for the reason of the solve the contact starts ('' if none).
        """
        clock = self.clock
        if clock.in_flight is None or clock.last_charged is None:
            return ""
        t_solve, plan, planner, compute = clock.last_charged
        stops = clock.latency.stopped_solves(plan, planner, compute,
                                             available=clock.in_flight)
        return self._stop(stops, "the contact", "warm-starts this one",
                          f"the solve of t = {t_solve:.4f} s")

    def _stop(self, stops: list[tuple[Plan, int]], where: str, then: str,
              whose: str = "its solve") -> str:
        """The MPC's ``stop_at`` on ``stops``; the note of the solves it stopped short."""
        stop = getattr(self.mpc, "stop_at", None)
        if stop is None or not stops:
            return ""
        kept = [(p, k) for p, k in stop(stops) if k < p.stats.iterations]
        if not kept:
            return ""
        counts = ", ".join(f"{k} of {p.stats.iterations}" for p, k in kept)
        if len(kept) == 1:
            return (f" (stopped at {where}: {whose} after {counts} iterations, that "
                    f"iterate {then})")
        return (f" (stopped at {where}: {len(kept)} of {whose.replace('solve', 'solves')} "
                f"after {counts} iterations, those iterates {then.replace('starts', 'start')})")

    def _solve_ahead(self, t: float, x: np.ndarray, mode: int, reason: str) -> Plan:
        """A charged solve, from the state predicted at the plan's arrival if compensating.

        A replan's solves start from the measured state (the planner's schedule starts at
        t); so does a solve whose prediction leaves the schedule, gives one the MPC cannot
        solve (a walking MPC's with no guard left), starts off the grid or chatters. The
        MPC is told each predicted event once. When events told it before, which the plant
        has not had, are not predicted again, the MPC holds a schedule the plant has not
        reached: the loop's schedule is planned anew from the solve's time
        (:func:`~hmpc_cli.run.realtime.rebase`), so the MPC installs it on its timing.
        """
        st, clock = self.st, self.clock
        pred = sched = None
        if self._predictor is not None and reason in ("period", "impact"):
            pred = self._predict(t, x, mode)
            sched = advance(st.schedule, pred.events) if pred is not None else None
            if sched is not None and self.mpc.check(sched):
                sched = None
        if sched is None:
            if clock.told:  # the MPC is ahead of the plant: plan its schedule anew
                st.schedule, st.domain_start = rebase(st.schedule, t, st.domain_start), t
            clock.told = []
            return self.mpc.solve(t, x, mode, st.schedule, st.events, st.guess)
        guards, told = [ev.guard for ev in pred.events], clock.told
        new = pred.events[len(told):]
        if guards[:len(told)] != told:  # the MPC is ahead of the plant: as above
            st.schedule = rebase(st.schedule, pred.t, st.domain_start)
            st.domain_start, sched, new = pred.t, advance(st.schedule, pred.events), pred.events
        clock.told = guards
        return self.mpc.solve(pred.t, pred.x, pred.mode, sched, [*st.events, *new], st.guess)

    def _predict(self, t: float, x: np.ndarray, mode: int):
        """The model's state at the plan's expected arrival (None: see ``predict``)."""
        clock, low = self.clock, self._lowlevel
        return predict(self._predictor, t, x, mode, clock.latency.expected(clock.last_solve),
                       lambda s: clock.plan_at(s, self.st.plan),
                       (low.contact_times, low.contact_guards))
