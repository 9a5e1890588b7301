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
