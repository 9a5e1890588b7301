"""Strict JSON for every file hmpc writes: NaN and +-inf become null (RFC 8259 has neither)."""

from __future__ import annotations

import json
import math
from typing import Any

__all__ = ["dumps", "finite"]


def finite(value: Any) -> Any:
    """``value`` with non-finite floats replaced by None, recursively.

    Dicts, lists and tuples are walked; NumPy scalars and arrays become Python values.
    """
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    tolist = getattr(value, "tolist", None)  # NumPy scalars and arrays
    if callable(tolist) and type(value).__module__ == "numpy":
        return finite(tolist())
    return value


def dumps(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`finite` (value) with ``allow_nan=False``."""
    return json.dumps(finite(value), allow_nan=False, **kwargs)
