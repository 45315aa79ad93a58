"""Read fixed-layout topics out of an indexed MCAP file at chunk speed (millions of messages per second).

Per chunk: decompress it once, take each channel's (log_time, offset) pairs from its MessageIndex record, and
gather every message's payload with one numpy fancy index, then view the bytes as the structured dtype.
Only the summary's chunk indexes are parsed record by record; messages never are. Topics whose schema is not
a fixed-layout message (the events topic) are read with the generic reader.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.exceptions import McapError
from mcap.reader import make_reader

from acquisition.schemas.cdr import FixedMessage, SchemaError
from acquisition.schemas.events import Event
from acquisition.schemas.ros2msg import parse_fixed_message

EVENTS_TOPIC = "/events"  # acquisition.schemas.topics.EVENTS (topics imports the robot model; this need not)
_MESSAGE_HEADER = 1 + 8 + 2 + 4 + 8 + 8  # opcode, record length, channel id, sequence, log time, publish time
_PUBLISH_TIME_AT = 1 + 8 + 2 + 4 + 8


@dataclass
class TopicData:
    """Every message of one topic: host log times, device publish times (ns) and the decoded rows."""

    topic: str
    message: FixedMessage
    log_time: np.ndarray
    publish_time: np.ndarray
    rows: np.ndarray

    def __len__(self) -> int:
        return len(self.rows)


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise SchemaError(f"unsupported chunk compression {compression!r}")


def chunk_records(f, offset: int, length: int) -> bytes:
    """The decompressed records of the Chunk record at ``offset``."""
    f.seek(offset)
    raw = f.read(length)
    pos = 1 + 8  # opcode, record length
    _start, _end, size, _crc, clen = struct.unpack_from("<QQQIi", raw, pos)
    pos += 8 + 8 + 8 + 4 + 4
    compression = raw[pos : pos + clen].decode()
    pos += clen
    (records_len,) = struct.unpack_from("<Q", raw, pos)
    pos += 8
    return _decompress(compression, raw[pos : pos + records_len], size)


def _message_indexes(f, offset: int, length: int) -> dict[int, np.ndarray]:
    """The (log_time, offset) pairs of each channel in the MessageIndex records after a chunk."""
    f.seek(offset)
    raw = f.read(length)
    out, pos = {}, 0
    while pos < len(raw):
        record_len = struct.unpack_from("<Q", raw, pos + 1)[0]
        channel_id, pairs_len = struct.unpack_from("<HI", raw, pos + 9)
        out[channel_id] = np.frombuffer(raw, dtype="<u8", count=pairs_len // 8, offset=pos + 15).reshape(
            -1, 2
        )
        pos += 9 + record_len
    return out


def read_fixed_topics(path: str | Path, topics: list[str] | None = None) -> dict[str, TopicData]:
    """Every fixed-layout topic of an indexed MCAP file (a finished or recovered one), in log-time order."""
    path = Path(path)
    with open(path, "rb") as f:
        try:
            summary = make_reader(f).get_summary()
        except (McapError, struct.error, OSError, EOFError) as exc:
            raise SchemaError(
                f"{path}: unreadable summary ({exc}); a torn file? run `vslab sessions recover`"
            ) from exc
        if summary is None:
            raise SchemaError(f"{path}: no summary (a torn file? run `vslab sessions recover`)")
        wanted: dict[int, tuple[str, FixedMessage]] = {}
        for cid, channel in summary.channels.items():
            schema = summary.schemas.get(channel.schema_id)
            if (topics is not None and channel.topic not in topics) or schema is None:
                continue
            message = parse_fixed_message(schema.name, schema.data.decode())
            if message is not None and channel.message_encoding == "cdr":
                wanted[cid] = (channel.topic, message)
        parts: dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {cid: [] for cid in wanted}
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            present = [cid for cid in ci.message_index_offsets if cid in wanted]
            if not present:
                continue
            records = np.frombuffer(chunk_records(f, ci.chunk_start_offset, ci.chunk_length), dtype=np.uint8)
            first_index = min(ci.message_index_offsets.values())
            indexes = _message_indexes(f, first_index, ci.message_index_length)
            for cid in present:
                pairs = indexes[cid]
                size = wanted[cid][1].size
                at = pairs[:, 1].astype(np.int64)
                lengths = records[(at + 1)[:, None] + np.arange(8)].view("<u8").reshape(-1)
                if np.any(lengths != _MESSAGE_HEADER - 9 + size):
                    raise SchemaError(f"{path}: {wanted[cid][0]} has messages that are not {size} bytes")
                payload = records[(at + _MESSAGE_HEADER)[:, None] + np.arange(size)]
                stamp = records[(at + _PUBLISH_TIME_AT)[:, None] + np.arange(8)].view("<u8").reshape(-1)
                parts[cid].append((pairs[:, 0].astype(np.int64), stamp.astype(np.int64), payload))
    out = {}
    for cid, (topic, message) in wanted.items():
        chunks = parts[cid]
        if chunks:
            log_time = np.concatenate([c[0] for c in chunks])
            publish = np.concatenate([c[1] for c in chunks])
            payload = np.concatenate([c[2] for c in chunks])
        else:
            log_time = publish = np.zeros(0, np.int64)
            payload = np.zeros((0, message.size), np.uint8)
        order = np.argsort(log_time, kind="stable")
        rows = payload[order].reshape(-1).view(message.dtype)
        out[topic] = TopicData(topic, message, log_time[order], publish[order], rows)
    return out


def read_events(path: str | Path) -> list[tuple[int, Event]]:
    """The events topic of an MCAP file (generic reader: few, variable-size messages): (log_time, event)."""
    with open(path, "rb") as f:
        return [
            (m.log_time, Event.decode(m.data))
            for _, _, m in make_reader(f).iter_messages(topics=[EVENTS_TOPIC], log_time_order=True)
        ]
