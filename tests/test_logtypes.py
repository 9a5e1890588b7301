"""The typed run log: viewer-valid schemas generated from the types, messages that match
them, and ``read_run`` arrays for the ball, the biped and the older untyped layout."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from conftest import BALL, SCENARIOS, standard_schema_errors
from hmpc_cli.log.topics import LOG_VERSION, TOPICS, named, topic_schemas
from hmpc_cli.log.schema import convert, validate, viewer_problems
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.reader import read_log
from hmpc_cli.log.rundata import read_run

NAMES = {"state": ("px", "py"), "input": ("u",), "disturbance": ("w",),
         "guard": ("floor",)}


@pytest.fixture(scope="module")
def logs(tmp_path_factory, invoke_hmpc) -> dict[str, Path]:
    """A short ball run and a short biped run (one contact each) through the CLI."""
    base = tmp_path_factory.mktemp("typed")
    out = {}
    for name, scenario, dur in (("ball", BALL, "0.6"),
                                ("biped", SCENARIOS / "biped_stairs.toml", "0.35")):
        proc = invoke_hmpc(["run", str(scenario), "-q", "--set", f"sim.duration={dur}",
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


@pytest.mark.parametrize("system", ["ball", "biped"])
def test_every_message_validates_with_a_standard_validator(logs, system):
    """jsonschema, not only the project's validator: no null where the schema says object
    (the ball's terrain, a planner without detail) or number."""
    log = read_log(logs[system])
    assert log.schemas.keys() >= set(TOPICS)
    assert standard_schema_errors(log) == []
    assert b"null" not in b"".join(m.data for m in log.raw if m.topic in TOPICS)


def test_none_nan_and_inf_are_left_out_and_the_message_still_validates(tmp_path):
    """A failed solve (NaN cost, inf violation, no schedule, no detail) as written."""
    import jsonschema

    from hmpc_cli.log.topics import MpcSolve

    names = {**NAMES, "body": ()}
    schema = topic_schemas(names)["/mpc/solve"][1]
    solve = MpcSolve(0.1, "period", "error: NaN", False, 0, 0.01, float("nan"),
                     float("inf"), 0.0, False, None, ())
    rec = Recorder(tmp_path / "run.mcap")
    rec.add_topic("/mpc/solve", "hmpc.MpcSolve", schema)
    rec.write("/mpc/solve", 0.1, solve)
    rec.close()
    (m,) = read_log(tmp_path / "run.mcap").topic("/mpc/solve")
    assert "cost" not in m.data and "max_violation" not in m.data
    assert "schedule" not in m.data and "detail" not in m.data
    assert list(jsonschema.Draft202012Validator(schema).iter_errors(m.data)) == []
    assert validate(schema, m.data) == []
    assert validate(schema, {**m.data, "schedule": None}) == [
        "schedule: null where the schema says object"]


def test_a_non_finite_number_inside_an_array_is_null_and_fails_its_schema(tmp_path):
    """The exception log-format.md names: inside an array of numbers a NaN stays in place
    as null, which the array's items (type number, no type list) do not admit."""
    import jsonschema

    from hmpc_cli.log.topics import MpcSolve, ScheduleRec

    schema = topic_schemas({**NAMES, "body": ()})["/mpc/solve"][1]
    sched = ScheduleRec((0, 1), ("a", "b"), (2,), ("g",), (float("nan"),), 0.0)
    solve = MpcSolve(0.1, "period", "Solve_Succeeded", True, 3, 0.01, 1.0, 0.0, 0.0, True,
                     sched, ())
    rec = Recorder(tmp_path / "run.mcap")
    rec.add_topic("/mpc/solve", "hmpc.MpcSolve", schema)
    rec.write("/mpc/solve", 0.1, solve)
    rec.close()
    (m,) = read_log(tmp_path / "run.mcap").topic("/mpc/solve")
    assert m.data["schedule"]["durations"] == [None]
    assert validate(schema, m.data) == [
        "schedule.durations[0]: null where the schema says number"]
    assert len(list(jsonschema.Draft202012Validator(schema).iter_errors(m.data))) == 1


def test_summary_json_and_the_run_summary_topic_differ_as_running_md_says():
    """Same fields in the same order and the same values, but x_end, contacts_by_guard,
    failure_statuses and non-finite numbers (running.md, "What a run gives you")."""
    from types import SimpleNamespace

    from hmpc_cli.log.books import RunResult
    from hmpc_cli.log.recorder import to_json_bytes
    from hmpc_cli.log.runlog import summary_record
    from hmpc_cli.run.runner import summary_text

    model = SimpleNamespace(state_names=("px", "py"), n_x=2,
                            guards=[SimpleNamespace(name="floor"), SimpleNamespace(name="wall")])
    r = RunResult("s", 3, x_end=[1.0, 2.0], contacts=3, solves=4, solver_failures=3,
                  contacts_by_guard={"floor": 1, "wall": 0, "ledge": 2},
                  failure_statuses={"b_status": 1, "a_status": 2}, warnings=["w"])
    file = json.loads(summary_text(r))
    topic = json.loads(to_json_bytes(summary_record(r, model)))
    assert "real_time" not in file and "real_time" not in topic  # time paused
    assert file["x_end"] == [1.0, 2.0] and topic["x_end"] == {"px": 1.0, "py": 2.0}
    assert file["contacts_by_guard"] == {"floor": 1, "wall": 0, "ledge": 2}
    assert topic["contacts_by_guard"] == {"floor": 1, "wall": 0}
    assert file["failure_statuses"] == {"b_status": 1, "a_status": 2}
    assert topic["failure_statuses"] == [{"status": "a_status", "count": 2},
                                         {"status": "b_status", "count": 1}]
    nulls = [k for k, v in file.items() if v is None]
    assert nulls == ["final_error", "solve_time_median", "solve_time_p95", "solve_time_max",
                     "plan_time_median"]
    assert list(topic) == [k for k in file if k not in nulls]
    shapes = {"x_end", "contacts_by_guard", "failure_statuses"}
    assert {k: v for k, v in topic.items() if k not in shapes} == \
        {k: v for k, v in file.items() if k not in shapes and k not in nulls}
    model.n_x = 3  # a plant whose state is not the model's size
    assert json.loads(to_json_bytes(summary_record(r, model)))["x_end"] == {}
    # compute time charged: the same object in both, a statistic of no solve left out
    r.real_time = {"latency": "model", "period": 0.1, "delay_median": float("nan"),
                   "delay_p95": float("nan"), "delay_max": float("nan"),
                   "charged_solves": 0, "late_solves": 0, "dropped_solves": 0,
                   "preempted_solves": 0}
    file = json.loads(summary_text(r))
    topic = json.loads(to_json_bytes(summary_record(r, model)))
    assert file["real_time"]["delay_max"] is None and list(file)[-1] == "real_time"
    assert topic["real_time"] == {k: v for k, v in file["real_time"].items()
                                  if v is not None}


def test_the_books_count_a_solve_late_by_the_time_it_kept_the_solver_busy():
    """real_time from the clock's charges: late when busy over the period (a dropped or
    stopped solve's busy time is not its charge); the delays are the charges; before any
    solve, none; the summary's row says it."""
    from hmpc_cli.cli.run import real_time_text
    from hmpc_cli.log.books import RunBooks

    books = RunBooks("s", 0)
    assert books.result.real_time is None  # time paused
    books.charge_time("model", 0.1)
    none = books.result.real_time
    assert (none["charged_solves"], none["late_solves"]) == (0, 0)
    assert none["delay_median"] != none["delay_median"]  # NaN: no charged solve
    assert real_time_text(none) == ("0 of 0 solves kept the solver busy over the 100.0 ms "
                                    "MPC period; charged median / p95 / max - / - / -")
    # /run/summary leaves the statistics of no solve out
    topic = {k: v for k, v in none.items() if not k.startswith("delay_")}
    assert real_time_text(topic) == real_time_text(none)
    books.time_charged([(0.05, 0.05), (0.3, 0.1), (0.3, 0.12), (0.2, 0.06)], 1, 1)
    rt = books.result.real_time
    assert rt == {"latency": "model", "period": 0.1, "delay_median": 0.25,
                  "delay_p95": pytest.approx(0.3), "delay_max": 0.3, "charged_solves": 4,
                  "late_solves": 1, "dropped_solves": 1, "preempted_solves": 1}
    assert real_time_text(rt) == (
        "1 of 4 solves kept the solver busy over the 100.0 ms MPC period; charged median / "
        "p95 / max 250.0 ms / 300.0 ms / 300.0 ms; 1 dropped (over sim.solve_budget); 1 "
        "stopped by a contact")


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


def test_read_run_gives_the_topic_types_back(logs):
    """One type per message both ways: what was written is what read_run returns."""
    from hmpc_cli.core.messages import BuildInfo
    from hmpc_cli.log.geometry import GeometryRec
    from hmpc_cli.log.topics import (
        MpcSolve, PlanArrays, PlannerCall, RolloutArrays, RunInfo, ScheduleRec,
        Summary, Versions)

    for system, n in (("ball", 4), ("biped", 12)):
        run = read_run(logs[system])
        assert run.complete and run.log_version == LOG_VERSION
        assert run.x.shape == (len(run.t), n) and np.all(np.isfinite(run.x))
        assert run.u.shape[0] == len(run.t) and run.events
        assert isinstance(run.info, RunInfo) and isinstance(run.info.versions, Versions)
        assert run.info.system == system and run.info.state_names == run.state_names
        assert isinstance(run.info.build, BuildInfo) and run.info.build.cache
        assert isinstance(run.geometry, GeometryRec)
        assert (run.geometry.terrain is None) == (system == "ball")  # left out, read None
        s = run.solves[0]
        assert isinstance(s, MpcSolve) and isinstance(s.plan, PlanArrays)
        assert isinstance(s.schedule, ScheduleRec) and s.schedule.guard_names
        assert s.plan.x.shape == (len(s.plan.t), n) and s.plan.u.shape[0] == len(s.plan.t)
        assert s.plan.t[0] == pytest.approx(s.t) and s.plan.mode.shape == s.plan.t.shape
        p = run.planner[0]
        assert isinstance(p, PlannerCall) and isinstance(p.rollout, RolloutArrays)
        assert isinstance(run.summary, Summary) and run.summary.contacts == len(run.events)
        assert run.summary.x_end.keys() == set(run.state_names)
        assert run.system["name"] == system
    ball, biped = read_run(logs["ball"]), read_run(logs["biped"])
    # a plug-in's detail comes back as a record typed from the log's own schema
    assert type(ball.solves[0].detail).__name__ == "ChainDetail"
    assert ball.solves[0].detail.counts and ball.planner[0].detail is None
    cand = biped.planner[0].detail.candidates[0]
    assert cand.guard_name.startswith("stair_") and isinstance(cand.success, bool)


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
            "u": {"u": 0.0}, "x_ref": {"py": 1.0}, "w": {"w": 0.0}}
    assert validate(schema, good) == []  # a value left out (NaN when written)
    assert validate(schema, {**good, "x_ref": {"px": None, "py": 1.0}}) == [
        "x_ref.px: null where the schema says number"]
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
    assert run.solves[0].plan.x.shape == (2, 2) and run.solves[0].detail.shifted == 2
    assert run.summary is None
    assert run.info.seed == 3 and run.info.state_names == ("px", "py")
    assert json.loads(run.info.scenario_json) == {"system": {"name": "ball"}}


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


def _logged_classes() -> list[type]:
    """Every dataclass a topic's or a bundled plug-in's detail schema is made of, and the
    other dataclasses of topics.py and geometry.py (a plan's and a rollout's arrays)."""
    import dataclasses
    import inspect

    from hmpc_cli.core.registry import registry
    from hmpc_cli.log import geometry, topics
    from hmpc_cli.log.schema import schema_classes

    reg = registry()
    roots = [cls for _, cls in TOPICS.values()]
    roots += [s.detail for specs in (reg.planners, reg.mpcs) for s in specs.values()
              if s.detail is not None and s.detail.__module__.startswith("hmpc_cli.")]
    out = dict.fromkeys(c for root in roots for c in schema_classes(root))
    out.update(dict.fromkeys(
        v for mod in (topics, geometry) for v in vars(mod).values()
        if inspect.isclass(v) and dataclasses.is_dataclass(v) and v.__module__ == mod.__name__))
    return list(out)


def test_every_logged_field_is_described():
    """Each field of a logged record has a description in its class's ``Attributes:``
    (docs/log-format.md's "what"), and none names a field the class does not have;
    the logged schemas carry no descriptions (the logs do not depend on the wording)."""
    import dataclasses

    from hmpc_cli.core.registry import registry
    from hmpc_cli.log.schema import field_docs

    classes = _logged_classes()
    assert {"RunInfo", "Versions", "GeometryRec", "BuildInfo", "PlanNode", "RolloutNode",
            "PlanArrays", "ChainDetail", "WalkingDetail", "FootholdsDetail",
            "Candidate"} <= {c.__name__ for c in classes}
    missing, stale = [], []
    for cls in classes:
        docs, names = field_docs(cls), [f.name for f in dataclasses.fields(cls)]
        missing += [f"{cls.__module__}.{cls.__name__}.{n}" for n in names if not docs.get(n)]
        stale += [f"{cls.__name__}.{n}" for n in docs if n not in names]
    assert not missing, f"fields without a description in their class's Attributes: {missing}"
    assert not stale, f"Attributes: entries of no field: {stale}"
    reg = registry()
    for p in reg.planners.values():
        for m in reg.mpcs.values():
            schemas = topic_schemas(NAMES, {"planner": p.detail, "mpc": m.detail})
            assert "description" not in json.dumps(schemas)


def test_field_docs_reads_the_attributes_section():
    from hmpc_cli.log.schema import field_docs

    @dataclass(frozen=True)
    class Rec:
        """A record.

        Attributes:
            a: the first line
                and its continuation [s].

            b (int): a typed entry.
            d:
                on the next line only.

        Note:
            not an attribute: the section ended.
        """

        a: float
        b: int
        c: str
        d: str

    @dataclass(frozen=True)
    class Sub(Rec):
        """A sub-record (its own entry wins).

        Attributes:
            b: overridden.
            e: new.
        """

        e: int = 0

    assert field_docs(Rec) == {"a": "the first line and its continuation [s].",
                               "b": "a typed entry.", "d": "on the next line only."}
    assert "c" not in field_docs(Rec)  # a field without a description: not there
    assert field_docs(Sub) == {**field_docs(Rec), "b": "overridden.", "e": "new."}

    @dataclass
    class Bare:
        x: int

    @dataclass
    class Bad:
        """Bad.

        Attributes:
            x is the value.
        """

        x: int

    assert field_docs(Bare) == {}
    with pytest.raises(ValueError, match="Bad: Attributes: entry 'x is the value.'"):
        field_docs(Bad)
