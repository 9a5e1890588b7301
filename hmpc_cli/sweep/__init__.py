"""Parameter sweeps: plan, execution (local pool or Dask), output lock, results table.

May import: ``core``, ``run``, ``log``.
"""
