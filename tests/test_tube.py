"""Tubes (Section III-B): every formula against a closed form, and ``hmpc tube`` end to end."""

from __future__ import annotations

import json
import math
import os
import subprocess
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from conftest import BALL, REPO, SCENARIOS, cli_env, hmpc_command, hmpc_in_process
from hmpc_cli.core.hybrid import Guard, HybridSystem, Mode
from hmpc_cli.tube import (
    Margins, Region, TubeError, a_bound, analyse, eiss_constants, eta_bound,
    feedforward_tube, lipschitz, low_level_share, margins, pd_certificate,
    region_from_scenario, solve_lyapunov, tau_of, trivial_tube, zeta_bound)

BIPED = SCENARIOS / "biped_stairs.toml"
RATES = ("5 Hz", "10 Hz", "20 Hz", "50 Hz", "100 Hz")


def make_system(flow, n: int, m: int, n_w: int, u_box: float = 1.0, gain=None,
                guard: bool = False, x0=None) -> HybridSystem:
    """One mode with the given flow(x, u, w) (SX expressions), optionally one guard x1 = 1."""
    x, u, w = ca.SX.sym("x", n), ca.SX.sym("u", m), ca.SX.sym("w", n_w)
    mode = Mode("only", ca.Function("f", [x, u, w], [flow(x, u, w)]), (-u_box,) * m,
                (u_box,) * m)
    guards = (Guard("wall", "only", "only", ca.Function("h", [x], [x[0]]), 1.0, +1,
                    reset=ca.Function("R", [x], [x])),) if guard else ()
    return HybridSystem(
        name="toy", state_names=tuple(f"x{i}" for i in range(n)),
        input_names=tuple(f"u{i}" for i in range(m)),
        disturbance_names=tuple(f"w{i}" for i in range(n_w)), modes=(mode,), guards=guards,
        initial_mode="only", final_mode="only",
        x0=np.zeros(n) if x0 is None else np.asarray(x0, float), goal=np.zeros(n),
        goal_map=ca.Function("g", [x], [x]), stage_cost=ca.Function("L", [x, u], [ca.sumsqr(x)]),
        terminal_set=None,
        tracking_gain=gain or (lambda kp, kd: np.zeros((m, n))))


def linear(A, B, Bw, **kw) -> HybridSystem:
    A, B, Bw = (np.atleast_2d(np.asarray(v, float)) for v in (A, B, Bw))
    return make_system(lambda x, u, w: ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u)
                       + ca.mtimes(ca.DM(Bw), w), A.shape[0], B.shape[1], Bw.shape[1], **kw)


BOX = Region(-np.ones(2), np.ones(2))


# ------------------------------------------------------------------ constants
def test_linear_system_lipschitz_constants_are_the_matrix_norms():
    A, B = np.array([[0.3, 2.0], [-1.0, 0.5]]), np.array([[1.0], [3.0]])
    est = lipschitz(linear(A, B, np.eye(2)), BOX, samples=500)
    assert est.L_x == pytest.approx(np.linalg.norm(A, 2), rel=1e-12)
    assert est.L_u == pytest.approx(np.linalg.norm(B, 2), rel=1e-12)
    assert "not a certificate" in est.note and est.samples >= 500


def test_lipschitz_of_sin_2x_is_2_within_one_percent():
    sys_ = make_system(lambda x, u, w: ca.vertcat(ca.sin(2 * x[0]), ca.sin(2 * x[1]) + u[0]),
                       2, 1, 1)
    est = lipschitz(sys_, Region([0.2, 0.3], [1.3, 2.5]), samples=2000, seed=3)
    # |d sin(2 x)/dx| = |2 cos(2 x)| reaches 2 only at x = k pi / 2 (x2 = pi / 2 here)
    assert 0.99 * 2 <= est.L_x <= 2 + 1e-12
    assert abs(est.argmax_x[1] - math.pi / 2) < 0.05


def test_eta_of_a_known_w_map():
    Bw = np.array([[1.0, 0.0], [0.0, 3.0]])
    d = eta_bound(linear(np.zeros((2, 2)), np.zeros((2, 1)), Bw), BOX, "box", 2.0, 200)
    assert d.eta == pytest.approx(3.0 * 2.0 * math.sqrt(2.0), rel=1e-12)
    assert d.gain == pytest.approx(3.0) and not d.zero


def test_zero_disturbance_set_is_reported():
    d = eta_bound(linear(np.eye(2), np.ones((2, 1)), np.eye(2)), BOX, "none", 10.0)
    assert d.zero and d.eta == 0.0 and "zero disturbance set" in d.note
    assert eta_bound(linear(np.eye(2), np.ones((2, 1)), np.eye(2)), BOX, "box", 0.0).zero


def test_region_errors_and_non_finite_jacobian():
    sys_ = linear(np.eye(2), np.ones((2, 1)), np.eye(2))
    with pytest.raises(TubeError, match="empty") as exc:
        lipschitz(sys_, Region([0.0, 1.0], [1.0, 0.0]))
    assert exc.value.quantity == "region"
    with pytest.raises(TubeError, match="degenerate"):
        lipschitz(sys_, Region([0.0, 0.0], [0.0, 0.0]))
    with pytest.raises(TubeError, match="non-finite"):
        lipschitz(sys_, Region([0.0, -np.inf], [1.0, 1.0]))
    root = make_system(lambda x, u, w: ca.vertcat(ca.sqrt(x[0]), x[1] + u[0]), 2, 1, 1)
    with pytest.raises(TubeError, match="not finite") as exc:
        lipschitz(root, BOX, samples=100)
    assert exc.value.quantity == "L_x"


def test_region_from_scenario_spans_x0_and_the_goal():
    sys_ = linear(np.eye(2), np.ones((2, 1)), np.eye(2), x0=[1.0, 0.0])
    reg = region_from_scenario(sys_, pad=0.5)  # goal 0 selected by the identity goal map
    np.testing.assert_allclose(reg.lower, [-0.5, -0.5])
    np.testing.assert_allclose(reg.upper, [1.5, 0.5])


# ------------------------------------------------------------------ the plant's mismatch
def test_eta_adds_the_plants_flow_mismatch_to_its_own_w_part():
    """eta = max ||f_p(x, u, 0) - f(x, u, 0)|| + max ||df_p/dw|| ||w_max||: closed forms."""
    model = linear(np.eye(2), [[1.0], [0.0]], np.eye(2), u_box=2.0)
    plant = linear(np.eye(2), [[1.0], [3.0]], 2.0 * np.eye(2), u_box=2.0)
    d = eta_bound(model, BOX, "box", 2.0, 300, plant=plant, plant_note="B, Bw changed")
    # f_p - f = (0, 3 u): largest at the input box's corner |u| = 2
    assert 0.99 * 6.0 <= d.mismatch <= 6.0 + 1e-12 and d.mismatch_samples >= 300
    assert d.gain == pytest.approx(2.0, rel=1e-12)  # the plant's df/dw, not the model's 1
    assert d.from_w == pytest.approx(2.0 * 2.0 * math.sqrt(2.0), rel=1e-12)
    assert d.eta == d.mismatch + d.from_w and not d.zero
    assert d.plant == "B, Bw changed" and "max ||f_plant - f_model||_2" in d.note
    (x, u) = (np.array(d.mismatch_x), np.array(d.mismatch_u))
    assert abs(3.0 * u[0]) == pytest.approx(d.mismatch, rel=1e-12) and BOX.lower[0] <= x[0]
    # no w part (kind none): eta is the mismatch alone, not the zero set
    none = eta_bound(model, BOX, "none", 2.0, 300, plant=plant)
    assert none.eta == none.mismatch > 0.0 and none.from_w == 0.0 and not none.zero
    # the model as its own plant: exactly the plant-free bound, nothing more sampled
    alone = eta_bound(model, BOX, "box", 2.0, 300)
    assert eta_bound(model, BOX, "box", 2.0, 300, plant=model) == alone
    assert alone.mismatch == 0.0 and alone.mismatch_samples == 0 and alone.plant == ""
    other = linear(np.eye(3), np.ones((3, 1)), np.eye(3))
    with pytest.raises(TubeError, match="modes or dimensions") as exc:
        eta_bound(model, BOX, "box", 2.0, 300, plant=other)
    assert exc.value.quantity == "eta"


def _ball(sets: list[str]):
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.run.tube_margins import plant_system

    sc, _ = load_scenario(SCENARIOS / "ball_disturbed.toml", sets)
    model = build_system(sc.system)
    return sc, model, *plant_system(sc)


def _report(model, sc, plant=None, note=""):
    return analyse(model, region=region_from_scenario(model), kind=sc.disturbance.kind,
                   magnitude=sc.disturbance.magnitude, kp=sc.lowlevel.kp, kd=sc.lowlevel.kd,
                   rate_hz=sc.mpc.rate_hz, samples=2000, plant=plant, plant_note=note)


def test_a_heavier_ball_plant_widens_its_tube_and_an_identical_one_changes_nothing():
    sc, model, plant, note = _ball(["plant.mass=2.0"])
    assert note == "mass = 2" and plant is not None
    d = _report(model, sc, plant, note).disturbance
    # f_p - f = (0, 0, u / 2 - u): 0.5 ||u||, largest at the inside box's corner 100 sqrt 2
    assert 0.99 * 50 * math.sqrt(2) <= d.mismatch <= 50 * math.sqrt(2) * (1 + 1e-12)
    assert d.gain == pytest.approx(1.0) and d.from_w == pytest.approx(10 * math.sqrt(2))
    assert d.eta == d.mismatch + d.from_w
    base = _report(model, sc)  # the plant ignored (the old analysis)
    assert d.eta > 3 * base.disturbance.eta
    # an identical plant (or none) is the model: bit for bit the plant-free report
    for sets in (["plant.mass=1.0"], []):
        sc1, model1, plant1, note1 = _ball(sets)
        assert (plant1, note1) == (None, "")
        assert _report(model1, sc1, plant1, note1).to_dict() == base.to_dict()


def test_the_tube_cache_is_keyed_by_the_plant_and_its_file_records_it(tmp_path, monkeypatch):
    from hmpc_cli.run.tube_margins import tube_margins_file, tube_margins_path

    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    rate = ["mpc.rate_hz=20"]
    same = {tube_margins_path(_ball(rate + s)[0]) for s in ([], ["plant.mass=1.0"])}
    heavy = _ball(rate + ["plant.mass=2.0"])
    assert len(same) == 1 and tube_margins_path(heavy[0]) not in same
    file = tube_margins_file(heavy[0], heavy[1])
    dist = file.disturbance
    assert dist["plant"] == "mass = 2" and dist["plant_mismatch"] > 70.0
    assert dist["eta"] == dist["plant_mismatch"] + dist["from_w"]
    plain = tube_margins_file(*_ball(rate)[:2])
    assert "plant" not in plain.disturbance
    assert file.at(20.0).radius > plain.at(20.0).radius > 0.0


def test_the_bipeds_eta_holds_its_heavier_plant():
    """The 1.1x heavier plant's flow differs from the model's by far more than the pushes.

    Independently: with every mass and inertia x s, M, C, G scale by s, so
    f_p(x, u) - f(x, u) = (1/s - 1) (f(x, u) - f(x, 0)) (CasADi, not the sampler's NumPy).
    """
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.run.tube_margins import plant_system

    sc, _ = load_scenario(BIPED)
    model = build_system(sc.system)
    plant, note = plant_system(sc)
    assert note == "mass_scale = 1.1"
    region = region_from_scenario(model)
    d = eta_bound(model, region, "box", 25.0, 2000, plant=plant, plant_note=note)
    alone = eta_bound(model, region, "box", 25.0, 2000)  # the old eta: the box only
    assert d.eta == d.mismatch + d.from_w and d.from_w == d.gain * 25.0
    assert d.gain == pytest.approx(alone.gain / 1.1, rel=0.05)  # M_p^-1 = M^-1 / 1.1
    assert d.mismatch > 100 * alone.eta and d.plant == note

    mode = model.modes[0]
    w0 = np.zeros(model.n_w)

    def gap(x, u):
        fm, fp, f0 = (np.array(f(x, v, w0), dtype=float).ravel() for f, v in (
            (mode.flow, u), (plant.modes[0].flow, u), (mode.flow, 0 * u)))
        assert np.allclose(fp - fm, (1 / 1.1 - 1) * (fm - f0), rtol=1e-9, atol=1e-9)
        return float(np.linalg.norm(fp - fm))

    assert gap(np.array(d.mismatch_x), np.array(d.mismatch_u)) == pytest.approx(
        d.mismatch, rel=1e-9)
    rng = np.random.default_rng(7)
    lo, hi = np.array(mode.u_lower), np.array(mode.u_upper)
    for _ in range(100):
        assert gap(rng.uniform(region.lower, region.upper), rng.uniform(lo, hi)) <= d.mismatch
    # the auditor's points: x0 with +-300 N m torques
    for signs in rng.choice([-1.0, 1.0], (20, model.n_u)):
        assert gap(model.x0, 300.0 * signs) <= d.mismatch


# ------------------------------------------------------------------ tubes
def test_trivial_and_feedforward_tubes_closed_form():
    t = np.array([0.0, 0.1, 0.5])
    np.testing.assert_allclose(trivial_tube(t, 2.0, 3.0, 0.5, 4.0),
                               (2.0 + 0.5 * 4.0) * t * np.exp(3.0 * t))
    assert feedforward_tube(0.1, 2.0, 3.0) == pytest.approx(2.0 * 0.1 * math.exp(0.3))
    assert trivial_tube(0.0, 2.0, 3.0, 0.5, 4.0) == 0.0


def test_low_level_share_is_self_consistent():
    eta, lx, lu, k, box, t = 1.0, 2.0, 0.5, 3.0, 100.0, 0.1
    r, zeta = low_level_share(t, eta, lx, lu, k, box)
    assert zeta == pytest.approx(k * r)
    assert r == pytest.approx(trivial_tube(t, eta, lx, lu, zeta))
    r_sat, z_sat = low_level_share(t, eta, lx, lu, k, box_diameter=0.01)  # the box bound is smaller
    assert z_sat == 0.01 and r_sat == pytest.approx(trivial_tube(t, eta, lx, lu, 0.01))
    assert low_level_share(t, eta, lx, lu, 0.0, box)[1] == 0.0


def test_zeta_bound():
    sys_ = linear(np.eye(2), np.eye(2), np.eye(2), u_box=2.0,
                  gain=lambda kp, kd: np.diag([kp, kd]))
    assert zeta_bound(sys_, 0.0, 0.0, 1.0) == 0.0
    assert zeta_bound(sys_, 3.0, 1.0, 0.5) == pytest.approx(1.5)
    assert zeta_bound(sys_, 300.0, 1.0, 0.5) == pytest.approx(4.0 * math.sqrt(2.0))


# ------------------------------------------------------------------ certificate
def test_lyapunov_solver_against_hand_solutions():
    P = solve_lyapunov(np.array([[0.0, 1.0], [-2.0, -3.0]]), np.eye(2))
    np.testing.assert_allclose(P, [[1.25, 0.25], [0.25, 0.25]], atol=1e-12)
    assert solve_lyapunov(np.array([[-4.0]]), np.eye(1))[0, 0] == pytest.approx(1 / 8)


def test_eiss_bound_holds_on_random_errors_and_disturbances():
    A = np.array([[0.0, 1.0], [-5.0, -1.5]])
    Q = np.eye(2)
    P = solve_lyapunov(A, Q)
    k1, k2, k3 = eiss_constants(P, Q)
    eta, rng = 0.7, np.random.default_rng(0)
    e = rng.standard_normal((20000, 2)) * rng.uniform(0.01, 3.0, (20000, 1))
    w = rng.standard_normal((20000, 2))
    w *= eta * rng.uniform(0, 1, (20000, 1)) / np.linalg.norm(w, axis=1, keepdims=True)
    v = np.sqrt(np.einsum("bi,ij,bj->b", e, P, e))
    vdot = np.einsum("bi,ij,bj->b", e, P, e @ A.T + w) / v
    norm = np.linalg.norm(e, axis=1)
    assert np.all(k1 * norm <= v + 1e-12) and np.all(v <= k2 * norm + 1e-12)
    assert np.all(vdot <= -k3 * norm + k2 * eta + 1e-12)


def test_scalar_eiss_example_closed_form():
    k, eta = 2.0, 0.3
    sys_ = linear([[-k]], [[1.0]], [[1.0]], u_box=1e6)
    cert = pd_certificate(sys_, 0.0, 0.0, eta, samples=500)
    assert cert.certified and cert.check
    assert cert.k1 == pytest.approx(cert.k2) and cert.gamma == pytest.approx(k)
    t = np.linspace(0, 3, 7)
    np.testing.assert_allclose(cert.a(t), eta / k * (1 - np.exp(-k * t)), rtol=1e-12)
    assert cert.tau == math.inf and cert.roa_capped  # linear: the ROA is everything
    np.testing.assert_allclose(a_bound(t, cert.sigma, cert.gamma, cert.k1), cert.a(t))


def test_pd_double_integrator_is_certified_and_its_condition_fails():
    sys_ = linear([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[0.0], [1.0]], u_box=1e6,
                  gain=lambda kp, kd: np.array([[kp, kd]]))
    cert = pd_certificate(sys_, 4.0, 3.0, 0.5, samples=500)
    assert cert.certified and cert.tau == math.inf
    assert cert.k2 > cert.k1 and not cert.check  # sigma/k1 <= eta iff k1 = k2
    assert "k2/k1" in cert.check_text
    none = pd_certificate(sys_, 0.0, 0.0, 0.5)
    assert not none.certified and "kp = kd = 0" in none.reason and none.k1 is None


def test_eigenvalues_negative_only_within_round_off_are_said_to_be_so():
    """kp = kd = 1e9 on a double integrator: eigenvalues -1 and -1e9, the -1 within the
    round-off tolerance of A - B K's entries; the reason said only 'not Hurwitz: largest
    eigenvalue real part -1'."""
    sys_ = linear([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[0.0], [1.0]], u_box=1e12,
                  gain=lambda kp, kd: np.array([[kp, kd]]))
    cert = pd_certificate(sys_, 1e9, 1e9, 0.5, samples=100)
    assert not cert.certified
    assert cert.reason.startswith(
        "A - B K linearised at x0 in mode 'only' is not Hurwitz: largest eigenvalue real "
        "part -1, not below -1 (1e-9 x the largest |entry| of A - B K: zero within "
        "round-off) (eigenvalues "), cert.reason


def test_saturation_limits_the_region_of_attraction():
    # x' = x + u, u = -K e saturated at |u| <= 1: V decreases only for |e| < 1
    sys_ = linear([[1.0]], [[1.0]], [[1.0]], u_box=1.0, gain=lambda kp, kd: np.array([[kp]]))
    small = pd_certificate(sys_, 3.0, 0.0, 0.1, samples=2000, scale=1.0)
    assert small.certified and small.a_inf == pytest.approx(0.05) and small.tau == math.inf
    big = pd_certificate(sys_, 3.0, 0.0, 4.0, samples=2000)  # a(inf) = 2 > the ROA
    assert big.roa_radius == pytest.approx(1.0, rel=0.02) and not big.roa_capped
    assert big.tau == pytest.approx(math.log(2.0 / (2.0 - big.roa_radius)) / 2.0)
    assert big.a(big.tau) == pytest.approx(big.roa_radius)


def test_a_thin_band_of_rising_v_decades_below_the_cap_bounds_the_region_of_attraction():
    """V' >= 0 only for |e| in about [0.9895, 1.0105], the search starting at a level a
    thousand times larger: the ROA estimate stops at the band, not at the cap (sampling V
    uniformly up to the cap hit the band with probability 2e-5 a sample, so the estimate
    was the cap, tau infinite, and hmpc tube used Prop. 3 at every rate)."""
    sys_ = make_system(lambda x, u, w: -x + 3.0 * x * ca.exp(-((x * x - 1.0) / 0.02) ** 2) + w,
                       1, 1, 1)
    cert = pd_certificate(sys_, 0.0, 0.0, 2.0, samples=2000, scale=1e3)  # a(inf) = 2
    assert cert.certified and not cert.roa_capped
    band = 0.02 * math.sqrt(math.log(3.0))  # 3 exp(-((e^2 - 1) / 0.02)^2) >= 1
    assert math.sqrt(1.0 - band) <= cert.roa_radius <= math.sqrt(1.0 - band) * 1.002
    assert cert.tau == pytest.approx(tau_of(cert.roa_level, cert.k2, cert.a_inf, cert.gamma))
    assert math.isfinite(cert.tau)


def test_ball_default_scenario_has_no_certificate():
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.scenario import load_scenario

    sc, _ = load_scenario(BALL)
    system = build_system(sc.system)
    rep = analyse(system, region=region_from_scenario(system), kind=sc.disturbance.kind,
                  magnitude=sc.disturbance.magnitude, kp=sc.lowlevel.kp, kd=sc.lowlevel.kd,
                  rate_hz=sc.mpc.rate_hz, samples=500)
    assert not rep.certificate.certified and "kp = kd = 0" in rep.certificate.reason
    assert rep.disturbance.zero and all(r.diam == 0.0 for r in rep.rows)
    assert [r.rate_hz for r in rep.rows] == [5.0, 10.0, 20.0, 50.0, 100.0]
    json.dumps(rep.to_dict(), allow_nan=False)


# ------------------------------------------------------------------ margins
def test_margins_round_trip_and_values():
    sys_ = linear(np.eye(2), np.eye(2), np.eye(2), u_box=2.0, guard=True)
    m = margins(sys_, 0.3, zeta=0.5)
    assert (m.guards[0].avoid, m.guards[0].pass_through) == (0.3, 0.3)  # a distance guard
    assert m.inputs[0].per_side == (0.5, 0.5) and not m.inputs[0].capped
    assert margins(sys_, 0.3, zeta=5.0).inputs[0].per_side == (2.0, 2.0)  # half the width
    for mm in (m, margins(sys_, math.inf, zeta=5.0)):
        text = json.dumps(mm.to_dict(), allow_nan=False)
        assert Margins.from_dict(json.loads(text)) == mm


def test_infeasible_initial_state_is_a_warning():
    sys_ = linear(np.zeros((2, 2)), np.eye(2), np.eye(2), guard=True, x0=[0.5, 0.0])
    rep = analyse(sys_, region=BOX, kind="box", magnitude=10.0, kp=0.0, kd=0.0, rate_hz=10,
                  samples=200)
    assert any("wall" in w and "infeasible at the initial state" in w for w in rep.warnings)
    assert rep.row(10.0).diam == pytest.approx(10 * math.sqrt(2) * 0.1)


# ------------------------------------------------------------------ command line
def hmpc(args: list[str], cwd: Path, env: dict | None = None) -> subprocess.CompletedProcess:
    """``hmpc ARGS`` in this process; in a fresh one with its own environment ``env``."""
    if env is None:
        return hmpc_in_process(args, cwd)
    return subprocess.run([*hmpc_command(), *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow
@pytest.mark.parametrize("scenario", [BALL, BIPED], ids=["ball", "biped"])
def test_cli_tube(scenario: Path, tmp_path: Path):
    out = tmp_path / "tube"
    proc = hmpc(["tube", str(scenario), "--out", str(out), "--samples", "4000"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    text = proc.stdout
    for word in ("L_x", "L_u", "eta", "zeta", "not a certificate", *RATES):
        assert word in text, word
    data = json.loads((out / "tube.json").read_text())
    assert [r["rate_hz"] for r in data["rows"]] == [5.0, 10.0, 20.0, 50.0, 100.0]
    for name in ("tube_diameter.pdf", "tube_diameter.png", "tube_margins.png"):
        assert (out / name).stat().st_size > 0, name
    if scenario == BALL:  # disturbance.kind = "none"
        assert "zero disturbance set" in text and "kp = kd = 0" in text
        assert data["disturbance"]["mismatch"] == 0.0 and data["disturbance"]["plant"] == ""
    else:
        assert data["certificate"]["certified"] and "k1, k2, k3" in text
        # its [plant] (mass_scale = 1.1): eta's two parts, printed and in tube.json
        d = data["disturbance"]
        assert d["plant"] == "mass_scale = 1.1" and d["mismatch"] > 100 * d["from_w"] > 0.0
        assert d["eta"] == d["mismatch"] + d["from_w"]
        assert data["certificate"]["sigma"] == pytest.approx(data["certificate"]["k2"]
                                                             * d["eta"])
        row = " ".join(text.split("eta", 1)[1].split("kinematic states")[0].split())
        assert "max ||f_plant - f_model|| = " in row and "(plant: mass_scale = 1.1;" in row
        assert "+ max ||df_plant/dw|| x ||w_max|| = " in row


@pytest.mark.slow
def test_the_balls_margins_file_is_unchanged_and_a_plant_is_recorded(tmp_path: Path):
    """No [plant]: the committed margins file byte for byte; a heavier plant: its eta."""
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.tube.margins_file import margins_problems, read_margins

    disturbed = SCENARIOS / "ball_disturbed.toml"
    committed = SCENARIOS / "margins" / "ball_fig3.toml"
    for name, sets in (("same.toml", []), ("heavy.toml", ["--set", "plant.mass=2.0"])):
        proc = hmpc(["tube", str(disturbed), *sets, "--write", name, "--out", "o", "-q",
                     "--formats", "png"], tmp_path)
        assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "same.toml").read_bytes() == committed.read_bytes()
    heavy = read_margins(tmp_path / "heavy.toml")
    assert heavy.disturbance["plant"] == "mass = 2"
    assert heavy.disturbance["eta"] == (heavy.disturbance["plant_mismatch"]
                                        + heavy.disturbance["from_w"])
    assert "# plant: mass = 2 (parameters sha256:" in (tmp_path / "heavy.toml").read_text()
    assert heavy.at(20.0).radius > read_margins(committed).at(20.0).radius
    sc, _ = load_scenario(disturbed)
    assert margins_problems(tmp_path / "heavy.toml", sc.system, 20.0) == []


def test_cli_tube_disturbed_ball_warns_and_defaults_its_directory(tmp_path: Path):
    proc = hmpc(["tube", str(SCENARIOS / "ball_disturbed.toml"), "--samples", "2000",
                 "--formats", "png", "--set", "mpc.rate_hz=2"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "warning: at 2 Hz the tightened guard-avoid row of floor" in proc.stdout
    assert (tmp_path / "results" / "ball_disturbed" / "tube" / "tube_margins.png").is_file()


@pytest.mark.slow
def test_cli_tube_region_from_a_run_log(tmp_path: Path):
    from hmpc_cli.log.recorder import Recorder

    states = [[1.0, 1.0, 0.0, 0.0], [2.0, 1.5, 3.0, -1.0], [3.0, 2.0, -2.0, 4.0]]
    with Recorder(tmp_path / "run.mcap") as rec:
        rec.add_topic("/sim/state", "state", {"type": "object"})
        for i, x in enumerate(states):
            rec.write("/sim/state", 0.1 * i, {"x": x})
    proc = hmpc(["tube", str(SCENARIOS / "ball_disturbed.toml"), "--states", str(tmp_path),
                 "--pad", "0", "--out", "out", "--samples", "1000", "--formats", "png"],
                tmp_path)
    assert proc.returncode == 0, proc.stderr
    region = json.loads((tmp_path / "out" / "tube.json").read_text())["region"]
    assert region["lower"] == [1.0, 1.0, -2.0, -1.0] and region["upper"] == [3.0, 2.0, 3.0, 4.0]
    bad = hmpc(["tube", str(BALL), "--states", str(tmp_path / "none.mcap")], tmp_path)
    assert bad.returncode == 2 and bad.stderr.startswith("error: ")


def test_cli_tube_bad_input(tmp_path: Path):
    proc = hmpc(["tube", str(BALL), "--set", "lowlevel.kp=-1", "--out", str(tmp_path)],
                tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("error: --set lowlevel.kp=-1: lowlevel.kp:")
    proc = hmpc(["tube", str(tmp_path / "missing.toml")], tmp_path)
    assert proc.returncode == 2 and "file not found" in proc.stderr
    # named by the option (inf and 1e300 were blamed on the region)
    for pad in ("nan", "inf", "-1", "1e+300"):
        proc = hmpc(["tube", str(BALL), "--pad", pad, "--out", str(tmp_path / "o")], tmp_path)
        assert (proc.returncode, proc.stderr) == (2, f"error: --pad {pad}: must be a number in "
                                                     "[0, 100] (a fraction of each coordinate's "
                                                     "width per side, e.g. 0.1)\n")
    assert not (tmp_path / "o").exists()


def test_cli_tube_without_trivial_tube_exits_2(tmp_path: Path):
    """A plug-in whose flow has no finite Jacobian on the region: one error line, exit 2."""
    (tmp_path / "hmpc_root-0.1.dist-info").mkdir()
    (tmp_path / "hmpc_root-0.1.dist-info" / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: hmpc-root\nVersion: 0.1\n")
    (tmp_path / "hmpc_root-0.1.dist-info" / "entry_points.txt").write_text(
        "[hmpc.systems]\nroot = hmpc_root:SYSTEM\n")
    (tmp_path / "hmpc_root.py").write_text(ROOT_PLUGIN)
    (tmp_path / "root.toml").write_text('[system]\nname = "root"\n[mpc]\nrate_hz = 10\n')
    env = cli_env()
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(REPO)])
    proc = hmpc(["tube", "root.toml", "--out", "out", "--samples", "200"], tmp_path, env)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.startswith("error: root.toml: tube: L_x: the Jacobian")
    assert "Traceback" not in proc.stderr


ROOT_PLUGIN = '''
from typing import Literal
import casadi as ca
import numpy as np
from pydantic import BaseModel, ConfigDict
from hmpc_cli.core.hybrid import HybridSystem, Mode
from hmpc_cli.core.registry import SystemSpec
from hmpc_cli.core.tasks import ReachGoal


class RootParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: Literal["root"] = "root"


def build(p):
    x, u, w = ca.SX.sym("x", 2), ca.SX.sym("u", 1), ca.SX.sym("w", 1)
    flow = ca.Function("f", [x, u, w], [ca.vertcat(ca.sqrt(x[0]), u[0] + w[0])])
    return HybridSystem(
        name="root", state_names=("a", "b"), input_names=("u",), disturbance_names=("w",),
        modes=(Mode("m", flow, (-1.0,), (1.0,)),), guards=(), initial_mode="m",
        final_mode="m", x0=np.array([0.0, 0.0]), goal=np.array([1.0, 0.0]),
        goal_map=ca.Function("g", [x], [x]),
        stage_cost=ca.Function("L", [x, u], [ca.sumsqr(x)]), terminal_set=None,
        tracking_gain=lambda kp, kd: np.zeros((1, 2)))


SYSTEM = SystemSpec(name="root", params=RootParams, build=build,
                    task=lambda p, s: ReachGoal(s, 0.1), planner="cem", mpc="fixed_mode")
'''


def test_a_tube_analysis_removes_the_figures_of_an_earlier_one(tmp_path: Path):
    """hmpc tube writes into a directory an earlier analysis wrote (its default is one
    per scenario): the figures this one did not write (another format's; tube_reality
    without --runs) would be read as its own, so they go, and a note names them; other
    files stay."""
    from hmpc_cli.cli.tube import _remove_stale_figures

    out = tmp_path / "tube"
    out.mkdir()
    names = ["tube_diameter.pdf", "tube_diameter.png", "tube_diameter.svg", "tube_margins.pdf",
             "tube_reality.png", "tube_reality.svg", "notes.png"]
    for name in names:
        (out / name).write_bytes(b"x")
    assert _remove_stale_figures(out, "png,svg", with_reality=True) == [
        "tube_diameter.pdf", "tube_margins.pdf"]
    assert _remove_stale_figures(out, "png", with_reality=False) == [
        "tube_diameter.svg", "tube_reality.png", "tube_reality.svg"]
    assert sorted(p.name for p in out.iterdir()) == ["notes.png", "tube_diameter.png"]
    # through the command: an earlier --runs analysis's figure goes, with a note
    (out / "tube_reality.pdf").write_bytes(b"x")
    proc = hmpc(["tube", str(BALL), "--out", str(out), "--samples", "500", "--formats", "png",
                 "-q"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert f"note: removed tube_reality.pdf from {out}: an earlier analysis's" in proc.stderr
    assert sorted(p.name for p in out.iterdir()) == [
        "notes.png", "tube.json", "tube_diameter.png", "tube_margins.png"]


def test_a_stop_while_the_tube_writes_its_outputs_acts_after_they_are_whole(tmp_path,
                                                                          monkeypatch):
    """A stop while tube.json and the figures were written left some (tube.json and the
    diameter figures, no margins figures) and said only 'interrupted': the outputs are now
    written whole, then the command stops and says so."""
    import signal

    from typer.testing import CliRunner

    import hmpc_cli.figures.tube as figures
    from hmpc_cli.cli.app import app

    draw = figures.draw_diameters

    def stopped_while_drawing(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return draw(*args, **kwargs)

    monkeypatch.setattr(figures, "draw_diameters", stopped_while_drawing)
    out = tmp_path / "t"
    res = CliRunner().invoke(app, ["tube", str(SCENARIOS / "ball_disturbed.toml"), "--samples",
                                   "20", "--out", str(out), "--formats", "png", "-q"])
    assert res.exit_code == 143, res.output
    assert res.stderr.splitlines()[-1] == (
        f"interrupted (SIGTERM) once the analysis was written whole to {out}")
    assert sorted(p.name for p in out.iterdir()) == [
        "tube.json", "tube_diameter.png", "tube_margins.png"]


def test_a_region_of_attraction_search_from_level_zero_is_level_zero():
    """A start level of 0 (eta 0, scale 0) raised ZeroDivisionError in the log sampling."""
    sys_ = linear([[0.0, 1.0], [0.0, 0.0]], [[0.0], [1.0]], [[0.0], [1.0]], u_box=1e6,
                  gain=lambda kp, kd: np.array([[kp, kd]]))
    cert = pd_certificate(sys_, 4.0, 4.0, 0.0, samples=100, scale=0.0)
    assert cert.certified and cert.roa_level == 0.0 and cert.roa_capped
