"""Figure 2 of the paper from a recorded run: the virtual pass-through node and its tube.

Draws a :class:`~hmpc_cli.analysis.passthrough.PassThroughGeometry` (computed from a run log by
:func:`hmpc_cli.analysis.passthrough.pass_through_geometry`; this module never rebuilds a model),
in the plane of the system's ``plane`` states, two panels (the planned domain, and a
zoom on the guard):

* the guard the plan crosses first (the zero level set of its logged grid of gaps);
* the planned nodes of the domain before the guard, the last of them the *guard node*;
* the *virtual pass-through node* x_v and a tube disc of radius d around every planned
  node of that domain and around x_v (the projection onto the plane of the state-norm
  ball of radius d), and the disc's point nearest the guard;
* the reset: the post-reset node, a dashed arrow from the guard node to it, and the next
  domain's first planned nodes.

The title states whether x_v's disc lies entirely past the guard and whether the solve
was softened.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hmpc_cli.figures.common import (
    TEXT_WIDTH_IN,
    check_size,
    figure_style,
    make_out_dir,
    parse_formats,
    save_figure,
)

if TYPE_CHECKING:
    from hmpc_cli.analysis.passthrough import PassThroughGeometry

__all__ = ["fig2"]

NODE_COLOR = "#4a6fa5"  # planned nodes: muted blue
GUARD_NODE_COLOR = "#d62728"  # red
VIRTUAL_COLOR = "#ff7f0e"  # the paper's orange
RESET_COLOR = "#2e8b57"  # green
SOFT_TOL = 1e-6  # slack or guard-node gap above this: a softened solve, said in the title


def _draw(ax, geo: PassThroughGeometry, view: str, title: str) -> None:
    """One panel (``view``: "whole" or "zoom"): guard, tube discs, nodes, virtual node, reset."""
    from matplotlib.patches import Circle

    i, j = geo.plane
    gx, gy, gap = geo.guard_grids[view]
    if np.nanmin(gap, initial=np.inf) <= 0.0 <= np.nanmax(gap, initial=-np.inf):
        ax.contour(gx, gy, np.ma.masked_invalid(gap), levels=[0.0], colors="black",
                   linewidths=0.9, zorder=2)
    ax.plot([], [], color="black", lw=0.9, label=f"guard {geo.guard_name}")
    d = geo.radius
    for p in geo.nodes:
        ax.add_patch(Circle((p[i], p[j]), d, facecolor=NODE_COLOR, alpha=0.15,
                            edgecolor=NODE_COLOR, lw=0.4, zorder=3))
    ax.add_patch(Circle((geo.virtual_node[i], geo.virtual_node[j]), d, facecolor=VIRTUAL_COLOR,
                        alpha=0.25, edgecolor=VIRTUAL_COLOR, lw=0.6, zorder=3))
    ax.fill([], [], color=NODE_COLOR, alpha=0.3, label=f"tube disc, d = {d:.3g}")
    nodes = geo.nodes
    ax.plot(nodes[:-1, i], nodes[:-1, j], "o-", color=NODE_COLOR, ms=2.5, lw=0.6, zorder=4,
            label=f"planned nodes ({geo.source_mode})")
    ax.plot([nodes[-2, i], nodes[-1, i]] if len(nodes) > 1 else [],
            [nodes[-2, j], nodes[-1, j]] if len(nodes) > 1 else [], "-", color=NODE_COLOR,
            lw=0.6, zorder=4)
    gn, xv, post = geo.guard_node, geo.virtual_node, geo.post_reset
    ax.plot([gn[i], xv[i]], [gn[j], xv[j]], ":", color=VIRTUAL_COLOR, lw=0.9, zorder=4)
    ax.plot([gn[i]], [gn[j]], "s", color=GUARD_NODE_COLOR, ms=4.0, zorder=6,
            label="guard node")
    ax.plot([xv[i]], [xv[j]], "D", mfc="white", mec=VIRTUAL_COLOR, mew=0.9, ms=4.0,
            zorder=6, label="virtual node")
    ax.plot([geo.disc_point[0]], [geo.disc_point[1]], "x", color="black", ms=3.5, mew=0.7,
            zorder=7, label="disc point nearest the guard")
    after = geo.next_nodes
    ax.plot(after[:, i], after[:, j], "o-", color=RESET_COLOR, ms=2.5, lw=0.6, alpha=0.8,
            zorder=4, label=f"after the reset ({geo.target_mode})")
    changed = geo.reset_changes
    ax.plot([post[i]], [post[j]], "o", mfc="none", mec=RESET_COLOR, mew=0.9, ms=6.5,
            zorder=5, label=f"post-reset node (reset changes {', '.join(changed) or 'nothing'})")
    if math.hypot(post[i] - gn[i], post[j] - gn[j]) > 1e-9:
        ax.annotate("", xy=(post[i], post[j]), xytext=(gn[i], gn[j]), zorder=5,
                    arrowprops={"arrowstyle": "->", "linestyle": "--", "color": RESET_COLOR,
                                "lw": 0.8})
    ax.set_xlim(*geo.views[view][0])
    ax.set_ylim(*geo.views[view][1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"{geo.plane_names[0]}")
    ax.set_title(title)


def _title(geo: PassThroughGeometry) -> str:
    """The figure's title: the verdict on the virtual node's disc, never hidden."""
    verdict = ("its tube disc lies entirely past the guard" if geo.disc_past else
               "its tube disc is NOT entirely past the guard")
    text = (f"solve {geo.solve} (t = {geo.t:.3f} s) crosses {geo.guard_name}: virtual node "
            f"gap {geo.virtual_gap:.4g}, disc's nearest point {geo.disc_gap:.4g}: {verdict}")
    if geo.slack > SOFT_TOL or abs(geo.guard_node_gap) > SOFT_TOL:
        text += (f"\nsoftened solve (slack {geo.slack:.2g}): the guard node's gap is "
                 f"{geo.guard_node_gap:.2g}")
    return text


def _figure(geo: PassThroughGeometry, width: float, height: float):
    """The two-panel Figure (no pyplot state): the domain's plan, and a zoom on the guard."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="compressed")  # fixed-aspect panels
    fig.get_layout_engine().set(w_pad=0.02, h_pad=0.02, wspace=0.04)
    ax_a, ax_b = fig.subplots(1, 2)
    _draw(ax_a, geo, "whole", "the planned domain")
    _draw(ax_b, geo, "zoom", "at the guard")
    ax_a.set_ylabel(f"{geo.plane_names[1]}")
    handles, labels = ax_a.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right center", handlelength=1.6,
               labelspacing=0.6)
    fig.suptitle(_title(geo), fontsize=7)
    return fig


def check_request(formats: str | Iterable[str], width: float, height: float) -> list[str]:
    """The formats of a Figure 2 request (FigureInputError: bad formats or size)."""
    check_size(width, height)
    return parse_formats(formats)


def fig2(geo: PassThroughGeometry, out_dir: str | Path,
         formats: str | Iterable[str] = ("pdf", "svg", "png"), *,
         width: float = TEXT_WIDTH_IN, height: float = 2.8, dpi: int = 300) -> list[Path]:
    """Draws Figure 2 of a pass-through into out_dir/fig2.<fmt>; returns the files.

    Sizes in inches. Raises FigureInputError on bad formats or sizes, before anything is
    written.
    """
    fmts = check_request(formats, width, height)
    out = Path(out_dir)
    make_out_dir(out)
    with figure_style():  # nothing from the user's matplotlibrc leaks in
        save_figure(_figure(geo, width, height), out, "fig2", fmts, dpi=dpi)
    return [out / f"fig2.{f}" for f in fmts]
