"""Parameters and bounds of one fixed-mode NLP solve, filled block by block by name.

The blocks are those of :class:`~hmpc_cli.mpc.nlp.FixedModeNLP` (see its docstring and
the module docstring of :mod:`hmpc_cli.mpc.nlp` for the rows they switch on).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from hmpc_cli.mpc.builder import Bounds
from hmpc_cli.mpc.layout import FLOW, HOLD, RESET, ChainLayout, NodeSchedule

if TYPE_CHECKING:
    from hmpc_cli.mpc.nlp import FixedModeNLP

INF = np.inf
VIRTUAL_INPUT_WEIGHT = 1e-3


def problem_data(nlp: FixedModeNLP, ns: NodeSchedule, lay: ChainLayout, x0: np.ndarray):
    """Parameters and bounds of one solve of ``nlp``.

    Args:
        nlp: the NLP.
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
    for k in range(nlp.L):
        _link(nlp, lay, k, par, bounds)
    for k in range(1, lay.last + 1):
        if not lay.first_after_reset[k]:
            _node(nlp, ns, lay, k, par, bounds)
    if "terminal" in nlp.layout.g:
        bounds.lbg["terminal"][:] = 0.0
    return (nlp.layout.p.pack(par), *bounds.arrays())


def _link(nlp: FixedModeNLP, lay: ChainLayout, k: int, par: dict, bounds: Bounds) -> None:
    """Link k: its type (a, b, e), cost weights, input hold and input bounds."""
    typ, mode = lay.link_type[k], lay.link_mode[k]
    lo = hi = np.zeros(nlp.m)
    if typ == FLOW:
        par["a"][k, nlp.mode_col[mode]], par["w"][k] = 1.0, nlp.dt
        lo, hi = nlp.input_box(mode)
        # first-order hold up to the next link's input (the virtual input before a guard
        # node); the horizon's last interval holds its input
        if nlp.s.input_hold == "foh" and k + 1 < nlp.L and lay.link_type[k + 1] != HOLD:
            par["foh"][k] = 1.0
    elif typ == RESET:
        par["b"][k, lay.link_guard[k]] = 1.0
        if nlp.s.robust:
            par["v"][k] = VIRTUAL_INPUT_WEIGHT * nlp.dt
            lo, hi = nlp.input_box(mode)
    else:
        par["e"][k] = 1.0
    bounds.lbx["u"][k], bounds.ubx["u"][k] = lo, hi


def _node(nlp: FixedModeNLP, ns: NodeSchedule, lay: ChainLayout, k: int, par: dict,
          bounds: Bounds) -> None:
    """Node k's path rows: guard-avoid or guard-hit per guard of its mode (+ guard node)."""
    j = int(lay.seg[k])
    entered_by = ns.guards[j - 1] if j > 0 else -1
    is_guard_node = j < len(ns.guards) and lay.local[k] == ns.counts[j]
    for gi in nlp.guards_of[ns.modes[j]]:
        c = nlp.guard_col[gi]
        par["s"][k, c] = 1.0
        bounds.lbg["guard_avoid"][k, c] = 0.0
        if is_guard_node and gi == ns.guards[j]:  # guard-hit: |q| <= sigma
            par["hit"][k, gi] = 1.0
            bounds.ubg["guard_hit"][k] = 0.0
        else:
            par["kappa"][k, c] = nlp.avoid_offsets[gi][0 if gi == entered_by else 1]
    if is_guard_node:
        _guard_node(nlp, ns.guards[j], k, par, bounds)


def _guard_node(nlp: FixedModeNLP, gi: int, k: int, par: dict, bounds: Bounds) -> None:
    """Guard node k of guard gi: the virtual pass-through row and the region rows."""
    g = nlp.system.guards[gi]
    par["beta"][k, gi] = 1.0  # without the virtual node: region rows only
    if nlp.s.robust:
        par["kappa_v"][k] = nlp.margins.pass_through[gi]
        bounds.lbg["virtual_node"][k] = 0.0
    dims = g.region.size1_out(0) if g.region is not None else 0
    if dims:
        bounds.lbg["region"][k, :dims] = 0.0
