"""Hybrid MPC by the cross-entropy method (the ball's planner).

Samples open-loop input sequences (``knots`` values per input channel over the horizon,
linearly interpolated), rolls each out with the hybrid simulator (same guard logic and
exact event location as the plant, no disturbance, step ``1 / rollout_rate_hz``), and
keeps the elite. The domain/guard sequence and durations of the best rollout are the
schedule. Reference parameters by default: 50 samples plus the current mean, 1 elite,
15 iterations, initial mean -20, covariance 250 I never adapted.

Rollouts and the best sample's recorded trajectory run in compiled C
(:mod:`hmpc_cli.sim.rollout`, same guard logic, same numbers) when a C compiler is
available, else with the NumPy simulator, which is also the reference.
"""

from __future__ import annotations

import time
import warnings
from typing import Literal

import numpy as np
from pydantic import ConfigDict, Field, ValidationInfo, field_validator

from hmpc_cli.core.kinds import PlannerSettings
from hmpc_cli.core import signals
from hmpc_cli.core.cbuild import compiler_problem
from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import ModeSchedule, PlannerResult, Trajectory
from hmpc_cli.core.numeric import compile_numpy
from hmpc_cli.sim.rollout import CRollout, RolloutBuildError
from hmpc_cli.core.registry import PlannerSpec
from hmpc_cli.core.settings_types import (
    BoundedInt, FiniteFloat, StrictBool, duration_text, gib, memory_limit)
from hmpc_cli.sim.simulator import HybridSimulator

UNREACHED_PENALTY = 1e4


class CEMSettings(PlannerSettings):
    """Cross-entropy planner settings."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["cem"] = Field("cem", description="cross-entropy method (ball)")
    horizon: FiniteFloat = Field(3.0, gt=0.0, description="planning horizon [s]")
    knots: BoundedInt = Field(45, ge=2, description="input knots per channel over the horizon")
    samples: BoundedInt = Field(50, ge=1, description="random samples per iteration (+ the "
                                "mean); a planner call rolls out at most 1e9 steps in all "
                                "(iterations x (samples + 1) x horizon x rollout_rate_hz)")
    elites: BoundedInt = Field(1, ge=1)
    iterations: BoundedInt = Field(15, ge=1, description="CEM iterations per planner call "
                                   "(the work limit: see samples)")
    init_mean: FiniteFloat = Field(0.0, description="initial mean of every knot (a system may "
                             "set its own default)")
    init_cov: FiniteFloat = Field(250.0, gt=0.0, description="initial variance of every knot")
    adapt_covariance: StrictBool = Field(False, description="refit the variance to the elites "
                                         "(with planner.elites >= 2)")
    min_cov: FiniteFloat = Field(1.0, gt=0.0, description="variance floor when adapting")
    rollout_rate_hz: BoundedInt = Field(60, gt=0, description="rollout integration rate [Hz]")
    warm_start: StrictBool = Field(False, description="start from the previous best, shifted")
    seed: BoundedInt = Field(0, ge=0, description="base seed (the run seed is mixed in)")
    cost: Literal["hmpc", "reference"] = Field(
        "hmpc", description="rollout cost: 'hmpc' (the final domain is absorbing: a rollout "
        "entering it stops and accrues its entry state's stage cost [cost units] for the rest "
        "of the horizon; one never entering pays a penalty of 1e4) or 'reference' (the "
        "authors' plan: the stage cost summed over the whole horizon [s] with the sampled "
        "inputs, the final domain not absorbing, no penalty; a plan must have entered it)")
    rollout_backend: Literal["auto", "c", "numpy"] = Field(
        "auto", description="rollout code: compiled C, NumPy, or auto (C if it builds, "
                            "else NumPy with a warning)")

    @field_validator("elites")
    @classmethod
    def _elites(cls, v: int, info: ValidationInfo) -> int:
        samples = info.data.get("samples")
        if samples is not None and v > samples + 1:
            raise ValueError(f"{v} elites exceed the {samples} samples + the mean")
        return v


    def size_problems(self) -> list[str]:
        """Planner calls too long to wait for or too short, or arrays too big for memory.

        Too short: a horizon of less than one rollout step.

        Work: a planner call rolls out iterations x (samples + 1) input sequences of
        horizon x rollout_rate_hz steps each, at most :data:`MAX_ROLLOUT_STEPS` steps in
        all. Memory: per input channel a CEM iteration holds 2 x (samples + 1) x knots
        floats (the samples and their noise) and, per batch of at most
        :data:`ROLLOUT_BATCH` samples, 2 x batch x rollout steps (the interpolated inputs).
        """
        out = []
        steps = self.horizon * self.rollout_rate_hz
        if round(steps) < 1:
            out.append(
                f"planner.horizon: {self.horizon:g} s x {self.rollout_rate_hz:g} Hz "
                f"(planner.rollout_rate_hz) = {steps:.3g} rollout steps: a rollout needs at "
                f"least one; lengthen planner.horizon to {1.0 / self.rollout_rate_hz:g} s or "
                "more, or raise planner.rollout_rate_hz")
        rollouts = self.iterations * (self.samples + 1)
        work = rollouts * max(1.0, steps)
        if work > MAX_ROLLOUT_STEPS:
            secs = work * ROLLOUT_STEP_NS * 1e-9
            out.append(
                f"planner.iterations x planner.samples: {self.iterations} iterations x "
                f"({self.samples} + 1) samples = {rollouts:.3g} rollouts of {steps:.3g} steps "
                f"(planner.horizon x planner.rollout_rate_hz) = {work:.3g} rollout steps per "
                f"planner call, limit {MAX_ROLLOUT_STEPS:.0e} (about {duration_text(secs)} "
                f"per planner call at {ROLLOUT_STEP_NS:g} ns per step in C)")
        batch = min(self.samples + 1, ROLLOUT_BATCH)
        knots, inputs = (self.samples + 1) * self.knots, batch * steps
        need = 8.0 * 2 * (knots + inputs) * MAX_INPUTS
        if need > memory_limit():  # named by the larger term: the keys to lower
            keys = "planner.samples x planner.knots" if knots >= inputs else \
                "planner.horizon x planner.rollout_rate_hz"
            out.append(
                f"{keys}: 2 x (({self.samples} + 1) samples x {self.knots} knots + "
                f"{batch} x {steps:.3g} rollout steps) x {MAX_INPUTS} inputs x 8 B = "
                f"{gib(need)} exceeds the memory limit {gib(memory_limit())} (half of this "
                f"machine's RAM); lower {keys.replace(' x ', ' or ')}")
        return out


#: most rollout steps of one planner call (iterations x (samples + 1) x horizon steps):
#: about 2 minutes of C rollouts; the paper's planner needs 1.4e5
MAX_ROLLOUT_STEPS = 1e9
#: measured time of one rollout step in C [ns] (ball, one core of a 2-core machine)
ROLLOUT_STEP_NS = 120.0
#: samples rolled out in one batch: a stop signal is checked between batches (a larger
#: iteration is cut in batches; rollouts of one batch advance in lockstep, see
#: :mod:`hmpc_cli.sim.rollout`, so a batch's results are the same in C and NumPy)
ROLLOUT_BATCH = 4096
#: input channels the memory estimate assumes (the biped's 4; the ball has 2)
MAX_INPUTS = 4


def _warn_numpy(why: str) -> None:
    """The fallback's warning, from this one line: Python's filter says it once a process."""
    warnings.warn(f"C rollouts unavailable, using NumPy: {why}", RuntimeWarning, stacklevel=1)


class CrossEntropyPlanner:
    """Plans a mode schedule from a hybrid state by the cross-entropy method.

    Attributes:
        backend: "c" or "numpy", the rollout implementation in use. With
            ``rollout_backend = "auto"`` the C library compiles while the rest of the run
            is built; the first rollout waits for it (a failed compile: "numpy", with a
            warning, the same numbers bit for bit on IEEE +, -, *, /, sqrt).

    Raises:
        RolloutBuildError: ``rollout_backend="c"`` and the C rollout cannot be built.
    """

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
        k = np.searchsorted(self.t_knots, self.t_steps, side="right") - 1
        self._knot = np.clip(k, 0, len(self.t_knots) - 2)  # left knot of each step
        k = self._knot
        a = (self.t_steps - self.t_knots[k]) / (self.t_knots[k + 1] - self.t_knots[k])
        self._weight = a[None, :, None]  # weight of the right knot
        self.run_seed = run_seed
        self._previous: np.ndarray | None = None
        self._previous_t = 0.0
        self.backend, self._c = "numpy", None
        if settings.rollout_backend != "numpy":
            try:  # "auto": compiled while the stack builds, waited for at the first plan
                self._c = CRollout(system, self.sim.max_events, self.sim.time_tol,
                                   wait=settings.rollout_backend == "c")
                self.backend = "c"
            except RolloutBuildError as e:
                self._without_c(e)

    def _compiled(self) -> CRollout | None:
        """The C rollouts once compiled, or None (NumPy: not built, or their build failed)."""
        if self._c is not None and not self._c.ready:
            try:
                self._c.wait()
            except RolloutBuildError as e:
                self._without_c(e)
        return self._c

    def _without_c(self, error: RolloutBuildError) -> None:
        """The C rollouts failed to build: an error for "c", NumPy for "auto" (a warning)."""
        first = (str(error).splitlines() or [""])[0]
        if self.s.rollout_backend == "c":
            raise RolloutBuildError(
                f"planner.rollout_backend = 'c': the C rollouts cannot be built "
                f"({first}); set it to 'auto' or 'numpy'") from error
        self.backend, self._c = "numpy", None
        if not compiler_problem():  # an unusable $CC has had its one warning
            _warn_numpy(first)

    def _inputs(self, knots: np.ndarray) -> np.ndarray:
        """Knot values (B, knots, m) -> step inputs (B, n_steps, m), linear interpolation."""
        k, a = self._knot, self._weight
        knots = np.asarray(knots, dtype=float)
        out = np.take(knots, k, axis=1)  # (1 - a) * left + a * right, in place
        out *= 1.0 - a
        right = np.take(knots, k + 1, axis=1)
        right *= a
        out += right
        return out

    def rollout_cost(self, x0: np.ndarray, mode0: int, knots: np.ndarray,
                     bound: float = np.inf):
        """Costs (B,) and final-domain flags (B,) of knot sequences (B, knots, m).

        Runs in C if ``backend == "c"``, else :meth:`rollout_cost_numpy`; both give the
        same numbers bit for bit (the C kernel keeps NumPy's batch semantics). More than
        :data:`ROLLOUT_BATCH` samples are rolled out in batches of that many, a stop signal
        checked before each (:func:`hmpc_cli.core.signals.check`).

        Raises:
            hmpc_cli.core.signals.Interrupted: a stop signal is pending.
        """
        knots = np.asarray(knots, dtype=float)
        if knots.shape[0] <= ROLLOUT_BATCH:
            signals.check()
            return self._batch_cost(x0, mode0, knots, bound)
        costs, flags = [], []
        for i in range(0, knots.shape[0], ROLLOUT_BATCH):
            signals.check()
            cost, reached = self._batch_cost(x0, mode0, knots[i:i + ROLLOUT_BATCH], bound)
            costs.append(cost)
            flags.append(reached)
        return np.concatenate(costs), np.concatenate(flags)

    def _batch_cost(self, x0: np.ndarray, mode0: int, knots: np.ndarray, bound: float):
        """:meth:`rollout_cost` of one batch, in C or NumPy."""
        c = self._compiled()
        if c is None:
            return self.rollout_cost_numpy(x0, mode0, knots, bound)
        cost, reached = c.cost(np.asarray(x0, dtype=float), mode0, self._inputs(knots),
                               self.dt, self.final_mode, bound, self.penalty, self.absorbing)
        return cost + self._stay_cost(x0, mode0), reached

    def _stay_cost(self, x0: np.ndarray, mode0: int) -> float:
        """A rollout's cost when it starts in the (absorbing) final domain (0 elsewhere).

        Its entry state's stage cost, zero input, over the whole horizon.
        """
        if not self.absorbing or mode0 != self.final_mode:
            return 0.0
        x = np.asarray(x0, dtype=float)[None, :]
        stage = self.cost_fn(x, np.zeros((1, self.system.n_u)))[0][0, 0]
        return float(self.n_steps * self.dt * stage)

    @property
    def absorbing(self) -> bool:
        """Whether a rollout stops in the final domain (cost "hmpc") or runs on."""
        return self.s.cost == "hmpc"

    @property
    def penalty(self) -> float:
        """Cost added to a rollout that never enters the final domain."""
        return UNREACHED_PENALTY if self.absorbing else 0.0

    def rollout_cost_numpy(self, x0: np.ndarray, mode0: int, knots: np.ndarray,
                           bound: float = np.inf):
        """Costs (B,) and final-domain flags (B,) of knot sequences (B, knots, m), NumPy.

        Cost "hmpc": the final domain is absorbing: a rollout that enters it stops there
        and accrues the stage cost of its entry state (zero input) for the rest of the
        horizon (from x0 in it: the whole horizon); one that never enters pays
        ``UNREACHED_PENALTY`` on top of its cost.
        Cost "reference": every rollout runs the whole horizon with its sampled inputs
        (leaving the final domain again is possible), the flag says whether it ever
        entered, no penalty. Costs only grow along a rollout, so one whose running cost
        exceeds ``bound`` is stopped and gets cost inf (exact pruning when only the best
        sample matters).
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
        absorbing = self.absorbing
        cost += self._stay_cost(x0, mode0)  # started in it: the entry cost, all along
        for k in range(self.n_steps):
            todo = alive & ~reached if absorbing else alive
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
            if not absorbing:
                reached[run] = (reached[run] | (res.mode == self.final_mode)) & alive[run]
                continue
            reached[run] = (res.mode == self.final_mode) & alive[run]
            entered = np.arange(b)[run][reached[run]]
            if entered.size:
                rest = self.n_steps - k - 1
                cost[entered] += rest * self.dt * self.cost_fn(x[entered], u_zero[entered])[0][:, 0]
        cost = np.where(alive, cost, np.inf) + np.where(reached, 0.0, self.penalty)
        return cost, reached

    def plan(self, t: float, x0: np.ndarray, mode0: int, solve=None) -> PlannerResult:
        """Runs the CEM from state x0 in mode ``mode0`` at simulated time t [s].

        ``solve`` (the stack contract's MPC callback) is not used: rollouts rank the
        samples. A best rollout that never reaches the final domain gives no schedule.
        """
        self._compiled()  # waits for a background compile: build time, not the plan's
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
        entered = np.zeros(0, dtype=bool)
        for _ in range(s.iterations):
            signals.check()  # the run stops within one iteration (and batch) of a signal
            noise = rng.standard_normal((s.samples, s.knots, m))
            samples = np.concatenate([mean[None], mean[None] + np.sqrt(var)[None] * noise])
            bound = best_cost if s.elites == 1 else np.inf
            cost, entered = self.rollout_cost(x0, mode0, samples, bound)
            order = np.argsort(cost, kind="stable")
            elite = samples[order[: s.elites]]
            if cost[order[0]] < best_cost:
                best_cost, best = float(cost[order[0]]), samples[order[0]].copy()
            mean = elite.mean(axis=0)
            if s.adapt_covariance and s.elites > 1:
                var = np.maximum(elite.var(axis=0), s.min_cov)
        signals.check()
        self._previous, self._previous_t = best, t
        traj = self.trajectory(x0, mode0, best)
        reached = bool(traj.mode[-1] == self.final_mode)
        schedule = schedule_from(traj, t) if reached else None
        note = "" if reached else "no rollout reached the final domain"
        if not reached and not self.absorbing and entered.any():  # they ranked lower
            note = (f"the best rollout did not reach the final domain ({int(entered.sum())} "
                    f"of the last iteration's {entered.size} did, at a higher cost)")
        return PlannerResult(schedule, traj, best_cost, reached,
                             time.perf_counter() - start, s.iterations, note)

    def trajectory(self, x0: np.ndarray, mode0: int, knots: np.ndarray) -> Trajectory:
        """The recorded rollout of one knot sequence (resets appear as two nodes)."""
        u = self._inputs(knots[None])[0]
        c = self._compiled()
        if c is not None:
            steps = c.trajectory(x0, mode0, u, self.dt, self.final_mode)
        else:
            steps = self._steps_numpy(x0, mode0, u)
        num = self.sim.num
        ts, xs, us = [0.0], [np.asarray(x0, dtype=float).copy()], []
        ms, segs, guards = [mode0], [0], []
        mode = mode0
        for k, (x, mode_next, events) in enumerate(steps):
            u_k = num.saturate(np.array([mode]), u[k][None])[0]
            for tau, g, before, after in events:
                guards.append(g)
                for state, mode_e in ((before, ms[-1]), (after, num.target[g])):
                    us.append(u_k)
                    ts.append(k * self.dt + tau)
                    xs.append(state)
                    ms.append(int(mode_e))
                    segs.append(len(guards) - (state is before))
            us.append(u_k)
            ts.append((k + 1) * self.dt)
            xs.append(x)
            ms.append(mode_next)
            segs.append(len(guards))
            mode = mode_next
        us.append(us[-1])
        return Trajectory(np.array(ts), np.array(xs), np.array(us), np.array(ms),
                          np.array(segs), tuple(guards))

    def _steps_numpy(self, x0: np.ndarray, mode0: int, u: np.ndarray) -> list[tuple]:
        """Steps one sample with the NumPy simulator (the reference for the C rollouts).

        Stops after the step that ends in Zeno chattering, a non-finite state or the final
        mode.

        Args:
            x0: initial state (n,).
            mode0: initial mode index.
            u: inputs (n_steps, m), one held over each step of ``self.dt`` seconds.

        Returns:
            Per step taken: (x after (n,), mode after, events as (tau [s] into the step,
            guard, state before (n,), state after (n,)) in time order).
        """
        x, mode = x0[None, :].astype(float), np.array([mode0])
        w = np.zeros((1, self.system.n_w))
        steps = []
        for k in range(self.n_steps):
            res = self.sim.step(x, mode, u[k][None], w, self.dt, raise_zeno=False)
            x, mode = res.x, res.mode
            steps.append((x[0].copy(), int(mode[0]),
                          [(e.tau, e.guard, e.x_before, e.x_after) for e in res.events]))
            if res.zeno.any() or not np.all(np.isfinite(x)) or mode[0] == self.final_mode:
                break
        return steps


def schedule_from(traj: Trajectory, t0: float = 0.0) -> ModeSchedule:
    """The domain/guard sequence and per-domain durations of a recorded trajectory.

    The schedule is stamped as planned at simulated time t0 [s].
    """
    n_seg = len(traj.guards) + 1
    starts = [float(traj.t[np.argmax(traj.seg == j)]) for j in range(n_seg)]
    modes = tuple(int(traj.mode[np.argmax(traj.seg == j)]) for j in range(n_seg))
    durations = tuple(starts[j + 1] - starts[j] for j in range(n_seg - 1))
    return ModeSchedule(modes, tuple(int(g) for g in traj.guards), durations, float(t0))


PLANNER = PlannerSpec(
    kind="cem", settings=CEMSettings,
    make=lambda system, settings, seed: CrossEntropyPlanner(system, settings, run_seed=seed))
