"""What a hybrid system is: the paper's Definition 1, H = (J, Gamma, D, U, F, G, R).

Modes J carry a flow f_I(x, u, w) and a box input set U_I; each guard is a level set
h(x) = c of its source domain, crossed in a stated direction, optionally only inside an
activity region, with exactly one reset map R_G into its target mode; the transitions
Gamma are the (source, target) pairs of the guards. Everything is written once in CasADi
SX; :meth:`HybridSystem.numeric` compiles the same graphs for NumPy evaluation.

The mode is carried explicitly next to the state, never guessed from x. A plug-in may
also expose named outputs (feet, body points, inverse dynamics), a piecewise-flat terrain
and drawing hints, derived once with the system, for controllers and figures that need them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import casadi as ca
import numpy as np

from hmpc_cli.core.drawing import Drawing
from hmpc_cli.core.numeric import (compile_evaluator, supported_operations,
                                   unsupported_operations)
from hmpc_cli.core.shapes import shape_problems
from hmpc_cli.core.text import closest
from hmpc_cli.core.walker import WalkerModel


#: fields of a logged plan node besides the state and input names
RESERVED_NAMES = frozenset({"t", "seg", "mode", "mode_name"})


def _linear_margin(lipschitz: float) -> Callable[[float, bool], float]:
    def margin(d: float, past: bool) -> float:
        return lipschitz * d

    return margin


@dataclass(frozen=True)
class Mode:
    """A discrete mode: its flow and its box input set.

    Attributes:
        name: mode name (unique).
        flow: CasADi function (x[n], u[m], w[n_w]) -> dx/dt[n].
        u_lower: lower input bounds, shape (m,).
        u_upper: upper input bounds, shape (m,).
    """

    name: str
    flow: ca.Function
    u_lower: tuple[float, ...]
    u_upper: tuple[float, ...]


@dataclass(frozen=True)
class Guard:
    """A guard G = {x : h(x) = c} of a source domain, with its reset map.

    The signed *gap* is positive before the crossing and non-positive past it:
    gap = h - c for ``direction = -1`` (h falls through c), gap = c - h for ``+1``.
    The guard fires when the gap goes from > 0 to <= 0 inside a step, and only where
    every component of ``region(x)`` is >= 0 (if a region is given).

    Attributes:
        name: guard name (unique).
        source: source mode name.
        target: target mode name.
        h: CasADi function x[n] -> scalar.
        level: the level c.
        direction: -1 or +1, see above.
        reset: CasADi function x[n] -> x+[n] (the reset map R_G).
        region: CasADi function x[n] -> r[k] or None (active everywhere).
        nlp_gap: smooth function x -> q with the sign of the gap, used by the NLP
            (default: the gap itself).
        margin: (d, past) -> kappa such that q(x) >= kappa (before side) or
            -q(x) >= kappa (past side) puts the whole tube ball of radius d on that side.
            Default: lipschitz * d.
        lipschitz: Lipschitz constant of the gap in the tube norm (default 1, a distance).
    """

    name: str
    source: str
    target: str
    h: ca.Function
    level: float
    direction: int
    reset: ca.Function
    region: ca.Function | None = None
    nlp_gap: ca.Function | None = None
    margin: Callable[[float, bool], float] | None = None
    lipschitz: float = 1.0

    def gap_expr(self, x: ca.SX) -> ca.SX:
        """Signed gap of a symbolic state (positive before the crossing)."""
        return -self.direction * (self.h(x) - self.level)

    def q_expr(self, x: ca.SX) -> ca.SX:
        """NLP gap expression q(x) (same sign as the gap)."""
        return self.nlp_gap(x) if self.nlp_gap is not None else self.gap_expr(x)

    def kappa(self, d: float, past: bool) -> float:
        """Offset of the NLP row for a tube of radius d (see ``margin``)."""
        return (self.margin or _linear_margin(self.lipschitz))(d, past)


@dataclass(frozen=True)
class Terrain:
    """A piecewise-flat terrain in the (x, y) plane of a walking system [m].

    Attributes:
        ground: height for x <= 0.
        segments: consecutive flat segments (start, end, height) from x = 0, ascending.
    """

    ground: float
    segments: tuple[tuple[float, float, float], ...]

    @property
    def end(self) -> float:
        """X where the last segment ends [m]."""
        return self.segments[-1][1]

    def heights(self, x: float) -> list[float]:
        """Heights at x: one, two on a segment boundary, none beyond the end [m]."""
        out = [self.ground] if x <= 0.0 else []
        out += [h for a, b, h in self.segments if a <= x <= b and h not in out]
        return out

    def profile(self, x) -> np.ndarray:
        """Height under each x [m] (vectorised).

        The higher side on a boundary, the ground for x <= 0, the last segment's height
        past the end.
        """
        x = np.asarray(x, dtype=float)
        out = np.where(x <= 0.0, self.ground, -np.inf)
        for a, b, h in self.segments:
            out = np.where((x >= a) & (x <= b), np.maximum(out, h), out)
        return np.where(x > self.end, self.segments[-1][2], out)

    def segment_at(self, x: float) -> int | None:
        """Index of the segment holding x (the first on a boundary), None if none."""
        for i, (a, b, _) in enumerate(self.segments):
            if a <= x <= b:
                return i
        return None


@dataclass(frozen=True)
class HybridSystem:
    """A hybrid control system with its control task.

    Attributes:
        name: system name.
        state_names: names of the n states.
        input_names: names of the m inputs.
        disturbance_names: names of the n_w disturbance channels (w enters the flow).
        modes: the modes (domains).
        guards: the guards (one transition each).
        initial_mode: mode of ``x0``.
        final_mode: the domain D_F holding the target equilibrium.
        x0: default initial state, shape (n,).
        goal: target point in the coordinates picked by ``goal_map``.
        goal_map: CasADi function x -> y, the quantity compared with ``goal``.
        stage_cost: CasADi function (x[n], u[m]) -> L (per second of horizon).
        terminal_set: CasADi function x -> r, terminal set {r >= 0}, or None.
        tracking_gain: (kp, kd) -> K[m, n], gain of the low-level PD law u = u_ff + K e.
        params: the validated parameters the system was built from (for the log).
        outputs: named CasADi functions the plug-in exposes to controllers and figures
            (each documents its own signature), e.g. ``points_world`` x -> (2, P) body
            points in the world [m], ``stance_foot`` x -> (2,), ``inverse_dynamics``.
        point_names: names of the P columns of the ``points``/``points_world`` outputs.
        skeleton: polylines through named points, for drawing the body.
        terrain: the walking surface, if the system walks on one.
        plane: two state names spanning the plane a figure draws trajectories in.
        state_box: (lower, upper) bounds on x, shape (n,) each (inf: unbounded), that
            every domain's states must satisfy (the walking MPC imposes them at every
            node; the chain MPC does not read them).
        guard_surfaces: per guard index, the flat contact surface (start, end, height)
            it models [m] (contact-planning systems: the foothold candidates).
        drawing: how the run log's 3D scene draws the system (static geometry, body,
            plan trace; :mod:`hmpc_cli.core.drawing`), or None (no scene).
        walker: what walking MPCs and foothold planners need of a walker
            (:class:`~hmpc_cli.core.walker.WalkerModel`, checked here), or None.
        stage_residuals: CasADi function (x[n], u[m]) -> r with ``stage_cost`` = |r|^2,
            every entry reading x or u only (Gauss-Newton back-ends: the walking MPC's
            ``sqp_hpipm`` and ``rti``), or None; checked against ``stage_cost`` here.
    """

    name: str
    state_names: tuple[str, ...]
    input_names: tuple[str, ...]
    disturbance_names: tuple[str, ...]
    modes: tuple[Mode, ...]
    guards: tuple[Guard, ...]
    initial_mode: str
    final_mode: str
    x0: np.ndarray
    goal: np.ndarray
    goal_map: ca.Function
    stage_cost: ca.Function
    terminal_set: ca.Function | None
    tracking_gain: Callable[[float, float], np.ndarray]
    params: dict = field(default_factory=dict)
    outputs: Mapping[str, ca.Function] = field(default_factory=dict)
    point_names: tuple[str, ...] = ()
    skeleton: tuple[tuple[str, ...], ...] = ()
    terrain: Terrain | None = None
    plane: tuple[str, str] | None = None
    state_box: tuple[np.ndarray, np.ndarray] | None = None
    guard_surfaces: Mapping[int, tuple[float, float, float]] = field(default_factory=dict)
    drawing: Drawing | None = None
    walker: WalkerModel | None = None
    stage_residuals: ca.Function | None = None

    def __post_init__(self) -> None:
        self._check_names()
        shapes = shape_problems(self)
        if shapes:
            raise ValueError(f"{self.name}: " + "; ".join(shapes))
        self._check_operations()
        self._check_walker()
        self._check_residuals()

    def _check_operations(self) -> None:
        """The functions evaluated with NumPy use only operations it runs.

        They are the flows, the guards' h, regions and resets, the stage cost and the goal
        map (the simulator, the CEM and the task: :mod:`hmpc_cli.core.numeric`).
        """
        funs = [self.goal_map, self.stage_cost, *(m.flow for m in self.modes),
                *(f for g in self.guards for f in (g.h, g.reset, g.region) if f is not None)]
        bad = {f.name(): ops for f in funs if (ops := unsupported_operations(f))}
        if bad:
            used = "; ".join(f"{name} uses {', '.join(ops)}" for name, ops in bad.items())
            raise ValueError(
                f"{self.name}: {used}: CasADi operations the simulator's and planner's NumPy "
                f"evaluators cannot run (they run {', '.join(supported_operations())}; "
                f"'call' is a Function called inside, e.g. an interpolant or a Callback)")

    def _check_names(self) -> None:
        """Modes, guards, points, plane and vector names: unique and known."""
        names = [m.name for m in self.modes]
        if len(set(names)) != len(names):
            raise ValueError(f"{self.name}: duplicate mode names {names}")
        gnames = [g.name for g in self.guards]
        if len(set(gnames)) != len(gnames):
            raise ValueError(f"{self.name}: duplicate guard names {gnames}")
        for g in self.guards:
            unknown = [m for m in (g.source, g.target) if m not in names]
            if unknown:
                raise ValueError(f"{self.name}: guard {g.name} links unknown mode(s) "
                                 f"{', '.join(map(repr, unknown))} (modes: {names})")
            if g.direction not in (-1, 1):
                raise ValueError(f"{self.name}: guard {g.name} direction must be -1 or +1")
        for field_name, mode in (("initial_mode", self.initial_mode),
                                 ("final_mode", self.final_mode)):
            if mode not in names:
                near = closest(mode, names)
                raise ValueError(f"{self.name}: {field_name} {mode!r} is not a mode (modes: "
                                 f"{', '.join(map(repr, names))}"
                                 + (f"; did you mean {near!r}?)" if near else ")"))
        for line in self.skeleton:
            if not set(line) <= set(self.point_names):
                raise ValueError(f"{self.name}: skeleton names unknown points {line}")
        if self.plane is not None and not set(self.plane) <= set(self.state_names):
            raise ValueError(f"{self.name}: plane {self.plane} names unknown states")
        vector_names = [*self.state_names, *self.input_names]
        clash = sorted({n for n in vector_names if vector_names.count(n) > 1}
                       | (set(vector_names) & RESERVED_NAMES))
        if clash:
            raise ValueError(f"{self.name}: state and input names must be distinct and not "
                             f"{sorted(RESERVED_NAMES)} (a logged plan node holds them all): "
                             f"{clash}")

    def _check_residuals(self) -> None:
        """|stage_residuals|^2 equals ``stage_cost`` at x0 and at a fixed other point."""
        r = self.stage_residuals
        if r is None:
            return
        n, m = self.n_x, self.n_u
        if r.n_in() != 2 or r.size1_in(0) != n or r.size1_in(1) != m:
            raise ValueError(f"{self.name}: stage_residuals must map (x[{n}], u[{m}]) -> r")
        rng = np.random.default_rng(0)
        for x, u in ((self.x0, np.zeros(m)), (self.x0 + rng.normal(0, 0.1, n),
                                              rng.normal(0, 1.0, m))):
            cost, res = float(self.stage_cost(x, u)), np.asarray(r(x, u)).ravel()
            if not np.isclose(res @ res, cost, rtol=1e-9, atol=1e-12):
                raise ValueError(f"{self.name}: |stage_residuals(x, u)|^2 = {res @ res:.9g} "
                                 f"but stage_cost(x, u) = {cost:.9g}")

    def _check_walker(self) -> None:
        """Checks ``walker`` against this system (:meth:`WalkerModel.check`), if any."""
        if self.walker is not None:
            try:
                self.walker.check(self.x0, self.n_u, self.n_w, [m.name for m in self.modes])
            except ValueError as exc:
                raise ValueError(f"{self.name}: {exc}") from None

    def output(self, name: str) -> ca.Function:
        """The named output ``name``.

        Raises:
            KeyError: the plug-in does not expose it (the message lists what it has).
        """
        if name not in self.outputs:
            raise KeyError(f"system {self.name!r} has no output {name!r} (it has "
                           f"{sorted(self.outputs) or 'none'})")
        return self.outputs[name]

    @property
    def n_x(self) -> int:
        """n, the state dimension."""
        return len(self.state_names)

    @property
    def n_u(self) -> int:
        """m, the input dimension."""
        return len(self.input_names)

    @property
    def n_w(self) -> int:
        """n_w, the disturbance dimension."""
        return len(self.disturbance_names)

    def mode_index(self, name: str) -> int:
        """Index of a mode by name."""
        return [m.name for m in self.modes].index(name)

    def guard_index(self, name: str) -> int:
        """Index of a guard by name."""
        return [g.name for g in self.guards].index(name)

    def guards_of(self, mode: int) -> list[int]:
        """Indices of the guards whose source is mode ``mode`` (the set P_I)."""
        name = self.modes[mode].name
        return [i for i, g in enumerate(self.guards) if g.source == name]

    def initial_avoid_violations(self, avoid: Sequence[float]
                                 ) -> list[tuple[str, float, float]]:
        """Tightened guard-avoid rows x0 violates: (guard, q(x0), kappa) per guard.

        ``avoid``: per guard (system order) its guard-avoid offset kappa (NLP row units).
        Only the initial mode's guards that are active at x0 (inside their region) and
        that x0 is before (q(x0) > 0; one x0 lies on is the x0 check's:
        :func:`hmpc_cli.run.setup_checks.initial_state_problems`).
        """
        x = ca.SX.sym("x", self.n_x)
        out = []
        for gi in self.guards_of(self.mode_index(self.initial_mode)):
            g = self.guards[gi]
            q = float(ca.Function("q", [x], [g.q_expr(x)])(self.x0))
            active = g.region is None or bool(np.all(np.asarray(g.region(self.x0)) >= 0))
            if active and 0.0 < q < float(avoid[gi]):
                out.append((g.name, q, float(avoid[gi])))
        return out

    @property
    def transitions(self) -> set[tuple[str, str]]:
        """The transition graph Gamma as (source, target) mode-name pairs."""
        return {(g.source, g.target) for g in self.guards}

    @cached_property
    def numeric(self) -> NumericSystem:
        """NumPy-compiled flows, gaps, regions and resets (built once)."""
        return NumericSystem(self)


def rk4_expr(mode: Mode, x, u, w, h):
    """Symbolic RK4 step of length h with the input clipped to the mode's box."""
    u = ca.fmin(ca.fmax(u, ca.DM(mode.u_lower)), ca.DM(mode.u_upper))
    k1 = mode.flow(x, u, w)
    k2 = mode.flow(x + h / 2 * k1, u, w)
    k3 = mode.flow(x + h / 2 * k2, u, w)
    k4 = mode.flow(x + h * k3, u, w)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


class NumericSystem:
    """Batched NumPy evaluators of a :class:`HybridSystem` (same SX graphs).

    A batch of one (the simulated plant) is evaluated on Python floats where the
    expressions allow it (:func:`~hmpc_cli.core.numeric.compile_evaluator`), with the same
    numbers.
    """

    def __init__(self, system: HybridSystem) -> None:
        n = system.n_x
        x = ca.SX.sym("x", n)
        self.system = system
        self._outputs: dict[str, Callable[..., list[np.ndarray]]] = {}
        self.flows = [compile_evaluator(m.flow) for m in system.modes]
        self.u_lower = np.array([m.u_lower for m in system.modes], dtype=float)
        self.u_upper = np.array([m.u_upper for m in system.modes], dtype=float)
        self.gaps = [
            compile_evaluator(ca.Function(f"gap_{g.name}", [x], [g.gap_expr(x)]))
            for g in system.guards
        ]
        self.regions = [compile_evaluator(g.region) if g.region is not None else None
                        for g in system.guards]
        self.resets = [compile_evaluator(g.reset) for g in system.guards]
        self.target = np.array([system.mode_index(g.target) for g in system.guards])
        self.source = np.array([system.mode_index(g.source) for g in system.guards])
        self.guards_of = [system.guards_of(i) for i in range(len(system.modes))]
        self._goal_map = compile_evaluator(system.goal_map)
        u = ca.SX.sym("u", system.n_u)
        w = ca.SX.sym("w", system.n_w)
        h = ca.SX.sym("h")
        self.rk4 = []
        for mode in system.modes:
            step = rk4_expr(mode, x, u, w, h)
            self.rk4.append(compile_evaluator(ca.Function(f"rk4_{mode.name}", [x, u, w, h],
                                                          [step])))
        self.mode_gaps = [
            compile_evaluator(ca.Function(f"gaps_{m.name}", [x], [ca.vertcat(
                *[system.guards[g].gap_expr(x) for g in self.guards_of[i]], ca.SX(0, 1))]))
            for i, m in enumerate(system.modes)]
        self.gaps_along = []
        for i, mode in enumerate(system.modes):
            # gap along the RK4 sub-step and its rate dgap/dx . f(x_tau) (the exact
            # d/dtau of the RK4 step differs by O(h^4): Newton still converges fast)
            x_tau = rk4_expr(mode, x, u, w, h)
            gaps = ca.vertcat(*[system.guards[g].gap_expr(x) for g in self.guards_of[i]],
                              ca.SX(0, 1))
            u_sat = ca.fmin(ca.fmax(u, ca.DM(mode.u_lower)), ca.DM(mode.u_upper))
            rate = ca.jtimes(gaps, x, mode.flow(x, u_sat, w))
            at_tau = ca.Function("at_tau", [x, u, w], [gaps, rate])
            phi, dphi = at_tau(x_tau, u, w)
            self.gaps_along.append(compile_evaluator(ca.Function(
                f"phi_{mode.name}", [x, u, w, h], [phi, dphi, x_tau])))

    def output(self, name: str) -> Callable[..., list[np.ndarray]]:
        """The named output ``name`` compiled for NumPy (batched; compiled once)."""
        if name not in self._outputs:
            self._outputs[name] = compile_evaluator(self.system.output(name))
        return self._outputs[name]

    def flow(self, mode: int, x: np.ndarray, u: np.ndarray, w: np.ndarray) -> np.ndarray:
        """dx/dt of mode ``mode`` for a batch, shapes (B, n), (B, m), (B, n_w) -> (B, n)."""
        return self.flows[mode](x, u, w)[0]

    def gap(self, guard: int, x: np.ndarray) -> np.ndarray:
        """Signed gap of guard ``guard``, (B, n) -> (B,)."""
        return self.gaps[guard](x)[0][..., 0]

    def active(self, guard: int, x: np.ndarray) -> np.ndarray:
        """Whether x lies in the guard's activity region, (B, n) -> bool (B,)."""
        region = self.regions[guard]
        if region is None:
            return np.ones(x.shape[:-1], dtype=bool)
        return np.all(region(x)[0] >= 0.0, axis=-1)

    def reset(self, guard: int, x: np.ndarray) -> np.ndarray:
        """Reset map of guard ``guard``, (B, n) -> (B, n)."""
        return self.resets[guard](x)[0]

    def saturate(self, mode: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Clips inputs to each sample's mode input box, shapes (B,), (B, m)."""
        return np.clip(u, self.u_lower[mode], self.u_upper[mode])

    def goal_error(self, x: np.ndarray) -> np.ndarray:
        """Distance |goal_map(x) - goal|, (..., n) -> (...)."""
        return np.linalg.norm(self._goal_map(x)[0] - self.system.goal, axis=-1)
