"""The ``hmpc`` application: its options, its commands (one module each), ``hmpc schema``.

Exit codes: 0 ran; 1 ``--strict`` failure, lost work or an internal error; 2 bad input or
environment; 129/130/143 hang-up/interrupt/termination.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import signal
import sys
import threading
from typing import Annotated

import typer

from hmpc_cli.cli.common import print_version, with_verbosity

app = typer.Typer(
    name="hmpc", no_args_is_help=True, add_completion=True,
    context_settings={"help_option_names": ["-h", "--help"]},
    help="Layered nonlinear MPC of hybrid systems (Olkin & Ames, 2024): run, log, inspect.",
    epilog="Exit codes: 0 ran; 1 --strict failure, lost work or an internal error; 2 bad "
           "input or environment; 129/130/143 signals (hang-up, interrupt, termination).")

@app.callback()
def _main(
    version: Annotated[bool, typer.Option(
        "--version", callback=print_version, is_eager=True,
        help="print the hmpc, CasADi and Python versions and exit")] = False,
) -> None:
    """Layered nonlinear MPC of hybrid systems (Olkin & Ames, 2024): run, log, inspect.

    Exit codes: 0 ran; 1 --strict failure, lost work or an internal error; 2 bad input or
    environment; 129/130/143 signals (hang-up, interrupt, termination).
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


def _flags_without_a_type() -> None:
    """Help shows no value type beside a flag or a counted option.

    Typer's help prints one beside every option, flags too (``--strict <bool>``, ``-v
    <int>``), which reads as if they took a value (``--strict true`` is then an error).
    Left as Typer has it if its option class does not look as expected.
    """
    from typer.core import TyperOption

    shown = getattr(TyperOption, "display_type_rich", None)
    if shown is None or getattr(shown, "_hmpc_flags", False):
        return

    def display_type_rich(self, ctx):
        if getattr(self, "is_flag", False) or getattr(self, "count", False):
            return None
        return shown(self, ctx)

    display_type_rich._hmpc_flags = True
    TyperOption.display_type_rich = display_type_rich


_register()
_flags_without_a_type()


def main() -> None:
    """Console-script entry point (also ``python -m hmpc_cli``).

    The process ends as soon as the command is done (:func:`end_process`).
    """
    try:
        try:
            app(prog_name="hmpc")
            code = 0
        except SystemExit as stop:
            code = stop.code
    except KeyboardInterrupt as exc:  # after the command's own handlers were taken off
        from hmpc_cli.core.signals import as_interrupted

        stop = as_interrupted(exc)
        print(f"interrupted ({stop.name})", file=sys.stderr)
        code = stop.exit_code
    end_process(code)


def end_process(code: object) -> None:
    """Ends the process with ``code`` as ``sys.exit`` would, without the interpreter's teardown.

    The atexit handlers run (log handlers, temporary directories, worker pools, the build
    cache's compile at exit) and the standard streams are flushed (stdout failing, e.g. a
    full disk or a closed pipe: said on stderr, status 120 as CPython gives it unless the
    status is already an error); then ``os._exit``. The teardown it skips frees CasADi's
    and the plug-ins' objects one by one and writes nothing. While another non-daemon
    thread is alive it exits the ordinary way, which waits for that thread.

    A stop signal from here on is held to the end (no traceback from inside an atexit
    handler): one stderr line says so, and a status of 0 becomes 128 + its number.
    """
    others = [t for t in threading.enumerate()
              if t is not threading.main_thread() and t.is_alive() and not t.daemon]
    if others:
        raise SystemExit(code)
    held = _hold_stop_signals()
    if code is None or isinstance(code, int):
        status = code or 0
    else:  # sys.exit("message"): the message on stderr, status 1
        print(code, file=sys.stderr)
        status = 1
    atexit._run_exitfuncs()
    try:
        if sys.stdout is not None:  # None: started without a stdout (``>&-``)
            sys.stdout.flush()
    except (OSError, ValueError) as exc:  # ValueError: stdout was closed
        with contextlib.suppress(Exception):
            print(f"hmpc: the output could not be written: {exc}", file=sys.stderr)
        status = status or 120
    if held:
        name = signal.Signals(held[0]).name
        with contextlib.suppress(Exception):
            print(f"interrupted ({name}) while exiting; the command had finished",
                  file=sys.stderr)
        status = status or 128 + held[0]
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    os._exit(status & 0xFF)


def _hold_stop_signals() -> list[int]:
    """From now on SIGINT, SIGTERM and SIGHUP are recorded (returned list), not raised.

    A second one ends the process at once (an atexit handler that hangs), status 128 + its
    number. A signal the process ignores (e.g. SIGINT in a background job) stays ignored.
    """
    held: list[int] = []

    def hold(signum: int, frame) -> None:
        if held:
            for stream in (sys.stdout, sys.stderr):  # what was printed, best effort
                with contextlib.suppress(Exception):
                    stream.flush()
            os._exit(128 + signum)
        held.append(signum)

    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        with contextlib.suppress(ValueError, OSError):
            if signal.getsignal(sig) is not signal.SIG_IGN:
                signal.signal(sig, hold)
    return held


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
