"""The ball's controller stack: CEM hybrid planner, fixed-mode MPC, node shifting.

After each simulator step (see :class:`hmpc_cli.loop_core.LoopCore`): each guard event
advances the schedule (node shifting on impact), may trigger the planner (policy
``on_contact``) and a re-solve; every MPC period the elapsed nodes are shifted and the MPC
re-solved; policy ``periodic`` replans every ``replanning.period``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hmpc_cli.loop_core import LoopCore, RunResult, versions
from hmpc_cli.messages import PlannerResult
from hmpc_cli.mpc.controller import FixedModeMPC
from hmpc_cli.mpc.layout import NodeSchedule
from hmpc_cli.planner.cem import CrossEntropyPlanner
from hmpc_cli.scenario import Scenario
from hmpc_cli.sim import Event
from hmpc_cli.systems import build_system

__all__ = ["LayeredLoop", "RunResult", "make_loop", "versions"]


def make_loop(scenario: Scenario, recorder, mpc=None) -> LoopCore:
    """The closed loop of the scenario's system (ball: :class:`LayeredLoop`, biped:
    :class:`hmpc_cli.loop_walking.WalkingLoop`); ``mpc``: a prebuilt controller to reuse."""
    if scenario.system.name == "biped":
        from hmpc_cli.loop_walking import WalkingLoop

        return WalkingLoop(scenario, recorder, mpc=mpc)
    return LayeredLoop(scenario, recorder, mpc=mpc)


class LayeredLoop(LoopCore):
    """The three layers of the paper around the simulator, for mode-schedule systems."""

    def __init__(self, scenario: Scenario, recorder, progress: Callable | None = None,
                 mpc: FixedModeMPC | None = None) -> None:
        sc = scenario
        super().__init__(sc, recorder, build_system(sc.system), progress=progress)
        self.planner = CrossEntropyPlanner(self.system, sc.planner, run_seed=sc.seed)
        self.mpc = mpc or FixedModeMPC(self.system, sc.mpc)
        self.final_mode = self.system.mode_index(self.system.final_mode)
        names = sc.replanning.contact_guards
        if names is None:
            self.contact_guards = {i for i, g in enumerate(self.system.guards)
                                   if g.target != self.system.final_mode}
        else:
            unknown = set(names) - {g.name for g in self.system.guards}
            if unknown:
                raise ValueError(f"replanning.contact_guards: unknown guards {sorted(unknown)}")
            self.contact_guards = {self.system.guard_index(n) for n in names}
        self.has_schedule = False
        h = 1.0 / sc.sim.rate_hz
        self._h = h
        self._per_solve = sc.sim.rate_hz // sc.mpc.rate_hz
        self._per_replan = int(round(sc.replanning.period * sc.sim.rate_hz))
        self._since_solve = 0
        self._step_state()

    def _step_state(self) -> None:
        self._need_replan, self._impact, self._shifted_by_impact = False, False, False

    def _schedule_dict(self) -> dict | None:
        ns = self.mpc.node_schedule if self.has_schedule else None
        if ns is None:
            return None
        return {**ns.to_dict(), "mode_names": [self.system.modes[m].name for m in ns.modes],
                "guard_names": [self.system.guards[g].name for g in ns.guards]}

    # ------------------------------------------------------------- layers
    def _replan(self, t: float, x: np.ndarray, mode: int, reason: str) -> None:
        result: PlannerResult = self.planner.plan(t, x, mode)
        self.res.planner_calls += 1
        self.plan_times.append(result.wall_time)
        accepted, note = result.schedule is not None, ""
        if accepted:
            try:  # a schedule the NLP chain cannot hold (too many switches) is rejected
                ns = NodeSchedule.from_schedule(result.schedule, self.mpc.N, self.mpc.dt)
                self.mpc.set_schedule(ns, result.trajectory)
            except ValueError as exc:
                accepted, note = False, str(exc)
        else:
            note = "no rollout reached the final domain"
        if accepted:
            self.has_schedule = True
        else:
            self.res.planner_rejected += 1
            note += "; previous schedule kept" if self.has_schedule else "; no schedule yet"
        sched = result.schedule.to_dict(self.system) if result.schedule is not None else None
        tr = result.trajectory
        self.rec.write("/planner/plan", t, {
            "t": t, "reason": reason, "accepted": accepted, "reached_final": result.reached_final,
            "cost": result.cost, "wall_time": result.wall_time, "iterations": result.iterations,
            "note": note, "schedule": sched, "t_rollout": tr.t, "x_rollout": tr.x})

    def _solve(self, t: float, x: np.ndarray, reason: str, shifted: int) -> None:
        if not self.has_schedule:
            return
        plan = self.mpc.solve(t, x)
        self.record_solve(t, plan, reason, {"shifted": shifted,
                                            "schedule": self._schedule_dict()})

    def _advance_schedule(self, guard: int, mode_after: int) -> tuple[bool, bool, bool]:
        """Updates the node schedule after a real event.

        Returns:
            (scheduled: the pending guard fired, dropped: domains were dropped,
            need_replan: the schedule no longer matches the real mode).
        """
        if not self.has_schedule:
            return False, False, mode_after != self.final_mode
        ns = self.mpc.node_schedule
        if ns.guards and ns.guards[0] == guard:
            self.mpc.on_impact()
            return True, True, False
        if guard in ns.guards[1:]:
            for _ in range(ns.guards.index(guard, 1) + 1):
                self.mpc.on_impact()
            return False, True, False
        if ns.modes[0] == mode_after:
            return False, False, False  # unscheduled self-loop (e.g. an extra bounce)
        if mode_after == self.final_mode:
            self.mpc.set_schedule(NodeSchedule((mode_after,), (), (self.mpc.N,)))
            return False, True, False
        return False, False, True

    # ------------------------------------------------------------ hooks
    def start(self, x: np.ndarray, mode: int) -> None:
        if mode == self.final_mode:
            self.mpc.set_schedule(NodeSchedule((mode,), (), (self.mpc.N,)))
            self.has_schedule = True
        else:
            self._replan(0.0, x, mode, "initial")
        self._solve(0.0, x, "initial", 0)

    def on_event(self, ev: Event, t: float) -> bool:
        scheduled, dropped, forced = self._advance_schedule(
            ev.guard, int(self.sim.num.target[ev.guard]))
        self._shifted_by_impact |= dropped
        self._impact = True
        self._need_replan |= forced or (self.sc.replanning.policy == "on_contact"
                                        and ev.guard in self.contact_guards)
        return scheduled

    def after_step(self, i: int, t: float, x: np.ndarray, mode: int, events: list[Event],
                   last: bool) -> None:
        sc, h = self.sc, self._h
        need_replan, impact = self._need_replan, self._impact
        shifted_by_impact = self._shifted_by_impact
        self._step_state()
        self._since_solve += 1
        if sc.replanning.policy == "periodic" and (i + 1) % self._per_replan == 0:
            need_replan = True
        if not self.has_schedule and self._since_solve >= self._per_solve:
            need_replan = True  # no accepted schedule yet: retry every MPC period
        if last:  # the run ends here: no more controller work
            return
        reason = ""
        if need_replan:
            why = "contact" if impact else ("periodic" if self.has_schedule else "retry")
            self._replan(t, x, mode, why)
            reason = "replan"
        elif impact and sc.mpc.resolve_on_impact:
            reason = "impact"
        elif self._since_solve >= self._per_solve:
            reason = "period"
        if reason:
            shifted = 0
            if self.has_schedule and reason != "replan" and not shifted_by_impact:
                shifted = self.mpc.shift(int(round(self._since_solve * h / self.mpc.dt)))
            self._solve(t, x, reason, shifted)
            self._since_solve = 0
