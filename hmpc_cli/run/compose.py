"""The closed loop's parts, composed from a scenario: :func:`build`.

:func:`build` is the only code that reads a :class:`~hmpc_cli.run.scenario.Scenario`: the
registry gives the system, its task and the planner and MPC plug-ins; each part gets its
own settings. What it returns (:class:`PreparedRun`) is everything a run needs but its
log: the runner opens the recorder and hands the loop a topic writer over it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from hmpc_cli.core.messages import BuildInfo, ConstraintMargins
from hmpc_cli.core.stack import FixedModeMPC, Planner, Task
from hmpc_cli.log.books import RunBooks, RunResult
from hmpc_cli.log.runlog import RunIdentity
from hmpc_cli.run.realtime import Latency
from hmpc_cli.run.scenario import did_you_mean
from hmpc_cli.run.setup_checks import (built_problems, check_task, margins_of, plant_problems,
                                       region_warnings)

__all__ = ["PreparedRun", "StackTiming", "build"]


@dataclass(frozen=True)
class StackTiming:
    """When the stack works, in simulator steps.

    Attributes:
        per_solve: simulator steps per MPC period.
        per_replan: steps per replanning period (policy ``periodic``), else None.
        on_contact: guards whose events trigger a replan (policy ``on_contact``).
        resolve_on_impact: re-solve right after a guard event.
        latency: how compute time is charged before a plan reaches the plant.
    """

    per_solve: int
    per_replan: int | None
    on_contact: frozenset[int]
    resolve_on_impact: bool
    latency: Latency = field(default_factory=Latency)


@dataclass(frozen=True)
class PreparedRun:
    """One run's parts, built and checked, and its books; no file is open.

    Attributes:
        plant: simulator, disturbance and low level (:class:`~hmpc_cli.run.plant.Plant`).
        planner: the hybrid MPC; mpc: the fixed-mode MPC.
        timing: the stack's rates and triggers.
        task: success and failure of the run.
        duration: simulated time [s]; divergence_bound: |x| beyond this ends the run.
        identity: what the log says of the run (/run/info).
        books: the run's counts (its result, also when the run is stopped).
    """

    plant: object
    planner: Planner
    mpc: FixedModeMPC
    timing: StackTiming
    task: Task
    duration: float
    divergence_bound: float
    identity: RunIdentity
    books: RunBooks

    @property
    def result(self) -> RunResult:
        """The run's result so far (final after the run)."""
        return self.books.result


# ------------------------------------------------------------------ composition
_PROBLEMS: dict[str, object] = {}


def build(scenario) -> PreparedRun:
    """Composes the parts of a validated scenario's run (the only reader of a Scenario).

    The MPC's NLPs are built once per process per (system, MPC settings, margins) and
    shared. The planner is built before them: what it compiles in the background (the
    CEM's C rollouts) overlaps their build, and its first plan waits for what is left
    (in the run's loop, outside the plan's own time). A planner that fails to build is
    reported before the MPC is built.

    Raises:
        hmpc_cli.core.registry.PluginError: a plug-in fails to build (message names it).
        ValueError: settings that do not fit the built system (e.g. unknown guards, a
            margins file that does not fit: ``mpc.margins: ...``).
    """
    from hmpc_cli.core.registry import build_system, plugin_call, registry

    sc, reg = scenario, registry()
    spec = reg.system(sc.system.name)
    model = build_system(sc.system)
    world = sc.plant_params()
    system = build_system(world) if sc.plant else model
    s = sc.sim
    plant = _plant(sc, model, system)
    margins = margins_of(sc, model)
    problems = built_problems(sc, model, margins)
    if sc.plant:
        problems += plant_problems(model, system)
    if problems:  # before the NLPs are built
        raise ValueError("\n".join(problems))
    # the planner first: what it compiles in the background (the CEM's C rollouts)
    # overlaps the MPC's NLP build
    planner = plugin_call(f"planner: {sc.planner.kind!r} failed to build for system "
                          f"{spec.name!r}", reg.planner(sc.planner.kind).make, model,
                          sc.planner, sc.seed)
    mpc, problem = _mpc(sc, model, margins)
    task = check_task(plugin_call(f"system: the task of {spec.name!r} failed to build",
                                  spec.task, world, system), spec.name, system)
    identity = RunIdentity(
        sc.name, sc.seed, sc.model_dump(mode="json"), s.rate_hz // s.log_rate_hz,
        _margins_record(sc, model, margins),
        (sc.planner.kind, sc.mpc.kind),
        {"planner": reg.planner(sc.planner.kind).detail, "mpc": reg.mpc(sc.mpc.kind).detail},
        _build_info(problem), s.log_plan_stride)
    timing = _timing(sc, model)
    return PreparedRun(plant, planner, mpc, timing, task, s.duration, s.divergence_bound,
                       identity, _books(sc, model, timing, margins))


def _plant(sc, model, system):
    """The simulated plant: ``system`` under the disturbance, tracked by the low level."""
    from hmpc_cli.lowlevel import LowLevelController
    from hmpc_cli.run.plant import Plant
    from hmpc_cli.sim.disturbance import make_disturbance
    from hmpc_cli.sim.simulator import HybridSimulator

    s, d = sc.sim, sc.disturbance
    dist = make_disturbance(d.kind, n_w=model.n_w, duration=s.duration,
                            magnitude=d.magnitude, hold=d.hold, seed=sc.seed, trial=d.trial)
    return Plant(model, system, HybridSimulator(system, s.max_events_per_step,
                                                s.event_time_tol),
                 dist, LowLevelController(model, sc.lowlevel), s.rate_hz,
                 s.input_at_events == "recompute", s.max_events_per_step)


def _books(sc, model, timing: StackTiming, margins: ConstraintMargins | None = None
           ) -> RunBooks:
    """The run's books: every guard of the model, the charged compute time if any.

    Set-up warnings go into its summary: measured latency, and (fixed-mode MPC) guards
    whose region x0 lies outside (:func:`~hmpc_cli.run.setup_checks.region_warnings`).
    """
    books = RunBooks(sc.name, sc.seed, [g.name for g in model.guards])
    if timing.latency.kind != "paused":
        books.charge_time(timing.latency.kind, timing.per_solve / sc.sim.rate_hz)
    if timing.latency.kind == "measured":
        books.warn("sim.latency = 'measured': plans reach the plant after their measured "
                   "compute time, so this run is not reproducible")
    for line in region_warnings(model, margins) if sc.mpc.kind == "fixed_mode" else []:
        books.warn(line)
    return books


def _margins_record(sc, model, margins: ConstraintMargins | None) -> dict | None:
    """/run/info's margins: :meth:`ConstraintMargins.to_dict`, a margins file's digest too."""
    if margins is None:
        return None
    record = margins.to_dict(model)
    if sc.mpc.margins_file() is not None:
        from hmpc_cli.core.paths import file_digest

        digest = file_digest(Path(sc.mpc.margins_file()))
        record |= {"sha256": digest} if digest is not None else {}
    return record


def _build_info(problem) -> BuildInfo | None:
    """How an MPC problem's NLPs were built (its ``build_info``), if it says."""
    info = getattr(problem, "build_info", None)
    return info if isinstance(info, BuildInfo) else None


def _mpc(sc, model, margins: ConstraintMargins | None) -> tuple[FixedModeMPC, object]:
    """The MPC controller and its problem (built once per process per system and settings).

    The problem is shared by the runs of one (system, MPC settings, margins): the
    plug-in's ``problem(system, settings, margins)`` gets a margins file's or the tube's
    values, or None for the kind's hand margins.
    """
    from hmpc_cli.core.registry import plugin_call, registry

    reg = registry()
    mpc_spec = reg.mpc(sc.mpc.kind)
    from_file = margins is not None and margins.source != "hand"
    key = json.dumps([sc.system.model_dump(mode="json"), sc.mpc.model_dump(mode="json"),
                      margins.to_dict(model) if from_file else None], sort_keys=True)
    what = f"mpc: {sc.mpc.kind!r} failed to build for system {sc.system.name!r}"
    if key not in _PROBLEMS:
        _PROBLEMS[key] = plugin_call(what, mpc_spec.problem, model, sc.mpc,
                                     margins if from_file else None)
    return plugin_call(what, mpc_spec.make, model, sc.mpc, _PROBLEMS[key]), _PROBLEMS[key]


def _timing(sc, model) -> StackTiming:
    """The stack's timing from the scenario's rates and replanning policy."""
    rp, final = sc.replanning, model.final_mode
    if rp.policy != "on_contact":  # guards no replan waits for (a given list: a warning)
        contact = frozenset()
    elif rp.contact_guards is None:  # every guard but those entering the final domain
        contact = frozenset(i for i, g in enumerate(model.guards)
                            if g.target != final or g.source == final)
    else:
        names = [g.name for g in model.guards]
        unknown = [n for n in dict.fromkeys(rp.contact_guards) if n not in names]
        if unknown:
            which = ", ".join(f"{n!r}{did_you_mean(n, names)}" for n in unknown)
            raise ValueError(f"replanning.contact_guards: unknown guard{'s' * (len(unknown) > 1)} "
                             f"{which}; the system's guards: {', '.join(map(repr, names))}")
        contact = frozenset(model.guard_index(n) for n in rp.contact_guards)
    per_replan = int(round(rp.period * sc.sim.rate_hz)) if rp.policy == "periodic" else None
    s = sc.sim
    latency = Latency.of(s.latency, s.latency_first, s.latency_model, s.solve_budget,
                         s.delay_compensation, s.preempt_at_contact)
    return StackTiming(s.rate_hz // sc.mpc.rate_hz, per_replan, contact,
                       sc.mpc.resolves_on_impact(), latency)
