"""What a run log records of its system's geometry, so figures never rebuild a model.

``/run/info`` carries a :class:`GeometryRec`: the drawing plane (two state names), the
goal, the drawing's static polylines (guards, walls, stairs), the body's point names and
skeleton, and the terrain of a walking system. A system whose drawing has links (a
skeleton) also logs its body points with every ``/sim/state`` sample and with every guard
event (``body`` / ``body_before``: ``<point>_x``, ``<point>_y`` in the plane [m]).

Everything here is taken from the :class:`~hmpc_cli.core.hybrid.HybridSystem` and its
:class:`~hmpc_cli.core.drawing.Drawing` when the run starts; readers get it back through
:func:`hmpc_cli.log.rundata.read_run` (``RunData.geometry``, ``RunData.body``).
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["GeometryRec", "LineRec", "PolylineRec", "SegmentRec", "TerrainRec", "body_logger",
           "body_names", "geometry_record", "record_maker"]


@dataclass(frozen=True)
class PolylineRec:
    """A static polyline of the drawing: name, vertices a (K,), b (K,) [m], closed.

    Attributes:
        name: what it draws, e.g. a guard's name.
        a: the vertices' first plane coordinate (K,) [m] (to the right).
        b: the vertices' second plane coordinate (K,) [m] (up).
        closed: the last vertex joins the first (a loop).
    """

    name: str
    a: tuple[float, ...]
    b: tuple[float, ...]
    closed: bool


@dataclass(frozen=True)
class LineRec:
    """A polyline through named body points (a skeleton line).

    Attributes:
        points: the body points it joins, in order (names of ``point_names``).
    """

    points: tuple[str, ...]


@dataclass(frozen=True)
class SegmentRec:
    """A flat terrain segment from x0 to x1 [m] at height [m].

    Attributes:
        x0: where the segment starts [m].
        x1: where the segment ends [m].
        height: the segment's height [m].
    """

    x0: float
    x1: float
    height: float


@dataclass(frozen=True)
class TerrainRec:
    """A piecewise-flat terrain: the ground height for x <= 0 [m] and its segments.

    Attributes:
        ground: the height for x <= 0 [m].
        segments: consecutive flat segments from x = 0, ascending.
    """

    ground: float
    segments: tuple[SegmentRec, ...]


@dataclass(frozen=True)
class GeometryRec:
    """The system's geometry as the run's figures draw it (see the module docstring).

    Attributes:
        plane: two state names spanning the plane figures draw trajectories in
            (``HybridSystem.plane``; empty: none declared).
        goal: the goal point, in the coordinates of the system's ``goal_map``.
        static: the drawing's static polylines (guards, walls, stairs; empty: no drawing).
        point_names: names of the logged body points (empty: no body is logged).
        skeleton: polylines through body points (empty: no body is logged).
        terrain: the walking surface (absent: the system walks on none).
    """

    plane: tuple[str, ...]
    goal: tuple[float, ...]
    static: tuple[PolylineRec, ...]
    point_names: tuple[str, ...]
    skeleton: tuple[LineRec, ...]
    terrain: TerrainRec | None = None


@functools.lru_cache(maxsize=128)
def record_maker(keys: tuple[str, ...]):
    """``f(v0, v1, ...) -> {keys[0]: v0, keys[1]: v1, ...}``.

    A dict display compiled once per key tuple: the fastest way to make many dicts of
    the same keys (the keys enter the source as string literals, by ``repr``).
    """
    args = ", ".join(f"v{i}" for i in range(len(keys)))
    body = ", ".join(f"{k!r}: v{i}" for i, k in enumerate(keys))
    return eval(f"lambda {args}: {{{body}}}")


def body_names(point_names: Sequence[str]) -> tuple[str, ...]:
    """The logged coordinates of body points: ``<point>_x``, ``<point>_y`` per point."""
    return tuple(f"{p}_{c}" for p in point_names for c in ("x", "y"))


def _logs_body(system) -> bool:
    drawing = getattr(system, "drawing", None)
    return drawing is not None and bool(drawing.links)


def geometry_record(system) -> GeometryRec:
    """The :class:`GeometryRec` of a :class:`~hmpc_cli.core.hybrid.HybridSystem`."""
    drawing = getattr(system, "drawing", None)
    static = () if drawing is None else tuple(
        PolylineRec(p.name, tuple(float(v[0]) for v in p.points),
                    tuple(float(v[1]) for v in p.points), bool(p.closed))
        for p in drawing.static)
    body = _logs_body(system)
    terrain = getattr(system, "terrain", None)
    return GeometryRec(
        tuple(system.plane or ()),
        tuple(np.asarray(system.goal, dtype=float).ravel().tolist()), static,
        tuple(drawing.point_names) if body else (),
        tuple(LineRec(tuple(line)) for line in drawing.links) if body else (),
        None if terrain is None else TerrainRec(float(terrain.ground), tuple(
            SegmentRec(float(a), float(b), float(h)) for a, b, h in terrain.segments)))


class BodyLogger:
    """State x -> the body's logged coordinates {``<point>_x``, ``<point>_y``} [m]."""

    def __init__(self, drawing) -> None:
        self.drawing = drawing
        self.keys = body_names(drawing.point_names)

    def __call__(self, x: np.ndarray) -> dict:
        """The body of one state x (n,)."""
        return dict(zip(self.keys, self.drawing.body(x).T.ravel().tolist(), strict=True))

    def many(self, xs: np.ndarray) -> list[dict]:
        """The bodies of states xs (K, n), in order (one batched drawing call)."""
        pts = self.drawing.bodies(xs)  # (K, 2, P)
        rows = pts.transpose(0, 2, 1).reshape(len(pts), -1).tolist()
        return list(itertools.starmap(record_maker(self.keys), rows))


def body_logger(system) -> BodyLogger | None:
    """The body logger of a system's drawing; None: no body logged."""
    if not _logs_body(system):
        return None
    return BodyLogger(system.drawing)
