"""The Cochran-Armitage trend test, against hand-computed values."""

import math

import pytest

from hmpc_cli.analysis.trend import cochran_armitage


def test_a_rising_trend_by_hand():
    # N = 30, K = 15, p = 1/2; T = 0 (2 - 5) + 1 (5 - 5) + 2 (8 - 5) = 6;
    # var = 1/4 (10 (0 + 1 + 4) - (10 (0 + 1 + 2))^2 / 30) = 1/4 (50 - 30) = 5
    tr = cochran_armitage([10, 10, 10], [2, 5, 8], [0, 1, 2])
    assert tr.z == pytest.approx(6 / math.sqrt(5), rel=1e-12)
    assert tr.p == pytest.approx(math.erfc(6 / math.sqrt(10)), rel=1e-12)
    assert tr.direction == "rises"


def test_falling_flat_and_undefined():
    assert cochran_armitage([10, 10], [9, 1], [0, 1]).direction == "falls"
    flat = cochran_armitage([10, 10, 10], [5, 5, 5], [0, 1, 2])
    assert flat.z == 0.0 and flat.p == pytest.approx(1.0) and flat.direction == "flat"
    same = cochran_armitage([10, 10], [10, 10], [0, 1])  # every run succeeded
    assert math.isnan(same.p) and same.direction == "flat"
    with pytest.raises(ValueError, match="outside"):
        cochran_armitage([10], [11], [0])
