"""sim.log_plan_stride: every k-th plan node logged, resets and the plan's end kept."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hmpc_cli.core.messages import Trajectory
from hmpc_cli.log.reader import read_log
from hmpc_cli.log.runlog import thinned

ROOT = Path(__file__).resolve().parents[1]


def _traj(seg: list[int]) -> Trajectory:
    n = len(seg)
    return Trajectory(t=np.arange(n) * 0.1, x=np.arange(2 * n, dtype=float).reshape(n, 2),
                      u=np.arange(n, dtype=float).reshape(n, 1), mode=np.array(seg) % 2,
                      seg=np.array(seg), guards=(0,), input_hold="foh")


def test_thinned_keeps_every_kth_node_the_last_and_both_sides_of_a_reset():
    tr = _traj([0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1])  # a reset between nodes 4 and 5
    th = thinned(tr, 3)
    kept = [0, 3, 4, 5, 6, 9, 10]
    assert np.array_equal(th.t, tr.t[kept]) and np.array_equal(th.x, tr.x[kept])
    assert np.array_equal(th.u, tr.u[kept]) and np.array_equal(th.seg, tr.seg[kept])
    assert np.array_equal(th.mode, tr.mode[kept])
    assert th.guards == (0,) and th.input_hold == "foh"
    assert thinned(tr, 1) is tr and len(thinned(_traj([]), 4).t) == 0


def test_a_thinned_log_holds_the_full_logs_nodes_it_keeps(tmp_path, invoke_hmpc):
    from hmpc_cli.run.runner import run_scenario
    from hmpc_cli.run.scenario import load_scenario

    logs = {}
    for k in (1, 3):
        sc, text = load_scenario(ROOT / "scenarios" / "ball.toml",
                                 ["sim.duration=0.8", f"sim.log_plan_stride={k}"])
        run_scenario(sc, text, tmp_path / str(k))
        logs[k] = read_log(tmp_path / str(k) / "run.mcap")
    full, thin = logs[1].topic("/mpc/solve"), logs[3].topic("/mpc/solve")
    assert len(full) == len(thin) >= 8
    resets = 0
    for a, b in zip(full, thin, strict=True):
        nodes = a.data["plan"]
        seg = [n["seg"] for n in nodes]
        keep = [i for i in range(len(nodes)) if i % 3 == 0 or i == len(nodes) - 1
                or (i + 1 < len(nodes) and seg[i] != seg[i + 1])
                or (i > 0 and seg[i] != seg[i - 1])]
        resets += sum(seg[i] != seg[i + 1] for i in range(len(seg) - 1))
        assert b.data["plan"] == [nodes[i] for i in keep]  # the same numbers, bit for bit
        # the plan's own node count, not the logged one (the latency model scales by it)
        assert a.data["nodes"] == b.data["nodes"] == len(nodes) > len(keep)
    assert resets > 0  # the plans cross guards: the reset pairs were checked
    scene = {k: sum(len(bytes(m.data)) for m in logs[k].raw if m.topic == "/scene/plan")
             for k in logs}
    assert scene[3] < 0.6 * scene[1]  # the 3D scene draws the thinned plan
    assert (tmp_path / "3" / "run.mcap").stat().st_size < 0.7 * (
        tmp_path / "1" / "run.mcap").stat().st_size
    _readers_that_need_every_node(tmp_path / "1", tmp_path / "3")
    proc = invoke_hmpc(["replay", str(tmp_path / "3" / "run.mcap"), "--topic", "/run/summary"],
                       tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "thinned: sim.log_plan_stride = 3 (one node in 3," in " ".join(proc.stdout.split())


def _readers_that_need_every_node(full: Path, thin: Path) -> None:
    """The pass-through and tube-vs-reality read the full log and refuse the thinned one."""
    import pytest

    from hmpc_cli.analysis.passthrough import PassThroughError, pass_through_geometry
    from hmpc_cli.log.rundata import read_run
    from hmpc_cli.analysis.tube_reality import read_run as read_reality

    assert read_run(full).plan_stride == 1 and read_run(thin).plan_stride == 3
    assert pass_through_geometry(full).dt > 0 and read_reality(full).solves
    with pytest.raises(PassThroughError, match=r"thinned \(sim.log_plan_stride = 3.*"
                                               r"--set sim.log_plan_stride=1"):
        pass_through_geometry(thin)
    with pytest.raises(ValueError, match=r"thinned .*tube vs reality"):
        read_reality(thin)
