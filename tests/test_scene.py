"""The run log's 3D scene: foxglove.SceneUpdate on /scene, from real ball and biped runs."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from google.protobuf import descriptor_pool
from google.protobuf.descriptor_pb2 import FileDescriptorSet

from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.reader import read_log
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.runner import run_scenario
from hmpc_cli.run.scenario import load_scenario
from hmpc_cli.log.scene import FRAME, STATIC, TOPICS, TUBE_SPHERES

from conftest import BALL, SCENARIOS

CENTER, RADIUS = (4.0, 3.5), 0.8


def _run(tmp_path_factory, scenario, name, *sets):
    sc, text = load_scenario(scenario, list(sets))
    out = tmp_path_factory.mktemp(name) / "run"
    run_scenario(sc, text, out)
    return sc, read_log(out / "run.mcap"), out


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    return _run(tmp_path_factory, BALL, "ball", "sim.duration=0.5")


@pytest.fixture(scope="module")
def moved(tmp_path_factory):
    return _run(tmp_path_factory, BALL, "moved", "sim.duration=0.1",
                f"system.circle_center=[{CENTER[0]}, {CENTER[1]}]",
                f"system.circle_radius={RADIUS}")


@pytest.fixture(scope="module")
def biped(tmp_path_factory):
    return _run(tmp_path_factory, SCENARIOS / "biped_stairs.toml", "biped", "sim.duration=0.3")


def updates(log):
    """(log_time_ns, SceneUpdate) of every /scene/* message, decoded with the published type."""
    return [(m.log_time_ns, SceneUpdate.FromString(m.data)) for m in log.raw
            if m.topic in TOPICS]


def entities(log, entity_id):
    return [(ns, e) for ns, u in updates(log) for e in u.entities if e.id == entity_id]


def xyz(p):
    return np.array([p.x, p.y, p.z])


def test_schema_is_the_published_protobuf_scene_update(ball):
    _, log, _ = ball
    assert set(log.raw_schemas) == set(TOPICS)
    schema = log.raw_schemas[STATIC]
    assert all(log.raw_schemas[t] == schema for t in TOPICS)
    assert schema.name == "foxglove.SceneUpdate" and schema.encoding == "protobuf"
    fds = FileDescriptorSet.FromString(schema.data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    assert pool.FindMessageTypeByName("foxglove.SceneUpdate").full_name == "foxglove.SceneUpdate"
    assert {m.encoding for m in log.raw} == {"protobuf"}
    assert not set(TOPICS) & set(log.schemas)
    assert not set(TOPICS) & {m.topic for m in log.messages}


def test_static_entities_appear_once_at_t0(ball):
    _, log, _ = ball
    ups = updates(log)
    ids = [e.id for _, u in ups for e in u.entities if e.id.startswith("static/")]
    assert len(log.raw_topic(STATIC)) == 1
    assert sorted(ids) == ["static/circle", "static/floor", "static/wall"]
    ns, first = ups[0]
    assert ns == 0 and {e.id for e in first.entities} == set(ids)
    for e in first.entities:
        assert e.frame_locked and e.frame_id == FRAME
        assert e.lifetime.seconds == 0 and e.lifetime.nanos == 0


def test_ball_sphere_is_at_the_logged_state(ball):
    sc, log, _ = ball
    states = {m.log_time_ns: list(m.data["x"].values()) for m in log.topic("/sim/state")}
    bodies = entities(log, "body")
    from hmpc_cli.log.scene import MAX_RATE_HZ

    # 0.5 s of 100 Hz states drawn at <= 30 Hz: every 4th sample (25 Hz), 13 of them
    assert len(bodies) == 13
    times = [ns for ns, _ in bodies]
    assert min(np.diff(times)) >= 1e9 / MAX_RATE_HZ - 1
    for ns, e in bodies:
        (sphere,) = e.spheres
        x = states[ns]
        assert xyz(sphere.pose.position) == pytest.approx([x[0], 0.0, x[1]], abs=1e-12)
        assert sphere.size.x == pytest.approx(2 * sc.system.radius)


def test_guards_are_drawn_where_the_parameters_put_them(moved):
    sc, log, _ = moved
    statics = {e.id: e for _, e in entities(log, "static/circle")}
    (line,) = statics["static/circle"].lines
    pts = np.array([xyz(p) for p in line.points])
    assert len(pts) >= 32 and np.all(pts[:, 1] == 0.0)
    dist = np.hypot(pts[:, 0] - CENTER[0], pts[:, 2] - CENTER[1])
    assert dist == pytest.approx(RADIUS, abs=1e-12)
    ((_, floor),) = entities(log, "static/floor")
    fx = sc.system.floor_extent
    assert [xyz(p).tolist() for p in floor.lines[0].points] == [[fx[0], 0, 0], [fx[1], 0, 0]]


def test_plan_line_has_a_vertex_per_node(ball):
    _, log, _ = ball
    solves = {m.log_time_ns: m.data for m in log.topic("/mpc/solve")}
    plans = entities(log, "plan")
    assert len(plans) == len(solves)
    radius = log.topic("/run/info")[0].data["margins"]["radius"]
    tubes = dict(entities(log, "tube"))
    for ns, e in plans:
        x_plan = np.array([[n[k] for k in ("px", "py", "vx", "vy")]
                           for n in solves[ns]["plan"]])
        segs = [n["seg"] for n in solves[ns]["plan"]]
        runs = [k for k in np.split(np.arange(len(segs)),
                                    np.flatnonzero(np.diff(segs)) + 1) if len(k) >= 2]
        assert len(e.lines) == len(runs)  # one strip per domain segment: broken at resets
        for line, nodes in zip(e.lines, runs, strict=True):
            pts = np.array([xyz(p) for p in line.points])
            assert pts.shape == (len(nodes), 3)
            assert pts[:, [0, 2]] == pytest.approx(x_plan[nodes, 0:2], abs=1e-12)
        spheres = tubes[ns].spheres
        assert len(spheres) == min(len(x_plan), TUBE_SPHERES)
        assert all(s.size.x == pytest.approx(2 * radius) for s in spheres)
    (rollout,) = entities(log, "rollout")
    (call,) = log.topic("/planner/plan")
    # one strip per domain segment of the rollout (segments of one node draw nothing)
    sizes = [len(line.points) for line in rollout[1].lines]
    assert sizes and min(sizes) >= 2 and sum(sizes) <= len(call.data["rollout"])


def test_biped_links_join_the_logged_points_world(biped):
    sc, log, _ = biped
    system = build_system(sc.system)
    names, skeleton = system.point_names, system.skeleton
    states = {m.log_time_ns: list(m.data["x"].values()) for m in log.topic("/sim/state")}
    bodies = entities(log, "body")
    assert bodies
    for ns, e in bodies:
        pw = np.asarray(system.output("points_world")(states[ns]))  # (2, 6)
        want = [pw[:, names.index(n)] for line in skeleton
                for a, b in zip(line[:-1], line[1:], strict=True) for n in (a, b)]
        (links,) = e.lines
        got = np.array([xyz(p) for p in links.points])
        assert got[:, [0, 2]] == pytest.approx(np.array(want), abs=1e-12)
        feet = [xyz(s.pose.position)[[0, 2]] for s in e.spheres]
        assert feet[0] == pytest.approx(pw[:, names.index("stance_foot")], abs=1e-12)
        assert feet[1] == pytest.approx(pw[:, names.index("swing_foot")], abs=1e-12)


def test_biped_stairs_and_plans(biped):
    sc, log, _ = biped
    terrain = build_system(sc.system).terrain
    ((_, stairs),) = entities(log, "static/stairs")
    pts = np.array([xyz(p) for p in stairs.lines[0].points])
    for a, b, h in terrain.segments:  # every segment's edge is a vertex
        assert any(np.allclose(p, [a, 0, h]) for p in pts)
        assert any(np.allclose(p, [b, 0, h]) for p in pts)
    solves = {m.log_time_ns: m.data for m in log.topic("/mpc/solve")}
    plans = entities(log, "plan")
    assert plans and len(plans) == len(solves)
    for ns, e in plans:
        # hip and swing foot, each broken at the reset: one strip per swing (domain segment)
        segs = [n["seg"] for n in solves[ns]["plan"]]
        per_seg = sorted(segs.count(s) for s in set(segs) if segs.count(s) >= 2)
        assert len(e.lines) == 2 * len(per_seg)
        assert sorted(len(line.points) for line in e.lines) == sorted(per_seg * 2)


def test_truncated_log_reads_both_encodings_front_to_back(ball, tmp_path):
    _, full, out = ball
    cut = tmp_path / "cut.mcap"
    shutil.copy(out / "run.mcap", cut)
    data = cut.read_bytes()
    cut.write_bytes(data[:-40])  # no footer: the linear scan of every chunk
    log = read_log(cut)
    assert not log.complete
    assert [m.data for m in log.messages] == [m.data for m in full.messages]
    assert [m.data for m in log.raw] == [m.data for m in full.raw]
    assert log.raw_schemas[STATIC].name == "foxglove.SceneUpdate"


def test_recorder_keeps_json_and_protobuf_topics_apart(tmp_path):
    path = tmp_path / "r.mcap"
    with Recorder(path) as rec:
        rec.add_topic("/j", "J", {"type": "object"})
        rec.add_protobuf_topic("/p", SceneUpdate)
        with pytest.raises(TypeError):
            rec.write("/p", 0.0, {"a": 1})
        with pytest.raises(KeyError):
            rec.write_protobuf("/j", 0.0, SceneUpdate())
        rec.write("/j", 0.0, {"a": 1})
        rec.write_protobuf("/p", 0.5, SceneUpdate(entities=[{"id": "e"}]))
    log = read_log(path)
    assert [m.data for m in log.messages] == [{"a": 1}]
    (raw,) = log.raw
    assert raw.t == 0.5 and SceneUpdate.FromString(raw.data).entities[0].id == "e"


def test_points_wire_bytes_equal_the_message_api():
    """The fast line encoding parses to exactly the points the message API builds."""
    from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive

    from hmpc_cli.log.scene import points_wire

    pts = np.array([[0.0, 1.5, -2.0], [np.nan, 0.0, 1e300], [-0.0, 3.25, 7.0]])
    fast, slow = LinePrimitive(thickness=0.1), LinePrimitive(thickness=0.1)
    fast.MergeFromString(points_wire(LinePrimitive.DESCRIPTOR.fields_by_name["points"].number,
                                     pts))
    for x, y, z in pts.tolist():
        slow.points.add(x=x, y=y, z=z)
    got = np.array([[p.x, p.y, p.z] for p in fast.points])
    assert np.array_equal(got, pts, equal_nan=True)
    assert LinePrimitive.FromString(fast.SerializeToString()).points[2].y == 3.25
    assert [[p.x, p.y, p.z] for p in slow.points][0] == [0.0, 1.5, -2.0]


def test_spheres_wire_bytes_equal_the_message_api():
    from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
    from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive

    from hmpc_cli.log.scene import spheres_wire

    centers = np.array([[0.0, 0.0, 0.0], [1.5, -2.0, 3.25], [1e-300, 7.0, -0.0]])
    rest = SpherePrimitive(size={"x": 0.1, "y": 0.1, "z": 0.1},
                           color={"r": 0.1, "g": 0.6, "b": 0.1, "a": 0.25}).SerializeToString()
    slow = SceneEntity(id="tube")
    for c in centers:
        s = slow.spheres.add()
        s.pose.position.x, s.pose.position.y, s.pose.position.z = c
        s.pose.orientation.w = 1.0
        s.size.x = s.size.y = s.size.z = 0.1
        s.color.r, s.color.g, s.color.b, s.color.a = 0.1, 0.6, 0.1, 0.25
    fast = SceneEntity(id="tube")
    fast.MergeFromString(spheres_wire(SceneEntity.DESCRIPTOR.fields_by_name["spheres"].number,
                                      centers, rest))
    assert fast == slow and len(fast.spheres) == 3
    assert SceneEntity.FromString(fast.SerializeToString()) == slow


def test_scene_writer_bytes_equal_the_message_api():
    """The wire-composed SceneUpdate parses to what the published classes build."""
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    from hmpc_cli.core.drawing import Ball, Drawing, Polyline
    from hmpc_cli.log.scene import FRAME, SceneWriter

    class Capture:
        def __init__(self):
            self.out = []

        def add_protobuf_topic(self, topic, message_type):
            pass

        def write_protobuf_bytes(self, topic, t, data):
            self.out.append((topic, t, data))

    drawing = Drawing(points=lambda x: np.array([[x[0], 0.0], [x[1], 1.0]]),
                      point_names=("a", "b"), links=(("a", "b"),),
                      balls=(Ball("a", 0.05, (0.1, 0.2, 0.3, 1.0)),),
                      static=(Polyline("floor", ((0.0, 0.0), (2.0, 0.0))),))
    rec = Capture()
    writer = SceneWriter(rec, drawing, max_rate_hz=1e9)
    writer.start()
    writer.state(1.25, np.array([0.5, -0.5]))
    (_, _, static), (_, t, body) = rec.out
    assert t == 1.25
    want = SceneUpdate()
    e = want.entities.add(frame_id=FRAME, id="body")
    e.timestamp.FromNanoseconds(1_250_000_000)
    line = e.lines.add(type=2, thickness=drawing.link_thickness)  # LINE_LIST
    line.pose.position.SetInParent()  # an explicit origin, as the scene has always written
    line.pose.orientation.w = 1.0
    line.color.r, line.color.g, line.color.b, line.color.a = drawing.link_color
    line.points.add(x=0.5, y=0.0, z=-0.5)
    line.points.add(x=0.0, y=0.0, z=1.0)
    s = e.spheres.add()
    s.pose.position.x, s.pose.position.z = 0.5, -0.5
    s.pose.orientation.w = 1.0
    s.size.x = s.size.y = s.size.z = 0.1
    s.color.r, s.color.g, s.color.b, s.color.a = 0.1, 0.2, 0.3, 1.0
    assert SceneUpdate.FromString(body) == want
    floor = SceneUpdate.FromString(static).entities[0]
    assert floor.id == "static/floor" and floor.frame_locked and floor.frame_id == FRAME
    assert not floor.HasField("timestamp") or floor.timestamp.ToNanoseconds() == 0
