"""Scenario files: pydantic v2 models in TOML, each layer owning its settings section.

Unknown keys are rejected; rates are integers in Hz and must be commensurate (the MPC
period a whole number of node steps and of simulator steps). :func:`load_scenario` turns
every problem into :class:`ScenarioError` lines of the form ``file: key.path: reason``.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from hmpc_cli.lowlevel import LowLevelSettings
from hmpc_cli.mpc.nlp import MPCSettings
from hmpc_cli.mpc.walking_nlp import WalkingMPCSettings
from hmpc_cli.planner.cem import CEMSettings
from hmpc_cli.planner.footholds import FootholdSettings
from hmpc_cli.systems import BallParams, BipedParams

SystemSection = Annotated[BallParams | BipedParams, Field(discriminator="name")]
PlannerSection = Annotated[CEMSettings | FootholdSettings, Field(discriminator="kind")]
MPCSection = Annotated[MPCSettings | WalkingMPCSettings, Field(discriminator="kind")]
#: per system: the planner and MPC kinds its controller stack uses (the section defaults)
STACKS = {"ball": ("cem", "fixed_mode"), "biped": ("footholds", "walking")}
#: per system: defaults of other sections' keys (section, key, value) its stack needs
STACK_DEFAULTS = {"biped": (("sim", "input_at_events", "recompute"),
                            ("replanning", "policy", "on_contact"))}
_TAGS = {"system": set(STACKS), "planner": {"cem", "footholds"},
         "mpc": {"fixed_mode", "walking"}}


class ScenarioError(Exception):
    """Invalid scenario input; ``lines`` holds one message per problem."""

    def __init__(self, lines: list[str]) -> None:
        super().__init__("\n".join(lines))
        self.lines = lines


class SimSettings(BaseModel):
    """Simulator settings."""

    model_config = ConfigDict(extra="forbid")
    rate_hz: int = Field(600, gt=0, description="fixed RK4 step rate [Hz]")
    duration: float = Field(3.0, gt=0.0, description="simulated time [s]")
    max_events_per_step: int = Field(10, ge=1, description="more is Zeno chattering")
    event_time_tol: float = Field(1e-10, gt=0.0, description="event time bracket [s]")
    divergence_bound: float = Field(1e6, gt=0.0, description="|x| beyond this is divergence")
    log_rate_hz: int = Field(100, gt=0, description="state logging rate [Hz]")
    input_at_events: Literal["hold", "recompute"] = Field(
        "hold", description="after a reset inside a step: hold the step's input (the "
        "paper's ball) or let the controllers react at the event time and compute a new "
        "input for the rest of the step (needed when a reset relabels the inputs: biped)")


class DisturbanceSettings(BaseModel):
    """Disturbance w(t) (added to the flow, eq. (1))."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["none", "box", "paper_fig3"] = "none"
    magnitude: float = Field(10.0, ge=0.0, description="uniform box half-width per channel")
    hold: float = Field(0.05, gt=0.0, description="hold period [s] (box)")
    trial: int = Field(1, ge=1, le=10, description="paper_fig3 trial 1..10")


class ReplanSettings(BaseModel):
    """When the hybrid MPC (planner) runs again."""

    model_config = ConfigDict(extra="forbid")
    policy: Literal["once", "on_contact", "periodic"] = "once"
    period: float = Field(0.5, gt=0.0, description="replanning period [s] (periodic)")
    contact_guards: list[str] | None = Field(
        None, description="guards that trigger on_contact (default: all not entering the "
                          "final domain)")


class Scenario(BaseModel):
    """A complete experiment: system, simulator, disturbance and the three layers."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field("scenario", pattern=r"^[A-Za-z0-9_.-]+$")
    description: str = ""
    seed: int = Field(0, ge=0)
    system: SystemSection = Field(default_factory=BallParams)
    plant: dict[str, Any] = Field(
        default_factory=dict, description="system parameters of the simulated plant that "
        "differ from the controllers' model, e.g. mass_scale = 1.1 (the biped of Fig. 4)")
    sim: SimSettings = Field(default_factory=SimSettings)
    disturbance: DisturbanceSettings = Field(default_factory=DisturbanceSettings)
    planner: PlannerSection = Field(default_factory=CEMSettings)
    replanning: ReplanSettings = Field(default_factory=ReplanSettings)
    mpc: MPCSection = Field(default_factory=MPCSettings)
    lowlevel: LowLevelSettings = Field(default_factory=LowLevelSettings)

    @model_validator(mode="before")
    @classmethod
    def _section_kinds(cls, data: Any) -> Any:
        """Fills the system name (ball) and the planner/MPC kinds of that system's stack."""
        if not isinstance(data, dict):
            return data
        data = dict(data)
        system = data.get("system", {})
        if isinstance(system, dict):
            system = data["system"] = {"name": "ball", **system}
            if not isinstance(system["name"], str) or system["name"] not in STACKS:
                choices = ", ".join(repr(k) for k in STACKS)
                raise ValueError(f"system.name: unknown system {system['name']!r} (choose "
                                 f"from {choices})")
            defaults = [(key, "kind", kind) for key, kind in
                        zip(("planner", "mpc"), STACKS[system["name"]])]
            for key, name, value in defaults + list(STACK_DEFAULTS.get(system["name"], ())):
                section = data.get(key, {})
                if isinstance(section, dict):
                    data[key] = {name: value, **section}
        return data

    def plant_params(self) -> BallParams | BipedParams:
        """The simulated plant's parameters: the system's, updated by ``plant``."""
        return type(self.system).model_validate({**self.system.model_dump(), **self.plant})

    @model_validator(mode="after")
    def _rates(self) -> Scenario:
        # One "key.path: reason" line per problem (format_errors splits them).
        m, s = self.mpc, self.sim
        problems = self._stack_problems()
        steps = (("sim.rate_hz", s.rate_hz),) if isinstance(m, WalkingMPCSettings) else (
            ("mpc.nodes_per_second", m.nodes_per_second), ("sim.rate_hz", s.rate_hz))
        divides = [f"{k} = {v}" for k, v in steps if v % m.rate_hz]
        if divides:
            what = "simulator steps" if len(steps) == 1 else \
                "node steps and of simulator steps"
            problems.append(f"mpc.rate_hz: {m.rate_hz} must divide " + " and ".join(divides)
                            + f" (the MPC period must be a whole number of {what})")
        if s.rate_hz % s.log_rate_hz:
            problems.append(f"sim.log_rate_hz: {s.log_rate_hz} must divide sim.rate_hz = "
                            f"{s.rate_hz}")
        if not _whole(s.duration * s.rate_hz):
            problems.append("sim.duration: must be a whole number of simulator steps")
        if self.disturbance.kind == "box" and not _whole(self.disturbance.hold * s.rate_hz):
            problems.append("disturbance.hold: must be a whole number of simulator steps")
        if self.replanning.policy == "periodic" and not _whole(self.replanning.period * s.rate_hz):
            problems.append("replanning.period: must be a whole number of simulator steps")
        if isinstance(m, MPCSettings) and (m.horizon * m.nodes_per_second < 2
                                           or not _whole(m.horizon * m.nodes_per_second)):
            problems.append("mpc.horizon: must be a whole number (>= 2) of node steps")
        if problems:
            raise ValueError("\n".join(problems))
        return self

    def _stack_problems(self) -> list[str]:
        """The system, planner and MPC must belong to one controller stack; plant keys
        must be valid system parameters."""
        out = []
        name = self.system.name
        planner, mpc = STACKS[name]
        if self.planner.kind != planner:
            out.append(f"planner.kind: {self.planner.kind!r} does not fit system {name!r} "
                       f"(use {planner!r})")
        if self.mpc.kind != mpc:
            out.append(f"mpc.kind: {self.mpc.kind!r} does not fit system {name!r} "
                       f"(use {mpc!r})")
        if name == "biped" and self.replanning.policy != "on_contact":
            out.append(f"replanning.policy: the biped chooses its foothold at every contact; "
                       f"use 'on_contact', not {self.replanning.policy!r}")
        if name == "biped" and self.sim.input_at_events != "recompute":
            out.append("sim.input_at_events: the biped's reset swaps the legs, so the torque "
                       "held before it would act on the other leg; use 'recompute'")
        if self.plant:
            try:
                self.plant_params()
            except ValidationError as exc:
                for err in exc.errors():
                    loc = ".".join(["plant", *(str(p) for p in err["loc"])])
                    msg = err["msg"].removeprefix("Value error, ")
                    msg = "unknown key" if err["type"] == "extra_forbidden" else msg
                    out.append(f"{loc}: {msg}")
        return out


def _whole(v: float) -> bool:
    return abs(v - round(v)) < 1e-9 * max(1.0, abs(v))


def apply_overrides(data: dict, overrides: list[str], source: str) -> dict:
    """Applies ``key.path=value`` overrides (value parsed as TOML, else a string)."""
    errors = []
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            errors.append(f"--set {item!r}: expected key.path=value")
            continue
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        node = data
        parts = key.strip().split(".")
        for part in parts[:-1]:
            nxt = node.setdefault(part, {})
            if not isinstance(nxt, dict):
                errors.append(f"--set {item!r}: {part} is not a table")
                break
            node = nxt
        else:
            node[parts[-1]] = value
    if errors:
        raise ScenarioError([f"{source}: {e}" for e in errors])
    return data


def format_errors(exc: ValidationError, source: str) -> list[str]:
    """One ``file: key.path: reason`` line per pydantic error."""
    lines = []
    for err in exc.errors():
        parts = [str(p) for p in err["loc"] if p not in ("function-after",)]
        if len(parts) >= 2 and parts[1] in _TAGS.get(parts[0], ()):
            del parts[1]  # the union member's tag (e.g. planner.cem.samples -> planner.samples)
        loc = ".".join(parts) or "(top)"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        if not err["loc"] and err["type"] == "value_error":  # Scenario._rates: own key paths
            lines += [f"{source}: {m}" for m in msg.split("\n")]
            continue
        lines.append(f"{source}: {loc}: {msg}")
    return lines


def load_scenario(path: str | Path, overrides: list[str] = (), seed: int | None = None
                  ) -> tuple[Scenario, str]:
    """Reads, overrides and validates a scenario file.

    Returns:
        The scenario and the effective TOML text (after overrides).

    Raises:
        ScenarioError: missing file, TOML syntax error or invalid settings.
    """
    path = Path(path)
    if not path.is_file():
        raise ScenarioError([f"{path}: file not found"])
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError([f"{path}: TOML syntax error: {exc}"]) from None
    except UnicodeDecodeError:
        raise ScenarioError([f"{path}: not a UTF-8 text file"]) from None
    data = apply_overrides(data, list(overrides), str(path))
    if seed is not None:
        data["seed"] = seed
    data.setdefault("name", re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem))
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as exc:
        raise ScenarioError(format_errors(exc, str(path))) from None
    return scenario, dump_toml(scenario.model_dump(mode="json", exclude_none=True))


def dump_toml(data: dict) -> str:
    """Minimal TOML writer for scenario dictionaries (tables, scalars, arrays)."""
    import json

    def value(v) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):  # TOML basic string (no surrogate-pair \u escapes, DEL escaped)
            return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{value(str(k))} = {value(x)}" for k, x in v.items()) + "}"
        raise TypeError(f"cannot write {type(v).__name__} to TOML")

    top = [f"{k} = {value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    out = "\n".join(top) + "\n"
    for k, v in data.items():
        if isinstance(v, dict):
            out += f"\n[{k}]\n" + "".join(f"{kk} = {value(vv)}\n" for kk, vv in v.items())
    return out
