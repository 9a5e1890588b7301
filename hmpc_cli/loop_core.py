"""The closed loop's plant side, shared by every controller stack.

Every simulator step: low-level command from the current plan, one hybrid simulator step
(events located exactly, resets applied, disturbance held), logging; the controller
stack (a subclass: :class:`hmpc_cli.loop.LayeredLoop` for the ball,
:class:`hmpc_cli.loop_walking.WalkingLoop` for the biped) reacts to events and periods
in :meth:`LoopCore.after_step`. Simulated time pauses while controllers compute; their
wall time is recorded.
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
from hmpc_cli.hybrid import HybridSystem
from hmpc_cli.logschema import TOPICS
from hmpc_cli.lowlevel import LowLevelController
from hmpc_cli.messages import Plan
from hmpc_cli.scenario import Scenario
from hmpc_cli.sim import Event, HybridSimulator, ZenoError
from hmpc_cli.systems import build_system

SOFTENED_TOL = 1e-6  # a solve whose hybrid-constraint slack exceeds this is "softened"


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


class LoopCore:
    """Simulator, disturbance, low-level controller and log around a controller stack.

    Args:
        scenario: the validated scenario.
        recorder: an open :class:`hmpc_cli.recorder.Recorder` (may be set later).
        system: the controllers' model. plant: the simulated system (default: the model
            updated by the scenario's ``[plant]`` keys).
        progress: ``progress(step, n_steps)`` after every simulator step.
    """

    def __init__(self, scenario: Scenario, recorder, system: HybridSystem,
                 plant: HybridSystem | None = None, progress: Callable | None = None) -> None:
        sc = self.sc = scenario
        self.system = system
        if plant is None:
            plant = build_system(sc.plant_params()) if sc.plant else system
        self.plant = plant
        self.sim = HybridSimulator(self.plant, sc.sim.max_events_per_step,
                                   sc.sim.event_time_tol)
        self.lowlevel = LowLevelController(self.system, sc.lowlevel)
        self.dist = make_disturbance(
            sc.disturbance.kind, n_w=self.system.n_w, duration=sc.sim.duration,
            magnitude=sc.disturbance.magnitude, hold=sc.disturbance.hold, seed=sc.seed,
            trial=sc.disturbance.trial)
        self.rec = recorder
        self.progress = progress
        self.res = RunResult(sc.name, sc.seed)
        self.solve_times: list[float] = []
        self.plan_times: list[float] = []
        self.plan: Plan | None = None
        self._stopped = False  # ended early (divergence, Zeno or a task failure)

    # --------------------------------------------------------- stack hooks
    def start(self, x: np.ndarray, mode: int) -> None:
        """Called once at t = 0 before the first step (initial plan and solve)."""

    def on_event(self, ev: Event, t: float) -> bool:
        """Called for each guard event (at time t [s]), in time order, before it is
        logged; returns whether it was the scheduled one."""
        return False

    def after_step(self, i: int, t: float, x: np.ndarray, mode: int, events: list[Event],
                   last: bool) -> None:
        """Called after simulator step i (ending at time t) with its events; ``last``: the
        run ends here (no controller work needed)."""

    def failure(self, x: np.ndarray, mode: int) -> str:
        """A reason to end the run as failed after a step ('' to go on)."""
        return ""

    def is_success(self, x: np.ndarray, mode: int) -> bool:
        """The run's success criterion at its end (default: goal distance <= radius)."""
        r = self.res
        return bool(np.isfinite(r.final_error) and r.final_error <= self.system.success_radius)

    def run_info(self) -> dict:
        """Extra fields of /run/info."""
        return {}

    # -------------------------------------------------------------- logging
    def _open_log(self) -> None:
        for topic, (schema_name, schema) in TOPICS.items():
            self.rec.add_topic(topic, schema_name, schema)
        sysm = self.system
        info = {"scenario_name": self.sc.name, "seed": self.sc.seed, "versions": versions(),
                "scenario": self.sc.model_dump(mode="json"),
                "state_names": list(sysm.state_names), "input_names": list(sysm.input_names),
                "mode_names": [m.name for m in sysm.modes],
                "guard_names": [g.name for g in sysm.guards], **self.run_info()}
        self.rec.write("/run/info", 0.0, info)
        self.rec.add_metadata("run", {"scenario": self.sc.name, "seed": str(self.sc.seed),
                                      **{f"version.{k}": v for k, v in versions().items()}})

    def record_solve(self, t: float, plan: Plan, reason: str, extra: dict,
                     adopt: bool = True) -> None:
        """Counts one fixed-mode MPC solve, logs it to /mpc/solve and (``adopt``) makes
        its plan the one the low level tracks."""
        st = plan.stats
        self.res.solves += 1
        self.solve_times.append(st.wall_time)
        if not st.success:
            self.res.solver_failures += 1
            self.res.failure_statuses[st.status] = self.res.failure_statuses.get(st.status, 0) + 1
        elif st.slack > SOFTENED_TOL:
            self.res.softened_solves += 1
            self.res.max_slack = max(self.res.max_slack, st.slack)
        if adopt:
            self.plan = plan
        self.rec.write("/mpc/solve", t, {
            "t": t, "reason": reason, "status": st.status, "success": st.success,
            "iterations": st.iterations, "wall_time": st.wall_time, "cost": st.cost,
            "max_violation": st.max_violation, "slack": st.slack, **extra,
            "t_plan": plan.traj.t + t,
            "x_plan": plan.traj.x, "u_plan": plan.traj.u, "seg_plan": plan.traj.seg})

    # ---------------------------------------------------------------- run
    def run(self) -> RunResult:
        """Runs the scenario to its duration (or divergence); always closes cleanly."""
        sc, sysm = self.sc, self.system
        start = time.perf_counter()
        self._open_log()
        h = 1.0 / sc.sim.rate_hz
        n_steps = int(round(sc.sim.duration * sc.sim.rate_hz))
        per_log = sc.sim.rate_hz // sc.sim.log_rate_hz
        x = np.array(sysm.x0, dtype=float)
        mode = sysm.mode_index(sysm.initial_mode)
        self.start(x, mode)
        last_w, t = None, 0.0
        for i in range(n_steps):
            t = i * h
            w = self.dist(t)
            u, x_ref = self.lowlevel.command(t, x, self.plan, h)
            u = sysm.numeric.saturate(np.array([mode]), u[None])[0]
            if i % per_log == 0:
                self.rec.write("/sim/state", t, {"t": t, "x": x, "mode": mode, "u": u,
                                                 "x_ref": x_ref, "w": w})
            if last_w is None or not np.array_equal(w, last_w):
                self.rec.write("/disturbance", t, {"t": t, "w": w})
                last_w = w
            try:
                x, mode, events = self._advance(i * h, h, x, mode, u, w)
            except ZenoError as exc:
                self._fail(t, f"zeno: {exc}")
                break
            t = (i + 1) * h
            if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > sc.sim.divergence_bound:
                self._fail(t, "diverged: non-finite or unbounded state")
                break
            why = self.failure(x, mode)
            if why:
                self._fail(t, why, diverged=False)
                break
            self.after_step(i, t, x, mode, events, i + 1 == n_steps)
            if self.progress is not None:
                self.progress(i + 1, n_steps)
        self.res.t_end = t
        self.rec.write("/sim/state", t, {"t": t, "x": x, "mode": mode,
                                         "u": np.zeros(sysm.n_u), "x_ref": x, "w": self.dist(t)})
        return self._finish(x, mode, start)

    def _advance(self, t0: float, h: float, x: np.ndarray, mode: int, u: np.ndarray,
                 w: np.ndarray) -> tuple[np.ndarray, int, list[Event]]:
        """One simulator step of h seconds from time t0; handles and logs its events.

        With ``sim.input_at_events = "recompute"`` the step stops at each reset, the
        stack reacts (:meth:`on_event` at the event time) and the low level computes a
        new input for the rest of the step.

        Raises:
            ZenoError: more than ``sim.max_events_per_step`` events in the step.
        """
        split = self.sc.sim.input_at_events == "recompute"
        left, events = h, []
        while True:
            step = self.sim.step(x[None], np.array([mode]), u[None], w[None], left,
                                 stop_at_event=split)
            x, mode = step.x[0], int(step.mode[0])
            if len(events) + len(step.events) > self.sc.sim.max_events_per_step:
                raise ZenoError(f"more than {self.sc.sim.max_events_per_step} guard events "
                                f"in one step of {h} s (Zeno chattering)")
            for ev in step.events:
                t_ev = t0 + (h - left) + ev.tau
                self._event(ev, t_ev)
                events.append(ev)
            left = float(step.remaining[0])
            if not split or left <= 0.0 or not step.events:
                return x, mode, events
            t_now = t0 + h - left
            u, _ = self.lowlevel.command(t_now, x, self.plan, left)
            u = self.system.numeric.saturate(np.array([mode]), u[None])[0]

    def _event(self, ev: Event, t_ev: float) -> None:
        g = self.plant.guards[ev.guard]
        scheduled = self.on_event(ev, t_ev)
        self.res.contacts += 1
        self.res.contacts_by_guard[g.name] = self.res.contacts_by_guard.get(g.name, 0) + 1
        self.rec.write("/sim/event", t_ev, {
            "t": t_ev, "guard": ev.guard, "guard_name": g.name, "mode_before": g.source,
            "mode_after": g.target, "x_before": ev.x_before, "x_after": ev.x_after,
            "scheduled": scheduled})

    def _fail(self, t: float, reason: str, diverged: bool = True) -> None:
        """Ends the run early as failed (``diverged``: numerically, else by the task's
        failure test, e.g. a fall)."""
        self.res.diverged = diverged
        self.res.reason = reason
        self.res.t_end = t
        self._stopped = True

    def _finish(self, x: np.ndarray, mode: int, start: float) -> RunResult:
        r, sysm = self.res, self.system
        r.x_end = [float(v) for v in x]
        r.mode_end = sysm.modes[mode].name
        r.final_error = float(sysm.numeric.goal_error(x)) if np.all(np.isfinite(x)) else \
            float("nan")
        r.success = not self._stopped and self.is_success(x, mode)
        if self.solve_times:
            st = np.array(self.solve_times)
            r.solve_time_median = float(np.median(st))
            r.solve_time_p95 = float(np.percentile(st, 95))
            r.solve_time_max = float(st.max())
        if self.plan_times:
            r.plan_time_median = float(np.median(self.plan_times))
        r.wall_time = time.perf_counter() - start
        if not r.reason:
            r.reason = "success" if r.success else self.failure_reason(x, mode)
        self.rec.write("/run/summary", r.t_end, r.__dict__)
        return r

    def failure_reason(self, x: np.ndarray, mode: int) -> str:
        """Why a run that ended normally is not a success."""
        return f"final error {self.res.final_error:.3f} > {self.system.success_radius}"
