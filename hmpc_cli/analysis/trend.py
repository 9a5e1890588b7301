"""The Cochran-Armitage test for a trend in success proportions across ordered groups.

Used by the robustness report: does the success rate rise or fall with the MPC rate?
Groups i (e.g. MPC rates) with n_i runs, k_i successes and scores s_i (the report uses
log f: its rates are roughly geometric); p = K / N; the statistic
T = sum_i s_i (k_i - n_i p) has variance p (1 - p) (sum_i n_i s_i^2 - (sum_i n_i s_i)^2 / N)
under "no trend", z = T / sqrt(var) is standard normal, the p-value two-sided.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["Trend", "cochran_armitage"]


@dataclass(frozen=True)
class Trend:
    """A trend test's result.

    Attributes:
        z: the standardized statistic (> 0: success rises with the score).
        p: its two-sided p-value (NaN: undefined, every run alike or one group).
    """

    z: float
    p: float

    @property
    def direction(self) -> str:
        """``rises``, ``falls`` or ``flat`` (z = 0 or undefined)."""
        if not math.isfinite(self.z) or self.z == 0.0:
            return "flat"
        return "rises" if self.z > 0 else "falls"


def cochran_armitage(runs: Sequence[int], successes: Sequence[int],
                     scores: Sequence[float]) -> Trend:
    """The test over groups given by their runs n_i, successes k_i and scores s_i.

    Raises:
        ValueError: lengths differ, or a group has k_i outside [0, n_i].
    """
    if not len(runs) == len(successes) == len(scores):
        raise ValueError("cochran_armitage: runs, successes and scores differ in length")
    if any(k < 0 or k > n for n, k in zip(runs, successes, strict=True)):
        raise ValueError("cochran_armitage: successes outside [0, runs]")
    total, hits = sum(runs), sum(successes)
    if total == 0:
        return Trend(math.nan, math.nan)
    p = hits / total
    t = sum(s * (k - n * p) for n, k, s in zip(runs, successes, scores, strict=True))
    spread = sum(n * s * s for n, s in zip(runs, scores, strict=True)) - sum(
        n * s for n, s in zip(runs, scores, strict=True)) ** 2 / total
    var = p * (1.0 - p) * spread
    if var <= 0.0:
        return Trend(math.nan, math.nan)
    z = t / math.sqrt(var)
    return Trend(z, math.erfc(abs(z) / math.sqrt(2.0)))
