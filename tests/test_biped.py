"""The five-link biped plug-in: kinematics, Lagrangian dynamics, impact, leg swap, guards."""

import casadi as ca
import numpy as np
import pytest
from pydantic import ValidationError

from hmpc_cli.sim.simulator import HybridSimulator
from hmpc_cli.systems.biped import POINT_NAMES, BipedParams, build_biped, make_biped_model

P = BipedParams()
MODEL = make_biped_model(P)
MASSES = np.array([P.calf_mass, P.thigh_mass, P.torso_mass, P.thigh_mass, P.calf_mass])
INERTIAS = np.array([P.calf_inertia, P.thigh_inertia, P.torso_inertia, P.thigh_inertia,
                     P.calf_inertia])
RNG = np.random.default_rng(12)


def arr(v) -> np.ndarray:
    return np.array(v, dtype=float)


def pts(q) -> dict[str, np.ndarray]:
    m = arr(MODEL.points(q))
    return {name: m[:, i] for i, name in enumerate(POINT_NAMES)}


def random_state(scale_q=1.0, scale_v=2.0, foot=(0.3, 0.1)) -> np.ndarray:
    q = np.array(P.q0) + scale_q * RNG.uniform(-0.5, 0.5, 5)
    return np.r_[q, scale_v * RNG.normal(size=5), foot]


# ---------------------------------------------------------------- kinematics


def test_reference_kinematics_of_q0():
    p = pts(P.q0)
    assert p["stance_foot"] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert p["hip"] == pytest.approx([0.2334, 0.6815], abs=1e-3)
    assert p["swing_foot"] == pytest.approx([0.2987, 0.0016], abs=1e-3)
    assert p["torso_top"] == pytest.approx([0.1504, 1.3009], abs=1e-3)
    system = build_biped(P)
    assert arr(system.goal_map(system.x0)).ravel() == pytest.approx([0.2334, 0.6815], abs=1e-3)


def test_link_lengths_and_centres_of_mass_are_the_physical_points():
    for _ in range(20):
        q = RNG.uniform(-2, 2, 5)
        p = pts(q)
        coms = arr(MODEL.coms(q))

        def dist(a, b):
            return float(np.linalg.norm(a - b))

        assert dist(p["stance_knee"], p["stance_foot"]) == pytest.approx(P.calf_length)
        assert dist(p["hip"], p["stance_knee"]) == pytest.approx(P.thigh_length)
        assert dist(p["torso_top"], p["hip"]) == pytest.approx(P.torso_length)
        assert dist(p["swing_knee"], p["hip"]) == pytest.approx(P.thigh_length)
        assert dist(p["swing_foot"], p["swing_knee"]) == pytest.approx(P.calf_length)
        # (com, proximal joint, distal joint, distance from the proximal joint): the CoM
        # lies on the link at that distance, on BOTH legs (calf: from the knee)
        spec = [(0, "stance_knee", "stance_foot", P.calf_com),
                (1, "hip", "stance_knee", P.thigh_com),
                (2, "hip", "torso_top", P.torso_com),
                (3, "hip", "swing_knee", P.thigh_com),
                (4, "swing_knee", "swing_foot", P.calf_com)]
        for b, prox, dist_end, d in spec:
            length = dist(p[prox], p[dist_end])
            assert dist(coms[:, b], p[prox]) == pytest.approx(d, abs=1e-12)
            assert dist(coms[:, b], p[dist_end]) == pytest.approx(length - d, abs=1e-12)


def test_jacobians_match_finite_differences():
    q = RNG.uniform(-1, 1, 5)
    eps = 1e-6
    for point, jac in ((MODEL.swing_foot, MODEL.swing_foot_jacobian),
                       (MODEL.hip, MODEL.hip_jacobian)):
        fd = np.column_stack([(arr(point(q + eps * e)) - arr(point(q - eps * e))).ravel()
                              / (2 * eps) for e in np.eye(5)])
        assert arr(jac(q)) == pytest.approx(fd, abs=1e-8)
    assert arr(MODEL.hip_force_map(q)).ravel() == pytest.approx(arr(MODEL.hip_jacobian(q))[0])


# ---------------------------------------------------------------- dynamics


def lagrangian_reference(masses, inertias, gravity):
    """M, C qd, G by CasADi AD of T and V built from the model's CoMs and link angles."""
    q, qd = ca.SX.sym("q", 5), ca.SX.sym("qd", 5)
    coms, theta = MODEL.coms(q), MODEL.link_angles(q)
    kin, pot = 0, 0
    for b in range(5):
        v = ca.jtimes(coms[:, b], q, qd)
        omega = ca.jtimes(theta[b], q, qd)
        kin += 0.5 * masses[b] * ca.sumsqr(v) + 0.5 * inertias[b] * omega**2
        pot += masses[b] * gravity * coms[1, b]
    mass = ca.hessian(kin, qd)[0]
    dk_dqd = ca.gradient(kin, qd)
    cor = ca.jtimes(dk_dqd, q, qd) - ca.gradient(kin, q)
    return ca.Function("ref", [q, qd], [mass, cor, ca.gradient(pot, q), kin])


def test_closed_form_dynamics_equal_the_ad_lagrangian():
    ref = lagrangian_reference(MASSES, INERTIAS, P.gravity)
    for _ in range(10):
        q, qd = RNG.uniform(-2, 2, 5), RNG.normal(0, 3, 5)
        m_ref, c_ref, g_ref, k_ref = (arr(v) for v in ref(q, qd))
        assert arr(MODEL.mass_matrix(q)) == pytest.approx(m_ref, abs=1e-11)
        assert arr(MODEL.coriolis(q, qd)).ravel() == pytest.approx(c_ref.ravel(), abs=1e-10)
        assert arr(MODEL.gravity(q)).ravel() == pytest.approx(g_ref.ravel(), abs=1e-10)
        assert arr(MODEL.bias(q, qd)).ravel() == pytest.approx((c_ref + g_ref).ravel(),
                                                               abs=1e-10)
        x = np.r_[q, qd, 0.0, 0.0]
        assert float(MODEL.kinetic(x)) == pytest.approx(k_ref.item(), rel=1e-12)


def test_mass_matrix_symmetric_positive_definite():
    for _ in range(200):
        m = arr(MODEL.mass_matrix(RNG.uniform(-np.pi, np.pi, 5)))
        assert np.max(np.abs(m - m.T)) < 1e-13
        assert np.linalg.eigvalsh(m).min() > 1e-3


def test_mass_scale_scales_m_and_g_exactly():
    heavy = make_biped_model(BipedParams(mass_scale=1.1))
    for _ in range(5):
        q, qd = RNG.uniform(-2, 2, 5), RNG.normal(0, 3, 5)
        np.testing.assert_allclose(arr(heavy.mass_matrix(q)), 1.1 * arr(MODEL.mass_matrix(q)),
                                   rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(arr(heavy.gravity(q)), 1.1 * arr(MODEL.gravity(q)),
                                   rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(arr(heavy.coriolis(q, qd)), 1.1 * arr(MODEL.coriolis(q, qd)),
                                   rtol=1e-13, atol=1e-13)
    assert heavy.total_mass == pytest.approx(1.1 * MODEL.total_mass)
    assert MODEL.total_mass == pytest.approx(18.0)


def test_forward_and_inverse_dynamics_with_the_torso_force():
    for _ in range(5):
        q, qd = RNG.uniform(-2, 2, 5), RNG.normal(0, 3, 5)
        u, w = RNG.normal(0, 50, 5), RNG.normal(0, 20, 1)
        m = arr(MODEL.mass_matrix(q))
        jh = arr(MODEL.hip_jacobian(q))[0]
        rhs = u + jh * w[0] - arr(MODEL.bias(q, qd)).ravel()
        qdd = arr(MODEL.forward_dynamics(q, qd, u, w)).ravel()
        assert qdd == pytest.approx(np.linalg.solve(m, rhs), rel=1e-10, abs=1e-10)
        assert arr(MODEL.inverse_dynamics(q, qd, qdd, w)).ravel() == pytest.approx(u, abs=1e-9)
        xdot = arr(MODEL.flow(np.r_[q, qd, 0.7, 0.1], u, w)).ravel()
        assert xdot == pytest.approx(np.r_[qd, qdd, 0.0, 0.0], abs=1e-12)


def test_unactuated_flow_conserves_energy_in_the_simulator():
    system = build_biped(P)
    sim = HybridSimulator(system)
    x = np.array([[0.05, 0.2, -0.1, 0.9, -1.2, 1.5, -2.0, 2.0, 3.0, -3.0, 0.0, 0.0]])
    mode = np.array([0])
    energy = [float(MODEL.energy(x[0]))]
    foot_y = []
    for _ in range(400):  # 0.2 s at 2 kHz
        res = sim.step(x, mode, np.zeros((1, 5)), np.zeros((1, 1)), 5e-4)
        assert not res.events
        x, mode = res.x, res.mode
        energy.append(float(MODEL.energy(x[0])))
        foot_y.append(float(MODEL.swing_foot_world(x[0])[1]))
    assert min(foot_y) > 0.05, "the window must hold no guard event"
    assert float(MODEL.kinetic(x[0])) > 5.0, "the robot must actually move"
    e = np.array(energy)
    # RK4 at 2 kHz holds it to ~1e-14; the brief asks < 1e-6, we keep margin for rounding
    assert np.max(np.abs(e - e[0])) < 1e-9 * abs(e[0])


def test_input_box_and_state_bounds():
    system = build_biped(P)
    assert system.modes[0].u_lower == (-3000.0,) * 5
    assert system.modes[0].u_upper == (3000.0,) * 5
    assert MODEL.state_lower[1] == 0.0 and MODEL.state_upper[1] == pytest.approx(np.pi / 2)
    assert (MODEL.state_lower[2], MODEL.state_upper[2]) == pytest.approx((-np.pi / 2,
                                                                          np.pi / 2))
    assert np.all(MODEL.state_upper[5:10] == 35.0) and np.all(MODEL.state_lower[5:10] == -35.0)
    k = system.tracking_gain(700.0, 10.0)
    assert k.shape == (5, 12)
    assert np.array_equal(k[:, :5], 700 * np.eye(5)) and np.array_equal(k[:, 5:10],
                                                                         10 * np.eye(5))
    assert not k[:, 10:].any()


# ---------------------------------------------------------------- impact and swap


def momentum_functions(masses, inertias):
    q, qd, about = ca.SX.sym("q", 5), ca.SX.sym("qd", 5), ca.SX.sym("o", 2)
    coms, theta = MODEL.coms(q), MODEL.link_angles(q)
    lin, ang = 0, 0
    for b in range(5):
        v = ca.jtimes(coms[:, b], q, qd)
        r = coms[:, b] - about
        lin += masses[b] * v
        ang += masses[b] * (r[0] * v[1] - r[1] * v[0]) + inertias[b] * ca.jtimes(theta[b], q,
                                                                                  qd)
    return ca.Function("mom", [q, qd, about], [lin, ang])


def test_impact_solves_the_constrained_impulse_equations():
    mom = momentum_functions(MASSES, INERTIAS)
    for _ in range(10):
        x = random_state()
        q, v_minus = x[:5], x[5:10]
        v_plus = arr(MODEL.impact(x)).ravel()[5:10]
        assert arr(MODEL.impact(x)).ravel()[[0, 1, 2, 3, 4, 10, 11]] == pytest.approx(
            x[[0, 1, 2, 3, 4, 10, 11]], abs=0)
        m, jac = arr(MODEL.mass_matrix(q)), arr(MODEL.swing_foot_jacobian(q))
        assert np.abs(jac @ v_plus).max() < 1e-12  # the landing foot stops
        lam, *_ = np.linalg.lstsq(jac.T, m @ (v_plus - v_minus), rcond=None)
        assert np.abs(jac.T @ lam - m @ (v_plus - v_minus)).max() < 1e-10
        assert lam == pytest.approx(arr(MODEL.impulse(x)).ravel(), rel=1e-9, abs=1e-12)
        # momenta conjugate to the motions that keep the landing foot still are conserved
        null = np.linalg.svd(jac)[2][2:]
        assert np.abs(null @ m @ (v_plus - v_minus)).max() < 1e-10
        # whole-body impulse balance: the landing impulse Lambda at the swing foot plus the
        # stance-pin impulse (from the linear momentum change) explain the angular momentum
        # change about the impact point (it is conserved only if the pin impulse points at
        # the impact point: the paper's 5-DOF impact keeps the stance foot pinned)
        foot = arr(MODEL.swing_foot(q)).ravel()
        p0, h0 = (arr(v).ravel() for v in mom(q, v_minus, foot))
        p1, h1 = (arr(v).ravel() for v in mom(q, v_plus, foot))
        pin = p1 - p0 - lam
        r = -foot  # stance foot (origin) relative to the impact point
        assert h1[0] - h0[0] == pytest.approx(r[0] * pin[1] - r[1] * pin[0], abs=1e-10)
        # dissipative: kinetic energy never grows in a plastic impact
        assert float(MODEL.kinetic(MODEL.impact(x))) <= float(MODEL.kinetic(x)) + 1e-12


#: POINT_NAMES after the swap: the feet and the knees exchange roles, hip and torso stay
SWAPPED = [5, 4, 2, 3, 1, 0]


def point_velocities(x) -> np.ndarray:
    """World velocities of the six points (2 x 6) for a state x (stance foot at rest)."""
    q, qd = ca.SX.sym("q", 5), ca.SX.sym("qd", 5)
    f = ca.Function("v", [q, qd], [ca.jtimes(MODEL.points(q), q, qd)])
    return arr(f(x[:5], x[5:10]))


def test_swap_after_impact_keeps_every_point_and_velocity():
    for _ in range(10):
        x = random_state()
        x_imp = arr(MODEL.impact(x)).ravel()
        x_new = arr(MODEL.reset(x)).ravel()
        assert x_new == pytest.approx(arr(MODEL.swap(x_imp)).ravel(), abs=1e-12)
        before, after = arr(MODEL.points_world(x)), arr(MODEL.points_world(x_new))
        assert after == pytest.approx(before[:, SWAPPED], abs=1e-12)  # roles exchanged
        assert x_new[10:] == pytest.approx(arr(MODEL.swing_foot_world(x)).ravel(), abs=1e-12)
        v_before, v_after = point_velocities(x_imp), point_velocities(x_new)
        assert np.abs(v_before[:, -1]).max() < 1e-12  # landing foot at rest
        assert np.abs(v_after[:, 0]).max() == 0.0  # new stance foot at rest (pinned)
        # every joint moves as before; the new swing foot moves like the old stance foot
        assert v_after == pytest.approx(v_before[:, SWAPPED], abs=1e-10)
        # the new q1 rate is the absolute rate of the old swing calf
        assert x_new[5] == pytest.approx(x_imp[5:10].sum(), abs=1e-12)
        assert x_new[:5] == pytest.approx([x[:5].sum(), -x[4], -x[3], -x[2], -x[1]],
                                          abs=1e-12)
        assert float(MODEL.energy(x_new)) == pytest.approx(float(MODEL.energy(x_imp)),
                                                           rel=1e-12)


def test_swap_is_an_involution():
    for _ in range(10):
        x = random_state()
        twice = arr(MODEL.swap(MODEL.swap(x))).ravel()
        assert twice == pytest.approx(x, abs=1e-12)


# ---------------------------------------------------------------- guards and the simulator


@pytest.mark.parametrize("foot, guard, height", [((0.0, 0.0), "stair_1", 0.0),
                                                 ((0.5, 0.075), "stair_2", 0.075)])
def test_touchdown_fires_the_segment_guard_and_swaps(foot, guard, height):
    system = build_biped(BipedParams(stance_foot0=foot))
    sim = HybridSimulator(system)
    x = system.x0.copy()
    x[5:10] = [0.0, 0.0, 0.0, 0.0, 1.0]  # swing knee unfolds: the foot swings down
    x, mode = x[None], np.array([0])
    events = []
    for _ in range(200):
        res = sim.step(x, mode, np.zeros((1, 5)), np.zeros((1, 1)), 1e-3)
        x, mode = res.x, res.mode
        events += res.events
        if events:
            break
    assert events, "the swing foot must land"
    e = events[0]
    assert system.guards[e.guard].name == guard
    assert float(MODEL.swing_foot_world(e.x_before)[1]) == pytest.approx(height, abs=1e-8)
    assert e.x_after[10:] == pytest.approx(arr(MODEL.swing_foot_world(e.x_before)).ravel())
    assert e.x_after == pytest.approx(arr(MODEL.reset(e.x_before)).ravel(), abs=1e-12)


def test_guards_and_cost():
    system = build_biped(P)
    names = [g.name for g in system.guards]
    assert names == ["stair_1", "stair_2", "stair_3", "stair_4", "ground"]
    edges = [(0.0, 0.4), (0.4, 1.4), (1.4, 1.6), (1.6, 2.85)]
    # the four stairs; the last guard (ground) has no edges
    for g, (a, b), h in zip(system.guards, edges, (0.0, 0.075, 0.125, 0.175), strict=False):
        assert (g.level, g.direction, g.source, g.target) == (h, -1, "single_support",
                                                             "single_support")
        for fx, inside in ((a + 0.01, True), (b - 0.01, True), (a - 0.01, False),
                           (b + 0.01, False)):
            x = system.x0.copy()
            x[10] = fx - arr(MODEL.swing_foot(x[:5])).ravel()[0]
            assert bool(np.all(arr(g.region(x)) >= 0)) == inside
    assert system.goal == pytest.approx([2.0, 0.8])
    assert system.terminal_set is None
    assert system.initial_mode == system.final_mode == "single_support"
    cost_fn = system.stage_cost
    x = system.x0.copy()
    hip = arr(MODEL.hip_world(x)).ravel()
    assert float(cost_fn(x, np.zeros(5))) == pytest.approx(P.q_hip * np.sum((hip - [2, .8])**2))
    assert float(cost_fn(x, np.ones(5))) > float(cost_fn(x, np.zeros(5)))


# ---------------------------------------------------------------- parameter validation


def errors_of(**kw) -> list[tuple[str, str]]:
    with pytest.raises(ValidationError) as info:
        BipedParams(**kw)
    return [(".".join(str(p) for p in e["loc"]), e["msg"]) for e in info.value.errors()]


def test_bad_parameters_give_keyed_errors():
    errs = errors_of(stairs=[{"length": 0.4, "height": 0.0}, {"length": -1.0, "height": 0.1}])
    assert errs[0][0] == "stairs.1.length" and "greater than 0" in errs[0][1]
    errs = errors_of(stance_foot0=(0.0, 0.05))
    assert errs == [("stance_foot0", errs[0][1])] and "on the ground" in errs[0][1]
    errs = errors_of(stance_foot0=(0.3, 0.0))  # swing foot over the 0.075 m step, at 0.0016
    assert errs[0][0] == "q0" and "below the terrain" in errs[0][1]
    errs = errors_of(stance_foot0=(3.0, 0.175))
    assert errs[0][0] == "stance_foot0" and "beyond the stairs' end" in errs[0][1]
    assert len(errs) == 1  # not q0's swing foot too: it is placed from the stance foot
    errs = errors_of(q0=(-0.78, -0.2, 0.0133, 0.51, -1.0951))
    assert errs[0][0] == "q0" and "stance knee" in errs[0][1]
    errs = errors_of(thigh_com=0.5)
    assert errs[0][0] == "thigh_com" and "beyond the link" in errs[0][1]
    errs = errors_of(torso_range=(1.0, -1.0))
    assert errs[0][0] == "torso_range"
    assert errors_of(spin=1)[0][0] == "spin"
    assert errors_of(name="ball")[0][0] == "name"
    assert errors_of(stairs=[])[0][0] == "stairs"
    # already on the top segment: nothing to climb (one flat stair)
    errs = errors_of(stairs=[{"length": 3.0, "height": 0.0}])
    assert errs == [("stance_foot0", "(0, 0) is on the top segment [0, 3] at "
                     "height 0 already: nothing to climb (add a stair, or start before the "
                     "top)")]
    # valid: stance foot on a segment boundary, at either height
    lifted = (-0.78, 0.9, 0.0133, 0.8, -1.8)  # swing foot 0.18 m up
    for height in (0.0, 0.075):
        assert BipedParams(stance_foot0=(0.4, height), q0=lifted).stance_foot0[1] == height


def test_success_needs_the_stance_foot_at_the_top_segments_height():
    """A stance foot within the top segment's x range but 5 m above it (the one stair's
    height is -5 m, the foot on the ground at 0) is not on it."""
    from hmpc_cli.systems.biped.task import ClimbStairs

    system = build_biped(BipedParams(stairs=[{"length": 1.0, "height": -5.0}]))
    task = ClimbStairs(system, 0.35)
    x = system.x0.copy()
    x[10:] = (0.5, 0.0)
    verdict = task.verdict(x, 0)
    assert not verdict.success
    assert verdict.reason == ("stance foot at (0.500, 0.000) m is not on the top segment "
                              "[0, 1] at height -5")
    x[11] = -5.0 + 1e-9  # a touchdown's stance foot: within the event tolerance
    assert task.verdict(x, 0).success
    x[11] = -5.0 + 2e-3  # 2 mm above: not on it
    assert not task.verdict(x, 0).success


def test_a_swing_foot_inside_the_terrain_where_no_guard_stops_it_is_a_fall():
    """Past the stairs' end the terrain keeps the top's height but no guard catches the
    swing foot: a walker whose swing foot sank 0.24 m into it there counted as a success.
    Once the foot has cleared the terrain since its lift-off (a new stance foot), or has
    left the ground it lifted off from (into a riser), more than 1 mm inside is a fall (a
    trip), as a knee's is; before that, over its lift-off ground, it is a scuff: the foot
    still on it, down to 1 cm (a run's swing foot dipped 0.169 m so and ran on)."""
    from hmpc_cli.systems.biped.task import ON_SEGMENT, SCUFF, ClimbStairs

    system = build_biped(BipedParams())
    top, end = system.terrain.segments[-1][2], system.terrain.end
    task = ClimbStairs(system, 0.35)
    stance = np.array([end + 0.1, top])
    assert task._tripped(stance, np.array([end + 0.3, top - 0.009]), top) == ""  # a scuff
    assert task._tripped(stance, np.array([end + 0.3, top + 0.02]), top) == ""  # cleared
    reason = task._tripped(stance, np.array([end + 0.3, top - 0.0105]), top)
    assert reason == (f"fall: the swing foot is 10.50 mm inside the terrain at x = "
                      f"{end + 0.3:.3f} m (no guard there, deeper than 1 mm: it tripped)")
    # in mm to 0.01 mm: a depth just past the bound reads past it (in m to 1 mm it read
    # "0.001 m", at the bound)
    assert task._tripped(stance, np.array([end + 0.3, top - 0.00104]), top).startswith(
        "fall: the swing foot is 1.04 mm inside")
    assert task._tripped(stance, np.array([end + 0.3, top - ON_SEGMENT / 2]), top) == ""
    # a new stance foot on the first segment [0, 0.4]: the swing foot drags into the
    # riser of the second (0.075 m high) before it ever cleared the ground
    stance = np.array([0.3, 0.0])
    assert task._tripped(stance, np.array([0.35, -0.004]), 0.0) == ""  # a scuff
    assert task._tripped(stance, np.array([0.41, 0.07]), 0.075).startswith(
        "fall: the swing foot is 5.00 mm inside the terrain at x = 0.410 m (no guard there")
    # lifted off the ground before x = 0: the first segment is the same flat ground, so a
    # scuff over it is no trip (a review found it one)
    stance = np.array([0.0, 0.0])
    assert task._tripped(stance, np.array([-0.2, 0.0]), 0.0) == ""
    assert task._tripped(stance, np.array([0.05, -0.004]), 0.0) == ""
    # a scuff deeper than SCUFF is the leg driven into the ground: a trip
    assert SCUFF == 0.01
    assert task._tripped(stance, np.array([0.05, -0.0099]), 0.0) == ""
    assert task._tripped(stance, np.array([0.05, -0.169]), 0.0) == (
        "fall: the swing foot is 169.00 mm inside the terrain at x = 0.050 m (driven into the "
        "ground it lifted off from before clearing it, deeper than 10 mm: it tripped)")
    assert task._tripped(stance, np.array([0.05, -0.01001]), 0.0).startswith(
        "fall: the swing foot is 10.01 mm inside")
    # the whole check on a state: x0 stands on the ground with its swing foot on it
    assert ClimbStairs(system, 0.35).failure(system.x0.copy(), 0) == ""
