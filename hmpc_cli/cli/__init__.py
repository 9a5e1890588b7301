"""The ``hmpc`` command line (Typer): argument handling only, one module per command.

Heavy imports stay inside the commands, so ``hmpc --help`` loads neither CasADi nor
matplotlib.

May import: everything.
"""
