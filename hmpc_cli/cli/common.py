"""Options every ``hmpc`` command shares (-q/-v, --version) and shell completions.

Light on purpose: ``hmpc --help`` and shell completion import no CasADi or matplotlib.
"""

from __future__ import annotations

import functools
import inspect
import logging
import sys
import warnings
from typing import Annotated

import typer

__all__ = ["EXIT_BAD_INPUT", "EXIT_INTERNAL", "VERBOSITY", "checked_output",
           "complete_figure", "complete_set_key", "environment_error", "internal_error",
           "is_quiet", "print_version", "with_verbosity"]

#: -1 quiet, 0 default, 1 and more verbose; set by every command's -q/-v
VERBOSITY = [0]

#: -q's help per command that does not declare it (default: :data:`QUIET_WRITES`)
QUIET_HELP = {
    "replay_command": "print only errors and, with --export or --figures, the directory "
                      "written; with neither, the run's summary alone",
    "schema": "print only errors and the schema (the default too)"}
QUIET_WRITES = ("print only errors and the path of what was written (no progress, no "
                "tables)")
_VERBOSE = Annotated[int, typer.Option(
    "--verbose", "-v", count=True, help="more detail on stderr (-vv: debug)")]


def _quiet(command: str):
    """The -q/--quiet option of ``command`` (a function's name) with its help."""
    return Annotated[bool, typer.Option("--quiet", "-q",
                                        help=QUIET_HELP.get(command, QUIET_WRITES))]


def is_quiet() -> bool:
    """Whether the command runs with -q: errors and the final path only on the terminal."""
    return VERBOSITY[0] < 0


def set_verbosity(quiet: bool, verbose: int) -> None:
    """Sets :data:`VERBOSITY` and the level of hmpc's loggers (stderr)."""
    VERBOSITY[0] = -1 if quiet else int(verbose)
    level = (logging.ERROR if quiet else logging.WARNING if not verbose
             else logging.INFO if verbose == 1 else logging.DEBUG)
    warnings.formatwarning = _one_line_warning
    logger = logging.getLogger("hmpc_cli")
    logger.setLevel(level)
    if not logger.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        logger.addHandler(handler)


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    """Python warnings on the command line: ``warning: <first line>`` (no source line)."""
    first = (str(message).splitlines() or [""])[0]
    return f"warning: {first}\n"


def with_verbosity(fn):
    """``fn`` as a Typer command that also takes -q/--quiet and -v/--verbose.

    A command that declares ``quiet`` or ``verbose`` itself receives them as well. Every
    command stops on SIGINT, SIGTERM and SIGHUP (:func:`hmpc_cli.core.signals.handle_signals`)
    with one ``interrupted (SIGTERM)`` line on stderr and exit code 128 + the signal
    number; long computations also poll :func:`hmpc_cli.core.signals.check`.
    """
    sig = inspect.signature(fn, eval_str=True)
    own = set(sig.parameters)
    extra = [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default,
                               annotation=annotation)
             for name, default, annotation in (("quiet", False, _quiet(fn.__name__)),
                                               ("verbose", 0, _VERBOSE))
             if name not in own]

    @functools.wraps(fn)
    def command(*args, **kwargs):
        quiet = kwargs["quiet"] if "quiet" in own else kwargs.pop("quiet", False)
        verbose = kwargs["verbose"] if "verbose" in own else kwargs.pop("verbose", 0)
        set_verbosity(bool(quiet), int(verbose or 0))
        from hmpc_cli.core.signals import handle_signals

        try:
            with handle_signals():  # SIGTERM, SIGHUP like Ctrl-C: exit 128 + signal, one line
                return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, typer.BadParameter):
            raise
        except KeyboardInterrupt as exc:  # Ctrl-C in any command: 128 + signal, one line
            from hmpc_cli.core.signals import as_interrupted

            stop = as_interrupted(exc)
            if not getattr(exc, "reported", False):
                typer.echo(f"interrupted ({stop.name})", err=True)
            raise typer.Exit(stop.exit_code) from None
        except Exception as exc:  # a bug, not bad input: one line, exit 1, trace with -v
            if _is_cli_exception(exc):
                raise
            stopped_meanwhile(exc)
            environment_error(exc)
            internal_error(exc)

    params = [*sig.parameters.values(), *extra]
    command.__signature__ = sig.replace(parameters=params)
    command.__annotations__ = {p.name: p.annotation for p in params}
    return command


#: exit code of an internal error (like lost work: the command did not finish its job)
EXIT_INTERNAL = 1


def _is_cli_exception(exc: BaseException) -> bool:
    """Whether ``exc`` is the command-line framework's own (usage errors and exits)."""
    return any(cls.__name__ == "ClickException" for cls in type(exc).__mro__)


def stopped_meanwhile(exc: BaseException) -> None:
    """Exits 128 + signal with one line when a stop signal came before ``exc``; else returns.

    The handler's KeyboardInterrupt, raised where C code runs Python, can come out as
    another exception: a SIGINT to ``hmpc replay`` once ended in ``TypeError: expected a
    message argument`` (CPython 3.11.2; the text of ``PyErr_SetImportError``, the import
    machinery's). The stop is what ended the command; ``exc``'s traceback with -v.
    """
    from hmpc_cli.core.signals import Interrupted, pending

    signum = pending()
    if signum is None:
        return
    stop = Interrupted(signum)
    typer.echo(f"interrupted ({stop.name})", err=True)
    if VERBOSITY[0] >= 1:
        _echo_traceback(exc)
    raise typer.Exit(stop.exit_code) from None


def _echo_traceback(exc: BaseException) -> None:
    import traceback

    typer.echo("".join(traceback.format_exception(exc)).rstrip(), err=True)


def environment_error(exc: BaseException) -> None:
    """Exits 2 with one line when ``exc`` is bad input or environment, not a bug.

    An unusable output path (:class:`hmpc_cli.core.paths.OutputPathError`), a damaged or
    foreign log (:class:`hmpc_cli.log.damage.DamagedLogError`), plug-ins that cannot be
    used together (:class:`hmpc_cli.core.registry.PluginError`) or a full or read-only disk
    (:data:`hmpc_cli.core.paths.DISK_ERRNOS`) wherever a command meets it; else returns.
    """
    from hmpc_cli.core.paths import OutputPathError, disk_error, disk_error_text
    from hmpc_cli.core.registry import PluginError
    from hmpc_cli.log.damage import DamagedLogError

    if isinstance(exc, (OutputPathError, DamagedLogError, PluginError)):
        line = " ".join(str(exc).split())
    elif disk_error(exc):
        line = f"cannot write: {disk_error_text(exc)}"
    else:
        return
    typer.echo(f"error: {line}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT) from None


#: exit code of bad input or environment
EXIT_BAD_INPUT = 2


def internal_error(exc: BaseException) -> None:
    """Reports an unexpected exception in one line (the traceback with -v) and exits 1."""
    first = " ".join(str(exc).split())[:300]
    typer.echo(f"error: internal error: {type(exc).__name__}" + (f": {first}" if first else ""),
               err=True)
    if VERBOSITY[0] >= 1:
        _echo_traceback(exc)
    else:
        typer.echo("(run again with -v for the traceback; please report it)", err=True)
    raise typer.Exit(EXIT_INTERNAL) from None


def _version(name: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "not installed"


def print_version(value: bool) -> None:
    """--version: hmpc, CasADi and Python versions (CasADi is not imported)."""
    if not value:
        return
    import platform

    from hmpc_cli import __version__

    typer.echo(f"hmpc {__version__}")
    typer.echo(f"casadi {_version('casadi')}")
    typer.echo(f"python {platform.python_version()} ({sys.executable})")
    raise typer.Exit(0)


def complete_figure(incomplete: str) -> list[str]:
    """Figure names for ``hmpc plot``."""
    names = ("fig2", "fig3", "robustness", "fig4")
    return [n for n in names if n.startswith(incomplete)]


def _schema_keys(schema: dict) -> list[str]:
    """Dotted setting paths of the scenario JSON Schema (objects walked through $refs)."""
    defs = schema.get("$defs", {})
    keys: list[str] = []

    def walk(node: dict, prefix: str, depth: int) -> None:
        if "$ref" in node:
            node = defs.get(node["$ref"].rsplit("/", 1)[-1], {})
        for option in [*node.get("anyOf", []), *node.get("allOf", []), *node.get("oneOf", [])]:
            if "$ref" in option or option.get("properties"):
                walk(option, prefix, depth)
        for name, sub in (node.get("properties") or {}).items():
            path = f"{prefix}{name}"
            keys.append(path)
            if depth < 3:
                walk(sub, path + ".", depth + 1)

    walk(schema, "", 0)
    return sorted(set(keys))


def complete_set_key(incomplete: str) -> list[str]:
    """``--set`` keys from the scenario schema (``key=``), for shell completion."""
    if "=" in incomplete:
        return []
    try:
        from hmpc_cli.run.scenario import scenario_model

        keys = _schema_keys(scenario_model().model_json_schema())
    except Exception:  # completion must never fail loudly
        return []
    return [f"{k}=" for k in keys if k.startswith(incomplete)]


def checked_output(path, option: str, kind: str = "dir"):
    """``path`` if it can take the output (:func:`hmpc_cli.core.paths.output_problem`).

    Otherwise prints ``error: <option> <path>: <problem>`` and exits 2, nothing written.
    """
    from hmpc_cli.core.paths import OutputPathError, check_output

    try:
        return check_output(path, option, kind)
    except OutputPathError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(EXIT_BAD_INPUT) from None
