"""Parameter sweeps: one scenario x ``[set]`` overrides x ``[grid]`` axes x seeds.

A sweep file (TOML) names a scenario, overrides applied to every run (``[set]``), grid
axes (a scenario key with a list of values, or a name with a list of override tables,
each with an optional ``label``) and seeds. Every run is validated before any starts;
runs go to ``<out>/runs/<run_id>/`` (see :mod:`hmpc_cli.run.runner`), in-process, in spawned
worker processes (:mod:`hmpc_cli.sweep.pool`) or on a Dask cluster whose workers return
their files through the futures (:mod:`hmpc_cli.sweep.dask`), and ``<out>/results.csv``
is rebuilt from their ``summary.json`` files. A run id hashes the run's sorted overrides
and seed only.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import os
import re
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from hmpc_cli.run.scenario import (
    ScenarioError, format_errors, load_scenario, other_kind_of_file, read_toml_file,
    scenario_model, seeded_toml, shown_item)
from hmpc_cli.core.settings_types import MAX_INT
from hmpc_cli.sweep.table import METRICS, REAL_TIME, cell_text, toml_value

RESERVED = {"run_id", "seed", "log", *METRICS, *REAL_TIME}
#: most seeds of a sweep and most runs (cells x seeds); validating a run takes ~0.3 ms and
#: running one seconds to minutes: 20 000 runs is already hours of work on this machine
MAX_SEEDS = 100_000
MAX_RUNS = 20_000
_INDEX = re.compile(r"\[\d+\]$")
_KEY = re.compile(r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*$")


class SweepSpec(BaseModel):
    """The sweep file as written (grid and [set] are checked after flattening)."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(pattern=r"^[A-Za-z0-9_.-]+$", description=(
        "the results folder's name (results/sweeps/<name>)"),
        json_schema_extra={"default_text": "the file's stem"})
    description: str = ""
    scenario: str = Field(min_length=1, description="scenario file, relative to the sweep file")
    seeds: list[int] = Field(default_factory=lambda: [0], description="list, or N for 0..N-1")
    set_: dict[str, Any] = Field(default_factory=dict, alias="set", description=(
        "overrides of every run, key.path = value (an axis entry that sets the same key "
        "wins in its cells)"))
    grid: dict[str, Any] = Field(default_factory=dict, description=(
        "axes: key.path = a list of values, or name = a list of override tables; the "
        "runs are every combination of their values x the seeds"))

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not v.strip("."):  # "." or "..": results/sweeps/<name> would be another folder
            raise ValueError(f"{v!r} is not a name (it names a folder above the sweep's: "
                             "use letters, digits, '_', '-' or '.')")
        return v

    @field_validator("seeds", mode="before")
    @classmethod
    def _seeds(cls, v: Any) -> list[int]:
        if isinstance(v, int) and not isinstance(v, bool):
            if v < 1:
                raise ValueError(f"a seed count must be >= 1, got {v}")
            if v > MAX_SEEDS:
                raise ValueError(f"{v} seeds exceed the limit {MAX_SEEDS}")
            return list(range(v))
        if not isinstance(v, list) or not v:
            raise ValueError("expected a non-empty list of seeds or a seed count")
        if len(v) > MAX_SEEDS:
            raise ValueError(f"{len(v)} seeds exceed the limit {MAX_SEEDS}")
        if any(not isinstance(s, int) or isinstance(s, bool) or not 0 <= s <= MAX_INT
               for s in v):
            raise ValueError(f"seeds must be integers from 0 to {MAX_INT}")
        if len(set(v)) != len(v):
            raise ValueError("duplicate seeds")
        return v


@dataclass(frozen=True)
class Axis:
    """One grid axis: per entry a column value (label or value) and its overrides."""

    name: str
    table: bool
    labels: tuple[Any, ...]
    overrides: tuple[dict[str, Any], ...]


@dataclass
class Run:
    """One run of the sweep."""

    run_id: str
    seed: int
    cell: tuple[Any, ...]
    overrides: dict[str, Any]
    origin: dict[str, str]
    toml: str = ""
    #: its compute time is charged (``sim.latency`` not ``"paused"``): it records real_time
    charged: bool = False


@dataclass
class SweepPlan:
    """A validated sweep: every run's effective scenario text is known."""

    path: Path
    text: str
    spec: SweepSpec
    scenario: Path
    axes: list[Axis]
    runs: list[Run]
    keys: list[str] = field(default_factory=list)
    only_seeds: frozenset[int] | None = None  # run only these seeds (the table keeps all)
    #: the scenario file as every run read it when planned (no override, seed 0); "" when
    #: it is valid only with the sweep's overrides (then no committed row counts as a run)
    base_toml: str = ""

    @property
    def stored_text(self) -> str:
        """The text stored as ``<out>/sweep.toml``: the file's, naming the sweep.

        A file without ``name`` gets its resolved name (from the file's stem) as a first
        line: the directory's owner (:func:`hmpc_cli.sweep.lock.owner_problem`) is read
        from it, and the stored file's own stem is ``sweep``.
        """
        import tomllib

        if "name" in tomllib.loads(self.text):
            return self.text
        return f"name = {toml_value(self.spec.name)}  # hmpc sweep: the file's stem\n{self.text}"

    @property
    def selected(self) -> list[Run]:
        """The runs to execute: all, or those of ``only_seeds``."""
        return [r for r in self.runs if self.only_seeds is None or r.seed in self.only_seeds]

    @property
    def columns(self) -> list[str]:
        """results.csv columns, in order.

        The real-time ones only when a run charges compute time: a time-paused sweep's
        table keeps its columns.
        """
        real_time = REAL_TIME if any(r.charged for r in self.runs) else ()
        return ["run_id", *(a.name for a in self.axes), "seed",
                *(f"set.{k}" for k in self.keys), *METRICS, *real_time, "log"]


def _models(ann: Any) -> list[type[BaseModel]]:
    """The settings models an annotation stands for (a model, or the members of a union)."""
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return [ann]
    args = ann if isinstance(ann, list) else typing.get_args(ann)
    return [m for a in args for m in _models(a)]


def _flatten(data: dict, model: Any, where: str = "", twice: list[str] | None = None) -> dict:
    """Dotted keys; descends into tables only where the scenario has a settings section.

    A key written two ways (``"mpc.rate_hz"`` and ``mpc = {rate_hz = ...}``) keeps its
    first value; ``twice`` then receives ``<where>.<key>: written two ways, ...``.
    """
    out: dict[str, Any] = {}
    spelled: dict[str, str] = {}
    for parts, v in _leaves(data, model, ()):
        key = ".".join(parts)
        spelling = ".".join(p if re.fullmatch(r"[A-Za-z0-9_-]+", p) else json.dumps(p)
                            for p in parts)
        if key not in out:
            out[key], spelled[key] = v, spelling
        elif twice is not None:
            twice.append(f"{where}.{key}: written two ways, {spelled[key]} and {spelling} "
                         "(the same key): keep one")
    return out


def _leaves(data: dict, model: Any, path: tuple[str, ...]
            ) -> list[tuple[tuple[str, ...], Any]]:
    """``(key path as written, value)`` of every setting in ``data`` (see :func:`_flatten`)."""
    models = _models(model)
    items = []
    for k, v in data.items():
        subs = [m.model_fields[k].annotation for m in models if k in m.model_fields]
        if isinstance(v, dict) and any(_models(a) for a in subs):
            items += _leaves(v, subs, (*path, k))
        else:
            items.append(((*path, k), v))
    return items


def _axes(spec: SweepSpec, src: str, errors: list[str]) -> list[Axis]:
    """The grid's axes in file order; problems go to ``errors``, broken axes are left out."""
    axes = []
    for name, values in _flatten(spec.grid, scenario_model(), f"{src}: grid", errors).items():
        where = f"{src}: grid.{name}"
        problem = _axis_problem(name, values)
        if problem is not None:
            errors.append(f"{where}: {problem}")
        elif isinstance(values[0], dict):
            axes.append(_table_axis(name, values, where, errors))
        else:
            axes.append(Axis(name, False, tuple(values), tuple({name: v} for v in values)))
    seen: dict[str, str] = {}
    for ax in axes:
        for k in sorted({k for ov in ax.overrides for k in ov}):
            if k in seen:
                errors.append(f"{src}: grid.{ax.name}: {k}: also set by axis {seen[k]}")
            seen.setdefault(k, ax.name)
    return axes


def _dead_sets(base: dict, axes: list[Axis], src: str) -> list[str]:
    """``set.key`` lines for a [set] value every cell of an axis overrides (never applied).

    A key only some of an axis's tables set keeps the [set] value in the others: a default.
    """
    return [f"{src}: set.{k}: never applied: every cell of grid.{ax.name} sets {k} "
            f"(remove it from [set], or leave it out of some of the axis's entries)"
            for k in base for ax in axes if all(k in ov for ov in ax.overrides)]


def _axis_problem(name: str, values: Any) -> str | None:
    """Why grid entry ``name = values`` is not an axis, or None if it is one."""
    if name in RESERVED or name.startswith("set.") or name == "seed":
        return "reserved name (use another axis name; seeds via `seeds`)"
    if not isinstance(values, list):
        return "expected a list of values or of override tables"
    if not values:
        return "empty axis (no values)"
    if len({isinstance(v, dict) for v in values}) > 1:
        return "mixes override tables and plain values"
    return None


def _table_axis(name: str, tables: list[dict], where: str, errors: list[str]) -> Axis:
    """An axis of override tables, each labelled by its ``label`` or by its overrides."""
    labels, overrides = [], []
    for i, entry in enumerate(tables):
        entry = dict(entry)
        label = entry.pop("label", None)
        if label is not None and not isinstance(label, str):
            errors.append(f"{where}[{i}].label: must be a string")
            label = None
        ov = _flatten(entry, scenario_model(), f"{where}[{i}]", errors)
        labels.append(label if label is not None else
                      ", ".join(f"{k}={cell_text(v)}" for k, v in ov.items()) or "(base)")
        overrides.append(ov)
    dup = sorted({lb for lb in labels if labels.count(lb) > 1})
    if dup:
        errors.append(f"{where}: duplicate labels {dup}")
    return Axis(name, True, tuple(labels), tuple(overrides))


def run_id(overrides: dict[str, Any], seed: int) -> str:
    """Short stable hash of a run's sorted overrides and seed."""
    blob = json.dumps({"overrides": overrides, "seed": seed}, sort_keys=True,
                      separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:10]


def _rewrite(line: str, scenario: Path, src: str, run: Run) -> str:
    """Attributes a scenario error on an overridden key to the sweep file and its entry.

    ``sweep.toml: grid.axis[i]: key.path: reason (value v)`` (or ``[set]``); an element
    of an overridden list (``system.x0[3]``) counts as the list's key. An override that
    cannot be applied at all (its key path runs through a value) is said once per axis.
    """
    for k, v in run.overrides.items():
        prefix = f"--set {shown_item(f'{k}={toml_value(v)}')}: "
        if line.startswith(prefix):
            where = run.origin[k]
            axis = _INDEX.sub("", where)
            return (f"{src}: {axis if axis == f'grid.{k}' else where}: {k}: "
                    f"{line.removeprefix(prefix)}")
    rest = line.removeprefix(f"{scenario}: ")
    key, sep, reason = rest.partition(": ")
    unknown = reason.startswith("unknown key")  # an unknown section an override made
    hit = [k for k in run.overrides if key == k or key.startswith((f"{k}.", f"{k}["))
           or (unknown and k.startswith(f"{key}."))]
    if rest == line or not sep or not hit:
        return line
    where = run.origin[hit[-1]]
    if reason.startswith("unknown key"):  # a value axis: one line for all its values
        axis = _INDEX.sub("", where)
        return f"{src}: {axis if axis == f'grid.{hit[-1]}' else where}: {key}: {reason}"
    return f"{src}: {where}: {key}: {reason} (value {toml_value(run.overrides[hit[-1]])})"


def _relative_hint(given: str, base: Path) -> str:
    """`` (a relative scenario is read from ...)`` for a relative scenario path.

    '' for an absolute path, or a sweep file in the current directory. A file found in
    the current directory instead is named as the sweep file should name it.
    """
    if Path(given).is_absolute() or base.resolve() == Path.cwd().resolve():
        return ""
    hint = f" (a relative scenario is read from the sweep file's directory, {base}"
    if Path(given).is_file():
        hint += (f"; {given} is in the current directory: name it "
                 f"{os.path.relpath(Path(given).resolve(), base.resolve())!r}")
    return hint + ")"


def plan_sweep(path: str | Path) -> SweepPlan:
    """Reads a sweep file, expands it and validates every run's scenario.

    Raises:
        ScenarioError: one ``file: key.path: reason`` line per problem.
    """
    path, src = Path(path), str(path)
    text, spec = _read_spec(path, src)
    errors: list[str] = []
    scenario = path.parent / spec.scenario
    itself = scenario.resolve() == path.resolve()
    if scenario.is_dir():
        errors.append(f"{src}: scenario: {scenario} is a directory, not a scenario file"
                      + _relative_hint(spec.scenario, path.parent))
    elif not scenario.is_file():
        errors.append(f"{src}: scenario: file not found: {scenario}"
                      + _relative_hint(spec.scenario, path.parent))
    elif itself or _is_a_sweep_file(scenario):  # its runs would say "run it with hmpc sweep"
        this = " (this sweep file itself)" if itself else ""
        raise ScenarioError([f"{src}: scenario: {scenario} is a sweep file{this}, not a "
                             "scenario: name the scenario file its runs start from (one "
                             "with system and mpc sections)"])
    base = _flatten(spec.set_, scenario_model(), f"{src}: set", errors)
    axes = _axes(spec, src, errors)  # broken axes are left out; their runs still checked
    errors += _dead_sets(base, axes, src)
    bad_keys = _bad_keys(src, [(k, v, "set") for k, v in base.items()] + [
        (k, v, f"grid.{a.name}") for a in axes for ov in a.overrides for k, v in ov.items()])
    if bad_keys:
        raise ScenarioError(list(dict.fromkeys(errors + bad_keys)))
    total = _run_count(spec, axes)
    if total > MAX_RUNS:
        cells = " x ".join(str(len(a.labels)) for a in axes) or "1"
        raise ScenarioError([*errors, f"{src}: seeds: {cells} grid cells x {len(spec.seeds)} "
                             f"seeds = {total} runs exceeds the limit {MAX_RUNS}"])
    runs = _expand(spec, base, axes, src, errors)
    # a cell's scenario is validated once; its other seeds differ from it in the seed only
    cells: dict[tuple[str, ...], tuple[Callable[[int], str], bool] | None] = {}  # None: invalid
    for run in runs if scenario.is_file() else []:
        items = tuple(f"{k}={toml_value(v)}" for k, v in run.overrides.items())
        try:
            if items not in cells:
                cell, run.toml = load_scenario(scenario, list(items), run.seed,
                                               attribute_sets=False)
                cells[items] = seeded_toml(cell), cell.sim.latency != "paused"
                run.charged = cells[items][1]
            elif (known := cells[items]) is not None:
                run.toml, run.charged = known[0](run.seed), known[1]
        except ScenarioError as exc:
            cells[items] = None
            errors += [_rewrite(line, scenario, src, run) for line in exc.lines]
    errors += _same_scenarios(runs, src)
    if errors:
        raise ScenarioError(list(dict.fromkeys(errors)))
    keys = sorted({k for r in runs for k in r.overrides})
    try:
        base = load_scenario(scenario, [], 0, check_margins=False)[1]
    except ScenarioError:
        base = ""
    return SweepPlan(path, text, spec, scenario, axes, runs, keys, base_toml=base)


def planned_runs(path: str | Path) -> int | None:
    """How many runs the sweep file at ``path`` plans: its seeds x its grid's cells.

    None when it cannot tell (the file unreadable or not a valid sweep, an axis broken);
    the scenario is not read.
    """
    try:
        _, spec = _read_spec(Path(path), str(path))
    except ScenarioError:
        return None
    errors: list[str] = []
    axes = _axes(spec, str(path), errors)
    return None if errors else _run_count(spec, axes)


def _run_count(spec: SweepSpec, axes: list[Axis]) -> int:
    """The runs a sweep plans: its seeds x its grid's cells."""
    return len(spec.seeds) * math.prod(len(a.labels) for a in axes)


def _is_a_sweep_file(path: Path) -> bool:
    """Whether ``path`` reads as a sweep file (unreadable: left to the scenario's loader)."""
    try:
        _, data = read_toml_file(path)
    except ScenarioError:
        return False
    return bool(other_kind_of_file(data, str(path), "scenario"))


def _read_spec(path: Path, src: str) -> tuple[str, SweepSpec]:
    """The sweep file's text and validated spec (its name defaults to the file's stem).

    Raises:
        ScenarioError: the file is missing, a directory, unreadable, not UTF-8 TOML,
            nested too deeply, or not a valid sweep.
    """
    text, data = read_toml_file(path, "sweep file", src)
    data.setdefault("name", re.sub(r"[^A-Za-z0-9_.-]", "_", path.stem))
    try:
        return text, SweepSpec.model_validate(data)
    except ValidationError as exc:
        # a scenario file: that line alone (its keys' errors all follow from it)
        raise ScenarioError(other_kind_of_file(data, src, "sweep")
                            or format_errors(exc, src, SweepSpec)) from None


def _expand(spec: SweepSpec, base: dict[str, Any], axes: list[Axis], src: str,
            errors: list[str]) -> list[Run]:
    """Every grid cell x seed as a run: ``[set]`` overrides, then each axis's, in order.

    A run identical to an earlier one (two cells with the same overrides) is left out and
    reported in ``errors``.
    """
    runs, ids = [], {}
    for combo in itertools.product(*(range(len(a.labels)) for a in axes)):
        overrides, origin = dict(base), dict.fromkeys(base, "[set]")
        for a, i in zip(axes, combo, strict=True):
            overrides.update(a.overrides[i])
            where = f"grid.{a.name}[{i}]"
            origin.update(dict.fromkeys(a.overrides[i], where))
        cell = tuple(a.labels[i] for a, i in zip(axes, combo, strict=True))
        for seed in spec.seeds:
            run = Run(run_id(overrides, seed), seed, cell, dict(sorted(overrides.items())),
                      origin)
            if run.run_id in ids:
                errors.append(f"{src}: grid: cells {ids[run.run_id]} and {list(cell)} have "
                              "identical overrides")
                continue
            ids[run.run_id] = list(cell)
            runs.append(run)
    return runs


def _same_scenarios(runs: list[Run], src: str) -> list[str]:
    """``grid: cells A and B run the same scenario`` lines ([] if none).

    Cells whose overrides differ only in how a value is written (15 and 15.0), or in a value
    the scenario already has, would run the same runs twice under two run ids.
    """
    first: dict[str, Run] = {}
    out = []
    for run in runs:
        if not run.toml:
            continue
        other = first.setdefault(run.toml, run)
        if other is not run and other.run_id != run.run_id:
            out.append(f"{src}: grid: cells {list(other.cell)} and {list(run.cell)} run the "
                       "same scenario (a value written two ways, e.g. 15 and 15.0, or one "
                       "the scenario already has): keep one")
    return list(dict.fromkeys(out))


def first_seeds(plan: SweepPlan, n: int | None) -> SweepPlan:
    """The plan set to run only its first ``n`` seeds (None: all).

    Run ids ignore the seed list, so the whole sweep later skips these runs; results.csv
    keeps every finished run.

    Raises:
        ScenarioError: unless 1 <= n <= the sweep's number of seeds.
    """
    seeds = plan.spec.seeds
    if n is not None and not 1 <= n <= len(seeds):
        raise ScenarioError([(f"{plan.path}: --seeds {n}: the sweep has {len(seeds)} "
                              f"seed(s); choose 1..{len(seeds)}")])
    return plan if n is None else dataclasses.replace(plan, only_seeds=frozenset(seeds[:n]))


def _bad_keys(src: str, items: list[tuple[str, Any, str]]) -> list[str]:
    """Problems with override keys and values themselves (before any scenario)."""
    out = []
    for key, value, where in items:
        if key == "seed":
            out.append(f"{src}: {where}: seed: set the seeds with `seeds`")
        elif not _KEY.match(key):
            out.append(f"{src}: {where}: {key!r}: not a key path")
        else:
            try:
                toml_value(value)
            except TypeError as exc:
                out.append(f"{src}: {where}: {key}: {exc}")
    return out
