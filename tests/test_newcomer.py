"""What a newcomer meets first: quiet output, full contact counts, the paper's column only
for the paper's setting, and a results page without any machine's absolute paths."""

from __future__ import annotations

import json
import re
import subprocess

import pytest
from typer.testing import CliRunner

from conftest import BALL, REPO, cli_env, hmpc_command

SHORT = ["--set", "sim.duration=0.3", "--set", "planner.iterations=3"]


# ------------------------------------------------------------- 3: -q is errors and the path
@pytest.fixture(scope="module")
def quiet_run(tmp_path_factory):
    """``hmpc run ball.toml -q`` (short) in a fresh process: (run directory, process)."""
    base = tmp_path_factory.mktemp("quiet")
    out = base / "run"
    proc = subprocess.run([*hmpc_command(), "run", str(BALL), "--out", str(out), "-q", *SHORT],
                          cwd=base, env=cli_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc


@pytest.mark.slow
def test_run_quiet_prints_only_the_log_path(quiet_run):
    out, proc = quiet_run
    assert proc.stdout == f"{out / 'run.mcap'}\n"
    assert proc.stderr == ""


def test_run_quiet_in_process_prints_only_the_log_path(tmp_path, monkeypatch):
    from hmpc_cli.cli.app import app

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "r"
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(out), "-q", *SHORT])
    assert res.exit_code == 0, res.output
    assert res.stdout.splitlines() == [str(out / "run.mcap")]  # no summary table


@pytest.mark.slow
def test_replay_export_quiet_prints_only_the_export_directory(quiet_run, tmp_path):
    from hmpc_cli.cli.app import app

    out, _ = quiet_run
    res = CliRunner().invoke(app, ["replay", str(out), "--export", str(tmp_path / "x"), "-q"],
                             env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert res.stdout.splitlines() == [str(tmp_path / "x")]
    assert (tmp_path / "x" / "info.json").is_file()
    loud = CliRunner().invoke(app, ["replay", str(out), "--export", str(tmp_path / "y")],
                              env={"COLUMNS": "200"})
    assert loud.exit_code == 0 and "summary" in loud.stdout and "timeline" in loud.stdout


def test_sweep_quiet_prints_only_the_results_path(tmp_path, monkeypatch):
    from hmpc_cli.cli.app import app

    monkeypatch.chdir(tmp_path)
    sweep = tmp_path / "s.toml"
    sweep.write_text(f'name = "s"\nscenario = "{BALL.as_posix()}"\n[set]\n'
                     '"sim.duration" = 0.1\n"planner.iterations" = 2\n')
    res = CliRunner().invoke(app, ["sweep", str(sweep), "--workers", "1", "--out",
                                   str(tmp_path / "o"), "-q"])
    assert res.exit_code == 0, res.output
    assert res.stdout.splitlines() == [str(tmp_path / "o" / "results.csv")]


# --------------------------------------------------- 4: every guard in summary.json's counts
@pytest.mark.slow
def test_summary_lists_every_guard_zeros_included(quiet_run):
    from hmpc_cli.log.reader import read_log

    out, _ = quiet_run
    summary = json.loads((out / "summary.json").read_text())
    counts = summary["contacts_by_guard"]
    assert list(counts) == ["floor", "wall", "circle_in", "circle_out"]
    assert 0 in counts.values()  # 0.3 s: the ball has not entered the circle
    assert sum(counts.values()) == summary["contacts"]
    (last,) = read_log(out / "run.mcap").topic("/run/summary")
    assert last.data["contacts_by_guard"] == counts  # summary.json as /run/summary


def test_run_log_counts_start_at_zero_for_every_guard():

    from hmpc_cli.log.books import RunBooks

    books = RunBooks("ball", 0, ("floor", "wall", "circle_in", "circle_out"))
    assert books.result.contacts_by_guard == {"floor": 0, "wall": 0, "circle_in": 0,
                                            "circle_out": 0}


# ------------------------------------------- 5: the paper's counts for the paper's setting only
def test_paper_geometry_is_the_balls_default():
    from hmpc_cli.figures.fig3 import PAPER_GEOMETRY
    from hmpc_cli.systems.ball import BallParams

    defaults = BallParams().model_dump(mode="json")
    assert {k: defaults[k] for k in PAPER_GEOMETRY} == PAPER_GEOMETRY


def test_not_the_paper_says_why():
    from hmpc_cli.figures.fig3 import not_the_paper

    ball = {"system": {"name": "ball", "circle_center": [3.0, 3.0], "radius": 0.1}}
    assert not_the_paper([ball, {"system": {"name": "ball"}}]) == ""
    assert not_the_paper([ball, {"system": {"name": "biped"}}]) == \
        "runs of system 'biped', not the paper's 'ball'"
    moved = {"system": {"name": "ball", "circle_center": [5.0, 3.0]}}
    assert not_the_paper([moved]) == \
        "system.circle_center = [5.0, 3.0], not the paper's [3.0, 3.0]"
    assert not_the_paper([{**ball, "plant": {"radius": 0.2}}]) == \
        "plant.radius = 0.2, not the paper's 0.1"


def test_paper_column_left_out_for_another_geometry(capsys):
    from hmpc_cli.cli.plot import _print_counts
    from hmpc_cli.figures.fig3 import REFERENCE_COUNTS, PanelCounts

    paper = {"10 Hz fixed": PanelCounts("10 Hz fixed", 11, 9)}
    _print_counts(paper, REFERENCE_COUNTS)
    assert "9/11" in capsys.readouterr().out
    why = "system.circle_center = [5.0, 3.0], not the paper's [3.0, 3.0]"
    moved = {"10 Hz fixed": PanelCounts("10 Hz fixed", 11, 7, not_paper=why)}
    _print_counts(moved, REFERENCE_COUNTS)
    out = " ".join(capsys.readouterr().out.split())
    assert "9/11" not in out and "paper column left out: system.circle_center" in out


# ----------------------------------------------------- 7: no absolute path on the results page
ABSOLUTE = re.compile(r"(?<![\w.])(/work/|/home/|/tmp/|/root/|/Users/)|[A-Za-z]:\\")


def test_committed_results_pages_hold_no_absolute_paths():
    pages = sorted((REPO / "results").rglob("*.md"))
    assert REPO / "results" / "README.md" in pages
    found = [f"{p.relative_to(REPO)}:{i}: {m.group(0)}" for p in pages
             for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), start=1)
             for m in ABSOLUTE.finditer(line)]
    assert found == []
    # the page regenerates from the repository alone: it names no path outside it either
    assert "<...>" not in (REPO / "results" / "README.md").read_text(encoding="utf-8")


def test_portable_paths(tmp_path):
    from hmpc_cli.report.paths import portable_command, portable_path, portable_text

    root = tmp_path / "repo"
    assert portable_path(root / "sweeps" / "a.toml", root) == "sweeps/a.toml"
    assert portable_path("/work/campaign/robustness", root) == "<...>/campaign/robustness"
    assert portable_path("results/x", root) == "results/x"
    assert portable_command(f"hmpc report --fig3 /work/runs/fig3 --biped scenarios/b.toml "
                            f"--results {root / 'results'}", root) == \
        "hmpc report --fig3 <...>/runs/fig3 --biped scenarios/b.toml --results results"
    assert portable_text("/home/me/x/results.csv:3: bad; /run/summary at 1/600 s", root) == \
        "<...>/x/results.csv:3: bad; /run/summary at 1/600 s"
    assert portable_text(r"C:\Users\me\runs\a.mcap: damaged", root) == \
        "<...>/runs/a.mcap: damaged"
