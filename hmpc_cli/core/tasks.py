"""Reusable tasks (:class:`hmpc_cli.core.stack.Task` implementations) for system plug-ins."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.stack import Verdict


@dataclass(frozen=True)
class ReachGoal:
    """Reach a ball around a goal point: success when |goal_map(x_end) - goal| <= radius.

    Attributes:
        system: the system whose ``goal_map`` and ``goal`` define the error.
        radius: success radius, in the units of ``goal_map``.
    """

    system: HybridSystem
    radius: float

    @property
    def goal(self) -> np.ndarray:
        """The goal point, in the coordinates of ``system.goal_map``."""
        return self.system.goal

    def error(self, x: np.ndarray) -> float:
        """|goal_map(x) - goal| (NaN for a non-finite state)."""
        if not np.all(np.isfinite(x)):
            return float("nan")
        return float(self.system.numeric.goal_error(np.asarray(x, dtype=float)))

    def failure(self, x: np.ndarray, mode: int) -> str:
        """Never stops a run early (divergence is the loop's business)."""
        return ""

    def verdict(self, x: np.ndarray, mode: int) -> Verdict:
        """Success iff the final error is at most ``radius``."""
        err = self.error(x)
        if np.isfinite(err) and err <= self.radius:
            return Verdict(True, err, "success")
        return Verdict(False, err, f"final error {err:.3f} > {self.radius:g}")
