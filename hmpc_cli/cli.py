"""The ``hmpc`` command line (Typer). Argument handling only; heavy imports inside commands.

Exit codes: 0 ran; 1 ``--strict`` failure or lost work; 2 bad input or environment;
129/130/143 hang-up/interrupt/termination.
"""

from __future__ import annotations

import json
import sys
from datetime import datetime, UTC
from pathlib import Path
from typing import Annotated

import typer

from hmpc_cli.cli_common import complete_set_key, print_version, with_verbosity

app = typer.Typer(
    name="hmpc", no_args_is_help=True, add_completion=True,
    context_settings={"help_option_names": ["-h", "--help"]},
    help="Layered nonlinear MPC of hybrid systems (Olkin & Ames, 2024): run, log, inspect.",
    epilog="Exit codes: 0 ran; 1 --strict failure or lost work; 2 bad input or environment; "
    "129/130/143 signals (hang-up, interrupt, termination).")

EXIT_FAILED = 1
EXIT_BAD_INPUT = 2


@app.callback()
def _main(
    version: Annotated[bool, typer.Option(
        "--version", callback=print_version, is_eager=True,
        help="print the hmpc, CasADi and Python versions and exit")] = False,
) -> None:
    """Layered nonlinear MPC of hybrid systems (Olkin & Ames, 2024): run, log, inspect.

    Exit codes: 0 ran; 1 --strict failure or lost work; 2 bad input or environment;
    129/130/143 signals (hang-up, interrupt, termination).
    """


def _err(lines: list[str]) -> None:
    for line in lines:
        typer.echo(f"error: {line}", err=True)


@app.command()
@with_verbosity
def run(
    scenario: Annotated[Path, typer.Argument(help="scenario TOML file")],
    out: Annotated[Path | None, typer.Option(
        "--out", help="run directory (default results/<scenario>/<time>-seed<N>)")] = None,
    set_: Annotated[list[str] | None, typer.Option(
        "--set", help="override a setting: key.path=value (repeatable)",
        autocompletion=complete_set_key)] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="override the seed")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar")] = False,
    live: Annotated[bool, typer.Option(
        "--live", help="also stream the log's topics to a Foxglove WebSocket server on "
        "127.0.0.1 (needs foxglove-sdk), paced to real time")] = False,
    live_port: Annotated[int, typer.Option(
        "--live-port", help="port of the --live server")] = 8765,
    strict: Annotated[bool, typer.Option(
        "--strict", help="exit 1 when the run's task fails (success false)")] = False,
) -> None:
    """Run the layered controller in closed loop and log everything to MCAP.

    When stdout is not a terminal, the log's path is also printed whole on the last line.
    """
    from hmpc_cli.scenario import ScenarioError, load_scenario

    try:
        sc, toml_text = load_scenario(scenario, set_ or [], seed)
    except ScenarioError as exc:
        _err(exc.lines)
        raise typer.Exit(EXIT_BAD_INPUT) from None
    from hmpc_cli.registry import PluginError
    from hmpc_cli.runner import prepare

    try:
        loop = prepare(sc)
    except (PluginError, ValueError) as exc:
        _err([f"{scenario}: {exc}"])
        raise typer.Exit(EXIT_BAD_INPUT) from None

    if out is None:
        stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
        out = Path("results") / sc.name / f"{stamp}-seed{sc.seed}"
    if (out / "run.mcap").exists():
        _err([f"{out}: already holds a run (choose another --out)"])
        raise typer.Exit(EXIT_BAD_INPUT)
    from hmpc_cli.runlog import Provenance

    loop.log.provenance = Provenance(overrides=tuple(
        [*(set_ or []), *([f"seed={seed}"] if seed is not None else [])]))
    sink = _live_sink(live_port) if live else None
    try:
        result = _execute(loop, sc, toml_text, out, quiet, sink)
    finally:
        if sink is not None:
            sink.close()
    _print_summary(result, out)
    if not sys.stdout.isatty():
        typer.echo(str(out / "run.mcap"))
    if strict and not result.success:
        raise typer.Exit(EXIT_FAILED)


def _live_sink(port: int):
    """The --live server (exit 2 with a clear message without foxglove-sdk)."""
    from hmpc_cli.live import LiveSink, LiveError

    try:
        sink = LiveSink(port)
    except LiveError as exc:
        _err([str(exc)])
        raise typer.Exit(EXIT_BAD_INPUT) from None
    typer.echo(f"live: connect Foxglove or Lichtblick to {sink.url}", err=True)
    return sink


def _execute(loop, sc, toml_text: str, out: Path, quiet: bool, sink=None):
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from hmpc_cli.runner import execute_run

    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                        TextColumn("t = {task.fields[t]:.2f} s"), TimeElapsedColumn(),
                        disable=quiet, transient=True)
    try:
        with progress:
            task = progress.add_task(sc.name, total=1.0, t=0.0)
            dur = sc.sim.duration

            def tick(i: int, n: int, note: str = "") -> None:
                if i % 20 == 0 or i == n:
                    desc = f"{sc.name} [yellow]({note})[/]" if note else sc.name
                    progress.update(task, completed=i / n, t=i / n * dur, description=desc)

            return execute_run(loop, toml_text, out, tick, sink)
    except KeyboardInterrupt:
        typer.echo(f"interrupted; partial log in {out / 'run.mcap'}", err=True)
        raise typer.Exit(130) from None


def _print_summary(r, out: Path) -> None:
    from rich.console import Console
    from rich.table import Table

    def ms(v: float) -> str:
        return "-" if v != v else f"{1e3 * v:.1f} ms"

    table = Table(title=f"{r.scenario} (seed {r.seed})", show_header=False)
    table.add_row("result", "[green]success[/]" if r.success else f"[red]failed[/]: {r.reason}")
    table.add_row("final distance to goal", f"{r.final_error:.4f}")
    table.add_row("simulated time", f"{r.t_end:.3f} s")
    table.add_row("contacts", f"{r.contacts} " + json.dumps(r.contacts_by_guard))
    table.add_row("MPC solves", str(r.solves))
    table.add_row("solve time median / p95 / max",
                  f"{ms(r.solve_time_median)} / {ms(r.solve_time_p95)} / {ms(r.solve_time_max)}")
    table.add_row("solver failures", f"{r.solver_failures} "
                  + (json.dumps(r.failure_statuses) if r.failure_statuses else ""))
    table.add_row("softened solves (max slack)",
                  f"{r.softened_solves}" + (f" ({r.max_slack:.3g})" if r.softened_solves else ""))
    table.add_row("planner calls (rejected)", f"{r.planner_calls} ({r.planner_rejected})")
    table.add_row("plan time median", ms(r.plan_time_median))
    table.add_row("wall time", f"{r.wall_time:.2f} s")
    for w in r.warnings:
        table.add_row("[yellow]warning[/]", w)
    table.add_row("log", str(out / "run.mcap"))
    Console().print(table)


@app.command()
@with_verbosity
def schema() -> None:
    """Print the scenario JSON Schema."""
    from hmpc_cli.scenario import scenario_model

    typer.echo(json.dumps(scenario_model().model_json_schema(), indent=2))


def _register() -> None:
    from hmpc_cli.cli_plot import plot_command
    from hmpc_cli.cli_replay import replay_command
    from hmpc_cli.cli_report import report_command
    from hmpc_cli.cli_sweep import sweep_command
    from hmpc_cli.cli_tube import tube_command

    app.command("sweep")(with_verbosity(sweep_command))
    app.command("plot")(with_verbosity(plot_command))
    app.command("report")(with_verbosity(report_command))
    app.command("tube")(with_verbosity(tube_command))
    app.command("replay")(with_verbosity(replay_command))


_register()


def main() -> None:
    """Console-script entry point (also ``python -m hmpc_cli``)."""
    app(prog_name="hmpc")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
