"""``hmpc plot fig2``: the virtual pass-through node of a recorded ball plan; bad input."""

from __future__ import annotations

import json

import casadi as ca
import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import BALL
from hmpc_cli.figures.fig2 import fig2
from hmpc_cli.analysis.passthrough import PassThroughError, _logged_system
from hmpc_cli.analysis.passthrough import pass_through_geometry as fig2_geometry
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.reader import read_log
from test_plot import make_app

TOL = 1e-6  # the solver's tolerance (1e-8) with room for the logged rounding


@pytest.fixture(scope="module")
def run(tmp_path_factory, invoke_hmpc):
    """A short nominal ball run through the real command line (its directory)."""
    base = tmp_path_factory.mktemp("fig2_run")
    proc = invoke_hmpc(["run", str(BALL), "--set", "sim.duration=0.3", "--out",
                        str(base / "run"), "-q"], cwd=base)
    assert proc.returncode == 0, proc.stderr
    return base / "run"


def rewrite(src, dst, edit):
    """Copies a run log, passing each message's data through ``edit(topic, data)``."""
    log = read_log(src)
    with Recorder(dst) as rec:
        for topic in dict.fromkeys(m.topic for m in log.messages):
            rec.add_topic(topic, f"copy{topic}", log.schemas[topic])
        for m in log.messages:
            rec.write(m.topic, m.t, edit(m.topic, dict(m.data)))
    return dst


@pytest.mark.slow
def test_cli_writes_the_figure_deterministically(run, invoke_hmpc, tmp_path):
    first = invoke_hmpc(["plot", "fig2", str(run), "--out", str(tmp_path / "a")], cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    assert "crosses guard" in first.stdout and "past the guard" in first.stdout
    for fmt in ("pdf", "svg", "png"):
        assert (tmp_path / "a" / f"fig2.{fmt}").stat().st_size > 5000
    assert (tmp_path / "a" / "fig2.pdf").read_bytes().startswith(b"%PDF")
    again = invoke_hmpc(["plot", "fig2", str(run / "run.mcap"), "--out", str(tmp_path / "b")],
                        cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    for fmt in ("pdf", "svg", "png"):
        name = f"fig2.{fmt}"
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


def test_virtual_node_is_past_the_guard_by_the_tube(run):
    log = read_log(run / "run.mcap")
    info = log.topic("/run/info")[0].data
    system = _logged_system(json.loads(info["scenario_json"])["system"], "log")
    solves = log.topic("/mpc/solve")
    crossing = [i + 1 for i, m in enumerate(solves)
                if max(n["seg"] for n in m.data["plan"]) >= 1]
    assert crossing and fig2_geometry(run).solve == crossing[0]
    for k in crossing:
        geo = fig2_geometry(run, solve=k)
        g = system.guards[geo.guard]
        assert geo.guard == solves[k - 1].data["schedule"]["guards"][0]
        assert geo.radius == 0.025 and geo.slack <= TOL
        # the guard node is on the guard, the post-reset node is its reset
        assert abs(geo.guard_node_gap) < TOL
        assert np.allclose(geo.post_reset, geo.reset_of_guard_node, rtol=0, atol=1e-9)
        # the NLP's virtual-node row: q(x_v) <= -kappa(d, past=True)
        assert geo.kappa == g.kappa(geo.radius, past=True)
        assert geo.virtual_q <= -geo.kappa + TOL and geo.nlp_row >= -TOL
        assert geo.virtual_gap < 0.0 and geo.disc_past
        # x_v is one RK4 interval of the source flow (node step) with the virtual input
        mode = system.mode_index(g.source)
        xv = system.numeric.rk4[mode](geo.guard_node[None], geo.virtual_input[None],
                                      np.zeros((1, system.n_w)), np.array([[geo.dt]]))[0]
        assert np.allclose(geo.virtual_node, xv[0], rtol=0, atol=1e-9)
        assert abs(geo.dt - 1 / 60) < 1e-9
        xs = ca.SX.sym("x", system.n_x)
        q = ca.Function("q", [xs], [g.q_expr(xs)])
        assert abs(float(q(geo.virtual_node)) - geo.virtual_q) < 1e-12
        # the disc's point nearest the guard has the largest gap over the disc
        dist = np.linalg.norm(geo.disc_point - geo.virtual_node[list(geo.plane)])
        assert abs(dist - geo.radius) < 1e-9
        assert geo.disc_gap >= geo.virtual_gap


def test_radius_options_and_the_verdict(run, tmp_path):
    geo = fig2_geometry(run, radius=0.3)
    fig2(geo, tmp_path, "png")
    assert geo.radius == 0.3 and geo.radius_source == "given radius"
    assert not geo.disc_past and geo.nlp_row < 0  # a tube this large does not pass
    assert (tmp_path / "fig2.png").is_file() and not (tmp_path / "fig2.pdf").exists()
    tube = fig2_geometry(run, from_tube=True)  # nominal: no disturbance, zero tube
    assert tube.radius == 0.0 and tube.radius_source == (
        f"the kinematic tube at 10 Hz, the radius of guard {tube.guard_name!r}'s margins")
    assert tube.disc_gap == pytest.approx(tube.virtual_gap)


def test_from_tube_draws_the_radius_the_guards_margins_use(tmp_path):
    """The disturbed ball at 10 Hz: the guard sees positions only, so --from-tube draws
    the kinematic tube hmpc tube gives its margins, not the full-state diam T(dt)."""
    from conftest import run_loop
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.tube import analyse, region_from_scenario

    sc, _ = load_scenario(BALL.with_name("ball_disturbed.toml"), ["sim.duration=0.3"])
    run_loop(sc, tmp_path / "run.mcap")
    geo = fig2_geometry(tmp_path / "run.mcap", from_tube=True)
    system = build_system(sc.system)
    report = analyse(system, region=region_from_scenario(system), kind=sc.disturbance.kind,
                     magnitude=sc.disturbance.magnitude, kp=sc.lowlevel.kp,
                     kd=sc.lowlevel.kd, rate_hz=10.0, seed=sc.seed)
    row = report.row(10.0)
    assert geo.radius == row.margins.guards[geo.guard].radius == row.kinematic
    assert 0.0 < geo.radius < row.diam
    assert geo.kappa == row.margins.guards[geo.guard].pass_through


def _with_margins(run, dst, source: str, row, scenario: dict | None = None):
    """The run's log as if its NLP had used margins ``row`` (a RateMargins) from ``source``."""

    def edit(topic, data):
        if topic == "/run/info":
            data["margins"] = {**data["margins"], "source": source, "radius": row.radius,
                               "guards": [{"guard": k, "avoid": g.avoid,
                                           "pass_through": g.pass_through}
                                          for k, g in row.guards.items()]}
            if scenario is not None:
                data["scenario_json"] = json.dumps(scenario)
        return data

    return rewrite(run / "run.mcap", dst, edit)


def test_the_default_radius_is_the_one_the_runs_margins_used(run, tmp_path):
    """With mpc.margins a file or "tube", the NLP used the guard's offsets from there: the
    figure draws that guard's radius, and its kappa is the logged pass-through offset; a
    file that no longer holds the logged offset is refused."""
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import scenario_model
    from hmpc_cli.run.tube_margins import tube_margins_file
    from hmpc_cli.tube.margins_file import read_margins

    file = BALL.parent / "margins" / "ball_fig3.toml"
    row = read_margins(file).at(10.0)
    geo = fig2_geometry(_with_margins(run, tmp_path / "file.mcap", str(file), row))
    offsets = row.guards[geo.guard_name]
    assert geo.radius == offsets.radius > 0.0 and geo.kappa == offsets.pass_through
    assert geo.radius_source == f"the radius of guard {geo.guard_name!r}'s margins in {file}"
    changed = tmp_path / "changed.toml"
    changed.write_text(file.read_text().replace(
        f"pass_through = {offsets.pass_through!r}", "pass_through = 0.5"))
    with pytest.raises(PassThroughError, match=(
            f"{changed} no longer holds the pass-through offset the run used for guard "
            f"'{geo.guard_name}' .*; pass --radius or --from-tube")):
        fig2_geometry(_with_margins(run, tmp_path / "changed.mcap", str(changed), row))
    scenario = json.loads(read_log(run / "run.mcap").topic("/run/info")[0].data[
        "scenario_json"])
    scenario["disturbance"]["kind"] = "paper_fig3"
    scenario["mpc"]["margins"] = "tube"
    sc = scenario_model().model_validate(scenario)
    tube = tube_margins_file(sc, build_system(sc.system)).at(10.0)
    geo = fig2_geometry(_with_margins(run, tmp_path / "tube.mcap", "tube at 10 Hz", tube,
                                      scenario))
    assert geo.radius == tube.guards[geo.guard_name].radius > 0.0
    assert geo.kappa == tube.guards[geo.guard_name].pass_through
    assert geo.radius_source.endswith("margins in the run's tube at 10 Hz")


def bad_cases(run, tmp_path) -> dict[str, list[str]]:
    log = run / "run.mcap"

    def no_crossing(topic, data):
        if topic == "/mpc/solve":
            for node in data["plan"]:
                node["seg"] = 0
        return data

    def no_plane(topic, data):
        if topic == "/run/info":
            data["scenario_json"] = json.dumps({**json.loads(data["scenario_json"]),
                                                "system": {"name": "biped"}})
        return data

    flat = rewrite(log, tmp_path / "flat.mcap", no_crossing)
    biped = rewrite(log, tmp_path / "biped.mcap", no_plane)
    return {"no such log": [str(tmp_path / "missing")],
            "no crossing": [str(flat)],
            "no plane": [str(biped)],
            "solve 0": [str(log), "--solve", "0"],
            "solve too large": [str(log), "--solve", "99"],
            "both radii": [str(log), "--radius", "0.1", "--from-tube"],
            "negative radius": [str(log), "--radius", "-1"],
            "bad format": [str(log), "--formats", "gif"]}


def test_bad_input_exits_2_and_writes_nothing(run, tmp_path):
    app = make_app()
    before = sorted(p.name for p in run.iterdir())
    for name, args in bad_cases(run, tmp_path).items():
        out = tmp_path / f"out_{name.replace(' ', '_')}"
        res = CliRunner().invoke(app, ["plot", "fig2", *args, "--out", str(out)])
        assert res.exit_code == 2, f"{name}: {res.output}"
        err = res.stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), f"{name}: {res.stderr!r}"
        assert not out.exists(), name
    assert sorted(p.name for p in run.iterdir()) == before
    with pytest.raises(PassThroughError, match="no logged solve plans a guard crossing"):
        fig2_geometry(tmp_path / "flat.mcap")
    with pytest.raises(PassThroughError, match="no 2-D drawing plane"):
        fig2_geometry(tmp_path / "biped.mcap")


def test_title_says_what_went_wrong(run):
    from dataclasses import replace

    from hmpc_cli.figures.fig2 import _title

    geo = fig2_geometry(run)
    assert "lies entirely past the guard" in _title(geo) and "softened" not in _title(geo)
    assert "NOT entirely past" in _title(replace(geo, disc_gap=0.01))
    soft = _title(replace(geo, slack=0.008, guard_node_gap=0.008))
    assert "softened solve (slack 0.008)" in soft and "gap is 0.008" in soft
