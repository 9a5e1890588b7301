"""What the layers hand each other (and what the recorder logs).

Times are seconds; arrays are NumPy with the shapes given per field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class ModeSchedule:
    """A domain/guard sequence with the time spent in each non-final domain.

    Attributes:
        modes: domain sequence D_0..D_S as mode indices (D_S is the final domain).
        guards: guard sequence G_1..G_S (guard G_j leads from D_{j-1} to D_j).
        durations: planned time in D_0..D_{S-1} [s] (D_S takes the rest of the horizon).
    """

    modes: tuple[int, ...]
    guards: tuple[int, ...]
    durations: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.modes) != len(self.guards) + 1 or len(self.durations) != len(self.guards):
            raise ValueError("a schedule needs S guards, S durations and S + 1 modes")

    @property
    def n_switches(self) -> int:
        return len(self.guards)

    def to_dict(self, system=None) -> dict:
        d = {"modes": list(self.modes), "guards": list(self.guards),
             "durations": [float(v) for v in self.durations]}
        if system is not None:
            d["mode_names"] = [system.modes[m].name for m in self.modes]
            d["guard_names"] = [system.guards[g].name for g in self.guards]
        return d


@dataclass(frozen=True)
class Trajectory:
    """A sampled hybrid trajectory: node times t (K+1,), states x (K+1, n), inputs
    u (K+1, m) at each node, mode (K+1,), domain-segment index seg (K+1,), the guards
    crossed between segments, and how the input runs between nodes: ``input_hold`` "zoh"
    (u_k held) or "foh" (linear from u_k to u_k+1). A reset appears as two nodes with the
    same time (on the guard, then after the reset)."""

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    mode: np.ndarray
    seg: np.ndarray
    guards: tuple[int, ...] = ()
    input_hold: str = "zoh"


@dataclass(frozen=True)
class PlannerResult:
    """Output of a hybrid-MPC (planner) call.

    Attributes:
        schedule: the domain/guard sequence with durations (None if no rollout reached
            the final domain).
        trajectory: the best rollout (an initial guess for the fixed-mode MPC).
        cost: its cost.
        reached_final: whether the best rollout reached the final domain.
        wall_time: measured computation time [s].
        iterations: iterations run.
    """

    schedule: ModeSchedule | None
    trajectory: Trajectory
    cost: float
    reached_final: bool
    wall_time: float
    iterations: int


@dataclass(frozen=True)
class SolveStats:
    """Statistics of one fixed-mode MPC solve.

    Attributes:
        status: the solver's return status.
        success: the solver converged to a finite point.
        iterations: solver iterations.
        wall_time: measured solve time [s].
        cost: optimal cost (NaN if none).
        max_violation: largest violation of the solved NLP's rows and bounds.
        slack: largest relaxation of the hybrid (guard, virtual-node, region, terminal)
            constraints by the soft-constraint slacks; 0 when they hold exactly.
    """

    status: str
    success: bool
    iterations: int
    wall_time: float
    cost: float
    max_violation: float
    slack: float = 0.0


@dataclass(frozen=True)
class Plan:
    """A fixed-mode MPC solution handed to the low-level controller.

    Attributes:
        t0: simulated time the plan starts at [s].
        traj: planned trajectory (times relative to t0).
        stats: solver statistics.
        schedule: the schedule it was solved for.
    """

    t0: float
    traj: Trajectory
    stats: SolveStats
    schedule: ModeSchedule
    extra: dict = field(default_factory=dict)
