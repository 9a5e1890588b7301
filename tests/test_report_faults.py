"""``hmpc report`` under faults: stop signals, a section that fails, inputs that are not sweeps."""

from __future__ import annotations

import csv
import signal
import time
from pathlib import Path

import pytest

from conftest import BALL, REPO, signal_handlers_installed, stop_process
from test_report import TRUTH, write_study

#: every section left out (a test gives back the one it needs)
NONE = {"--fig3": "", "--fig3-extra": "", "--fig3-reference": "", "--fig3-reference-extra": "",
        "--fig3-schedule": "", "--biped": "", "--biped-push": "", "--fig3-trials": "",
        "--realtime": "", "--robustness": ""}


def _args(**given: str) -> list[str]:
    """``report`` with every section left out but ``given`` (``fig3_extra=`` for --fig3-extra)."""
    options = NONE | {"--" + k.replace("_", "-"): v for k, v in given.items()}
    return ["report", *(x for kv in options.items() for x in kv)]


def _wait_for(cond, what: str, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP])
def test_a_stopped_report_run_exits_128_plus_the_signal_and_says_what_finished(
        tmp_path, start_hmpc, sig):
    """A stop signal to ``hmpc report --run`` in its first run: exit 128 + the signal, one
    line saying how many of the missing runs finished (none), no page, no figures."""
    sweep = tmp_path / "slow_study.toml"
    sweep.write_text(f'name = "slow_study"\nscenario = "{BALL.as_posix()}"\nseeds = 2\n'
                     '[set]\n"sim.duration" = 30.0\n"mpc.horizon" = 1.0\n')
    res = tmp_path / "results"
    proc = start_hmpc([*_args(robustness=str(sweep)), "--run", "--results", str(res),
                       "--workers", "1"], tmp_path)
    runs = res / "sweeps" / "slow_study" / "runs"
    _wait_for(lambda: proc.poll() is not None or (
        signal_handlers_installed(proc.pid) and any(runs.glob("*/run.mcap"))), "a run")
    assert proc.poll() is None, proc.communicate()
    _, err = stop_process(proc, sig, timeout=120)
    assert proc.returncode == 128 + sig, err
    assert err.splitlines()[-1] == ("interrupted: 0 of 2 missing runs done; run the same "
                                    "command again to resume"), err
    assert "Traceback" not in err
    assert not (res / "README.md").exists() and not (res / "report").exists()


def _tree(root: Path) -> dict[str, bytes | None]:
    """Every path under ``root`` with its bytes (None: a directory)."""
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(root.rglob("*"))}


def _push_table_without_its_push_column(d: Path) -> Path:
    d.mkdir(parents=True)
    (d / "results.csv").write_text("run_id,seed,mpc.rate_hz,success,log\n"
                                   "a,0,10,true,\nb,1,10,false,\n")
    return d


def test_a_report_that_fails_in_a_later_section_leaves_the_results_as_they_were(
        tmp_path, invoke_hmpc):
    """The robustness section draws, then the push section's table lacks its column: exit
    2, the error names the option, and the results directory is byte for byte as before
    (the page and figures of the report before it; no report/ on a first report)."""
    study = write_study(tmp_path / "study" / "results.csv").parent
    bad = _push_table_without_its_push_column(tmp_path / "push")
    res = tmp_path / "results"
    failing = [*_args(robustness=str(study), biped_push=str(bad)), "--results", str(res)]
    first = invoke_hmpc(failing, tmp_path)
    assert first.returncode == 2, first.stderr
    assert first.stderr == (
        f"error: --biped-push {bad}: {bad / 'results.csv'}: missing column(s) "
        "disturbance.magnitude (has: run_id, seed, mpc.rate_hz, success, log): not the table "
        "of the sweep --biped-push draws; give that sweep's file or output directory (`hmpc "
        "report --help` names the default)\n")
    assert not res.exists()  # a first report: nothing made, not even --results
    ok = invoke_hmpc([*_args(robustness=str(study)), "--results", str(res)], tmp_path)
    assert ok.returncode == 0, ok.stderr
    (res / "report" / "mine.txt").write_text("kept\n")
    before = _tree(res)
    assert "report/study.png" in before and "README.md" in before
    again = invoke_hmpc([*failing, "--replace"], tmp_path)
    assert again.returncode == 2 and again.stderr == first.stderr
    assert _tree(res) == before


def test_figure_3_robustness_and_authors_errors_name_their_option(tmp_path, invoke_hmpc):
    """Another section's table given to --fig3-extra or to --robustness, and an --authors
    directory without the authors' files: exit 2, one line naming the option and its
    value, nothing written. A study whose table is there but unusable is an error, not a
    'Not drawn' section of a page that exits 0."""
    push = _push_table_without_its_push_column(tmp_path / "push")
    empty = tmp_path / "authors"
    empty.mkdir()
    res = tmp_path / "results"
    has = "(has: run_id, seed, mpc.rate_hz, success, log)"
    cases = {
        "fig3_extra": f"error: --fig3-extra {push}: {push / 'results.csv'}: missing column(s) "
        f"controller, disturbance {has}: not the table of the sweep --fig3-extra draws; give "
        "that sweep's file or output directory (`hmpc report --help` names the default)",
        "robustness": f"error: --robustness {push}: {push / 'results.csv'}: no "
        "replanning.policy column, and the scenario of run 'a' cannot be read (no run "
        "directory; pass the sweep file)"}
    for option, line in cases.items():
        proc = invoke_hmpc([*_args(**{option: str(push)}), "--results", str(res)], tmp_path)
        assert (proc.returncode, proc.stderr) == (2, line + "\n"), proc.stderr
    fig3 = REPO / "results" / "sweeps" / "fig3_100hz"
    proc = invoke_hmpc([*_args(fig3_extra=str(fig3)), "--authors", str(empty),
                        "--results", str(res)], tmp_path)
    assert (proc.returncode, proc.stderr) == (2, (
        f"error: --authors {empty}: {empty}: none of the authors' Figure 3 files is there "
        "(fig3_left_10hz_fixed.csv, fig3_middle_20hz_fixed.csv, fig3_right_10hz_hybrid.csv, "
        "fig3_extra_100hz_fixed.csv)\n")), proc.stderr
    assert not res.exists()


def test_an_extra_figure_3_panel_alone_is_drawn(tmp_path, invoke_hmpc):
    """--fig3-extra without --fig3 draws the 100 Hz panel (it was 'nothing to report')."""
    res = tmp_path / "results"
    proc = invoke_hmpc([*_args(fig3_extra=str(REPO / "results" / "sweeps" / "fig3_100hz")),
                        "--authors", str(REPO / "results" / "authors"), "--results", str(res)],
                       tmp_path)
    assert proc.returncode == 0, proc.stderr
    page = (res / "README.md").read_text()
    assert "run by hmpc in 1 mode:\n" in page
    assert "| ![hmpc mode extra](report/fig3_extra/fig3.png) |\n" in page
    assert "| 100 Hz fixed | - | 4/11 (trial 3, trial 4, trial 5, trial 6, trial 7, trial 9, " \
        "trial 10) | 11/11 |\n" in page
    assert (res / "report" / "fig3_extra" / "fig3.png").is_file()
    assert not (res / "report" / "fig3.png").exists()


def test_a_directory_that_is_not_a_sweeps_output_is_refused_by_option(tmp_path, invoke_hmpc):
    """An empty directory, or a folder of sweep files, for a sweep option: exit 2 naming
    the option and what to give; nothing written."""
    sweeps = tmp_path / "sweeps"
    sweeps.mkdir()
    (sweeps / "a.toml").write_text(f'name = "a"\nscenario = "{BALL.as_posix()}"\n')
    empty = tmp_path / "empty"
    empty.mkdir()
    res = tmp_path / "results"
    proc = invoke_hmpc([*_args(robustness=str(sweeps), biped_push=str(empty)),
                        "--results", str(res)], tmp_path)
    assert proc.returncode == 2, proc.stderr
    why = ("not a sweep's output directory (no results.csv or sweep.toml); give a sweep "
           "file to run it, or the directory `hmpc sweep --out` wrote")
    assert proc.stderr.splitlines() == [f"error: --biped-push {empty}: {why}",
                                        f"error: --robustness {sweeps}: {why}"]
    assert not res.exists()


def test_an_empty_value_leaves_a_section_out_and_a_dot_is_the_current_directory(
        tmp_path, invoke_hmpc):
    """``--robustness ''`` leaves the study out (nothing to report); ``--robustness .`` in a
    sweep's output directory reads it."""
    study = write_study(tmp_path / "study" / "results.csv").parent
    res = tmp_path / "results"
    left_out = invoke_hmpc([*_args(robustness=""), "--results", str(res)], study)
    assert left_out.returncode == 2 and "nothing to report" in left_out.stderr
    here = invoke_hmpc([*_args(robustness="."), "--results", str(res)], study)
    assert here.returncode == 0, here.stderr
    page = (res / "README.md").read_text()
    assert "## Robustness study" in page and "![study](report/study.png)" in page
    assert (res / "report" / "study.png").is_file()


def test_a_signal_while_the_page_is_drawn_leaves_the_results_as_they_were(tmp_path,
                                                                          monkeypatch):
    """A stop signal in a section after figures were drawn: the staging directory goes,
    the results directory is byte for byte as before (the signal goes on up)."""
    import hmpc_cli.report.push
    from hmpc_cli.core.signals import Interrupted
    from hmpc_cli.report.page import ReportInputs, write_report

    study = write_study(tmp_path / "study" / "results.csv").parent
    res = tmp_path / "results"
    write_report(res, ReportInputs(None, None, study), "hmpc report")
    before = _tree(res)

    def stopped(*args, **kwargs):
        raise Interrupted(signal.SIGTERM)

    monkeypatch.setattr(hmpc_cli.report.push, "push_section", stopped)
    changed = write_study(tmp_path / "later" / "study" / "results.csv",  # other figures
                          {k: 10 - v for k, v in TRUTH.items()}).parent
    with pytest.raises(Interrupted):
        write_report(res, ReportInputs(None, None, changed, biped_push=study), "hmpc report")
    assert _tree(res) == before


def test_a_signal_while_the_page_is_written_stops_the_command_after_it(tmp_path,
                                                                      monkeypatch):
    """A stop signal while the figures and the page are put in place is held until they
    all are, then stops the command (it was dropped: the command exited 0)."""
    import os

    import hmpc_cli.core.paths
    from hmpc_cli.core.signals import Interrupted, handle_signals, reset
    from hmpc_cli.report.page import ReportInputs, write_report

    study = write_study(tmp_path / "study" / "results.csv").parent
    res = tmp_path / "results"
    write_atomic = hmpc_cli.core.paths.write_atomic

    def signalled(path, text):  # the page is being written when the signal comes
        os.kill(os.getpid(), signal.SIGTERM)
        return write_atomic(path, text)

    monkeypatch.setattr(hmpc_cli.core.paths, "write_atomic", signalled)
    try:
        with handle_signals(), pytest.raises(Interrupted) as stop:
            write_report(res, ReportInputs(None, None, study), "hmpc report")
    finally:
        reset()  # the signal this process sent itself is not the next test's
    assert stop.value.signum == signal.SIGTERM
    assert (res / "README.md").read_text().startswith("# hmpc results")
    assert (res / "report" / "study.png").is_file()
    assert [p.name for p in res.iterdir() if p.name.startswith(".")] == []


def _study_and_its_directory(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A one-run sweep file, a results directory and its sweep directory (made, empty)."""
    sweep = tmp_path / "study.toml"
    sweep.write_text(f'name = "study"\nscenario = "{BALL.as_posix()}"\nseeds = 1\n'
                     '[set]\n"sim.duration" = 0.2\n')
    res = tmp_path / "results"
    out = res / "sweeps" / "study"
    out.mkdir(parents=True)
    return sweep, res, out


def test_report_run_takes_the_sweeps_lock(tmp_path, run_hmpc):
    """``report --run`` into a sweep directory another ``hmpc sweep`` writes (its lock
    held): refused, exit 2, nothing run and no page (it ran the sweep beside it)."""
    import os

    from hmpc_cli.sweep.lock import output_lock

    sweep, res, out = _study_and_its_directory(tmp_path)
    with output_lock(out):  # held by this process, as by a running hmpc sweep
        proc = run_hmpc([*_args(robustness=str(sweep)), "--run", "--results", str(res),
                         "--workers", "1"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        f"error: {out}: another sweep is writing here (pid {os.getpid()})"), proc.stderr
    assert not (out / "runs").exists() and not (res / "README.md").exists()


def test_a_sigkilled_reports_staging_directory_goes_with_the_next_report(tmp_path):
    """A report killed by SIGKILL leaves its ``.report-staging-*`` directory, whose lock
    its death released; the next report removes it. A staging directory whose lock is held
    (a report running, here in another process) stays, as does one without a lock file
    (an older report's, or one being made) and a file of that name."""
    import signal
    import subprocess
    import sys

    from hmpc_cli.report.page import STAGING_LOCK, remove_stale_staging

    names = [".report-staging-killed", ".report-staging-running", ".report-staging-old"]
    for name in names:
        (tmp_path / name / "report").mkdir(parents=True)
        (tmp_path / name / "report" / "fig.png").write_bytes(b"png")
    (tmp_path / ".report-staging-file").write_text("not a directory")
    hold = ("import fcntl, os, sys, time\n"
            "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT, 0o644)\n"
            "fcntl.flock(fd, fcntl.LOCK_EX)\nprint('held', flush=True)\ntime.sleep(60)\n")
    procs = [subprocess.Popen([sys.executable, "-c", hold, str(tmp_path / n / STAGING_LOCK)],
                              stdout=subprocess.PIPE, text=True) for n in names[:2]]
    try:
        assert [p.stdout.readline().strip() for p in procs] == ["held", "held"]
        procs[0].send_signal(signal.SIGKILL)
        procs[0].wait()
        assert remove_stale_staging(tmp_path) == [tmp_path / names[0]]
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
            [*names[1:], ".report-staging-file"])
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
            proc.stdout.close()


def _tabled_study(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A sweep file over a copy of the ball scenario and its table as ``hmpc sweep`` writes
    it (rows of the plan's run ids, the base scenario beside it), no run directories.

    Returns:
        The sweep file, the scenario copy and the sweep's output directory.
    """
    from hmpc_cli.sweep.plan import plan_sweep
    from hmpc_cli.sweep.table import BASE_SCENARIO

    scenario = tmp_path / "ball.toml"
    scenario.write_text(BALL.read_text())
    sweep = tmp_path / "study.toml"
    sweep.write_text('name = "study"\nscenario = "ball.toml"\nseeds = 2\n[grid]\n'
                     '"mpc.rate_hz" = [10, 20]\n"replanning.policy" = ["once"]\n'
                     '"disturbance.magnitude" = [5.0]\n')
    plan = plan_sweep(sweep)
    out = tmp_path / "results" / "sweeps" / "study"
    out.mkdir(parents=True)
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, plan.columns, restval="")
        w.writeheader()
        for r in plan.runs:
            w.writerow({"run_id": r.run_id, "seed": r.seed, "success": "true",
                        "mpc.rate_hz": r.overrides["mpc.rate_hz"], "replanning.policy": "once",
                        "disturbance.magnitude": 5.0, "final_error": 0.01})
    (out / BASE_SCENARIO).write_text(plan.base_toml)
    return sweep, scenario, out


def test_a_sweep_files_stale_table_is_refused_and_its_directory_draws_it(tmp_path, invoke_hmpc):
    """After its sweep file or its base scenario changed, a sweep's table is no table of the
    file's runs: ``hmpc report`` without ``--run`` refuses it (exit 2, why, what to do,
    nothing written) instead of drawing it as the file's results; the directory given
    instead draws it as it is."""
    sweep, scenario, out = _tabled_study(tmp_path)
    res = tmp_path / "results"
    ok = invoke_hmpc([*_args(robustness=str(sweep)), "--results", str(res)], tmp_path)
    assert ok.returncode == 0, ok.stderr
    assert "4 finished runs, 2 seeds" in (res / "README.md").read_text()
    before = _tree(res)
    table = out / "results.csv"
    how = (f"; `hmpc report --run` rewrites it from the runs that stand (running the missing "
           f"ones first), or give the directory (--robustness {out}) to draw it as it is")
    sweep.write_text(sweep.read_text().replace("[10, 20]", "[10, 30]"))
    from hmpc_cli.sweep.plan import plan_sweep

    gone = [r.run_id for r in plan_sweep(sweep).runs]
    with open(table) as f:
        foreign = [row["run_id"] for row in csv.DictReader(f) if row["run_id"] not in gone]
    assert len(foreign) == 2

    def refused(why: str) -> None:  # exit 2, the one line, nothing written
        proc = invoke_hmpc([*_args(robustness=str(sweep)), "--results", str(res), "--replace"],
                           tmp_path)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.splitlines() == [
            f"error: --robustness {sweep}: {table} is not this sweep file's table: {why}{how}"]
        assert _tree(res) == before

    refused(f"2 of its 4 rows are runs this sweep file does not plan (run ids "
            f"{', '.join(foreign)}): the grid, [set] or seeds changed since it was written")
    sweep.write_text(sweep.read_text().replace("[10, 30]", "[10, 20]"))
    scenario.write_text(scenario.read_text().replace("duration = 3.0", "duration = 2.5", 1))
    refused(f"it was written for another base scenario: {scenario} changed since (the one "
            f"it ran: {out / 'base_scenario.toml'})")
    as_is = invoke_hmpc([*_args(robustness=str(out)), "--results", str(res), "--replace"],
                        tmp_path)
    assert as_is.returncode == 0, as_is.stderr
    assert "4 finished runs, 2 seeds" in (res / "README.md").read_text()


def test_two_sweep_files_of_one_name_are_refused_naming_both(tmp_path, invoke_hmpc):
    """Two sweep files of one ``name`` would share ``<results>/sweeps/<name>`` (the first
    section showing the second's runs): exit 2 naming both files and the name, nothing
    written."""
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    for path, rate in ((a, 10), (b, 30)):
        path.write_text(f'name = "study"\nscenario = "{BALL.as_posix()}"\nseeds = 1\n'
                        f'[set]\n"sim.duration" = 0.2\n[grid]\n"mpc.rate_hz" = [{rate}]\n')
    res = tmp_path / "results"
    args = ["report", *(x for kv in (NONE | {"--robustness": str(a)}).items() for x in kv),
            "--robustness", str(b), "--results", str(res), "--run", "--workers", "1"]
    proc = invoke_hmpc(args, tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"error: --robustness {a} and --robustness {b}: both sweep files are named 'study' "
        f"and would share {res / 'sweeps' / 'study'}; give one of them another name"]
    assert not res.exists()


def test_report_run_refuses_a_sweep_directory_that_is_not_its_sweeps(tmp_path, invoke_hmpc):
    """``report --run`` checks each sweep's directory as ``hmpc sweep`` checks ``--out``:
    one that is no sweep's, or another sweep's, is refused (exit 2, nothing run, no
    page); it wrote its runs among the files there."""
    sweep, res, out = _study_and_its_directory(tmp_path)
    (out / "notes.txt").write_text("mine\n")
    args = [*_args(robustness=str(sweep)), "--run", "--results", str(res), "--workers", "1"]
    proc = invoke_hmpc(args, tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"error: --robustness {sweep}: {out}: is not a sweep's directory (no sweep.toml; it "
        f"holds notes.txt): choose a new or empty --results"]
    (out / "sweep.toml").write_text('name = "other"\n')
    proc = invoke_hmpc(args, tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"error: --robustness {sweep}: {out}: belongs to sweep 'other' (its sweep.toml), not "
        f"'study': choose another --results (the same sweep resumes in its own directory)"]
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "sweep.toml"]
    assert not (res / "README.md").exists()


def _swept_study(tmp_path: Path, invoke_hmpc) -> tuple[Path, Path, Path]:
    """A sweep file over a copy of the ball scenario, swept (2 runs) into the results'
    sweeps directory: (the sweep file, the scenario copy, the sweep's output directory)."""
    scenario = tmp_path / "ball.toml"
    scenario.write_text(BALL.read_text())
    sweep = tmp_path / "study.toml"
    sweep.write_text('name = "study"\nscenario = "ball.toml"\nseeds = 1\n[set]\n'
                     '"sim.duration" = 0.2\n[grid]\n"mpc.rate_hz" = [10, 20]\n')
    out = tmp_path / "results" / "sweeps" / "study"
    proc = invoke_hmpc(["sweep", str(sweep), "--out", str(out), "--workers", "1", "-q"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    return sweep, scenario, out


def test_a_table_behind_its_finished_runs_is_refused(tmp_path, invoke_hmpc):
    """A sweep stopped (SIGKILL) before it rewrote results.csv: its finished run
    directories hold more runs than the table. ``hmpc report`` drew the table as it stood
    ('1 finished runs'); it now refuses (exit 2, why, what rewrites it, nothing written)."""
    sweep, _, out = _swept_study(tmp_path, invoke_hmpc)
    table = out / "results.csv"
    table.write_text("".join(table.read_text().splitlines(keepends=True)[:2]))  # one row
    res = tmp_path / "results"
    proc = invoke_hmpc([*_args(robustness=str(sweep)), "--results", str(res)], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"error: --robustness {sweep}: {table} is not this sweep file's table: it is behind "
        f"its finished runs: 1 finished run directory is not in it (the sweep stopped before "
        f"it rewrote its table); `hmpc report --run` rewrites it from the runs that stand "
        f"(running the missing ones first), or give the directory (--robustness {out}) to "
        f"draw it as it is"]
    assert not (res / "README.md").exists() and not (res / "report").exists()


def test_a_base_scenario_changed_in_keys_every_run_overrides_is_no_stale_table(
        tmp_path, invoke_hmpc):
    """The base scenario changed only in a key every run overrides: every row is vouched
    for by a finished run directory (its effective scenario is the planned one), so the
    table is drawn (it was refused as written for another base scenario)."""
    sweep, scenario, _ = _swept_study(tmp_path, invoke_hmpc)
    scenario.write_text(scenario.read_text().replace("duration = 3.0", "duration = 2.5", 1))
    assert scenario.read_text() != BALL.read_text()
    res = tmp_path / "results"
    proc = invoke_hmpc([*_args(robustness=str(sweep)), "--results", str(res)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "2 finished runs, 1 seeds" in (res / "README.md").read_text()


def test_a_sweep_file_that_cannot_be_read_names_its_option(tmp_path):
    """A missing or broken sweep file given to a section: its lines name the option (they
    named the file alone, so which of a dozen options was wrong had to be guessed)."""
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app

    (tmp_path / "broken.toml").write_text("name = \n")
    for option, value, why in (("fig3", "nonexist.toml", "file not found"),
                               ("fig3_trials", str(tmp_path / "broken.toml"),
                                "TOML syntax error: ")):
        res = CliRunner().invoke(app, [*_args(**{option: value}), "--results",
                                       str(tmp_path / "r")])
        assert res.exit_code == 2
        flag = "--" + option.replace("_", "-")
        assert res.output.startswith(f"error: {flag} {value}: {why}"), res.output
    assert not (tmp_path / "r").exists()
