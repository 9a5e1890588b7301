"""mpc.node_shift: the elapsed nodes (hmpc) or the reference code's floor(60 x elapsed)."""

from pathlib import Path

import pytest

from hmpc_cli.mpc.chain.nlp import MPCSettings
from hmpc_cli.log.rundata import read_run
from hmpc_cli.run.runner import prepare, run_to_log
from hmpc_cli.run.scenario import ScenarioError, load_scenario

ROOT = Path(__file__).resolve().parents[1]
BALL = ROOT / "scenarios" / "ball.toml"


@pytest.mark.parametrize("rate, nps, shift, elapsed, moved", [
    (10, 60, "elapsed", 0.1, 6), (10, 60, "floor", 0.1, 6),
    (20, 60, "floor", 0.05, 3), (100, 60, "floor", 0.01, 0), (100, 100, "elapsed", 0.01, 1),
    # the reference's floor of a floating-point difference: 0.3 - 0.2 < 0.1
    (10, 60, "floor", 0.3 - 0.2, 5), (10, 60, "elapsed", 0.3 - 0.2, 6)])
def test_nodes_moved_per_period(rate, nps, shift, elapsed, moved):
    s = MPCSettings(rate_hz=rate, nodes_per_second=nps, node_shift=shift)
    assert s.shifted_nodes(elapsed) == moved


def test_floor_shift_allows_a_period_that_is_no_whole_number_of_nodes():
    with pytest.raises(ScenarioError, match="mpc.rate_hz: 100 must divide"):
        load_scenario(BALL, ["mpc.rate_hz=100"])
    sc, _ = load_scenario(BALL, ["mpc.rate_hz=100", 'mpc.node_shift="floor"'])
    assert sc.mpc.node_shift == "floor" and sc.mpc.nodes_per_second == 60


def _counts(tmp_path: Path, name: str, overrides: list[str]) -> list[tuple[int, list[int]]]:
    """(shifted, counts) of every periodic /mpc/solve of a 0.1 s ball run at 100 Hz."""
    sc, _ = load_scenario(BALL, ["sim.duration=0.1", "mpc.rate_hz=100", "mpc.horizon=1.2",
                                 *overrides])
    run_to_log(prepare(sc), tmp_path / f"{name}.mcap")
    run = read_run(tmp_path / f"{name}.mcap")
    return [(s.detail.shifted, list(s.detail.counts)) for s in run.solves
            if s.reason == "period"]


@pytest.mark.slow  # two NLP builds and 0.1 s at 100 Hz each: about 10-25 s
def test_floor_shift_at_100_hz_never_moves_a_node(tmp_path):
    floor = _counts(tmp_path, "floor", ['mpc.node_shift="floor"'])
    exact = _counts(tmp_path, "exact", ["mpc.nodes_per_second=100"])
    assert len(floor) == len(exact) == 9  # solves at 0.01 .. 0.09 s (0: the initial one)
    # floor(60 x 0.01) = 0: the first domain keeps its intervals, so its guard stays
    # equally far ahead at every re-solve
    assert [s for s, _ in floor] == [0] * 9
    assert len({tuple(c) for _, c in floor}) == 1
    # the exact shift moves one 0.01 s node per period from the first domain to the last
    assert [s for s, _ in exact] == [1] * 9
    firsts = [c[0] for _, c in exact]
    assert firsts == list(range(firsts[0], firsts[0] - 9, -1))
    assert len({sum(c) for _, c in exact}) == 1  # the horizon keeps its length


def test_solves_off_the_period_grid_move_the_time_elapsed(tmp_path):
    """A fixed latency of 0.02 s at 60 Hz: the solver runs at its own pace, a solve every
    0.02 s = 1.2 node steps. The nodes moved add up to the time elapsed (each solve moved
    round(1.2) = 1 and dropped the rest, so the planned guard slid 3.3 ms later at every
    solve): the planned guard time stays within half a node step of where it was."""
    sc, _ = load_scenario(BALL, ["sim.duration=0.45", "mpc.rate_hz=60", "sim.latency=0.02",
                                 'sim.latency_first="paused"',
                                 'lowlevel.past_guard="next_domain"'])
    run_to_log(prepare(sc), tmp_path / "r.mcap")
    solves = [s for s in read_run(tmp_path / "r.mcap").solves
              if s.t > 0.21 and len(s.detail.counts) == 2]  # after the floor: circle next
    dt = 1 / 60
    assert len(solves) >= 10 and {round(b.t - a.t, 9) for a, b in zip(
        solves, solves[1:], strict=False)} == {0.02}
    guard = [s.t + s.detail.counts[0] * dt for s in solves]
    assert max(guard) - min(guard) <= dt + 1e-9  # within +- dt/2 of one time: no drift
    moved = sum(s.detail.shifted for s in solves[1:])
    assert abs(moved * dt - (solves[-1].t - solves[0].t)) <= dt / 2 + 1e-9
