"""The shapes of a hybrid system's parts, checked when it is built.

A plug-in whose flow, guard, reset, cost or gain has the wrong size fails here with the
part named (``mode 'air': flow must map ...``), not later inside CasADi or a run.
:class:`hmpc_cli.core.hybrid.HybridSystem` calls :func:`shape_problems` on construction.
"""

from __future__ import annotations

import numpy as np

__all__ = ["shape_problems"]


def _sig(fn) -> str:
    """``f(x[4], u[2]) -> [4x1]``: a CasADi function's input and output shapes."""
    ins = ", ".join(f"{fn.name_in(i)}[{fn.size1_in(i)}x{fn.size2_in(i)}]"
                    for i in range(fn.n_in()))
    outs = ", ".join(f"[{fn.size1_out(i)}x{fn.size2_out(i)}]" for i in range(fn.n_out()))
    return f"({ins}) -> {outs}"


def _maps(fn, ins: tuple[int, ...], out: int | None) -> bool:
    """Whether ``fn`` maps column vectors of sizes ``ins`` to a column of size ``out``.

    ``out`` None: a column of any size (the first output).
    """
    if fn.n_in() != len(ins) or fn.n_out() < 1:
        return False
    if any((fn.size1_in(i), fn.size2_in(i)) != (n, 1) for i, n in enumerate(ins) if n):
        return False
    if any(fn.nnz_in(i) for i, n in enumerate(ins) if not n):  # an empty vector
        return False
    return fn.size2_out(0) == 1 and (out is None or fn.size1_out(0) == out)


def shape_problems(system) -> list[str]:
    """Lines naming each part of ``system`` (a HybridSystem) whose shape does not fit.

    n states, m inputs, n_w disturbance channels: ``x0`` and ``goal`` are vectors of the
    sizes they need; a mode's flow maps (x[n], u[m], w[n_w]) -> [n] and its input bounds
    have m entries each, lower <= upper; a guard's ``h`` and ``nlp_gap`` map x[n] to a
    scalar, its reset x[n] -> [n], its region x[n] -> a column; ``goal_map`` maps x[n] to
    ``goal``'s size; ``stage_cost`` (x[n], u[m]) -> a scalar; ``terminal_set`` x[n] -> a
    column; ``tracking_gain(1, 1)`` is m x n; a ``state_box`` side has n entries.
    """
    n = len(system.state_names)
    out = []
    x0 = np.asarray(system.x0, dtype=float)
    if x0.shape != (n,):
        out.append(f"x0 has shape {x0.shape}, expected ({n},) (one entry per state "
                   f"{list(system.state_names)})")
    return out + _mode_problems(system) + _guard_problems(system) + _task_problems(system)


def _mode_problems(system) -> list[str]:
    """Each mode's flow and input bounds."""
    n, m, nw = len(system.state_names), len(system.input_names), len(system.disturbance_names)
    out = []
    for mode in system.modes:
        if not _maps(mode.flow, (n, m, nw), n):
            out.append(f"mode {mode.name!r}: flow must map (x[{n}], u[{m}], w[{nw}]) -> "
                       f"dx/dt[{n}], not {_sig(mode.flow)}")
        lo, hi = np.asarray(mode.u_lower, dtype=float), np.asarray(mode.u_upper, dtype=float)
        if lo.shape != (m,) or hi.shape != (m,):
            out.append(f"mode {mode.name!r}: u_lower and u_upper need {m} entries each (one "
                       f"per input {list(system.input_names)}), not {lo.size} and {hi.size}")
        elif np.any(lo > hi):
            out.append(f"mode {mode.name!r}: u_lower {lo.tolist()} exceeds u_upper "
                       f"{hi.tolist()}")
    return out


def _guard_problems(system) -> list[str]:
    """Each guard's h, reset, nlp_gap and region."""
    n = len(system.state_names)
    out = []
    for g in system.guards:
        for what, fn, size in (("h", g.h, 1), ("reset", g.reset, n),
                               ("nlp_gap", g.nlp_gap, 1), ("region", g.region, None)):
            if fn is not None and not _maps(fn, (n,), size):
                want = "a column" if size is None else f"[{size}]"
                out.append(f"guard {g.name!r}: {what} must map x[{n}] -> {want}, not "
                           f"{_sig(fn)}")
    return out


def _task_problems(system) -> list[str]:
    """The goal, costs, terminal set, tracking gain and state box."""
    n, m = len(system.state_names), len(system.input_names)
    out = []
    goal = np.asarray(system.goal, dtype=float).ravel()
    if not _maps(system.goal_map, (n,), goal.size):
        out.append(f"goal_map must map x[{n}] -> [{goal.size}] (the size of goal), not "
                   f"{_sig(system.goal_map)}")
    if not _maps(system.stage_cost, (n, m), 1):
        out.append(f"stage_cost must map (x[{n}], u[{m}]) -> a scalar, not "
                   f"{_sig(system.stage_cost)}")
    if system.terminal_set is not None and not _maps(system.terminal_set, (n,), None):
        out.append(f"terminal_set must map x[{n}] -> a column, not {_sig(system.terminal_set)}")
    gain = np.asarray(system.tracking_gain(1.0, 1.0), dtype=float)
    if gain.shape != (m, n):
        out.append(f"tracking_gain(kp, kd) must be {m} x {n} (inputs x states), not "
                   f"{' x '.join(str(k) for k in gain.shape) or 'a scalar'}")
    if system.state_box is not None:
        sizes = [np.asarray(side, dtype=float).shape for side in system.state_box]
        if sizes != [(n,), (n,)]:
            out.append(f"state_box needs ({n},) lower and upper bounds, not {sizes}")
    return out
