"""Writing MCAP run logs: JSON messages (``jsonschema``/``json`` encodings), sim time as log time.

Protobuf channels (e.g. the 3D scene's ``foxglove.SceneUpdate``) are written beside them:
schema encoding ``protobuf`` with the message's ``FileDescriptorSet`` as schema data,
message encoding ``protobuf`` (what Foxglove and Lichtblick read). Chunks reach the disk as
they fill, so a killed run's log stays readable (:mod:`hmpc_cli.log.reader`).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from hmpc_cli.log.codecs import add_messages, zstd_chunks_at_level
from hmpc_cli.log.codecs import compression as mcap_compression
from hmpc_cli.core.text import printable

__all__ = ["NS_PER_S", "Recorder", "file_descriptor_set", "to_json_bytes"]

#: nanoseconds per second (MCAP log times are integer nanoseconds)
NS_PER_S = 1_000_000_000


def _library_id() -> str:
    """Returns the MCAP header library string."""
    try:
        from . import __version__
    except ImportError:
        return "hmpc"
    return f"hmpc {__version__}"


def _to_ns(t: float) -> int:
    """Converts simulated time in seconds to integer nanoseconds."""
    t = float(t)
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"log time must be a finite number >= 0 seconds, got {t!r}")
    return round(t * NS_PER_S)


def _jsonable(obj: Any) -> Any:
    """Recursively converts `obj` to plain JSON types; non-finite floats become None."""
    if isinstance(obj, str):
        return printable(obj)  # a path's bytes that are not UTF-8 as \\xNN
    if obj is None or isinstance(obj, bool):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {(printable(k) if isinstance(k, str) else _jsonable(k)): _jsonable(v)
                for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind == "f" and not np.isfinite(obj).all():
            obj = np.where(np.isfinite(obj), obj.astype(object), None)
        return obj.tolist() if obj.dtype.kind in "biuf" else _jsonable(obj.tolist())
    if isinstance(obj, np.generic):  # numpy scalars: bool_, integer, floating, ...
        return _jsonable(obj.item())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    raise TypeError(f"cannot encode object of type {type(obj).__name__} as JSON")


def _left_out(obj: Any) -> Any:
    """``obj`` (decoded JSON) with every object key whose value is null left out."""
    if isinstance(obj, dict):
        return {k: _left_out(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list):
        return [_left_out(v) for v in obj]
    return obj


def to_json_bytes(payload: Any) -> bytes:
    """Encodes `payload` as compact UTF-8 JSON (numpy and dataclasses ok).

    A field that is None, NaN or +-inf is left out of its object, never written as null:
    a JSON schema's ``"type": "object"`` or ``"number"`` admits no null, and the viewers
    cannot parse ``["object", "null"]`` (readers take an absent number as NaN, an
    absent object as None). orjson encodes dataclasses, numpy arrays and scalars
    natively; a message with a null in it (rare) is decoded and encoded again without
    those keys; anything orjson refuses (e.g. non-string keys) takes the recursive
    conversion.
    """
    import orjson

    opts = orjson.OPT_SERIALIZE_NUMPY
    try:
        data = orjson.dumps(payload, option=opts)
    except TypeError:
        obj = _left_out(_jsonable(payload))
        return json.dumps(obj, separators=(",", ":"), allow_nan=False,
                          ensure_ascii=False).encode()
    if b"null" in data:
        return orjson.dumps(_left_out(orjson.loads(data)), option=opts)
    return data


def file_descriptor_set(message_type: Any) -> bytes:
    """The serialized ``FileDescriptorSet`` of a protobuf message class.

    Holds the message's file and every file it imports, dependencies first (the MCAP
    ``protobuf`` schema encoding).
    """
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds, seen = FileDescriptorSet(), set()

    def add(file: Any) -> None:
        if file.name in seen:
            return
        seen.add(file.name)
        for dep in file.dependencies:
            add(dep)
        file.CopyToProto(fds.file.add())

    add(message_type.DESCRIPTOR.file)
    return fds.SerializeToString()


class Recorder:
    """Writes one run's MCAP log: JSON messages on topics, sim time (s) as log time.

    Args:
        path: the MCAP file to write.
        flush_every: messages per flush (closes a chunk: a killed run keeps it).
        chunk_size: MCAP chunk size [bytes].
        mirror: also gets every topic and message (e.g. :class:`hmpc_cli.log.live.LiveSink`):
            ``add_topic(topic, message_encoding, schema_name, schema_encoding, data)`` and
            ``write(topic, log_time_ns, data)``; None: the file only.
    """

    def __init__(self, path: str | Path, *, flush_every: int = 200, chunk_size: int = 256 * 1024,
                 mirror: Any = None):
        if flush_every < 1:
            raise ValueError(f"flush_every must be >= 1, got {flush_every}")
        self.path = Path(path)
        self.flush_every = int(flush_every)
        self._file = open(self.path, "wb")  # noqa: SIM115 - open until close()
        try:
            compression = mcap_compression()
            if compression == CompressionType.ZSTD:
                zstd_chunks_at_level()
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=compression)
            self._writer.start(profile="", library=_library_id())
            self._file.flush()  # header on disk: even a run killed at once leaves valid magic
        except BaseException:
            self._file.close()
            raise
        self._channels: dict[str, int] = {}  # topic -> channel id
        self._schema_ids: dict[tuple[str, bytes], int] = {}  # (name, data) -> schema id
        self._protobuf: set[str] = set()  # topics with protobuf messages
        self._sequence: dict[str, int] = {}
        self._pending: list[tuple[int, int, bytes, int]] = []  # (channel, ns, data, seq)
        self._closed = False
        self.mirror = mirror

    @property
    def closed(self) -> bool:
        """Whether close() has been called."""
        return self._closed

    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"recorder for {self.path} is closed")

    def add_topic(self, topic: str, schema_name: str, schema: dict) -> None:
        """Registers `topic` with a JSON schema; raises ValueError if already registered."""
        self._check_open()
        if topic in self._channels:
            raise ValueError(f"topic {topic!r} is already registered")
        data = json.dumps(schema, separators=(",", ":")).encode("utf-8")
        key = (schema_name, data)
        if key not in self._schema_ids:
            self._schema_ids[key] = self._writer.register_schema(schema_name, "jsonschema", data)
        self._channels[topic] = self._writer.register_channel(topic, "json", self._schema_ids[key])
        if self.mirror is not None:
            self.mirror.add_topic(topic, "json", schema_name, "jsonschema", data)
        self._sequence[topic] = 0

    def add_protobuf_topic(self, topic: str, message_type: Any) -> None:
        """Registers `topic` for protobuf messages of class `message_type`.

        The schema is named by the message's full name (e.g. ``foxglove.SceneUpdate``)
        and holds its ``FileDescriptorSet``; raises ValueError if already registered.
        """
        self._check_open()
        if topic in self._channels:
            raise ValueError(f"topic {topic!r} is already registered")
        name = message_type.DESCRIPTOR.full_name
        key = (name, file_descriptor_set(message_type))
        if key not in self._schema_ids:
            self._schema_ids[key] = self._writer.register_schema(name, "protobuf", key[1])
        self._channels[topic] = self._writer.register_channel(topic, "protobuf",
                                                              self._schema_ids[key])
        self._sequence[topic] = 0
        self._protobuf.add(topic)
        if self.mirror is not None:
            self.mirror.add_topic(topic, "protobuf", name, "protobuf", key[1])

    def _check_json_topic(self, topic: str) -> None:
        """Raises unless the recorder is open and `topic` a registered JSON topic."""
        self._check_open()
        if topic not in self._channels:
            known = sorted(self._channels)
            raise KeyError(f"unknown topic {topic!r}; call add_topic() first (registered: {known})")
        if topic in self._protobuf:
            raise TypeError(f"topic {topic!r} holds protobuf messages: use write_protobuf()")

    def write(self, topic: str, t: float, payload: dict) -> None:
        """Writes one JSON message on `topic` at simulated time `t` (s, >= 0)."""
        self._check_json_topic(topic)
        self._add(topic, _to_ns(t), to_json_bytes(payload))

    def write_many(self, topic: str, ts: Any, payloads: Any) -> None:
        """Writes JSON messages on `topic` at simulated times `ts` (s, >= 0), in order.

        The same messages as a :meth:`write` per pair, the topic checked once.
        """
        self._check_json_topic(topic)
        for t, payload in zip(ts, payloads, strict=True):
            self._add(topic, _to_ns(t), to_json_bytes(payload))

    def write_protobuf(self, topic: str, t: float, message: Any) -> None:
        """Writes one protobuf message on `topic` at simulated time `t` (s, >= 0)."""
        self._check_open()
        if topic not in self._protobuf:
            raise KeyError(f"unknown protobuf topic {topic!r}; call add_protobuf_topic() first")
        self._add(topic, _to_ns(t), message.SerializeToString())

    def write_protobuf_bytes(self, topic: str, t: float, data: bytes) -> None:
        """Writes one protobuf message, already encoded, on `topic` at sim time `t` (s)."""
        self._check_open()
        if topic not in self._protobuf:
            raise KeyError(f"unknown protobuf topic {topic!r}; call add_protobuf_topic() first")
        self._add(topic, _to_ns(t), bytes(data))

    def _add(self, topic: str, ns: int, data: bytes) -> None:
        """Queues one encoded message; flushes every ``flush_every`` messages.

        The queue reaches mcap's writer at the flush, in one tight loop: its per-message
        Python code then costs less than spread between the solves. A message waits no
        longer than it did in mcap's open chunk, which reaches the file at the flush too.
        """
        self._pending.append((self._channels[topic], ns, data, self._sequence[topic]))
        if self.mirror is not None:
            self.mirror.write(topic, ns, data)
        self._sequence[topic] = (self._sequence[topic] + 1) & 0xFFFFFFFF
        if len(self._pending) >= self.flush_every:
            self.flush()

    def _drain(self) -> None:
        """Hands the queued messages to mcap's writer, in order."""
        add_messages(self._writer, self._pending)
        self._pending.clear()

    def flush(self) -> None:
        """Closes the current chunk and pushes everything written so far to the OS."""
        self._check_open()
        self._drain()
        self._writer.flush()

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Adds a named string-to-string metadata record."""
        self._check_open()
        self._drain()
        for k, v in data.items():
            if not isinstance(k, str) or not isinstance(v, str):
                raise TypeError(f"metadata {name!r}: keys and values must be str, got {k!r}: {v!r}")
        self._writer.add_metadata(name, dict(data))
        self._file.flush()

    def add_attachment(self, name: str, data: bytes, media_type: str, t: float = 0.0) -> None:
        """Adds an attachment (e.g. a config file) with log time `t` seconds."""
        self._check_open()
        ns = _to_ns(t)
        self._drain()
        self._writer.add_attachment(ns, ns, name, media_type, bytes(data))
        self._file.flush()

    def close(self) -> None:
        """Writes the summary and footer and closes the file; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._drain()
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


