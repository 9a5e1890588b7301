"""System plug-ins: each turns validated parameters into a :class:`HybridSystem`.

To add a system, write a pydantic ``Params`` model with a literal ``name`` field and a
``build(params) -> HybridSystem`` function, and register both in :data:`REGISTRY`.
"""

from __future__ import annotations

from collections.abc import Callable

from hmpc_cli.hybrid import HybridSystem
from hmpc_cli.systems.ball import BallParams, build_ball
from hmpc_cli.systems.biped import BipedParams, build_biped

REGISTRY: dict[str, tuple[type, Callable[..., HybridSystem]]] = {
    "ball": (BallParams, build_ball),
    "biped": (BipedParams, build_biped),
}

SystemParams = BallParams | BipedParams


def build_system(params: SystemParams) -> HybridSystem:
    """Builds the system named by ``params.name``."""
    _, build = REGISTRY[params.name]
    return build(params)
