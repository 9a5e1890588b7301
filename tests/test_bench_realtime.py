"""benchmarks/realtime.py: its sweep is the yardstick's grid and plans (no run)."""

import importlib.util
from pathlib import Path

from hmpc_cli.sweep.plan import plan_sweep

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location("bench_realtime",
                                                  ROOT / "benchmarks" / "realtime.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_yardstick_grid_plans(tmp_path):
    rt = _module()
    text = rt.sweep_text(rt.LATENCIES, rt.RATES, rt.POLICIES, rt.TRIALS, True)
    (tmp_path / "realtime.toml").write_text(text)
    plan = plan_sweep(tmp_path / "realtime.toml")
    assert len(plan.runs) == 3 * 4 * 2 * 11
    at_100 = [r for r in plan.runs if r.overrides["mpc.rate_hz"] == 100]
    assert {r.overrides["mpc.nodes_per_second"] for r in at_100} == {100}
    assert all(r.overrides["sim.delay_compensation"] is True for r in plan.runs)
    assert {r.overrides["sim.latency"] for r in plan.runs} == set(rt.LATENCIES)


def test_the_report_says_what_the_runs_set():
    """The header states delay compensation and the first plan from the runs' effective
    scenarios: one value when all agree, the values found when a grid varies them."""
    rt = _module()
    assert rt.run_settings(plan_sweep(ROOT / "sweeps" / "realtime_biped_rti.toml")) == (
        "Delay compensation off, first plan charged or paused (as each controller's label "
        "says)")
    assert rt.run_settings(plan_sweep(ROOT / "sweeps" / "realtime_ipopt.toml")) == (
        "Delay compensation off, first plan paused")


def test_the_yardstick_grid_states_its_settings(tmp_path):
    rt = _module()
    text = rt.sweep_text(["paused"], [10], ["once"], 1, True)
    (tmp_path / "realtime.toml").write_text(text)
    assert rt.run_settings(plan_sweep(tmp_path / "realtime.toml")) == (
        "Delay compensation on, first plan paused")
