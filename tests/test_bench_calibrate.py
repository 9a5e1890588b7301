"""benchmarks/calibrate_latency.py: its report charges what it prints (no run)."""

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _module():
    spec = importlib.util.spec_from_file_location(
        "calibrate_latency", ROOT / "benchmarks" / "calibrate_latency.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_model_column_is_what_the_printed_constants_charge():
    """A fit of 1.46 ms + 4.126 ms per iteration prints 0.0015 and 0.0041; at 79 iterations
    the column says 325.4 ms (what sim.latency = "model" charges with those), not the
    unrounded fit's 327.4 ms."""
    cal = _module()
    points = [(1, 0.0056, False), (79, 0.33, False), (79, 0.32, False)]
    text = cal.report(points, {"overhead": 0.00146, "per_iteration": 0.004126}, ["s.toml"], [])
    assert "overhead = 0.0015\nper_iteration = 0.0041\n" in text
    rows = {int(m[1]): float(m[2]) for m in re.finditer(
        r"^\| no \| (\d+) \| \d+ \| [\d.]+ \| [\d.]+ \| ([\d.]+) \|$", text, re.M)}
    assert rows == {1: 5.6, 79: 325.4}
