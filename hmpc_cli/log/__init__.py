"""The run log: topic types, schemas, the MCAP recorder and reader, books and scene.

Topic types (:mod:`.topics`) and their generated schemas (:mod:`.schema`), the MCAP recorder
and reader (:mod:`.recorder`), the run's books (:mod:`.runlog`), geometry, scene, live
stream and :func:`.rundata.read_run`.

May import: ``core``. A peer of ``planner``, ``mpc``, ``lowlevel`` and ``tube``.
"""
