"""Tubes held against reality: the observed deviation of recorded runs from their plans.

Per adopted plan solved at t_j and until the next adopted plan at t_{j+1}: the deviation
||x(t) - x_plan(t)||_2 [state norm] at the logged states whose time is one of the plan's
node times (never interpolated between nodes), in the domain the plant is in (the plan
segment after as many resets as the plant had guard events since t_j), plus the period's
end: the next solve's measured state at t_{j+1} when that is a node time of the plan. A
period with neither is skipped (counted). Each bound (a function of tau = t - t_j) is then
checked per period: inside when every sample is at most the bound, and its conservatism is
the bound over the observed deviation at the period's largest deviation.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["BoundCheck", "Period", "RealityReport", "RunData", "Violation", "check_bounds",
           "read_run", "reality", "run_periods"]

#: two times closer than this [s] are the same time
TIME_TOL = 1e-9


@dataclass(frozen=True)
class RunData:
    """What a recorded run contributes.

    Attributes:
        name: the run's name (its directory or file).
        system: the logged ``[system]`` section of its scenario.
        t: state sample times (K,) [s].
        x: state samples (K, n).
        events: guard event times (E,) [s].
        solves: adopted solves in time order: (t_j [s], t_plan (N,) [s] absolute,
            x_plan (N, n), seg_plan (N,)).
    """

    name: str
    system: dict
    t: np.ndarray
    x: np.ndarray
    events: np.ndarray
    solves: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Period:
    """The observed deviation over one MPC period.

    Attributes:
        run: run name.
        t0: the plan's solve time t_j [s].
        tau: times since t_j of the samples (K,) [s], K >= 1.
        dev: deviations ||x - x_plan|| (K,) [state norm].
    """

    run: str
    t0: float
    tau: np.ndarray
    dev: np.ndarray


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
    """Periods, skips and the per-bound checks of a set of runs."""

    periods: list[Period]
    skipped: int
    unmatched: int
    checks: list[BoundCheck]


def read_run(path: Path) -> RunData:
    """Reads a run directory or run.mcap.

    Raises:
        ValueError: unreadable, or without states or adopted solves.
    """
    from hmpc_cli.figures.common import resolve_run_log
    from hmpc_cli.recorder import read_log

    log_path = resolve_run_log(path)
    try:
        log = read_log(log_path)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{log_path}: cannot read the log ({exc})") from None
    infos = log.topic("/run/info")
    system = dict(((infos[0].data.get("scenario") or {}) if infos else {}).get("system") or {})
    states = log.topic("/sim/state")
    if not states:
        raise ValueError(f"{log_path}: no /sim/state")
    solves = [(float(m.data["t"]), np.asarray(m.data["t_plan"], dtype=float),
               np.atleast_2d(np.asarray(m.data["x_plan"], dtype=float)),
               np.asarray(m.data["seg_plan"], dtype=int))
              for m in log.topic("/mpc/solve") if m.data.get("adopted", True)]
    if not solves:
        raise ValueError(f"{log_path}: no adopted /mpc/solve")
    name = log_path.parent.name if log_path.name == "run.mcap" else log_path.name
    return RunData(name, system, np.array([float(m.data["t"]) for m in states]),
                   np.array([m.data["x"] for m in states], dtype=float),
                   np.array([float(m.data["t"]) for m in log.topic("/sim/event")]),
                   sorted(solves, key=lambda s: s[0]))


def _node(t_plan: np.ndarray, x_plan: np.ndarray, seg_plan: np.ndarray, t: float,
          seg: int) -> np.ndarray | None:
    """The plan's node state at time t in segment seg, or None if no node is there."""
    hit = np.flatnonzero((np.abs(t_plan - t) < TIME_TOL) & (seg_plan == seg))
    return x_plan[hit[0]] if hit.size else None


def run_periods(run: RunData) -> tuple[list[Period], int, int]:
    """The periods of one run: (periods, skipped periods, unmatched samples).

    An unmatched sample is a logged state at a node time of the plan whose domain (after
    the plant's resets) has no node there.
    """
    periods, skipped, unmatched = [], 0, 0
    for j, (t0, t_plan, x_plan, seg_plan) in enumerate(run.solves):
        nxt = run.solves[j + 1] if j + 1 < len(run.solves) else None
        t1 = nxt[0] if nxt is not None else float(run.t[-1]) + TIME_TOL
        pts = [(t, x) for t, x in zip(run.t, run.x, strict=True)
               if t0 + TIME_TOL < t < t1 - TIME_TOL]
        if nxt is not None:
            pts.append((t1, nxt[2][0]))
        taus, devs = [], []
        for t, x in pts:
            if not np.any(np.abs(t_plan - t) < TIME_TOL):
                continue
            resets = int(np.count_nonzero((run.events > t0 + TIME_TOL) &
                                          (run.events <= t + TIME_TOL)))
            node = _node(t_plan, x_plan, seg_plan, t, int(seg_plan[0]) + resets)
            if node is None:
                unmatched += 1
                continue
            taus.append(t - t0)
            devs.append(float(np.linalg.norm(np.asarray(x, dtype=float) - node)))
        if taus:
            periods.append(Period(run.name, t0, np.array(taus), np.array(devs)))
        else:
            skipped += 1
    return periods, skipped, unmatched


def check_bounds(periods: Iterable[Period],
                 bounds: Callable[[np.ndarray], dict[str, np.ndarray]]) -> list[BoundCheck]:
    """Checks each bound on the periods.

    Args:
        periods: observed periods.
        bounds: tau (K,) [s] -> bound name -> bound (K,) [state norm]; NaN where a bound
            does not hold (that sample is not checked against it).

    Returns:
        One :class:`BoundCheck` per bound name, in the order ``bounds`` first returns.
    """
    checks: dict[str, BoundCheck] = {}
    for p in periods:
        for name, b in bounds(p.tau).items():
            c = checks.setdefault(name, BoundCheck(name))
            b = np.asarray(b, dtype=float)
            ok = ~np.isnan(b)
            if not np.any(ok):
                continue
            c.periods += 1
            out = ok & (p.dev > b)
            c.inside += int(not np.any(out))
            c.violations += [Violation(name, p.run, p.t0 + float(p.tau[k]), float(p.dev[k]),
                                       float(b[k])) for k in np.flatnonzero(out)]
            k = int(np.argmax(np.where(ok, p.dev, -np.inf)))
            if p.dev[k] > 0:
                c.ratios.append(float(b[k] / p.dev[k]))
    return list(checks.values())


def reality(runs: Iterable[RunData],
            bounds: Callable[[np.ndarray], dict[str, np.ndarray]]) -> RealityReport:
    """The periods of all runs and each bound's check."""
    periods, skipped, unmatched = [], 0, 0
    for run in runs:
        p, s, u = run_periods(run)
        periods += p
        skipped += s
        unmatched += u
    return RealityReport(periods, skipped, unmatched, check_bounds(periods, bounds))
