"""Figure 4 of the paper: a walking system climbing its terrain, drawn from one run log.

Top: stick-figure snapshots over the terrain profile (colour = time, with a colour bar;
poses that barely moved are skipped), touchdown points marked. Below: hip x(t), hip y(t)
and the first disturbance channel (the biped's horizontal torso force F_x(t)), contact
times as dotted lines. Also a GIF animation of
the walk. Reads the MCAP log only (:func:`hmpc_cli.log.rundata.read_run`): the body points
logged with every state sample and guard event, the skeleton and the terrain of the log's
geometry (:mod:`hmpc_cli.log.geometry`). Any system whose drawing has links, a ``hip`` and
a ``swing_foot`` point and a terrain can be drawn.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.figures.common import (
    COLUMN_WIDTH_IN,
    GIF_DPI,
    OKABE_ITO,
    check_size,
    figure_style,
    make_out_dir,
    parse_formats,
    save_figure,
    save_gif)
from hmpc_cli.analysis.tables import FigureInputError, resolve_run_log

__all__ = ["WalkLog", "animate_walk", "fig4", "load_walk", "resolve_run_log"]

WALKER_POINTS = ("hip", "swing_foot")  #: the body points fig4 draws a walker by
LINK_COLOR = OKABE_ITO["blue"]
STAIR_COLOR = "#555555"
CONTACT_COLOR = OKABE_ITO["vermillion"]
HEIGHT_IN = 4.2  # default height at one-column width
MIN_MOVE_M = 0.03  # a snapshot is drawn only if some body point moved this far [m]


@dataclass
class WalkLog:
    """A walking run read from its log.

    Times t (K,), body points (K, P, 2) in the world [m], hip (K, 2), contacts
    [(t, guard name, foot x, foot y)], disturbance samples (t, w_0), terrain segments
    [(x0, x1, height)], ground height, the skeleton as point-index polylines, logged
    success; ``log_note``: the damage or cut of a log not read whole
    (:func:`hmpc_cli.log.rundata.damage_note`; '' if intact).
    """

    path: Path
    t: np.ndarray
    points: np.ndarray
    hip: np.ndarray
    contacts: list[tuple[float, str, float, float]]
    force: tuple[np.ndarray, np.ndarray]
    stairs: list[tuple[float, float, float]]
    ground_height: float
    success: bool | None
    reason: str
    skeleton: list[list[int]]
    log_note: str = ""


def load_walk(path: str | Path) -> WalkLog:
    """Reads a walking run's log (any complete chunks of a killed run are used).

    Everything comes from the log (:class:`~hmpc_cli.log.rundata.RunData`): the body points
    of every state sample, the skeleton, the terrain and the touchdown points.

    Raises:
        FigureInputError: no such log, unreadable, or a log without the terrain and the
            body points ``hip`` and ``swing_foot`` (not a walking run, or written by an
            hmpc before log version 3; the message names what is missing).
    """
    from hmpc_cli.log.rundata import read_run, sweep_text

    path = Path(path)
    if not path.is_file():
        sweep = sweep_text(path) if path.is_dir() else ""
        raise FigureInputError(f"{path}{sweep or ': no such log'}")
    try:
        run = read_run(path, with_plans=False)
    except ValueError as exc:
        raise FigureInputError(f"{path}: cannot read log ({exc})") from None
    geo = run.geometry
    names = list(geo.point_names) if geo is not None else []
    if geo is None or geo.terrain is None or not set(WALKER_POINTS) <= set(names):
        why = f"log version {run.log_version} has no geometry; re-run it with this hmpc" \
            if run.log_version < 3 else _not_a_walker(run.system.get("name", "?"), geo)
        raise FigureInputError(f"{path}: not a walking run to draw ({why})")
    keep = np.all(np.isfinite(run.body), axis=(1, 2)) & np.all(np.isfinite(run.x), axis=1)
    if not np.any(keep):
        raise FigureInputError(f"{path}: log has no finite /sim/state samples")
    points = run.body[keep]
    terrain = geo.terrain
    return WalkLog(path, run.t[keep], points, points[:, names.index("hip"), :],
                   _contacts(run, names.index("swing_foot")), _force(run),
                   [(s.x0, s.x1, s.height) for s in terrain.segments],
                   float(terrain.ground), *_outcome(run),
                   [[names.index(n) for n in line.points] for line in geo.skeleton],
                   run.damage_text)


def _not_a_walker(system: str, geo) -> str:
    """What fig4 needs that a log's geometry ``geo`` (None: none) lacks, and what it logs."""
    names = list(geo.point_names) if geo is not None else []
    lacks = [*(["no terrain"] if geo is None or geo.terrain is None else []),
             *(f"no body point {n!r}" for n in WALKER_POINTS if n not in names)]
    logs = f"its body points: {', '.join(map(repr, names))}" if names else "no body points"
    return (f"fig4 needs the terrain and the body points named "
            f"{' and '.join(map(repr, WALKER_POINTS))}; system {system!r} logs {', '.join(lacks)}"
            f" ({logs})")


def _contacts(run, foot: int) -> list[tuple[float, str, float, float]]:
    """(t, guard name, swing foot x, y) of every logged guard event (its body before)."""
    out = []
    for ev in run.events:
        if len(ev.body_before) <= foot or not np.all(np.isfinite(ev.body_before[foot])):
            continue
        out.append((ev.t, ev.guard_name, float(ev.body_before[foot, 0]),
                    float(ev.body_before[foot, 1])))
    return out


def _force(run) -> tuple[np.ndarray, np.ndarray]:
    """The first disturbance channel as a step trace (t, w_0) to the run's end.

    The disturbance is logged when it changes; its last value holds until the run ends
    (the summary's ``t_end``, else the last state sample), which closes the trace.
    """
    end = run.summary.t_end if run.summary is not None else (run.t[-1] if run.t.size else 0.0)
    if not run.t_w.size or not run.w_changes.shape[1]:
        return np.array([0.0, end]), np.array([0.0, 0.0])
    t, w = run.t_w, run.w_changes[:, 0]
    if end > t[-1]:
        t, w = np.append(t, end), np.append(w, w[-1])
    return t, w


def _outcome(run) -> tuple[bool | None, str]:
    """The logged success (None if the run has no summary) and reason."""
    if run.summary is None:
        return None, "no summary (killed?)"
    return bool(run.summary.success), run.summary.reason


def _draw_terrain(ax, walk: WalkLog) -> tuple[float, float, float]:
    """The terrain's profile under the walk, dotted past the last segment's end.

    Past the end the terrain keeps the top's height, with no guard there.

    Returns:
        x_min, x_max, y_min [m]: the limits that hold the terrain and every body point.
    """
    x_min = min(-0.2, float(walk.points[:, :, 0].min()) - 0.05)
    end, top = walk.stairs[-1][1], walk.stairs[-1][2]
    x_max = max(end, float(walk.points[:, :, 0].max())) + 0.05
    xs, ys = [x_min, 0.0], [walk.ground_height, walk.ground_height]
    for a, b, h in walk.stairs:
        xs += [a, b]
        ys += [h, h]
    ax.plot(xs, ys, color=STAIR_COLOR, lw=1.0)
    ax.plot([end, x_max], [top, top], color=STAIR_COLOR, lw=1.0, ls=":")
    return x_min, x_max, min(*ys, float(walk.points[:, :, 1].min())) - 0.02


def _draw_stick(ax, pts: np.ndarray, skeleton: list[list[int]], color, lw: float = 0.8
                ) -> None:
    """The skeleton's polylines (the first is the legs, the others drawn thicker)."""
    for j, line in enumerate(skeleton):
        ax.plot(pts[line, 0], pts[line, 1], color=color, lw=lw * (1.0 if j == 0 else 1.4),
                solid_capstyle="round")


def _snapshots(walk: WalkLog, every: float, min_move: float = MIN_MOVE_M) -> list[int]:
    """Samples ``every`` seconds apart, less those where the robot stands still.

    A snapshot whose body points all lie within ``min_move`` metres of the last drawn one is
    skipped (it would only redraw the same pose on top of itself).
    """
    picks, next_t = [], walk.t[0]
    for k, tk in enumerate(walk.t):
        if tk >= next_t - 1e-9 or k == len(walk.t) - 1:
            next_t = tk + every
            if picks and np.max(np.linalg.norm(walk.points[k] - walk.points[picks[-1]],
                                               axis=1)) < min_move:
                continue
            picks.append(k)
    return picks


def _draw_walk(ax, walk: WalkLog, every: float, cmap, norm) -> None:
    """The top panel: snapshots coloured by time, hip path, stairs, touchdowns."""
    for k in _snapshots(walk, every):
        _draw_stick(ax, walk.points[k], walk.skeleton, cmap(norm(walk.t[k])))
    ax.plot(walk.hip[:, 0], walk.hip[:, 1], color="0.4", lw=0.5, ls="--", label="hip path")
    x_min, x_max, y_min = _draw_terrain(ax, walk)
    if walk.contacts:
        ax.plot([c[2] for c in walk.contacts], [c[3] for c in walk.contacts], "v",
                color=CONTACT_COLOR, ms=3.5, label="touchdown")
    ax.set_aspect("equal")
    ax.set_xlim(x_min, x_max)
    # headroom above the tallest pose for the legend
    ax.set_ylim(y_min, float(walk.points[:, :, 1].max()) + 0.3)
    ax.set_xlabel("$x$ (m)")
    ax.set_ylabel("$y$ (m)")
    verdict = {True: "success", False: "failed", None: "unfinished"}[walk.success]
    ax.set_title(f"biped on the stairs ({verdict}), snapshots every {every:g} s")
    ax.legend(loc="upper left", ncol=2, handlelength=1.6, columnspacing=1.0)


def _figure(walk: WalkLog, every: float, width: float, height: float):
    """Builds Figure 4 (no pyplot state).

    The walk with a time colour bar over the hip x(t), y(t) and force panels (one shared
    time axis, contact times dotted).
    """
    import matplotlib as mpl
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import ListedColormap, Normalize
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    fig = Figure(figsize=(width, height), layout="constrained")
    fig.get_layout_engine().set(w_pad=0.02, h_pad=0.02, hspace=0.03)
    grid = fig.add_gridspec(4, 1, height_ratios=[2.3, 1.0, 1.0, 1.0])
    ax = fig.add_subplot(grid[0])
    t0, t1 = walk.t[0], max(walk.t[-1], walk.t[0] + 1e-9)
    # viridis without its palest yellow (too faint on white), t0 .. t1 over the bar
    cmap = ListedColormap(mpl.colormaps["viridis"](np.linspace(0.0, 0.9, 256)))
    norm = Normalize(t0, t1)
    _draw_walk(ax, walk, every, cmap, norm)
    # the bar as high as the equal-aspect panel itself (an inset follows its drawn box)
    bar = fig.colorbar(ScalarMappable(norm, cmap), cax=ax.inset_axes([1.025, 0.0, 0.035, 1.0]))
    ax.set_anchor("C")  # a wide figure's equal-aspect panel stays centred
    bar.set_label("$t$ (s)")
    bar.locator = MaxNLocator(4)
    bar.update_ticks()
    panels = [(walk.t, walk.hip[:, 0], "hip $x$ (m)"), (walk.t, walk.hip[:, 1], "hip $y$ (m)"),
              (walk.force[0], walk.force[1], "$F_x$ (N)")]
    axes = []
    for j, (tt, yy, label) in enumerate(panels):
        a = fig.add_subplot(grid[j + 1], sharex=axes[0] if axes else None)
        a.plot(tt, yy, color=LINK_COLOR, drawstyle="steps-post" if j == 2 else "default")
        for c in walk.contacts:
            a.axvline(c[0], color=CONTACT_COLOR, lw=0.5, ls=":")
        a.set_xlim(t0, t1)
        a.set_ylabel(label)
        a.yaxis.set_major_locator(MaxNLocator(3))
        a.tick_params(labelbottom=j == 2)
        axes.append(a)
    axes[-1].set_xlabel("$t$ (s)")
    fig.align_ylabels(axes)
    return fig


def fig4(log: str | Path | WalkLog, out_dir: str | Path | None = None,
         formats: str | Iterable[str] = ("pdf", "svg", "png"), *,
         every: float = 0.1, width: float = COLUMN_WIDTH_IN, height: float = HEIGHT_IN
         ) -> WalkLog:
    """Draws Figure 4 from a walking run into out_dir/fig4.<fmt>; returns the parsed log.

    ``log``: a log path, a run directory or a loaded :class:`WalkLog`.

    ``every``: time between stick-figure snapshots [s] (poses that barely moved are
    skipped); sizes in inches (default: one IEEE column).
    """
    if not every > 0.0:
        raise FigureInputError(f"snapshot interval must be > 0 s, got {every}")
    fmts = parse_formats(formats)
    check_size(width, height)
    walk = log if isinstance(log, WalkLog) else load_walk(resolve_run_log(log))
    out = make_out_dir(Path(out_dir) if out_dir is not None else walk.path.parent)
    with figure_style():
        save_figure(_figure(walk, every, width, height), out, "fig4", fmts)
    return walk


def animate_walk(log: str | Path | WalkLog, out_path: str | Path, fps: int = 25,
                 speed: float = 1.0, width: float = 5.0, height: float = 2.6,
                 dpi: int = GIF_DPI) -> Path:
    """Writes a GIF of the walk.

    ``fps`` frames per second of playback, each advancing ``speed / fps`` seconds of
    simulated time (speed 1: real time); ``width`` x ``height`` [in] at ``dpi`` [dots per
    inch] (the default: 750 x 390 pixels).
    """
    if fps < 1 or not speed > 0.0:
        raise FigureInputError(f"need fps >= 1 and speed > 0, got {fps}, {speed}")
    check_size(width, height)
    walk = log if isinstance(log, WalkLog) else load_walk(resolve_run_log(log))
    out_path = Path(out_path)
    make_out_dir(out_path.parent)
    frames = np.arange(walk.t[0], walk.t[-1] + 1e-9, speed / fps)
    idx = np.minimum(np.searchsorted(walk.t, frames), len(walk.t) - 1)
    with figure_style():
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(width, height))
        x_min, x_max, y_min = _draw_terrain(ax, walk)
        ax.set_aspect("equal")
        ax.set_xlim(x_min, x_max)
        ax.set_ylim(y_min, float(walk.points[:, :, 1].max()) + 0.08)
        legs, = ax.plot([], [], color=LINK_COLOR, lw=1.5)
        torso, = ax.plot([], [], color=LINK_COLOR, lw=2.2)
        trail, = ax.plot([], [], color="0.5", lw=0.5, ls="--")
        label = ax.text(0.01, 0.95, "", transform=ax.transAxes, va="top")

        def frame(k: int) -> None:
            signals.check()  # a stop signal ends the animation between frames
            p = walk.points[k]
            legs.set_data(p[walk.skeleton[0], 0], p[walk.skeleton[0], 1])
            rest = [i for line in walk.skeleton[1:] for i in (*line, None)]
            torso.set_data([np.nan if i is None else p[i, 0] for i in rest],
                           [np.nan if i is None else p[i, 1] for i in rest])
            trail.set_data(walk.hip[: k + 1, 0], walk.hip[: k + 1, 1])
            label.set_text(f"t = {walk.t[k]:.2f} s")

        try:
            save_gif(fig, frame, idx, out_path, fps, dpi)
        except OSError as exc:
            raise FigureInputError(f"{out_path}: cannot write the animation ({exc})") from None
        finally:
            plt.close(fig)
    return out_path
