"""The run log's 3D scene: ``foxglove.SceneUpdate`` messages on the ``/scene/*`` topics.

Built from the system's :class:`~hmpc_cli.core.drawing.Drawing` (None: no scene) with the
published Foxglove protobuf schemas (``foxglove_schemas_protobuf``), so Foxglove and
Lichtblick draw a run in their 3D panel. All entities are in frame ``world``; the system's
plane (a, b) stands upright as world (a, 0, b): z is the plane's "up".

Topics and entities (ids), all entities with lifetime 0 (kept until replaced by id):

* ``/scene/static``: ``static/<name>``, the drawing's static polylines (guards, walls,
  terrain), written once at t = 0, ``frame_locked``;
* ``/scene/body``: ``body``, links (line list) and balls (spheres) at each /sim/state
  sample, at most ``max_rate_hz`` (30 Hz) times per simulated second (the scene's share
  of the logging overhead: ``benchmarks/bench_logging.py``);
* ``/scene/plan``: at each MPC solve, ``plan``, per trace point one line strip per domain
  segment of the plan through its nodes (one vertex per node; the line breaks at each
  reset, where the biped's legs swap), and ``tube``, spheres of the MPC's tube radius (its
  margins' ``radius``, in the state norm, drawn in the plane) around the first trace
  point at up to :data:`TUBE_SPHERES` plan nodes (only with margins);
* ``/scene/rollout``: ``rollout``, at each planner call with a trajectory, per trace point
  one line strip per domain segment.

One topic per kind because a viewer that seeks shows the latest message of each topic:
the static geometry, the body and the current plan all stay on screen after a seek.

The protobuf modules are imported when a writer is made (not at import time).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from hmpc_cli.core.drawing import Drawing, Rgba
from hmpc_cli.core.messages import Plan, Trajectory

__all__ = ["BODY", "FRAME", "MAX_RATE_HZ", "PLAN", "ROLLOUT", "STATIC", "TOPICS", "TUBE_SPHERES",
           "SceneWriter", "open_scene", "to_world"]

STATIC, BODY, PLAN, ROLLOUT = "/scene/static", "/scene/body", "/scene/plan", "/scene/rollout"
TOPICS = (STATIC, BODY, PLAN, ROLLOUT)
FRAME = "world"
MAX_RATE_HZ = 30.0
TUBE_SPHERES = 12
_NS_PER_S = 1_000_000_000
PLAN_COLORS: tuple[Rgba, ...] = ((0.1, 0.6, 0.1, 1.0), (0.6, 0.2, 0.7, 1.0),
                                 (0.1, 0.5, 0.8, 1.0))
REJECTED: Rgba = (0.8, 0.2, 0.2, 0.6)
ORANGE: Rgba = (0.95, 0.65, 0.1, 0.8)
TUBE: Rgba = (0.1, 0.6, 0.1, 0.25)


#: one Point3 as a repeated-field entry: tag, length 27, then x, y, z as tagged doubles
_POINT = np.dtype([("tag", "u1"), ("len", "u1"), ("tx", "u1"), ("x", "<f8"), ("ty", "u1"),
                   ("y", "<f8"), ("tz", "u1"), ("z", "<f8")])


def points_wire(field_number: int, world: np.ndarray) -> bytes:
    """Protobuf wire bytes of points (K, 3) as repeated ``Point3`` field ``field_number``.

    Parsed into a message (``MergeFromString``) they append K points, exactly as K
    ``points.add(x=, y=, z=)`` calls do (x, y, z are Point3's double fields 1, 2, 3), at a
    fraction of the cost: a plan's line is drawn at every MPC solve. ``field_number`` < 16.
    """
    pts = np.asarray(world, dtype=float).reshape(-1, 3)
    rec = np.empty(len(pts), dtype=_POINT)
    rec["tag"], rec["len"] = (field_number << 3) | 2, 27
    rec["tx"], rec["ty"], rec["tz"] = (1 << 3) | 1, (2 << 3) | 1, (3 << 3) | 1
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    return rec.tobytes()


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        byte, n = n & 0x7F, n >> 7
        out.append(byte | (0x80 if n else 0))
        if not n:
            return bytes(out)


#: a pose message at (x, y, z), no rotation: position Vector3 (field 1, three tagged
#: doubles), orientation Quaternion (field 2) with only w = 1 (field 4)
_POSE_HEAD = bytes([0x0A, 27, 0x09])
_POSE_TAIL = bytes([0x12, 9, 0x21]) + np.float64(1.0).astype("<f8").tobytes()


def spheres_wire(field_number: int, centers: np.ndarray, rest: bytes) -> bytes:
    """Protobuf wire bytes of spheres at world points (K, 3) as repeated field ``field_number``.

    Each sphere is ``SpherePrimitive`` bytes: its pose (field 1) at the centre, then
    ``rest`` (the serialized size and colour, the same for all). Parsed into an entity
    (``MergeFromString``) they append K spheres, as K ``spheres.add(...)`` calls do.
    """
    c = np.asarray(centers, dtype=float).reshape(-1, 3)
    dtype, head, tail = _sphere_layout(field_number, rest)
    rec = np.empty(len(c), dtype=dtype)
    rec["head"], rec["tail"] = head, tail
    rec["ty"], rec["tz"] = 0x11, 0x19
    rec["x"], rec["y"], rec["z"] = c[:, 0], c[:, 1], c[:, 2]
    return rec.tobytes()


@lru_cache(maxsize=64)
def _sphere_layout(field_number: int, rest: bytes) -> tuple[np.dtype, np.void, np.void]:
    """(record dtype, head, tail) of one sphere's wire bytes around its centre's doubles."""
    pose = len(_POSE_HEAD) + 8 + 1 + 8 + 1 + 8 + len(_POSE_TAIL)
    body = bytes([0x0A]) + _varint(pose) + _POSE_HEAD
    head = _varint((field_number << 3) | 2) + _varint(len(body) + pose - len(_POSE_HEAD)
                                                      + len(rest)) + body
    tail = _POSE_TAIL + rest
    dtype = np.dtype([("head", f"V{len(head)}"), ("x", "<f8"), ("ty", "u1"), ("y", "<f8"),
                      ("tz", "u1"), ("z", "<f8"), ("tail", f"V{len(tail)}")])
    return dtype, np.void(head), np.void(tail)


def to_world(points: np.ndarray) -> np.ndarray:
    """Plane points (..., 2) -> world points (..., 3) = (a, 0, b) [m]."""
    p = np.asarray(points, dtype=float)
    return np.stack([p[..., 0], np.zeros(p.shape[:-1]), p[..., 1]], axis=-1)


def _field(number: int, payload: bytes) -> bytes:
    """A length-delimited protobuf field: tag, length, payload."""
    return _varint((number << 3) | 2) + _varint(len(payload)) + payload


def _timestamp(t: float) -> bytes:
    """``google.protobuf.Timestamp`` bytes of sim time t [s] >= 0 (zero fields omitted)."""
    sec, nanos = divmod(round(t * _NS_PER_S), _NS_PER_S)
    return (b"\x08" + _varint(sec) if sec else b"") + (b"\x10" + _varint(nanos) if nanos
                                                        else b"")


class SceneWriter:
    """Writes the ``/scene/*`` topics of one run (see the module docstring).

    Messages are composed as protobuf wire bytes (field by field, the constant parts
    serialized once with the published classes): what the published ``SceneUpdate``
    parses, at a fraction of the message API's cost (tests decode every message).

    Args:
        recorder: an open :class:`~hmpc_cli.log.recorder.Recorder` (protobuf topics).
        drawing: the system's drawing.
        tube_radius: the MPC's tube radius (margins ``radius``), or None (no tube).
        max_rate_hz: at most this many body updates per simulated second.
    """

    def __init__(self, recorder: Any, drawing: Drawing, tube_radius: float | None = None,
                 max_rate_hz: float = MAX_RATE_HZ) -> None:
        from foxglove_schemas_protobuf import (
            Color_pb2, LinePrimitive_pb2, Pose_pb2, Quaternion_pb2, SceneEntity_pb2,
            SceneUpdate_pb2, SpherePrimitive_pb2, Vector3_pb2)

        self.pb = {"Color": Color_pb2.Color, "Line": LinePrimitive_pb2.LinePrimitive,
                   "Pose": Pose_pb2.Pose, "Quaternion": Quaternion_pb2.Quaternion,
                   "Sphere": SpherePrimitive_pb2.SpherePrimitive,
                   "Vector3": Vector3_pb2.Vector3}
        entity = SceneEntity_pb2.SceneEntity.DESCRIPTOR.fields_by_name
        self._f = {"points": LinePrimitive_pb2.LinePrimitive.DESCRIPTOR.fields_by_name[
            "points"].number, "lines": entity["lines"].number,
            "spheres": entity["spheres"].number, "timestamp": entity["timestamp"].number,
            "frame_id": entity["frame_id"].number, "id": entity["id"].number,
            "frame_locked": entity["frame_locked"].number,
            "entities": SceneUpdate_pb2.SceneUpdate.DESCRIPTOR.fields_by_name[
                "entities"].number}
        self._templates: dict[tuple, bytes] = {}  # constant parts of primitives, by look
        self.rec, self.drawing = recorder, drawing
        #: the body's columns of its link segments' ends, in order (a LINE_LIST's points)
        self._link_idx = [i for line in drawing.links
                          for a, b in zip(line[:-1], line[1:], strict=True)
                          for i in (drawing.index(a), drawing.index(b))]
        self.tube_radius = tube_radius if tube_radius and tube_radius > 0 else None
        self.period = 1.0 / max_rate_hz
        self._next = 0.0
        for topic in TOPICS:
            self.rec.add_protobuf_topic(topic, SceneUpdate_pb2.SceneUpdate)

    # ------------------------------------------------------------ primitives
    def _line(self, kind: str, world: np.ndarray, color: Rgba, thickness: float) -> bytes:
        """LinePrimitive bytes of `kind` (LINE_STRIP, LINE_LOOP, LINE_LIST), points (K, 3)."""
        key = ("line", kind, tuple(color), float(thickness))
        head = self._templates.get(key)
        if head is None:
            Line, pb = self.pb["Line"], self.pb
            head = self._templates[key] = Line(
                type=Line.Type.Value(kind), thickness=float(thickness),
                pose=pb["Pose"](position=pb["Vector3"](), orientation=pb["Quaternion"](w=1.0)),
                color=pb["Color"](r=color[0], g=color[1], b=color[2], a=color[3])
            ).SerializeToString()
        return head + points_wire(self._f["points"], world)

    def _spheres(self, centers: np.ndarray, radius: float, color: Rgba) -> bytes:
        """SceneEntity ``spheres`` field bytes: spheres of `radius` [m] at `centers` (K, 3)."""
        key = ("sphere", float(radius), tuple(color))
        rest = self._templates.get(key)
        if rest is None:
            d = 2.0 * float(radius)
            rest = self._templates[key] = self.pb["Sphere"](
                size=self.pb["Vector3"](x=d, y=d, z=d),
                color=self.pb["Color"](r=color[0], g=color[1], b=color[2], a=color[3])
            ).SerializeToString()
        return spheres_wire(self._f["spheres"], centers, rest)

    def _entity(self, t: float, entity_id: str, lines: list[bytes] = (), fields: bytes = b"",
                frame_locked: bool = False) -> bytes:
        """SceneUpdate ``entities`` field bytes: an entity at sim time `t` [s], lifetime 0.

        ``lines``: LinePrimitive bytes (each framed as a ``lines`` field); ``fields``: more
        SceneEntity field bytes, already framed (e.g. :meth:`_spheres`).
        """
        f = self._f
        body = (_field(f["timestamp"], _timestamp(t)) + _field(f["frame_id"], FRAME.encode())
                + _field(f["id"], entity_id.encode())
                + (_varint(f["frame_locked"] << 3) + b"\x01" if frame_locked else b"")
                + b"".join(_field(f["lines"], line) for line in lines) + fields)
        return _field(f["entities"], body)

    def _write(self, topic: str, t: float, entities: list[bytes]) -> None:
        self.rec.write_protobuf_bytes(topic, t, b"".join(entities))

    # --------------------------------------------------------------- topics
    def start(self) -> None:
        """Writes the static geometry once at t = 0 (``static/<name>``, frame-locked)."""
        entities = []
        for line in self.drawing.static:
            kind = "LINE_LOOP" if line.closed else "LINE_STRIP"
            prim = self._line(kind, to_world(np.array(line.points)), line.color, line.thickness)
            entities.append(self._entity(0.0, f"static/{line.name}", [prim], frame_locked=True))
        if entities:
            self._write(STATIC, 0.0, entities)

    def state(self, t: float, x: np.ndarray) -> None:
        """The ``body`` at state x (n,) and time t [s]; skipped within the rate limit."""
        self.states((t,), np.asarray(x, dtype=float)[None])

    def states(self, ts: tuple[float, ...], xs: np.ndarray) -> None:
        """The ``body`` at states xs (K, n) and times ts (K,) [s], in order.

        A state within the rate limit of the last body written is skipped.
        """
        due = []
        for k, t in enumerate(ts):
            if t >= self._next - 1e-9:
                due.append(k)
                self._next = t + self.period
        if not due:
            return
        bodies = to_world(self.drawing.bodies(np.asarray(xs)[due]).transpose(0, 2, 1))
        for k, body in zip(due, self._bodies_wire(bodies), strict=True):
            self._write(BODY, ts[k], [self._entity(ts[k], "body", fields=body)])

    def _bodies_wire(self, bodies: np.ndarray) -> list[bytes]:
        """Per body (K, P, 3) world points: its entity's ``lines`` and ``spheres`` bytes.

        All K bodies in one encoding call per part (the records have fixed sizes), then
        cut per body: what ``_line`` and ``_spheres`` per body give, byte for byte.
        """
        d, k = self.drawing, len(bodies)
        parts = []  # per part: (its K bytes, one body's share of them, its field prefix)
        link_idx = self._link_idx
        if link_idx:
            head = self._line("LINE_LIST", np.empty((0, 3)), d.link_color, d.link_thickness)
            pts = points_wire(self._f["points"], bodies[:, link_idx])
            share = len(pts) // k
            parts.append((pts, share, _varint((self._f["lines"] << 3) | 2)
                          + _varint(len(head) + share) + head))
        for ball in d.balls:
            spheres = self._spheres(bodies[:, d.index(ball.point)], ball.radius, ball.color)
            parts.append((spheres, len(spheres) // k, b""))
        return [b"".join(prefix + data[j * share:(j + 1) * share]
                         for data, share, prefix in parts) for j in range(k)]

    def _traces(self, xs: np.ndarray, colors: tuple[Rgba, ...], thickness: float,
                seg: np.ndarray | None = None) -> list:
        """Line strips per trace point along states xs (K, n), one per domain segment.

        ``seg`` (K,): each node's domain segment; the line breaks where it changes (a
        reset: the biped's legs swap, the swing foot jumps) instead of drawing a
        segment across the reset. A segment of one node draws nothing.
        """
        traced = to_world(self.drawing.traced(xs))  # (T, K, 3)
        pieces = _pieces(seg, len(xs))
        return [self._line("LINE_STRIP", path[a:b], colors[i % len(colors)], thickness)
                for i, path in enumerate(traced) for a, b in pieces]

    def plan(self, t: float, plan: Plan) -> None:
        """The ``plan`` (and ``tube``) of an MPC solve at time t [s]."""
        if not self.drawing.trace or len(plan.traj.x) == 0:
            return
        xs = np.atleast_2d(np.asarray(plan.traj.x, dtype=float))
        colors = PLAN_COLORS if plan.adopt else (REJECTED,)
        entities = [self._entity(t, "plan", self._traces(xs, colors, 0.015,
                                                         _segments(plan.traj, len(xs))))]
        if self.tube_radius is not None:
            centers = to_world(self.drawing.traced(xs[_tube_nodes(len(xs))])[0])
            entities.append(self._entity(t, "tube", fields=self._spheres(
                centers, self.tube_radius, TUBE)))
        self._write(PLAN, t, entities)

    def rollout(self, t: float, trajectory: Trajectory | None) -> None:
        """The planner's ``rollout`` at time t [s] (nothing without a trajectory)."""
        if trajectory is None or not self.drawing.trace or len(trajectory.x) == 0:
            return
        xs = np.atleast_2d(np.asarray(trajectory.x, dtype=float))
        self._write(ROLLOUT, t, [self._entity(t, "rollout", self._traces(
            xs, (ORANGE,), 0.01, _segments(trajectory, len(xs))))])


def _segments(traj: Trajectory, k: int) -> np.ndarray | None:
    """A trajectory's per-node domain segments (K,), or None when it has none of K."""
    seg = getattr(traj, "seg", None)
    if seg is None:
        return None
    seg = np.asarray(seg).reshape(-1)
    return seg if len(seg) == k else None


def _pieces(seg: np.ndarray | None, k: int) -> list[tuple[int, int]]:
    """Node ranges [a, b) of equal ``seg`` with at least two nodes (all K: one range)."""
    if seg is None or k == 0:
        return [(0, k)]
    cuts = [0, *(np.flatnonzero(np.diff(seg) != 0) + 1).tolist(), k]
    return [(a, b) for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b - a >= 2]


@lru_cache(maxsize=64)
def _tube_nodes(n: int) -> np.ndarray:
    """Indices of the (at most TUBE_SPHERES) plan nodes drawn as tube spheres, of n."""
    nodes = np.unique(np.linspace(0, n - 1, min(n, TUBE_SPHERES)).round()).astype(int)
    nodes.setflags(write=False)
    return nodes


def open_scene(recorder: Any, system: Any, margins: dict | None = None,
               max_rate_hz: float = MAX_RATE_HZ) -> SceneWriter | None:
    """The scene writer of a run, its static geometry written; None without a drawing.

    Args:
        recorder: the run's open recorder.
        system: the simulated :class:`~hmpc_cli.core.hybrid.HybridSystem` (its ``drawing``).
        margins: the MPC's margins record (``/run/info`` ``margins``: its ``radius`` is
            the tube's), or None.
        max_rate_hz: at most this many body updates per simulated second.
    """
    if recorder is None or getattr(system, "drawing", None) is None:
        return None
    radius = (margins or {}).get("radius")
    writer = SceneWriter(recorder, system.drawing, radius, max_rate_hz)
    writer.start()
    return writer
