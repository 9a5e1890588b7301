"""mpc.margins = "tube": each MPC rate gets the margins of its own tube, as hmpc tube writes."""

import subprocess
import tomllib
from pathlib import Path

import pytest

import hmpc_cli.tube as tube_pkg
from conftest import cli_env, hmpc_command, hmpc_in_process
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.scenario import load_scenario
from hmpc_cli.run.setup_checks import margins_of
from hmpc_cli.run.tube_margins import tube_margins_path

ROOT = Path(__file__).resolve().parents[1]
DISTURBED = ROOT / "scenarios" / "ball_disturbed.toml"


def _margins(rate: int):
    sc, _ = load_scenario(DISTURBED, ['mpc.margins="tube"', f"mpc.rate_hz={rate}"])
    model = build_system(sc.system)
    return sc, model, margins_of(sc, model)


def test_each_rate_gets_the_margins_hmpc_tube_writes_for_it(tmp_path, monkeypatch):
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    file = tmp_path / "margins.toml"
    proc = hmpc_in_process(["tube", str(DISTURBED), "--write", str(file), "--out",
                            str(tmp_path / "tube"), "-q"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    written = tomllib.loads(file.read_text())["rates"]
    avoid = {}
    for rate in (5, 10, 20):
        sc, model, m = _margins(rate)
        row = written[str(rate)]
        assert m.source == f"tube at {rate} Hz"
        assert m.radius == pytest.approx(row["radius"], rel=1e-12)
        for g, offset in zip(model.guards, m.avoid, strict=True):
            assert offset == pytest.approx(row["guards"][g.name]["avoid"], rel=1e-12)
        avoid[rate] = m.avoid[model.guard_index("floor")]
        assert tube_margins_path(sc).is_file()  # cached for the next run of this cell
    # a faster MPC has a smaller tube, hence smaller margins (the paper's mechanism)
    assert avoid[5] > avoid[10] > avoid[20] > 0.0
    assert avoid[10] == pytest.approx(0.0764, abs=1e-4)
    assert avoid[20] == pytest.approx(0.0184, abs=1e-4)


def test_hmpc_tube_samples_as_tube_margins_do_whatever_the_scenarios_seed(tmp_path,
                                                                          monkeypatch):
    """The sampling seed of both is 0: ``hmpc tube`` sampled with the scenario's seed, so
    ``--set seed=1`` gave another certificate (its ROA estimate) than the seed-0 tube a
    run's ``mpc.margins = "tube"`` uses whatever the run's seed."""
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    gains = ["lowlevel.kp=10", "lowlevel.kd=2"]  # certified (a sampled ROA), no box capped
    made = {}
    for seed in (0, 1):
        out = tmp_path / f"seed{seed}"
        proc = subprocess.run([*hmpc_command(), "tube", str(DISTURBED), "--out", str(out),
                               "--write", str(out / "margins.toml"), "-q",
                               *(x for g in [*gains, f"seed={seed}"] for x in ("--set", g))],
                              env=cli_env(), capture_output=True, text=True, timeout=600,
                              cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        made[seed] = [(out / f).read_text() for f in ("tube.json", "margins.toml")]
    assert made[1] == made[0]
    row = tomllib.loads(made[1][1])["rates"]["20"]
    sc, _ = load_scenario(DISTURBED, ['mpc.margins="tube"', "mpc.rate_hz=20", *gains, "seed=1"])
    m = margins_of(sc, build_system(sc.system))
    assert m.source == "tube at 20 Hz" and m.radius == row["radius"]


def test_a_cached_tube_is_read_not_recomputed(tmp_path, monkeypatch):
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    _, _, first = _margins(20)

    def no_analysis(*args, **kwargs):
        raise AssertionError("the cached tube was analysed again")

    monkeypatch.setattr(tube_pkg, "analyse", no_analysis)
    _, _, again = _margins(20)
    assert again == first


def test_margins_that_do_not_fit_are_refused_with_the_tubes_reason(tmp_path, monkeypatch):
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    proc = hmpc_in_process(["run", str(DISTURBED), "--set", 'mpc.margins="tube"', "--set",
                            "mpc.rate_hz=2", "--out", str(tmp_path / "r"), "-q"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert "mpc.margins: the tube's margins at 2 Hz do not fit" in line
    assert "infeasible at the initial state" in line and "Traceback" not in proc.stderr
    assert not (tmp_path / "r").exists()


def test_the_tube_study_is_the_hand_margin_study_with_tube_margins():
    from hmpc_cli.sweep.plan import plan_sweep

    tube = plan_sweep(ROOT / "sweeps" / "robustness_tube.toml")
    hand = plan_sweep(ROOT / "sweeps" / "robustness.toml")
    assert len(tube.runs) == len(hand.runs) == 2000
    for a, b in zip(tube.runs, hand.runs, strict=True):
        assert a.overrides == {**b.overrides, "mpc.margins": "tube"}


@pytest.mark.slow
def test_the_committed_fig3_margins_file_is_what_its_documented_command_writes(tmp_path,
                                                                             monkeypatch):
    """docs/tubes.md: scenarios/margins/ball_fig3.toml is written by ``hmpc tube
    scenarios/ball_disturbed.toml --write scenarios/margins/ball_fig3.toml``; the same
    command (its output directory and file under tmp_path, a fresh cache) writes it byte
    for byte (the file names no path)."""
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    file = tmp_path / "ball_fig3.toml"
    proc = hmpc_in_process(["tube", str(DISTURBED), "--write", str(file)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == \
        f"wrote margins file {file} (rates 5, 10, 20, 50, 100 Hz)"
    assert file.read_bytes() == (ROOT / "scenarios" / "margins" / "ball_fig3.toml").read_bytes()


def test_no_disturbance_is_a_zero_tube_whatever_the_gains():
    """eta = 0 (the zero disturbance set, plant = model): the error starts and stays 0, so
    the tube is 0 at every rate, PD gains or not (it jumped to the saturated bound once
    L_u ||K|| t e^{L_x t} reached 1: 0 at 0.009 s, 2.83 at 0.0099 s)."""
    from hmpc_cli.tube.bounds import low_level_share

    assert low_level_share(0.009, 0.0, 1.109, 1.0, 100.0, 282.84) == (0.0, 0.0)
    assert low_level_share(0.0099, 0.0, 1.109, 1.0, 100.0, 282.84) == (0.0, 0.0)
    assert low_level_share(0.0099, 1e-9, 1.109, 1.0, 100.0, 282.84)[1] == 282.84
    sc, _ = load_scenario(DISTURBED, ['disturbance.kind="none"', "lowlevel.kp=100",
                                      'mpc.margins="tube"', "mpc.rate_hz=10"])
    m = margins_of(sc, build_system(sc.system))
    assert m.radius == 0.0 and all(v == 0.0 for v in m.avoid)
    assert all(v == 0.0 for box in m.inputs for v in box)


def test_a_tube_that_shrinks_an_input_box_to_a_point_is_refused(tmp_path, monkeypatch):
    """Stiff PD gains: the low level's share zeta reaches half of every input box, so the
    feed-forward boxes collapse to their centres and the MPC keeps no input authority
    (a run with it failed where hand margins succeed): refused like an infeasible tube,
    and a hand shrink of exactly half a box too."""
    from hmpc_cli.run.setup_checks import setup_problems

    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    sc, _ = load_scenario(DISTURBED, ['mpc.margins="tube"', "mpc.rate_hz=30",
                                      "lowlevel.kp=100", "lowlevel.kd=20"])
    with pytest.raises(ValueError) as exc:
        margins_of(sc, build_system(sc.system))
    assert "the tube's margins at 30 Hz do not fit: at 30 Hz the input shrink zeta = " \
           "282.8 reaches half of mode outside's input box (capped)" in str(exc.value)
    hand, _ = load_scenario(DISTURBED, ["mpc.input_margin=50"])
    assert setup_problems(hand) == [
        "mpc.input_margin: 50 per side reaches half the input box of mode 'outside' input 0 "
        "([-100, 0]: half-width 50; the MPC would keep no input authority)"]


def test_a_margins_file_whose_formula_does_not_hold_is_refused_as_tube_refuses_it(tmp_path):
    from hmpc_cli.tube.margins_file import margins_problems

    text = (ROOT / "scenarios" / "margins" / "ball_fig3.toml").read_text()
    sc, _ = load_scenario(DISTURBED, ["mpc.rate_hz=20"])
    good = tmp_path / "good.toml"
    good.write_text(text)
    assert margins_problems(good, sc.system, 20) == []
    head, rest = text.split("[rates.20.guards.circle_in]", 1)
    bad = tmp_path / "bad.toml"
    bad.write_text(head + "[rates.20.guards.circle_in]" +
                   rest.replace("formula_holds = true", "formula_holds = false", 1))
    assert margins_problems(bad, sc.system, 20) == [
        f"{bad}: at 20 Hz the margin formula of guard circle_in does not hold for its tube "
        "(formula_holds = false: the tube does not fit the guard's geometry), as "
        "mpc.margins = \"tube\" refuses it"]


def test_a_damaged_cached_tube_is_computed_again_and_the_key_follows_the_system(
        tmp_path, monkeypatch):
    from hmpc_cli.run.tube_margins import _tube_sources, tube_margins_file

    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    sc, model, m = _margins(20)
    path = tube_margins_path(sc)
    path.write_text(path.read_text()[:200])  # cut: not TOML any more
    assert tube_margins_file(sc, model).at(20).radius == m.radius
    assert tomllib.loads(path.read_text())["rates"]["20"]["radius"] == m.radius  # rewritten
    raw = bytearray(path.read_bytes())
    raw[100] = 0xFF  # not UTF-8 any more
    path.write_bytes(bytes(raw))
    assert tube_margins_file(sc, model).at(20).radius == m.radius
    # the system plug-in's own source is part of the key (its flows and guards)
    assert _tube_sources("ball") != _tube_sources("biped")
