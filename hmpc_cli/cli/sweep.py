"""``hmpc sweep``: argument handling and output; the work is in :mod:`hmpc_cli.sweep.plan`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, NoReturn

import typer

EXIT_BAD_INPUT = 2
EXIT_FAILED = 1
EXIT_INTERRUPTED = 130


def path_option(value: str) -> Path:
    """``--out``'s parser: :func:`hmpc_cli.core.paths.path_option` ('' refused later)."""
    from hmpc_cli.core.paths import path_option as parse

    return parse(value)


def _err(lines: list[str]) -> None:
    for line in lines:
        typer.echo(f"error: {line}", err=True)


def sweep_command(
    sweep_file: Annotated[Path, typer.Argument(metavar="SWEEP.toml", help="sweep TOML file")],
    workers: Annotated[int | None, typer.Option(
        "--workers", min=1, help="worker processes (default: all cores; 1 = in-process)")
    ] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", metavar="DIR", help="output directory (default results/sweeps/<name>)",
        parser=path_option)] = None,
    dask: Annotated[str | None, typer.Option(
        "--dask", help="run on a Dask cluster: scheduler address, e.g. tcp://host:8786")
    ] = None,
    dry_run: Annotated[bool, typer.Option(
        "--dry-run", help="validate and list the runs, run nothing")] = False,
    seeds: Annotated[int | None, typer.Option(
        "--seeds", help="run only the sweep's first N seeds (the rest resume later)")
    ] = None,
    dask_timeout: Annotated[float, typer.Option(
        "--dask-timeout", min=0.1, help="seconds to wait for the --dask scheduler")] = 10.0,
    show: Annotated[str | None, typer.Option(
        "--show", help="print run RUN_ID's effective scenario (TOML that hmpc run takes: "
        "one row of the table again), run nothing")] = None,
) -> None:
    """Run a grid of scenario overrides x seeds in parallel; resumable; one results table."""
    import os

    from hmpc_cli.cli.common import is_quiet

    plan = _checked_plan(sweep_file, seeds)
    if show is not None:
        return _show(plan, show)
    out = out if out is not None else Path("results") / "sweeps" / plan.spec.name
    _check_out(out, plan)  # a dry run too: it says whether the real one would start
    if dry_run:
        _list_runs(plan)
        return
    client = _dask_client(dask, dask_timeout, workers)
    try:
        outcome = _locked_execute(plan, out, workers or os.cpu_count() or 1, client)
    except KeyboardInterrupt as exc:  # a stop as the runs start or end: what is done
        _stopped_at_an_edge(plan, out, exc)
    finally:
        if client is not None:
            client.close()
    _report_outcome(plan, out, outcome, is_quiet())


def _stopped_at_an_edge(plan, out: Path, exc: KeyboardInterrupt) -> NoReturn:
    """Says how many runs are done, as a resume counts them, then stops.

    For a stop the sweep's executor did not see: before its first run, after its table.
    """
    from hmpc_cli.core.signals import as_interrupted
    from hmpc_cli.sweep.table import finished_runs

    stop = as_interrupted(exc)
    if getattr(exc, "reported", False):
        raise stop from None
    try:
        done = sum(s is not None for s in finished_runs(plan, out).values())
    except OSError:
        done = 0
    table = f"; the table: {out / 'results.csv'}" if (out / "results.csv").is_file() else ""
    typer.echo(f"interrupted ({stop.name}): {_progress_text(done, len(plan.selected))}{table}",
               err=True)
    stop.reported = True
    raise stop from None


def _report_outcome(plan, out: Path, outcome, quiet: bool) -> None:
    """Prints the sweep's cells and table, its lost runs; exits for a stop or lost work.

    A stop signal while this prints (the runs have ended) says how many runs are done
    and where their table is, then stops.
    """
    from hmpc_cli.core.signals import check

    try:
        if not outcome.interrupted:  # its stop is said below
            check()
        if quiet:  # errors and the table's path only
            typer.echo(str(out / "results.csv"))
        else:
            _print_cells(plan, out)
            typer.echo(f"results: {out / 'results.csv'}")
    except KeyboardInterrupt as exc:
        from hmpc_cli.core.signals import as_interrupted

        stop = as_interrupted(exc)
        when = " while the sweep stopped" if outcome.interrupted else \
            " after the sweep's runs ended"
        typer.echo(f"interrupted ({stop.name}){when}: "
                   f"{_progress_text(outcome.done, outcome.total)}; the table: "
                   f"{out / 'results.csv'}", err=True)
        stop.reported = True
        raise stop from None
    if outcome.lost:
        _err([f"run not recorded (rerun to retry): {x}" for x in outcome.lost])
    if outcome.interrupted:
        typer.echo(f"interrupted: {_progress_text(outcome.done, outcome.total)}", err=True)
        raise typer.Exit(128 + outcome.signum)
    if outcome.lost:
        raise typer.Exit(EXIT_FAILED)


def _progress_text(done: int, total: int) -> str:
    """``K of N runs done; run the same command again to resume``, or ``all N runs done``."""
    runs = "run" if total == 1 else "runs"
    if done >= total:
        return f"all {total} {runs} done"
    return f"{done} of {total} {runs} done; run the same command again to resume"


def _dask_client(address: str | None, timeout: float, workers: int | None):
    """The ``--dask`` cluster's client (None: run locally); exit 2 if it does not answer."""
    if address is None:
        return None
    from hmpc_cli.run.scenario import ScenarioError

    if workers is not None:
        typer.echo("note: --workers is ignored with --dask", err=True)
    try:
        return connect_dask(address, timeout)
    except ScenarioError as exc:
        _err(exc.lines)
        raise typer.Exit(EXIT_BAD_INPUT) from None


def _check_out(out: Path, plan) -> None:
    """Exits 2 (nothing written) when ``out`` cannot take the sweep or is another's."""
    from hmpc_cli.cli.common import checked_output
    from hmpc_cli.sweep.lock import owner_problem

    checked_output(out, "--out")
    problem = owner_problem(out, plan.spec.name, text=plan.text)
    if problem is not None:
        _err([f"--out {out}: {problem}"])
        raise typer.Exit(EXIT_BAD_INPUT)


def _locked_execute(plan, out: Path, workers: int, client):
    """:func:`_execute` holding the output directory's lock, stop signals handled.

    Exits 2 when another sweep writes to ``out``, or when the disk fills up (the line
    says how many runs were kept: finished runs stay, the rest resume later).
    """
    from hmpc_cli.core.paths import disk_error, disk_error_text
    from hmpc_cli.core.signals import handle_signals
    from hmpc_cli.sweep.lock import SweepLockedError, output_lock

    try:
        with output_lock(out), handle_signals():
            return _execute(plan, out, workers, client)
    except SweepLockedError as exc:
        _err([str(exc)])
        raise typer.Exit(EXIT_BAD_INPUT) from None
    except OSError as exc:
        if not disk_error(exc):
            raise
        kept = sum(cell.runs for cell in _safe_stats(plan, out))
        _err([f"cannot write: {disk_error_text(exc)}; {kept} of {len(plan.runs)} runs kept "
              f"in {out} (finished runs stay; free space and run the same command to "
              "resume)"])
        raise typer.Exit(EXIT_BAD_INPUT) from None


def _safe_stats(plan, out: Path) -> list:
    """:func:`hmpc_cli.sweep.table.cell_stats`, or none when even reading fails."""
    from hmpc_cli.sweep.table import cell_stats

    try:
        return cell_stats(plan, out)
    except OSError:
        return []


def _checked_plan(sweep_file: Path, seeds: int | None):
    """The sweep's plan, every cell set-up checked; exit 2 with every problem if any."""
    from hmpc_cli.run.scenario import ScenarioError
    from hmpc_cli.sweep.plan import first_seeds, plan_sweep

    try:
        plan = first_seeds(plan_sweep(sweep_file), seeds)
    except ScenarioError as exc:
        _err(exc.lines)
        raise typer.Exit(EXIT_BAD_INPUT) from None
    problems, warnings = cell_checks(plan)
    if problems:  # what only the built system can tell, for every cell, before any run
        _err(problems)
        raise typer.Exit(EXIT_BAD_INPUT)
    for line in warnings:  # on stderr, also with -q
        typer.echo(f"warning: {line}", err=True)
    return plan


def cell_checks(plan, runs=None) -> tuple[list[str], list[str]]:
    """The set-up checks of every distinct (system, MPC) cell of a sweep, attributed.

    ``runs``: those of the plan to check (default: every selected one).

    Returns ``(problems, warnings)``: lines ``SWEEP: cell axis=label, ...: key.path:
    reason`` (the cell named by its grid axes).
    Problems: :func:`hmpc_cli.run.setup_checks.setup_problems` (seeds and settings that
    cannot change them share one check: the system, MPC and planner, with the tube's
    margins also the disturbance, plant and low level); a cell whose own tube's margins
    do not fit (``mpc.margins = "tube"``) is a warning, its runs recorded as refused (a
    finding of a robustness study). Warnings: a margins file computed
    for another disturbance or low level (:func:`hmpc_cli.run.scenario.margins_file_warnings`) and a
    setting the cell's runs ignore (:func:`hmpc_cli.run.scenario.inert_settings`: an
    axis over it would run the same runs again), each reason once, with the number of
    cells it holds for.
    """
    import json
    import tomllib

    from hmpc_cli.run.scenario import margins_file_warnings, scenario_model
    from hmpc_cli.run.setup_checks import setup_problems as scenario_problems
    from hmpc_cli.tube.margins_file import REFUSED

    checked: dict[str, list[str]] = {}  # what the checks read -> their problems
    out: list[str] = []
    noted: dict[str, list[str]] = {}  # reason -> the cells it holds for
    read: dict[str, list[str]] = {}  # the margins file and what it is compared with -> reasons
    for run in plan.selected if runs is None else runs:
        sc = scenario_model().model_validate(tomllib.loads(run.toml))
        cell = ", ".join(f"{a.name}={v}" for a, v in zip(plan.axes, run.cell, strict=True)
                         ) or "the base scenario"
        margins = json.dumps([sc.mpc.margins_source(), sc.disturbance.kind,
                              sc.disturbance.magnitude, sc.lowlevel.kp, sc.lowlevel.kd])
        if margins not in read:
            read[margins] = margins_file_warnings(sc)
        for line in [*read[margins], *_inert(plan, run, sc, read)]:
            if cell not in noted.setdefault(line, []):
                noted[line].append(cell)
        # what the checks read: the tube margins also the disturbance, plant and low level
        parts = [sc.system, sc.mpc, sc.planner] + ([sc.disturbance, sc.plant, sc.lowlevel]
                                                   if sc.mpc.margins_source() == "tube" else [])
        key = json.dumps([part if isinstance(part, dict) else part.model_dump(mode="json")
                          for part in parts], sort_keys=True)  # [plant]: a dict
        first = key not in checked
        if first:
            checked[key] = scenario_problems(sc)
        for line in checked[key]:
            if sc.mpc.margins_source() == "tube" and line.startswith(REFUSED):
                # the rate's own tube does not fit: a finding of the study, not an error
                line = f"{line} (its runs are recorded as refused)"
                if cell not in noted.setdefault(line, []):
                    noted[line].append(cell)
            elif first:
                out.append(f"{plan.path}: cell {cell}: {line}")
    warnings = [f"{plan.path}: cell {cells[0]}"
                + (f" (and {len(cells) - 1} other cell{'s' * (len(cells) > 2)})"
                   if len(cells) > 1 else "")
                + f": {line}" for line, cells in noted.items()]
    return out, warnings


def _inert(plan, run, sc, read: dict[str, list[str]]) -> list[str]:
    """``key: no effect with ...`` per setting of ``run``'s cell that its runs ignore.

    Computed once per distinct set of overrides (kept in ``read``).
    """
    import json

    from hmpc_cli.run.scenario import inert_settings
    from hmpc_cli.sweep.table import toml_value

    items = [f"{k}={toml_value(v)}" for k, v in run.overrides.items()]
    key = json.dumps(["inert", items])
    if key not in read:
        read[key] = inert_settings(plan.scenario, items, sc, attributed=False)
    return read[key]


def _show(plan, run_id: str) -> None:
    """Prints a planned run's effective scenario; exit 2 naming the closest ids if none.

    Without the disturbance keys its kind ignores (every key is written out in an
    effective scenario; ``hmpc run`` would warn of those), which change nothing the run does.
    """
    import difflib
    import tomllib

    from hmpc_cli.run.scenario import dump_toml
    from hmpc_cli.sim.disturbance import READS

    run = next((r for r in plan.runs if r.run_id == run_id), None)
    if run is None:
        ids = [r.run_id for r in plan.runs]
        close = difflib.get_close_matches(run_id, ids, n=1, cutoff=0.5)
        hint = f"did you mean {close[0]!r}? " if close else ""
        _err([f"--show {run_id}: no run of {plan.path} has this id ({hint}`hmpc sweep "
              f"{plan.path} --dry-run` lists its {len(ids)} runs)"])
        raise typer.Exit(EXIT_BAD_INPUT)
    data = tomllib.loads(run.toml)
    kind = data.get("disturbance", {}).get("kind", "none")
    data["disturbance"] = {k: v for k, v in data.get("disturbance", {}).items()
                           if k == "kind" or k in READS.get(kind, ())}
    cell = ", ".join(f"{a.name}={label}" for a, label in zip(plan.axes, run.cell, strict=True))
    note = "; its description is the scenario file's, which the sweep's settings below " \
        "change" if data.get("description") and run.overrides else ""
    typer.echo(f"# run {run.run_id} of {plan.path}: {cell or 'its one cell'}, seed "
               f"{run.seed}{note}")
    typer.echo(dump_toml(data), nl=False)


def _list_runs(plan) -> None:
    for run in plan.selected:
        cell = zip(plan.axes, run.cell, strict=True)  # one label per axis
        parts = [run.run_id, *(f"{a.name}={v}" for a, v in cell)]
        typer.echo("  ".join([*parts, f"seed={run.seed}"]))
    n = len(plan.selected)
    typer.echo(f"{n} run{'s' if n != 1 else ''}, all valid (dry run: nothing started)")


def _execute(plan, out: Path, workers: int, client):
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                               TimeElapsedColumn, TimeRemainingColumn)

    from hmpc_cli.cli.common import is_quiet
    from hmpc_cli.sweep.execute import execute_sweep

    quiet = is_quiet()
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                        MofNCompleteColumn(), TextColumn("ok {task.fields[ok]}"),
                        TimeElapsedColumn(), TimeRemainingColumn(), transient=True,
                        disable=quiet)
    task = progress.add_task(plan.spec.name, total=len(plan.selected), ok=0)
    state = {"ok": 0}

    def on_start(total: int, skipped: int, ok: int, replaced: list[str]) -> None:
        todo = total - skipped
        if replaced:  # on stderr, also with -q
            typer.echo(f"warning: {len(replaced)} finished run(s) in {out / 'runs'} were made "
                       f"with another scenario (their scenario.toml differs from this sweep's "
                       f"now, or the margins file they read has changed since, e.g. run "
                       f"{replaced[0]}): they are run again and their files replaced (a "
                       f"sweep into another --out keeps them)", err=True)
        where = f"Dask {client.scheduler.address}" if client is not None else (
            "in-process" if min(workers, todo) <= 1 else f"{min(workers, todo)} worker processes")
        state["ok"] = ok
        progress.update(task, completed=skipped, ok=ok)
        if not quiet:
            typer.echo(f"{plan.spec.name}: {total} runs, {skipped} skipped (already done), "
                       f"{total - skipped} to run ({where}) -> {out}")

    def on_done(run, summary: dict) -> None:
        state["ok"] += bool(summary.get("success"))
        progress.update(task, advance=1, ok=state["ok"])
        if not state.get("noted"):
            note = not_compiled_note(out / "runs" / run.run_id)
            if note:  # advice, on stderr (also with -q: stdout holds the table's path only)
                state["noted"] = True
                typer.echo(note, err=True)

    with progress:
        return execute_sweep(plan, out, workers, client, on_start, on_done)


def not_compiled_note(run_dir: Path) -> str:
    """A note when a finished run solved its MPC NLPs uncompiled for a build cache miss.

    '' when the run's /run/info says the NLPs were loaded compiled, every NLP's stage
    kernels ran in C (the chain NLP on IPOPT: compiled, a Figure 3 campaign gains 8 %,
    docs/performance.md), the cache is off, or the log cannot be read. Measured before
    the stage kernels: the paper robustness sweep's runs 1.5x faster compiled,
    bit-identical (``hmpc replay --verify``).
    """
    from hmpc_cli.log.reader import first_message
    from hmpc_cli.mpc.kernels import IN_C, IN_SX

    build = ((first_message(run_dir / "run.mcap", "/run/info") or {}).get("build") or {})
    reason = build.get("reason", "")
    if build.get("cache") != "miss" or build.get("compiled") or \
            (IN_C in reason and IN_SX not in reason):
        return ""
    return (f"note: the MPC's NLPs of this sweep are not compiled (build cache miss), so "
            f"every run solves them in CasADi's SX virtual machine, slower. Compile them once "
            f"(minutes of CPU, GBs of memory): HMPC_BUILD_CACHE=sync hmpc run "
            f"{run_dir / 'scenario.toml'} --set sim.duration=0.1 --out <a scratch dir>; "
            f"sweep workers started after that load them (a resumed sweep; the same results "
            f"bit for bit).")


def _print_cells(plan, out: Path) -> None:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    import dataclasses

    from hmpc_cli.sweep.table import CellStats, cell_stats

    table = Table(title=f"{plan.spec.name}: success per grid cell (seeds pooled)")
    for a in plan.axes:
        table.add_column(a.name)
    charged = any(r.charged for r in plan.runs)
    for name in ("runs", "successes", "success rate",
                 *(["solves past the period"] if charged else [])):
        table.add_column(name, justify="right")
    cells = cell_stats(plan, out)
    for c in cells:
        table.add_row(*map(escape, c.cell), *c.columns(charged))
    total = CellStats((), *(sum(getattr(c, f.name) for c in cells)
                            for f in dataclasses.fields(CellStats)[1:]))
    table.add_section()
    table.add_row(*(["all"] + [""] * (len(plan.axes) - 1) if plan.axes else []),
                  *total.columns(charged))
    Console().print(table)


DASK_HINT = "is it the dashboard port 8787? the scheduler listens on 8786"


def _probe_scheduler(address: str, timeout: float) -> str:
    """'' if a TCP Dask scheduler at ``address`` sends its handshake within ``timeout``.

    A scheduler writes its handshake frame (8-byte little-endian length, then the message)
    as soon as a connection is accepted; an HTTP server or a silent peer sends nothing.
    Addresses of other protocols (tls://, ucx://, ...) are not probed. Otherwise returns why.
    """
    import socket
    import struct
    import time

    scheme, _, rest = address.rpartition("://")
    if scheme not in ("", "tcp"):
        return ""
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit():
        return ""  # left to distributed (default port, names it resolves itself)
    deadline = time.monotonic() + timeout
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout) as sock:
            head = b""
            while len(head) < 8:
                sock.settimeout(max(deadline - time.monotonic(), 0.01))
                chunk = sock.recv(8 - len(head))
                if not chunk:
                    return "the peer closed the connection without a Dask handshake"
                head += chunk
    except TimeoutError:
        return f"no Dask scheduler answered within {timeout:g} s"
    except OSError as exc:
        return f"cannot connect: {exc.strerror or exc}"
    (size,) = struct.unpack("<Q", head)
    if not 0 < size < 1 << 26:
        return "the peer does not speak the Dask protocol"
    return ""


def connect_dask(address: str, timeout: float = 10.0):
    """A ``distributed.Client`` for ``address``, connected within ``timeout`` seconds.

    Raises:
        ScenarioError: distributed missing, or no scheduler answered in time (one line with
            a hint about the dashboard port).
    """
    import threading

    from hmpc_cli.run.scenario import ScenarioError

    try:
        from distributed import Client
    except ImportError:
        raise ScenarioError([f"--dask {address}: the 'distributed' package is not installed "
                             "(pip install 'hmpc[dask]')"]) from None
    reason = _probe_scheduler(address, timeout)
    if reason:  # something listens there (the dashboard, say) or the port is the dashboard's
        hint = "" if reason.startswith("cannot connect") and not address.endswith(":8787") \
            else f" ({DASK_HINT})"
        raise ScenarioError([f"--dask {address}: {reason}{hint}"])
    box: dict = {}

    def connect() -> None:
        try:
            box["client"] = Client(address, timeout=timeout)
        except BaseException as exc:
            box["error"] = exc

    worker = threading.Thread(target=connect, name="hmpc-dask-connect", daemon=True)
    worker.start()
    worker.join(timeout + 1.0)
    if "client" in box:
        return box["client"]
    exc = box.get("error")
    reason = (" ".join(str(exc).split()) or type(exc).__name__) if exc is not None else \
        f"no Dask scheduler answered within {timeout:g} s"
    hint = f" ({DASK_HINT})" if address.endswith(":8787") else ""
    raise ScenarioError([f"--dask {address}: cannot connect: {reason}{hint}"])
