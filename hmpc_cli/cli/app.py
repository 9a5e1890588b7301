"""The ``hmpc`` application: its options, its commands (one module each), ``hmpc schema``.

Exit codes: 0 ran; 1 ``--strict`` failure or lost work; 2 bad input or environment;
129/130/143 hang-up/interrupt/termination.
"""

from __future__ import annotations

import json
import sys
from typing import Annotated

import typer

from hmpc_cli.cli.common import print_version, with_verbosity

app = typer.Typer(
    name="hmpc", no_args_is_help=True, add_completion=True,
    context_settings={"help_option_names": ["-h", "--help"]},
    help="Layered nonlinear MPC of hybrid systems (Olkin & Ames, 2024): run, log, inspect.",
    epilog="Exit codes: 0 ran; 1 --strict failure or lost work; 2 bad input or environment; "
    "129/130/143 signals (hang-up, interrupt, termination).")

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


def schema() -> None:
    """Print the scenario JSON Schema."""
    from hmpc_cli.run.schema import scenario_json_schema

    typer.echo(json.dumps(scenario_json_schema(), indent=2))


def _register() -> None:
    from hmpc_cli.cli.plot import plot_command
    from hmpc_cli.cli.replay import replay_command
    from hmpc_cli.cli.run import run_command
    from hmpc_cli.cli.report import report_command
    from hmpc_cli.cli.sweep import sweep_command
    from hmpc_cli.cli.tube import tube_command

    app.command("run")(with_verbosity(run_command))
    app.command("schema")(with_verbosity(schema))
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
