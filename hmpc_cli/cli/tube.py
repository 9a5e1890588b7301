"""``hmpc tube``: the tracking-error tubes of a scenario (heavy imports inside the command).

Reads the scenario, builds its system through the registry, runs
:func:`hmpc_cli.tube.analyse` on plain values and prints, writes and draws the report.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer

from hmpc_cli.cli.common import complete_set_key
from hmpc_cli.core.paths import path_option

__all__ = ["tube_command"]

EXIT_BAD_INPUT = 2
#: MPC rates of the margin-vs-rate figure [Hz]
PLOT_RATES = (1, 2, 3, 5, 7, 10, 15, 20, 30, 50, 70, 100, 150, 200)


def _fail(lines: list[str]) -> None:
    """Prints ``error:`` lines and exits with the bad-input code."""
    for line in lines:
        typer.echo(f"error: {line}", err=True)
    raise typer.Exit(EXIT_BAD_INPUT)


def _system(scenario: Path, sc):
    """The scenario's built system; exits 2 when x0 lies outside its initial mode's domain.

    A tube region spanned from such an x0 would start in a domain x0 is not in.

    Raises:
        hmpc_cli.core.registry.PluginError: the system fails to build.
    """
    from hmpc_cli.core.registry import build_system
    from hmpc_cli.run.setup_checks import initial_state_problems

    system = build_system(sc.system)
    outside = initial_state_problems(system)
    if outside:
        _fail([f"{scenario}: {line}" for line in outside])
    return system


class _OptionError(ValueError):
    """A bad ``--states``/``--runs``/``--pad`` input: the message names the option."""


def _blamed(scenario: Path, exc: Exception) -> str:
    """The error line of a failed analysis: an option's own, else the scenario's."""
    return str(exc) if isinstance(exc, _OptionError) else f"{scenario}: {exc}"


def _check_pad(pad: float | None) -> None:
    """Exits 2 when --pad is not a number in [0, :data:`MAX_PAD`]."""
    if pad is not None and not (math.isfinite(pad) and 0 <= pad <= MAX_PAD):
        _fail([f"--pad {pad:g}: must be a number in [0, {MAX_PAD:g}] (a fraction of each "
               "coordinate's width per side, e.g. 0.1)"])


#: the widest --pad: a region 201 times as wide as the one it pads
MAX_PAD = 100.0


def _check_samples(samples: int) -> None:
    """Exits 2 when --samples asks for more than the sampling limit (with its cost)."""
    from hmpc_cli.tube.sampling import samples_problem

    problem = samples_problem(samples)
    if problem:
        _fail([f"--samples: {problem}"])


def _g(v: float | None) -> str:
    """A number for the tables: 4 significant digits, inf, or '-' for None."""
    if v is None:
        return "-"
    return str(float(v)) if not math.isfinite(v) else f"{v:.4g}"


def _states_of(log: Path, n: int) -> object:
    """The states a recorded run visited (K, n), from its /sim/state topic.

    A damaged or cut log's states are used, with a warning saying so.

    Raises:
        _OptionError: the log cannot be read or has no state of dimension n.
    """
    from hmpc_cli.log.rundata import damage_note, read_run

    try:
        run = read_run(log)
    except ValueError as exc:  # its message starts with the log's path
        raise _OptionError(f"--states {exc}") from None
    if not run.t.size or run.x.shape[1] != n:
        raise _OptionError(f"--states {run.lacks(f'no /sim/state state of dimension {n}')}")
    note = damage_note(run.damage, run.complete)
    if note:  # as --runs: what it holds is used, and said
        typer.echo(f"warning: --states {log}: the region spans the states the log holds"
                   f"{note}", err=True)
    return run.x


def _constants_table(report, sc_name: str):
    """Rich table of the constants and the certificate."""
    from rich.markup import escape
    from rich.table import Table

    lx, dist, cert = report.lipschitz, report.disturbance, report.certificate
    row = report.row(report.rate_hz)
    t = Table(title=f"tube constants: {sc_name} ({report.system})", show_header=False)
    t.add_row("region", escape(f"{report.region.note}; diameter {_g(report.region.diameter)}"))
    t.add_row("L_x", f"{_g(lx.L_x)} 1/s  (max ||df/dx||_2, mode {lx.mode_x})")
    t.add_row("L_u", f"{_g(lx.L_u)}  (max ||df/du||_2, mode {lx.mode_u})")
    t.add_row("", escape(f"L_x, L_u: {lx.samples} Jacobian evaluations each (--samples "
                         f"uniform samples + local refinement); {lx.note}"))
    t.add_row("eta", escape(_eta_text(dist)))
    names = [report.state_names[i] for i in report.kinematic_states]
    t.add_row("kinematic states", escape(
        f"{', '.join(names)}: flow = another state or 0, so their error is "
        "int ||e|| <= int_0^dt diam T(s) ds" if names else "none (no kinematic tube)"))
    t.add_row("zeta", f"{_g(row.margins.zeta)} at {report.rate_hz:g} Hz  (min(||K|| "
              f"diam T(dt), D_U): ||K|| = {_g(report.gain_norm)}, kp = {report.kp:g}, "
              f"kd = {report.kd:g}, D_U = {_g(report.box_diameter)})")
    if not cert.certified:
        t.add_row("certificate", f"[red]none[/]: {escape(cert.reason)}")
        return t
    t.add_row("certificate", f"V = sqrt(e^T P e), A_cl = A - B K at x0 in mode {cert.mode} "
              f"({len(cert.states)} error states)")
    t.add_row("k1, k2, k3", f"{_g(cert.k1)}, {_g(cert.k2)}, {_g(cert.k3)}")
    t.add_row("sigma(eta), gamma", f"{_g(cert.sigma)}, {_g(cert.gamma)} 1/s;  a(inf) = "
              f"{_g(cert.a_inf)}")
    t.add_row("check sigma/k1 <= eta", f"{'true' if cert.check else 'false'}: "
              f"{cert.check_text}")
    t.add_row("ROA (estimate)", f"{{V <= {_g(cert.roa_level)}}} ⊇ ball of radius "
              f"{_g(cert.roa_radius)} ({cert.roa_samples} samples"
              f"{', none violating up to the cap' if cert.roa_capped else ''})")
    t.add_row("tau", f"{_g(cert.tau)} s")
    return t


def _eta_text(dist) -> str:
    """The eta row: its value and its parts (the plant's mismatch, the disturbance box's)."""
    if not dist.plant:
        return f"{_g(dist.eta)}  ({dist.note})"
    box = (f"max ||df_plant/dw|| x ||w_max|| = {_g(dist.gain)} x {_g(dist.w_norm)} = "
           f"{_g(dist.from_w)}" if dist.w_norm else f"no w part ({dist.kind}: 0)")
    return (f"{_g(dist.eta)} = max ||f_plant - f_model|| = {_g(dist.mismatch)} (plant: "
            f"{dist.plant}; w = 0, mode {dist.mismatch_mode}, {dist.mismatch_samples} flow "
            f"evaluations) + {box}")


def _diam_table(report):
    """Rich table of diam T(dt) per MPC rate."""
    from rich.markup import escape
    from rich.table import Table

    t = Table(title=escape("diam T(dt) per MPC rate [state norm]"))
    for col in ("MPC rate", escape("dt [s]"), "trivial", "ff-only", "Prop. 3", "diam T(dt)",
                "bound", "kinematic", "zeta"):
        t.add_column(col, justify="left" if col == "bound" else "right")
    for r in report.rows:
        mark = " *" if r.rate_hz == report.rate_hz else ""
        t.add_row(f"{r.rate_hz:g} Hz{mark}", _g(r.dt), _g(r.trivial), _g(r.ff_only),
                  _g(r.prop3), _g(r.diam), r.bound, _g(r.kinematic), _g(r.margins.zeta))
    return t


def _margin_table(report):
    """Rich table of the implied margins per guard and mode, one column per rate."""
    from rich.table import Table

    t = Table(title="implied margins: guard-avoid / pass-through offsets (NLP row units), "
                    "input margin per side")
    t.add_column("constraint")
    for r in report.rows:
        t.add_column(f"{r.rate_hz:g} Hz", justify="right")
    first = report.rows[0].margins
    for i, g in enumerate(first.guards):
        kin = " (kinematic)" if report.kinematic_guards and report.kinematic_guards[i] else ""
        t.add_row(f"guard {g.guard}{kin}", *[
            f"{_g(r.margins.guards[i].avoid)} / {_g(r.margins.guards[i].pass_through)}"
            + ("" if r.margins.guards[i].monotone else " !") for r in report.rows])
    for i, m in enumerate(first.inputs):
        t.add_row(f"inputs {m.mode}", *[
            _g(max(r.margins.inputs[i].per_side, default=0.0))
            + (" (capped)" if r.margins.inputs[i].capped else "") for r in report.rows])
    return t


def _print(report, sc_name: str) -> None:
    """Prints the three tables, then the notes and warnings."""
    from rich.console import Console
    from rich.markup import escape

    con = Console()
    con = Console(width=max(con.width, 110))
    con.print(_constants_table(report, sc_name))
    con.print(_diam_table(report))
    con.print(_margin_table(report))
    con.print("* the scenario's MPC rate; ! the guard's margin formula does not hold at "
              "that radius; (kinematic): the guard's gap depends on kinematic states only, "
              "its margins are of the kinematic radius. L_x, L_u, eta and the ROA are "
              "sampled estimates, not certificates; the MPC applies them only through a "
              "margins file (--write, mpc.margins).")
    for line in report.notes:
        con.print(f"note: {escape(line)}")
    for line in report.warnings:
        con.print(f"[bold yellow]warning[/]: {escape(line)}")


def _write(report, system, out: Path, formats: str, title: str, reality=None) -> list[str]:
    """Writes tube.json and the figures into ``out``; returns the file names.

    tube.json holds everything printed: the analysis and, with ``--runs``, the tube vs
    reality table (``reality``: a :class:`~hmpc_cli.analysis.tube_reality.RealityReport`).
    """
    import numpy as np

    from hmpc_cli.figures.common import parse_formats
    from hmpc_cli.figures.tube import draw_diameters, draw_margins
    from hmpc_cli.core.jsonio import dumps
    from hmpc_cli.tube import diameter_curves

    fmts = parse_formats(formats)
    out.mkdir(parents=True, exist_ok=True)
    from hmpc_cli.core.paths import write_atomic

    doc = report.to_dict()
    if reality is not None:
        doc["reality"] = _reality_dict(reality)
    write_atomic(out / "tube.json", dumps(doc, indent=2) + "\n")
    periods = [r.dt for r in report.rows]
    t = np.linspace(0.0, max(periods), 401)[1:]
    cert = report.certificate
    draw_diameters(out, t, diameter_curves(report, t), cert.tau if cert.certified else None,
                   periods, title, fmts)
    rows = [report.row_at(system, r) for r in PLOT_RATES]
    guards = {g.guard: np.array([r.margins.guards[i].avoid if r.margins.guards[i].monotone
                                 else np.nan for r in rows])  # invalid formula: not drawn
              for i, g in enumerate(rows[0].margins.guards)}
    inputs = {m.mode: np.array([max(r.margins.inputs[i].per_side, default=0.0) for r in rows])
              for i, m in enumerate(rows[0].margins.inputs)}
    draw_margins(out, np.array(PLOT_RATES, dtype=float), guards, inputs, report.rate_hz,
                 title, fmts)
    return ["tube.json"] + [f"{s}.{f}" for s in ("tube_diameter", "tube_margins") for f in fmts]


def _analyse(sc, system, observed: list, states: Path | None, pad: float | None,
             samples: int):
    """The tube report of a scenario.

    The region spans the states of the run ``states``, else those of the observed runs,
    else x0 and the goal (see :func:`hmpc_cli.tube.region_from_scenario`). A ``[plant]``
    that differs from the system is built and passed down: eta holds its flow's mismatch.
    """
    from hmpc_cli.run.tube_margins import scenario_tube
    from hmpc_cli.tube import region_from_scenario

    visited = _states_of(states, system.n_x) if states is not None else (
        _stack([r.x for r in observed]) if observed else None)
    return scenario_tube(sc, system, region=region_from_scenario(system, pad, visited),
                         samples=samples)


def tube_command(
    scenario: Annotated[Path, typer.Argument(metavar="SCENARIO", help="scenario TOML file")],
    set_: Annotated[list[str] | None, typer.Option(
        "--set", metavar="KEY.PATH=VALUE", help="override a setting (repeatable)",
        autocompletion=complete_set_key)] = None,
    out: Annotated[Path | None, typer.Option(
        "--out", metavar="DIR",
        help="output directory (default results/<name>/tube, name the scenario's)",
        parser=path_option)] = None,
    samples: Annotated[int, typer.Option(
        "--samples", min=1, help="uniform samples per estimated constant (at most 1e7; "
        "local refinement adds evaluations)")] = 20000,
    pad: Annotated[float | None, typer.Option(
        "--pad", help="region padding per side, x each coordinate's width "
        "(default 1; with --states or --runs 0.1)")] = None,
    states: Annotated[Path | None, typer.Option(
        "--states", metavar="RUN", help="a run log (run.mcap or its directory): the region "
        "spans the states it visited instead of x0 and the goal")] = None,
    formats: Annotated[str, typer.Option(
        "--formats", help="comma-separated figure formats: pdf,svg,png")] = "pdf,png",
    write: Annotated[Path | None, typer.Option(
        "--write", metavar="FILE", help="also write a margins file (TOML) a scenario's "
        "mpc.margins can name: the radius and margins per tabulated MPC rate",
        parser=path_option)] = None,
    runs: Annotated[list[Path] | None, typer.Option(
        "--runs", metavar="RUN", help="a run of this scenario's system (directory or run.mcap; "
        "repeatable): its deviation from its plans against the tubes; without --states "
        "the region spans the runs' states")] = None,
) -> None:
    """Tracking-error tubes of a scenario: L_x, L_u, eta, zeta, Prop. 3, diam T(dt), margins."""
    sc, system, observed, report = _analysed(scenario, set_ or [], samples, pad, states,
                                             formats, out, write, runs or [])
    _publish(sc, system, observed, report, out, formats, write, samples)


def _analysed(scenario: Path, sets: list[str], samples: int, pad: float | None,
              states: Path | None, formats: str, out: Path | None, write: Path | None,
              runs: list[Path]) -> tuple:
    """(scenario, system, observed runs, tube report): the inputs checked, read, analysed.

    Every bad input (options, outputs, scenario, runs) exits 2 before anything is written.
    """
    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.figures.common import parse_formats
    from hmpc_cli.core.registry import PluginError
    from hmpc_cli.run.scenario import ScenarioError, load_scenario
    from hmpc_cli.tube import TubeError

    _check_samples(samples)  # before anything is read or built
    _check_pad(pad)
    try:
        sc, _ = load_scenario(scenario, sets, check_margins=False)
        parse_formats(formats)
    except ScenarioError as exc:
        _fail(exc.lines)
    except FigureInputError as exc:
        _fail([f"--formats: {exc}"])
    _check_outputs(out, write, sc.name)
    try:
        system = _system(scenario, sc)
        observed = _read_runs(runs, sc.system)
        return sc, system, observed, _analyse(sc, system, observed, states, pad, samples)
    except TubeError as exc:
        _fail([f"{scenario}: tube: {exc.quantity}: {exc.reason} (no trivial tube)"])
    except (PluginError, ValueError) as exc:
        _fail([_blamed(scenario, exc)])


def _publish(sc, system, observed: list, report, out: Path | None, formats: str,
             write: Path | None, samples: int) -> None:
    """Prints the report (-q: its warnings) and writes tube.json, the figures, the margins."""
    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.cli.common import is_quiet
    from hmpc_cli.core.signals import deferred

    quiet = is_quiet()  # -q: the warnings (stderr), errors and the written paths only
    if quiet:
        for line in report.warnings:
            typer.echo(f"warning: {line}", err=True)
    else:
        _print(report, sc.name)
    out = out if out is not None else Path("results") / sc.name / "tube"
    from hmpc_cli.analysis.tube_reality import other_tube_settings

    settings = sc.model_dump(mode="json")
    for run in observed:  # a log not read whole: its deviations are those of what it holds
        if run.damaged:
            typer.echo(f"warning: --runs {run.name}: tube vs reality uses what the log "
                       f"holds{run.damaged}", err=True)
        other = other_tube_settings(run, settings)
        if other:  # another closed loop: its deviations are not this tube's to bound
            typer.echo(f"warning: --runs {run.name}: ran with {'; '.join(other)}: this "
                       "tube is not its closed loop's", err=True)
    reality = _reality_report(report, observed) if observed else None
    with deferred():  # the outputs are written whole: a stop meanwhile acts after them
        try:
            names = _write(report, system, out, formats, f"{sc.name}: tubes", reality)
        except (OSError, FigureInputError) as exc:
            _fail([f"{out}: cannot write ({exc})"])
        if not quiet:
            typer.echo(f"wrote {', '.join(names)} to {out}")
        if reality is not None:
            _reality(report, reality, len(observed), out, formats,
                     f"{sc.name}: tube vs reality", quiet)
        stale = _remove_stale_figures(out, formats, with_reality=reality is not None)
        if stale:
            typer.echo(f"note: removed {', '.join(stale)} from {out}: an earlier analysis's, "
                       "not this one's", err=True)
        if quiet:
            typer.echo(str(out))
        if write is not None:
            _write_margins(report, sc, write, samples)
    _stopped_after_writing(out, write)


def _stopped_after_writing(out: Path, write: Path | None) -> None:
    """Stops (one stderr line) if a stop signal came while the outputs were written."""
    from hmpc_cli.core.signals import as_interrupted, check

    try:
        check()
    except KeyboardInterrupt as exc:
        stop = as_interrupted(exc)
        typer.echo(f"interrupted ({stop.name}) once the analysis was written whole to {out}"
                   + (f" and {write}" if write is not None else ""), err=True)
        stop.reported = True
        raise stop from None


#: the figures hmpc tube writes, by file stem (tube_reality: with --runs)
FIGURE_STEMS = ("tube_diameter", "tube_margins", "tube_reality")


def _remove_stale_figures(out: Path, formats: str, with_reality: bool) -> list[str]:
    """Removes hmpc tube's figures in ``out`` that this analysis did not write.

    Those are another format's, and tube_reality's without ``--runs``. Returns their
    names, sorted.
    """
    from hmpc_cli.figures.common import FORMATS, parse_formats

    written = {f"{stem}.{fmt}" for stem in FIGURE_STEMS[:3 if with_reality else 2]
               for fmt in parse_formats(formats)}
    stale = sorted(name for stem in FIGURE_STEMS for fmt in FORMATS
                   if (name := f"{stem}.{fmt}") not in written and (out / name).is_file())
    for name in stale:
        (out / name).unlink(missing_ok=True)
    return stale


def _check_outputs(out: Path | None, write: Path | None, name: str) -> None:
    """Every output checked before any work: a bad path exits 2 with nothing written."""
    from hmpc_cli.cli.common import checked_output
    from hmpc_cli.figures.common import FORMATS

    out = out if out is not None else Path("results") / name / "tube"
    checked_output(out, "--out")
    own = ["tube.json", *(f"{s}.{f}" for s in FIGURE_STEMS for f in FORMATS)]
    taken = [n for n in own if (out / n).is_dir()]
    if taken:  # it would be written last, the others before it: half a set
        _fail([f"--out {out}: {out / n} is a directory, where this command writes a file: "
               "remove it or choose another --out" for n in taken])
    if write is not None:
        checked_output(write, "--write", "file")
        if write.resolve().parent == out.resolve() and write.name in own:
            _fail([f"--write {write}: is {write.name}, a file this command writes to --out "
                   f"{out}: name the margins file otherwise (e.g. {out / 'margins.toml'})"])
        if _foreign_file(write):
            _fail([f"--write {write}: exists and is not an hmpc margins file: it would be "
                   "overwritten (choose another path)"])


def _foreign_file(path: Path) -> bool:
    """Whether ``path`` is an existing, non-empty file whose first line is not a margins file's."""
    from hmpc_cli.tube.margins_file import MARK

    try:
        with open(path, "rb") as f:
            first = f.readline(len(MARK))
    except OSError:  # none there, a directory or an unreadable file: the write reports it
        return False
    return first not in (b"", MARK.encode())


def _stack(arrays: list) -> object:
    """The rows of ``arrays`` stacked (sum K, n)."""
    import numpy as np

    return np.vstack(arrays)


def _read_runs(runs: list[Path], params) -> list:
    """The runs read by :func:`hmpc_cli.analysis.tube_reality.read_run`, each of ``params``' system.

    Raises:
        _OptionError: a run cannot be read or is of another system.
    """
    from pydantic import ValidationError

    from hmpc_cli.core.registry import PluginError, registry
    from hmpc_cli.analysis.tube_reality import read_run

    from hmpc_cli.log.rundata import resolve_log

    out, seen = [], {}
    for path in runs:
        try:
            log = resolve_log(path).resolve()
        except ValueError:
            log = None  # read_run says what is wrong with it
        if log is not None and log in seen:  # it would count its periods twice
            raise _OptionError(f"--runs {path}: the same log as --runs {seen[log]} ({log}); "
                               "give each run once")
        seen.setdefault(log, path)
        try:  # missing, unreadable or damaged (read_run guards the content it decodes)
            run = read_run(path)
        except ValueError as exc:  # its message starts with the log's path
            raise _OptionError(f"--runs {exc}") from None
        try:
            logged = registry().system(run.system.get("name", "")).params.model_validate(
                run.system)
        except (PluginError, ValidationError):
            logged = None
        if logged != params:
            what = (f"logged {run.system['name']!s} with other parameters" if logged
                    or run.system.get("name") else "its log names no system")
            raise _OptionError(f"--runs {path}: not a run of this scenario's system ({what})"
                               f"{run.damaged}")
        out.append(run)
    return out


def _reality_report(report, runs: list):
    """The observed deviations of ``runs`` against the tube of ``report``."""
    from hmpc_cli.analysis.tube_reality import reality
    from hmpc_cli.tube import diameter_curves

    return reality(runs, lambda tau: diameter_curves(report, tau),
                   dict(zip(report.kinematic_states, report.kinematic_rates, strict=True)))


def _reality_dict(rep) -> dict:
    """The tube vs reality table as tube.json's ``reality`` (what the table prints)."""
    return {"periods": len(rep.periods), "skipped": rep.skipped, "unmatched": rep.unmatched,
            "interpolated": list(rep.interpolated),
            "bounds": [{"bound": c.bound, "periods": c.periods, "inside": c.inside,
                        "fraction_inside": c.fraction, "median_ratio": c.median_ratio,
                        "worst_ratio": c.worst_ratio,
                        "violations": [{"run": v.run, "t": v.t, "observed": v.observed,
                                        "predicted": v.predicted} for v in c.violations]}
                       for c in rep.checks]}


def _violations_note(zero: bool, worst: float) -> str:
    """What a violation of the tube vs reality table may be (``worst``: largest excess)."""
    text = ("note: the observed deviation also holds the plan's own error against the "
            "plant, which no disturbance tube bounds: the NLP's integrator at its node step "
            "(mpc.integrator, mpc.nodes_per_second) against the simulator's 1/sim.rate_hz "
            "steps and its guard nodes against the plant's exact events; the largest "
            f"violation exceeds its bound by {worst:.3g}")
    if zero:
        text += (" (the disturbance set is {0}, so every tube is 0 and each violation here "
                 "is that error)")
    return text


def _reality(report, rep, n_runs: int, out: Path, formats: str, title: str,
             quiet: bool = False) -> None:
    """Prints the "tube vs reality" table and writes tube_reality.<fmt> into ``out``."""
    import numpy as np
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.figures.common import parse_formats
    from hmpc_cli.figures.tube import draw_reality
    from hmpc_cli.tube import diameter_curves

    how = (f"; {len(rep.interpolated)} against the interpolated plan (no sample at a node "
           "time)" if rep.interpolated else "")
    t = Table(title=escape(f"tube vs reality: {n_runs} runs, {len(rep.periods)} periods "
                           f"({rep.skipped} skipped: no sample; {rep.unmatched} samples "
                           f"with no node in the plant's domain{how})"))
    for col in ("bound", "periods", "inside", "median ratio", "worst ratio", "violations"):
        t.add_column(col, justify="left" if col == "bound" else "right")
    for c in rep.checks:
        t.add_row(c.bound, str(c.periods), f"{c.fraction:.3f}", _g(c.median_ratio),
                  _g(c.worst_ratio), str(len(c.violations)))
    con = Console(width=120, quiet=quiet)
    con.print(t)
    for c in rep.checks:
        for v in c.violations:
            con.print(f"violation: {v.bound}: run {escape(v.run)} t = {v.t:.6g} s: observed "
                      f"{v.observed:.4g} > predicted {v.predicted:.4g}")
    excess = [v.observed - v.predicted for c in rep.checks for v in c.violations]
    if excess:
        con.print(escape(_violations_note(report.disturbance.zero, max(excess))))
    tmax = max((float(p.tau.max()) for p in rep.periods), default=1.0)
    grid = np.linspace(0.0, tmax, 201)[1:]
    try:
        paths = draw_reality(out, [(p.tau, p.dev) for p in rep.periods], grid,
                             diameter_curves(report, grid), title, parse_formats(formats),
                             [(p.tau, p.dev_kin) for p in rep.periods
                              if p.dev_kin is not None])
    except (OSError, FigureInputError) as exc:
        _fail([f"{out}: cannot write ({exc})"])
    if not quiet:
        typer.echo(f"wrote {', '.join(p.name for p in paths)} to {out}")


def _write_margins(report, sc, path: Path, samples: int) -> None:
    """Writes the margins file of ``report`` (``hmpc tube --write``)."""
    from hmpc_cli.run.tube_margins import plant_difference
    from hmpc_cli.tube.margins_file import write_margins

    try:
        write_margins(path, report, scenario=sc.name, params=sc.system,
                      kind=sc.disturbance.kind, magnitude=sc.disturbance.magnitude,
                      samples=samples, plant=plant_difference(sc)[0])
    except OSError as exc:
        _fail([f"{path}: cannot write ({exc})"])
    from hmpc_cli.cli.common import is_quiet

    if is_quiet():
        typer.echo(str(path))
        return
    typer.echo(f"wrote margins file {path} (rates "
               f"{', '.join(f'{r.rate_hz:g}' for r in report.rows)} Hz)")
