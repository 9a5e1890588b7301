"""The run's books and its log topics: what a closed-loop run writes, in one place.

:class:`RunLog` wraps an open MCAP writer (:class:`hmpc_cli.recorder.Recorder` or
anything with ``add_topic``/``add_metadata``/``write``), which the caller opens and
closes; it writes the topics of :data:`hmpc_cli.logschema.TOPICS` and keeps the
:class:`RunResult` counts (contacts, solves, failures, planner calls) that become
``summary.json``.
"""

from __future__ import annotations

import platform
import sys
from dataclasses import dataclass, field

import numpy as np

from hmpc_cli import __version__
from hmpc_cli.hybrid import HybridSystem
from hmpc_cli.logschema import TOPICS
from hmpc_cli.messages import GuardEvent, Plan, PlannerResult

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
    warnings: list = field(default_factory=list)


def versions() -> dict[str, str]:
    """Versions of everything that can change a trajectory."""
    import casadi
    import mcap
    import pydantic

    return {"hmpc": __version__, "python": sys.version.split()[0], "numpy": np.__version__,
            "casadi": casadi.__version__, "pydantic": pydantic.__version__,
            "mcap": getattr(mcap, "__version__", "?"), "platform": platform.platform()}


class RunLog:
    """Topics and books of one run.

    Args:
        recorder: an open MCAP writer (closed by the caller), or None to log nothing.
        per_state: simulator steps per /sim/state sample.
    """

    def __init__(self, recorder, per_state: int = 1) -> None:
        self.rec = recorder
        self.per_state = per_state
        self.result = RunResult("scenario", 0)
        self.info: dict = {}
        self.solve_times: list[float] = []
        self.plan_times: list[float] = []
        self._last_w: np.ndarray | None = None
        self.scene = None  # 3D scene writer (hmpc_cli.scene.SceneWriter), set by the runner

    def set_info(self, name: str, seed: int, scenario: dict, per_state: int,
                 margins: dict | None = None) -> None:
        """The run's identity for /run/info and the summary.

        Args:
            name: scenario name.
            seed: run seed.
            scenario: the validated scenario (JSON-ready).
            per_state: simulator steps per /sim/state sample.
            margins: the MPC's margins (source, radius, per guard, per mode), if it has any.
        """
        self.result.scenario, self.result.seed = name, seed
        self.info = {"scenario_name": name, "seed": seed, "scenario": scenario}
        if margins is not None:
            self.info["margins"] = margins
        self.per_state = per_state

    def _write(self, topic: str, t: float, payload: dict) -> None:
        if self.rec is not None:
            self.rec.write(topic, t, payload)

    def open(self, model: HybridSystem) -> None:
        """Registers the topics and writes /run/info (seed, versions, scenario, names)."""
        if self.rec is None:
            return
        for topic, (schema_name, schema) in TOPICS.items():
            self.rec.add_topic(topic, schema_name, schema)
        vers = versions()
        self._write("/run/info", 0.0, {
            **self.info, "versions": vers, "system": model.name,
            "state_names": list(model.state_names), "input_names": list(model.input_names),
            "mode_names": [m.name for m in model.modes],
            "guard_names": [g.name for g in model.guards]})
        self.rec.add_metadata("run", {"scenario": self.result.scenario,
                                      "seed": str(self.result.seed),
                                      **{f"version.{k}": v for k, v in vers.items()}})

    def step(self, i: int, t: float, x: np.ndarray, mode: int, u: np.ndarray,
             x_ref: np.ndarray, w: np.ndarray) -> None:
        """Logs before simulator step i.

        /sim/state every ``per_state`` steps, /disturbance whenever w changes.
        """
        if i % self.per_state == 0:
            self.state(t, x, mode, u, x_ref, w)
        if self._last_w is None or not np.array_equal(w, self._last_w):
            self._write("/disturbance", t, {"t": t, "w": w})
            self._last_w = w

    def state(self, t: float, x: np.ndarray, mode: int, u: np.ndarray, x_ref: np.ndarray,
              w: np.ndarray) -> None:
        """One /sim/state sample."""
        self._write("/sim/state", t, {"t": t, "x": x, "mode": mode, "u": u, "x_ref": x_ref,
                                      "w": w})
        if self.scene is not None:  # scene
            self.scene.state(t, x)

    def event(self, ev: GuardEvent, system: HybridSystem, scheduled: bool) -> None:
        """Counts and logs a guard event of the simulated system."""
        g = system.guards[ev.guard]
        r = self.result
        r.contacts += 1
        r.contacts_by_guard[g.name] = r.contacts_by_guard.get(g.name, 0) + 1
        self._write("/sim/event", ev.t, {
            "t": ev.t, "guard": ev.guard, "guard_name": g.name, "mode_before": g.source,
            "mode_after": g.target, "x_before": ev.x_before, "x_after": ev.x_after,
            "scheduled": scheduled})

    def planner(self, t: float, reason: str, result: PlannerResult, accepted: bool,
                note: str, model: HybridSystem) -> None:
        """Logs one planner call (counted by the loop)."""
        self.plan_times.append(result.wall_time)
        sched = result.schedule.to_dict(model) if result.schedule is not None else None
        rollout = {}
        if result.trajectory is not None:
            rollout = {"t_rollout": result.trajectory.t, "x_rollout": result.trajectory.x}
        self._write("/planner/plan", t, {
            "t": t, "reason": reason, "accepted": accepted,
            "reached_final": result.reached_final, "cost": result.cost,
            "wall_time": result.wall_time, "iterations": result.iterations, "note": note,
            "schedule": sched, **rollout, **result.extra})
        if self.scene is not None:  # scene
            self.scene.rollout(t, result.trajectory)

    def solve(self, t: float, plan: Plan, reason: str, model: HybridSystem) -> None:
        """Counts one fixed-mode MPC solve and logs it to /mpc/solve."""
        st, r = plan.stats, self.result
        r.solves += 1
        self.solve_times.append(st.wall_time)
        if not st.success:
            r.solver_failures += 1
            r.failure_statuses[st.status] = r.failure_statuses.get(st.status, 0) + 1
        elif st.slack > SOFTENED_TOL:
            r.softened_solves += 1
            r.max_slack = max(r.max_slack, st.slack)
        self._write("/mpc/solve", t, {
            "t": t, "reason": reason, "status": st.status, "success": st.success,
            "iterations": st.iterations, "wall_time": st.wall_time, "cost": st.cost,
            "max_violation": st.max_violation, "slack": st.slack, **plan.extra,
            "schedule": plan.schedule.to_dict(model), "adopted": plan.adopt,
            "t_plan": plan.traj.t + t, "x_plan": plan.traj.x, "u_plan": plan.traj.u,
            "seg_plan": plan.traj.seg})
        if self.scene is not None:  # scene
            self.scene.plan(t, plan)

    def summary(self, r: RunResult) -> None:
        """Fills the timing statistics and writes /run/summary."""
        if self.solve_times:
            st = np.array(self.solve_times)
            r.solve_time_median = float(np.median(st))
            r.solve_time_p95 = float(np.percentile(st, 95))
            r.solve_time_max = float(st.max())
        if self.plan_times:
            r.plan_time_median = float(np.median(self.plan_times))
        self._write("/run/summary", r.t_end, r.__dict__)
