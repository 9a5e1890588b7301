"""How a system is drawn: what a system plug-in declares for the run log's 3D scene.

A :class:`Drawing` lives on :attr:`hmpc_cli.core.hybrid.HybridSystem.drawing` (None: the system
is not drawn). Everything is in the system's plane (first coordinate to the right, second
up) in metres; :mod:`hmpc_cli.log.scene` stands that plane upright in the 3D world, plane
(a, b) -> world (x, y, z) = (a, 0, b), so that the second coordinate is "up" (z) in a
3D viewer.

A drawing has three parts:

* ``static``: world geometry drawn once (guards, walls, terrain) as :class:`Polyline`;
* the body as a function of the state: ``points`` maps a state to named points in the
  plane; ``links`` are polylines through them (a skeleton), ``balls`` spheres at some;
* ``trace``: the points whose paths draw the MPC plan, the planner's rollout and the
  tube (one line strip per trace point, one vertex per plan node).

This module is part of the bottom vocabulary: it imports nothing from hmpc.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["Ball", "Drawing", "Polyline", "circle"]

Rgba = tuple[float, float, float, float]

GREY: Rgba = (0.6, 0.6, 0.6, 1.0)


@dataclass(frozen=True)
class Polyline:
    """A static line strip in the plane.

    Attributes:
        name: what it draws (e.g. a guard's name); the scene entity's id suffix.
        points: vertices ((a, b), ...) in the plane [m], at least two.
        color: RGBA, each in [0, 1].
        thickness: line width [m].
        closed: join the last vertex to the first (a loop).
    """

    name: str
    points: tuple[tuple[float, float], ...]
    color: Rgba = GREY
    thickness: float = 0.02
    closed: bool = False

    def __post_init__(self) -> None:
        if len(self.points) < 2:
            raise ValueError(f"polyline {self.name!r} needs at least two points")


@dataclass(frozen=True)
class Ball:
    """A sphere on one of the body's named points.

    Attributes:
        point: the name of the point (one of :attr:`Drawing.point_names`).
        radius: sphere radius [m].
        color: RGBA, each in [0, 1].
    """

    point: str
    radius: float
    color: Rgba = (0.9, 0.4, 0.1, 1.0)


@dataclass(frozen=True)
class Drawing:
    """A system's drawing (see the module docstring).

    Attributes:
        points: state x, shape (n,) -> named body points in the plane, shape (2, P) [m].
        point_names: names of the P columns of ``points``.
        links: polylines through named points (e.g. the skeleton), drawn as segments.
        balls: spheres on named points (e.g. the ball itself, the feet).
        trace: names of the points whose paths draw plans and rollouts.
        static: world geometry drawn once.
        link_color: RGBA of the links.
        link_thickness: width of the links [m].
        points_many: optional batched ``points``: states (K, n) -> (K, 2, P) [m] (plans and
            rollouts are drawn from it in one call).
    """

    points: Callable[[np.ndarray], np.ndarray]
    point_names: tuple[str, ...]
    links: tuple[tuple[str, ...], ...] = ()
    balls: tuple[Ball, ...] = ()
    trace: tuple[str, ...] = ()
    static: tuple[Polyline, ...] = ()
    link_color: Rgba = (0.2, 0.3, 0.8, 1.0)
    link_thickness: float = 0.03
    points_many: Callable[[np.ndarray], np.ndarray] | None = None

    def __post_init__(self) -> None:
        named = set(self.point_names)
        used = {p for line in self.links for p in line} | {b.point for b in self.balls}
        unknown = (used | set(self.trace)) - named
        if unknown:
            raise ValueError(f"drawing names unknown points {sorted(unknown)}")

    def index(self, name: str) -> int:
        """Column of the named point in ``points(x)``."""
        return self.point_names.index(name)

    def body(self, x: np.ndarray) -> np.ndarray:
        """The body points of state x, shape (n,) -> (2, P) [m]."""
        x = np.asarray(x, dtype=float)
        if self.points_many is not None:
            return np.asarray(self.points_many(x[None]), dtype=float)[0]
        pts = np.asarray(self.points(x), dtype=float)
        return pts.reshape(2, len(self.point_names))

    def bodies(self, xs: np.ndarray) -> np.ndarray:
        """The body points of states xs, shape (K, n) -> (K, 2, P) [m]."""
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        if self.points_many is not None:
            return np.asarray(self.points_many(xs), dtype=float).reshape(
                len(xs), 2, len(self.point_names))
        return np.stack([self.body(x) for x in xs]) if len(xs) else \
            np.empty((0, 2, len(self.point_names)))

    def traced(self, xs: np.ndarray) -> np.ndarray:
        """The trace points along states xs, shape (K, n) -> (T, K, 2) [m]."""
        cols = [self.index(n) for n in self.trace]
        xs = np.atleast_2d(np.asarray(xs, dtype=float))
        if self.points_many is not None:  # (K, 2, P) -> (T, K, 2)
            return np.asarray(self.points_many(xs), dtype=float)[:, :, cols].transpose(2, 0, 1)
        out = np.empty((len(cols), len(xs), 2))
        for k, x in enumerate(xs):
            out[:, k, :] = self.body(x)[:, cols].T
        return out


def circle(name: str, center: tuple[float, float], radius: float, color: Rgba = GREY,
           thickness: float = 0.02, n: int = 64) -> Polyline:
    """A closed polyline of n vertices on the circle |p - center| = radius [m]."""
    ang = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    pts = tuple((float(center[0] + radius * np.cos(a)), float(center[1] + radius * np.sin(a)))
                for a in ang)
    return Polyline(name, pts, color, thickness, closed=True)
