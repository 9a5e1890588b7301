"""sim.latency: the controllers' compute time charged to the simulation."""

from pathlib import Path

import numpy as np
import pytest

from hmpc_cli.log.reader import read_log
from hmpc_cli.log.rundata import read_run
from hmpc_cli.run.runner import prepare, run_to_log
from hmpc_cli.run.scenario import ScenarioError, load_scenario

ROOT = Path(__file__).resolve().parents[1]
BALL = ROOT / "scenarios" / "ball.toml"
L = 0.05  # [s]: 30 simulator steps of 1/600 s, half an MPC period of 0.1 s


def _run(tmp_path, name, overrides):
    """Runs the ball for 0.6 s; returns the log, the solves (t, plan) and the plan
    handed to the low level at each step (t, plan or None)."""
    sc, _ = load_scenario(BALL, ["sim.duration=0.6", *overrides])
    loop = prepare(sc)
    solves, used = [], []
    solve, command = loop.mpc.solve, loop.plant.command

    def spy_solve(t, *args, **kw):
        plan = solve(t, *args, **kw)
        solves.append((t, plan))
        return plan

    def spy_command(t, x, mode, plan, span):
        used.append((t, plan))
        return command(t, x, mode, plan, span)

    loop.mpc.solve, loop.plant.command = spy_solve, spy_command
    result = run_to_log(loop, tmp_path / f"{name}.mcap")
    return result, tmp_path / f"{name}.mcap", solves, used


def _first_use(used, plan):
    return next(t for t, p in used if p is plan)


def test_a_fixed_latency_delays_each_plan_by_exactly_that(tmp_path):
    _, log_p, solves_p, used_p = _run(tmp_path, "paused", ["sim.latency=\"paused\""])
    _, log_d, solves_d, used_d = _run(tmp_path, "delayed", [f"sim.latency={L}"])
    h = 1.0 / 600
    # the first plan is solved from the same state at t = 0 in both runs
    (t0p, first_p), (t0d, first_d) = solves_p[0], solves_d[0]
    assert t0p == t0d == 0.0
    assert np.array_equal(first_p.traj.u, first_d.traj.u)
    assert _first_use(used_p, first_p) == 0.0
    assert _first_use(used_d, first_d) == pytest.approx(L, abs=1e-12)  # 30 steps later
    assert all(p is None for t, p in used_d if t < L - 1e-9)  # nothing to track before
    # every adopted plan reaches the plant at its solve time (paused) or exactly L later,
    # to the simulator step; the previous plan is tracked meanwhile
    for solves, used, delay in ((solves_p, used_p, 0.0), (solves_d, used_d, L)):
        for t, plan in solves:
            if plan.adopt and t + delay < 0.6 - h / 2:
                due = np.ceil((t + delay) / h - 1e-6) * h
                assert _first_use(used, plan) == pytest.approx(due, abs=1e-9), (t, delay)
    assert len(solves_d) > 3
    # the delay is logged with each solve
    lat_p = [m.data["latency"] for m in read_log(log_p).topic("/mpc/solve")]
    lat_d = [s.latency for s in read_run(log_d).solves]
    assert lat_p == [0.0] * len(solves_p) and lat_d == [L] * len(solves_d)


def test_the_first_plan_can_be_computed_with_time_paused(tmp_path):
    _, log, solves, used = _run(tmp_path, "first", [f"sim.latency={L}",
                                                    'sim.latency_first="paused"'])
    _, _, solves_c, used_c = _run(tmp_path, "charged", [f"sim.latency={L}"])
    h = 1.0 / 600
    (t0, first), (_, first_c) = solves[0], solves_c[0]
    assert t0 == 0.0 and np.array_equal(first.traj.u, first_c.traj.u)
    assert _first_use(used, first) == 0.0  # tracked at once: no step without a plan
    assert all(p is not None for _, p in used)
    assert _first_use(used_c, first_c) == pytest.approx(L, abs=1e-12)  # the default waits
    later = [(t, p) for t, p in solves[1:] if p.adopt and t + L < 0.6 - h / 2]
    assert len(later) >= 3  # every later plan waits its latency, to the simulator step
    for t, plan in later:
        assert _first_use(used, plan) == pytest.approx(np.ceil((t + L) / h - 1e-6) * h,
                                                       abs=1e-9), t
    lat = [m.data["latency"] for m in read_log(log).topic("/mpc/solve")]
    assert lat[0] == 0.0 and lat[1:] == [L] * (len(lat) - 1)


def test_paused_is_the_default_bit_for_bit(tmp_path):
    _, log_default, _, _ = _run(tmp_path, "default", [])
    _, log_paused, _, _ = _run(tmp_path, "paused", ["sim.latency=\"paused\""])
    a, b = read_run(log_default), read_run(log_paused)
    assert len(a.t) > 0 and np.array_equal(a.t, b.t)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.u, b.u)


@pytest.mark.slow
def test_measured_latency_is_the_compute_time_and_is_flagged(tmp_path):
    result, log, solves, used = _run(tmp_path, "measured", ["sim.latency=\"measured\""])
    assert any("not reproducible" in w for w in result.warnings)
    run = read_run(log)
    for rec, (_, plan) in zip(run.solves, solves, strict=True):
        assert rec.latency >= plan.stats.wall_time > 0.0  # + the planner's time, if it ran


@pytest.mark.parametrize("value", ["\"later\"", "-0.1"])
def test_bad_latency_is_a_keyed_error(value):
    with pytest.raises(ScenarioError) as exc:
        load_scenario(BALL, [f"sim.latency={value}"])
    assert any("sim.latency" in line for line in exc.value.lines)


def test_one_solver_a_rate_beyond_its_pace_runs_at_its_pace(tmp_path):
    """With L = 0.05 s a solve falling due while the solver computes waits for it: solves
    are at least L apart, and 100 Hz solves exactly when 20 Hz (period L) does."""
    # every rate a whole number of node steps; a 1 s horizon keeps that grid's NLPs small
    grid = ["mpc.nodes_per_second=100", "mpc.horizon=1.0"]
    _, _, solves_fast, _ = _run(tmp_path, "fast", [f"sim.latency={L}", "mpc.rate_hz=100",
                                                   *grid])
    _, _, solves_20, _ = _run(tmp_path, "twenty", [f"sim.latency={L}", "mpc.rate_hz=20",
                                                   *grid])
    times = [t for t, _ in solves_fast]
    assert len(times) > 5
    assert min(np.diff(times)) >= L - 1e-9
    assert times == [t for t, _ in solves_20]
    # time paused, 100 Hz really solves every 0.01 s
    _, _, solves_p, _ = _run(tmp_path, "paused100", ["mpc.rate_hz=100", *grid])
    assert len(solves_p) > 2 * len(solves_fast)
