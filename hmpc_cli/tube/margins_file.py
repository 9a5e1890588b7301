"""Margins files: a tube report's radii and margins per MPC rate, as TOML a scenario names.

``hmpc tube SCENARIO --write PATH`` writes one (:func:`write_margins`); a scenario's
``mpc.margins = "PATH"`` reads it back (:func:`read_margins`, :class:`MarginsFile`) and
:func:`margins_problems` checks that it was computed for the scenario's system, with the
same parameters (:func:`params_hash`), and holds the scenario's MPC rate. Layout::

    # header comment: what computed it
    format = 1
    system = "ball"
    params_hash = "sha256:..."
    ...
    [disturbance]
    kind = "box"
    magnitude = 25.0
    plant = "mass_scale = 1.1"  # only when the simulated plant is not the model: with
    ...                         # plant_hash, plant_mismatch, from_w, eta (format 1 still)
    [rates.10]                  # one table per MPC rate [Hz]
    dt = 0.1                    # [s]
    radius = 0.0123             # diam T(dt) [state norm]
    [rates.10.guards.floor]     # NLP row units
    avoid = ...                 # guard-avoid offset kappa(d, past=False)
    pass_through = ...          # virtual-node offset kappa(d, past=True)
    [rates.10.inputs]
    flight = [0.1, 0.1]         # input-box shrink per side, one per input

Floats are written with ``repr`` (exact round trip); infinities as TOML ``inf``.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from hmpc_cli import __version__
from hmpc_cli.core.messages import ConstraintMargins
from hmpc_cli.tube.report import TubeReport, TubeRow

__all__ = ["FORMAT", "GuardOffsets", "MARK", "MarginsFile", "REFUSED", "RateMargins",
           "constraint_margins", "margins_problems", "margins_text", "margins_warnings",
           "params_hash", "read_margins", "write_margins"]

#: how the message of margins refused at a run's set-up begins (a margins file or a tube
#: that does not fit the scenario, its rate or its NLP); a sweep's table holds the run's
#: reason as ``ValueError: <message>``
REFUSED = "mpc.margins: "

FORMAT = 1
#: the first line of every margins file starts so (``hmpc tube --write`` rewrites only such
#: a file)
MARK = "# hmpc margins file"
_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


class GuardOffsets(BaseModel):
    """One guard's row offsets at a tube radius (NLP row units)."""

    model_config = ConfigDict(extra="forbid")
    radius: float | None = Field(None, ge=0.0, description="the radius d_g the offsets are "
                                 "of (the kinematic radius for a guard on kinematic states)")
    avoid: float = Field(ge=0.0, description="guard-avoid offset kappa(d, past=False) (a "
                         "negative one would loosen the row)")
    pass_through: float = Field(ge=0.0, description="virtual-node offset kappa(d, past=True)")
    formula_holds: bool = Field(True, description="kappa is monotone on [0, d]")


class RateMargins(BaseModel):
    """The tube and its margins at one MPC rate."""

    model_config = ConfigDict(extra="forbid")
    dt: float = Field(gt=0.0, description="MPC period [s]")
    radius: float = Field(ge=0.0, description="tube radius diam T(dt) [state norm]")
    kinematic: float | None = Field(None, ge=0.0, description="kinematic tube "
                                    "int_0^dt diam T(s) ds (none: no kinematic states)")
    bound: str = Field(description="the bound the radius is (prop3 or trivial)")
    zeta: float = Field(ge=0.0, description="the low level's input share")
    guards: dict[str, GuardOffsets] = Field(description="offsets by guard name")
    inputs: dict[str, list[Annotated[float, Field(ge=0.0)]]] = Field(
        description="shrink per side by mode name (a negative one would widen the box)")


class MarginsFile(BaseModel):
    """A margins file read back (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")
    format: Literal[1] = Field(description="the file format (1)")
    hmpc_version: str
    scenario: str
    system: str
    params_hash: str
    rate_hz: float = Field(description="the MPC rate of the scenario it was computed for")
    disturbance: dict[str, str | float]
    lowlevel: dict[str, float]
    region: dict[str, str | int]
    rates: dict[str, RateMargins]

    def at(self, rate_hz: float) -> RateMargins | None:
        """The margins of MPC rate ``rate_hz`` [Hz], or None when the file has none."""
        return next((v for k, v in self.rates.items() if _float(k) == float(rate_hz)), None)


def _float(key: str) -> float:
    try:
        return float(key)
    except ValueError:
        return math.nan


def params_hash(params: BaseModel) -> str:
    """``sha256:<hex>`` of a system's parameters (their sorted JSON dump)."""
    text = json.dumps(params.model_dump(mode="json"), sort_keys=True)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def _key(k: str) -> str:
    return k if _BARE.match(k) else json.dumps(k)


def _val(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(float(v)) if math.isfinite(v) else ("nan" if v != v else
                                                  ("inf" if v > 0 else "-inf"))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_val(x) for x in v) + "]"
    return json.dumps(str(v), ensure_ascii=False)


def _rate_key(rate: float) -> str:
    return str(int(rate)) if float(rate).is_integer() else json.dumps(f"{rate:g}")


def _rate_tables(row: TubeRow) -> list[str]:
    m, k = row.margins, _rate_key(row.rate_hz)
    out = [f"\n[rates.{k}]", f"dt = {_val(row.dt)}  # [s]",
           f"radius = {_val(row.diam)}  # diam T(dt) [state norm]",
           f"bound = {_val(row.bound)}", f"zeta = {_val(m.zeta)}"]
    if row.kinematic is not None:
        out.append(f"kinematic = {_val(row.kinematic)}  # int_0^dt diam T(s) ds")
    for g in m.guards:
        out += [f"\n[rates.{k}.guards.{_key(g.guard)}]", f"radius = {_val(g.radius)}",
                f"avoid = {_val(g.avoid)}",
                f"pass_through = {_val(g.pass_through)}",
                f"formula_holds = {_val(g.monotone)}"]
    out.append(f"\n[rates.{k}.inputs]  # shrink per side, one per input")
    out += [f"{_key(i.mode)} = {_val(list(i.per_side))}" for i in m.inputs]
    return out


def margins_text(report: TubeReport, *, scenario: str, params: BaseModel, kind: str,
                 magnitude: float, samples: int, plant: BaseModel | None = None) -> str:
    """The margins file of a tube report (TOML text with a header comment).

    Args:
        report: the tube analysis (its rows: every tabulated rate).
        scenario: the scenario's name.
        params: the system's parameters (their hash identifies them).
        kind: disturbance kind.
        magnitude: the disturbance box's half-width per channel.
        samples: uniform samples per estimated constant.
        plant: the simulated plant's parameters when they differ from ``params`` (eta then
            holds the mismatch of its flow: recorded in the header and in ``[disturbance]``
            as ``plant``, ``plant_hash``, ``plant_mismatch``, ``from_w`` and ``eta``);
            None: the plant is the model (nothing more is written).
    """
    h = params_hash(params)
    lines = [f"{MARK}, written by hmpc {__version__} (hmpc tube --write)",
             f"# scenario {scenario}: system {report.system} (parameters {h})",
             f"# disturbance {kind}, magnitude {magnitude:g}; low level kp = {report.kp:g}, "
             f"kd = {report.kd:g}",
             *_plant_header(report, plant),
             f"# region: {report.region.note}; {samples} samples per estimated constant",
             "# per MPC rate [Hz]: the tube radius d = diam T(dt) [state norm] and the",
             "# kinematic radius int_0^dt diam T(s) ds; per guard its radius d_g (the",
             "# kinematic one when the guard sees kinematic states only), the guard-avoid",
             "# offset kappa(d_g, past=False) and the pass-through offset kappa(d_g,",
             "# past=True) (NLP row units); per mode the input-box shrink per side.",
             "# Estimates (sampled L_x, L_u, eta), not certificates.",
             f"format = {FORMAT}", f"hmpc_version = {_val(__version__)}",
             f"scenario = {_val(scenario)}", f"system = {_val(report.system)}",
             f"params_hash = {_val(h)}",
             f"rate_hz = {_val(float(report.rate_hz))}  # the scenario's MPC rate",
             "\n[disturbance]", f"kind = {_val(kind)}", f"magnitude = {_val(float(magnitude))}",
             *_plant_keys(report, plant),
             "\n[lowlevel]", f"kp = {_val(float(report.kp))}", f"kd = {_val(float(report.kd))}",
             "\n[region]", f"note = {_val(report.region.note)}", f"samples = {int(samples)}"]
    for row in report.rows:
        lines += _rate_tables(row)
    return "\n".join(lines) + "\n"


def _plant_header(report: TubeReport, plant: BaseModel | None) -> list[str]:
    """The header's plant line ([] when the plant is the model)."""
    if plant is None:
        return []
    d = report.disturbance
    return [f"# plant: {d.plant} (parameters {params_hash(plant)}): eta = {d.eta:.6g} = "
            f"max ||f_plant - f_model|| {d.mismatch:.6g} + the box's {d.from_w:.6g}"]


def _plant_keys(report: TubeReport, plant: BaseModel | None) -> list[str]:
    """``[disturbance]``'s plant keys ([] when the plant is the model)."""
    if plant is None:
        return []
    d = report.disturbance
    return [f"plant = {_val(d.plant)}", f"plant_hash = {_val(params_hash(plant))}",
            f"plant_mismatch = {_val(float(d.mismatch))}  # max ||f_plant - f_model||",
            f"from_w = {_val(float(d.from_w))}  # max ||df_plant/dw|| ||w_max||",
            f"eta = {_val(float(d.eta))}  # plant_mismatch + from_w"]


def write_margins(path: Path, report: TubeReport, **meta) -> None:
    """Writes :func:`margins_text` (keywords ``meta``) to ``path`` (raises OSError)."""
    path = Path(path)
    if path.parent != Path(""):
        path.parent.mkdir(parents=True, exist_ok=True)
    from hmpc_cli.core.paths import write_atomic

    write_atomic(path, margins_text(report, **meta))


def read_margins(path: Path) -> MarginsFile:
    """Reads a margins file.

    Raises:
        ValueError: missing, not TOML, or not a margins file (the message says which).
    """
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path}: a directory, not a margins file")
    if not path.is_file():
        raise ValueError(f"file not found: {path}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        return MarginsFile.model_validate(data)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a TOML file ({exc})") from None
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err["loc"]) or "(top)"
        if err["type"] in ("greater_than_equal", "literal_error"):  # a margins file's value
            raise ValueError(f"{path}: {loc}: {err['msg']} (got {err['input']!r}; hmpc tube "
                             "--write makes the file)") from None
        raise ValueError(f"{path}: not a margins file ({loc}: {err['msg']})") from None


def margins_problems(path: Path, system: BaseModel, rate_hz: float) -> list[str]:
    """Why a margins file does not fit a scenario ([] if it does).

    Args:
        path: the margins file.
        system: the scenario's system parameters (with its ``name``).
        rate_hz: the scenario's MPC rate [Hz].
    """
    try:
        mf = read_margins(path)
    except ValueError as exc:
        return [str(exc)]
    name = getattr(system, "name", "?")
    if mf.system != name:
        return [f"{path} was computed for system {mf.system!r}, not {name!r}"]
    if mf.params_hash != params_hash(system):
        return [f"{path} was computed for other {name} parameters (hash {mf.params_hash}, "
                f"the scenario's {params_hash(system)}): run hmpc tube --write again"]
    row = mf.at(rate_hz)
    if row is None:
        rates = ", ".join(sorted(mf.rates, key=_float))
        return [f"{path} has no margins for mpc.rate_hz = {rate_hz:g} (rates: {rates})"]
    values = [row.radius, *[v for g in row.guards.values() for v in (g.avoid, g.pass_through)],
              *[v for s in row.inputs.values() for v in s]]
    if not all(math.isfinite(v) for v in values):
        return [f"{path}: the tube at {rate_hz:g} Hz is not finite (no usable margins)"]
    bent = [name for name, g in row.guards.items() if not g.formula_holds]
    if bent:
        return [f"{path}: at {rate_hz:g} Hz the margin formula of guard {bent[0]} does not "
                f"hold for its tube (formula_holds = false: the tube does not fit the "
                f"guard's geometry), as mpc.margins = \"tube\" refuses it"]
    return []


def margins_warnings(path: Path, kind: str, magnitude: float, kp: float,
                     kd: float, plant: tuple[str, str] | None = None) -> list[str]:
    """Why a margins file that fits a scenario may not be its tube ([] if it is).

    The tube grows with the disturbance box (every kind draws w from |w_i| <= magnitude;
    kind none is the zero set) and with the plant's mismatch with the model, and depends
    on the low level's gains. A file made for a smaller box, or without this scenario's
    plant, does not cover the scenario's disturbance; one made for other gains is another
    closed loop's tube. A file made for a larger box is conservative: no line. An
    unreadable file gives none either (:func:`margins_problems` names it), nor a
    magnitude or gains the file does not record.

    Args:
        path: the margins file.
        kind: the scenario's ``disturbance.kind``.
        magnitude: its ``disturbance.magnitude`` (box half-width per channel).
        kp: the scenario's ``lowlevel.kp``.
        kd: its ``lowlevel.kd``.
        plant: the scenario's plant when it differs from its system: (its
            :func:`params_hash`, what differs, e.g. "mass_scale = 1.1"); None: the model.
    """
    try:
        mf = read_margins(path)
    except ValueError:
        return []
    fix = ("hmpc tube SCENARIO --write FILE writes this scenario's, or mpc.margins = "
           "\"tube\" computes it for each run")
    file_kind = str(mf.disturbance.get("kind", "none"))
    file_bound = _bound(file_kind, mf.disturbance.get("magnitude", 0.0))
    out = []
    if _bound(kind, magnitude) > file_bound:
        out.append(f"{path} was computed for {_box(file_kind, file_bound)}; this scenario's "
                   f"disturbance.magnitude = {magnitude:g} (disturbance.kind = {kind!r}) is "
                   f"larger: its margins do not cover this disturbance ({fix})")
    if "kp" in mf.lowlevel and "kd" in mf.lowlevel and \
            (mf.lowlevel["kp"], mf.lowlevel["kd"]) != (float(kp), float(kd)):
        out.append(f"{path} was computed for the low level's kp = {mf.lowlevel['kp']:g}, kd = "
                   f"{mf.lowlevel['kd']:g}, not this scenario's lowlevel.kp = {kp:g}, "
                   f"lowlevel.kd = {kd:g}: its margins are another closed loop's tube ({fix})")
    if plant is not None and mf.disturbance.get("plant_hash") != plant[0]:
        made = (f"the plant {mf.disturbance['plant']}" if "plant" in mf.disturbance
                else "a plant that is the model")
        out.append(f"{path} was computed for {made}, not this scenario's plant ({plant[1]}): "
                   f"its margins may not cover this plant's mismatch with the model ({fix})")
    return out


def _bound(kind: str, magnitude) -> float:
    """The box half-width |w_i| <= bound a disturbance draws from (0: none; NaN: unreadable)."""
    try:
        return 0.0 if kind == "none" else float(magnitude)
    except (TypeError, ValueError):
        return math.nan


def _box(kind: str, bound: float) -> str:
    return f"no disturbance ({kind})" if bound == 0.0 else f"|w_i| <= {bound:g} ({kind})"


def constraint_margins(path: Path, system, params: BaseModel,
                       rate_hz: float) -> ConstraintMargins:
    """The MPC's margins from a margins file, at the scenario's MPC rate.

    Args:
        path: the margins file.
        system: the built :class:`~hmpc_cli.core.hybrid.HybridSystem` (guard and mode order).
        params: its parameters (checked against the file's hash).
        rate_hz: the scenario's MPC rate [Hz].

    Raises:
        ValueError: ``mpc.margins: <reason>`` when the file does not fit.
    """
    problems = margins_problems(path, params, rate_hz)
    if problems:
        raise ValueError(f"{REFUSED}{problems[0]}")
    row = read_margins(path).at(rate_hz)
    try:
        return ConstraintMargins.by_name(
            system, str(path), row.radius,
            {k: (g.avoid, g.pass_through) for k, g in row.guards.items()}, row.inputs)
    except ValueError as exc:
        raise ValueError(f"{REFUSED}{path}: {exc}") from None
