"""Scenario files: loading, overrides, error reporting (direct and through ``hmpc run``)."""

from __future__ import annotations

import json
import re
import shutil
import tomllib
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hmpc_cli.cli.app import app
from hmpc_cli.log.reader import read_log
from hmpc_cli.run.schema import scenario_json_schema
from hmpc_cli.run.scenario import Scenario, ScenarioError, dump_toml, load_scenario

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = REPO / "scenarios"
BALL = SCENARIOS / "ball.toml"

# "error: <file>: <key.path>: <reason>" as printed by the CLI
# (a problem with a key a --set override set is attributed to "--set key=value")
KEYED = re.compile(r"^error: (?P<file>--(?:set|seed) \S+|[^:\s]+): (?P<key>[A-Za-z_][\w.\[\]]*): "
                   r"(?P<reason>\S.*)$")


@pytest.fixture
def work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A scratch directory holding a copy of ball.toml, made the current directory."""
    shutil.copy(BALL, tmp_path / "ball.toml")
    monkeypatch.chdir(tmp_path)
    return tmp_path


#: what an unknown top-level key's line adds (no key close to it: the keys there)
TOP_KEYS = (" (the keys here: description, disturbance, lowlevel, mpc, name, planner, plant, "
            "replanning, seed, sim, system)")


def far(n: int) -> str:
    """What an unknown key's line adds when none of a section's ``n`` keys is close."""
    return f" (none of the {n} keys here is close: `hmpc schema` lists them)"


def _tree(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _with_lines(src: Path, dst: Path, **sections: str) -> Path:
    """Copies ``src`` and appends ``line`` under each ``[section]`` (``_top`` = top level)."""
    text = src.read_text(encoding="utf-8")
    lines = text.splitlines()
    for section, line in sections.items():
        if section == "_top":
            lines.insert(lines.index("name = \"ball\""), line)
        else:
            lines.insert(lines.index(f"[{section}]") + 1, line)
    return _write(dst, "\n".join(lines) + "\n")


def cli_bad(work: Path, args: list[str]) -> list[str]:
    """Runs ``hmpc run ARGS`` in ``work`` expecting bad input; returns the stderr lines.

    Checks exit code 2, no traceback, nothing on stdout and that neither the default
    results directory nor any other file was created.
    """
    before = _tree(work)
    res = CliRunner().invoke(app, ["run", *args])
    assert res.exit_code == 2, res.output
    assert isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    assert res.stdout == ""
    assert _tree(work) == before, "bad input must not create any file or directory"
    assert not (work / "results").exists()
    lines = res.stderr.splitlines()
    assert lines and all(line.startswith("error: ") for line in lines), lines
    return lines


def one_keyed(lines: list[str], file: str, key: str) -> str:
    """Asserts exactly one ``error: file: key: reason`` line; returns the reason."""
    assert len(lines) == 1, lines
    m = KEYED.match(lines[0])
    assert m, lines[0]
    assert (m["file"], m["key"]) == (file, key), lines[0]
    return m["reason"]


def load_error(*args, **kwargs) -> list[str]:
    with pytest.raises(ScenarioError) as info:
        load_scenario(*args, **kwargs)
    lines = info.value.lines
    assert str(info.value) == "\n".join(lines)
    assert all("\n" not in line for line in lines)
    return lines


# --------------------------------------------------------------- bad input, through the CLI
def test_missing_file(work: Path) -> None:
    lines = cli_bad(work, ["nope.toml"])
    assert lines == ["error: nope.toml: file not found"]
    assert load_error(work / "nope.toml") == [f"{work / 'nope.toml'}: file not found"]


def test_missing_file_with_out_creates_nothing(work: Path) -> None:
    out = work / "runs" / "x"
    cli_bad(work, ["nope.toml", "--out", str(out)])
    assert not out.exists() and not (work / "runs").exists()


def test_directory_is_not_a_scenario(work: Path) -> None:
    (work / "adir.toml").mkdir()
    assert cli_bad(work, ["adir.toml"]) == [
        "error: adir.toml: is a directory, not a scenario file"]


def test_toml_syntax_error(work: Path) -> None:
    _write(work / "syn.toml", 'name = "ball"\n[mpc\nrate_hz = 10\n')
    lines = cli_bad(work, ["syn.toml", "--out", str(work / "o")])
    assert len(lines) == 1
    assert lines[0].startswith("error: syn.toml: TOML syntax error: ")
    assert "line 2" in lines[0]
    assert not (work / "o").exists()


def test_not_utf8(work: Path) -> None:
    (work / "bin.toml").write_bytes(b'name = "\xff\xfe"\n')
    assert cli_bad(work, ["bin.toml"]) == ["error: bin.toml: not a UTF-8 text file"]
    # a run log given as the scenario: say what it is and what reads it
    (work / "run.mcap").write_bytes(b"\x89MCAP0\r\n\xff\xfe")
    assert cli_bad(work, ["run.mcap"]) == [
        "error: run.mcap: not a UTF-8 text file (a run log: `hmpc replay run.mcap` reads it; "
        "the scenario file of its run is the scenario.toml beside it)"]


def test_a_byte_order_mark_is_read_past_and_a_dangling_link_named(work: Path) -> None:
    """A UTF-8 byte-order mark (some editors write one) was a syntax error at line 1; a
    symbolic link looping on itself was 'file not found'."""
    from hmpc_cli.run.scenario import load_scenario

    (work / "bom.toml").write_bytes(b"\xef\xbb\xbf" + (work / "ball.toml").read_bytes())
    assert load_scenario(work / "bom.toml")[0] == load_scenario(work / "ball.toml")[0]
    (work / "loop.toml").symlink_to(work / "loop.toml")
    assert cli_bad(work, ["loop.toml"]) == [
        "error: loop.toml: a symbolic link to nothing (a missing file, or a loop)"]


@pytest.mark.parametrize("via_file", [False, True], ids=["set", "file"])
def test_wrong_type(work: Path, via_file: bool) -> None:
    if via_file:
        text = (work / "ball.toml").read_text()
        assert "\nrate_hz = 10\n" in text
        _write(work / "bad.toml", text.replace("\nrate_hz = 10\n", '\nrate_hz = "fast"\n'))
        lines = cli_bad(work, ["bad.toml"])
        file = "bad.toml"
    else:
        lines = cli_bad(work, ["ball.toml", "--set", 'mpc.rate_hz="fast"'])
        file = '--set mpc.rate_hz="fast"'
    reason = one_keyed(lines, file, "mpc.rate_hz")
    assert "integer" in reason


def test_wrong_type_unquoted_string(work: Path) -> None:
    # an unparsable TOML value is taken as a string, then rejected by the model
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", "sim.duration=long"]),
                       "--set sim.duration=long", "sim.duration")
    assert "number" in reason


@pytest.mark.parametrize("key,hint", [
    ("foo", TOP_KEYS), ("mpc.foo", far(22)), ("system.spin", far(18)),
    ("sim.rate", " (did you mean 'rate_hz'?)"),
    ("mpc.rate", " (did you mean 'rate_hz'?)"), ("simm", " (did you mean 'sim'?)"),
    ("planner.samles", " (did you mean 'samples'?)"), ("seeed", " (did you mean 'seed'?)"),
    ("system.circle_radiu", " (did you mean 'circle_radius'?)"),
    ("plant.mas", " (did you mean 'mass'?)")])
def test_unknown_key_via_set(work: Path, key: str, hint: str) -> None:
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", f"{key}=1"]), f"--set {key}=1", key)
    assert reason == "unknown key" + hint


def test_unknown_key_suggests_a_key_of_the_selected_kind(work: Path) -> None:
    # the biped's MPC and planner are other union members than the ball's: their keys
    biped = Path(__file__).parent.parent / "scenarios" / "biped_stairs.toml"
    lines = cli_bad(work, [str(biped), "--set", "system.circle_radiu=1"])
    assert lines == ["error: --set system.circle_radiu=1: system.circle_radiu: unknown key"
                     + far(30)]
    lines = cli_bad(work, ["ball.toml", "--set", "system.circle_radiu=1"])
    assert lines == ["error: --set system.circle_radiu=1: system.circle_radiu: unknown key "
                     "(did you mean 'circle_radius'?)"]


def test_an_unknown_system_name_suggests_the_closest(tmp_path: Path) -> None:
    f = tmp_path / "s.toml"
    f.write_text('[system]\nname = "balll"\n')
    assert load_error(f) == [f"{f}: system.name: unknown system 'balll' (did you mean "
                             "'ball'? choose from 'ball', 'biped')"]


def test_unknown_section_via_set_is_the_sets(work: Path) -> None:
    lines = cli_bad(work, ["ball.toml", "--set", "simm.rate_hz=10"])
    assert lines == ["error: --set simm.rate_hz=10: simm: unknown key (did you mean 'sim'?)"]


def test_unknown_key_in_a_file_suggests_at_every_level(work: Path) -> None:
    _with_lines(work / "ball.toml", work / "bad.toml", _top="sed = 3", sim="rate = 600",
                mpc="horizn = 1.0")
    lines = cli_bad(work, ["bad.toml"])
    assert sorted(lines) == [
        "error: bad.toml: mpc.horizn: unknown key (did you mean 'horizon'?)",
        "error: bad.toml: sed: unknown key (did you mean 'seed'?)",
        "error: bad.toml: sim.rate: unknown key (did you mean 'rate_hz'?)"]


def test_unknown_key_in_file(work: Path) -> None:
    _with_lines(work / "ball.toml", work / "bad.toml", _top="colour = 3")
    assert one_keyed(cli_bad(work, ["bad.toml"]), "bad.toml", "colour") == \
        "unknown key" + TOP_KEYS
    _with_lines(work / "ball.toml", work / "bad2.toml", mpc="foo = 1")
    assert one_keyed(cli_bad(work, ["bad2.toml"]), "bad2.toml", "mpc.foo") == \
        "unknown key" + far(22)


def test_unknown_section(work: Path) -> None:
    _write(work / "bad.toml", (work / "ball.toml").read_text() + "\n[rocket]\nthrust = 1\n")
    assert one_keyed(cli_bad(work, ["bad.toml"]), "bad.toml", "rocket") == \
        "unknown key" + TOP_KEYS


def test_unknown_system(work: Path) -> None:
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", 'system.name="rocket"']),
                       '--set system.name="rocket"', "system.name")
    assert "'ball'" in reason  # says what is allowed


@pytest.mark.parametrize("key,value", [("sim.rate_hz", "0"), ("mpc.rate_hz", "-5"),
                                       ("sim.log_rate_hz", "0"), ("mpc.nodes_per_second", "-60")])
def test_non_positive_rate(work: Path, key: str, value: str) -> None:
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", f"{key}={value}"]),
                       f"--set {key}={value}", key)
    assert "greater than 0" in reason


@pytest.mark.parametrize("rate", [7, 100, 11])
def test_non_commensurate_mpc_rate(work: Path, rate: int) -> None:
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", f"mpc.rate_hz={rate}"]),
                       f"--set mpc.rate_hz={rate}", "mpc.rate_hz")
    assert str(rate) in reason and "mpc.nodes_per_second = 60" in reason


def test_non_commensurate_other_rates(work: Path) -> None:
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", "sim.log_rate_hz=7"]),
                       "--set sim.log_rate_hz=7", "sim.log_rate_hz")
    assert "sim.rate_hz = 600" in reason
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", "sim.rate_hz=605",
                                      "--set", "sim.log_rate_hz=5"]),
                       "--set sim.rate_hz=605", "mpc.rate_hz")  # the --set it names
    assert "sim.rate_hz = 605" in reason and "nodes_per_second" not in reason
    one_keyed(cli_bad(work, ["ball.toml", "--set", "sim.duration=0.0001"]),
              "--set sim.duration=0.0001", "sim.duration")
    one_keyed(cli_bad(work, ["ball.toml", "--set", "mpc.horizon=0.001"]),
              "--set mpc.horizon=0.001", "mpc.horizon")


def test_disturbance_knots_on_simulator_steps(work: Path) -> None:
    # each process holds its values on a knot grid the simulator must step on: the paper's
    # 0.05 s (at 30 Hz its knots fell between steps and were applied up to 1/60 s late)
    fig3 = ["--set", 'disturbance.kind="paper_fig3"', "--set", "disturbance.magnitude=10"]
    reason = one_keyed(cli_bad(work, ["ball.toml", *fig3, "--set", "sim.rate_hz=30",
                                      "--set", "sim.log_rate_hz=30"]),
                       '--set disturbance.kind="paper_fig3"', "disturbance.kind")
    assert reason == ("paper_fig3 holds each value 0.05 s, which must be a whole number of "
                      "simulator steps (1/sim.rate_hz = 1/30 s); pick a sim.rate_hz that is "
                      "a multiple of 20")
    box = ["--set", 'disturbance.kind="box"', "--set", "disturbance.magnitude=1"]
    reason = one_keyed(cli_bad(work, ["ball.toml", *box, "--set", "disturbance.hold=0.0025"]),
                       "--set disturbance.hold=0.0025", "disturbance.hold")
    assert reason == ("0.0025 s must be a whole number of simulator steps "
                      "(1/sim.rate_hz = 1/600 s)")


@pytest.mark.parametrize("item", ["nokey", "=3", " =3", ""])
def test_set_bad_syntax(work: Path, item: str) -> None:
    lines = cli_bad(work, ["ball.toml", "--set", item])
    assert lines == [f"error: --set {item!r}: expected key.path=value"]


def test_set_through_a_scalar(work: Path) -> None:
    lines = cli_bad(work, ["ball.toml", "--set", "mpc.rate_hz.x=1"])
    assert lines == ["error: --set 'mpc.rate_hz.x=1': mpc.rate_hz is a value (10), not a "
                     "table, so mpc.rate_hz.x names no key: set mpc.rate_hz itself"]


@pytest.mark.parametrize("text,reason", [
    ("sim = 5", "must be a table of settings, not 5: write [sim] with its keys below it, or "
                "sim = {key = value, ...}"),
    ("[[sim]]\nduration = 0.3", "an array of tables ([[sim]]), not one table: write [sim] "
                                "once, its keys below it"),
    ('sim = "fast"', 'must be a table of settings, not "fast": write [sim] with its keys below '
                     "it, or sim = {key = value, ...}")])
def test_a_section_written_as_another_value_says_how_to_write_a_table(work: Path, text: str,
                                                                      reason: str) -> None:
    """A section given as a number, text or an array of tables: the message named pydantic's
    class ("a valid dictionary or instance of SimSettings") and said nothing of TOML."""
    _write(work / "bad.toml", f'name = "ball"\n{text}\n[system]\nname = "ball"\n')
    assert cli_bad(work, ["bad.toml"]) == [f"error: bad.toml: sim: {reason}"]


@pytest.mark.parametrize("item,reason", [
    ("sim.rate_hz={x=1}", "Input should be a valid integer (got a table: this key takes one "
                          "value)"),
    ("sim.rate_hz=[1,2]", "Input should be a valid integer (got an array: this key takes one "
                          "value)"),
    ("sim.delay_compensation={}", "Input should be a valid boolean (got a table: this key "
                                  "takes one value)"),
    ("system.x0={a=1}", "Input should be a valid tuple (got a table: write an array, "
                        "[a, b, ...])")])
def test_a_table_or_array_where_one_value_belongs_says_so(work: Path, item: str,
                                                          reason: str) -> None:
    """pydantic's "Input should be a valid integer" did not say a table was given."""
    key = item.partition("=")[0]
    assert cli_bad(work, ["ball.toml", "--set", item]) == [
        f"error: --set {item}: {key}: {reason}"]


def test_an_empty_margins_value_is_said_empty(work: Path) -> None:
    """``mpc.margins = ""`` was read as the scenario's directory ("a directory, not a margins
    file")."""
    assert cli_bad(work, ["ball.toml", "--set", 'mpc.margins=""']) == [
        'error: --set mpc.margins="": mpc.margins: empty: give "hand", "tube" or a margins '
        "file's path"]


def test_two_problems_two_lines(work: Path) -> None:
    lines = cli_bad(work, ["ball.toml", "--set", "mpc.foo=1", "--set", 'sim.rate_hz="x"'])
    assert len(lines) == 2, lines
    found = {KEYED.match(line)["key"]: KEYED.match(line)["reason"] for line in lines}
    assert found.keys() == {"mpc.foo", "sim.rate_hz"}
    assert found["mpc.foo"] == "unknown key" + far(22)


def test_two_rate_problems_two_lines(work: Path) -> None:
    lines = cli_bad(work, ["ball.toml", "--set", "mpc.rate_hz=7", "--set", "sim.log_rate_hz=7"])
    assert [KEYED.match(line)["key"] for line in lines] == ["mpc.rate_hz", "sim.log_rate_hz"]


def test_two_bad_sets_two_lines(work: Path) -> None:
    lines = cli_bad(work, ["ball.toml", "--set", "a", "--set", "b"])
    assert lines == ["error: --set 'a': expected key.path=value",
                     "error: --set 'b': expected key.path=value"]


def test_negative_seed(work: Path) -> None:
    """The --seed is at fault, not the file."""
    one_keyed(cli_bad(work, ["ball.toml", "--seed", "-1"]), "--seed -1", "seed")


def test_bad_solver_options_no_traceback(work: Path) -> None:
    # passes validation but CasADi refuses it while the loop is built
    lines = cli_bad(work, ["ball.toml", "--set", "mpc.solver_options={bogus_option=1}"])
    assert len(lines) == 1 and lines[0].startswith(
        "error: --set mpc.solver_options={bogus_option=1}: mpc.solver_options: ")
    assert "bogus_option" in lines[0]


def test_unknown_contact_guard(work: Path) -> None:
    reason = one_keyed(cli_bad(work, ["ball.toml", "--set", "replanning.policy=on_contact",
                                      "--set", 'replanning.contact_guards=["x"]']),
                       '--set replanning.contact_guards=["x"]', "replanning.contact_guards")
    assert "'x'" in reason


def test_unknown_contact_guard_names_the_guards_and_the_closest(work: Path) -> None:
    item = 'replanning.contact_guards=["flor", "x"]'
    assert cli_bad(work, ["ball.toml", "--set", "replanning.policy=on_contact", "--set",
                          item]) == [
        f"error: --set {item}: replanning.contact_guards: unknown guards 'flor' (did you mean "
        "'floor'?), 'x'; the system's guards: 'floor', 'wall', 'circle_in', 'circle_out'"]


def test_bad_input_in_a_real_process(tmp_path: Path, run_hmpc) -> None:
    _write(tmp_path / "bad.toml", 'name = "ball"\n[mpc]\nrate_hz = 7\nfoo = 1\n')
    proc = run_hmpc(["run", "bad.toml", "--set", "sim.rate_hz=0"], cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert "Traceback" not in proc.stderr
    assert sorted(proc.stderr.splitlines()) == [
        "error: --set sim.rate_hz=0: sim.rate_hz: Input should be greater than 0 (got 0)",
        "error: bad.toml: mpc.foo: unknown key" + far(22)]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


# ------------------------------------------------------------------ load_scenario directly
def test_an_empty_key_part_and_a_margins_file_elsewhere_are_named(tmp_path, monkeypatch):
    """``--set sim..duration=3`` said "sim.: unknown key"; a directory as mpc.margins was
    "file not found"; a relative mpc.margins read from the scenario's directory while the
    file sits in the current one (hmpc tube --write writes it there) now says so."""
    (tmp_path / "sc").mkdir()
    path = _write(tmp_path / "sc" / "s.toml", '[system]\nname = "ball"\n')
    assert load_scenario(path, ["sim . duration=1.5"])[0].sim.duration == 1.5  # as TOML reads
    for item in ("sim..duration=3", ".sim.duration=3", "sim.duration.=3"):
        key = item.partition("=")[0]
        assert load_error(path, [item]) == [
            f"--set {item!r}: {key!r} has an empty part: the key is dotted names, e.g. "
            "sim.duration"]
    (tmp_path / "dir").mkdir()
    assert load_error(path, [f'mpc.margins="{tmp_path / "dir"}"']) == [
        f"--set mpc.margins=\"{tmp_path / 'dir'}\": mpc.margins: {tmp_path / 'dir'}: a "
        "directory, not a margins file"]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "m.toml").write_text("")
    assert load_error(path, ['mpc.margins="m.toml"']) == [
        f"--set mpc.margins=\"m.toml\": mpc.margins: file not found: {tmp_path}/sc/m.toml (a "
        "relative mpc.margins is read from the scenario file's directory; m.toml is in the "
        "current directory: name it '../m.toml' or by its absolute path)"]


def test_a_misspelled_choice_names_the_value_given_and_the_closest_choice(tmp_path) -> None:
    """A literal setting's error said only what it should be: it names the value given and
    the closest choice (another case, or a near spelling), as unknown keys do."""
    path = _write(tmp_path / "s.toml", '[disturbance]\nkind = "paper_fig33"\n')
    assert load_error(path) == [f"{path}: disturbance.kind: Input should be 'none', 'box' or "
                                f"'paper_fig3' (got \"paper_fig33\") (did you mean "
                                f"'paper_fig3'?)"]
    path = _write(tmp_path / "t.toml", '[system]\nname = "ball"\n')
    assert load_error(path, ['sim.latency="measurd"']) == [
        "--set sim.latency=\"measurd\": sim.latency: expected 'paused', 'measured', 'model' or "
        "a delay in [0, 1e6) s, got 'measurd' (did you mean 'measured'?)"]
    assert sorted(load_error(path, ['lowlevel.past_guard="Hold"', 'replanning.policy="zzz"'])) == [
        "--set lowlevel.past_guard=\"Hold\": lowlevel.past_guard: Input should be 'hold' or "
        "'next_domain' (got \"Hold\") (did you mean 'hold'?)",
        "--set replanning.policy=\"zzz\": replanning.policy: Input should be 'once', "
        "'on_contact' or 'periodic' (got \"zzz\")"]


def test_load_errors_directly(tmp_path: Path) -> None:
    path = _write(tmp_path / "s.toml", "[mpc]\nrate_hz = 7\n[sim]\nrate_hz = -1\n")
    lines = load_error(path)
    assert lines == [f"{path}: sim.rate_hz: Input should be greater than 0 (got -1)"]
    lines = load_error(path, ["sim.rate_hz=600", "mpc.bar=2"])
    assert lines == ["--set mpc.bar=2: mpc.bar: unknown key" + far(22),  # and the rate one
                     f"{path}: mpc.rate_hz: 7 must divide mpc.nodes_per_second = 60 and "
                     "sim.rate_hz = 600 (the MPC period must be a whole number of node steps "
                     "and of simulator steps)"]
    lines = load_error(path, ["sim.rate_hz=600"])
    assert len(lines) == 1 and lines[0].startswith(f"{path}: mpc.rate_hz: 7 must divide")
    assert not any("(top)" in line for line in load_error(path, ["sim.rate_hz=601"]))


def test_defaults_and_name_from_file(tmp_path: Path) -> None:
    sc, text = load_scenario(_write(tmp_path / "empty_one.toml", "seed = 0\n"))
    assert sc == Scenario(name="empty_one")
    assert tomllib.loads(text)["name"] == "empty_one"


def test_overrides_take_effect() -> None:
    base, _ = load_scenario(BALL)
    sc, text = load_scenario(BALL, [
        "mpc.max_iter=77",                 # int
        "sim.duration=0.5",                # float
        "system.drag=2.5e-2",              # float, exponent
        'mpc.integrator="euler"',          # quoted string
        "lowlevel.feedforward=zoh",        # bare word -> string
        "mpc.warm_start=false",            # bool
        "planner.adapt_covariance=true",   # bool
        "system.goal=[2.5, 3]",            # array
        "mpc.solver_options={print_level=0}",  # inline table
        'disturbance.kind="box"',          # section present in the file
        "mpc.rate_hz=5", "mpc.rate_hz=20",  # the last one wins
    ])
    assert (sc.mpc.max_iter, sc.sim.duration, sc.system.drag) == (77, 0.5, 0.025)
    assert isinstance(sc.mpc.max_iter, int) and isinstance(sc.sim.duration, float)
    assert (sc.mpc.integrator, sc.lowlevel.feedforward) == ("euler", "zoh")
    assert sc.mpc.warm_start is False and base.mpc.warm_start is True
    assert sc.planner.adapt_covariance is True and base.planner.adapt_covariance is False
    assert sc.system.goal == (2.5, 3.0)
    assert sc.mpc.solver_options == {"print_level": 0}
    assert sc.disturbance.kind == "box" and sc.mpc.rate_hz == 20
    # everything else untouched
    assert sc.model_copy(update={
        "mpc": base.mpc, "sim": base.sim, "system": base.system, "lowlevel": base.lowlevel,
        "planner": base.planner, "disturbance": base.disturbance}) == base
    # the effective TOML holds the overrides
    data = tomllib.loads(text)
    assert data["mpc"]["max_iter"] == 77 and data["mpc"]["warm_start"] is False
    assert data["disturbance"]["kind"] == "box"


def test_override_creates_missing_table(tmp_path: Path) -> None:
    path = _write(tmp_path / "mini.toml", 'name = "mini"\n')
    sc, _ = load_scenario(path, ["lowlevel.kp=3", "disturbance.magnitude=1.5"])
    assert sc.lowlevel.kp == 3.0 and sc.disturbance.magnitude == 1.5


def test_override_value_is_toml_not_string() -> None:
    # 123 is a TOML integer, not the string "123": the str field rejects it
    lines = load_error(BALL, ["description=123"])
    assert lines == ["--set description=123: description: Input should be a valid string "
                     '(a number here; text is quoted in TOML: "123")']
    assert load_scenario(BALL, ['description="123"'])[0].description == "123"


def test_seed_override() -> None:
    assert load_scenario(BALL)[0].seed == 0
    assert load_scenario(BALL, seed=42)[0].seed == 42
    assert load_scenario(BALL, ["seed=5"])[0].seed == 5
    assert load_scenario(BALL, ["seed=5"], seed=9)[0].seed == 9  # --seed wins
    assert tomllib.loads(load_scenario(BALL, seed=42)[1])["seed"] == 42


@pytest.mark.parametrize("overrides", [
    [],
    ['description="quote \\" backslash \\\\ tab \\t newline \\n del \\u007f smile \\U0001F600"',
     "mpc.solver_options={\"ipopt.tol\"=1e-8, print_level=0, nested={a=[1, 2.5]}}",
     "system.terminal_radius=0.05", 'replanning.contact_guards=["wall", "floor"]',
     "sim.event_time_tol=1e-12", "sim.divergence_bound=1e300", "system.x0=[-0.0, 1, 2, 3]"],
])
def test_effective_toml_round_trips(tmp_path: Path, overrides: list[str]) -> None:
    sc, text = load_scenario(BALL, overrides)
    path = _write(tmp_path / "again.toml", text)
    again, text2 = load_scenario(path)
    assert again == sc
    assert text2 == text
    assert dump_toml(sc.model_dump(mode="json", exclude_none=True)) == text


@pytest.mark.slow
def test_cli_overrides_and_seed_reach_the_run(tmp_path: Path, run_hmpc) -> None:
    out = tmp_path / "o"
    proc = run_hmpc(["run", str(BALL), "--out", str(out), "-q", "--seed", "11",
                     "--set", "sim.duration=0.06", "--set", "planner.iterations=1",
                     "--set", "planner.samples=4", "--set", "mpc.warm_start=false",
                     "--set", 'description="short"', "--set", "sim.log_rate_hz=50",
                     "--set", "system.goal=[2.5, 3.5]"], cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    written, _ = load_scenario(out / "scenario.toml")
    assert written.seed == 11 and written.sim.duration == 0.06
    assert (written.planner.iterations, written.planner.samples) == (1, 4)
    assert written.mpc.warm_start is False and written.description == "short"
    assert written.system.goal == (2.5, 3.5)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["seed"] == 11 and summary["t_end"] == pytest.approx(0.06)
    log = read_log(out / "run.mcap")
    (info,) = log.topic("/run/info")
    assert info.data["seed"] == 11
    assert Scenario.model_validate(json.loads(info.data["scenario_json"])) == written
    assert len(log.topic("/sim/state")) == 0.06 * 50 + 1


# --------------------------------------------------------------------- schema and bundle
def test_schema_command() -> None:
    res = CliRunner().invoke(app, ["schema"])
    assert res.exit_code == 0, res.output
    schema = json.loads(res.stdout)
    assert schema == scenario_json_schema()
    props = schema["properties"]
    for key in ("system", "sim", "mpc", "planner", "lowlevel", "disturbance", "replanning"):
        assert key in props, key
    assert schema.get("additionalProperties") is False
    assert props["sim"]["$ref"].startswith("#/$defs/")
    sim_def = schema["$defs"][props["sim"]["$ref"].rsplit("/", 1)[1]]
    assert sim_def["properties"]["rate_hz"]["type"] == "integer"


def test_a_standard_validator_accepts_what_hmpc_accepts_and_rejects_its_bounds(
        tmp_path: Path) -> None:
    """The schema an editor reads (Draft 2020-12): every bundled scenario and a table
    without its kind are valid (a kind left out is the system's default); a number past
    a field's bound or the magnitude limit, an unknown kind and an unknown key are not."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(scenario_json_schema())
    for path in sorted(SCENARIOS.glob("*.toml")):
        data = tomllib.loads(path.read_text(encoding="utf-8"))
        assert list(validator.iter_errors(data)) == [], path.name
    for good in ({"mpc": {"rate_hz": 20}}, {"planner": {"iterations": 3}},
                 {"system": {"name": "biped"}, "mpc": {"kind": "walking"}}):
        assert list(validator.iter_errors(good)) == [], good
        load_scenario(_write(tmp_path / "good.toml", dump_toml(good)))  # hmpc accepts it
    for bad in ({"system": {"terminal_radius": 0.0}}, {"system": {"radius": 2e9}},
                {"sim": {"duration": -1e10}}, {"mpc": {"kind": "nope"}},
                {"mpc": {"rate": 20}}):
        assert list(validator.iter_errors(bad)), bad


BUNDLED = sorted(SCENARIOS.glob("*.toml"))


def test_bundle_is_not_empty() -> None:
    assert BALL in BUNDLED


@pytest.mark.parametrize("path", BUNDLED, ids=[p.name for p in BUNDLED])
def test_bundled_scenario(path: Path, tmp_path: Path) -> None:
    first = path.read_text(encoding="utf-8").splitlines()[0]
    assert first.startswith("#:schema "), first
    assert (path.parent / first.removeprefix("#:schema ").strip()).is_file(), first
    sc, text = load_scenario(path)
    assert sc.name
    assert load_scenario(_write(tmp_path / path.name, text))[0] == sc


@pytest.mark.parametrize("system,override,expected", [
    ("biped_stairs.toml", 'mpc.kind="fixed_mode"', "mpc.kind: the biped's swing needs the "
     "walking transcription"),
    ("biped_stairs.toml", 'planner.kind="cem"', "planner.kind: the biped's hybrid problem"),
    ("ball.toml", 'mpc.kind="walking"', "mpc.kind: 'walking' does not fit system 'ball': it "
     "needs WalkerModel, guard_surfaces, terrain (use 'fixed_mode')"),
    ("ball.toml", 'planner.kind="footholds"', "planner.kind: 'footholds' does not fit system "
     "'ball': it needs WalkerModel, guard_surfaces (use 'cem')"),
])
def test_a_kind_the_system_cannot_use_is_one_keyed_line(system, override, expected):
    """Reported before the section's other keys are checked against the wrong kind."""
    lines = load_error(SCENARIOS / system, [override])
    assert len(lines) == 1 and f": {expected}" in lines[0], lines


def test_field_and_cross_field_problems_are_reported_together(work: Path) -> None:
    # a wrong type (a field error) and rates that do not divide (a check across settings)
    _with_lines(work / "ball.toml", work / "bad.toml", planner="elites = 0",
                sim="log_rate_hz = 7", replanning="period = 0.1234")
    lines = cli_bad(work, ["bad.toml"])
    assert lines == ["error: bad.toml: planner.elites: Input should be greater than or equal to 1 "
                     "(got 0)",
                     "error: bad.toml: sim.log_rate_hz: 7 must divide sim.rate_hz = 600"]
    lines = cli_bad(work, ["bad.toml", "--set", 'replanning.policy="periodic"'])
    assert lines == ["error: bad.toml: planner.elites: Input should be greater than or equal to 1 "
                     "(got 0)",
                     "error: bad.toml: sim.log_rate_hz: 7 must divide sim.rate_hz = 600",
                     "error: bad.toml: replanning.period: 0.1234 s must be a whole number of "
                     "simulator steps (1/sim.rate_hz = 1/600 s)"]


def test_a_cross_field_problem_about_a_wrong_key_is_not_guessed(tmp_path: Path) -> None:
    # sim.rate_hz is wrong: whether mpc.rate_hz divides it cannot be told (no default guess)
    path = _write(tmp_path / "s.toml", "[mpc]\nrate_hz = 7\n[sim]\nrate_hz = -1\n"
                  "log_rate_hz = 0\nduration = 0.0001\n")
    assert load_error(path) == [f"{path}: sim.rate_hz: Input should be greater than 0 (got -1)",
                                f"{path}: sim.log_rate_hz: Input should be greater than 0 "
                                "(got 0)"]


def test_a_sweep_file_given_as_a_scenario_and_back_says_which_command_takes_it():
    from hmpc_cli.sweep.plan import plan_sweep

    sweep = REPO / "sweeps" / "fig3.toml"
    with pytest.raises(ScenarioError) as err:
        load_scenario(sweep)
    assert err.value.lines == [f"{sweep}: this looks like a sweep file (it has scenario, "
                               f"seeds and a grid or set): run it with `hmpc sweep {sweep}`"]
    ball = BALL
    with pytest.raises(ScenarioError) as err:
        plan_sweep(ball)
    assert err.value.lines == [  # that line alone: the keys' errors all follow from it
        f"{ball}: this looks like a scenario file (it has system and mpc, no scenario): run "
        f"it with `hmpc run {ball}`, or name it in a sweep file's `scenario`"]


def test_a_set_up_problem_a_set_causes_is_the_sets(work):
    """Problems the set-up checks find on the built model (after validation) are the
    ``--set``'s when they go away without it, whatever key they name."""
    circle = "system.circle_center=[1.2,1.2]"
    assert cli_bad(work, ["ball.toml", "--set", circle]) == [
        f"error: --set {circle}: system.x0: (1, 1, 0, 0) lies past guard 'circle_in' of its "
        "initial mode 'outside' (gap -0.7172 < 0), so the run would start outside that mode's "
        "domain; move system.x0 or the guard"]
    option = "mpc.solver_options.ipopt.nosuch_option=1"
    assert cli_bad(work, ["ball.toml", "--set", "sim.duration=1", "--set", option]) == [
        f"error: --set {option}: mpc.solver_options.ipopt.nosuch_option: IPOPT has no option "
        "'nosuch_option' (IPOPT's options: https://coin-or.github.io/Ipopt/OPTIONS.html)"]


@pytest.mark.parametrize("centre,surface,span", [
    ("[1.5,0.6]", "floor's guard y = radius = 0.1 over [0.634, 2.366]", "floor"),
    ("[1.0,3.0]", "wall's guard x = radius = 0.1 over [2.564, 3.436]", "wall"),
    ("[-0.5,0.5]", "floor's guard y = radius = 0.1 over [0, 0.4165]", "floor")])
def test_a_circle_reaching_floor_or_wall_is_refused(work, centre, surface, span):
    """Floor and wall bounce only ``outside``: a circle across them let the ball fall
    through the floor inside it and leave the circle below it (exit 0, no warning)."""
    lines = cli_bad(work, ["ball.toml", "--set", f"system.circle_center={centre}"])
    reason = one_keyed(lines, f"--set system.circle_center={centre}", "system")
    assert f"reaches the {surface}: inside the circle the ball does not bounce" in reason
    assert reason.endswith(f"move circle_center at least circle_radius + radius from the {span}")


def test_a_circle_clear_of_floor_and_wall_is_taken() -> None:
    from hmpc_cli.systems.ball import BallParams

    BallParams(circle_center=(1.1, 1.1))  # tangent to both guard lines: never below them
    BallParams(circle_center=(9.5, 0.5))  # across the floor's line beyond its extent
    BallParams(circle_center=(0.5, -1.0), circle_radius=0.5)  # below the floor's line


def test_a_hand_margin_that_fails_at_x0_is_refused(work):
    """A hand-set tube margin whose guard-avoid tightening x0 already violates is refused
    as the tube's own margins are (every solve would be softened from the first node)."""
    assert cli_bad(work, ["ball.toml", "--set", "mpc.tube_margin=0.95"]) == [
        "error: --set mpc.tube_margin=0.95: mpc.tube_margin: 0.95 tightens the guard-avoid "
        "row of floor by kappa = 0.95, more than its gap at x0 (0.9): the tightened problem "
        "is infeasible at the initial state (choose a smaller mpc.tube_margin)"]
    _write(work / "wide.toml", BALL.read_text().replace("tube_margin = 0.025",
                                                        "tube_margin = 0.95"))
    assert cli_bad(work, ["wide.toml"])[0].startswith(
        "error: wide.toml: mpc.tube_margin: 0.95 tightens the guard-avoid row of floor")


def test_common_slips_in_a_set_get_a_way_out():
    """A key in the wrong case, an unknown kind, malformed TOML syntax: each says what to
    write instead (the bare-word text value stays a string)."""
    assert load_error(BALL, ["MPC.rate_hz=20"]) == [
        "--set MPC.rate_hz=20: MPC: unknown key (did you mean 'mpc'?)"]
    assert load_error(BALL, ["planner.kind=cme"]) == [
        "--set planner.kind=cme: planner: unknown kind 'cme' (did you mean 'cem'?); choose "
        "from 'cem', 'footholds', 'schedule'"]
    (line,) = load_error(BALL, ["system.x0=[1,1,0"])  # the parser's words vary by Python
    assert line.startswith("--set 'system.x0=[1,1,0': the value is not valid TOML (")
    assert line.endswith("); a text value needs no quotes, an array [a, b], a table {k = v}")
    sc, _ = load_scenario(BALL, ["description=a bare word"])
    assert sc.description == "a bare word"
    # a kind that is no name: an error line, not a traceback from the plug-ins' lookup
    assert load_error(BALL, ["planner.kind=[1]"]) == [
        "--set planner.kind=[1]: planner: unknown kind '[1]'; choose from 'cem', 'footholds', "
        "'schedule'"]


def test_a_disturbance_setting_its_kind_ignores_is_named():
    from hmpc_cli.run.scenario import inert_settings

    disturbed = SCENARIOS / "ball_disturbed.toml"
    assert inert_settings(disturbed) == []
    assert inert_settings(disturbed, ["disturbance.hold=0.2"]) == [
        "--set disturbance.hold=0.2: disturbance.hold: no effect with disturbance.kind = "
        "'paper_fig3' (the paper's sequence holds each value 0.05 s)"]
    assert inert_settings(BALL, ["disturbance.trial=3", "disturbance.magnitude=5"]) == [
        "--set disturbance.magnitude=5: disturbance.magnitude: no effect with "
        "disturbance.kind = 'none'",
        "--set disturbance.trial=3: disturbance.trial: no effect with disturbance.kind = "
        "'none' (trial picks a paper_fig3 sequence)"]
    for scenario in sorted(SCENARIOS.glob("*.toml")):  # the shipped ones set nothing idle
        assert inert_settings(scenario) == [], scenario
        assert inert_settings(scenario, [], load_scenario(scenario)[0]) == [], scenario


def test_a_setting_another_setting_switches_off_is_named(tmp_path):
    """Given keys the run ignores because of another setting: the --set that gave them,
    or the file; a key left at its default is not named."""
    from hmpc_cli.run.scenario import inert_settings

    def inert(sets, path=BALL):
        return inert_settings(path, sets, load_scenario(path, sets)[0])

    assert inert(["replanning.period=0.3", "replanning.contact_guards=['floor']"]) == [
        '--set replanning.period=0.3: replanning.period: no effect with replanning.policy = '
        '"once" (only "periodic" replans on a period)',
        "--set replanning.contact_guards=['floor']: replanning.contact_guards: no effect with "
        'replanning.policy = "once" (only "on_contact" replans at contacts)']
    assert inert(["replanning.policy=periodic", "replanning.period=0.3"]) == []
    assert inert(["sim.latency=0.02", "sim.latency_model.per_iteration=0.001"]) == [
        "--set sim.latency_model.per_iteration=0.001: sim.latency_model: no effect with "
        'sim.latency = 0.02 (only "model" charges its compute times)']
    assert inert(["planner.min_cov=2.0", "planner.adapt_covariance=true"]) == [
        "--set planner.adapt_covariance=true: planner.adapt_covariance: no effect with "
        "planner.elites = 1 (the variance is refitted to two elites or more)",
        "--set planner.min_cov=2.0: planner.min_cov: no effect with planner.elites = 1 (the "
        "floor of a refitted variance)"]
    assert inert(["planner.elites=4", "planner.adapt_covariance=true", "planner.min_cov=2.0"]
                 ) == []
    assert inert(["planner.elites=4", "planner.min_cov=2.0"]) == [
        "--set planner.min_cov=2.0: planner.min_cov: no effect with planner.adapt_covariance = "
        "false (the floor of a refitted variance)"]
    assert inert(['mpc.margins="tube"', "mpc.tube_margin=0.1"]) == [
        '--set mpc.tube_margin=0.1: mpc.tube_margin: no effect with mpc.margins = "tube" '
        "(its margins replace the hand-set ones)"]
    own = tmp_path / "own.toml"
    own.write_text('[system]\nname = "ball"\n[replanning]\nperiod = 0.3\n')
    assert inert([], own) == [f'{own}: replanning.period: no effect with replanning.policy = '
                              '"once" (only "periodic" replans on a period)']
