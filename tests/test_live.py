"""``hmpc run --live``: the log's topics mirrored to a Foxglove WebSocket server."""

from __future__ import annotations

import sys

import pytest
from conftest import BALL
from mcap.reader import make_reader
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


def test_pacing_never_runs_ahead_of_the_wall_clock_and_does_not_burst_after_a_stall():
    """Sim time 0, 0.1, 0.2, 0.3 s at speed 1; the run stalls 1.5 s (an NLP build) after
    its first message: the next goes out at once, and the pace resumes from there."""
    from hmpc_cli.log.live import Pacing

    wall, slept = [0.0], []

    def sleep(dt):
        slept.append(round(dt, 9))
        wall[0] += dt

    pacing = Pacing(1.0, clock=lambda: wall[0], sleep=sleep)
    sent = []
    for sim, work in ((0.0, 1.5), (0.1, 0.02), (0.2, 0.0), (0.3, 0.0)):
        pacing.wait(sim)
        sent.append(round(wall[0], 9))
        wall[0] += work
    assert sent == [0.0, 1.5, 1.6, 1.7]
    assert slept == [0.08, 0.1]
    Pacing(0.0, clock=lambda: 1 / 0, sleep=lambda dt: 1 / 0).wait(5.0)  # speed 0: no pacing


def test_pacing_sends_a_message_no_later_than_one_sent_at_once_and_keeps_the_pace():
    """The log writes a batch of states, then their scene at the same times: the scene's
    messages go out at once, and the next new time is due where it was (no slow-down)."""
    from hmpc_cli.log.live import Pacing

    wall = [0.0]

    def sleep(dt):
        wall[0] += dt

    pacing, sent = Pacing(1.0, clock=lambda: wall[0], sleep=sleep), []
    for sim in (0.0, 1.0, 0.5, 1.0, 1.5):
        pacing.wait(sim)
        sent.append(wall[0])
    assert sent == [0.0, 1.0, 1.0, 1.0, 1.5]


def _foxglove_client(url: str, want: set[str], timeout: float = 20.0) -> dict[str, bytes]:
    """A Foxglove WebSocket client: subscribes to every channel; the first payload of each
    topic in ``want`` (returns when all came, or at ``timeout`` [s])."""
    import json
    import struct
    import time

    from websockets.sync.client import connect

    got: dict[str, bytes] = {}
    topics: dict[int, str] = {}
    end = time.monotonic() + timeout
    with connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                 max_size=None) as ws:
        while set(got) < want and time.monotonic() < end:
            try:
                msg = ws.recv(timeout=max(end - time.monotonic(), 0.01))
            except TimeoutError:
                break
            if isinstance(msg, str):
                op = json.loads(msg)
                if op.get("op") == "advertise":
                    subs = []
                    for ch in op["channels"]:
                        sub = len(topics) + 1
                        topics[sub] = ch["topic"]
                        subs.append({"id": sub, "channelId": ch["id"]})
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif msg[0] == 1:  # message data: opcode, subscription id, log time, payload
                (sub,) = struct.unpack_from("<I", msg, 1)
                got.setdefault(topics[sub], bytes(msg[13:]))
    return got


def test_a_client_that_connects_after_the_start_gets_the_latched_topics(tmp_path):
    """The run is over before the client connects: its description, static scene and the
    planner call of t = 0 with its rollout (a run that plans once writes them before any
    client can subscribe) are still sent to it, byte for byte the log's."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websockets")
    from hmpc_cli.log.live import LATCHED, LiveSink
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(BALL, ["sim.duration=0.05"])
    sink = LiveSink(port=0, speed=0.0)
    try:
        execute_run(prepare(sc), text, tmp_path / "r", mirror=sink)
        got = _foxglove_client(sink.url, set(LATCHED))
    finally:
        sink.close()
    assert set(got) >= set(LATCHED) >= {"/run/info", "/scene/static", "/planner/plan",
                                        "/scene/rollout"}, sorted(got)
    with open(tmp_path / "r" / "run.mcap", "rb") as f:
        logged = {ch.topic: msg.data for _, ch, msg in
                  make_reader(f).iter_messages(topics=list(LATCHED))}
    assert {topic: got[topic] for topic in LATCHED} == logged


@pytest.mark.parametrize("args, message", [
    (["--live-port", "9000"], "error: --live-port 9000: needs --live"),
    (["--live", "--live-port", "70000"],
     "error: --live-port 70000: not a TCP port (1-65535, or 0: any free port)"),
])
def test_a_live_port_without_live_or_out_of_range_exits_2(tmp_path, args, message):
    res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(tmp_path / "r"), *args])
    assert res.exit_code == 2, res.output
    assert res.stderr.strip() == message and "Traceback" not in res.output
    assert not (tmp_path / "r").exists()


def _stream_client(url: str, topic: str, got: list, arrived, done) -> None:
    """A Foxglove WebSocket client subscribed to ``topic`` alone: appends each message's
    (log time, payload) to ``got`` and notifies ``arrived``, until ``done`` is set.

    foxglove-sdk 0.30 sends a channel's advertisement before it records the channel as
    advertised to that client: a subscription that arrives in between is refused with the
    status "Unknown channel ID: N". The client then subscribes again, as a viewer would
    have to."""
    import json
    import struct

    from websockets.sync.client import connect

    with connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                 max_size=None) as ws:
        wanted = None
        while not done.is_set():
            try:
                msg = ws.recv(timeout=0.2)
            except TimeoutError:
                continue
            if isinstance(msg, str):
                op = json.loads(msg)
                ids = [ch["id"] for ch in op.get("channels", []) if ch["topic"] == topic]
                if op.get("op") == "advertise" and ids:
                    wanted = ids[0]
                elif wanted is None or op.get("op") != "status" or (
                        op.get("message") != f"Unknown channel ID: {wanted}"):
                    continue
                ws.send(json.dumps({"op": "subscribe",
                                    "subscriptions": [{"id": 1, "channelId": wanted}]}))
            elif msg[0] == 1:  # message data: opcode, subscription id, log time, payload
                _, ns = struct.unpack_from("<IQ", msg, 1)
                with arrived:
                    got.append((ns, bytes(msg[13:])))
                    arrived.notify_all()


def test_a_client_subscribed_during_the_run_gets_each_state_as_it_is_logged(tmp_path):
    """A client subscribes to /sim/state (not latched) while the run goes on and receives
    each state the run logs, with the log's time and bytes, before the run logs the next:
    the run waits at each state until the client holds all earlier ones (a hang guard of
    20 s, then no more waiting), so the k-th state is written when the client holds k."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websockets")
    import json
    import threading

    from hmpc_cli.log.live import LiveSink
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    topic = "/sim/state"
    arrived, done = threading.Condition(), threading.Event()
    subscribed = threading.Event()
    got: list[tuple[int, bytes]] = []  # (log time, payload) as the client received them
    held: list[int] = []  # how many states the client held when the run wrote each state
    stalled: list[int] = []  # the state the run stopped waiting at (hang guard)

    class Sink(LiveSink):
        def on_subscribe(self, client, channel):
            super().on_subscribe(client, channel)
            if channel.topic == topic:
                subscribed.set()

        def write(self, t, ns, data):
            if t == topic and not stalled:
                ready = subscribed.wait(timeout=20)
                with arrived:
                    if not (ready and arrived.wait_for(lambda: len(got) >= len(held),
                                                       timeout=20)):
                        stalled.append(len(held))
                    held.append(len(got))
            super().write(t, ns, data)

    sc, text = load_scenario(BALL, ["sim.duration=0.3"])
    sink = Sink(port=0, speed=0.0)
    thread = threading.Thread(target=_stream_client,
                              args=(sink.url, topic, got, arrived, done), daemon=True)
    thread.start()
    try:
        execute_run(prepare(sc), text, tmp_path / "r", mirror=sink)
        with arrived:  # the last state, still on its way (hang guard)
            stalled or arrived.wait_for(lambda: len(got) >= len(held), timeout=20)
    finally:
        done.set()
        thread.join(timeout=10)
        sink.close()
    with open(tmp_path / "r" / "run.mcap", "rb") as f:
        logged = [(msg.log_time, msg.data) for _, _, msg in
                  make_reader(f).iter_messages(topics=[topic], log_time_order=False)]
    assert stalled == []
    assert len(logged) == 31 and held == list(range(31))
    assert got == logged
    first = json.loads(got[0][1])
    assert first["t"] == 0.0 and first["x"] == {"px": 1.0, "py": 1.0, "vx": 0.0, "vy": 0.0}


def test_a_latched_message_goes_to_a_new_subscriber_twice_and_close_waits_for_the_queue(
        tmp_path):
    """The server may call on_subscribe before the client's subscription takes messages
    (foxglove-sdk PR #533): the latched message, sent at once, is sent again RESEND_S
    later. close() with a client subscribed waits FLUSH_S before stopping the server
    (stopped at once, it dropped the run's last messages now and then); without one it
    does not."""
    pytest.importorskip("foxglove")
    pytest.importorskip("websockets")
    import json
    import time

    from websockets.sync.client import connect

    from hmpc_cli.log.live import FLUSH_S, LATCHED, RESEND_S, LiveSink
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    sent: list[tuple[str, float]] = []

    class Sink(LiveSink):
        def _resend(self, topic):
            sent.append((topic, time.monotonic()))
            super()._resend(topic)

    sc, text = load_scenario(BALL, ["sim.duration=0.05"])
    sink, slept = Sink(port=0, speed=0.0), []
    sink._sleep = slept.append
    execute_run(prepare(sc), text, tmp_path / "r", mirror=sink)
    with connect(sink.url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                 max_size=None) as ws:
        deadline = time.monotonic() + 20
        while len(sent) < 2 * len(LATCHED) and time.monotonic() < deadline:
            try:
                msg = ws.recv(timeout=0.05)
            except TimeoutError:
                continue
            if isinstance(msg, str) and json.loads(msg).get("op") == "advertise":
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": ch["id"], "channelId": ch["id"]}  # one per channel
                    for ch in json.loads(msg)["channels"]]}))
        sink.close()  # the client still subscribed
    for topic in LATCHED:
        times = [t for s, t in sent if s == topic]
        assert len(times) == 2 and times[1] - times[0] >= RESEND_S * 0.99, sent
    assert slept == [FLUSH_S]
    idle, slept = LiveSink(port=0, speed=0.0), []
    idle._sleep = slept.append
    idle.close()
    assert slept == []
