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
    """Compute time modelled at 30 Hz (a 33.3 ms period), a budget of 50 ms, the first
    plan paused: solves under the period, over it, and dropped."""
    return _run(tmp_path_factory.mktemp("t") / "budget", "sim.latency=model",
                "mpc.rate_hz=30", "sim.solve_budget=0.05", "sim.latency_first=paused",
                "lowlevel.past_guard=next_domain")


@pytest.fixture(scope="module")
def paused(tmp_path_factory) -> Path:
    return _run(tmp_path_factory.mktemp("t") / "paused")


def plot(*args) -> object:
    res = CliRunner().invoke(app, ["plot", "timing", *map(str, args)], env=ENV)
    assert "Traceback" not in res.output, res.output
    return res


def test_charged_solves_their_charges_the_dropped_ones_and_the_runs_own_count(budget):
    from hmpc_cli.figures.timing import _title, solve_times
    from hmpc_cli.log.rundata import read_run

    st, run = solve_times(budget), read_run(budget)
    rt = run.summary.real_time
    sim = run.scenario["sim"]["rate_hz"]
    assert st.charged == "model" and st.period == rt.period == (sim // 30) / sim
    assert round(1e3 * st.period, 1) == 33.3
    assert st.t.tolist() == [s.t for s in run.solves]
    assert st.compute.tolist() == [s.latency for s in run.solves]  # what the plant waited
    assert st.wall.tolist() == [s.wall_time for s in run.solves]
    assert st.dropped.tolist() == [s.reason.endswith(" (over budget: dropped)")
                                   for s in run.solves]
    assert int(st.dropped.sum()) == rt.dropped_solves > 0
    assert int(st.counted.sum()) == rt.charged_solves == len(st.t) - 1  # not the first
    assert st.counted.tolist() == [i > 0 for i in range(len(st.t))] and st.compute[0] == 0
    assert st.above.tolist() == [s.latency > st.period for s in run.solves]
    assert (st.above & ~st.dropped).any() and (st.counted & ~st.above).any()  # all kinds
    assert not st.stopped.any() and rt.preempted_solves == 0
    assert st.contacts.tolist() == [e.t for e in run.events]
    above, dropped = int(st.above.sum()), int((st.above & st.dropped).sum())
    assert _title(st) == (
        f"compute time charged (model); {above} of {rt.charged_solves} charged solves charged "
        f"more than the 33.3 ms MPC period ({dropped} dropped over budget)\nreal_time: "
        f"{rt.late_solves} of {rt.charged_solves} charged solves kept the solver busy past "
        f"the period, {rt.dropped_solves} dropped, {rt.preempted_solves} stopped by a contact")


def test_what_the_figure_draws(budget):
    from hmpc_cli.figures.common import figure_style
    from hmpc_cli.figures.timing import _figure, solve_times

    st = solve_times(budget)
    with figure_style():
        fig = _figure(st, 7.16, 2.4)
    (ax,) = fig.axes
    lines = {ln.get_label(): ln for ln in ax.get_lines() if not ln.get_label().startswith("_")}
    assert set(lines) == {"contact", "measured wall time", "MPC period 33.3 ms",
                          "solve (charged)", "above the period", "dropped over budget"}
    assert lines["above the period"].get_xdata().tolist() == \
        st.t[st.above & ~st.dropped].tolist()
    assert lines["dropped over budget"].get_ydata().tolist() == \
        (1e3 * st.compute[st.dropped]).tolist()
    assert len(lines["measured wall time"].get_xdata()) == len(st.t)
    assert lines["solve (charged)"].get_xdata().tolist() == \
        st.t[st.counted & ~st.above].tolist()  # the paused first plan: its wall time only


@pytest.mark.parametrize("latency,first,counted", [
    ("0.03", "paused", "all but the first"), ("0", "charged", "all")])
def test_a_fixed_latency_and_the_first_plan_paused_count_as_real_time_does(
        tmp_path, latency, first, counted):
    from hmpc_cli.figures.timing import count_text, solve_times
    from hmpc_cli.log.rundata import read_run

    d = _run(tmp_path / "run", f"sim.latency={latency}", f"sim.latency_first={first}",
             "sim.duration=0.4")
    st, rt = solve_times(d), read_run(d).summary.real_time
    assert st.charged == rt.latency == "fixed"
    assert int(st.counted.sum()) == rt.charged_solves
    assert st.counted.tolist() == [counted == "all" or i > 0 for i in range(len(st.t))]
    assert st.compute.tolist() == [0.0 if first == "paused" and i == 0 else float(latency)
                                   for i in range(len(st.t))]
    assert count_text(st) == (f"compute time charged (fixed); 0 of {rt.charged_solves} "
                              "charged solves charged more than the 100.0 ms MPC period")


def test_the_stopped_solves_are_found_from_the_notes_after_them():
    from hmpc_cli.figures.timing import _stopped

    t = np.array([0.3, 0.415, 0.415, 0.415, 0.5])
    reasons = ["period", "impact", "impact (after a contact stopped the solve of t = 0.4150 "
               "s: dropped)", "impact (after a contact stopped the solve of t = 0.4150 s: "
               "dropped)", "period (after a contact stopped the solve of t = 0.3000, 0.4150 s:"
               " dropped)"]
    assert _stopped(reasons, t).tolist() == [True, True, True, True, False]
    assert _stopped(["period", "period"], np.array([0.1, 0.2])).tolist() == [False, False]


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
        f"time paused: each solve's measured wall time; {int(st.above.sum())} of {len(st.t)} "
        "solves above the 100.0 ms MPC period")
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


def test_a_solve_charged_0_s_is_drawn_at_the_bottom_of_the_log_axis():
    """"model" charges a 0-iteration solve 0 s, which a log axis cannot show: such solves
    are dashes at the bottom (they vanished from the figure)."""
    from hmpc_cli.figures.timing import SolveTimes, _figure

    n = 4
    st = SolveTimes(t=np.arange(n) * 0.1, compute=np.array([0.004, 0.0, 0.0, 0.002]),
                    wall=np.full(n, 0.001), dropped=np.zeros(n, bool),
                    stopped=np.zeros(n, bool), counted=np.ones(n, bool), period=0.1,
                    charged="model", contacts=np.array([]), real_time=None, log_note="")
    fig = _figure(st, 6.0, 2.4)
    lines = {ln.get_label(): ln for ln in fig.axes[0].get_lines()}
    zero = lines["charged 0 s (drawn at the bottom)"]
    assert zero.get_xdata().tolist() == [0.1, 0.2]
    assert zero.get_ydata().tolist() == [1.0, 1.0]  # half the smallest charge drawn, in ms
    assert lines["solve (charged)"].get_ydata().tolist() == [4.0, 2.0]
