"""``hmpc plot timing``: a run's MPC solves against its period, from the log alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import REPO
from hmpc_cli.cli.app import app

ENV = {"COLUMNS": "220", "NO_COLOR": "1", "TERM": "dumb"}


def _run(out: Path, *overrides: str) -> Path:
    """One short ball run in this process; returns its run directory."""
    from hmpc_cli.run.runner import run_scenario
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(REPO / "scenarios" / "ball.toml", ["sim.duration=0.6", *overrides])
    run_scenario(sc, text, out)
    return out


@pytest.fixture(scope="module")
def budget(tmp_path_factory) -> Path:
    """Compute time modelled, a budget of 20 ms: the switching solves are dropped."""
    return _run(tmp_path_factory.mktemp("t") / "budget", "sim.latency=model",
                "sim.solve_budget=0.02")


@pytest.fixture(scope="module")
def paused(tmp_path_factory) -> Path:
    return _run(tmp_path_factory.mktemp("t") / "paused")


def plot(*args) -> object:
    res = CliRunner().invoke(app, ["plot", "timing", *map(str, args)], env=ENV)
    assert "Traceback" not in res.output, res.output
    return res


def test_charged_solves_their_charges_the_dropped_ones_and_the_runs_own_count(budget):
    from hmpc_cli.figures.timing import solve_times
    from hmpc_cli.log.rundata import read_run

    st, run = solve_times(budget), read_run(budget)
    rt = run.summary.real_time
    assert st.charged == "model" and st.period == rt.period == 0.1
    assert st.t.tolist() == [s.t for s in run.solves]
    assert st.compute.tolist() == [s.latency for s in run.solves]  # what the plant waited
    assert st.wall.tolist() == [s.wall_time for s in run.solves]
    assert st.dropped.tolist() == [s.reason.endswith(" (over budget: dropped)")
                                   for s in run.solves]
    assert int(st.dropped.sum()) == rt.dropped_solves > 0
    assert int(st.counted.sum()) == rt.charged_solves  # every solve charged
    assert st.above.tolist() == [s.latency > 0.1 for s in run.solves]
    assert st.contacts.tolist() == [e.t for e in run.events]
    from hmpc_cli.figures.timing import _title

    above = int(st.above.sum())
    assert _title(st) == (
        f"compute time charged (model); {above} of {rt.charged_solves} charged solves above "
        f"the 100.0 ms MPC period ({int((st.above & st.dropped).sum())} dropped over "
        f"budget)\nreal_time: {rt.late_solves} of {rt.charged_solves} charged solves kept "
        f"the solver busy past the period, {rt.dropped_solves} dropped, "
        f"{rt.preempted_solves} stopped by a contact")


def test_time_paused_shows_the_wall_times_against_the_scenarios_period(paused):
    from hmpc_cli.figures.timing import solve_times
    from hmpc_cli.log.rundata import read_run

    st, run = solve_times(paused), read_run(paused)
    assert st.charged == "" and st.real_time is None and run.summary.real_time is None
    assert np.array_equal(st.compute, st.wall) and st.counted.all()
    sim, mpc = run.scenario["sim"]["rate_hz"], run.scenario["mpc"]["rate_hz"]
    assert st.period == (sim // mpc) / sim == 0.1
    assert st.above.tolist() == [s.wall_time > 0.1 for s in run.solves]


def test_plot_timing_writes_the_same_figure_twice_and_prints_its_count(paused, tmp_path):
    from hmpc_cli.figures.timing import solve_times

    st = solve_times(paused)
    res = plot(paused, "--out", tmp_path / "a", "--formats", "png,svg")
    assert res.exit_code == 0, res.output
    assert res.output.splitlines()[0] == (
        f"{int(st.above.sum())} of {len(st.t)} solves above the 100.0 ms MPC period; time "
        "paused: the solves' measured wall times")
    assert plot(paused / "run.mcap", "--out", tmp_path / "b", "--formats", "png,svg",
                "-q").exit_code == 0
    for f in ("timing.png", "timing.svg"):
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()


def test_plot_timing_bad_input_is_one_line_and_exit_2(tmp_path):
    nosolve = _run(tmp_path / "nosolve", "planner.iterations=6", "planner.samples=20",
                   "planner.knots=10", "mpc.horizon=1.0", "sim.duration=0.3")
    res = plot(nosolve, "--out", tmp_path / "f")
    assert res.exit_code == 2
    assert res.output.strip() == f"error: {nosolve / 'run.mcap'}: no MPC solve in the log"
    assert not (tmp_path / "f").exists()  # nothing written
    res = plot(tmp_path / "none")
    assert res.exit_code == 2 and "no such run log" in res.output
    res = plot(nosolve, "--every", "0.2")
    assert res.exit_code == 2 and "--every is fig4's option, not timing's" in res.output
