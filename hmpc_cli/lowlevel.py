"""Low-level controller: feed-forward of the MPC inputs plus PD on the tracking error.

u(t) = u_ff(t) + K (x_ref(t) - x), K = system.tracking_gain(kp, kd). The feed-forward
interpolates the plan's inputs as the plan was computed with (``feedforward = "plan"``:
the plan's ``input_hold``, first-order or zero-order hold) or as forced by the setting;
the reference is the linear interpolation of the plan's states, both over the plan's
current domain only: past its guard node the reference holds the guard node and its
virtual input, until the loop re-solves after the impact. Evaluated every simulator step
and held over it: the feed-forward is its mean over the step (same impulse as the plan).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import Plan
from hmpc_cli.core.settings_types import FiniteFloat


class LowLevelSettings(BaseModel):
    """Low-level tracking controller settings."""

    model_config = ConfigDict(extra="forbid")
    kp: FiniteFloat = Field(0.0, ge=0.0, description="proportional gain")
    kd: FiniteFloat = Field(0.0, ge=0.0, description="derivative gain")
    feedforward: Literal["plan", "foh", "zoh"] = Field(
        "plan", description="input interpolation: as the plan was computed ('plan'), or "
                            "forced first-order ('foh') or zero-order ('zoh') hold")


class LowLevelController:
    """Tracks a :class:`Plan` with feed-forward + PD."""

    def __init__(self, system: HybridSystem, settings: LowLevelSettings) -> None:
        self.settings = settings
        self.K = np.asarray(system.tracking_gain(settings.kp, settings.kd), dtype=float)
        self._memo: tuple | None = None  # (plan, its domain's arrays): see _domain

    def reference(self, t: float, plan: Plan, span: float = 0.0
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Reference state and feed-forward input of ``plan`` at simulated time ``t``.

        Both are taken from the plan's current domain only (see the module docstring).

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
        ts, xs, us, zoh, cum = self._domain(plan)
        tau = t - plan.t0
        x_ref = _interp(ts, xs, tau, zoh=False)
        if span <= 0.0:
            return x_ref, _interp(ts, us, tau, zoh)
        return x_ref, (_integral(ts, us, tau + span, zoh, cum)
                       - _integral(ts, us, tau, zoh, cum)) / span

    def _domain(self, plan: Plan) -> tuple:
        """(ts (K,), xs (K, n), us (K, m), zoh, cum (K, m)) of the plan's current domain.

        ``cum[k]``: the integral of the interpolated input from ts[0] to ts[k]. Made once
        per plan (the simulator asks for the reference at every step, the plan changes at
        the MPC's rate).
        """
        if self._memo is not None and self._memo[0] is plan:
            return self._memo[1]
        tr = plan.traj
        first = np.nonzero(tr.seg == tr.seg[0])[0]
        ts, xs, us = tr.t[first], tr.x[first], tr.u[first]
        hold = self.settings.feedforward
        zoh = (tr.input_hold if hold == "plan" else hold) == "zoh"
        pieces = np.diff(ts)[:, None] * (us[:-1] if zoh else 0.5 * (us[:-1] + us[1:]))
        cum = np.concatenate([np.zeros((1, us.shape[1])), np.cumsum(pieces, axis=0)])
        self._memo = (plan, (ts, xs, us, zoh, cum))
        return self._memo[1]

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


def _interp(ts: np.ndarray, vs: np.ndarray, tau: float, zoh: bool) -> np.ndarray:
    """Value (d,) at tau of samples vs (K, d) taken at increasing times ts (K,).

    Linear interpolation, or held from the left if ``zoh``; the first and last samples are
    held outside [ts[0], ts[-1]].
    """
    if tau >= ts[-1] or len(ts) == 1:
        return vs[-1]
    if tau <= ts[0]:
        return vs[0]
    k = int(np.searchsorted(ts, tau, side="right")) - 1
    if zoh:
        return vs[k]
    a = (tau - ts[k]) / (ts[k + 1] - ts[k])
    return (1.0 - a) * vs[k] + a * vs[k + 1]


def _integral(ts: np.ndarray, vs: np.ndarray, tau: float, zoh: bool,
              cum: np.ndarray) -> np.ndarray:
    """Integral from ts[0] to tau of the interpolated samples (constant outside).

    ``cum`` (K, d): the integral up to each sample time (see ``LowLevelController._domain``).
    """
    if tau <= ts[0] or len(ts) == 1:
        return (tau - ts[0]) * vs[0]
    k = min(int(np.searchsorted(ts, tau, side="right")) - 1, len(ts) - 1)
    done = cum[k]
    if k == len(ts) - 1:
        return done + (tau - ts[-1]) * vs[-1]
    v_tau = _interp(ts, vs, tau, zoh)
    return done + (tau - ts[k]) * (vs[k] if zoh else 0.5 * (vs[k] + v_tau))
