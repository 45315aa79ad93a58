"""Dynamixel Protocol 2.0: packets, CRC-16 and byte stuffing (ROBOTIS e-manual; devices.md).

Instruction: ``FF FF FD 00 | ID | LEN_L LEN_H | INST | params | CRC_L CRC_H`` with LEN = len(params) + 3;
status: ``… | ID | LEN | 0x55 | ERR | params | CRC`` with LEN = len(params) + 4. Stuffing inserts an extra
``FD`` after every ``FF FF FD`` inside INST..params; LEN and CRC are computed after stuffing.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from acquisition.errors import CodecError

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
STATUS = 0x55

# instructions
PING, READ, WRITE, REG_WRITE, ACTION, FACTORY_RESET, REBOOT, CLEAR = (
    0x01,
    0x02,
    0x03,
    0x04,
    0x05,
    0x06,
    0x08,
    0x10,
)
SYNC_READ, SYNC_WRITE, FAST_SYNC_READ, BULK_READ, BULK_WRITE = 0x82, 0x83, 0x8A, 0x92, 0x93

# error byte
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = (
    range(1, 8)
)
ERR_HARDWARE_ALERT = 0x80
ERROR_NAMES = {
    ERR_RESULT_FAIL: "Result Fail",
    ERR_INSTRUCTION: "Instruction Error",
    ERR_CRC: "CRC Error",
    ERR_DATA_RANGE: "Data Range Error",
    ERR_DATA_LENGTH: "Data Length Error",
    ERR_DATA_LIMIT: "Data Limit Error",
    ERR_ACCESS: "Access Error",
}

# XM430-W350 control table (address, size)
MODEL_NUMBER = (0, 2)
FIRMWARE_VERSION = (6, 1)
ID = (7, 1)
BAUD_RATE = (8, 1)
RETURN_DELAY_TIME = (9, 1)
DRIVE_MODE = (10, 1)
OPERATING_MODE = (11, 1)
CURRENT_LIMIT = (38, 2)
VELOCITY_LIMIT = (44, 4)
MAX_POSITION_LIMIT = (48, 4)
MIN_POSITION_LIMIT = (52, 4)
TORQUE_ENABLE = (64, 1)
LED = (65, 1)
STATUS_RETURN_LEVEL = (68, 1)
HARDWARE_ERROR_STATUS = (70, 1)
POSITION_D_GAIN = (80, 2)
POSITION_I_GAIN = (82, 2)
POSITION_P_GAIN = (84, 2)
GOAL_CURRENT = (102, 2)
GOAL_VELOCITY = (104, 4)
PROFILE_ACCELERATION = (108, 4)
PROFILE_VELOCITY = (112, 4)
GOAL_POSITION = (116, 4)
REALTIME_TICK = (120, 2)
MOVING = (122, 1)
MOVING_STATUS = (123, 1)
PRESENT_PWM = (124, 2)
PRESENT_CURRENT = (126, 2)
PRESENT_VELOCITY = (128, 4)
PRESENT_POSITION = (132, 4)
PRESENT_INPUT_VOLTAGE = (144, 2)
PRESENT_TEMPERATURE = (146, 1)
PROTOCOL_VERSION = (13, 1)
EEPROM_END = 64  # addresses below are writable only with torque off
CONTROL_TABLE_SIZE = 662  # addresses 0 … 661 (Indirect Data 56); the items: acquisition.codecs.xm430
XM430_W350_MODEL = 1020
OPERATING_MODE_POSITION = 3

# XM430 register units in SI (e-manual): one count of each register
POSITION_COUNTS_PER_REV = 4096
RAD_PER_POSITION_COUNT = 2 * math.pi / POSITION_COUNTS_PER_REV
RAD_S_PER_VELOCITY_UNIT = 0.229 * 2 * math.pi / 60  # 0.229 rpm (Present Velocity, Profile Velocity)
RAD_S2_PER_ACCELERATION_UNIT = 214.577 * 2 * math.pi / 3600  # 214.577 rev/min² (Profile Acceleration)
AMP_PER_CURRENT_UNIT = 2.69e-3  # Present Current, Goal Current
CURRENT_LIMIT_DEFAULT = 1193

# Present Current, Velocity and Position read together (addresses 126–135) in one transaction
STATE_BLOCK = (126, 10)


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes, crc: int = 0) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0, not reflected); ``crc`` continues a running CRC."""
    for byte in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ byte) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert FD after every FF FF FD (applied to INST..params)."""
    return body.replace(b"\xff\xff\xfd", b"\xff\xff\xfd\xfd")


def unstuff(body: bytes) -> bytes:
    """Remove the FD inserted after every FF FF FD."""
    return body.replace(b"\xff\xff\xfd\xfd", b"\xff\xff\xfd")


def _packet(dxl_id: int, body: bytes) -> bytes:
    body = stuff(body)
    head = HEADER + bytes([dxl_id]) + struct.pack("<H", len(body) + 2)
    crc = crc16(head + body)
    return head + body + struct.pack("<H", crc)


def instruction(dxl_id: int, inst: int, params: bytes = b"") -> bytes:
    """An instruction packet (what the host sends)."""
    return _packet(dxl_id, bytes([inst]) + params)


def status(dxl_id: int, error: int = 0, params: bytes = b"") -> bytes:
    """A status packet (what a servo answers)."""
    return _packet(dxl_id, bytes([STATUS, error]) + params)


def fast_sync_read_status(replies: list[tuple[int, int, bytes]]) -> bytes:
    """Fast Sync Read reply: one packet from ID 0xFE with (error, id, data) per servo, each followed by
    the running CRC of the packet so far; not stuffed (ROBOTIS e-manual)."""
    length = 1 + sum(1 + 1 + len(data) + 2 for _, _, data in replies) + 2
    out = bytearray(HEADER + bytes([BROADCAST_ID]) + struct.pack("<H", length) + bytes([STATUS]))
    for error, dxl_id, data in replies:
        out += bytes([error, dxl_id]) + data
        out += struct.pack("<H", crc16(bytes(out)))
    out += struct.pack("<H", crc16(bytes(out)))
    return bytes(out)


@dataclass(frozen=True)
class Packet:
    """A decoded packet: ``inst`` is 0x55 for status packets (``error`` then holds the error byte)."""

    dxl_id: int
    inst: int
    params: bytes
    error: int = 0


class PacketError(CodecError):
    """Bytes that do not decode as a packet (too short, a length that does not match, a failed CRC)."""


class CrcError(PacketError):
    """A packet failed its CRC."""


MIN_PACKET = 10  # header, ID, LEN, INST, CRC: an instruction without parameters


class PacketReader:
    """Splits a byte stream into packets by LEN (never by a header seen inside params, see devices.md)."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def reset(self) -> None:
        self._buf.clear()

    def feed(self, data: bytes) -> list[Packet | PacketError]:
        """Append bytes; return every complete packet (or the PacketError it gave, in its place)."""
        self._buf += data
        out: list[Packet | PacketError] = []
        while True:
            start = self._buf.find(HEADER)
            if start < 0:
                del self._buf[: max(0, len(self._buf) - 3)]  # keep a possible partial header
                return out
            del self._buf[:start]
            if len(self._buf) < 7:
                return out
            length = struct.unpack_from("<H", self._buf, 5)[0]
            total = 7 + length
            if len(self._buf) < total:
                return out
            raw = bytes(self._buf[:total])
            del self._buf[:total]
            out.append(decode(raw))

    def pending(self) -> int:
        return len(self._buf)


def decode(raw: bytes) -> Packet | PacketError:
    """Decode one complete packet (header through CRC); any other bytes give a PacketError (returned, not
    raised: a reader hands it on in the packet's place)."""
    if len(raw) < MIN_PACKET or raw[:4] != HEADER:
        return PacketError(f"not a packet: {len(raw)} bytes starting {bytes(raw[:4]).hex(' ')}")
    length = struct.unpack_from("<H", raw, 5)[0]
    if length != len(raw) - 7:
        return PacketError(f"packet from ID {raw[4]}: LEN {length} but {len(raw) - 7} bytes follow it")
    if crc16(raw[:-2]) != struct.unpack_from("<H", raw, len(raw) - 2)[0]:
        return CrcError(f"CRC mismatch in packet from ID {raw[4]}")
    body = unstuff(raw[7:-2])
    if body[0] == STATUS:
        if len(body) < 2:
            return PacketError(f"status packet from ID {raw[4]} without an error byte")
        return Packet(raw[4], STATUS, body[2:], body[1])
    return Packet(raw[4], body[0], body[1:])
