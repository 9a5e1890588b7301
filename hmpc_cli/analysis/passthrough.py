"""The robust virtual pass-through node of a logged plan (the paper's Figure 2), computed.

Takes one logged ``/mpc/solve`` whose plan crosses a guard into another domain (its
``seg_plan`` has two segments or more) and rebuilds, from the controllers' model named
in the log (through the registry), what the NLP asserted there, in the plane of the
system's ``plane`` states:

* the guard the plan crosses first (its signed gap on a grid around the plan; the
  other states at the guard node's values) and the planned nodes of the domain before
  it, the last of them the *guard node* (on the guard);
* the *virtual pass-through node* x_v = Phi(x_G, u_v): one more interval of the source
  mode's flow from the guard node x_G, with the virtual input u_v = the guard node's
  logged ``u_plan`` row held over the interval (the NLP's reset link has no first-order
  hold), w = 0, the interval the plan's node step (the positive spacing of ``t_plan``),
  integrated with one classic RK4 step (one Euler step when the logged scenario's
  ``mpc.integrator`` is "euler"), as the NLP's ``virtual_node`` row does;
* the tube radius d: the one the NLP used (the scenario's ``mpc.tube_margin``, or the
  guard's radius in the run's margins file or own tube, ``mpc.margins``), a given radius,
  or diam T(dt) at the scenario's MPC rate from :func:`hmpc_cli.tube.analyse`;
* whether x_v's disc lies entirely past the guard: the largest signed gap over the disc
  (its point nearest the guard, found on a fine polar grid) must be <= 0; the NLP's own
  test is the ``virtual_node`` row q(x_v) <= -kappa(d, past=True) with the guard's smooth
  gap q and margin kappa;
* the reset: the post-reset node (the first node of the next segment) and R_G(x_G).

It composes the run log (:func:`hmpc_cli.log.rundata.read_run`), the registry and the tube,
so it lives above them; :mod:`hmpc_cli.figures.fig2` only draws its result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PassThroughError", "PassThroughGeometry", "pass_through_geometry"]

GRID = 401  # guard grid points per side of a view
NEXT_NODES = 6  # planned nodes of the next domain kept after the reset


class PassThroughError(ValueError):
    """A run log whose pass-through cannot be computed (the message says why)."""


@dataclass(frozen=True)
class PassThroughGeometry:
    """The pass-through of one logged plan (full states; ``plane`` picks the drawn ones).

    Attributes:
        log: the run log.
        solve: 1-based index of the drawn ``/mpc/solve`` message among all of them.
        t: its time [s].
        guard: index of the crossed guard; ``guard_name`` its name.
        source_mode, target_mode: mode names before and after the guard.
        plane: indices of the two drawn states; ``plane_names`` their names.
        dt: the plan's node step [s] (the virtual interval).
        radius: tube radius d [state norm]; ``radius_source`` where it comes from.
        nodes: planned nodes of the source domain (K, n), the guard node last.
        next_nodes: the next domain's first planned nodes (J, n), the post-reset node first.
        virtual_input: u_v (m,), the guard node's logged input.
        virtual_node: x_v = Phi(x_G, u_v) (n,).
        reset_of_guard_node: R_G(x_G) (n,), to compare with the post-reset node.
        guard_node_gap: signed gap of the guard node (~0: on the guard).
        virtual_gap: signed gap of x_v (<= 0: past the guard).
        virtual_q: the NLP gap q(x_v); ``kappa`` = kappa(d, past=True) of the guard.
        disc_gap: largest signed gap over x_v's disc; ``disc_point`` where (2,).
        slack: the solve's logged relaxation max sigma_k.
        state_names: the system's state names; ``reset_changes`` those the reset changes.
        views: ``whole`` (the domain's plan) and ``zoom`` (at the guard): ((x0, x1),
            (y0, y1)) in the plane [m].
        guard_grids: per view, the crossed guard's signed gap (gx, gy, gap), each
            (G, G), on a grid over the view, the other states at the guard node's (NaN
            outside the guard's activity region): its zero level set is the guard.
        log_note: the damage or cut of a log not read whole
            (:func:`hmpc_cli.log.rundata.damage_note`; '' if intact): ``solve`` counts
            the solves read.
    """

    log: Path
    solve: int
    t: float
    guard: int
    guard_name: str
    source_mode: str
    target_mode: str
    plane: tuple[int, int]
    plane_names: tuple[str, str]
    dt: float
    radius: float
    radius_source: str
    nodes: np.ndarray
    next_nodes: np.ndarray
    virtual_input: np.ndarray
    virtual_node: np.ndarray
    reset_of_guard_node: np.ndarray
    guard_node_gap: float
    virtual_gap: float
    virtual_q: float
    kappa: float
    disc_gap: float
    disc_point: np.ndarray
    slack: float
    state_names: tuple[str, ...] = ()
    reset_changes: tuple[str, ...] = ()
    views: dict = field(default_factory=dict)
    guard_grids: dict = field(default_factory=dict)
    log_note: str = ""

    @property
    def guard_node(self) -> np.ndarray:
        """The guard node x_G (n,): the last planned node before the reset."""
        return self.nodes[-1]

    @property
    def post_reset(self) -> np.ndarray:
        """The post-reset node (n,): the first node of the next segment."""
        return self.next_nodes[0]

    @property
    def disc_past(self) -> bool:
        """Whether x_v's whole tube disc lies past the guard (largest gap <= 0)."""
        return self.disc_gap <= 0.0

    @property
    def nlp_row(self) -> float:
        """-q(x_v) - kappa(d, past=True): >= 0 when the NLP's virtual-node row holds."""
        return -self.virtual_q - self.kappa


def _array(value, where: str, ndim: int) -> np.ndarray:
    """A logged vector/matrix as a finite float array of ``ndim`` dimensions."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.ndim != ndim or not arr.size or not np.isfinite(arr).all():
        raise PassThroughError(f"{where} is missing or malformed")
    return arr


def _crosses(solve) -> bool:
    """Whether a logged solve's plan has two segments or more."""
    return solve.plan.seg.size > 0 and int(solve.plan.seg.max()) >= 1


def _pick(run, solve: int | None, path: Path):
    """(1-based index, message) of the chosen solve of ``run`` (a run log's arrays)."""
    solves = run.solves
    if not solves:
        raise PassThroughError(run.lacks("the log has no /mpc/solve message"))
    if solve is not None:
        if not 1 <= solve <= len(solves):
            raise PassThroughError(f"--solve {solve} is out of range: the log has "
                                   f"{len(solves)} solves (1..{len(solves)})")
        if not _crosses(solves[solve - 1]):
            raise PassThroughError(f"{path}: solve {solve} plans no guard crossing (one "
                                   f"segment)")
        return solve, solves[solve - 1]
    for i, m in enumerate(solves):
        if _crosses(m):
            return i + 1, m
    raise PassThroughError(f"{path}: no logged solve plans a guard crossing "
                           f"({len(solves)} solves)")


def _interval(mode, x: np.ndarray, u: np.ndarray, n_w: int, h: float,
              euler: bool) -> np.ndarray:
    """One interval of length h of ``mode``'s flow from x with u held and w = 0."""
    w = np.zeros(n_w)

    def f(z):
        return np.asarray(mode.flow(z, u, w), dtype=float).ravel()

    if euler:
        return x + h * f(x)
    k1 = f(x)
    k2 = f(x + h / 2 * k1)
    k3 = f(x + h / 2 * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def _node_step(t: np.ndarray, where: str) -> float:
    """The plan's node step: the common positive spacing of its node times."""
    steps = np.diff(t)
    steps = steps[steps > 1e-12]
    if not len(steps) or np.ptp(steps) > 1e-6 * steps.max():
        raise PassThroughError(f"{where}: t_plan has no single node step")
    return float(np.median(steps))


def _tube_radius(system, scenario: dict, where: str, guard: int) -> tuple[float, str]:
    """The guard's tube radius at the scenario's MPC rate (hmpc tube's defaults).

    The radius the guard's margins are computed from: the kinematic tube for a guard
    whose gap sees kinematic states only, else diam T(dt) (:func:`hmpc_cli.tube.bounds.margins`).
    """
    from hmpc_cli.tube import TubeError, analyse, region_from_scenario

    mpc, dist = scenario.get("mpc") or {}, scenario.get("disturbance") or {}
    low = scenario.get("lowlevel") or {}
    try:
        rate = float(mpc["rate_hz"])
        report = analyse(system, region=region_from_scenario(system), kind=dist["kind"],
                         magnitude=float(dist["magnitude"]), kp=float(low["kp"]),
                         kd=float(low["kd"]), rate_hz=rate, seed=int(scenario.get("seed", 0)))
    except KeyError as exc:
        raise PassThroughError(f"{where}: the logged scenario has no {exc.args[0]} "
                               f"setting (needed by --from-tube)") from None
    except TubeError as exc:
        raise PassThroughError(f"{where}: tube: {exc.quantity}: {exc.reason}") from None
    except (TypeError, ValueError) as exc:
        raise PassThroughError(f"{where}: --from-tube: {exc}") from None
    row = report.row(rate)
    d = row.margins.guards[guard].radius
    kinematic = row.kinematic is not None and bool(report.kinematic_guards) \
        and report.kinematic_guards[guard]
    what = "the kinematic tube" if kinematic else f"diam T(dt) ({row.bound} bound)"
    if not math.isfinite(d):
        raise PassThroughError(f"{where}: {what} at {rate:g} Hz is not finite")
    return float(d), f"{what} at {rate:g} Hz, the radius of guard " \
                     f"{system.guards[guard].name!r}'s margins"


def _used_radius(system, scenario: dict, used, where: str, guard: int) -> tuple[float, str]:
    """The radius d_g behind the pass-through offset the run's NLP used for the guard.

    ``used`` is the logged margins (:class:`~hmpc_cli.log.topics.MarginsRec`) of a margins
    file or of the run's own tube (``mpc.margins = "tube"``): that file, or the tube
    (cached, or computed as the run did), is read again and must still hold the logged
    offset.
    """
    from pydantic import ValidationError

    from hmpc_cli.run.scenario import scenario_model
    from hmpc_cli.run.tube_margins import tube_margins_file
    from hmpc_cli.tube.margins_file import read_margins

    name = system.guards[guard].name
    logged = next((g.pass_through for g in used.guards if g.guard == name), math.nan)
    tube = used.source.startswith("tube at ")
    what = f"the run's {used.source}" if tube else used.source
    retry = "pass --radius or --from-tube"
    try:
        mf = (tube_margins_file(scenario_model().model_validate(scenario), system) if tube
              else read_margins(Path(used.source)))
        row = mf.at(float((scenario.get("mpc") or {})["rate_hz"]))
    except (KeyError, TypeError, ValueError, ValidationError) as exc:
        raise PassThroughError(f"{where}: the run's margins ({used.source}) cannot be read "
                               f"again ({exc}); {retry}") from None
    offsets = row.guards.get(name) if row is not None else None
    if offsets is None or offsets.pass_through != logged:
        raise PassThroughError(f"{where}: {what} no longer holds the pass-through offset "
                               f"the run used for guard {name!r} ({logged:g}); {retry}")
    d = offsets.radius if offsets.radius is not None else row.radius
    return float(d), f"the radius of guard {name!r}'s margins in {what}"


def _radius(system, scenario: dict, radius: float | None, from_tube: bool,
            where: str, guard: int, info=None) -> tuple[float, str]:
    """The tube radius d and where it comes from (``info``: the run's /run/info)."""
    used = getattr(info, "margins", None)
    if radius is not None and from_tube:
        raise PassThroughError("give either --radius or --from-tube, not both")
    if radius is not None:
        if not (math.isfinite(radius) and radius >= 0.0):
            raise PassThroughError(f"--radius must be a finite number >= 0, got {radius}")
        return float(radius), "given radius"
    if from_tube:
        return _tube_radius(system, scenario, where, guard)
    if used is not None and used.source != "hand":
        return _used_radius(system, scenario, used, where, guard)
    d = (scenario.get("mpc") or {}).get("tube_margin")
    if not isinstance(d, (int, float)) or not math.isfinite(d) or d < 0:
        raise PassThroughError(f"{where}: the logged scenario has no mpc.tube_margin "
                               f"(pass --radius)")
    return float(d), "mpc.tube_margin"


def _disc_max_gap(numeric, gi: int, centre: np.ndarray, plane, d: float):
    """Largest signed gap over the disc of radius d around ``centre`` in the plane."""
    ang = np.linspace(0.0, 2 * np.pi, 2880, endpoint=False)
    rings = np.linspace(0.0, 1.0, 9)
    pts = np.tile(centre, (ang.size * rings.size, 1))
    rr, aa = np.meshgrid(rings, ang, indexing="ij")
    i, j = plane
    pts[:, i] += d * (rr * np.cos(aa)).ravel()
    pts[:, j] += d * (rr * np.sin(aa)).ravel()
    gaps = numeric.gap(gi, pts)
    k = int(np.argmax(gaps))
    return float(gaps[k]), pts[k, [i, j]].copy()


def _logged_system(system: dict, where: str, note: str = "") -> Any:
    """Builds the registered system a logged ``[system]`` section names.

    Raises:
        PassThroughError: no system section, an unknown or broken plug-in, or
            parameters its plug-in rejects.
    """
    from pydantic import ValidationError

    from hmpc_cli.core.registry import PluginError, build_system, registry

    if not system or not isinstance(system.get("name"), str):
        raise PassThroughError(f"{where}: the log names no system{note}")
    try:
        params = registry().system(system["name"]).params.model_validate(system)
        return build_system(params)
    except PluginError as exc:
        raise PassThroughError(f"{where}: {exc}") from None
    except ValidationError as exc:
        raise PassThroughError(f"{where}: bad {system['name']} parameters in the log "
                               f"({exc.error_count()} errors)") from None


def _open(log_path: str | Path):
    """(path, run, system, plane indices, logged scenario) of a run with a 2-D plane.

    Raises:
        PassThroughError: no such log, unreadable, plans thinned by ``sim.log_plan_stride``,
            or a system without a 2-D plane.
    """
    from hmpc_cli.log.rundata import damage_note, read_run, resolve_log

    try:
        path = resolve_log(Path(log_path))
        run = read_run(path)
        run.full_plans("the pass-through (its node step and guard-side node)")
    except ValueError as exc:
        raise PassThroughError(str(exc)) from None
    system = _logged_system(run.system, str(path), damage_note(run.damage, run.complete))
    if system.plane is None or len(system.plane) != 2:
        raise PassThroughError(f"{path}: system {system.name!r} has no 2-D drawing plane")
    plane = tuple(system.state_names.index(s) for s in system.plane)
    return path, run, system, plane, run.scenario


def pass_through_geometry(log_path: str | Path, *, solve: int | None = None,
                          radius: float | None = None,
                          from_tube: bool = False) -> PassThroughGeometry:
    """The pass-through of a logged plan, from its run log (see the module docstring).

    Args:
        log_path: run log (run.mcap, or the run directory holding it).
        solve: 1-based index of the ``/mpc/solve`` to draw (default: the first whose plan
            crosses a guard).
        radius: tube radius d (default: the one the NLP used: the logged
            ``mpc.tube_margin``, or the guard's radius in the run's margins file or tube).
        from_tube: d = the guard's tube radius at the scenario's MPC rate from
            :mod:`hmpc_cli.tube` (the kinematic tube for a guard of kinematic states).

    Raises:
        PassThroughError: no such log, no solve crossing a guard, ``solve`` out of range,
            a system without a 2-D plane, a malformed plan.
    """
    import casadi as ca

    path, run, system, plane, scenario = _open(log_path)
    index, msg = _pick(run, solve, path)
    where = f"{path}: solve {index}"
    t = _array(msg.plan.t, f"{where}: plan t", 1)
    x = _array(msg.plan.x, f"{where}: plan x", 2)
    u = _array(msg.plan.u, f"{where}: plan u", 2)
    seg = msg.plan.seg
    guards = list(msg.schedule.guards) if msg.schedule is not None else []
    if not (len(t) == len(x) == len(u) == len(seg)) or x.shape[1] != system.n_x \
            or u.shape[1] != system.n_u:
        raise PassThroughError(f"{where}: the plan's arrays do not fit the system")
    if not guards or not 0 <= guards[0] < len(system.guards):
        raise PassThroughError(f"{where}: the schedule names no known guard")
    gi, g = int(guards[0]), system.guards[int(guards[0])]
    src, nxt = np.flatnonzero(seg == 0), np.flatnonzero(seg == 1)
    if not len(src) or not len(nxt) or nxt[0] != src[-1] + 1:
        raise PassThroughError(f"{where}: the plan's segments are not consecutive")
    k = int(src[-1])
    dt = _node_step(t, where)
    euler = (scenario.get("mpc") or {}).get("integrator") == "euler"
    d, d_source = _radius(system, scenario, radius, from_tube, str(path), gi, run.info)
    xv = _interval(system.modes[system.mode_index(g.source)], x[k], u[k], system.n_w, dt,
                   euler)
    xs = ca.SX.sym("x", system.n_x)
    q = ca.Function("q", [xs], [g.q_expr(xs)])
    num = system.numeric
    disc_gap, disc_point = _disc_max_gap(num, gi, xv, plane, d)
    geo = PassThroughGeometry(
        log=path, solve=index, t=float(msg.t), guard=gi, guard_name=g.name,
        source_mode=g.source, target_mode=g.target, plane=plane,
        plane_names=tuple(system.plane), dt=dt, radius=d, radius_source=d_source,
        nodes=x[src].copy(), next_nodes=x[nxt[:NEXT_NODES]].copy(),
        virtual_input=u[k].copy(), virtual_node=xv,
        reset_of_guard_node=num.reset(gi, x[k][None])[0],
        guard_node_gap=float(num.gap(gi, x[k][None])[0]),
        virtual_gap=float(num.gap(gi, xv[None])[0]), virtual_q=float(q(xv)),
        kappa=float(g.kappa(d, past=True)), disc_gap=disc_gap, disc_point=disc_point,
        slack=float(msg.slack), state_names=tuple(system.state_names),
        log_note=run.damage_text)
    return _with_grids(system, geo)


def _box(points: np.ndarray, pad: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """A square-ish view around 2-D points, padded by ``pad`` on each side."""
    lo, hi = points.min(axis=0) - pad, points.max(axis=0) + pad
    mid, half = (lo + hi) / 2, max(hi - lo) / 2
    return (mid[0] - half, mid[0] + half), (mid[1] - half, mid[1] + half)


def _views(geo: PassThroughGeometry) -> dict:
    """The ``whole`` and ``zoom`` views of a pass-through (see PassThroughGeometry)."""
    i, j = geo.plane
    d = geo.radius
    near = np.vstack([p[[i, j]] for p in (geo.guard_node, geo.virtual_node, geo.post_reset)])
    span = float(np.ptp(near, axis=0).max())
    every = np.vstack([geo.nodes[:, [i, j]], near, geo.next_nodes[:, [i, j]]])
    return {"whole": _box(every, max(1.5 * d, 0.08 * float(np.ptp(every, axis=0).max()),
                                     1e-3)),
            "zoom": _box(near, max(2.5 * d, 0.3 * span, 1e-3))}


def _guard_grid(system, geo: PassThroughGeometry, view, n: int = GRID):
    """The crossed guard's signed gap on an n x n grid over ``view`` (NaN outside)."""
    (x0, x1), (y0, y1) = view
    gx, gy = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    states = np.tile(geo.guard_node, (gx.size, 1))
    i, j = geo.plane
    states[:, i], states[:, j] = gx.ravel(), gy.ravel()
    gap = system.numeric.gap(geo.guard, states)
    gap = np.where(system.numeric.active(geo.guard, states), gap, np.nan)
    return gx, gy, gap.reshape(gx.shape)


def _with_grids(system, geo: PassThroughGeometry) -> PassThroughGeometry:
    """``geo`` with its views, guard grids and the states its reset changes."""
    views = _views(geo)
    gn, post = geo.guard_node, geo.post_reset
    changed = tuple(system.state_names[s] for s in range(system.n_x)
                    if abs(post[s] - gn[s]) > 1e-9 * (1.0 + abs(gn[s])))
    return replace(geo, views=views, reset_changes=changed,
                   guard_grids={k: _guard_grid(system, geo, v) for k, v in views.items()})


