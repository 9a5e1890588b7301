"""The hybrid vocabulary at the bottom of the house: what every other package speaks.

Definition 1 (:mod:`.hybrid`), the messages the layers hand each other (:mod:`.messages`), the
stack contract (:mod:`.stack`), the plug-in registries (:mod:`.registry`), the walker
capability (:mod:`.walker`), tasks, drawings, settings field types, strict JSON, stop
signals and the compiled-code cache helpers.

May import: nothing of hmpc_cli outside ``core``.
"""
