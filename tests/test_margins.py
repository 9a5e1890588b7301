"""Margins files: ``hmpc tube --write``, ``mpc.margins`` in a scenario, the run log's record."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import BALL
from hmpc_cli.cli.app import app
from hmpc_cli.core.messages import ConstraintMargins
from hmpc_cli.log.reader import read_log
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.scenario import ScenarioError, load_scenario
from hmpc_cli.tube import analyse, region_from_scenario
from hmpc_cli.tube.margins_file import (
    constraint_margins, margins_text, params_hash, read_margins, write_margins)

SHORT = ["--set", "sim.duration=0.6", "-q"]


def _report(scenario: Path = BALL, magnitude: float = 10.0, kind: str = "box"):
    sc, _ = load_scenario(scenario)
    system = build_system(sc.system)
    report = analyse(system, region=region_from_scenario(system, None), kind=kind,
                     magnitude=magnitude, kp=1.0, kd=0.5, rate_hz=30, samples=300)
    return sc, system, report


def test_margins_file_round_trip(tmp_path: Path):
    sc, system, report = _report()
    path = tmp_path / "m.toml"
    write_margins(path, report, scenario=sc.name, params=sc.system, kind="box",
                  magnitude=10.0, samples=300)
    text = path.read_text()
    assert text.startswith("# hmpc margins file, written by hmpc ")
    assert params_hash(sc.system) in text.splitlines()[1] and "[rates.30]" in text
    mf = read_margins(path)
    assert (mf.system, mf.scenario, mf.params_hash) == ("ball", "ball", params_hash(sc.system))
    assert mf.rate_hz == 30.0 and mf.disturbance == {"kind": "box", "magnitude": 10.0}
    assert sorted(float(k) for k in mf.rates) == [r.rate_hz for r in report.rows]
    for row in report.rows:
        got = mf.at(row.rate_hz)
        assert got.radius == row.diam and got.dt == row.dt and got.zeta == row.margins.zeta
        for g in row.margins.guards:  # floats round-trip exactly
            assert (got.guards[g.guard].avoid, got.guards[g.guard].pass_through) == \
                (g.avoid, g.pass_through)
        for i in row.margins.inputs:
            assert got.inputs[i.mode] == list(i.per_side)
    assert mf.at(7) is None
    # the MPC's value object, in system order
    cm = constraint_margins(path, system, sc.system, 20)
    row = report.row(20.0)
    assert cm.source == str(path) and cm.radius == row.diam
    assert cm.avoid == tuple(g.avoid for g in row.margins.guards)
    assert cm.pass_through == tuple(g.pass_through for g in row.margins.guards)
    assert cm.entered == tuple(g.kappa(0.0, past=False) for g in system.guards)
    assert cm.inputs == tuple(i.per_side for i in row.margins.inputs)
    assert margins_text(report, scenario=sc.name, params=sc.system, kind="box",
                        magnitude=10.0, samples=300) == text


def test_hand_margins_are_todays_numbers():
    sc, _ = load_scenario(BALL)
    system = build_system(sc.system)
    hand = ConstraintMargins.hand(system, 0.025, 0.1)
    assert hand.source == "hand" and hand.radius == 0.025
    for i, g in enumerate(system.guards):
        assert hand.avoid[i] == g.kappa(0.025, past=False)
        assert hand.entered[i] == g.kappa(0.0, past=False)
        assert hand.pass_through[i] == g.kappa(0.025, past=True)
    assert hand.inputs == ((0.1, 0.1),) * len(system.modes)
    lo = np.array(system.modes[0].u_lower) + 0.1
    assert np.array_equal(lo, np.array(system.modes[0].u_lower) + np.array(hand.inputs[0]))
    with pytest.raises(ValueError, match="no margins for floor"):
        ConstraintMargins.by_name(system, "f", 0.0, {}, {})


@pytest.fixture(scope="module")
def ball_file(tmp_path_factory) -> Path:
    """``hmpc tube scenarios/ball.toml --write F`` (no disturbance: every margin 0)."""
    base = tmp_path_factory.mktemp("tube")
    f = base / "sub" / "ball_margins.toml"
    res = CliRunner().invoke(app, ["tube", str(BALL), "--write", str(f), "--out",
                                   str(base / "tube"), "--samples", "500", "--formats", "png"])
    assert res.exit_code == 0, res.output
    assert f"wrote margins file {f}" in " ".join(res.output.split())
    return f


def _edit(src: Path, dst: Path, pattern: str, repl: str) -> Path:
    text, n = re.subn(pattern, repl, src.read_text(), flags=re.M)
    assert n, pattern
    dst.write_text(text)
    return dst


@pytest.mark.parametrize("case", ["system", "params", "rate", "missing", "widening shrink",
                                  "loosening offset", "format", "no format"])
def test_a_margins_file_that_does_not_fit_exits_2(case: str, ball_file: Path, tmp_path: Path):
    m = tmp_path / "m.toml"
    f = {"system": lambda: _edit(ball_file, m, r'^system = "ball"', 'system = "biped"'),
         "widening shrink": lambda: _edit(ball_file, m, r"^(\[rates\.10\.inputs\].*\n"
                                          r"outside = )\[0\.0", r"\1[-1.0"),
         "loosening offset": lambda: _edit(ball_file, m, r"^(\[rates\.10\.guards\.floor\]"
                                           r"(.*\n)+?avoid = ).*$", r"\1-5.0"),
         "format": lambda: _edit(ball_file, m, r"^format = 1$", "format = 2"),
         "no format": lambda: _edit(ball_file, m, r"^format = 1\n", ""),
         "params": lambda: _edit(ball_file, tmp_path / "m.toml", r'^params_hash = ".*"',
                                 'params_hash = "sha256:0"'),
         "rate": lambda: _edit(ball_file, tmp_path / "m.toml", r"^\[rates\.10", "[rates.11"),
         "missing": lambda: tmp_path / "none.toml"}[case]()
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(out), "--set",
                                   f'mpc.margins="{f}"', *SHORT])
    assert res.exit_code == 2, res.output
    assert f"error: --set mpc.margins=\"{f}\": mpc.margins: " in res.output  # the --set's file
    assert {"system": "system 'biped', not 'ball'", "params": "other ball parameters",
            "rate": "no margins for mpc.rate_hz = 10", "missing": "file not found",
            "widening shrink": "rates.10.inputs.outside.0: Input should be greater than or "
                               "equal to 0 (got -1.0",
            "loosening offset": "rates.10.guards.floor.avoid: Input should be greater than "
                                "or equal to 0 (got -5.0",
            "format": "format: Input should be 1 (got 2",
            "no format": "not a margins file (format: Field required)"}[case] \
        in " ".join(res.output.split())
    assert not out.exists()


def test_a_margins_file_infeasible_at_x0_exits_2(ball_file: Path, tmp_path: Path):
    """As ``mpc.margins = "tube"`` refuses its tube: a guard-avoid row the file tightens
    beyond its NLP gap at x0 fails at the first nodes (every solve softened or failed)."""
    f = _edit(ball_file, tmp_path / "m.toml",
              r"^(\[rates\.10\.guards\.floor\]\nradius = .*\navoid = ).*$", r"\g<1>1000.0")
    sc, _ = load_scenario(BALL)
    system = build_system(sc.system)
    (q,) = [float(g.q_expr(system.x0)) for g in system.guards if g.name == "floor"]
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(out), "--set",
                                   f'mpc.margins="{f}"', *SHORT])
    assert res.exit_code == 2, res.output
    assert " ".join(res.output.split()) == " ".join(
        f"error: --set mpc.margins=\"{f}\": mpc.margins: {f}: at 10 Hz the tightened "
        f"guard-avoid row of floor (kappa = 1000) exceeds its NLP gap at x0 ({q:.4g}): the "
        "tightened problem is infeasible at the initial state".split())
    assert not out.exists()


def test_other_parameters_do_not_fit(ball_file: Path):
    with pytest.raises(ScenarioError, match=r"mpc\.margins: .*other ball parameters"):
        load_scenario(BALL, ["system.radius=0.6", f'mpc.margins="{ball_file}"'])


def test_margins_path_is_relative_to_the_scenario(ball_file: Path, tmp_path: Path):
    sc, toml = load_scenario(BALL, ["mpc.margins=\"m.toml\""], check_margins=False)
    assert sc.mpc.margins == str((BALL.parent / "m.toml").resolve())
    assert f'margins = "{sc.mpc.margins}"' in toml
    scen = tmp_path / "s.toml"
    scen.write_text(BALL.read_text())
    (tmp_path / "m.toml").write_text(ball_file.read_text())
    sc, _ = load_scenario(scen, ["mpc.margins=\"m.toml\""])
    assert sc.mpc.margins == str(tmp_path.resolve() / "m.toml")


def _xs(path: Path, topic: str, key: str) -> list:
    return [m.data[key] for m in read_log(path / "run.mcap").topic(topic)]


@pytest.mark.slow
def test_a_run_with_a_computed_margins_file(ball_file: Path, tmp_path: Path):
    """All margins 0: the same trajectories as the hand-set tube_margin = 0."""
    runs = {"file": [f'mpc.margins="{ball_file}"'], "hand": ["mpc.tube_margin=0"]}
    for name, sets in runs.items():
        args = [a for s in sets for a in ("--set", s)]
        res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(tmp_path / name),
                                       *args, *SHORT])
        assert res.exit_code == 0, res.output
    for topic, key in (("/sim/state", "x"), ("/mpc/solve", "plan"), ("/sim/event", "t")):
        assert _xs(tmp_path / "file", topic, key) == _xs(tmp_path / "hand", topic, key)
    info = _xs(tmp_path / "file", "/run/info", "margins")[0]
    assert info["source"] == str(ball_file.resolve()) and info["radius"] == 0.0
    assert [g["guard"] for g in info["guards"]] == ["floor", "wall", "circle_in",
                                                    "circle_out"]
    assert all(g["avoid"] == g["pass_through"] == 0.0 for g in info["guards"])
    assert info["inputs"] == [{"mode": "outside", "per_side": [0.0, 0.0]},
                              {"mode": "inside", "per_side": [0.0, 0.0]}]
    hand = _xs(tmp_path / "hand", "/run/info", "margins")[0]
    assert hand["source"] == "hand" and hand["guards"] == info["guards"]


def test_a_sweep_checks_its_margins_files_before_any_run(ball_file: Path, tmp_path: Path):
    from hmpc_cli.sweep.plan import plan_sweep

    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'name = "m"\nscenario = "{BALL}"\n[grid]\nm = [\n'
                     f'  {{ label = "file", "mpc.margins" = "{ball_file}" }},\n'
                     '  { label = "hand", "mpc.margins" = "hand" },\n]\n')
    runs = plan_sweep(sweep).runs
    assert sorted(f'margins = "{ball_file}"' in r.toml for r in runs) == [False, True]
    sweep.write_text(sweep.read_text().replace(str(ball_file), "missing.toml"))
    with pytest.raises(ScenarioError, match=r"mpc\.margins: file not found: .*missing\.toml"):
        plan_sweep(sweep)


FIG3_FILE = BALL.parent / "margins" / "ball_fig3.toml"  # |w_i| <= 10 (paper_fig3), kp = kd = 0
FIX = ('(hmpc tube SCENARIO --write FILE writes this scenario\'s, or mpc.margins = "tube" '
       'computes it for each run)')


def _margin_warnings(file: Path, sets: list[str]) -> list[str]:
    from hmpc_cli.run.scenario import margins_file_warnings

    return margins_file_warnings(load_scenario(BALL, [f'mpc.margins="{file}"', *sets])[0])


def test_a_margins_file_for_a_smaller_disturbance_or_other_gains_is_named(ball_file: Path):
    """The file fits the system and rate, but its tube is another setting's: a warning for
    a larger disturbance box than the file's and for other low-level gains, none for a
    smaller box (its margins are conservative) or the same setting."""
    f = ball_file.resolve()
    assert _margin_warnings(ball_file, []) == []
    assert _margin_warnings(ball_file, ["disturbance.kind=box", "disturbance.magnitude=3"]) == [
        f"mpc.margins: {f} was computed for no disturbance (none); this scenario's "
        f"disturbance.magnitude = 3 (disturbance.kind = 'box') is larger: its margins do not "
        f"cover this disturbance {FIX}"]
    assert _margin_warnings(ball_file, ["disturbance.kind=box", "disturbance.magnitude=0"]) == []
    assert _margin_warnings(ball_file, ["lowlevel.kd=2"]) == [
        f"mpc.margins: {f} was computed for the low level's kp = 0, kd = 0, not this "
        f"scenario's lowlevel.kp = 0, lowlevel.kd = 2: its margins are another closed loop's "
        f"tube {FIX}"]
    fig3 = ["mpc.rate_hz=20", "disturbance.kind=paper_fig3"]
    assert _margin_warnings(FIG3_FILE, fig3) == []  # the file's own disturbance
    assert _margin_warnings(FIG3_FILE, ["mpc.rate_hz=20"]) == []  # none: conservative
    assert _margin_warnings(FIG3_FILE, [*fig3, "disturbance.magnitude=9.5"]) == []
    (line,) = _margin_warnings(FIG3_FILE, [*fig3, "disturbance.magnitude=10.5"])
    assert "computed for |w_i| <= 10 (paper_fig3); this scenario's disturbance.magnitude " \
           "= 10.5 (disturbance.kind = 'paper_fig3') is larger: its margins do not cover" in line


def test_a_margins_file_made_without_the_scenarios_plant_is_named():
    """A scenario whose [plant] differs from its model, reading a margins file computed
    for the model (its eta holds no plant mismatch): a warning naming the plant; none for
    a [plant] that changes nothing."""
    fig3 = ["mpc.rate_hz=20", "disturbance.kind=paper_fig3"]
    assert _margin_warnings(FIG3_FILE, [*fig3, "plant.mass=1.0"]) == []  # the model's own
    assert _margin_warnings(FIG3_FILE, [*fig3, "plant.mass=2.0"]) == [
        f"mpc.margins: {FIG3_FILE.resolve()} was computed for a plant that is the model, not "
        "this scenario's plant (mass = 2): its margins may not cover this plant's mismatch "
        f"with the model {FIX}"]


def test_hmpc_run_and_sweep_warn_of_another_settings_margins_file(ball_file: Path,
                                                                  tmp_path: Path):
    """On stderr, before anything runs; a sweep names each reason once with its cells."""
    taken = tmp_path / "taken"
    taken.write_text("")  # --out is a file: exit 2 after the warnings, before the build
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(taken), "--set",
                                   f'mpc.margins="{ball_file}"', "--set", "lowlevel.kp=1",
                                   *SHORT])
    assert res.exit_code == 2
    assert res.output.splitlines()[0] == (
        f'warning: --set mpc.margins="{ball_file}": mpc.margins: {ball_file.resolve()} was '
        "computed for the low level's kp = 0, kd = 0, not this scenario's lowlevel.kp = 1, "
        f"lowlevel.kd = 0: its margins are another closed loop's tube {FIX}")
    own = tmp_path / "own.toml"  # the file in the scenario: the --set that changed kp is named
    own.write_text(BALL.read_text().replace("tube_margin = 0.025",
                                            f'margins = "{ball_file.resolve()}"'))
    res = CliRunner().invoke(app, ["run", str(own), "--out", str(taken), "--set",
                                   "lowlevel.kp=1", *SHORT])
    assert res.output.splitlines()[0].startswith(
        "warning: --set lowlevel.kp=1: mpc.margins: ")
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(
        f'name = "m"\nscenario = "{BALL}"\nseeds = [0, 1]\n[set]\n"mpc.margins" = '
        f'"{ball_file}"\n"disturbance.kind" = "box"\n[grid]\n"disturbance.magnitude" = '
        '[0, 2, 4]\n"lowlevel.kp" = [0, 1]\n')
    res = CliRunner().invoke(app, ["sweep", str(sweep), "--dry-run", "--out",
                                   str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    warnings = [x for x in res.output.splitlines() if x.startswith("warning: ")]
    assert [w.split(": mpc.margins: ")[0] for w in warnings] == [
        f"warning: {sweep}: cell disturbance.magnitude=0, lowlevel.kp=1 (and 2 other cells)",
        f"warning: {sweep}: cell disturbance.magnitude=2, lowlevel.kp=0 (and 1 other cell)",
        f"warning: {sweep}: cell disturbance.magnitude=4, lowlevel.kp=0 (and 1 other cell)"]
    assert "this scenario's disturbance.magnitude = 2 (disturbance.kind = 'box')" in warnings[1]
    assert res.output.splitlines()[-1] == "12 runs, all valid (dry run: nothing started)"


def test_a_resumed_sweep_runs_again_what_an_edited_margins_file_made(ball_file: Path,
                                                                     tmp_path: Path):
    """/run/info records the margins file's digest; a resume skips a run while the file is
    unchanged and runs it again, saying so, once the file changed."""
    from hmpc_cli.core.paths import file_digest

    margins = tmp_path / "m.toml"
    margins.write_text(ball_file.read_text())
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'name = "m"\nscenario = "{BALL}"\n[set]\n"mpc.margins" = "{margins}"\n'
                     '"sim.duration" = 0.1\n')
    out = tmp_path / "out"
    args = ["sweep", str(sweep), "--out", str(out), "--workers", "1"]
    first = CliRunner().invoke(app, args)
    assert first.exit_code == 0, first.output
    (run,) = out.glob("runs/*/run.mcap")
    info = read_log(run).topic("/run/info")[0].data["margins"]
    assert info["source"] == str(margins) and info["sha256"] == file_digest(margins)
    made = run.stat().st_mtime_ns
    again = CliRunner().invoke(app, args)
    assert "1 runs, 1 skipped" in again.output and run.stat().st_mtime_ns == made
    margins.write_text(margins.read_text() + "# edited\n")
    edited = CliRunner().invoke(app, args)
    assert edited.exit_code == 0, edited.output
    assert "1 runs, 0 skipped (already done), 1 to run" in edited.output
    assert "warning: 1 finished run(s) in" in edited.stderr
    assert read_log(run).topic("/run/info")[0].data["margins"]["sha256"] == \
        file_digest(margins) != info["sha256"]
