"""Tubes held against reality: the observed deviation of recorded runs from their plans.

Per adopted plan solved at t_j and until the next adopted plan at t_{j+1}: the deviation
||x(t) - x_plan(t)||_2 [state norm], and that of the kinematic states alone (see
:mod:`hmpc_cli.tube.structure`), in the domain the plant is in (the plan segment after as
many resets as the plant had guard events since t_j), at

* ``nodes``: the logged states whose time is one of the plan's node times, plus the
  period's end (the next solve's measured state at t_{j+1} when that is a node time);
* ``interpolated``: every logged state, against the plan interpolated between the nodes
  of that domain: cubic Hermite for a kinematic state whose rate is a state (its
  derivative is known at the nodes: exact for the piecewise-constant accelerations of a
  walking plan), linear otherwise; used for a run where fewer than half of the periods
  have a sample on a node time (e.g. the biped's walking plan, whose node spacing
  follows the swing's remaining time). Interpolation error adds to the deviation.

A period without samples is skipped (counted). Each bound (a function of tau = t - t_j)
is then checked per period: inside when every sample is at most the bound, and its
conservatism is the bound over the observed deviation at the period's largest deviation.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["BoundCheck", "Period", "RealityReport", "RecordedRun", "Violation", "check_bounds",
           "read_run", "reality", "run_periods"]

#: bound names checked against the kinematic deviation
KINEMATIC = "kinematic"

#: two times closer than this [s] are the same time
TIME_TOL = 1e-9


@dataclass(frozen=True)
class RecordedRun:
    """What a recorded run contributes.

    Attributes:
        name: the run's name (its directory or file).
        system: the logged ``[system]`` section of its scenario.
        t: state sample times (K,) [s].
        x: state samples (K, n).
        events: guard event times (E,) [s].
        solves: adopted solves in time order: (t_j [s], t_plan (N,) [s] absolute,
            x_plan (N, n), seg_plan (N,)).
        damaged: for messages, the damage or cut that may have lost part of the log
            (:func:`hmpc_cli.log.rundata.damage_note`; '' if intact).
        scenario: the logged scenario as run ({}: not recorded).
    """

    name: str
    system: dict
    t: np.ndarray
    x: np.ndarray
    events: np.ndarray
    solves: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]
    damaged: str = ""
    scenario: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Period:
    """The observed deviation over one MPC period.

    Attributes:
        run: run name.
        t0: the plan's solve time t_j [s].
        tau: times since t_j of the samples (K,) [s], K >= 1.
        dev: deviations ||x - x_plan|| (K,) [state norm].
        dev_kin: deviations of the kinematic states alone (K,), or None (none given).
    """

    run: str
    t0: float
    tau: np.ndarray
    dev: np.ndarray
    dev_kin: np.ndarray | None = None


@dataclass(frozen=True)
class Violation:
    """A sample outside a bound: run, absolute time [s], observed and predicted [state norm]."""

    bound: str
    run: str
    t: float
    observed: float
    predicted: float


@dataclass
class BoundCheck:
    """One bound against the periods.

    Attributes:
        bound: bound name (trivial, ff_only, prop3).
        periods: periods with at least one sample where the bound holds (finite).
        inside: those whose every such sample is at most the bound.
        ratios: bound / observed at each period's largest deviation (positive ones).
        violations: every sample outside the bound.
    """

    bound: str
    periods: int = 0
    inside: int = 0
    ratios: list[float] = field(default_factory=list)
    violations: list[Violation] = field(default_factory=list)

    @property
    def fraction(self) -> float:
        """Fraction of the periods inside (NaN without periods)."""
        return self.inside / self.periods if self.periods else float("nan")

    @property
    def median_ratio(self) -> float:
        """Median conservatism (NaN without ratios)."""
        return float(np.median(self.ratios)) if self.ratios else float("nan")

    @property
    def worst_ratio(self) -> float:
        """Smallest conservatism (below 1: violated; NaN without ratios)."""
        return float(min(self.ratios)) if self.ratios else float("nan")


@dataclass
class RealityReport:
    """Periods, skips and the per-bound checks of a set of runs.

    Attributes:
        periods: the observed periods.
        skipped: periods without a sample.
        unmatched: samples with no plan node (or node interval) in the plant's domain.
        checks: one per bound.
        interpolated: names of the runs compared against the interpolated plan.
    """

    periods: list[Period]
    skipped: int
    unmatched: int
    checks: list[BoundCheck]
    interpolated: list[str] = field(default_factory=list)


def read_run(path: Path) -> RecordedRun:
    """Reads a run directory or run.mcap (through :func:`hmpc_cli.log.rundata.read_run`).

    Raises:
        ValueError: unreadable, plans thinned by ``sim.log_plan_stride`` (the deviation
            from a plan interpolated over the missing nodes would count the interpolation's
            error as the plant's), or without states or adopted solves.
    """
    from hmpc_cli.log.damage import reading
    from hmpc_cli.log.rundata import damage_note, read_run as read_log_arrays

    run = read_log_arrays(path)
    run.full_plans("tube vs reality (the plan at every logged state)")
    if not run.t.size:
        raise ValueError(run.lacks("no /sim/state"))
    with reading(run.path):  # what the decoded log holds, of a wrong shape: damage
        solves = [(s.t, s.plan.t, np.atleast_2d(s.plan.x), s.plan.seg) for s in run.adopted()]
        events = np.array([e.t for e in run.events], dtype=float)
    if not solves:
        raise ValueError(run.lacks("no adopted /mpc/solve"))
    return RecordedRun(run.name, run.system, run.t, run.x, events,
                       sorted(solves, key=lambda s: s[0]),
                       damage_note(run.damage, run.complete), dict(run.scenario))


#: the settings besides the system's parameters that make a run's tube: disturbance,
#: the low level's gains, the simulated plant
TUBE_SETTINGS = (("disturbance", "kind"), ("disturbance", "magnitude"), ("lowlevel", "kp"),
                 ("lowlevel", "kd"), ("plant",))


def other_tube_settings(run: RecordedRun, scenario: dict) -> list[str]:
    """``key: run value (scenario value)`` for each of :data:`TUBE_SETTINGS` that differs.

    A setting the run's log does not record is not compared.
    """
    out = []
    for path in TUBE_SETTINGS:
        have, want = run.scenario, scenario
        for key in path:
            have = have.get(key) if isinstance(have, dict) else None
            want = want.get(key) if isinstance(want, dict) else None
        if have is not None and have != want:
            out.append(f"{'.'.join(path)} = {have!r} (the scenario's: {want!r})")
    return out


def _node(t_plan: np.ndarray, x_plan: np.ndarray, seg_plan: np.ndarray, t: float,
          seg: int) -> np.ndarray | None:
    """The plan's node state at time t in segment seg, or None if no node is there."""
    hit = np.flatnonzero((np.abs(t_plan - t) < TIME_TOL) & (seg_plan == seg))
    return x_plan[hit[0]] if hit.size else None


def _hermite(t: float, ts: np.ndarray, y: np.ndarray, dy: np.ndarray) -> float:
    """Cubic Hermite interpolation of values y and slopes dy at sorted times ts."""
    k = int(np.clip(np.searchsorted(ts, t) - 1, 0, len(ts) - 2))
    h = ts[k + 1] - ts[k]
    if h <= 0.0:
        return float(y[k])
    s = (t - ts[k]) / h
    h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
    h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
    return float(h00 * y[k] + h10 * h * dy[k] + h01 * y[k + 1] + h11 * h * dy[k + 1])


def _interpolator(rates: Mapping[int, int]):
    """The plan's state at time t in segment seg (None outside its nodes).

    ``rates``: kinematic state -> the state that is its rate (Hermite), -1: zero flow.
    """
    def at(t_plan: np.ndarray, x_plan: np.ndarray, seg_plan: np.ndarray, t: float,
           seg: int) -> np.ndarray | None:
        idx = np.flatnonzero(seg_plan == seg)
        if idx.size == 0 or not (t_plan[idx[0]] - TIME_TOL <= t <= t_plan[idx[-1]] + TIME_TOL):
            return None
        ts, xs = t_plan[idx], x_plan[idx]
        if idx.size == 1:
            return xs[0].copy()
        out = np.array([np.interp(t, ts, xs[:, i]) for i in range(xs.shape[1])])
        for i, j in rates.items():
            if j >= 0:
                out[i] = _hermite(t, ts, xs[:, i], xs[:, j])
        return out

    return at


def _samples(run: RecordedRun, j: int, interpolate: bool) -> list[tuple[float, np.ndarray]]:
    """The (t, x) samples of solve j's period (the period's end only with nodes)."""
    t0 = run.solves[j][0]
    nxt = run.solves[j + 1] if j + 1 < len(run.solves) else None
    t1 = nxt[0] if nxt is not None else float(run.t[-1]) + 2 * TIME_TOL
    pts = [(float(t), x) for t, x in zip(run.t, run.x, strict=True)
           if t0 + TIME_TOL < t < t1 - TIME_TOL]
    if nxt is not None:
        pts.append((t1, nxt[2][0]))
    if not interpolate:
        t_plan = run.solves[j][1]
        pts = [(t, x) for t, x in pts if np.any(np.abs(t_plan - t) < TIME_TOL)]
    return pts


def run_periods(run: RecordedRun, kinematic: Mapping[int, int] | None = None,
                interpolate: bool = False) -> tuple[list[Period], int, int]:
    """The periods of one run: (periods, skipped periods, unmatched samples).

    Args:
        run: the recorded run.
        kinematic: kinematic state -> the state that is its rate (-1: zero flow); their
            deviation is ``Period.dev_kin``.
        interpolate: compare every sample with the interpolated plan (else node times).

    An unmatched sample is one whose domain (after the plant's resets) has no node there
    (no node interval, interpolating).
    """
    kinematic = dict(kinematic or {})
    pick = _interpolator(kinematic) if interpolate else _node
    kin = sorted(kinematic)
    periods, skipped, unmatched = [], 0, 0
    for j, (t0, t_plan, x_plan, seg_plan) in enumerate(run.solves):
        taus, devs, kins = [], [], []
        for t, x in _samples(run, j, interpolate):
            resets = int(np.count_nonzero((run.events > t0 + TIME_TOL) &
                                          (run.events <= t + TIME_TOL)))
            node = pick(t_plan, x_plan, seg_plan, t, int(seg_plan[0]) + resets)
            if node is None:
                unmatched += 1
                continue
            err = np.asarray(x, dtype=float) - node
            taus.append(t - t0)
            devs.append(float(np.linalg.norm(err)))
            kins.append(float(np.linalg.norm(err[kin])) if kin else np.nan)
        if taus:
            periods.append(Period(run.name, t0, np.array(taus), np.array(devs),
                                  np.array(kins) if kin else None))
        else:
            skipped += 1
    return periods, skipped, unmatched


def check_bounds(periods: Iterable[Period],
                 bounds: Callable[[np.ndarray], dict[str, np.ndarray]]) -> list[BoundCheck]:
    """Checks each bound on the periods.

    Args:
        periods: observed periods.
        bounds: tau (K,) [s] -> bound name -> bound (K,) [state norm]; NaN where a bound
            does not hold (that sample is not checked against it). The bound named
            :data:`KINEMATIC` is checked against ``Period.dev_kin`` (skipped without it).

    Returns:
        One :class:`BoundCheck` per bound name, in the order ``bounds`` first returns.
    """
    checks: dict[str, BoundCheck] = {}
    for p in periods:
        for name, b in bounds(p.tau).items():
            c = checks.setdefault(name, BoundCheck(name))
            dev = p.dev_kin if name == KINEMATIC else p.dev
            if dev is None:
                continue
            b = np.asarray(b, dtype=float)
            ok = ~np.isnan(b)
            if not np.any(ok):
                continue
            c.periods += 1
            out = ok & (dev > b)
            c.inside += int(not np.any(out))
            c.violations += [Violation(name, p.run, p.t0 + float(p.tau[k]), float(dev[k]),
                                       float(b[k])) for k in np.flatnonzero(out)]
            k = int(np.argmax(np.where(ok, dev, -np.inf)))
            if dev[k] > 0:
                c.ratios.append(float(b[k] / dev[k]))
    return list(checks.values())


def reality(runs: Iterable[RecordedRun],
            bounds: Callable[[np.ndarray], dict[str, np.ndarray]],
            kinematic: Mapping[int, int] | None = None) -> RealityReport:
    """The periods of all runs and each bound's check.

    A run is compared at the plan's node times; one where fewer than half of the
    periods have a sample at a node time is compared against the interpolated plan
    (listed in ``interpolated``).
    """
    periods, skipped, unmatched, interpolated = [], 0, 0, []
    for run in runs:
        p, s, u = run_periods(run, kinematic)
        if 2 * len(p) < len(run.solves):
            p, s, u = run_periods(run, kinematic, interpolate=True)
            interpolated.append(run.name)
        periods += p
        skipped += s
        unmatched += u
    return RealityReport(periods, skipped, unmatched, check_bounds(periods, bounds),
                         interpolated)
