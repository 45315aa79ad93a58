"""Writing the MCAP container (with ``mcap_reader``, the one module that knows its records): a writer for
batches of fixed-size messages, and the copy of a damaged file's readable records into a new, indexed file.

The batch writer builds message records and indexes with numpy.

The mcap package's ``Writer`` costs ~10 µs per ``add_message`` (a Python call, a struct.pack and an index
append per message): ~90 k messages/s here, less than a batched twin produces. Our messages come in batches of
one topic with a fixed payload size, so a batch of records is one structured array (opcode, length, channel,
sequence, log time, publish time, payload) turned into bytes at once, and each chunk's MessageIndex records
are two numpy columns. Everything else (header, schemas, channels, metadata, chunk records, statistics,
summary, footer) is serialised with the mcap package's own record classes, so the file is standard MCAP:
summary with chunk indexes and statistics, CRCs, zstd chunks. Schemas and channels sit in the data section
before any chunk, so a torn file still says what its messages are.
"""

from __future__ import annotations

import copy
import struct
import threading
import zlib
from collections import deque
from collections.abc import Iterable
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np
import zstandard
from mcap import __version__
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    MetadataIndex,
    Opcode,
    RecordBuilder,
    Statistics,
    SummaryOffset,
)
from mcap.writer import CompressionType, Writer

from acquisition.schemas.cdr import SchemaError
from acquisition.schemas.mcap_reader import MAGIC, Channel, Message, Metadata, RecordWalk, Schema

MCAP_LIBRARY_VERSION = __version__  # the mcap package's, recorded in each session
_RECORD_PREFIX = 1 + 8  # opcode + length
_MESSAGE_FIXED = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time


_MAX_COMPRESSING = 4  # chunks of one file compressing at once (in ``compress_in``): ~4 MB held
_compressors = threading.local()  # a ZstdCompressor may not be used by two threads at once: one a thread


def _compressed(level: int, data: bytes) -> tuple[bytes, int]:
    """A chunk's zstd frame and the crc32 of its uncompressed bytes."""
    by_level = _compressors.__dict__.setdefault("by_level", {})
    compressor = by_level.get(level) or by_level.setdefault(level, zstandard.ZstdCompressor(level=level))
    return compressor.compress(data), zlib.crc32(data)


def message_record_dtype(payload_size: int) -> np.dtype:
    """One Message record with a ``payload_size``-byte payload, packed as MCAP lays it out."""
    return np.dtype(
        [("opcode", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
         ("log_time", "<u8"), ("publish_time", "<u8"), ("data", "u1", (payload_size,))]
    )  # fmt: skip


@dataclass
class _OpenChunk:
    blocks: list[bytes] = field(default_factory=list)
    size: int = 0
    index: dict[int, list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)
    start: int | None = None
    end: int | None = None

    def add(self, channel: int, records: bytes, log_time: np.ndarray, offsets: np.ndarray) -> None:
        self.blocks.append(records)
        self.index.setdefault(channel, []).append((log_time, offsets + self.size))
        self.size += len(records)
        lo, hi = int(log_time.min()), int(log_time.max())
        self.start = lo if self.start is None else min(self.start, lo)
        self.end = hi if self.end is None else max(self.end, hi)


class BatchMcapWriter:
    """``start`` → ``register_schema``/``register_channel`` → ``add_batch``/``add_message``/``add_metadata``
    (``flush`` any time) → ``finish``. Not thread-safe: one writer thread per file."""

    def __init__(self, stream: BinaryIO, chunk_size: int = 1 << 20, compression_level: int = 3,
                 compress_in: Executor | None = None) -> None:  # fmt: skip
        """``compress_in``: threads to compress chunks in while the caller goes on (zstd and crc32 let go of
        the GIL); chunks are still written in their order, each before any later record, so the file is
        byte for byte the one written without them."""
        self.stream = stream
        self.chunk_size = chunk_size
        self.compression_level = compression_level
        self._compress_in = compress_in
        self._compressing: deque[tuple[_OpenChunk, int, Future]] = deque()  # in the order written
        self._open: dict[bool, _OpenChunk] = {}  # the chunk being filled: of measured, of derived channels
        self._derived: set[int] = set()  # channels registered ``derived``
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._stats = Statistics(
            attachment_count=0, channel_count=0, channel_message_counts={}, chunk_count=0, message_count=0,
            message_end_time=0, message_start_time=0, metadata_count=0, schema_count=0,
        )  # fmt: skip
        self._record_dtypes: dict[int, np.dtype] = {}
        self._good: tuple[int, int, int, int, Statistics] = (0, 0, 0, 0, copy.deepcopy(self._stats))

    def _put(self, data: bytes) -> None:
        """Write all of ``data`` (an unbuffered file may take part of it: a disk that fills mid-record)."""
        view = memoryview(data)
        while view:
            n = self.stream.write(view)
            view = view[len(view) if n is None else n :]

    # ------------------------------------------------------------------------------- plain records
    def _write_record(self, record) -> int:
        """Serialise one record straight to the stream (after every chunk still compressing); returns its
        offset."""
        self._write_compressed(wait_all=True)
        builder = RecordBuilder()
        record.write(builder)
        offset = self.stream.tell()
        self._put(builder.end())
        return offset

    def start(self, profile: str, library: str) -> None:
        self._put(MAGIC)
        self._write_record(Header(profile=profile, library=library))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas[schema.id] = schema
        self._stats.schema_count += 1
        self._write_record(schema)
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, metadata=None,
                         derived: bool = False) -> int:  # fmt: skip
        """A channel's id. ``derived``: its messages are computed from the others' (what a viewer draws):
        they go in chunks of their own, so a reader of the measured channels never decompresses them (a third
        of a session's bytes). Chunks of the two kinds overlap in time, as MCAP allows."""
        channel = Channel(
            id=len(self._channels) + 1, topic=topic, message_encoding=message_encoding,
            schema_id=schema_id, metadata=dict(metadata or {}),
        )  # fmt: skip
        self._channels[channel.id] = channel
        if derived:
            self._derived.add(channel.id)
        self._stats.channel_count += 1
        self._stats.channel_message_counts[channel.id] = 0
        self._write_record(channel)
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._finalize_chunk()  # metadata lives between chunks
        offset = self._write_record(Metadata(name=name, metadata=dict(data)))
        self._metadata_indexes.append(
            MetadataIndex(offset=offset, length=self.stream.tell() - offset, name=name)
        )
        self._stats.metadata_count += 1

    def add_attachment(self, name: str, media_type: str, data: bytes, log_time: int = 0) -> None:
        """A file carried in the MCAP (the robot's URDF), indexed in the summary."""
        self._finalize_chunk()  # attachments live between chunks
        record = Attachment(
            create_time=log_time, log_time=log_time, name=name, media_type=media_type, data=data
        )
        offset = self._write_record(record)
        self._attachment_indexes.append(
            AttachmentIndex(offset=offset, length=self.stream.tell() - offset, log_time=log_time,
                            create_time=log_time, data_size=len(data), name=name, media_type=media_type)
        )  # fmt: skip
        self._stats.attachment_count += 1

    # ------------------------------------------------------------------------------------ messages
    def add_batch(self, channel_id: int, log_time: np.ndarray, publish_time: np.ndarray,
                  sequence: np.ndarray, payload: np.ndarray) -> None:  # fmt: skip
        """Messages of one channel: ``payload`` an (n, size) uint8 array (or n structured rows)."""
        payload = np.ascontiguousarray(payload).view(np.uint8).reshape(len(log_time), -1)
        n, size = payload.shape
        if n == 0:
            return
        dtype = self._record_dtypes.get(size) or self._record_dtypes.setdefault(
            size, message_record_dtype(size)
        )
        per_chunk = max(1, self.chunk_size // dtype.itemsize)
        for lo in range(0, n, per_chunk):
            hi = min(n, lo + per_chunk)
            records = np.empty(hi - lo, dtype=dtype)
            records["opcode"] = Opcode.MESSAGE
            records["length"] = _MESSAGE_FIXED + size
            records["channel"] = channel_id
            records["sequence"] = sequence[lo:hi]
            records["log_time"] = log_time[lo:hi]
            records["publish_time"] = publish_time[lo:hi]
            records["data"] = payload[lo:hi]
            offsets = np.arange(hi - lo, dtype=np.uint64) * np.uint64(dtype.itemsize)
            self._add(channel_id, records.tobytes(), np.asarray(log_time[lo:hi], np.uint64), offsets)

    def add_message(
        self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int
    ) -> None:
        """One message of any size (events)."""
        record = struct.pack("<BQHIQQ", Opcode.MESSAGE, _MESSAGE_FIXED + len(data), channel_id, sequence,
                             log_time, publish_time) + data  # fmt: skip
        self._add(channel_id, record, np.array([log_time], dtype=np.uint64), np.zeros(1, np.uint64))

    def _add(self, channel_id: int, records: bytes, log_time: np.ndarray, offsets: np.ndarray) -> None:
        """Records of one channel into the open chunk of its kind, closed when full."""
        derived = channel_id in self._derived
        chunk = self._open.get(derived) or self._open.setdefault(derived, _OpenChunk())
        chunk.add(channel_id, records, log_time, offsets)
        self._count(channel_id, log_time)
        if chunk.size >= self.chunk_size:
            self._finalize_chunk(derived)

    def _count(self, channel_id: int, log_time: np.ndarray) -> None:
        st = self._stats
        n = len(log_time)
        lo, hi = int(np.min(log_time)), int(np.max(log_time))
        st.message_start_time = lo if st.message_count == 0 else min(st.message_start_time, lo)
        st.message_end_time = hi if st.message_count == 0 else max(st.message_end_time, hi)
        st.message_count += n
        st.channel_message_counts[channel_id] += n

    def _finalize_chunk(self, derived: bool | None = None) -> None:
        """Close the open chunk of measured (False) or derived (True) channels; None: both."""
        if derived is None:
            for kind in sorted(self._open):
                self._finalize_chunk(kind)
            return
        chunk = self._open.pop(derived, None)
        if chunk is None or not chunk.blocks:
            return
        self._stats.chunk_count += 1
        data = b"".join(chunk.blocks)
        if self._compress_in is None:
            self._write_chunk(chunk, len(data), *_compressed(self.compression_level, data))
            return
        self._compressing.append(
            (chunk, len(data), self._compress_in.submit(_compressed, self.compression_level, data))
        )
        self._write_compressed(wait_all=False)

    def _write_compressed(self, wait_all: bool) -> None:
        """Write the compressed chunks in their order: those done (all of them with ``wait_all``, and the
        oldest while more than ``_MAX_COMPRESSING`` wait, so memory stays bounded)."""
        queue = self._compressing
        while queue and (wait_all or len(queue) > _MAX_COMPRESSING or queue[0][2].done()):
            chunk, size, future = queue.popleft()
            self._write_chunk(chunk, size, *future.result())

    def _write_chunk(self, chunk: _OpenChunk, uncompressed_size: int, compressed: bytes, crc: int) -> None:
        """The chunk record, its message indexes and its entry in the chunk index."""
        record = Chunk(
            message_start_time=chunk.start, message_end_time=chunk.end, uncompressed_size=uncompressed_size,
            uncompressed_crc=crc, compression="zstd", data=compressed,
        )  # fmt: skip
        builder = RecordBuilder()
        record.write(builder)
        chunk_offset = self.stream.tell()
        self._put(builder.end())
        chunk_length = self.stream.tell() - chunk_offset
        index_start = self.stream.tell()
        index_offsets = {}
        for channel_id, pieces in chunk.index.items():
            log_time = np.concatenate([p[0] for p in pieces])
            offsets = np.concatenate([p[1] for p in pieces])
            order = np.argsort(log_time, kind="stable")
            pairs = np.stack([log_time[order], offsets[order]], axis=1).astype("<u8").tobytes()
            index_offsets[channel_id] = self.stream.tell()
            self._put(struct.pack("<BQHI", Opcode.MESSAGE_INDEX, 2 + 4 + len(pairs), channel_id, len(pairs)))
            self._put(pairs)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=chunk.start, message_end_time=chunk.end, chunk_start_offset=chunk_offset,
                chunk_length=chunk_length, message_index_offsets=index_offsets,
                message_index_length=self.stream.tell() - index_start, compression="zstd",
                compressed_size=len(compressed), uncompressed_size=uncompressed_size,
            )
        )  # fmt: skip

    def flush(self) -> None:
        """Close the open chunk and push everything to the OS (no fsync): the file is whole records now."""
        self._finalize_chunk()
        self._write_compressed(wait_all=True)
        self.stream.flush()
        self._good = (
            self.stream.tell(), len(self._chunk_indexes), len(self._metadata_indexes),
            len(self._attachment_indexes), copy.deepcopy(self._stats),
        )  # fmt: skip

    def salvage(self, last: tuple[int, int, bytes, int] | None = None) -> bool:
        """After a failed write: cut the file back to its last flush (whole records only), add ``last``
        ((channel, log time, data, sequence): why it ends) and close it with its summary. False when even
        that could not be written: the file then ends at the last flush, torn but whole up to it."""
        offset, chunks, metadata, attachments, stats = self._good
        self._open.clear()
        for _, _, future in self._compressing:  # chunks after the last flush: dropped with the rest
            future.cancel()
        self._compressing.clear()
        del self._chunk_indexes[chunks:], self._metadata_indexes[metadata:]
        del self._attachment_indexes[attachments:]
        self._stats = copy.deepcopy(stats)
        self.stream.truncate(offset)
        self.stream.seek(offset)
        if offset == 0:  # not even its header was whole: nothing to close
            return False
        try:
            if last is not None:
                channel, log_time, data, sequence = last
                self.add_message(channel, log_time, data, log_time, sequence)
            self.finish()
            return True
        except OSError:
            self.stream.truncate(offset)
            return False

    def finish(self) -> None:
        """Data end, summary (schemas, channels, statistics, chunk and metadata indexes), footer."""
        self._finalize_chunk()
        self._write_record(DataEnd(data_section_crc=0))
        summary_start = self.stream.tell()
        builder = RecordBuilder()
        offsets = []
        groups = [
            (Opcode.SCHEMA, list(self._schemas.values())),
            (Opcode.CHANNEL, list(self._channels.values())),
            (Opcode.STATISTICS, [self._stats]),
            (Opcode.CHUNK_INDEX, self._chunk_indexes),
            (Opcode.ATTACHMENT_INDEX, self._attachment_indexes),
            (Opcode.METADATA_INDEX, self._metadata_indexes),
        ]
        for opcode, records in groups:
            start = builder.count
            for record in records:
                record.write(builder)
            offsets.append(SummaryOffset(opcode, summary_start + start, builder.count - start))
        summary_offset_start = summary_start + builder.count
        for offset in offsets:
            offset.write(builder)
        summary = builder.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        self._put(summary)
        self._write_record(Footer(summary_start, summary_offset_start, crc))
        self._put(MAGIC)
        self.stream.flush()


def copy_readable(source: BinaryIO, output: BinaryIO, library: str) -> tuple[int, int, bool, str]:
    """Every record of ``source`` before its first cut-off or corrupt one (``RecordWalk``) written again into
    ``output`` by the mcap package's Writer, which adds the summary and indexes: (messages, channels, torn,
    what stopped the walk)."""
    messages = 0
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    writer = Writer(output, compression=CompressionType.ZSTD)
    header_seen = False
    walk = RecordWalk(source)
    for record in walk:
        if not header_seen:
            header_seen = True
            writer.start(profile=getattr(record, "profile", ""), library=library)
        if isinstance(record, Schema) and record.id not in schema_ids:
            schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel) and record.id not in channel_ids:
            channel_ids[record.id] = writer.register_channel(
                record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), record.metadata
            )
        elif isinstance(record, Message) and record.channel_id in channel_ids:
            writer.add_message(
                channel_ids[record.channel_id],
                record.log_time,
                record.data,
                record.publish_time,
                record.sequence,
            )
            messages += 1
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, record.metadata)
        elif isinstance(record, Attachment):
            writer.add_attachment(record.log_time, record.create_time, record.name, record.media_type,
                                  record.data)  # fmt: skip
    if not header_seen:
        writer.start(profile="", library=library)
    writer.finish()
    return messages, len(channel_ids), not walk.complete, walk.reason


def merge_with(
    sources: list[BinaryIO],
    output: BinaryIO,
    library: str,
    batches: Iterable,
    attachments: Iterable[tuple[str, str, bytes]] = (),
    replace: Iterable[str] = (),
) -> int:
    """Every record of the indexed files ``sources`` (a session's parts: schemas, channels, messages,
    metadata, attachments; one channel per topic across them) and ``batches`` (objects with ``topic``,
    ``schema_name``, ``schema_text``, ``log_time`` and ``payloads``: ros2msg/CDR messages) written into one
    new indexed ``output`` with ``attachments`` ((name, media type, bytes)); returns the messages written. The
    sources' topics in ``replace``, and their attachments of the names in ``attachments``, are left out."""
    attachments = list(attachments)
    replace, replaced_files = set(replace), {name for name, _, _ in attachments}
    writer = Writer(output, compression=CompressionType.ZSTD)
    writer.start(profile="ros2", library=library)
    schemas: dict[tuple[str, str, bytes], int] = {}
    channels: dict[str, int] = {}

    def channel(topic: str, encoding: str, schema: tuple[str, str, bytes], metadata=None) -> int:
        if schema not in schemas:
            schemas[schema] = writer.register_schema(*schema)
        if topic not in channels:
            channels[topic] = writer.register_channel(topic, encoding, schemas[schema], dict(metadata or {}))
        return channels[topic]

    messages = 0
    for source in sources:
        ids: dict[int, int] = {}
        known: dict[int, Schema] = {}
        walk = RecordWalk(source)
        for record in walk:
            if isinstance(record, Schema):
                known[record.id] = record
            elif isinstance(record, Channel) and record.topic not in replace:
                s = known.get(record.schema_id)
                key = (s.name, s.encoding, s.data) if s is not None else ("", "", b"")
                ids[record.id] = channel(record.topic, record.message_encoding, key, record.metadata)
            elif isinstance(record, Message) and record.channel_id in ids:
                writer.add_message(ids[record.channel_id], record.log_time, record.data, record.publish_time,
                                   record.sequence)  # fmt: skip
                messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Attachment) and record.name not in replaced_files:
                writer.add_attachment(record.log_time, record.create_time, record.name, record.media_type,
                                      record.data)  # fmt: skip
        if not walk.complete:  # a merge is of whole files: never one that silently ends early
            where = getattr(source, "name", "a source")
            raise SchemaError(f"{where}: unreadable from a record on ({walk.reason})")
    sequence: dict[str, int] = {}  # each topic's messages numbered from 0, across its batches
    for batch in batches:
        cid = channel(batch.topic, "cdr", (batch.schema_name, "ros2msg", batch.schema_text.encode()))
        for t, data in zip(np.asarray(batch.log_time).tolist(), batch.payloads, strict=True):
            seq = sequence[batch.topic] = sequence.get(batch.topic, -1) + 1
            writer.add_message(cid, t, bytes(data), t, seq)
            messages += 1
    for name, media_type, data in attachments:
        writer.add_attachment(0, 0, name, media_type, data)
    writer.finish()
    return messages
