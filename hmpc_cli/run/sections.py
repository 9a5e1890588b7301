"""The scenario's own sections: simulator, disturbance and replanning settings.

The plug-in sections (``system``, ``planner``, ``mpc``) come from the registry and the
low level's from :mod:`hmpc_cli.lowlevel`; :mod:`hmpc_cli.run.scenario` assembles them all.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from hmpc_cli.core.settings_types import BoundedInt, FiniteFloat, LargeFloat, StrictBool
from hmpc_cli.core.text import did_you_mean

__all__ = ["DisturbanceSettings", "LatencyModelSettings", "ReplanSettings", "SimSettings"]


class LatencyModelSettings(BaseModel):
    """The deterministic latency model: a solve's charged compute time from its iterations.

    Defaults fitted by ``benchmarks/calibrate_latency.py`` (its report:
    ``results/bench/latency_model.md``); re-fit them for your machine.
    """

    model_config = ConfigDict(extra="forbid")
    overhead: FiniteFloat = Field(0.0015, ge=0.0, description="per MPC solve [s]")
    per_iteration: FiniteFloat = Field(0.0041, ge=0.0, description="per NLP iteration [s]")
    per_switching_iteration: FiniteFloat | None = Field(
        None, ge=0.0, description="per NLP iteration of a solve with a switch left [s] "
        "(its NLP is larger; None: per_iteration)")
    planner: FiniteFloat = Field(0.01, ge=0.0, description="per planner call [s]; the "
                                 "fixed-mode MPC solves a planner makes itself (foothold "
                                 "candidates) are charged beside it as solves")
    nodes: BoundedInt | None = Field(
        None, ge=2, description="the plan nodes the constants were fitted at: a solve whose "
        "plan has n nodes is charged n / nodes times its overhead and iterations (a larger "
        "NLP costs more per iteration, e.g. a finer node grid); None: every solve as fitted, "
        "whatever its size")


class SimSettings(BaseModel):
    """Simulator settings."""

    model_config = ConfigDict(extra="forbid")
    rate_hz: BoundedInt = Field(600, gt=0, description="fixed RK4 step rate [Hz]")
    duration: FiniteFloat = Field(3.0, gt=0.0, description="simulated time [s]")
    max_events_per_step: BoundedInt = Field(10, ge=1, le=1000,
                                            description="more is Zeno chattering")
    event_time_tol: FiniteFloat = Field(1e-10, gt=0.0, description="event time bracket [s], "
                                        "at most 1e-3 of a simulator step")
    divergence_bound: LargeFloat = Field(1e6, gt=0.0, description="|x| beyond this is "
                                         "divergence")
    log_rate_hz: BoundedInt = Field(100, gt=0, description="state logging rate [Hz]")
    log_plan_stride: BoundedInt = Field(
        1, ge=1, description="log every k-th node of each MPC plan (/mpc/solve and the 3D "
        "scene; the nodes either side of a reset and the last node always): 1 logs every "
        "node; 3 makes a ball log about half as large")
    input_at_events: Literal["hold", "recompute"] = Field(
        "hold", description="after a reset inside a step: hold the step's input (the "
        "paper's ball) or let the controllers react at the event time and compute a new "
        "input for the rest of the step (needed when a reset relabels the inputs: biped)")
    latency: Literal["paused", "measured", "model"] | FiniteFloat = Field(
        "paused", description="solve time charged to the simulation: 'paused' (simulated "
        "time stops while the controllers compute; the paper's runs), 'measured' (a plan "
        "reaches the plant its measured compute wall time [s] after the state it was "
        "computed from: not reproducible), 'model' (a deterministic charge from the "
        "solve's iterations, sim.latency_model) or a fixed delay [s], in [0, 1e6); until then the "
        "previous plan is tracked, and a plan takes effect at the first simulator step at "
        "or after t + latency")
    latency_model: LatencyModelSettings = Field(
        default_factory=lambda: LatencyModelSettings(),
        description="sim.latency = 'model': the charged compute time of a solve")
    solve_budget: FiniteFloat | None = Field(
        None, gt=0.0, description="with a latency: a solve charged more than this [s] is "
        "dropped at t + budget and the previous plan tracked on; the iterate its solver had "
        "reached when the budget ran out warm-starts the next solve; a replan whose planner's "
        "own MPC solves had not all finished then takes the planner's choice among those "
        "that had (the planner's optional within; none, or a planner without it: keeps "
        "the schedule before it and plans again); a planner call "
        "that found none stops there too (None: no budget)")
    delay_compensation: StrictBool = Field(
        False, description="with a latency: solve from the state the model predicts (w = 0, "
        "through its resets) at the step the plan is expected to reach the plant (after the "
        "last charged solve's own compute time, at most the budget), for the MPC period's "
        "and impacts' solves (a replan's solves start from the measured state)")
    preempt_at_contact: StrictBool = Field(
        False, description="with a latency: a contact that makes the stack work (a replan, "
        "or the impact's re-solve) stops the solve in flight, solved from the state before "
        "the contact: its plan is dropped and the stack works at the contact (default: the "
        "contact waits until the solver is free)")
    latency_first: Literal["charged", "paused"] = Field(
        "charged", description="with a latency: 'charged' (default) lets the first plan, too, "
        "reach the plant only after the latency (no plan and zero input until then); "
        "'paused' computes the first plan (planner and MPC at t = 0) with time paused, as "
        "a controller that planned before the run started, and charges every later solve "
        "(also a first plan found only after t = 0)")

    @field_validator("event_time_tol")
    @classmethod
    def _event_time_tol(cls, v: float, info: ValidationInfo) -> float:
        rate = info.data.get("rate_hz")
        if rate is not None and v > 1e-3 / rate:
            raise ValueError(f"{v:g} s brackets an event time to more than 1e-3 of a "
                             f"simulator step (1/sim.rate_hz = {1.0 / rate:.4g} s): events "
                             f"would be placed anywhere in the step; use at most "
                             f"{1e-3 / rate:.3g} s (default 1e-10)")
        return v

    @field_validator("latency", mode="before")
    @classmethod
    def _latency(cls, v: Any) -> Any:
        ok = v in ("paused", "measured", "model") if isinstance(v, str) else (
            isinstance(v, int | float) and not isinstance(v, bool) and 0.0 <= v < 1e6)
        if not ok:
            raise ValueError(f"expected 'paused', 'measured', 'model' or a delay in [0, 1e6) "
                             f"s, got {v!r}" + (did_you_mean(v, ["paused", "measured", "model"])
                                                if isinstance(v, str) else ""))
        return float(v) if not isinstance(v, str) else v


class DisturbanceSettings(BaseModel):
    """Disturbance w(t) (added to the flow, eq. (1))."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["none", "box", "paper_fig3"] = "none"
    magnitude: FiniteFloat = Field(10.0, ge=0.0, description="uniform box half-width per channel")
    hold: FiniteFloat = Field(0.05, gt=0.0, description="hold period [s] (box; paper_fig3 "
                              "holds 0.05 s): a whole number of simulator steps")
    trial: BoundedInt = Field(1, ge=1, le=10, description="paper_fig3 trial 1..10")


class ReplanSettings(BaseModel):
    """When the hybrid MPC (planner) runs again."""

    model_config = ConfigDict(extra="forbid")
    policy: Literal["once", "on_contact", "periodic"] = "once"
    period: FiniteFloat = Field(0.5, gt=0.0, description="replanning period [s] (periodic)")
    contact_guards: list[str] | None = Field(
        None, description="guards that trigger on_contact (default: all but those "
                          "entering the final domain from another domain)")
