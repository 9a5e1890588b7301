"""benchmarks/realtime.py: its sweep is the yardstick's grid and plans (no run)."""

from pathlib import Path

from conftest import load_benchmark
from hmpc_cli.sweep.plan import plan_sweep

ROOT = Path(__file__).resolve().parents[1]


def _module():
    return load_benchmark("realtime")


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


def test_a_report_over_a_committed_table_is_printed_not_written(tmp_path):
    """A committed table's rows have no logs: the solve percentiles would leave them out, so
    --write refuses (exit 2, nothing written); the grid form may not take over another
    sweep's directory; the machine is the runs' when the table names it."""
    import shutil
    import subprocess
    import sys

    rt = _module()
    out = tmp_path / "realtime_rti"
    out.mkdir()
    for name in ("results.csv", "sweep.toml", "base_scenario.toml"):
        shutil.copy(ROOT / "results" / "sweeps" / "realtime_rti" / name, out / name)
    counts, solves, _, no_log, cpus = rt.summarise(out)
    assert sum(c[1] for c in counts.values()) == no_log == 264 and not solves
    assert cpus == ["AMD EPYC"]  # the table names the machine its runs ran on
    assert rt.machine().endswith("(the machine that wrote this report; the table does not "
                                 "name the runs')")
    assert rt.machine(["Intel X"]) == "Intel X (the runs' own, from the table)"
    bench = [sys.executable, str(ROOT / "benchmarks" / "realtime.py"), "--out", str(out)]
    written = subprocess.run([*bench, "--sweep", str(ROOT / "sweeps" / "realtime_rti.toml"),
                              "--write", str(tmp_path / "x.md")], capture_output=True,
                             text=True, timeout=300)
    assert written.returncode == 2 and not (tmp_path / "x.md").exists()
    assert written.stderr.startswith(f"error: --write {tmp_path / 'x.md'}: 264 of 264 runs in "
                                     f"{out} have no log")
    assert "| 100 Hz once | 11/11 | 10/11 | 9/11 |" in written.stdout
    # the runs' real_time, pooled from the table
    assert ("`-`: not recorded):\n\n| controller | model | measured |\n|---|---|---|\n"
            "| 10 Hz once | 0 % (0/341) | 0 % (0/339) |\n") in written.stdout
    assert "| 100 Hz on_contact | 23 % (622/2718) | 39 % (851/2200) |\n" in written.stdout
    assert rt.past_period(out)[("model", "100 Hz once")] == [2942, 536, 0, 0]
    grid = subprocess.run([*bench, "--scenario", str(ROOT / "scenarios" / "ball_realtime.toml")],
                          capture_output=True, text=True, timeout=300)
    assert grid.returncode == 2 and grid.stderr == (
        f"error: --out {out}: belongs to sweep 'realtime_rti' (its sweep.toml), not "
        "'realtime': choose another --out (the same sweep resumes in its own directory)\n")
    assert not (out / "realtime.toml").exists()


def test_the_report_names_whose_latency_model_the_runs_charge(tmp_path):
    """A sweep whose latency entries set their own model (realtime_ipopt) is not said to
    charge the scenario's; one that does not (realtime_biped) is."""
    import argparse

    rt = _module()
    said = {}
    for name in ("realtime_ipopt", "realtime_biped"):
        args = argparse.Namespace(sweep=ROOT / "sweeps" / f"{name}.toml",
                                  out=tmp_path / name)
        rt._plan(args)
        said[name] = (args.own_model, args.grid_says)
    assert said["realtime_ipopt"] == (True, "the grid of `" + (
        ROOT / "sweeps" / "realtime_ipopt.toml").as_posix() + "` sets the rest, its latency "
        "entries their own latency model")
    assert said["realtime_biped"][0] is False
    assert not said["realtime_biped"][1].endswith("latency model")
