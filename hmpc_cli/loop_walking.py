"""The biped's controller stack: foothold choice, walking MPC, PD low level (paper Fig. 4).

Hybrid MPC layer: at t = 0 and right after every contact (at the contact time, with the
post-impact state; ``sim.input_at_events = "recompute"`` makes the simulator stop there),
the walking MPC is solved for every candidate stair segment
(:func:`hmpc_cli.planner.footholds.candidates`) and the best one is kept
(:func:`~hmpc_cli.planner.footholds.choose`: the largest final hip x by default). A failed
candidate is skipped and logged; if all fail, or none is within reach, the previous plan
is kept (a choice that found no plan is retried every MPC period). Fixed-mode MPC: every
``mpc.rate_hz`` period the chosen segment's NLP is re-solved from the measured state (time
already spent in the swing as a parameter); a failed solve is logged and the previous
plan kept. The simulated robot is the model updated by the scenario's ``[plant]`` keys
(the paper: every mass and inertia x 1.1).

Counting: a foothold choice is one planner call (its wall time covers every candidate
solve; the candidates' statuses are in /planner/plan); the chosen candidate's solve and
every periodic re-solve are the MPC solves of the summary.

A fall ends the run as failed (``diverged`` stays false): the hip less than
``fall_hip_height`` above the terrain under it, or a knee, the hip or the torso top below
the terrain, all judged on the plant's geometry and terrain. Success: no fall and the
stance foot on the top segment at the end.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from hmpc_cli.loop_core import LoopCore
from hmpc_cli.messages import Plan
from hmpc_cli.mpc.walking import WalkingMPC
from hmpc_cli.numeric import compile_numpy
from hmpc_cli.planner.footholds import candidates, choose
from hmpc_cli.scenario import Scenario
from hmpc_cli.sim import Event
from hmpc_cli.systems.biped import (
    POINT_NAMES, STANCE_X, BipedParams, build_biped, make_biped_model, stair_edges,
    terrain_profile)

__all__ = ["WalkingLoop"]

_BODY = [POINT_NAMES.index(n) for n in ("stance_knee", "hip", "torso_top", "swing_knee")]
_HIP = POINT_NAMES.index("hip")


class WalkingLoop(LoopCore):
    """Foothold choice + walking MPC + PD around the simulated (heavier) biped."""

    def __init__(self, scenario: Scenario, recorder, progress: Callable | None = None,
                 mpc: WalkingMPC | None = None) -> None:
        sc = scenario
        params: BipedParams = sc.system
        system = build_biped(params)
        self.world: BipedParams = sc.plant_params()  # the simulated robot and its terrain
        plant = build_biped(self.world) if sc.plant else system
        super().__init__(sc, recorder, system, plant, progress)
        self.mpc = mpc or WalkingMPC(params, sc.mpc)
        self.mpc.reset()
        self.footholds = sc.planner
        self.segments = stair_edges(params)
        self._world_points = compile_numpy(make_biped_model(self.world).points_world) \
            if sc.plant else compile_numpy(self.mpc.nlp.model.points_world)
        self._per_solve = sc.sim.rate_hz // sc.mpc.rate_hz
        self._since_solve = 0
        self.segment: int | None = None
        self._chosen = False  # the last foothold choice found a plan
        self.swing_start = 0.0

    # ------------------------------------------------------- hybrid layer
    def _choose_foothold(self, t: float, x: np.ndarray, reason: str) -> None:
        """Solves every candidate segment from x at time t and keeps the best plan."""
        start = time.perf_counter()
        try:
            cand = candidates(float(x[STANCE_X]), self.segments, self.footholds)
        except ValueError as exc:
            cand, plans, note = [], [], f"{exc}; previous plan kept"
        else:
            plans = self.mpc.solve_candidates(t, x, cand, 0.0)
            note = ""
        best = choose(plans, self.footholds) if plans else None
        wall = time.perf_counter() - start
        self.res.planner_calls += 1
        self.plan_times.append(wall)
        if plans and best is None:
            note = "every candidate failed; previous plan kept"
        if best is None:
            self.res.planner_rejected += 1
        rows = [{"segment": c, "guard_name": self.system.guards[c].name,
                 "status": p.stats.status, "success": p.stats.success,
                 "iterations": p.stats.iterations, "wall_time": p.stats.wall_time,
                 "cost": p.stats.cost, "final_hip": list(p.extra["final_hip"]),
                 "touchdown": list(p.extra["touchdown"])} for c, p in zip(cand, plans)]
        chosen = plans[best] if best is not None else None
        self.rec.write("/planner/plan", t, {
            "t": t, "reason": reason, "accepted": chosen is not None,
            "reached_final": chosen is not None,
            "cost": chosen.stats.cost if chosen else float("nan"), "wall_time": wall,
            "iterations": int(sum(p.stats.iterations for p in plans)), "note": note,
            "schedule": chosen.schedule.to_dict(self.system) if chosen else None,
            "candidates": rows})
        self._chosen = chosen is not None
        if chosen is not None:
            self.segment = cand[best]
            self.record_solve(t, chosen, reason, self._solve_extra(chosen))

    def _solve_extra(self, plan: Plan) -> dict:
        seg = plan.extra["segment"]
        return {"shifted": 0, "schedule": plan.schedule.to_dict(self.system),
                "segment": seg, "warm": plan.extra["warm"],
                "elapsed": plan.extra["elapsed"], "touchdown": list(plan.extra["touchdown"])}

    # ------------------------------------------------------------- hooks
    def start(self, x: np.ndarray, mode: int) -> None:
        self._choose_foothold(0.0, x, "initial")

    def on_event(self, ev: Event, t: float) -> bool:
        scheduled = self.segment is not None and ev.guard == self.segment
        self.mpc.on_impact(self.segment if self._chosen else None)
        self.swing_start = t
        self._since_solve = 0
        self._choose_foothold(t, ev.x_after, "contact")
        return scheduled

    def after_step(self, i: int, t: float, x: np.ndarray, mode: int, events: list[Event],
                   last: bool) -> None:
        self._since_solve += 1
        if last or self._since_solve < self._per_solve:
            return
        self._since_solve = 0
        if not self._chosen:  # no foothold plan for this swing yet: choose again
            self._choose_foothold(t, x, "retry")
            return
        plan = self.mpc.solve(t, x, self.segment, t - self.swing_start)
        self.record_solve(t, plan, "period", self._solve_extra(plan),
                          adopt=plan.stats.success)

    def failure(self, x: np.ndarray, mode: int) -> str:
        pts = self._world_points(x[None])[0].reshape(len(POINT_NAMES), 2)
        ground = terrain_profile(self.world, pts[:, 0])
        hip_gap = pts[_HIP, 1] - ground[_HIP]
        if hip_gap < self.world.fall_hip_height:
            return (f"fall: hip {hip_gap:.3f} m above the terrain (< "
                    f"{self.world.fall_hip_height} m)")
        for k in _BODY:
            if pts[k, 1] < ground[k]:
                return f"fall: {POINT_NAMES[k]} touched the ground at x = {pts[k, 0]:.3f} m"
        return ""

    def is_success(self, x: np.ndarray, mode: int) -> bool:
        start, end, _ = stair_edges(self.world)[-1]
        return bool(start <= x[STANCE_X] <= end)

    def failure_reason(self, x: np.ndarray, mode: int) -> str:
        start, end, _ = stair_edges(self.world)[-1]
        return (f"stance foot at x = {x[STANCE_X]:.3f} m is not on the top segment "
                f"[{start:g}, {end:g}]")
