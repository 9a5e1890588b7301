"""``hmpc run --live``: the run's topics streamed to a Foxglove WebSocket server.

A :class:`LiveSink` mirrors a :class:`~hmpc_cli.log.recorder.Recorder`: every topic the
recorder registers (JSON or protobuf, same schemas) becomes a channel of a Foxglove
WebSocket server on 127.0.0.1 (``foxglove-sdk``, the optional extra ``live``), and every
message written to the log is also sent there with the same log time, paced
(:class:`Pacing`) so that simulated time runs no faster than ``speed`` times the wall
clock. The run's description, static scene and newest planner call with its rollout
(:data:`LATCHED`) are sent again to each client that subscribes to them later.
Connect Foxglove or Lichtblick with Open connection → Foxglove WebSocket →
``ws://127.0.0.1:8765``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

from hmpc_cli.log.scene import ROLLOUT, STATIC

__all__ = ["FLUSH_S", "LATCHED", "LiveSink", "LiveError", "Pacing", "RESEND_S", "port_problem"]

_NS_PER_S = 1_000_000_000
#: topics written rarely that a client subscribing later still needs: the run's
#: description, the static scene, and the newest planner call and its rollout (written
#: once at t = 0 when the run plans once; before a client can have subscribed)
LATCHED = ("/run/info", STATIC, "/planner/plan", ROLLOUT)
RESEND_S = 0.1  #: a latched message is sent to a new subscriber again this much later [s]
FLUSH_S = 0.3  #: the wait for queued messages before the server stops, with a subscriber [s]


def port_problem(port: int) -> str | None:
    """What is wrong with a --live-port value (None: a TCP port, or 0 for any free one)."""
    return None if 0 <= port <= 65535 else "not a TCP port (1-65535, or 0: any free port)"


class LiveError(RuntimeError):
    """The optional ``foxglove-sdk`` package is not installed, or the server cannot start."""


class Pacing:
    """Holds messages back so that simulated time never runs ahead of the wall clock.

    The first message anchors sim time 0 to the wall clock; a message that is late (the
    run was slower than ``speed``, e.g. while it built its NLPs) moves the anchor, so
    the stream goes on at ``speed`` from there instead of catching up in a burst. A
    message no later than one already sent (the log writes a batch of states, then their
    scene) goes out at once and moves nothing.

    Args:
        speed: simulated seconds per wall-clock second (<= 0: no pacing).
        clock: the wall clock [s]. sleep: waits that many seconds.
    """

    def __init__(self, speed: float, clock: Callable[[], float] = time.perf_counter,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.speed, self._clock, self._sleep = float(speed), clock, sleep
        self._anchor: float | None = None  # wall time [s] of sim time 0
        self._latest = -math.inf  # the latest sim time [s] paced

    def wait(self, sim_time: float) -> None:
        """Returns when a message at ``sim_time`` [s] is due."""
        if self.speed <= 0 or sim_time <= self._latest:
            return
        self._latest = sim_time
        now, due = self._clock(), sim_time / self.speed
        self._anchor = now - due if self._anchor is None else max(self._anchor, now - due)
        if self._anchor + due > now:
            self._sleep(self._anchor + due - now)


class LiveSink:
    """A Foxglove WebSocket server the run log mirrors its messages to.

    Args:
        port: TCP port on 127.0.0.1 (1-65535, or 0: any free port).
        speed: simulated seconds per wall-clock second (<= 0: no pacing).

    Raises:
        LiveError: ``foxglove-sdk`` is missing or the server fails to start.
    """

    def __init__(self, port: int = 8765, speed: float = 1.0) -> None:
        try:
            import foxglove
        except ImportError:
            raise LiveError("--live needs the foxglove-sdk package: pip install "
                            "'hmpc[live]' (or pip install foxglove-sdk)") from None
        if (problem := port_problem(port)) is not None:
            raise LiveError(f"--live-port {port}: {problem}")
        self._fg = foxglove
        self.context = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._held: dict[str, tuple[int, bytes]] = {}  # latched topic -> (ns, data)
        self._subscribers = 0  # subscriptions open (the server's callbacks count them)
        self._timers: list[threading.Timer] = []  # latched messages' second sending
        self._sleep = time.sleep
        try:
            self.server = foxglove.start_server(
                name="hmpc", host="127.0.0.1", port=port, context=self.context,
                capabilities=[foxglove.Capability.Time], server_listener=self)
        except Exception as exc:  # the SDK raises its own error types
            raise LiveError(f"--live: cannot start the server on port {port}: "
                            f"{exc}") from None
        self.pacing = Pacing(speed)

    @property
    def url(self) -> str:
        """The WebSocket address to connect to."""
        return f"ws://127.0.0.1:{self.server.port}"

    def add_topic(self, topic: str, message_encoding: str, schema_name: str,
                  schema_encoding: str, schema_data: bytes) -> None:
        """Opens the server channel of a recorder topic (same encodings and schema)."""
        schema = self._fg.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
        self._channels[topic] = self._fg.Channel(topic, schema=schema,
                                                 message_encoding=message_encoding,
                                                 context=self.context)

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Sends one encoded message at sim time `log_time_ns`, paced to the wall clock."""
        self.pacing.wait(log_time_ns / _NS_PER_S)
        if topic in LATCHED:  # held before it is sent: a subscriber gets it either way
            self._held[topic] = (log_time_ns, data)
        self._channels[topic].log(data, log_time=log_time_ns)
        self.server.broadcast_time(log_time_ns)

    def on_subscribe(self, client: Any, channel: Any) -> None:
        """The server's callback: a latched topic's message, again, to a new subscriber.

        Sent at once (if written yet) and again :data:`RESEND_S` later: the server may call
        this before the client's subscription takes messages (foxglove-sdk PR #533), and a
        message sent meanwhile, this one or the run's own, is lost. Clients subscribed
        before get it more than once (the same message).
        """
        self._subscribers += 1
        if channel.topic in LATCHED:  # also when its message is being written just now
            self._resend(channel.topic)
            timer = threading.Timer(RESEND_S, self._resend, (channel.topic,))
            timer.daemon = True
            self._timers.append(timer)
            timer.start()

    def _resend(self, topic: str) -> None:
        """Sends the latched topic's held message again (none yet: nothing)."""
        held = self._held.get(topic)
        if held is not None:
            self._channels[topic].log(held[1], log_time=held[0])

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        """The server's callback: one subscription fewer."""
        self._subscribers -= 1

    def close(self) -> None:
        """Stops the server once what it queued went out (clients keep what they received).

        With a subscriber, waits :data:`FLUSH_S` first: stopping right after the last
        write dropped the run's last messages (its summary among them) now and then.
        """
        if self._subscribers > 0:
            self._sleep(FLUSH_S)  # a latched message's second sending is due in it too
        for timer in self._timers:
            timer.cancel()
        self.server.stop()
