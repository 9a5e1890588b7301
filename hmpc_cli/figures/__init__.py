"""Paper figures drawn from recorded runs (sweep tables and MCAP logs); never runs a controller."""

from __future__ import annotations

__all__ = ["FIGURES"]

# Figure name -> what it shows (the drawing modules import matplotlib, so they load lazily).
FIGURES: dict[str, str] = {
    "fig2": "the virtual pass-through node of one logged MPC plan and its tube discs",
    "fig3": "bouncing ball under disturbances, one panel per controller",
    "robustness": "success rate vs MPC rate per replanning policy and disturbance size",
    "fig4": "biped on the stairs: stick figures, hip x(t), y(t), torso force (+ GIF)",
    "timing": "one run's MPC solves: compute time against the MPC period, contacts",
}
