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
#: the deepest a swing foot may dip into its lift-off ground before it clears it, still
#: on it (a scuff) [m]: deeper, the leg is driven into the ground, a trip. Set after
#: runs that dipped the swing foot 0.169 m (a fall later) and 0.10 m (counted a success)
#: so; biped_push's successes scuff at most 6.6 mm
SCUFF = 1e-2


@dataclass(frozen=True)
class ClimbStairs:
    """Falls and success judged on the simulated robot's geometry and terrain.

    A fall ends the run: the hip less than ``fall_hip_height`` above the terrain under
    it, a knee, the hip or the torso top below the terrain, or the swing foot tripped:
    more than :data:`ON_SEGMENT` inside the terrain once it has cleared it since its
    lift-off, or off the flat ground it lifted off from (where no guard stops it: a stair's
    riser, or past the stairs' end, where the terrain keeps the top's height). Before it
    clears, over the ground it lifted off from, a foot at most :data:`SCUFF` below it is
    still on it (a scuff, not a trip). Success: no fall and the stance foot on the top
    segment at the end. The reported error is |hip - goal| [m].

    :meth:`failure` follows one run step by step (it keeps the lift-off it saw last).

    Attributes:
        system: the simulated plant (its ``points_world`` output and ``terrain``).
        fall_hip_height: [m].
    """

    system: HybridSystem
    fall_hip_height: float
    _points: object = field(init=False, repr=False, compare=False)
    #: the swing foot's lift-off: (stance foot (x, y), the x range it lifted off from,
    #: whether it has cleared the terrain since) [m]
    _lift: list = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:  # judged at every simulator step: one state at a time
        object.__setattr__(self, "_points",
                           compile_evaluator(self.system.output("points_world")))
        object.__setattr__(self, "_lift", [None, (0.0, 0.0), False])

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
        return self._tripped(pts[names.index("stance_foot")], pts[names.index("swing_foot")],
                             float(ground[names.index("swing_foot")]))

    def _tripped(self, stance: np.ndarray, foot: np.ndarray, ground: float) -> str:
        """A swing foot inside the terrain off its lift-off ground, or deep in it.

        Off it: cleared since its lift-off, or moved past its ends; deep: more than
        :data:`SCUFF` below it before clearing it.
        """
        lift, depth = self._lift, ground - float(foot[1])
        if lift[0] != (float(stance[0]), float(stance[1])):  # a new stance: a lift-off
            lift[:] = [(float(stance[0]), float(stance[1])), self._ground_of(foot[0]), False]
        lift[2] = lift[2] or depth < -ON_SEGMENT
        lo, hi = lift[1]
        if depth > ON_SEGMENT and (lift[2] or not lo <= foot[0] <= hi):
            why = f"no guard there, deeper than {ON_SEGMENT * 1e3:g} mm"
        elif depth > SCUFF:
            why = (f"driven into the ground it lifted off from before clearing it, deeper "
                   f"than {SCUFF * 1e3:g} mm")
        else:  # every simulator step: no message built
            return ""
        # in mm to 0.01 mm: a depth just past either bound reads past it
        return (f"fall: the swing foot is {depth * 1e3:.2f} mm inside the terrain at x = "
                f"{foot[0]:.3f} m ({why}: it tripped)")

    def _ground_of(self, x: float) -> tuple[float, float]:
        """The x range [m] of the flat ground under x.

        Its piece (the ground before 0, a segment, past the end) and the neighbours of the
        same height.
        """
        terrain = self.system.terrain
        pieces = [(-np.inf, 0.0, terrain.ground), *terrain.segments,
                  (terrain.end, np.inf, terrain.segments[-1][2])]
        k = 0 if x <= 0.0 else len(pieces) - 1 if x > terrain.end else \
            1 + terrain.segment_at(x)
        lo = hi = k
        while lo > 0 and pieces[lo - 1][2] == pieces[k][2]:
            lo -= 1
        while hi < len(pieces) - 1 and pieces[hi + 1][2] == pieces[k][2]:
            hi += 1
        return (pieces[lo][0], pieces[hi][1])

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
