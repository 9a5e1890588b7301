"""``hmpc run --live``: the log's topics mirrored to a Foxglove WebSocket server."""

from __future__ import annotations

import sys

import pytest
from conftest import BALL
from typer.testing import CliRunner

from hmpc_cli.cli.app import app
from hmpc_cli.log.reader import read_log
from hmpc_cli.log.scene import TOPICS


def test_live_without_foxglove_sdk_exits_2(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import fails
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(tmp_path / "r"), "-q",
                                   "--live", "--set", "sim.duration=0.1"])
    assert res.exit_code == 2, res.output
    assert "foxglove-sdk" in res.stderr and "Traceback" not in res.output
    assert not (tmp_path / "r").exists()


def test_live_mirrors_every_topic_and_message(tmp_path):
    pytest.importorskip("foxglove")
    from hmpc_cli.log.live import LiveSink
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(BALL, ["sim.duration=0.2"])
    sink = LiveSink(port=0, speed=0.0)
    sent: list[tuple[str, int]] = []
    write = sink.write

    def spy(topic, ns, data):
        sent.append((topic, ns))
        write(topic, ns, data)

    sink.write = spy
    try:
        execute_run(prepare(sc), text, tmp_path / "r", mirror=sink)
    finally:
        sink.close()
    log = read_log(tmp_path / "r" / "run.mcap")
    assert set(sink._channels) == {m.topic for m in log.messages} | set(TOPICS)
    logged = sorted([(m.topic, m.log_time_ns) for m in log.messages]
                    + [(m.topic, m.log_time_ns) for m in log.raw])
    assert sorted(sent) == logged
