"""Low-level controller: feed-forward of the MPC inputs plus PD on the tracking error.

u(t) = u_ff(t) + K (x_ref(t) - x), K = system.tracking_gain(kp, kd). The feed-forward
interpolates the plan's inputs as the plan was computed with (``feedforward = "plan"``:
the plan's ``input_hold``, first-order or zero-order hold) or as forced by the setting;
the reference is the linear interpolation of the plan's states, both over one domain of
the plan. Evaluated every simulator step and held over it: the feed-forward is its mean
over the step (same impulse as the plan).

Which domain (``past_guard``): with ``"hold"`` (the default, the paper's runs) always the
plan's first: past its guard node the reference holds the guard node and its virtual
input until the loop re-solves after the impact. With ``"next_domain"`` the low level
follows the plant's contacts (:meth:`LowLevelController.contact`): once the plant has
crossed the plan's next k guards, in the plan's order, since the plan's start, the
reference is the plan's domain k, re-timed to begin at the k-th contact's time (when a
plan arrives its latency after an impact, it is tracked across it instead of held at its
pre-impact guard node); a contact the plan does not schedule next falls back to
``"hold"``. With ``"hold"`` the run's summary warns after how many contacts a plan was
tracked past its guard (:meth:`LowLevelController.warning`).
"""

from __future__ import annotations

from bisect import bisect_right
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import Plan
from hmpc_cli.core.settings_types import FiniteFloat


#: a contact within this of a time [s] counts as at that time (the input recomputed at an
#: event's time, or a plan solved at it: both times are the event's up to rounding)
TIME_TOL = 1e-9


class LowLevelSettings(BaseModel):
    """Low-level tracking controller settings."""

    model_config = ConfigDict(extra="forbid")
    kp: FiniteFloat = Field(0.0, ge=0.0, description="proportional gain")
    kd: FiniteFloat = Field(0.0, ge=0.0, description="derivative gain")
    feedforward: Literal["plan", "foh", "zoh"] = Field(
        "plan", description="input interpolation: as the plan was computed ('plan'), or "
                            "forced first-order ('foh') or zero-order ('zoh') hold")
    past_guard: Literal["hold", "next_domain"] = Field(
        "hold", description="after the plant crosses the plan's guard and before a new plan "
        "arrives: 'hold' the guard node and its input (the paper's runs, where the loop "
        "re-solves at the impact with time paused), or track the plan's 'next_domain' from "
        "the contact's time (real time: a plan arrives its latency after the impact)")


class LowLevelController:
    """Tracks a :class:`Plan` with feed-forward + PD."""

    def __init__(self, system: HybridSystem, settings: LowLevelSettings) -> None:
        self.settings = settings
        self.K = np.asarray(system.tracking_gain(settings.kp, settings.kd), dtype=float)
        self._memo: tuple | None = None  # (plan, k, its domain k's arrays): see _domain
        self._follow = settings.past_guard == "next_domain"
        #: the plant's guard events so far, in time order: their times [s] and guards
        self.contact_times: list[float] = []
        self.contact_guards: list[int] = []
        self._held: set[int] = set()  # contacts after which "hold" kept a pre-impact node

    def contact(self, t: float, guard: int) -> None:
        """The plant crossed ``guard`` at t [s] (events arrive in time order)."""
        self.contact_times.append(t)
        self.contact_guards.append(guard)

    def _where(self, t: float, plan: Plan) -> tuple[int, float]:
        """(k, tau): the plan's domain k the reference is on at t [s] and the plan time there.

        k counts the plan's guards the plant crossed after the plan's start and up to t,
        in the plan's order; 0 (the first domain, tau = t - t0) with ``past_guard =
        "hold"``, before any such contact, or after a contact the plan does not schedule.
        """
        tau = t - plan.t0
        if not self.contact_times:
            return 0, tau
        i = bisect_right(self.contact_times, plan.t0 + TIME_TOL)
        j = bisect_right(self.contact_times, t + TIME_TOL)
        k, guards = j - i, plan.traj.guards
        if k and not self._follow:
            self._held.add(j - 1)
        if not self._follow or k == 0 or k > len(guards) \
                or tuple(self.contact_guards[i:j]) != tuple(guards[:k]):
            return 0, tau
        nodes = np.flatnonzero(plan.traj.seg == plan.traj.seg[0] + k)
        if not len(nodes):
            return 0, tau
        return k, float(plan.traj.t[nodes[0]] + (t - self.contact_times[j - 1]))

    def warning(self) -> str:
        """The summary's warning when ``hold`` tracked a plan past a contact ('' if never)."""
        if not self._held:
            return ""
        return (f"after {len(self._held)} of {len(self.contact_times)} contacts the low level "
                "held the plan's pre-impact guard node until a new plan arrived "
                "(lowlevel.past_guard = \"hold\"); \"next_domain\" follows the plan "
                "across the impact")

    def reference(self, t: float, plan: Plan, span: float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Reference state and feed-forward input of ``plan`` at simulated time ``t``.

        Both are taken from one domain of the plan (see the module docstring).

        Args:
            t: simulated time [s].
            plan: the plan to track.
            span: length [s] of the simulator step the input is held over.

        Returns:
            ``(x_ref, u_ff)``: x_ref (n,) the plan's state at t (linear interpolation);
            u_ff (m,) the mean of the feed-forward over [t, t + span] (its value at t if
            span <= 0), the held input that gives the plant over the step the same impulse
            as the plan's interpolated input.
        """
        k, tau = self._where(t, plan)
        ts, xs, us, zoh, cum = self._domain(plan, k)
        x_ref = _interp(ts, xs, tau, zoh=False)
        if span <= 0.0:
            return x_ref, _interp(ts, us, tau, zoh)
        return x_ref, (_integral(ts, us, tau + span, zoh, cum)
                       - _integral(ts, us, tau, zoh, cum)) / span

    def _domain(self, plan: Plan, k: int = 0) -> tuple:
        """(ts (K floats), xs (K, n), us (K, m), zoh, cum (K, m)) of the plan's domain k.

        In float64 whatever the plan's dtype (a plug-in's float32 plan is tracked alike).

        ``cum[i]``: the integral of the interpolated input from ts[0] to ts[i]. Made once
        per plan and domain (the simulator asks for the reference at every step, the plan
        changes at the MPC's rate).
        """
        if self._memo is not None and self._memo[0] is plan and self._memo[1] == k:
            return self._memo[2]
        tr = plan.traj
        nodes = np.nonzero(tr.seg == tr.seg[0] + k)[0]
        ts, xs, us = (np.asarray(a[nodes], dtype=float) for a in (tr.t, tr.x, tr.u))
        hold = self.settings.feedforward
        zoh = (tr.input_hold if hold == "plan" else hold) == "zoh"
        pieces = np.diff(ts)[:, None] * (us[:-1] if zoh else 0.5 * (us[:-1] + us[1:]))
        cum = np.concatenate([np.zeros((1, us.shape[1])), np.cumsum(pieces, axis=0)])
        self._memo = (plan, k, (ts.tolist(), xs, us, zoh, cum))
        return self._memo[2]

    def command(self, t: float, x: np.ndarray, plan: Plan | None, span: float = 0.0):
        """Input to hold over [t, t + span] and the reference state at t.

        Args:
            t: simulated time [s].
            x: current state (n,).
            plan: the plan to track, or None (no plan yet).
            span: length [s] of the simulator step the input is held over.

        Returns:
            ``(u, x_ref)``: u (m,) = u_ff + K (x_ref - x) and x_ref (n,) from
            :meth:`reference`; without a plan, u = 0 and x_ref is all NaN.
        """
        if plan is None:
            return np.zeros(self.K.shape[0]), np.full(self.K.shape[1], np.nan)
        x_ref, u_ff = self.reference(t, plan, span)
        return u_ff + self.K @ (x_ref - x), x_ref


def _interp(tl: list[float], vs: np.ndarray, tau: float, zoh: bool) -> np.ndarray:
    """Value (d,) at tau of samples vs (K, d) taken at increasing times tl (K floats).

    Linear interpolation, or held from the left if ``zoh``; the first and last samples are
    held outside [tl[0], tl[-1]].
    """
    if tau >= tl[-1] or len(tl) == 1:
        return vs[-1]
    if tau <= tl[0]:
        return vs[0]
    return _between(tl, vs, tau, zoh, bisect_right(tl, tau) - 1)


def _between(tl: list[float], vs: np.ndarray, tau: float, zoh: bool, k: int) -> np.ndarray:
    """Value (d,) at tau in [tl[k], tl[k + 1]) of the samples vs (K, d) at the times tl."""
    if zoh:
        return vs[k]
    a = (tau - tl[k]) / (tl[k + 1] - tl[k])
    return (1.0 - a) * vs[k] + a * vs[k + 1]


def _integral(tl: list[float], vs: np.ndarray, tau: float, zoh: bool,
              cum: np.ndarray) -> np.ndarray:
    """Integral from tl[0] to tau of the interpolated samples (constant outside).

    ``cum`` (K, d): the integral up to each sample time (see ``LowLevelController._domain``).
    """
    if tau <= tl[0] or len(tl) == 1:
        return (tau - tl[0]) * vs[0]
    k = bisect_right(tl, tau) - 1
    done = cum[k]
    if k == len(tl) - 1:
        return done + (tau - tl[-1]) * vs[-1]
    v_tau = _between(tl, vs, tau, zoh, k)
    return done + (tau - tl[k]) * (vs[k] if zoh else 0.5 * (vs[k] + v_tau))
