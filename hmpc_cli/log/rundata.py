"""A run log read back as the types it was written from, for any system: :func:`read_run`.

The one reader of the run log's payloads: figures, ``hmpc tube --runs`` and ``hmpc
replay`` read through it. /run/info, /run/summary, /mpc/solve and /planner/plan come
back as their topic types (:mod:`hmpc_cli.log.topics`: :class:`RunInfo`,
:class:`Summary`, :class:`MpcSolve` with its plan as :class:`PlanArrays`,
:class:`PlannerCall`), /sim/state and /disturbance as arrays; a plug-in's detail as a
record typed from the log's own schema (:func:`~hmpc_cli.log.schema.record_type`, no
plug-in imported). It understands the typed log (vectors as named objects, plans as
arrays of nodes), the older untyped layout (log version 1: plain arrays), and a log cut
short (``complete`` False).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hmpc_cli.log.damage import DamagedLogError, reading
from hmpc_cli.log.geometry import GeometryRec, body_names
from hmpc_cli.log.schema import read_record, record_type
from hmpc_cli.log.trace import TRACE_NAME, TRACE_TOPICS
from hmpc_cli.log.topics import (
    MpcSolve, PlanArrays, PlannerCall, RolloutArrays, RunInfo, Summary)

__all__ = ["DamagedLogError", "Event", "RunData", "TRAJECTORY_TOPICS", "read_run", "resolve_log",
           "sweep_text"]


def resolve_log(path: Path) -> Path:
    """``path`` itself, or ``path/run.mcap`` for a run directory (ValueError: neither).

    A run log that is not there is read from the trajectory log beside it
    (:data:`~hmpc_cli.log.trace.TRACE_NAME`, a committed results page's copy) if there is one.
    """
    path = Path(path)
    if path.is_dir():
        sweep = sweep_text(path)
        if sweep and not (path / "run.mcap").is_file():
            raise ValueError(f"{path}{sweep}")
        path = path / "run.mcap"
    if not path.is_file() and path.name == "run.mcap" and (path.parent / TRACE_NAME).is_file():
        path = path.parent / TRACE_NAME
    if not path.is_file():
        raise ValueError(f"{path}: no such run log")
    return path


def sweep_text(directory: Path) -> str:
    """``: a sweep's output directory, ...`` for one; '' for any other directory.

    A sweep's: its ``runs/`` beside its table or its ``sweep.toml`` (stopped before its
    table).
    """
    sweep = (directory / "runs").is_dir() and any(
        (directory / name).is_file() for name in ("results.csv", "sweep.toml"))
    return (f": a sweep's output directory, not a run's: its runs are in "
            f"{directory / 'runs'}/<run id>") if sweep else ""


@dataclass(frozen=True)
class Event:
    """A guard event: time [s], guard index and name, modes, states before/after (n,).

    ``body_before``: the body points before the event (P, 2) [m] (P = 0: none logged).
    """

    t: float
    guard: int
    guard_name: str
    mode_before: str
    mode_after: str
    x_before: np.ndarray
    x_after: np.ndarray
    scheduled: bool
    body_before: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass
class RunData:
    """Everything a run log holds, as arrays.

    Attributes:
        path: the log file.
        complete: False when the file was cut short (no footer).
        log_version: the log layout (1: untyped arrays, 2: typed, 3: with geometry, 4: no
            nulls, 5: /mpc/solve's nodes, 6: /run/summary's real_time).
        info: /run/info (None when missing; an older log's missing fields empty).
        scenario: the scenario as run (a dict).
        state_names, input_names, mode_names, guard_names: the system's names.
        t (K,) [s], x (K, n), u (K, m), x_ref (K, n), w (K, n_w), mode (K,): /sim/state.
        events: /sim/event in time order.
        t_w (D,) [s], w_changes (D, n_w): /disturbance.
        solves: /mpc/solve in time order; planner: /planner/plan.
        summary: /run/summary (None: the run did not finish).
        damage: why reading stopped early at a damaged chunk ('' if it did not).
        geometry: /run/info's ``geometry`` (None for logs before version 3).
        body: the body points of each /sim/state sample (K, P, 2) [m] (P = 0: none logged;
            names in ``geometry["point_names"]``).
    """

    path: Path
    complete: bool
    log_version: int
    info: RunInfo | None
    scenario: dict
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    mode_names: tuple[str, ...]
    guard_names: tuple[str, ...]
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    x_ref: np.ndarray
    w: np.ndarray
    mode: np.ndarray
    events: list[Event] = field(default_factory=list)
    t_w: np.ndarray = field(default_factory=lambda: np.zeros(0))
    w_changes: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    solves: list[MpcSolve] = field(default_factory=list)
    planner: list[PlannerCall] = field(default_factory=list)
    summary: Summary | None = None
    damage: str = ""
    geometry: GeometryRec | None = None
    body: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 2)))

    @property
    def name(self) -> str:
        """The run's name: its directory for a run.mcap, else the file name."""
        return self.path.parent.name if self.path.name == "run.mcap" else self.path.name

    @property
    def system(self) -> dict:
        """The scenario's ``[system]`` section."""
        return dict(self.scenario.get("system") or {})

    @property
    def plan_stride(self) -> int:
        """The scenario's ``sim.log_plan_stride`` (:func:`plan_stride`)."""
        return plan_stride(self.scenario)

    @property
    def damage_text(self) -> str:
        """:func:`damage_note` of this log: its damage or cut ('' if read whole)."""
        return damage_note(self.damage, self.complete)

    def lacks(self, what: str) -> str:
        """``<path>: <what>``, naming the damage or the cut that may have lost it (one line)."""
        return f"{self.path}: {what}{damage_note(self.damage, self.complete)}"

    def full_plans(self, use: str) -> None:
        """Raises ValueError when the logged plans are thinned: ``use`` needs every node.

        The message names the setting and how to get a log with every node.
        """
        if self.plan_stride > 1:
            raise ValueError(
                f"{self.path}: the logged plans are thinned (sim.log_plan_stride = "
                f"{self.plan_stride}: one node in {self.plan_stride}); {use} needs every "
                "plan node: run the scenario again with --set sim.log_plan_stride=1")

    def adopted(self) -> list[MpcSolve]:
        """The solves whose plan the loop adopted."""
        return [s for s in self.solves if s.adopted]


def plan_stride(scenario: dict) -> int:
    """A logged scenario's ``sim.log_plan_stride``: one plan node in k was logged (1: all)."""
    try:
        return max(1, int((scenario.get("sim") or {}).get("log_plan_stride", 1)))
    except (TypeError, ValueError):
        return 1


def _vec(value, names) -> np.ndarray:
    """A logged vector (named object or plain list; None entries NaN) as a float array."""
    if isinstance(value, dict):
        return np.array([np.nan if value.get(n) is None else value[n] for n in names],
                        dtype=float)
    vals = list(value or [])
    return np.array([np.nan if v is None else v for v in vals], dtype=float)


def _part(node: dict, key: str) -> dict:
    """A node's nested vector ``key`` (an early typed layout), else the node itself (flat)."""
    v = node.get(key)
    return v if isinstance(v, dict) else node


def _mat(rows: list[np.ndarray], width: int) -> np.ndarray:
    return np.vstack(rows) if rows else np.zeros((0, width))


def _plan(d: dict, names: tuple, inputs: tuple) -> PlanArrays:
    """The plan of a solve record (typed or untyped)."""
    if "plan" in d:
        nodes = d.get("plan") or []
        return PlanArrays(np.array([float(n["t"]) for n in nodes]),
                          np.array([int(n["seg"]) for n in nodes], dtype=int),
                          np.array([int(n.get("mode", -1)) for n in nodes], dtype=int),
                          _mat([_vec(_part(n, "x"), names) for n in nodes], len(names)),
                          _mat([_vec(_part(n, "u"), inputs) for n in nodes], len(inputs)))
    x = np.atleast_2d(np.asarray(d.get("x_plan") or np.zeros((0, len(names))), dtype=float))
    u = np.atleast_2d(np.asarray(d.get("u_plan") or np.zeros((0, len(inputs))), dtype=float))
    t = np.asarray(d.get("t_plan") or [], dtype=float)
    return PlanArrays(t, np.asarray(d.get("seg_plan") or [], dtype=int),
                      np.full(len(t), -1, dtype=int), x, u)


_SOLVE_KEYS = ("t", "reason", "status", "success", "iterations", "wall_time", "cost", "slack",
               "adopted", "schedule", "plan", "x_plan", "u_plan", "t_plan", "seg_plan",
               "max_violation", "detail", "latency", "nodes")


def _detail(d: dict, schema: dict | None, old: dict, title: str):
    """A record's plug-in detail, typed from the log's schema (older logs: its keys)."""
    value = d.get("detail") or old
    if not value:
        return None
    props = (schema or {}).get("properties", {}).get("detail")
    if not props or not props.get("properties"):
        props = {"type": "object", "properties": {k: {} for k in value}}
    return read_record(record_type(props, title), value)


def _solve(d: dict, names: tuple, inputs: tuple, schema: dict | None) -> MpcSolve:
    rec = read_record(MpcSolve, {k: v for k, v in d.items() if k not in ("plan", "detail")})
    old = {k: v for k, v in d.items() if k not in _SOLVE_KEYS}  # log version 1
    return dataclasses.replace(rec, plan=_plan(d, names, inputs),
                               detail=_detail(d, schema, old, "MPCDetail"))


def _planner(d: dict, names: tuple, schema: dict | None) -> PlannerCall:
    if "rollout" in d:
        nodes = d.get("rollout") or []
        t_r = np.array([float(n["t"]) for n in nodes])
        x_r = _mat([_vec(_part(n, "x"), names) for n in nodes], len(names))
    else:
        t_r = np.asarray(d.get("t_rollout") or [], dtype=float)
        x_r = np.atleast_2d(np.asarray(d.get("x_rollout") or np.zeros((0, len(names))),
                                       dtype=float))
    rec = read_record(PlannerCall, {k: v for k, v in d.items()
                                    if k not in ("rollout", "detail")})
    old = {"candidates": d["candidates"]} if "candidates" in d else {}
    return dataclasses.replace(rec, rollout=RolloutArrays(t_r, x_r),
                               detail=_detail(d, schema, old, "PlannerDetail"))


def _points(value, coords: tuple[str, ...]) -> np.ndarray:
    """Logged body coordinates (``coords``: ``<p>_x``, ``<p>_y``, ...) as points (P, 2) [m].

    NaN where missing; (0, 2) when no body is logged (``coords`` empty).
    """
    if not coords:
        return np.zeros((0, 2))
    return _vec(value if isinstance(value, dict) else {}, coords).reshape(-1, 2)


def _body(states: list[dict], coords: tuple[str, ...]) -> np.ndarray:
    """The body points of each state sample, (K, P, 2) [m]."""
    if not coords:
        return np.zeros((len(states), 0, 2))
    return np.stack([_points(s.get("body"), coords) for s in states]) if states else \
        np.zeros((0, len(coords) // 2, 2))


def _scenario(info: dict) -> dict:
    """The scenario as run (an older log's object, else the JSON text's)."""
    if "scenario_json" in info:
        try:
            return dict(json.loads(info["scenario_json"] or "{}"))
        except (json.JSONDecodeError, TypeError):
            return {}
    return dict(info.get("scenario") or {})


def _names(info: dict, key: str, first: list, width: int) -> tuple[str, ...]:
    """The logged names, else those of the first named record, else x0, x1, ..."""
    if info.get(key):
        return tuple(info[key])
    if first and isinstance(first[0], dict):
        return tuple(first[0])
    return tuple(f"{key[0]}{i}" for i in range(width))


def damage_note(damage: str, complete: bool) -> str:
    """`` (damaged log: ...)`` or `` (the log is cut short)`` for a message ('' if intact)."""
    if damage:
        return f" (damaged log: {damage})"
    return "" if complete else " (the log is cut short)"


#: the topics :func:`read_run` reads without the plans (``with_plans=False``): a trajectory
#: log's, but for the planner's
TRAJECTORY_TOPICS = frozenset(TRACE_TOPICS) - {"/planner/plan"}


def read_run(path: Path, with_plans: bool = True) -> RunData:
    """Reads a run log (a run.mcap or its run directory) into arrays.

    ``with_plans=False`` decodes only :data:`TRAJECTORY_TOPICS`, not /mpc/solve and
    /planner/plan (most of a log's bytes) nor the scene: ``solves`` and ``planner`` are
    then empty and the rest as with them, but for a message of the undecoded topics that
    is malformed inside an intact chunk (see :func:`~hmpc_cli.log.reader.read_log`).

    Raises:
        ValueError: missing, not an MCAP file, or not readable at all (the message says
            which); a log cut short is read up to its last complete chunk.
        DamagedLogError: a ValueError: content of the wrong type or shape (a damaged or
            foreign log).
    """
    from hmpc_cli.log.reader import read_log

    log_path = resolve_log(path)
    try:
        log = read_log(log_path, None if with_plans else TRAJECTORY_TOPICS)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{log_path}: cannot read the log ({exc})") from None
    with reading(log_path):  # wrongly typed or missing fields: damage, not a bug
        return _run_data(log_path, log)


def _run_data(log_path: Path, log) -> RunData:
    """:func:`read_run` of a decoded log (its content trusted: the caller guards it)."""
    infos = log.topic("/run/info")
    info = dict(infos[0].data) if infos else {}
    schemas = getattr(log, "schemas", {}) or {}
    states = [{"t": m.t, **m.data} for m in log.topic("/sim/state")]
    width = len(states[0]["x"]) if states else 0
    names = _names(info, "state_names", [s["x"] for s in states[:1]], width)
    inputs = _names(info, "input_names", [s.get("u") for s in states[:1]],
                    len(states[0].get("u") or []) if states else 0)
    dist = _names(info, "disturbance_names", [s.get("w") for s in states[:1]],
                  len(states[0].get("w") or []) if states else 0)
    w_msgs = [{"t": m.t, **m.data} for m in log.topic("/disturbance")]
    geometry = read_record(GeometryRec, info["geometry"]) if info.get("geometry") else None
    coords = body_names(geometry.point_names if geometry else ())  # once, not per sample
    summaries = log.topic("/run/summary")
    return RunData(
        log_path, log.complete, int(info.get("log_version", 1)),
        _run_info(info) if infos else None, _scenario(info),
        names, inputs, tuple(info.get("mode_names") or ()),
        tuple(info.get("guard_names") or ()),
        np.array([float(s["t"]) for s in states]),
        _mat([_vec(s["x"], names) for s in states], len(names)),
        _mat([_vec(s.get("u"), inputs) for s in states], len(inputs)),
        _mat([_vec(s.get("x_ref"), names) for s in states], len(names)),
        _mat([_vec(s.get("w"), dist) for s in states], len(dist)),
        np.array([int(s.get("mode", 0)) for s in states], dtype=int),
        sorted((Event(float(d["t"]), int(d.get("guard", -1)), str(d.get("guard_name", "")),
                      str(d.get("mode_before", "")), str(d.get("mode_after", "")),
                      _vec(d.get("x_before"), names), _vec(d.get("x_after"), names),
                      bool(d.get("scheduled", True)), _points(d.get("body_before"), coords))
                for d in (m.data for m in log.topic("/sim/event"))), key=lambda e: e.t),
        np.array([float(d["t"]) for d in w_msgs]),
        _mat([_vec(d.get("w"), dist) for d in w_msgs], len(dist)),
        sorted((_solve(m.data, names, inputs, schemas.get("/mpc/solve"))
                for m in log.topic("/mpc/solve")), key=lambda s: s.t),
        sorted((_planner(m.data, names, schemas.get("/planner/plan"))
                for m in log.topic("/planner/plan")), key=lambda p: p.t),
        read_record(Summary, summaries[-1].data) if summaries else None,
        getattr(log, "damage", ""), geometry, _body(states, coords))


def _run_info(info: dict) -> RunInfo:
    """/run/info typed (an older layout's scenario object as its JSON text)."""
    if "scenario_json" not in info and isinstance(info.get("scenario"), dict):
        info = {**info, "scenario_json": json.dumps(info["scenario"], sort_keys=True)}
    return read_record(RunInfo, info)
