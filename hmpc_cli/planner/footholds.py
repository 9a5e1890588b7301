"""The biped's hybrid planner: which stair segment the next swing lands on (Step 3).

The hybrid problem of the walking example is a choice among few footholds: at the start
and after each contact the fixed-mode walking MPC is solved once per candidate segment
and the best solution is kept (the reference: the largest final hip x). This module
holds the pure logic: candidate enumeration and selection. It never solves anything.

Segments are the (start, end, height) triples of
:func:`hmpc_cli.systems.biped.stair_edges`, indexed from 0 (segment i is guard
``stair_{i+1}``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from hmpc_cli.messages import Plan

Segment = tuple[float, float, float]


class FootholdSettings(BaseModel):
    """Candidate enumeration and selection settings."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["footholds"] = Field("footholds", description="foothold candidates (biped)")
    reach: float = Field(0.45, gt=0.0, description="a segment is a candidate if one of "
                         "its ends lies within this of the stance foot [m]")
    include_current: bool = Field(True, description="the segment under the stance foot "
                                  "is always a candidate")
    ahead_only: bool = Field(True, description="drop segments that end at or behind "
                             "the stance foot")
    criterion: Literal["max_hip_x", "min_cost"] = Field(
        "max_hip_x", description="max_hip_x: largest final hip x (reference); min_cost: "
                                 "lowest MPC cost")


def candidates(stance_x: float, segments: Sequence[Segment],
               settings: FootholdSettings | None = None) -> list[int]:
    """Indices of the candidate segments for a swing from stance-foot x, ascending.

    A segment qualifies if min(|x - start|, |x - end|) <= reach (the reference rule), or
    if it holds the stance foot (``include_current``); with ``ahead_only`` a segment
    ending at or behind x never qualifies.

    Raises:
        ValueError: no segment qualifies (e.g. the foot is beyond the stairs' end).
    """
    s = settings or FootholdSettings()
    out = []
    for i, (start, end, _) in enumerate(segments):
        if s.ahead_only and end <= stance_x:
            continue
        near = min(abs(stance_x - start), abs(stance_x - end)) <= s.reach
        under = s.include_current and start <= stance_x <= end
        if near or under:
            out.append(i)
    if not out:
        ends = f"[{segments[0][0]:g}, {segments[-1][1]:g}]" if segments else "(none)"
        raise ValueError(f"no foothold candidate within reach {s.reach:g} m of the stance "
                         f"foot at x = {stance_x:.4f} m (stairs span {ends})")
    return out


def choose(plans: Sequence[Plan | None], settings: FootholdSettings | None = None
           ) -> int | None:
    """Index of the best successful plan in ``plans``, or None if every one failed.

    ``max_hip_x`` reads ``plan.extra["final_hip"][0]`` (the plan's last hip x in the
    world [m]); ``min_cost`` reads ``plan.stats.cost``. Ties keep the first. None tells
    the caller to keep its previous plan.
    """
    s = settings or FootholdSettings()
    best, best_score = None, None
    for i, plan in enumerate(plans):
        if plan is None or not plan.stats.success:
            continue
        if s.criterion == "max_hip_x":
            score = float(plan.extra["final_hip"][0])
        else:
            score = -float(plan.stats.cost)
        if best_score is None or score > best_score:
            best, best_score = i, score
    return best
