"""The plant's physics: simulator, disturbance processes w(t), compiled rollout kernel.

The fixed-step hybrid simulator (:mod:`.simulator`), the disturbance processes
(:mod:`.disturbance`) and the C batch rollout that the sampling planner flies (:mod:`.rollout`).

May import: ``core``.
"""
