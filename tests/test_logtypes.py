"""The typed run log: viewer-valid schemas generated from the types, messages that match
them, and ``read_run`` arrays for the ball, the biped and the older untyped layout."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import BALL, SCENARIOS
from hmpc_cli.log.topics import LOG_VERSION, TOPICS, named, topic_schemas
from hmpc_cli.log.schema import convert, validate, viewer_problems
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.reader import read_log
from hmpc_cli.log.rundata import read_run

NAMES = {"state": ("px", "py"), "input": ("u",), "disturbance": ("w",),
         "guard": ("floor",)}


@pytest.fixture(scope="module")
def logs(tmp_path_factory, run_hmpc) -> dict[str, Path]:
    """A short ball run and a short biped run (one contact each) through the CLI."""
    base = tmp_path_factory.mktemp("typed")
    out = {}
    for name, scenario, dur in (("ball", BALL, "0.6"),
                                ("biped", SCENARIOS / "biped_stairs.toml", "0.35")):
        proc = run_hmpc(["run", str(scenario), "-q", "--set", f"sim.duration={dur}",
                         "--out", str(base / name)], cwd=base)
        assert proc.returncode == 0, proc.stderr
        out[name] = base / name / "run.mcap"
    return out


@pytest.mark.slow
@pytest.mark.parametrize("system", ["ball", "biped"])
def test_every_topic_schema_is_inside_the_viewers_subset(logs, system):
    log = read_log(logs[system])
    assert set(log.schemas) >= set(TOPICS)
    for topic in TOPICS:
        assert viewer_problems(log.schemas[topic]) == [], topic


@pytest.mark.parametrize("system", ["ball", "biped"])
def test_every_logged_message_validates_against_its_schema(logs, system):
    log = read_log(logs[system])
    counts = {}
    for m in log.messages:
        assert validate(log.schemas[m.topic], m.data) == [], (m.topic, m.t)
        counts[m.topic] = counts.get(m.topic, 0) + 1
    assert counts["/sim/state"] > 10 and counts["/mpc/solve"] >= 1
    assert counts["/sim/event"] >= 1 and counts["/run/summary"] == 1


def test_states_plans_and_details_are_named(logs):
    log = read_log(logs["biped"])
    info = log.topic("/run/info")[0].data
    assert info["log_version"] == LOG_VERSION and info["mpc_kind"] == "walking"
    state = log.topic("/sim/state")[0].data
    assert list(state["x"]) == info["state_names"] and state["mode_name"] == "single_support"
    solve = log.topic("/mpc/solve")[0].data
    node = solve["plan"][0]  # plan[:].q1 ...: the names are the node's own fields
    assert list(node) == ["t", "seg", "mode", "mode_name", *info["state_names"],
                          *info["input_names"]]
    assert set(solve["detail"]) == {"segment", "elapsed", "warm", "touchdown", "final_hip"}
    plan = log.topic("/planner/plan")[0].data
    assert plan["detail"]["candidates"][0]["guard_name"].startswith("stair_")
    schema = log.schemas["/mpc/solve"]["properties"]["plan"]["items"]
    assert list(schema["properties"]) == list(node)
    rollout = log.schemas["/planner/plan"]["properties"]["rollout"]["items"]
    assert list(rollout["properties"]) == ["t", *info["state_names"]]


def test_read_run_gives_arrays_per_topic(logs):
    for system, n in (("ball", 4), ("biped", 12)):
        run = read_run(logs[system])
        assert run.complete and run.log_version == LOG_VERSION
        assert run.x.shape == (len(run.t), n) and np.all(np.isfinite(run.x))
        assert run.u.shape[0] == len(run.t) and run.events
        s = run.solves[0]
        assert s.x_plan.shape == (len(s.t_plan), n) and s.u_plan.shape[0] == len(s.t_plan)
        assert s.t_plan[0] == pytest.approx(s.t)
        assert run.summary["contacts"] == len(run.events)
        assert run.system["name"] == system


def test_the_generator_refuses_what_the_viewers_reject():
    @dataclass(frozen=True)
    class Bad:
        rows: tuple[tuple[float, ...], ...]

    with pytest.raises(TypeError, match="scalars or objects"):
        convert(Bad, {"rows": ()})  # converting is fine ...
        topic_schemas(NAMES, {"mpc": Bad})  # ... a schema of arrays of arrays is not
    assert viewer_problems({"type": ["number", "null"]}) == ["(root): type ['number', "
                                                             "'null'] is not one string"]
    assert viewer_problems({"type": "object"}) == ["(root): object without properties"]
    assert viewer_problems({"type": "array", "items": {"type": "array", "items": {
        "type": "number"}}}) == ["(root): array items must be scalars or objects"]


def test_validate_names_drift():
    schema = topic_schemas(NAMES)["/sim/state"][1]
    good = {"t": 0.0, "mode": 0, "mode_name": "a", "x": named(("px", "py"), [1, 2]),
            "u": {"u": 0.0}, "x_ref": {"px": None, "py": 1.0}, "w": {"w": 0.0}}
    assert validate(schema, good) == []
    assert validate(schema, {**good, "extra": 1}) == ["(root): unknown field 'extra'"]
    assert validate(schema, {**good, "mode": "zero"}) == ["mode: expected integer, got str"]
    assert validate(schema, {**good, "x": {"px": 1.0, "pz": 2.0}}) == [
        "x: unknown field 'pz'"]


def test_read_run_reads_the_older_untyped_layout(tmp_path):
    """Log version 1: plain arrays, scenario as an object, no names in the records."""
    path = tmp_path / "old.mcap"
    with Recorder(path) as rec:
        for topic in ("/run/info", "/sim/state", "/mpc/solve"):
            rec.add_topic(topic, "old", {"type": "object", "properties": {}})
        rec.write("/run/info", 0.0, {"scenario": {"system": {"name": "ball"}}, "seed": 3,
                                     "state_names": ["px", "py"]})
        for k in range(3):
            rec.write("/sim/state", 0.1 * k, {"t": 0.1 * k, "x": [k, -k], "mode": 0,
                                               "u": [0.0], "x_ref": [k, -k], "w": [None]})
        rec.write("/mpc/solve", 0.0, {"t": 0.0, "status": "ok", "success": True,
                                      "t_plan": [0.0, 0.1], "x_plan": [[0, 0], [1, -1]],
                                      "u_plan": [[0.0], [0.0]], "seg_plan": [0, 0],
                                      "shifted": 2})
    run = read_run(path)
    assert run.log_version == 1 and run.system == {"name": "ball"}
    assert run.x.tolist() == [[0, 0], [1, -1], [2, -2]] and np.isnan(run.w).all()
    assert run.solves[0].x_plan.shape == (2, 2) and run.solves[0].detail == {"shifted": 2}
    assert run.summary is None
    assert json.dumps(run.info)  # plain JSON


def test_plan_nodes_are_the_schemas_records_node_by_node():
    """plan_nodes' compiled dict display gives, per node, dict(zip(keys, row))."""
    from hmpc_cli.log.topics import PlanNode
    from hmpc_cli.log.schema import flat_keys
    from hmpc_cli.core.messages import Trajectory
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.log.geometry import record_maker
    from hmpc_cli.log.runlog import plan_nodes
    from hmpc_cli.systems.ball import BallParams

    model = build_system(BallParams())
    rng = np.random.default_rng(3)
    n = 7
    traj = Trajectory(t=np.linspace(0.0, 0.6, n), x=rng.normal(size=(n, 4)),
                      u=rng.normal(size=(n, 2)), mode=np.array([0, 0, 0, 1, 1, 1, 1]),
                      seg=np.array([0, 0, 0, 1, 1, 1, 1]))
    nodes = plan_nodes(traj, 2.0, model)
    keys = flat_keys(PlanNode, {"state": model.state_names, "input": model.input_names})
    modes = [m.name for m in model.modes]
    assert nodes == tuple(
        dict(zip(keys, [2.0 + traj.t[k], int(traj.seg[k]), int(traj.mode[k]),
                        modes[traj.mode[k]], *traj.x[k], *traj.u[k]], strict=True))
        for k in range(n))
    empty = Trajectory(t=np.zeros(0), x=np.zeros((0, 4)), u=np.zeros((0, 2)),
                       mode=np.zeros(0, int), seg=np.zeros(0, int))
    assert plan_nodes(empty, 0.0, model) == ()
    assert record_maker(("a", "b c", "'q'"))(1, 2.5, "x") == {"a": 1, "b c": 2.5, "'q'": "x"}
