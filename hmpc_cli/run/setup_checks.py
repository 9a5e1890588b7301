"""Set-up checks: what only the built system can tell about a scenario, before any NLP.

:func:`hmpc_cli.run.compose.build` runs them once the controllers' model is built (and before
its NLPs are); :func:`setup_problems` runs them alone (``hmpc sweep`` checks every cell
with it before a run starts). Every problem is a ``key.path: reason`` line.
"""

from __future__ import annotations

from hmpc_cli.core.messages import ConstraintMargins

__all__ = ["built_problems", "check_task", "initial_state_problems", "margins_of",
           "region_warnings", "setup_problems"]


def setup_problems(scenario) -> list[str]:
    """The set-up checks :func:`hmpc_cli.run.compose.build` makes on the built model, and no more.

    ``key.path: reason`` lines (none: the scenario sets up): margins that do not fit the
    system (a margins file, an input shrink beyond half an input box), solver options
    the solver rejects and planner settings that do not fit the system (a schedule), a
    task that is not one (:func:`check_task`) and a ``[plant]`` that does not fit the
    model (:func:`plant_problems`). Builds the controllers' model (and the plant) only
    (no NLP, no planner), so a sweep checks every cell before it starts a run.
    """
    from hmpc_cli.core.registry import PluginError, build_system, plugin_call, registry

    try:
        model = build_system(scenario.system)
        name = scenario.system.name
        check_task(plugin_call(f"system: the task of {name!r} failed to build",
                               registry().system(name).task, scenario.system, model),
                   name, model)
        margins = margins_of(scenario, model)
        system = build_system(scenario.plant_params()) if scenario.plant else None
    except (PluginError, ValueError) as exc:
        return str(exc).splitlines()
    problems = built_problems(scenario, model, margins)
    return problems + (plant_problems(model, system) if system is not None else [])


def plant_problems(model, system) -> list[str]:
    """The simulated system's (``[plant]``) problems: its guards, the model's x0 in it."""
    return (plant_guard_problems(model, system)
            + initial_state_problems(system, model.x0, "the plant's "))


def check_task(task, name: str, system):
    """``task`` (a system plug-in's), once checked on ``system``'s x0 in its initial mode.

    Its ``failure`` must give a str and its ``verdict`` a Verdict there, so a wrong task
    fails before the run, not in it (``failure`` may follow the run step by step: x0 is
    where the run starts).

    Raises:
        hmpc_cli.core.registry.PluginError: a method is missing, raises or returns
            another type (the message names the system).
    """
    from hmpc_cli.core.registry import PluginError, plugin_call
    from hmpc_cli.core.stack import Verdict

    where = f"system: the task of {name!r}"
    missing = [m for m in ("failure", "verdict") if not callable(getattr(task, m, None))]
    if missing or getattr(task, "goal", None) is None:
        what = ", ".join([*(f"a method {m}(x, mode)" for m in missing),
                          *([] if getattr(task, "goal", None) is not None else ["a goal"])])
        raise PluginError(f"{where} is a {type(task).__name__} without {what} "
                          "(a task has goal, failure(x, mode) -> str and verdict(x, mode) "
                          "-> Verdict: docs/plugins.md)")
    x0, mode = system.x0, system.mode_index(system.initial_mode)
    why = plugin_call(f"{where} failed at x0", task.failure, x0, mode)
    verdict = plugin_call(f"{where} failed at x0", task.verdict, x0, mode)
    for method, value, kind in (("failure", why, str), ("verdict", verdict, Verdict)):
        if not isinstance(value, kind):
            raise PluginError(f"{where}: {method}(x0, mode) returned a "
                              f"{type(value).__name__}, not a {kind.__name__}")
    return task


def built_problems(sc, model, margins: ConstraintMargins | None) -> list[str]:
    """The checks of a scenario against its built model: x0, margins, solver, planner."""
    key = "system.x0" if "x0" in type(sc.system).model_fields else \
        f"the x0 that {sc.system.name!r} builds (it has no x0 setting)"
    return (initial_state_problems(model, key=key) + _margin_problems(sc, model, margins)
            + _solver_problems(sc) + _planner_problems(sc, model))


def plant_guard_problems(model, system) -> list[str]:
    """``plant: reason`` when the simulated system's guards are not the model's one for one.

    The controllers take a contact's guard by its index in the model's list (schedules,
    the low level, replanning triggers, the log's names and counts), so a ``[plant]`` may
    move a guard (another stair height, circle, extent) but not add, drop, rename or
    reorder guards, nor change their modes.
    """
    def listed(s) -> list[tuple[str, str, str]]:
        return [(g.name, g.source, g.target) for g in s.guards]

    ours, theirs = listed(model), listed(system)
    if ours == theirs:
        return []
    if len(ours) != len(theirs):
        what = f"{len(theirs)} guards, the model {len(ours)}"
    else:
        k = next(i for i, (a, b) in enumerate(zip(ours, theirs, strict=True)) if a != b)
        what = (f"its guard {k} is {theirs[k][0]!r} ({theirs[k][1]} -> {theirs[k][2]}), the "
                f"model's {ours[k][0]!r} ({ours[k][1]} -> {ours[k][2]})")
    return [f"plant: the simulated system has {what}: the controllers name a contact by "
            f"its guard's place in the model's list, so [plant] may move guards but not "
            f"add, drop or reorder them (e.g. keep the number of stairs)"]


def initial_state_problems(system, x0=None, whose: str = "", key: str = "system.x0"
                           ) -> list[str]:
    """``system.x0: reason`` when x0 lies on or past a guard of its initial mode.

    ``key``: how the lines name x0 (a system without an x0 setting: where it comes from).

    x0 (default ``system.x0``) must lie in the domain of ``system.initial_mode``: every
    guard out of that mode whose activity region holds x0 has a gap > 0 there. A guard
    already crossed, or one x0 lies on, never fires (it fires when its gap goes from > 0
    to <= 0), so the run would start in a mode its state has left, or pass through it.
    ``whose`` names another system checked with the controllers' x0 (``"the plant's "``).
    Then: guards' gaps that are not finite at x0, an ``nlp_gap`` without its gap's sign
    there, a flow that is not finite there.
    """
    import numpy as np

    x0 = np.asarray(system.x0 if x0 is None else x0, dtype=float)
    mode, moved = system.initial_mode, "system.x0" if key == "system.x0" else "x0"
    out = []
    for i in system.guards_of(system.mode_index(mode)):
        g = system.guards[i]
        gap = _at(system, g.gap_expr, x0)
        inside = _inside(g, x0)
        point = ", ".join(f"{v:g}" for v in x0)
        if inside and gap < 0.0:
            out.append(f"{key}: ({point}) lies past {whose}guard {g.name!r} of its "
                       f"initial mode {mode!r} (gap {gap:.4g} < 0), so the run would start "
                       f"outside that mode's domain; move {moved} or the guard")
        elif inside and gap == 0.0:
            out.append(f"{key}: ({point}) lies on {whose}guard {g.name!r} of its initial "
                       f"mode {mode!r} (gap 0): a guard fires when its gap goes from > 0 to "
                       f"<= 0 within a step, so from there it would never fire; move "
                       f"{moved} off the guard")
    return (out + _finite_gap_problems(system, x0, whose, key)
            + _nlp_gap_problems(system, x0, whose) + _flow_problems(system, x0, whose, key))


def _finite_gap_problems(system, x0, whose: str = "", key: str = "system.x0") -> list[str]:
    """``system.x0: reason`` when a guard of the initial mode has a gap that is not finite at x0.

    Every guard of the mode, inside its region or not: the simulator evaluates each gap
    every step (a NaN or inf one never fires) and the NLP its ``nlp_gap`` at every node
    of the mode (NaN rows). The plant (``whose`` given) is checked for h only: the NLP
    reads the controllers' model.
    """
    import numpy as np

    mode, out = system.initial_mode, []
    moved = "system.x0" if key == "system.x0" else "x0"
    point = ", ".join(f"{v:g}" for v in x0)
    for i in system.guards_of(system.mode_index(mode)):
        g = system.guards[i]
        parts = [("h", g.h)] + ([("nlp_gap", g.nlp_gap)]
                                if g.nlp_gap is not None and not whose else [])
        values = [(name, _at(system, f, x0)) for name, f in parts]
        bad = [f"{name}(x0) = {v:g}" for name, v in values if not np.isfinite(v)]
        if bad:
            out.append(f"{key}: {whose}guard {g.name!r} of mode {mode!r} is not finite at x0 "
                       f"({point}): {', '.join(bad)}: a gap that is NaN or inf never fires "
                       f"in the simulator and makes the NLP's rows NaN; check the guard's "
                       f"expression where x0 lies (a square root of a negative number, a "
                       f"division by 0), or move {moved}")
    return out


def _nlp_gap_problems(system, x0, whose: str = "") -> list[str]:
    """``system: reason`` when a guard's ``nlp_gap`` has not the gap's sign at x0.

    For each guard of the initial mode that has an ``nlp_gap`` and is active at x0 with
    a gap > 0 there: the NLP reads q = nlp_gap in place of the gap, so a q <= 0 turns its
    guard-avoid rows around (a plan must then cross the guard at once). The plant
    (``whose`` given) is not checked: the NLP reads the controllers' model only.
    """
    if whose:
        return []
    mode, out = system.initial_mode, []
    for i in system.guards_of(system.mode_index(mode)):
        g = system.guards[i]
        if g.nlp_gap is None or not _inside(g, x0):
            continue
        gap, q = (_at(system, f, x0) for f in (g.gap_expr, g.q_expr))
        if gap > 0.0 and q <= 0.0:
            how = "has the opposite sign to" if q < 0.0 else "is not positive like"
            out.append(f"system: guard {g.name!r} of mode {mode!r}: nlp_gap(x0) = {q:.4g} "
                       f"{how} its gap at x0 ({gap:.4g} = -direction (h(x0) - level), h(x0) "
                       f"= {float(g.h(x0)):.4g}, level {g.level:g}, direction "
                       f"{g.direction:+d}): the NLP's gap must be positive where the "
                       "guard's gap is, before the crossing (docs/plugins.md)")
    return out


def _flow_problems(system, x0, whose: str = "", key: str = "system.x0") -> list[str]:
    """``system.x0: reason`` when the initial mode's flow is not finite at x0.

    Evaluated with no disturbance and the input nearest 0 within the mode's bounds: a flow
    that returns NaN or inf there (a square root of a negative number, a division by 0)
    would end the run at its first step as "diverged".
    """
    import numpy as np

    mode = system.modes[system.mode_index(system.initial_mode)]
    moved = "system.x0" if key == "system.x0" else "x0"
    u = np.clip(np.zeros(system.n_u), np.asarray(mode.u_lower, dtype=float),
                np.asarray(mode.u_upper, dtype=float))
    value = np.asarray(mode.flow(x0, u, np.zeros(system.n_w)), dtype=float).ravel()
    if np.all(np.isfinite(value)):
        return []
    bad = [n for n, v in zip(system.state_names, value, strict=False) if not np.isfinite(v)]
    point = ", ".join(f"{v:g}" for v in x0)
    return [f"{key}: the flow of {whose}mode {mode.name!r} is not finite at x0 ({point}) "
            f"with u = {', '.join(f'{v:g}' for v in u) or '()'} and w = 0 (d/dt of "
            f"{', '.join(bad)}): the run would diverge at its first step; check the flow's "
            f"expression where x0 lies, or move {moved}"]


def region_warnings(system, margins: ConstraintMargins | None = None) -> list[str]:
    """Warnings for guards of x0's mode whose avoid row fails at x0, outside their region.

    The fixed-mode MPC imposes a guard's guard-avoid rows (q >= kappa) at every node of
    the domains it leaves from, inside its activity region or not (the region is honoured
    by the simulator and at the switching node only). A guard of the initial mode (not
    the final one: its nodes there are the first solve's) whose region x0 lies outside
    and whose row fails at x0 (q(x0) < kappa, ``margins``' guard-avoid offset, 0 without
    margins) is a region that does not cover the workspace: solves are softened or
    infeasible. The run goes on (the soft rows may carry it).
    """
    out, mode = [], system.mode_index(system.initial_mode)
    if system.initial_mode == system.final_mode:
        return out
    for i in system.guards_of(mode):
        g = system.guards[i]
        if g.region is None or _inside(g, system.x0):
            continue
        q = _at(system, g.q_expr, system.x0)
        kappa = margins.avoid[i] if margins is not None else 0.0
        if q < kappa:
            out.append(
                f"system: guard {g.name!r} of mode {g.source!r}: x0 lies outside its region "
                f"and its guard-avoid row fails there (nlp_gap(x0) = {q:.4g}, kappa = "
                f"{kappa:.4g}): the fixed-mode MPC imposes that row at every node of mode "
                f"{g.source!r}, outside the region too, so solves are softened or "
                f"infeasible; fold the region into the guard's nlp_gap (docs/plugins.md)")
    return out


def _at(system, f, x0) -> float:
    """The scalar CasADi expression ``f(x)`` of ``system``'s state, at x0."""
    import casadi as ca

    x = ca.SX.sym("x", system.n_x)
    return float(ca.Function("v", [x], [f(x)])(x0))


def _inside(guard, x0) -> bool:
    """Whether x0 lies in ``guard``'s activity region (everywhere without one)."""
    import numpy as np

    return guard.region is None or bool(np.all(np.asarray(guard.region(x0)) >= 0.0))


def _planner_problems(sc, model) -> list[str]:
    """``planner.key: reason`` lines from planner settings that check a built system."""
    return list(sc.planner.system_problems(model))


def margins_of(sc, model) -> ConstraintMargins | None:
    """The MPC's margins: hand-set, from the scenario's margins file, or None (no field).

    Raises:
        ValueError: ``mpc.margins: ...`` when the file does not fit the scenario, or its
            margins (a margins file's or the tube's) make the tightened problem infeasible
            at x0.
    """
    from hmpc_cli.core.registry import registry

    source = sc.mpc.margins_source()
    hand = registry().mpc(sc.mpc.kind).hand_margins
    if source is None or (source == "hand" and hand is None):  # an MPC without margins
        return None
    if source == "hand":
        return hand(model, sc.mpc)
    if source == "tube":
        from hmpc_cli.run.tube_margins import tube_margins

        return tube_margins(sc, model)  # refused when computed if infeasible at x0
    from hmpc_cli.tube.margins_file import constraint_margins

    return _feasible_at_x0(constraint_margins(source, model, sc.system, sc.mpc.rate_hz),
                           model, sc.mpc.rate_hz)


def _feasible_at_x0(margins: ConstraintMargins, model, rate_hz: float) -> ConstraintMargins:
    """``margins``, once no guard-avoid row they tighten fails at x0 already.

    The check ``mpc.margins = "tube"`` makes when it computes its tube, made on a margins
    file: such a row fails at the NLP's first nodes, so every solve would be softened or
    fail.

    Raises:
        ValueError: ``mpc.margins: ...`` naming the first guard whose row fails at x0.
    """
    from hmpc_cli.tube.margins_file import REFUSED

    violated = model.initial_avoid_violations(margins.avoid)
    if not violated:
        return margins
    name, q, kappa = violated[0]
    raise ValueError(f"{REFUSED}{margins.source}: at {rate_hz:g} Hz the tightened guard-avoid "
                     f"row of {name} (kappa = {kappa:.4g}) exceeds its NLP gap at x0 "
                     f"({q:.4g}): the tightened problem is infeasible at the initial state")


def _margin_problems(sc, model, margins: ConstraintMargins | None) -> list[str]:
    """``mpc.<margin>: reason`` when an input shrink leaves a mode's input box empty.

    A box shrunk to a point counts too: the MPC keeps no input authority there.
    """
    if margins is None:
        return []
    key = sc.mpc.input_margin_key() if margins.source == "hand" else "mpc.margins"
    for mode, shrink in zip(model.modes, margins.inputs, strict=False):
        for i, (lo, hi, m) in enumerate(zip(mode.u_lower, mode.u_upper, shrink, strict=False)):
            if 2.0 * m >= hi - lo and m > 0.0:
                what = "exceeds" if 2.0 * m > hi - lo else "reaches"
                return [f"{key}: {m:g} per side {what} half the input box of mode "
                        f"{mode.name!r} input {i} ([{lo:g}, {hi:g}]: half-width "
                        f"{(hi - lo) / 2:g}; the MPC would keep no input authority)"]
    return []


def _solver_problems(sc) -> list[str]:
    """The MPC's solver options, tried on a tiny NLP per back-end it builds.

    See ``option_problems``.
    """
    from hmpc_cli.mpc.solver import option_problems

    lines = [line for choice in sc.mpc.solver_choices() for line in option_problems(*choice)]
    return list(dict.fromkeys(lines))
