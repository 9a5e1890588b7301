"""Hybrid MPC by the cross-entropy method (the ball's planner).

Samples open-loop input sequences (``knots`` values per input channel over the horizon,
linearly interpolated), rolls each out with the hybrid simulator (same guard logic and
exact event location as the plant, no disturbance, step ``1 / rollout_rate_hz``), and
keeps the elite. The domain/guard sequence and durations of the best rollout are the
schedule. Reference parameters by default: 50 samples plus the current mean, 1 elite,
15 iterations, initial mean -20, covariance 250 I never adapted.
"""

from __future__ import annotations

import time

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from hmpc_cli.hybrid import HybridSystem
from hmpc_cli.messages import ModeSchedule, PlannerResult, Trajectory
from hmpc_cli.numeric import compile_numpy
from hmpc_cli.sim import HybridSimulator

UNREACHED_PENALTY = 1e4


class CEMSettings(BaseModel):
    """Cross-entropy planner settings."""

    model_config = ConfigDict(extra="forbid")
    kind: str = Field("cem", pattern="^cem$")
    horizon: float = Field(3.0, gt=0.0, description="planning horizon [s]")
    knots: int = Field(45, ge=2, description="input knots per channel over the horizon")
    samples: int = Field(50, ge=1, description="random samples per iteration (+ the mean)")
    elites: int = Field(1, ge=1)
    iterations: int = Field(15, ge=1)
    init_mean: float = Field(-20.0, description="initial mean of every knot")
    init_cov: float = Field(250.0, gt=0.0, description="initial variance of every knot")
    adapt_covariance: bool = Field(False, description="refit the variance to the elites")
    min_cov: float = Field(1.0, gt=0.0, description="variance floor when adapting")
    rollout_rate_hz: int = Field(60, gt=0, description="rollout integration rate [Hz]")
    warm_start: bool = Field(False, description="start from the previous best, shifted")
    seed: int = Field(0, ge=0, description="base seed (the run seed is mixed in)")

    @field_validator("elites")
    @classmethod
    def _elites(cls, v: int, info: ValidationInfo) -> int:
        samples = info.data.get("samples")
        if samples is not None and v > samples + 1:
            raise ValueError(f"{v} elites exceed the {samples} samples + the mean")
        return v


class CrossEntropyPlanner:
    """Plans a mode schedule from a hybrid state by the cross-entropy method."""

    def __init__(self, system: HybridSystem, settings: CEMSettings, run_seed: int = 0):
        self.system = system
        self.s = settings
        self.sim = HybridSimulator(system)
        self.cost_fn = compile_numpy(system.stage_cost)
        self.final_mode = system.mode_index(system.final_mode)
        self.dt = 1.0 / settings.rollout_rate_hz
        self.n_steps = int(round(settings.horizon * settings.rollout_rate_hz))
        self.t_knots = np.linspace(0.0, settings.horizon, settings.knots)
        self.t_steps = np.arange(self.n_steps) * self.dt
        self.run_seed = run_seed
        self._previous: np.ndarray | None = None
        self._previous_t = 0.0

    def _inputs(self, knots: np.ndarray) -> np.ndarray:
        """Knot values (B, knots, m) -> step inputs (B, n_steps, m), linear interpolation."""
        k = np.searchsorted(self.t_knots, self.t_steps, side="right") - 1
        k = np.clip(k, 0, len(self.t_knots) - 2)
        a = ((self.t_steps - self.t_knots[k]) / (self.t_knots[k + 1] - self.t_knots[k]))
        a = a[None, :, None]
        return (1.0 - a) * knots[:, k, :] + a * knots[:, k + 1, :]

    def rollout_cost(self, x0: np.ndarray, mode0: int, knots: np.ndarray,
                     bound: float = np.inf):
        """Costs (B,) and final-domain flags (B,) of knot sequences (B, knots, m).

        The final domain is absorbing: a rollout that enters it stops there and accrues
        the stage cost of its entry state (zero input) for the rest of the horizon; one
        that never enters pays ``UNREACHED_PENALTY`` on top of its cost. Costs only grow
        along a rollout, so one whose running cost exceeds ``bound`` is stopped and
        gets cost inf (exact pruning when only the best sample matters).
        """
        b = knots.shape[0]
        u = self._inputs(knots)
        x = np.repeat(x0[None, :], b, axis=0)
        mode = np.full(b, mode0)
        w = np.zeros((b, self.system.n_w))
        u_zero = np.zeros((b, self.system.n_u))
        cost = np.zeros(b)
        alive = np.ones(b, dtype=bool)
        reached = mode == self.final_mode
        for k in range(self.n_steps):
            todo = alive & ~reached
            if todo.all():
                run = slice(None)  # views, no copies
            else:
                run = np.nonzero(todo)[0]
                if run.size == 0:
                    break
            u_run = u[run, k, :]
            u_k = self.sim.num.saturate(mode[run], u_run)
            cost[run] += self.dt * self.cost_fn(x[run], u_k)[0][:, 0]
            res = self.sim.step(x[run], mode[run], u_run, w[run], self.dt,
                                record=False, raise_zeno=False)
            x[run], mode[run] = res.x, res.mode
            alive[run] &= ~res.zeno & np.isfinite(res.x).all(axis=1) & (cost[run] <= bound)
            reached[run] = (res.mode == self.final_mode) & alive[run]
            entered = np.arange(b)[run][reached[run]]
            if entered.size:
                rest = self.n_steps - k - 1
                cost[entered] += rest * self.dt * self.cost_fn(x[entered], u_zero[entered])[0][:, 0]
        cost = np.where(alive, cost, np.inf) + np.where(reached, 0.0, UNREACHED_PENALTY)
        return cost, reached

    def plan(self, t: float, x0: np.ndarray, mode0: int) -> PlannerResult:
        """Runs the CEM from state x0 in mode ``mode0`` at simulated time t [s]."""
        start = time.perf_counter()
        s, m = self.s, self.system.n_u
        rng = np.random.default_rng([s.seed, self.run_seed, int(round(t * 1e6))])
        mean = np.full((s.knots, m), s.init_mean)
        if s.warm_start and self._previous is not None:
            shifted = self.t_knots + (t - self._previous_t)
            for j in range(m):
                mean[:, j] = np.interp(shifted, self.t_knots, self._previous[:, j])
        var = np.full((s.knots, m), s.init_cov)
        best_cost, best = np.inf, mean.copy()
        for _ in range(s.iterations):
            noise = rng.standard_normal((s.samples, s.knots, m))
            samples = np.concatenate([mean[None], mean[None] + np.sqrt(var)[None] * noise])
            bound = best_cost if s.elites == 1 else np.inf
            cost, _ = self.rollout_cost(x0, mode0, samples, bound)
            order = np.argsort(cost, kind="stable")
            elite = samples[order[: s.elites]]
            if cost[order[0]] < best_cost:
                best_cost, best = float(cost[order[0]]), samples[order[0]].copy()
            mean = elite.mean(axis=0)
            if s.adapt_covariance and s.elites > 1:
                var = np.maximum(elite.var(axis=0), s.min_cov)
        self._previous, self._previous_t = best, t
        traj = self.trajectory(x0, mode0, best)
        reached = bool(traj.mode[-1] == self.final_mode)
        schedule = schedule_from(traj) if reached else None
        return PlannerResult(schedule, traj, best_cost, reached,
                             time.perf_counter() - start, s.iterations)

    def trajectory(self, x0: np.ndarray, mode0: int, knots: np.ndarray) -> Trajectory:
        """The recorded rollout of one knot sequence (resets appear as two nodes)."""
        u = self._inputs(knots[None])[0]
        x, mode = x0[None, :].astype(float), np.array([mode0])
        w = np.zeros((1, self.system.n_w))
        ts, xs, us, ms, segs, guards = [0.0], [x[0].copy()], [], [mode0], [0], []
        for k in range(self.n_steps):
            u_k = self.sim.num.saturate(mode, u[k][None])[0]
            res = self.sim.step(x, mode, u[k][None], w, self.dt, raise_zeno=False)
            for e in res.events:
                guards.append(e.guard)
                for state, mode_e in ((e.x_before, ms[-1]), (e.x_after, self.sim.num.target[e.guard])):
                    us.append(u_k)
                    ts.append(k * self.dt + e.tau)
                    xs.append(state)
                    ms.append(int(mode_e))
                    segs.append(len(guards) - (state is e.x_before))
            us.append(u_k)
            x, mode = res.x, res.mode
            ts.append((k + 1) * self.dt)
            xs.append(x[0].copy())
            ms.append(int(mode[0]))
            segs.append(len(guards))
            if res.zeno.any() or not np.all(np.isfinite(x)) or mode[0] == self.final_mode:
                break
        us.append(us[-1])
        return Trajectory(np.array(ts), np.array(xs), np.array(us), np.array(ms),
                          np.array(segs), tuple(guards))


def schedule_from(traj: Trajectory) -> ModeSchedule:
    """The domain/guard sequence and per-domain durations of a recorded trajectory."""
    n_seg = len(traj.guards) + 1
    starts = [float(traj.t[np.argmax(traj.seg == j)]) for j in range(n_seg)]
    modes = tuple(int(traj.mode[np.argmax(traj.seg == j)]) for j in range(n_seg))
    durations = tuple(starts[j + 1] - starts[j] for j in range(n_seg - 1))
    return ModeSchedule(modes, tuple(int(g) for g in traj.guards), durations)
