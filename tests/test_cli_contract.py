"""The command line researchers expect: --version, -h, -q/-v, completion, exit codes, pins."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tomllib

import pytest

from conftest import BALL, REPO, cli_env, hmpc_command, signal_handlers_installed

COMMANDS = ["run", "schema", "sweep", "plot", "report", "tube", "replay"]


def _hmpc(args, cwd, env=None, timeout=120):
    return subprocess.run([*hmpc_command(), *args], cwd=cwd, env=env or cli_env(),
                          capture_output=True, text=True, timeout=timeout)


def test_version_prints_hmpc_casadi_python(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "hmpc_cli", "--version"], cwd=tmp_path,
                          env={**cli_env(), "PYTHONPATH": str(REPO)}, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert [ln.split()[0] for ln in lines] == ["hmpc", "casadi", "python"]
    assert re.match(r"casadi \d+\.\d+", lines[1])


def test_dash_h_and_verbosity_options_on_every_command(tmp_path):
    top = _hmpc(["-h"], tmp_path)
    assert top.returncode == 0 and "Usage: hmpc" in top.stdout
    for option in ("--install-completion", "--show-completion", "--version", "Exit codes"):
        assert option in top.stdout
    for command in COMMANDS:
        proc = _hmpc([command, "-h"], tmp_path)
        assert proc.returncode == 0 and f"Usage: hmpc {command}" in proc.stdout, command
        for option in ("--quiet", "-q", "--verbose", "-v"):
            assert option in proc.stdout, (command, option)


def test_quiet_and_verbose_are_accepted(tmp_path):
    proc = _hmpc(["schema", "-q"], tmp_path)
    assert proc.returncode == 0 and '"properties"' in proc.stdout
    proc = _hmpc(["plot", "-v", "fig9", "nothing"], tmp_path)
    assert proc.returncode == 2 and "unknown figure 'fig9'" in proc.stderr


def test_help_imports_no_casadi_or_matplotlib(tmp_path):
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "hmpc_cli", "--help"],
                          cwd=tmp_path, env={**cli_env(), "PYTHONPATH": str(REPO)},
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0
    imported = {ln.split("|")[-1].strip().split(".")[0] for ln in proc.stderr.splitlines()
                if ln.startswith("import time:")}
    assert "typer" in imported and not imported & {"casadi", "matplotlib"}


def test_completion_of_figures_and_set_keys(tmp_path):
    from hmpc_cli.cli.common import complete_figure, complete_set_key

    assert complete_figure("fig") == ["fig2", "fig3", "fig4"]
    assert "sim.duration=" in complete_set_key("sim.d")
    assert "planner.rollout_backend=" in complete_set_key("planner.roll")
    env = {**cli_env(), "_HMPC_COMPLETE": "complete_bash", "COMP_WORDS": "hmpc plot fi",
           "COMP_CWORD": "2"}
    proc = _hmpc([], tmp_path, env=env)
    assert {"fig2", "fig3", "fig4"} <= set(proc.stdout.split()), proc.stdout + proc.stderr
    for command in ("run", "tube"):  # both commands that take --set complete its keys
        env.update(COMP_WORDS=f"hmpc {command} scenarios/ball.toml --set sim.dur",
                   COMP_CWORD="4")
        proc = _hmpc([], tmp_path, env=env)
        assert "sim.duration=" in proc.stdout.split(), (command, proc.stdout + proc.stderr)


@pytest.mark.slow
def test_run_prints_its_log_path_and_strict_exits_1_on_failure(tmp_path):
    out = tmp_path / "short run"
    proc = _hmpc(["run", str(BALL), "--set", "sim.duration=0.2", "--out", str(out), "-q",
                  "--strict"], tmp_path)
    assert proc.returncode == 1, proc.stderr[-2000:]  # 0.2 s does not reach the goal
    assert proc.stdout.splitlines()[-1] == str(out / "run.mcap")
    assert (out / "run.mcap").is_file()
    reason = json.loads((out / "summary.json").read_text())["reason"]
    assert proc.stderr.splitlines()[-1] == (
        f"error: --strict: the run failed ({reason}); its log: {out / 'run.mcap'}")
    assert "final error" in proc.stderr.splitlines()[-1]


def test_run_refuses_a_directory_that_holds_anything(tmp_path):
    """--out must be new, empty or a run's own: a run never overwrites the user's files
    (a scenario.toml of their own) nor mixes with another tool's (a sweep's table)."""
    own = tmp_path / "exp1"
    own.mkdir()
    mine = "# my notes\n" + BALL.read_text()
    (own / "scenario.toml").write_text(mine)
    proc = _hmpc(["run", "scenario.toml", "--out", ".", "-q"], own)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == ("error: --out .: is not empty (scenario.toml): a run writes run.mcap, "
                           "scenario.toml and summary.json into a directory of its own "
                           "(choose a new or empty --out)\n")
    assert (own / "scenario.toml").read_text() == mine
    assert sorted(p.name for p in own.iterdir()) == ["scenario.toml"]


def test_tube_write_refuses_to_overwrite_a_file_that_is_not_a_margins_file(tmp_path):
    scenario = tmp_path / "s2.toml"
    text = BALL.read_text()
    scenario.write_text(text)
    proc = _hmpc(["tube", str(scenario), "--write", str(scenario), "-q"], tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr == (f"error: --write {scenario}: exists and is not an hmpc margins "
                           "file: it would be overwritten (choose another path)\n")
    assert scenario.read_text() == text and sorted(tmp_path.iterdir()) == [scenario]
    # an empty file (mktemp's) holds nothing to lose: written over, as a margins file is
    empty = tmp_path / "m.toml"
    empty.write_text("")
    proc = _hmpc(["tube", str(scenario), "--samples", "200", "--formats", "png", "--out",
                  str(tmp_path / "t"), "--write", str(empty), "-q"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert empty.read_text().startswith("# hmpc margins file, written by hmpc ")


#: hmpc report's Figure 3 in reference mode and with the authors' plan flown, left out
NO_REFERENCE = ["--fig3-reference", "", "--fig3-reference-extra", "", "--fig3-schedule", ""]


def test_report_runs_nothing_without_run(tmp_path):
    sweep = tmp_path / "tiny.toml"
    sweep.write_text(f'name = "tiny"\nscenario = "{BALL.as_posix()}"\nseeds = 3\n'
                     '[set]\n"sim.duration" = 0.5\n')
    proc = _hmpc(["report", "--results", str(tmp_path / "r"), "--fig3", "", "--fig3-extra",
                  "", *NO_REFERENCE, "--biped", "",
                  "--biped-push", "", "--fig3-trials", "", "--realtime", "",
                  "--robustness", str(sweep)],
                 tmp_path)
    assert "3 of 3 runs missing (1.5 s of simulated time" in proc.stderr, proc.stderr
    assert "hmpc report --run" in proc.stderr
    assert not (tmp_path / "r" / "sweeps" / "tiny" / "runs").exists()


def test_readme_documents_exit_codes_and_constraints():
    text = (REPO / "README.md").read_text()
    assert "129/130/143" in text and "--strict" in text
    assert "pip install -e '.[test]' -c constraints/tested.txt" in text


def _lower_bounds() -> dict[str, str]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in project["optional-dependencies"].values():
        reqs += extra
    out = {}
    for req in reqs:
        m = re.match(r"^([A-Za-z0-9_.-]+)\s*>=\s*([0-9][^,;\s]*)", req)
        if m:
            out[m.group(1)] = m.group(2)
    return out


def test_installed_versions_satisfy_every_lower_bound():
    from importlib.metadata import PackageNotFoundError, version

    from packaging.version import Version

    bounds = _lower_bounds()
    assert bounds["mcap"] == "1.5"
    for name, low in bounds.items():
        try:
            have = version(name)
        except PackageNotFoundError:
            continue  # an optional extra that is not installed here
        assert Version(have) >= Version(low), f"{name} {have} < {low}"


def _pins() -> dict[str, str]:
    """constraints/tested.txt as {normalised name: version}."""
    from packaging.utils import canonicalize_name

    pins: dict[str, str] = {}
    for line in (REPO / "constraints" / "tested.txt").read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, sep, ver = line.partition("==")
        assert sep and ver.strip(), f"constraints/tested.txt: {line!r} is not name==version"
        key = canonicalize_name(name.strip())
        assert key not in pins, f"constraints/tested.txt pins {name} twice"
        pins[key] = ver.strip()
    return pins


def _declared(extras: tuple[str, ...] = ("test", "dask")):
    """The runtime requirements and those of the given extras, as packaging Requirements."""
    from packaging.requirements import Requirement

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for extra in extras:
        reqs += project["optional-dependencies"][extra]
    return [Requirement(r) for r in reqs]


def test_constraints_pin_every_declared_dependency_within_its_bounds():
    """The pins reproduce the tested environment: every runtime and test requirement is
    pinned, to a version its bounds in pyproject.toml admit. No installed version is
    compared here, so a new release on the registry cannot fail this test."""
    from packaging.utils import canonicalize_name
    from packaging.version import Version

    pins = _pins()
    for ver in pins.values():
        Version(ver)  # every pin is a valid version
    for req in _declared():
        name = canonicalize_name(req.name)
        assert name in pins, f"constraints/tested.txt does not pin {req.name}"
        assert req.specifier.contains(pins[name], prereleases=True), \
            f"constraints/tested.txt pins {req.name}=={pins[name]}, outside {req}"


@pytest.mark.skipif(os.environ.get("HMPC_PINNED") != "1",
                    reason="opt-in: after pip install -e '.[test]' -c constraints/tested.txt, "
                           "run HMPC_PINNED=1 pytest (or .ci/pinned)")
def test_the_pinned_environment_is_the_installed_one():
    """Opt-in (.ci/pinned): the environment under test is exactly the pinned one."""
    from importlib.metadata import PackageNotFoundError, version

    for name, pinned in _pins().items():
        try:
            assert version(name) == pinned, name
        except PackageNotFoundError:
            pytest.fail(f"constraints/tested.txt pins {name}, which is not installed")


@pytest.mark.slow
def test_a_crash_inside_the_loop_is_one_line_exit_1_with_its_traceback_on_disk(
        tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app
    from hmpc_cli.run.loop import ClosedLoop

    calls = {"n": 0}
    real = ClosedLoop.run

    def crash_later(self, *args, **kwargs):
        calls["n"] += 1
        self.log.state = _boom  # the first logged state sample crashes the run
        return real(self, *args, **kwargs)

    monkeypatch.setattr(ClosedLoop, "run", crash_later)
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(out), "-q", "--set",
                                   "sim.duration=0.2"])
    assert res.exit_code == 1, res.output
    assert "Traceback" not in res.stderr
    err = res.stderr.strip().splitlines()
    assert err[0].startswith("error: the run crashed at t = ") and "ZeroDivisionError" in err[0]
    assert str(out) in err[1] and len(err) == 2
    assert "ZeroDivisionError" in (out / "error.txt").read_text()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reason"].startswith("ZeroDivisionError") and not summary["success"]


def _boom(*args, **kwargs):
    return 1 / 0


@pytest.mark.parametrize("summary_too", [False, True], ids=["log", "log and summary"])
def test_a_full_disk_inside_the_loop_names_only_the_files_written_exit_2(
        tmp_path, monkeypatch, summary_too):
    """A full disk is the environment's (exit 2, no traceback file); the second line names
    what the run directory really holds (it promised summary.json and error.txt that a
    full disk had not let exist)."""
    import errno

    from typer.testing import CliRunner

    import hmpc_cli.run.runner as runner
    from hmpc_cli.cli.app import app
    from hmpc_cli.run.loop import ClosedLoop

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", "run.mcap")

    real = ClosedLoop.run

    def full_later(self, *args, **kwargs):
        self.log.state = full
        return real(self, *args, **kwargs)

    monkeypatch.setattr(ClosedLoop, "run", full_later)
    if summary_too:
        monkeypatch.setattr(runner, "_write_summary", full)
    out = tmp_path / "run"
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(out), "-q", "--set",
                                   "sim.duration=0.2"])
    assert res.exit_code == 2, res.output
    err = res.stderr.strip().splitlines()
    assert err[0].startswith("error: the run stopped at t = ")
    assert err[0].endswith(" s: cannot write: run.mcap: No space left on device")
    held = "its log (run.mcap) is" if summary_too else "its log (run.mcap) and summary.json are"
    assert err[1:] == [f"error: {held} in {out}"]
    assert not (out / "error.txt").exists()
    assert (out / "summary.json").exists() is not summary_too


def test_a_crash_while_setting_up_is_an_internal_error_traceback_only_with_v(
        tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from hmpc_cli.run import runner
    from hmpc_cli.cli.app import app

    def broken(*args, **kwargs):
        raise TypeError("an unexpected bug")

    monkeypatch.setattr(runner, "prepare", broken)
    args = ["run", str(BALL), "--out", str(tmp_path / "r"), "-q"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 1 and "Traceback" not in res.stderr, res.output
    assert res.stderr.splitlines()[0] == "error: internal error: TypeError: an unexpected bug"
    assert "run again with -v" in res.stderr
    verbose = CliRunner().invoke(app, [*args[:-1], "-v"])
    assert verbose.exit_code == 1 and "Traceback" in verbose.stderr
    assert not (tmp_path / "r").exists()


def test_sigint_while_the_controllers_are_built_says_so_and_exits_130(tmp_path):
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "-m", "hmpc_cli", "run", str(BALL), "--out",
                             str(tmp_path / "run"), "-q"], cwd=tmp_path, env=cli_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60  # hmpc's handlers in place: it is setting up
    while time.monotonic() < deadline and not signal_handlers_installed(proc.pid):
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "Aborted" not in err
    assert "interrupted (SIGINT)" in err
    assert not (tmp_path / "run" / "run.mcap").exists() or "partial log" in err


def test_no_help_text_holds_what_rich_markup_would_eat():
    """``[s]`` in an option's help or a command's text is a rich markup tag: --help drops
    it (the --every and --view units were lost so); units are written (s), in m."""
    import typer
    from typer.testing import CliRunner

    from hmpc_cli.cli.app import app

    command = typer.main.get_command(app)
    texts = [(name, p.name if p is not None else "(text)",
              (sub.help if p is None else getattr(p, "help", None)) or "")
             for name, sub in command.commands.items() for p in [*sub.params, None]]
    assert len(texts) > 50
    assert [(c, p, m.group()) for c, p, text in texts
            for m in re.finditer(r"\[[^\[\]]*\]", text)] == []
    shown = " ".join(CliRunner().invoke(app, ["plot", "--help"], env={"COLUMNS": "200"})
                     .output.split())
    assert "snapshots (s)" in shown and '"x0,x1,y0,y1" in m' in shown


def test_a_full_disk_before_anything_is_logged_keeps_nothing_and_frees_out(tmp_path,
                                                                          monkeypatch):
    """The log's header cannot be written: the error said nothing was written while the
    claimed run.mcap and scenario.toml stayed, and the same --out was then refused ("already
    holds a run"); now nothing is kept, and a retry into it runs."""
    import errno

    from typer.testing import CliRunner

    import hmpc_cli.run.runner as runner
    from hmpc_cli.cli.app import app

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", "run.mcap")

    monkeypatch.setattr(runner, "Recorder", full)
    out = tmp_path / "run"
    args = ["run", str(BALL), "--out", str(out), "-q", "--set", "sim.duration=0.05"]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2, res.output
    assert res.stderr.strip().splitlines() == [
        "error: the run stopped at t = 0.000 s: cannot write: run.mcap: No space left on device",
        f"error: nothing of the run could be kept in {out} (--out can be used again)"]
    assert list(out.iterdir()) == []
    monkeypatch.undo()
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 0, again.output


def test_help_shows_no_value_type_beside_a_flag_and_fits_80_columns():
    """Typer's help printed `<bool>` beside flags and `<int>` beside -v, which read as if
    they took a value (`--strict true` is an error); `hmpc report --help` at 80 columns cut
    an option's name (`--fig3-reference-e…`)."""
    env = {**cli_env(), "COLUMNS": "80"}
    run = subprocess.run([sys.executable, "-m", "hmpc_cli", "run", "--help"], env=env,
                         capture_output=True, text=True, timeout=120)
    rows = {line.split()[1]: line for line in run.stdout.splitlines()
            if line.startswith("│ --")}
    for flag in ("--quiet", "--live", "--strict", "--verbose", "--help"):
        assert "<" not in rows[flag], rows[flag]
    # options that take a value say so, in words where the type alone says little
    assert "<int>" in rows["--seed"] and "KEY.PATH=VALUE" in rows["--set"]
    assert "DIR" in rows["--out"] and "list[" not in run.stdout
    report = subprocess.run([sys.executable, "-m", "hmpc_cli", "report", "--help"], env=env,
                            capture_output=True, text=True, timeout=120)
    names = [line.split()[1] for line in report.stdout.splitlines() if line.startswith("│ --")]
    assert "--fig3-reference-extra" in names and not any("…" in n for n in names), names
