"""``mpc.margins = "tube"``: the margins of the scenario's own tube at its MPC rate.

The paper's robust MPC tightens its constraints by the tube of its own period: diam T(dt),
dt = 1 / ``mpc.rate_hz``, under the scenario's disturbance box and low-level gains, on the
region spanned by x0 and the goal, eta holding the simulated plant's mismatch when the
scenario's ``[plant]`` differs from its system (what ``hmpc tube SCENARIO --write``
computes). A sweep
over MPC rates thus gives each rate its own margins. The analysis is written once as a
margins file in ``<cache>/tubes/`` (keyed by everything it depends on) and read back by
every later run; margins that make the tightened problem infeasible at x0 are refused
with the tube's own reason.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from hmpc_cli import __version__
from hmpc_cli.core.cbuild import cache_dir
from hmpc_cli.core.messages import ConstraintMargins

if TYPE_CHECKING:
    from pydantic import BaseModel

    from hmpc_cli.core.hybrid import HybridSystem
    from hmpc_cli.tube import Region, TubeReport

__all__ = ["SAMPLES", "TUBE", "plant_difference", "plant_system", "scenario_tube",
           "tube_margins",
           "tube_margins_file", "tube_margins_path"]

TUBE = "tube"  #: the ``mpc.margins`` value
SAMPLES = 20000  #: samples per estimated constant (``hmpc tube``'s default)
SEED = 0  #: one tube per system and setting, whatever the run's seed


def _tube_sources(system: str) -> str:
    """sha256 of what the tube is computed from (a change to any: another cache entry).

    The tube analysis, this module, the hybrid system's vocabulary and the system
    plug-in's own source (its package's modules, for a package).
    """
    import inspect

    from hmpc_cli.core import hybrid
    from hmpc_cli.core.registry import PluginError, registry

    here = Path(__file__).resolve()
    paths = {*(here.parents[1] / "tube").glob("*.py"), here, Path(hybrid.__file__).resolve()}
    try:
        source = Path(inspect.getsourcefile(registry().system(system).build)).resolve()
        paths |= set(source.parent.glob("*.py")) if source.name == "__init__.py" else {source}
    except (PluginError, TypeError, OSError):
        pass  # no such plug-in (refused elsewhere) or no source file: the rest decides
    h = hashlib.sha256()
    for path in sorted(paths):
        h.update(path.name.encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


def plant_difference(sc) -> tuple[BaseModel | None, str]:
    """The plant's parameters and what differs ("mass_scale = 1.1"), or (None, "").

    (None, ""): no ``[plant]`` table, or one that leaves every parameter as the system's
    (the plant is the model: no mismatch).
    """
    world = sc.plant_params() if sc.plant else sc.system
    if world == sc.system:
        return None, ""
    model, plant = sc.system.model_dump(mode="json"), world.model_dump(mode="json")
    return world, ", ".join(f"{k} = {_text(v)}" for k, v in plant.items()
                            if v != model.get(k))


def _text(v) -> str:
    return f"{v:g}" if isinstance(v, float) else json.dumps(v)


def plant_system(sc) -> tuple[HybridSystem | None, str]:
    """The plant's built system when it differs from the model, and how (None, "": not).

    Raises:
        hmpc_cli.core.registry.PluginError: the plant's system fails to build.
    """
    from hmpc_cli.core.registry import build_system

    params, note = plant_difference(sc)
    return (None, "") if params is None else (build_system(params), note)


def scenario_tube(sc, system: HybridSystem, *, region: Region | None = None,
                  rate_hz: float | None = None, rates: Sequence[float] | None = None,
                  samples: int = 20000, seed: int | None = None) -> TubeReport:
    """``hmpc tube``'s analysis of a scenario: its disturbance, low level and ``[plant]``.

    ``system``: the scenario's built system; ``region`` defaults to
    :func:`hmpc_cli.tube.region_from_scenario`'s, ``rate_hz`` to ``mpc.rate_hz``,
    ``rates`` to the tube's defaults and ``seed`` (of the sampling) to :data:`SEED`, not
    the scenario's: one tube per setting, as ``mpc.margins = "tube"`` computes it. A
    ``[plant]`` that
    differs from the system is built and passed down: eta holds its flow's mismatch.

    Raises:
        hmpc_cli.tube.TubeError: no tube (e.g. a non-finite constant).
        hmpc_cli.core.registry.PluginError: the plant's system fails to build.
    """
    from hmpc_cli.tube import DEFAULT_RATES, analyse, region_from_scenario

    plant, note = plant_system(sc)
    return analyse(system, region=region_from_scenario(system) if region is None else region,
                   kind=sc.disturbance.kind, magnitude=sc.disturbance.magnitude,
                   kp=sc.lowlevel.kp, kd=sc.lowlevel.kd,
                   rate_hz=sc.mpc.rate_hz if rate_hz is None else rate_hz,
                   rates=DEFAULT_RATES if rates is None else rates, samples=samples,
                   seed=SEED if seed is None else seed, plant=plant, plant_note=note)


def _inputs(sc) -> dict:
    """Everything the tube depends on (JSON-ready): the plant's parameters too."""
    plant = plant_difference(sc)[0]
    return {"hmpc": __version__, "sources": _tube_sources(sc.system.name),
            "system": sc.system.model_dump(mode="json"),
            "plant": None if plant is None else plant.model_dump(mode="json"),
            "disturbance": [sc.disturbance.kind, float(sc.disturbance.magnitude)],
            "lowlevel": [float(sc.lowlevel.kp), float(sc.lowlevel.kd)],
            "rate_hz": float(sc.mpc.rate_hz), "samples": SAMPLES, "seed": SEED}


def tube_margins_path(sc) -> Path:
    """The cached margins file of the scenario's tube (it may not exist yet)."""
    key = hashlib.sha256(json.dumps(_inputs(sc), sort_keys=True).encode()).hexdigest()[:20]
    return cache_dir() / "tubes" / f"{sc.system.name}-{sc.mpc.rate_hz:g}hz-{key}.toml"


def tube_margins(sc, model) -> ConstraintMargins:
    """The margins of the scenario's tube at ``mpc.rate_hz`` (computed once, cached).

    Raises:
        ValueError: ``mpc.margins: ...`` when the tube's margins make the tightened problem
            infeasible at x0, or no finite tube exists at that rate.
    """
    rate = float(sc.mpc.rate_hz)
    row = tube_margins_file(sc, model).at(rate)
    return ConstraintMargins.by_name(
        model, f"tube at {rate:g} Hz", row.radius,
        {k: (g.avoid, g.pass_through) for k, g in row.guards.items()}, row.inputs)


def tube_margins_file(sc, model):
    """The scenario's tube as a :class:`~hmpc_cli.tube.margins_file.MarginsFile` (cached).

    Read from :func:`tube_margins_path` when a run wrote it, else (or when that file is
    damaged: not TOML or not a margins file) computed and written there (an unwritable
    cache: computed again next time).

    Raises:
        ValueError: as :func:`tube_margins`.
    """
    import tomllib

    from hmpc_cli.tube.margins_file import MarginsFile

    from pydantic import ValidationError

    path = tube_margins_path(sc)
    text = _read(path)
    if text is not None:
        try:
            return MarginsFile.model_validate(tomllib.loads(text))
        except (tomllib.TOMLDecodeError, ValidationError):
            pass  # a damaged cache entry (a disk full, an editor): computed again
    text = _compute(sc, model, float(sc.mpc.rate_hz))
    try:
        from hmpc_cli.core.paths import write_atomic

        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, text)
    except OSError:
        pass
    return MarginsFile.model_validate(tomllib.loads(text))


def _read(path: Path) -> str | None:
    """The cached file's text (None: none, unreadable, or not UTF-8: damaged)."""
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None


def _compute(sc, model, rate: float) -> str:
    """The margins file text of the scenario's tube at ``rate`` [Hz]."""
    from hmpc_cli.tube import TubeError
    from hmpc_cli.tube.margins_file import REFUSED, margins_text

    try:
        report = scenario_tube(sc, model, rate_hz=rate, rates=(), samples=SAMPLES, seed=SEED)
    except TubeError as exc:
        raise ValueError(f"{REFUSED}no tube at {rate:g} Hz: {exc}") from None
    if report.warnings:
        raise ValueError(f"{REFUSED}the tube's margins at {rate:g} Hz do not fit: "
                         f"{report.warnings[0]}")
    return margins_text(report, scenario=sc.name, params=sc.system, kind=sc.disturbance.kind,
                        magnitude=sc.disturbance.magnitude, samples=SAMPLES,
                        plant=plant_difference(sc)[0])
