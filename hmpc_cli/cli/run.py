"""``hmpc run``: one scenario in closed loop, logged to MCAP, its summary printed."""

from __future__ import annotations

import json
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any

import typer

from hmpc_cli.cli.common import complete_set_key
from hmpc_cli.core.paths import path_option

__all__ = ["real_time_text", "run_command"]

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


def _err(lines: list[str]) -> None:
    for line in lines:
        typer.echo(f"error: {line}", err=True)


def run_command(
    scenario: Annotated[Path, typer.Argument(metavar="SCENARIO", help="scenario TOML file")],
    out: Annotated[Path | None, typer.Option(
        "--out", metavar="DIR", help="run directory (default "
        "results/<name>/<time>-seed<N>, name the scenario's)",
        parser=path_option)] = None,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", metavar="KEY.PATH=VALUE", help="override a setting (repeatable)",
        autocompletion=complete_set_key)] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="override the seed")] = None,
    quiet: Annotated[bool, typer.Option(
        "--quiet", "-q", help="no progress bar, no summary table: errors and the log's path "
        "only")] = False,
    live: Annotated[bool, typer.Option(
        "--live", help="also stream the log's topics to a Foxglove WebSocket server on "
        "127.0.0.1 (needs foxglove-sdk), paced to real time")] = False,
    live_port: Annotated[int | None, typer.Option(
        "--live-port", help="port of the --live server (default 8765; 0: any free "
        "port)")] = None,
    strict: Annotated[bool, typer.Option(
        "--strict", help="exit 1 when the run's task fails (success false)")] = False,
) -> None:
    """Run the layered controller in closed loop and log everything to MCAP.

    SIGINT, SIGTERM and SIGHUP stop the run within one simulator step: the log is closed, summary.json says "interrupted (SIGTERM)", stderr names the partial log, and the exit code is 128 + the signal number.

    When stdout is not a terminal, a finished run's log path is also printed whole on the last line; with -q it is the only line printed on stdout.
    """  # noqa: E501 (Typer's help rewraps a paragraph; a line break would stay in it)
    from hmpc_cli.core.signals import as_interrupted, handle_signals
    from hmpc_cli.log.live import port_problem

    if live_port is not None and (problem := "needs --live" if not live else
                                  port_problem(live_port)) is not None:
        _err([f"--live-port {live_port}: {problem}"])
        raise typer.Exit(EXIT_BAD_INPUT)
    try:
        with handle_signals():
            _run(scenario, out, set_ or [], seed, quiet, live,
                 8765 if live_port is None else live_port, strict)
    except KeyboardInterrupt as exc:
        stop = as_interrupted(exc)
        if not getattr(exc, "reported", False):  # stopped while setting up: say so
            typer.echo(f"interrupted ({stop.name}) while setting up; no run was started",
                       err=True)
        raise typer.Exit(stop.exit_code) from None


def _run(scenario: Path, out: Path | None, sets: list[str], seed: int | None, quiet: bool,
         live: bool, live_port: int, strict: bool = False) -> None:
    """The body of ``hmpc run`` (signal handlers installed)."""
    from hmpc_cli.run.scenario import (ScenarioError, attribute_to_sets, inert_settings,
                                       load_scenario, margins_file_warnings)

    try:
        sc, toml_text = load_scenario(scenario, sets, seed)
    except ScenarioError as exc:
        _err(exc.lines)
        from hmpc_cli.cli.common import VERBOSITY
        from hmpc_cli.core.registry import load_tracebacks

        for trace in load_tracebacks(exc.lines) if VERBOSITY[0] >= 1 else []:
            typer.echo(trace.rstrip("\n"), err=True)  # where the plug-in failed to import
        raise typer.Exit(EXIT_BAD_INPUT) from None
    for line in [*inert_settings(scenario, sets, sc), *attribute_to_sets(
            [f"{scenario}: {w}" for w in margins_file_warnings(sc)], str(scenario), sets,
            True)]:
        typer.echo(f"warning: {line}", err=True)
    from hmpc_cli.core.registry import PluginError
    from hmpc_cli.run.runner import out_problem, prepare

    check = out if out is not None else Path("results") / sc.name / "run"
    problem = out_problem(check)  # before the solvers are built
    if problem is not None:
        from hmpc_cli.core.paths import EmptyPath

        shown = '""' if isinstance(out, EmptyPath) else out
        _err([f"--out {shown}: {problem}" if out is not None else
              f"{check.parent}: {problem}"])
        raise typer.Exit(EXIT_BAD_INPUT)
    try:
        prepared = prepare(sc)
    except (PluginError, ValueError) as exc:
        _err(attribute_to_sets([f"{scenario}: {line}" for line in str(exc).splitlines()],
                               str(scenario), sets, True, _setup_caused(scenario, sets, seed),
                               anywhere=True))
        from hmpc_cli.cli.common import VERBOSITY

        if VERBOSITY[0] >= 1 and getattr(exc, "plugin_traceback", None):
            typer.echo(exc.plugin_traceback.rstrip("\n"), err=True)  # where in the plug-in
        raise typer.Exit(EXIT_BAD_INPUT) from None
    sink = _live_sink(live_port) if live else None  # before the run directory is made
    from hmpc_cli.log.runlog import Provenance

    provenance = Provenance(overrides=tuple(
        [*sets, *([f"seed={seed}"] if seed is not None else [])]))
    out, result = _claimed_run(out, prepared, sc, toml_text, quiet, sink, provenance)
    _report_finished(result, out, quiet)
    if strict and not result.success:
        _err([f"--strict: the run failed ({result.reason or 'task not achieved'}); its log: "
              f"{out / 'run.mcap'}"])
        raise typer.Exit(EXIT_FAILED)


def _claimed_run(out: Path | None, prepared, sc, toml_text: str, quiet: bool, sink,
                 provenance) -> tuple[Path, Any]:
    """Claims the run directory and runs into it; returns (the directory, the result).

    From the claim to the report a stop is only recorded where it arrives: the loop acts
    on it once its log is open (the log then ends where the run was stopped), the report
    once the run has finished. The --live ``sink`` is closed here.
    """
    from hmpc_cli.core.signals import deferred

    with deferred():
        try:
            out = _run_dir(out, sc)
            return out, _execute(prepared, sc, toml_text, out, quiet, sink, provenance)
        finally:
            if sink is not None:
                sink.close()


def _setup_caused(scenario: Path, sets: list[str], seed: int | None):
    """``caused(item, key)`` for a set-up problem of ``hmpc run``.

    True when the set-up checks report ``key`` with every ``--set`` and not without
    ``item``; a problem they do not reproduce is never a ``--set``'s.
    """
    from functools import cache

    from hmpc_cli.run.scenario import ScenarioError, load_scenario
    from hmpc_cli.run.setup_checks import setup_problems

    @cache
    def keys(items: tuple[str, ...]) -> frozenset[str] | None:
        try:
            sc, _ = load_scenario(scenario, list(items), seed)
        except ScenarioError:
            return None
        return frozenset(line.partition(": ")[0] for line in setup_problems(sc))

    def caused(item: str, key: str) -> bool:
        full = keys(tuple(sets))
        if full is None or key not in full:
            return False
        without = keys(tuple(o for o in sets if o is not item))
        return without is not None and key not in without

    return caused


def _report_finished(result, out: Path, quiet: bool) -> None:
    """Prints a finished run's summary (or, with -q, its log's path).

    A stop signal meanwhile, or one received after the run's last check, says that the
    run and its log are complete, then stops.
    """
    from hmpc_cli.core.signals import check

    try:
        check()
        if quiet:  # errors and the log's path only
            typer.echo(str(out / "run.mcap"))
        else:
            _print_summary(result, out)
            if not sys.stdout.isatty():
                typer.echo(str(out / "run.mcap"))
    except KeyboardInterrupt as exc:
        from hmpc_cli.core.signals import as_interrupted

        stop = as_interrupted(exc)
        typer.echo(f"interrupted ({stop.name}) after the run finished; its log is complete: "
                   f"{out / 'run.mcap'}", err=True)
        stop.reported = True
        raise stop from None


def _run_dir(out: Path | None, sc) -> Path:
    """The run directory: ``--out`` (refused if it holds a run) or a new unique default.

    The default ``results/<scenario>/<UTC time>-seed<N>`` is created atomically; a
    directory of the same name (two runs in one second) gets a suffix ``-2``, ``-3``...
    """
    from hmpc_cli.run.runner import RunDirTakenError, claim_run_dir

    if out is not None:
        try:  # exclusively: two runs into one --out never share it
            return claim_run_dir(out)
        except RunDirTakenError as exc:
            _err([str(exc)])
            raise typer.Exit(EXIT_BAD_INPUT) from None
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    base = Path("results") / sc.name / f"{stamp}-seed{sc.seed}"
    base.parent.mkdir(parents=True, exist_ok=True)
    for k in range(1, 10_000):
        path = base if k == 1 else base.with_name(f"{base.name}-{k}")
        try:
            path.mkdir()
        except FileExistsError:
            continue
        return path
    _err([f"{base}: cannot create a unique run directory"])
    raise typer.Exit(EXIT_BAD_INPUT)


def _live_sink(port: int):
    """The --live server (exit 2 with a clear message without foxglove-sdk)."""
    from hmpc_cli.log.live import LiveSink, LiveError

    try:
        sink = LiveSink(port)
    except LiveError as exc:
        _err([str(exc)])
        raise typer.Exit(EXIT_BAD_INPUT) from None
    typer.echo(f"live: connect Foxglove or Lichtblick to {sink.url}", err=True)
    return sink


def _execute(prepared, sc, toml_text: str, out: Path, quiet: bool, sink=None,
             provenance=None):
    from hmpc_cli.run.runner import execute_run

    progress = None  # -q: no progress bar, nothing of rich's to import
    if not quiet:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                            TextColumn("t = {task.fields[t]:.2f} s"), TimeElapsedColumn(),
                            transient=True)
    try:
        if progress is None:
            return execute_run(prepared, toml_text, out, None, sink, provenance)
        with progress:
            task = progress.add_task(sc.name, total=1.0, t=0.0)
            dur = sc.sim.duration

            def tick(i: int, n: int, note: str = "") -> None:
                if i % 20 == 0 or i == n:
                    desc = f"{sc.name} [yellow]({note})[/]" if note else sc.name
                    progress.update(task, completed=i / n, t=i / n * dur, description=desc)

            return execute_run(prepared, toml_text, out, tick, sink, provenance)
    except KeyboardInterrupt as exc:
        from hmpc_cli.core.signals import as_interrupted

        stop = as_interrupted(exc)
        typer.echo(f"interrupted ({stop.name}) at t = {prepared.result.t_end:.3f} s; partial log "
                   f"in {out / 'run.mcap'}", err=True)
        stop.reported = True
        raise stop from None
    except Exception as exc:  # a crash inside the loop: the log and summary are written
        _crashed(exc, prepared.result.t_end, out)


def _crashed(exc: Exception, t_end: float, out: Path) -> None:
    """Reports a run that crashed: one line, the traceback in ``out/error.txt``; exit 1.

    A full or read-only disk is the environment's (exit 2, no traceback). The second line
    names the files the run directory really holds (a write that failed leaves none).
    """
    import contextlib
    import traceback

    from hmpc_cli.cli.common import EXIT_INTERNAL, VERBOSITY
    from hmpc_cli.core.paths import disk_error, disk_error_text

    trace = "".join(traceback.format_exception(exc))
    disk = disk_error(exc)
    if disk and not _log_has_messages(out / "run.mcap"):  # nothing kept: --out free again
        for name in ("run.mcap", "scenario.toml", "summary.json"):
            with contextlib.suppress(OSError):
                (out / name).unlink(missing_ok=True)
    if not disk:
        try:  # the one-line report does not depend on it
            (out / "error.txt").write_text(trace, encoding="utf-8")
        except OSError:  # no empty or partial traceback left behind
            with contextlib.suppress(OSError):
                (out / "error.txt").unlink(missing_ok=True)
    if disk:
        first = f"the run stopped at t = {t_end:.3f} s: cannot write: {disk_error_text(exc)}"
    else:
        msg = " ".join(str(exc).split())[:300]
        first = f"the run crashed at t = {t_end:.3f} s: {type(exc).__name__}: {msg}"
    _err([first, _written_text(out)])
    if VERBOSITY[0] >= 1:
        typer.echo(trace.rstrip(), err=True)
    raise typer.Exit(EXIT_BAD_INPUT if disk else EXIT_INTERNAL)


#: what a run directory holds after a crash, as :func:`_written_text` names it
_WRITTEN = (("run.mcap", "its log (run.mcap)"), ("summary.json", "summary.json"),
            ("error.txt", "the traceback (error.txt)"))


def _log_has_messages(path: Path) -> bool:
    """Whether the run log at ``path`` holds a readable message (a header only: no)."""
    from hmpc_cli.log.reader import read_log

    try:
        return bool(read_log(path).messages)
    except (OSError, ValueError):
        return False


def _written_text(out: Path) -> str:
    """Which of a crashed run's files ``out`` holds (not empty), as one line."""
    held = [text if name != "run.mcap" or _log_has_messages(out / name) else
            "its log (run.mcap, no message)" for name, text in _WRITTEN
            if (out / name).is_file() and (out / name).stat().st_size > 0]
    if not held:
        return f"nothing of the run could be kept in {out} (--out can be used again)"
    listed = held[0] if len(held) == 1 else f"{', '.join(held[:-1])} and {held[-1]}"
    return f"{listed} {'is' if len(held) == 1 else 'are'} in {out}"


def real_time_text(rt: dict) -> str:
    """One line of a summary's ``real_time``: the charged solves against the MPC period.

    ``rt``: summary.json's object, or /run/summary's (a statistic of no solve left out).
    """
    from hmpc_cli.analysis.replay import ms_text as _ms

    text = (f"{rt['late_solves']} of {rt['charged_solves']} solves kept the solver busy "
            f"over the {_ms(rt['period'])} MPC period; charged median / p95 / max "
            f"{_ms(rt.get('delay_median'))} / {_ms(rt.get('delay_p95'))} / "
            f"{_ms(rt.get('delay_max'))}")
    if rt["dropped_solves"]:
        text += f"; {rt['dropped_solves']} dropped (over sim.solve_budget)"
    if rt["preempted_solves"]:
        text += f"; {rt['preempted_solves']} stopped by a contact"
    return text


def _print_summary(r, out: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    from hmpc_cli.analysis.replay import ms_text as _ms

    table = Table(title=f"{r.scenario} (seed {r.seed})", show_header=False)
    table.add_row("result", "[green]success[/]" if r.success else f"[red]failed[/]: {r.reason}")
    table.add_row("final distance to goal", f"{r.final_error:.4f}")
    table.add_row("simulated time", f"{r.t_end:.3f} s")
    table.add_row("contacts", f"{r.contacts} " + json.dumps(r.contacts_by_guard))
    table.add_row("MPC solves", str(r.solves))
    table.add_row("solve time median / p95 / max",
                  f"{_ms(r.solve_time_median)} / {_ms(r.solve_time_p95)} / {_ms(r.solve_time_max)}")
    if r.real_time is not None:
        table.add_row(f"compute time charged ({r.real_time['latency']})",
                      real_time_text(r.real_time))
    table.add_row("solver failures", f"{r.solver_failures} "
                  + (json.dumps(r.failure_statuses) if r.failure_statuses else ""))
    if r.fallbacks:
        table.add_row("back-end fallbacks to IPOPT", str(r.fallbacks))
    table.add_row("softened solves (max slack)",
                  f"{r.softened_solves}" + (f" ({r.max_slack:.3g})" if r.softened_solves else ""))
    table.add_row("planner calls (rejected)", f"{r.planner_calls} ({r.planner_rejected})")
    table.add_row("plan time median", _ms(r.plan_time_median))
    table.add_row("wall time", f"{r.wall_time:.2f} s")
    for w in r.warnings:
        table.add_row("[yellow]warning[/]", w)
    table.add_row("log", str(out / "run.mcap"))
    Console().print(table)
