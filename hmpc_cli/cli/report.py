"""``hmpc report``: run the paper's sweeps (resumably), draw their figures, write the page."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hmpc_cli.core.paths import path_option

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
DEFAULT_AUTHORS = Path("results/authors")  # the authors' Figure 3 data, committed
#: the robustness study's sweeps: paper geometry, a moved geometry, solve latency charged
#: (0.05 s: about one solve here; 0.03 s: the largest the undisturbed ball survives), and
#: the real-time iterations with time paused and with their modelled compute time charged
ROBUSTNESS = (Path("sweeps/robustness.toml"), Path("sweeps/robustness_tube.toml"),
              Path("sweeps/robustness_moved.toml"), Path("sweeps/robustness_moved_tube.toml"),
              Path("sweeps/robustness_latency.toml"), Path("sweeps/robustness_latency_30ms.toml"),
              Path("sweeps/robustness_realtime_paused.toml"),
              Path("sweeps/robustness_realtime.toml"))
REALTIME = (Path("sweeps/realtime_rti.toml"), Path("sweeps/realtime_ipopt.toml"),
            Path("sweeps/realtime_biped.toml"), Path("sweeps/realtime_biped_rti.toml"))


#: the options of ``hmpc report`` (its signature below)
_Results = Annotated[Path, typer.Option(
    "--results", metavar="DIR", help="results directory (page: <results>/README.md)",
    parser=path_option)]
_Fig3 = Annotated[str | None, typer.Option(
    "--fig3", metavar="SWEEP", help="Figure 3 sweep file ('' to leave out)")]
_Fig3Extra = Annotated[str | None, typer.Option(
    "--fig3-extra", metavar="SWEEP", help="extra Figure 3 panel sweep (100 Hz; '' to leave out)")]
_Fig3Reference = Annotated[str | None, typer.Option(
    "--fig3-reference", metavar="SWEEP", help="Figure 3 sweep in reference mode ('' to leave out)")]
_Fig3ReferenceExtra = Annotated[str | None, typer.Option(
    "--fig3-reference-extra", metavar="SWEEP", help="its 100 Hz panels ('' to leave out)")]
_Fig3Schedule = Annotated[str | None, typer.Option(
    "--fig3-schedule", metavar="SWEEP",
    help="Figure 3 sweep flying the authors' plan ('' to leave out)")]
_Authors = Annotated[str | None, typer.Option(
    "--authors", metavar="DIR",
    help="directory of the authors' Figure 3 CSVs (fig3_*.csv) for the "
    "trial-by-trial comparison (default: results/authors if it exists; '' to leave "
    "out)")]
_Robustness = Annotated[list[str] | None, typer.Option(
    "--robustness", metavar="SWEEP",
    help="robustness study sweep file or output directory, repeatable "
    "(default: sweeps/robustness.toml, robustness_tube.toml, robustness_moved.toml, "
    "robustness_moved_tube.toml, robustness_latency.toml, robustness_latency_30ms.toml, "
    "robustness_realtime_paused.toml and robustness_realtime.toml; '' to leave out)")]
_Biped = Annotated[str | None, typer.Option(
    "--biped", metavar="FILE", help="biped scenario for Figure 4 ('' to leave out)")]
_Fig3Trials = Annotated[str | None, typer.Option(
    "--fig3-trials", metavar="SWEEP",
    help="a Figure 3 sweep tabled trial by trial against the authors' "
    "failures, from its table alone ('' to leave out)")]
_BipedPush = Annotated[str | None, typer.Option(
    "--biped-push", metavar="SWEEP",
    help="the biped's push study: sweep file or output directory ('' to "
    "leave out)")]
_Realtime = Annotated[list[str] | None, typer.Option(
    "--realtime", metavar="SWEEP",
    help="real-time sweep file or output directory, repeatable (default: "
    "sweeps/realtime_rti.toml, realtime_ipopt.toml, realtime_biped.toml and "
    "realtime_biped_rti.toml; '' to leave out)")]
_Run = Annotated[bool, typer.Option(
    "--run/--no-run", help="run the missing sweep runs first (finished ones are skipped; "
    "default: run nothing, print what is missing)")]
_Workers = Annotated[int | None, typer.Option(
    "--workers", metavar="N", min=1, help="worker processes (default: all cores)")]
_Seeds = Annotated[int | None, typer.Option(
    "--seeds", metavar="N",
    help="robustness study: only its first N seeds (resume later with more)")]
_Replace = Annotated[bool, typer.Option(
    "--replace", help="replace a page of <results> generated with other sections")]


def report_command(
    results: _Results = Path("results"),
    fig3: _Fig3 = "sweeps/fig3.toml",
    fig3_extra: _Fig3Extra = "sweeps/fig3_100hz.toml",
    fig3_reference: _Fig3Reference = "sweeps/fig3_reference.toml",
    fig3_reference_extra: _Fig3ReferenceExtra = "sweeps/fig3_reference_100hz.toml",
    fig3_schedule: _Fig3Schedule = "sweeps/fig3_reference_schedule.toml",
    authors: _Authors = None,
    robustness: _Robustness = None,
    biped: _Biped = "scenarios/biped_stairs.toml",
    fig3_trials: _Fig3Trials = "sweeps/fig3_reference_rule.toml",
    biped_push: _BipedPush = "sweeps/biped_push.toml",
    realtime: _Realtime = None,
    run: _Run = False,
    workers: _Workers = None,
    seeds: _Seeds = None,
    replace: _Replace = False,
) -> None:
    """Regenerate the results page: Figure 3 (both modes, beside the paper), robustness, Fig. 4.

    Each sweep option takes a sweep file (its runs: <results>/sweeps/<name>) or a sweep's
    output directory (read as it is, never run).
    """
    from hmpc_cli.cli.common import checked_output

    checked_output(results, "--results")  # before anything is read, run or written
    if not replace:
        _refuse_another_page(results)
    files = _parts(dict(fig3=fig3, fig3_extra=fig3_extra, fig3_reference=fig3_reference,
                        fig3_reference_extra=fig3_reference_extra,
                        fig3_schedule=fig3_schedule, biped_push=biped_push,
                        fig3_trials=fig3_trials), realtime=realtime, robustness=robustness)
    plans, dirs = _sweeps(results, seeds, _given(biped), files)
    from hmpc_cli.cli.common import is_quiet

    if not run:
        _refuse_stale_tables(plans, dirs)
        if not is_quiet():
            _print_missing(plans, dirs)
    lost = _run_sweeps(plans, dirs, workers) if run else []
    biped_dir = _biped_run(_given(biped), results, run)
    _write_page(results, dirs, biped_dir, _authors_dir(authors), plans,
                files | {"biped": _given(biped)})
    if lost:  # the page holds every finished run; these are missing from it
        for line in lost:
            typer.echo(f"error: worker failed, run not recorded (rerun to retry): {line}",
                       err=True)
        raise typer.Exit(EXIT_FAILED)


#: options that change how a page is made, not what it shows
_HOW = {"--run", "--no-run", "--workers", "--seeds", "--replace", "-q", "--quiet", "-v",
        "-vv", "--verbose"}


#: options of :data:`_HOW` that take no value
_FLAGS = _HOW - {"--workers", "--seeds"}


def _sections(args: list[str]) -> dict[str, list[str]]:
    """What a report command's arguments show: {option: values} for every section option.

    Options of :data:`_HOW` are left out (short flags combined too: ``-qv``); an option
    with a default that is not None and not given has it, so the order of the options,
    ``--opt=value`` against ``--opt value``, such a default given explicitly and
    ``./path`` against ``path`` make no difference. (``--authors``, ``--robustness`` and
    ``--realtime`` find their defaults when the page is made: given or not, they differ.)
    """
    import inspect
    import os
    import re

    shown: dict[str, list[str]] = {}
    for name, p in inspect.signature(report_command).parameters.items():
        option = "--" + name.replace("_", "-")
        if option not in _HOW and p.default is not None:
            shown[option] = [os.path.normpath(str(p.default)) if p.default else ""]
    given: dict[str, list[str]] = {}
    k = 0
    while k < len(args):
        name, eq, value = args[k].partition("=")
        flag = name in _FLAGS or re.fullmatch(r"-[qv]+", name) is not None
        if not eq and not flag and k + 1 < len(args):
            value, k = args[k + 1], k + 1
        k += 1
        if name not in _HOW and not flag:
            given.setdefault(name, []).append(os.path.normpath(value) if value else value)
    return shown | given


def _refuse_another_page(results: Path) -> None:
    """Exits 2 if ``<results>/README.md`` is not a page this command would regenerate.

    That is another file, or a page generated with other sections (``--replace``
    replaces it).
    """
    import shlex
    import sys

    from hmpc_cli.report.page import page_command
    from hmpc_cli.report.paths import portable_command

    page = results / "README.md"
    try:
        made = page_command(page.read_text(errors="replace"))
    except OSError:
        return  # no page (or an unreadable one: the write reports it)
    try:
        before = shlex.split(made)[2:] if made is not None else None
    except ValueError:
        before = None
    now = shlex.split(portable_command(shlex.join(["hmpc", *sys.argv[1:]])))[2:]
    if before is not None and _sections(before) == _sections(now):
        return
    what = (f"was generated by `{made}`, with other sections" if before is not None
            else "is not a page hmpc report wrote")
    typer.echo(f"error: --results {results}: {page} {what}; this command would replace it "
               f"and the figures in {results / 'report'}: write the page elsewhere "
               f"(--results DIR, a new directory) or pass --replace", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def _sweeps(results: Path, seeds: int | None, biped: Path | None,
            files: dict[str, Path | None]) -> tuple[dict, dict[str, Path]]:
    """The sweep plans to run and every part's output directory.

    A sweep file runs into ``<results>/sweeps/<name>``; a directory is a sweep's output,
    read as it is; '' leaves a part out.

    Raises:
        typer.Exit: an invalid sweep file, a directory that is not a sweep's output, or
            nothing to report (exit code 2).
    """
    from hmpc_cli.sweep.lock import is_sweep_output

    given = {k: v if v.name not in ("", "..") else v.resolve()  # its name names its section
             for k, v in files.items() if v is not None and v.is_dir()}
    bad = [f"{_option(k)} {v}: not a sweep's output directory (no results.csv or "
           "sweep.toml); give a sweep file to run it, or the directory `hmpc sweep --out` "
           "wrote" for k, v in given.items() if not is_sweep_output(v)]
    if bad:
        _echo_errors(bad)
        raise typer.Exit(EXIT_BAD_INPUT)
    plans = _plan_sweeps({k: v for k, v in files.items() if k not in given}, seeds)
    _refuse_shared_names(plans, results)
    if not plans and not given and biped is None:
        typer.echo("error: nothing to report (every sweep option and --biped are empty)",
                   err=True)
        raise typer.Exit(EXIT_BAD_INPUT)
    return plans, {k: results / "sweeps" / p.spec.name for k, p in plans.items()} | given


def _refuse_shared_names(plans: dict, results: Path) -> None:
    """Exit 2 when two different sweep files have one ``name`` (one output directory).

    Both would run into ``<results>/sweeps/<name>``, and the first section would show
    the second sweep's runs.
    """
    first: dict[str, tuple[str, Path]] = {}  # name -> (part, sweep file)
    lines = []
    for key, plan in plans.items():
        name = plan.spec.name
        seen = first.setdefault(name, (key, plan.path))
        if Path(seen[1]).resolve() != Path(plan.path).resolve():
            lines.append(f"{_option(seen[0])} {seen[1]} and {_option(key)} {plan.path}: both "
                         f"sweep files are named {name!r} and would share "
                         f"{results / 'sweeps' / name}; give one of them another name")
    if lines:
        _echo_errors(lines)
        raise typer.Exit(EXIT_BAD_INPUT)


def _print_missing(plans: dict, dirs: dict[str, Path]) -> None:
    """Prints, per sweep, how many runs are missing and their simulated time (an estimate).

    A run is there when its run directory is finished or its sweep's table stands for it
    (:func:`hmpc_cli.sweep.table.finished_runs`: a committed table has no run logs).
    """
    import tomllib

    from hmpc_cli.sweep.table import finished_runs

    total = 0
    for key, plan in plans.items():
        done = finished_runs(plan, dirs[key].resolve())
        missing = [r for r in plan.selected if done[r.run_id] is None]
        if not missing:
            continue
        total += len(missing)
        duration: dict[tuple, float] = {}  # per cell: its runs differ in the seed only
        sim = 0.0
        for r in (r for r in missing if r.toml):
            cell = tuple(map(repr, r.cell))
            if cell not in duration:
                duration[cell] = float(
                    tomllib.loads(r.toml).get("sim", {}).get("duration", 0.0) or 0.0)
            sim += duration[cell]
        typer.echo(f"note: {plan.path}: {len(missing)} of {len(plan.selected)} runs missing "
                   f"({sim:g} s of simulated time, several times that in wall time)",
                   err=True)
    if total:
        typer.echo(f"note: nothing was run; `hmpc report --run` runs the {total} missing "
                   "runs (resumable), then writes the page", err=True)


def _refuse_stale_tables(plans: dict, dirs: dict[str, Path]) -> None:
    """Exit 2 when a sweep file's table is not a table of its runs (the file was edited).

    Drawn as it stands, such a table would be shown as the sweep file's results
    (:func:`hmpc_cli.sweep.table.stale_table` says why it is not). ``--run`` rewrites it;
    the directory given instead of the file draws it as it is.
    """
    from hmpc_cli.sweep.table import stale_table

    lines = []
    for key, plan in plans.items():
        why = stale_table(plan, dirs[key].resolve())
        if why is not None:
            table = dirs[key] / "results.csv"
            lines.append(f"{_option(key)} {plan.path}: {table} is not this sweep file's "
                         f"table: {why}; `hmpc report --run` rewrites it from the runs that "
                         f"stand (running the missing ones first), or give the directory "
                         f"({_option(key)} {dirs[key]}) to draw it as it is")
    if lines:
        _echo_errors(lines)
        raise typer.Exit(EXIT_BAD_INPUT)


def _parts(single: dict[str, str | None], **repeated: list[str] | None
           ) -> dict[str, Path | None]:
    """The sweep options' paths per report part (None: left out).

    The repeatable options' parts are ``realtime:<i>`` and ``robustness:<i>`` (their
    defaults when not given).
    """
    defaults = {"realtime": REALTIME, "robustness": ROBUSTNESS}
    parts = {k: _given(v) for k, v in single.items()}
    for name, values in repeated.items():
        given = map(str, defaults[name]) if values is None else values
        parts |= {f"{name}:{i}": _given(v) for i, v in enumerate(given)}
    return parts


def _option(key: str) -> str:
    """The option of a report part: ``robustness:2`` -> ``--robustness``."""
    return "--" + key.split(":")[0].replace("_", "-")


def _given(value: str | None) -> Path | None:
    """An optional input's path: None when left out (no value, or '').

    The options are strings: typer turns a Path option's '' into '.', the current
    directory, which is an input of its own.
    """
    return None if value is None or value == "" else Path(value)


def _echo_errors(lines: list[str]) -> None:
    """Prints one ``error: ...`` line per problem on stderr."""
    for line in lines:
        typer.echo(f"error: {line}", err=True)


def _plan_sweeps(files: dict[str, Path | None], seeds: int | None) -> dict:
    """Reads and validates the sweep files that are not left out.

    Args:
        files: sweep file per report part (``fig3``, ``fig3_extra``, ``robustness:<i>``...).
        seeds: the robustness study runs only its first ``seeds`` seeds (None: all).

    Returns:
        The :class:`~hmpc_cli.sweep.plan.SweepPlan` per part given, in the order of ``files``.

    Raises:
        typer.Exit: a sweep file is invalid (exit code 2, its problems printed).
    """
    from hmpc_cli.run.scenario import ScenarioError
    from hmpc_cli.sweep.plan import first_seeds, plan_sweep

    plans = {}
    for key, path in files.items():
        if path is None:
            continue
        try:
            plans[key] = plan_sweep(path)
            if key.startswith("robustness"):
                plans[key] = first_seeds(plans[key], seeds)
        except ScenarioError as exc:  # each line names the file: say which option too
            _echo_errors([f"{_option(key)} {line}" for line in exc.lines])
            raise typer.Exit(EXIT_BAD_INPUT) from None
    return plans


def _run_sweeps(plans: dict, dirs: dict[str, Path], workers: int | None) -> list[str]:
    """Runs each sweep's unfinished runs (finished ones are skipped), prints its cells.

    Args:
        plans: sweep plan per report part.
        dirs: output directory per report part.
        workers: worker processes (None: all cores).

    Returns:
        One line per run a worker lost: ``<sweep name>: <run id>: <reason>``.

    Raises:
        typer.Exit: stopped by a signal (exit code 128 + its number, the line saying how
            many of the missing runs finished; the same command resumes).
    """
    import os

    from hmpc_cli.cli.common import is_quiet
    from hmpc_cli.cli.sweep import _locked_execute, _print_cells
    from hmpc_cli.core.signals import Interrupted, as_interrupted

    _check_owners(plans, dirs)
    missing = _check_missing(plans, dirs)
    lost: list[str] = []
    done = 0
    try:
        for key, plan in plans.items():
            # the sweep's lock: another hmpc sweep writing there is refused (exit 2)
            outcome = _locked_execute(plan, dirs[key], workers or os.cpu_count() or 1, None)
            done += outcome.ran
            if not is_quiet():
                _print_cells(plan, dirs[key])
            lost += [f"{plan.spec.name}: {x}" for x in outcome.lost]
            if outcome.interrupted:
                raise Interrupted(outcome.signum)
    except KeyboardInterrupt as exc:
        _echo_errors([f"worker failed, run not recorded (rerun to retry): {x}" for x in lost])
        _stopped(as_interrupted(exc), f"{done} of {missing} missing runs done")
    return lost


def _check_owners(plans: dict, dirs: dict[str, Path]) -> None:
    """Exit 2 (nothing run) when a sweep's directory is another's or no sweep's.

    ``hmpc sweep``'s check of ``--out`` (:func:`hmpc_cli.sweep.lock.owner_problem`).
    """
    from hmpc_cli.sweep.lock import owner_problem

    lines = []
    for key, plan in plans.items():
        problem = owner_problem(dirs[key], plan.spec.name, "--results", plan.text)
        if problem is not None:
            lines.append(f"{_option(key)} {plan.path}: {dirs[key]}: {problem}")
    if lines:
        _echo_errors(lines)
        raise typer.Exit(EXIT_BAD_INPUT)


def _stopped(stop, what: str) -> None:
    """Exits 128 + the signal number with one line: ``interrupted: <what>; ...``."""
    typer.echo(f"interrupted: {what}; run the same command again to resume", err=True)
    raise typer.Exit(stop.exit_code) from None


def _check_missing(plans: dict, dirs: dict[str, Path]) -> int:
    """``hmpc sweep``'s set-up checks of the runs still to run, before any runs.

    Exit 2 with every problem; warnings (a margins file for another setting) on stderr.
    Returns the number of runs still to run.
    """
    from hmpc_cli.cli.sweep import cell_checks
    from hmpc_cli.sweep.table import finished_runs

    problems: list[str] = []
    count = 0
    for key, plan in plans.items():
        done = finished_runs(plan, dirs[key].resolve())
        missing = [r for r in plan.selected if done[r.run_id] is None]
        count += len(missing)
        found, warnings = cell_checks(plan, missing) if missing else ([], [])
        problems += found
        for line in warnings:
            typer.echo(f"warning: {line}", err=True)
    if problems:
        for line in problems:
            typer.echo(f"error: {line}", err=True)
        raise typer.Exit(EXIT_BAD_INPUT)
    return count


def _authors_dir(value: str | None) -> tuple[Path | None, str]:
    """The authors' data directory and, when there is none, the page's note saying so.

    Raises:
        typer.Exit: an explicitly given directory that does not exist (exit code 2).
    """
    if value is None:
        if DEFAULT_AUTHORS.is_dir():
            return DEFAULT_AUTHORS, ""
        return None, (f"The authors' data ({DEFAULT_AUTHORS}) was not found: the "
                      "trial-by-trial comparison is left out (`hmpc report --authors DIR`).")
    path = _given(value)
    if path is None:
        return None, ""
    if not path.is_dir():
        typer.echo(f"error: --authors: {path}: no such directory", err=True)
        raise typer.Exit(EXIT_BAD_INPUT)
    return path, ""


def _write_page(results: Path, dirs: dict[str, Path], biped_dir: Path | None,
                authors: tuple[Path | None, str] = (None, ""),
                plans: dict | None = None, given: dict[str, Path | None] | None = None
                ) -> None:
    """Draws the figures from the finished runs and writes ``<results>/README.md``.

    Args:
        results: results directory.
        dirs: sweep output directory per report part given.
        biped_dir: run directory of the biped scenario (None: no Figure 4).
        authors: the authors' data directory (None: none) and the page's note about it.
        plans: the sweep plan per part given as a sweep file (resume commands, seeds).
        given: the path given per part (its option's value, for errors; ``biped``: the
            scenario).

    Raises:
        typer.Exit: a figure's input is unusable (exit code 2; nothing written).
    """
    import shlex
    import sys

    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.report.page import ReportInputs, write_report

    from hmpc_cli.report.robustness import Study

    plans = plans or {}
    studies = tuple(Study(d, plans[k].path if k in plans else None,
                          len(plans[k].spec.seeds) if k in plans else None)
                    for k, d in dirs.items() if k.startswith("robustness"))
    inputs = ReportInputs(dirs.get("fig3"), dirs.get("fig3_extra"), studies or None,
                          biped_dir, dirs.get("fig3_reference"),
                          dirs.get("fig3_reference_extra"), *authors,
                          dirs.get("fig3_schedule"), dirs.get("biped_push"),
                          dirs.get("fig3_trials"),
                          tuple(d for k, d in dirs.items() if k.startswith("realtime:")))
    try:
        page = write_report(results, inputs, shlex.join(["hmpc", *sys.argv[1:]]))
    except FigureInputError as exc:
        where = dirs | ({"biped": biped_dir} if biped_dir is not None else {}) \
            | ({"authors": authors[0]} if authors[0] is not None else {})
        typer.echo(f"error: {_attributed(exc, where, given or {})}", err=True)
        raise typer.Exit(EXIT_BAD_INPUT) from None
    from hmpc_cli.cli.common import is_quiet

    typer.echo(str(page) if is_quiet() else f"wrote {page} and {results / 'report'}/")


def _attributed(exc: Exception, dirs: dict[str, Path], given: dict[str, Path | None]) -> str:
    """A figure input's error prefixed with the option (and value) it came from, if known.

    ``exc.source``: the input directory that failed
    (:func:`hmpc_cli.analysis.tables.blamed_on`).
    """
    source = getattr(exc, "source", None)
    key = next((k for k, d in dirs.items() if source is not None and d == source), None)
    if key is None:
        return str(exc)
    text = f"{_option(key)} {given.get(key) or dirs[key]}: {exc}"
    if "missing column" in text and key not in ("authors", "biped"):
        text += (f": not the table of the sweep {_option(key)} draws; give that sweep's file "
                 "or output directory (`hmpc report --help` names the default)")
    return text


def _biped_run(scenario: Path | None, results: Path, run: bool) -> Path | None:
    """Runs the biped scenario into results/<name>/report (unless done); its directory."""
    if scenario is None:
        return None
    from hmpc_cli.run.runner import prepare
    from hmpc_cli.run.runner import execute_run
    from hmpc_cli.run.scenario import ScenarioError, load_scenario

    try:
        sc, toml_text = load_scenario(scenario)
    except ScenarioError as exc:
        _echo_errors(exc.lines)
        raise typer.Exit(EXIT_BAD_INPUT) from None
    from hmpc_cli.sweep.table import finished_in

    out = results / sc.name / "report"
    if run and finished_in(out, toml_text) is None:
        if out.exists():
            import shutil

            shutil.rmtree(out)
        from hmpc_cli.cli.common import is_quiet

        if not is_quiet():
            typer.echo(f"{sc.name}: running -> {out}")
        try:
            execute_run(prepare(sc), toml_text, out)
        except KeyboardInterrupt as exc:
            from hmpc_cli.core.signals import as_interrupted

            _stopped(as_interrupted(exc), f"the run of {scenario} into {out} did not finish")
        except (ValueError, RuntimeError) as exc:
            typer.echo(f"error: {scenario}: {' '.join(str(exc).split())[:300]}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
    return out
