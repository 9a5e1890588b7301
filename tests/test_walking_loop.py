"""The biped in closed loop (short horizons): footholds, contacts, falls, Figure 4, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from hmpc_cli.analysis.tables import FigureInputError
from hmpc_cli.figures.fig4 import fig4, load_walk
from conftest import run_loop
from hmpc_cli.log.reader import read_log
from hmpc_cli.run.scenario import load_scenario
from hmpc_cli.systems.biped import BipedParams, make_biped_model, stair_terrain

STAIRS = REPO / "scenarios" / "biped_stairs.toml"


@pytest.fixture(scope="module")
def short_walk(tmp_path_factory) -> Path:
    """0.7 s of the bundled scenario (two steps) through the real command line."""
    import subprocess

    from conftest import cli_env, hmpc_command

    out = tmp_path_factory.mktemp("walk") / "run"
    proc = subprocess.run([*hmpc_command(), "run", str(STAIRS), "--out", str(out), "-q",
                           "--set", "sim.duration=0.7"], capture_output=True, text=True,
                          env=cli_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


@pytest.mark.slow
def test_two_steps_land_on_the_long_segment_and_replan_at_each_contact(short_walk):
    summary = json.loads((short_walk / "summary.json").read_text())
    assert not summary["diverged"]
    counts = summary["contacts_by_guard"]  # every guard, zeros included
    assert {k: n for k, n in counts.items() if n} == {"stair_2": 2}  # the 1.0 m segment, twice
    assert "stair_2" in counts and len(counts) > 1
    assert summary["solver_failures"] == 0
    assert summary["planner_calls"] == 3 and summary["planner_rejected"] == 0
    # success needs the top segment: not reached after 0.7 s, and the reason says so
    assert not summary["success"] and "top segment" in summary["reason"]
    log = read_log(short_walk / "run.mcap")
    plans = log.topic("/planner/plan")
    assert [m.data["reason"] for m in plans] == ["initial", "contact", "contact"]
    events = log.topic("/sim/event")
    for plan, ev in zip(plans[1:], events, strict=True):  # a replan at each contact
        assert plan.t == pytest.approx(ev.t, abs=1e-12)  # planned at the contact itself
        segs = [c["segment"] for c in plan.data["detail"]["candidates"]]
        assert segs == sorted(segs) and 1 in segs  # the 1.0 m segment was a candidate
    # periodic re-solves at 10 Hz between the contacts, all warm and successful
    period = [m for m in log.topic("/mpc/solve") if m.data["reason"] == "period"]
    assert len(period) >= 4 and all(m.data["success"] for m in period)


def test_the_touchdowns_hit_the_guard_inside_the_segment(short_walk):
    p = BipedParams()
    model = make_biped_model(p.model_copy(update={"mass_scale": 1.1}))
    for ev in read_log(short_walk / "run.mcap").topic("/sim/event"):
        xb = np.array(list(ev.data["x_before"].values()))
        xa = np.array(list(ev.data["x_after"].values()))
        foot = np.asarray(model.swing_foot_world(xb)).ravel()
        assert foot[1] == pytest.approx(0.075, abs=1e-8)  # on the guard (stair 2's level)
        assert 0.4 < foot[0] < 1.4
        np.testing.assert_allclose(xa[10:], foot, atol=1e-12)  # new stance foot: the touchdown
        np.testing.assert_allclose(np.asarray(model.reset(xb)).ravel(), xa, atol=1e-9)


@pytest.mark.slow
def test_a_run_is_bit_for_bit_reproducible(tmp_path):
    logs = []
    for k in range(2):
        sc, _ = load_scenario(STAIRS, ["sim.duration=0.35"])
        run_loop(sc, tmp_path / f"{k}.mcap")
        logs.append(read_log(tmp_path / f"{k}.mcap"))
    for topic in ("/sim/state", "/sim/event", "/disturbance"):
        a = [m.data for m in logs[0].topic(topic)]
        b = [m.data for m in logs[1].topic(topic)]
        assert a == b and a, topic


@pytest.mark.slow
def test_a_fall_ends_the_run_cleanly_as_failed(tmp_path, invoke_hmpc):
    out = tmp_path / "fall"
    proc = invoke_hmpc(["run", str(STAIRS), "--out", str(out), "-q", "--set",
                        "disturbance.magnitude=5000", "--set", "sim.duration=1.2"], tmp_path,
                       timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert not summary["success"] and summary["reason"].startswith("fall:")
    assert not summary["diverged"]  # a task failure, not a numerical one
    log = read_log(out / "run.mcap")
    assert log.complete and log.topic("/run/summary")[-1].data["reason"] == summary["reason"]


def test_no_candidate_keeps_the_previous_plan_and_is_logged(tmp_path):
    sc, _ = load_scenario(STAIRS, ["sim.duration=0.4", "planner.reach=0.01",
                                   "planner.include_current=false"])
    res = run_loop(sc, tmp_path / "run.mcap")
    assert res.planner_rejected >= 1
    notes = [m.data["note"] for m in read_log(tmp_path / "run.mcap").topic("/planner/plan")]
    # the schedule of t = 0 was followed to its contact: not "no schedule yet" (it said so)
    assert notes[0] == "" and len(notes) == 3
    assert all("no foothold candidate within reach" in n and
               n.endswith("; no usable schedule (the last one is used up)") for n in notes[1:])
    # and the summary says the MPC stopped planning for the rest of the run
    assert res.warnings[-1] == (
        "no usable schedule from t = 0.2988 s to the end (t = 0.4000 s): 2 planner calls "
        "found none (the last: no foothold candidate within reach 0.01 m of the stance foot "
        "at x = 0.3277 m (stairs span [0, 2.85])); the low level tracked the last plan")


def test_terrain_height_of_the_figure_4_course():
    p = BipedParams()
    xs = np.array([-0.3, 0.0, 0.2, 0.4, 0.9, 1.45, 1.6, 2.5, 3.5])
    np.testing.assert_allclose(stair_terrain(p).profile(xs),
                               [0, 0, 0, 0.075, 0.075, 0.125, 0.175, 0.175, 0.175])


def test_figure_4_from_the_log_is_deterministic(short_walk, tmp_path):
    a = fig4(short_walk / "run.mcap", tmp_path / "a", "png,svg,pdf")
    fig4(short_walk, tmp_path / "b", "png,svg,pdf")  # the run directory works too
    for name in ("fig4.png", "fig4.svg", "fig4.pdf"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    assert len(a.contacts) == 2 and a.contacts[0][1] == "stair_2"
    hip0 = load_walk(short_walk / "run.mcap").hip[0]
    np.testing.assert_allclose(hip0, [0.2334, 0.6815], atol=1e-3)
    # the F_x step trace holds its last value to the run's end (the last state sample)
    t_f, f_x = a.force
    assert t_f[-1] == pytest.approx(a.t[-1], abs=1e-9) and f_x[-1] == f_x[-2]


@pytest.mark.parametrize("width,height", [(None, None), (7.16, 4.2)])
def test_fig4_is_legible_at_one_column(short_walk, tmp_path, width, height):
    """One column by default (--width overrides): the saved size, STIX, text >= 7 pt, no
    overlapping text; a colour bar for time; poses that did not move are not redrawn."""
    from figcheck import assert_legible
    from matplotlib.axes import Axes

    from hmpc_cli.figures import fig4 as f4
    from hmpc_cli.figures.common import COLUMN_WIDTH_IN, figure_style
    from PIL import Image

    walk = load_walk(short_walk / "run.mcap")
    kw = {} if width is None else {"width": width, "height": height}
    fig4(walk, tmp_path, "png", **kw)
    width, height = width or COLUMN_WIDTH_IN, height or f4.HEIGHT_IN
    with Image.open(tmp_path / "fig4.png") as im:
        assert im.size == (round(width * 300), round(height * 300))
    with figure_style():
        fig = f4._figure(walk, 0.1, width, height)
        assert_legible(fig, width, height)
        assert any(ax.get_ylabel() == "$t$ (s)" for ax in fig.findobj(Axes))  # the time bar
        labels = {ax.get_xlabel() for ax in fig.axes} | {ax.get_ylabel() for ax in fig.axes}
        assert {"$x$ (m)", "$t$ (s)", "$F_x$ (N)"} <= labels
    # Standing still: the same pose repeated is drawn once.
    still = f4.WalkLog(**{**walk.__dict__, "t": np.arange(5) * 0.1,
                          "points": np.repeat(walk.points[:1], 5, axis=0)})
    assert f4._snapshots(still, 0.1) == [0]
    assert len(f4._snapshots(walk, 0.1)) >= 5


def test_fig4_draws_the_terrain_past_the_end_at_the_tops_height(short_walk):
    """Past the last segment's end the terrain keeps the top's height (no guard there):
    Figure 4 drew a drop there and cut the view at the end, so a walker that went on was
    drawn off the plot, over no ground."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from hmpc_cli.figures import fig4 as f4

    walk = load_walk(short_walk / "run.mcap")
    end, top = walk.stairs[-1][1], walk.stairs[-1][2]
    # the same walk carried 1 m past the end, 0.3 m up
    far = f4.WalkLog(**{**walk.__dict__, "points": walk.points + [end + 1.0, top]})
    ax = Figure().add_subplot()
    x_min, x_max, y_min = f4._draw_terrain(ax, far)
    assert x_max == pytest.approx(float(far.points[:, :, 0].max()) + 0.05)
    profile, past = ax.lines
    assert min(profile.get_ydata()) == walk.ground_height  # no drop below the ground
    assert list(profile.get_xdata()[-1:]) == [end] and profile.get_ydata()[-1] == top
    assert list(past.get_xdata()) == [end, x_max] and list(past.get_ydata()) == [top, top]
    assert past.get_linestyle() == ":"
    assert y_min == pytest.approx(walk.ground_height - 0.02)
    # a walk that stays on the stairs: the view ends 5 cm past the end, as before
    assert f4._draw_terrain(Figure().add_subplot(), walk)[1] == pytest.approx(end + 0.05)


@pytest.mark.slow
def test_plot_fig4_command_writes_the_gif_and_rejects_a_ball_log(short_walk, tmp_path,
                                                                  invoke_hmpc, full_run):
    proc = invoke_hmpc(["plot", "fig4", str(short_walk), "--out", str(tmp_path / "f"),
                        "--formats", "png"], tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "contact t = 0.3" in proc.stdout
    gif = (tmp_path / "f" / "walk.gif").read_bytes()
    assert gif[:6] in (b"GIF89a", b"GIF87a") and len(gif) > 10_000
    bad = invoke_hmpc(["plot", "fig4", str(full_run.out), "--out", str(tmp_path / "g")], tmp_path)
    assert bad.returncode == 2 and "not a walking run to draw" in bad.stderr
    assert "Traceback" not in bad.stderr
    with pytest.raises(FigureInputError, match="no such log"):
        load_walk(tmp_path / "missing.mcap")


@pytest.mark.parametrize("override,key", [
    ('mpc.kind="fixed_mode"', "mpc.kind"),
    ("mpc.rate_hz=7", "mpc.rate_hz"),
    ('replanning.policy="once"', "replanning.policy"),
    ("plant.mass_scal=1.1", "plant.mass_scal"),
    ("plant.mass_scale=-1", "plant.mass_scale"),
    ("system.stairs=[{length = 0.4, height = 0.0}, {length = -1.0, height = 0.1}]",
     "system.stairs[1].length"),
    ("system.stance_foot0=[0.0, 0.2]", "system.stance_foot0"),
])
def test_bad_biped_scenarios_give_one_keyed_line(tmp_path, invoke_hmpc, override, key):
    proc = invoke_hmpc(["run", str(STAIRS), "--out", str(tmp_path / "r"), "--set", override],
                       tmp_path)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and f"--set {override}: {key}:" in lines[0], proc.stderr
    assert not (tmp_path / "r").exists()


def test_results_page_figure_4_section(short_walk, tmp_path):
    from hmpc_cli.report.page import ReportInputs, write_report

    page = write_report(tmp_path / "results", ReportInputs(None, None, None, short_walk),
                        "hmpc report").read_text()
    assert "## Figure 4" in page and "![Figure 4](report/fig4.png)" in page
    assert "| 1 | 0.300 | stair_2 |" in page and "| 2 | " in page
    assert (tmp_path / "results" / "report" / "walk.gif").is_file()


@pytest.mark.slow
def test_a_biped_sweep_reuses_one_nlp_per_worker(tmp_path):
    from hmpc_cli.mpc import kernels
    from hmpc_cli.run import compose
    from hmpc_cli.sweep.execute import execute_sweep
    from hmpc_cli.sweep.plan import plan_sweep

    sweep = tmp_path / "biped.toml"
    sweep.write_text(f'name = "biped_tiny"\nscenario = "{STAIRS.as_posix()}"\nseeds = 2\n'
                     '[set]\n"sim.duration" = 0.35\n'
                     '[grid]\n"disturbance.magnitude" = [0.0, 25.0]\n')
    compose._PROBLEMS.clear()  # NLPs built by earlier tests in this process
    outcome = execute_sweep(plan_sweep(sweep), tmp_path / "out", workers=1)
    assert outcome.done == 4 and not outcome.lost
    assert len(compose._PROBLEMS) == 1  # one walking NLP served all four runs
    # its runs waited for their kernels' compiles; this process's later builds do not
    # (they did: every later test's NLP of other kernels waited for the compiler)
    assert kernels._WAIT is False
    import csv

    with open(tmp_path / "out" / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4
    assert all(r["contacts"] == "1" and r["diverged"] == "false" for r in rows)  # one step


def test_a_minimal_biped_scenario_gets_its_stack_defaults(tmp_path):
    path = tmp_path / "mini.toml"
    path.write_text('[system]\nname = "biped"\n')
    sc, _ = load_scenario(path)
    assert (sc.planner.kind, sc.mpc.kind) == ("footholds", "walking")
    assert sc.sim.input_at_events == "recompute" and sc.replanning.policy == "on_contact"
