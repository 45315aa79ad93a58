"""Shared-memory rings: a device daemon hands its samples to the session writer without locks or pickling.

One ring per stream (topic). The producer is the daemon that owns the device; the consumer is the writer
process, the only one that advances ``tail``; any number of peekers (the supervisor's plan runner and live
view) read without consuming. A ring is a file on tmpfs (``/dev/shm``) mapped by every process, so it
outlives a killed daemon or writer: the restarted process attaches the same file and goes on from its
counters (no ``multiprocessing.shared_memory``: its resource tracker unlinks segments when a child dies).

Layout: a header of int64 words, then ``capacity`` slots of ``[int64 host_ns][int32 length][int32 pad]
[payload]``. The producer fills a slot and then publishes it by storing ``head`` (one aligned 8-byte store,
ordered after the slot's stores on x86-64's total store order; a weakly ordered CPU would need a fence here).
Each word of the header has one writer: the producer owns ``head`` and the stream account, the consumer owns
``tail`` and ``written``, so no read-modify-write is ever shared.

A full ring drops the new sample and counts it (``dropped``): a stalled writer must never stall a device.
"""

from __future__ import annotations

import mmap
import os
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAGIC = 0x76736C6162524E47  # "vslabRNG"
HEADER_WORDS = 32
HEADER_BYTES = HEADER_WORDS * 8
SLOT_HEAD = 16  # int64 host_ns, int32 length, int32 pad

# header words
_MAGIC, _CAPACITY, _SLOT_SIZE, _HEAD, _TAIL, _WRITTEN, _DROPPED = range(7)
_EXPECTED, _LOST, _LAST_SEQ, _LAST_NS, _GAPS, _RECEIVED, _WRITER_LOST, _BRIDGE = range(7, 15)
_NO_SEQ = -1


def map_file(path: Path) -> mmap.mmap:
    """All of the file ``path`` mapped read-write, shared with every process that maps it (rings and status
    blocks alike)."""
    with open(path, "r+b") as f:
        return mmap.mmap(f.fileno(), 0)


def unmap(mm: mmap.mmap) -> None:
    """Close a mapping; while a caller still holds a view of it, the mapping goes with the process instead."""
    with suppress(BufferError):
        mm.close()


@dataclass(frozen=True)
class StreamCounts:
    """One stream's account: samples the device should have given (``expected``), taken from it
    (``received``), never taken (``lost``: in gaps, skipped poll slots, holes in its sequence numbers),
    written to the file (``written``), and taken but never written (``dropped``: ring full, writer killed)."""

    expected: int
    received: int
    lost: int
    written: int
    dropped: int
    gaps: int

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


class Ring:
    """A ring of ``capacity`` slots of up to ``payload_size`` bytes, in the file ``path``."""

    def __init__(self, path: Path, mm: mmap.mmap) -> None:
        self.path = Path(path)
        self._mm = mm
        self.header = np.ndarray((HEADER_WORDS,), np.int64, buffer=mm, offset=0)
        if int(self.header[_MAGIC]) != MAGIC:
            raise ValueError(f"{path} is not a vslab ring")
        self.capacity = int(self.header[_CAPACITY])
        self.slot_size = int(self.header[_SLOT_SIZE])
        self.payload_size = self.slot_size - SLOT_HEAD
        self.slots = np.ndarray((self.capacity, self.slot_size), np.uint8, buffer=mm, offset=HEADER_BYTES)
        self._times = np.ndarray(
            (self.capacity,), np.int64, buffer=mm, offset=HEADER_BYTES, strides=(self.slot_size,)
        )
        self._lengths = np.ndarray(
            (self.capacity,), np.int32, buffer=mm, offset=HEADER_BYTES + 8, strides=(self.slot_size,)
        )
        self._cursor = 0  # a peeker's own position

    # --------------------------------------------------------------------------------- lifecycle
    @classmethod
    def create(cls, path: Path, capacity: int, payload_size: int) -> Ring:
        """A new, empty ring file (replacing any old one at ``path``)."""
        if capacity < 2 or payload_size < 1:
            raise ValueError(f"a ring needs ≥ 2 slots of ≥ 1 byte, got {capacity} × {payload_size}")
        slot_size = -(-(SLOT_HEAD + payload_size) // 8) * 8
        size = HEADER_BYTES + capacity * slot_size
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as f:
            f.truncate(size)
            header = np.zeros(HEADER_WORDS, np.int64)
            header[[_MAGIC, _CAPACITY, _SLOT_SIZE]] = MAGIC, capacity, slot_size
            header[_LAST_SEQ] = _NO_SEQ
            f.write(header.tobytes())
        os.replace(tmp, path)
        return cls.attach(path)

    @classmethod
    def attach(cls, path: Path) -> Ring:
        """Map an existing ring file (any process)."""
        return cls(path, map_file(path))

    def close(self) -> None:
        """Unmap (the file stays; the supervisor removes it at the end of the session)."""
        self.header = self.slots = self._times = self._lengths = None  # type: ignore[assignment]
        unmap(self._mm)

    # ---------------------------------------------------------------------------------- producer
    @property
    def head(self) -> int:
        return int(self.header[_HEAD])

    @property
    def tail(self) -> int:
        return int(self.header[_TAIL])

    def put(self, host_ns: int, payload: bytes | np.ndarray) -> bool:
        """Append one record; False (and counted as dropped) when the ring is full."""
        head = int(self.header[_HEAD])
        self.header[_RECEIVED] += 1
        if head - int(self.header[_TAIL]) >= self.capacity:
            self.header[_DROPPED] += 1
            return False
        data = np.frombuffer(payload, np.uint8) if isinstance(payload, bytes | bytearray) else payload
        n = data.size
        if n > self.payload_size:
            raise ValueError(f"{self.path.name}: a {n}-byte record in {self.payload_size}-byte slots")
        i = head % self.capacity
        self._times[i] = host_ns
        self._lengths[i] = n
        self.slots[i, SLOT_HEAD : SLOT_HEAD + n] = data.reshape(-1)
        self.header[_HEAD] = head + 1  # publish
        return True

    # ---------------------------------------------------------------------------------- consumer
    def take(self, limit: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copy out and consume what was published: (host_ns (n,), lengths (n,), payloads (n, slot))."""
        tail, head = int(self.header[_TAIL]), int(self.header[_HEAD])
        if limit is not None:
            head = min(head, tail + limit)
        out = self._copy(tail, head)
        self.header[_TAIL] = head
        return out

    def note_written(self, n: int) -> None:
        """The consumer made ``n`` more records durable in the file."""
        self.header[_WRITTEN] += n

    # ---------------------------------------------------------------------------------- peekers
    def peek(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What was published since this object's last peek, without consuming it (records the producer
        overwrote meanwhile are skipped)."""
        head = int(self.header[_HEAD])
        start = max(self._cursor, head - self.capacity)
        out = self._copy(start, head)
        self._cursor = head
        floor = int(self.header[_HEAD]) - self.capacity  # slots below this may have been rewritten
        if start < floor:
            keep = slice(floor - start, None)
            out = (out[0][keep], out[1][keep], out[2][keep])
        return out

    def latest(self) -> tuple[int, np.ndarray] | None:
        """(host_ns, payload) of the newest record, or None before the first."""
        head = int(self.header[_HEAD])
        if head == 0:
            return None
        i = (head - 1) % self.capacity
        t, n = int(self._times[i]), int(self._lengths[i])
        payload = self.slots[i, SLOT_HEAD : SLOT_HEAD + n].copy()
        if int(self.header[_HEAD]) - self.capacity >= head:  # lapped while copying
            return self.latest()
        return t, payload

    def _copy(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        idx = np.arange(lo, hi) % self.capacity
        return self._times[idx].copy(), self._lengths[idx].copy(), self.slots[idx, SLOT_HEAD:]

    # ------------------------------------------------------------------------------ the account
    def account(self, seq: int, host_ns: int, modulo: int, rate_hz: float) -> bool:
        """The producer took the sample numbered ``seq`` (the device's counter, wrapping at ``modulo``, or a
        poll slot): count it as expected, and every number it skipped as expected and lost. A number that
        does not follow (the device was reset, or the counter jumped back) is bridged by the time since the
        last sample at ``rate_hz``. The first sample of a session starts the account, unless the stream
        started in a gap (:meth:`start_in_gap`): then it is bridged by the time since the gap began. False:
        the number was the last one again (a repeated sample, not a new one)."""
        h = self.header
        last = int(h[_LAST_SEQ])
        if last == _NO_SEQ:
            n = max(1, round((host_ns - int(h[_LAST_NS])) * rate_hz / 1e9)) if h[_LAST_NS] else 1
        else:
            step = (seq - last) % modulo
            if step == 0 and not h[_BRIDGE]:
                return False
            if step >= modulo // 2 or h[_BRIDGE]:  # not a successor: bridge the time instead
                step = max(1, round((host_ns - int(h[_LAST_NS])) * rate_hz / 1e9))
            n = step
        h[_EXPECTED] += n
        h[_LOST] += n - 1
        h[_LAST_SEQ] = seq % modulo
        h[_LAST_NS] = host_ns
        h[_BRIDGE] = 0
        return True

    def restart_sequence(self) -> None:
        """The device's counter starts afresh (a reconnection reset it): bridge the next sample by time."""
        self.header[_BRIDGE] = 1

    def start_in_gap(self, since_ns: int) -> None:
        """The device did not answer at first (from ``since_ns``): before the stream's first sample, the time
        until it counts as lost samples. Once a sample is in, a gap is bridged from the last one instead."""
        if int(self.header[_LAST_SEQ]) == _NO_SEQ:
            self.header[_LAST_NS] = since_ns

    def note_gap(self) -> None:
        """The producer lost its device (or was restarted): one more gap in this stream."""
        self.header[_GAPS] += 1

    def note_writer_lost(self) -> None:
        """A new consumer found records its killed predecessor consumed but never wrote: count them."""
        lost = int(self.header[_TAIL]) - int(self.header[_WRITTEN]) - int(self.header[_WRITER_LOST])
        if lost > 0:
            self.header[_WRITER_LOST] += lost

    def counts(self) -> StreamCounts:
        h = self.header
        return StreamCounts(
            expected=int(h[_EXPECTED]),
            received=int(h[_RECEIVED]),
            lost=int(h[_LOST]),
            written=int(h[_WRITTEN]),
            dropped=int(h[_DROPPED]) + int(h[_WRITER_LOST]),
            gaps=int(h[_GAPS]),
        )
