"""mpc.schedule_rule = "reference": the reference code's schedule bookkeeping, emulated.

The nominal ball flies the reference's own six-contact schedule (planner "schedule",
scenarios/ball_reference_schedule.toml) at 10 Hz with the reference's floor shift. The node
counts are computed by hand below from the planned durations and the rule.
"""

from pathlib import Path

from hmpc_cli.run.runner import prepare, run_unlogged
from hmpc_cli.run.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "scenarios" / "ball_reference_schedule.toml"

# durations [0.241, 0.097, 0.339, 0.571, 0.158, 0.594, 0.18] s at 60 nodes/s, rounded up:
# 14.46 -> 15, 5.82 -> 6, 20.34 -> 21, 34.26 -> 35, 9.48 -> 10, 35.64 -> 36, 10.8 -> 11;
# the final domain takes the rest of the 180-node horizon: 180 - 134 = 46.
PLANNED = [15, 6, 21, 35, 10, 36, 11, 46]


def _counts(overrides: list[str], duration: float) -> list[tuple[float, str, list[int]]]:
    sc, _ = load_scenario(SCENARIO, [f"sim.duration={duration}", *overrides])
    loop = prepare(sc)
    out, solve = [], loop.mpc.solve

    def spy(t, *args, **kw):
        plan = solve(t, *args, **kw)
        out.append((t, list(plan.detail.counts)))
        return plan

    loop.mpc.solve = spy
    run_unlogged(loop)
    return out


def test_the_reference_rule_drops_a_domain_at_every_contact_and_when_its_time_passes():
    got = _counts(['mpc.schedule_rule="reference"', 'mpc.node_shift="floor"'], 0.5)
    counts = [c for _, c in got]
    assert counts[0] == PLANNED
    # t = 0.1, 0.2: floor(60 x 0.1) = 6 nodes move from the first domain to the final one
    assert counts[1] == [9, 6, 21, 35, 10, 36, 11, 52]
    assert counts[2] == [3, 6, 21, 35, 10, 36, 11, 58]
    # the floor contact at t = 0.25 drops the first domain: its 3 nodes go to the final one
    assert counts[3] == [6, 21, 35, 10, 36, 11, 61]
    # t = 0.35: 6 nodes elapsed since the contact >= the wall domain's 6: its planned time
    # has passed, so it is dropped without a contact (the impact rule would keep 1 node)
    t4, c4 = got[4]
    assert abs(t4 - 0.35) < 1e-6 and c4 == [21, 35, 10, 36, 11, 67]
    # the wall contact then comes (at 0.35 s + 1e-7) and drops the next domain too: the
    # floor domain the plant never flew
    assert counts[5] == [35, 10, 36, 11, 88]


def test_the_impact_rule_keeps_the_domain_until_its_guard_fires():
    counts = [c for _, c in _counts([], 0.5)]
    assert counts[:3] == [PLANNED, [9, 6, 21, 35, 10, 36, 11, 52],
                          [3, 6, 21, 35, 10, 36, 11, 58]]
    assert counts[3] == [6, 21, 35, 10, 36, 11, 61]  # the scheduled floor contact
    # elapsed nodes never empty a domain whose guard is pending: the wall domain keeps 1
    assert counts[4][0] >= 1 and counts[4][1:3] == [21, 35]
