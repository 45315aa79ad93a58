"""Read fixed-layout topics out of an indexed MCAP file at chunk speed (millions of messages per second).

Per chunk: decompress it once, take each channel's (log_time, offset) pairs from its MessageIndex record, and
gather every message's payload with one numpy fancy index (``mcap_reader.fixed_size_messages``), then view the
bytes as the topic's structured dtype. Topics whose schema is not a fixed-layout message (the events topic)
are read with the generic reader.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from acquisition.schemas import mcap_reader
from acquisition.schemas.cdr import FixedMessage, SchemaError
from acquisition.schemas.events import EVENTS, Event
from acquisition.schemas.ros2msg import parse_fixed_message
from acquisition.storage import as_path


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


def read_fixed_topics(
    path: str | Path, topics: list[str] | None = None, damaged: list[mcap_reader.ChunkDamage] | None = None
) -> dict[str, TopicData]:
    """Every fixed-layout topic of an indexed MCAP file (a finished or recovered one), in log-time order.
    Every chunk read is checked (CRC, message index): a damaged one raises ``DamagedChunkError`` naming the
    file and the chunk's offset, or, given a ``damaged`` list, is added to it and its messages left out."""
    return read_topics(path, topics, set(), damaged)[0]


def read_topics(
    path: str | Path,
    topics: list[str] | None,
    others: set[str],
    damaged: list[mcap_reader.ChunkDamage] | None = None,
) -> tuple[dict[str, TopicData], list[tuple[int, int, int, bytes]]]:
    """``read_fixed_topics`` and, in the same pass over the chunks, (channel id, log time, publish time,
    payload) of every message of the ``others`` topics (any layout, e.g. events): each chunk read once."""
    path = as_path(path)
    with path.open("rb") as f:
        summary = mcap_reader.read_summary(f)
        if summary is None:
            raise SchemaError(f"{path}: no readable summary (a torn file? run `vslab sessions recover`)")
        return read_open_topics(f, summary, path, topics, others, damaged)


def read_open_topics(
    f: BinaryIO,
    summary: mcap_reader.Summary,
    path: Path,
    topics: list[str] | None,
    others: set[str],
    damaged: list[mcap_reader.ChunkDamage] | None = None,
) -> tuple[dict[str, TopicData], list[tuple[int, int, int, bytes]]]:
    """``read_topics`` of a file already open at ``path`` whose ``summary`` was read (nothing read twice)."""
    wanted: dict[int, tuple[str, FixedMessage]] = {}
    for cid, channel in summary.channels.items():
        schema = summary.schemas.get(channel.schema_id)
        if (topics is not None and channel.topic not in topics) or schema is None:
            continue
        message = parse_fixed_message(schema.name, schema.data.decode())
        if message is not None and channel.message_encoding == "cdr":
            wanted[cid] = (channel.topic, message)
    other_ids = {cid for cid, c in summary.channels.items() if c.topic in others and cid not in wanted}
    try:
        parts, rest = mcap_reader.chunk_messages(
            f, summary, {cid: m.size for cid, (_, m) in wanted.items()}, other_ids, damaged
        )
    except mcap_reader.DamagedChunkError as exc:
        raise mcap_reader.DamagedChunkError(exc.damage, summary, path) from exc
    except SchemaError as exc:
        raise SchemaError(f"{path}: {exc}") from exc
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
        if len(log_time) > 1 and not np.all(log_time[1:] >= log_time[:-1]):  # chunks overlap in time
            order = np.argsort(log_time, kind="stable")
            log_time, publish, payload = log_time[order], publish[order], payload[order]
        out[topic] = TopicData(topic, message, log_time, publish, payload.reshape(-1).view(message.dtype))
    return out, rest


def read_events(path: str | Path) -> list[tuple[int, Event]]:
    """The events topic of an MCAP file (generic reader: few, variable-size messages): (log_time, event)."""
    with as_path(path).open("rb") as f:
        return [(t, Event.decode(data)) for t, data in mcap_reader.topic_messages(f, [EVENTS])]
