"""CAN 2.0 frames as the bus carries them: identifiers, data, and how many bits a frame takes on the wire.

A frame's length on the bus is what limits a CAN network: its bits are counted exactly here, stuff bits
included (after five equal bits the transmitter inserts the opposite one, over start of frame … CRC), so the
twin's bus times each frame as a controller would send it and the bus load it reports is the real one, not a
worst-case estimate (reference: ISO 11898-1; CRC-15 polynomial 0x4599).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

from acquisition.errors import CodecError

STANDARD_ID_MAX = 0x7FF
EXTENDED_ID_MAX = 0x1FFF_FFFF
MAX_DATA = 8
_CRC15_POLY = 0x4599
# after the CRC: delimiter 1, ACK slot and delimiter 2, end of frame 7, interframe space 3 (never stuffed)
_TRAILER_BITS = 1 + 2 + 7 + 3


@dataclass(frozen=True)
class CanFrame:
    """One classic CAN frame: ``can_id`` (11-bit, or 29-bit when ``extended``), up to 8 data bytes, or a
    remote request (``remote``: no data, ``dlc`` says how many bytes are asked for)."""

    can_id: int
    data: bytes = b""
    extended: bool = False
    remote: bool = False
    dlc: int | None = None  # remote frames only; a data frame's DLC is len(data)

    def __post_init__(self) -> None:
        top = EXTENDED_ID_MAX if self.extended else STANDARD_ID_MAX
        if not 0 <= self.can_id <= top:
            raise CodecError(f"CAN id {self.can_id:#x} outside 0..{top:#x}")
        if len(self.data) > MAX_DATA:
            raise CodecError(f"CAN frame {self.can_id:#x}: {len(self.data)} data bytes, at most {MAX_DATA}")
        if self.remote and self.data:
            raise CodecError(f"CAN frame {self.can_id:#x}: a remote request carries no data")
        if self.dlc is not None and not 0 <= self.dlc <= MAX_DATA:
            raise CodecError(f"CAN frame {self.can_id:#x}: DLC {self.dlc} outside 0..{MAX_DATA}")

    @property
    def length(self) -> int:
        """The DLC field: the data length, or the length a remote frame asks for."""
        return self.dlc if self.remote and self.dlc is not None else len(self.data)


def _table() -> tuple[int, ...]:
    """CRC-15 of each byte value (MSB first), for eight bits at a time."""
    out = []
    for byte in range(256):
        crc = byte << 7
        for _ in range(8):
            crc = ((crc << 1) ^ _CRC15_POLY if crc & 0x4000 else crc << 1) & 0x7FFF
        out.append(crc)
    return tuple(out)


_CRC15_TABLE = _table()


def _crc15_of(value: int, width: int) -> int:
    """The CRC-15 of the ``width`` bits of ``value`` (MSB first): the bits over a whole byte one at a time,
    then a byte at a time (the bus times every frame it carries: ~1,700 a second on POPUP's)."""
    crc, lead = 0, width % 8
    for k in range(width - 1, width - 1 - lead, -1):
        feedback = ((value >> k) & 1) ^ (crc >> 14)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    for shift in range(width - lead - 8, -1, -8):
        crc = ((crc << 8) & 0x7FFF) ^ _CRC15_TABLE[((crc >> 7) ^ (value >> shift)) & 0xFF]
    return crc


def _stuff_count(bits: str) -> int:
    """Stuff bits a transmitter inserts into ``bits`` ("0"/"1"): after each first five equal bits, the
    opposite bit, which starts the next run (so the search goes on from it)."""
    count, pos = 0, 0
    while True:
        zeros, ones = bits.find("00000", pos), bits.find("11111", pos)
        i = zeros if ones < 0 or 0 <= zeros < ones else ones
        if i < 0:
            return count
        pos = i + 5
        bits = bits[:pos] + ("1" if bits[i] == "0" else "0") + bits[pos:]
        count += 1


def _head(frame: CanFrame) -> tuple[int, int]:
    """Start of frame through the data field as (value, width) (dominant 0, recessive 1)."""
    rtr = int(frame.remote)
    if frame.extended:  # SOF, base id, SRR, IDE, id extension, RTR, r1, r0
        value, width = ((frame.can_id >> 18) << 2 | 0b11) << 18 | (frame.can_id & 0x3FFFF), 1 + 11 + 2 + 18
    else:  # SOF, id, RTR, IDE, r0
        value, width = frame.can_id, 1 + 11
    value, width = (value << 3 | rtr << 2) << 4 | frame.length, width + 3 + 4
    if frame.data:
        value = value << 8 * len(frame.data) | int.from_bytes(frame.data, "big")
        width += 8 * len(frame.data)
    return value, width


def crc15(bits: list[int]) -> int:
    """The CAN CRC-15 of a bit sequence (start of frame through the data field)."""
    return _crc15_of(int("".join(map(str, bits)) or "0", 2), len(bits))


def unstuffed_bits(frame: CanFrame) -> list[int]:
    """The frame's bits from start of frame through the CRC, before stuffing (dominant 0, recessive 1)."""
    value, width = _head(frame)
    return [int(b) for b in format(value << 15 | _crc15_of(value, width), f"0{width + 15}b")]


def stuff_bits(bits: list[int]) -> int:
    """How many stuff bits a transmitter inserts into ``bits`` (one after every run of five equal bits,
    the stuff bit itself starting the next run)."""
    return _stuff_count("".join(map(str, bits)))


@functools.lru_cache(maxsize=256)  # the bus times a frame when it arbitrates and again when it ends
def frame_bits(frame: CanFrame) -> int:
    """Bits the frame occupies on the bus, stuff bits and the 3-bit interframe space included (an 8-byte
    standard frame: 111 plus 0–24 stuff bits)."""
    value, width = _head(frame)
    stuffed = format(value << 15 | _crc15_of(value, width), f"0{width + 15}b")
    return width + 15 + _stuff_count(stuffed) + _TRAILER_BITS
