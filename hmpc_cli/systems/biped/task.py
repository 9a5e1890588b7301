"""The walking task: climb to the top segment without falling (paper Fig. 4)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem
from hmpc_cli.core.numeric import compile_evaluator
from hmpc_cli.core.stack import Verdict

#: body points that must stay above the terrain (a knee, the hip or the torso top down
#: is a fall)
BODY = ("stance_knee", "hip", "torso_top", "swing_knee")
#: a stance foot this close to a segment's height stands on it [m] (a touchdown is located
#: on the guard's near side, within the event tolerance: |foot velocity| x
#: sim.event_time_tol, at most 1e-3 of a step)
ON_SEGMENT = 1e-3


@dataclass(frozen=True)
class ClimbStairs:
    """Falls and success judged on the simulated robot's geometry and terrain.

    A fall ends the run: the hip less than ``fall_hip_height`` above the terrain under
    it, a knee, the hip or the torso top below the terrain, or the swing foot more than
    :data:`ON_SEGMENT` below it (where no guard stops it: a stair's riser, or past the
    stairs' end, where the terrain keeps the top's height). Success: no fall and the
    stance foot on the top segment at the end. The reported error is |hip - goal| [m].

    Attributes:
        system: the simulated plant (its ``points_world`` output and ``terrain``).
        fall_hip_height: [m].
    """

    system: HybridSystem
    fall_hip_height: float
    _points: object = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:  # judged at every simulator step: one state at a time
        object.__setattr__(self, "_points",
                           compile_evaluator(self.system.output("points_world")))

    @property
    def goal(self) -> np.ndarray:
        """The hip target in the world [m]."""
        return self.system.goal

    def _world_points(self, x: np.ndarray) -> np.ndarray:
        return self._points(np.asarray(x, dtype=float)[None])[0].reshape(-1, 2)

    def failure(self, x: np.ndarray, mode: int) -> str:
        """A fall, or '' (see the class docstring)."""
        names = self.system.point_names
        pts = self._world_points(x)
        ground = self.system.terrain.profile(pts[:, 0])
        hip = names.index("hip")
        gap = pts[hip, 1] - ground[hip]
        if gap < self.fall_hip_height:
            return f"fall: hip {gap:.3f} m above the terrain (< {self.fall_hip_height} m)"
        for name in BODY:
            k = names.index(name)
            if pts[k, 1] < ground[k]:
                return f"fall: {name} touched the ground at x = {pts[k, 0]:.3f} m"
        k = names.index("swing_foot")
        depth = ground[k] - pts[k, 1]
        if depth > ON_SEGMENT:
            return (f"fall: the swing foot is {depth:.3f} m inside the terrain at x = "
                    f"{pts[k, 0]:.3f} m (no guard there: it tripped)")
        return ""

    def verdict(self, x: np.ndarray, mode: int) -> Verdict:
        """Success iff the stance foot stands on the top segment.

        On it: within its x range and at its height (to :data:`ON_SEGMENT` m).
        """
        err = float(self.system.numeric.goal_error(x)) if np.all(np.isfinite(x)) else \
            float("nan")
        foot_x, foot_y = (float(v) for v in self.system.numeric.output("stance_foot")(x)[0])
        start, end, top = self.system.terrain.segments[-1]
        if start <= foot_x <= end and abs(foot_y - top) <= ON_SEGMENT:
            return Verdict(True, err, "success")
        return Verdict(False, err, f"stance foot at ({foot_x:.3f}, {foot_y:.3f}) m is not on "
                                   f"the top segment [{start:g}, {end:g}] at height {top:g}")
