"""The typed run log: one frozen dataclass per topic, its JSON schema generated from it.

Every topic's message is a dataclass below; :func:`topic_schemas` turns the types into
JSON schemas inside the subset Foxglove and Lichtblick parse (:func:`viewer_problems`):
every ``type`` one string, every object with ``properties``, array items scalars or
objects. Vectors of a system are objects with one number per name (``x.px``), so a
run's schemas depend on its system's names (:class:`Names`); a plug-in's log detail (a
planner's candidates, an MPC's node shift) is a typed field whose dataclass the plug-in
declares (:class:`Detail`). Values are written as they are (NaN and inf as null: the
viewers do not validate values); :func:`validate` checks a message against its schema.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from hmpc_cli.loggeometry import GeometryRec, record_maker

__all__ = [
    "LOG_VERSION", "TOPICS", "BuildRec", "Detail", "GuardEventRec", "MarginsRec", "MpcSolve",
    "Names", "PlanNode", "PlannerCall", "RolloutNode", "RunInfo", "ScheduleRec",
    "StateSample", "StatusCount", "Summary", "Versions", "WRec", "convert", "flat_keys",
    "named", "record_maker",
    "topic_schemas", "validate", "viewer_problems"]

#: the log layout this hmpc writes (1: plain arrays, untyped; 2: this module; 3: with the
#: system's geometry and body points, :mod:`hmpc_cli.loggeometry`)
LOG_VERSION = 3


@dataclass(frozen=True)
class Names:
    """A vector written as an object with one field per name of a name set.

    ``kind``: ``state``, ``input``, ``disturbance``, ``guard`` (the system's names) or
    ``body`` (the logged body points' coordinates, :func:`~hmpc_cli.loggeometry.body_names`);
    ``value``: the JSON type of each field; ``flat``: the names are fields of the
    enclosing object itself (a plan node's ``px``, ``ux``), not of a nested one.
    """

    kind: str
    value: str = "number"
    flat: bool = False


@dataclass(frozen=True)
class Detail:
    """A plug-in's typed log detail: ``of`` is ``planner`` or ``mpc``."""

    of: str


State = Annotated[dict, Names("state")]
Input = Annotated[dict, Names("input")]
Dist = Annotated[dict, Names("disturbance")]
Body = Annotated[dict, Names("body")]


@dataclass(frozen=True)
class Versions:
    """Versions of everything that can change a trajectory."""

    hmpc: str
    python: str
    numpy: str
    casadi: str
    pydantic: str
    mcap: str
    platform: str


@dataclass(frozen=True)
class GuardMarginRec:
    """A guard's row offsets (NLP row units)."""

    guard: str
    avoid: float
    pass_through: float


@dataclass(frozen=True)
class InputMarginRec:
    """A mode's input-box shrink per side."""

    mode: str
    per_side: tuple[float, ...]


@dataclass(frozen=True)
class MarginsRec:
    """The MPC's margins: hand-set or a margins file's."""

    source: str
    radius: float
    guards: tuple[GuardMarginRec, ...]
    inputs: tuple[InputMarginRec, ...]


@dataclass(frozen=True)
class BuildRec:
    """How the MPC's NLPs were built (:class:`hmpc_cli.mpc.cache.BuildInfo`).

    Attributes:
        cache: "hit" (compiled NLPs loaded from the build cache), "miss" (built in SX
            and cached) or "disabled" (built in SX, no cache).
        compiled: the solves call compiled code (else CasADi's SX virtual machine).
        reason: why, in one line.
    """

    cache: str
    compiled: bool
    reason: str


@dataclass(frozen=True)
class RunInfo:
    """/run/info: the run's identity (written first)."""

    log_version: int
    scenario_name: str
    seed: int
    system: str
    mpc_kind: str
    planner_kind: str
    command: str
    overrides: tuple[str, ...]
    versions: Versions
    scenario_json: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    disturbance_names: tuple[str, ...]
    mode_names: tuple[str, ...]
    guard_names: tuple[str, ...]
    margins: MarginsRec | None = None
    geometry: GeometryRec | None = None
    sweep: str = ""  # the sweep file of a sweep's run, "" for a single run
    build: BuildRec | None = None


@dataclass(frozen=True)
class StateSample:
    """/sim/state: the simulated state, the applied input, the reference, the disturbance."""

    t: float
    mode: int
    mode_name: str
    x: State
    u: Input
    x_ref: State
    w: Dist
    body: Body = field(default_factory=dict)


@dataclass(frozen=True)
class GuardEventRec:
    """/sim/event: a guard crossing of the simulated system."""

    t: float
    guard: int
    guard_name: str
    mode_before: str
    mode_after: str
    x_before: State
    x_after: State
    scheduled: bool
    body_before: Body = field(default_factory=dict)


@dataclass(frozen=True)
class WRec:
    """/disturbance: the disturbance from this time on."""

    t: float
    w: Dist


@dataclass(frozen=True)
class ScheduleRec:
    """A domain/guard sequence: modes, the guards between them, their durations [s]."""

    modes: tuple[int, ...]
    mode_names: tuple[str, ...]
    guards: tuple[int, ...]
    guard_names: tuple[str, ...]
    durations: tuple[float, ...]
    t0: float


@dataclass(frozen=True)
class PlanNode:
    """One node of an MPC plan: absolute time [s], domain segment, mode, values.

    The state's and the input's named values are fields of the node itself
    (``plan[:].px``).
    """

    t: float
    seg: int
    mode: int
    mode_name: str
    x: Annotated[dict, Names("state", flat=True)]
    u: Annotated[dict, Names("input", flat=True)]


@dataclass(frozen=True)
class MpcSolve:
    """/mpc/solve: one fixed-mode MPC solve and its plan."""

    t: float
    reason: str
    status: str
    success: bool
    iterations: int
    wall_time: float
    cost: float
    max_violation: float
    slack: float
    adopted: bool
    schedule: ScheduleRec | None
    plan: tuple[PlanNode, ...]
    detail: Annotated[Any, Detail("mpc")] = None
    #: delay [s] before the plan reaches the plant (``sim.latency``; 0: time paused)
    latency: float = 0.0


@dataclass(frozen=True)
class RolloutNode:
    """One node of a planner's rollout: absolute time [s] and the state's named values."""

    t: float
    x: Annotated[dict, Names("state", flat=True)]


@dataclass(frozen=True)
class PlannerCall:
    """/planner/plan: one hybrid-planner call."""

    t: float
    reason: str
    accepted: bool
    reached_final: bool
    cost: float
    wall_time: float
    iterations: int
    note: str
    schedule: ScheduleRec | None
    rollout: tuple[RolloutNode, ...]
    detail: Annotated[Any, Detail("planner")] = None


@dataclass(frozen=True)
class StatusCount:
    """How often a solver status occurred."""

    status: str
    count: int


@dataclass(frozen=True)
class Summary:
    """/run/summary: the run's outcome (summary.json, typed)."""

    scenario: str
    seed: int
    success: bool
    final_error: float
    t_end: float
    x_end: State
    mode_end: str
    contacts: int
    contacts_by_guard: Annotated[dict, Names("guard", "integer")]
    solves: int
    solver_failures: int
    failure_statuses: tuple[StatusCount, ...]
    softened_solves: int
    max_slack: float
    fallbacks: int
    solve_time_median: float
    solve_time_p95: float
    solve_time_max: float
    planner_calls: int
    planner_rejected: int
    plan_time_median: float
    diverged: bool
    reason: str
    wall_time: float
    warnings: tuple[str, ...]


#: topic -> (schema name, message type)
TOPICS: dict[str, tuple[str, type]] = {
    "/run/info": ("hmpc.RunInfo", RunInfo),
    "/sim/state": ("hmpc.State", StateSample),
    "/sim/event": ("hmpc.GuardEvent", GuardEventRec),
    "/disturbance": ("hmpc.Disturbance", WRec),
    "/mpc/solve": ("hmpc.MpcSolve", MpcSolve),
    "/planner/plan": ("hmpc.PlannerCall", PlannerCall),
    "/run/summary": ("hmpc.Summary", Summary),
}

_SCALARS = {float: "number", int: "integer", str: "string", bool: "boolean"}


def named(names: typing.Sequence[str], values) -> dict:
    """The vector ``values`` as an object {name: value} (values as Python floats)."""
    if values is None:
        return {}
    vals = np.asarray(values, dtype=float).ravel().tolist()
    if len(vals) == len(names):
        return record_maker(tuple(names))(*vals)
    return dict(zip(names, vals, strict=False))




@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


def _strip_optional(tp):
    """(X, nullable) for X | None."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return tp, False


def _schema(tp, names: Mapping[str, typing.Sequence[str]],
            details: Mapping[str, type | None]) -> dict:
    """JSON schema of a field type."""
    tp, _ = _strip_optional(tp)
    if typing.get_origin(tp) is Annotated:
        base, *meta = typing.get_args(tp)
        for m in meta:
            if isinstance(m, Names):
                return {"type": "object", "properties": {
                    n: {"type": m.value} for n in names.get(m.kind, ())}}
            if isinstance(m, Detail):  # no declared detail: an empty object (always null)
                cls = details.get(m.of)
                return {"type": "object", "properties": {}} if cls is None else \
                    _schema(cls, names, details)
        return _schema(base, names, details)
    if tp in _SCALARS:
        return {"type": _SCALARS[tp]}
    if typing.get_origin(tp) in (tuple, list):
        item = typing.get_args(tp)[0]
        inner = _schema(item, names, details)
        if inner["type"] == "array":
            raise TypeError(f"array items must be scalars or objects, not {item!r}")
        return {"type": "array", "items": inner}
    if dataclasses.is_dataclass(tp):
        return _object_schema(tp, names, details)
    raise TypeError(f"no JSON schema for {tp!r}")


def _object_schema(tp: type, names: Mapping[str, typing.Sequence[str]],
                   details: Mapping[str, type | None]) -> dict:
    """The object schema of a dataclass (flat name fields spliced into its properties)."""
    hints, props = _hints(tp), {}
    for f in dataclasses.fields(tp):
        flat = _flat(hints[f.name])
        if flat is None:
            props[f.name] = _schema(hints[f.name], names, details)
            continue
        for n in names.get(flat.kind, ()):
            if n in props:
                raise TypeError(f"{tp.__name__}: name {n!r} of {flat.kind} names collides "
                                "with another field")
            props[n] = {"type": flat.value}
    return {"title": tp.__name__, "type": "object", "properties": props}


def _flat(tp) -> Names | None:
    """The flat :class:`Names` of a field annotation, or None."""
    if typing.get_origin(tp) is Annotated:
        return next((m for m in typing.get_args(tp)[1:]
                     if isinstance(m, Names) and m.flat), None)
    return None


def flat_keys(cls: type, names: Mapping[str, typing.Sequence[str]]) -> tuple[str, ...]:
    """The JSON keys of a record with flat name fields, in field order (e.g. PlanNode)."""
    hints, out = _hints(cls), []
    for f in dataclasses.fields(cls):
        flat = _flat(hints[f.name])
        out += list(names.get(flat.kind, ())) if flat is not None else [f.name]
    return tuple(out)


def topic_schemas(names: Mapping[str, typing.Sequence[str]],
                  details: Mapping[str, type | None] | None = None) -> dict[str, tuple[str, dict]]:
    """The topics' (schema name, JSON schema) for a run's names and plug-in detail types.

    Args:
        names: ``state``, ``input``, ``disturbance``, ``guard`` -> the system's names.
        details: ``planner``, ``mpc`` -> the plug-ins' detail dataclasses (or None).
    """
    details = dict(details or {})
    return {topic: (name, _schema(cls, names, details)) for topic, (name, cls) in TOPICS.items()}


def convert(cls, value):
    """``value`` (dicts, lists, dataclasses) as an instance of dataclass ``cls``.

    Nested dataclass fields and tuples of dataclasses are converted recursively; the
    result raises TypeError on unknown or missing fields (a plug-in's detail that does
    not match its declared type).
    """
    if value is None or isinstance(value, cls):
        return value
    if dataclasses.is_dataclass(value):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    hints = _hints(cls)
    return cls(**{k: _convert_field(hints.get(k, Any), v) for k, v in dict(value).items()})


def _convert_field(tp, v):
    tp, _ = _strip_optional(tp)
    if typing.get_origin(tp) is Annotated:
        tp = typing.get_args(tp)[0]
    if dataclasses.is_dataclass(tp) and isinstance(v, Mapping):
        return convert(tp, v)
    if typing.get_origin(tp) in (tuple, list) and v is not None:
        item = typing.get_args(tp)[0]
        return tuple(_convert_field(item, x) for x in v)
    return v


def viewer_problems(schema: dict, path: str = "") -> list[str]:
    """Where ``schema`` leaves the viewers' subset (empty: Foxglove/Lichtblick parse it)."""
    out = []
    t = schema.get("type")
    where = path or "(root)"
    if not isinstance(t, str):
        return [f"{where}: type {t!r} is not one string"]
    if t == "object":
        if "properties" not in schema:
            out.append(f"{where}: object without properties")
        for k, sub in schema.get("properties", {}).items():
            out += viewer_problems(sub, f"{path}.{k}" if path else k)
    elif t == "array":
        items = schema.get("items")
        if not isinstance(items, dict) or items.get("type") == "array":
            out.append(f"{where}: array items must be scalars or objects")
        else:
            out += viewer_problems(items, f"{path}[]")
    return out


_PY = {"number": (int, float), "integer": (int,), "string": (str,), "boolean": (bool,)}


def validate(schema: dict, value, path: str = "") -> list[str]:
    """Where a decoded JSON ``value`` does not match ``schema`` (null allowed anywhere).

    Objects must have exactly the schema's properties (no unknown keys; absent ones are
    allowed only for null-able fields written as null).
    """
    where = path or "(root)"
    if value is None:
        return []
    t = schema["type"]
    if t == "object":
        if not isinstance(value, dict):
            return [f"{where}: expected an object"]
        props = schema["properties"]
        out = [f"{where}: unknown field {k!r}" for k in value if k not in props]
        for k, sub in props.items():
            if k in value:
                out += validate(sub, value[k], f"{path}.{k}" if path else k)
        return out
    if t == "array":
        if not isinstance(value, list):
            return [f"{where}: expected an array"]
        return [p for i, v in enumerate(value) for p in validate(schema["items"], v,
                                                                 f"{path}[{i}]")]
    ok = isinstance(value, _PY[t]) and not (t in ("number", "integer")
                                              and isinstance(value, bool))
    return [] if ok else [f"{where}: expected {t}, got {type(value).__name__}"]
