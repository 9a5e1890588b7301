"""Figure 2 of the paper from a recorded run: the virtual pass-through node and its tube.

Takes one logged ``/mpc/solve`` whose plan crosses a guard into another domain (the
plan's ``seg_plan`` has two segments or more) and draws, in the plane of the system's
``plane`` states (any registered system with one; rebuilt through the registry from the
logged parameters):

* the guard the plan crosses first (the zero level set of its gap inside its activity
  region; the other states at the guard node's values);
* the planned nodes of the domain before the guard, the last of them the *guard node*
  (on the guard);
* the *virtual pass-through node* x_v = Phi(x_G, u_v): one more interval of the source
  mode's flow from the guard node x_G, with the virtual input u_v = the guard node's
  logged ``u_plan`` row held over the interval (the NLP's reset link has no first-order
  hold), w = 0, the interval the plan's node step (the positive spacing of ``t_plan``),
  integrated with one classic RK4 step (one Euler step when the logged scenario's
  ``mpc.integrator`` is "euler"), as the NLP's ``virtual_node`` row does;
* a tube disc of radius d around every planned node of that domain and around x_v: the
  projection onto the plane of the state-norm ball of radius d. d is the scenario's
  ``mpc.tube_margin`` (what the NLP used), a given radius, or diam T(dt) at the scenario's
  MPC rate from :func:`hmpc_cli.tube.analyse`;
* the reset: the post-reset node (the first node of the next segment), a dashed arrow
  from the guard node to it, and the next domain's first planned nodes.

The figure states whether x_v's disc lies entirely past the guard: the largest signed gap
over the disc (its point nearest the guard, found on a fine polar grid) must be <= 0. The
NLP's own test is the ``virtual_node`` row q(x_v) <= -kappa(d, past=True) with the guard's
smooth gap q and margin kappa; both are returned in :class:`Fig2Geometry`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hmpc_cli.figures.common import (
    TEXT_WIDTH_IN,
    FigureInputError,
    check_size,
    figure_style,
    make_out_dir,
    parse_formats,
    resolve_run_log,
    save_figure,
)

__all__ = ["Fig2Geometry", "fig2", "fig2_geometry"]

NODE_COLOR = "#4a6fa5"  # planned nodes: muted blue
GUARD_NODE_COLOR = "#d62728"  # red
VIRTUAL_COLOR = "#ff7f0e"  # the paper's orange
RESET_COLOR = "#2e8b57"  # green
NEXT_NODES = 6  # planned nodes of the next domain drawn after the reset
SOFT_TOL = 1e-6  # slack or guard-node gap above this: a softened solve, said in the title


@dataclass(frozen=True)
class Fig2Geometry:
    """What Figure 2 draws (full states; ``plane`` picks the drawn coordinates).

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
        raise FigureInputError(f"{where} is missing or malformed")
    return arr


def _crosses(solve) -> bool:
    """Whether a logged solve's plan has two segments or more."""
    return solve.seg_plan.size > 0 and int(solve.seg_plan.max()) >= 1


def _pick(solves: list, solve: int | None, path: Path):
    """(1-based index, message) of the chosen solve."""
    if not solves:
        raise FigureInputError(f"{path}: the log has no /mpc/solve message")
    if solve is not None:
        if not 1 <= solve <= len(solves):
            raise FigureInputError(f"--solve {solve} is out of range: the log has "
                                   f"{len(solves)} solves (1..{len(solves)})")
        if not _crosses(solves[solve - 1]):
            raise FigureInputError(f"{path}: solve {solve} plans no guard crossing (one "
                                   f"segment)")
        return solve, solves[solve - 1]
    for i, m in enumerate(solves):
        if _crosses(m):
            return i + 1, m
    raise FigureInputError(f"{path}: no logged solve plans a guard crossing "
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
        raise FigureInputError(f"{where}: t_plan has no single node step")
    return float(np.median(steps))


def _tube_radius(system, scenario: dict, where: str) -> tuple[float, str]:
    """The tube radius diam T(dt) at the scenario's MPC rate (hmpc tube's defaults)."""
    from hmpc_cli.tube import TubeError, analyse, region_from_scenario

    mpc, dist = scenario.get("mpc") or {}, scenario.get("disturbance") or {}
    low = scenario.get("lowlevel") or {}
    try:
        rate = float(mpc["rate_hz"])
        report = analyse(system, region=region_from_scenario(system), kind=dist["kind"],
                         magnitude=float(dist["magnitude"]), kp=float(low["kp"]),
                         kd=float(low["kd"]), rate_hz=rate, seed=int(scenario.get("seed", 0)))
    except KeyError as exc:
        raise FigureInputError(f"{where}: the logged scenario has no {exc.args[0]} "
                               f"setting (needed by --from-tube)") from None
    except TubeError as exc:
        raise FigureInputError(f"{where}: tube: {exc.quantity}: {exc.reason}") from None
    except (TypeError, ValueError) as exc:
        raise FigureInputError(f"{where}: --from-tube: {exc}") from None
    d = report.row(rate).diam
    if not math.isfinite(d):
        raise FigureInputError(f"{where}: diam T(dt) at {rate:g} Hz is not finite")
    return float(d), f"diam T(dt) at {rate:g} Hz ({report.row(rate).bound} bound)"


def _radius(system, scenario: dict, radius: float | None, from_tube: bool,
            where: str) -> tuple[float, str]:
    """The tube radius d and where it comes from."""
    if radius is not None and from_tube:
        raise FigureInputError("give either --radius or --from-tube, not both")
    if radius is not None:
        if not (math.isfinite(radius) and radius >= 0.0):
            raise FigureInputError(f"--radius must be a finite number >= 0, got {radius}")
        return float(radius), "given radius"
    if from_tube:
        return _tube_radius(system, scenario, where)
    d = (scenario.get("mpc") or {}).get("tube_margin")
    if not isinstance(d, (int, float)) or not math.isfinite(d) or d < 0:
        raise FigureInputError(f"{where}: the logged scenario has no mpc.tube_margin "
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


def fig2_geometry(log_path: str | Path, *, solve: int | None = None,
                  radius: float | None = None, from_tube: bool = False) -> Fig2Geometry:
    """Computes what Figure 2 draws from a run log (see :func:`_geometry`)."""
    return _geometry(log_path, solve, radius, from_tube)[0]


def _open(log_path: str | Path):
    """(path, log, system, plane indices, logged scenario) of a run with a 2-D plane.

    Raises:
        FigureInputError: no such log, unreadable, or a system without a 2-D plane.
    """
    from hmpc_cli.figures.model import read_logged_system

    path = resolve_run_log(log_path)
    run, system = read_logged_system(path, "run log")
    if system.plane is None or len(system.plane) != 2:
        raise FigureInputError(f"{path}: system {system.name!r} has no 2-D drawing plane")
    plane = tuple(system.state_names.index(s) for s in system.plane)
    return path, run, system, plane, run.scenario


def _geometry(log_path: str | Path, solve: int | None, radius: float | None,
              from_tube: bool):
    """(geometry, system): what Figure 2 draws from a run log (see the module docstring).

    Args:
        log_path: run log (run.mcap, or the run directory holding it).
        solve: 1-based index of the ``/mpc/solve`` to draw (default: the first whose plan
            crosses a guard).
        radius: tube radius d (default: the logged ``mpc.tube_margin``).
        from_tube: d = diam T(dt) at the scenario's MPC rate from :mod:`hmpc_cli.tube`.

    Raises:
        FigureInputError: no such log, no solve crossing a guard, ``solve`` out of range,
            a system without a 2-D plane, a malformed plan.
    """
    import casadi as ca

    path, run, system, plane, scenario = _open(log_path)
    index, msg = _pick(run.solves, solve, path)
    where = f"{path}: solve {index}"
    t = _array(msg.t_plan, f"{where}: t_plan", 1)
    x = _array(msg.x_plan, f"{where}: x_plan", 2)
    u = _array(msg.u_plan, f"{where}: u_plan", 2)
    seg = msg.seg_plan
    guards = list((msg.schedule or {}).get("guards") or [])
    if not (len(t) == len(x) == len(u) == len(seg)) or x.shape[1] != system.n_x \
            or u.shape[1] != system.n_u:
        raise FigureInputError(f"{where}: the plan's arrays do not fit the system")
    if not guards or not 0 <= guards[0] < len(system.guards):
        raise FigureInputError(f"{where}: the schedule names no known guard")
    gi, g = int(guards[0]), system.guards[int(guards[0])]
    src = np.flatnonzero(seg == 0)
    nxt = np.flatnonzero(seg == 1)
    if not len(src) or not len(nxt) or nxt[0] != src[-1] + 1:
        raise FigureInputError(f"{where}: the plan's segments are not consecutive")
    k = int(src[-1])
    dt = _node_step(t, where)
    euler = (scenario.get("mpc") or {}).get("integrator") == "euler"
    d, d_source = _radius(system, scenario, radius, from_tube, str(path))
    xv = _interval(system.modes[system.mode_index(g.source)], x[k], u[k], system.n_w, dt,
                   euler)
    xs = ca.SX.sym("x", system.n_x)
    q = ca.Function("q", [xs], [g.q_expr(xs)])
    num = system.numeric
    disc_gap, disc_point = _disc_max_gap(num, gi, xv, plane, d)
    slack = msg.slack
    geo = Fig2Geometry(
        log=path, solve=index, t=float(msg.t), guard=gi, guard_name=g.name,
        source_mode=g.source, target_mode=g.target, plane=plane,
        plane_names=tuple(system.plane), dt=dt, radius=d, radius_source=d_source,
        nodes=x[src].copy(), next_nodes=x[nxt[:NEXT_NODES]].copy(),
        virtual_input=u[k].copy(), virtual_node=xv,
        reset_of_guard_node=num.reset(gi, x[k][None])[0],
        guard_node_gap=float(num.gap(gi, x[k][None])[0]),
        virtual_gap=float(num.gap(gi, xv[None])[0]), virtual_q=float(q(xv)),
        kappa=float(g.kappa(d, past=True)), disc_gap=disc_gap, disc_point=disc_point,
        slack=float(slack))
    return geo, system


def _guard_field(system, geo: Fig2Geometry, view, n: int = 401):
    """The crossed guard's signed gap on a grid over ``view`` (NaN outside its region)."""
    (x0, x1), (y0, y1) = view
    gx, gy = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n))
    states = np.tile(geo.guard_node, (gx.size, 1))
    i, j = geo.plane
    states[:, i], states[:, j] = gx.ravel(), gy.ravel()
    gap = system.numeric.gap(geo.guard, states)
    gap = np.where(system.numeric.active(geo.guard, states), gap, np.nan)
    return gx, gy, gap.reshape(gx.shape)


def _box(points: np.ndarray, pad: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """A square-ish view around 2-D points, padded by ``pad`` on each side."""
    lo, hi = points.min(axis=0) - pad, points.max(axis=0) + pad
    mid, half = (lo + hi) / 2, max(hi - lo) / 2
    return (mid[0] - half, mid[0] + half), (mid[1] - half, mid[1] + half)


def _draw(ax, system, geo: Fig2Geometry, view, title: str) -> None:
    """One panel: guard, tube discs, nodes, virtual node, reset."""
    from matplotlib.patches import Circle

    i, j = geo.plane
    gx, gy, gap = _guard_field(system, geo, view)
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
    changed = [system.state_names[s] for s in range(system.n_x)
               if abs(post[s] - gn[s]) > 1e-9 * (1.0 + abs(gn[s]))]
    ax.plot([post[i]], [post[j]], "o", mfc="none", mec=RESET_COLOR, mew=0.9, ms=6.5,
            zorder=5, label=f"post-reset node (reset changes {', '.join(changed) or 'nothing'})")
    if math.hypot(post[i] - gn[i], post[j] - gn[j]) > 1e-9:
        ax.annotate("", xy=(post[i], post[j]), xytext=(gn[i], gn[j]), zorder=5,
                    arrowprops={"arrowstyle": "->", "linestyle": "--", "color": RESET_COLOR,
                                "lw": 0.8})
    ax.set_xlim(*view[0])
    ax.set_ylim(*view[1])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"{geo.plane_names[0]}")
    ax.set_title(title)


def _title(geo: Fig2Geometry) -> str:
    """The figure's title: the verdict on the virtual node's disc, never hidden."""
    verdict = ("its tube disc lies entirely past the guard" if geo.disc_past else
               "its tube disc is NOT entirely past the guard")
    text = (f"solve {geo.solve} (t = {geo.t:.3f} s) crosses {geo.guard_name}: virtual node "
            f"gap {geo.virtual_gap:.4g}, disc's nearest point {geo.disc_gap:.4g}: {verdict}")
    if geo.slack > SOFT_TOL or abs(geo.guard_node_gap) > SOFT_TOL:
        text += (f"\nsoftened solve (slack {geo.slack:.2g}): the guard node's gap is "
                 f"{geo.guard_node_gap:.2g}")
    return text


def _figure(system, geo: Fig2Geometry, width: float, height: float):
    """The two-panel Figure (no pyplot state): the domain's plan, and a zoom on the guard."""
    from matplotlib.figure import Figure

    i, j = geo.plane
    pl = lambda a: np.asarray(a)[..., [i, j]]  # noqa: E731
    d = geo.radius
    near = np.vstack([pl(geo.guard_node), pl(geo.virtual_node), pl(geo.post_reset)])
    span = float(np.ptp(near, axis=0).max())
    zoom = _box(near, max(2.5 * d, 0.3 * span, 1e-3))
    every = np.vstack([pl(geo.nodes), near, pl(geo.next_nodes)])
    whole = _box(every, max(1.5 * d, 0.08 * float(np.ptp(every, axis=0).max()), 1e-3))
    fig = Figure(figsize=(width, height), layout="compressed")  # fixed-aspect panels
    fig.get_layout_engine().set(w_pad=0.02, h_pad=0.02, wspace=0.04)
    ax_a, ax_b = fig.subplots(1, 2)
    _draw(ax_a, system, geo, whole, "the planned domain")
    _draw(ax_b, system, geo, zoom, "at the guard")
    ax_a.set_ylabel(f"{geo.plane_names[1]}")
    handles, labels = ax_a.get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right center", handlelength=1.6,
               labelspacing=0.6)
    fig.suptitle(_title(geo), fontsize=7)
    return fig


def fig2(log_path: str | Path, out_dir: str | Path | None = None,
         formats: str | Iterable[str] = ("pdf", "svg", "png"), *, solve: int | None = None,
         radius: float | None = None, from_tube: bool = False,
         width: float = TEXT_WIDTH_IN, height: float = 2.8, dpi: int = 300) -> Fig2Geometry:
    """Draws Figure 2 from a run log into out_dir/fig2.<fmt> and returns its geometry.

    ``out_dir`` defaults to the log's directory; sizes in inches; see
    :func:`fig2_geometry` for the other arguments. Raises FigureInputError on bad input,
    before anything is written.
    """
    check_size(width, height)
    fmts = parse_formats(formats)
    geo, system = _geometry(log_path, solve, radius, from_tube)
    out = Path(out_dir) if out_dir is not None else geo.log.parent
    make_out_dir(out)
    with figure_style():  # nothing from the user's matplotlibrc leaks in
        save_figure(_figure(system, geo, width, height), out, "fig2", fmts, dpi=dpi)
    return geo
