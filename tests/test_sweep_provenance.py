"""A sweep's run records what made it: its grid overrides, its seed and the sweep file."""

from __future__ import annotations

import re

from test_replay import replay
from test_sweep import TINY_SET, write_sweep
from hmpc_cli.log.reader import read_log
from hmpc_cli.sweep.execute import execute_sweep, run_provenance
from hmpc_cli.sweep.plan import plan_sweep

ONE = """name = "one"
scenario = "{scenario}"
seeds = [3]
""" + TINY_SET + """
[grid]
"mpc.rate_hz" = [20]
"""


def test_run_provenance_lists_set_and_grid_overrides_and_the_seed(tmp_path):
    plan = plan_sweep(write_sweep(tmp_path, ONE))
    (run,) = plan.runs
    prov = run_provenance(plan, run, "hmpc sweep one.toml")
    assert prov.command == "hmpc sweep one.toml" and prov.sweep == str(plan.path)
    assert prov.overrides == ("mpc.horizon=1.0", "mpc.rate_hz=20", "planner.iterations=6",
                              "planner.knots=10", "planner.samples=20", "sim.duration=0.3",
                              "seed=3")


def test_sweep_run_log_shows_its_overrides_and_verifies(tmp_path):
    path = write_sweep(tmp_path, ONE)
    out = tmp_path / "out"
    outcome = execute_sweep(plan_sweep(path), out)
    assert outcome.done == 1 and not outcome.lost
    (log,) = out.glob("runs/*/run.mcap")
    info = read_log(log).topic("/run/info")[0].data
    assert "mpc.rate_hz=20" in info["overrides"] and info["overrides"][-1] == "seed=3"
    assert info["sweep"] == str(path)
    res = replay(log)
    assert res.exit_code == 0, res.output
    assert re.search(r"overrides\W+mpc\.horizon=1\.0 mpc\.rate_hz=20 .*seed=3", res.output)
    assert re.search(rf"sweep\W+{re.escape(str(path))}", res.output)
    res = replay(log, "--verify")
    assert res.exit_code == 0, res.output
    assert "identical (" in res.output
