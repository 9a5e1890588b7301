"""``hmpc run --live``: the run's topics streamed to a Foxglove WebSocket server.

A :class:`LiveSink` mirrors a :class:`~hmpc_cli.log.recorder.Recorder`: every topic the
recorder registers (JSON or protobuf, same schemas) becomes a channel of a Foxglove
WebSocket server on 127.0.0.1 (``foxglove-sdk``, the optional extra ``live``), and every
message written to the log is also sent there with the same log time, paced so that
simulated time runs no faster than ``speed`` times the wall clock. Connect Foxglove or
Lichtblick with Open connection → Foxglove WebSocket → ``ws://127.0.0.1:8765``.
"""

from __future__ import annotations

import time
from typing import Any

__all__ = ["LiveSink", "LiveError"]

_NS_PER_S = 1_000_000_000


class LiveError(RuntimeError):
    """The optional ``foxglove-sdk`` package is not installed, or the server cannot start."""


class LiveSink:
    """A Foxglove WebSocket server the run log mirrors its messages to.

    Args:
        port: TCP port on 127.0.0.1 (0: any free port).
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
        self._fg = foxglove
        self.context = foxglove.Context()
        try:
            self.server = foxglove.start_server(
                name="hmpc", host="127.0.0.1", port=port, context=self.context,
                capabilities=[foxglove.Capability.Time])
        except Exception as exc:  # the SDK raises its own error types
            raise LiveError(f"--live: cannot start the server on port {port}: "
                                  f"{exc}") from None
        self.speed = float(speed)
        self._channels: dict[str, Any] = {}
        self._start = time.perf_counter()

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
        if self.speed > 0:
            ahead = log_time_ns / _NS_PER_S / self.speed - (time.perf_counter() - self._start)
            if ahead > 0:
                time.sleep(ahead)
        self._channels[topic].log(data, log_time=log_time_ns)
        self.server.broadcast_time(log_time_ns)

    def close(self) -> None:
        """Stops the server (clients keep what they received)."""
        self.server.stop()
