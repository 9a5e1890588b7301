"""The scenario's JSON Schema, as editors and standard validators read it.

Pydantic's schema of :func:`hmpc_cli.run.scenario.scenario_model`, made to accept every
file hmpc accepts and to state its bounds in standard keywords:

* a plug-in union (``system``, ``planner``, ``mpc``) is an ``anyOf``, not a ``oneOf``: a
  table without its tag takes the system's default kind, which JSON Schema cannot say,
  so ``[mpc] rate_hz = 20`` is valid under both MPC kinds; a tag that is given still
  selects its member (each member's tag is a ``const``);
* a bound on an optional number (pydantic writes ``gt``/``ge``/``lt``/``le`` there) is
  written as ``exclusiveMinimum``/``minimum``/``exclusiveMaximum``/``maximum``.

``hmpc schema`` prints it; ``scenarios/scenario.schema.json`` holds it.
"""

from __future__ import annotations

from typing import Any

__all__ = ["scenario_json_schema", "standard_schema"]

#: pydantic's bound keys on a nested number -> JSON Schema's
_BOUNDS = {"gt": "exclusiveMinimum", "ge": "minimum", "lt": "exclusiveMaximum",
           "le": "maximum"}


def scenario_json_schema() -> dict[str, Any]:
    """The scenario JSON Schema (Draft 2020-12) with the registered plug-ins' sections."""
    from hmpc_cli.run.scenario import scenario_model

    return standard_schema(scenario_model().model_json_schema())


def standard_schema(node: Any) -> Any:
    """A pydantic JSON Schema (or a part) in the standard form this module describes.

    Plug-in unions become ``anyOf``, bounds standard keywords; of an inclusive and an
    exclusive bound on one side (a field's ``> 0`` beside the magnitude's ``>= -1e9``)
    the tighter is kept.
    """
    if isinstance(node, list):
        return [standard_schema(v) for v in node]
    if not isinstance(node, dict):
        return node
    out = {k: standard_schema(v) for k, v in node.items()}
    if "discriminator" in out and "oneOf" in out:
        out["anyOf"] = out.pop("oneOf")
    for short, keyword in _BOUNDS.items():
        if short in out and out.get("type") in ("number", "integer"):
            value = out.pop(short)
            if keyword in out:  # the magnitude bound beside the field's own: the tighter
                value = max(value, out[keyword]) if short[0] == "g" else min(value, out[keyword])
            out[keyword] = value
    for inclusive, exclusive, tighter in (("minimum", "exclusiveMinimum", max),
                                          ("maximum", "exclusiveMaximum", min)):
        if inclusive in out and exclusive in out:  # e.g. > 0 beside the magnitude's >= -1e9
            if tighter(out[inclusive], out[exclusive]) == out[exclusive]:
                del out[inclusive]
            else:
                del out[exclusive]
    return out
