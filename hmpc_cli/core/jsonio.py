"""Strict JSON for every file hmpc writes: NaN and +-inf become null (RFC 8259 has neither)."""

from __future__ import annotations

import json
import math
from typing import Any

from hmpc_cli.core.text import printable

__all__ = ["dumps", "finite"]


def finite(value: Any) -> Any:
    """``value`` with non-finite floats replaced by None, recursively.

    Dicts, lists and tuples are walked; NumPy scalars and arrays become Python values;
    text is :func:`~hmpc_cli.core.text.printable`.
    """
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, str):
        return printable(value)  # a path's bytes that are not UTF-8 as \\xNN
    if isinstance(value, dict):
        return {printable(k) if isinstance(k, str) else k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    tolist = getattr(value, "tolist", None)  # NumPy scalars and arrays
    if callable(tolist) and type(value).__module__ == "numpy":
        return finite(tolist())
    return value


def dumps(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`finite` (value) with ``allow_nan=False``."""
    return json.dumps(finite(value), allow_nan=False, **kwargs)
