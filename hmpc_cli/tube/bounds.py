"""Tube bounds (Prop. 2, its Remark), the low level's input share and the margins.

The trivial tube (eta + L_u zeta) t e^{L_x t}, the feed-forward-only tube eta t e^{L_x t},
zeta (what the PD law adds to the feed-forward), the kinematic tube (a tube integrated
once: :mod:`.structure`) and the tightened constraints of problem (14) a tube implies:
guard-avoid rows, the virtual pass-through node and the input boxes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.tube.sampling import num

__all__ = ["GuardMargin", "InputMargin", "Margins", "feedforward_tube", "initial_violations",
           "input_box_diameter", "integrated_tube", "low_level_share", "margins",
           "trivial_tube", "zeta_bound"]

#: pieces of the Riemann sum of :func:`integrated_tube`
PIECES = 400


def input_box_diameter(system: HybridSystem) -> float:
    """The largest input-box diameter ||u_upper - u_lower||_2 over the modes."""
    return max(float(np.linalg.norm(np.subtract(m.u_upper, m.u_lower))) for m in system.modes)


def zeta_bound(system: HybridSystem, kp: float, kd: float, radius: float) -> float:
    """The low level's input share zeta = min(||K||_2 radius, D_U); 0 when kp = kd = 0.

    The low level adds K (x_ref - x) to the feed-forward; with ||x - x_ref|| <= radius its
    share is at most ||K|| radius, and the saturated input never leaves the box, so it is
    also at most D_U, the largest input-box diameter over the modes (projecting on the box
    does not expand distances).
    """
    K = np.atleast_2d(np.asarray(system.tracking_gain(kp, kd), dtype=float))
    if not np.any(K):
        return 0.0
    return float(min(np.linalg.norm(K, 2) * radius, input_box_diameter(system)))


def trivial_tube(t, eta: float, L_x: float, L_u: float, zeta: float):
    """Prop. 2's diameter (eta + L_u zeta) t e^{L_x t} (t >= 0 [s], scalar or array)."""
    with np.errstate(over="ignore", invalid="ignore"):
        out = (eta + L_u * zeta) * np.asarray(t, dtype=float) * np.exp(L_x * np.asarray(t))
    return np.where(np.asarray(t) == 0, 0.0, out) if np.ndim(out) else float(
        0.0 if t == 0 else out)


def feedforward_tube(t, eta: float, L_x: float):
    """The Remark's feed-forward-only diameter eta t e^{L_x t} (no low-level feedback)."""
    return trivial_tube(t, eta, L_x, 0.0, 0.0)


def low_level_share(t: float, eta: float, L_x: float, L_u: float, gain_norm: float,
                    box_diameter: float) -> tuple[float, float]:
    """The self-consistent trivial tube at t and the low level's share zeta: (diam, zeta).

    zeta = min(||K|| r, D) with r the tube radius itself: r = eta c / (1 - L_u ||K|| c),
    c = t e^{L_x t}, when L_u ||K|| c < 1 (if the error never reached r, the PD share
    stayed below ||K|| r and Gronwall keeps the error below r up to t); else, and whenever
    it is smaller, r = (eta + L_u D) c with zeta = D (the saturated input stays in its box).
    With eta = 0 the error starts and stays 0 (Gronwall with L_x + L_u ||K||): (0, 0).
    """
    if eta == 0.0:  # no disturbance: the error stays 0 (Gronwall on L_x + L_u ||K||)
        return 0.0, 0.0
    sat = trivial_tube(t, eta, L_x, L_u, box_diameter)
    if gain_norm == 0.0:
        return float(trivial_tube(t, eta, L_x, 0.0, 0.0)), 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        c = t * np.exp(L_x * t)
        denom = 1.0 - L_u * gain_norm * c
        fixed = eta * c / denom if denom > 0 else math.inf
    if fixed <= sat:
        return float(fixed), float(min(gain_norm * fixed, box_diameter))
    return float(sat), float(box_diameter)


def integrated_tube(t: float, diam: Callable[[np.ndarray], np.ndarray],
                    pieces: int = PIECES) -> float:
    """An upper bound of int_0^t diam(s) ds [state norm s]: the kinematic tube at t.

    The right Riemann sum of the running maximum of ``diam`` (an upper bound for any
    ``diam``, exact as pieces grow for a non-decreasing one); NaN samples count as inf.
    """
    if t <= 0.0:
        return 0.0
    s = np.linspace(0.0, t, pieces + 1)[1:]
    d = np.asarray(diam(s), dtype=float)
    d = np.maximum.accumulate(np.where(np.isnan(d), np.inf, d))
    with np.errstate(over="ignore", invalid="ignore"):
        return float(np.sum(d) * (t / pieces))


@dataclass(frozen=True)
class GuardMargin:
    """A guard's NLP row offsets for a tube radius.

    Attributes:
        guard: guard name.
        radius: the radius the offsets are of: the kinematic radius when the guard's gap
            depends on kinematic states only, else the state radius.
        avoid: guard-avoid offset kappa(d, past=False): q(x) >= avoid keeps the ball before it.
        pass_through: virtual-node offset kappa(d, past=True): -q(x) >= it puts the ball past.
        monotone: whether kappa is non-decreasing on [0, d] (False: the guard's margin
            formula does not hold at this radius, e.g. a ball larger than a circle).
    """

    guard: str
    radius: float
    avoid: float
    pass_through: float
    monotone: bool = True


@dataclass(frozen=True)
class InputMargin:
    """A mode's input-box tightening per side (zeta, capped at half each box width)."""

    mode: str
    per_side: tuple[float, ...]
    capped: bool


@dataclass(frozen=True)
class Margins:
    """The tightened constraints a tube radius implies (JSON-ready through :meth:`to_dict`).

    Attributes:
        radius: the tube radius d [state norm].
        zeta: the low level's input share the input boxes are shrunk by.
        kinematic: the kinematic tube radius (<= radius), or None (no kinematic states).
        guards: one :class:`GuardMargin` per guard.
        inputs: one :class:`InputMargin` per mode.
    """

    radius: float
    zeta: float
    guards: tuple[GuardMargin, ...]
    inputs: tuple[InputMargin, ...]
    kinematic: float | None = None

    def to_dict(self) -> dict:
        """JSON-ready dict (infinities as "inf")."""
        return {"radius": num(self.radius), "zeta": num(self.zeta),
                "kinematic": None if self.kinematic is None else num(self.kinematic),
                "guards": [{"guard": g.guard, "radius": num(g.radius), "avoid": num(g.avoid),
                            "pass_through": num(g.pass_through), "monotone": g.monotone}
                           for g in self.guards],
                "inputs": [{"mode": i.mode, "per_side": [num(v) for v in i.per_side],
                            "capped": i.capped} for i in self.inputs]}

    @classmethod
    def from_dict(cls, d: dict) -> Margins:
        """Inverse of :meth:`to_dict`."""
        kin = d.get("kinematic")
        return cls(float(d["radius"]), float(d["zeta"]),
                   tuple(GuardMargin(g["guard"], float(g["radius"]), float(g["avoid"]),
                                     float(g["pass_through"]), bool(g["monotone"]))
                         for g in d["guards"]),
                   tuple(InputMargin(i["mode"], tuple(float(v) for v in i["per_side"]),
                                     bool(i["capped"])) for i in d["inputs"]),
                   None if kin is None else float(kin))


def _monotone(guard, d: float) -> bool:
    """Whether both offsets of ``guard`` are non-decreasing on [0, d] (d finite)."""
    if not math.isfinite(d):
        return True
    grid = np.linspace(0.0, d, 11)
    for past in (False, True):
        ks = np.array([guard.kappa(float(s), past) for s in grid])
        if not np.all(np.diff(ks) >= -1e-12 * (1 + np.abs(ks[1:]))):
            return False
    return True


def margins(system: HybridSystem, d: float, zeta: float = 0.0,
            kinematic: float | None = None, kinematic_guards: Sequence[bool] = ()) -> Margins:
    """Guard-avoid, pass-through and input margins of a tube of radius ``d``.

    Per guard g of radius d_g: ``g.kappa(d_g, past=False)`` and ``g.kappa(d_g, past=True)``,
    d_g = min(d, kinematic) when ``kinematic_guards[g]`` (its gap depends on kinematic
    states only, :mod:`.structure`) and a kinematic radius is given, else d. Per mode:
    each input bound moves inwards by zeta (||u - u_ff|| <= zeta bounds every component),
    at most to the box's centre.
    """
    guards = []
    for i, g in enumerate(system.guards):
        use = kinematic is not None and i < len(kinematic_guards) and kinematic_guards[i]
        r = min(d, kinematic) if use else d
        guards.append(GuardMargin(g.name, float(r), float(g.kappa(r, False)),
                                  float(g.kappa(r, True)), _monotone(g, r)))
    inputs = []
    for m in system.modes:
        half = 0.5 * (np.asarray(m.u_upper, dtype=float) - np.asarray(m.u_lower, dtype=float))
        inputs.append(InputMargin(m.name, tuple(np.minimum(zeta, half).tolist()),
                                  bool(np.any(zeta >= half))))
    return Margins(float(d), float(zeta), tuple(guards), tuple(inputs),
                   None if kinematic is None else float(min(d, kinematic)))


def initial_violations(system: HybridSystem, m: Margins) -> list[tuple[str, float, float]]:
    """Tightened guard-avoid rows x0 violates: (guard, q(x0), kappa) per guard.

    Only the initial mode's guards that are active at x0 (inside their region) and that
    x0 is before (q(x0) > 0, so the untightened row holds): the violation is the tube's
    (:meth:`~hmpc_cli.core.hybrid.HybridSystem.initial_avoid_violations`).
    """
    return system.initial_avoid_violations([g.avoid for g in m.guards])
