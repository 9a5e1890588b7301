"""Field types shared by every settings model of a scenario: strict and finite.

Booleans and strings are not numbers (``duration = true`` and ``rate_hz = "600"`` are
errors, an integer is a valid float), NaN and infinities are rejected, and no value may
exceed :data:`MAX_FLOAT` / :data:`MAX_INT` in magnitude (beyond them a setting is a typo
or an overflow waiting to happen). Fields that need tighter bounds add their own.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, AllowInfNan, Strict, StrictBool

#: largest magnitude of a float setting
MAX_FLOAT = 1e9
#: largest integer setting
MAX_INT = 10**9


def magnitude_problem(v: float) -> str | None:
    """Why a finite number is too large for a setting; None if it is not.

    An integer is checked against :data:`MAX_INT`, a float against :data:`MAX_FLOAT` (the
    bound of :data:`BoundedInt` and :data:`FiniteFloat`).
    """
    if isinstance(v, int) and abs(v) > MAX_INT:
        return f"{v} exceeds the largest allowed magnitude {MAX_INT:g}"
    if isinstance(v, float) and abs(v) > MAX_FLOAT:
        return f"{v:g} exceeds the largest allowed magnitude {MAX_FLOAT:g}"
    return None


def _float_magnitude(v: float) -> float:
    why = magnitude_problem(v)
    if why is not None:
        raise ValueError(why)
    return v


def _int_magnitude(v: int) -> int:
    why = magnitude_problem(v)
    if why is not None:
        raise ValueError(why)
    return v


class _MagnitudeInSchema:
    """The magnitude bound in a field's JSON Schema: ``minimum`` and ``maximum``.

    Only on a side where the field sets no bound of its own (its Field(ge=...) wins).
    """

    def __init__(self, bound: float) -> None:
        self.bound = bound

    def __get_pydantic_json_schema__(self, core_schema, handler):
        schema = handler(core_schema)
        schema.setdefault("minimum", -self.bound)
        schema.setdefault("maximum", self.bound)
        return schema


# (a validator, not ge/le: a field's own Field(ge=...) must keep its bound)
FiniteFloat = Annotated[float, Strict(), AllowInfNan(False), AfterValidator(_float_magnitude),
                        _MagnitudeInSchema(MAX_FLOAT)]
BoundedInt = Annotated[int, Strict(), AfterValidator(_int_magnitude), _MagnitudeInSchema(MAX_INT)]
#: a finite float without the magnitude bound (a threshold where "huge" means "never")
LargeFloat = Annotated[float, Strict(), AllowInfNan(False)]

#: most nodes of one NLP: IPOPT and CasADi's expression graphs grow with them (a ball
#: NLP of 180 nodes solves in milliseconds; 20 000 nodes is minutes per solve)
MAX_NLP_NODES = 20_000


def memory_limit() -> int:
    """Bytes one array of a run may take: half this machine's physical memory."""
    import os

    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):  # pragma: no cover (not POSIX)
        return 4 * 1024**3


def gib(n: float) -> str:
    """Bytes as GiB text."""
    return f"{n / 1024**3:.3g} GiB"


def duration_text(secs: float) -> str:
    """A duration for a size message: seconds, minutes, hours or days (3 digits)."""
    for unit, size in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if secs >= size:
            return f"{secs / size:.3g} {unit}"
    return f"{secs:.3g} s"


def nlp_estimate(nodes: float, mib_per_node: float, ms_per_node: float,
                 per: str = "node") -> str:
    """What building an NLP of ``nodes`` nodes would take, as message text.

    Args:
        nodes: NLP nodes asked for (or other units of ``per``).
        mib_per_node: measured memory per node [MiB] (the NLP's graphs and solvers).
        ms_per_node: measured build time per node [ms] (on a 2-core machine).
        per: the unit counted (``node``, ``switch``).
    """
    mem = nodes * mib_per_node * 1024**2
    secs = nodes * ms_per_node / 1e3
    when = f"{secs / 3600:.3g} h" if secs >= 3600 else f"{secs / 60:.3g} min"
    return (f"about {gib(mem)} of memory (this machine: {gib(2 * memory_limit())}) and "
            f"{when} to build, at {mib_per_node:g} MiB and {ms_per_node:g} ms per {per}")


#: a pair of finite floats (bounds, positions)
Pair = tuple[FiniteFloat, FiniteFloat]

__all__ = ["MAX_FLOAT", "MAX_INT", "MAX_NLP_NODES", "BoundedInt", "FiniteFloat", "LargeFloat",
           "Pair", "StrictBool", "duration_text", "gib", "magnitude_problem", "memory_limit",
           "nlp_estimate"]
