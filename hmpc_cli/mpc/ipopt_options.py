"""IPOPT's own options, read from IPOPT: names, kinds and allowed values.

IPOPT refuses a misspelt option or a value of the wrong kind with "No such IPOPT option:
max_iterr" or 'Assertion "is_int()" failed: type mismatch' (not naming the option); hmpc's
error names the option, the value and a suggestion from this catalogue instead. The
catalogue is IPOPT's ``print_options_documentation`` output of the installed build, read
once per process in a child process (IPOPT prints it on the C stdout).
"""

from __future__ import annotations

import difflib
import re
import subprocess
import sys
from dataclasses import dataclass
from functools import lru_cache

__all__ = ["IpoptOption", "catalogue", "listing", "problems"]

_CHILD = """
import casadi as ca
x = ca.SX.sym("x")
ca.nlpsol("s", "ipopt", {"x": x, "f": x ** 2},
          {"ipopt": {"print_options_documentation": "yes", "print_advanced_options": "yes"},
           "print_time": False})(x0=1.0)
"""
#: an option's first line: a number's range and default, or a string's default (a name of
#: 39 characters or more touches its default: ``constraint_violation_norm_type("1-norm")``)
_NUMBER = re.compile(r"^(\w+) +(\S+) +(<=?) +\(\s*\S+\) +(<=?) +(\S+)\s*$")
_STRING = re.compile(r'^(\w+) *\("(.*)"\)\s*$')
_VALUE = re.compile(r"^ {4}- (\S+)")


@dataclass(frozen=True)
class IpoptOption:
    """One IPOPT option.

    Attributes:
        name: the option's name.
        kind: ``"number"`` (an integer or a real: IPOPT's listing does not tell them
            apart) or ``"string"``.
        values: a string option's allowed values (``()``: any string).
        bounds: a number option's range as IPOPT prints it, e.g. ``("0", "<", "<", "+inf")``
            for 0 < value < +inf (``()``: a string option).
    """

    name: str
    kind: str
    values: tuple[str, ...] = ()
    bounds: tuple[str, str, str, str] | tuple[()] = ()

    def out_of_range(self, value: float) -> str | None:
        """``lo < name <= hi`` as IPOPT prints it if ``value`` lies outside, else None."""
        if not self.bounds:
            return None
        lo, op_lo, op_hi, hi = self.bounds
        low, high = float(lo), float(hi)
        inside = ((low < value if op_lo == "<" else low <= value)
                  and (value < high if op_hi == "<" else value <= high))
        return None if inside else f"{lo} {op_lo} {self.name} {op_hi} {hi}"


def _parse(text: str) -> dict[str, IpoptOption]:
    """The options of an IPOPT ``print_options_documentation`` listing, by name."""
    out: dict[str, IpoptOption] = {}
    current: str | None = None
    for line in text.splitlines():
        if m := _NUMBER.match(line):
            name, lo, op_lo, op_hi, hi = m.groups()
            out[name], current = IpoptOption(name, "number", bounds=(lo, op_lo, op_hi, hi)), None
        elif m := _STRING.match(line):
            current = m.group(1)
            out[current] = IpoptOption(current, "string")
        elif line[:1] not in ("", " "):  # a line of no option's (a section's title)
            current = None
        elif (current is not None and (m := _VALUE.match(line)) and m.group(1) != "*"
              and m.group(1) not in out[current].values):
            opt = out[current]
            out[current] = IpoptOption(opt.name, opt.kind, (*opt.values, m.group(1)))
    return out


def listing() -> str:
    """The installed IPOPT's ``print_options_documentation`` text ("" if it cannot run).

    The text ends where IPOPT's banner of the solve that printed it begins.
    """
    try:
        proc = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True,
                              text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return ""
    return proc.stdout.split("\n*****", 1)[0]


@lru_cache(maxsize=1)
def catalogue() -> dict[str, IpoptOption]:
    """The installed IPOPT's options by name ({} if the listing cannot be read)."""
    return _parse(listing())


def problems(options: dict, key: str) -> list[str]:
    """``key.name: reason`` for each option IPOPT does not have or cannot take.

    Args:
        options: an ``ipopt`` section (option name -> value as given).
        key: the section's key path, e.g. ``mpc.solver_options.ipopt``.
    """
    known = catalogue()
    if not known:
        return []
    lines = []
    for name, value in options.items():
        opt = known.get(name)
        if opt is None:
            near = difflib.get_close_matches(name, known, n=1)
            hint = f"did you mean {near[0]!r}?" if near else "IPOPT's options: " \
                "https://coin-or.github.io/Ipopt/OPTIONS.html"
            lines.append(f"{key}.{name}: IPOPT has no option {name!r} ({hint})")
        elif opt.kind == "number" and (isinstance(value, bool)
                                        or not isinstance(value, int | float)):
            lines.append(f"{key}.{name}: needs a number, got {value!r}")
        elif opt.kind == "number" and (rng := opt.out_of_range(float(value))) is not None:
            lines.append(f"{key}.{name}: {value!r} is outside IPOPT's range {rng}")
        elif opt.kind == "string" and not isinstance(value, str):
            allowed = f" ({', '.join(map(repr, opt.values))})" if opt.values else ""
            lines.append(f"{key}.{name}: needs a string{allowed}, got {value!r}")
        elif opt.kind == "string" and opt.values and value.lower() not in opt.values:
            near = difflib.get_close_matches(value.lower(), opt.values, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            lines.append(f"{key}.{name}: {value!r} is not one of "
                         f"{', '.join(map(repr, opt.values))}{hint}")
    return lines
