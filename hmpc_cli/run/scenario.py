"""Scenario files: pydantic v2 models in TOML, each layer owning its settings section.

The ``system``, ``planner`` and ``mpc`` sections are unions over the registered plug-ins
(:mod:`hmpc_cli.core.registry`), discriminated by ``system.name``, ``planner.kind`` and
``mpc.kind``; the planner and MPC kinds and other settings default to what the system's
plug-in names, and settings a plug-in requires are checked with the reason. Unknown keys
are rejected; rates are integers in Hz and must be commensurate (the MPC period a whole
number of simulator steps and of the MPC's node steps). :func:`load_scenario` turns
every problem into :class:`ScenarioError` lines of the form ``file: key.path: reason``.
The model class is assembled on first use: ``from hmpc_cli.run.scenario import Scenario``.
"""

from __future__ import annotations

import copy
import difflib
import json
import math
import os
import re
import tomllib
import types
import typing
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any, Union

from pydantic import (
    BaseModel, ConfigDict, Field, ValidationError, create_model, field_validator,
    model_validator)

from hmpc_cli.lowlevel import LowLevelSettings
from hmpc_cli.core.registry import PluginError, Requirement, registry
from hmpc_cli.core.text import did_you_mean, printable
from hmpc_cli.run.sections import DisturbanceSettings, ReplanSettings, SimSettings
from hmpc_cli.sim.disturbance import knot_period
from hmpc_cli.core.settings_types import BoundedInt

#: the system of a scenario that names none
DEFAULT_SYSTEM = "ball"
#: most simulator steps of a run (duration x rate: ~5 h at 600 Hz; per-step arrays grow)
MAX_SIM_STEPS = 10_000_000


class ScenarioError(Exception):
    """Invalid scenario input; ``lines`` holds one message per problem."""

    def __init__(self, lines: list[str]) -> None:
        super().__init__("\n".join(lines))
        self.lines = lines


class ScenarioBase(BaseModel):
    """A complete experiment: system, simulator, disturbance and the three layers.

    The ``system``, ``planner`` and ``mpc`` fields are added by :func:`scenario_model`.
    """

    model_config = ConfigDict(extra="forbid")
    name: str = Field("scenario", pattern=r"^[A-Za-z0-9_.-]+$", max_length=100,
                      description="run directory name: letters, digits, _ . - (not only "
                      "dots); from a file, its default is the file's name without .toml "
                      "(other characters as _)")
    description: str = ""
    seed: BoundedInt = Field(0, ge=0)
    plant: dict[str, Any] = Field(
        default_factory=dict, description="system parameters of the simulated plant that "
        "differ from the controllers' model, e.g. mass_scale = 1.1 (the biped of Fig. 4)")
    sim: SimSettings = Field(default_factory=SimSettings)
    disturbance: DisturbanceSettings = Field(default_factory=DisturbanceSettings)
    replanning: ReplanSettings = Field(default_factory=ReplanSettings)
    lowlevel: LowLevelSettings = Field(default_factory=LowLevelSettings)

    @field_validator("name")
    @classmethod
    def _not_only_dots(cls, v: str) -> str:
        if not v.strip("."):
            raise ValueError(f"{v!r} is not a directory name (only dots: the run would be "
                             "written outside results/)")
        return v

    @model_validator(mode="before")
    @classmethod
    def _plugin_defaults(cls, data: Any) -> Any:
        """Fills the system name, the planner/MPC kinds and the plug-ins' settings.

        Defaults and required values of the plug-ins fill what the scenario leaves
        out; a value the scenario sets always wins (a wrong one is reported later).
        """
        if not isinstance(data, dict):
            return data
        data = dict(data)
        system = data.get("system", {})
        if not isinstance(system, dict):
            return data
        system = data["system"] = {"name": DEFAULT_SYSTEM, **system}
        reg = registry()
        if not isinstance(system["name"], str) or system["name"] not in reg.systems:
            raise ValueError(f"system.name: {_unknown(reg, system['name'])}")
        spec = reg.system(system["name"])
        problems = _plugin_key_problems(reg, spec, data)
        if problems:  # the plug-in's mistake: not blamed on the scenario's own keys
            raise ValueError("\n".join(problems))
        for section, kind in (("planner", spec.planner), ("mpc", spec.mpc)):
            sec = data.get(section, {})
            if isinstance(sec, dict):
                kind = sec.get("kind", kind)
                data[section] = {"kind": kind, **spec.defaults.get(f"{section}.{kind}", {}),
                                 **sec}
        for key, values in spec.defaults.items():
            if "." not in key and isinstance(data.get(key, {}), dict):
                data[key] = {**values, **data.get(key, {})}
        for req in _requirements(reg, data):
            section, _, name = req.key.partition(".")
            if isinstance(data.get(section, {}), dict):
                data[section] = {name: req.value, **data.get(section, {})}
        problems = _kind_problems(reg, spec, data)
        if problems:  # before the sections' own keys are checked against the wrong kind
            raise ValueError("\n".join(problems))
        return data

    def plant_params(self) -> BaseModel:
        """The simulated plant's parameters: the system's, updated by ``plant``."""
        return type(self.system).model_validate({**self.system.model_dump(), **self.plant})

    @model_validator(mode="after")
    def _consistent(self) -> ScenarioBase:
        # One "key.path: reason" line per problem (format_errors splits them).
        problems = self._stack_problems() + self._rate_problems() + self._size_problems()
        if problems:
            raise ValueError("\n".join(problems))
        return self

    def _rate_problems(self) -> list[str]:
        m, s, problems = self.mpc, self.sim, []
        steps = [*m.period_steps(), ("sim.rate_hz", s.rate_hz)]
        divides = [f"{k} = {v}" for k, v in steps if v % m.rate_hz]
        if divides:
            what = "simulator steps" if len(steps) == 1 else \
                "node steps and of simulator steps"
            problems.append(f"mpc.rate_hz: {m.rate_hz} must divide " + " and ".join(divides)
                            + f" (the MPC period must be a whole number of {what})")
        if s.rate_hz % s.log_rate_hz:
            problems.append(f"sim.log_rate_hz: {s.log_rate_hz} must divide sim.rate_hz = "
                            f"{s.rate_hz}")
        step = f"must be a whole number of simulator steps (1/sim.rate_hz = 1/{s.rate_hz} s)"
        if not _whole(s.duration * s.rate_hz):
            problems.append(f"sim.duration: {s.duration:g} s {step}")
        d = self.disturbance
        if (held := knot_period(d.kind, d.hold)) is not None and not _whole(held * s.rate_hz):
            problems.append(f"disturbance.hold: {d.hold:g} s {step}" if d.kind == "box" else
                            f"disturbance.kind: {d.kind} holds each value {held:g} s, which "
                            f"{step}; pick a sim.rate_hz that is a multiple of {1 / held:g}")
        if self.replanning.policy == "periodic" and not _whole(self.replanning.period * s.rate_hz):
            problems.append(f"replanning.period: {self.replanning.period:g} s {step}")
        return problems + list(m.scenario_problems())

    def _size_problems(self) -> list[str]:
        """Upper bounds on the work a run asks for, checked before anything is built."""
        s = self.sim
        steps = s.duration * s.rate_hz
        out = []
        if steps > MAX_SIM_STEPS:
            out.append(f"sim.duration: {s.duration:g} s x {s.rate_hz} steps/s (sim.rate_hz) "
                       f"= {steps:.3g} "
                       f"simulator steps exceeds the limit {MAX_SIM_STEPS:.0e}")
        out += list(self.planner.size_problems())
        out += list(self.mpc.size_problems())
        return out

    def _stack_problems(self) -> list[str]:
        """Required settings of the plug-ins; plant keys must be valid system parameters."""
        reg = registry()
        out = []
        data = self.model_dump()
        for req in _requirements(reg, data):
            section, _, name = req.key.partition(".")
            value = data.get(section, {}).get(name)
            if value != req.value:
                out.append(f"{req.key}: {req.why}; use {req.value!r}, not {value!r}")
        if self.plant:
            out += self._plant_problems()
        return out

    def _plant_problems(self) -> list[str]:
        out = []
        try:
            self.plant_params()
        except ValidationError as exc:
            out += [_plant_error(err, type(self.system))
                    for err in _tuple_lengths(exc.errors(), type(self.system))]
        return out


def _unknown(reg, name: Any) -> str:
    """'unknown system ...' with the choices, or why that plug-in failed to load."""
    why = reg.failure("system", name) if isinstance(name, str) else None
    if why is not None:
        return why
    choices = ", ".join(repr(k) for k in sorted(reg.systems))
    close = difflib.get_close_matches(str(name), sorted(reg.systems), n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    return f"unknown system {name!r} ({hint}choose from {choices})"


#: the scenario sections a plug-in's defaults and requirements may set beside its kinds
_SECTIONS = {"sim": SimSettings, "disturbance": DisturbanceSettings,
             "replanning": ReplanSettings, "lowlevel": LowLevelSettings}


def _plugin_key_problems(reg, spec, data: dict) -> list[str]:
    """Lines for plug-in defaults and requirements that name no scenario setting.

    The system's ``defaults`` (its sections, and ``planner.<kind>`` / ``mpc.<kind>`` of
    registered kinds) and the ``requires`` of the system and of the scenario's planner and
    MPC kinds: a key its section's model lacks is the plug-in's mistake, so the line is at
    the key that chose the plug-in (``system.name``, ``planner.kind``, ``mpc.kind``).
    """
    kinds = {"planner": reg.planners, "mpc": reg.mpcs}
    chosen = {sec: _chosen_kind(data, sec) or getattr(spec, sec) for sec in kinds}
    checks = [("system.name", f"system plug-in {spec.name!r}", "SystemSpec.defaults", key, k)
              for key, values in spec.defaults.items() for k in values]
    owners = [("system.name", f"system plug-in {spec.name!r}", "SystemSpec", spec)]
    owners += [(f"{sec}.kind", f"{sec} plug-in {chosen[sec]!r}",
                f"{type(table[chosen[sec]]).__name__}", table[chosen[sec]])
               for sec, table in kinds.items() if chosen[sec] in table]
    for at, who, attr, owner in owners:
        for req in owner.requires:
            section, _, name = req.key.partition(".")
            checks.append((at, who, f"{attr}.requires", section, name))
    out = []
    for at, who, attr, section, key in checks:
        base, _, kind = section.partition(".")
        kind = kind or (chosen.get(base) if base in kinds else "")
        if base in kinds and kind not in kinds[base]:
            continue  # defaults for a kind not installed apply to nothing
        model = kinds[base][kind].settings if base in kinds else _SECTIONS.get(base)
        if model is None:
            out.append(f"{at}: the {who} sets [{section}] in its {attr}, which is no "
                       f"section a plug-in may set (sections: "
                       f"{', '.join([*_SECTIONS, 'planner.<kind>', 'mpc.<kind>'])}); the "
                       f"plug-in must be fixed, not the scenario")
        elif key not in model.model_fields:
            close = difflib.get_close_matches(key, list(model.model_fields), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            out.append(f"{at}: the {who} sets {section}.{key} in its {attr}, which is not a "
                       f"setting of [{section}]{hint}; the plug-in must be fixed, not the "
                       f"scenario")
    return out


def _kind_problems(reg, spec, data: dict) -> list[str]:
    """``planner.kind`` / ``mpc.kind`` lines for a kind the system cannot use.

    A kind needs capabilities the system does not provide, or the system or the other
    plug-in requires another kind.
    """
    out = []
    required = {r.key: r for r in _requirements(reg, data)}
    for section, table in (("planner", reg.planners), ("mpc", reg.mpcs)):
        kind = _chosen_kind(data, section)
        if kind not in table:
            continue  # an unknown kind (or not a name) is the union's error
        req = required.get(f"{section}.kind")
        missing = sorted(table[kind].needs - spec.provides)
        if missing:
            out.append(f"{section}.kind: {kind!r} does not fit system {spec.name!r}: it "
                       f"needs {', '.join(missing)} (use {getattr(spec, section)!r})")
        elif req is not None and req.value != kind:
            out.append(f"{section}.kind: {req.why}; use {req.value!r}, not {kind!r}")
    return out


def _requirements(reg, data: dict) -> list[Requirement]:
    """Settings required by the scenario's system, planner and MPC plug-ins."""
    out = list(reg.system(data["system"]["name"]).requires)
    for section, table in (("planner", reg.planners), ("mpc", reg.mpcs)):
        kind = _chosen_kind(data, section)
        if kind in table:
            out += table[kind].requires
    return out


def _chosen_kind(data: dict, section: str) -> str | None:
    """The ``kind`` a scenario's ``planner`` / ``mpc`` table names (None: none, or not text)."""
    kind = data[section].get("kind") if isinstance(data.get(section), dict) else None
    return kind if isinstance(kind, str) else None


def _union(models: list[type[BaseModel]], tag: str) -> Any:
    if len(models) == 1:
        return models[0]
    return Annotated[Union[tuple(models)], Field(discriminator=tag)]  # noqa: UP007


@lru_cache(maxsize=1)
def scenario_model() -> type[ScenarioBase]:
    """The Scenario model with the registered plug-ins' sections (built once)."""
    reg = registry()
    default = reg.systems.get(DEFAULT_SYSTEM) or next(iter(reg.systems.values()))
    for what, kind, table in (("planner", default.planner, reg.planners),
                              ("mpc", default.mpc, reg.mpcs)):
        if kind not in table:  # e.g. a plug-in registered under a bundled kind's name
            raise PluginError(f"{what} {kind!r}, the default of system {default.name!r}, "
                              f"cannot be used: {reg.failure(what, kind) or 'not registered'}")
    planner = reg.planners[default.planner].settings
    mpc = reg.mpcs[default.mpc].settings
    model = create_model(
        "Scenario", __base__=ScenarioBase, __module__=__name__,
        system=(_union([s.params for s in reg.systems.values()], "name"),
                Field(default_factory=default.params)),
        planner=(_union([p.settings for p in reg.planners.values()], "kind"),
                 Field(default_factory=planner)),
        mpc=(_union([m.settings for m in reg.mpcs.values()], "kind"),
             Field(default_factory=mpc)),
    )
    model.model_rebuild(_types_namespace=globals())
    return model


def _tags() -> dict[str, set[str]]:
    """Union member tags pydantic puts in error locations, per section."""
    reg = registry()
    return {"system": set(reg.systems), "planner": set(reg.planners), "mpc": set(reg.mpcs)}


def __getattr__(name: str) -> Any:
    if name == "Scenario":
        return scenario_model()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _whole(v: float) -> bool:
    return abs(v - round(v)) < 1e-9 * max(1.0, abs(v))


def apply_overrides(data: dict, overrides: list[str], source: str) -> dict:
    """Applies ``key.path=value`` overrides (value parsed as TOML, else a string).

    A table value (``mpc={rate_hz=20}``) is merged into the table already there, key by
    key and table by table (the keys it does not name keep their values); any other value
    replaces what was there. A problem is reported as ``--set 'item': reason`` (the
    ``--set`` is at fault, not ``source``, the scenario file).
    """
    errors = []
    for item in overrides:
        key, sep, raw = item.partition("=")
        if printable(item) != item:  # a scenario is UTF-8 text, and so is its log
            errors.append(f"--set '{printable(item)}': holds bytes that are not UTF-8 "
                          "text (shown as \\xNN); give the value in UTF-8")
            continue
        if not sep or not key.strip():
            errors.append(f"--set {item!r}: expected key.path=value")
            continue
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError as exc:
            if raw.strip()[:1] in ("[", "{", '"', "'"):  # TOML syntax, not a bare word
                errors.append(f"--set {shown_item(item)}: the value is not valid TOML ({exc}); "
                              "a text value needs no quotes, an array [a, b], a table "
                              "{k = v}")
                continue
            value = raw
        except RecursionError:
            errors.append(f"--set {shown_item(item)}: the value is nested too deeply (more "
                          f"than {MAX_DEPTH} levels)")
            continue
        if nesting(value) > MAX_DEPTH:
            errors.append(f"--set {shown_item(item)}: the value is nested too deeply (more "
                          f"than {MAX_DEPTH} levels)")
            continue
        node = data
        parts = [p.strip() for p in key.strip().split(".")]  # TOML: "sim . duration" too
        if not all(parts):  # "sim..duration", ".sim", "sim."
            errors.append(f"--set {shown_item(item)}: {key.strip()!r} has an empty part: "
                          "the key is dotted names, e.g. sim.duration")
            continue
        for i, part in enumerate(parts[:-1]):
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                at, text = ".".join(parts[:i + 1]), _cut(_toml_value(nxt))
                errors.append(f"--set {shown_item(item)}: {at} is a value ({text}), not a "
                              f"table, so {'.'.join(parts)} names no key: set {at} itself")
                break
            node = nxt
        else:
            old = node.get(parts[-1])
            node[parts[-1]] = merged(old, value) if isinstance(old, dict) else value
    if errors:
        raise ScenarioError(errors)
    return data


def shown_item(item: str, width: int = 60) -> str:
    """A ``--set`` item for a message: quoted, a long one cut to ``width`` characters."""
    return repr(item) if len(item) <= width else repr(item[:width]) + "..."


def merged(base: Any, value: Any) -> Any:
    """``value`` merged into ``base``: tables key by key (recursively), else ``value``."""
    if not isinstance(base, dict) or not isinstance(value, dict):
        return value
    out = dict(base)
    for k, v in value.items():
        out[k] = merged(out.get(k), v)
    return out


#: deepest nesting of tables and arrays a scenario may have (its own are 3 levels deep)
MAX_DEPTH = 32


def nesting(value: Any) -> int:
    """How deeply tables and arrays nest in ``value`` (a scalar: 0), without recursion."""
    deepest, todo = 0, [(value, 0)]
    while todo:
        v, depth = todo.pop()
        if isinstance(v, dict):
            todo += [(x, depth + 1) for x in v.values()]
        elif isinstance(v, (list, tuple)):
            todo += [(x, depth + 1) for x in v]
        else:
            deepest = max(deepest, depth)
            continue
        deepest = max(deepest, depth + 1)
        if deepest > MAX_DEPTH:
            break
    return deepest


#: most keys :func:`unknown_key` lists when none is close to the unknown one
LISTED_KEYS = 16


def unknown_key(key: Any, allowed: list[str]) -> str:
    """``unknown key``, with ``(did you mean 'x'?)`` when an allowed key is close to it.

    With none close, the allowed keys (up to :data:`LISTED_KEYS` of them; beyond, their
    number and where they are listed).
    """
    hint = did_you_mean(key, allowed)
    if hint or not allowed:
        return "unknown key" + hint
    if len(allowed) > LISTED_KEYS:
        return (f"unknown key (none of the {len(allowed)} keys here is close: `hmpc schema` "
                "lists them)")
    return f"unknown key (the keys here: {', '.join(allowed)})"


def _not_a_table(kind: str, loc: str, given: Any, msg: str) -> str:
    """A section or table given as another kind of value: how to write it as a table.

    ``msg`` unchanged for other errors (``kind``: pydantic's error type).
    """
    if kind not in ("model_type", "dict_type"):
        return msg
    if isinstance(given, list) and given and all(isinstance(g, dict) for g in given):
        return (f"an array of tables ([[{loc}]]), not one table: write [{loc}] once, "
                "its keys below it")
    text = _cut(_toml_value(given)) if isinstance(given, bool | int | float | str | list) \
        else type(given).__name__
    return (f"must be a table of settings, not {text}: write [{loc}] with its keys below "
            f"it, or {loc} = {{key = value, ...}}")


def _field_names(models: list[type[BaseModel]]) -> list[str]:
    """The keys a section accepts: its models' field names (aliases where they have one)."""
    return sorted({f.alias or name for m in models for name, f in m.model_fields.items()})


def _members(ann: Any) -> list[Any]:
    """An annotation's alternatives (the members of a union; ``Annotated`` unwrapped)."""
    if typing.get_origin(ann) is Annotated:
        return _members(typing.get_args(ann)[0])
    if typing.get_origin(ann) in (Union, types.UnionType):
        return [m for a in typing.get_args(ann) for m in _members(a)]
    return [ann]


def _tag_of(model: type[BaseModel]) -> set[Any]:
    """The literal values of a model's fields (a union member's discriminator tags)."""
    out: set[Any] = set()
    for f in model.model_fields.values():
        if typing.get_origin(f.annotation) is typing.Literal:
            out.update(typing.get_args(f.annotation))
    return out


def models_at(model: Any, loc: tuple | list) -> list[type[BaseModel]]:
    """The settings models at an error location of ``model`` (empty: not a section).

    A location walks fields by name, list items by index, dict values by key and the
    member of a discriminated union by its tag (pydantic puts the tag in the location).
    """
    anns, parts = [model], list(loc)
    while parts:
        part = parts.pop(0)
        members = [m for a in anns for m in _members(a)]
        models = [m for m in members if isinstance(m, type) and issubclass(m, BaseModel)]
        tagged = [m for m in models if len(models) > 1 and part in _tag_of(m)]
        if tagged:
            anns = tagged
            continue
        nxt = []
        for m in members:
            if isinstance(m, type) and issubclass(m, BaseModel):
                nxt += [f.annotation for name, f in m.model_fields.items()
                        if part in (name, f.alias)]
            elif typing.get_origin(m) in (list, tuple) and isinstance(part, int):
                nxt += list(typing.get_args(m)[:1])
            elif typing.get_origin(m) is dict and isinstance(part, str):
                nxt += list(typing.get_args(m)[1:2])
        if not nxt:
            return []
        anns = nxt
    members = [m for a in anns for m in _members(a)]
    return [m for m in members if isinstance(m, type) and issubclass(m, BaseModel)]


def format_errors(exc: ValidationError, source: str, model: Any = None) -> list[str]:
    """One ``file: key.path: reason`` line per pydantic error.

    An unknown key's line suggests the closest key of its section (``(did you mean
    'rate_hz'?)``); the section's keys are those of ``model`` (default: the scenario
    model when ``exc`` is the scenario's), for a union section those of the member given.
    """
    lines, tags = [], _tags()
    if model is None and exc.title == "Scenario":
        model = scenario_model()
    errors = _tuple_lengths(exc.errors(), model)
    if any(e["loc"][:1] == ("system",) for e in errors):  # the kinds follow the system's
        errors = [e for e in errors if e["type"] != "union_tag_not_found"]
    for err in errors:
        parts = [p for p in err["loc"] if p not in ("function-after",)]
        if len(parts) >= 2 and parts[1] in tags.get(str(parts[0]), ()):
            del parts[1]  # the union member's tag (e.g. planner.cem.samples -> planner.samples)
        loc = key_path(parts) or "(top)"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "union_tag_invalid":  # a kind that failed to load says why
            ctx, section = err.get("ctx") or {}, str(parts[0]) if parts else ""
            why = registry().failure(section, str(ctx.get("tag"))) \
                if section in registry().failed else None
            msg = why or _tag_text(ctx, msg)
        given = err.get("input")
        if err["type"] == "string_type" and isinstance(given, int | float) \
                and not isinstance(given, bool):
            msg += f' (a number here; text is quoted in TOML: "{given}")'
        msg += (_unquoted_hint(err["type"], given) + _given_value(err["type"], given)
                + _container_hint(err["type"], given))
        if err["type"] in ("literal_error", "enum") and isinstance(given, str):
            msg += did_you_mean(given, re.findall(r"'([^']*)'", str(
                (err.get("ctx") or {}).get("expected", ""))))
        if err["type"] == "extra_forbidden":
            raw = [p for p in err["loc"] if p not in ("function-after",)]
            allowed = _field_names(models_at(model, raw[:-1])) if model is not None else []
            msg = unknown_key(raw[-1], allowed)
        msg = _not_a_table(err["type"], loc, given, msg)
        if not err["loc"] and err["type"] == "value_error":  # Scenario._rates: own key paths
            lines += [f"{source}: {m}" for m in msg.split("\n")]
            continue
        lines.append(f"{source}: {loc}: {msg}")
    return lines


def _plant_error(err: dict, params: Any) -> str:
    """``plant.key: reason`` of one pydantic error of a system's ``params`` given as [plant]."""
    msg = err["msg"].removeprefix("Value error, ") + _given_value(err["type"], err.get("input"))
    if err["type"] == "extra_forbidden":
        msg = unknown_key(err["loc"][-1], _field_names([params]))
    loc = key_path(['plant', *err['loc']])
    return f"{loc}: {_not_a_table(err['type'], loc, err.get('input'), msg)}"


def _tuple_lengths(errors: list[dict], model: Any) -> list[dict]:
    """The errors pydantic gives, those of a tuple of the wrong length as one per tuple.

    A tuple too short is one ``missing`` error per absent item (``system.x0[3]: Field
    required``), one too long a ``too_long`` error: both become one error at the tuple,
    ``needs 4 numbers, got 3``, with the field's description when it has one (its items'
    names, its units).
    """
    out, seen = [], set()
    for err in errors:
        loc, given = tuple(err["loc"]), err.get("input")
        ctx = err.get("ctx") or {}
        if err["type"] == "missing" and loc and isinstance(loc[-1], int) \
                and isinstance(given, list | tuple):
            at = loc[:-1]
            need = 1 + max(e["loc"][-1] for e in errors if e["type"] == "missing"
                           and tuple(e["loc"][:-1]) == at and isinstance(e["loc"][-1], int))
        elif err["type"] == "too_long" and ctx.get("field_type") == "Tuple" \
                and isinstance(given, list | tuple):
            at, need = loc, ctx.get("max_length")
        else:
            out.append(err)
            continue
        if at in seen:
            continue
        seen.add(at)
        out.append({**err, "type": "tuple_length", "loc": at,
                    "msg": _length_text(model, at, need, len(given))})
    return out


def _length_text(model: Any, loc: tuple, need: int, got: int) -> str:
    """``needs 4 numbers, got 3 (the field's description)`` for the tuple at ``loc``."""
    fields = [f for m in (models_at(model, loc[:-1]) if model is not None and loc else [])
              for name, f in m.model_fields.items() if loc[-1] in (name, f.alias)]
    items = [typing.get_args(t) for f in fields for t in _members(f.annotation)
             if typing.get_origin(t) is tuple]  # an optional tuple's too
    numbers = bool(items) and all(
        m in (int, float) for args in items for a in args for m in _members(a))
    text = f"needs {need} {'numbers' if numbers else 'items'}, got {got}"
    desc = next((f.description for f in fields if f.description), None)
    return f"{text} ({desc})" if desc else text


#: pydantic's error type of a value of the wrong type -> (the types it wants, their name)
_WANTED = {"int_type": ((int,), "an integer"), "float_type": ((int, float), "a number"),
           "bool_type": ((bool,), "a boolean")}


#: pydantic errors whose message does not show the value given
_VALUE_NOT_SHOWN = frozenset({"greater_than", "greater_than_equal", "less_than",
                              "less_than_equal", "string_pattern_mismatch", "int_from_float",
                              "string_too_long", "too_long", "too_short", "literal_error",
                              "enum"})


def _given_value(kind: str, given: Any) -> str:
    """`` (got -1)`` for a bound or pattern error's number or text (to 40 characters).

    '' for other errors and values.
    """
    if kind not in _VALUE_NOT_SHOWN or isinstance(given, bool) \
            or not isinstance(given, int | float | str):
        return ""
    return f" (got {_cut(_toml_value(given))})"


def _cut(text: str, width: int = 40) -> str:
    """``text`` for a message: one longer than ``width`` characters cut, with "..."."""
    return text if len(text) <= width else text[:width - 3] + "..."


def _container_hint(kind: str, given: Any) -> str:
    """`` (got a table: this key takes one value)`` for a container where a value is wanted.

    A table or an array where a number, a boolean or text is wanted; a table where an
    array is (`` (got a table: write an array, ...)``); '' else.
    """
    what = "a table" if isinstance(given, dict) else "an array" if isinstance(given, list) \
        else None
    if what is None:
        return ""
    if kind in ("tuple_type", "list_type"):
        return " (got a table: write an array, [a, b, ...])" if what == "a table" else ""
    if kind in _WANTED or kind == "string_type":
        return f" (got {what}: this key takes one value)"
    return ""


def _unquoted_hint(kind: str, given: Any) -> str:
    """`` (text here; a number is written without quotes in TOML: 600)`` for ``"600"``.

    When a number or boolean setting is given text that, unquoted, is a value of the
    wanted type ('' otherwise).
    """
    if kind not in _WANTED or not isinstance(given, str):
        return ""
    types, what = _WANTED[kind]
    if "\n" in given or "\r" in given or "#" in given:  # one value, written on one line
        return ""
    try:
        parsed = tomllib.loads(f"v = {given.strip()}")
    except (tomllib.TOMLDecodeError, RecursionError):
        return ""
    if list(parsed) != ["v"]:
        return ""
    value = parsed["v"]
    ok = isinstance(value, types) and (kind == "bool_type" or not isinstance(value, bool))
    if not ok or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    return f" (text here; {what} is written without quotes in TOML: {given.strip()})"


def _tag_text(ctx: dict, msg: str) -> str:
    """An unknown ``kind`` (a union's tag) with its choices and the closest one."""
    tag, expected = ctx.get("tag"), ctx.get("expected_tags")
    if tag is None or not expected:
        return msg
    choices = [c.strip().strip("'") for c in str(expected).split(",")]
    close = difflib.get_close_matches(str(tag), choices, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"unknown kind {str(tag)!r}{hint}; choose from {', '.join(map(repr, choices))}"


def key_path(parts: list) -> str:
    """``['system', 'x0', 3]`` -> ``'system.x0[3]'``."""
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def load_scenario(path: str | Path, overrides: list[str] = (), seed: int | None = None,
                  check_margins: bool = True, attribute_sets: bool = True,
                  ) -> tuple[ScenarioBase, str]:
    """Reads, overrides and validates a scenario file.

    A margins file (``mpc.margins``) is resolved against the scenario file's directory
    (the effective TOML holds the absolute path, so a sweep worker or a rerun of the run
    directory's copy finds it) and, with ``check_margins``, checked against the scenario
    (its system, parameters and MPC rate; ``hmpc tube`` skips the check: it writes them).
    Every problem is reported at once; with ``attribute_sets`` a problem with a key an
    override set is attributed to ``--set key=value`` rather than to the file, and one
    with the seed given here to ``--seed N``.

    Returns:
        The scenario and the effective TOML text (after overrides).

    Raises:
        ScenarioError: missing or empty file, TOML syntax error or invalid settings.
    """
    path = Path(path)
    raw = _read_toml(path)

    def effective(items: list[str]) -> dict:
        data = apply_overrides(copy.deepcopy(raw), items, str(path))
        if seed is not None:
            data["seed"] = seed
        data.setdefault("name", re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem))
        return data

    def caused(item: str, key: str) -> bool:
        """Whether the problem with ``key`` goes away without ``--set item``.

        Not when the file's own value of what the ``--set`` sets is wrong too: the
        ``--set`` then repairs the file (which is at fault) rather than breaking it.
        """
        try:
            lines = _problems(effective([o for o in overrides if o is not item]), str(path))
        except (ScenarioError, PluginError, ValueError, TypeError):
            return True
        keys = {line.removeprefix(f"{path}: ").partition(": ")[0] for line in lines}
        return key not in keys and not keys & set(_set_keys(item))

    def blame(lines: list[str], confirm=None) -> list[str]:
        lines = attribute_to_sets(lines, str(path), overrides, attribute_sets, confirm)
        return _attribute_to_seed(lines, str(path), seed if attribute_sets else None)

    data = effective(list(overrides))
    try:
        scenario = scenario_model().model_validate(data)
    except ValidationError as exc:
        lines = (format_errors(exc, str(path)) + _hidden_problems(data, str(path))
                 + _cross_field_problems(data, exc, str(path)))
        lines = other_kind_of_file(raw, str(path), "scenario") or lines  # a sweep's: alone
        raise ScenarioError(blame(list(dict.fromkeys(lines)), caused)) from None
    except PluginError as exc:
        raise ScenarioError(blame([f"{path}: {exc}"])) from None
    problems = _resolve_margins(scenario, path, check_margins)
    if problems:
        raise ScenarioError(blame([f"{path}: mpc.margins: {p}" for p in problems]))
    return scenario, effective_toml(scenario)


def other_kind_of_file(data: dict, source: str, expected: str) -> list[str]:
    """The line naming the command that takes a file of the other kind, or none.

    ``expected``: ``"scenario"`` (``data`` may be a sweep file's) or ``"sweep"`` (a
    scenario's).
    """
    keys = set(data)
    if expected == "scenario" and {"scenario", "seeds"} <= keys and keys & {"grid", "set"}:
        return [f"{source}: this looks like a sweep file (it has scenario, seeds and a grid "
                f"or set): run it with `hmpc sweep {source}`"]
    if expected == "sweep" and {"system", "mpc"} <= keys and "scenario" not in keys:
        return [f"{source}: this looks like a scenario file (it has system and mpc, no "
                f"scenario): run it with `hmpc run {source}`, or name it in a sweep file's "
                "`scenario`"]
    return []


def inert_settings(path: str | Path, overrides: list[str] = (),
                   scenario: ScenarioBase | None = None, attributed: bool = True
                   ) -> list[str]:
    """Settings the file or a ``--set`` gives that the run ignores (a valid scenario's).

    The disturbance's keys its kind does not read and, with the validated ``scenario``,
    the settings another setting of it switches off (:func:`_switched_off`; those of
    :data:`SET_ONLY` only when a ``--set`` gives them).
    ``source: key: no effect ...`` lines, ``source`` the ``--set`` when one set the key;
    ``key: no effect ...`` without ``attributed`` (a sweep names its cells instead).
    """
    from hmpc_cli.sim.disturbance import inert_keys

    data = apply_overrides(_read_toml(Path(path)), list(overrides), str(path))
    given = data.get("disturbance") if isinstance(data.get("disturbance"), dict) else {}
    lines = inert_keys(given.get("kind", "none"), given)
    if attributed:
        lines = attribute_to_sets([f"{path}: {line}" for line in lines], str(path),
                                  list(overrides), True)
    if scenario is None:
        return lines
    keys = [(k, item) for item in overrides for k in _set_keys(item)]
    for line in _switched_off(data, scenario):  # the last --set that gave the key, else the file
        key = line.partition(": ")[0]
        given_by = [item for k, item in keys
                    if k == key or k.startswith(f"{key}.") or key.startswith(f"{k}.")]
        source = f"--set {given_by[-1]}" if given_by else None if key in SET_ONLY else path
        if source is not None:
            lines.append(f"{source}: {line}" if attributed else line)
    return lines


#: switched-off settings named only when a ``--set`` gives them: a file may hold them for
#: its runs with another setting (``ball_realtime.toml``'s model for ``sim.latency = "model"``)
SET_ONLY = frozenset({"sim.latency_model"})


def _switched_off(data: dict, sc: ScenarioBase) -> list[str]:
    """``key: no effect with ...`` per setting ``data`` gives (not its default) ``sc`` ignores."""
    policy, latency = sc.replanning.policy, sc.sim.latency
    planner, mpc = sc.planner, sc.mpc
    elites = getattr(planner, "elites", None)  # the CEM planner's (other planners: none)
    rules = [  # (section, key, switched off, why)
        ("replanning", "period", policy != "periodic",
         f'replanning.policy = "{policy}" (only "periodic" replans on a period)'),
        ("replanning", "contact_guards", policy != "on_contact",
         f'replanning.policy = "{policy}" (only "on_contact" replans at contacts)'),
        ("sim", "latency_model", latency != "model",
         (f'sim.latency = "{latency}"' if isinstance(latency, str) else
          f"sim.latency = {latency:g}") + ' (only "model" charges its compute times)'),
        ("planner", "adapt_covariance", elites == 1,
         "planner.elites = 1 (the variance is refitted to two elites or more)"),
        ("planner", "min_cov", elites == 1 or getattr(planner, "adapt_covariance", True)
         is False, ("planner.elites = 1" if elites == 1 else
                    "planner.adapt_covariance = false") + " (the floor of a refitted "
         "variance)"),
        *(("mpc", key, getattr(mpc, "margins", "hand") != "hand",
           f'mpc.margins = "{getattr(mpc, "margins", "")}" (its margins replace the '
           'hand-set ones)') for key in ("tube_margin", "input_margin"))]
    return [f"{section}.{key}: no effect with {why}" for section, key, off, why in rules
            if off and isinstance(data.get(section), dict) and key in data[section]
            and not _is_default(getattr(sc, section), key)]


def _is_default(settings: Any, key: str) -> bool:
    """Whether a settings model's ``key`` holds its default.

    A run's recorded scenario, and ``hmpc sweep --show``'s, write every default out.
    """
    field = type(settings).model_fields[key]
    return getattr(settings, key) == field.get_default(call_default_factory=True)


def _attribute_to_seed(lines: list[str], source: str, seed: int | None) -> list[str]:
    """``source: seed: reason`` lines as ``--seed N: seed: reason`` (the option's fault)."""
    if seed is None:
        return lines
    return [f"--seed {seed}: " + line.removeprefix(f"{source}: ")
            if line.startswith(f"{source}: seed: ") else line for line in lines]


def effective_toml(scenario: ScenarioBase) -> str:
    """A validated scenario as the TOML text a run records (unset optional keys left out)."""
    return dump_toml(scenario.model_dump(mode="json", exclude_none=True))


def seeded_toml(scenario: ScenarioBase) -> Callable[[int], str]:
    """``seed -> effective_toml(scenario with that seed)``, its tables written once.

    A sweep cell's runs differ in the seed only, a top-level key, so each run's text is
    the cell's top-level lines with its seed, then the cell's tables, unchanged.
    """
    data = scenario.model_dump(mode="json", exclude_none=True)
    tables = _toml_tables(data)
    top = {k: v for k, v in data.items() if not isinstance(v, dict)}
    return lambda seed: _toml_top({**top, "seed": seed}) + tables


def _problems(data: dict, source: str) -> list[str]:
    """The ``source: key: reason`` lines of scenario data ([] if it is valid)."""
    try:
        scenario_model().model_validate(data)
    except ValidationError as exc:
        return (format_errors(exc, source) + _hidden_problems(data, source)
                + _cross_field_problems(data, exc, source))
    return []


def read_toml_file(path: Path, what: str = "scenario file", src: str | None = None
                   ) -> tuple[str, dict]:
    """A TOML file's text and table, or one :class:`ScenarioError` line saying why not.

    Args:
        path: the file.
        what: what it should be, for the messages ("scenario file", "sweep file").
        src: how the messages name it (default: the path).
    """
    src = str(path) if src is None else src
    if path.is_dir():
        raise ScenarioError([f"{src}: is a directory, not a {what}"])
    if not path.exists():
        raise ScenarioError([f"{src}: a symbolic link to nothing (a missing file, or a loop)"
                             if path.is_symlink() else f"{src}: file not found"])
    if not path.is_file():  # a FIFO or a device: reading it may block forever
        raise ScenarioError([f"{src}: not a regular file"])
    deep = f"{src}: tables or arrays nested too deeply (more than {MAX_DEPTH} levels)"
    try:  # a byte-order mark some editors write is not TOML's: skipped
        text = path.read_text(encoding="utf-8-sig")
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError([f"{src}: TOML syntax error: {exc}"]) from None
    except UnicodeDecodeError:
        raise ScenarioError([f"{src}: not a UTF-8 text file" + _binary_hint(path, what)]) \
            from None
    except RecursionError:
        raise ScenarioError([deep]) from None
    except OSError as exc:  # unreadable (permissions), a FIFO's error, an I/O error
        raise ScenarioError([f"{src}: cannot read it: {exc.strerror or exc}"]) from None
    if nesting(data) > MAX_DEPTH:
        raise ScenarioError([deep])
    return text, data


def _binary_hint(path: Path, what: str) -> str:
    """What a binary file given as a TOML file is, when it is a run log (else '')."""
    try:
        with open(path, "rb") as f:
            magic = f.read(5)
    except OSError:
        return ""
    if magic != b"\x89MCAP":
        return ""
    return (f" (a run log: `hmpc replay {path}` reads it; the {what} of its run is the "
            "scenario.toml beside it)" if what == "scenario file"
            else f" (a run log: `hmpc replay {path}` reads it)")


def _read_toml(path: Path) -> dict:
    """A scenario file's TOML table (raises :class:`ScenarioError`)."""
    _, data = read_toml_file(path)
    if not data:
        raise ScenarioError([f"{path}: file is empty (no settings; write at least "
                             f"[system] name = \"{DEFAULT_SYSTEM}\")"])
    return data


#: sections validated on their own when the system is unknown
_COMMON = ("name", "description", "seed", "sim", "disturbance", "replanning", "lowlevel")


def _hidden_problems(data: dict, source: str) -> list[str]:
    """Problems the first validation could not reach.

    An unknown system stops the plug-in sections from being checked: the common sections
    are then validated on their own (with the default system). ``[plant]`` keys are
    checked against the system's parameters even when other sections are wrong.
    """
    reg = registry()
    system = data.get("system", {})
    if not isinstance(system, dict):
        return []
    name = system.get("name", DEFAULT_SYSTEM)
    if not isinstance(name, str) or name not in reg.systems:
        common = {k: v for k, v in data.items() if k in _COMMON}
        try:
            scenario_model().model_validate(common)
        except ValidationError as exc:
            return [line for line in format_errors(exc, source)
                    if line.split(": ")[1].split(".")[0].split("[")[0] in _COMMON]
        return []
    plant = data.get("plant")
    if not isinstance(plant, dict) or not plant:
        return []
    params = reg.systems[name].params
    base = {k: v for k, v in system.items() if k not in plant}
    try:
        params.model_validate({**base, **plant})
    except ValidationError as exc:
        out = []
        for err in _tuple_lengths(exc.errors(), params):
            if err["loc"] and err["loc"][0] in plant:
                out.append(f"{source}: {_plant_error(err, params)}")
        return out
    return []


def _data_path(loc: tuple, tags: dict[str, set[str]]) -> list:
    """An error location as the path of keys in the scenario's data (no union tags)."""
    parts = [p for p in loc if p not in ("function-after",)]
    if len(parts) >= 2 and parts[1] in tags.get(str(parts[0]), ()):
        del parts[1]
    return parts


def _without(data: dict, path: list) -> tuple[dict, str] | None:
    """A copy of ``data`` without the deepest key of ``path`` it holds, and that key's path.

    An element of a list removes the whole list (a key takes its default when absent).
    """
    keys, node = [], data
    for part in path:
        if not isinstance(part, str) or not isinstance(node, dict) or part not in node:
            break
        keys.append(part)
        node = node[part]
    if not keys:
        return None
    out = node = dict(data)
    for part in keys[:-1]:
        node[part] = dict(node[part])
        node = node[part]
    del node[keys[-1]]
    return out, ".".join(keys)


def _cross_field_problems(data: dict, exc: ValidationError, source: str) -> list[str]:
    """The checks across settings (rates, sizes, plug-in requirements) despite field errors.

    pydantic runs the scenario's cross-field checks only when every field is valid, so
    a file with both kinds of problem would show them one after the other. The wrong
    keys are left out (their defaults taken) and the rest validated again; a problem of
    that check that names a left-out setting, or is in its section, is dropped (it would
    be about the default).
    """
    errors = exc.errors()
    if not errors or any(not e["loc"] for e in errors):  # a whole-scenario problem already
        return []
    tags, removed = _tags(), []
    for err in errors:
        cut = _without(data, _data_path(err["loc"], tags))
        if cut is not None:
            data, key = cut
            if err["type"] != "extra_forbidden":  # an unknown key changes no setting
                removed.append(key)
    try:
        scenario_model().model_validate(data)
    except ValidationError as again:
        found = [e for e in again.errors() if not e["loc"] and e["type"] == "value_error"]
        lines = [line for e in found
                 for line in e["msg"].removeprefix("Value error, ").split("\n")]
    except (PluginError, ValueError, TypeError):
        return []
    else:
        return []
    named = [re.compile(rf"(?<![\w.]){re.escape(k)}(?![\w])") for k in removed]
    sections = {k.split(".")[0] for k in removed}
    return [f"{source}: {line}" for line in lines
            if not any(r.search(line) for r in named) and line.split(".")[0] not in sections]


#: a dotted key path inside a message (``sim.rate_hz``, ``system.x0[2]``)
_KEY_IN_TEXT = re.compile(r"(?<![\w.])[A-Za-z_]\w*(?:\.\w+)+")


def attribute_to_sets(lines: list[str], source: str, overrides: list[str], on: bool,
                      caused: Callable[[str, str], bool] | None = None,
                      anywhere: bool = False) -> list[str]:
    """Re-attributes ``source: key: reason`` lines caused by a ``--set`` to that ``--set``.

    A line is the ``--set``'s when its key is the overridden key or inside it (or, for an
    unknown key, a table the ``--set`` made); when the overridden key is inside the line's
    key (``system.x0: Input should be a valid tuple`` after ``--set system.x0.0=1``;
    without ``caused``, only a direct child the reason names: ``planner: Input tag 'x'
    found using 'kind'``); or when its key or reason names the overridden key
    (``mpc.rate_hz: 10 must divide sim.rate_hz = 7`` after ``--set sim.rate_hz=7``). The
    last such ``--set`` wins. For the last two, ``caused(item, key)`` (if given) must
    confirm it: the problem with ``key`` goes away without that ``--set`` (a ``--set``
    that fixed one rate is not blamed for the file's other rate). With ``anywhere`` (and
    ``caused``), a line none of these match is the last ``--set`` it confirms (the set-up
    checks' ``system.x0: ... lies past guard`` after ``--set system.circle_center=...``);
    without, the file keeps it (its value is at fault, the ``--set`` only made it count).
    """
    if not on or not overrides:
        return lines
    keys, out = [(k, item) for item in overrides for k in _set_keys(item)], []
    for line in lines:
        if not line.startswith(f"{source}: "):
            out.append(line)
            continue
        key, _, reason = line.removeprefix(f"{source}: ").partition(": ")
        unknown = reason.startswith("unknown key")  # an unknown section the --set made
        hit = [item for k, item in keys if key == k or key.startswith((f"{k}.", f"{k}["))
               or (unknown and k.startswith(f"{key}."))]
        if not hit:  # a --set inside the key's table: confirmed by caused, else named
            hit = [item for k, item in keys if k.startswith(f"{key}.") and (
                caused is not None or ("." not in k.removeprefix(f"{key}.") and re.search(
                    rf"(?<![\w.]){re.escape(k.rpartition('.')[2])}(?!\w)", reason)))]
            if not hit:
                named = set(_KEY_IN_TEXT.findall(f"{key} {reason}"))
                hit = [item for k, item in keys if k in named]
            hit = [item for item in dict.fromkeys(hit) if caused is None or caused(item, key)]
            if not hit and anywhere and caused is not None:  # the --set it goes away without
                hit = [item for item in dict.fromkeys(i for _, i in keys) if caused(item, key)]
        out.append(f"--set {hit[-1]}: " + line.removeprefix(f"{source}: ") if hit else line)
    return out


def _set_keys(item: str) -> list[str]:
    """The keys a ``--set`` item sets: its key, or a table's leaves (merged key by key)."""
    key, _, raw = item.partition("=")
    key = key.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except (tomllib.TOMLDecodeError, RecursionError):
        return [key]
    out, todo = [], [(key, value)]
    while todo:
        k, v = todo.pop()
        if isinstance(v, dict) and v:
            todo += [(f"{k}.{kk}", vv) for kk, vv in v.items()]
        else:
            out.append(k)
    return out


def _resolve_margins(scenario: ScenarioBase, path: Path, check: bool) -> list[str]:
    """Makes ``mpc.margins`` absolute (relative: to the scenario's directory); its problems.

    A relative file missing there but present in the current directory says so.
    """
    given = scenario.mpc.margins_file()
    file = scenario.mpc.resolve_margins_file(path.parent)
    if file is None or not check:  # hand or tube ("tube": computed when the run is built)
        return []
    from hmpc_cli.tube.margins_file import margins_problems

    problems = margins_problems(file, scenario.system, scenario.mpc.rate_hz)
    here = Path(given) if given is not None else None
    if problems and not file.exists() and here is not None and not here.is_absolute() \
            and here.is_file():
        problems[0] += (f" (a relative mpc.margins is read from the scenario file's "
                        f"directory; {given} is in the current directory: name it "
                        f"{os.path.relpath(here.resolve(), file.parent.resolve())!r} or by "
                        f"its absolute path)")
    return problems


def margins_file_warnings(scenario: ScenarioBase) -> list[str]:
    """``mpc.margins: reason`` when a loaded scenario's margins file is another setting's tube.

    The file fits (:func:`load_scenario` checked system, parameters and rate) but was
    computed for a smaller disturbance box, without this scenario's plant, or for other
    low-level gains
    (:func:`hmpc_cli.tube.margins_file.margins_warnings`); [] otherwise.
    """
    source = scenario.mpc.margins_file()
    if source is None:
        return []
    from hmpc_cli.run.tube_margins import plant_difference
    from hmpc_cli.tube.margins_file import margins_warnings, params_hash

    d, low = scenario.disturbance, scenario.lowlevel
    world, differs = plant_difference(scenario)
    plant = (params_hash(world), differs) if world is not None else None
    return [f"mpc.margins: {line}" for line in
            margins_warnings(Path(source), d.kind, d.magnitude, low.kp, low.kd, plant)]


def dump_toml(data: dict) -> str:
    """Minimal TOML writer for scenario dictionaries (tables, scalars, arrays)."""
    return _toml_top(data) + _toml_tables(data)


def _toml_value(v) -> str:
    """One value as TOML (inline tables for dictionaries)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):  # TOML basic string (no surrogate-pair \u escapes, DEL escaped)
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_value(str(k))} = {_toml_value(x)}"
                               for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _toml_top(data: dict) -> str:
    """The top-level (non-table) keys of :func:`dump_toml`'s text."""
    return "\n".join(f"{k} = {_toml_value(v)}" for k, v in data.items()
                     if not isinstance(v, dict)) + "\n"


def _toml_tables(data: dict) -> str:
    """The ``[table]`` sections of :func:`dump_toml`'s text, in the data's order."""
    return "".join(f"\n[{k}]\n" + "".join(f"{kk} = {_toml_value(vv)}\n" for kk, vv in v.items())
                   for k, v in data.items() if isinstance(v, dict))
