"""Figure 3 beside the authors' data, trial by trial, and why outcomes differ.

For each run of a Figure 3 sweep (results.csv with ``controller``, ``disturbance``,
``success``, ``log``) and the authors' trajectory of the same panel and trial
(:mod:`hmpc_cli.analysis.authors`): the contact sequence (ours: the log's guard events; theirs:
found in their positions), the circle-entry time (the first time |p - c| <= the circle's
radius: ours the logged circle_in event, theirs the first such sample), the end point and
success. Where the outcomes differ, the reason
is computed from the log and the data, never written by hand: whether the initial plans
differ (ours: the first accepted planner call; theirs: the contacts of their undisturbed
run in that panel), when the two paths part, the first contact that differs, and how the
failing side failed.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hmpc_cli.analysis.authors import (
    PANEL_FILES, AuthorsTrace, BallGeometry, Contact, circle_entry, contacts)
from hmpc_cli.analysis.replay import SOFTENED_TOL

__all__ = ["APART", "RunFacts", "Side", "TrialComparison", "authors_panel", "compare_sweep",
           "sequence_text"]

APART = 0.1  # [m] the two paths have parted once their positions are this far apart
DRIFT = 0.05  # [s] a contact this far from its planned time is off the plan
CONTACT_TOL = 0.030  # [s] two sides' k-th contacts match when this close in time too
_BOUNCES = ("floor", "wall")


@dataclass(frozen=True)
class Side:
    """One trajectory's contacts, circle entry [s] (None: never), end (2,) [m], success.

    Its positions: t (K,) [s], xy (K, 2) [m].
    """

    contacts: tuple[Contact, ...]
    entry: float | None
    end: np.ndarray
    success: bool
    t: np.ndarray
    xy: np.ndarray


@dataclass(frozen=True)
class RunFacts:
    """What our log says beyond the path.

    The initial plan's contacts (planned times [s]), MPC solves, softened and failed
    solves, the summary's reason, the nodes each periodic re-solve moved (``shifted``).
    """

    plan: tuple[Contact, ...]
    solves: int
    softened: int
    failed: int
    reason: str
    period_shifts: tuple[int, ...] = ()


@dataclass
class TrialComparison:
    """One trial of one panel, ours beside the authors'.

    ``ours`` None: no readable log (``note`` says why); ``theirs`` None: no authors' data
    for it; ``their_plan``: the contacts of their undisturbed run in the same panel.
    """

    panel: str
    trial: str
    ours: Side | None
    facts: RunFacts | None
    theirs: Side | None
    their_plan: tuple[Contact, ...] = ()
    note: str = ""
    geometry: Any = None  # our log's GeometryRec (guards to draw; None: none logged)
    why: str = field(init=False, default="")

    def __post_init__(self) -> None:
        """Computes ``why`` (empty unless both sides exist and their outcomes differ)."""
        self.why = _why(self)

    @property
    def same_sequence(self) -> bool | None:
        """Whether both sides hit the same guards in the same order (None: a side missing)."""
        if self.ours is None or self.theirs is None:
            return None
        return _names(self.ours.contacts) == _names(self.theirs.contacts)

    @property
    def end_gap(self) -> float | None:
        """Distance [m] between the two end points (None: a side missing)."""
        if self.ours is None or self.theirs is None:
            return None
        return float(np.hypot(*(self.ours.end - self.theirs.end)))

    @property
    def same_timed_sequence(self) -> bool | None:
        """Same guards in the same order, each within :data:`CONTACT_TOL` of theirs.

        None: a side missing.
        """
        if not self.same_sequence:
            return self.same_sequence
        return all(abs(a.t - b.t) <= CONTACT_TOL
                   for a, b in zip(self.ours.contacts, self.theirs.contacts, strict=True))

    @property
    def path_deviation(self) -> tuple[float, float] | None:
        """(max, RMS) [m] of the paths' distance at the authors' sample times.

        Ours interpolated, where both runs exist; None: a side missing or no overlap.
        """
        if self.ours is None or self.theirs is None:
            return None
        return path_deviation(self.ours, self.theirs)

    @property
    def apart_at(self) -> float | None:
        """First time [s] the paths are :data:`APART` apart (None: never, or a side missing)."""
        if self.ours is None or self.theirs is None:
            return None
        return _apart(self.ours, self.theirs)

    @property
    def first_difference(self) -> str:
        """The first contact that differs, as text ('' if the sequences agree)."""
        if self.ours is None or self.theirs is None:
            return ""
        return _first_difference(self.ours.contacts, self.theirs.contacts)


def _names(cs: Sequence[Contact]) -> list[str]:
    return [c.guard for c in cs]


def sequence_text(cs: Sequence[Contact]) -> str:
    """Guard names in order, repeats folded: ``floor, wall, floor x2, circle_in``."""
    out: list[list] = []
    for c in cs:
        if out and out[-1][0] == c.guard:
            out[-1][1] += 1
        else:
            out.append([c.guard, 1])
    return ", ".join(g if n == 1 else f"{g} x{n}" for g, n in out) or "none"


def _apart(a: Side, b: Side) -> float | None:
    """First time [s] on b's grid where a's interpolated path is APART from b's."""
    t = b.t[(b.t >= a.t[0]) & (b.t <= a.t[-1])]
    if not len(t):
        return None
    pa = np.column_stack([np.interp(t, a.t, a.xy[:, i]) for i in range(2)])
    pb = np.column_stack([np.interp(t, b.t, b.xy[:, i]) for i in range(2)])
    far = np.flatnonzero(np.hypot(*(pa - pb).T) > APART)
    return float(t[far[0]]) if far.size else None


def path_deviation(ours: Side, theirs: Side) -> tuple[float, float] | None:
    """(max, RMS) [m] of |ours(t) - theirs(t)| over the authors' times t inside both runs."""
    keep = (theirs.t >= ours.t[0]) & (theirs.t <= ours.t[-1])
    t = theirs.t[keep]
    if not len(t):
        return None
    pa = np.column_stack([np.interp(t, ours.t, ours.xy[:, i]) for i in range(2)])
    d = np.hypot(*(pa - theirs.xy[keep]).T)
    d = d[np.isfinite(d)]
    if not len(d):
        return None
    return float(d.max()), float(np.sqrt(np.mean(d ** 2)))


def _first_difference(ours: Sequence[Contact], theirs: Sequence[Contact]) -> str:
    for k in range(max(len(ours), len(theirs))):
        a = ours[k] if k < len(ours) else None
        b = theirs[k] if k < len(theirs) else None
        if a is not None and b is not None and a.guard == b.guard:
            continue
        sa = f"{a.guard} at {a.t:.2f} s" if a else "none"
        sb = f"{b.guard} at {b.t:.2f} s" if b else "none"
        return f"contact {k + 1}: ours {sa}, theirs {sb}"
    return ""


def _tail(side: Side, window: float = 1.0) -> int:
    """Floor and wall contacts in the side's last ``window`` seconds."""
    return sum(1 for c in side.contacts if c.guard in _BOUNCES and c.t >= side.t[-1] - window)


def _failure(who: str, side: Side, centre: Sequence[float], facts: RunFacts | None) -> str:
    """How one failing side failed (from its contacts, end point and, for ours, the log)."""
    d = math.hypot(side.end[0] - centre[0], side.end[1] - centre[1])
    outs = [c.t for c in side.contacts if c.guard == "circle_out"]
    if side.entry is None:
        how = "never entered the circle"
    elif outs:
        how = f"entered at {side.entry:.2f} s, left at {outs[-1]:.2f} s"
    else:
        how = f"entered at {side.entry:.2f} s"
    n = _tail(side)
    text = (f"{who} {how}, {n} floor/wall contact{'' if n == 1 else 's'} in the last second, "
            f"ends {d:.2f} m from the centre")
    if facts is not None:
        text += (f" ({facts.softened} of {facts.solves} solves softened, {facts.failed} "
                 f"failed; {facts.reason})")
    return text


def _drift(cs: Sequence[Contact], plan: Sequence[Contact], whose: str) -> str:
    """The first contact off ``plan``: another guard, or more than :data:`DRIFT` off its time."""
    for k, (c, p) in enumerate(zip(cs, plan, strict=False)):
        if c.guard != p.guard:
            return (f"its contact {k + 1} was {c.guard} at {c.t:.2f} s where {whose} had "
                    f"{p.guard} at {p.t:.2f} s")
        if abs(c.t - p.t) > DRIFT:
            return (f"its contact {k + 1} ({c.guard}) came at {c.t:.2f} s, {c.t - p.t:+.2f} s "
                    f"off {whose} ({p.t:.2f} s)")
    if len(cs) < len(plan):
        p = plan[len(cs)]
        return f"{whose}'s contact {len(cs) + 1} ({p.guard} at {p.t:.2f} s) never came"
    return ""


def _plans(facts: RunFacts, their_plan: Sequence[Contact]) -> str:
    """The initial plans compared: same guard sequence, or how they differ."""
    if not facts.plan:
        return "no accepted plan in our log"
    if not their_plan:
        return ""
    ours = f"{len(facts.plan)} contacts, last at {facts.plan[-1].t:.2f} s"
    theirs = f"{len(their_plan)} contacts, last at {their_plan[-1].t:.2f} s"
    if _names(facts.plan) == _names(their_plan):
        return f"same planned sequence (ours {ours}; theirs {theirs})"
    return f"plans differ (ours: {sequence_text(facts.plan)}, {ours}; theirs: " \
           f"{sequence_text(their_plan)}, {theirs})"


def _why(c: TrialComparison) -> str:
    """Why the outcomes differ ('' if they agree or a side is missing); computed."""
    if c.ours is None or c.theirs is None or c.ours.success == c.theirs.success:
        return ""
    centre = BallGeometry().centre
    parts = [_plans(c.facts, c.their_plan)] if c.facts is not None else []
    apart = c.apart_at
    parts.append(f"paths {APART:g} m apart from {apart:.2f} s" if apart is not None
                 else f"paths never {APART:g} m apart")
    if c.first_difference:
        parts.append(c.first_difference)
    plans = (c.facts.plan if c.facts else (), "our plan"), (c.their_plan, "their undisturbed run")
    for (who, side, facts), (plan, whose) in zip(
            (("ours", c.ours, c.facts), ("theirs", c.theirs, None)), plans, strict=True):
        if not side.success:
            parts.append(_failure(who, side, centre, facts))
            parts.append(_drift(side.contacts, plan, whose))
    return "; ".join(p for p in parts if p)


def _natural(text: str) -> list:
    """Sort key: nominal first, then trial 1, 2, ..., 10."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t)
            for t in re.split(r"(\d+)", "" if text == "nominal" else text)]


def _panel_key(panel: str) -> tuple[int, str]:
    """Sort key: the paper's panels in the paper's order, then the rest by name."""
    key = authors_panel(panel, list(PANEL_FILES))
    return (list(PANEL_FILES).index(key) if key else len(PANEL_FILES), panel)


def authors_panel(panel: str, available: Sequence[str]) -> str | None:
    """The authors' panel for one of ours: the longest available label ours starts with."""
    hits = [a for a in available if panel == a or panel.startswith(a + ",")
            or panel.startswith(a + " ")]
    return max(hits, key=len) if hits else None


def _our_side(run, success: bool, geo: BallGeometry) -> tuple[Side, RunFacts]:
    """Our side and the log's facts, from a run read by ``read_run``."""
    from hmpc_cli.analysis.tables import trace_of

    trace = trace_of(run, run.path)
    entry = next((e.t for e in run.events if e.guard_name == "circle_in"), None)
    side = Side(tuple(Contact(e.t, e.guard_name) for e in run.events),
                entry if entry is not None else circle_entry(trace.t, trace.xy, geo),
                trace.xy[-1].copy(), success, trace.t, trace.xy)
    plan: tuple[Contact, ...] = ()
    first = next((p for p in run.planner if p.accepted and p.schedule), None)
    if first is not None:
        times = float(first.schedule.t0) + np.cumsum(first.schedule.durations)
        plan = tuple(Contact(float(t), str(g)) for t, g in
                     zip(times, first.schedule.guard_names, strict=False))
    shifted = [k for s in run.solves if s.reason == "period"
               and (k := getattr(s.detail, "shifted", None)) is not None]
    if not run.solves:  # a trajectory log: the shifts are in its metadata
        from hmpc_cli.log.trace import period_shifts

        shifted = list(period_shifts(run.path))
    sm = run.summary  # the books' counts: the same from a run log and its trajectory log
    facts = RunFacts(plan, sm.solves if sm else len(run.solves),
                     sm.softened_solves if sm else sum(
                         1 for s in run.solves if s.success and s.slack > SOFTENED_TOL),
                     sm.solver_failures if sm else sum(1 for s in run.solves if not s.success),
                     sm.reason if sm is not None else "unfinished",
                     tuple(int(k) for k in shifted))
    return side, facts


def _their_side(trace: AuthorsTrace, geo: BallGeometry, radius: float) -> Side:
    """Their side; success = end within ``radius`` [m] of the centre, as in the paper."""
    end = trace.xy[-1].copy()
    ok = math.hypot(end[0] - geo.centre[0], end[1] - geo.centre[1]) <= radius
    return Side(tuple(contacts(trace.t, trace.xy, geo)), circle_entry(trace.t, trace.xy, geo),
                end, ok, trace.t, trace.xy)


def compare_sweep(table: Path, authors: Mapping[str, Mapping[str, AuthorsTrace]]
                  ) -> list[TrialComparison]:
    """Every run of a Figure 3 sweep table beside the authors' same panel and trial.

    Rows come in the panels' order of first appearance, nominal first, then trial 1..10.

    Raises:
        FigureInputError: the table is missing, empty or lacks a column.
    """
    from hmpc_cli.analysis.tables import FigureInputError, parse_bool, read_table, resolve_log
    from hmpc_cli.log.rundata import read_run

    rows = read_table(table, ["controller", "disturbance", "success", "log"])
    order = sorted(dict.fromkeys(r["controller"].strip() for r in rows), key=_panel_key)
    rows.sort(key=lambda r: (order.index(r["controller"].strip()),
                             _natural(r["disturbance"].strip())))
    out = []
    for line, row in enumerate(rows, start=2):
        panel, trial = row["controller"].strip(), row["disturbance"].strip()
        key = authors_panel(panel, list(authors))
        geo, ours, facts, note, radius, drawing = BallGeometry(), None, None, "", None, None
        try:
            run = read_run(resolve_log(table, row["log"], f"{table}:{line}"))
            geo, drawing = BallGeometry.from_params(run.system), run.geometry
            radius = run.system.get("success_radius")
            ours, facts = _our_side(run, parse_bool(row["success"], f"{table}:{line}"), geo)
        except (FigureInputError, ValueError) as exc:
            note = f"no readable log: {exc}"
        radius = float(radius or geo.circle_radius)
        data = authors.get(key, {}) if key else {}
        theirs = _their_side(data[trial], geo, radius) if trial in data else None
        their_plan = tuple(contacts(data["nominal"].t, data["nominal"].xy, geo)) \
            if "nominal" in data else ()
        out.append(TrialComparison(panel, trial, ours, facts, theirs, their_plan, note,
                                   drawing))
    return out
