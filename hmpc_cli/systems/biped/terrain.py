"""The stairs as a :class:`~hmpc_cli.hybrid.Terrain` (consecutive flat segments from x = 0)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from hmpc_cli.hybrid import Terrain

if TYPE_CHECKING:
    from hmpc_cli.systems.biped.params import BipedParams


def stair_edges(p: BipedParams) -> list[tuple[float, float, float]]:
    """(start, end, height) of each stair segment, consecutive from x = 0 [m]."""
    out, x = [], 0.0
    for s in p.stairs:
        out.append((x, x + s.length, s.height))
        x += s.length
    return out


def stair_terrain(p: BipedParams) -> Terrain:
    """The ground (x <= 0) and the stair segments as a terrain."""
    return Terrain(p.ground_height, tuple(stair_edges(p)))
