"""System plug-ins bundled with hmpc: the ball (:mod:`.ball`) and the biped (:mod:`.biped`).

Each registers a :class:`hmpc_cli.core.registry.SystemSpec` through the ``hmpc.systems`` entry
point group (see ``pyproject.toml``), exactly as a user's package does; nothing outside
this package names them. See the README's plug-in guide.
"""
