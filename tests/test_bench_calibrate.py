"""benchmarks/calibrate_latency.py: its report charges what it prints; --sweep fits the
solves a sweep logged (no new run)."""

import re
from pathlib import Path

import pytest

from conftest import load_benchmark

ROOT = Path(__file__).resolve().parents[1]


def _module():
    return load_benchmark("calibrate_latency")


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


def _sweep_dir(tmp_path: Path, log: Path) -> Path:
    """A sweep output directory whose results.csv names ``log`` twice: once paused, once
    measured (only the paused row's log exists)."""
    import shutil

    sweep = tmp_path / "sweep"
    (sweep / "runs" / "a").mkdir(parents=True)
    shutil.copy(log, sweep / "runs" / "a" / "run.mcap")
    (sweep / "results.csv").write_text(
        "run_id,latency,success,log\n"
        "a,paused,true,runs/a/run.mcap\n"
        "b,measured,false,runs/b/run.mcap\n")
    return sweep


def test_a_sweeps_logged_solves_are_fitted_without_running_anything(full_run, tmp_path):
    """--sweep DIR --where latency=paused reads the matching rows' logs: every logged MPC
    solve with its iterations, wall time and whether a switch was left, as the log has
    them; the report names the runs it fitted and charges what it prints."""
    import subprocess
    import sys

    from hmpc_cli.log.reader import read_log

    cal = _module()
    log = full_run.out / "run.mcap"
    sweep = _sweep_dir(tmp_path, log)
    assert cal.sweep_logs(sweep, ["latency=paused"]) == [sweep / "runs" / "a" / "run.mcap"]
    want = [(int(m.data["iterations"]), float(m.data["wall_time"]),
             bool((m.data.get("schedule") or {}).get("guards")), len(m.data["plan"]))
            for m in read_log(log).messages
            if m.topic == "/mpc/solve" and m.data.get("iterations", 0) > 0]
    got = cal.solves_in(sweep / "runs" / "a" / "run.mcap")
    assert got == want and len(got) == 32 and sum(s for _, _, s, _ in got) == 7
    assert min(n for *_, n in got) == 181  # the final-domain plans: 180 links
    out = tmp_path / "fit.md"
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "calibrate_latency.py"), "--switching",
         "--scale-nodes", "--sweep", str(sweep), "--where", "latency=paused", "--write",
         str(out)],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    assert f"32 solves of the 1 runs of `{sweep}` with `latency=paused` (their logged " \
           "`wall_time`)." in text
    assert "per_switching_iteration = " in text and text == proc.stdout.rstrip("\n") + "\n"
    # the reference size is the fitted solves' median plan: 25 final-domain plans of 181
    assert "nodes = 181\n" in text and "| 181 | 25 | " in text


def test_a_sweep_that_cannot_be_fitted_is_said(full_run, tmp_path):
    """No results.csv, an unknown column, no matching row and a missing log each stop with
    a message naming the file and what to do."""
    cal = _module()
    sweep = _sweep_dir(tmp_path, full_run.out / "run.mcap")
    cases = [(tmp_path / "none", [], "results.csv: no such file"),
             (sweep, ["rate=10"], "--where rate=10: want COLUMN=VALUE with a column of"),
             (sweep, ["latency"], "--where latency: want COLUMN=VALUE"),
             (sweep, ["latency=model"], "no run matches latency=model"),
             (sweep, ["latency=measured"], "1 run logs missing (first: "
              f"{sweep / 'runs' / 'b' / 'run.mcap'}): run the sweep again")]
    for where, pairs, said in cases:
        with pytest.raises(SystemExit, match=None) as stop:
            cal.sweep_logs(where, pairs)
        assert said in str(stop.value), (pairs, stop.value)


def test_a_fit_scaled_by_plan_nodes_recovers_its_constants_and_charges_them():
    """--scale-nodes: solves timed exactly (n / 181) x (5 ms + 2 ms per iteration, 4 ms
    with a switch left) on 181- and 301-node plans give back those constants at 181 nodes;
    the report prints nodes whole and charges each solve as sim.latency = "model" does."""
    import numpy as np

    cal = _module()
    points = [(k, n / 181 * (0.005 + (0.004 if sw else 0.002) * k), sw, n)
              for n in (181, 191, 301) for sw in (False, True) for k in (1, 2, 5, 9)]
    model = cal.fit(points, switching=True, nodes=181)
    assert model["nodes"] == 181
    assert np.allclose([model[k] for k in ("overhead", "per_iteration",
                                           "per_switching_iteration")],
                       [0.005, 0.002, 0.004], rtol=1e-12, atol=1e-15)
    text = cal.report(points, model, ["s.toml"], [])
    assert "nodes = 181\n" in text and "overhead = 0.0050\n" in text
    assert "| 301 | 8 | " in text  # the table by plan nodes
    assert "median charge of the row's solves" in text
    bad = [*points, (2, 0.01, False, 0)]
    with pytest.raises(SystemExit, match="1 of 25 solves have no plan nodes"):
        cal.fit(bad, switching=True, nodes=181)


def test_a_log_without_plan_nodes_gives_them_where_it_logged_every_node():
    """A log written before /mpc/solve had `nodes` (version 4): the logged plan's length
    when the run logged every node (sim.log_plan_stride = 1), 0 (unknown) when it thinned
    them; a field present is taken as it is."""
    import json

    from hmpc_cli.log.reader import LogMessage

    def info(stride):
        return LogMessage("/run/info", 0.0, {"scenario_json": json.dumps(
            {"sim": {"log_plan_stride": stride}})}, 0)

    old = LogMessage("/mpc/solve", 0.1, {"iterations": 2, "wall_time": 0.01,
                                         "plan": [{}, {}, {}]}, 0)
    new = LogMessage("/mpc/solve", 0.2, {"iterations": 3, "wall_time": 0.02, "nodes": 181,
                                         "plan": [{}] * 61}, 0)
    cal = _module()
    assert cal.logged_solves([info(1), old, new]) == [(2, 0.01, False, 3),
                                                      (3, 0.02, False, 181)]
    assert cal.logged_solves([info(3), old, new]) == [(2, 0.01, False, 0),
                                                      (3, 0.02, False, 181)]


def test_the_whole_solve_call_is_logged_and_fitted_with_time_call(full_run, tmp_path,
                                                                  monkeypatch):
    """/mpc/solve's call_wall_time is the controller's whole solve call (the NLP solver's
    call inside it); --time call fits it, what sim.latency = "measured" charges; a log
    without it (written before version 7) is said."""
    import dataclasses
    import subprocess
    import sys

    from hmpc_cli.log.reader import read_log

    cal = _module()
    log = full_run.out / "run.mcap"
    solves = [m.data for m in read_log(log).messages if m.topic == "/mpc/solve"]
    assert all(d["call_wall_time"] > d["wall_time"] > 0 for d in solves)
    monkeypatch.setattr(cal, "TIME", ["call_wall_time"])
    got = cal.solves_in(log)
    assert [w for _, w, _, _ in got] == [d["call_wall_time"] for d in solves
                                         if d["iterations"] > 0]
    old = [dataclasses.replace(m, data={k: v for k, v in m.data.items()
                                        if k != "call_wall_time"})
           for m in read_log(log).messages]
    with pytest.raises(SystemExit) as stop:
        cal.logged_solves(old)
    assert "has no call_wall_time (a log written before hmpc logged it, version 7)" in \
        str(stop.value)
    sweep = _sweep_dir(tmp_path, log)
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "calibrate_latency.py"), "--time", "call",
         "--sweep", str(sweep), "--where", "latency=paused"],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "(their logged `call_wall_time`)." in proc.stdout


def test_a_replan_that_returned_a_foothold_candidates_plan_is_fitted_once(monkeypatch):
    """A foothold replan's /mpc/solve returns a candidate's stored plan: its statistics
    are the candidate's, its call_wall_time only the return. --time call leaves it out
    (said in the report) instead of fitting 7 iterations to 10 us; --candidates fits the
    candidates' own solver calls, whose set-up is in the planner's own time, with either
    --time."""
    from hmpc_cli.log.reader import LogMessage

    cands = [{"iterations": 5, "wall_time": 0.03}, {"iterations": 7, "wall_time": 0.04}]
    sched = {"guards": ["stair_1"]}
    msgs = [LogMessage("/planner/plan", 0.3, {"wall_time": 0.08,
                                              "detail": {"candidates": cands}}, 0),
            LogMessage("/mpc/solve", 0.3, {"iterations": 7, "wall_time": 0.04,
                                           "call_wall_time": 1e-5, "nodes": 40,
                                           "schedule": sched}, 0),
            LogMessage("/mpc/solve", 0.4, {"iterations": 4, "wall_time": 0.02,
                                           "call_wall_time": 0.022, "nodes": 40,
                                           "schedule": sched}, 0)]
    cal = _module()
    monkeypatch.setattr(cal, "REUSED", [0])
    monkeypatch.setattr(cal, "OWN", [])
    assert cal.logged_solves(msgs) == [(7, 0.04, True, 40), (4, 0.02, True, 40)]
    assert cal.REUSED == [0] and cal.OWN == []
    monkeypatch.setattr(cal, "TIME", ["call_wall_time"])
    assert cal.logged_solves(msgs) == [(4, 0.022, True, 40)]
    assert cal.REUSED == [1]
    got = cal.logged_solves(msgs, candidates=True)
    assert got == [(5, 0.03, True, 0), (7, 0.04, True, 0), (4, 0.022, True, 40)]
    assert len(cal.OWN) == 1 and cal.OWN[0] == pytest.approx(0.01)
    text = cal.report([(4, 0.022, True, 40)], {"overhead": 0.0, "per_iteration": 0.005},
                      ["x.toml"], [], source="the runs", reused=1)
    assert ("4 solves" not in text and "1 solves of the runs; 1 replan solves left out: each "
            "returned a foothold candidate's plan, whose time is the planner call's "
            "(`--candidates` fits the candidates).") in text
