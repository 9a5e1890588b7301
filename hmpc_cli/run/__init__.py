"""One closed-loop run: scenario, set-up checks, plant, closed loop and runner.

The scenario (the only reader of a Scenario file), the set-up checks, the plant, the closed
loop composing the stack, and the runner that puts a run on disk.

May import: ``core``, ``sim``, ``lowlevel``, ``planner``, ``mpc``, ``tube``, ``log``; never a
system plug-in (those come through the registry).
"""
