"""The fixed-mode MPC layer: NLP builder, solver back-ends, build cache and the MPC kinds.

The chain MPC of problems (12)/(14) is :mod:`.chain`, the biped's walking MPC :mod:`.walking`.

May import: ``core``, ``tube.margins_file`` (the constraint margins it is handed). A peer of
``planner``, ``lowlevel``, ``log`` and the rest of ``tube``: never imports them.
"""
