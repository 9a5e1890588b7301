"""Does the controller keep up: each MPC solve's compute time against its period, from a log.

One panel over simulated time (log scale in milliseconds):

* each solve's compute time at the time it was made: what the plant waited for its plan
  (``/mpc/solve``'s ``latency``) when compute time is charged, else its measured wall
  time (what ``sim.latency = "measured"`` would have charged on this machine);
* under ``"model"`` or a fixed latency, the measured wall times beside, in grey;
* the MPC period as a line: a solve charged more kept the one solver busy past the next
  period's solve (red) unless ``sim.solve_budget`` dropped it (a cross: busy for the
  budget) or a contact stopped it in flight (a triangle: busy until the contact); a first
  plan computed with ``sim.latency_first = "paused"`` is neither counted nor drawn but by
  its wall time; a solve charged 0 s (a model's 0 iterations) is a dash at the bottom;
* the contacts as vertical lines.

The title counts the solves above the period, and under charged time the run's own
``real_time`` (its ``late_solves`` also count a dropped solve's budget and a stopped
solve's time until the contact; :class:`hmpc_cli.log.topics.RealTime`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hmpc_cli.analysis.tables import FigureInputError
from hmpc_cli.figures.common import (
    TEXT_WIDTH_IN,
    check_size,
    figure_style,
    make_out_dir,
    parse_formats,
    save_figure,
)

__all__ = ["SolveTimes", "count_text", "solve_times", "timing"]

LATE_COLOR = "#d62728"  # red: above the period
ON_TIME_COLOR = "#4a6fa5"  # muted blue
WALL_COLOR = "#9a9a9a"  # grey: measured wall times under a charge that is not them
DROPPED = " (over budget: dropped)"  # /mpc/solve's reason suffix
#: the note a solve's reason carries of solves a contact stopped before it (their times)
STOPPED = re.compile(r"after a contact stopped the solve of t = ([0-9., e+-]+?) s: dropped")


@dataclass(frozen=True)
class SolveTimes:
    """A run's MPC solves in time order, and what their times are measured against.

    Attributes:
        t: the times the solves were made at (S,) [s].
        compute: each solve's compute time (S,) [s]: its charge when compute time is
            charged (``charged``), else its measured wall time.
        wall: each solve's measured wall time (S,) [s].
        dropped: the solves dropped over ``sim.solve_budget`` (S,).
        stopped: the solves a contact stopped in flight (S,) (``sim.preempt_at_contact``).
        counted: the solves whose compute time the plant waited for (S,): all with time
            paused, else the charged ones (not a first plan computed with
            ``sim.latency_first = "paused"``).
        period: the fixed-mode MPC's period [s] (None: the log does not say).
        charged: ``sim.latency``'s kind when compute time is charged ("model",
            "measured", "fixed"), else "" (time paused).
        contacts: the contacts' times (C,) [s].
        real_time: the run summary's ``real_time`` (None: paused, or not finished).
        log_note: the damage or cut of a log not read whole
            (:func:`hmpc_cli.log.rundata.damage_note`; '' if intact).
    """

    t: np.ndarray
    compute: np.ndarray
    wall: np.ndarray
    dropped: np.ndarray
    stopped: np.ndarray
    counted: np.ndarray
    period: float | None
    charged: str
    contacts: np.ndarray
    real_time: dict | None
    log_note: str = ""

    @property
    def above(self) -> np.ndarray:
        """The counted solves whose compute time exceeds the period (S,)."""
        if self.period is None:
            return np.zeros(len(self.t), dtype=bool)
        return self.counted & (self.compute > self.period)


def _period(scenario: dict) -> float | None:
    """The MPC period [s] as the loop runs it: whole simulator steps per solve."""
    try:
        sim_hz, mpc_hz = int(scenario["sim"]["rate_hz"]), int(scenario["mpc"]["rate_hz"])
        return (sim_hz // mpc_hz) / sim_hz if sim_hz >= mpc_hz > 0 else None
    except (KeyError, TypeError, ValueError):
        return None


def _charged(scenario: dict) -> str:
    """``sim.latency``'s kind: "" for time paused (or not said), else "model", ...."""
    latency = (scenario.get("sim") or {}).get("latency", "paused")
    if isinstance(latency, str):
        return "" if latency == "paused" else latency
    return "fixed"


def solve_times(path: str | Path) -> SolveTimes:
    """The solve times of the run log at ``path`` (a run.mcap or its run directory).

    Raises:
        FigureInputError: not a readable log, or a log without an MPC solve.
    """
    from hmpc_cli.log.rundata import read_run

    try:
        run = read_run(Path(path))
    except ValueError as exc:
        raise FigureInputError(str(exc)) from None
    if not run.solves:
        raise FigureInputError(run.lacks("no MPC solve in the log"))
    real_time = None
    if run.summary is not None and run.summary.real_time is not None:
        from dataclasses import asdict

        real_time = asdict(run.summary.real_time)
    charged = real_time["latency"] if real_time else _charged(run.scenario)
    t = np.array([s.t for s in run.solves], dtype=float)
    wall = np.array([s.wall_time for s in run.solves], dtype=float)
    counted = np.ones(len(t), dtype=bool)
    if charged and (run.scenario.get("sim") or {}).get("latency_first") == "paused":
        counted[0] = False  # the first solve, made with time paused
    return SolveTimes(
        t, np.array([s.latency for s in run.solves], dtype=float) if charged else wall, wall,
        np.array([s.reason.endswith(DROPPED) for s in run.solves], dtype=bool),
        _stopped([s.reason for s in run.solves], t), counted,
        real_time["period"] if real_time else _period(run.scenario), charged,
        np.array([e.t for e in run.events], dtype=float), real_time,
        run.damage_text)


def _stopped(reasons: list[str], t: np.ndarray) -> np.ndarray:
    """The solves a contact stopped in flight (S,), from the notes of the solves after.

    A solve's reason names the solve times (to 0.1 ms) a contact stopped before it: each
    is the latest earlier solve of that time not named yet (solves after contacts in one
    step share their time).
    """
    out = np.zeros(len(t), dtype=bool)
    for i, reason in enumerate(reasons):
        for m in STOPPED.finditer(reason):
            for v in (float(x) for x in m.group(1).split(", ")):
                j = next((j for j in range(i - 1, -1, -1)
                          if not out[j] and abs(t[j] - v) < 5.01e-5), None)
                if j is not None:
                    out[j] = True
    return out


def count_text(st: SolveTimes) -> str:
    """The counted solves above the period, and how compute time was charged (one line)."""
    n, above = int(st.counted.sum()), int(st.above.sum())
    head = (f"compute time charged ({st.charged})" if st.charged else
            "time paused: each solve's measured wall time")
    what = "charged solves" if st.charged else "solves"
    if st.period is None:
        return f"{head}; {n} {what} (the log does not give the MPC period)"
    more = [f"{k} {how}" for k, how in ((int((st.above & st.dropped).sum()),
                                         "dropped over budget"),
                                        (int((st.above & st.stopped).sum()),
                                         "stopped by a contact")) if k]
    over = "charged more than" if st.charged else "above"
    return (f"{head}; {above} of {n} {what} {over} the {1e3 * st.period:.1f} ms MPC period"
            + (f" ({', '.join(more)})" if more else ""))


def _title(st: SolveTimes) -> str:
    """What the figure shows, counted; the run's own real_time beneath."""
    rt = st.real_time
    return count_text(st) + (
        f"\nreal_time: {rt['late_solves']} of {rt['charged_solves']} charged solves kept the "
        f"solver busy past the period, {rt['dropped_solves']} dropped, "
        f"{rt['preempted_solves']} stopped by a contact" if rt else "")


def _minor_label(v: float, _pos=None) -> str:
    """A log axis' minor tick label: 2 and 5 times a power of ten only (20, 0.5)."""
    if v <= 0:
        return ""
    lead = v / 10.0 ** np.floor(np.log10(v))
    return f"{v:g}" if round(lead) in (2, 5) else ""


def _figure(st: SolveTimes, width: float, height: float):
    """The one-panel Figure (no pyplot state)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    ax = fig.subplots()
    ms = 1e3 * st.compute
    for i, t in enumerate(st.contacts):
        ax.axvline(t, color="black", lw=0.5, ls=":", label="contact" if i == 0 else None)
    if st.charged in ("model", "fixed"):  # a charge that is not the solve's wall time
        ax.plot(st.t, 1e3 * np.maximum(st.wall, 1e-6), ".", ms=2.5, color=WALL_COLOR,
                label="measured wall time")
    if st.period is not None:
        ax.axhline(1e3 * st.period, color="black", lw=0.8,
                   label=f"MPC period {1e3 * st.period:.1f} ms")
    ended = st.counted & (st.dropped | st.stopped)  # not busy for their whole charge
    late = st.above & ~ended
    kept = st.counted & ~st.above & ~ended
    what = "charged" if st.charged else "wall time"
    zero = kept & (ms <= 0.0)  # charged 0 s (a model's 0 iterations): a log axis has no 0
    kept &= ~zero
    if kept.any():
        ax.plot(st.t[kept], ms[kept], "o", ms=3, color=ON_TIME_COLOR, label=f"solve ({what})")
    if zero.any():
        shown = ms[st.counted & (ms > 0.0)]
        floor = 0.5 * float(np.min(shown)) if shown.size else 1e-3
        ax.plot(st.t[zero], np.full(int(zero.sum()), floor), "_", ms=5, color=ON_TIME_COLOR,
                label="charged 0 s (drawn at the bottom)")
    if late.any():
        ax.plot(st.t[late], ms[late], "o", ms=3, color=LATE_COLOR, label="above the period")
    for sel, marker, label in ((st.counted & st.dropped, "x", "dropped over budget"),
                               (st.counted & st.stopped & ~st.dropped, "v",
                                "stopped by a contact")):
        if sel.any():
            ax.plot(st.t[sel], ms[sel], marker, ms=4, color=LATE_COLOR, label=label)
    ax.set_yscale("log")
    from matplotlib.ticker import FuncFormatter

    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # 100, not 10^2
    ax.yaxis.set_minor_formatter(FuncFormatter(_minor_label))
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("compute time [ms]")
    fig.legend(*ax.get_legend_handles_labels(), loc="outside right center", fontsize=6,
               handlelength=1.4)
    ax.set_title(_title(st), fontsize=7)
    return fig


def timing(log: str | Path | SolveTimes, out_dir: str | Path,
           formats: str | Iterable[str] = ("pdf", "svg", "png"), *,
           width: float = TEXT_WIDTH_IN, height: float = 2.4, dpi: int = 300) -> list[Path]:
    """Draws the run's solve times against its MPC period into out_dir/timing.<fmt>.

    ``log``: the run log (a run.mcap or its run directory), or its :func:`solve_times`.
    Sizes in inches. Returns the files. Raises FigureInputError on bad formats or sizes,
    an unreadable log or one without a solve, before anything is written.
    """
    check_size(width, height)
    fmts = parse_formats(formats)
    st = log if isinstance(log, SolveTimes) else solve_times(log)
    out = make_out_dir(Path(out_dir))
    with figure_style():
        save_figure(_figure(st, width, height), out, "timing", fmts, dpi=dpi)
    return [out / f"timing.{f}" for f in fmts]
