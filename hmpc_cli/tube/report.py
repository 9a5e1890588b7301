"""The tube analysis of one system: :func:`analyse` and its :class:`TubeReport`.

diam T(dt) per MPC rate (the paper: "we will use diam T(dt) as the error tube for
planning", dt the MPC period) by every bound, the one used, and the margins it implies.
Takes a built system and plain values: never a Scenario (the command line reads it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.tube.bounds import (
    Margins, feedforward_tube, initial_violations, input_box_diameter, integrated_tube,
    low_level_share, margins)
from hmpc_cli.tube.certificate import Certificate, pd_certificate
from hmpc_cli.tube.sampling import (
    DisturbanceBound, LipschitzEstimate, Region, eta_bound, lipschitz, num)
from hmpc_cli.tube.structure import guard_states, kinematic_rates

__all__ = ["DEFAULT_RATES", "TubeReport", "TubeRow", "analyse", "diameter_curves",
           "kinematic_curve", "planning_diameter", "tube_row"]

#: MPC rates [Hz] every report tabulates (plus the scenario's own rate)
DEFAULT_RATES = (5, 10, 20, 50, 100)


@dataclass(frozen=True)
class TubeRow:
    """diam T(dt) at one MPC rate and the margins it implies.

    Attributes:
        rate_hz: MPC rate [Hz]; ``dt`` = 1 / rate_hz [s].
        trivial: Prop. 2's diameter with the self-consistent zeta (:func:`low_level_share`).
        ff_only: the Remark's feed-forward-only diameter (valid without feedback only).
        prop3: a(dt) when certified and dt <= tau, else None.
        diam: the planning tube diam T(dt): min(a(dt), trivial) when Prop. 3 applies.
        bound: which bound ``diam`` is ("prop3" or "trivial").
        margins: the margins of ``diam`` (and of ``kinematic`` for guards that see only
            kinematic states).
        kinematic: the kinematic tube int_0^dt diam T(s) ds, or None without kinematic
            states (:mod:`hmpc_cli.tube.structure`).
    """

    rate_hz: float
    dt: float
    trivial: float
    ff_only: float
    prop3: float | None
    diam: float
    bound: str
    margins: Margins
    kinematic: float | None = None

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {"rate_hz": self.rate_hz, "dt": self.dt, "trivial": num(self.trivial),
                "ff_only": num(self.ff_only),
                "prop3": None if self.prop3 is None else num(self.prop3),
                "diam": num(self.diam), "bound": self.bound,
                "kinematic": None if self.kinematic is None else num(self.kinematic),
                "margins": self.margins.to_dict()}


@dataclass(frozen=True)
class TubeReport:
    """Everything :func:`analyse` finds (JSON-ready through :meth:`to_dict`).

    Attributes:
        system: system name.
        region: the state box of the estimates.
        lipschitz: L_x, L_u.
        disturbance: eta.
        kp: proportional gain; ``kd``: derivative gain of the low level.
        gain_norm: ||K||_2, K = system.tracking_gain(kp, kd).
        box_diameter: the largest input-box diameter.
        certificate: Prop. 3's certificate, or why there is none.
        rate_hz: the scenario's MPC rate [Hz].
        rows: diam T(dt) and margins per rate (ascending).
        state_names: the system's state names.
        kinematic_states: indices of the kinematic states (may be empty).
        kinematic_rates: per kinematic state, the index of the state that is its rate
            (-1: its flow is zero).
        kinematic_guards: per guard, whether its gap depends on kinematic states only.
        warnings: problems the margins cause (e.g. infeasible at x0).
        notes: quantities that could not be computed and why.
    """

    system: str
    region: Region
    lipschitz: LipschitzEstimate
    disturbance: DisturbanceBound
    kp: float
    kd: float
    gain_norm: float
    box_diameter: float
    certificate: Certificate
    rate_hz: float
    rows: tuple[TubeRow, ...]
    state_names: tuple[str, ...] = ()
    kinematic_states: tuple[int, ...] = ()
    kinematic_rates: tuple[int, ...] = ()
    kinematic_guards: tuple[bool, ...] = ()
    warnings: tuple[str, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)

    def row(self, rate_hz: float) -> TubeRow:
        """The tabulated row of ``rate_hz``."""
        return next(r for r in self.rows if r.rate_hz == rate_hz)

    def row_at(self, system: HybridSystem, rate_hz: float) -> TubeRow:
        """The row of any MPC rate [Hz] from this report's constants (``system``: its own)."""
        return tube_row(system, rate_hz, self.lipschitz, self.disturbance.eta,
                        self.certificate, self.gain_norm, self.box_diameter,
                        self.kinematic_guards if self.kinematic_states else None)

    def to_dict(self) -> dict:
        """JSON-ready dict of the whole report."""
        return {"system": self.system, "region": self.region.to_dict(),
                "lipschitz": self.lipschitz.to_dict(),
                "disturbance": self.disturbance.to_dict(), "kp": self.kp, "kd": self.kd,
                "gain_norm": self.gain_norm, "box_diameter": self.box_diameter,
                "certificate": self.certificate.to_dict(), "rate_hz": self.rate_hz,
                "rows": [r.to_dict() for r in self.rows],
                "kinematic_states": list(self.kinematic_states),
                "kinematic_rates": list(self.kinematic_rates),
                "kinematic_guards": list(self.kinematic_guards),
                "warnings": list(self.warnings),
                "notes": list(self.notes)}


def planning_diameter(t: np.ndarray, lx: LipschitzEstimate, eta: float, cert: Certificate,
                      gain_norm: float, box: float) -> np.ndarray:
    """The planning tube diam T(t) on times t (K,) [s].

    The trivial tube, or a(t) where Prop. 3 holds and is smaller.
    """
    t = np.asarray(t, dtype=float)
    out = np.array([low_level_share(float(s), eta, lx.L_x, lx.L_u, gain_norm, box)[0]
                    for s in t.ravel()]).reshape(t.shape)
    if cert.certified:
        a = np.where(t <= cert.tau, cert.a(t), np.inf)
        out = np.minimum(out, a)
    return out


def tube_row(system: HybridSystem, rate: float, lx: LipschitzEstimate, eta: float,
             cert: Certificate, gain_norm: float, box: float,
             kinematic_guards: Sequence[bool] | None = None) -> TubeRow:
    """The tube diam T(1 / rate) by every bound, the chosen one and its margins.

    Args:
        system: the hybrid system (its guards and input boxes).
        rate: MPC rate [Hz].
        lx: the Lipschitz estimates.
        eta: the disturbance bound.
        cert: Prop. 3's certificate (used when certified and 1 / rate <= tau).
        gain_norm: ||K||_2 of the low level.
        box: the largest input-box diameter.
        kinematic_guards: per guard, whether it sees kinematic states only; None: the
            system has no kinematic states (no kinematic tube).
    """
    dt = 1.0 / rate
    trivial, zeta = low_level_share(dt, eta, lx.L_x, lx.L_u, gain_norm, box)
    ff = float(feedforward_tube(dt, eta, lx.L_x))
    a = cert.a(dt) if cert.certified and dt <= cert.tau else None
    diam, bound = (a, "prop3") if a is not None and a <= trivial else (trivial, "trivial")
    if bound == "prop3":
        zeta = min(gain_norm * diam, box)
    kin = None if kinematic_guards is None else min(diam, integrated_tube(
        dt, lambda s: planning_diameter(s, lx, eta, cert, gain_norm, box)))
    return TubeRow(float(rate), dt, trivial, ff, a, diam, bound,
                   margins(system, diam, zeta, kin, kinematic_guards or ()), kin)


def analyse(system: HybridSystem, *, region: Region, kind: str, magnitude: float,
            kp: float, kd: float, rate_hz: float, rates: Sequence[float] = DEFAULT_RATES,
            samples: int = 20000, seed: int = 0, plant: HybridSystem | None = None,
            plant_note: str = "") -> TubeReport:
    """The tube analysis of a system under a disturbance box and a PD low level.

    Args:
        system: the (controllers' model) hybrid system.
        region: state box of the Lipschitz and disturbance estimates.
        kind: disturbance kind (none, box, paper_fig3).
        magnitude: the disturbance box's half-width per channel.
        kp: low-level proportional gain.
        kd: low-level derivative gain.
        rate_hz: the scenario's MPC rate [Hz] (tabulated with ``rates``).
        rates: further MPC rates [Hz] to tabulate.
        samples: uniform samples per estimated constant (plus refinement).
        seed: sampling seed.
        plant: the simulated plant's system when it differs from the model (its flow's
            mismatch is part of eta, :func:`~hmpc_cli.tube.sampling.eta_bound`); None: the
            model is the plant.
        plant_note: how the plant differs (e.g. "mass_scale = 1.1"), for the report.

    Raises:
        TubeError: the region is empty/degenerate or a Jacobian is not finite on it (no
            trivial tube then).
    """
    lx = lipschitz(system, region, samples, seed)
    dist = eta_bound(system, region, kind, magnitude, samples, seed, plant, plant_note)
    K = np.atleast_2d(np.asarray(system.tracking_gain(kp, kd), dtype=float))
    gain_norm = float(np.linalg.norm(K, 2)) if np.any(K) else 0.0
    box = input_box_diameter(system)
    cert = pd_certificate(system, kp, kd, dist.eta, max(samples // 10, 200), seed,
                          scale=region.diameter)
    rates_of = kinematic_rates(system)
    kin = tuple(rates_of)
    kin_guards = tuple(set(guard_states(g, system.n_x)) <= set(kin) for g in system.guards)
    rows = tuple(tube_row(system, r, lx, dist.eta, cert, gain_norm, box,
                          kin_guards if kin else None)
                 for r in sorted({float(r) for r in (*rates, rate_hz)}))
    notes = [f"eta: {dist.note}"] if dist.zero else []
    if not cert.certified:
        notes.append(f"certificate: none: {cert.reason} (the trivial tube still holds)")
    return TubeReport(system.name, region, lx, dist, float(kp), float(kd), gain_norm, box,
                      cert, float(rate_hz), rows, system.state_names, kin,
                      tuple(rates_of.values()), kin_guards,
                      tuple(_warnings(system, rows, rate_hz, lx.L_x)), tuple(notes))


def _warnings(system: HybridSystem, rows: Sequence[TubeRow], rate_hz: float,
              L_x: float) -> list[str]:
    """Infeasibility at x0, invalid margin formulas, collapsed input boxes at the rate."""
    row = next(r for r in rows if r.rate_hz == float(rate_hz))
    out = [f"at {rate_hz:g} Hz the tightened guard-avoid row of {name} (kappa = {k:.4g}) "
           f"exceeds its NLP gap at x0 ({q:.4g}): the tightened problem is infeasible at "
           f"the initial state" for name, q, k in initial_violations(system, row.margins)]
    out += [f"at {rate_hz:g} Hz the margin of guard {g.guard} decreases with the radius "
            f"{g.radius:.4g}: its formula does not hold for a tube this large (the tube "
            f"does not fit the guard's geometry)" for g in row.margins.guards if not g.monotone]
    out += [f"at {rate_hz:g} Hz the input shrink zeta = {row.margins.zeta:.4g} reaches half "
            f"of mode {i.mode}'s input box (capped): its feed-forward box collapses to the "
            f"centre, the MPC keeps no input authority there" for i in row.margins.inputs
            if i.capped]
    if not math.isfinite(row.diam):
        out.append(f"at {rate_hz:g} Hz diam T(dt) overflows (L_x dt = "
                   f"{row.dt * L_x:.4g}): no finite tube")
    return out


def kinematic_curve(report: TubeReport, t: np.ndarray) -> np.ndarray:
    """The kinematic tube int_0^t diam T(s) ds on times ``t`` (K,) [s] (NaN: none)."""
    if not report.kinematic_states:
        return np.full(np.shape(t), np.nan)
    lx, eta = report.lipschitz, report.disturbance.eta

    def diam(s):
        return planning_diameter(s, lx, eta, report.certificate, report.gain_norm,
                                 report.box_diameter)

    return np.array([integrated_tube(float(s), diam, 100) for s in np.ravel(t)])


def diameter_curves(report: TubeReport, t: np.ndarray) -> dict[str, np.ndarray]:
    """Each bound on times ``t`` (K,) [s] by name.

    trivial, ff_only, prop3 (NaN past tau) and, with kinematic states, ``kinematic``
    (their tube, :func:`kinematic_curve`).
    """
    lx, eta = report.lipschitz, report.disturbance.eta
    trivial = np.array([low_level_share(float(s), eta, lx.L_x, lx.L_u, report.gain_norm,
                                        report.box_diameter)[0] for s in t])
    out = {"trivial": trivial, "ff_only": np.asarray(feedforward_tube(t, eta, lx.L_x))}
    cert = report.certificate
    if cert.certified:
        out["prop3"] = np.where(t <= cert.tau, cert.a(t), np.nan)
    if report.kinematic_states:
        out["kinematic"] = kinematic_curve(report, t)
    return out
