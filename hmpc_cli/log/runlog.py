"""The run's log topics: what a closed-loop run writes, in one place.

:class:`TopicWriter` writes over an open MCAP writer (:class:`hmpc_cli.log.recorder.Recorder`
or anything with ``add_topic``/``add_metadata``/``write``/``write_many``), which the
caller opens, passes in and closes: the typed topics of :mod:`hmpc_cli.log.topics` (their
JSON schemas generated from the types, with the system's names and the plug-ins' detail
types) and the 3D scene. :class:`NullWriter` is the writer of a run without a log. The
counts (``summary.json``) are the books' (:mod:`hmpc_cli.log.books`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import platform
import shlex
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from hmpc_cli import __version__
from hmpc_cli.core.blas import kernels
from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.machine import cpu_model
from hmpc_cli.core.source import source_commit
from hmpc_cli.log.geometry import body_logger, body_names, geometry_record
from hmpc_cli.log.topics import (
    LOG_VERSION,
    GuardEventRec,
    MarginsRec,
    MpcSolve,
    PlanArrays,
    PlanNode,
    PlannerCall,
    RealTime,
    RolloutArrays,
    RolloutNode,
    RunInfo,
    ScheduleRec,
    StateSample,
    StatusCount,
    Summary,
    Versions,
    WRec,
    named,
    topic_schemas)
from hmpc_cli.log.schema import convert, flat_keys
from hmpc_cli.log.geometry import record_maker
from hmpc_cli.core.messages import (
    BuildInfo, GuardEvent, ModeSchedule, Plan, PlannerResult, Trajectory)
from hmpc_cli.log.books import RunResult



def versions() -> dict[str, str]:
    """Versions of everything that can change a trajectory."""
    import casadi
    import mcap
    import pydantic

    return {"hmpc": __version__, "python": sys.version.split()[0], "numpy": np.__version__,
            "casadi": casadi.__version__, "pydantic": pydantic.__version__,
            "mcap": getattr(mcap, "__version__", "?"), "platform": platform.platform(),
            "cpu": cpu_model(), "source": source_commit(), "blas": kernels()}


@dataclass
class Provenance:
    """What started a run: the command line and the overrides applied to its scenario.

    Attributes:
        command: the command line (default: this process's ``sys.argv``).
        overrides: the ``key=value`` overrides (``--set``, a sweep cell's, ``seed=``).
        sweep: the sweep file of a sweep's run (as given on the command line), else "".
    """

    command: str = field(default_factory=lambda: shlex.join(sys.argv))
    overrides: tuple[str, ...] = ()
    sweep: str = ""


#: :class:`StateSample`'s fields: its JSON object's keys, in order (a dict of them encodes
#: as the dataclass does, without a frozen dataclass per sample)
_STATE_KEYS = tuple(f.name for f in dataclasses.fields(StateSample))
#: messages (/sim/state samples, MPC solves, disturbances) held before they are written
#: (see :meth:`TopicWriter.flush_held`)
HELD = 64


@dataclass(frozen=True)
class RunIdentity:
    """What /run/info says of a run besides the model's names, and how densely it logs.

    Attributes:
        scenario_name: the scenario's name; seed: the run's seed.
        scenario: the validated scenario (JSON-ready).
        per_state: simulator steps per /sim/state sample.
        margins: the MPC's margins (source, radius, per guard, per mode), if it has any.
        kinds: (planner kind, MPC kind).
        details: ``planner``/``mpc`` -> the plug-ins' log detail dataclasses.
        build: how the MPC's NLPs were built.
        plan_stride: every k-th node of a plan is logged (:func:`thinned`).
    """

    scenario_name: str = "scenario"
    seed: int = 0
    scenario: Mapping = field(default_factory=dict)
    per_state: int = 1
    margins: Mapping | None = None
    kinds: tuple[str, str] = ("", "")
    details: Mapping[str, type | None] = field(default_factory=dict)
    build: BuildInfo | None = None
    plan_stride: int = 1


class NullWriter:
    """The topic writer of a run without a log: every call writes nothing."""

    def open(self, model: HybridSystem, plant: HybridSystem | None = None) -> None:
        """Nothing to register."""

    def step(self, *args, **kwargs) -> None:
        """Nothing to log."""

    state = event = planner = mpc_solve = summary = step

    def flush_held(self) -> None:
        """Nothing held."""


class TopicWriter:
    """The topics of one run over an open recorder.

    Args:
        recorder: an open MCAP writer (closed by the caller).
        identity: the run's identity (/run/info) and logging densities.
        provenance: the command line and overrides that started the run.
        scene: the run's 3D scene writer (:func:`hmpc_cli.log.scene.open_scene`), or None.
    """

    def __init__(self, recorder, identity: RunIdentity, provenance: Provenance | None = None,
                 scene=None) -> None:
        self.rec = recorder
        self.identity = identity
        self.provenance = provenance if provenance is not None else Provenance()
        self.scene = scene
        self._last_w: bytes | None = None  # the last logged disturbance's bytes
        self._model: HybridSystem | None = None
        self._body = None  # x -> the plant's body points (None: no body logged)
        #: messages not yet written, in order: (None, /sim/state sample) or (writer, args)
        self._held: list[tuple] = []
        self._state_t: float | None = None  # the time of the last /sim/state sample

    def _write(self, topic: str, t: float, payload) -> None:
        if self._held:
            self.flush_held()
        self.rec.write(topic, t, payload)

    def _hold(self, writer, args: tuple) -> None:
        """Holds one message: ``writer(*args)`` writes it (None: a /sim/state sample)."""
        self._held.append((writer, args))
        if len(self._held) >= HELD:
            self.flush_held()

    def open(self, model: HybridSystem, plant: HybridSystem | None = None) -> None:
        """Registers the topics and writes /run/info (seed, versions, scenario, names).

        Args:
            model: the controllers' model (names, modes, guards).
            plant: the simulated system (default: the model): its geometry and body
                points are logged (:mod:`hmpc_cli.log.geometry`).
        """
        self._model = model
        plant = model if plant is None else plant
        geometry = geometry_record(plant)
        self._body = body_logger(plant)
        names = {"state": model.state_names, "input": model.input_names,
                 "disturbance": model.disturbance_names,
                 "guard": [g.name for g in model.guards],
                 "body": body_names(geometry.point_names)}
        for topic, (schema_name, schema) in topic_schemas(names,
                                                          dict(self.identity.details)).items():
            self.rec.add_topic(topic, schema_name, schema)
        vers = versions()
        idn = self.identity
        self._write("/run/info", 0.0, RunInfo(
            LOG_VERSION, idn.scenario_name, int(idn.seed), model.name, idn.kinds[1],
            idn.kinds[0], self.provenance.command, tuple(self.provenance.overrides),
            Versions(**vers), json.dumps(dict(idn.scenario), sort_keys=True),
            tuple(model.state_names), tuple(model.input_names),
            tuple(model.disturbance_names), tuple(m.name for m in model.modes),
            tuple(g.name for g in model.guards),
            convert(MarginsRec, dict(idn.margins)) if idn.margins else None, geometry,
            self.provenance.sweep, idn.build))
        if hasattr(self.rec, "flush"):
            self.rec.flush()  # the run's identity on disk at once (a killed run keeps it)
        self.rec.add_metadata("run", {"scenario": idn.scenario_name, "seed": str(idn.seed),
                                      "log_version": str(LOG_VERSION),
                                      **{f"version.{k}": v for k, v in vers.items()}})

    def step(self, i: int, t: float, x: np.ndarray, mode: int, u: np.ndarray,
             x_ref: np.ndarray, w: np.ndarray) -> None:
        """Logs before simulator step i.

        /sim/state every ``per_state`` steps, /disturbance whenever w changes.
        """
        if i % self.identity.per_state == 0:
            self.state(t, x, mode, u, x_ref, w)
        key = np.asarray(w, dtype=float).tobytes()
        if key != self._last_w:
            self._hold(self._write_w, (t, np.array(w, dtype=float)))
            self._last_w = key

    def _write_w(self, t: float, w: np.ndarray) -> None:
        self.rec.write("/disturbance", t, WRec(t, named(self._model.disturbance_names, w)))

    def state(self, t: float, x: np.ndarray, mode: int, u: np.ndarray, x_ref: np.ndarray,
              w: np.ndarray) -> None:
        """One /sim/state sample (with its scene body), held (copied): see :meth:`flush_held`.

        A sample at the time of the last one is not written again (a run that ends where a
        step began, which sampled it).
        """
        if t == self._state_t:
            return
        self._state_t = t
        self._hold(None, (t, int(mode), *(None if v is None else np.array(v, dtype=float)
                                          for v in (x, u, x_ref, w))))

    def flush_held(self) -> None:
        """Writes the held messages, in order (the file's message order is unchanged).

        Messages are held until the next message of a topic that is not held,
        :data:`HELD` of them, or this call: encoded together, with warm caches, they cost
        less than written one at a time (docs/performance.md). Consecutive /sim/state
        samples are written by :meth:`_write_samples` in one batch.
        """
        held, self._held = self._held, []
        samples: list[tuple] = []
        for writer, args in held:
            if writer is None:
                samples.append(args)
                continue
            if samples:
                self._write_samples(samples)
                samples = []
            writer(*args)
        if samples:
            self._write_samples(samples)

    def _write_samples(self, samples: list[tuple]) -> None:
        """Writes /sim/state samples and their scene bodies.

        Column by column: each vector column becomes its dicts in one ``tolist`` and one
        compiled dict display per row, and the body points of all samples come from one
        batched drawing call (:meth:`~hmpc_cli.core.drawing.Drawing.bodies`).
        """
        m = self._model
        ts, modes, xs, us, refs, ws = zip(*samples, strict=True)
        mode_names = [m.modes[k].name for k in modes]
        cols = [_named_rows(names, col) for names, col in (
            (m.state_names, xs), (m.input_names, us), (m.state_names, refs),
            (m.disturbance_names, ws))]
        bodies = self._body.many(np.stack(xs)) if self._body is not None else \
            [{}] * len(samples)
        sample = record_maker(_STATE_KEYS)  # StateSample's JSON
        self.rec.write_many("/sim/state", ts, map(sample, ts, modes, mode_names, *cols, bodies))
        if self.scene is not None:
            self.scene.states(ts, np.stack(xs))

    def event(self, ev: GuardEvent, system: HybridSystem, scheduled: bool) -> None:
        """Logs a guard event of the simulated system."""
        g = system.guards[ev.guard]
        self._write("/sim/event", ev.t, GuardEventRec(
            ev.t, int(ev.guard), g.name, g.source, g.target,
            named(system.state_names, ev.x_before), named(system.state_names, ev.x_after),
            bool(scheduled), self._body(ev.x_before) if self._body is not None else {}))

    def planner(self, t: float, reason: str, result: PlannerResult, accepted: bool,
                note: str, model: HybridSystem) -> None:
        """Logs one planner call to /planner/plan (and its rollout to the scene)."""
        traj = result.trajectory
        rollout = RolloutArrays(np.zeros(0), np.zeros((0, model.n_x))) if traj is None else \
            RolloutArrays(np.asarray(traj.t, dtype=float), np.asarray(traj.x, dtype=float))
        msg = PlannerCall(
            t, reason, bool(accepted), bool(result.reached_final), float(result.cost),
            float(result.wall_time), int(result.iterations), note,
            _schedule(result.schedule, model), rollout,
            _detail(self.identity.details.get("planner"), result.detail, "planner"))
        self._write("/planner/plan", t, dataclasses.replace(  # on the wire: node records
            msg, rollout=rollout_nodes(rollout, model)))
        if self.scene is not None:
            self.scene.rollout(t, result.trajectory)

    def mpc_solve(self, t: float, plan: Plan, reason: str, model: HybridSystem,
                  latency: float = 0.0, call_time: float = 0.0) -> None:
        """Logs one fixed-mode MPC solve to /mpc/solve (held: a snapshot of the plan).

        ``latency`` [s]: the compute time charged (``sim.latency``; 0: time paused): a plan
        reaches the plant that long after t, unless it is dropped (over budget: not
        adopted; or stopped by a contact, which the next solve's reason names).
        ``call_time`` [s]: the measured wall time of the controller's whole solve call.
        """
        stride = self.identity.plan_stride
        traj = plan.traj
        traj = thinned(traj, stride) if stride > 1 else dataclasses.replace(
            traj, t=np.array(traj.t, dtype=float), x=np.array(traj.x, dtype=float),
            u=np.array(traj.u, dtype=float), mode=np.array(traj.mode), seg=np.array(traj.seg))
        detail = _detail(self.identity.details.get("mpc"), plan.detail, "mpc")
        self._hold(self._write_mpc_solve,
                   (t, dataclasses.replace(plan, traj=traj), reason, model, latency, detail,
                    plan.nodes, call_time))

    def _write_mpc_solve(self, t: float, plan: Plan, reason: str, model: HybridSystem,
                         latency: float, detail, nodes: int, call_time: float) -> None:
        """Writes one /mpc/solve message and its scene plan (``detail``: the MPC's).

        The plan's node times are absolute: ``plan.t0`` + its relative times (t0 is the
        predicted arrival when the solve started from a predicted state, else t).
        """
        st, traj = plan.stats, plan.traj
        msg = MpcSolve(
            t, reason, st.status, bool(st.success), int(st.iterations), float(st.wall_time),
            float(st.cost), float(st.max_violation), float(st.slack), bool(plan.adopt),
            _schedule(plan.schedule, model),
            PlanArrays(np.asarray(traj.t, dtype=float) + plan.t0, np.asarray(traj.seg),
                       np.asarray(traj.mode), np.asarray(traj.x, dtype=float),
                       np.asarray(traj.u, dtype=float)), detail, float(latency), int(nodes),
            float(call_time))
        wire = plan_nodes(msg.plan, 0.0, model)  # on the wire: node records
        self.rec.write("/mpc/solve", t, dataclasses.replace(msg, plan=wire))
        if self.scene is not None:
            self.scene.plan(t, plan)

    def summary(self, r: RunResult) -> None:
        """Writes /run/summary (the books' result)."""
        if self._model is not None:
            self._write("/run/summary", r.t_end, summary_record(r, self._model))


def _named_rows(names: Sequence[str], rows: Sequence[np.ndarray | None]) -> list[dict]:
    """Vectors (each (len(names),) or None) -> their :func:`named` dicts, in order."""
    if any(r is None or r.size != len(names) for r in rows):
        return [named(names, r) for r in rows]
    return list(itertools.starmap(record_maker(tuple(names)),
                                  np.stack(rows).reshape(len(rows), -1).tolist()))


def thinned(traj: Trajectory, stride: int) -> Trajectory:
    """Every ``stride``-th node of ``traj``; the last node is always kept.

    So are both nodes of every domain-segment change (a reset's pair: on the guard, after
    the reset).
    """
    seg = np.asarray(traj.seg)
    n = len(seg)
    if stride <= 1 or n == 0:
        return traj
    keep = np.zeros(n, dtype=bool)
    keep[::stride] = True
    keep[-1] = True
    change = np.flatnonzero(seg[1:] != seg[:-1])
    keep[change] = keep[change + 1] = True
    return dataclasses.replace(traj, t=np.asarray(traj.t)[keep], x=np.asarray(traj.x)[keep],
                               u=np.asarray(traj.u)[keep], mode=np.asarray(traj.mode)[keep],
                               seg=seg[keep])


def rollout_nodes(rollout: RolloutArrays, model: HybridSystem) -> tuple[dict, ...]:
    """A rollout's nodes as :class:`RolloutNode` records (its wire form)."""
    if len(rollout.t) == 0:
        return ()
    keys = flat_keys(RolloutNode, {"state": model.state_names})
    return tuple(map(record_maker(keys), rollout.t.tolist(), *rollout.x.T.tolist()))


def plan_nodes(traj: Trajectory | PlanArrays, t0: float,
               model: HybridSystem) -> tuple[dict, ...]:
    """A plan's nodes as :class:`PlanNode` records (its wire form; times t0 + traj.t).

    A plan with no input columns (a rejected schedule's: the state alone, see
    :func:`~hmpc_cli.mpc.chain.kind.rejected_plan`) has none.
    """
    if len(traj.t) == 0 or (np.shape(traj.u)[-1] == 0 and model.input_names):
        return ()
    keys = flat_keys(PlanNode, {"state": model.state_names, "input": model.input_names})
    modes = [m.name for m in model.modes]
    md = np.asarray(traj.mode).tolist()
    # one plain dict per node with PlanNode's keys (the schema's; tests validate every
    # message), made by a dict display over the columns: a dataclass per node costs more
    # than the rest of the logging of a solve, dict(zip(keys, row)) 2.7x this
    return tuple(map(record_maker(keys), (np.asarray(traj.t, dtype=float) + t0).tolist(),
                     np.asarray(traj.seg).tolist(), md, [modes[m] for m in md],
                     *np.asarray(traj.x, dtype=float).T.tolist(),
                     *np.asarray(traj.u, dtype=float).T.tolist()))


def _schedule(schedule: ModeSchedule | None, model: HybridSystem) -> ScheduleRec | None:
    if schedule is None:
        return None
    d = schedule.to_dict(model)
    return ScheduleRec(tuple(d["modes"]), tuple(d["mode_names"]), tuple(d["guards"]),
                       tuple(d["guard_names"]), tuple(d["durations"]), d["t0"])


def _detail(cls: type | None, detail, of: str):
    """A plug-in's detail to log: None without a declared type (or a detail).

    Raises:
        TypeError: the detail is not an instance of the type the plug-in's spec declares.
    """
    if cls is None or detail is None:
        return None
    if not isinstance(detail, cls):
        raise TypeError(f"the {of} plug-in's detail is a {type(detail).__name__}; its spec "
                        f"declares {cls.__name__} (detail=)")
    return detail


def summary_record(r: RunResult, model: HybridSystem) -> Summary:
    """The typed /run/summary of a result (every guard named in ``contacts_by_guard``)."""
    d = dict(r.__dict__)
    d["x_end"] = named(model.state_names, r.x_end) if len(r.x_end) == model.n_x else {}
    d["contacts_by_guard"] = {g.name: int(r.contacts_by_guard.get(g.name, 0))
                              for g in model.guards}
    d["failure_statuses"] = tuple(StatusCount(k, int(v))
                                  for k, v in sorted(r.failure_statuses.items()))
    d["warnings"] = tuple(str(w) for w in r.warnings)
    d["real_time"] = RealTime(**r.real_time) if r.real_time is not None else None
    return Summary(**d)
