"""benchmarks/probe_rti_step.py: the hand-rolled real-time iteration it probes gives
sqpmethod's step bit for bit, and CasADi's HPIPM conic reused on one buffer does not
repeat its step (the probe's two findings in docs/performance.md). No timing asserted."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import probe_rti_step


def test_the_hand_rolled_step_is_sqpmethods_bit_for_bit():
    rows = {r["nlp"]: r for r in probe_rti_step.compare()}
    assert set(rows) == {"final", "switching"}
    for r in rows.values():
        assert r["problems"] > 0 and r["identical"] == r["problems"], r
        assert r["reused_buffer_same"] is False, r
