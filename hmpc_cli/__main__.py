"""``python -m hmpc_cli``: the ``hmpc`` command line."""

from hmpc_cli.cli import main

main()
