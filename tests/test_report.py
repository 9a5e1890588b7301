"""Robustness curves (Wilson intervals) and the results page (``hmpc report``)."""

from __future__ import annotations

import csv
import math
import shlex
from pathlib import Path

import pytest
from typer.testing import CliRunner

from conftest import BALL, REPO
from hmpc_cli.analysis.tables import FigureInputError
from hmpc_cli.figures.robustness import cells, robustness, wilson
from hmpc_cli.report.page import ReportInputs, write_report

COLUMNS = ["run_id", "seed", "mpc.rate_hz", "replanning.policy", "disturbance.magnitude",
           "success", "log"]
# (rate, policy, magnitude) -> successes out of 10 seeds
TRUTH = {(5, "once", 10.0): 3, (50, "once", 10.0): 10, (5, "on_contact", 10.0): 7,
         (50, "on_contact", 10.0): 10, (5, "once", 30.0): 0, (50, "once", 30.0): 2,
         (5, "on_contact", 30.0): 1, (50, "on_contact", 30.0): 5}


def write_study(path: Path, truth=TRUTH, seeds: int = 10) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(COLUMNS)
        for i, ((rate, policy, mag), k) in enumerate(truth.items()):
            for s in range(seeds):
                w.writerow([f"{i}-{s}", s, rate, policy, mag, "true" if s < k else "false", ""])
    return path


@pytest.mark.parametrize("k,n,lo,hi", [(0, 10, 0.0, 0.2775), (5, 10, 0.2366, 0.7634),
                                       (10, 10, 0.7225, 1.0), (1, 100, 0.0018, 0.0545)])
def test_wilson_interval_known_values(k, n, lo, hi):
    got = wilson(k, n)
    assert got == pytest.approx((lo, hi), abs=1e-4)


def test_wilson_interval_contains_the_estimate_and_shrinks_with_n():
    for n in (1, 7, 50, 400):
        for k in range(0, n + 1, max(1, n // 7)):
            lo, hi = wilson(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0
    assert (lambda a, b: a[1] - a[0] > b[1] - b[0])(wilson(5, 10), wilson(50, 100))


def test_cells_pool_seeds_per_rate_policy_and_magnitude(tmp_path):
    data = cells(write_study(tmp_path / "results.csv"), "mpc.rate_hz", "replanning.policy",
                 "disturbance.magnitude")
    assert len(data) == len(TRUTH)
    for c in data:
        assert c.runs == 10
        assert c.successes == TRUTH[(int(c.x), c.series, float(c.panel))]
    # panels in numeric order, rates ascending within a series
    assert [c.panel for c in data][:4] == ["10.0"] * 4
    assert [c.x for c in data if c.panel == "10.0" and c.series == "once"] == [5.0, 50.0]


def test_cells_follow_the_sweeps_grid_order_not_the_first_row(tmp_path):
    """A sweep's results.csv is sorted by run id: its series come in the grid's order."""
    truth = dict(reversed(list(TRUTH.items())))  # the first row is on_contact
    table = write_study(tmp_path / "sweep" / "results.csv", truth)
    order = lambda: list(dict.fromkeys(c.series for c in cells(  # noqa: E731
        table, "mpc.rate_hz", "replanning.policy", "disturbance.magnitude")))
    assert order() == ["on_contact", "once"]  # no sweep file: order of appearance
    (table.parent / "sweep.toml").write_text(
        'name = "s"\nscenario = "x.toml"\n[grid]\n"replanning.policy" = ["once", '
        '"on_contact"]\n"mpc.rate_hz" = [50, 5]\n')
    assert order() == ["once", "on_contact"]
    data = cells(table, "mpc.rate_hz", "replanning.policy", "disturbance.magnitude")
    assert [c.x for c in data if c.panel == "10.0" and c.series == "once"] == [5.0, 50.0]


def test_robustness_figure_is_deterministic_and_tabled(tmp_path):
    table = write_study(tmp_path / "results.csv")
    robustness(table, tmp_path / "a", "png,svg,pdf")
    robustness(table, tmp_path / "b", "png,svg,pdf")
    for name in ("robustness.png", "robustness.svg", "robustness.pdf", "robustness_table.csv"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    with open(tmp_path / "a" / "robustness_table.csv") as f:
        rows = list(csv.DictReader(f))
    row = next(r for r in rows if r["replanning.policy"] == "once" and r["mpc.rate_hz"] == "5"
               and r["disturbance.magnitude"] == "10.0")
    assert (row["runs"], row["successes"]) == ("10", "3")
    assert float(row["wilson95_lo"]) == pytest.approx(wilson(3, 10)[0], abs=1e-4)


def test_robustness_bad_tables_are_clear_errors(tmp_path):
    with pytest.raises(FigureInputError, match="no such table"):
        robustness(tmp_path / "missing.csv", tmp_path)
    (tmp_path / "run").mkdir()  # a run's directory given where a sweep's is expected
    (tmp_path / "run" / "run.mcap").write_bytes(b"")
    with pytest.raises(FigureInputError) as err:
        robustness(tmp_path / "run", tmp_path)
    assert str(err.value) == (
        f"{tmp_path / 'run'}: a run's directory, not a table: give a sweep's output "
        "directory or its results.csv (a run's figures: hmpc plot fig2, timing)")
    bad = tmp_path / "bad.csv"
    bad.write_text("run_id,success\n1,true\n")
    with pytest.raises(FigureInputError, match="missing column"):
        robustness(bad, tmp_path)
    nonnum = tmp_path / "nonnum.csv"
    nonnum.write_text(",".join(COLUMNS) + "\n1,0,fast,once,10.0,true,\n")
    with pytest.raises(FigureInputError, match="expected a number"):
        robustness(nonnum, tmp_path)
    assert not (tmp_path / "robustness.png").exists()


@pytest.mark.parametrize("column", ["set.disturbance.magnitude", None])
def test_plot_robustness_panels_follow_the_size_set_for_the_whole_sweep_or_are_one(
        tmp_path, column):
    """A study whose disturbance size is in its [set] (a set.* column) or in its scenario
    (no column) is drawn by the default command: panels by that column, else one panel."""
    from test_plot import make_app

    table = write_study(tmp_path / "study" / "results.csv",
                        {k: v for k, v in TRUTH.items() if k[2] == 10.0})
    text = table.read_text().replace("disturbance.magnitude", column or "size", 1)
    if column is None:
        text = "\n".join(",".join(c for i, c in enumerate(line.split(",")) if i != 4)
                         for line in text.splitlines()) + "\n"
    table.write_text(text)
    res = CliRunner().invoke(make_app(), ["plot", "robustness", str(table), "--out",
                                          str(tmp_path / "fig"), "--formats", "png"])
    assert res.exit_code == 0, res.output
    with open(tmp_path / "fig" / "robustness_table.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r[column or "panel"], r["replanning.policy"], r["mpc.rate_hz"], r["successes"])
            for r in rows] == [(("10.0" if column else "all runs"), p, x, str(TRUTH[
                (int(x), p, 10.0)])) for p in ("once", "on_contact") for x in ("5", "50")]


def test_plot_robustness_axes_follow_the_values_a_table_axis_gives(tmp_path):
    """A table whose rate and policy a table axis's entries set (``set.`` columns, as
    sweeps/fig3.toml's controllers do): the default command drew nothing ("missing
    column(s) mpc.rate_hz"); it draws them as the x axis and the series."""
    from test_plot import make_app

    table = write_study(tmp_path / "study" / "results.csv")
    header, rest = table.read_text().split("\n", 1)
    header = ",".join({"mpc.rate_hz": "set.mpc.rate_hz", "replanning.policy":
                       "set.replanning.policy"}.get(c, c) for c in header.split(","))
    table.write_text(header + "\n" + rest)
    res = CliRunner().invoke(make_app(), ["plot", "robustness", str(table), "--out",
                                          str(tmp_path / "fig"), "--formats", "svg"])
    assert res.exit_code == 0, res.output
    with open(tmp_path / "fig" / "robustness_table.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["disturbance.magnitude"], r["set.replanning.policy"], r["set.mpc.rate_hz"],
             r["successes"]) for r in rows] == [
        (str(m), p, x, str(TRUTH[(int(x), p, m)])) for m in (10.0, 30.0)
        for p in ("once", "on_contact") for x in ("5", "50")]
    svg = (tmp_path / "fig" / "robustness.svg").read_text()
    assert "MPC rate [Hz]" in svg and "set.mpc" not in svg  # labelled as the grid axis is


@pytest.mark.parametrize("kept", [80, 40])
def test_plot_robustness_warns_when_the_table_holds_fewer_runs_than_its_sweep_plans(
        tmp_path, kept):
    """An interrupted sweep's table was drawn without a word: its missing cells simply
    vanished from the figure."""
    from test_plot import make_app

    table = write_study(tmp_path / "study" / "results.csv")
    lines = table.read_text().splitlines()
    table.write_text("\n".join(lines[:1 + kept]) + "\n")
    (table.parent / "sweep.toml").write_text(
        'name = "s"\nscenario = "x.toml"\nseeds = 10\n[grid]\n"mpc.rate_hz" = [5, 50]\n'
        '"replanning.policy" = ["once", "on_contact"]\n'
        '"disturbance.magnitude" = [10.0, 30.0]\n')
    res = CliRunner().invoke(make_app(), ["plot", "robustness", str(table.parent), "--out",
                                          str(tmp_path / "fig"), "--formats", "png"])
    assert res.exit_code == 0, res.output
    warning = (f"warning: {table} holds {kept} of the 80 runs its sweep plans "
               f"({table.parent / 'sweep.toml'}): the figure shows those; `hmpc sweep` on "
               "the sweep file resumes the rest")
    assert res.stderr.splitlines() == ([] if kept == 80 else [warning])


def test_report_page_tables_the_study(tmp_path):
    write_study(tmp_path / "results" / "sweeps" / "robustness" / "results.csv")
    page = write_report(tmp_path / "results",
                        ReportInputs(None, None, tmp_path / "results" / "sweeps" / "robustness"),
                        "hmpc report")
    text = page.read_text()
    assert "![robustness](report/robustness.png)" in text
    assert (tmp_path / "results" / "report" / "robustness.png").is_file()
    lo, hi = wilson(3, 10)
    assert f"| ±10.0 | once | 3/10 ({100 * lo:.0f}-{100 * hi:.0f} %) |" in text
    # 50 Hz beats 5 Hz with separate intervals only where the data say so
    assert "±10.0, once: 50 Hz is higher than 5 Hz (100 % vs 30 %; intervals separate)" in text
    assert "±30.0, once: 50 Hz vs 5 Hz: 20 % vs 0 %, intervals overlap; trend" in text
    # 38 of the 80 runs succeed; seeds 0-2 at +-10 succeed in all four cells, seeds 5-9 at
    # +-30 fail in all four, the other 12 draws differ between cells
    assert "How the runs failed (each run's summary):\n\n- Failed runs: 42 of 80.\n" in text
    assert ("- The same disturbance draw (seed and size) in every rate and policy: succeeds "
            "in all its cells for 3 of 20 draws, fails in all for 5, differs between cells "
            "for 12.") in text


def test_failure_lines_say_how_failed_runs_ended():
    from hmpc_cli.report.robustness import failure_lines

    def row(seed, ok, err, fails, reason, rate):
        return {"seed": str(seed), "disturbance.magnitude": "15.0", "mpc.rate_hz": str(rate),
                "success": ok, "final_error": str(err), "solver_failures": str(fails),
                "reason": reason}

    rows = [row(0, "true", 0.05, 0, "success", 5), row(0, "false", 2.5, 7,
            "final error 2.500 > 0.6", 50), row(1, "false", 1.5, 3, "final error 1.500 > 0.6",
            5), row(1, "false", float("nan"), 11, "diverged: |x| 1e+07 > 1e6", 50)]
    assert failure_lines(rows, "disturbance.magnitude") == [
        "- Failed runs: 3 of 4; they end a median 2.00 m from the goal (successful runs: "
        "0.05 m; 1 failed run without a finite value); with a median 7 solver failures per "
        "run (successful runs: 0); reasons: `final error … > …` (2), `diverged: |x| … > …` "
        "(1).",
        "- The same disturbance draw (seed and size) in every rate and policy: succeeds in "
        "all its cells for 0 of 2 draws, fails in all for 1, differs between cells for 1."]
    assert failure_lines(rows[:1], "disturbance.magnitude") == ["- Failed runs: none of 1."]
    # a draw not yet run in every cell (a campaign under way) is left out; names keep
    # their digits; no successful run and no finite distance: said, never "nan"
    late = rows[1:] + [row(2, "false", float("nan"), 1, "guard wall2 at 1E-3 s", 5)]
    lines = failure_lines(late, "disturbance.magnitude")
    assert lines[0].startswith("- Failed runs: 4 of 4; they end a median 2.00 m from the "
                               "goal (2 failed runs without a finite value); with a median ")
    assert "`guard wall2 at … s` (1)" in lines[0] and "nan" not in "\n".join(lines)
    assert lines[1].endswith("all its cells for 0 of 1 draws, fails in all for 1, differs "
                             "between cells for 0.")  # seeds 0 and 2: one cell each
    lone = failure_lines([row(0, "false", float("nan"), 1, "d", 5)], "disturbance.magnitude")
    assert lone == ["- Failed runs: 1 of 1; they end a median n/a from the goal (1 failed run "
                    "without a finite value); with a median 1 solver failures per run; "
                    "reasons: `d` (1)."]
    # runs refused at set-up for their margins never ran: counted, left out of the numbers
    refused = row(2, "false", float("nan"), 0, "ValueError: mpc.margins: the tube's margins "
                  "at 5 Hz do not fit: ...", 5)
    assert failure_lines(rows + [refused, refused], "disturbance.magnitude")[0] == (
        "- Failed runs: 5 of 6 (2 never ran: margins refused at set-up; the numbers below are "
        "the 3 that ran); they end a median 2.00 m from the goal (successful runs: 0.05 m; 1 "
        "failed run without a finite value); with a median 7 solver failures per run "
        "(successful runs: 0); reasons: `final error … > …` (2), `diverged: |x| … > …` (1).")
    assert failure_lines([refused], "disturbance.magnitude")[0] == (
        "- Failed runs: 1 of 1 (1 never ran: margins refused at set-up).")


def test_the_wall_time_line_names_the_cpus_that_ran_the_runs():
    from hmpc_cli.report.robustness import wall_text

    rows = [{"wall_time": "2.0", "cpu": "AMD EPYC"}, {"wall_time": "4.0", "cpu": ""},
            {"wall_time": "3.0"}, {"wall_time": "3.0", "cpu": "AMD EPYC"},
            {"wall_time": "1.0", "cpu": "Intel(R) Xeon(R) Processor"}]
    assert wall_text(rows) == (
        "the runs took 0.0 core-hours (2.6 s per run on average; divide by the worker "
        "processes for the elapsed time); run on AMD EPYC (2 runs), Intel(R) Xeon(R) "
        "Processor (1 run), a CPU not recorded (2 runs)")
    # a table written before hmpc recorded the CPU says so: wall times compare on one CPU
    assert wall_text(rows[1:3]) == ("the runs took 0.0 core-hours (3.5 s per run on average; "
                                    "divide by the worker processes for the elapsed time); "
                                    "its CPU not recorded")
    assert wall_text([]) == "wall time not recorded"


def test_a_comparison_shows_the_digits_that_make_its_verdict_visible():
    """27/40 against 34/50 is lower, so the rates are not both printed as 68 %."""
    from hmpc_cli.figures.robustness import Cell
    from hmpc_cli.report.robustness import _compare

    def cell(k, n):
        return Cell("p", "s", 5.0, n, k)

    assert _compare(cell(27, 40), cell(34, 50), "100 Hz", "5 Hz") == (
        "100 Hz vs 5 Hz: 67.5 % vs 68.0 %, intervals overlap")  # no direction claimed
    assert _compare(cell(20, 40), cell(25, 50), "a", "b") == (
        "a vs b: 50 % vs 50 %, intervals overlap")
    assert _compare(cell(0, 40), cell(18, 50), "a", "b") == (
        "a is lower than b (0 % vs 36 %; intervals separate)")


def test_report_run_checks_the_runs_it_would_run_before_any(tmp_path, invoke_hmpc):
    """hmpc report --run applies hmpc sweep's set-up checks to the runs still missing: a
    cell the built system refuses stops it before any run and any page (exit 2)."""
    sweep = tmp_path / "bad_study.toml"
    sweep.write_text(f'name = "bad_study"\nscenario = "{BALL.as_posix()}"\nseeds = 1\n'
                     '[grid]\n"mpc.input_margin" = [0.0, 60.0]\n"mpc.rate_hz" = [10, 20]\n')
    res = tmp_path / "results"
    proc = invoke_hmpc(["report", "--run", "--results", str(res), "--fig3", "", "--fig3-extra", "",
                        "--fig3-reference", "", "--fig3-reference-extra", "", "--fig3-schedule",
                        "", "--biped", "", "--biped-push", "", "--fig3-trials", "", "--realtime",
                        "", "--robustness", str(sweep), "--workers", "1"], tmp_path)
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
    assert lines == [f"error: {sweep}: cell mpc.input_margin=60.0, mpc.rate_hz={f}: "
                     "mpc.input_margin: 60 per side exceeds half the input box of mode "
                     "'outside' input 0 ([-100, 0]: half-width 50; the MPC would keep no "
                     "input authority)" for f in (10, 20)]
    assert not (res / "README.md").exists() and not list(res.glob("sweeps/*/runs/*"))


@pytest.mark.slow
def test_report_command_runs_a_tiny_study_then_writes_the_page(tmp_path, invoke_hmpc):
    sweep = tmp_path / "tiny_study.toml"
    sweep.write_text(f"""name = "tiny_study"
scenario = "{BALL.as_posix()}"
seeds = 2
[set]
"disturbance.kind" = "box"
"sim.duration" = 0.3
"mpc.horizon" = 1.0
"planner.iterations" = 4
"planner.samples" = 10
"planner.knots" = 10
[grid]
"mpc.rate_hz" = [10, 20]
"replanning.policy" = ["once", "on_contact"]
"disturbance.magnitude" = [5.0]
""")
    res = tmp_path / "results"
    args = ["report", "--run", "--results", str(res), "--fig3", "", "--fig3-extra", "",
            "--fig3-reference", "", "--fig3-reference-extra", "", "--fig3-schedule", "",
            "--biped", "", "--biped-push", "", "--fig3-trials", "", "--realtime", "",
            "--robustness", str(sweep), "--workers", "1"]
    proc = invoke_hmpc(args, tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with open(res / "report" / "tiny_study_table.csv") as f:  # named after the sweep
        rows = list(csv.DictReader(f))
    assert len(rows) == 4 and all(r["runs"] == "2" for r in rows)
    page = (res / "README.md").read_text()
    assert "8 finished runs, 2 seeds" in page
    assert "![tiny_study](report/tiny_study.png)" in page
    # the tube diameter of the sweep's own scenario on the same rate axis (Step 5)
    assert "| ±5, trivial | " in page and "| tube | 10 Hz | 20 Hz |" in page
    from hmpc_cli.report.paths import portable_command, portable_path

    # no machine path on the page: paths relative to where the report ran
    assert f"Resume or complete: `hmpc sweep {portable_path(sweep, tmp_path)}`" in page
    assert str(tmp_path) not in page
    assert "### Reading" in page
    # rerun: every run is skipped (resume), the page is rewritten identically
    again = invoke_hmpc(args, tmp_path, timeout=600)
    assert again.returncode == 0 and "8 skipped" in again.stdout
    assert (res / "README.md").read_text() == page
    # how to regenerate it
    assert f"Generated by `{portable_command(shlex.join(['hmpc', *args]), tmp_path)}`" in page
    # a seed prefix runs nothing new and the table keeps every finished run (only the
    # command on the page's first line differs)
    prefix = invoke_hmpc(args + ["--seeds", "1"], tmp_path, timeout=600)
    assert prefix.returncode == 0 and "4 skipped" in prefix.stdout
    new = (res / "README.md").read_text()
    assert new.split("\n", 3)[3] == page.split("\n", 3)[3]


def test_report_without_results_is_a_clear_error(tmp_path, invoke_hmpc):
    proc = invoke_hmpc(["report", "--no-run", "--results", str(tmp_path / "r"),
                        "--fig3", str(REPO / "sweeps" / "fig3.toml"), "--fig3-extra", "",
                        "--fig3-reference", "", "--fig3-reference-extra", "",
                        "--fig3-schedule", "", "--robustness", "", "--biped", "",
                        "--biped-push", "", "--fig3-trials", "", "--realtime", ""], tmp_path)
    assert "no such table" in proc.stderr
    assert proc.returncode == 2
    assert "error:" in proc.stderr and "Traceback" not in proc.stderr
    bad = invoke_hmpc(["report", "--no-run", "--fig3", str(tmp_path / "nope.toml")], tmp_path)
    assert bad.returncode == 2 and "nope.toml" in bad.stderr


def test_every_default_robustness_sweep_is_bundled_and_valid():
    """`hmpc report --run`'s robustness sweeps exist, plan (every run's scenario is
    validated) and hold the study's grid: 5 rates x 2 policies (x sizes) x 100 seeds."""
    from hmpc_cli.cli.report import ROBUSTNESS
    from hmpc_cli.sweep.plan import plan_sweep

    for rel in ROBUSTNESS:
        plan = plan_sweep(REPO / rel)
        sizes = len({r.overrides.get("disturbance.magnitude") for r in plan.runs})
        assert len(plan.runs) == 5 * 2 * sizes * 100, rel
        assert {r.seed for r in plan.runs} == set(range(100)), rel


def test_first_seeds_is_a_resumable_prefix_of_the_study():
    from hmpc_cli.run.scenario import ScenarioError
    from hmpc_cli.sweep.plan import first_seeds, plan_sweep

    full = plan_sweep(REPO / "sweeps" / "robustness.toml")
    assert len(full.runs) == 5 * 2 * 2 * 100  # rates x policies x disturbance sizes x seeds
    part = first_seeds(full, 3)
    assert len(part.selected) == 5 * 2 * 2 * 3 and {r.seed for r in part.selected} == {0, 1, 2}
    assert part.runs == full.runs  # the results table still covers every finished run
    assert first_seeds(full, None) is full
    for bad in (0, 101):
        with pytest.raises(ScenarioError, match="the sweep has 100 seed"):
            first_seeds(full, bad)


def test_latency_study_sits_beside_its_paused_twin_and_the_reading_counts(tmp_path):
    """Three studies: paused, moved (another geometry), latency charged (the size fixed
    in [set]); the latency cells are compared with the paused twin only; counts exact."""
    from hmpc_cli.report.robustness import Study, robustness_sections

    def study(name: str, fixed: str, truth: dict, size_in_grid: bool = True) -> Path:
        d = tmp_path / name
        write_study(d / "results.csv", truth, seeds=20)
        if not size_in_grid:  # the size is the sweep's fixed setting: its set. column
            text = (d / "results.csv").read_text().replace(
                "disturbance.magnitude", "set.disturbance.magnitude", 1)
            (d / "results.csv").write_text(text)
        (d / "sweep.toml").write_text(f'name = "{name}"\nseeds = 20\n[set]\n{fixed}\n')
        return d

    paused = {(5, "once", 15.0): 2, (50, "once", 15.0): 20, (5, "on_contact", 15.0): 19,
              (50, "on_contact", 15.0): 20}
    moved = {(5, "once", 15.0): 10, (50, "once", 15.0): 12}
    charged = {(5, "once", 15.0): 2, (50, "once", 15.0): 3}
    dirs = [study("paper", '"disturbance.kind" = "box"', paused),
            study("moved", '"disturbance.kind" = "box"\n"system.circle_radius" = 0.6', moved),
            study("lat", '"disturbance.kind" = "box"\n"sim.latency" = 0.05\n'
                  '"disturbance.magnitude" = 15.0', charged, size_in_grid=False)]
    lines = robustness_sections([Study(d) for d in dirs], tmp_path / "fig", tmp_path)
    text = "\n".join(lines)
    assert ("- ±15.0, once: 50 Hz is higher than 5 Hz (100 % vs 10 %; intervals separate); "
            "trend across rates (Cochran-Armitage, scores log f): z = +5.72, p = 1.06e-08: "
            "success rises with the MPC rate at the 5 % level.") in text
    assert "- ±15.0, 5 Hz: on_contact is higher than once (95 % vs 10 %; intervals separate)." \
        in text
    assert "`lat` beside the same cells of `paper`. The first plan, too, reaches the plant " \
        "0.05 s after the state it was computed from" in text  # not the moved geometry
    assert ("- ±15.0, once, 50 Hz: 0.05 s latency is lower than time paused (15 % vs 100 %; "
            "intervals separate).") in text
    assert "- ±15.0, once, 5 Hz: 0.05 s latency vs time paused: 10 % vs 10 %, intervals " \
        "overlap." in text
    # paused series: paper once (up), paper on_contact (overlap), moved once (overlap)
    assert "in 1 of 3 series" in text and "in 0 less often; 2 unresolved" in text
    assert "better in 1 of 2 cells with separated intervals, worse in 0; 1 unresolved" in text
    assert "Solve time charged (0.05 s latency): 1 of 2 cells succeed less often" in text
    # the latency study's own rates: 5 Hz 2/20 vs 50 Hz 3/20 overlap; its solver's pace
    assert ("- Faster MPC (0.05 s latency charged): in 0 of 1 series (policy) the fastest "
            "rate succeeds more often than the slowest with separated intervals, in 0 less "
            "often; 1 unresolved") in text
    assert "rates above 1/L = 20 Hz solve at most 20 times a second." in text
    assert (" One solver at 0.05 s per solve runs at most 20 Hz: the 50 Hz cells solve at "
            "most that often, so their differences are not those of their nominal rates.") \
        in text  # the reading's rate line says which rates the pace holds
    for name in ("paper", "moved", "lat"):
        assert (tmp_path / "fig" / f"{name}.png").is_file()
        assert (tmp_path / "fig" / f"{name}_table.csv").is_file()


def test_a_charged_study_tables_its_solves_past_the_period_per_policy_and_rate(tmp_path):
    """From the table's real_time columns, every size and run pooled (a row without them
    left out); a study whose table has none gets no such table (exact)."""
    from hmpc_cli.report.robustness import Study, robustness_sections

    truth = {(5, "once", 15.0): 2, (50, "once", 15.0): 3, (50, "on_contact", 15.0): 4,
             (50, "on_contact", 5.0): 5}
    d = tmp_path / "lat"
    write_study(d / "results.csv", truth, seeds=2)
    (d / "sweep.toml").write_text('name = "lat"\nseeds = 2\n[set]\n"disturbance.kind" = '
                                  '"box"\n"sim.latency" = "model"\n')
    with open(d / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    counts = {("5", "once"): ("10", "0", "0", "0"), ("50", "once"): ("40", "3", "1", "0"),
              ("50", "on_contact"): ("30", "6", "0", "2")}
    with open(d / "results.csv", "w", newline="") as f:
        pooled = ("charged_solves", "late_solves", "dropped_solves", "preempted_solves")
        w = csv.DictWriter(f, [*rows[0], *pooled])
        w.writeheader()
        for i, r in enumerate(rows):
            c = counts[(r["mpc.rate_hz"], r["replanning.policy"])] if i else ("",) * 4
            w.writerow({**r, **dict(zip(pooled, c, strict=True))})
    text = "\n".join(robustness_sections([Study(d)], tmp_path / "fig", tmp_path))
    assert ("Solves that kept the one solver busy past the MPC period, so that the next "
            "period's solve waited (`late_solves` of `charged_solves`, every disturbance size "
            "and run that recorded them pooled, failed ones too; then the solves whose plans "
            "the budget dropped and those a contact stopped): a rate whose solves fit its "
            "period runs at that rate.\n\n| replanning | 5 Hz | 50 Hz |\n|---|---|---|\n"
            "| once | 0 % (0/10) | 8 % (6/80); 2 dropped |\n"
            "| on_contact | - | 20 % (24/120); 8 stopped |\n") in text  # row 0 left out
    write_study(d / "results.csv", truth, seeds=2)  # flown before hmpc recorded them
    text = "\n".join(robustness_sections([Study(d)], tmp_path / "fig", tmp_path))
    assert ("Solves past the MPC period: not in this table; its runs were flown before hmpc "
            "recorded `real_time`.") in text
    (d / "sweep.toml").write_text('name = "lat"\nseeds = 2\n[set]\n"disturbance.kind" = '
                                  '"box"\n')  # time paused: nothing to say
    text = "\n".join(robustness_sections([Study(d)], tmp_path / "fig", tmp_path))
    assert "past the MPC period" not in text


def test_latency_study_with_the_first_plan_paused_or_measured_latency_is_said(tmp_path):
    """sim.latency_first = "paused" still finds the twin and is said; "measured" reads as
    words; a latency study without a paused twin says so instead of vanishing."""
    from hmpc_cli.report.robustness import Study, robustness_sections

    truth = {(5, "once", 15.0): 2, (50, "once", 15.0): 20}

    def study(name: str, fixed: str) -> Path:
        d = tmp_path / name
        write_study(d / "results.csv", truth, seeds=20)
        (d / "sweep.toml").write_text(f'name = "{name}"\nseeds = 20\n[set]\n{fixed}\n')
        return d

    box = '"disturbance.kind" = "box"'
    dirs = [study("paper", box),
            study("first", f'{box}\n"sim.latency" = 0.03\n"sim.latency_first" = "paused"'),
            study("meas", f'{box}\n"sim.latency" = "measured"'),
            study("alone", '"disturbance.kind" = "box"\n"sim.latency" = 0.02\n'
                  '"system.circle_radius" = 0.6'),
            study("follow", f'{box}\n"sim.latency" = 0.05\n"sim.latency_first" = "paused"\n'
                  '"lowlevel.past_guard" = "next_domain"')]
    text = "\n".join(robustness_sections([Study(d) for d in dirs], tmp_path / "fig", tmp_path))
    assert "### 0.03 s latency charged vs time paused" in text
    assert ("`first` beside the same cells of `paper`. The first plan is computed with time "
            "paused at t = 0 (`sim.latency_first = \"paused\"`); every later plan is "
            "charged.") in text
    assert "### measured latency charged vs time paused" in text
    assert "reaches the plant its solve time after the state" in text
    assert "- ±15.0, once, 50 Hz: measured latency vs time paused: " in text
    assert ("### 0.02 s latency charged\n\n`alone`: no study on this page has its settings "
            "with time paused, so its cells are not compared.") in text
    assert "measured s" not in text
    # the low level past the guard does not keep a latency study from its paused twin
    assert ("`follow` beside the same cells of `paper`. The first plan is computed with time "
            "paused at t = 0 (`sim.latency_first = \"paused\"`); every later plan is charged. "
            "After an impact the low level follows the plan's next domain until the next plan "
            "arrives (`lowlevel.past_guard = \"next_domain\"`; the paused study holds the "
            "guard node, which differs only where an impact's re-solve fails).") in text
    assert ("- Solve time charged (0.05 s latency, first plan paused, low level following "
            "the plan): 0 of 2 cells") in text
    # one reading line per latency study, named by its latency and first plan
    assert "- Solve time charged (0.03 s latency, first plan paused): 0 of 2 cells" in text
    assert "- Solve time charged (measured latency): 0 of 2 cells" in text
    assert "rates above 1/L = 33.3 Hz solve at most 33.3 times a second." in text
    assert "- Faster MPC (0.03 s latency charged, first plan paused): in 1 of 1 series" in text
    # for `first` and `follow`; not for measured latency, not for `alone`
    assert text.count("rates above 1/L") == 2


def test_a_modelled_latency_study_pairs_with_the_paused_study_of_its_own_scenario(tmp_path):
    """``sim.latency = "model"`` reads as words, and the paused twin is the study of the
    same scenario file, not another controller's study with the same [set]."""
    from hmpc_cli.report.robustness import Study, robustness_sections

    def study(name: str, scenario: str, fixed: str, truth: dict) -> Path:
        d = tmp_path / name
        write_study(d / "results.csv", truth, seeds=20)
        (d / "sweep.toml").write_text(f'name = "{name}"\nscenario = "{scenario}"\n'
                                      f'seeds = 20\n[set]\n{fixed}\n')
        return d

    box = '"disturbance.kind" = "box"'
    dirs = [study("ipopt", "../scenarios/ball.toml", box,
                  {(5, "once", 15.0): 20, (60, "once", 15.0): 20}),
            study("rti", "../scenarios/ball_realtime.toml", box,
                  {(5, "once", 15.0): 4, (60, "once", 15.0): 20}),
            study("rti_model", "../scenarios/ball_realtime.toml",
                  f'{box}\n"sim.latency" = "model"', {(5, "once", 15.0): 3, (60, "once", 15.0): 9})]
    text = "\n".join(robustness_sections([Study(d) for d in dirs], tmp_path / "fig", tmp_path))
    assert "### modelled latency charged vs time paused" in text
    assert "`rti_model` beside the same cells of `rti`." in text
    assert "reaches the plant its modelled compute time after the state" in text
    # the first plan paused by the runs' scenario, not by the sweep's [set]: said so (the
    # first run's effective scenario, in its run directory)
    (dirs[2] / "runs" / "0-0").mkdir(parents=True)
    (dirs[2] / "runs" / "0-0" / "scenario.toml").write_text(
        (REPO / "scenarios" / "ball_realtime.toml").read_text())
    again = "\n".join(robustness_sections([Study(d) for d in dirs], tmp_path / "f2", tmp_path))
    assert ("`rti_model` beside the same cells of `rti`. The first plan is computed with time "
            "paused at t = 0") in again
    assert "- Solve time charged (modelled latency, first plan paused): 1 of 2 cells" in again
    assert ("- ±15.0, once, 60 Hz: modelled latency is lower than time paused (45 % vs 100 %; "
            "intervals separate).") in text
    assert "- Solve time charged (modelled latency): 1 of 2 cells succeed less often" in text
    assert "model s" not in text and "rates above 1/L" not in text


def test_report_with_a_missing_authors_directory_is_a_clear_error(tmp_path, invoke_hmpc):
    fig3 = write_study(tmp_path / "fig3" / "results.csv").parent  # a sweep's output
    proc = invoke_hmpc(["report", "--no-run", "--results", str(tmp_path / "r"),
                        "--fig3", str(fig3), "--fig3-extra", "", "--fig3-reference", "",
                        "--fig3-reference-extra", "", "--fig3-schedule", "", "--robustness", "",
                        "--biped", "", "--biped-push", "", "--fig3-trials", "", "--realtime", "",
                        "--authors",
                        str(tmp_path / "nowhere")], tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"error: --authors: {tmp_path / 'nowhere'}: no such directory"


def test_the_push_study_section_maps_where_the_walker_fails(tmp_path):
    """From a push sweep's results.csv alone: the table with intervals, the boundary per
    rate, the trends (counts exact; no log, so no Figure 4 is redrawn)."""
    from hmpc_cli.report.push import push_section

    truth = {(10, 0.0): 20, (10, 900.0): 20, (10, 1200.0): 9, (10, 1500.0): 0,
             (20, 0.0): 20, (20, 900.0): 20, (20, 1200.0): 14, (20, 1500.0): 3}
    d = tmp_path / "biped_push"
    d.mkdir()
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "seed", "disturbance.magnitude", "mpc.rate_hz", "success", "log"])
        for (rate, push), k in truth.items():
            for s in range(20):
                rid = f"{rate}-{push}-{s}"
                w.writerow([rid, s, push, rate, "true" if s < k else "false",
                            f"runs/{rid}/run.mcap"])
    text = "\n".join(push_section(d, tmp_path / "fig", tmp_path))
    assert (tmp_path / "fig" / "biped_push.png").is_file()
    lo, hi = wilson(9, 20)
    assert f"| ±1200 N | 9/20 ({100 * lo:.0f}-{100 * hi:.0f} %) |" in text
    assert ("- 10 Hz: every run walked up to ±900 N; the first failure at ±1200 N; none "
            "walked at ±1500 N.") in text
    assert "- 20 Hz: every run walked up to ±900 N; the first failure at ±1200 N." in text
    assert "- 10 Hz, across push sizes (scores: push [N]): z = -" in text
    assert "success falls with the push at the 5 % level." in text
    assert "- ±1500 N, across MPC rates (scores: log f): z = +" in text
    # the boundary run of 10 Hz: the largest push any seed walked through (1200 N, seed 0)
    assert ("Figure 4 at the boundary: a 10 Hz walk at the largest push size it walked "
            "through (±1200 N, seed 0, run 10-1200.0-0): its log is not here") in text
    assert "Counted once" not in text  # a table without final errors cannot tell


def test_the_push_study_counts_a_cell_of_one_repeated_run_once_and_says_how_runs_ended(
        tmp_path):
    """No push: every seed gives the same run (row for row alike), counted once in the
    table and the trends; the falls before the first touchdown, the solver failures and
    the successes' distance to the goal are counted over the distinct runs."""
    from hmpc_cli.report.push import push_section

    d = tmp_path / "biped_push"
    d.mkdir()
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "seed", "disturbance.magnitude", "mpc.rate_hz", "success",
                    "final_error", "contacts", "solves", "solver_failures", "reason", "log"])
        for s in range(4):  # no push: one run four times
            w.writerow([f"a{s}", s, 0.0, 10, "true", 0.0959, 8, 27, 0, "", ""])
        for s, (ok, err, contacts, fails) in enumerate([(True, 0.1, 8, 0), (True, 0.5, 9, 2),
                                                        (False, 2.0, 0, 1), (False, 1.5, 3, 0)]):
            w.writerow([f"b{s}", s, 900.0, 10, str(ok).lower(), err, contacts, 30, fails,
                        "" if ok else "fall", ""])
    text = "\n".join(push_section(d, tmp_path / "fig", tmp_path))
    assert "| ±0 N | 1/1 (21-100 %) |" in text and "| ±900 N | 2/4 (" in text
    assert ("Counted once: ±0 N at 10 Hz (its 4 seeds gave one run, row for row alike: no "
            "push, nothing for the seed to draw).") in text
    assert ("1 of the 2 failures fall before the first touchdown (no contact: in the first "
            "swing; 10 Hz 1 of 2).") in text
    assert "2 of the 5 runs had a solver failure (1 of the 3 successes)." in text
    assert ("the successes end a median 0.10 m from the goal (at most 0.50 m).") in text
    assert "z = " in text  # the trend across push sizes counts the unpushed run once


RESULTS = REPO / "results"


def _tracked(prefix: str) -> list[str]:
    """The repository's files under ``prefix`` as git holds them (what a fresh clone has)."""
    import subprocess

    out = subprocess.run(["git", "ls-files", "-z", prefix], cwd=REPO, capture_output=True,
                         check=True).stdout.decode()
    return sorted(p for p in out.split("\0") if p)


@pytest.mark.slow
def test_the_results_page_regenerates_from_what_the_repository_holds(tmp_path, run_hmpc):
    """results/README.md and every figure and table of results/report/, byte for byte, from
    the repository's files alone (sweep files, scenarios, the committed per-run tables, the
    trajectory logs of the runs the page draws, the authors' data): the page's own command,
    run again in a copy that holds nothing else."""
    import re
    import shutil

    page = (RESULTS / "README.md").read_text()
    command = re.search(r"Generated by `([^`]+)`", page).group(1)
    root = tmp_path / "repo"
    for rel in _tracked("sweeps") + _tracked("scenarios") + _tracked("results"):
        if not rel.startswith(("results/report/", "results/README.md")):
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, root / rel)
    args = shlex.split(command)
    assert args[:2] == ["hmpc", "report"] and "--run" not in args
    proc = run_hmpc(args[1:], cwd=root, timeout=900)  # about a minute on 2 idle cores
    assert proc.returncode == 0, proc.stderr
    out = root / "results"
    assert (out / "README.md").read_text() == page
    committed = [p.removeprefix("results/") for p in _tracked("results/report")]
    assert committed == sorted(str(p.relative_to(out)) for p in (out / "report").rglob("*")
                               if p.is_file())
    for rel in committed:
        assert (out / rel).read_bytes() == (RESULTS / rel).read_bytes(), rel


def test_figure_3_trial_by_trial_from_a_table_alone(tmp_path):
    """The reference rule's table: per controller, the counts, each side's failures, which
    of the authors' failures appear, and the verdict (exact)."""
    from hmpc_cli.report.fig3_trials import fig3_trials_section

    d = tmp_path / "fig3_rule"
    d.mkdir()
    (d / "sweep.toml").write_text('name = "fig3_rule"\ndescription = "rule"\n'
                                  '[set]\n"mpc.schedule_rule" = "reference"\n')
    trials = ["nominal", *(f"trial {k}" for k in range(1, 11))]
    failed = {"10 Hz fixed": {"trial 5"}, "100 Hz fixed": set(trials)}
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "controller", "disturbance", "seed", "success", "log"])
        for c in ("10 Hz fixed", "20 Hz fixed", "100 Hz fixed"):
            for t in trials:
                w.writerow([f"{c}-{t}", c, t, 0, str(t not in failed.get(c, ())).lower(), ""])
    text = "\n".join(fig3_trials_section(d))
    assert ("| 10 Hz fixed | 10/11 | 9/11 | trial 5, trial 7 | trial 5 | 1 of 2 (not: trial 7) |"
            in text)
    assert "| 20 Hz fixed | 11/11 | 11/11 | none | none | - |" in text
    assert "- 10 Hz fixed: not reproduced (10/11 vs the paper's 9/11; of the authors' 2 " \
        "failures 1 fail here)." in text
    assert "- 20 Hz fixed: count and failing trials reproduced (11/11 vs the paper's 11/11; of "\
        "the authors' 0 failures " \
        "0 fail here)." in text
    # 100 Hz is not in the paper: its count is the authors' data's, and said so
    assert "| 100 Hz fixed | 0/11 | - | trial 3, trial 4," in text
    assert "- 100 Hz fixed: not reproduced (0/11 vs the authors' data's (not in the paper) " \
        "4/11; of the authors' 7 failures 7 fail here, and 4 more)." in text
    # a partial table: the authors' count is still theirs, over their 11 runs
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "controller", "disturbance", "seed", "success", "log"])
        for t in trials[:5]:
            w.writerow([t, "100 Hz fixed", t, 0, "true", ""])
    assert "- 100 Hz fixed: not reproduced (5/5 vs the authors' data's (not in the paper) " \
        "4/11; of the authors' 7 failures 0 fail here)." in "\n".join(fig3_trials_section(d))


def test_the_authors_failures_are_their_data():
    """AUTHORS_FAILED against the authors' CSVs (committed in results/authors)."""
    from hmpc_cli.analysis.authors import end_distance, read_panels
    from hmpc_cli.report.fig3_trials import AUTHORS_FAILED

    ref = REPO / "results" / "authors"
    panels = read_panels(ref)
    assert {p: tuple(t for t, tr in trials.items() if end_distance(tr.xy) > 1.0)
            for p, trials in panels.items()} == AUTHORS_FAILED


def test_a_table_only_section_without_its_table_is_not_drawn(tmp_path):
    """A push or trial-by-trial sweep not run yet: its section says so; the page is written."""
    write_study(tmp_path / "results" / "sweeps" / "robustness" / "results.csv")
    page = write_report(tmp_path / "results", ReportInputs(
        None, None, tmp_path / "results" / "sweeps" / "robustness",
        biped_push=tmp_path / "results" / "sweeps" / "biped_push",
        fig3_trials=tmp_path / "results" / "sweeps" / "fig3_reference_rule"), "hmpc report")
    text = page.read_text()
    assert "## Figure 3 trial by trial\n\nNot drawn: " in text
    assert "## The biped under pushes that matter\n\nNot drawn: " in text
    assert "no such table" in text.split("## The biped under pushes that matter")[1]


def test_a_tube_margins_study_sits_beside_its_hand_margin_twin(tmp_path):
    """The tube study is paired with the study of the same settings but mpc.margins, cell by
    cell (tube | hand), separated cells named, and the reading counts (exact)."""
    from hmpc_cli.report.robustness import Study, robustness_sections

    def study(name: str, fixed: str, truth: dict) -> Path:
        d = tmp_path / name
        write_study(d / "results.csv", truth, seeds=20)
        (d / "sweep.toml").write_text(f'name = "{name}"\nseeds = 20\n[set]\n{fixed}\n')
        return d

    hand = {(5, "once", 15.0): 2, (50, "once", 15.0): 20}
    tube = {(5, "once", 15.0): 16, (50, "once", 15.0): 19}
    dirs = [study("hand", '"disturbance.kind" = "box"', hand),
            study("tube", '"disturbance.kind" = "box"\n"mpc.margins" = "tube"', tube)]
    text = "\n".join(robustness_sections([Study(d) for d in dirs], tmp_path / "fig", tmp_path))
    assert "### Each rate's tube margins vs one hand margin: `tube` beside `hand`" in text
    assert "| ±15.0 | once | 16/20 \\| 2/20 | 19/20 \\| 20/20 |" in text
    assert ("- ±15.0, once, 5 Hz: success with tube margins is higher than with the hand "
            "margin (80 % vs 10 %; intervals separate).") in text
    assert "50 Hz: tube margins" not in text  # 19/20 vs 20/20: intervals overlap
    assert ("- Each rate's tube margins vs one hand margin (`tube`): better in 1 of 2 cells "
            "with separated intervals, worse in 0; 1 unresolved.") in text


def test_the_real_time_section_from_a_table_alone(tmp_path):
    """Successes per controller and latency, and the measured runs' solve times (exact)."""
    from hmpc_cli.report.realtime import realtime_section

    d = tmp_path / "rt"
    d.mkdir()
    (d / "sweep.toml").write_text('name = "rt"\nscenario = "../scenarios/ball_realtime.toml"\n')
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "latency", "controller", "disturbance", "seed", "success",
                    "solves", "solve_time_median", "solve_time_p95", "wall_time", "log"])
        for k, (lat, ctrl, ok, n, med, p95) in enumerate([
                ("paused", "60 Hz once", "true", 180, 0.002, 0.010),
                ("measured", "60 Hz once", "true", 90, 0.003, 0.012),
                ("measured", "60 Hz once", "false", 40, 0.005, 0.020),
                ("measured", "20 Hz once", "true", 60, 0.001, "nan")]):
            w.writerow([k, lat, ctrl, "nominal", 0, ok, n, med, p95, 1.0, ""])
    text = "\n".join(realtime_section(d))
    # the solves of the successful runs against the time-paused twin's
    assert "(median; a successful run flies the scenario's whole duration)." in text
    assert "| 60 Hz once | 180 | 90 (50 %) |" in text and "| 20 Hz once | - | 60 |" in text
    assert ("- `measured`: as many solves as with time paused (at least 95 %) for 0 of the 1 "
            "controllers with successful runs both ways; fewer: 60 Hz once 50 %.") in text
    # a sweep the repository does not hold: its name, no path the reader cannot find
    assert "### `rt.toml`: rt\n\nFrom its per-run table (4 runs of " \
        "`scenarios/ball_realtime.toml`; " in text
    assert "| controller | paused | measured |" in text
    assert "| 60 Hz once | 1/1 | 1/2 |" in text and "| 20 Hz once | - | 1/1 |" in text
    assert "| 60 Hz once | 4.0 | 20.0 |" in text and "| 20 Hz once | 1.0 | - |" in text
    assert "machine: `results/bench/rt.md`" in text
    assert ("Solves past the MPC period: not in this table; the `measured` runs were flown "
            "before hmpc recorded `real_time`.") in text  # no such column
    with pytest.raises(FigureInputError, match="missing column"):
        (d / "results.csv").write_text("run_id,success\n1,true\n")
        realtime_section(d)


def test_the_real_time_section_pools_the_solves_busy_past_the_period(tmp_path):
    """late, dropped and stopped solves of the charged ones per controller and charged
    latency, every run of the cell pooled (failed ones too); a row flown before real_time
    was recorded is left out, a cell with none recorded is '-', a latency with none is
    named (exact)."""
    from hmpc_cli.report.realtime import realtime_section

    d = tmp_path / "rt"
    d.mkdir()
    (d / "sweep.toml").write_text('name = "rt"\nscenario = "../scenarios/ball.toml"\n')
    head = ["run_id", "latency", "controller", "seed", "success", "solves", "charged_solves",
            "late_solves", "dropped_solves", "preempted_solves", "log"]
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(head)
        for k, row in enumerate([("paused", "10 Hz", "true", 30, "", "", "", ""),
                                 ("model", "10 Hz", "true", 30, 30, 3, 0, 0),
                                 ("model", "10 Hz", "false", 12, 12, 9, 2, 1),
                                 ("model", "10 Hz", "true", 30, "", "", "", ""),  # before
                                 ("model", "60 Hz", "true", 100, 0, 0, 0, 0),
                                 ("measured", "60 Hz", "true", 90, "", "", "", ""),
                                 ("paused", "100 Hz", "true", 300, "", "", "", ""),
                                 ("model", "100 Hz", "true", 150, "", "", "", "")]):
            w.writerow([k, *row[:2], 0, *row[2:], ""])
    text = "\n".join(realtime_section(d))
    assert ("Solves that kept the one solver busy past the MPC period, so that the next "
            "period's solve waited (`late_solves` of `charged_solves`, every run of the cell "
            "that recorded them pooled, failed ones too; then the solves whose plans the "
            "budget dropped and "
            "those a contact stopped; `-`: no run of the cell recorded them; the `measured` "
            "runs were flown before hmpc recorded `real_time`):\n\n"
            "| controller | model |\n|---|---|\n"
            "| 10 Hz | 29 % (12/42); 2 dropped, 1 stopped |\n| 60 Hz | 0/0 |\n"
            "| 100 Hz | - |") in text
    (d / "results.csv").write_text(",".join(head) + "\n0,model,10 Hz,0,true,30,30,some,0,0,\n")
    with pytest.raises(FigureInputError, match=r"results.csv:2: late_solves: expected a "
                                               r"count, got 'some'"):
        realtime_section(d)


def test_the_real_time_section_says_what_each_latency_entry_sets(tmp_path):
    """Latency entries that also set the low level past the guard (sweeps/realtime_ipopt.toml):
    their meaning comes from the sweep file, and every measured entry gets its solve times."""
    from hmpc_cli.report.realtime import realtime_section

    d = tmp_path / "rt"
    d.mkdir()
    (d / "sweep.toml").write_text(
        'name = "rt"\ndescription = "two low levels"\nscenario = "../scenarios/ball.toml"\n'
        '[set]\n"sim.latency_first" = "paused"\n"sim.delay_compensation" = false\n'
        "[grid]\nlatency = [\n"
        '  { label = "measured, hold", "sim.latency" = "measured", '
        '"lowlevel.past_guard" = "hold" },\n'
        '  { label = "measured, next", "sim.latency" = "measured", '
        '"lowlevel.past_guard" = "next_domain" },\n]\n')
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "latency", "controller", "disturbance", "seed", "success",
                    "solves", "solve_time_median", "solve_time_p95", "wall_time", "log"])
        w.writerow([0, "measured, hold", "10 Hz once", "nominal", 0, "false", 9, 0.1, 0.8, 1,
                    ""])
        w.writerow([1, "measured, next", "10 Hz once", "nominal", 0, "true", 31, 0.009, 0.03, 1,
                    ""])
    text = "\n".join(realtime_section(d))
    assert text.startswith("### `rt.toml`: two low levels\n")
    assert ("settings of every run: `sim.latency_first = \"paused\"`, "
            "`sim.delay_compensation = false`;") in text
    assert ("- `measured, hold`: each solve charged its measured wall time on the machine "
            "that ran the table (not reproducible elsewhere); the low level holds the plan's "
            "guard node after an impact until the next plan arrives.") in text
    assert "; the low level follows the plan's next domain from the contact's time." in text
    assert "| 10 Hz once | 0/1 | 1/1 |" in text
    assert "| 10 Hz once | 100.0 | 800.0 | 9.0 | 30.0 |" in text


def test_rates_whose_margins_were_refused_are_named_not_read_as_control_failures(tmp_path):
    """Every 5 Hz run of one series refused at set-up for its tube margins (the runner's
    reason): the table, figure and findings say so, the comparison and a second trend
    use the rates set up, the reading counts the series (exact)."""
    from hmpc_cli.analysis.trend import cochran_armitage
    from hmpc_cli.report.robustness import Study, margins_refused, robustness_sections

    refused = ("ValueError: mpc.margins: the tube's margins at 5 Hz do not fit: at 5 Hz the "
               "tightened guard-avoid row of floor (kappa = 0.2) exceeds its NLP gap")
    truth = {(5, "once", 30.0): 0, (10, "once", 30.0): 14, (50, "once", 30.0): 13,
             (100, "once", 30.0): 12}
    d = tmp_path / "tube"
    table = write_study(d / "results.csv", truth, seeds=20)
    with open(table, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r["reason"] = refused if r["mpc.rate_hz"] == "5" else (
            "success" if r["success"] == "true" else "final error 2 > 0.6")
    with open(table, "w", newline="") as f:
        w = csv.DictWriter(f, [*COLUMNS, "reason"])
        w.writeheader()
        w.writerows(rows)
    (d / "sweep.toml").write_text('name = "tube"\nseeds = 20\n[set]\n"mpc.margins" = "tube"\n')
    hand = tmp_path / "hand"
    write_study(hand / "results.csv", {**truth, (5, "once", 30.0): 15}, seeds=20)
    (hand / "sweep.toml").write_text('name = "hand"\nseeds = 20\n')
    text = "\n".join(robustness_sections([Study(hand), Study(d)], tmp_path / "fig", tmp_path))

    assert "| ±30.0 | once | 0/20, margins refused | 14/20 (" in text
    everywhere = cochran_armitage([20] * 4, [0, 14, 13, 12], [math.log(x) for x in
                                                              (5, 10, 50, 100)])
    set_up = cochran_armitage([20] * 3, [14, 13, 12], [math.log(x) for x in (10, 50, 100)])
    assert everywhere.z > 0 > set_up.z  # the refused rate alone makes the rise
    assert ("- ±30.0, once: at 5 Hz every run's margins were refused at set-up (none ran); "
            "of the rates set up, 100 Hz vs 10 Hz: 60 % vs 70 %, intervals overlap; trend "
            "across all rates (a refused run counts as failed; Cochran-Armitage, scores "
            f"log f): z = {everywhere.z:+.2f}, p = {everywhere.p:.3g}: success rises with "
            f"the MPC rate at the 5 % level; across the rates set up (10-100 Hz): z = "
            f"{set_up.z:+.2f}, p = {set_up.p:.3g}: no trend at the 5 % level (direction: "
            "falls).") in text
    assert ("- Faster MPC (time paused): in 0 of 2 series (study x disturbance size x "
            "policy) the fastest rate succeeds more often than the slowest with separated "
            "intervals, in 0 less often; 2 unresolved at this sample size. In 1 of these "
            "series a slower rate's margins were refused at set-up") in text
    # beside its hand-margin twin: the refused cell is marked and said, not compared
    assert "| ±30.0 | once | 0/20 refused \\| 15/20 | 14/20 \\| 14/20 |" in text
    assert ("- ±30.0, once, 5 Hz: the tube margins were refused at set-up (none of its 20 "
            "runs ran); with the hand margin 75 % (15/20).") in text
    assert ("(`tube`): better in 0 of 4 cells with separated intervals, worse in 1 (1 of them "
            "cells whose tube margins were refused at set-up); 3 unresolved.") in text
    with open(tmp_path / "fig" / "tube_table.csv", newline="") as f:
        by_rate = {r["mpc.rate_hz"]: r["not_set_up"] for r in csv.DictReader(f)}
    assert by_rate == {"5": "20", "10": "0", "50": "0", "100": "0"}
    assert (tmp_path / "fig" / "tube.png").is_file()
    # the committed tube study: its refused runs are the ones the runner wrote so
    with open(REPO / "results" / "sweeps" / "robustness_tube" / "results.csv",
              newline="") as f:
        committed = list(csv.DictReader(f))
    assert sum(map(margins_refused, committed)) == 200
    assert {r["mpc.rate_hz"] for r in committed if margins_refused(r)} == {"5"}


def test_a_users_sweep_without_policy_or_size_columns_is_drawn(tmp_path, monkeypatch):
    """A sweep over the rate and a labelled axis of policy tables, the size left at the
    scenario's: the section takes the policy from each run's label and the size from the
    scenario, and its resume line names no sweep file that does not exist."""
    from hmpc_cli.report.robustness import Study, robustness_sections
    from hmpc_cli.sweep.plan import plan_sweep

    monkeypatch.chdir(tmp_path)  # no sweeps/<name>.toml here
    d = tmp_path / "out_mine"
    d.mkdir()
    spec = (f'name = "mine"\nscenario = "{BALL.as_posix()}"\nseeds = 4\n[grid]\n'
            '"mpc.rate_hz" = [10, 60]\npolicy = [\n'
            '  { label = "plan once", "replanning.policy" = "once" },\n'
            '  { label = "replan", replanning = { policy = "on_contact" } },\n]\n')
    (d / "sweep.toml").write_text(spec)
    (tmp_path / "mine.toml").write_text(spec)
    runs = plan_sweep(tmp_path / "mine.toml").runs
    with open(d / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["run_id", "seed", "mpc.rate_hz", "policy", "success", "log"])
        for r in runs:  # replanning at 60 Hz always holds, the rest half the time
            (d / "runs" / r.run_id).mkdir(parents=True)  # as a sweep leaves each run
            (d / "runs" / r.run_id / "scenario.toml").write_text(r.toml)
            rate, label = r.cell
            ok = (rate == 60 and label == "replan") or r.seed % 2 == 0
            w.writerow([r.run_id, r.seed, rate, label, "true" if ok else "false", ""])
    text = "\n".join(robustness_sections([Study(d)], tmp_path / "fig", tmp_path))
    assert "Not drawn" not in text, text
    assert "| ±10.0 | once | 2/4 (15-85 %) | 2/4 (15-85 %) |" in text, text
    assert "| ±10.0 | on_contact | 2/4 (15-85 %) | 4/4 (51-100 %) |" in text, text
    assert ("Resume or complete: `hmpc sweep` on the sweep file of `mine` with `--out "
            "out_mine` (finished runs are skipped).") in text
    # an axis of tables that sets the policy in some entries only cannot be read: an
    # error blamed on the study's directory (the command names its option)
    (d / "sweep.toml").write_text(spec.replace('"replanning.policy" = "once" ', 'x = 1 '))
    with pytest.raises(FigureInputError, match="^grid.policy: its entries set "
                       "replanning.policy, but not every entry does, under a label of its "
                       "own") as caught:
        robustness_sections([Study(d)], tmp_path / "fig", tmp_path)
    assert caught.value.source == d


def test_a_trend_is_tested_again_without_the_slowest_rate_and_tallied_both_ways(tmp_path):
    """A rise that only the slowest rate makes (2/20 at 5 Hz, then 19, 15, 12 of 20) is
    tested again without it (a fall), and the reading tallies rises and falls at the 5 %
    and the Bonferroni level (exact)."""
    from hmpc_cli.analysis.trend import cochran_armitage
    from hmpc_cli.report.robustness import Study, robustness_sections

    once, contact = [2, 19, 15, 12], [20, 18, 15, 10]
    rates = (5, 10, 50, 100)
    truth = {**{(f, "once", 15.0): k for f, k in zip(rates, once, strict=True)},
             **{(f, "on_contact", 15.0): k for f, k in zip(rates, contact, strict=True)}}
    d = tmp_path / "s"
    write_study(d / "results.csv", truth, seeds=20)
    (d / "sweep.toml").write_text('name = "s"\nseeds = 20\n')
    text = "\n".join(robustness_sections([Study(d)], tmp_path / "fig", tmp_path))
    logs = [math.log(f) for f in (5, 10, 50, 100)]
    everywhere = cochran_armitage([20] * 4, once, logs)
    fast = cochran_armitage([20] * 3, once[1:], logs[1:])
    assert everywhere.z > 0 > fast.z and everywhere.p < 0.05 and fast.p < 0.05
    assert (f"trend across rates (Cochran-Armitage, scores log f): z = {everywhere.z:+.2f}, "
            f"p = {everywhere.p:.3g}: success rises with the MPC rate at the 5 % level; "
            f"without the slowest rate (10-100 Hz): z = {fast.z:+.2f}, p = {fast.p:.3g}: "
            "success falls with the MPC rate at the 5 % level.") in text
    assert everywhere.p > 0.025 and cochran_armitage([20] * 4, contact, logs).p < 0.025
    rest = cochran_armitage([20] * 3, contact[1:], logs[1:])
    assert rest.z < 0 and rest.p < 0.05  # both fall without the slowest rate
    assert ("Trend tests across the rates set up (Cochran-Armitage, scores log f): success "
            "rises with the rate in 1 of these 2 series and falls in 1 at the 5 % level; at "
            "the Bonferroni level 0.05/2 = 0.025, it rises in 0 and falls in 1; without each "
            "series' slowest rate (2 series of 3 rates or more), it rises in 0 and falls in 2 "
            "at the 5 % level.") in text
    assert "not a certificate of one, and the trends above (time paused) point both " \
        "ways." in text
    # one direction only: the reading does not say both
    write_study(d / "results.csv", {k: v for k, v in truth.items() if k[1] == "on_contact"},
                seeds=20)
    text = "\n".join(robustness_sections([Study(d)], tmp_path / "fig", tmp_path))
    assert "rises with the rate in 0 of these 1 series and falls in 1" in text
    assert "not a certificate of one.\n" in text


def test_report_never_replaces_a_page_made_with_other_sections(tmp_path, invoke_hmpc):
    """``--results`` holding the repository's page (``hmpc report``) or a file of the user:
    a report with other sections refuses (exit 2, the page untouched) and says how to write
    elsewhere; ``--replace`` is the way to replace it."""
    results = tmp_path / "results"
    results.mkdir()
    mine = "# my notes\n"
    sections = ["--no-run", "--fig3", "", "--fig3-extra", "", "--fig3-reference", "",
                "--fig3-reference-extra", "", "--fig3-schedule", "", "--robustness", "",
                "--biped-push", "", "--fig3-trials", "", "--realtime", "", "--biped", ""]
    for page, what in [(RESULTS / "README.md", "was generated by `hmpc report`, with other "
                        "sections"), (None, "is not a page hmpc report wrote")]:
        text = page.read_text() if page else mine
        (results / "README.md").write_text(text)
        proc = invoke_hmpc(["report", "--results", str(results), *sections], cwd=tmp_path)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr == (
            f"error: --results {results}: {results / 'README.md'} {what}; this command would "
            f"replace it and the figures in {results / 'report'}: write the page elsewhere "
            "(--results DIR, a new directory) or pass --replace\n")
        assert (results / "README.md").read_text() == text
        assert not (results / "report").exists()
    proc = invoke_hmpc(["report", "--results", str(results), *sections, "--replace"],
                       cwd=tmp_path)
    assert proc.returncode == 2 and "nothing to report" in proc.stderr  # past the guard


def test_a_grid_axis_whose_entries_would_be_pooled_is_refused_by_name():
    """A robustness section's cells are (MPC rate, policy, disturbance size): an axis two
    of whose entries share a cell but differ otherwise (margins, latency) is refused
    naming it; an axis of disturbance draws is pooled like seeds. The committed robustness
    studies pass; Figure 3's 100 Hz panels (floor shift or not at one rate) do not."""
    import tomllib

    from hmpc_cli.report.robustness import _refuse_pooled_axes, charged

    def spec(name: str) -> dict:
        return tomllib.loads((REPO / "sweeps" / f"{name}.toml").read_text())

    for ok in ("robustness", "robustness_tube", "robustness_realtime", "fig3"):
        _refuse_pooled_axes(spec(ok))
    mine = {"grid": {"mpc.rate_hz": [10, 20], "margins": [
        {"label": "hand", "mpc.margins": "hand"}, {"label": "tube", "mpc.margins": "t.toml"}]}}
    for refused, axis in ((mine, "margins"), (spec("margins"), "margins"),
                          (spec("fig3_reference_100hz"), "controller"),
                          ({"grid": {"mpc.horizon": [1.0, 2.0]}}, "mpc.horizon")):
        with pytest.raises(FigureInputError) as err:
            _refuse_pooled_axes(refused)
        assert str(err.value) == (
            f"grid.{axis}: a robustness section tells runs apart by MPC rate, replanning "
            "policy and disturbance size only, so entries of this axis would be pooled into "
            "one cell: report each as a study of its own (a sweep per entry, one --robustness "
            f"each), or draw it with hmpc plot robustness DIR --series-axis {axis}")
    # the latency its runs were charged: the sweep's [set], else their scenario's
    assert charged({"effective": {"sim.latency": "model"}}) == "model"
    assert charged({"set": {"sim.latency": "paused"}, "effective": {"sim.latency": "model"}}) \
        is None
    assert charged({"effective": {"sim.latency": "paused"}}) is None


def test_the_model_latency_entry_says_what_it_charges(tmp_path):
    """The modelled latency's costs come from the runs' scenario (the sweep's [set] wins,
    a latency entry's own keys over both), and the page says they are the fitted solves'
    costs, not the controller's own."""
    from hmpc_cli.report.realtime import _model_costs as costs_of
    from hmpc_cli.report.realtime import _sim_settings

    def _model_costs(table, spec, entry=None):
        return costs_of(_sim_settings(table, spec, entry))

    (tmp_path / "base_scenario.toml").write_text(
        '[sim]\nlatency_model = {"overhead" = 0.0, "per_iteration" = 0.0024, '
        '"per_switching_iteration" = 0.008, "planner" = 0.01}\n')
    table = tmp_path / "results.csv"
    assert _model_costs(table, {}) == (
        ": 0 ms per solve + 2.4 ms per iteration (8 ms with a switch left), the costs of the "
        "solves they were fitted to (on one machine; not scaled to the NLP's size) whatever "
        "the controller's own, and 10 ms per planner call")
    assert _model_costs(table, {"set": {"sim.latency_model.per_iteration": 0.003}}).startswith(
        ": 0 ms per solve + 3 ms per iteration")
    entry = {"label": "model", "sim.latency": "model", "sim.latency_model.overhead": 0.0058,
             "sim.latency_model.per_iteration": 0.0018, "sim.latency_model.nodes": 301}
    from hmpc_cli.report.realtime import _meaning

    assert _meaning("model", {"model": entry}).startswith(
        "each solve charged by the sweep's fitted solve-time model")
    assert _meaning("model", {"model": {"sim.latency": "model"}}).startswith(
        "each solve charged by the scenario's fitted solve-time model")
    assert _model_costs(table, {"set": {"sim.latency_model.per_iteration": 0.003}},
                        entry).startswith(
        ": 5.8 ms per solve + 1.8 ms per iteration (8 ms with a switch left), the costs of "
        "the solves they were fitted to (on one machine; at 301 plan nodes, a plan of n nodes "
        "charged n / 301 times them) whatever")
    (tmp_path / "base_scenario.toml").write_text("[sim]\n")
    assert _model_costs(table, {}) == ""


def test_a_studys_tube_table_names_the_region_its_constants_hold_on():
    """The robustness section's tube table says which box L_x was sampled on (the default
    region: x0 and the goal padded; the ball's velocities within ±2 m/s) and that its tubes
    do not cover states outside it."""
    from hmpc_cli.analysis.tables import read_table
    from hmpc_cli.report.robustness import region_text, tube_reports

    table = REPO / "results" / "sweeps" / "robustness" / "results.csv"
    rows = read_table(table, ["seed"])
    reports = tube_reports(table, rows, sweep_file=REPO / "sweeps" / "robustness.toml")
    assert sorted(reports) == [15.0, 30.0]
    assert region_text(reports) == (
        "L_x = 1.109 1/s, the largest ||df/dx|| sampled on `hmpc tube`'s default region, the "
        "box px [-1, 5], py [-1, 5], vx [-2, 2], vy [-2, 2]: a Lipschitz constant inside "
        "that box only, so these tubes do not cover a run's states outside it (docs/tubes.md, "
        "\"The region\", measures how far the ball's runs leave it)")
    assert region_text({}) == ""


def test_a_study_whose_table_holds_its_header_alone_is_not_run_yet(tmp_path):
    """A sweep stopped before its first run ends leaves results.csv's header alone: its
    section says it is not run yet (an error only for a table of runs that is unusable)."""
    from hmpc_cli.report.robustness import Study, robustness_sections

    d = tmp_path / "started"
    d.mkdir()
    (d / "results.csv").write_text("run_id,seed,mpc.rate_hz,success,log\n")
    sweep = tmp_path / "started.toml"
    sweep.write_text('name = "started"\n')
    lines = robustness_sections([Study(d, sweep)], tmp_path / "fig", tmp_path)
    assert "### started" in lines
    assert any(x.startswith("Not run yet: no run of ") for x in lines), lines
    (d / "results.csv").write_text("run_id,seed,mpc.rate_hz,success,log\na,0,10,true,\n")
    with pytest.raises(FigureInputError) as caught:
        robustness_sections([Study(d, sweep)], tmp_path / "fig", tmp_path)
    assert caught.value.source == d


def test_a_studys_tubes_hold_its_plants_mismatch(tmp_path):
    """A study whose runs fly a [plant] other than their model: its tube table's eta is
    hmpc tube's, the plant's flow mismatch included (as mpc.margins = "tube" computes it)."""
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.report.robustness import tube_reports
    from hmpc_cli.run.scenario import load_scenario
    from hmpc_cli.run.tube_margins import plant_system
    from hmpc_cli.sweep.plan import plan_sweep
    from hmpc_cli.tube import analyse, region_from_scenario

    sweep = tmp_path / "heavy.toml"
    sweep.write_text(f'name = "heavy"\nscenario = "{BALL.as_posix()}"\nseeds = 1\n[set]\n'
                     '"plant.mass" = 2.0\n"disturbance.kind" = "box"\n'
                     '"disturbance.magnitude" = 15.0\n')
    d = tmp_path / "out"
    run = plan_sweep(sweep).runs[0]
    (d / "runs" / run.run_id).mkdir(parents=True)
    (d / "runs" / run.run_id / "scenario.toml").write_text(run.toml)
    with open(d / "results.csv", "w", newline="") as f:
        csv.writer(f).writerows([["run_id", "seed", "mpc.rate_hz", "disturbance.magnitude",
                                  "success", "log"], [run.run_id, 0, 10, 15.0, "true", ""]])
    with open(d / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    (rep,) = tube_reports(d / "results.csv", rows, sweep_file=sweep).values()
    sc = load_scenario(BALL, ["plant.mass=2.0", "disturbance.kind='box'",
                              "disturbance.magnitude=15.0"])[0]
    plant, note = plant_system(sc)
    system = build_system(sc.system)
    alone = analyse(system, region=region_from_scenario(system), kind="box", magnitude=15.0,
                    kp=sc.lowlevel.kp, kd=sc.lowlevel.kd, rate_hz=sc.mpc.rate_hz,
                    rates=[10.0], seed=sc.seed, plant=plant, plant_note=note)
    assert rep.disturbance.mismatch > 0
    assert rep.disturbance.eta == alone.disturbance.eta


def test_only_series_the_rate_reading_compares_count_as_refused():
    """A series with fewer than two rates set up is not compared: its refused rate is not
    one of 'these series' (a ±30 series with one rate set up was counted)."""
    from types import SimpleNamespace as Cell

    from hmpc_cli.report.robustness import _refused_series

    cells = [Cell(panel="±15", series="once", x=x, ran=True) for x in (5, 20)] + [
        Cell(panel="±30", series="once", x=5, ran=False),
        Cell(panel="±30", series="once", x=20, ran=True),
        Cell(panel="±30", series="replan", x=5, ran=False),
        *[Cell(panel="±30", series="replan", x=x, ran=True) for x in (10, 20)]]
    assert _refused_series(cells) == 1


def test_a_page_is_the_same_sections_however_its_options_are_written():
    """Options in another order, ``--opt=value``, a default given explicitly or ``./x``
    for ``x`` show the same sections (such a report refused to regenerate its own page,
    'with other sections'); another value, or a section left out, does not."""
    from hmpc_cli.cli.report import _sections

    made = ["--results", "repro", "--no-run", "--fig3-extra", "", "--fig3-trials", "",
            "--realtime", ""]
    for same in (["--results=repro", "--realtime", "", "--fig3-trials", "", "--fig3-extra",
                  "", "--run", "--workers", "2"],
                 ["--results", "./repro", "--fig3", "sweeps/fig3.toml", "--fig3-extra=",
                  "--fig3-trials", "", "--realtime", "", "-q"],
                 ["-qv", "--results", "repro", "-vvv", "--fig3-extra", "", "--fig3-trials",
                  "", "--realtime", ""]):
        assert _sections(same) == _sections(made), same
    for other in (["--results", "repro", "--fig3-extra", "", "--fig3-trials", ""],
                  ["--results", "repro", "--fig3-extra", "x.toml", "--fig3-trials", "",
                   "--realtime", ""]):
        assert _sections(other) != _sections(made), other


def test_a_section_names_only_files_the_repository_holds(tmp_path, monkeypatch):
    """A section made from a sweep outside the repository's layout named `sweeps/X.toml`
    and `scenarios/Y.toml`, files the reader cannot find: only what exists is a path."""
    from hmpc_cli.report.paths import repository_file

    monkeypatch.chdir(REPO)
    assert repository_file("sweeps", "fig3.toml") == "`sweeps/fig3.toml`"
    assert repository_file("scenarios", "ball.toml") == "`scenarios/ball.toml`"
    monkeypatch.chdir(tmp_path)
    assert repository_file("sweeps", "s9.toml") == "`s9.toml`"


def test_the_tube_panel_says_what_each_curve_bounds():
    """The trivial curve is diam T(1/f), a bound on the state's norm; the kinematic one its
    integral over the period, a bound on the positions: one axis, so the legend says it."""
    from matplotlib.figure import Figure

    from hmpc_cli.figures.robustness import _diameter_panel

    ax = Figure().subplots()
    _diameter_panel(ax, {15.0: {"trivial": [(10.0, 0.5)], "kinematic": [(10.0, 0.01)]}}, "15")
    assert [ln.get_label() for ln in ax.get_lines()] == [
        "trivial: diam $T(1/f)$, state norm", r"kinematic: $\int_0^{1/f}$ diam $T$, positions"]
