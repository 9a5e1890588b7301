"""The closed loop: plant, stack (planner + fixed-mode MPC), task and run log, composed.

:func:`build` is the only code that reads a :class:`~hmpc_cli.run.scenario.Scenario`: the
registry gives the system, its task and the planner and MPC plug-ins; each part gets its
own settings. :class:`ClosedLoop` runs the multi-rate loop once for every system:

* every simulator step: low-level command from the current plan, one plant step (events
  located exactly, resets applied, disturbance held), logging;
* at each guard event: the schedule advances by the paper's impact rule
  (:meth:`~hmpc_cli.core.messages.ModeSchedule.after_event`), an off-schedule event forces a
  replan, ``replanning.policy = "on_contact"`` replans at the contact guards;
* the stack reacts after the step (or at the event time when the simulator stops at
  events): replan if needed, else re-solve after an impact, else every MPC period.
  Policy ``periodic`` replans every ``replanning.period``; while no schedule the MPC can
  solve is held, the planner is retried every MPC period.

``sim.latency`` says how the controllers' compute time is charged
(:class:`~hmpc_cli.run.realtime.Latency`): ``"paused"`` (the default, the paper's runs)
pauses simulated time while they compute and a new plan is tracked at once; a fixed
delay L [s], ``"model"`` (iterations x a calibrated cost) or ``"measured"`` (the plan's
measured compute wall time: planner, if it ran for this solve, plus MPC; runs are then
not reproducible) lets a plan computed from the state at t reach the plant at the first
simulator step at or after t + L, the previous plan being tracked until then (the first
plan too, unless ``sim.latency_first = "paused"``: then it is computed with time paused
at t = 0). The delay is logged with each solve (/mpc/solve ``latency``). There is one
solver: a solve that falls due while it is still computing (a period, an impact, a
replanning) waits until it is free and then starts from the state of that moment, so an
MPC rate faster than 1 / L runs at the solver's pace. A solve charged more than
``sim.solve_budget`` is dropped at t + budget (the previous plan tracked on); with
``sim.delay_compensation`` the period's and impacts' solves start from the state
predicted at the plan's arrival (:func:`~hmpc_cli.run.realtime.predict`).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.core.messages import (
    OFF_SCHEDULE, SCHEDULED, ConstraintMargins, GuardEvent, ModeSchedule, Plan)
from hmpc_cli.log.runlog import RunLog, RunResult, versions
from hmpc_cli.run.realtime import Latency, advance, predict
from hmpc_cli.run.setup_checks import built_problems, margins_of
from hmpc_cli.core.stack import FixedModeMPC, Planner, Task

__all__ = ["ClosedLoop", "RunResult", "StackTiming", "build", "versions"]


@dataclass(frozen=True)
class StackTiming:
    """When the stack works, in simulator steps.

    Attributes:
        per_solve: simulator steps per MPC period.
        per_replan: steps per replanning period (policy ``periodic``), else None.
        on_contact: guards whose events trigger a replan (policy ``on_contact``).
        resolve_on_impact: re-solve right after a guard event.
        latency: how compute time is charged before a plan reaches the plant.
    """

    per_solve: int
    per_replan: int | None
    on_contact: frozenset[int]
    resolve_on_impact: bool
    latency: Latency = field(default_factory=Latency)


@dataclass
class _State:
    """What the stack holds between steps."""

    schedule: ModeSchedule | None = None
    usable: bool = False  # the MPC can solve ``schedule``
    guess: object = None
    plan: Plan | None = None
    events: list[GuardEvent] = field(default_factory=list)
    since_solve: int = 0
    need_replan: bool = False
    impact: bool = False
    accepted_plans: int = 0
    last_note: str = ""
    pending: list[tuple[float, Plan]] = field(default_factory=list)  # (due [s], plan)
    planner_wall: float = 0.0  # wall time [s] of the planner call the next solve follows
    free_at: float = 0.0  # sim time [s] the solver is free again (latency charged)
    last_delay: float = 0.0  # the last charged delay [s] (what a prediction expects)
    told: list[int] = field(default_factory=list)  # guards of predicted events told the MPC
    over_budget: int = 0  # solves dropped for their budget


class ClosedLoop:
    """The paper's three layers around the simulated plant, for every system.

    Args:
        plant: simulator, disturbance and low level.
        planner: the hybrid MPC.
        mpc: the fixed-mode MPC.
        timing: the stack's rates and triggers.
        task: success and failure of the run.
        log: the open run log (the caller opens and closes it).
        duration: simulated time [s]; divergence_bound: |x| beyond this ends the run.
        progress: ``progress(step, n_steps, note)`` after every simulator step.
    """

    def __init__(self, plant, planner: Planner, mpc: FixedModeMPC, timing: StackTiming,
                 task: Task, log: RunLog, duration: float, divergence_bound: float,
                 progress: Callable[[int, int, str], None] | None = None) -> None:
        self.plant, self.planner, self.mpc, self.timing = plant, planner, mpc, timing
        self.task, self.log, self.progress = task, log, progress
        self.model = plant.model
        self.final_mode = self.model.mode_index(self.model.final_mode)
        self.n_steps = int(round(duration * plant.rate_hz))
        self.divergence_bound = divergence_bound
        self.st = _State()
        self.res = log.result
        self._predictor = _model_plant(plant) if timing.latency.compensate else None
        if timing.latency.kind == "measured":
            self.res.warnings.append("sim.latency = 'measured': plans reach the plant after "
                                     "their measured compute time, so this run is not "
                                     "reproducible")

    # ---------------------------------------------------------------- run
    def run(self) -> RunResult:
        """Runs to the end of the scenario (or a failure); the log is the caller's.

        A stop signal (:mod:`hmpc_cli.core.signals`, checked after every step and every solve)
        or an exception ends the run where it is: the result and /run/summary get the
        time and state reached and the statistics so far, then the exception propagates
        (:class:`hmpc_cli.core.signals.Interrupted` for a signal or Ctrl-C).
        """
        start = time.perf_counter()
        self.log.open(self.model, self.plant.system)
        x = np.array(self.model.x0, dtype=float)
        mode = self.model.mode_index(self.model.initial_mode)
        self._now = (0.0, x, mode)
        try:
            with signals.deferred():
                x, mode, stopped = self._steps(x, mode)
        except KeyboardInterrupt as exc:
            self._abort(start, signals.as_interrupted(exc), "interrupted")
        except Exception as exc:
            self._abort(start, exc, f"{type(exc).__name__}: {' '.join(str(exc).split())}")
        if not stopped:
            self.res.t_end = self._now[0]
        t = self.res.t_end
        self.log.state(t, x, mode, np.zeros(self.model.n_u), x, self.plant.disturbance(t))
        return self._finish(x, mode, stopped, start)

    def _steps(self, x: np.ndarray, mode: int) -> tuple[np.ndarray, int, bool]:
        """The simulator loop; returns the final (x, mode, stopped by a failure)."""
        self._start(x, mode)
        signals.check()
        for i in range(self.n_steps):
            t = i * self.plant.h
            if self.st.pending:
                self._adopt_due(t)
            u, x_ref = self.plant.command(t, x, mode, self.st.plan, self.plant.h)
            x, mode, stopped = self._step(i, t, x, mode, u, x_ref)
            if stopped:  # the failure set the end time (the step's start for Zeno)
                return x, mode, True
            t = (i + 1) * self.plant.h
            self._now = (t, x, mode)
            self._after_step(i, t, x, mode, i + 1 == self.n_steps)
            if self.progress is not None:
                self.progress(i + 1, self.n_steps, self._note())
            signals.check()
        return x, mode, False

    def _abort(self, start: float, exc: BaseException, reason: str) -> None:
        """Ends an interrupted or crashed run at the last state reached; re-raises ``exc``."""
        t, x, mode = self._now
        if isinstance(exc, signals.Interrupted):
            reason = f"interrupted ({exc.name})"
        with signals.deferred():
            r = self.res
            r.t_end, r.reason = t, reason
            try:
                self.log.state(t, x, mode, np.zeros(self.model.n_u), x,
                               self.plant.disturbance(t))
                self._finish(x, mode, True, start)
            except Exception:
                pass
        raise exc

    def _step(self, i: int, t: float, x: np.ndarray, mode: int, u: np.ndarray,
              x_ref: np.ndarray) -> tuple[np.ndarray, int, bool]:
        """One plant step with logging; returns (x, mode, stopped)."""
        from hmpc_cli.sim.simulator import ZenoError

        w = self.plant.disturbance(t)
        self.log.step(i, t, x, mode, u, x_ref, w)
        try:
            x, mode, _ = self.plant.step(t, x, mode, u, w, self._on_event,
                                         lambda: self.st.plan)
        except ZenoError as exc:
            return x, mode, self._fail(t, f"zeno: {exc}")
        t1 = t + self.plant.h
        if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > self.divergence_bound:
            return x, mode, self._fail(t1, "diverged: non-finite or unbounded state")
        why = self.task.failure(x, mode)
        return x, mode, bool(why) and self._fail(t1, why, diverged=False)

    def _note(self) -> str:
        """The progress line's note: why the stack holds no schedule, if so."""
        if self.st.usable or self.res.planner_calls == 0:
            return ""
        return f"no schedule: {self.st.last_note}" if self.st.last_note else "no schedule"

    # --------------------------------------------------------------- stack
    def _start(self, x: np.ndarray, mode: int) -> None:
        final = ModeSchedule.final(mode, 0.0)
        if mode == self.final_mode and not self.mpc.check(final):
            self.st.schedule, self.st.usable = final, True
        else:
            self._replan(0.0, x, mode, "initial")
        self._solve(0.0, x, mode, "initial")

    def _on_event(self, ev: GuardEvent) -> None:
        """Schedule bookkeeping and contact triggers at a guard event (time ev.t)."""
        st, tm = self.st, self.timing
        if st.told and st.told[0] == ev.guard:
            st.told.pop(0)  # predicted and told the MPC at its last solve
        else:
            st.events.append(ev)
        scheduled = False
        if st.schedule is None:
            st.need_replan |= ev.mode_after != self.final_mode
        else:
            after, outcome = st.schedule.after_event(ev.guard, ev.mode_after)
            scheduled = outcome == SCHEDULED
            final = ModeSchedule.final(ev.mode_after, ev.t)
            if outcome != OFF_SCHEDULE:
                st.schedule = after
            elif ev.mode_after == self.final_mode and not self.mpc.check(final):
                st.schedule = final
            else:
                st.need_replan = True
            st.usable = not self.mpc.check(st.schedule)
        st.impact = True
        st.need_replan |= ev.guard in tm.on_contact
        self.log.event(ev, self.plant.system, scheduled)
        if self.plant.recompute_at_events:  # react at the event time
            self._react(ev.t, ev.x_after, ev.mode_after)

    def _after_step(self, i: int, t: float, x: np.ndarray, mode: int, last: bool) -> None:
        st, tm = self.st, self.timing
        st.since_solve += 1
        if tm.per_replan is not None and (i + 1) % tm.per_replan == 0:
            st.need_replan = True
        if not st.usable and st.since_solve >= tm.per_solve:
            st.need_replan = True  # no schedule the MPC can solve: retry every period
        if last:  # the run ends here: no more controller work
            return
        if (not self._react(t, x, mode) and st.since_solve >= tm.per_solve
                and self._solver_free(t)):
            self._solve(t, x, mode, "period")
            st.since_solve = 0

    def _solver_free(self, t: float) -> bool:
        """Whether the solver is done with its last solve at sim time t [s]."""
        return t >= self.st.free_at - 1e-9

    def _react(self, t: float, x: np.ndarray, mode: int) -> bool:
        """Replans and/or re-solves after events or a replanning trigger.

        Returns:
            Whether the stack worked (the MPC period restarts then).
        """
        st = self.st
        if not self._solver_free(t):
            return False  # the triggers wait for the solver
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
        self.res.planner_calls += 1
        st.planner_wall = result.wall_time
        note = result.note
        if result.schedule is not None:
            note = self.mpc.check(result.schedule)
        accepted = result.schedule is not None and not note
        if accepted:
            st.schedule, st.guess, st.usable = result.schedule, result.trajectory, True
            st.accepted_plans += 1
        else:
            self.res.planner_rejected += 1
            note += "; previous schedule kept" if st.usable else "; no schedule yet"
        st.last_note = note
        self.log.planner(t, reason, result, accepted, note, self.model)

    def _solve(self, t: float, x: np.ndarray, mode: int, reason: str) -> None:
        st, lat = self.st, self.timing.latency
        if not st.usable:
            return
        planned = st.planner_wall > 0.0
        if not lat.charged(reason):
            plan = self.mpc.solve(t, x, mode, st.schedule, st.events, st.guess)
            st.events = []
            self.log.solve(t, plan, reason, self.model)
            if plan.adopt:
                st.plan = plan
        else:
            plan = self._solve_ahead(t, x, mode, reason)
            delay = lat.charge(plan.stats.iterations, plan.stats.wall_time, st.planner_wall,
                               planned)
            if lat.over_budget(delay):
                st.over_budget += 1
                self.log.solve(t, plan, f"{reason} (over budget: dropped)", self.model,
                               lat.budget)
                st.free_at = t + lat.budget
            else:
                self.log.solve(t, plan, reason, self.model, delay)
                st.free_at = t + delay
                if plan.adopt:
                    st.pending.append((t + delay, plan))
            st.last_delay = delay
        st.planner_wall = 0.0
        signals.check()

    def _solve_ahead(self, t: float, x: np.ndarray, mode: int, reason: str) -> Plan:
        """A charged solve, from the state predicted at the plan's arrival if compensating.

        A replan's solves start from the measured state (the planner's schedule starts at
        t); so does a solve whose prediction leaves the schedule or starts off the grid.
        """
        st = self.st
        pred = sched = None
        if self._predictor is not None and reason in ("period", "impact"):
            pred = predict(self._predictor, t, x, mode,
                           self.timing.latency.expected(st.last_delay), self._plan_at)
            sched = advance(st.schedule, pred.events) if pred is not None else None
        if pred is None or sched is None:
            plan = self.mpc.solve(t, x, mode, st.schedule, st.events, st.guess)
            st.told = []
        else:
            plan = self.mpc.solve(pred.t, pred.x, pred.mode, sched,
                                  [*st.events, *pred.events], st.guess)
            st.told = [ev.guard for ev in pred.events]
        st.events = []
        return plan

    def _plan_at(self, t: float) -> Plan | None:
        """The plan the plant tracks over the step at t [s], pending plans included."""
        due = [p for t_due, p in self.st.pending if t_due <= t + 1e-9]
        return due[-1] if due else self.st.plan

    def _adopt_due(self, t: float) -> None:
        """Tracks the newest pending plan due at step time t [s]; older ones are dropped.

        A plan is due at the first simulator step at or after its solve time + latency
        (1e-9 s of rounding allowed: t is a step count times the step).
        """
        pending = self.st.pending
        due = [k for k, (t_due, _) in enumerate(pending) if t_due <= t + 1e-9]
        if due:
            self.st.plan = pending[due[-1]][1]
            del pending[: due[-1] + 1]

    # ------------------------------------------------------------ the end
    def _fail(self, t: float, reason: str, diverged: bool = True) -> bool:
        """Ends the run early as failed (``diverged``: numerically, else by the task)."""
        self.res.diverged, self.res.reason, self.res.t_end = diverged, reason, t
        return True

    def _finish(self, x: np.ndarray, mode: int, stopped: bool, start: float) -> RunResult:
        r = self.res
        verdict = self.task.verdict(x, mode)
        r.x_end = [float(v) for v in x]
        r.mode_end = self.model.modes[mode].name
        r.final_error = verdict.error
        r.success = not stopped and verdict.success
        if not r.reason:
            r.reason = verdict.reason
        if self.st.over_budget:
            r.warnings.append(f"{self.st.over_budget} solves charged more than the budget "
                              f"sim.solve_budget = {self.timing.latency.budget:g} s were "
                              "dropped (the previous plan tracked on)")
        if r.planner_calls and not self.st.accepted_plans:
            r.warnings.append(f"the planner never found a schedule ({r.planner_calls} "
                              f"calls; last: {self.st.last_note})")
        r.wall_time = time.perf_counter() - start
        self.log.summary(r)
        return r


# ------------------------------------------------------------------ composition
_PROBLEMS: dict[str, object] = {}


def build(scenario, log: RunLog,
          progress: Callable[[int, int, str], None] | None = None) -> ClosedLoop:
    """Composes the closed loop of a validated scenario (the only reader of a Scenario).

    The MPC's NLPs are built once per process per (system, MPC settings, margins) and
    shared.

    Raises:
        hmpc_cli.core.registry.PluginError: a plug-in fails to build (message names it).
        ValueError: settings that do not fit the built system (e.g. unknown guards, a
            margins file that does not fit: ``mpc.margins: ...``).
    """
    from hmpc_cli.sim.disturbance import make_disturbance
    from hmpc_cli.lowlevel import LowLevelController
    from hmpc_cli.run.plant import Plant
    from hmpc_cli.core.registry import build_system, plugin_call, registry
    from hmpc_cli.sim.simulator import HybridSimulator

    sc, reg = scenario, registry()
    spec = reg.system(sc.system.name)
    model = build_system(sc.system)
    world = sc.plant_params()
    system = build_system(world) if sc.plant else model
    s = sc.sim
    dist = make_disturbance(sc.disturbance.kind, n_w=model.n_w, duration=s.duration,
                            magnitude=sc.disturbance.magnitude, hold=sc.disturbance.hold,
                            seed=sc.seed, trial=sc.disturbance.trial)
    plant = Plant(model, system, HybridSimulator(system, s.max_events_per_step,
                                                 s.event_time_tol),
                  dist, LowLevelController(model, sc.lowlevel), s.rate_hz,
                  s.input_at_events == "recompute", s.max_events_per_step)
    margins = margins_of(sc, model)
    problems = built_problems(sc, model, margins)
    if problems:  # before the NLPs are built
        raise ValueError("\n".join(problems))
    mpc, problem = _mpc(sc, model, margins)
    planner = plugin_call(f"planner: {sc.planner.kind!r} failed to build for system "
                          f"{spec.name!r}", reg.planner(sc.planner.kind).make, model,
                          sc.planner, sc.seed)
    task = plugin_call(f"system: the task of {spec.name!r} failed to build", spec.task, world,
                       system)
    log.set_info(sc.name, sc.seed, sc.model_dump(mode="json"), s.rate_hz // s.log_rate_hz,
                 margins.to_dict(model) if margins is not None else None,
                 (sc.planner.kind, sc.mpc.kind),
                 {"planner": reg.planner(sc.planner.kind).detail,
                  "mpc": reg.mpc(sc.mpc.kind).detail}, _build_info(problem),
                 s.log_plan_stride)
    return ClosedLoop(plant, planner, mpc, _timing(sc, model), task, log, s.duration,
                      s.divergence_bound, progress)


def _build_info(problem) -> dict | None:
    """How an MPC problem's NLPs were built (its ``build_info``), JSON-ready, if it says."""
    info = getattr(problem, "build_info", None)
    return dataclasses.asdict(info) if dataclasses.is_dataclass(info) else None


def _mpc(sc, model, margins: ConstraintMargins | None) -> tuple[FixedModeMPC, object]:
    """The MPC controller and its problem (built once per process per system and settings).

    The problem is shared by the runs of one (system, MPC settings, margins). A margins
    file's values go to the plug-in's ``problem`` as a third argument.
    """
    from hmpc_cli.core.registry import plugin_call, registry

    reg = registry()
    mpc_spec = reg.mpc(sc.mpc.kind)
    from_file = margins is not None and margins.source != "hand"
    key = json.dumps([sc.system.model_dump(mode="json"), sc.mpc.model_dump(mode="json"),
                      margins.to_dict(model) if from_file else None], sort_keys=True)
    what = f"mpc: {sc.mpc.kind!r} failed to build for system {sc.system.name!r}"
    if key not in _PROBLEMS:
        extra = (margins,) if from_file else ()
        _PROBLEMS[key] = plugin_call(what, mpc_spec.problem, model, sc.mpc, *extra)
    return plugin_call(what, mpc_spec.make, model, sc.mpc, _PROBLEMS[key]), _PROBLEMS[key]


def _timing(sc, model) -> StackTiming:
    """The stack's timing from the scenario's rates and replanning policy."""
    rp, final = sc.replanning, model.final_mode
    if rp.contact_guards is None:  # every guard but those entering the final domain
        contact = frozenset(i for i, g in enumerate(model.guards)
                            if g.target != final or g.source == final)
    else:
        unknown = set(rp.contact_guards) - {g.name for g in model.guards}
        if unknown:
            raise ValueError(f"replanning.contact_guards: unknown guards {sorted(unknown)}")
        contact = frozenset(model.guard_index(n) for n in rp.contact_guards)
    if rp.policy != "on_contact":
        contact = frozenset()
    per_replan = int(round(rp.period * sc.sim.rate_hz)) if rp.policy == "periodic" else None
    s = sc.sim
    latency = Latency.of(s.latency, s.latency_first, s.latency_model, s.solve_budget,
                         s.delay_compensation)
    return StackTiming(s.rate_hz // sc.mpc.rate_hz, per_replan, contact,
                       sc.mpc.resolves_on_impact(), latency)


def _model_plant(plant):
    """The plant a prediction flies: the controllers' model, no disturbance."""
    from hmpc_cli.sim.simulator import HybridSimulator

    sim = plant.sim if plant.system is plant.model else HybridSimulator(
        plant.model, plant.sim.max_events, plant.sim.time_tol)
    zeros = np.zeros(plant.model.n_w)
    return dataclasses.replace(plant, system=plant.model, sim=sim,
                               disturbance=lambda t: zeros)
