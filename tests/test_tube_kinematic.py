"""The kinematic tube: states whose error integrates another's, and the margins it buys.

Closed forms: int_0^t c s e^{L s} ds; the kinematic states of the ball and the biped;
Hermite interpolation exact on a constant-acceleration plan; the biped's declared
foot-height Lipschitz constant above every sampled gradient; the walking MPC's margins
from a margins file (the same mechanism as the chain NLP's).
"""

from __future__ import annotations

import math
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import SCENARIOS
from hmpc_cli.cli.app import app
from hmpc_cli.core.messages import ConstraintMargins
from hmpc_cli.core.registry import build_system, registry
from hmpc_cli.tube import Region, analyse, margins, trivial_tube
from hmpc_cli.tube.bounds import integrated_tube
from hmpc_cli.tube.structure import ZERO, guard_states, kinematic_rates
from hmpc_cli.analysis.tube_reality import RecordedRun, run_periods


def _system(name: str):
    return build_system(registry().system(name).params())


def test_integrated_trivial_tube_matches_its_closed_form_from_above():
    c, L, t = 3.0, 7.0, 0.05
    exact = c * ((t / L - 1 / L**2) * math.exp(L * t) + 1 / L**2)
    got = integrated_tube(t, lambda s: trivial_tube(s, c, L, 0.0, 0.0))
    assert exact <= got <= exact * 1.01
    assert integrated_tube(0.0, lambda s: s) == 0.0
    # any (even decreasing) function: the running maximum keeps it an upper bound
    assert integrated_tube(1.0, lambda s: 1.0 - s) >= 0.5
    assert math.isinf(integrated_tube(1.0, lambda s: np.where(s > 0.5, np.nan, s)))


def test_the_balls_positions_and_the_bipeds_angles_and_stance_are_kinematic():
    ball = _system("ball")
    assert kinematic_rates(ball) == {0: 2, 1: 3}  # px' = vx, py' = vy
    biped = _system("biped")
    assert kinematic_rates(biped) == {**{i: i + 5 for i in range(5)}, 10: ZERO, 11: ZERO}
    for g in ball.guards:
        assert set(guard_states(g, 4)) <= {0, 1}
    assert guard_states(ball.guards[0], 4) == (1,)  # the floor sees py only


def test_a_state_whose_rate_differs_between_modes_is_not_kinematic():
    """docs/tubes.md: the same rate in every mode. A position that is p' = v in one mode
    and held (p' = 0) in the other, as a foot that follows the body in flight and is
    pinned in stance, is not kinematic; one held in every mode is (ZERO)."""
    from dataclasses import replace

    ball = _system("ball")
    x, u, w = ca.SX.sym("x", 4), ca.SX.sym("u", 2), ca.SX.sym("w", 2)
    inside = ball.modes[1]
    f = inside.flow(x, u, w)
    held = replace(inside, flow=ca.Function("f_held", [x, u, w], [ca.vertcat(0, f[1:])]))
    assert kinematic_rates(replace(ball, modes=(ball.modes[0], held))) == {1: 3}
    out = ball.modes[0].flow(x, u, w)
    both = [replace(m, flow=ca.Function(f"f_{m.name}", [x, u, w], [ca.vertcat(0, g[1:])]))
            for m, g in ((ball.modes[0], out), (inside, f))]
    assert kinematic_rates(replace(ball, modes=tuple(both))) == {0: ZERO, 1: 3}


def test_kinematic_guards_get_the_kinematic_radius():
    ball = _system("ball")
    m = margins(ball, 0.5, 0.0, kinematic=0.01, kinematic_guards=(True, False, True, True))
    assert [g.radius for g in m.guards] == [0.01, 0.5, 0.01, 0.01]
    assert m.guards[0].avoid == pytest.approx(0.01) and m.guards[1].avoid == 0.5
    assert m.kinematic == 0.01
    # the kinematic radius never exceeds the state radius
    assert margins(ball, 0.1, 0.0, 5.0, (True,) * 4).guards[0].radius == 0.1


def test_the_ball_reports_a_kinematic_tube_far_below_its_state_tube():
    ball = _system("ball")
    rep = analyse(ball, region=Region([0, 0, -5, -5], [10, 10, 5, 5]), kind="box",
                  magnitude=10.0, kp=0.0, kd=0.0, rate_hz=20, samples=2000)
    row = rep.row(20.0)
    # |e_p(dt)| <= int_0^dt diam(s) ds: about dt / 2 of diam T(dt) for small L_x dt
    assert 0 < row.kinematic < row.diam * 0.05 * 0.6
    assert rep.kinematic_guards == (True,) * 4
    assert all(g.radius == row.kinematic for g in row.margins.guards)


def test_hermite_interpolation_is_exact_on_a_constant_acceleration_plan():
    """Plan nodes on an uneven grid, samples between them: zero kinematic deviation."""
    acc, v0 = 3.0, -1.0

    def x(t):
        return np.array([v0 * t + 0.5 * acc * t**2, v0 + acc * t])

    t_plan = np.array([0.0, 0.013, 0.029, 0.041, 0.06])
    run = RecordedRun("r", {}, np.array([0.005, 0.02, 0.035, 0.05]),
                      np.array([x(t) for t in (0.005, 0.02, 0.035, 0.05)]), np.zeros(0),
                      [(0.0, t_plan, np.array([x(t) for t in t_plan]), np.zeros(5, dtype=int))])
    (p,), skipped, unmatched = run_periods(run, {0: 1}, interpolate=True)
    assert skipped == unmatched == 0 and len(p.tau) == 4
    assert np.max(p.dev_kin) < 1e-12 and np.max(p.dev) < 1e-12  # the velocity: linear
    # interpolating the position linearly too (no known rate) would not be exact:
    (q,), _, _ = run_periods(run, {0: ZERO}, interpolate=True)
    assert np.max(q.dev_kin) > 1e-5


def test_biped_foot_height_lipschitz_constant_bounds_its_gradient():
    biped = _system("biped")
    g = biped.guards[0]
    x = ca.SX.sym("x", biped.n_x)
    grad = ca.Function("dq", [x], [ca.gradient(g.q_expr(x), x)])
    rng = np.random.default_rng(0)
    lo, hi = biped.state_box
    lo, hi = np.where(np.isfinite(lo), lo, -5), np.where(np.isfinite(hi), hi, 5)
    worst = max(float(np.linalg.norm(np.asarray(grad(rng.uniform(lo, hi)))))
                for _ in range(2000))
    assert worst <= g.lipschitz and worst > 0.5 * g.lipschitz


def test_walking_nlp_takes_its_margins_from_constraint_margins():
    from hmpc_cli.mpc.walking.nlp import WalkingMPCSettings, WalkingNLP, hand_margins

    biped = _system("biped")
    s = WalkingMPCSettings()
    hand = hand_margins(biped, s)
    assert hand.avoid == (s.terrain_margin,) * len(biped.guards)
    assert hand.inputs == ((s.torque_margin,) * 5,)
    n = len(biped.guards)
    m = ConstraintMargins("file", 0.01, (0.03,) * n, (0.0,) * n, (0.1,) * n,
                          ((100.0, 200.0, 300.0, 400.0, 500.0),))
    nlp = WalkingNLP(biped, WalkingMPCSettings(nodes_per_swing=6, apex_node=3), m)
    assert nlp.terrain_margin == 0.03 and nlp.segment_margin == 0.1
    seg = next(iter(biped.guard_surfaces.values()))
    _, _, _, lbg, ubg = nlp.problem_data(np.asarray(biped.x0, float), seg, 0.0)
    rows = nlp.layout.g
    torque = np.asarray(ubg)[rows["torque"]].reshape(-1, 5)
    assert np.allclose(torque, 3000.0 - np.array([100, 200, 300, 400, 500]))
    assert np.allclose(np.asarray(lbg)[rows["torque"]].reshape(-1, 5), -torque)
    td = np.asarray(lbg)[rows["touchdown"]]
    assert td[0] == pytest.approx(seg[0] + 0.1)


def test_a_biped_margins_file_without_a_finite_tube_exits_2(tmp_path: Path):
    """The biped's trivial tube overflows at 10 Hz: the run refuses the file, exit 2."""
    runner = CliRunner()
    f = tmp_path / "biped_margins.toml"
    res = runner.invoke(app, ["tube", str(SCENARIOS / "biped_stairs.toml"), "--samples",
                              "300", "--formats", "png", "--out", str(tmp_path / "t"),
                              "--write", str(f)])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["run", str(SCENARIOS / "biped_stairs.toml"), "--set",
                              f'mpc.margins="{f}"', "--out", str(tmp_path / "r")])
    assert res.exit_code == 2
    assert "mpc.margins" in res.output and "not finite" in res.output
    assert not (tmp_path / "r").exists()
