"""Words for messages: the closest choice ("did you mean ...?"), text UTF-8 can encode."""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from typing import Any

__all__ = ["closest", "did_you_mean", "printable"]


def closest(name: Any, choices: Sequence[str]) -> str | None:
    """The choice that is ``name`` in another case, else the nearest spelling, else None."""
    same = [c for c in choices if c.casefold() == str(name).casefold()]
    near = same or difflib.get_close_matches(str(name), list(choices), n=1)
    return near[0] if near else None


def did_you_mean(name: Any, choices: Sequence[str]) -> str:
    """`` (did you mean 'x'?)`` for :func:`closest` of ``name`` in ``choices``, else ''."""
    near = closest(name, choices)
    return f" (did you mean {near!r}?)" if near is not None else ""


def printable(text: str) -> str:
    r"""``text`` as UTF-8 can encode it: bytes that are not UTF-8 as ``\xNN``.

    Python keeps such bytes of a path or an argument as surrogate escapes, which no
    UTF-8 file can hold (another lone surrogate comes out as ``\uNNNN``); other text
    comes back unchanged.
    """
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        try:
            return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
        except UnicodeEncodeError:  # a lone surrogate no byte stands for: \uNNNN
            return text.encode("utf-8", "backslashreplace").decode("utf-8")
    return text
