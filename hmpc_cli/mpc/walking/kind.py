"""The biped's fixed-mode walking MPC in closed loop: candidates, shifting, warm starts.

One :class:`WalkingNLP` (see :mod:`hmpc_cli.mpc.walking.nlp` for the formulation) is
re-solved per target contact surface ("candidate"): the first guard of the schedule it
is given, whose surface is ``HybridSystem.guard_surfaces[guard]``. Behind the stack
contract (:meth:`WalkingMPC.solve`) every guard event ends the current swing (the swing
clock restarts at the event time); a schedule with no guard left has no target and is
rejected; a repeated solve of the same (t, x, target), e.g. the loop solving the schedule
a foothold planner has just chosen by solving it, returns the stored plan.

Timing: ``elapsed`` is the time already spent in the current swing (since the last
contact, or since the start of the run). Swing 0 keeps its N nodes and shrinks its node
step to the remaining time (``WalkingNLP.dt0``); no node moves between swings.

Warm starts, per candidate: after a re-solve in the same swing, the stored solution's
swing 0 (primal, bound and constraint multipliers) is re-interpolated on the new swing-0
time grid (multipliers of path rows and bounds scaled by the node-step ratio) and swing 1
is kept as is; the warm IPOPT instance is used. After a contact (:meth:`on_impact`) the
executed plan's swing 1 becomes every candidate's swing-0 guess and is repeated as the
swing-1 guess; with ``impact_duals`` (default) its multipliers move the same way (the
touchdown and reset rows keep theirs) and the warm IPOPT instance is used, else primal
only with the cold instance. Without either: the current state held at every node, zero
accelerations (cold).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import ConstraintMargins, GuardEvent, ModeSchedule, Plan, Trajectory
from hmpc_cli.mpc.chain.kind import rejected_plan
from hmpc_cli.mpc.solver import failed, iterate_at
from hmpc_cli.mpc.walking.nlp import WalkingMPCSettings, WalkingNLP, hand_margins
from hmpc_cli.core.registry import MPCSpec
from hmpc_cli.core.walker import WalkerModel

__all__ = ["MPC", "WalkingMPC", "WalkingMPCSettings", "WalkingNLP"]


@dataclass
class _Memory:
    """A stored solution of one candidate.

    Primal w, multipliers (None: primal only), swing 0's node 0 (its (q, qd) part is
    used) and the elapsed swing time it was solved for [s].
    """

    w: np.ndarray
    lam_x: np.ndarray | None
    lam_g: np.ndarray | None
    x0: np.ndarray
    elapsed: float


class WalkingMPC:
    """Two-swing walking MPC over stair-segment candidates, re-solved with warm starts.

    Usage: :meth:`solve` (every period, for the chosen segment, or for every candidate
    at a contact), :meth:`on_impact` right after each contact, before solving again.
    """

    def __init__(self, system: HybridSystem, settings: WalkingMPCSettings | None = None,
                 nlp: WalkingNLP | None = None) -> None:
        self.system = system
        self.s = settings or WalkingMPCSettings()
        self.rate_hz = self.s.rate_hz
        self.nlp = nlp or WalkingNLP(system, self.s)
        self.segments = dict(system.guard_surfaces)
        self._memory: dict[int, _Memory] = {}
        self._template: _Memory | None = None
        self._executing: int | None = None  # target of the last successful solve
        self._swing_start = 0.0  # [s]
        self._t_event = -math.inf  # the newest event applied [s]
        self._planned_at = math.nan  # the t0 of the schedule last solved over [s]
        self._recent: tuple[float, bytes, dict[int, Plan]] = (math.nan, b"", {})
        #: this planning step's solves (same t and x as ``_recent``), by target: (its
        #: solver call, the target's memory before it), and the executing target before
        #: them (:meth:`stop_at`)
        self._step: dict[int, tuple] = {}
        self._step_executing: int | None = None
        self._call: tuple | None = None  # the last solve_segment's solver call

    # -------------------------------------------------------------- contract
    def check(self, schedule: ModeSchedule) -> str:
        """Why ``schedule`` cannot be solved ('' if it can).

        It needs a target guard with a contact surface.
        """
        if not schedule.guards:
            return "no foothold target: the schedule has no guard left"
        g = schedule.guards[0]
        if g not in self.segments:
            return f"guard {self.system.guards[g].name} has no contact surface"
        return ""

    def solve(self, t: float, x: np.ndarray, mode: int, schedule: ModeSchedule,
              events: Sequence[GuardEvent] = (), guess: Trajectory | None = None) -> Plan:
        """Plans two swings from x (12,) at time t [s] (the stack contract).

        The first swing lands on the surface of ``schedule.guards[0]`` (see the module
        docstring); ``guess`` is not used.
        """
        if schedule.t0 != self._planned_at:  # planned anew: an event after t is new to it,
            self._planned_at = schedule.t0  # also one before a withdrawn predicted event
            self._t_event = min(self._t_event, t)
        for ev in events:
            if ev.t > self._t_event:
                self._t_event = ev.t
                self.on_impact(self._executing)
                self._swing_start = ev.t
        reason = self.check(schedule)
        if reason:
            return rejected_plan(t, x, mode, schedule, reason)
        target = schedule.guards[0]
        key = np.asarray(x, dtype=float).tobytes()
        if self._recent[0] != t or self._recent[1] != key:
            self._recent = (t, key, {})
            self._step, self._step_executing = {}, self._executing
        plan = self._recent[2].get(target)
        if plan is None:
            before, self._call = self._memory.get(target), None
            plan = self.solve_segment(t, x, target, t - self._swing_start)
            self._recent[2][target] = plan
            if self._call is not None:
                self._step[target] = (self._call, before)
        if plan.stats.success:
            self._executing = target
        return replace(plan, adopt=plan.stats.success)

    def stop_at(self, stops: Sequence[tuple[Plan, int]]) -> list[tuple[Plan, int]]:
        """Solves stopped by the solve budget or a contact, each where its time ran out.

        ``stops``: (a plan of this planning step's solves, the iterations its solver had
        finished when its time ran out). A solve stopped short leaves its iterate there as its
        target's memory (the next solve's warm start; 0 or a non-finite iterate: the
        memory before it); the plant executes the plan it had before the step (the
        contact's template comes from that target's memory).

        A solve may be stopped again, earlier (a contact before its budget ran out),
        until the next planning step.

        Returns:
            (plan, iterations kept) of the solves stopped; the others keep their whole
            solution (a back-end that cannot stop at an iteration keeps it too).
        """
        out = []
        for plan, k in stops:
            detail = plan.detail
            entry = self._step.get(getattr(detail, "segment", None)) \
                if plan.t0 == self._recent[0] else None
            if entry is None:
                continue
            call, before = entry
            target = detail.segment
            self._executing = self._step_executing
            got = iterate_at(self.nlp.session, k, plan.stats.iterations, call[:8])
            if got is None:
                continue
            kept, res = got
            if res is not None:
                self._memory[target] = _Memory(res.x, res.lam_x, res.lam_g, *call[8:])
            elif kept == 0 and before is None:
                self._memory.pop(target, None)
            elif kept == 0:
                self._memory[target] = before
            out.append((plan, kept))
        return out

    # ---------------------------------------------------------------- memory
    def reset(self) -> None:
        """Forgets every stored solution (next solves start cold)."""
        self._memory.clear()
        self._template = None

    def on_impact(self, segment: int | None) -> None:
        """A contact ended the swing whose plan targeted ``segment`` (None: unknown).

        Every candidate of the new swing starts from that plan's swing 1.
        """
        old = self._memory.get(segment) if segment is not None else None
        self._memory.clear()
        self._template = None
        if old is None:
            return
        nlp = self.nlp
        w = self._repeat_swing1(old.w)
        lam_x = lam_g = None
        if self.s.impact_duals and old.lam_x is not None and old.lam_g is not None:
            lam_x = self._repeat_swing1(old.lam_x)
            lam_g = old.lam_g.copy()
            lam_g[nlp.interval_rows[0]] = old.lam_g[nlp.interval_rows[1]]
            lam_g[nlp.layout.g["liftoff"]] = 0.0
        self._template = _Memory(w, lam_x, lam_g, old.w[nlp.x_idx[1, 0]], 0.0)

    def _repeat_swing1(self, v: np.ndarray) -> np.ndarray:
        """Copy of v with swing 1's node and interval entries on both swings."""
        nlp = self.nlp
        out = v.copy()
        for j in range(2):
            out[nlp.x_idx[j, 1:]] = v[nlp.x_idx[1, 1:]]
            out[nlp.a_idx[j]] = v[nlp.a_idx[1]]
        return out

    def _start(self, segment: int, x0: np.ndarray, elapsed: float) -> tuple:
        """The start (w0, lam_x, lam_g, kind) of a solve onto ``segment`` from x0.

        In order: its own memory shifted, the template after a contact, a neighbour's
        solution of the same state, or the held state (cold).
        """
        start = self._start_of(segment, x0, elapsed)
        return (self._stance_guess(start[0], x0), *start[1:])

    def _start_of(self, segment: int, x0: np.ndarray, elapsed: float) -> tuple:
        if not self.s.warm_start:
            return self._hold(x0), None, None, "cold"
        mem = self._memory.get(segment)
        if mem is not None:
            w0, lam_x, lam_g = self._shifted(mem, elapsed)
            return w0, lam_x, lam_g, "primal-dual" if lam_g is not None else "primal"
        if self._template is not None:
            tpl = self._template
            return (tpl.w.copy(), tpl.lam_x, tpl.lam_g,
                    "primal-dual" if tpl.lam_g is not None else "primal")
        near = self._neighbour(x0, elapsed)
        if near is not None:
            return near.w.copy(), near.lam_x, near.lam_g, "neighbour"
        return self._hold(x0), None, None, "cold"

    def _stance_guess(self, w: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """Sets swing 1's stance-foot variables of w (stage-wise transcription) and returns w.

        Their value is the touchdown of w's swing-0 end state on x0's stance foot: the
        reset's value at w.
        """
        nlp = self.nlp
        if not nlp.stagewise:
            return w
        end = np.concatenate([w[nlp.x_idx[0, nlp.N]], x0[nlp.walker.stance_index]])
        w[nlp.layout.x["stance"]] = np.asarray(nlp.walker.swing_foot_world(end)).ravel()
        return w

    def _neighbour(self, x0: np.ndarray, elapsed: float) -> _Memory | None:
        """Another surface's solution from this very state and swing time, if any.

        The candidates of one planning step share x0 and differ only in the touchdown
        surface (parameters): a cold candidate starts from a solved one (primal-dual)
        instead of the held state (the first foothold step: ~70 IPOPT iterations cold).
        """
        for mem in self._memory.values():
            if mem.elapsed == elapsed and np.array_equal(mem.x0, x0):
                return mem
        return None

    def _hold(self, x0: np.ndarray) -> np.ndarray:
        w = np.zeros(self.nlp.nw)
        w[self.nlp.layout.x["x"]] = x0[:self.nlp.nx]
        return w

    def _shifted(self, mem: _Memory, elapsed: float):
        """The memory re-interpolated on the swing-0 grid of ``elapsed`` (module docstring)."""
        nlp, N = self.nlp, self.nlp.N
        t_old = mem.elapsed + np.arange(N + 1) * nlp.dt0(mem.elapsed)
        t_new = elapsed + np.arange(N + 1) * nlp.dt0(elapsed)
        ratio = nlp.dt0(elapsed) / nlp.dt0(mem.elapsed)

        def interp(values: np.ndarray, t_from: np.ndarray, t_to: np.ndarray) -> np.ndarray:
            return np.column_stack([np.interp(t_to, t_from, values[:, i])
                                    for i in range(values.shape[1])])

        w = mem.w.copy()
        xs = np.vstack([mem.x0[:nlp.nx], mem.w[nlp.x_idx[0, 1:]]])
        w[nlp.x_idx[0, 1:]] = interp(xs, t_old, t_new)[1:]
        w[nlp.a_idx[0]] = interp(mem.w[nlp.a_idx[0]], t_old[:N], t_new[:N])
        if mem.lam_x is None or mem.lam_g is None:
            return w, None, None
        lx = mem.lam_x.copy()
        lxs = mem.lam_x[nlp.x_idx[0, 1:]]
        lx[nlp.x_idx[0, 1:]] = ratio * interp(np.vstack([lxs[:1], lxs]), t_old, t_new)[1:]
        lx[nlp.a_idx[0]] = interp(mem.lam_x[nlp.a_idx[0]], t_old[:N], t_new[:N])
        lg = mem.lam_g.copy()
        rows = nlp.interval_rows[0]
        block = interp(mem.lam_g[rows], t_old[:N], t_new[:N])
        block[~np.isin(rows, nlp.layout.g["dynamics"])] *= ratio  # path rows
        lg[rows] = block
        return w, lx, lg

    # ---------------------------------------------------------------- solve
    def solve_segment(self, t: float, x0: np.ndarray, segment: int, elapsed: float = 0.0
                      ) -> Plan:
        """Plans two swings from x0, the first landing on the surface of guard ``segment``.

        Args:
            t: simulated time of x0 [s] (the plan's t0).
            x0: state (q, qd, p_st), shape (12,).
            segment: the target guard's index (it must have a contact surface).
            elapsed: time already spent in the current swing [s].

        Returns:
            The plan; ``stats.success`` False on any solver failure or a segment too
            short for the margin (never raises for those); its detail a
            :class:`WalkingDetail` (segment, elapsed, warm start, touchdown, final hip).

        Raises:
            IndexError: no such surface.
        """
        if segment not in self.segments:
            raise IndexError(f"guard {segment} has no contact surface (surfaces: "
                             f"{sorted(self.segments)})")
        nlp = self.nlp
        x0 = np.asarray(x0, dtype=float).reshape(-1)
        p, lbx, ubx, lbg, ubg = nlp.problem_data(x0, self.segments[segment], elapsed)
        w0, lam_x, lam_g, kind = self._start(segment, x0, elapsed)
        a, b, _ = self.segments[segment]
        if not np.all(np.isfinite(x0)):
            res = failed(w0, "non-finite initial state")
        elif b - a < 2 * nlp.segment_margin:
            res = failed(w0, f"segment {self.system.guards[segment].name} ({b - a:g} m) "
                             f"is shorter than {2 * nlp.segment_margin:g} m, twice the "
                             f"segment margin")
        else:
            res = nlp.optimize(w0, p, lbx, ubx, lbg, ubg, lam_x, lam_g)
            self._call = (w0, p, lbx, ubx, lbg, ubg, lam_x, lam_g, x0, elapsed)
        if res.stats.success:
            self._memory[segment] = _Memory(res.x, res.lam_x, res.lam_g, x0, elapsed)
        else:
            self._memory.pop(segment, None)
        finite = bool(np.all(np.isfinite(res.x)))
        traj = self.trajectory(res.x if finite else w0, p, segment)
        remaining = nlp.N * nlp.dt0(elapsed)
        td = np.asarray(nlp.walker.swing_foot_world(traj.x[nlp.N])).ravel()
        hip = np.asarray(nlp.walker.hip_world(traj.x[-1])).ravel()
        detail = WalkingDetail(int(segment), float(elapsed), kind,
                               tuple(float(v) for v in td), tuple(float(v) for v in hip))
        stance = (nlp.mode, nlp.mode)
        return Plan(t, traj, res.stats, ModeSchedule(stance, (segment,), (remaining,), t),
                    detail)

    # ------------------------------------------------------------- trajectory
    def trajectory(self, w: np.ndarray, p: np.ndarray, segment: int) -> Trajectory:
        """The plan at primal point w: 2 (N + 1) nodes, the touchdown as a node pair.

        Times relative to t0; x rows (q, qd, p_st); u rows the inverse-dynamics torques
        of the interval starting at each node (the last node of a swing repeats the
        previous one); every node in the stance mode; seg 0 up to the pre-impact node, 1
        from the post-reset node.
        """
        nlp, N = self.nlp, self.nlp.N
        xs, us = nlp.states_inputs(w, p)
        dt0 = float(p[nlp.layout.p["dt0"]])
        t = np.r_[np.arange(N + 1) * dt0, N * dt0 + np.arange(N + 1) * self.s.dt]
        u = np.vstack([us[:N], us[N - 1:N], us[N:], us[-1:]])
        seg = np.r_[np.zeros(N + 1, dtype=int), np.ones(N + 1, dtype=int)]
        mode = np.full(2 * N + 2, nlp.mode, dtype=int)
        return Trajectory(t, xs, u, mode, seg, (segment,), "zoh")


@dataclass(frozen=True)
class WalkingDetail:
    """/mpc/solve detail of the walking MPC.

    Attributes:
        segment: the target guard's index (/run/info ``guard_names``), whose contact
            surface the first swing lands on.
        elapsed: time already spent in the current swing [s] (since the last contact, or
            the run's start).
        warm: the warm start ("primal-dual", "primal", "neighbour": another surface's
            solution from the same state, or "cold").
        touchdown: the planned touchdown, the swing foot's (x, y) in the world at the
            first swing's last node [m].
        final_hip: the hip's (x, y) in the world at the plan's last node [m].
    """

    segment: int
    elapsed: float
    warm: str
    touchdown: tuple[float, ...]
    final_hip: tuple[float, ...]


def _problem(system: HybridSystem, settings: WalkingMPCSettings,
             margins: ConstraintMargins | None = None) -> WalkingNLP:
    return WalkingNLP(system, settings, margins)


MPC = MPCSpec(
    kind="walking", settings=WalkingMPCSettings, problem=_problem, make=WalkingMPC,
    hand_margins=hand_margins, detail=WalkingDetail,
    needs=frozenset({"terrain", "guard_surfaces", WalkerModel}))
