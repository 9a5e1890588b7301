"""JSON schemas of the run log's topics (self-contained, for Foxglove/Lichtblick)."""

from __future__ import annotations

NUM = {"type": ["number", "null"]}
VEC = {"type": "array", "items": NUM}
MAT = {"type": "array", "items": VEC}
INT = {"type": "integer"}
FLOAT = {"type": "number"}
STR = {"type": "string"}
BOOL = {"type": "boolean"}
SCHEDULE = {
    "type": ["object", "null"],
    "properties": {
        "modes": {"type": "array", "items": INT},
        "mode_names": {"type": "array", "items": STR},
        "guards": {"type": "array", "items": INT},
        "guard_names": {"type": "array", "items": STR},
        "durations": VEC,
        "t0": NUM,
    },
}


def _obj(title: str, **props) -> dict:
    return {"title": title, "type": "object", "properties": props}


TOPICS: dict[str, tuple[str, dict]] = {
    "/run/info": ("hmpc.RunInfo", _obj(
        "RunInfo", scenario_name=STR, seed=INT, system=STR, versions={"type": "object"},
        scenario={"type": "object"}, state_names={"type": "array", "items": STR},
        input_names={"type": "array", "items": STR},
        mode_names={"type": "array", "items": STR},
        guard_names={"type": "array", "items": STR},
        margins=_obj("Margins", source=STR, radius=FLOAT, guards={
            "type": "array", "items": _obj("GuardMargins", guard=STR, avoid=FLOAT,
                                           pass_through=FLOAT)},
            inputs={"type": "array", "items": _obj(
                "InputMargins", mode=STR, per_side={"type": "array", "items": FLOAT})}))),
    "/sim/state": ("hmpc.State", _obj(
        "State", t=NUM, x=VEC, mode=INT, u=VEC, x_ref=VEC, w=VEC)),
    "/sim/event": ("hmpc.GuardEvent", _obj(
        "GuardEvent", t=NUM, guard=INT, guard_name=STR, mode_before=STR, mode_after=STR,
        x_before=VEC, x_after=VEC, scheduled=BOOL)),
    "/disturbance": ("hmpc.Disturbance", _obj("Disturbance", t=NUM, w=VEC)),
    "/mpc/solve": ("hmpc.MpcSolve", _obj(
        "MpcSolve", t=NUM, reason=STR, status=STR, success=BOOL, iterations=INT,
        wall_time=NUM, cost=NUM, max_violation=NUM, slack=NUM, adopted=BOOL, schedule=SCHEDULE,
        shifted=INT, counts={"type": "array", "items": INT},  # chain MPC
        segment=INT, elapsed=NUM, warm=STR, touchdown=VEC, final_hip=VEC,  # walking MPC
        t_plan=VEC, x_plan=MAT, u_plan=MAT, seg_plan={"type": "array", "items": INT})),
    "/planner/plan": ("hmpc.PlannerCall", _obj(
        "PlannerCall", t=NUM, reason=STR, accepted=BOOL, reached_final=BOOL, cost=NUM,
        wall_time=NUM, iterations=INT, note=STR, schedule=SCHEDULE, t_rollout=VEC,
        x_rollout=MAT, candidates={"type": "array", "items": _obj(
            "Candidate", segment=INT, guard_name=STR, status=STR, success=BOOL,
            iterations=INT, wall_time=NUM, cost=NUM, final_hip=VEC, touchdown=VEC)})),
    "/run/summary": ("hmpc.Summary", _obj("Summary")),
}
