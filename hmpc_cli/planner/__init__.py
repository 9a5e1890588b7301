"""The hybrid MPC layer: mode schedules by cross-entropy, footholds, fixed schedules.

May import: ``core``, ``sim`` (the simulator and rollout kernel it plans with). A peer of
``mpc``, ``lowlevel``, ``tube`` and ``log``: never imports them.
"""
