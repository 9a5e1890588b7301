"""``python -m hmpc_cli``: the ``hmpc`` command line."""

from hmpc_cli.cli.app import main

main()
