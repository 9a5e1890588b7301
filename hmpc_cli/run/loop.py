"""The closed loop: plant, stack (planner + fixed-mode MPC), task, books and log.

:class:`ClosedLoop` runs the multi-rate loop of a prepared run
(:func:`hmpc_cli.run.compose.build`) once for every system:

* every simulator step: low-level command from the current plan, one plant step (events
  located exactly, resets applied, disturbance held), logging;
* at each guard event: the schedule advances by the paper's impact rule
  (:meth:`~hmpc_cli.core.messages.ModeSchedule.after_event`), an off-schedule event forces a
  replan, ``replanning.policy = "on_contact"`` replans at the contact guards;
* the stack reacts after the step (or at the event time when the simulator stops at
  events): replan if needed, else re-solve after an impact, else every MPC period.
  Policy ``periodic`` replans every ``replanning.period``; while no schedule the MPC can
  solve is held, the planner is retried every MPC period. The schedule's bookkeeping and
  these triggers are :class:`~hmpc_cli.run.layers.MPCLayers`'.

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
``sim.solve_budget`` is dropped at t + budget (the previous plan tracked on, the
iterate its solver had reached then the next warm start); with
``sim.preempt_at_contact`` a contact that makes the stack work stops the solve in flight
(its plan dropped) and the stack works at once; with
``sim.delay_compensation`` the period's and impacts' solves start from the state
predicted at the plan's arrival (:func:`~hmpc_cli.run.realtime.predict`). The solver's
time line is a :class:`~hmpc_cli.run.realtime.SolverClock`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.core.messages import GuardEvent
from hmpc_cli.log.books import RunResult
from hmpc_cli.log.runlog import NullWriter, TopicWriter
from hmpc_cli.run.compose import PreparedRun
from hmpc_cli.run.layers import MPCLayers

__all__ = ["ClosedLoop"]


class ClosedLoop:
    """The paper's three layers around the simulated plant, for every system.

    Args:
        run: the prepared run (plant, planner, MPC, timing, task, books).
        log: the topic writer (over a recorder the caller opens and closes).
        progress: ``progress(step, n_steps, note)`` after every simulator step.
    """

    def __init__(self, run: PreparedRun, log: TopicWriter | NullWriter,
                 progress: Callable[[int, int, str], None] | None = None) -> None:
        self.prepared, self.log, self.progress = run, log, progress
        self.plant, self.books, self.model = run.plant, run.books, run.plant.model
        self.n_steps = int(round(run.duration * run.plant.rate_hz))
        self.layers = MPCLayers(run, log)
        #: the input, reference and disturbance of the last step begun (None before it)
        self._applied: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def run(self) -> RunResult:
        """Runs to the end of the scenario (or a failure); the log is the caller's.

        A stop signal (:mod:`hmpc_cli.core.signals`, checked after every step and every solve)
        or an exception ends the run where it is: the result and /run/summary get the
        time and state reached and the statistics so far, then the exception propagates
        (:class:`hmpc_cli.core.signals.Interrupted` for a signal or Ctrl-C).
        """
        start, res = time.perf_counter(), self.books.result
        self.log.open(self.model, self.plant.system)
        x = np.array(self.model.x0, dtype=float)
        mode = self.model.mode_index(self.model.initial_mode)
        self._now = (0.0, x, mode)
        try:
            with signals.deferred():
                signals.check()  # stopped before the first step: the log ends at t = 0
                x, mode, stopped = self._steps(x, mode)
        except KeyboardInterrupt as exc:
            self._abort(start, signals.as_interrupted(exc), "interrupted")
        except Exception as exc:
            self._abort(start, exc, f"{type(exc).__name__}: {' '.join(str(exc).split())}")
        if not stopped:
            res.t_end = self._now[0]
        self._last_state(res.t_end, x, mode)
        return self._finish(x, mode, stopped, start)

    def _steps(self, x: np.ndarray, mode: int) -> tuple[np.ndarray, int, bool]:
        """The simulator loop; returns the final (x, mode, stopped by a failure)."""
        self.layers.start(x, mode)
        signals.check()
        for i in range(self.n_steps):
            t = i * self.plant.h
            self.layers.arrive(t)
            u, x_ref = self.plant.command(t, x, mode, self.layers.plan, self.plant.h)
            w = self.plant.disturbance(t)
            self._applied = (u, x_ref, w)
            self.log.step(i, t, x, mode, u, x_ref, w)
            x, mode, stopped = self._step(t, x, mode, u, w)
            if stopped:  # the failure set the end time (the step's start for Zeno)
                return x, mode, True
            t = (i + 1) * self.plant.h
            self._now = (t, x, mode)
            self.layers.after_step(i, t, x, mode, i + 1 == self.n_steps)
            if self.progress is not None:
                self.progress(i + 1, self.n_steps, self.layers.note())
            signals.check()
        return x, mode, False

    def _step(self, t: float, x: np.ndarray, mode: int, u: np.ndarray,
              w: np.ndarray) -> tuple[np.ndarray, int, bool]:
        """One plant step; returns (x, mode, stopped)."""
        from hmpc_cli.sim.simulator import ZenoError

        start = self._now
        try:
            x, mode, _ = self.plant.step(t, x, mode, u, w, self._on_event,
                                         lambda: self.layers.plan)
        except ZenoError as exc:
            if self._now is not start:  # events of this step were handled (recompute): end
                t, x, mode = self._now  # after the last, as logged and counted
            return x, mode, self._fail(t, f"zeno: {exc}")
        t1 = t + self.plant.h
        if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > self.prepared.divergence_bound:
            return x, mode, self._fail(t1, self._diverged(x, mode))
        why = self.prepared.task.failure(x, mode)
        return x, mode, bool(why) and self._fail(t1, why, diverged=False)

    def _diverged(self, x: np.ndarray, mode: int) -> str:
        """The reason of a state that is not finite or beyond ``sim.divergence_bound``.

        Names the non-finite states (up to 3), else the largest one and the bound, and the
        mode the step ended in.
        """
        names, where = self.model.state_names, self.model.modes[mode].name
        bad = [i for i in range(len(x)) if not np.isfinite(x[i])]
        if bad:
            what = ", ".join(f"{names[i]} = {x[i]}" for i in bad[:3])
            more = f" and {len(bad) - 3} more" if len(bad) > 3 else ""
            return f"diverged: non-finite state ({what}{more}) in mode '{where}'"
        i = int(np.argmax(np.abs(x)))
        return (f"diverged: |{names[i]}| {abs(x[i]):.6g} > "
                f"{self.prepared.divergence_bound:.6g} (sim.divergence_bound) in mode "
                f"'{where}'")

    def _on_event(self, ev: GuardEvent) -> None:
        """A guard event inside a step: the run has reached it, then the stack reacts.

        A stop during the reaction (a re-solve at the event time) ends the run at the
        event, in the state after its reset: the contact is in the log and the counts.
        """
        self._now = (ev.t, ev.x_after, ev.mode_after)
        self.layers.on_event(ev)

    def _last_state(self, t: float, x: np.ndarray, mode: int) -> None:
        """The /sim/state sample at the end: the state reached, with the step's values.

        The input, reference and disturbance of the last step (none is applied after
        it); before any step, no input, the state as its reference and the disturbance
        at t.
        """
        u, x_ref, w = self._applied if self._applied is not None else (
            np.zeros(self.model.n_u), x, self.plant.disturbance(t))
        self.log.state(t, x, mode, u, x_ref, w)

    def _fail(self, t: float, reason: str, diverged: bool = True) -> bool:
        """Ends the run early as failed (``diverged``: numerically, else by the task)."""
        self.books.fail(t, reason, diverged)
        return True

    def _abort(self, start: float, exc: BaseException, reason: str) -> None:
        """Ends an interrupted or crashed run at the last state reached; re-raises ``exc``."""
        t, x, mode = self._now
        if isinstance(exc, signals.Interrupted):
            reason = f"interrupted ({exc.name})"
        with signals.deferred():
            self.books.result.t_end, self.books.result.reason = t, reason
            try:
                self._last_state(t, x, mode)
                self._finish(x, mode, True, start)
            except Exception:
                pass
        raise exc

    def _finish(self, x: np.ndarray, mode: int, stopped: bool, start: float) -> RunResult:
        clock = self.layers.clock
        for warning in [*clock.warnings(), self.plant.lowlevel.warning(),
                        self.layers.warning(self.books.result.t_end)]:
            if warning:
                self.books.warn(warning)
        self.books.time_charged([(delay, busy) for _, delay, busy in clock.charges],
                                clock.over_budget, clock.preempted)
        r = self.books.close(x, self.model.modes[mode].name,
                             self.prepared.task.verdict(x, mode), stopped,
                             time.perf_counter() - start)
        self.log.summary(r)
        return r
