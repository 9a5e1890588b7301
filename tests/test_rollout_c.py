"""Compiled C rollouts of the CEM planner against the NumPy simulator (the reference)."""

import os
import shutil
import subprocess
import sys
import threading

import numpy as np
import pytest

from hmpc_cli.sim import rollout as rollout_c
from hmpc_cli.planner.cem import UNREACHED_PENALTY, CEMSettings, CrossEntropyPlanner
from hmpc_cli.sim.rollout import CRollout, RolloutBuildError
from hmpc_cli.sim.simulator import HybridSimulator
from hmpc_cli.systems.ball import BallParams, build_ball

BALL_MEAN = -20.0  # the ball plug-in's CEM initial mean (its default)

R = 0.1
HAVE_CC = any(shutil.which(c) for c in ((os.environ.get("CC") or "cc").split()[:1] + ["gcc"]))
needs_cc = pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine")

# start states: nominal, corner shot (wall + floor in one step), beyond the floor's region
# (crossing dropped, searched again), close to the circle, resting on the floor (Zeno-prone)
STARTS = [(1.0, 1.0, 0.0, 0.0), (0.3, 0.35, -6.0, -6.0), (7.8, 0.6, 6.0, 0.0),
          (1.5, 3.2, 4.0, 0.0), (4.0, R + 1e-5, 0.0, 0.0)]


@pytest.fixture(scope="module", autouse=True)
def cache(tmp_path_factory):
    """One compile cache for the module (the cache tests use their own)."""
    with pytest.MonkeyPatch.context() as mp:
        folder = tmp_path_factory.mktemp("hmpc-cache")
        mp.setenv("HMPC_CACHE_DIR", str(folder))
        yield folder


def _planner(backend, params=None, **kw):
    ball = build_ball(params or BallParams())
    settings = CEMSettings(init_mean=BALL_MEAN, rollout_backend=backend, **kw)
    return ball, CrossEntropyPlanner(ball, settings)


def _knots(rng, b):
    """CEM-like samples plus saturated, idle and push-down sequences."""
    knots = -20.0 + np.sqrt(250.0) * rng.standard_normal((b, 45, 2))
    knots[0] = 0.0
    knots[1] = -100.0
    knots[2, :, 0], knots[2, :, 1] = 0.0, -100.0  # pin it to the floor: Zeno-prone
    knots[3] = 150.0 * rng.standard_normal((45, 2))
    knots[4:b // 2] *= 0.1  # gentler pushes: some reach the circle
    return knots


@needs_cc
@pytest.mark.parametrize("params", [BallParams(), BallParams(drag=0.0, gravity=0.0),
                                    BallParams(u_outside=(-1e4, 0.0))])
def test_c_step_equals_the_simulator_bit_for_bit(params):
    ball = build_ball(params)
    sim = HybridSimulator(ball)
    c = CRollout(ball)
    rng = np.random.default_rng(5)
    xs = [np.array(s) for s in STARTS] + [np.array([0.12, 0.13, -2.0, -2.0]),
                                          np.array([4.0, R + 1e-4, 0.0, -1e-3])]
    for _ in range(300):
        near = rng.random() < 0.5  # near the floor and the wall, or anywhere
        xs.append(np.r_[rng.uniform(0.1, 0.6 if near else 9.0, 2), rng.normal(0.0, 8.0, 2)])
    x = np.array(xs)
    mode = (np.linalg.norm(x[:, :2] - 3.0, axis=1) < 1.0).astype(int)
    u = rng.uniform(-150, 150, (len(x), 2))
    u[len(STARTS) + 1] = (0.0, -1e4)
    n_multi = n_zeno = 0
    for dt in (1 / 60, 0.05, 0.1):
        ref = sim.step(x, mode, u, np.zeros((len(x), 2)), dt, raise_zeno=False)
        x_c, mode_c, zeno_c = c.step(x, mode, u, dt)
        assert np.array_equal(x_c, ref.x) and np.array_equal(mode_c, ref.mode)
        assert np.array_equal(zeno_c, ref.zeno)
        for i in range(0, len(x), 37):  # batches of one
            one = sim.step(x[i:i + 1], mode[i:i + 1], u[i:i + 1], np.zeros((1, 2)), dt,
                           raise_zeno=False)
            x1, m1, z1 = c.step(x[i:i + 1], mode[i:i + 1], u[i:i + 1], dt)
            assert np.array_equal(x1, one.x) and m1[0] == one.mode[0] and z1[0] == one.zeno[0]
        per_sample = np.bincount([e.sample for e in ref.events], minlength=len(x))
        n_multi += np.sum(per_sample > 1)
        n_zeno += zeno_c.sum()
    assert n_multi > 5 and (n_zeno > 0 or params.u_outside[0] == -100.0)


@needs_cc
@pytest.mark.parametrize("start", STARTS)
def test_c_rollout_equals_numpy(start):
    _, planner = _planner("c")
    assert planner.backend == "c"
    x0 = np.array(start)
    knots = _knots(np.random.default_rng(11), 24)
    cost, reached = planner.rollout_cost(x0, 0, knots)
    running = (cost - np.where(reached, 0.0, UNREACHED_PENALTY))[np.isfinite(cost)]
    bound = float(np.median(running)) if running.size else np.inf  # prunes about half
    for bnd in (np.inf, bound):
        cost, reached = planner.rollout_cost(x0, 0, knots, bnd)
        ref, ref_reached = planner.rollout_cost_numpy(x0, 0, knots, bnd)
        assert np.array_equal(reached, ref_reached)
        np.testing.assert_allclose(cost, ref, rtol=1e-9, atol=0.0)
        assert np.array_equal(cost, ref)  # in fact bit for bit
    assert np.isinf(cost).sum() > len(cost) // 3  # the bound pruned


@pytest.mark.slow
@needs_cc
@pytest.mark.parametrize("start", [STARTS[0], STARTS[3], STARTS[4]])
def test_reference_cost_c_equals_numpy_and_runs_the_whole_horizon(start):
    _, planner = _planner("c", cost="reference")
    _, hmpc = _planner("c")
    x0 = np.array(start)
    knots = _knots(np.random.default_rng(11), 24)
    cost, reached = planner.rollout_cost(x0, 0, knots)
    ref, ref_reached = planner.rollout_cost_numpy(x0, 0, knots)
    assert np.array_equal(reached, ref_reached) and np.array_equal(cost, ref)
    finite = cost[np.isfinite(cost)]
    bound = float(np.median(finite))
    for bnd in (bound, np.inf):  # pruning too, bit for bit
        a, ra = planner.rollout_cost(x0, 0, knots, bnd)
        b, rb = planner.rollout_cost_numpy(x0, 0, knots, bnd)
        assert np.array_equal(a, b) and np.array_equal(ra, rb)
    # no penalty; a rollout that never enters costs what the absorbing cost charges it
    # without the penalty (both integrate the same steps)
    h_cost, h_reached = hmpc.rollout_cost(x0, 0, knots)
    never = ~reached & ~h_reached & np.isfinite(cost)
    assert never.any() or start == STARTS[3]  # near the circle every sample enters
    np.testing.assert_allclose(cost[never] + UNREACHED_PENALTY, h_cost[never], rtol=1e-12)


@needs_cc
def test_c_rollout_zeno_and_start_in_the_final_domain():
    _, planner = _planner("c", BallParams(u_outside=(-1e4, 0.0)))
    x0 = np.array(STARTS[-1])
    knots = _knots(np.random.default_rng(2), 16)
    knots[2, :, 1] = -1e4
    cost, reached = planner.rollout_cost(x0, 0, knots)
    ref, ref_reached = planner.rollout_cost_numpy(x0, 0, knots)
    assert np.isinf(cost[2]) and np.isinf(ref[2])  # Zeno: frozen and dropped
    assert np.array_equal(reached, ref_reached)
    assert np.array_equal(cost, ref)
    cost0, reached0 = planner.rollout_cost(x0, 1, knots)  # already in the final domain
    stay = planner.n_steps * planner.dt * planner.cost_fn(x0[None], np.zeros((1, 2)))[0][0, 0]
    assert reached0.all() and np.all(cost0 == stay) and stay > 0  # its stage cost all along
    assert np.array_equal(cost0, planner.rollout_cost_numpy(x0, 1, knots)[0])


def _same_trajectory(a, b):
    for f in ("t", "x", "u", "mode", "seg"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    assert a.guards == b.guards


@pytest.mark.slow
@needs_cc
@pytest.mark.parametrize("cost", ["hmpc", "reference"])
def test_plan_is_the_same_with_both_backends(cost):
    ball, c = _planner("c", warm_start=True, cost=cost)
    _, py = _planner("numpy", warm_start=True, cost=cost)
    for t in (0.0, 0.02):
        a, b = c.plan(t, ball.x0, 0), py.plan(t, ball.x0, 0)
        assert a.reached_final and a.schedule == b.schedule and a.cost == b.cost
        _same_trajectory(a.trajectory, b.trajectory)


@needs_cc
@pytest.mark.parametrize("start", STARTS)
def test_c_trajectory_equals_numpy(start):
    _, c = _planner("c", BallParams(u_outside=(-1e3, 0.0)))
    _, py = _planner("numpy", BallParams(u_outside=(-1e3, 0.0)))
    x0 = np.array(start)
    knots = _knots(np.random.default_rng(4), 8)
    knots[5] *= 10.0  # hard pushes: multi-event steps and Zeno
    for k in knots:
        _same_trajectory(c.trajectory(x0, 0, k), py.trajectory(x0, 0, k))


@needs_cc
def test_compiled_library_is_cached_on_disk(tmp_path, monkeypatch):
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path))
    ball = build_ball(BallParams(radius=0.11))
    before = rollout_c.COMPILES
    first = CRollout(ball)
    assert first.compile_seconds is not None and rollout_c.COMPILES - before == 1
    stamp = first.path.stat().st_mtime_ns
    monkeypatch.setattr(rollout_c, "_LIBS", {})  # as a new process: only the disk cache
    second = CRollout(ball)
    assert second.compile_seconds is None and rollout_c.COMPILES - before == 1
    assert second.path == first.path and first.path.stat().st_mtime_ns == stamp
    # no temp files: the library and its sha256
    assert sorted(p.name for p in tmp_path.iterdir()) == [first.path.name,
                                                          first.path.name + ".sha256"]


@needs_cc
def test_concurrent_processes_share_one_build(tmp_path):
    code = ("from hmpc_cli.sim.rollout import CRollout; "
            "from hmpc_cli.systems.ball import BallParams, build_ball; "
            "print(CRollout(build_ball(BallParams(radius=0.12))).path)")
    env = {**os.environ, "HMPC_CACHE_DIR": str(tmp_path)}
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env, stdout=subprocess.PIPE,
                              text=True) for _ in range(2)]
    paths = {p.communicate(timeout=120)[0].strip() for p in procs}
    assert all(p.returncode == 0 for p in procs) and len(paths) == 1
    name = os.path.basename(paths.pop())
    assert sorted(p.name for p in tmp_path.iterdir()) == [name, name + ".sha256"]


def test_missing_compiler_falls_back_to_numpy(tmp_path, monkeypatch):
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", "/nonexistent/cc")
    with pytest.warns(RuntimeWarning, match="C rollouts unavailable"):
        ball, planner = _planner("auto")
    assert planner.backend == "numpy"
    knots = _knots(np.random.default_rng(0), 4)
    cost, reached = planner.rollout_cost(ball.x0, 0, knots)
    ref, ref_reached = planner.rollout_cost_numpy(ball.x0, 0, knots)
    assert np.array_equal(cost, ref) and np.array_equal(reached, ref_reached)
    with pytest.raises(RolloutBuildError, match="nonexistent"):
        _planner("c")


def test_numpy_setting_does_not_build(tmp_path, monkeypatch):
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path))
    _, planner = _planner("numpy")
    assert planner.backend == "numpy" and list(tmp_path.iterdir()) == []


def _slow_cc(tmp_path, seconds: float = 1.5):
    """A compiler that takes ``seconds`` longer than cc (its --version answers at once)."""
    cc = tmp_path / "slow-cc"
    cc.write_text('#!/bin/sh\n[ "$1" = --version ] && exec cc --version\n'
                  f'sleep {seconds}\nexec cc "$@"\n')
    cc.chmod(0o755)
    return str(cc)


@needs_cc
def test_a_background_compile_is_waited_for_at_the_first_rollout(tmp_path, monkeypatch):
    """rollout_backend = "auto" compiles while the run builds: the planner is made while
    the compiler still runs, and its first rollout waits for the library (the same costs
    as NumPy's)."""
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", _slow_cc(tmp_path))
    before = rollout_c.COMPILES
    ball, planner = _planner("auto", BallParams(radius=0.105))
    assert planner.backend == "c" and not planner._c._build.done  # still compiling
    assert not planner._c.ready and planner._c.compile_seconds is None
    knots = _knots(np.random.default_rng(3), 8)
    cost, reached = planner.rollout_cost(ball.x0, 0, knots)
    ref, ref_reached = planner.rollout_cost_numpy(ball.x0, 0, knots)
    assert np.array_equal(cost, ref) and np.array_equal(reached, ref_reached)
    assert planner._c.ready and planner._c.compile_seconds >= 1.5
    assert rollout_c.COMPILES - before == 1
    name = planner._c.path.name
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [name, name + ".sha256"]


@needs_cc
def test_builds_of_one_source_under_way_share_one_compile(tmp_path, monkeypatch):
    """Two builds started while the first compiles (another planner, another thread of a
    threaded worker) share it: one compile, one library."""
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", _slow_cc(tmp_path))
    source = rollout_c.generate_source(build_ball(BallParams(radius=0.115)))
    before = rollout_c.COMPILES
    first = rollout_c.start_library(source)
    assert not first.done
    results = []
    threads = [threading.Thread(target=lambda: results.append(
        rollout_c.start_library(source).result())) for _ in range(2)]
    for t in threads:
        t.start()
    lib, path, seconds = first.result()
    for t in threads:
        t.join()
    assert seconds is not None and results == [(lib, path, seconds)] * 2
    assert rollout_c.COMPILES - before == 1
    assert rollout_c.start_library(source).result()[0] is lib


@needs_cc
def test_a_background_compile_that_fails_falls_back_to_numpy(tmp_path, monkeypatch):
    """A compiler that answers --version but cannot compile: "auto" plans with NumPy (one
    warning, at the first rollout), "c" is an error when the planner is made."""
    cc = tmp_path / "cc"
    cc.write_text('#!/bin/sh\n[ "$1" = --version ] && echo "broken 1.0" && exit 0\n'
                  'echo "cc: internal error" >&2\nexit 1\n')
    cc.chmod(0o755)
    monkeypatch.setenv("HMPC_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(cc))
    ball, planner = _planner("auto", BallParams(radius=0.125))
    assert planner.backend == "c"
    knots = _knots(np.random.default_rng(4), 6)
    with pytest.warns(RuntimeWarning, match="C rollouts unavailable, using NumPy: .*failed"):
        cost, reached = planner.rollout_cost(ball.x0, 0, knots)
    assert planner.backend == "numpy"
    ref, ref_reached = planner.rollout_cost_numpy(ball.x0, 0, knots)
    assert np.array_equal(cost, ref) and np.array_equal(reached, ref_reached)
    with pytest.raises(RolloutBuildError, match="planner.rollout_backend = 'c'.*failed"):
        _planner("c", BallParams(radius=0.125))
    assert [p.name for p in (tmp_path / "cache").iterdir()] == []  # no temporary files


@needs_cc
def test_an_exit_during_a_background_compile_leaves_the_library_whole(tmp_path):
    """The process ends right after starting the compile: it waits for it, so the cache
    holds the library and its sha256, and no temporary file."""
    code = ("from hmpc_cli.sim.rollout import CRollout; "
            "from hmpc_cli.systems.ball import BallParams, build_ball; "
            "c = CRollout(build_ball(BallParams(radius=0.135)), wait=False); "
            "print(c.path.name, c.ready)")
    env = {**os.environ, "HMPC_CACHE_DIR": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    name, ready = proc.stdout.split()
    assert ready == "False"
    assert sorted(p.name for p in tmp_path.iterdir()) == [name, name + ".sha256"]
