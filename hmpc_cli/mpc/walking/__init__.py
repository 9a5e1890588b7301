"""The walking MPC of the biped: a one-step NLP per foothold candidate.

May import: ``core``, ``mpc`` (builder, solver, cache) and ``mpc.chain.kind`` (the shared kind
helpers).
"""
