"""Parameters and bounds of one fixed-mode NLP solve, filled block by block by name.

The blocks are those of :class:`~hmpc_cli.mpc.chain.nlp.FixedModeNLP` (see its docstring and
the module docstring of :mod:`hmpc_cli.mpc.chain.nlp` for the rows they switch on).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.messages import ConstraintMargins
from hmpc_cli.mpc.builder import Bounds, NLPLayout
from hmpc_cli.mpc.chain.layout import FLOW, HOLD, RESET, ChainLayout, NodeSchedule

INF = np.inf
VIRTUAL_INPUT_WEIGHT = 1e-3


@dataclass(frozen=True)
class ChainShape:
    """What one solve's parameters and bounds need of a built chain NLP.

    Attributes:
        system: the controllers' hybrid system.
        s: the MPC settings (``soft_penalty``, ``input_hold``, ``robust`` are read).
        layout: the NLP's variable, parameter and row layout.
        L: links in the chain (N + S).
        m: inputs.
        dt: the node spacing [s].
        margins: the constraint tightenings.
        input_boxes: per mode its tightened input box, shape (modes, 2, m).
        mode_cols: per mode its column of the link-type parameter a (-1: no flow).
        guards_of: per mode the indices of its guards.
        guard_col: guard index -> its column of the guard rows.
        avoid_offsets: per guard (offset when just entered, offset otherwise).
    """

    system: HybridSystem
    s: Any
    layout: NLPLayout
    L: int
    m: int
    dt: float
    margins: ConstraintMargins
    input_boxes: np.ndarray
    mode_cols: np.ndarray
    guards_of: list[list[int]]
    guard_col: dict[int, int]
    avoid_offsets: list[tuple[float, float]]


def problem_data(nlp: ChainShape, ns: NodeSchedule, lay: ChainLayout, x0: np.ndarray):
    """Parameters and bounds of one solve of ``nlp`` (vectorised over links and nodes).

    Args:
        nlp: the built NLP's shape.
        ns: the node schedule.
        lay: its layout on the NLP's chain.
        x0: the current state, shape (n,).

    Returns:
        (p, lbx, ubx, lbg, ubg), flat, shapes (np,), (nx,), (nx,), (ng,), (ng,).
    """
    par = nlp.layout.p.zeros()
    bounds = nlp.layout.bounds()
    bounds.lbx["sigma"][:] = 0.0
    bounds.ubx["sigma"][:] = INF if nlp.s.soft_penalty > 0.0 else 0.0
    bounds.lbx["z"][0] = bounds.ubx["z"][0] = x0
    bounds.lbg["dynamics"][:] = bounds.ubg["dynamics"][:] = 0.0
    _links(nlp, lay, par, bounds)
    for j in range(len(ns.modes)):
        _segment(nlp, ns, lay, j, par, bounds)
    if "terminal" in nlp.layout.g:
        bounds.lbg["terminal"][:] = 0.0
    return (nlp.layout.p.pack(par), *bounds.arrays())


def _links(nlp: ChainShape, lay: ChainLayout, par: dict, bounds: Bounds) -> None:
    """Every link: its type (a, b, e), cost weights, input hold and input bounds."""
    typ, mode = lay.link_type, lay.link_mode
    lo, hi = np.zeros((nlp.L, nlp.m)), np.zeros((nlp.L, nlp.m))
    boxes = nlp.input_boxes  # (modes, 2, m)
    flow = np.nonzero(typ == FLOW)[0]
    par["a"][flow, nlp.mode_cols[mode[flow]]] = 1.0
    par["w"][flow] = nlp.dt
    lo[flow], hi[flow] = boxes[mode[flow], 0], boxes[mode[flow], 1]
    # first-order hold up to the next link's input (the virtual input before a guard
    # node); the horizon's last interval holds its input
    if nlp.s.input_hold == "foh":
        nxt = np.append(typ[1:], HOLD)
        par["foh"][flow[nxt[flow] != HOLD]] = 1.0
    reset = np.nonzero(typ == RESET)[0]
    par["b"][reset, lay.link_guard[reset]] = 1.0
    # the reset link's input: the virtual node's (robust), and in either case the end of
    # the first-order hold of the interval before the guard node, so within the source
    # mode's box (pinned at 0 without the virtual node, it ramped that interval's input
    # to 0 and left the tightened box)
    par["v"][reset] = VIRTUAL_INPUT_WEIGHT * nlp.dt
    lo[reset], hi[reset] = boxes[mode[reset], 0], boxes[mode[reset], 1]
    par["e"][typ == HOLD] = 1.0
    bounds.lbx["u"][:], bounds.ubx["u"][:] = lo, hi


def _segment(nlp: ChainShape, ns: NodeSchedule, lay: ChainLayout, j: int, par: dict,
             bounds: Bounds) -> None:
    """Domain j's path rows: guard-avoid per guard of its mode, guard-hit at its guard node.

    Its nodes from 1 on, without the first node after a reset (fixed by the reset link).
    """
    k = np.nonzero((lay.seg == j) & ~lay.first_after_reset)[0]
    k = k[k >= 1]
    entered_by = ns.guards[j - 1] if j > 0 else -1
    guard_node = lay.node_of(j, ns.counts[j]) if j < len(ns.guards) else -1
    for gi in nlp.guards_of[ns.modes[j]]:
        c = nlp.guard_col[gi]
        par["s"][k, c] = 1.0
        bounds.lbg["guard_avoid"][k, c] = 0.0
        par["kappa"][k, c] = nlp.avoid_offsets[gi][0 if gi == entered_by else 1]
        if guard_node >= 0 and gi == ns.guards[j]:  # guard-hit: |q| <= sigma
            par["kappa"][guard_node, c] = 0.0
            par["hit"][guard_node, gi] = 1.0
            bounds.ubg["guard_hit"][guard_node] = 0.0
    if guard_node >= 0:
        _guard_node(nlp, ns.guards[j], guard_node, par, bounds)


def _guard_node(nlp: ChainShape, gi: int, k: int, par: dict, bounds: Bounds) -> None:
    """Guard node k of guard gi: the virtual pass-through row and the region rows."""
    g = nlp.system.guards[gi]
    par["beta"][k, gi] = 1.0  # without the virtual node: region rows only
    if nlp.s.robust:
        par["kappa_v"][k] = nlp.margins.pass_through[gi]
        bounds.lbg["virtual_node"][k] = 0.0
    dims = g.region.size1_out(0) if g.region is not None else 0
    if dims:
        bounds.lbg["region"][k, :dims] = 0.0
