"""``hmpc sweep``: expansion, validation, 1 vs 2 workers vs Dask, failures, resume, Ctrl-C."""

from __future__ import annotations

import ast
import csv
import json
import tomllib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import BALL, REPO, cli_env
from hmpc_cli.cli.sweep import connect_dask
from hmpc_cli.run.scenario import ScenarioError
from hmpc_cli.sweep.table import TIMING
from hmpc_cli.sweep.plan import plan_sweep, run_id

# ``hmpc`` with the sweep command registered (cli.py registers it the same way).
REGISTER = ("from hmpc_cli.cli.app import app\n"
            "from hmpc_cli.cli.sweep import sweep_command\n"
            "if not any(c.name == 'sweep' for c in app.registered_commands):\n"
            "    app.command('sweep')(sweep_command)\n"
            "app()\n")
TINY_SET = """
[set]
"sim.duration" = 0.3
"mpc.horizon" = 1.0
"planner.iterations" = 6
"planner.samples" = 20
"planner.knots" = 10
"""
TINY = """name = "tiny"
scenario = "{scenario}"
seeds = 2
""" + TINY_SET + """
[grid]
"lowlevel.kp" = [0.0, 1.0]
case = [
  { label = "ok" },
  { label = "diverge", "sim.divergence_bound" = 0.5 },
  { label = "crash", "replanning.policy" = "on_contact", "replanning.contact_guards" = ["nope"] },
]
"""


def sweep(args: list[str], cwd: Path, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
    """``hmpc sweep ARGS`` in a fresh process."""
    return subprocess.run([sys.executable, "-c", REGISTER, "sweep", *args], cwd=cwd,
                          env=cli_env(), capture_output=True, text=True, timeout=timeout, **kw)


def write_sweep(folder: Path, text: str, name: str = "sweep.toml") -> Path:
    """A sweep file in ``folder`` whose scenario path is relative to it."""
    path = folder / name
    path.write_text(text.replace("{scenario}", os.path.relpath(BALL, folder)))
    return path


def table(out: Path, timing: bool = False) -> list[dict[str, str]]:
    """results.csv rows (without the timing columns unless asked)."""
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return rows if timing else [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """The tiny sweep run once in-process (--workers 1): (folder, sweep file, out, proc)."""
    base = tmp_path_factory.mktemp("sweep")
    path = write_sweep(base, TINY)
    out = base / "w1"
    proc = sweep([str(path), "--workers", "1", "--out", str(out)], base)
    assert proc.returncode == 0, proc.stderr
    return base, path, out, proc


def test_tiny_sweep_table_and_failures(tiny):
    _, path, out, proc = tiny
    rows = table(out, timing=True)
    plan = plan_sweep(path)
    assert len(rows) == len(plan.runs) == 12
    assert [r["run_id"] for r in rows] == [r.run_id for r in plan.runs]  # grid order
    assert list(rows[0]) == [
        "run_id", "lowlevel.kp", "case", "seed", "set.lowlevel.kp", "set.mpc.horizon",
        "set.planner.iterations", "set.planner.knots", "set.planner.samples",
        "set.replanning.contact_guards", "set.replanning.policy", "set.sim.divergence_bound",
        "set.sim.duration", "success", "final_error", "contacts", "solves", "solver_failures",
        "softened_solves", "planner_calls", "planner_rejected", "diverged", "reason",
        "solve_time_median", "solve_time_p95", "solve_time_max", "plan_time_median",
        "wall_time", "cpu", "log"]
    from hmpc_cli.core.machine import cpu_model

    assert {r["cpu"] for r in rows} == {cpu_model()}  # crashed runs too
    by_case = {c: [r for r in rows if r["case"] == c] for c in ("ok", "diverge", "crash")}
    assert all(len(v) == 4 for v in by_case.values())
    assert {(r["lowlevel.kp"], r["seed"]) for r in by_case["ok"]} == {
        ("0.0", "0"), ("0.0", "1"), ("1.0", "0"), ("1.0", "1")}
    for r in by_case["crash"]:  # raised inside the run: recorded, the others went on
        assert r["success"] == "false" and r["log"] == ""
        assert r["reason"] == ("ValueError: replanning.contact_guards: unknown guard 'nope'; the "
                               "system's guards: 'floor', 'wall', 'circle_in', 'circle_out'")
        assert r["set.replanning.contact_guards"] == '["nope"]'
        assert (out / "runs" / r["run_id"] / "error.txt").read_text().startswith("Traceback")
    for r in by_case["diverge"]:
        assert r["diverged"] == "true" and r["success"] == "false"
        assert r["reason"].startswith("diverged") and r["set.sim.divergence_bound"] == "0.5"
    for r in by_case["ok"]:
        assert r["diverged"] == "false" and not r["reason"].startswith(("diverged", "Value"))
        assert r["log"] == f"runs/{r['run_id']}/run.mcap" and (out / r["log"]).is_file()
        assert float(r["wall_time"]) > 0 and r["set.sim.duration"] == "0.3"
    summary = json.loads((out / "runs" / by_case["ok"][0]["run_id"] / "summary.json").read_text())
    assert summary["seed"] == int(by_case["ok"][0]["seed"])
    assert (out / "sweep.toml").read_text() == path.read_text()
    assert "12 to run (in-process)" in proc.stdout
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("│")]
    assert sum("100 %" in ln or "0 %" in ln for ln in lines) == 7  # 6 cells + all


def test_two_workers_give_the_same_table(tiny):
    base, path, out, _ = tiny
    out2 = base / "w2"
    proc = sweep([str(path), "--workers", "2", "--out", str(out2)], base)
    assert proc.returncode == 0, proc.stderr
    assert "(2 worker processes)" in proc.stdout
    assert table(out2) == table(out)
    assert table(out2, timing=True) != table(out, timing=True)  # timings are measured
    from hmpc_cli.log.reader import read_log

    row = next(r for r in table(out2) if r["case"] == "ok" and r["lowlevel.kp"] == "1.0")
    info = read_log(out2 / row["log"]).topic("/run/info")[0].data  # written by a worker
    assert "lowlevel.kp=1.0" in info["overrides"] and f"seed={row['seed']}" in info["overrides"]
    assert info["sweep"] == str(path) and info["command"].endswith(f"--out {out2}")


def test_resume_skips_finished_runs(tiny):
    base, path, out, _ = tiny
    out3 = base / "resume"
    shutil.copytree(out, out3)
    rows = table(out3)
    gone, stopped, other = rows[3]["run_id"], rows[7]["run_id"], rows[9]["run_id"]
    shutil.rmtree(out3 / "runs" / gone)
    s = out3 / "runs" / stopped / "summary.json"
    s.write_text(json.dumps({**json.loads(s.read_text()), "reason": "interrupted"}))
    # a run finished with another scenario (as after an edit of the scenario file)
    stored = out3 / "runs" / other / "scenario.toml"
    stored.write_text("".join('description = "old"\n' if line.startswith("description = ")
                              else line for line in stored.read_text().splitlines(True)))
    (out3 / "results.csv").unlink()
    kept = {p.parent.name: p.stat().st_mtime_ns for p in out3.glob("runs/*/summary.json")
            if p.parent.name != stopped}
    proc = sweep([str(path), "--workers", "1", "--out", str(out3)], base)
    assert proc.returncode == 0, proc.stderr
    assert "12 runs, 9 skipped (already done), 3 to run" in proc.stdout
    assert proc.stderr.splitlines()[0] == (
        f"warning: 1 finished run(s) in {out3 / 'runs'} were made with another scenario "
        f"(their scenario.toml differs from this sweep's now, or the margins file they read "
        f"has changed since, e.g. run {other}): they are run again and their files replaced "
        "(a sweep into another --out keeps them)")
    now = {p.parent.name: p.stat().st_mtime_ns for p in out3.glob("runs/*/summary.json")}
    assert {k for k in now if now[k] != kept.get(k)} == {gone, stopped, other}
    assert table(out3) == table(out)


def _as_committed(out: Path, to: Path) -> Path:
    """A copy of sweep directory ``out`` as a repository holds it: no run directories."""
    shutil.copytree(out, to, ignore=shutil.ignore_patterns("runs"))
    return to


def test_a_committed_table_resumes_without_its_run_directories(tiny):
    """A fresh clone holds results.csv, sweep.toml and base_scenario.toml, no run logs (at
    most a drawn run's trace.mcap): its rows are finished runs; rows taken out of the
    table are run again, and the table comes back in grid order."""
    base, path, out, _ = tiny
    committed = _as_committed(out, base / "committed")
    assert (committed / "base_scenario.toml").is_file()
    drawn = next(r["run_id"] for r in table(out)[2:] if r["log"])  # a drawn run: its trace
    (committed / "runs" / drawn).mkdir(parents=True)
    shutil.copy(out / "runs" / drawn / "run.mcap", committed / "runs" / drawn / "trace.mcap")
    proc = sweep([str(path), "--workers", "1", "--out", str(committed)], base)
    assert proc.returncode == 0, proc.stderr
    assert "12 runs, 12 skipped (already done), 0 to run" in proc.stdout
    assert (committed / "results.csv").read_bytes() == (out / "results.csv").read_bytes()
    lines = (committed / "results.csv").read_text().splitlines(keepends=True)
    (committed / "results.csv").write_text("".join([lines[0], *lines[3:]]))  # 2 rows out
    proc = sweep([str(path), "--workers", "1", "--out", str(committed)], base)
    assert proc.returncode == 0, proc.stderr
    assert "12 runs, 10 skipped (already done), 2 to run" in proc.stdout
    assert table(committed) == table(out)
    assert sorted(p.name for p in (committed / "runs").iterdir()) == sorted(
        [drawn, *(r["run_id"] for r in table(out)[:2])])


REAL_TIME_SWEEP = """name = "charged"
scenario = "{scenario}"

[set]
"sim.duration" = 0.6

[grid]
"sim.latency" = ["paused", "model"]
"""


def test_a_sweep_that_charges_compute_time_tables_its_real_time(tmp_path):
    """Its table carries each run's real_time (a time-paused run's cells empty; a paused
    sweep's header has none, test_tiny_sweep_table_and_failures) and its printed cell
    table the late solves' share, from run directories and tabled rows alike; a table
    flown before hmpc recorded real_time resumes with those cells empty, nothing run
    again."""
    from hmpc_cli.sweep.table import REAL_TIME, cell_text

    path = write_sweep(tmp_path, REAL_TIME_SWEEP)
    out = tmp_path / "out"
    proc = sweep([str(path), "--workers", "1", "--out", str(out)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    rows = table(out, timing=True)
    assert list(rows[0])[-len(REAL_TIME) - 2:] == ["cpu", *REAL_TIME, "log"]
    paused, model = rows
    assert (paused["sim.latency"], model["sim.latency"]) == ("paused", "model")
    assert {paused[k] for k in REAL_TIME} == {""}
    real_time = json.loads((out / "runs" / model["run_id"] / "summary.json").read_text())[
        "real_time"]
    assert {k: model[k] for k in REAL_TIME} == {k: cell_text(real_time[k]) for k in REAL_TIME}
    assert int(model["charged_solves"]) == int(model["solves"]) > 0  # the first charged
    late, charged = int(model["late_solves"]), int(model["charged_solves"])
    assert (model["dropped_solves"], model["preempted_solves"]) == ("0", "0")  # no budget
    share = f"{100 * late / charged:.0f} % ({late}/{charged})"  # the cells' printed table
    ok = int(model["success"] == "true")

    def printed(proc) -> list[list[str]]:
        return [[c.strip() for c in line.split("│")[1:-1]] for line in
                proc.stdout.splitlines() if line.startswith("│ model ")]

    assert printed(proc) == [["model", "1", str(ok), f"{100 * ok} %", share]]
    committed = _as_committed(out, tmp_path / "committed")  # the tabled rows say it too
    proc = sweep([str(path), "--workers", "1", "--out", str(committed)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert printed(proc) == [["model", "1", str(ok), f"{100 * ok} %", share]]
    older = _as_committed(out, tmp_path / "older")
    with open(older / "results.csv", newline="") as f:
        kept = [{k: v for k, v in r.items() if k not in REAL_TIME} for r in csv.DictReader(f)]
    with open(older / "results.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, list(kept[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(kept)
    proc = sweep([str(path), "--workers", "1", "--out", str(older)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "2 runs, 2 skipped (already done), 0 to run" in proc.stdout
    assert table(older, timing=True) == [{**r, **dict.fromkeys(REAL_TIME, "")}
                                         for r in table(out, timing=True)]
    assert printed(proc) == [["model", "1", str(ok), f"{100 * ok} %", "-"]]


def test_a_cells_solves_past_the_period_read_as_counts():
    from hmpc_cli.sweep.table import CellStats, late_text

    assert late_text(25, 3) == "12 % (3/25)"
    assert late_text(9, 0, 4, 1) == "0 % (0/9); 4 dropped, 1 stopped"
    assert late_text(9, 2, 0, 1) == "22 % (2/9); 1 stopped"
    assert late_text(0, 0) == "0/0"
    assert CellStats(("a",), 2, 1, 2, 9, 0, 4).columns(True) == [
        "2", "1", "50 %", "0 % (0/9); 4 dropped"]
    assert CellStats(("a",), 2, 1, 1).columns(True) == ["2", "1", "50 %", "0/0"]  # no solve
    assert CellStats(("a",), 2, 1).columns(True) == ["2", "1", "50 %", "-"]  # not recorded
    assert CellStats(("a",), 0).columns(False) == ["0", "0", "-"]
    from hmpc_cli.sweep.table import _pooled

    counts = {"charged_solves": "9", "late_solves": "2", "dropped_solves": "0",
              "preempted_solves": "1"}
    assert _pooled(counts) == [9, 2, 0, 1] and _pooled({**counts, "late_solves": 2}) == [9, 2, 0, 1]
    assert _pooled({**counts, "late_solves": "two"}) is None  # an edited table: not counted
    assert _pooled({}) is None


@pytest.mark.parametrize("case", ["another scenario", "no base_scenario.toml"])
def test_a_table_of_another_or_an_unknown_scenario_counts_for_nothing(tiny, case):
    base, path, out, _ = tiny
    committed = _as_committed(out, base / f"other-{case.replace(' ', '-')}")
    side = committed / "base_scenario.toml"
    if case == "no base_scenario.toml":
        side.unlink()
    else:
        text = side.read_text()
        assert "rate_hz = 10\n" in text
        side.write_text(text.replace("rate_hz = 10\n", "rate_hz = 20\n", 1))
    proc = sweep([str(path), "--workers", "1", "--out", str(committed), "--seeds", "1"],
                 base)
    assert proc.returncode == 0, proc.stderr
    assert "0 skipped (already done), 6 to run" in proc.stdout
    assert {r["seed"] for r in table(committed)} == {"0"}  # the untrusted rows are gone


def test_a_tabled_run_takes_its_labels_from_the_plan_and_a_bom_keeps_its_rows(tiny):
    """A label renamed in the sweep file (same overrides, so the same run ids) renames the
    committed rows' cell; a results.csv re-saved with a byte-order mark still counts."""
    base, path, out, _ = tiny
    committed = _as_committed(out, base / "relabelled")
    (committed / "results.csv").write_bytes(b"\xef\xbb\xbf" + (out / "results.csv").read_bytes())
    renamed = write_sweep(base, TINY.replace('label = "ok"', 'label = "fine"'), "renamed.toml")
    proc = sweep([str(renamed), "--workers", "1", "--out", str(committed)], base)
    assert proc.returncode == 0, proc.stderr
    assert "12 runs, 12 skipped (already done), 0 to run" in proc.stdout
    old = table(out)
    assert table(committed) == [{**r, "case": "fine" if r["case"] == "ok" else r["case"]}
                                for r in old]


def test_the_recorded_base_scenario_is_the_one_the_runs_were_planned_with(tmp_path):
    """A scenario file edited while the sweep runs: base_scenario.toml is the planned one,
    so a later clone does not take the old rows for runs of the edited file."""
    from hmpc_cli.sweep.table import BASE_SCENARIO, write_results

    scenario = tmp_path / "ball.toml"
    scenario.write_text(BALL.read_text())
    path = tmp_path / "s.toml"
    path.write_text('name = "s"\nscenario = "ball.toml"\n' + TINY_SET)
    plan = plan_sweep(path)
    scenario.write_text(BALL.read_text().replace("rate_hz = 10\n", "rate_hz = 20\n", 1))
    (tmp_path / "out").mkdir()
    write_results(plan, tmp_path / "out")
    recorded = (tmp_path / "out" / BASE_SCENARIO).read_text()
    assert recorded == plan.base_toml and "rate_hz = 10\n" in recorded
    assert plan_sweep(path).base_toml != recorded


@pytest.mark.slow
def test_dask_matches_local(tiny):
    import distributed  # in the `test` extra
    base, path, out, _ = tiny
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        proc = sweep([str(path), "--dask", cluster.scheduler_address, "--out",
                      str(base / "dask")], base)
    assert proc.returncode == 0, proc.stderr
    assert f"(Dask {cluster.scheduler_address})" in proc.stdout
    assert table(base / "dask") == table(out)


def test_dask_unreachable_exits_2_quickly(tmp_path):
    path = write_sweep(tmp_path, TINY)
    # a hang fails through the subprocess timeout, not a wall-clock assert
    proc = sweep([str(path), "--dask", "tcp://127.0.0.1:1", "--out", "out"], tmp_path,
                 timeout=60)
    assert proc.returncode == 2
    assert "error: --dask tcp://127.0.0.1:1: cannot connect" in proc.stderr
    assert "8787" not in proc.stderr  # the dashboard's port is no hint for port 1
    assert not (tmp_path / "out").exists()


def test_dask_not_installed_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ScenarioError) as exc:
        connect_dask("tcp://127.0.0.1:8786")
    assert exc.value.lines == ["--dask tcp://127.0.0.1:8786: the 'distributed' package is not "
                               "installed (pip install 'hmpc[dask]')"]


BAD = {
    "unknown key": ('[grid]\n"mpc.rate_hzz" = [10, 20]\n',
                    "sweep.toml: grid.mpc.rate_hzz: mpc.rate_hzz: unknown key "
                    "(did you mean 'rate_hz'?)"),
    "bad value": ('[grid]\nc = [{ label = "a" }, { label = "b", "mpc.rate_hz" = 7 }]\n',
                  "sweep.toml: grid.c[1]: mpc.rate_hz: 7 must divide mpc.nodes_per_second = 60 "
                  "and sim.rate_hz = 600 (the MPC period must be a whole number of node steps "
                  "and of simulator steps) (value 7)"),
    "bad type in [set]": ('[set]\n"planner.samples" = "many"\n',
                          "sweep.toml: [set]: planner.samples: Input should be a valid integer "
                          "(value \"many\")"),
    "empty axis": ('[grid]\n"mpc.rate_hz" = []\n',
                   "sweep.toml: grid.mpc.rate_hz: empty axis (no values)"),
    "missing scenario": ('scenario = "nope/ball.toml"\n',
                         "sweep.toml: scenario: file not found: nope/ball.toml"),
    "itself as its scenario": ('scenario = "sweep.toml"\nseeds = 1\n[set]\n"sim.duration" = 0.2\n',
                               "sweep.toml: scenario: sweep.toml is a sweep file (this sweep "
                               "file itself), not a scenario: name the scenario file its runs "
                               "start from (one with system and mpc sections)"),
    "itself as its scenario, nothing else": ('scenario = "sweep.toml"\n',
                                             "sweep.toml: scenario: sweep.toml is a sweep file "
                                             "(this sweep file itself), not a scenario: name "
                                             "the scenario file its runs start from (one with "
                                             "system and mpc sections)"),
    "a directory as its scenario": ('scenario = "."\n',
                                    "sweep.toml: scenario: . is a directory, not a scenario "
                                    "file"),
    "a key path through a value, an axis": (
        '[grid]\n"sim.duration.x" = [1, 2]\n',
        "sweep.toml: grid.sim.duration.x: sim.duration.x: sim.duration is a value (3.0), not a "
        "table, so sim.duration.x names no key: set sim.duration itself"),
    "a key path through a value, [set]": (
        '[set]\n"sim.duration.x" = 1\n',
        "sweep.toml: [set]: sim.duration.x: sim.duration is a value (3.0), not a table, so "
        "sim.duration.x names no key: set sim.duration itself"),
    "a section given as a number": ('set = 5\n',
                                    "sweep.toml: set: must be a table of settings, not 5: write "
                                    "[set] with its keys below it, or set = {key = value, ...}"),
    "unknown key in a table entry": (
        '[grid]\nc = [{ label = "a", "mpc.rate_hz" = 10 }, { label = "b", '
        '"replaning.policy" = "once" }]\n',
        "sweep.toml: grid.c[1]: replaning: unknown key (did you mean 'replanning'?)"),
    "unknown sweep key": ('seed = 3\n',
                         "sweep.toml: seed: unknown key (did you mean 'seeds'?)"),
    "one value written twice": ('[set]\n"disturbance.kind" = "box"\n[grid]\n'
                                '"disturbance.magnitude" = [15, 15.0]\n',
                                "sweep.toml: grid: cells [15] and [15.0] run the same scenario "
                                "(a value written two ways, e.g. 15 and 15.0, or one the "
                                "scenario already has): keep one"),
    "one key written two ways in [grid]": (
        '[grid]\n"mpc.rate_hz" = [10, 20]\n[grid.mpc]\nrate_hz = [30, 60]\n',
        'sweep.toml: grid.mpc.rate_hz: written two ways, "mpc.rate_hz" and mpc.rate_hz (the '
        'same key): keep one'),
    "one key written two ways in [set]": (
        '[set]\n"mpc.rate_hz" = 30\n[set.mpc]\nrate_hz = 60\n',
        'sweep.toml: set.mpc.rate_hz: written two ways, "mpc.rate_hz" and mpc.rate_hz (the '
        'same key): keep one'),
    "one key written two ways in an axis entry": (
        '[grid]\nc = [{ label = "a", "mpc.rate_hz" = 30, mpc = { rate_hz = 60 } }]\n',
        'sweep.toml: grid.c[0].mpc.rate_hz: written two ways, "mpc.rate_hz" and mpc.rate_hz '
        '(the same key): keep one'),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_sweep_exits_2_and_creates_nothing(tmp_path, case):
    text, line = BAD[case]
    head = 'name = "bad"\n' + ("" if "scenario =" in text else 'scenario = "{scenario}"\n')
    write_sweep(tmp_path, head + text)
    proc = sweep(["sweep.toml", "--out", "out"], tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.splitlines() == [f"error: {line}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sweep.toml"]
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize("where", ["after the table", "while printing the cells"])
def test_a_stop_after_the_sweeps_runs_ended_says_they_are_all_done(tmp_path, monkeypatch,
                                                                     invoke_hmpc, where):
    """A SIGTERM after the last run's row was written said only "interrupted (SIGTERM)":
    nothing told the user the table was complete (a resume ran nothing)."""
    import hmpc_cli.cli.sweep as cli_sweep

    write_sweep(tmp_path, 'name = "one"\nscenario = "{scenario}"\nseeds = 1\n' + TINY_SET)
    stage = "_locked_execute" if where == "after the table" else "_print_cells"
    real = getattr(cli_sweep, stage)

    def then_stopped(*args, **kwargs):
        real(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(cli_sweep, stage, then_stopped)
    proc = invoke_hmpc(["sweep", "sweep.toml", "--out", "out"], tmp_path)
    when = "" if where == "after the table" else " after the sweep's runs ended"
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.splitlines() == [
        f"interrupted (SIGINT){when}: all 1 run done; the table: out/results.csv"]
    assert len(table(Path(tmp_path / "out"))) == 1


def test_a_scenario_path_relative_to_the_wrong_directory_says_how_to_name_it(tmp_path):
    """A sweep file elsewhere naming a scenario relative to the current directory: the
    error said only 'file not found: sweeps/ball.toml' (read from the sweep's directory)."""
    (tmp_path / "sweeps").mkdir()
    (tmp_path / "ball.toml").write_text(BALL.read_text())
    (tmp_path / "sweeps" / "s.toml").write_text('name = "s"\nscenario = "ball.toml"\n')
    proc = sweep(["sweeps/s.toml", "--out", "out"], tmp_path)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert proc.stderr.splitlines() == [
        "error: sweeps/s.toml: scenario: file not found: sweeps/ball.toml (a relative "
        "scenario is read from the sweep file's directory, sweeps; ball.toml is in the "
        "current directory: name it '../ball.toml')"]


def test_run_ids_are_stable_hashes_of_overrides_and_seed(tmp_path):
    a = write_sweep(tmp_path, 'name = "a"\nscenario = "{scenario}"\nseeds = [1, 0]\n[set]\n'
                    'sim.duration = 0.5\n[grid]\n"mpc.rate_hz" = [10, 20]\n'
                    'd = [{ label = "x", "disturbance.kind" = "none" }]\n', "a.toml")
    b = write_sweep(tmp_path, 'seeds = [0, 1]\nname = "b"\nscenario = "{scenario}"\n[grid]\n'
                    'd = [{ "disturbance.kind" = "none", label = "y" }]\n'
                    'mpc = { rate_hz = [20, 10] }\n[set]\n"sim.duration" = 0.5\n', "b.toml")
    ra, rb = plan_sweep(a).runs, plan_sweep(b).runs
    assert len(ra) == 4 and sorted(r.run_id for r in ra) == sorted(r.run_id for r in rb)
    ov = {"disturbance.kind": "none", "mpc.rate_hz": 10, "sim.duration": 0.5}
    assert ra[0].overrides == ov and ra[0].seed == 1 and ra[0].run_id == run_id(ov, 1)
    assert len(run_id(ov, 1)) == 10 and run_id(ov, 1) != run_id(ov, 0)


def test_fig3_expands_to_33_valid_runs(tmp_path):
    proc = sweep([str(REPO / "sweeps" / "fig3.toml"), "--dry-run"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[-1] == "33 runs, all valid (dry run: nothing started)"
    assert len(set(lines[:-1])) == 33 and not list(tmp_path.iterdir())
    plan = plan_sweep(REPO / "sweeps" / "fig3.toml")
    cells = {r.cell: r for r in plan.runs}
    assert len(cells) == 33 and {r.seed for r in plan.runs} == {0}
    assert cells[("10 Hz replan", "trial 7")].overrides == {
        "disturbance.kind": "paper_fig3", "disturbance.trial": 7, "mpc.rate_hz": 10,
        "replanning.policy": "on_contact"}
    assert cells[("20 Hz fixed", "nominal")].overrides == {
        "disturbance.kind": "none", "mpc.rate_hz": 20, "replanning.policy": "once"}
    assert 'rate_hz = 20' in cells[("20 Hz fixed", "nominal")].toml
    fast = plan_sweep(REPO / "sweeps" / "fig3_100hz.toml")
    assert len(fast.runs) == 11 and all(r.overrides["mpc.nodes_per_second"] == 100
                                        and r.overrides["mpc.rate_hz"] == 100
                                        for r in fast.runs)


@pytest.mark.parametrize("name", ["robustness_moved_tube", "biped_push", "robustness_realtime"])
def test_each_runs_scenario_is_the_one_loaded_for_it_alone(name):
    """A cell's scenario is validated once for all its seeds: every run's recorded TOML is
    still what loading the scenario with that run's overrides and seed gives."""
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.sweep.table import toml_value

    plan = plan_sweep(REPO / "sweeps" / f"{name}.toml")
    by_cell = {}
    for run in plan.runs:
        by_cell.setdefault(run.cell, []).append(run)
    picked = [r for runs in by_cell.values() for r in (runs[0], runs[-1])][:40]
    assert len({r.seed for r in picked}) > 1
    for run in picked:
        items = [f"{k}={toml_value(v)}" for k, v in run.overrides.items()]
        assert run.toml == load_scenario(plan.scenario, items, run.seed,
                                         attribute_sets=False)[1], run.cell
        assert f"seed = {run.seed}\n" in run.toml


@pytest.mark.slow
def test_ctrl_c_stops_cleanly_and_resumes(tmp_path):
    path = write_sweep(tmp_path, 'name = "stop"\nscenario = "{scenario}"\nseeds = 4\n'
                       + TINY_SET.replace("0.3", "0.6"))
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-c", REGISTER, "sweep", str(path), "--workers", "2", "--out",
         str(out)], cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not list(out.glob("runs/*/summary.json")):
            time.sleep(0.05)
        os.killpg(proc.pid, signal.SIGINT)  # a terminal's Ctrl-C: the whole process group
        _, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, stderr
    assert "interrupted:" in stderr and "Traceback" not in stderr
    assert _group_gone(proc.pid), "no worker process left behind"
    done = len(table(out))
    assert 1 <= done < 4
    again = sweep([str(path), "--workers", "2", "--out", str(out)], tmp_path)
    assert again.returncode == 0, again.stderr
    assert f"4 runs, {done} skipped (already done), {4 - done} to run" in again.stdout
    assert len(table(out)) == 4


def _group_gone(pgid: int, wait: float = 10.0) -> bool:
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        time.sleep(0.1)
    return False


def test_cli_sweep_imports_stay_light():
    tree = ast.parse((REPO / "hmpc_cli" / "cli" / "sweep.py").read_text())
    top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    names = {a.name for n in top for a in n.names} | {n.module for n in top
                                                       if isinstance(n, ast.ImportFrom)}
    assert names <= {"__future__", "annotations", "pathlib", "Path", "typing", "Annotated",
                     "NoReturn", "Optional", "typer"}
    assert not any("click" in ast.unparse(n) for n in ast.walk(tree)
                   if isinstance(n, (ast.Import, ast.ImportFrom)))
    code = ("import sys; import hmpc_cli.cli.sweep; print(sorted(m for m in ('casadi', 'numpy', "
            "'hmpc_cli.sweep.plan', 'hmpc_cli.run.loop', 'hmpc_cli.run.runner') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=REPO, check=True).stdout
    assert out.strip() == "[]"


def test_a_run_of_an_older_hmpc_stays_finished_unless_a_value_changed(tmp_path):
    """A setting added since a run (absent from its scenario.toml) takes its default: the
    run stays finished, so a sweep resumes across an upgrade; a changed value does not."""
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.sweep.table import finished_in, same_scenario

    _, text = load_scenario(REPO / "scenarios" / "ball.toml")
    older = "".join(line + "\n" for line in text.splitlines()
                    if not line.startswith("node_shift"))  # written before mpc.node_shift
    assert older != text and same_scenario(older, text)
    changed = older.replace("rate_hz = 10\n", "rate_hz = 20\n")  # the MPC rate
    assert changed != older and not same_scenario(changed, text)
    assert not same_scenario("not = [toml", text)
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.json").write_text('{"success": true, "reason": "success"}')
    (run / "scenario.toml").write_text(older)
    from conftest import write_finished_log

    write_finished_log(run)
    assert finished_in(run, text) == {"success": True, "reason": "success"}
    (run / "scenario.toml").write_text(changed)
    assert finished_in(run, text) is None


def test_an_interrupted_seeds_selection_counts_only_its_own_finished_runs(tmp_path,
                                                                           monkeypatch):
    """``--seeds 1`` stopped before its runs finish: 0 of its runs are done, though the
    table holds the other seeds' finished rows (it said "2 of 2 runs done")."""
    from conftest import write_finished_log

    from hmpc_cli.sweep import execute
    from hmpc_cli.sweep.plan import first_seeds

    path = write_sweep(tmp_path, 'name = "part"\nscenario = "{scenario}"\nseeds = [0, 1]\n'
                       '[grid]\n"mpc.rate_hz" = [20, 10]\n')
    plan = first_seeds(plan_sweep(path), 1)
    out = tmp_path / "out"
    for run in (r for r in plan.runs if r not in plan.selected):  # seed 1's runs finished
        d = out / "runs" / run.run_id
        d.mkdir(parents=True)
        (d / "scenario.toml").write_text(run.toml, encoding="utf-8")
        (d / "summary.json").write_text(json.dumps({"success": True, "reason": ""}))
        write_finished_log(d)

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(execute, "run_one", stopped)
    outcome = execute.execute_sweep(plan, out)
    assert (outcome.interrupted, outcome.done, outcome.total) == (True, 0, 2)
    assert len(table(out)) == 2  # the table keeps the other seed's rows


def test_results_rows_are_in_grid_order_not_completion_order(tmp_path):
    from conftest import write_finished_log

    from hmpc_cli.sweep.table import write_results

    path = write_sweep(tmp_path, 'name = "order"\nscenario = "{scenario}"\nseeds = [2, 0, 1]\n'
                       '[grid]\n"mpc.rate_hz" = [20, 10]\ncase = [{ label = "b" }, '
                       '{ label = "a", "lowlevel.kp" = 1.0 }]\n')
    plan = plan_sweep(path)
    out = tmp_path / "out"
    for run in reversed(plan.runs):  # the last run of the plan finishes first
        d = out / "runs" / run.run_id
        d.mkdir(parents=True)
        (d / "scenario.toml").write_text(run.toml, encoding="utf-8")
        (d / "summary.json").write_text(json.dumps({"success": True, "reason": ""}))
        write_finished_log(d)
        time.sleep(0.001)
    assert len(write_results(plan, out)) == 12
    rows = table(out)
    assert [(r["mpc.rate_hz"], r["case"], r["seed"]) for r in rows] == [
        (rate, case, seed) for rate in ("20", "10") for case in ("b", "a")
        for seed in ("0", "1", "2")]


@pytest.mark.parametrize("case, message", [
    ("directory", "is a directory, not a sweep file"),
    ("fifo", "not a regular file"),
    ("deep", "tables or arrays nested too deeply (more than 32 levels)"),
    ("binary", "not a UTF-8 text file"),
])
def test_a_sweep_file_that_cannot_be_read_is_one_line(tmp_path, case, message):
    """The sweep file's reader is the scenario file's: same checks, same messages."""
    path = tmp_path / "s.toml"
    if case == "directory":
        path.mkdir()
    elif case == "fifo":
        os.mkfifo(path)  # reading it would block: refused before it is opened
    elif case == "deep":
        path.write_text('name = "s"\na = ' + "[" * 100 + "1" + "]" * 100 + "\n")
    else:
        path.write_bytes(b"name = \xff\xfe\n")
    with pytest.raises(ScenarioError) as err:
        plan_sweep(path)
    assert err.value.lines == [f"{path}: {message}"]


def test_show_prints_one_rows_scenario_and_hmpc_run_gives_the_row_back(tmp_path, run_hmpc):
    """hmpc sweep SWEEP --show RUN_ID: the run's effective scenario, which hmpc run takes
    (no warning) and which gives the committed row back (the real-time iterations at
    10 Hz, modelled latency, Figure 3 trial 5); an unknown id names the closest."""
    repo = Path(__file__).resolve().parents[1]
    sweep_file = repo / "sweeps" / "realtime_rti.toml"
    shown = run_hmpc(["sweep", str(sweep_file), "--show", "bf0f30da1f"], cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    (run,) = [r for r in plan_sweep(sweep_file).runs if r.run_id == "bf0f30da1f"]
    planned, printed = tomllib.loads(run.toml), tomllib.loads(shown.stdout)
    assert planned["disturbance"].pop("hold") == 0.05  # paper_fig3 ignores it: left out
    assert printed == planned and not shown.stderr
    first = shown.stdout.splitlines()[0]  # the description is the scenario file's: says so
    assert first.startswith(f"# run bf0f30da1f of {sweep_file}: latency=") and \
        "disturbance=trial 5, seed 0; its description is the scenario file's, which the " \
        "sweep's settings below change" in first, first
    (tmp_path / "row.toml").write_text(shown.stdout)
    again = run_hmpc(["run", "row.toml", "--out", "row", "-q"], cwd=tmp_path)
    assert again.returncode == 0 and again.stderr == "", again.stderr
    with open(repo / "results" / "sweeps" / "realtime_rti" / "results.csv", newline="") as f:
        (row,) = [r for r in csv.DictReader(f) if r["run_id"] == "bf0f30da1f"]
    summary = json.loads((tmp_path / "row" / "summary.json").read_text())
    assert (row["success"], row["final_error"], row["contacts"], row["solves"]) == (
        "true", repr(summary["final_error"]), str(summary["contacts"]),
        str(summary["solves"])) and summary["success"] is True
    wrong = run_hmpc(["sweep", str(sweep_file), "--show", "bf0f30da1e"], cwd=tmp_path)
    assert wrong.returncode == 2 and wrong.stderr == (
        f"error: --show bf0f30da1e: no run of {sweep_file} has this id (did you mean "
        f"'bf0f30da1f'? `hmpc sweep {sweep_file} --dry-run` lists its 264 runs)\n")


def test_a_sweep_names_the_settings_its_cells_ignore(tmp_path, monkeypatch):
    """An axis over a setting another setting switches off would run the same runs again:
    the sweep names it, once per reason with the cells it holds for, on stderr before any
    run; cells that read it are not named."""
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app

    shutil.copy(BALL, tmp_path / "ball.toml")
    write_sweep(tmp_path, 'name = "ignored"\nscenario = "ball.toml"\nseeds = 1\n[grid]\n'
                '"replanning.policy" = ["once", "periodic"]\n'
                '"replanning.period" = [0.1, 0.2]\n')
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["sweep", "sweep.toml", "--dry-run"])
    assert res.exit_code == 0, res.output
    assert [line for line in res.stderr.splitlines() if line.startswith("warning")] == [
        "warning: sweep.toml: cell replanning.policy=once, replanning.period=0.1 (and 1 other "
        'cell): replanning.period: no effect with replanning.policy = "once" (only '
        '"periodic" replans on a period)']
    assert "4 runs, all valid" in res.stdout


@pytest.mark.parametrize("magnitudes", ["[15.0, 30.0]", "[30.0, 15.0]"])
def test_a_cell_whose_own_tube_does_not_fit_is_a_warning_in_either_axis_order(tmp_path,
                                                                              magnitudes):
    """With mpc.margins = "tube", a cell whose rate's tube is too wide is a finding of the
    study (its runs recorded as refused). It was an error (exit 2) when its cell came
    first and a failed run when another disturbance came first: the check of a cell was
    shared by cells with the same system and MPC, which the tube's margins outgrow."""
    from hmpc_cli.cli.sweep import cell_checks

    path = write_sweep(tmp_path, 'name = "tube"\nscenario = "{scenario}"\n[set]\n'
                       '"disturbance.kind" = "box"\n"mpc.nodes_per_second" = 100\n'
                       '"mpc.margins" = "tube"\n[grid]\n"mpc.rate_hz" = [5]\n'
                       f'"disturbance.magnitude" = {magnitudes}\n')
    problems, warnings = cell_checks(plan_sweep(path))
    assert problems == []
    assert warnings == [
        f"{path}: cell mpc.rate_hz=5, disturbance.magnitude=30.0: mpc.margins: the tube's "
        "margins at 5 Hz do not fit: at 5 Hz the tightened guard-avoid row of floor (kappa = "
        "0.9878) exceeds its NLP gap at x0 (0.9): the tightened problem is infeasible at the "
        "initial state (its runs are recorded as refused)"]


def test_a_sweep_file_without_a_name_resumes_in_its_directory(tmp_path):
    """A sweep named by its file's stem (no ``name``): its stored sweep.toml names it, so
    the same command resumes (it said 'belongs to sweep None'); another sweep is refused."""
    path = write_sweep(tmp_path, 'scenario = "{scenario}"\nseeds = 1\n[set]\n'
                       '"sim.duration" = 0.2\n', name="noname.toml")
    args = [str(path), "--workers", "1", "--out", "out"]
    first = sweep(args, tmp_path)
    assert first.returncode == 0, first.stderr
    assert (tmp_path / "out" / "sweep.toml").read_text() == (
        f'name = "noname"  # hmpc sweep: the file\'s stem\n{path.read_text()}')
    again = sweep(args, tmp_path)
    assert again.returncode == 0, again.stderr
    assert "noname: 1 runs, 1 skipped (already done), 0 to run" in again.stdout
    other = write_sweep(tmp_path, path.read_text(), name="other.toml")
    refused = sweep([str(other), "--out", "out", "--dry-run"], tmp_path)
    assert refused.returncode == 2
    assert refused.stderr.splitlines() == [
        "error: --out out: belongs to sweep 'noname' (its sweep.toml), not 'other': choose "
        "another --out (the same sweep resumes in its own directory)"]
    # a directory an older hmpc wrote (its sweep.toml the file's text, no name): resumes
    (tmp_path / "out" / "sweep.toml").write_text(path.read_text())
    older = sweep(args, tmp_path)
    assert older.returncode == 0, older.stderr
    assert "noname: 1 runs, 1 skipped (already done), 0 to run" in older.stdout
    (tmp_path / "out" / "sweep.toml").write_text(path.read_text() + "# edited\n")
    edited = sweep([*args, "--dry-run"], tmp_path)
    assert edited.returncode == 2 and edited.stderr.splitlines() == [
        "error: --out out: its sweep.toml names no sweep and is not this sweep file: choose "
        "another --out (the same sweep resumes in its own directory)"]
