"""Reading the MCAP container: the one module (with ``mcap_writer``) that knows its records.

What vslab reads of a file: its magic, its summary (schemas, channels, statistics, chunk and metadata
indexes), the chunks' records and message indexes (so that fixed-size messages are gathered with numpy, never
parsed one by one), metadata records, and, for a torn file without a summary, a linear walk of its records up
to the first one that is cut off or corrupt. Built on the mcap package's reader and record classes; the
byte layouts it reads itself are the spec's (https://mcap.dev/spec): a record is opcode (1) + length (8) +
body, a Message body is channel id (2), sequence (4), log time (8), publish time (8), data.
"""

from __future__ import annotations

import io
import struct
import threading
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import (
    AttachmentIndex,
    Channel,
    ChunkIndex,
    Footer,
    Header,
    Message,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)
from mcap.stream_reader import StreamReader
from mcap.summary import Summary

from acquisition.schemas.cdr import SchemaError

__all__ = ["Channel", "ChunkDamage", "DamagedChunkError", "Footer", "Header", "Message", "Metadata", "Schema",
           "Summary"]  # fmt: skip

MAGIC = b"\x89MCAP0\r\n"
RECORD_PREFIX = 1 + 8  # opcode, record length
MESSAGE_HEADER = RECORD_PREFIX + 2 + 4 + 8 + 8  # … channel id, sequence, log time, publish time
_CHUNK_OPCODE, _MESSAGE_OPCODE = 0x06, 0x05
# what a damaged file raises from the mcap package, struct, zstd or the OS
READ_ERRORS = (McapError, struct.error, zstandard.ZstdError, EOFError, ValueError, KeyError, OSError)


def first_line(exc: BaseException) -> str:
    """``Type: first line`` of an exception, for a one-line reason."""
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0][:200]}" if text else type(exc).__name__


@dataclass(frozen=True)
class ChunkDamage:
    """A chunk whose records cannot be trusted: where it starts (byte offset in the file), why, and what its
    index says it held (messages per channel id, log-time span in ns), so a reader can say what was lost."""

    offset: int
    reason: str
    messages: dict[int, int] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0

    def describe(self, summary: Summary | None = None) -> str:
        """One line: the chunk's offset, why it is damaged, and the messages and time span it held."""
        topics = summary.channels if summary is not None else {}
        names = {c: topics[c].topic if c in topics else str(c) for c in self.messages}
        held = ", ".join(f"{names[c]} {n:,}" for c, n in sorted(self.messages.items()))
        stats = summary.statistics if summary is not None else None
        t0 = stats.message_start_time if stats is not None and stats.message_count else self.start_ns
        span = f"{(self.start_ns - t0) / 1e9:.3f}–{(self.end_ns - t0) / 1e9:.3f} s into the file"
        lost = sum(self.messages.values())
        return (
            f"damaged chunk at byte {self.offset} ({self.reason}): {lost:,} messages lost "
            f"({held or 'none indexed'}), log times {span}"
        )


class DamagedChunkError(SchemaError):
    """A chunk that fails its CRC, does not decompress, or whose message index does not match its records."""

    def __init__(self, damage: ChunkDamage, summary: Summary | None = None, path: object = None) -> None:
        self.damage, self.path = damage, path
        super().__init__((f"{path}: " if path is not None else "") + damage.describe(summary))


def read_magic(f: BinaryIO) -> bytes:
    """The file's first bytes, as many as the magic has (compare with ``MAGIC``); leaves ``f`` at 0."""
    head = f.read(len(MAGIC))
    f.seek(0)
    return head


_FOOTER_RECORD = RECORD_PREFIX + 8 + 8 + 4  # summary start, summary offset start, CRC


def read_summary(f: BinaryIO) -> Summary | None:
    """The summary section, or None where the file has none (torn) or it cannot be read. The footer and
    then the whole summary are read in one piece each (the mcap package's reader asks the file for every
    field: thousands of small reads for a long session's chunk indexes)."""
    try:
        f.seek(-(_FOOTER_RECORD + len(MAGIC)), 2)
        footer = next(StreamReader(io.BytesIO(f.read()), skip_magic=True).records)
        if not isinstance(footer, Footer) or footer.summary_start == 0:
            return None
        f.seek(footer.summary_start)
        summary = Summary()
        for record in StreamReader(io.BytesIO(f.read()), skip_magic=True).records:
            if isinstance(record, Footer):
                return summary
            if isinstance(record, Statistics):
                summary.statistics = record
            elif isinstance(record, (Schema, Channel)):
                (summary.schemas if isinstance(record, Schema) else summary.channels)[record.id] = record
            elif isinstance(record, (ChunkIndex, AttachmentIndex, MetadataIndex)):
                {ChunkIndex: summary.chunk_indexes, AttachmentIndex: summary.attachment_indexes,
                 MetadataIndex: summary.metadata_indexes}[type(record)].append(record)  # fmt: skip
        return None  # no footer after the summary: not a whole file
    except (*READ_ERRORS, StopIteration):
        return None


def metadata_records(f: BinaryIO, summary: Summary | None = None) -> Iterator[tuple[str, dict[str, str]]]:
    """(name, map) of every metadata record, through the summary's metadata index (``summary``: the file's,
    read already)."""
    if summary is None:
        f.seek(0)
        for m in make_reader(f, validate_crcs=True).iter_metadata():
            yield m.name, dict(m.metadata)
        return
    for index in summary.metadata_indexes:
        f.seek(index.offset)
        record = next(StreamReader(f, skip_magic=True).records)
        if not isinstance(record, Metadata):
            raise McapError(f"the metadata index points at a {type(record).__name__} record")
        yield record.name, dict(record.metadata)


def topic_messages(f: BinaryIO, topics: list[str]) -> Iterator[tuple[int, bytes]]:
    """(log time, payload) of the topics' messages in log-time order (the generic reader: few messages)."""
    f.seek(0)
    for _, _, m in make_reader(f, validate_crcs=True).iter_messages(topics=topics, log_time_order=True):
        yield m.log_time, m.data


_decompressors = threading.local()  # one zstd context a thread (making one costs more than a small chunk)


def _zstd_decompressor() -> zstandard.ZstdDecompressor:
    _decompressors.zstd = zstandard.ZstdDecompressor()
    return _decompressors.zstd


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        decompressor = getattr(_decompressors, "zstd", None) or _zstd_decompressor()
        return decompressor.decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise SchemaError(f"unsupported chunk compression {compression!r}")


def chunk_records(f: BinaryIO, offset: int, length: int) -> bytes:
    """The decompressed records of the Chunk record at ``offset``, checked against the chunk's CRC32 of its
    uncompressed records (the spec's; 0 means none was written) and its uncompressed size: a
    ``DamagedChunkError`` otherwise (a flipped bit never becomes a value)."""
    f.seek(offset)
    raw = f.read(length)
    try:
        opcode, record_len = struct.unpack_from("<BQ", raw, 0)
        if opcode != _CHUNK_OPCODE or RECORD_PREFIX + record_len != length:
            raise SchemaError(f"no chunk record of {length} bytes there (opcode {opcode:#04x})")
        pos = RECORD_PREFIX
        _start, _end, size, crc, clen = struct.unpack_from("<QQQIi", raw, pos)
        pos += 8 + 8 + 8 + 4 + 4
        compression = raw[pos : pos + clen].decode()
        pos += clen
        (records_len,) = struct.unpack_from("<Q", raw, pos)
        pos += 8
        if pos + records_len != length:
            raise SchemaError(f"records length {records_len} does not fit the chunk")
        records = _decompress(compression, raw[pos : pos + records_len], size)
    except (SchemaError, struct.error, UnicodeDecodeError, zstandard.ZstdError, RuntimeError) as exc:
        raise DamagedChunkError(ChunkDamage(offset, first_line(exc))) from exc
    if len(records) != size:
        raise DamagedChunkError(ChunkDamage(offset, f"{len(records)} bytes decompressed, {size} expected"))
    if crc != 0 and zlib.crc32(records) != crc:
        raise DamagedChunkError(ChunkDamage(offset, f"CRC mismatch: {zlib.crc32(records):#010x}, {crc:#010x} "
                                                    "written"))  # fmt: skip
    return records


def message_index(f: BinaryIO, offset: int) -> np.ndarray:
    """The (log time, offset in the chunk) pairs of the MessageIndex record at ``offset``."""
    f.seek(offset + RECORD_PREFIX)
    _channel, length = struct.unpack("<HI", f.read(6))
    return np.frombuffer(f.read(length), dtype="<u8").reshape(-1, 2)


def _message_indexes(f: BinaryIO, offset: int, length: int) -> dict[int, np.ndarray]:
    """Each channel's (log time, offset) pairs from the MessageIndex records that follow a chunk."""
    f.seek(offset)
    raw = f.read(length)
    out, pos = {}, 0
    while pos < len(raw):
        record_len = struct.unpack_from("<Q", raw, pos + 1)[0]
        channel_id, pairs_len = struct.unpack_from("<HI", raw, pos + RECORD_PREFIX)
        if record_len != 2 + 4 + pairs_len or pairs_len % 16:  # not CRC'd: its lengths must agree
            raise SchemaError(f"message index record at byte {offset + pos} has inconsistent lengths")
        at = pos + RECORD_PREFIX + 6
        out[channel_id] = np.frombuffer(raw, dtype="<u8", count=pairs_len // 8, offset=at).reshape(-1, 2)
        pos += RECORD_PREFIX + record_len
    return out


def _chunks_holding(summary: Summary, channel_ids: Iterable[int]):
    wanted = set(channel_ids)
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        present = sorted(cid for cid in ci.message_index_offsets if cid in wanted)
        if present:
            yield ci, present


# a Message record's header, as it lies in a chunk's records (packed: 31 bytes)
_HEAD_FIELDS = [("opcode", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                ("log_time", "<u8"), ("publish_time", "<u8")]  # fmt: skip
MESSAGE_HEAD = np.dtype(_HEAD_FIELDS)


def _message_heads(records: np.ndarray, cid: int, pairs: np.ndarray, size: int = 0) -> np.ndarray | str:
    """The records a channel's message index (outside the chunk's CRC) points at: each header and ``size``
    payload bytes (field ``payload``) gathered with one numpy index; or why they do not match the index: each
    must be a Message of that channel with that log time."""
    at = pairs[:, 1].astype(np.int64)
    width = MESSAGE_HEADER + size
    if len(at) and (at.min() < 0 or at.max() + width > len(records)):
        return f"the message index of channel {cid} points outside the chunk"
    dtype = np.dtype([*_HEAD_FIELDS, ("payload", "u1", (size,))]) if size else MESSAGE_HEAD
    heads = _gathered(records, at, width).reshape(-1).view(dtype)
    if (
        np.any(heads["opcode"] != _MESSAGE_OPCODE)
        or np.any(heads["channel"] != cid)
        or np.any(heads["log_time"] != pairs[:, 0])
    ):
        return f"the message index of channel {cid} does not match the chunk's records"
    return heads


def _gathered(records: np.ndarray, at: np.ndarray, width: int) -> np.ndarray:
    """The ``width`` bytes at each offset ``at`` of ``records``, as an (n, width) array. A writer lays a
    batch of one channel's messages end to end, so the offsets run in steps of ``width``: each run is copied
    as one block (memory speed); offsets that seldom run so (messages of many sizes) are gathered as rows of
    a sliding window over the records (one index a message, not one a byte: 3× faster)."""
    runs = np.flatnonzero(np.diff(at) != width) + 1
    if len(runs) > len(at) // 16:
        return np.lib.stride_tricks.sliding_window_view(records, width)[at]
    out = np.empty((len(at), width), np.uint8)
    for lo, hi in zip([0, *runs.tolist()], [*runs.tolist(), len(at)], strict=True):
        start = int(at[lo])
        out[lo:hi] = records[start : start + (hi - lo) * width].reshape(hi - lo, width)
    return out


def _damage(f: BinaryIO, ci, reason: str) -> ChunkDamage:
    """The damage of the chunk ``ci`` with what its index says it held (counts omitted where unreadable)."""
    try:
        held = {cid: len(p) for cid, p in _message_indexes(f, min(ci.message_index_offsets.values()),
                                                             ci.message_index_length).items()}  # fmt: skip
    except (*READ_ERRORS, IndexError):
        held = {}
    return ChunkDamage(ci.chunk_start_offset, reason, held, ci.message_start_time, ci.message_end_time)


def checked_chunks(f: BinaryIO, summary: Summary, channel_ids: Iterable[int] | dict[int, int],
                   damaged: list[ChunkDamage] | None = None):  # fmt: skip
    """(chunk index, channels present, records as uint8 array, each channel's (log time, offset) pairs and
    records (``_message_heads``; with the payloads where ``channel_ids`` maps channels to payload sizes)) of
    every chunk holding one of the channels, its CRC and message indexes checked. A damaged chunk raises
    ``DamagedChunkError``, or, given a ``damaged`` list, is added to it and skipped (its messages unused)."""
    sizes = channel_ids if isinstance(channel_ids, dict) else {}
    for ci, present in _chunks_holding(summary, channel_ids):
        try:
            records = np.frombuffer(chunk_records(f, ci.chunk_start_offset, ci.chunk_length), dtype=np.uint8)
            try:
                offset = min(ci.message_index_offsets.values())
                indexes = _message_indexes(f, offset, ci.message_index_length)
                heads = {c: _message_heads(records, c, indexes[c], sizes.get(c, 0)) for c in present}
                reason = next((h for h in heads.values() if isinstance(h, str)), "")
            except (*READ_ERRORS, IndexError) as exc:
                reason = f"its message index cannot be read ({first_line(exc)})"
            if reason:
                raise DamagedChunkError(ChunkDamage(ci.chunk_start_offset, reason))
        except DamagedChunkError as exc:
            damage = _damage(f, ci, exc.damage.reason)
            if damaged is None:
                raise DamagedChunkError(damage, summary) from exc
            damaged.append(damage)
            continue
        yield ci, present, records, indexes, heads


def damaged_chunks(f: BinaryIO, summary: Summary) -> list[ChunkDamage]:
    """Every chunk of the file that fails its checks (``checked_chunks``): the one full check of a file."""
    damaged: list[ChunkDamage] = []
    for _ in checked_chunks(f, summary, set(summary.channels), damaged):
        pass
    return damaged


def fixed_size_messages(
    f: BinaryIO, summary: Summary, sizes: dict[int, int], damaged: list[ChunkDamage] | None = None
) -> dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """Per channel whose messages all have ``sizes[channel]`` payload bytes, per chunk: (log times, publish
    times, payloads as an (n, size) uint8 array), gathered with one numpy index per chunk and channel. A
    message of another size is a ``SchemaError``; a damaged chunk as in ``checked_chunks``."""
    return chunk_messages(f, summary, sizes, set(), damaged)[0]


def chunk_messages(
    f: BinaryIO, summary: Summary, sizes: dict[int, int], others: set[int], damaged: list[ChunkDamage] | None
) -> tuple[dict[int, list[tuple[np.ndarray, np.ndarray, np.ndarray]]], list[tuple[int, int, int, bytes]]]:
    """``fixed_size_messages`` of the ``sizes`` channels and ``indexed_messages`` of the ``others``, in one
    pass: each chunk decompressed and checked once."""
    out: dict[int, list] = {cid: [] for cid in sizes}
    rest: list[tuple[int, int, int, bytes]] = []
    wanted = {**dict.fromkeys(others, 0), **sizes}
    for ci, present, records, indexes, heads in checked_chunks(f, summary, wanted, damaged):
        for cid in present:
            pairs, head = indexes[cid], heads[cid]
            if cid not in sizes:
                rest += _variable_messages(f, summary, ci, cid, records, pairs, head)
                continue
            if np.any(head["length"] != MESSAGE_HEADER - RECORD_PREFIX + sizes[cid]):
                raise SchemaError(f"channel {cid} has messages that are not {sizes[cid]} bytes")
            payload = head["payload"]  # gathered with the headers the index check read
            out[cid].append((pairs[:, 0].astype(np.int64), head["publish_time"].astype(np.int64), payload))
    return out, rest


def _variable_messages(f: BinaryIO, summary: Summary, ci, cid: int, records: np.ndarray, pairs: np.ndarray,
                       heads: np.ndarray) -> list[tuple[int, int, int, bytes]]:  # fmt: skip
    """(channel id, log time, publish time, payload) of one channel's messages in one checked chunk."""
    ends = (pairs[:, 1] + RECORD_PREFIX + heads["length"]).tolist()
    if ends and max(ends) > len(records):
        raise DamagedChunkError(_damage(f, ci, "a message runs past the chunk's end"), summary)
    view = memoryview(records)  # the decompressed bytes, not copied
    publish = heads["publish_time"].tolist()
    return [
        (cid, log_time, stamp, bytes(view[offset + MESSAGE_HEADER : end]))
        for (log_time, offset), stamp, end in zip(pairs.tolist(), publish, ends, strict=True)
    ]


def indexed_messages(
    f: BinaryIO, summary: Summary, channel_ids: set[int], damaged: list[ChunkDamage] | None = None
) -> Iterator[tuple[int, int, int, bytes]]:
    """(channel id, log time, publish time, payload) of the channels' messages of any size, found through the
    chunks' message indexes: only chunks that hold one are decompressed (and checked, as in
    ``checked_chunks``), no other record is parsed."""
    for ci, present, records, indexes, heads in checked_chunks(f, summary, channel_ids, damaged):
        for cid in present:
            yield from _variable_messages(f, summary, ci, cid, records, indexes[cid], heads[cid])


def topic_spans(f: BinaryIO) -> dict[str, tuple[int, int | None, int | None]] | None:
    """Per topic: (messages, first log time, last log time) from the summary's statistics and the message
    indexes; None where either cannot be read (a torn or damaged file)."""
    try:
        summary = read_summary(f)
        if summary is None or summary.statistics is None:
            return None
        counts = summary.statistics.channel_message_counts
        out = {c.topic: (counts.get(cid, 0), None, None) for cid, c in summary.channels.items()}
        for ci in summary.chunk_indexes:
            for cid, offset in ci.message_index_offsets.items():
                pairs = message_index(f, offset)
                if len(pairs) == 0:
                    continue
                topic = summary.channels[cid].topic
                n, lo, hi = out[topic]
                first, last = int(pairs[:, 0].min()), int(pairs[:, 0].max())
                out[topic] = (
                    n,
                    first if lo is None else min(lo, first),
                    last if hi is None else max(hi, last),
                )
        return out
    except READ_ERRORS:
        return None


class RecordWalk:
    """The records of a file from its start, read linearly (no summary needed) up to the first that is cut
    off or corrupt (CRCs checked): ``for record in walk``; afterwards ``complete`` says whether the footer was
    reached and ``reason`` what stopped the walk ("" for a whole file). The one walk of a torn file."""

    def __init__(self, f: BinaryIO) -> None:
        self.f = f
        self.complete = False
        self.reason = ""

    def __iter__(self) -> Iterator[Header | Schema | Channel | Message | Metadata | Footer]:
        self.f.seek(0)
        try:
            for record in StreamReader(self.f, validate_crcs=True).records:
                if isinstance(record, Footer):
                    self.complete = True
                yield record
        except READ_ERRORS as exc:
            self.reason = first_line(exc)
