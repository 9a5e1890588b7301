"""Sampled constants of the tubes: the state box, L_x, L_u and the disturbance bound eta.

Every constant is the sampled maximum of a Jacobian norm over a box of states
(:class:`Region`) and each mode's input box (w = 0), refined by a local random search
from the best samples; so is eta's plant part, ||f_plant - f_model|| when the simulated
plant is another system than the controllers' model. A sampled maximum is a lower bound
on the true supremum: these are estimates, not certificates. The Jacobians are built
once per system in CasADi and evaluated on batches through
:func:`~hmpc_cli.core.numeric.compile_numpy`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass

import casadi as ca
import numpy as np

from hmpc_cli.core import signals
from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.numeric import compile_numpy

__all__ = ["ESTIMATE_NOTE", "DisturbanceBound", "LipschitzEstimate", "Region", "TubeError",
           "eta_bound", "jacobians", "lipschitz", "num", "region_from_scenario"]

ESTIMATE_NOTE = ("estimate: sampled maximum of the Jacobian norm (a lower bound on the "
                 "true constant), not a certificate")
_REFINE_ROUNDS, _REFINE_STARTS, _REFINE_TRIES = 25, 8, 16
#: most uniform samples per estimated constant (``hmpc tube --samples``)
MAX_SAMPLES = 10_000_000
#: measured cost of one sample of ``hmpc tube`` (ball, 2 cores): time [us], memory [KiB]
SAMPLE_US, SAMPLE_KIB = 5.0, 0.25


def samples_problem(samples: int) -> str:
    """Why ``samples`` per constant are too many to sample ('' if they are not)."""
    if samples <= MAX_SAMPLES:
        return ""
    from hmpc_cli.core.settings_types import duration_text, gib

    return (f"{samples:.3g} samples per constant exceeds the limit {MAX_SAMPLES:.0e} (it "
            f"would need about {gib(samples * SAMPLE_KIB * 1024)} of memory and "
            f"{duration_text(samples * SAMPLE_US * 1e-6)}, at {SAMPLE_KIB:g} KiB and "
            f"{SAMPLE_US:g} us per sample)")


class TubeError(ValueError):
    """A tube quantity that cannot be computed: ``quantity`` (e.g. "L_x") and ``reason``."""

    def __init__(self, quantity: str, reason: str) -> None:
        super().__init__(f"{quantity}: {reason}")
        self.quantity, self.reason = quantity, reason


def num(v: float) -> float | str:
    """A float for JSON: infinities as "inf"/"-inf" (float() reads them back), NaN as "nan"."""
    v = float(v)
    return v if math.isfinite(v) else str(v)


@dataclass(frozen=True)
class Region:
    """A box of states, lower <= x <= upper, shape (n,) each (finite).

    Attributes:
        lower: lower corner, shape (n,).
        upper: upper corner, shape (n,).
        note: how the box was made (for the report).
    """

    lower: np.ndarray
    upper: np.ndarray
    note: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "lower", np.asarray(self.lower, dtype=float).ravel())
        object.__setattr__(self, "upper", np.asarray(self.upper, dtype=float).ravel())

    def check(self, n: int) -> None:
        """Raises :class:`TubeError` ("region") unless this is a finite, non-empty box in R^n."""
        lo, hi = self.lower, self.upper
        if lo.shape != (n,) or hi.shape != (n,):
            raise TubeError("region", f"needs {n} bounds per corner, got {lo.shape[0]} and "
                            f"{hi.shape[0]}")
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise TubeError("region", "has non-finite bounds (sampling needs a finite box)")
        if np.any(lo > hi):
            raise TubeError("region", f"is empty: lower > upper in coordinate(s) "
                            f"{np.nonzero(lo > hi)[0].tolist()}")
        if np.all(lo == hi):
            raise TubeError("region", "is degenerate: a single point (pad it)")

    @property
    def diameter(self) -> float:
        """||upper - lower||_2 (state units)."""
        return float(np.linalg.norm(self.upper - self.lower))

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {"lower": self.lower.tolist(), "upper": self.upper.tolist(), "note": self.note}


def region_from_scenario(system: HybridSystem, pad: float | None = None,
                         states: np.ndarray | None = None) -> Region:
    """The box to estimate the constants on.

    Spanned by ``states`` (K, n) (e.g. the states a run visited) if given, else by x0 and
    the goal where the goal map picks state coordinates (a constant selection row). Each
    coordinate is then padded on both sides by ``pad`` x its width (default 1, with
    ``states`` 0.1); a coordinate of zero width by ``pad`` x the largest width (1 if all
    are zero: e.g. velocities at rest in x0). Finally clipped to the system's finite
    state-box bounds.
    """
    n = system.n_x
    if states is not None and len(states):
        pts, how = np.asarray(states, dtype=float).reshape(-1, n), "the given states"
    else:
        pts, how = np.atleast_2d(system.x0.astype(float)), "x0"
        goal = _goal_state(system)
        if goal is not None:
            pts, how = np.vstack([pts, goal]), "x0 and the goal"
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if not len(pts):
        raise TubeError("region", "no finite state to span it")
    if pad is None:
        pad = 0.1 if states is not None and len(states) else 1.0
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    width = hi - lo
    scale = float(width.max()) or 1.0
    grow = pad * np.where(width > 0, width, scale)
    lo, hi = lo - grow, hi + grow
    if system.state_box is not None:
        lo = np.maximum(lo, np.where(np.isfinite(system.state_box[0]), system.state_box[0], lo))
        hi = np.minimum(hi, np.where(np.isfinite(system.state_box[1]), system.state_box[1], hi))
    return Region(lo, hi, f"box spanned by {how}, padded by {pad:g} x each width "
                          f"({scale:g} where zero), clipped to the state box")


def _goal_state(system: HybridSystem) -> np.ndarray | None:
    """x0 with the coordinates the goal map selects set to the goal (None: no selection)."""
    x = ca.SX.sym("x", system.n_x)
    y = system.goal_map(x)
    jac = ca.jacobian(y, x)
    if ca.depends_on(jac, x):
        return None
    J = np.array(ca.Function("J", [x], [jac])(np.zeros(system.n_x)), dtype=float)
    goal = system.x0.astype(float).copy()
    for row, value in zip(J, np.ravel(system.goal), strict=False):
        idx = np.nonzero(row)[0]
        if len(idx) != 1 or row[idx[0]] != 1.0:
            return None
        goal[idx[0]] = value
    return goal


class _Jacobians:
    """df/dx, df/du, df/dw (n x n, n x m, n x n_w) and the flow per mode, batched NumPy."""

    def __init__(self, system: HybridSystem) -> None:
        x = ca.SX.sym("x", system.n_x)
        u = ca.SX.sym("u", system.n_u)
        w = ca.SX.sym("w", system.n_w)
        self.system, self.funs, self.flows, self.static = system, [], [], []
        for mode in system.modes:
            f = mode.flow(x, u, w)
            jacs = [ca.jacobian(f, v) for v in (x, u, w)]
            self.funs.append(compile_numpy(ca.Function(f"jac_{mode.name}", [x, u, w], jacs)))
            self.flows.append(compile_numpy(mode.flow))
            self.static.append(tuple(i for i in range(system.n_x) if f[i].is_zero()))

    def __call__(self, mode: int, X: np.ndarray, U: np.ndarray) -> list[np.ndarray]:
        """[df/dx (B, n, n), df/du (B, n, m), df/dw (B, n, n_w)] at (X, U, w = 0)."""
        s = self.system
        outs = self.funs[mode](X, U, np.zeros(s.n_w))
        B = X.shape[0]
        return [o.reshape(B, c, s.n_x).swapaxes(1, 2)
                for o, c in zip(outs, (s.n_x, s.n_u, s.n_w), strict=True)]


_JACOBIANS: dict[int, tuple[HybridSystem, _Jacobians]] = {}


def jacobians(system: HybridSystem) -> _Jacobians:
    """The system's compiled Jacobians (built once per system object)."""
    hit = _JACOBIANS.get(id(system))
    if hit is None or hit[0] is not system:
        if len(_JACOBIANS) > 8:
            _JACOBIANS.clear()
        hit = _JACOBIANS[id(system)] = (system, _Jacobians(system))
    return hit[1]


def _norms(mats: np.ndarray) -> np.ndarray:
    """Spectral norms of a stack (B, r, c) -> (B,); 0 for empty matrices."""
    if mats.shape[1] == 0 or mats.shape[2] == 0:
        return np.zeros(mats.shape[0])
    return np.linalg.norm(mats, 2, axis=(1, 2))


@dataclass(frozen=True)
class _Max:
    """A sampled maximum of one Jacobian norm: value, where, evaluations."""

    value: float
    x: np.ndarray
    u: np.ndarray
    mode: str
    evaluations: int


def _sampled_max(system: HybridSystem, region: Region, which: int, quantity: str,
                 samples: int, seed: int) -> _Max:
    """Max over modes, the region and the input boxes of ||J_which||_2 (0: x, 1: u, 2: w).

    Uniform samples, then a local random search (shrinking steps, staying in the boxes)
    from the best few.

    Raises:
        TubeError: ``quantity`` when the Jacobian is not finite at a sample.
    """
    jac = jacobians(system)

    def values(i: int, mode) -> Callable:
        def norm(X, U):
            with np.errstate(all="ignore"):  # a non-finite Jacobian is reported below
                J = jac(i, X, U)[which]
            bad = ~np.all(np.isfinite(J), axis=(1, 2))
            if np.any(bad):
                raise TubeError(quantity, f"the Jacobian of mode {mode.name!r} is not finite "
                                f"at x = {np.round(X[bad][0], 6).tolist()}")
            return _norms(J)
        return norm

    return _search(system, region, values, samples, seed)


def _search(system: HybridSystem, region: Region, values: Callable, samples: int,
            seed: int) -> _Max:
    """Max over modes, the region and the input boxes of ``values(i, mode)(X, U)`` (B,).

    ``samples`` uniform samples split over the modes, then :func:`_refine` from the best.
    """
    rng = np.random.default_rng(seed)
    best, count = None, 0
    per_mode = max(1, samples // len(system.modes))
    for i, mode in enumerate(system.modes):
        signals.check()  # a stop signal ends the sampling between modes and rounds
        ulo, uhi = np.array(mode.u_lower, dtype=float), np.array(mode.u_upper, dtype=float)
        norm = values(i, mode)
        X = rng.uniform(region.lower, region.upper, (per_mode, system.n_x))
        U = rng.uniform(ulo, uhi, (per_mode, system.n_u))
        vals = norm(X, U)
        X, U, vals, extra = _refine(norm, X, U, vals, (region.lower, region.upper),
                                    (ulo, uhi), rng)
        count += per_mode + extra
        k = int(np.argmax(vals))
        if best is None or vals[k] > best.value:
            best = _Max(float(vals[k]), X[k], U[k], mode.name, 0)
    return _Max(best.value, best.x, best.u, best.mode, count)


def _refine(norm: Callable, X: np.ndarray, U: np.ndarray, vals: np.ndarray,
            xbox: tuple, ubox: tuple, rng: np.random.Generator):
    """Local random search from the best samples; returns (X, U, vals, evaluations)."""
    top = np.argsort(vals)[-_REFINE_STARTS:]
    X, U, vals = X[top], U[top], vals[top]
    xw, uw = xbox[1] - xbox[0], ubox[1] - ubox[0]
    k, evals = len(top), 0
    for r in range(_REFINE_ROUNDS):
        signals.check()
        step = 0.1 * 0.8**r
        Xc = np.clip(np.repeat(X, _REFINE_TRIES, 0) + step * xw * rng.standard_normal(
            (k * _REFINE_TRIES, X.shape[1])), *xbox)
        Uc = np.clip(np.repeat(U, _REFINE_TRIES, 0) + step * uw * rng.standard_normal(
            (k * _REFINE_TRIES, U.shape[1])), *ubox)
        vc = norm(Xc, Uc).reshape(k, _REFINE_TRIES)
        evals += vc.size
        j = np.argmax(vc, axis=1)
        better = vc[np.arange(k), j] > vals
        pick = np.arange(k) * _REFINE_TRIES + j
        X[better], U[better] = Xc[pick][better], Uc[pick][better]
        vals = np.where(better, vc[np.arange(k), j], vals)
    return X, U, vals, evals


@dataclass(frozen=True)
class LipschitzEstimate:
    """L_x and L_u estimated on a region (see :func:`lipschitz`).

    Attributes:
        L_x: max ||df/dx||_2 found [1/s].
        L_u: max ||df/du||_2 found [state units / (input units s)].
        samples: Jacobian evaluations (uniform samples + local refinement) per constant.
        argmax_x: state (n,) where L_x was found; ``argmax_u_x``: where L_u was found.
        mode_x: mode where L_x was found; ``mode_u``: where L_u was found.
        note: says that these are estimates, not certificates.
    """

    L_x: float
    L_u: float
    samples: int
    argmax_x: tuple[float, ...]
    argmax_u_x: tuple[float, ...]
    mode_x: str
    mode_u: str
    note: str = ESTIMATE_NOTE

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)


def lipschitz(system: HybridSystem, region: Region, samples: int = 20000,
              seed: int = 0) -> LipschitzEstimate:
    """Estimates L_x = max ||df/dx||_2 and L_u = max ||df/du||_2 over modes and the region.

    States uniform in ``region``, inputs uniform in each mode's input box, w = 0; then a
    local search from the best samples (see :func:`_refine`).

    Raises:
        TubeError: empty or degenerate region, or a Jacobian that is not finite on it.
    """
    region.check(system.n_x)
    if samples < 1:
        raise TubeError("L_x", f"needs at least one sample, got {samples}")
    lx = _sampled_max(system, region, 0, "L_x", samples, seed)
    lu = _sampled_max(system, region, 1, "L_u", samples, seed + 1)
    return LipschitzEstimate(lx.value, lu.value, lx.evaluations, tuple(lx.x.tolist()),
                             tuple(lu.x.tolist()), lx.mode, lu.mode)


@dataclass(frozen=True)
class DisturbanceBound:
    """eta, the bound on ||f_plant(x, u, w) - f(x, u, 0)|| over the region, inputs and w box.

    f is the controllers' model, f_plant the simulated plant's flow (the model itself
    unless the scenario's ``[plant]`` differs): eta = mismatch + from_w, the plant's flow
    against the model's at w = 0 plus what the box of w adds to the plant's flow, since
    ||f_p(x, u, w) - f(x, u, 0)|| <= ||f_p(x, u, 0) - f(x, u, 0)|| + max ||df_p/dw|| ||w||.

    Attributes:
        eta: the bound [state units / s] (0: zero disturbance set, plant = model).
        kind: the disturbance kind (none, box, paper_fig3).
        magnitude: box half-width per channel.
        w_norm: ||w_max||_2 = magnitude sqrt(n_w) (0 for kind none).
        gain: max ||df_p/dw||_2 found (sampled, w = 0; the plant's flow).
        samples: Jacobian evaluations.
        note: how it was obtained, or why it is zero.
        from_w: gain x w_norm, the disturbance box's part.
        mismatch: max ||f_p(x, u, 0) - f(x, u, 0)||_2 found (0: the plant is the model).
        plant: what differs in the plant, e.g. "mass_scale = 1.1" ("": it is the model).
        mismatch_samples: flow evaluations of the mismatch (0 without a plant).
        mismatch_x: state (n,) where the mismatch was found (() without a plant).
        mismatch_u: input (m,) there; ``mismatch_mode``: its mode ("" without a plant).
    """

    eta: float
    kind: str
    magnitude: float
    w_norm: float
    gain: float
    samples: int
    note: str
    from_w: float = 0.0
    mismatch: float = 0.0
    plant: str = ""
    mismatch_samples: int = 0
    mismatch_x: tuple[float, ...] = ()
    mismatch_u: tuple[float, ...] = ()
    mismatch_mode: str = ""

    @property
    def zero(self) -> bool:
        """Whether the disturbance set is {0} (every tube is identically 0)."""
        return self.eta == 0.0

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return asdict(self)


def eta_bound(system: HybridSystem, region: Region, kind: str, magnitude: float,
              samples: int = 20000, seed: int = 0, plant: HybridSystem | None = None,
              plant_note: str = "") -> DisturbanceBound:
    """The disturbance bound eta = max ||f_p - f||_2 + max ||df_p/dw||_2 ||w_max||_2.

    ``plant``: the simulated plant's system when it differs from the model ``system``
    (None or ``system`` itself: the model, the mismatch is exactly 0 and not sampled);
    ``plant_note`` says how (e.g. "mass_scale = 1.1"). The mismatch is sampled over the
    region and each mode's input box (w = 0) as the other constants are; the w part is
    exact if f_p is affine in w. ``kind`` none (or a zero magnitude, or no channel) gives
    no w part: with the model as plant the zero disturbance set.

    Raises:
        TubeError: ("eta") a non-finite df/dw or flow, or a plant whose modes and
            dimensions are not the model's; ("region") a bad region.
    """
    region.check(system.n_x)
    plant = None if plant is system else plant
    mis = None if plant is None else _mismatch(system, plant, region, samples, seed + 3)
    w_norm = 0.0 if kind == "none" else abs(magnitude) * math.sqrt(system.n_w)
    if w_norm == 0.0:
        why = ("disturbance.kind = none" if kind == "none" else
               "no disturbance channel" if system.n_w == 0 else "magnitude 0")
        if mis is None:
            return DisturbanceBound(0.0, kind, magnitude, 0.0, 0.0, 0,
                                    f"zero disturbance set ({why}): every tube is "
                                    "identically 0")
        gain, from_w, evals, how = 0.0, 0.0, 0, f"no w part ({why})"
    else:
        gw = _sampled_max(plant or system, region, 2, "eta", samples, seed + 2)
        gain, from_w, evals = gw.value, gw.value * w_norm, gw.evaluations
        how = (f"max ||df{'_plant' if mis else ''}/dw||_2 = {gain:.4g} x ||w_max||_2 = "
               f"{w_norm:.4g} (w_max: the box's corner)")
    if mis is None:
        return DisturbanceBound(from_w, kind, magnitude, w_norm, gain, evals, how, from_w)
    what = plant_note or "other parameters"
    note = (f"max ||f_plant - f_model||_2 = {mis.value:.4g} (plant: {what}; w = 0, mode "
            f"{mis.mode}) + {how}")
    return DisturbanceBound(mis.value + from_w, kind, magnitude, w_norm, gain, evals, note,
                            from_w, mis.value, what, mis.evaluations, tuple(mis.x.tolist()),
                            tuple(mis.u.tolist()), mis.mode)


def _mismatch(system: HybridSystem, plant: HybridSystem, region: Region, samples: int,
              seed: int) -> _Max:
    """Max over modes, the region and the model's input boxes of ||f_p - f||_2 at w = 0.

    Raises:
        TubeError: ("eta") the plant's modes or dimensions differ from the model's, or a
            flow is not finite at a sample.
    """
    dims = ("n_x", "n_u", "n_w")
    if [getattr(plant, d) for d in dims] != [getattr(system, d) for d in dims] or \
            [m.name for m in plant.modes] != [m.name for m in system.modes]:
        raise TubeError("eta", "the plant's modes or dimensions differ from the model's (its "
                        "flow cannot be compared)")
    model, real, w0 = jacobians(system), jacobians(plant), np.zeros(system.n_w)

    def values(i: int, mode) -> Callable:
        def norm(X, U):
            with np.errstate(all="ignore"):  # a non-finite flow is reported below
                d = real.flows[i](X, U, w0)[0] - model.flows[i](X, U, w0)[0]
            bad = ~np.all(np.isfinite(d), axis=1)
            if np.any(bad):
                raise TubeError("eta", f"the flow of mode {mode.name!r} (plant or model) is "
                                f"not finite at x = {np.round(X[bad][0], 6).tolist()}")
            return np.linalg.norm(d, axis=1)
        return norm

    return _search(system, region, values, samples, seed)
