"""Registries of systems, planners and fixed-mode MPCs, filled from Python entry points.

A package registers a system by naming a :class:`SystemSpec` object under the entry-point
group ``hmpc.systems`` (planners: ``hmpc.planners`` with a :class:`PlannerSpec`, MPCs:
``hmpc.mpcs`` with an :class:`MPCSpec`); hmpc's own systems, planners and MPCs register
the same way in its ``pyproject.toml``. The scenario's section unions and its JSON schema
are assembled from what is registered (:mod:`hmpc_cli.run.scenario`).

An entry point that fails to load is remembered with its reason: using it raises
:class:`PluginError` naming the entry point; the others still work.

Capabilities (``SystemSpec.provides``, ``needs`` of planners and MPCs) are names (a named
output, or a field of :data:`CAPABILITIES`) or capability types (:data:`CAPABILITY_TYPES`,
e.g. :class:`~hmpc_cli.core.walker.WalkerModel`), kept by their class name.
"""

from __future__ import annotations

import re
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from importlib.metadata import EntryPoint, entry_points
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from hmpc_cli.core.kinds import MPCKindSettings, PlannerSettings
from hmpc_cli.core.walker import WalkerModel

if TYPE_CHECKING:  # the seams' types (no import at run time: the registry loads first)
    from hmpc_cli.core.hybrid import HybridSystem
    from hmpc_cli.core.messages import ConstraintMargins
    from hmpc_cli.core.stack import FixedModeMPC, Planner, Task

GROUPS = {"system": "hmpc.systems", "planner": "hmpc.planners", "mpc": "hmpc.mpcs"}


class PluginError(Exception):
    """A registered plug-in cannot be loaded, built or combined (message names it)."""


#: capabilities that are HybridSystem fields rather than named outputs
CAPABILITIES = frozenset({"terrain", "guard_surfaces", "state_box"})

#: capability types: a system provides one as an instance in the HybridSystem field named
CAPABILITY_TYPES: Mapping[type, str] = MappingProxyType({WalkerModel: "walker"})


def capability_names(items: Iterable[str | type]) -> frozenset[str]:
    """Capabilities by name: a name as given, a :data:`CAPABILITY_TYPES` type by its name.

    Raises:
        TypeError: neither a string nor a capability type.
    """
    out = set()
    for c in items:
        if not isinstance(c, str) and c not in CAPABILITY_TYPES:
            raise TypeError(f"a capability is a name or one of the types "
                            f"{', '.join(t.__name__ for t in CAPABILITY_TYPES)}, not {c!r}")
        out.add(c if isinstance(c, str) else c.__name__)
    return frozenset(out)


def _names_capabilities(spec: Any, attr: str) -> None:
    object.__setattr__(spec, attr, capability_names(getattr(spec, attr)))


@dataclass(frozen=True)
class Requirement:
    """A setting a plug-in needs: ``key`` (a scenario key path) must equal ``value``.

    The value is also the default when the scenario does not set the key.
    """

    key: str
    value: Any
    why: str


@dataclass(frozen=True)
class SystemSpec:
    """A system plug-in.

    Attributes:
        name: the system's name (``system.name`` in a scenario).
        params: pydantic model of its parameters, with a field ``name: Literal[name]``.
        build: params -> :class:`~hmpc_cli.core.hybrid.HybridSystem` (called once per process
            per parameter set).
        task: (params, system) -> :class:`~hmpc_cli.core.stack.Task`; called with the simulated
            plant's parameters and system (success is judged on the world).
        planner: default planner kind.
        mpc: default fixed-mode MPC kind.
        provides: capabilities planners and MPCs may need: named outputs, fields of
            :data:`CAPABILITIES`, capability types (e.g. ``WalkerModel``, then the built
            system's ``walker``); stored by name (:func:`capability_names`).
        requires: settings the system needs (and their defaults).
        defaults: default settings per section for this system: keys ``sim``,
            ``replanning``, ``lowlevel``, ``disturbance`` or ``planner.<kind>`` /
            ``mpc.<kind>`` (those apply only when that kind is used).
    """

    name: str
    params: type[BaseModel]
    build: Callable[[Any], HybridSystem]
    task: Callable[[Any, HybridSystem], Task]
    planner: str
    mpc: str
    provides: frozenset[str | type] = frozenset()
    requires: tuple[Requirement, ...] = ()
    defaults: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _names_capabilities(self, "provides")


@dataclass(frozen=True)
class PlannerSpec:
    """A planner (hybrid MPC) plug-in.

    Attributes:
        kind: ``planner.kind`` in a scenario.
        settings: pydantic model with a field ``kind: Literal[kind]``.
        make: (system, settings, run_seed) -> :class:`~hmpc_cli.core.stack.Planner`.
        needs: system capabilities it uses (names or capability types, stored by name;
            checked against ``SystemSpec.provides``).
        requires: settings it needs (and their defaults).
        detail: the frozen dataclass its ``PlannerResult.detail`` is logged as (the
            /planner/plan ``detail`` field; its JSON schema is generated from it), or
            None (no detail logged).
    """

    kind: str
    settings: type[BaseModel]
    make: Callable[[HybridSystem, Any, int], Planner]
    needs: frozenset[str | type] = frozenset()
    requires: tuple[Requirement, ...] = ()
    detail: type | None = None

    def __post_init__(self) -> None:
        _names_capabilities(self, "needs")


@dataclass(frozen=True)
class MPCSpec:
    """A fixed-mode MPC plug-in (one transcription).

    Attributes:
        kind: ``mpc.kind`` in a scenario.
        settings: pydantic model with fields ``kind: Literal[kind]`` and ``rate_hz``.
        problem: (system, settings, margins) -> the built NLP(s): expensive, built once
            per process per (system, settings, margins) and shared by the controllers
            made from it; ``margins``: a margins file's or the tube's
            :class:`~hmpc_cli.core.messages.ConstraintMargins`, or None (hand margins).
        make: (system, settings, problem) -> :class:`~hmpc_cli.core.stack.FixedModeMPC`.
        needs: system capabilities it uses (as for :class:`PlannerSpec`).
        requires: settings it needs (and their defaults).
        hand_margins: (system, settings) -> the hand-set
            :class:`~hmpc_cli.core.messages.ConstraintMargins` (``margins = "hand"``; logged
            in /run/info); None: the MPC applies no tube margins.
        detail: the frozen dataclass its ``Plan.detail`` is logged as (the /mpc/solve
            ``detail`` field), or None.
    """

    kind: str
    settings: type[BaseModel]
    problem: Callable[[HybridSystem, Any, ConstraintMargins | None], Any]
    make: Callable[[HybridSystem, Any, Any], FixedModeMPC]
    needs: frozenset[str | type] = frozenset()
    requires: tuple[Requirement, ...] = ()
    hand_margins: Callable[[HybridSystem, Any], ConstraintMargins] | None = None
    detail: type | None = None

    def __post_init__(self) -> None:
        _names_capabilities(self, "needs")


@dataclass(frozen=True)
class Registry:
    """Every loaded plug-in by name, and the entry points that failed (name -> reason)."""

    systems: Mapping[str, SystemSpec]
    planners: Mapping[str, PlannerSpec]
    mpcs: Mapping[str, MPCSpec]
    failed: Mapping[str, Mapping[str, str]]

    def system(self, name: str) -> SystemSpec:
        """The system plug-in ``name``.

        Raises:
            PluginError: not registered, or its entry point failed to load.
        """
        return self._get("system", self.systems, name)

    def planner(self, kind: str) -> PlannerSpec:
        """The planner plug-in ``kind`` (raises :class:`PluginError` like :meth:`system`)."""
        return self._get("planner", self.planners, kind)

    def mpc(self, kind: str) -> MPCSpec:
        """The MPC plug-in ``kind`` (raises :class:`PluginError` like :meth:`system`)."""
        return self._get("mpc", self.mpcs, kind)

    def _get(self, what: str, table: Mapping[str, Any], name: str) -> Any:
        if name in table:
            return table[name]
        why = self.failure(what, name)
        if why is not None:
            raise PluginError(why)
        raise PluginError(f"unknown {what} {name!r} (registered: "
                          f"{', '.join(map(repr, sorted(table))) or 'none'})")

    def failure(self, what: str, name: str) -> str | None:
        """Why the plug-in ``name`` of kind ``what`` failed to load, or None.

        Also an entry point under another name whose object is named ``name`` (it must be
        registered under its own name).
        """
        if name in self.failed[what]:
            return self.failed[what][name]
        field = "name" if what == "system" else "kind"
        return next((why for why in self.failed[what].values()
                     if f" registers {field} {name!r}:" in why), None)


def _load(group: str, kind_field: str, spec_type: type) -> tuple[dict, dict]:
    """Loads every entry point of ``group``; returns (specs by name, failures by name).

    A name registered by two different entry points is ambiguous: neither is used and
    using the name reports both.
    """
    specs, failed, values = {}, {}, {}
    for ep in sorted(entry_points(group=group), key=lambda e: (e.name, e.value)):
        if ep.name in values and values[ep.name] != ep.value:
            failed[ep.name] = (f"{kind_field} {ep.name!r} is registered twice in group "
                               f"{group}: {values[ep.name]!r} and {ep.value!r}")
            specs.pop(ep.name, None)
            continue
        values[ep.name] = ep.value
        if ep.name in failed or ep.name in specs:
            continue
        try:
            specs[ep.name] = _load_one(ep, group, kind_field, spec_type)
        except PluginError as exc:
            failed[ep.name] = str(exc)
    return specs, failed


def _load_one(ep: EntryPoint, group: str, kind_field: str, spec_type: type) -> Any:
    """Loads and checks one entry point.

    Raises:
        PluginError: import failure, wrong object, or a name that does not match.
    """
    where = f"entry point {ep.name!r} = {ep.value!r} (group {group})"
    try:
        spec = ep.load()
    except Exception as exc:
        import traceback

        _LOAD_TRACES[where] = "".join(traceback.format_exception(exc))
        raise PluginError(f"{where} failed to load: {type(exc).__name__}: {exc}") from None
    if not isinstance(spec, spec_type):
        raise PluginError(f"{where} is a {type(spec).__name__}, not a {spec_type.__name__}")
    name = getattr(spec, kind_field)
    if name != ep.name:
        raise PluginError(f"{where} registers {kind_field} {name!r}: the entry point "
                          f"must be named after it")
    model = spec.params if kind_field == "name" else spec.settings
    what = "parameters" if kind_field == "name" else "settings"
    label = repr(getattr(model, "__name__", model))
    base = {"hmpc.planners": PlannerSettings, "hmpc.mpcs": MPCKindSettings}.get(group)
    if base is not None and not (isinstance(model, type) and issubclass(model, base)):
        raise PluginError(f"{where}: its settings {label} must subclass "
                          f"hmpc_cli.plugin.{base.__name__} (the hooks hmpc calls)")
    if not (isinstance(model, type) and issubclass(model, BaseModel)):
        raise PluginError(f"{where}: its {what} {label} must be a pydantic model (a "
                          f"subclass of pydantic.BaseModel)")
    if model.model_config.get("extra") != "forbid":
        raise PluginError(f"{where}: its {what} {label} must forbid unknown keys, or a "
                          f"misspelled key in a scenario is silently ignored: set "
                          f"model_config = ConfigDict(extra=\"forbid\")")
    fld = model.model_fields.get(kind_field)
    if fld is None or fld.default != name:
        raise PluginError(f"{where}: {model.__name__} needs a field "
                          f"{kind_field}: Literal[{name!r}] = {name!r}")
    if typing.get_origin(fld.annotation) is not typing.Literal \
            or typing.get_args(fld.annotation) != (name,):
        shown = getattr(fld.annotation, "__name__", None) or repr(fld.annotation)
        section = {"hmpc.systems": "system", "hmpc.planners": "planner"}.get(group, "mpc")
        raise PluginError(f"{where}: {model.__name__}.{kind_field} must be "
                          f"Literal[{name!r}] = {name!r}, not {shown} (a scenario's "
                          f"[{section}] section is told apart by it)")
    if group == "hmpc.mpcs" and "rate_hz" not in model.model_fields:
        raise PluginError(f"{where}: {model.__name__} needs a field rate_hz (the re-solve "
                          f"rate [Hz] the loop keeps), e.g. rate_hz: int = 10")
    return spec


@lru_cache(maxsize=1)
def registry() -> Registry:
    """Every registered system, planner and MPC (loaded once per process)."""
    systems, f_sys = _load(GROUPS["system"], "name", SystemSpec)
    planners, f_pl = _load(GROUPS["planner"], "kind", PlannerSpec)
    mpcs, f_mpc = _load(GROUPS["mpc"], "kind", MPCSpec)
    if not systems and not f_sys:
        raise PluginError("no system is registered: hmpc is not installed (pip install -e .)")
    return Registry(systems, planners, mpcs,
                    {"system": f_sys, "planner": f_pl, "mpc": f_mpc})


def build_system(params: BaseModel) -> Any:
    """Builds the registered system named by ``params.name``, once per process per params.

    Raises:
        PluginError: the plug-in is missing or its ``build`` fails (reason included).
    """
    return _build_cached(type(params), params.model_dump_json())


@lru_cache(maxsize=32)
def _build_cached(model: type[BaseModel], params_json: str) -> Any:
    params = model.model_validate_json(params_json)
    spec = registry().system(params.name)
    system = plugin_call(f"system: {spec.name!r} failed to build", spec.build, params)
    missing = missing_capabilities(spec.provides, system)
    if missing:
        raise PluginError(f"system: {spec.name!r} declares that it provides "
                          f"{', '.join(missing)}, but its HybridSystem has none")
    return system


def missing_capabilities(names: Iterable[str], system: Any) -> list[str]:
    """The capabilities of ``names`` the built HybridSystem ``system`` lacks, sorted.

    A named output must be in ``system.outputs``; a :data:`CAPABILITIES` field must be
    non-empty; a capability type's field must hold an instance of it.
    """
    typed = {t.__name__: (t, f) for t, f in CAPABILITY_TYPES.items()}
    out = []
    for c in sorted(names):
        if c in typed:
            kind, attr = typed[c]
            ok = isinstance(getattr(system, attr, None), kind)
        elif c in CAPABILITIES:
            ok = bool(getattr(system, c))
        else:
            ok = c in system.outputs
        if not ok:
            out.append(c)
    return out


#: the traceback of each entry point that raised while imported, by its description
_LOAD_TRACES: dict[str, str] = {}


def load_tracebacks(lines: Iterable[str]) -> list[str]:
    """The tracebacks of the entry points that failed to import named in ``lines``.

    (``hmpc run -v`` prints them after the error lines: where in the plug-in to look.)
    """
    text = "\n".join(lines)
    return [tb for where, tb in _LOAD_TRACES.items() if where in text]


def plugin_call(what: str, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)``; any exception becomes a :class:`PluginError` 'what: Type: message'.

    The plug-in's traceback is kept as the error's ``plugin_traceback`` (``hmpc run -v``
    prints it).
    """
    try:
        return fn(*args)
    except PluginError:
        raise
    except Exception as exc:
        import traceback

        err = PluginError(f"{what}: {type(exc).__name__}: {one_line(exc)}")
        err.plugin_traceback = "".join(traceback.format_exception(exc))
        raise err from None


def one_line(exc: BaseException) -> str:
    """An exception's message on one line.

    CasADi's source locations and its trailing paragraphs are left out.
    """
    text = re.sub(r"\S*\.[ch]pp:\d+:\s*", "", str(exc).split("\n\n")[0])
    return " ".join(text.split())
