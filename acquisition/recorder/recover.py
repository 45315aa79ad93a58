"""Recover a torn MCAP part (writer killed: no summary, maybe half a chunk) into a new, valid, indexed file.

The original is never touched (raw sessions are immutable). A linear StreamReader walks the records until the
first one that is cut off or corrupt; every schema, channel, metadata record and message before it is written
again through a fresh Writer, which adds the summary and the indexes.
"""

from __future__ import annotations

import logging
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

log = logging.getLogger(__name__)

RECOVERED_SUFFIX = ".recovered.mcap"


@dataclass(frozen=True)
class RecoveryReport:
    source: Path
    output: Path
    messages: int
    channels: int
    torn: bool  # the source ended before its footer
    reason: str  # what stopped the walk ("" for a complete file)


def recovered_path(path: Path) -> Path:
    return path.with_name(path.name.removesuffix(".mcap") + RECOVERED_SUFFIX)


def recover(source: str | Path, output: str | Path | None = None) -> RecoveryReport:
    """Write every readable record of ``source`` into ``output`` (default ``<name>.recovered.mcap``)."""
    source = Path(source)
    output = recovered_path(source) if output is None else Path(output)
    if output.resolve() == source.resolve() or (output.exists() and os.path.samefile(output, source)):
        raise ValueError("recovery writes a new file; it never overwrites the original")
    partial = output.with_name(f".{output.name}.partial")  # renamed into place whole: never a half file
    try:
        messages, channels, torn, reason = _copy(source, partial)
        os.replace(partial, output)
    finally:
        partial.unlink(missing_ok=True)
    if torn:
        log.warning("%s: torn after %d messages (%s); recovered to %s", source, messages, reason, output)
    return RecoveryReport(source, output, messages, channels, torn, reason if torn else "")


def _copy(source: Path, output: Path) -> tuple[int, int, bool, str]:
    """Every readable record of ``source`` into a new file ``output``: (messages, channels, torn, reason)."""
    messages, reason, torn = 0, "", True
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    with open(source, "rb") as f, open(output, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        header_seen = False
        try:
            for record in StreamReader(f, validate_crcs=True).records:
                if not header_seen:
                    header_seen = True
                    profile = getattr(record, "profile", "")
                    writer.start(profile=profile, library="vslab recover")
                if isinstance(record, Schema) and record.id not in schema_ids:
                    schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channel_ids:
                    channel_ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0),
                        record.metadata,
                    )  # fmt: skip
                elif isinstance(record, Message) and record.channel_id in channel_ids:
                    writer.add_message(
                        channel_ids[record.channel_id], record.log_time, record.data,
                        record.publish_time, record.sequence,
                    )  # fmt: skip
                    messages += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, record.metadata)
                elif isinstance(record, Footer):
                    torn = False
        except (McapError, struct.error, zstandard.ZstdError, EOFError, ValueError, KeyError) as exc:
            text = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
            reason = text.splitlines()[0][:200]
        if not header_seen:
            writer.start(profile="", library="vslab recover")
        writer.finish()
    return messages, len(channel_ids), torn, reason
