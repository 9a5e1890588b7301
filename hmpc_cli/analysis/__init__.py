"""What recorded runs say: replay, export, pass-through, tubes vs reality, the authors.

Replay and export of a log, the pass-through node of a logged plan, tubes held against
reality, the authors' Figure 3 data and the trial-by-trial comparison, sweep tables.

May import: ``core``, ``tube``, ``log``, ``run`` (to re-run a logged scenario), ``sweep``.
"""
