"""The closed loop's plant side: the simulated system, its disturbance and the low level.

One :meth:`Plant.step` is one simulator step of ``1 / sim.rate_hz`` seconds: the input
(low-level command, saturated to the mode's box) and the disturbance are held, events are
located exactly and reset, and each event is handed to the caller. With
``sim.input_at_events = "recompute"`` the step stops at each reset, the caller reacts at
the event time and the low level computes a new input for the rest of the step.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.lowlevel import LowLevelController
from hmpc_cli.core.messages import GuardEvent, Plan
from hmpc_cli.sim.simulator import HybridSimulator, ZenoError, zeno_text


@dataclass
class Plant:
    """Simulator, disturbance and low-level controller.

    Attributes:
        model: the controllers' model (the low level's gains and input boxes).
        system: the simulated system (may differ from the model: ``[plant]`` keys).
        sim: the hybrid simulator of ``system``.
        disturbance: t [s] -> w (n_w,), held between its knots.
        lowlevel: feed-forward + PD tracking of the current plan.
        rate_hz: simulator step rate [Hz].
        recompute_at_events: stop at each reset and recompute the input after it.
        max_events: events allowed in one step (more is Zeno chattering).
    """

    model: HybridSystem
    system: HybridSystem
    sim: HybridSimulator
    disturbance: Callable[[float], np.ndarray]
    lowlevel: LowLevelController
    rate_hz: int
    recompute_at_events: bool
    max_events: int

    @property
    def h(self) -> float:
        """Simulator step [s]."""
        return 1.0 / self.rate_hz

    def command(self, t: float, x: np.ndarray, mode: int, plan: Plan | None, span: float
                ) -> tuple[np.ndarray, np.ndarray]:
        """The low level's command at time t [s].

        Returns:
            The input (m,) held over [t, t + span], saturated to the mode's box (the
            model's, then the simulated system's: the input the plant applies), and the
            reference state (n,) at t.
        """
        u, x_ref = self.lowlevel.command(t, x, plan, span)
        modes = np.array([mode])
        u = self.model.numeric.saturate(modes, u[None])
        if self.system is not self.model:  # [plant]: its own box acts on the input
            u = self.system.numeric.saturate(modes, u)
        return u[0], x_ref

    def step(self, t0: float, x: np.ndarray, mode: int, u: np.ndarray, w: np.ndarray,
             on_event: Callable[[GuardEvent], None], plan: Callable[[], Plan | None]
             ) -> tuple[np.ndarray, int, list[GuardEvent]]:
        """One simulator step from time t0 [s].

        ``on_event`` is called for each event in time order (before the input is
        recomputed), after the low level is told of it (:meth:`LowLevelController.contact`);
        ``plan()`` gives the plan to track.

        Raises:
            ZenoError: more than ``max_events`` events in the step.
        """
        h, left, events = self.h, self.h, []
        while True:
            step = self.sim.step(x[None], np.array([mode]), u[None], w[None], left,
                                 stop_at_event=self.recompute_at_events)
            x, mode = step.x[0], int(step.mode[0])
            if len(events) + len(step.events) > self.max_events:
                raise ZenoError(zeno_text(self.max_events, h))
            for ev in step.events:
                g = ev.guard
                gev = GuardEvent(t0 + (h - left) + ev.tau, g, int(self.sim.num.source[g]),
                                 int(self.sim.num.target[g]), ev.x_before, ev.x_after)
                self.lowlevel.contact(gev.t, g)
                on_event(gev)
                events.append(gev)
            left = float(step.remaining[0])
            if not self.recompute_at_events or left <= 0.0 or not step.events:
                return x, mode, events
            u, _ = self.command(t0 + h - left, x, mode, plan(), left)
