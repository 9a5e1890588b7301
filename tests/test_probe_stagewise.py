"""benchmarks/probe_stagewise.py: the Lagrangian's Hessian assembled stage by stage is
nlpsol's bit for bit with a zero-order hold and not with a first-order hold, where u_k is in
two links (the probe's finding in docs/performance.md). No timing asserted."""

import sys
from pathlib import Path

import pytest

from hmpc_cli.mpc.chain.nlp import MPCSettings
from hmpc_cli.systems.ball import BallParams, build_ball

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import probe_stagewise


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_the_staged_hessian_is_nlpsols_bit_for_bit_only_with_a_zero_order_hold(hold):
    settings = MPCSettings(horizon=1.0, max_switches=3, input_hold=hold)
    rows = {r["nlp"]: r for r in probe_stagewise.hessian_rows(build_ball(BallParams()),
                                                               settings, reps=1)}
    assert set(rows) == {"switching", "final"}
    for r in rows.values():
        assert r["same_sparsity"] and r["max_abs"] > 0, r
        if hold == "zoh":
            assert r["differing"] == 0 and r["max_diff"] == 0.0, r
        else:  # u_k's sums over links k-1 and k, associated otherwise: rounding apart
            assert r["differing"] > 0 and all("u" in pair for pair in r["blocks"]), r
            assert 0 < r["max_diff"] <= 1e-15 * r["max_abs"], r


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_the_staged_constraint_jacobian_is_nlpsols_bit_for_bit(hold):
    """Every row is one stage's, so the Jacobian assembled stage by stage is nlpsol's bit
    for bit with either hold (hmpc gives it to IPOPT: hmpc_cli/mpc/staged.py)."""
    settings = MPCSettings(horizon=1.0, max_switches=3, input_hold=hold)
    rows = probe_stagewise.jacobian_rows(build_ball(BallParams()), settings)
    assert [r["nlp"] for r in rows] == ["switching", "final"]
    for r in rows:
        assert r["same_sparsity"] and r["nnz"] > 0 and r["differing"] == 0, r
