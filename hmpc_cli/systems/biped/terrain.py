"""The stairs as a :class:`~hmpc_cli.core.hybrid.Terrain` (consecutive flat segments from x = 0)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from hmpc_cli.core.hybrid import Terrain


class _Stair(Protocol):
    length: float
    height: float


class Stairs(Protocol):
    """The terrain data the stairs read: the stair segments and the ground height [m]."""

    stairs: Sequence[_Stair]
    ground_height: float


def stair_edges(p: Stairs) -> list[tuple[float, float, float]]:
    """(start, end, height) of each stair segment, consecutive from x = 0 [m]."""
    out, x = [], 0.0
    for s in p.stairs:
        out.append((x, x + s.length, s.height))
        x += s.length
    return out


def stair_terrain(p: Stairs) -> Terrain:
    """The ground (x <= 0) and the stair segments as a terrain."""
    return Terrain(p.ground_height, tuple(stair_edges(p)))
