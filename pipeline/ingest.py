"""Ingest: a session directory's MCAP parts → one table per topic (see ``pipeline.tables``).

Fixed-layout topics take the chunk-speed path (``read_open_topics``: whole chunks viewed as structured
arrays, turned into columns without a per-message loop). Any other topic is decoded message by message by
``acquisition.schemas.dynamic`` (correct, not fast; mcap-ros2-support is the tests' oracle for it, not a
dependency). A torn part (killed recorder, no summary) is read in memory up to the tear, with a warning; the
session directory is never written. User-causable problems raise ``IngestError`` (which file, and why).
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pandas as pd
from pydantic import ValidationError

from acquisition.schemas.cdr import FixedMessage, SchemaError
from acquisition.schemas.dynamic import DynamicMessage
from acquisition.schemas.events import Event
from acquisition.schemas.fast_read import read_open_topics
from acquisition.schemas.mcap_reader import (
    MAGIC,
    READ_ERRORS,
    Channel,
    ChunkDamage,
    Message,
    Metadata,
    RecordWalk,
    Schema,
    first_line,
    metadata_records,
    read_magic,
    read_summary,
)
from acquisition.schemas.ros2msg import parse_fixed_message
from acquisition.schemas.scene import STANDARD_TOPICS
from acquisition.schemas.session_card import SESSION_METADATA, as_current, readable_parts
from acquisition.schemas.topics import EVENTS, session_topics
from acquisition.storage import as_path
from models.robot import RobotDescription
from pipeline.cache import file_hash
from pipeline.errors import PipelineError
from pipeline.tables import EVENT_COLUMNS, SessionTables, StageReport

log = logging.getLogger(__name__)


class IngestError(PipelineError):
    """A session that cannot be ingested: ``path`` says which file or directory, ``reason`` why."""

    def __init__(self, path: str | Path, reason: str) -> None:
        self.path, self.reason = as_path(path), reason
        super().__init__(f"{path}: {reason}")


DAMAGED_CHUNKS = "damaged_chunks"  # StageReport.values key: one line per chunk left out as damaged
_FixedChunk = tuple[FixedMessage, np.ndarray, np.ndarray, np.ndarray]  # message, log, publish, rows


@dataclass
class _Part:
    """What one part holds: fixed topics as (message, log, publish, rows), other topics as rows."""

    metadata: dict[str, str] = field(default_factory=dict)
    fixed: dict[str, list[_FixedChunk]] = field(default_factory=dict)
    generic: dict[str, list[dict]] = field(default_factory=dict)
    events: list[tuple[int, Event]] = field(default_factory=list)
    topics: set[str] = field(default_factory=set)


def content_hash(parts: Iterable[Path]) -> str:
    """sha256 over the parts' bytes, in order (streamed)."""
    return file_hash(parts)


def ingest_session(directory: Path, generic_topics: Collection[str] = (), content: str | None = None
                   ) -> SessionTables:  # fmt: skip
    """Every part of the session in ``directory`` as tables. Topics in ``generic_topics`` are decoded by the
    generic (message by message) path even when the fast path could read them (for checks and comparisons).
    ``content``: the parts' ``content_hash`` where the caller has it already (not read again)."""
    directory = as_path(directory)
    if not directory.is_dir():
        raise IngestError(directory, "not a session directory")
    parts = readable_parts(directory)
    if not parts:
        what = "empty directory" if not any(directory.iterdir()) else "no MCAP parts (*.mcap)"
        raise IngestError(directory, f"session has no parts: {what}")
    report = StageReport()
    read = [_read_part_checked(p, set(generic_topics), report) for p in parts]
    metadata = next((r.metadata for r in read if r.metadata), None)
    if metadata is None:
        raise IngestError(parts[0], f"no {SESSION_METADATA!r} metadata record: not recorded by vslab")
    robot = _robot(parts[0], metadata)
    expected = set(session_topics(robot))
    for path, r in zip(parts, read, strict=True):
        for topic in sorted(expected - r.topics):
            report.warnings.append(f"{path.name}: no {topic} stream")
    streams: dict[str, pd.DataFrame] = {}
    for topic in sorted(set().union(*(r.fixed for r in read))):
        streams[topic] = _fixed_table([c for r in read for c in r.fixed.get(topic, [])])
    for topic in sorted(set().union(*(r.generic for r in read))):
        rows = [row for r in read for row in r.generic.get(topic, [])]
        streams[topic] = _generic_table(rows)
    events = _events_table([e for r in read for e in r.events])
    return SessionTables(
        session_id=metadata.get("session_id", directory.name),
        robot=robot,
        metadata=as_current({k: v for k, v in metadata.items() if k != "robot_description"}),
        streams=streams,
        events=events,
        report=report,
        content_hash=content or content_hash(parts),
    )


def _robot(path: Path, metadata: dict[str, str]) -> RobotDescription:
    try:
        return RobotDescription.model_validate_json(metadata["robot_description"])
    except KeyError:
        raise IngestError(path, "session metadata has no robot_description") from None
    except ValidationError as exc:
        raise IngestError(path, f"bad robot_description: {str(exc).splitlines()[0]}") from exc


# ------------------------------------------------------------------------------------------ one part
def _read_part_checked(path: Path, generic_topics: set[str], report: StageReport) -> _Part:
    """``_read_part``, with any damage it meets (a garbled schema, record or payload) as an IngestError."""
    try:
        return _read_part(path, generic_topics, report)
    except (SchemaError, *READ_ERRORS) as exc:
        raise IngestError(path, f"unreadable ({first_line(exc)}); truncated or corrupt?") from exc


def _read_part(path: Path, generic_topics: set[str], report: StageReport) -> _Part:
    with path.open("rb") as f:
        head = read_magic(f)
        if head != MAGIC:
            what = "not an MCAP file (no MCAP magic)" if head else "empty file (0 bytes)"
            raise IngestError(path, f"{what}: move it out of the session folder")
        return _read_open(f, path, generic_topics, report)


def _read_open(f: BinaryIO, path: Path, generic_topics: set[str], report: StageReport) -> _Part:
    summary = read_summary(f)
    if summary is None:
        return _read_torn(path, generic_topics, report)
    part = _Part()
    fixed, generic = set(), set()
    for channel in summary.channels.values():
        schema = summary.schemas.get(channel.schema_id)
        part.topics.add(channel.topic)
        if channel.topic == EVENTS or channel.topic in STANDARD_TOPICS:  # derived: read what was measured
            continue
        message = _fixed_message(schema, channel.message_encoding)
        if message is not None and channel.topic not in generic_topics:
            fixed.add(channel.topic)
        else:
            generic.add(channel.topic)
    damaged: list[ChunkDamage] = []  # chunks failing their CRC or index: left out, said below
    try:
        for name, metadata in metadata_records(f, summary):
            if name == SESSION_METADATA:
                part.metadata = metadata
        # one pass over the chunks: fixed topics at chunk speed, the others message by message
        data, messages = read_open_topics(f, summary, path, sorted(fixed), generic | {EVENTS}, damaged)
        for topic, d in data.items():
            part.fixed[topic] = [(d.message, d.log_time, d.publish_time, d.rows)]
        decoders = _Decoders()
        wanted = {cid: c for cid, c in summary.channels.items() if c.topic in generic | {EVENTS}}
        for cid, log_time, publish_time, payload in messages:
            channel = wanted[cid]
            if channel.topic == EVENTS:
                part.events.append((log_time, Event.decode(payload)))
            else:
                schema = summary.schemas.get(channel.schema_id)
                row = _decode_generic(decoders, schema, channel, log_time, publish_time, payload)
                part.generic.setdefault(channel.topic, []).append(row)
    except (SchemaError, *READ_ERRORS) as exc:
        raise IngestError(path, f"unreadable ({first_line(exc)}); truncated or corrupt?") from exc
    _report_damage(path, summary, damaged, report)
    return part


def _report_damage(path: Path, summary, damaged: list[ChunkDamage], report: StageReport) -> None:
    """One warning per damaged chunk (each once: the fixed and the generic readers may both meet it), also
    kept under ``values["damaged_chunks"]`` so that a build can say which session lost what."""
    seen: set[int] = set()
    for damage in damaged:
        if damage.offset in seen:
            continue
        seen.add(damage.offset)
        text = f"{path.name}: {damage.describe(summary)}"
        report.warnings.append(text)
        report.values.setdefault(DAMAGED_CHUNKS, []).append(text)
        log.warning(text)


def _read_torn(path: Path, generic_topics: set[str], report: StageReport) -> _Part:
    """A part without a summary, read record by record up to the first cut-off or corrupt record."""
    part, schemas, channels = _Part(), {}, {}
    raw: dict[int, list[Message]] = {}
    with path.open("rb") as f:
        walk = RecordWalk(f)
        for record in walk:
            if isinstance(record, Schema):
                schemas[record.id] = record
            elif isinstance(record, Channel):
                channels[record.id] = record
                part.topics.add(record.topic)
            elif isinstance(record, Message) and record.channel_id in channels:
                raw.setdefault(record.channel_id, []).append(record)
            elif isinstance(record, Metadata) and record.name == SESSION_METADATA:
                part.metadata = dict(record.metadata)
    reason = walk.reason or "ended before its footer"
    if not part.metadata and not raw:
        raise IngestError(path, f"truncated: nothing readable before the tear ({reason})")
    decoders = _Decoders()
    for cid, messages in raw.items():
        channel, schema = channels[cid], schemas.get(channels[cid].schema_id)
        if channel.topic in STANDARD_TOPICS:
            continue
        messages.sort(key=lambda m: m.log_time)
        if channel.topic == EVENTS:
            part.events += [(m.log_time, Event.decode(m.data)) for m in messages]
            continue
        message = _fixed_message(schema, channel.message_encoding)
        if message is None or channel.topic in generic_topics:
            part.generic[channel.topic] = [
                _decode_generic(decoders, schema, channel, m.log_time, m.publish_time, m.data)
                for m in messages
            ]
            continue
        log_time = np.array([m.log_time for m in messages], dtype=np.int64)
        publish = np.array([m.publish_time for m in messages], dtype=np.int64)
        rows = message.decode(b"".join(m.data for m in messages))
        part.fixed[channel.topic] = [(message, log_time, publish, rows)]
    n = sum(len(v) for v in raw.values())
    text = f"{path.name}: torn part read up to the tear ({n} messages; {reason})"
    report.warnings.append(text)
    log.warning(text)
    return part


def _fixed_message(schema: Schema | None, encoding: str) -> FixedMessage | None:
    if schema is None or encoding != "cdr" or schema.encoding != "ros2msg":
        return None
    return parse_fixed_message(schema.name, schema.data.decode())


# ---------------------------------------------------------------------------------------- the tables
def _fixed_table(chunks: list[_FixedChunk]) -> pd.DataFrame:
    """Columns of a fixed-layout topic: log/publish times, then each field (arrays flattened)."""
    message = chunks[0][0]
    if all(c[0].dtype == message.dtype for c in chunks):
        if len(chunks) == 1:
            _, log_time, publish, rows = chunks[0]
        else:
            log_time = np.concatenate([c[1] for c in chunks])
            publish = np.concatenate([c[2] for c in chunks])
            rows = np.concatenate([c[3] for c in chunks])
        return fixed_columns(message, log_time, publish, rows)
    frames = [fixed_columns(*c) for c in chunks]  # parts with other array lengths: union of columns
    return pd.concat(frames, ignore_index=True)


def fixed_columns(message: FixedMessage, log_time, publish_time, rows: np.ndarray) -> pd.DataFrame:
    """One DataFrame from structured rows (vectorised: one strided copy per column)."""
    data: dict[str, np.ndarray] = {
        "log_time": np.asarray(log_time, np.int64),
        "publish_time": np.asarray(publish_time, np.int64),
    }
    for f in message.fields:
        values = rows[f.name]
        if f.count:
            for i in range(f.count):
                data[f"{f.name}_{i}"] = np.ascontiguousarray(values[:, i])
        else:
            data[f.name] = np.ascontiguousarray(values)
    return pd.DataFrame(data, copy=False)


class _Decoders:
    """One ``DynamicMessage`` per schema, made when its first message comes."""

    def __init__(self) -> None:
        self._by_schema: dict[int, DynamicMessage] = {}

    def decoder_for(self, channel: Channel, schema: Schema | None) -> DynamicMessage:
        if channel.message_encoding != "cdr" or schema is None or schema.encoding != "ros2msg":
            what = f"{schema.encoding!r} schema" if schema is not None else "no schema"
            encoding = channel.message_encoding
            raise SchemaError(f"{channel.topic}: cannot decode {encoding!r} messages ({what})")
        if schema.id not in self._by_schema:
            self._by_schema[schema.id] = DynamicMessage(schema.name, schema.data.decode("utf-8", "replace"))
        return self._by_schema[schema.id]


def _decode_generic(decoders: _Decoders, schema, channel, log_time: int, publish_time: int, data) -> dict:
    decode = decoders.decoder_for(channel, schema).decode
    row = {"log_time": log_time, "publish_time": publish_time}
    _flatten(decode(data), "", row)
    return row


def _flatten(value, name: str, out: dict) -> None:
    """Nested messages → ``<field>_<sub>``, sequences → ``<field>_<i>``, scalars as they are."""
    if isinstance(value, dict):
        for key, item in value.items():
            _flatten(item, f"{name}_{key}" if name else key, out)
    elif hasattr(value, "__slots__") and not isinstance(value, (str, bytes)):
        for slot in value.__slots__:
            _flatten(getattr(value, slot), f"{name}_{slot}" if name else slot, out)
    elif isinstance(value, (list, tuple, bytes, bytearray, np.ndarray)):
        for i, item in enumerate(value):
            _flatten(item, f"{name}_{i}", out)
    else:
        out[name] = value


def _generic_table(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    for name in ("log_time", "publish_time"):
        if name in df:
            df[name] = df[name].astype(np.int64)
    return df.sort_values("log_time", kind="stable", ignore_index=True) if len(df) else df


def _events_table(events: list[tuple[int, Event]]) -> pd.DataFrame:
    events = sorted(events, key=lambda e: e[0])
    df = pd.DataFrame(
        {
            "log_time": np.array([t for t, _ in events], dtype=np.int64),
            "kind": np.array([int(e.kind) for _, e in events], dtype=np.int64),
            "index": np.array([e.index for _, e in events], dtype=np.int64),
            "value": np.array([e.value for _, e in events], dtype=np.float64),
            "label": pd.Series([e.label for _, e in events], dtype=object),
            "text": pd.Series([e.text for _, e in events], dtype=object),
        }
    )
    return df[list(EVENT_COLUMNS)]
