"""An animation of any run from its logged 3D scene (``/scene/*``): no model rebuilt.

The frames replay what the viewers show: the static geometry, the body, the current MPC
plan with its tube and the planner's latest rollout, drawn in the system's plane (world
x horizontal, world z up; :mod:`hmpc_cli.log.scene` puts plane (a, b) at (a, 0, b)). Written
as GIF (Pillow, through Matplotlib) and as MP4 when ffmpeg is on the PATH.
"""

from __future__ import annotations

import shutil
from bisect import bisect_right
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hmpc_cli.analysis.tables import FigureInputError
from hmpc_cli.core import signals
from hmpc_cli.figures.common import figure_style, save_gif

__all__ = ["SceneFrames", "animate_scene", "read_scene"]

#: at most this many frames (the GIF's size)
MAX_FRAMES = 400


@dataclass
class SceneFrames:
    """The decoded scene: per topic, (times [s], entity lists) in time order."""

    static: list = field(default_factory=list)
    body: tuple[list[float], list] = field(default_factory=lambda: ([], []))
    plan: tuple[list[float], list] = field(default_factory=lambda: ([], []))
    rollout: tuple[list[float], list] = field(default_factory=lambda: ([], []))


def read_scene(log) -> SceneFrames:
    """The /scene/* topics of a read log (:func:`hmpc_cli.log.reader.read_log`).

    Raises:
        FigureInputError: the log has no scene (a system without a drawing, or an older
            log).
    """
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    out = SceneFrames()
    for topic, slot in (("/scene/body", "body"), ("/scene/plan", "plan"),
                        ("/scene/rollout", "rollout")):
        times, entities = getattr(out, slot)
        for m in log.raw_topic(topic):
            times.append(m.t)
            entities.append(list(SceneUpdate.FromString(m.data).entities))
    for m in log.raw_topic("/scene/static"):
        out.static += list(SceneUpdate.FromString(m.data).entities)
    if not out.body[0]:
        from hmpc_cli.log.rundata import damage_note

        cut = damage_note(log.damage, log.complete)
        if cut or out.static:  # a drawing was logged: the log ends before its first state
            raise FigureInputError("the log has no /scene/body sample" + (
                cut or " (it ends before its first state)"))
        raise FigureInputError("the log has no /scene/body (a system without a drawing, "
                               "or a log written before hmpc logged its scene)")
    return out


def _latest(series: tuple[list[float], list], t: float) -> list:
    times, entities = series
    i = bisect_right(times, t + 1e-12) - 1
    return entities[i] if i >= 0 else []


def _rgba(c) -> tuple[float, float, float, float]:
    return (c.r, c.g, c.b, c.a)


def _draw(ax, entities: list, zorder: int) -> None:
    """Lines (strips, loops, lists) and spheres (as circles) of scene entities."""
    from matplotlib.patches import Circle

    for e in entities:
        for ln in e.lines:
            pts = np.array([(p.x, p.z) for p in ln.points])
            if not len(pts):
                continue
            color = _rgba(ln.color)
            if ln.type == ln.LINE_LIST:
                for a, b in zip(pts[0::2], pts[1::2], strict=False):
                    ax.plot([a[0], b[0]], [a[1], b[1]], color=color, lw=1.2, zorder=zorder)
            else:
                if ln.type == ln.LINE_LOOP:
                    pts = np.vstack([pts, pts[:1]])
                ax.plot(pts[:, 0], pts[:, 1], color=color, lw=1.0, zorder=zorder)
        for s in e.spheres:
            ax.add_patch(Circle((s.pose.position.x, s.pose.position.z), s.size.x / 2,
                                color=_rgba(s.color), zorder=zorder + 1, lw=0))


def _bounds(frames: SceneFrames) -> tuple[float, float, float, float]:
    pts = [(p.x, p.z) for e in frames.static for ln in e.lines for p in ln.points]
    for ents in frames.body[1]:
        for e in ents:
            pts += [(p.x, p.z) for ln in e.lines for p in ln.points]
            pts += [(s.pose.position.x, s.pose.position.z) for s in e.spheres]
    a = np.array(pts, dtype=float)
    a = a[np.all(np.isfinite(a), axis=1)]
    lo, hi = a.min(axis=0), a.max(axis=0)
    pad = 0.05 * max(float(np.max(hi - lo)), 1e-3)
    return lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad


def animate_scene(log, out_dir: Path, title: str, fps: int = 20) -> list[Path]:
    """Writes ``scene.gif`` (and ``scene.mp4`` with ffmpeg) into ``out_dir``.

    The figure is 6 in wide: the GIF at :data:`~hmpc_cli.figures.common.GIF_DPI` (900
    pixels), the MP4 at the figure files' 300 dpi.

    Args:
        log: a read log (:func:`hmpc_cli.log.reader.read_log`) with /scene/* topics.
        out_dir: existing output directory.
        title: the figure title (the time is appended per frame).
        fps: frames per simulated second (playback in real time), capped so that at most
            :data:`MAX_FRAMES` frames are drawn.

    Raises:
        FigureInputError: the log has no scene.
    """
    import matplotlib.pyplot as plt
    from matplotlib.animation import FFMpegWriter, FuncAnimation

    frames = read_scene(log)
    t0, t1 = frames.body[0][0], frames.body[0][-1]
    n = int(min(MAX_FRAMES, max(2, round((t1 - t0) * fps) + 1)))
    times = np.linspace(t0, t1, n)
    x0, x1, z0, z1 = _bounds(frames)
    with figure_style():
        fig, ax = plt.subplots(figsize=(6.0, 6.0 * min(max((z1 - z0) / (x1 - x0), 0.3), 1.5)),
                               layout="constrained")

        def draw(k: int) -> None:
            signals.check()  # a stop signal ends the animation between frames
            ax.clear()
            _draw(ax, frames.static, 1)
            _draw(ax, _latest(frames.rollout, times[k]), 2)
            _draw(ax, _latest(frames.plan, times[k]), 3)
            _draw(ax, _latest(frames.body, times[k]), 5)
            ax.set_xlim(x0, x1)
            ax.set_ylim(z0, z1)
            ax.set_aspect("equal")
            ax.set_title(f"{title}  t = {times[k]:.2f} s")

        rate = max(1, round(n / max(t1 - t0, 1e-9)))
        paths = [Path(out_dir) / "scene.gif"]
        try:
            save_gif(fig, draw, range(n), paths[0], rate)
            if shutil.which("ffmpeg"):
                paths.append(Path(out_dir) / "scene.mp4")
                _save(FuncAnimation(fig, draw, frames=n), paths[1], FFMpegWriter(fps=rate))
        finally:
            plt.close(fig)
    return paths


def _save(anim, path: Path, writer) -> None:
    """Saves an animation under a temporary name (same suffix), then renames it.

    A failed save (a full disk) leaves neither the temporary nor a half file.
    """
    import os

    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        anim.save(tmp, writer=writer)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
