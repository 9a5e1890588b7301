"""Low-level controller: feed-forward of the MPC inputs plus PD on the tracking error.

u(t) = u_ff(t) + K (x_ref(t) - x), K = system.tracking_gain(kp, kd). The feed-forward is the
first-order hold (or zero-order hold) of the plan's inputs, the reference the linear
interpolation of its states, both over the plan's current domain only: past its guard
node the reference holds the guard node and its virtual input, until the loop re-solves
after the impact. Evaluated every simulator step.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from hmpc_cli.hybrid import HybridSystem
from hmpc_cli.messages import Plan


class LowLevelSettings(BaseModel):
    """Low-level tracking controller settings."""

    model_config = ConfigDict(extra="forbid")
    kp: float = Field(0.0, ge=0.0, description="proportional gain")
    kd: float = Field(0.0, ge=0.0, description="derivative gain")
    feedforward: Literal["foh", "zoh"] = "foh"


class LowLevelController:
    """Tracks a :class:`Plan` with feed-forward + PD."""

    def __init__(self, system: HybridSystem, settings: LowLevelSettings) -> None:
        self.settings = settings
        self.K = np.asarray(system.tracking_gain(settings.kp, settings.kd), dtype=float)

    def reference(self, t: float, plan: Plan) -> tuple[np.ndarray, np.ndarray]:
        """(x_ref (n,), u_ff (m,)) of ``plan`` at simulated time t [s]."""
        tr = plan.traj
        first = np.nonzero(tr.seg == tr.seg[0])[0]
        ts, xs, us = tr.t[first], tr.x[first], tr.u[first]
        tau = t - plan.t0
        if tau >= ts[-1] or len(ts) == 1:
            return xs[-1], us[-1]
        k = max(int(np.searchsorted(ts, tau, side="right")) - 1, 0)
        a = (tau - ts[k]) / (ts[k + 1] - ts[k])
        x_ref = (1.0 - a) * xs[k] + a * xs[k + 1]
        if self.settings.feedforward == "zoh":
            return x_ref, us[k]
        return x_ref, (1.0 - a) * us[k] + a * us[k + 1]

    def command(self, t: float, x: np.ndarray, plan: Plan | None):
        """Input (m,) and reference state (n,) at time t; zero input without a plan."""
        if plan is None:
            return np.zeros(self.K.shape[0]), np.full(self.K.shape[1], np.nan)
        x_ref, u_ff = self.reference(t, plan)
        return u_ff + self.K @ (x_ref - x), x_ref
