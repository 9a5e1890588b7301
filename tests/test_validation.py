"""Validation that cannot be fooled: every numeric setting, from the file, --set and a sweep.

The cases are generated from the scenario's JSON schema (both systems with their default
planner and MPC): every numeric field, and every number inside a tuple or list field, gets
NaN, inf, -inf, 1e300, a negative value where the field has a lower bound, and the wrong
types "1" and true. Each must end with exit 2, one ``source: key.path: reason`` line naming
the key and where the value came from, no traceback and nothing written. Runs go through
Typer's ``CliRunner`` in-process (``conftest.bad_input``); ``prepare`` is replaced so that
a value that slips through fails at once instead of running a simulation.
"""

from __future__ import annotations

import dataclasses
import math
import tracemalloc
from pathlib import Path

import pytest

from conftest import bad_input, forbid_prepare
from hmpc_cli.run.scenario import dump_toml, scenario_model

#: system -> (planner kind, MPC kind): the plug-in sections validated with it
STACKS = {"ball": ("cem", "fixed_mode"), "biped": ("footholds", "walking")}
#: fields that are finite but deliberately unbounded ("huge" means "never")
UNBOUNDED = {"sim.divergence_bound"}
BAD = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf, "huge": 1e300,
       "string": "1", "bool": True}


def _resolve(schema: dict, node: dict) -> dict:
    if "$ref" in node:
        return schema["$defs"][node["$ref"].rsplit("/", 1)[1]]
    branches = [b for b in node.get("anyOf", []) if b.get("type") != "null"]
    return _resolve(schema, branches[0]) if len(branches) == 1 else node


def _numeric(node: dict) -> bool:
    return node.get("type") in ("number", "integer")


def _has_lower_bound(node: dict) -> bool:
    low = node.get("minimum", node.get("exclusiveMinimum"))
    return low is not None and low >= 0


def _fields(schema: dict, model: dict, section: str):
    """(key path, path to the bad number, default, number schema) per numeric slot."""
    for name, prop in model["properties"].items():
        node = _resolve(schema, prop)
        key = f"{section}.{name}" if section else name
        if _numeric(node):
            yield key, (), prop.get("default"), node
        elif node.get("type") == "array" and "prefixItems" in node:
            default = list(prop.get("default") or [1.0] * len(node["prefixItems"]))
            for i, item in enumerate(node["prefixItems"]):
                if _numeric(_resolve(schema, item)):
                    yield key, (i,), default, _resolve(schema, item)
        elif node.get("type") == "array" and "$ref" in node.get("items", {}):
            item = _resolve(schema, node["items"])  # a list of tables (biped stairs)
            for sub, sub_node in item["properties"].items():
                if _numeric(_resolve(schema, sub_node)):
                    yield key, (0, sub), item, _resolve(schema, sub_node)


def _cases() -> list[tuple[str, str, tuple, object, dict]]:
    schema = scenario_model().model_json_schema()
    defs = schema["$defs"]
    seen, out = set(), []
    plugin = {"system": {s: f"{s.title()}Params" for s in STACKS},
              "planner": {"cem": "CEMSettings", "footholds": "FootholdSettings"},
              "mpc": {"fixed_mode": "MPCSettings", "walking": "WalkingMPCSettings"}}
    for system, (planner, mpc) in STACKS.items():
        sections = [("", schema), ("system", defs[plugin["system"][system]]),
                    ("planner", defs[plugin["planner"][planner]]),
                    ("mpc", defs[plugin["mpc"][mpc]])]
        sections += [(k, _resolve(schema, schema["properties"][k]))
                     for k in ("sim", "disturbance", "replanning", "lowlevel")]
        for section, model in sections:
            for key, path, default, node in _fields(schema, model, section):
                if (system, key, path) in seen or (system != "ball" and section in (
                        "", "sim", "disturbance", "replanning", "lowlevel")):
                    continue  # the common sections once (with the ball)
                seen.add((system, key, path))
                out.append((system, key, path, default, node))
    return out


CASES = _cases()


def _value(path: tuple, default, bad):
    """The TOML value of the key: the bad number itself or inside its tuple / table list."""
    if not path:
        return bad
    if len(path) == 1:
        value = list(default)
        value[path[0]] = bad
        return value
    table = {k: 1.0 for k, v in default["properties"].items() if _numeric(v) or "anyOf" in v}
    table[path[1]] = bad
    return [table]


def _key(key: str, path: tuple) -> str:
    """The key path an error names (``system.x0[2]``, ``system.stairs[0].length``)."""
    return key + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path)


def _toml(value) -> str:
    return dump_toml({"v": value}).strip().removeprefix("v = ")


def _values(node: dict) -> list[str]:
    names = [n for n in BAD if n != "huge" or node.get("type") == "integer"
             or node.get("maximum") is None]
    return names + (["negative"] if _has_lower_bound(node) else [])


def _bad(name: str, node: dict):
    return -1 if name == "negative" else BAD[name]


TABLE = [(s, k, p, d, n, v) for s, k, p, d, n in CASES for v in _values(n)]


@pytest.fixture
def work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A scratch current directory; building a loop fails the test (input slipped through)."""
    monkeypatch.chdir(tmp_path)
    forbid_prepare(monkeypatch)
    return tmp_path


def bad_run(work: Path, args: list[str]) -> list[str]:
    """``hmpc ARGS`` expecting bad input (:func:`conftest.bad_input`); the lines."""
    return bad_input(work, args)


def _scenario(work: Path, system: str, data: dict | None = None, name: str = "") -> Path:
    path = work / f"{name or system}.toml"
    data = {"name": system, **(data or {})}
    data.setdefault("system", {})["name"] = system
    path.write_text(dump_toml(data), encoding="utf-8")
    return path


def _nested(key: str, value) -> dict:
    head, _, rest = key.partition(".")
    return {head: _nested(rest, value) if rest else value}


def _is_unbounded(key: str, value: str) -> bool:
    return key in UNBOUNDED and value == "huge"


# ----------------------------------------------------------- every numeric field, every source
def test_the_table_covers_both_systems_and_every_section():
    keys = {(s, k.split(".")[0]) for s, k, *_ in CASES}
    for section in ("system", "planner", "mpc"):
        assert {("ball", section), ("biped", section)} <= keys
    assert {("ball", s) for s in ("sim", "disturbance", "replanning", "lowlevel", "seed")} <= keys
    assert len(TABLE) > 500


def test_every_bad_number_from_the_file_and_from_set(work: Path):
    """One in-process CLI call per (field, value, source); failures are collected."""
    failures = []
    for system, key, path, default, node, value in TABLE:
        if _is_unbounded(key, value):
            continue
        bad = _value(path, default, _bad(value, node))
        where = _key(key, path)
        scenario = _scenario(work, system, _nested(key, bad), "bad")
        for source, args in (
                ("file", ["run", scenario.name]),
                ("set", ["run", _scenario(work, system).name, "--set", f"{key}={_toml(bad)}"])):
            try:
                lines = bad_run(work, [*args, "--out", "out"])
                prefix = (f"error: {scenario.name}: " if source == "file"
                          else f"error: --set {key}={_toml(bad)}: ")
                assert any(line.startswith(prefix + where + ":") for line in lines), lines
            except AssertionError as exc:
                failures.append(f"{system} {where} = {value} ({source}): {exc}")
        scenario.unlink()
    assert not failures, f"{len(failures)} cases:\n" + "\n".join(failures[:20])


SWEEP_SAMPLE = [("mpc.horizon", "inf"), ("sim.duration", "nan"), ("system.mass", "huge"),
                ("planner.samples", "string"), ("mpc.rate_hz", "bool"),
                ("lowlevel.kp", "negative"), ("disturbance.magnitude", "-inf")]


@pytest.mark.parametrize("key,value", SWEEP_SAMPLE)
@pytest.mark.parametrize("axis", ["plain", "table"])
def test_a_bad_number_in_a_sweep_grid(work: Path, key: str, value: str, axis: str):
    (node,) = [n for s, k, p, d, n in CASES if s == "ball" and k == key and not p]
    bad = _toml(_bad(value, node))
    _scenario(work, "ball")
    if axis == "plain":
        grid, where = f'"{key}" = [{_toml(node.get("default", 1))}, {bad}]', f"grid.{key}[1]"
    else:
        grid, where = f'controller = [{{ label = "ok" }}, {{ "{key}" = {bad} }}]', \
            "grid.controller[1]"
    (work / "x.toml").write_text(f'name = "x"\nscenario = "ball.toml"\n[grid]\n{grid}\n')
    lines = bad_run(work, ["sweep", "x.toml", "--dry-run"])
    assert any(line.startswith(f"error: x.toml: {where}: {key}: ") for line in lines), lines


# ------------------------------------------------------------------------- the named defects
def test_bool_and_string_are_not_numbers(work: Path):
    ball = _scenario(work, "ball").name
    lines = bad_run(work, ["run", ball, "--set", "sim.duration=true"])
    assert lines == ["error: --set sim.duration=true: sim.duration: Input should be a valid "
                     "number"]
    lines = bad_run(work, ["run", ball, "--set", 'sim.rate_hz="600"'])
    assert lines == ['error: --set sim.rate_hz="600": sim.rate_hz: Input should be a valid '
                     'integer (text here; an integer is written without quotes in TOML: 600)']


@pytest.mark.parametrize("key,text,message", [
    ("sim.rate_hz", '"600"', "Input should be a valid integer (text here; an integer is "
                             "written without quotes in TOML: 600)"),
    ("sim.duration", '"0.3"', "Input should be a valid number (text here; a number is written "
                              "without quotes in TOML: 0.3)"),
    ("sim.duration", '"3"', "Input should be a valid number (text here; a number is written "
                            "without quotes in TOML: 3)"),
    ("sim.delay_compensation", '"true"', "Input should be a valid boolean (text here; a "
                                         "boolean is written without quotes in TOML: true)"),
    # no hint where the unquoted text would be wrong too
    ("sim.rate_hz", '"1e3"', "Input should be a valid integer"),
    ("sim.duration", '"nan"', "Input should be a valid number"),
    ("sim.rate_hz", '"many"', "Input should be a valid integer"),
])
def test_a_number_given_as_text_gets_a_quoting_hint(work: Path, key: str, text: str,
                                                    message: str):
    """As ``name = 600`` is told text is quoted, ``rate_hz = "600"`` is told numbers are not."""
    ball = _scenario(work, "ball").name
    assert bad_run(work, ["run", ball, "--set", f"{key}={text}"]) == [
        f"error: --set {key}={text}: {key}: {message}"]
    section, _, field = key.partition(".")
    (work / "q.toml").write_text(f"{(work / ball).read_text()}\n[{section}]\n{field} = {text}\n")
    assert bad_run(work, ["run", "q.toml"]) == [f"error: q.toml: {key}: {message}"]


def test_a_problem_made_on_the_command_line_names_the_option_not_the_file(work: Path):
    """--seed's own problem and a --set inside a value that is not a table."""
    ball = _scenario(work, "ball").name
    assert bad_run(work, ["run", ball, "--seed", "-1"]) == [
        "error: --seed -1: seed: Input should be greater than or equal to 0 (got -1)"]
    assert bad_run(work, ["run", ball, "--set", "system.x0.0=1"]) == [
        "error: --set system.x0.0=1: system.x0: Input should be a valid tuple (got a table: "
        "write an array, [a, b, ...])"]


@pytest.mark.parametrize("system,item,message", [
    ("ball", "system.x0=[1.0,1.0,0.0]",
     "system.x0: needs 4 numbers, got 3 (initial state (px, py, vx, vy) [m, m, m/s, m/s])"),
    ("ball", "system.x0=[1,2,3,4,5]",
     "system.x0: needs 4 numbers, got 5 (initial state (px, py, vx, vy) [m, m, m/s, m/s])"),
    ("ball", "system.circle_center=[3.0]",
     "system.circle_center: needs 2 numbers, got 1 (centre c (x, y) of the circle guard, the "
     "final domain [m]; the circle must not reach the floor's or the wall's guard)"),
    ("ball", "system.circle_center=[]",
     "system.circle_center: needs 2 numbers, got 0 (centre c (x, y) of the circle guard, the "
     "final domain [m]; the circle must not reach the floor's or the wall's guard)"),
    ("biped", "system.q0=[0.1,0.2]", "system.q0: needs 5 numbers, got 2 (initial angles [rad])"),
    ("ball", "plant.x0=[1.0]",
     "plant.x0: needs 4 numbers, got 1 (initial state (px, py, vx, vy) [m, m, m/s, m/s])"),
])
def test_a_tuple_of_the_wrong_length_says_how_many_numbers(work: Path, system: str, item: str,
                                                           message: str):
    """One line at the tuple (was: one "system.x0[3]: Field required" per missing item)."""
    name = _scenario(work, system).name
    assert bad_run(work, ["run", name, "--set", item]) == [f"error: --set {item}: {message}"]
    key, _, value = item.partition("=")
    section, _, field = key.partition(".")
    data = {section: {field: _parsed(value)}}
    bad = _scenario(work, system, data, "bad").name
    assert bad_run(work, ["run", bad]) == [f"error: {bad}: {message}"]


def _parsed(value: str):
    import tomllib

    return tomllib.loads(f"v = {value}")["v"]


@pytest.mark.parametrize("system,item,message", [
    ("ball", "mpc.solver_options={ipopt={tol=nan}}",
     "mpc.solver_options.ipopt.tol: Input should be a finite number"),
    ("biped", "mpc.solver_options.ipopt.tol=inf",
     "mpc.solver_options.ipopt.tol: Input should be a finite number"),
    ("ball", "mpc.solver_options.print_level=-inf",
     "mpc.solver_options.print_level: Input should be a finite number"),
    ("ball", "mpc.solver_options.ipopt.max_iter=100000000000",
     "mpc.solver_options.ipopt.max_iter: 100000000000 exceeds the largest allowed magnitude "
     "1e+09 (an integer; a float, e.g. 1e+11, may be larger)"),
    ("ball", "mpc.solver_options.ipopt=5",
     "mpc.solver_options.ipopt: must be a table of option = value, not 5 (e.g. ipopt = "
     "{tol = 1e-8}, or [mpc.solver_options.ipopt] with tol = 1e-8 below it)"),
    ("biped", 'mpc.solver_options.hpipm=["x"]',
     "mpc.solver_options.hpipm: must be a table of option = value, not ['x'] (e.g. hpipm = "
     "{iter_max = 30}, or [mpc.solver_options.hpipm] with iter_max = 30 below it)"),
    ("ball", "mpc.solver_options.ipopt.when=1979-05-27",
     "mpc.solver_options.ipopt.when: a date is no solver option value (give a number, "
     "text, a boolean, an array or a table)"),
])
def test_solver_options_values_are_checked_like_every_setting(work: Path, system: str,
                                                              item: str, message: str):
    """NaN, inf, an integer beyond 1e9, a section that is no table: one line naming the key
    path inside mpc.solver_options (was: an internal error, or a run with the value)."""
    name = _scenario(work, system).name
    assert bad_run(work, ["run", name, "--set", item, "--out", "out"]) == [
        f"error: --set {item}: {message}"]
    section, _, rest = item.removeprefix("mpc.solver_options.").partition(".")
    if "{" in item or not rest:
        return
    key, _, value = rest.partition("=")  # the same value in the file, and for hmpc tube
    bad = work / "bad.toml"
    bad.write_text(f"{(work / name).read_text()}\n[mpc.solver_options.{section}]\n"
                   f"{key} = {value}\n", encoding="utf-8")
    assert bad_run(work, ["run", bad.name, "--out", "out"]) == [f"error: {bad.name}: {message}"]
    assert bad_run(work, ["tube", bad.name, "--out", "t"]) == [f"error: {bad.name}: {message}"]


def test_solver_options_within_the_bounds_pass(work: Path):
    from hmpc_cli.mpc.solver_table import check_options

    ok = {"ipopt": {"tol": 1e-300, "max_iter": 10**9, "mu_strategy": "monotone",
                    "nlp_upper_bound_inf": 1e19, "obj_scaling_factor": -1e300},
          "hpipm": {}, "print_time": False, "nested": {"a": [1, 2.5]}}
    assert check_options(ok) is ok


@pytest.mark.parametrize("item,message", [
    ("mpc.horizon=1e6", "mpc.horizon: 1e+06 s x 60 nodes/s (mpc.nodes_per_second) = "
                        "6e+07 NLP nodes exceeds the limit 20000 (it would need about "
                        "4.98e+04 GiB of memory"),
    ("sim.duration=1e6", "sim.duration: 1e+06 s x 600 steps/s (sim.rate_hz) = 6e+08 "
                         "simulator steps exceeds the limit 1e+07"),
    # the other factor set: the --set is named, not the file
    ("sim.rate_hz=100000000", "sim.duration: 3 s x 100000000 steps/s (sim.rate_hz) = 3e+08 "
                              "simulator steps exceeds the limit 1e+07"),
    ("mpc.nodes_per_second=600000", "mpc.horizon: 3 s x 600000 nodes/s "
                                    "(mpc.nodes_per_second) = 1.8e+06 NLP nodes exceeds"),
    ("planner.samples=100000000", "planner.iterations x planner.samples: 15 iterations x "
                                  "(100000000 + 1) samples = 1.5e+09 rollouts of 180 steps"),
    ("planner.samples=1e10", "planner.samples: Input should be a valid integer"),
    # memory: named by the product's keys and blamed on the --set (was: the file's samples)
    ("planner.knots=100000000", "planner.samples x planner.knots: 2 x ((50 + 1) samples x "
                                "100000000 knots + 51 x 180 rollout steps) x 4 inputs x 8 B"),
    ("mpc.horizon=1e9", "mpc.horizon: 1e+09 s x 60 nodes/s (mpc.nodes_per_second) = 6e+10 "
                        "NLP nodes exceeds"),
])
def test_size_limits_are_checked_before_anything_is_built(work: Path, item: str, message: str):
    lines = bad_run(work, ["run", _scenario(work, "ball").name, "--set", item])
    assert lines[0].startswith(f"error: --set {item}: {message}"), lines
    # the one problem, or (huge samples) its work and its memory
    assert len(lines) == 1 or (len(lines) == 2 and "memory limit" in lines[1]), lines


def test_a_memory_limit_of_the_file_stays_the_file_s(work: Path):
    """knots in the file: the file's problem, though a --set changed the other factor."""
    name = _scenario(work, "ball", {"planner": {"knots": 100000000}}).name
    lines = bad_run(work, ["run", name, "--set", "planner.samples=60"])
    assert len(lines) == 1 and lines[0].startswith(
        f"error: {name}: planner.samples x planner.knots: 2 x ((60 + 1) samples x 100000000 "
        "knots"), lines
    assert lines[0].endswith("; lower planner.samples or planner.knots"), lines


@pytest.mark.parametrize("per_swing,nodes,build", [
    (20000, 40000, "about 85.9 GiB of memory"), (1000, 2000, "about 4.3 GiB of memory")])
def test_walking_nlp_size_limit(work: Path, per_swing: int, nodes: int, build: str):
    """The walking MPC's own limit, 1,000 nodes: its solves, not only its build, grow with
    them (2,000 nodes, under the chain's 20,000, had not run 0.03 s in 400 s)."""
    lines = bad_run(work, ["run", _scenario(work, "biped").name,
                           "--set", f"mpc.nodes_per_swing={per_swing}"])
    assert len(lines) == 1 and lines[0].startswith(
        f"error: --set mpc.nodes_per_swing={per_swing}: mpc.nodes_per_swing: 2 swings x "
        f"{per_swing} = {nodes} NLP nodes exceeds the walking MPC's limit 1000: its solves "
        "grow faster than its nodes (the first planning step took 12 s at 400 nodes; "
        f"the build alone would need {build}"), lines
    assert "at 2.2 MiB and 27 ms per node" in lines[0]


@pytest.mark.parametrize("seeds,message", [
    ("100000000", "x.toml: seeds: 100000000 seeds exceed the limit 100000"),
    ("50000", "x.toml: seeds: 2 grid cells x 50000 seeds = 100000 runs exceeds the limit "
              "20000"),
])
def test_sweep_size_limits_refuse_before_making_the_runs(work: Path, seeds: str, message: str):
    """Refused before the seed list or the runs are made: the command allocates a few MiB
    (measured: 2-3.4 MiB); the 100000 runs would take 49 MiB, the 10^8 seeds GiBs."""
    _scenario(work, "ball")
    (work / "x.toml").write_text(f'name = "x"\nscenario = "ball.toml"\nseeds = {seeds}\n'
                                 '[grid]\n"mpc.rate_hz" = [10, 20]\n')
    tracemalloc.start()
    try:
        assert bad_run(work, ["sweep", "x.toml", "--dry-run"]) == [f"error: {message}"]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, f"{peak / 2**20:.1f} MiB"


def test_unknown_system_still_reports_the_other_sections(work: Path):
    ball = _scenario(work, "ball", {"sim": {"rate_hz": 0}, "lowlevel": {"kp": math.nan}})
    lines = bad_run(work, ["run", ball.name, "--set", 'system.name="rocket"'])
    assert lines[0].startswith('error: --set system.name="rocket": system.name: unknown '
                               "system 'rocket'")
    assert sorted(lines[1:]) == ["error: ball.toml: lowlevel.kp: Input should be a finite number",
                                 "error: ball.toml: sim.rate_hz: Input should be greater than 0 "
                                 "(got 0)"]


def test_plant_problems_are_reported_with_the_others(work: Path):
    ball = _scenario(work, "ball", {"plant": {"mass": -1.0, "spin": 2}, "sim": {"rate_hz": 0}})
    assert sorted(bad_run(work, ["run", ball.name])) == [
        "error: ball.toml: plant.mass: Input should be greater than 0 (got -1.0)",
        "error: ball.toml: plant.spin: unknown key (none of the 18 keys here is close: "
        "`hmpc schema` lists them)",
        "error: ball.toml: sim.rate_hz: Input should be greater than 0 (got 0)"]


def test_empty_file(work: Path):
    (work / "empty.toml").write_text("# nothing\n")
    lines = bad_run(work, ["run", "empty.toml"])
    assert len(lines) == 1 and lines[0].startswith("error: empty.toml: file is empty")


@pytest.mark.parametrize("name", ["..", ".", "...", "a/b", "../up", "x" * 101])
def test_a_name_cannot_leave_results(work: Path, name: str):
    ball = _scenario(work, "ball", {"name": name})
    lines = bad_run(work, ["run", ball.name])
    assert len(lines) == 1 and lines[0].startswith("error: ball.toml: name: "), lines


def test_out_is_checked_before_the_solvers_are_built(work: Path):
    ball = _scenario(work, "ball").name
    (work / "afile").write_text("x")
    for out, reason in (("afile", "exists and is not a directory"),
                        ("afile/sub", "cannot create it: afile is not a directory"),
                        ("y" * 300, "name too long")):
        lines = bad_run(work, ["run", ball, "--out", out])
        assert len(lines) == 1 and lines[0].startswith(f"error: --out {out}: {reason}"), lines


# -------------------------------------------- cross-field checks that need the built system
@pytest.fixture
def real_prepare(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.mark.parametrize("system,item,message", [
    ("ball", "mpc.input_margin=60", "mpc.input_margin: 60 per side exceeds half the input box "
                                    "of mode 'outside' input 0 ([-100, 0]: half-width 50; the MPC "
                                    "would keep no input authority)"),
    ("biped", "mpc.torque_margin=3500", "mpc.torque_margin: 3500 per side exceeds half the "
                                        "input box of mode"),
    ("ball", 'mpc.solver_options={ipopt={linear_solver="ma57"}}',
     "mpc.solver_options.ipopt.linear_solver: 'ma57' is not available (available: mumps"),
    # IPOPT's own refusals name neither the option nor a way out: hmpc's name both
    ("ball", "mpc.solver_options={ipopt={max_iterr=5}}",
     "mpc.solver_options.ipopt.max_iterr: IPOPT has no option 'max_iterr' (did you mean "
     "'max_iter'?)"),
    ("ball", 'mpc.solver_options={ipopt={max_iter="x"}}',
     "mpc.solver_options.ipopt.max_iter: needs a number, got 'x'"),
    ("ball", "mpc.solver_options={ipopt={tol=-1,constraint_violation_norm_type=\"max-norm\"}}",
     "mpc.solver_options.ipopt.tol: -1 is outside IPOPT's range 0 < tol < +inf"),
    ("ball", 'mpc.solver_options={ipopt_warm={hessian_approximation="limited"}}',
     "mpc.solver_options.ipopt_warm.hessian_approximation: 'limited' is not one of 'exact', "
     "'limited-memory'; did you mean 'limited-memory'?"),
    ("ball", "mpc.solver_options={ipoptt={max_iter=5}}",
     "mpc.solver_options: the solver rejects these options (cold instance): Unknown option: "
     "ipoptt (did you mean 'ipopt'?)"),
])
def test_contradictory_settings_fail_at_set_up(real_prepare: Path, system: str, item: str,
                                               message: str):
    lines = bad_run(real_prepare, ["run", _scenario(real_prepare, system).name, "--set", item,
                                   "--out", "out"])
    assert len(lines) == 1 and lines[0].startswith(f"error: --set {item}: {message}"), lines


def test_a_refused_ipopt_option_prints_nothing_but_the_error(capfd):
    """IPOPT prints a refused value's documentation on the C stdout while hmpc probes the
    options; hmpc silences it: the error line alone."""
    import ctypes

    from hmpc_cli.mpc.solver import _option_problems, option_problems

    _option_problems.cache_clear()  # probed here, not answered from an earlier test's probe
    capfd.readouterr()
    assert option_problems("ipopt", {"ipopt": {"mu_strategy": "adaptiv"}}) == [
        "mpc.solver_options.ipopt.mu_strategy: 'adaptiv' is not one of 'monotone', "
        "'adaptive'; did you mean 'adaptive'?"]
    ctypes.CDLL(None).fflush(None)  # what the C library's stdout buffer holds, written out
    assert capfd.readouterr().out == ""


X0_PAST_CIRCLE = ("system.x0: (1, 1, 0, 0) lies past {}guard 'circle_in' of its initial mode "
                  "'outside' (gap -0.7172 < 0), so the run would start outside that mode's "
                  "domain; move system.x0 or the guard")


def test_an_initial_state_past_a_guard_of_its_mode_is_refused(real_prepare: Path):
    """x0 = (1, 1) inside a circle centred at (1.2, 1.2): it starts in mode 'outside', whose
    guard circle_in it has crossed (a crossed guard never fires), so hmpc run, hmpc tube and
    a sweep refuse it before anything is built or written."""
    name = _scenario(real_prepare, "ball", {"system": {"circle_center": [1.2, 1.2]}}).name
    message = X0_PAST_CIRCLE.format("")
    assert bad_run(real_prepare, ["run", name, "--out", "out"]) == [f"error: {name}: {message}"]
    assert bad_run(real_prepare, ["tube", name, "--out", "t"]) == [f"error: {name}: {message}"]
    (real_prepare / "x.toml").write_text(f'name = "x"\nscenario = "{name}"\nseeds = 1\n')
    assert bad_run(real_prepare, ["sweep", "x.toml"]) == [f"error: x.toml: cell the base "
                                                            f"scenario: {message}"]
    # the state set by --set is the --set's fault; the plant's own circle is checked too
    fine = _scenario(real_prepare, "ball", name="fine").name
    item = "system.x0=[3.0,3.0,0.0,0.0]"
    lines = bad_run(real_prepare, ["run", fine, "--set", item, "--out", "out"])
    assert len(lines) == 1 and lines[0].startswith(
        f"error: --set {item}: system.x0: (3, 3, 0, 0) lies past guard 'circle_in'"), lines
    item = "plant.circle_center=[1.2,1.2]"
    lines = bad_run(real_prepare, ["run", fine, "--set", item, "--out", "out"])
    assert lines == [f"error: --set {item}: "
                     f"{X0_PAST_CIRCLE.format('the plant' + chr(39) + 's ')}"]
    # a sweep checks the plant before it starts a run
    (real_prepare / "p.toml").write_text(
        f'name = "p"\nscenario = "{fine}"\nseeds = 1\n[grid]\nplant = [{{ label = "near", '
        f'"plant.circle_center" = [1.2, 1.2] }}]\n')
    lines = bad_run(real_prepare, ["sweep", "p.toml"])
    assert len(lines) == 1 and "lies past the plant's guard 'circle_in'" in lines[0], lines


def test_a_plant_whose_guards_are_not_the_models_is_refused(real_prepare: Path):
    """The controllers take a contact's guard by its place in the model's list: a plant
    with one stair more filed its landings under the wrong stair (and as unscheduled)."""
    name = _scenario(real_prepare, "biped", name="walk").name
    item = ("plant.stairs=[{length=0.2,height=0.0},{length=0.2,height=0.0},"
            "{length=1.0,height=0.075},{length=0.2,height=0.125},{length=1.25,height=0.175}]")
    assert bad_run(real_prepare, ["run", name, "--set", item, "--out", "out"]) == [
        f"error: --set {item}: plant: the simulated system has 6 guards, the model 5: the "
        "controllers name a contact by its guard's place in the model's list, so [plant] may "
        "move guards but not add, drop or reorder them (e.g. keep the number of stairs)"]
    from hmpc_cli.run.setup_checks import plant_guard_problems
    from hmpc_cli.systems.ball import BallParams, build_ball

    model = build_ball(BallParams())
    moved = build_ball(BallParams(circle_center=(4.0, 2.0), radius=0.2))
    assert plant_guard_problems(model, moved) == []
    swapped = dataclasses.replace(moved, guards=(moved.guards[1], moved.guards[0],
                                                 *moved.guards[2:]))
    assert plant_guard_problems(model, swapped)[0].startswith(
        "plant: the simulated system has its guard 0 is 'wall' (outside -> outside), the "
        "model's 'floor' (outside -> outside):")


def test_an_initial_state_on_a_guard_of_its_mode_is_refused(real_prepare: Path):
    """x0 on the floor (gap 0) moving into it: a guard fires when its gap goes from > 0 to
    <= 0 within a step, so the ball would fall through the floor; refused by the x0 check
    (not as a tube margin too large for its gap)."""
    fine = _scenario(real_prepare, "ball", name="fine").name
    item = "system.x0=[1.0,0.1,0.0,-1.0]"
    assert bad_run(real_prepare, ["run", fine, "--set", item, "--out", "out"]) == [
        f"error: --set {item}: system.x0: (1, 0.1, 0, -1) lies on guard 'floor' of its "
        "initial mode 'outside' (gap 0): a guard fires when its gap goes from > 0 to <= 0 "
        "within a step, so from there it would never fire; move system.x0 off the guard"]


def test_every_scenario_starts_inside_its_initial_mode():
    """The shipped scenarios pass the initial-state check (the biped's swing foot starts
    above the stair it stands before; the other stairs' gaps are negative outside their
    regions)."""
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.run.setup_checks import initial_state_problems

    for path in sorted((Path(__file__).resolve().parents[1] / "scenarios").glob("*.toml")):
        sc, _ = load_scenario(path)
        assert initial_state_problems(build_system(sc.system)) == [], path.name


def test_a_misspelt_hpipm_option_is_named_with_its_key_path(real_prepare: Path):
    """CasADi's HPIPM interface says "Unknown option." without the name: hmpc names it."""
    item = 'mpc.solver_options={hpipm={iter_maxx=3}}'
    lines = bad_run(real_prepare, ["run", _scenario(real_prepare, "ball").name,
                                   "--set", 'mpc.solver="rti"', "--set", 'mpc.input_hold="zoh"',
                                   "--set", item, "--out", "out"])
    assert lines == [f"error: --set {item}: mpc.solver_options.hpipm.iter_maxx: HPIPM has no "
                     "option 'iter_maxx' (did you mean 'iter_max'?)"], lines
    assert not (real_prepare / "out").exists()


def test_the_hpipm_options_named_in_that_error_exist():
    from hmpc_cli.mpc.solver import HPIPM_EXAMPLES, option_problems

    known = {k: "speed" if k == "mode" else 1 for k in HPIPM_EXAMPLES}
    assert option_problems("rti", {"hpipm": known}) == []
    assert option_problems("rti", {"hpipm": {"mu0": "x"}})[0].startswith(
        'mpc.solver_options.hpipm.mu0: HPIPM refuses "x": ')


@pytest.mark.parametrize("dry", [True, False])
def test_a_cell_the_built_system_refuses_stops_the_sweep_before_any_run(work: Path, dry: bool):
    """An input margin beyond half the ball's input box: only the built system knows."""
    _scenario(work, "ball")
    (work / "x.toml").write_text('name = "x"\nscenario = "ball.toml"\nseeds = 2\n[grid]\n'
                                 '"mpc.input_margin" = [0.0, 60.0]\n')
    lines = bad_run(work, ["sweep", "x.toml", *(["--dry-run"] if dry else [])])
    assert lines == ["error: x.toml: cell mpc.input_margin=60.0: mpc.input_margin: 60 per "
                     "side exceeds half the input box of mode 'outside' input 0 ([-100, 0]: "
                     "half-width 50; the MPC would keep no input authority)"]


@pytest.mark.parametrize("window,lines", [
    (["--from", "-5", "--to", "nan"],
     ["error: --from -5: a time in seconds from the run's start (finite, >= 0)",
      "error: --to nan: a time in seconds from the run's start (finite, >= 0)"]),
    (["--to", "inf"], ["error: --to inf: a time in seconds from the run's start (finite, >= 0)"]),
    (["--from", "2", "--to", "1"], ["error: --from 2 is after --to 1"]),
])
def test_replay_refuses_a_time_window_that_is_not_one(work: Path, window: list[str],
                                                        lines: list[str]):
    """Checked before the log is read (the log named here does not exist)."""
    assert bad_run(work, ["replay", "no_such_run", *window]) == lines


def test_a_set_value_every_cell_overrides_is_refused(work: Path):
    """[set] "mpc.rate_hz" = 20 beside an axis over mpc.rate_hz never applies: refused.
    An axis of tables that leaves the key out of some entries keeps [set] as their value."""
    _scenario(work, "ball")
    (work / "x.toml").write_text('name = "x"\nscenario = "ball.toml"\n[set]\n'
                                 '"mpc.rate_hz" = 20\n[grid]\n"mpc.rate_hz" = [10, 20]\n')
    assert bad_run(work, ["sweep", "x.toml", "--dry-run"]) == [
        "error: x.toml: set.mpc.rate_hz: never applied: every cell of grid.mpc.rate_hz sets "
        "mpc.rate_hz (remove it from [set], or leave it out of some of the axis's entries)"]
    from hmpc_cli.sweep.plan import plan_sweep

    (work / "y.toml").write_text('name = "y"\nscenario = "ball.toml"\n[set]\n'
                                 '"mpc.rate_hz" = 20\n[grid]\nc = [{ label = "fast", '
                                 '"mpc.rate_hz" = 60 }, { label = "set", "sim.duration" = 1.0 '
                                 '}]\n')
    rates = sorted(r.overrides["mpc.rate_hz"] for r in plan_sweep(work / "y.toml").runs)
    assert rates == [20, 60]


def test_a_dry_run_checks_the_output_directory_as_the_run_would(work: Path):
    _scenario(work, "ball")
    (work / "x.toml").write_text('name = "x"\nscenario = "ball.toml"\n')
    (work / "other").mkdir()
    (work / "other" / "sweep.toml").write_text('name = "other"\n')
    lines = bad_run(work, ["sweep", "x.toml", "--out", "other", "--dry-run"])
    assert len(lines) == 1 and lines[0].startswith("error: --out other: "), lines


def test_every_option_of_the_installed_ipopts_listing_is_read():
    """Each option line of IPOPT's own listing is in the catalogue, a long name touching its
    default too; a string option's values are its own, each once."""
    from hmpc_cli.mpc.ipopt_options import catalogue, listing

    heads = [line for line in listing().splitlines()
             if line[:1] not in ("", " ") and not line.startswith("###")]
    assert len(heads) > 250 and len(catalogue()) == len(heads)
    assert all(line.split("(")[0].split()[0] in catalogue() for line in heads)
    assert catalogue()["constraint_violation_norm_type"].values == (
        "1-norm", "2-norm", "max-norm")
    assert catalogue()["quality_function_centrality"].values == (
        "none", "log", "reciprocal", "cubed-reciprocal")
    assert catalogue()["max_iter"].kind == "number"
    assert all(len(set(o.values)) == len(o.values) for o in catalogue().values())


@pytest.mark.parametrize("sets,item,message", [
    (['mpc.solver="rti"'], "mpc.solver_options={max_iterr=1}",
     "mpc.solver_options.max_iterr: sqpmethod (back-end 'rti') has no option 'max_iterr' "
     "(did you mean 'max_iter'?)"),
    (['mpc.solver="sqpmethod"', 'mpc.input_hold="foh"'], "mpc.solver_options={tol_prr=1e-6}",
     "mpc.solver_options.tol_prr: sqpmethod (back-end 'sqpmethod') has no option 'tol_prr' "
     "(did you mean 'tol_pr'?)"),
    (['mpc.switching_solver="rti"'], "mpc.solver_options={hpipm={iter_maxx=3}}",
     "mpc.solver_options.hpipm.iter_maxx: HPIPM has no option 'iter_maxx' (did you mean "
     "'iter_max'?)"),
])
def test_an_option_the_other_back_ends_do_not_know_is_named_with_its_key_path(
        real_prepare: Path, sets: list[str], item: str, message: str):
    """The SQP back-ends' and a switching back-end's options are checked before the run
    like IPOPT's: the key path and CasADi's nearest option, not the build's 'failed to
    build ... Unknown option' of the whole MPC."""
    args = ["run", _scenario(real_prepare, "ball").name]
    for s in [*sets, 'mpc.input_hold="zoh"' if "foh" not in str(sets) else None, item]:
        if s is not None:
            args += ["--set", s]
    lines = bad_run(real_prepare, [*args, "--out", "out"])
    assert lines == [f"error: --set {item}: {message}"], lines
    assert not (real_prepare / "out").exists()


def test_mpc_solvers_own_options_do_not_reach_the_switching_nlps_other_back_end():
    """sqp_hpipm's switching NLP runs on IPOPT unless mpc.switching_solver says otherwise:
    an nlpsol option of sqp_hpipm (sqpmethod's tol_pr) stays with it, the IPOPT NLP gets
    its own sections; a named switching back-end the same as mpc.solver gets them all."""
    from hmpc_cli.mpc.chain.nlp import MPCSettings

    opts = {"tol_pr": 1e-6, "ipopt": {"tol": 1e-7}, "hpipm": {"iter_max": 30}}
    sections = {"ipopt": {"tol": 1e-7}, "hpipm": {"iter_max": 30}}
    s = MPCSettings(solver="sqp_hpipm", input_hold="zoh", solver_options=opts)
    assert s.options_of(0) == opts
    assert s.options_of(1) == sections
    assert s.solver_choices() == [("sqp_hpipm", opts), ("ipopt", sections)]
    same = MPCSettings(solver="sqp_hpipm", switching_solver="sqp_hpipm", input_hold="zoh",
                       solver_options=opts)
    assert same.options_of(1) == opts and same.solver_choices() == [("sqp_hpipm", opts)]
    # a switching sqp_hpipm under mpc.solver = "ipopt": its IPOPT fallback keeps the
    # user's ipopt section (a review found it dropped)
    from hmpc_cli.mpc.solver import plugin_options

    mixed = MPCSettings(solver="ipopt", switching_solver="sqp_hpipm", input_hold="zoh",
                        solver_options={"max_cpu_time": 5.0, **sections})
    assert mixed.options_of(1) == sections
    assert plugin_options("ipopt", 5, extra=mixed.options_of(1))["ipopt"]["tol"] == 1e-7


def test_an_nlpsol_option_of_sqp_hpipm_runs_beside_its_switching_nlps_ipopt(real_prepare: Path):
    """`tol_pr` (sqpmethod's) with mpc.solver = "sqp_hpipm": the switching NLP, on IPOPT,
    is built without it, and the run goes (it aborted: 'Unknown option: tol_pr')."""
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app

    res = CliRunner().invoke(app, [
        "run", _scenario(real_prepare, "ball").name, "-q", "--out", "out",
        "--set", 'mpc.solver="sqp_hpipm"', "--set", 'mpc.input_hold="zoh"',
        "--set", "mpc.solver_options={tol_pr=1e-6}", "--set", "sim.duration=0.05"])
    assert res.exit_code == 0, res.output
    assert (real_prepare / "out" / "run.mcap").is_file()


def test_a_linear_solver_probe_that_crashes_its_process_is_reported_and_the_rest_probed(
        monkeypatch: pytest.MonkeyPatch):
    """The linear solvers are probed in one child process; one that takes the process down
    (an HSL stub may) is reported as such and those after it are probed in a new one."""
    from hmpc_cli.mpc import solver

    crashing = solver._CHILD.replace(
        "for plugin, opts in json.loads(sys.argv[1]):\n",
        "for plugin, opts in json.loads(sys.argv[1]):\n"
        "    if opts.get('crash'):\n        import os; os._exit(7)\n")
    assert crashing != solver._CHILD
    monkeypatch.setattr(solver, "_CHILD", crashing)
    good, bad = ("ipopt", {"ipopt": {"max_iter": 5}}), ("ipopt", {"crash": True})
    unknown = ("ipopt", {"ipopt": {"max_iterr": 5}})
    found = solver._probe_isolated([good, bad, unknown, bad, good])
    assert found[0] is None and found[4] is None
    assert found[1] == found[3] == "the solver process crashed (exit 7)"
    assert found[2] == "Error calling IpoptInterface::finalize for 'probe': No such IPOPT " \
        "option: max_iterr"
