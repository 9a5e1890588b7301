"""benchmarks/latency_counts.py: IPOPT's counters recorded per call, the non-negative fits
and the report's rows (behaviour; its times are measured, never asserted)."""

from pathlib import Path

import numpy as np

from conftest import load_benchmark

ROOT = Path(__file__).resolve().parents[1]


def _module():
    return load_benchmark("latency_counts")


def test_the_fit_is_non_negative_and_recovers_a_non_negative_truth():
    mod = _module()
    rng = np.random.default_rng(0)
    x = rng.uniform(1.0, 2.0, (200, 3))
    assert np.allclose(mod.fit_nonnegative(x, x @ [0.5, 0.0, 2.0]), [0.5, 0.0, 2.0])
    coef = mod.fit_nonnegative(x, x @ [1.0, -3.0, 0.5])
    assert (coef >= 0).all() and coef[1] == 0.0


def test_the_sweeps_paused_cells_are_its_grid_without_the_latency_axis():
    cells = _module()._cells(ROOT / "sweeps" / "realtime_ipopt.toml", "latency", "paused")
    assert len(cells) == 8 * 11
    assert cells[0][:2] == ['sim.latency_first="paused"', 'sim.latency="paused"']
    assert cells[-1][-2:] == ["#100 Hz on_contact", "#trial 10"]


def test_a_flown_run_records_every_ipopt_calls_counters_and_the_report_tables_them():
    mod = _module()
    calls = mod.fly(("scenarios/ball.toml", ['sim.duration=0.3', "#short"]))
    assert len(calls) >= 3 and all(c["run"] == "short" for c in calls)
    for c in calls:
        assert c["iterations"] >= 1 and 0 <= c["regularised"] <= c["iterations"]
        assert c["nlp_jac_g"] >= c["iterations"] and c["nlp_g"] >= c["iterations"]
        assert c["wall"] > 0 and c["variables"] > 0
    other = [dict(c, run="other", wall=1.1 * c["wall"]) for c in calls]
    text = mod.report(calls + other, "short", "# head", [calls])
    rows = [line for line in text.splitlines() if line.startswith("| ")]
    assert [r.split(" | ")[0] for r in rows[1:4]] == [f"| {m}" for m in mod.MODELS]
