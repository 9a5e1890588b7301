"""Reading MCAP run logs back: JSON channels decoded, other channels kept raw, damage named.

:func:`read_log` decodes the JSON channels into :attr:`Log.messages` and keeps the other
channels' messages (the scene's protobuf) undecoded in :attr:`Log.raw`. Logs of killed runs
stay readable: it keeps every chunk that reached the disk and says why reading stopped; a
finished log with a damaged chunk keeps every other chunk (through its chunk index).
"""

from __future__ import annotations

import dataclasses
import io
import json
from collections.abc import Collection
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from hmpc_cli.log.codecs import codec_errors
from hmpc_cli.log.damage import CONTENT_ERRORS
from hmpc_cli.log.recorder import NS_PER_S

__all__ = ["MCAP_MAGIC", "Log", "LogMessage", "RawMessage", "first_message", "log_finished",
           "read_log"]

MCAP_MAGIC = b"\x89MCAP0\r\n"

# Errors that mean "damaged, truncated or foreign file" while decoding MCAP records: any
# the content can raise (a corrupted length field asks for gigabytes: MemoryError; a
# length past the file's end, a record of the wrong type: TypeError, ...).
_DAMAGE_ERRORS = (McapError, *CONTENT_ERRORS, *codec_errors())


@dataclasses.dataclass
class LogMessage:
    """One decoded message; `t` in seconds, `log_time_ns` the exact MCAP log time."""

    topic: str
    t: float
    data: dict
    log_time_ns: int = 0


@dataclasses.dataclass
class RawMessage:
    """One message of a non-JSON channel (e.g. protobuf), undecoded.

    Attributes:
        topic: its topic.
        t: log time [s].
        data: the encoded message (decode protobuf with ``MessageClass.FromString``).
        encoding: the channel's message encoding (e.g. ``protobuf``).
        schema_name: the schema's name (e.g. ``foxglove.SceneUpdate``).
        log_time_ns: the exact MCAP log time.
    """

    topic: str
    t: float
    data: bytes
    encoding: str
    schema_name: str
    log_time_ns: int = 0


@dataclasses.dataclass
class Log:
    """Contents of a run log; `complete` is False for truncated or damaged files.

    `messages` and `schemas` hold the JSON channels (decoded); `raw` the messages of the
    other channels undecoded, `raw_schemas` their schema records by topic. `damage` says
    why reading stopped at a chunk that failed its CRC, decompression or decoding (""
    otherwise, also for a file that merely ends early); damaged in what was read (see
    :func:`read_log`'s ``topics``).
    """

    messages: list[LogMessage]
    metadata: dict[str, dict[str, str]]
    attachments: dict[str, bytes]
    schemas: dict[str, dict]
    complete: bool
    damage: str = ""
    raw: list[RawMessage] = dataclasses.field(default_factory=list)
    raw_schemas: dict[str, Schema] = dataclasses.field(default_factory=dict)

    def topic(self, name: str) -> list[LogMessage]:
        """Returns the messages on topic `name`, in file order."""
        return [m for m in self.messages if m.topic == name]

    def raw_topic(self, name: str) -> list[RawMessage]:
        """Returns the undecoded messages on (non-JSON) topic `name`, in file order."""
        return [m for m in self.raw if m.topic == name]

    def _add(self, channel: Channel, schema: Schema | None, msg: Message,
             out: list[LogMessage], raw: list[RawMessage],
             topics: Collection[str] | None = None) -> None:
        """Files one message: JSON ones decoded into `out`, others into `raw`.

        A message whose topic is not in `topics` (None: every topic) is skipped.
        """
        if topics is not None and channel.topic not in topics:
            return
        if channel.message_encoding == "json":
            out.append(_message(channel, msg))
        else:
            raw.append(RawMessage(channel.topic, msg.log_time / NS_PER_S, msg.data,
                                  channel.message_encoding,
                                  schema.name if schema is not None else "", msg.log_time))

    def _add_channel(self, channel: Channel, schema: Schema | None) -> None:
        """Files one channel's schema (JSON schemas decoded)."""
        if channel.message_encoding == "json":
            self.schemas[channel.topic] = _schema_dict(schema)
        elif schema is not None:
            self.raw_schemas[channel.topic] = schema


def _message(channel: Channel, msg: Message) -> LogMessage:
    data = json.loads(msg.data)
    if not isinstance(data, dict):  # every JSON message of a run log is an object
        raise TypeError(f"{channel.topic}: a JSON message that is not an object")
    return LogMessage(channel.topic, msg.log_time / NS_PER_S, data, msg.log_time)


def _schema_dict(schema: Schema | None) -> dict:
    data = json.loads(schema.data) if schema is not None and schema.data else {}
    if not isinstance(data, dict):
        raise TypeError(f"schema {schema.name}: not a JSON object")
    return data


def _read_indexed(path: Path, topics: Collection[str] | None = None) -> Log:
    """Reads a finished file through its summary section (SeekingReader)."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        log = Log([], {}, {}, {}, complete=True)
        if summary is not None:
            for ch in summary.channels.values():
                log._add_channel(ch, summary.schemas.get(ch.schema_id))
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            if channel.topic not in log.schemas and channel.topic not in log.raw_schemas:
                log._add_channel(channel, schema)
            log._add(channel, schema, msg, log.messages, log.raw, topics)
        # the messages read whole: a damaged metadata or attachment record does not lose them
        damage = []
        try:
            log.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        except _DAMAGE_ERRORS as exc:
            damage.append(_damage_text("its metadata records are damaged, left out", exc))
        try:
            log.attachments = {a.name: a.data for a in reader.iter_attachments()}
        except _DAMAGE_ERRORS as exc:
            damage.append(_damage_text("its attachments are damaged, left out", exc))
        log.damage = "; ".join(damage)
    return log


def _read_chunks(path: Path, topics: Collection[str] | None = None) -> Log:
    """A finished file with damaged chunks: the intact ones, read through the chunk index.

    Every chunk is CRC-checked; a damaged one is left out whole and named in ``damage``.

    Raises:
        McapError (or a content error): no usable summary or chunk index; no chunk is
            damaged (the indexed read failed for another reason) or every one is (the
            index itself may be wrong): a linear scan says why.
    """
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        if summary is None or not summary.chunk_indexes:
            raise McapError("no chunk index")
        log = Log([], {}, {}, {}, complete=False)
        for ch in summary.channels.values():
            log._add_channel(ch, summary.schemas.get(ch.schema_id))
        index = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        bad: list[str] = []
        for k, entry in enumerate(index):
            f.seek(entry.chunk_start_offset)
            pending: list[LogMessage] = []
            pending_raw: list[RawMessage] = []
            try:  # a chunk is kept only as a whole, as in a linear scan
                chunk = next(StreamReader(io.BytesIO(f.read(entry.chunk_length)),
                                          skip_magic=True, emit_chunks=True).records)
                if not isinstance(chunk, Chunk):
                    raise McapError("the chunk index points at no chunk")
                for r in breakup_chunk(chunk, validate_crc=True):
                    if isinstance(r, Message):
                        channel = summary.channels[r.channel_id]
                        log._add(channel, summary.schemas.get(channel.schema_id), r,
                                 pending, pending_raw, topics)
            except (*_DAMAGE_ERRORS, StopIteration) as exc:
                bad.append(f"chunk {k + 1} (t = {entry.message_start_time / NS_PER_S:.3f}-"
                           f"{entry.message_end_time / NS_PER_S:.3f} s) "
                           f"{_damage_text('is damaged', exc)}")
                continue
            log.messages.extend(pending)
            log.raw.extend(pending_raw)
        # no chunk damaged, or every one (then the index itself may be wrong): a linear
        # scan says why
        if not bad or len(bad) == len(index):
            raise McapError("the chunk index does not tell the damage apart")
        f.seek(0)
        reader = make_reader(f)
        log.metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        log.attachments = {a.name: a.data for a in reader.iter_attachments()}
    log.damage = (f"{len(bad)} of {len(index)} chunks left out: " + "; ".join(bad[:3])
                  + ("; ..." if len(bad) > 3 else ""))
    return log


def _damage_text(what: str, exc: BaseException) -> str:
    """Why a linear scan stopped at a chunk, for :attr:`Log.damage`."""
    detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    return f"{what} ({detail[:120]})"


def _read_stream(path: Path, topics: Collection[str] | None = None,
                 finished: bool = False) -> Log:
    """Reads records front to back, keeping every fully written chunk.

    ``finished``: the file ends with its footer's magic, so a record that cannot be read
    is damage, not the end of a file cut short.
    """
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    log = Log([], {}, {}, {}, complete=False)

    def handle(record: Any, out: list[LogMessage], raw: list[RawMessage]) -> None:
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
            log._add_channel(record, schemas.get(record.schema_id))
        elif isinstance(record, Message):
            channel = channels[record.channel_id]
            log._add(channel, schemas.get(channel.schema_id), record, out, raw, topics)
        elif isinstance(record, Metadata):
            log.metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Attachment):
            log.attachments[record.name] = record.data

    saw_footer = False
    with open(path, "rb") as f:
        records = StreamReader(f, emit_chunks=True).records
        while (record := _next_record(records, log, finished)) is not None:
            pending: list[LogMessage] = []
            pending_raw: list[RawMessage] = []
            try:  # a chunk is kept only as a whole: CRC-checked, every message decoded
                chunk = isinstance(record, Chunk)
                for r in breakup_chunk(record, validate_crc=True) if chunk else [record]:
                    handle(r, pending, pending_raw)
            except _DAMAGE_ERRORS as exc:
                log.damage = _damage_text("a chunk is damaged", exc)
                return log  # corrupt chunk: stop at the last good one
            log.messages.extend(pending)
            log.raw.extend(pending_raw)
            saw_footer = saw_footer or isinstance(record, Footer)
    log.complete = saw_footer
    return log


def _next_record(records: Any, log: Log, finished: bool) -> Any:
    """The stream's next record, or None at its end or at a record that cannot be read.

    Such a record ends a file cut short (the records before it kept); in a ``finished``
    file (it ends with its footer) it is damage, named in ``log.damage``.
    """
    try:
        return next(records)
    except StopIteration:
        return None
    except _DAMAGE_ERRORS as exc:
        if finished:
            log.damage = _damage_text("a record is damaged, though the file ends with its "
                                      "footer", exc)
        return None


def read_log(path: str | Path, topics: Collection[str] | None = None) -> Log:
    """Reads a run log; truncated files yield the completed chunks with complete=False.

    ``topics``: only these topics' messages are kept (None: every topic). Every chunk is
    still read, CRC-checked and decompressed; the messages of other topics are not
    decoded, so a malformed one of them inside a chunk whose CRC holds (a writer's bug, a
    foreign file) is not seen: such a log reads complete here and damaged in full.
    """
    path = Path(path)
    with open(path, "rb") as f:
        head = f.read(8)
        tail = b""
        if f.seek(0, 2) >= 16:
            f.seek(-8, 2)
            tail = f.read(8)
    if head != MCAP_MAGIC:
        raise ValueError(f"{path} is not an MCAP file" + (
            " (it reads as text: a summary.json or a scenario?)"
            if head and all(32 <= b < 127 or b in b"\t\r\n" for b in head) else ""))
    log = _read(path, topics, tail == MCAP_MAGIC)
    bad = _damaged_attachments(path)
    for name in bad:  # left out: a damaged scenario must not pass for the run's
        log.attachments.pop(name, None)
    if bad:
        said = f"attachment(s) {', '.join(map(repr, bad))} damaged (CRC), left out"
        log.damage = f"{log.damage}; {said}" if log.damage else said
    return log


def _read(path: Path, topics: Collection[str] | None, finished: bool) -> Log:
    """The log through its index, its chunk index or a linear scan, the first that works."""
    if finished:
        try:
            return _read_indexed(path, topics)
        except (*_DAMAGE_ERRORS, OSError):
            pass  # footer present but file damaged: the intact chunks through the index
        try:
            return _read_chunks(path, topics)
        except (*_DAMAGE_ERRORS, OSError, StopIteration):
            pass  # no usable index: a linear scan up to the damage
    return _read_stream(path, topics, finished)


_ATTACHMENT = 0x09  # MCAP opcodes: attachment and the data end (the data section's last)
_DATA_END = 0x0F


def _damaged_attachments(path: Path) -> list[str]:
    """The names of the attachments whose CRC does not match their record.

    Walks the top-level records (opcode, length) from the magic to the data end, reading
    only the attachments' bodies; stops quietly at a length past the file's end (the
    readers say what is wrong there). The mcap reader skips the attachment CRC.
    """
    import struct
    import zlib

    bad = []
    with open(path, "rb") as f:
        size = f.seek(0, 2)
        pos = len(MCAP_MAGIC)
        while pos + 9 <= size:
            f.seek(pos)
            op, length = struct.unpack("<BQ", f.read(9))
            if op == _DATA_END or pos + 9 + length > size:
                break
            if op == _ATTACHMENT and length >= 4:
                body = f.read(length)
                stored = int.from_bytes(body[-4:], "little")
                if stored and zlib.crc32(body[:-4]) != stored:
                    bad.append(_attachment_name(body))
            pos += 9 + length
    return bad


def _attachment_name(body: bytes) -> str:
    """An attachment record's name (after its two 8-byte times), as far as it decodes."""
    n = int.from_bytes(body[16:20], "little")
    return body[20:20 + n].decode("utf-8", "replace") if n < len(body) else "?"


def first_message(path: str | Path, topic: str) -> dict | None:
    """The first JSON message on ``topic`` of a log (e.g. /run/info), or None.

    Reads only as far as that message (through the index of a finished file); None when
    the file is missing, unreadable or has no such message: for quick looks, not
    diagnosis (:func:`read_log` says what is wrong).
    """
    try:
        with open(path, "rb") as f:
            for _, _, msg in make_reader(f).iter_messages(topics=[topic]):
                data = json.loads(msg.data)
                return data if isinstance(data, dict) else None
    except (OSError, ValueError, McapError, *_DAMAGE_ERRORS):
        return None
    return None


_FINISHED: dict[tuple, bool] = {}


def log_finished(path: str | Path, summary: bool = True) -> bool:
    """Whether the run log at ``path`` reads back complete with its /run/summary.

    Complete: the file ends with its footer and summary section (as :func:`read_log`
    says ``complete``), its statistics count a /run/summary message, and that message
    (the last chunk, CRC-checked) decodes to a JSON object. False for a missing, empty,
    cut-short, damaged or foreign file. Cheap (the summary section and one chunk, not the
    whole log), and remembered per (path, size, modification time) in this process.
    ``summary`` False: complete is enough (a run that crashed has no /run/summary).
    """
    path = Path(path)
    try:
        st = path.stat()
    except OSError:
        return False
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, summary)
    if key not in _FINISHED:
        _FINISHED[key] = _log_finished(path, summary)
    return _FINISHED[key]


def _log_finished(path: Path, need_summary: bool) -> bool:
    try:
        with open(path, "rb") as f:
            if f.read(8) != MCAP_MAGIC or f.seek(0, 2) < 16:
                return False
            f.seek(-8, 2)
            if f.read(8) != MCAP_MAGIC:
                return False
            f.seek(0)
            reader = make_reader(f, validate_crcs=True)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                return False
            if not need_summary:
                return True
            ids = [i for i, ch in summary.channels.items() if ch.topic == "/run/summary"]
            if not any(summary.statistics.channel_message_counts.get(i, 0) for i in ids):
                return False
            for _, _, msg in reader.iter_messages(topics=["/run/summary"]):
                if isinstance(json.loads(msg.data), dict):
                    return True
    except (*_DAMAGE_ERRORS, OSError):
        return False
    return False
