"""Tests for the MCAP recorder / reader."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hmpc_cli.log import recorder
from hmpc_cli.log.codecs import ZSTD_LEVEL
from hmpc_cli.log.reader import Log, read_log
from hmpc_cli.log.recorder import Recorder, to_json_bytes

REPO = Path(__file__).resolve().parents[1]

STATE_SCHEMA = {
    "type": "object",
    "properties": {"k": {"type": "integer"}, "x": {"type": "array", "items": {"type": "number"}}},
}
INFO_SCHEMA = {"type": "object", "properties": {"msg": {"type": "string"}}}


@dataclasses.dataclass
class Sample:
    name: str
    values: np.ndarray
    gain: float


def _write_run(path: Path, n: int = 300, **kwargs) -> None:
    with Recorder(path, **kwargs) as rec:
        rec.add_topic("/state", "hmpc.State", STATE_SCHEMA)
        rec.add_topic("/info", "hmpc.Info", INFO_SCHEMA)
        rec.add_metadata("run", {"scenario": "hopper", "seed": "7"})
        for k in range(n):
            t = k * 0.001
            rec.write("/state", t, {"k": k, "x": np.array([k, -k, 0.5 * k])})
            if k % 10 == 0:
                rec.write("/info", t, {"msg": f"step {k}"})


def test_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    times = [0.0, 1e-9, 0.001, 1.234567891, 12.5, 3600.000000001]
    with Recorder(path, flush_every=2, chunk_size=64) as rec:
        rec.add_topic("/state", "hmpc.State", STATE_SCHEMA)
        rec.add_topic("/info", "hmpc.Info", INFO_SCHEMA)
        rec.add_topic("/nested", "hmpc.State", STATE_SCHEMA)  # shares the schema
        rec.add_metadata("config", {"horizon": "20", "solver": "ipopt"})
        rec.add_attachment("scenario.toml", b"[run]\nname = 'x'\n\x00\xff", "text/plain", t=0.5)
        for k, t in enumerate(times):
            rec.write("/state", t, {"k": k, "x": np.array([1.5, np.nan, k], dtype=np.float32)})
            rec.write("/info", t, {"msg": f"ü{k}", "flag": np.bool_(k % 2)})
        nested = {"b": [1, (2, np.float64(np.inf))], "c": {"d": np.int64(4)}}
        rec.write("/nested", 2.0, {"a": nested, "s": Sample("p", np.arange(3), float("nan"))})

    log = read_log(path)
    assert isinstance(log, Log)
    assert log.complete is True
    assert [m.topic for m in log.messages[:4]] == ["/state", "/info", "/state", "/info"]
    assert len(log.messages) == 2 * len(times) + 1

    state = log.topic("/state")
    assert [m.t for m in state] == times
    assert [m.log_time_ns for m in state] == [round(t * 1e9) for t in times]
    assert state[3].log_time_ns == 1_234_567_891
    assert state[5].log_time_ns == 3_600_000_000_001
    assert state[2].data == {"k": 2, "x": [1.5, None, 2.0]}

    info = log.topic("/info")
    assert [m.data["msg"] for m in info] == [f"ü{k}" for k in range(len(times))]
    assert [m.data["flag"] for m in info] == [bool(k % 2) for k in range(len(times))]

    (nested,) = log.topic("/nested")
    assert nested.t == 2.0
    assert nested.data == {
        "a": {"b": [1, [2, None]], "c": {"d": 4}},
        "s": {"name": "p", "values": [0, 1, 2]},  # a NaN field is left out, not null
    }

    assert log.metadata == {"config": {"horizon": "20", "solver": "ipopt"}}
    assert log.attachments == {"scenario.toml": b"[run]\nname = 'x'\n\x00\xff"}
    assert log.schemas == {"/state": STATE_SCHEMA, "/info": INFO_SCHEMA, "/nested": STATE_SCHEMA}
    assert log.topic("/missing") == []


def test_file_uses_standard_encodings(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    path = tmp_path / "run.mcap"
    _write_run(path, n=20)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert reader.get_header().profile == ""
    assert {c.message_encoding for c in summary.channels.values()} == {"json"}
    assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
    assert summary.statistics.message_count == 22


def test_to_json_bytes_non_finite_and_deterministic() -> None:
    payload = {
        "nan": float("nan"),
        "inf": float("inf"),
        "ninf": -math.inf,
        "arr": np.array([[np.nan, 1.0], [np.inf, -np.inf]]),
        "np_scalar": np.float32(np.nan),
        "list": [1, float("nan"), (np.inf, 2.5)],
        "deep": {"x": {"y": [np.float64("-inf")]}},
        "int": np.int32(-3),
        "dc": Sample("s", np.array([np.nan, 1.0]), np.inf),
    }
    out = to_json_bytes(payload)
    assert b"NaN" not in out and b"Infinity" not in out
    assert b" " not in out  # compact separators
    # a non-finite field of an object is left out (a schema's number admits no null);
    # inside an array it stays in place as null (the other elements keep their index)
    assert json.loads(out) == {
        "arr": [[None, 1.0], [None, None]],
        "list": [1, None, [None, 2.5]],
        "deep": {"x": {"y": [None]}},
        "int": -3,
        "dc": {"name": "s", "values": [None, 1.0]},
    }
    assert to_json_bytes(payload) == out
    assert to_json_bytes(dict(payload)) == out
    assert to_json_bytes({"a": 1, "b": [1.5, 2]}) == b'{"a":1,"b":[1.5,2]}'


def test_to_json_bytes_rejects_unknown_types() -> None:
    with pytest.raises(TypeError):
        to_json_bytes({"x": object()})


def test_killed_writer_keeps_flushed_chunks(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(
        f"""
        import os, signal
        import numpy as np
        from hmpc_cli.log.recorder import Recorder
        rec = Recorder({str(path)!r}, flush_every=100)
        rec.add_metadata("run", {{"seed": "1"}})
        rec.add_topic("/state", "hmpc.State", {{"type": "object"}})
        for k in range(5050):
            rec.write("/state", k * 0.01, {{"k": k, "x": np.array([k, 0.5 * k, np.nan])}})
        os.kill(os.getpid(), signal.SIGKILL)
        rec.close()
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        timeout=120,
    )
    assert proc.returncode == -9, proc.stderr.decode()

    log = read_log(path)
    assert log.complete is False
    assert 5000 <= len(log.messages) <= 5050  # everything up to the last flush
    for k, m in enumerate(log.messages):
        assert m.topic == "/state"
        assert m.log_time_ns == k * 10_000_000
        assert m.data == {"k": k, "x": [k, 0.5 * k, None]}
    assert log.metadata == {"run": {"seed": "1"}}
    assert log.schemas == {"/state": {"type": "object"}}


def _chunk_message_count(path: Path, chunk_index) -> int:
    from mcap.data_stream import ReadDataStream
    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk

    with open(path, "rb") as f:
        f.seek(chunk_index.chunk_start_offset + 1 + 8)
        chunk = Chunk.read(ReadDataStream(f))
    return sum(isinstance(r, Message) for r in breakup_chunk(chunk))


@pytest.mark.parametrize("compressed", [True, False])
@pytest.mark.parametrize("frac", [0.0, 0.01, 0.5, 0.999, 1.0])
def test_truncated_last_chunk(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, frac: float, compressed: bool
) -> None:
    from mcap.reader import make_reader
    from mcap.writer import CompressionType

    if not compressed:
        monkeypatch.setattr(recorder, "mcap_compression", lambda: CompressionType.NONE)
    full = tmp_path / "full.mcap"
    _write_run(full, n=400, flush_every=50)
    complete = read_log(full)
    assert complete.complete and len(complete.messages) == 440

    with open(full, "rb") as f:
        summary = make_reader(f).get_summary()
    assert len(summary.chunk_indexes) >= 5
    (compression,) = {c.compression for c in summary.chunk_indexes}
    assert compression in (("zstd", "lz4") if compressed else ("",))
    last = max(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    # cut 1 byte .. all but the opcode byte off the end of the last chunk record
    cut = min(max(1, int(frac * last.chunk_length)), last.chunk_length - 1)
    cut_file = tmp_path / "cut.mcap"
    shutil.copy(full, cut_file)
    with open(cut_file, "r+b") as f:
        f.truncate(last.chunk_start_offset + last.chunk_length - cut)

    log = read_log(cut_file)
    assert log.complete is False
    kept = len(log.messages)
    assert kept == len(complete.messages) - _chunk_message_count(full, last)
    assert [(m.topic, m.log_time_ns, m.data) for m in log.messages] == [
        (m.topic, m.log_time_ns, m.data) for m in complete.messages[:kept]
    ]
    assert log.metadata == complete.metadata
    assert log.schemas == complete.schemas


def test_truncated_summary_keeps_all_messages(tmp_path: Path) -> None:
    full = tmp_path / "full.mcap"
    _write_run(full, n=100)
    cut_file = tmp_path / "cut.mcap"
    data = full.read_bytes()
    cut_file.write_bytes(data[:-20])  # footer damaged, all chunks intact
    log = read_log(cut_file)
    assert log.complete is False
    assert len(log.messages) == len(read_log(full).messages) == 110


def test_header_only_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.mcap"
    rec = Recorder(path)
    rec.add_topic("/state", "hmpc.State", STATE_SCHEMA)
    shutil.copy(path, tmp_path / "snapshot.mcap")  # as if killed right after start
    rec.close()
    log = read_log(tmp_path / "snapshot.mcap")
    assert log.complete is False and log.messages == []
    finished = read_log(path)
    assert finished.complete is True and finished.messages == []
    assert finished.schemas == {"/state": STATE_SCHEMA}


@pytest.mark.parametrize("content", [b"", b"hello world, not an mcap file", b"\x89MCAP"])
def test_not_mcap_raises(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "bogus.mcap"
    path.write_bytes(content)
    with pytest.raises(ValueError, match="bogus.mcap"):
        read_log(path)


def test_topic_registration_errors(tmp_path: Path) -> None:
    with Recorder(tmp_path / "r.mcap") as rec:
        rec.add_topic("/state", "hmpc.State", STATE_SCHEMA)
        with pytest.raises(ValueError, match="/state"):
            rec.add_topic("/state", "hmpc.State", STATE_SCHEMA)
        with pytest.raises(KeyError, match="/nope"):
            rec.write("/nope", 0.0, {"k": 1})
        with pytest.raises(ValueError):
            rec.write("/state", -1.0, {"k": 1})
        with pytest.raises(ValueError):
            rec.write("/state", float("nan"), {"k": 1})
        rec.write("/state", 0.0, {"k": 1})
    assert len(read_log(tmp_path / "r.mcap").messages) == 1


def test_close_is_idempotent(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    rec = Recorder(path)
    rec.add_topic("/a", "A", {"type": "object"})
    rec.write("/a", 0.1, {"v": 1})
    rec.close()
    size = path.stat().st_size
    rec.close()
    assert rec.closed and path.stat().st_size == size
    with pytest.raises(ValueError):
        rec.write("/a", 0.2, {"v": 2})
    assert read_log(path).complete


def test_exit_on_exception_still_finishes_file(tmp_path: Path) -> None:
    path = tmp_path / "r.mcap"
    with pytest.raises(RuntimeError), Recorder(path) as rec:
        rec.add_topic("/a", "A", {"type": "object"})
        rec.write("/a", 0.0, {"v": 1})
        raise RuntimeError("boom")
    log = read_log(path)
    assert log.complete and [m.data for m in log.messages] == [{"v": 1}]


def test_chunks_are_zstd_at_the_recorders_level(tmp_path: Path) -> None:
    """mcap's Writer has no level setting: the recorder's chunks are zstd at ZSTD_LEVEL."""
    import zstandard
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    path = tmp_path / "level.mcap"
    _write_run(path, n=2000)
    _write_run(tmp_path / "again.mcap", n=10)  # a second recorder: the stand-in not stacked
    import mcap.writer

    assert type(mcap.writer.zstandard).__name__ == "_ZstdAtLevel"
    assert mcap.writer.zstandard.module is zstandard
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) >= 2 and all(c.compression == "zstd" for c in chunks)
    for c in chunks:
        raw = zstandard.decompress(c.data, max_output_size=c.uncompressed_size)
        assert c.data == zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress(raw)
        assert c.data != zstandard.ZstdCompressor(level=3).compress(raw)
    assert len(read_log(path).messages) == 2000 + 2000 // 10


def test_queued_messages_keep_their_order_around_metadata_and_attachments(
        tmp_path: Path) -> None:
    """Messages reach mcap's writer at flushes: in call order, nothing lost at close."""
    path = tmp_path / "order.mcap"
    with Recorder(path, flush_every=7) as rec:
        rec.add_topic("/a", "hmpc.Info", INFO_SCHEMA)
        rec.add_topic("/b", "hmpc.Info", INFO_SCHEMA)
        for k in range(50):
            rec.write("/a" if k % 3 else "/b", k * 0.1, {"msg": str(k)})
            if k == 20:
                rec.add_metadata("mid", {"k": "20"})
                rec.add_attachment("note.txt", b"hello", "text/plain", t=2.0)
    log = read_log(path)
    assert log.complete
    assert [m.data["msg"] for m in log.messages] == [str(k) for k in range(50)]
    assert [m.topic for m in log.messages] == ["/a" if k % 3 else "/b" for k in range(50)]
    assert log.metadata["mid"] == {"k": "20"}


@pytest.mark.parametrize("chunk_size", [256 * 1024, 700])  # 700 B: chunks close mid-batch
def test_batched_messages_are_the_bytes_of_add_message(tmp_path: Path, chunk_size) -> None:
    """The recorder's one-loop path writes exactly what mcap's add_message calls write."""
    import io

    from mcap.writer import Writer

    from hmpc_cli.log.codecs import add_messages

    rng = np.random.default_rng(3)
    batches = [[(1 + int(rng.integers(2)), int(t), bytes(rng.integers(0, 255, int(n),
                                                                      dtype=np.uint8)), s)
                for s, (t, n) in enumerate(zip(rng.integers(0, 10**9, 40),
                                               rng.integers(0, 90, 40), strict=True))]
               for _ in range(5)]  # times out of order too
    files = []
    for batched in (True, False):
        out = io.BytesIO()
        w = Writer(out, chunk_size=chunk_size)
        w.start()
        schema = w.register_schema("s", "jsonschema", b"{}")
        for topic in ("/a", "/b"):
            w.register_channel(topic, "json", schema)
        for batch in batches:
            if batched:
                add_messages(w, batch)
            else:
                for channel, ns, data, seq in batch:
                    w.add_message(channel, ns, data, ns, seq)
            w.flush()
        w.finish()
        files.append(out.getvalue())
    assert files[0] == files[1]
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    chunks = [r for r in StreamReader(io.BytesIO(files[0]), emit_chunks=True).records
              if isinstance(r, Chunk)]
    assert len(chunks) >= (5 if chunk_size == 256 * 1024 else 10)
