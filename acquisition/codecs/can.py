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


def _bits(value: int, width: int) -> list[int]:
    return [(value >> (width - 1 - k)) & 1 for k in range(width)]


def crc15(bits: list[int]) -> int:
    """The CAN CRC-15 of a bit sequence (start of frame through the data field)."""
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    return crc


def unstuffed_bits(frame: CanFrame) -> list[int]:
    """The frame's bits from start of frame through the CRC, before stuffing (dominant 0, recessive 1)."""
    rtr = int(frame.remote)
    if frame.extended:
        head = [0, *_bits(frame.can_id >> 18, 11), 1, 1, *_bits(frame.can_id & 0x3FFFF, 18), rtr, 0, 0]
    else:
        head = [0, *_bits(frame.can_id, 11), rtr, 0, 0]
    body = head + _bits(frame.length, 4)
    for byte in frame.data:
        body += _bits(byte, 8)
    return body + _bits(crc15(body), 15)


def stuff_bits(bits: list[int]) -> int:
    """How many stuff bits a transmitter inserts into ``bits`` (one after every run of five equal bits,
    the stuff bit itself starting the next run)."""
    count, run, last = 0, 0, None
    for bit in bits:
        if bit == last:
            run += 1
        else:
            run, last = 1, bit
        if run == 5:
            count += 1
            run, last = 1, 1 - bit  # the inserted opposite bit
    return count


@functools.lru_cache(maxsize=256)  # the bus times a frame when it arbitrates and again when it ends
def frame_bits(frame: CanFrame) -> int:
    """Bits the frame occupies on the bus, stuff bits and the 3-bit interframe space included (an 8-byte
    standard frame: 111 plus 0–24 stuff bits)."""
    bits = unstuffed_bits(frame)
    return len(bits) + stuff_bits(bits) + _TRAILER_BITS
