"""``hmpc replay``: what a recorded run did, its tables, and whether it re-runs identically.

Argument handling and printing only (heavy imports inside the command); the logic is
:mod:`hmpc_cli.analysis.replay` and :mod:`hmpc_cli.analysis.export`.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Annotated, Any

import typer

from hmpc_cli.core.paths import path_option

__all__ = ["replay_command"]

EXIT_BAD_INPUT = 2
EXIT_DIVERGED = 1


def _fail(lines: list[str]) -> None:
    """Prints ``error:`` lines and exits with the bad-input code."""
    for line in lines:
        typer.echo(f"error: {line}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def _text(v: Any) -> str:
    """A summary value as text: numbers in 6 significant digits, objects as JSON."""
    if isinstance(v, bool) or v is None:
        return str(v).lower() if v is not None else "-"
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else str(v)
    if isinstance(v, (dict, list)):
        return json.dumps(v, separators=(", ", ": "))
    return str(v)


def _recorded(info: dict, key: str) -> str:
    """An optional /run/info field as text, or "not recorded"."""
    v = info.get(key)
    if v is None:
        return "not recorded"
    return " ".join(map(str, v)) if isinstance(v, list) else _text(v)


def _identity_table(rp, size: int):
    """Rich table of the run's identity and the state of its log file."""
    from rich.markup import escape
    from rich.table import Table

    from hmpc_cli.log.rundata import plan_stride

    info = rp.info
    t = Table(title=escape(f"run {info.get('scenario_name', '?')}"), show_header=False)
    desc = rp.scenario.get("description")
    if desc:  # the scenario file's words: overrides and a sweep's settings are not in them
        settings = [o for o in info.get("overrides") or [] if not str(o).startswith("seed=")]
        by = "overrides" if settings else "sweep" if info.get("sweep") else ""
        t.add_row("description", escape(str(desc)) + (
            f" (the scenario file's; the {by} below changed the run)" if by else ""))
    t.add_row("system", escape(str(info.get("system", "?"))))
    t.add_row("seed", str(info.get("seed", "?")))
    vers = info.get("versions") or {}
    t.add_row("versions", escape(", ".join(f"{k} {v}" for k, v in vers.items()) or "-"))
    cmd = info.get("command") if info.get("command") is not None else info.get("argv")
    t.add_row("command", escape(_recorded({"c": cmd}, "c")))
    t.add_row("overrides", escape(_recorded(info, "overrides")))
    if info.get("sweep"):
        t.add_row("sweep", escape(str(info["sweep"])))
    build = info.get("build") or {}
    if build:  # how the MPC's NLPs were built (the build cache)
        t.add_row("NLP build", escape(f"{build.get('cache', '?')}"
                                      + (", compiled" if build.get("compiled") else "")
                                      + (f": {build['reason']}" if build.get("reason") else "")))
    t.add_row("log", escape(f"{rp.path} ({size} bytes)"))
    stride = plan_stride(rp.scenario)
    if stride > 1:
        t.add_row("plans", f"thinned: sim.log_plan_stride = {stride} (one node in {stride}, "
                  "both nodes of each reset and the last)")
    if rp.log.damage:
        t.add_row("file", f"[red]damaged[/]: {escape(rp.log.damage)}; the chunks read "
                  f"are shown (the last message at t = {rp.t_last:.3f} s)")
    elif rp.complete:
        t.add_row("file", "complete")
    else:
        t.add_row("file", f"[yellow]cut short at t = {rp.t_last:.3f} s[/] "
                  "(no footer: the completed chunks are shown)")
    note = rp.version_note()
    if note:
        t.add_row("log version", f"[yellow]{escape(note)}[/]")
    return t


def _summary_table(summary: dict):
    """Rich table of the /run/summary fields."""
    from rich.markup import escape
    from rich.table import Table

    from hmpc_cli.cli.run import real_time_text

    t = Table(title="summary", show_header=False)
    for key, v in summary.items():
        text = escape(_text(v))
        if key == "success":
            text = "[green]true[/]" if v else "[red]false[/]"
        elif key == "real_time" and isinstance(v, dict):
            text = escape(f"{v.get('latency', '?')}: {real_time_text(v)}")
        t.add_row(escape(key), text)
    return t


def _timeline_table(rows, n_messages: int, window: str):
    """Rich table of the timeline rows."""
    from rich.markup import escape
    from rich.table import Table

    t = Table(title=escape(f"timeline{window} ({n_messages} messages selected)"))
    t.add_column(escape("t [s]"), justify="right")
    t.add_column("what")
    t.add_column("details")
    for r in rows:
        text = escape(r.text)
        t.add_row(f"{r.t:.4f}", r.kind, f"[{r.style}]{text}[/]" if r.style else text)
    return t


def _disturbance_table(stats: dict):
    """Rich table of the disturbance statistics."""
    from rich.markup import escape
    from rich.table import Table

    t = Table(title=f"disturbance: {stats['values']} values ({stats['changes']} changes)")
    t.add_column("channel")
    t.add_column("max |w|", justify="right")
    t.add_column("mean |w| (time-weighted)", justify="right")
    for name, c in stats["channels"].items():
        t.add_row(escape(name), f"{c['max']:.4g}", f"{c['mean']:.4g}")
    return t


def _counts_line(messages: list) -> str:
    """'N messages: /topic n, ...' for the selected messages."""
    counts: dict[str, int] = {}
    for m in messages:
        counts[m.topic] = counts.get(m.topic, 0) + 1
    return ", ".join(f"{k} {n}" for k, n in sorted(counts.items())) or "none"


def _no_summary(rp) -> str:
    """Why a log shows no /run/summary: a damaged log's may be in what was not read."""
    if rp.log.damage:
        return ("no summary read (the log is damaged before it: whether the run finished "
                "is not known)")
    return "no summary (the run did not finish)"


def _print_report(console, rp, selected: list, show_all: bool, window: str,
                  span: tuple[float | None, float | None], topics: list[str] | None) -> None:
    """Identity, summary, timeline and disturbance statistics (over ``span``: --from, --to)."""
    from hmpc_cli.analysis.replay import charged_by, disturbance_stats, timeline

    console.print(_identity_table(rp, rp.path.stat().st_size))
    if rp.summary is None:
        console.print(f"[yellow]{_no_summary(rp)}[/]")
    else:
        console.print(_summary_table(rp.summary))
    sim = rp.scenario.get("sim") if rp.scenario else None
    rows = timeline(selected, show_all, charged_by(sim if isinstance(sim, dict) else None))
    console.print(_timeline_table(rows, len(selected), window))
    console.print(f"selected messages per topic: {_counts_line(selected)}", markup=False)
    if topics and "/disturbance" not in topics:
        return
    t_end = rp.t_last if span[1] is None else min(span[1], rp.t_last)
    stats = disturbance_stats(rp.log.messages, t_end, span[0])
    if stats["values"]:
        console.print(_disturbance_table(stats))


def _export(console, rp, selected: list, out: Path, fmt: str, filters: dict) -> None:
    """Writes the export and lists the files."""
    from hmpc_cli.analysis.export import ExportError, write_export

    info = {"log": str(rp.path), "complete": rp.complete, "damage": rp.log.damage,
            "filters": filters, "run_info": rp.info, "metadata": rp.log.metadata,
            "scenario_toml": rp.scenario_text}
    try:
        files = write_export(out, selected, info, fmt)
    except ExportError as exc:
        _fail([str(exc)])
    from hmpc_cli.cli.common import is_quiet

    if is_quiet():  # the export's directory only
        typer.echo(str(out))
        return
    console.print(f"exported {len(files)} files to {out}: "
                  + ", ".join(p.name for p in files), markup=False)


def _verify(console, rp) -> None:
    """Re-runs the scenario and prints the comparison; exits 1 on a divergence."""
    import tempfile

    from rich.markup import escape

    from hmpc_cli.analysis.replay import ReplayError, verify

    from hmpc_cli.cli.common import is_quiet

    if not is_quiet():  # replay_command refused an unverifiable log before this
        console.print("verify: re-running the attached scenario (seed "
                      f"{rp.info.get('seed', '?')}) ...", markup=False)
    where = tempfile.gettempdir()
    try:
        with tempfile.TemporaryDirectory(prefix="hmpc-verify-") as tmp:
            try:
                div, n, k = verify(rp, Path(tmp))
            except ReplayError as exc:
                _fail([f"{rp.path}: {exc}"])
    except OSError as exc:  # the re-run's log: a full or unwritable temporary directory
        _fail([f"{rp.path}: --verify: cannot write the re-run's log in {where} "
               f"({exc.strerror or exc}): point TMPDIR at a directory with room for it"])
    scope = "" if rp.complete else f" up to t = {rp.t_last:.4g} s (the log was cut short)"
    if rp.complete and rp.stopped_at is not None:
        scope = f" up to t = {rp.stopped_at:.4g} s (a stop signal ended the run there)"
    if div is None:
        console.print(f"[green]identical[/] ({n} messages on {k} topics){escape(scope)}")
        return
    console.print(f"[red]diverged[/] at t = {div.t:.6g} s on {escape(div.topic)}, field "
                  f"{escape(div.path)}: recorded {escape(_text(div.recorded))}, "
                  f"re-run {escape(_text(div.rerun))}")
    raise typer.Exit(EXIT_DIVERGED)


def replay_command(
    log: Annotated[Path, typer.Argument(help="a run log (run.mcap) or its run directory")],
    t_from: Annotated[float | None, typer.Option(
        "--from", metavar="T0", help="only messages at t >= T0 seconds")] = None,
    t_to: Annotated[float | None, typer.Option(
        "--to", metavar="T1", help="only messages at t <= T1 seconds")] = None,
    topic: Annotated[list[str] | None, typer.Option(
        "--topic", metavar="NAME", help="only this topic (repeatable): /mpc/solve, "
        "mpc/solve or solve; also plan, event, disturbance, state, info, summary")] = None,
    show_all: Annotated[bool, typer.Option(
        "--all", help="one timeline row per solve (default: runs of ordinary solves "
        "summarised in one row)")] = False,
    export: Annotated[Path | None, typer.Option(
        "--export", metavar="DIR", help="write one table per topic (after the filters) "
        "and info.json into this directory", parser=path_option)] = None,
    fmt: Annotated[str | None, typer.Option(
        "--format", metavar="FORMAT", show_default=False,
        help="export format: csv (default), or parquet (needs pyarrow)")] = None,
    check: Annotated[bool, typer.Option(
        "--verify", help="re-run the attached scenario with the same seed and compare the "
        "logs (exit 1 at the first divergence)")] = False,
    figures: Annotated[Path | None, typer.Option(
        "--figures", metavar="DIR", help="re-render the run's figures (those its system "
        "supports) and an animation of its logged scene (scene.gif; scene.mp4 with "
        "ffmpeg) into this directory", parser=path_option)] = None,
) -> None:
    """Replay a recorded run: identity, summary, timeline; filter, export, verify."""
    from hmpc_cli.analysis.replay import ReplayError, load_replay, resolve_topics
    from hmpc_cli.log.damage import DamagedLogError

    fmt = _checked_options(t_from, t_to, fmt, export, figures)
    try:
        rp = load_replay(log)
        topics = resolve_topics(topic or [], [m.topic for m in rp.log.messages],
                                sorted({m.topic for m in rp.log.raw}))
    except ReplayError as exc:
        _fail([f"{log}: {exc}"])
    from hmpc_cli.analysis.replay import unverifiable

    why = unverifiable(rp) if check else None
    if why is not None:  # before the export and figures: nothing written for a refusal
        _fail([f"{rp.path}: --verify: {why}"])
    try:
        _replay(rp, topics, t_from, t_to, show_all, export, fmt, check, figures)
    except DamagedLogError as exc:
        _fail([str(exc)])


def _checked_options(t_from: float | None, t_to: float | None, fmt: str | None,
                     export: Path | None, figures: Path | None) -> str:
    """The window, the export format and the outputs checked before anything is read.

    Exits 2 on a bad one (nothing read, nothing written); returns the export format.
    """
    from hmpc_cli.analysis.export import ExportError, earlier_export
    from hmpc_cli.core.paths import OutputPathError, check_output

    _check_window(t_from, t_to)
    if fmt is not None and export is None:
        _fail([f"--format {fmt}: the format of --export's tables; give --export DIR too"])
    try:  # the outputs first: a bad path writes nothing and reads nothing
        for option, where in (("--export", export), ("--figures", figures)):
            if where is not None:
                check_output(where, option)
        if export is not None:
            earlier_export(export)
    except OutputPathError as exc:
        _fail([str(exc)])
    except ExportError as exc:
        _fail([f"--export {exc}"])
    return fmt or "csv"


def _check_window(t_from: float | None, t_to: float | None) -> None:
    """Exits 2 unless --from and --to are finite times >= 0 s, --from not after --to."""
    import math

    bad = [f"{option} {t:g}: a time in seconds from the run's start (finite, >= 0)"
           for option, t in (("--from", t_from), ("--to", t_to))
           if t is not None and not (math.isfinite(t) and t >= 0.0)]
    if bad:
        _fail(bad)
    if t_from is not None and t_to is not None and t_from > t_to:
        _fail([f"--from {t_from:g} is after --to {t_to:g}"])


def _replay(rp, topics, t_from, t_to, show_all, export, fmt, check, figures) -> None:
    """The body of ``hmpc replay`` for a loaded log (its odd content reported as damage)."""
    from rich.console import Console

    from hmpc_cli.analysis.replay import guarded, select

    if export is not None:
        from hmpc_cli.analysis.export import ExportError, check_format

        try:
            check_format(fmt.lower())
        except ExportError as exc:
            _fail([str(exc)])
    selected = select(rp.log.messages, t_from, t_to, topics or None)
    window = "" if t_from is None and t_to is None else (
        f" from {'start' if t_from is None else f'{t_from:g} s'}"
        f" to {'end' if t_to is None else f'{t_to:g} s'}")
    from hmpc_cli.cli.common import is_quiet

    quiet = is_quiet()
    console = Console()
    with guarded(rp.path):
        if not quiet:
            _print_report(console, rp, selected, show_all, window, (t_from, t_to),
                          topics or None)
        elif export is None and figures is None and not check:  # the summary is the result
            console.print(_summary_table(rp.summary) if rp.summary is not None
                          else _no_summary(rp))
        if export is not None:
            _export(console, rp, selected, export, fmt.lower(),
                    {"from": t_from, "to": t_to, "topics": topics or "all"})
    if figures is not None:
        _figures(console, rp, figures)
    if check:
        _verify(console, rp)


def _figures(console, rp, out: Path) -> None:
    """Writes the run's figures and its scene animation into ``out`` (what applies)."""
    from rich.markup import escape

    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.figures.fig2 import fig2
    from hmpc_cli.figures.fig4 import fig4
    from hmpc_cli.figures.scene_anim import animate_scene
    from hmpc_cli.figures.timing import timing
    from hmpc_cli.analysis.passthrough import PassThroughError, pass_through_geometry

    made = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        _fail([f"--figures {out}: cannot write ({exc})"])
    from hmpc_cli.cli.common import is_quiet

    title = str(rp.info.get("scenario_name", rp.path.stem))
    quiet = is_quiet()
    jobs = (("fig2", lambda: fig2(pass_through_geometry(rp.path), out, ["pdf", "png"])),
            ("fig4", lambda: fig4(rp.path, out, ["pdf", "png"])),
            ("timing", lambda: timing(rp.path, out, ["pdf", "png"])),
            ("scene animation", lambda: animate_scene(rp.log, out, title)))
    missed = []
    for name, job in jobs:
        try:
            job()
            if not quiet:
                console.print(f"figures: {name} written to {escape(str(out))}")
        except (FigureInputError, PassThroughError) as exc:
            missed.append(f"{name}: {exc}")
            if not quiet:
                console.print(f"figures: {name} not drawn: {escape(str(exc))}")
        except OSError as exc:
            _fail([f"--figures {out}: cannot write ({exc})"])
    if len(missed) == len(jobs):  # nothing to show for the option: a refusal, not a result
        if made:
            shutil.rmtree(out, ignore_errors=True)
        _fail([f"--figures {out}: no figure could be drawn from this log", *missed])
    if quiet:
        typer.echo(str(out))
