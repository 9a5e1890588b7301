"""The walking NLP's stage-wise transcription and its back-ends (fatrop, sqp_hpipm, rti)."""

from dataclasses import replace
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from hmpc_cli.mpc.walking.kind import WalkingMPC
from hmpc_cli.mpc.walking.nlp import WalkingMPCSettings, WalkingNLP
from hmpc_cli.run.runner import prepare, run_unlogged
from hmpc_cli.run.scenario import load_scenario
from hmpc_cli.systems.biped import BipedParams, build_biped

ROOT = Path(__file__).resolve().parents[1]

SYS = build_biped(BipedParams())
SEGMENT = 1  # the 1.0 m segment


@pytest.fixture(scope="module")
def ipopt_plan():
    return WalkingMPC(SYS, WalkingMPCSettings()).solve_segment(0.0, SYS.x0, SEGMENT, 0.0)


def _names(nlp: WalkingNLP) -> np.ndarray:
    """Per row, the name of its block."""
    g = nlp.layout.g
    out = np.empty(g.size, dtype=object)
    for name in g.names:
        out[np.asarray(g[name]).ravel()] = name
    return out


def test_stagewise_transcription_has_the_stage_structure():
    ipopt = WalkingNLP(SYS, WalkingMPCSettings())
    stage = WalkingNLP(SYS, WalkingMPCSettings(solver="fatrop"))
    n = stage.N
    assert not ipopt.stagewise and stage.stagewise
    # swing 1 carries the stance foot (2 per node); two rows per swing-1 interval keep it
    assert stage.nw == ipopt.nw + 2 * (n + 1)
    assert stage.ng == ipopt.ng + 2 * n + 2
    st = stage.structure()
    assert st.sizes() == (stage.nw, stage.ng)
    assert st.nx[0] == 0 and st.nx[1] == stage.nx and st.nx[-1] == stage.nx + 2
    assert st.nu[n] == 0 and st.nu[-1] == 0
    # an interval's rows are the same 18 in both orders: the warm starts shift them alike
    assert stage.interval_rows.shape == ipopt.interval_rows.shape == (2, n, 18)
    assert (_names(stage)[stage.interval_rows] == _names(ipopt)[ipopt.interval_rows]).all()
    # gap rows before path rows: stage (0, 0) is its dynamics, torque, then the liftoff row
    names = _names(stage)
    assert list(names[:stage.nx]) == ["dynamics"] * stage.nx
    assert names[stage.nx + stage.nq] == "liftoff"
    eq = stage.equality_rows()
    assert eq.sum() == 10 * n + 12 * n + 12 + 1  # dynamics, stance foot, reset, touchdown y
    with pytest.raises(ValueError, match="stage-wise back-end"):
        ipopt.structure()


def test_stagewise_back_ends_reach_ipopts_optimum(ipopt_plan):
    """fatrop, and IPOPT on the stage-wise NLP (sqp_hpipm's fallback), find IPOPT's plan."""
    for settings in (WalkingMPCSettings(solver="fatrop"),
                     WalkingMPCSettings(solver="sqp_hpipm", max_sqp_iter=2)):
        plan = WalkingMPC(SYS, settings).solve_segment(0.0, SYS.x0, SEGMENT, 0.0)
        assert plan.stats.success, plan.stats.status
        assert plan.stats.cost == pytest.approx(ipopt_plan.stats.cost, rel=1e-6)
        assert np.abs(plan.traj.x - ipopt_plan.traj.x).max() < 1e-3
        assert plan.traj.x.shape == ipopt_plan.traj.x.shape
    assert plan.stats.fallback  # two Gauss-Newton steps from the held pose do not converge


def test_rti_steps_are_bounded_kept_and_hold_the_linear_rows(ipopt_plan):
    """One Gauss-Newton step per warm solve (three cold): each plan kept; the linear rows
    (dynamics, the stance foot kept) hold exactly, the torques within their limits, the
    cost near IPOPT's optimum. The impact map's rows are what such steps leave violated
    from one state (full steps oscillate on them): the plan is not IPOPT's optimum."""
    mpc = WalkingMPC(SYS, WalkingMPCSettings(solver="rti"))
    nlp = mpc.nlp
    plans = [mpc.solve_segment(0.0, SYS.x0, SEGMENT, 0.0) for _ in range(8)]
    assert [p.stats.iterations for p in plans] == [3] + [1] * 7
    assert all(p.stats.success for p in plans)  # kept although not converged
    assert plans[0].stats.status == "Maximum_Iterations_Exceeded"
    w = mpc._memory[SEGMENT].w
    p, lbx, ubx, lbg, ubg = nlp.problem_data(SYS.x0, mpc.segments[SEGMENT], 0.0)
    g = nlp.constraints(w, p)
    viol = np.maximum(lbg - g, g - ubg)
    rows = nlp.layout.g
    for name in ("dynamics", "stance_foot", "torque"):
        assert viol[np.asarray(rows[name]).ravel()].max() <= 1e-9, name
    assert viol[np.asarray(rows["reset"]).ravel()].max() > 0.1
    assert plans[-1].stats.cost == pytest.approx(ipopt_plan.stats.cost, rel=0.05)
    # swing 1's stance foot starts at the guess's touchdown (the reset's value)
    stance = w[nlp.layout.x["stance"]].reshape(-1, 2)
    assert np.ptp(stance, axis=0).max() <= 1e-9


def test_gauss_newton_back_ends_need_stage_residuals():
    bare = replace(SYS, stage_residuals=None)
    with pytest.raises(ValueError, match="needs the system's stage_residuals.*'biped'"):
        WalkingNLP(bare, WalkingMPCSettings(solver="rti"))
    assert WalkingNLP(bare, WalkingMPCSettings(solver="fatrop")).stagewise  # exact Hessian


def test_stage_residuals_are_checked_against_the_stage_cost():
    x, u = ca.SX.sym("x", SYS.n_x), ca.SX.sym("u", SYS.n_u)
    wrong = ca.Function("r", [x, u], [2.0 * SYS.stage_residuals(x, u)])
    with pytest.raises(ValueError, match=r"\|stage_residuals\(x, u\)\|\^2 = .* but stage_cost"):
        replace(SYS, stage_residuals=wrong)
    with pytest.raises(ValueError, match="must map"):
        replace(SYS, stage_residuals=ca.Function("r", [x], [x]))


@pytest.mark.slow
def test_biped_rti_climbs_with_its_compute_time_modelled():
    """scenarios/biped_rti.toml: deterministic (model latency), every solve one or three
    SQP steps, and it climbs; the same run twice gives the same end."""
    ends = []
    for _ in range(2):
        sc, _ = load_scenario(ROOT / "scenarios" / "biped_rti.toml")
        run = prepare(sc)
        result = run_unlogged(run)
        assert result.success, result.reason
        ends.append((result.t_end, result.final_error))
    assert ends[0] == ends[1]
