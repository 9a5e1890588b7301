"""The chain MPC's node-chain solver: node schedules, node shifting, warm starts."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import Plan, Trajectory
from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule, remap
from hmpc_cli.mpc.chain.nlp import FixedModeNLP, FixedModeNLPs, MPCSettings
from hmpc_cli.mpc.solver import iterate_at


class ChainSolver:
    """The chain MPC's node chain: its NLP over a node schedule, re-optimized with warm starts.

    Usage: :meth:`set_schedule` (with an initial guess), then :meth:`reoptimize` every
    period after :meth:`shift` (and after :meth:`on_impact` when the scheduled guard fires).
    Each schedule is solved on the NLP that fits it (:class:`FixedModeNLPs`); ``nlp`` is
    the one in use.
    """

    def __init__(self, system: HybridSystem, settings: MPCSettings,
                 nlps: FixedModeNLPs | None = None) -> None:
        self.system = system
        self.s = settings
        self.nlps = nlps or FixedModeNLPs(system, settings)
        self.nlp: FixedModeNLP = self.nlps.switching
        self.node_schedule: NodeSchedule | None = None
        self.layout: ChainLayout | None = None
        self._w: np.ndarray | None = None
        self._lam_x: np.ndarray | None = None
        self._lam_g: np.ndarray | None = None
        #: the last :meth:`reoptimize`'s call (its NLP, arguments, the warm start before it)
        self._last: tuple | None = None

    # ------------------------------------------------------------ schedule
    def set_schedule(self, ns: NodeSchedule, guess: Trajectory | None = None) -> None:
        """Installs a new node schedule; the initial guess comes from ``guess``."""
        self.nlp = self.nlps.for_schedule(ns)
        layout = ChainLayout.build(ns, self.nlp.L)
        self.node_schedule, self.layout = ns, layout
        self._w = self._guess_from(guess, ns, layout) if guess is not None else None
        self._lam_x = self._lam_g = None

    def shift(self, elapsed: int) -> int:
        """Moves ``elapsed`` intervals to the final domain; returns how many moved."""
        new_ns, moved = self.node_schedule.shift(elapsed)
        self._relayout(new_ns, dropped=0, offset0=elapsed)
        return moved

    def on_impact(self) -> None:
        """The scheduled guard fired: drop the current domain (virtual node included)."""
        self._relayout(self.node_schedule.on_impact(), dropped=1, offset0=0)

    def _relayout(self, ns: NodeSchedule, dropped: int, offset0: int) -> None:
        old, old_nlp = self.layout, self.nlp
        self.nlp = self.nlps.for_schedule(ns)
        new = ChainLayout.build(ns, self.nlp.L)
        node_map = remap(old, new, dropped, offset0)
        self._w, self._lam_x, self._lam_g = self.nlp.remap_vectors(
            node_map, self._w, self._lam_x, self._lam_g, source=old_nlp)
        self.node_schedule, self.layout = ns, new

    def _guess_from(self, traj: Trajectory, ns: NodeSchedule, layout: ChainLayout):
        """Primal guess: the planner's rollout, segment by segment, by time."""
        nlp = self.nlp
        w = np.zeros(nlp.nx_var)
        for k in range(nlp.L + 1):
            j = int(layout.seg[k]) if layout.seg[k] >= 0 else len(ns.counts) - 1
            rows = np.nonzero(traj.seg == j)[0]
            if rows.size == 0:
                rows = np.array([len(traj.t) - 1])
            t_seg = traj.t[rows] - traj.t[rows[0]]
            tau = layout.local[k] * nlp.dt if layout.seg[k] >= 0 else t_seg[-1]
            if j < len(ns.guards) and layout.local[k] == ns.counts[j]:
                tau = t_seg[-1]
            x = np.array([np.interp(tau, t_seg, traj.x[rows, i]) for i in range(nlp.n)])
            w[nlp.z_idx[k]] = x
            if k < nlp.L:
                w[nlp.u_idx[k]] = [np.interp(tau, t_seg, traj.u[rows, i])
                                   for i in range(nlp.m)]
        return w

    # ----------------------------------------------------------- reoptimize
    def reoptimize(self, t: float, x0: np.ndarray) -> Plan:
        """Re-optimizes from state ``x0`` at simulated time t; never raises on solver failure."""
        nlp, ns, lay = self.nlp, self.node_schedule, self.layout
        p, lbx, ubx, lbg, ubg = nlp.problem_data(ns, lay, x0)
        if self._w is None:  # no guess: hold the current state
            self._w = np.zeros(nlp.nx_var)
            self._w[nlp.z_idx] = x0
        w0 = self._w.copy()
        w0[nlp.z_idx[0]] = x0
        warm = self.s.warm_start and self._lam_g is not None
        call = (w0, p, lbx, ubx, lbg, ubg, self._lam_x if warm else None,
                self._lam_g if warm else None)
        res = nlp.optimize(*call)
        self._last = (t, res.stats, nlp, call, (self._w, self._lam_x, self._lam_g))
        ok = res.stats.success
        slack = float(np.max(res.x[nlp.s_idx], initial=0.0)) if ok else float("nan")
        if ok:
            self._w, self._lam_x, self._lam_g = res.x, res.lam_x, res.lam_g
        traj = nlp.trajectory(res.x if ok else self._w_with(x0), ns, lay)
        return Plan(t, traj, replace(res.stats, slack=slack), ns)

    def stop_at(self, plan: Plan, iterations: int) -> int | None:
        """The last :meth:`reoptimize`, which returned ``plan``, stopped after ``iterations``.

        Its iterate there becomes the next solve's warm start (0: the warm start it
        started from; a non-finite iterate: that too). It may be stopped again, earlier
        (a contact that came before its budget ran out), until the next solve.

        Returns:
            The iterations of the warm start kept, or None: ``plan`` is not the last
            solve's, or the back-end cannot stop at an iteration (its whole solution
            stays).
        """
        if self._last is None:
            return None
        t, stats, nlp, call, before = self._last
        if (plan.t0, plan.stats.iterations, plan.stats.wall_time) != \
                (t, stats.iterations, stats.wall_time):
            return None
        got = iterate_at(nlp.session, iterations, stats.iterations, call)
        if got is None:
            return None
        kept, res = got
        if res is not None:
            self._w, self._lam_x, self._lam_g = res.x, res.lam_x, res.lam_g
        elif kept == 0:
            self._w, self._lam_x, self._lam_g = before
        return kept

    def _w_with(self, x0: np.ndarray) -> np.ndarray:
        w = self._w.copy()
        w[self.nlp.z_idx[0]] = x0
        return w

    def constraint_report(self, plan_w: np.ndarray, x0: np.ndarray) -> dict:
        """Max violations of the NLP at a primal point (for tests and checks)."""
        p, lbx, ubx, lbg, ubg = self.nlp.problem_data(self.node_schedule, self.layout, x0)
        return {"violation": self.nlp.violation(plan_w, p, lbx, ubx, lbg, ubg)}

    @property
    def N(self) -> int:
        """Flow intervals over the horizon."""
        return self.nlps.N

    @property
    def dt(self) -> float:
        """Node step [s]."""
        return self.nlps.dt

    @property
    def solution(self) -> np.ndarray:
        """The current primal vector (last successful solve, remapped)."""
        return self._w
