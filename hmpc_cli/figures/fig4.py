"""Figure 4 of the paper: the five-link biped climbing the stairs, drawn from one run log.

Top: stick-figure snapshots over the stair profile (colour = time), touchdown points
marked. Bottom: hip x(t), hip y(t) and the horizontal torso force F_x(t), contact times
as dotted lines. Also a GIF animation of the walk. Reads the MCAP log only; the
kinematics come from the system's own CasADi functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from hmpc_cli.figures.common import (
    TEXT_WIDTH_IN, FigureInputError, check_size, figure_style, parse_formats, resolve_run_log,
    save_figure)

__all__ = ["WalkLog", "animate_walk", "fig4", "load_walk", "resolve_run_log"]

LINK_COLOR = "#1f4e8c"
STAIR_COLOR = "#555555"
CONTACT_COLOR = "#d62728"


@dataclass
class WalkLog:
    """A biped run: times t (K,), joint points (K, 6, 2) in the world [m], hip (K, 2),
    contacts [(t, guard name, foot x, foot y)], force samples (t, F_x), stair edges
    [(x0, x1, height)], ground height, logged success."""

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


def load_walk(path: str | Path) -> WalkLog:
    """Reads a biped run log (any complete chunks of a killed run are used)."""
    from hmpc_cli.numeric import compile_numpy
    from hmpc_cli.recorder import read_log
    from hmpc_cli.systems.biped import BipedParams, POINT_NAMES, make_biped_model, stair_edges

    path = Path(path)
    if not path.is_file():
        raise FigureInputError(f"{path}: no such log")
    try:
        log = read_log(path)
    except (OSError, ValueError) as exc:
        raise FigureInputError(f"{path}: cannot read log ({exc})") from None
    infos = log.topic("/run/info")
    system = dict((infos[0].data.get("scenario") or {}).get("system") or {}) if infos else {}
    if system.get("name") != "biped":
        raise FigureInputError(f"{path}: not a biped run (system {system.get('name')!r})")
    try:
        params = BipedParams.model_validate(system)
    except ValueError as exc:
        raise FigureInputError(f"{path}: bad biped parameters in the log ({exc})") from None
    states = [(m.t, m.data.get("x")) for m in log.topic("/sim/state")]
    states = [(t, x) for t, x in states if x is not None and len(x) == 12
              and all(v is not None and math.isfinite(v) for v in x)]
    if not states:
        raise FigureInputError(f"{path}: log has no finite /sim/state samples")
    t = np.array([s[0] for s in states])
    x = np.array([s[1] for s in states], dtype=float)
    points_fn = compile_numpy(make_biped_model(params).points_world)
    points = points_fn(x)[0].reshape(len(t), len(POINT_NAMES), 2)
    hip = points[:, POINT_NAMES.index("hip"), :]
    foot = POINT_NAMES.index("swing_foot")
    contacts = []
    for m in log.topic("/sim/event"):
        xb = m.data.get("x_before")
        if xb is None or len(xb) != 12:
            continue
        p = points_fn(np.array(xb, dtype=float)[None])[0].reshape(len(POINT_NAMES), 2)
        contacts.append((float(m.data.get("t", m.t)), str(m.data.get("guard_name", "")),
                         float(p[foot, 0]), float(p[foot, 1])))
    dist = [(m.t, (m.data.get("w") or [0.0])[0]) for m in log.topic("/disturbance")]
    ft = np.array([d[0] for d in dist] or [0.0])
    fx = np.array([float(d[1]) if d[1] is not None else math.nan for d in dist] or [0.0])
    summaries = log.topic("/run/summary")
    ok = summaries[-1].data.get("success") if summaries else None
    reason = str(summaries[-1].data.get("reason", "")) if summaries else "no summary (killed?)"
    return WalkLog(path, t, points, hip, contacts, (ft, fx), stair_edges(params),
                   params.ground_height, ok if isinstance(ok, bool) else None, reason)


def _stairs_xy(walk: WalkLog, x_min: float) -> tuple[list[float], list[float]]:
    xs, ys = [x_min, 0.0], [walk.ground_height, walk.ground_height]
    for a, b, h in walk.stairs:
        xs += [a, b]
        ys += [h, h]
    xs.append(walk.stairs[-1][1])
    ys.append(walk.ground_height - 0.05)
    return xs, ys


def _draw_stick(ax, pts: np.ndarray, color, lw: float = 0.8) -> None:
    """Stance leg foot->hip, torso hip->top, swing leg hip->foot (POINT_NAMES order)."""
    chain = pts[[0, 1, 2, 4, 5]]
    ax.plot(chain[:, 0], chain[:, 1], color=color, lw=lw, solid_capstyle="round")
    ax.plot(pts[[2, 3], 0], pts[[2, 3], 1], color=color, lw=lw * 1.4, solid_capstyle="round")


def _snapshots(walk: WalkLog, every: float) -> list[int]:
    picks, next_t = [], walk.t[0]
    for k, tk in enumerate(walk.t):
        if tk >= next_t - 1e-9:
            picks.append(k)
            next_t = tk + every
    if picks[-1] != len(walk.t) - 1:
        picks.append(len(walk.t) - 1)
    return picks


def _out_dir(out: Path) -> Path:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FigureInputError(f"{out}: cannot create the output directory ({exc})") from None
    return out


def fig4(log: str | Path | WalkLog, out_dir: str | Path | None = None,
         formats: str | Iterable[str] = ("pdf", "svg", "png"), *,
         every: float = 0.1, width: float = TEXT_WIDTH_IN, height: float = 4.2) -> WalkLog:
    """Draws Figure 4 from a biped run (log path, run directory or a loaded
    :class:`WalkLog`) into out_dir/fig4.<fmt>; returns the parsed log.

    ``every``: time between stick-figure snapshots [s]; sizes in inches.
    """
    import matplotlib as mpl

    if not every > 0.0:
        raise FigureInputError(f"snapshot interval must be > 0 s, got {every}")
    fmts = parse_formats(formats)
    check_size(width, height)
    walk = log if isinstance(log, WalkLog) else load_walk(resolve_run_log(log))
    out = _out_dir(Path(out_dir) if out_dir is not None else walk.path.parent)
    with figure_style():
        import matplotlib.pyplot as plt

        fig = plt.figure(figsize=(width, height))
        grid = fig.add_gridspec(2, 3, height_ratios=[2.4, 1.0], hspace=0.3, wspace=0.32,
                                left=0.07, right=0.99, top=0.95, bottom=0.09)
        ax = fig.add_subplot(grid[0, :])
        cmap = mpl.colormaps["viridis"]
        t0, t1 = walk.t[0], max(walk.t[-1], walk.t[0] + 1e-9)
        for k in _snapshots(walk, every):
            _draw_stick(ax, walk.points[k], cmap(0.9 * (walk.t[k] - t0) / (t1 - t0)))
        ax.plot(walk.hip[:, 0], walk.hip[:, 1], color="0.5", lw=0.5, ls="--", label="hip path")
        x_min = min(-0.2, float(walk.points[:, :, 0].min()) - 0.05)
        sx, sy = _stairs_xy(walk, x_min)
        ax.plot(sx, sy, color=STAIR_COLOR, lw=1.0, drawstyle="default")
        if walk.contacts:
            cx = [c[2] for c in walk.contacts]
            cy = [c[3] for c in walk.contacts]
            ax.plot(cx, cy, "v", color=CONTACT_COLOR, ms=3.5, label="touchdown")
        ax.set_aspect("equal")
        ax.set_xlim(x_min, walk.stairs[-1][1] + 0.05)
        ax.set_ylim(min(sy) - 0.02, float(walk.points[:, :, 1].max()) + 0.08)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        verdict = {True: "success", False: "failed", None: "unfinished"}[walk.success]
        ax.set_title(f"biped on the stairs ({verdict}); snapshots every {every:g} s, "
                     "colour = time")
        ax.legend(loc="upper left", ncol=2)
        panels = [(walk.t, walk.hip[:, 0], "hip x [m]"), (walk.t, walk.hip[:, 1], "hip y [m]"),
                  (walk.force[0], walk.force[1], "torso force $F_x$ [N]")]
        for j, (tt, yy, label) in enumerate(panels):
            a = fig.add_subplot(grid[1, j])
            a.plot(tt, yy, color=LINK_COLOR, drawstyle="steps-post" if j == 2 else "default")
            for c in walk.contacts:
                a.axvline(c[0], color=CONTACT_COLOR, lw=0.4, ls=":")
            a.set_xlim(t0, t1)
            a.set_xlabel("t [s]")
            a.set_ylabel(label)
        save_figure(fig, out, "fig4", fmts)
    return walk


def animate_walk(log: str | Path | WalkLog, out_path: str | Path, fps: int = 25,
                 speed: float = 1.0, width: float = 5.0, height: float = 2.6) -> Path:
    """Writes a GIF of the walk: ``fps`` frames per second of playback, each advancing
    ``speed / fps`` seconds of simulated time (speed 1: real time)."""
    if fps < 1 or not speed > 0.0:
        raise FigureInputError(f"need fps >= 1 and speed > 0, got {fps}, {speed}")
    check_size(width, height)
    walk = log if isinstance(log, WalkLog) else load_walk(resolve_run_log(log))
    out_path = Path(out_path)
    _out_dir(out_path.parent)
    frames = np.arange(walk.t[0], walk.t[-1] + 1e-9, speed / fps)
    idx = np.minimum(np.searchsorted(walk.t, frames), len(walk.t) - 1)
    with figure_style():
        import matplotlib.pyplot as plt
        from matplotlib.animation import FuncAnimation, PillowWriter

        fig, ax = plt.subplots(figsize=(width, height))
        x_min = min(-0.2, float(walk.points[:, :, 0].min()) - 0.05)
        sx, sy = _stairs_xy(walk, x_min)
        ax.plot(sx, sy, color=STAIR_COLOR, lw=1.0)
        ax.set_aspect("equal")
        ax.set_xlim(x_min, walk.stairs[-1][1] + 0.05)
        ax.set_ylim(min(sy) - 0.02, float(walk.points[:, :, 1].max()) + 0.08)
        legs, = ax.plot([], [], color=LINK_COLOR, lw=1.5)
        torso, = ax.plot([], [], color=LINK_COLOR, lw=2.2)
        trail, = ax.plot([], [], color="0.5", lw=0.5, ls="--")
        label = ax.text(0.01, 0.95, "", transform=ax.transAxes, va="top")

        def draw(i: int):
            k = idx[i]
            p = walk.points[k]
            legs.set_data(p[[0, 1, 2, 4, 5], 0], p[[0, 1, 2, 4, 5], 1])
            torso.set_data(p[[2, 3], 0], p[[2, 3], 1])
            trail.set_data(walk.hip[: k + 1, 0], walk.hip[: k + 1, 1])
            label.set_text(f"t = {walk.t[k]:.2f} s")
            return legs, torso, trail, label

        anim = FuncAnimation(fig, draw, frames=len(frames), blit=True)
        tmp = out_path.with_name(f".{out_path.name}.tmp.gif")
        try:
            anim.save(tmp, writer=PillowWriter(fps=fps))
            tmp.replace(out_path)
        except OSError as exc:
            raise FigureInputError(f"{out_path}: cannot write the animation ({exc})") from None
        finally:
            plt.close(fig)
            tmp.unlink(missing_ok=True)
    return out_path
