"""What the layers hand each other (and what the recorder logs).

Times are seconds; arrays are NumPy with the shapes given per field.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


#: outcomes of :meth:`ModeSchedule.after_event`
SCHEDULED, AHEAD, SELF_LOOP, OFF_SCHEDULE = "scheduled", "ahead", "self_loop", "off_schedule"


@dataclass(frozen=True)
class ModeSchedule:
    """A domain/guard sequence with the time spent in each non-final domain.

    Attributes:
        modes: domain sequence D_0..D_S as mode indices (D_S is the last domain).
        guards: guard sequence G_1..G_S (guard G_j leads from D_{j-1} to D_j).
        durations: planned time in D_0..D_{S-1} [s] (D_S takes the rest of the horizon).
        t0: simulated time the schedule was planned at [s]; schedules derived from it by
            events keep it, so a new plan is told apart from an advanced one.
    """

    modes: tuple[int, ...]
    guards: tuple[int, ...]
    durations: tuple[float, ...]
    t0: float = 0.0

    def __post_init__(self) -> None:
        if len(self.modes) != len(self.guards) + 1 or len(self.durations) != len(self.guards):
            raise ValueError("a schedule needs S guards, S durations and S + 1 modes")

    @property
    def n_switches(self) -> int:
        """S, the number of scheduled guard events."""
        return len(self.guards)

    def after_event(self, guard: int, mode_after: int) -> tuple[ModeSchedule, str]:
        """The paper's impact rule at the domain level: the schedule after a real event.

        Args:
            guard: index of the guard that fired.
            mode_after: the mode the plant is in after its reset.

        Returns:
            (schedule, outcome): ``SCHEDULED`` (the pending guard fired: its domain is
            dropped), ``AHEAD`` (a later scheduled guard fired: every domain up to it is
            dropped), ``SELF_LOOP`` (an unscheduled event that left the plant in the
            schedule's current mode, e.g. an extra bounce: unchanged) or
            ``OFF_SCHEDULE`` (the plant left the schedule: unchanged, replan).
        """
        if self.guards and self.guards[0] == guard:
            return self.drop(1), SCHEDULED
        if guard in self.guards[1:]:
            return self.drop(self.guards.index(guard, 1) + 1), AHEAD
        if self.modes[0] == mode_after:
            return self, SELF_LOOP
        return self, OFF_SCHEDULE

    def drop(self, k: int) -> ModeSchedule:
        """The schedule without its first ``k`` domains (and their guards)."""
        return ModeSchedule(self.modes[k:], self.guards[k:], self.durations[k:], self.t0)

    @classmethod
    def final(cls, mode: int, t0: float = 0.0) -> ModeSchedule:
        """The schedule that stays in domain ``mode`` (no switch)."""
        return cls((mode,), (), (), t0)

    def to_dict(self, system=None) -> dict:
        """JSON-ready dict; with ``system`` also the mode and guard names."""
        d = {"modes": list(self.modes), "guards": list(self.guards),
             "durations": [float(v) for v in self.durations], "t0": float(self.t0)}
        if system is not None:
            d["mode_names"] = [system.modes[m].name for m in self.modes]
            d["guard_names"] = [system.guards[g].name for g in self.guards]
        return d


@dataclass(frozen=True)
class Trajectory:
    """A sampled hybrid trajectory.

    Node times t (K+1,), states x (K+1, n), inputs u (K+1, m) at each node, mode (K+1,),
    domain-segment index seg (K+1,), the guards crossed between segments, and how the
    input runs between nodes: ``input_hold`` "zoh" (u_k held) or "foh" (linear from u_k
    to u_k+1). A reset appears as two nodes with the same time (on the guard, then after
    the reset).
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    mode: np.ndarray
    seg: np.ndarray
    guards: tuple[int, ...] = ()
    input_hold: str = "zoh"


@dataclass(frozen=True)
class GuardEvent:
    """A guard event of the plant, as the controllers are told of it.

    Attributes:
        t: event time [s].
        guard: index of the guard that fired.
        mode_before: mode index before the reset.
        mode_after: mode index after the reset.
        x_before: state on the guard, shape (n,).
        x_after: state after the reset, shape (n,).
    """

    t: float
    guard: int
    mode_before: int
    mode_after: int
    x_before: np.ndarray
    x_after: np.ndarray


@dataclass(frozen=True)
class PlannerResult:
    """Output of a hybrid-MPC (planner) call.

    Attributes:
        schedule: the domain/guard sequence with durations (None: no schedule found,
            ``note`` says why).
        trajectory: the best rollout or plan (an initial guess for the fixed-mode MPC),
            or None.
        cost: its cost (NaN if none).
        reached_final: whether the best candidate reached the final domain (or target).
        wall_time: measured computation time [s].
        iterations: iterations run (sampling iterations, or solver iterations summed).
        note: why no schedule was found ('' otherwise).
        detail: the planner's log detail, an instance of the frozen dataclass its spec
            declares (``PlannerSpec.detail``), or None.
        mpc_solves: the fixed-mode MPC solves the planner made itself (e.g. one per
            foothold candidate), in order: their failures count as solver failures,
            once each.
    """

    schedule: ModeSchedule | None
    trajectory: Trajectory | None
    cost: float
    reached_final: bool
    wall_time: float
    iterations: int
    note: str = ""
    detail: Any = None
    mpc_solves: tuple[Plan, ...] = ()


@dataclass(frozen=True)
class SolveStats:
    """Statistics of one fixed-mode MPC solve.

    Attributes:
        status: the solver's return status.
        success: the back-end accepted a finite point: its own success flag (it
            converged), or a bounded SQP run's ``Backend.judge`` (rti: any finite point
            at the iteration limit); see :class:`hmpc_cli.log.topics.MpcSolve`.
        iterations: solver iterations.
        wall_time: measured solve time [s].
        cost: optimal cost (NaN if none), the objective at the solution projected onto
            the variables' bounds (IPOPT may return a slack 1e-8 below its bound 0).
        max_violation: largest violation of the solved NLP's rows and bounds.
        slack: largest relaxation of the hybrid (guard, virtual-node, region, terminal)
            constraints by the soft-constraint slacks; 0 when they hold exactly.
        fallback: the back-end failed and IPOPT solved this problem instead.
    """

    status: str
    success: bool
    iterations: int
    wall_time: float
    cost: float
    max_violation: float
    slack: float = 0.0
    fallback: bool = False


@dataclass(frozen=True)
class Plan:
    """A fixed-mode MPC solution handed to the low-level controller.

    Attributes:
        t0: simulated time the plan starts at [s].
        traj: planned trajectory (times relative to t0).
        stats: solver statistics.
        schedule: the schedule it was solved for.
        detail: the MPC's log detail (e.g. nodes shifted, warm start kind), an instance
            of the frozen dataclass its spec declares (``MPCSpec.detail``), or None.
        adopt: whether the low level should track this plan; a failed solve's plan
            may still be a usable fallback (the fixed-mode MPC's: its last solution on
            the schedule, shifted, or before one the initial guess), else the low level
            keeps the plan it has.
    """

    t0: float
    traj: Trajectory
    stats: SolveStats
    schedule: ModeSchedule
    detail: Any = None
    adopt: bool = True

    @property
    def nodes(self) -> int:
        """The nodes the MPC solved over: ``traj``'s, or 0.

        0 for fewer than 2 nodes: a rejected schedule's plan, the state alone, solved
        nothing.
        """
        n = len(self.traj.t)
        return n if n >= 2 else 0


@dataclass(frozen=True)
class ConstraintMargins:
    """The tightenings the fixed-mode MPC applies (problem (14)), in system order.

    Built by hand from ``(tube_margin, input_margin)`` (:meth:`hand`) or from a margins
    file (:meth:`by_name`); the NLP data code reads only this.

    Attributes:
        source: "hand", or the margins file's path.
        radius: the tube radius d they come from [state norm].
        avoid: per guard, the guard-avoid offset kappa(d, past=False) (NLP row units).
        entered: per guard, the offset while the guard was just crossed (kappa(0, False):
            the tube is not applied to the guard the state has just left through).
        pass_through: per guard, the virtual-node offset kappa(d, past=True).
        inputs: per mode, the input-box shrink per side, one value per input.
    """

    source: str
    radius: float
    avoid: tuple[float, ...]
    entered: tuple[float, ...]
    pass_through: tuple[float, ...]
    inputs: tuple[tuple[float, ...], ...]

    @classmethod
    def hand(cls, system, tube_margin: float, input_margin: float) -> ConstraintMargins:
        """The hand-set margins: ``Guard.kappa`` of the radius, one shrink for every input.

        Args:
            system: the :class:`~hmpc_cli.core.hybrid.HybridSystem`.
            tube_margin: tube radius d [state norm].
            input_margin: input-box shrink per side [input units].
        """
        gs = system.guards
        return cls("hand", float(tube_margin),
                   tuple(g.kappa(tube_margin, past=False) for g in gs),
                   tuple(g.kappa(0.0, past=False) for g in gs),
                   tuple(g.kappa(tube_margin, past=True) for g in gs),
                   tuple((input_margin,) * system.n_u for _ in system.modes))

    @classmethod
    def by_name(cls, system, source: str, radius: float, guards: dict, inputs: dict
                ) -> ConstraintMargins:
        """Margins given by guard and mode name (a margins file's).

        Args:
            system: the :class:`~hmpc_cli.core.hybrid.HybridSystem`.
            source: where they come from (the file's path).
            radius: the tube radius d [state norm].
            guards: guard name -> (avoid, pass_through) offsets (NLP row units).
            inputs: mode name -> shrink per side, one value per input.

        Raises:
            ValueError: a guard or mode of the system is missing, or an input count is off.
        """
        missing = [g.name for g in system.guards if g.name not in guards]
        missing += [m.name for m in system.modes if m.name not in inputs]
        if missing:
            raise ValueError(f"no margins for {', '.join(missing)}")
        bad = [m.name for m in system.modes if len(inputs[m.name]) != system.n_u]
        if bad:
            raise ValueError(f"modes {', '.join(bad)}: expected {system.n_u} input margins")
        return cls(source, float(radius),
                   tuple(float(guards[g.name][0]) for g in system.guards),
                   tuple(g.kappa(0.0, past=False) for g in system.guards),
                   tuple(float(guards[g.name][1]) for g in system.guards),
                   tuple(tuple(float(v) for v in inputs[m.name]) for m in system.modes))

    def to_dict(self, system) -> dict:
        """The /run/info record: source, radius, offsets by guard, shrinks by mode."""
        return {"source": self.source, "radius": self.radius,
                "guards": [{"guard": g.name, "avoid": a, "pass_through": p}
                           for g, a, p in zip(system.guards, self.avoid, self.pass_through,
                                              strict=True)],
                "inputs": [{"mode": m.name, "per_side": list(v)}
                           for m, v in zip(system.modes, self.inputs, strict=True)]}


@dataclass(frozen=True)
class BuildInfo:
    """How an MPC's NLPs were built (the build cache's verdict, logged in /run/info).

    Attributes:
        cache: ``"hit"`` (every NLP loaded compiled from the build cache), ``"miss"``
            (an NLP built without its compiled library; ``reason`` says what the cache
            keeps of it) or ``"disabled"`` (built, no cache).
        compiled: every NLP's functions are the build cache's compiled library (else
            they run in CasADi's virtual machines, their stage kernels compiled to C
            where ``reason`` says so).
        reason: why, in one line (one clause per NLP where they differ).
    """

    cache: str
    compiled: bool
    reason: str
