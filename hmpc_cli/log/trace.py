"""A run's trajectory log: the topics that trajectory figures read, copied from its run log.

``trace.mcap`` beside a run's ``run.mcap`` holds /run/info, /sim/state, /sim/event,
/disturbance, /planner/plan and /run/summary as the run log has them (same schemas,
channels, log times and bytes), without the MPC's plans and the 3D scene: a few percent of
the log, small enough for a results page to commit the trajectories it draws.
:func:`hmpc_cli.log.rundata.read_run` reads it like a run log (its other topics empty).
Of the MPC's solves it keeps one fact, in a metadata record: the nodes each periodic
re-solve shifted its plan by (:func:`period_shifts`).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["TRACE_NAME", "TRACE_TOPICS", "period_shifts", "write_trace"]

#: the file name of a run's trajectory log (beside its run.mcap)
TRACE_NAME = "trace.mcap"
#: zstd level of a trajectory log's chunks (written once, committed: small over fast)
TRACE_ZSTD_LEVEL = 19
#: the metadata record holding the periodic re-solves' node shifts
SHIFTS_RECORD = "hmpc.period_shifts"
#: the topics a trajectory log keeps
TRACE_TOPICS = ("/run/info", "/sim/state", "/sim/event", "/disturbance", "/planner/plan",
                "/run/summary")


def write_trace(log: str | Path, out: str | Path | None = None) -> Path:
    """Writes the trajectory log of the run log ``log``; returns its path.

    Args:
        log: a run.mcap.
        out: the file to write (default: ``trace.mcap`` beside ``log``); replaced
            atomically, so a reader never sees half of it.

    Raises:
        ValueError: ``log`` cannot be read as an MCAP file.
    """
    from mcap.exceptions import McapError
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    from hmpc_cli.log.codecs import codec_errors, zstd_level
    from hmpc_cli.log.damage import CONTENT_ERRORS

    log = Path(log)
    out = Path(out) if out is not None else log.with_name(TRACE_NAME)
    tmp = out.with_name(f".{out.name}.tmp")
    try:
        with open(log, "rb") as src, open(tmp, "wb") as dst, zstd_level(TRACE_ZSTD_LEVEL):
            writer = Writer(dst, chunk_size=1024 * 1024, compression=CompressionType.ZSTD,
                            repeat_schemas=True, repeat_channels=True)
            writer.start(profile="", library="hmpc trace")
            schemas: dict[int, int] = {}
            channels: dict[int, int] = {}
            shifts: list[int] = []
            for schema, channel, message in make_reader(src).iter_messages(
                    topics=[*TRACE_TOPICS, "/mpc/solve"], log_time_order=True):
                if channel.topic not in TRACE_TOPICS:
                    shifts += _period_shift(message.data)
                    continue
                if schema is not None and schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(
                        schema.name, schema.encoding, schema.data)
                if channel.id not in channels:
                    channels[channel.id] = writer.register_channel(
                        channel.topic, channel.message_encoding,
                        schemas.get(schema.id, 0) if schema is not None else 0,
                        dict(channel.metadata))
                writer.add_message(channels[channel.id], message.log_time, message.data,
                                   message.publish_time, message.sequence)
            if shifts:
                writer.add_metadata(SHIFTS_RECORD, {"shifted": " ".join(map(str, shifts))})
            writer.finish()
        os.replace(tmp, out)
    except (OSError, McapError, *CONTENT_ERRORS, *codec_errors()) as exc:
        tmp.unlink(missing_ok=True)
        raise ValueError(f"{log}: cannot copy its trajectory ({exc})") from None
    return out


def _period_shift(data: bytes) -> list[int]:
    """[the nodes shifted] of an /mpc/solve message of a periodic re-solve that logs it."""
    import json

    try:
        msg = json.loads(data)
    except ValueError:
        return []
    shifted = (msg.get("detail") or {}).get("shifted") if isinstance(msg, dict) else None
    return [int(shifted)] if msg.get("reason") == "period" and isinstance(shifted, int) else []


def period_shifts(path: str | Path) -> tuple[int, ...]:
    """The nodes each periodic re-solve shifted by, as a trajectory log records them.

    Empty for a log without the record (a run log: read its /mpc/solve instead).

    Raises:
        ValueError: ``path`` cannot be read as an MCAP file.
    """
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            for record in make_reader(f).iter_metadata():
                if record.name == SHIFTS_RECORD:
                    return tuple(int(k) for k in record.metadata.get("shifted", "").split())
    except (OSError, McapError) as exc:
        raise ValueError(f"{path}: cannot read its metadata ({exc})") from None
    return ()
