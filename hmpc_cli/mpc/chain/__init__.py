"""The chain fixed-mode MPC: one multiple-shooting NLP over a mode schedule.

Resets, guard-hit and guard-avoid rows, the virtual pass-through node, node shifting.

May import: ``core``, ``mpc`` (builder, solver, cache, back-ends), ``tube.margins_file``.
"""
