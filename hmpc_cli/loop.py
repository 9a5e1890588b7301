"""Composition root: builds the layers from a scenario and runs the multi-rate loop.

Every simulator step: low-level command from the current plan, one hybrid simulator step
(events located exactly, resets applied, disturbance held). After the step: each guard
event advances the schedule (node shifting on impact), may trigger the planner (policy
``on_contact``) and a re-solve; every MPC period the elapsed nodes are shifted and the MPC
re-solved. Simulated time pauses while controllers compute; their wall time is recorded.
"""

from __future__ import annotations

import platform
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from hmpc_cli import __version__
from hmpc_cli.disturbance import make_disturbance
from hmpc_cli.logschema import TOPICS
from hmpc_cli.lowlevel import LowLevelController
from hmpc_cli.messages import Plan, PlannerResult
from hmpc_cli.mpc.controller import FixedModeMPC
from hmpc_cli.mpc.layout import NodeSchedule
from hmpc_cli.planner.cem import CrossEntropyPlanner
from hmpc_cli.scenario import Scenario
from hmpc_cli.sim import HybridSimulator, ZenoError
from hmpc_cli.systems import build_system


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
    solve_time_median: float = float("nan")
    solve_time_p95: float = float("nan")
    solve_time_max: float = float("nan")
    planner_calls: int = 0
    planner_rejected: int = 0
    plan_time_median: float = float("nan")
    diverged: bool = False
    reason: str = ""
    wall_time: float = 0.0


def versions() -> dict[str, str]:
    """Versions of everything that can change a trajectory."""
    import casadi
    import mcap
    import pydantic

    return {"hmpc": __version__, "python": sys.version.split()[0], "numpy": np.__version__,
            "casadi": casadi.__version__, "pydantic": pydantic.__version__,
            "mcap": getattr(mcap, "__version__", "?"), "platform": platform.platform()}


class LayeredLoop:
    """The three layers around the simulator, logging into a recorder."""

    def __init__(self, scenario: Scenario, recorder, progress: Callable | None = None,
                 mpc: FixedModeMPC | None = None) -> None:
        sc = self.sc = scenario
        self.system = build_system(sc.system)
        self.sim = HybridSimulator(self.system, sc.sim.max_events_per_step,
                                   sc.sim.event_time_tol)
        self.planner = CrossEntropyPlanner(self.system, sc.planner, run_seed=sc.seed)
        self.mpc = mpc or FixedModeMPC(self.system, sc.mpc)
        self.lowlevel = LowLevelController(self.system, sc.lowlevel)
        self.dist = make_disturbance(
            sc.disturbance.kind, n_w=self.system.n_w, duration=sc.sim.duration,
            magnitude=sc.disturbance.magnitude, hold=sc.disturbance.hold, seed=sc.seed,
            trial=sc.disturbance.trial)
        self.rec = recorder
        self.progress = progress
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
        self.res = RunResult(sc.name, sc.seed)
        self.solve_times: list[float] = []
        self.plan_times: list[float] = []
        self.plan: Plan | None = None
        self.has_schedule = False

    # -------------------------------------------------------------- logging
    def _open_log(self) -> None:
        for topic, (schema_name, schema) in TOPICS.items():
            self.rec.add_topic(topic, schema_name, schema)
        sysm = self.system
        info = {"scenario_name": self.sc.name, "seed": self.sc.seed, "versions": versions(),
                "scenario": self.sc.model_dump(mode="json"),
                "state_names": list(sysm.state_names), "input_names": list(sysm.input_names),
                "mode_names": [m.name for m in sysm.modes],
                "guard_names": [g.name for g in sysm.guards]}
        self.rec.write("/run/info", 0.0, info)
        self.rec.add_metadata("run", {"scenario": self.sc.name, "seed": str(self.sc.seed),
                                      **{f"version.{k}": v for k, v in versions().items()}})

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
        ns = None
        if accepted:
            try:
                ns = NodeSchedule.from_schedule(result.schedule, self.mpc.nlp.N, self.mpc.nlp.dt)
            except ValueError as exc:
                accepted, note = False, str(exc)
        else:
            note = "no rollout reached the final domain"
        if accepted:
            self.mpc.set_schedule(ns, result.trajectory)
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
        st = plan.stats
        self.res.solves += 1
        self.solve_times.append(st.wall_time)
        if not st.success:
            self.res.solver_failures += 1
            self.res.failure_statuses[st.status] = self.res.failure_statuses.get(st.status, 0) + 1
        self.plan = plan  # on failure: the shifted previous solution
        self.rec.write("/mpc/solve", t, {
            "t": t, "reason": reason, "status": st.status, "success": st.success,
            "iterations": st.iterations, "wall_time": st.wall_time, "cost": st.cost,
            "max_violation": st.max_violation, "shifted": shifted,
            "schedule": self._schedule_dict(), "t_plan": plan.traj.t + t,
            "x_plan": plan.traj.x, "u_plan": plan.traj.u, "seg_plan": plan.traj.seg})

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
            self.mpc.set_schedule(NodeSchedule((mode_after,), (), (self.mpc.nlp.N,)))
            return False, True, False
        return False, False, True

    # ---------------------------------------------------------------- run
    def run(self) -> RunResult:
        """Runs the scenario to its duration (or divergence); always closes cleanly."""
        sc, sysm = self.sc, self.system
        start = time.perf_counter()
        self._open_log()
        h = 1.0 / sc.sim.rate_hz
        n_steps = int(round(sc.sim.duration * sc.sim.rate_hz))
        per_solve = sc.sim.rate_hz // sc.mpc.rate_hz
        per_log = sc.sim.rate_hz // sc.sim.log_rate_hz
        per_replan = int(round(sc.replanning.period * sc.sim.rate_hz))
        node_dt = self.mpc.nlp.dt
        x = np.array(sysm.x0, dtype=float)
        mode = sysm.mode_index(sysm.initial_mode)
        if mode == self.final_mode:
            self.mpc.set_schedule(NodeSchedule((mode,), (), (self.mpc.nlp.N,)))
            self.has_schedule = True
        else:
            self._replan(0.0, x, mode, "initial")
        self._solve(0.0, x, "initial", 0)
        since_solve, last_w, t = 0, None, 0.0
        for i in range(n_steps):
            t = i * h
            w = self.dist(t)
            u, x_ref = self.lowlevel.command(t, x, self.plan)
            u = sysm.numeric.saturate(np.array([mode]), u[None])[0]
            if i % per_log == 0:
                self.rec.write("/sim/state", t, {"t": t, "x": x, "mode": mode, "u": u,
                                                 "x_ref": x_ref, "w": w})
            if last_w is None or not np.array_equal(w, last_w):
                self.rec.write("/disturbance", t, {"t": t, "w": w})
                last_w = w
            try:
                step = self.sim.step(x[None], np.array([mode]), u[None], w[None], h)
            except ZenoError as exc:
                self._fail(t, f"zeno: {exc}")
                break
            x, mode = step.x[0], int(step.mode[0])
            t = (i + 1) * h
            need_replan, impact, shifted_by_impact = False, False, False
            for ev in step.events:
                g = sysm.guards[ev.guard]
                scheduled, dropped, forced = self._advance_schedule(
                    ev.guard, int(self.sim.num.target[ev.guard]))
                shifted_by_impact |= dropped
                self.res.contacts += 1
                self.res.contacts_by_guard[g.name] = self.res.contacts_by_guard.get(g.name, 0) + 1
                self.rec.write("/sim/event", i * h + ev.tau, {
                    "t": i * h + ev.tau, "guard": ev.guard, "guard_name": g.name,
                    "mode_before": g.source, "mode_after": g.target, "x_before": ev.x_before,
                    "x_after": ev.x_after, "scheduled": scheduled})
                impact = True
                need_replan |= forced or (sc.replanning.policy == "on_contact"
                                          and ev.guard in self.contact_guards)
            if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > sc.sim.divergence_bound:
                self._fail(t, "diverged: non-finite or unbounded state")
                break
            since_solve += 1
            if sc.replanning.policy == "periodic" and (i + 1) % per_replan == 0:
                need_replan = True
            if not self.has_schedule and since_solve >= per_solve:
                need_replan = True  # no accepted schedule yet: retry every MPC period
            reason = ""
            if i + 1 == n_steps:  # the run ends here: no more controller work
                need_replan = False
            if need_replan:
                why = "contact" if impact else ("periodic" if self.has_schedule else "retry")
                self._replan(t, x, mode, why)
                reason = "replan"
            elif impact and sc.mpc.resolve_on_impact:
                reason = "impact"
            elif since_solve >= per_solve:
                reason = "period"
            if reason and i + 1 < n_steps:
                shifted = 0
                if self.has_schedule and reason != "replan" and not shifted_by_impact:
                    shifted = self.mpc.shift(int(round(since_solve * h / node_dt)))
                self._solve(t, x, reason, shifted)
                since_solve = 0
            if self.progress is not None:
                self.progress(i + 1, n_steps)
        self.res.t_end = t
        self.rec.write("/sim/state", t, {"t": t, "x": x, "mode": mode,
                                         "u": np.zeros(sysm.n_u), "x_ref": x, "w": self.dist(t)})
        return self._finish(x, mode, start)

    def _fail(self, t: float, reason: str) -> None:
        self.res.diverged = True
        self.res.reason = reason
        self.res.t_end = t

    def _finish(self, x: np.ndarray, mode: int, start: float) -> RunResult:
        r, sysm = self.res, self.system
        r.x_end = [float(v) for v in x]
        r.mode_end = sysm.modes[mode].name
        r.final_error = float(sysm.numeric.goal_error(x)) if np.all(np.isfinite(x)) else \
            float("nan")
        r.success = (not r.diverged and np.isfinite(r.final_error)
                     and r.final_error <= sysm.success_radius)
        if self.solve_times:
            st = np.array(self.solve_times)
            r.solve_time_median = float(np.median(st))
            r.solve_time_p95 = float(np.percentile(st, 95))
            r.solve_time_max = float(st.max())
        if self.plan_times:
            r.plan_time_median = float(np.median(self.plan_times))
        r.wall_time = time.perf_counter() - start
        if not r.reason:
            r.reason = "success" if r.success else \
                f"final error {r.final_error:.3f} > {sysm.success_radius}"
        self.rec.write("/run/summary", r.t_end, r.__dict__)
        return r
