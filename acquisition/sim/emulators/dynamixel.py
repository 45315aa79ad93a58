"""A Dynamixel Protocol 2.0 bus of XM430 servos, byte for byte (the real dynamixel-sdk talks to it).

Each servo has a 256-byte control table. Writes go to the table (EEPROM only with torque off) and then to
the hardware behind it (``ServoHardware``: the twin in the rig, a simple model in ``demo_bus``); reads
first refresh the present values from the hardware. Replies follow the SDK's expectations (devices.md):
status packets in the order the IDs were asked, stuffed; no reply to broadcast writes; a servo that does not
exist stays silent.
"""

from __future__ import annotations

import struct
from typing import Protocol

import numpy as np

from acquisition.protocols import dynamixel as dx
from acquisition.sim.emulators.base import Emulator

_RAM_REFRESH_FROM = dx.REALTIME_TICK[0]


class ControlTable:
    """One servo's control table with typed access by (address, size)."""

    def __init__(self, dxl_id: int, model: int = dx.XM430_W350_MODEL) -> None:
        self.data = bytearray(dx.CONTROL_TABLE_SIZE)
        self.set(dx.MODEL_NUMBER, model)
        self.set(dx.FIRMWARE_VERSION, 46)
        self.set(dx.ID, dxl_id)
        self.set(dx.BAUD_RATE, 3)
        self.set(dx.RETURN_DELAY_TIME, 250)
        self.set(dx.OPERATING_MODE, dx.OPERATING_MODE_POSITION)
        self.set(dx.CURRENT_LIMIT, 1193)
        self.set(dx.VELOCITY_LIMIT, 200)
        self.set(dx.MAX_POSITION_LIMIT, 4095)
        self.set(dx.STATUS_RETURN_LEVEL, 2)
        self.set(dx.POSITION_P_GAIN, 800)
        self.set(dx.PRESENT_INPUT_VOLTAGE, 120)
        self.set(dx.PRESENT_TEMPERATURE, 30)

    def get(self, item: tuple[int, int], signed: bool = False) -> int:
        address, size = item
        return int.from_bytes(self.data[address : address + size], "little", signed=signed)

    def set(self, item: tuple[int, int], value: int) -> None:
        address, size = item
        self.data[address : address + size] = (int(value) & ((1 << (8 * size)) - 1)).to_bytes(size, "little")

    @property
    def torque_on(self) -> bool:
        return bool(self.get(dx.TORQUE_ENABLE))


class ServoHardware(Protocol):
    """What stands behind the control tables."""

    def apply(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        """The host wrote to the table: act on goal, profile, torque."""

    def sense(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        """Before a read: write the present values (tick, moving, current, velocity, position)."""


class DynamixelBusEmulator(Emulator):
    """Servos on one bus; ``ids`` are the servos present."""

    name = "servo_bus"

    def __init__(self, ids: list[int], hardware: ServoHardware) -> None:
        self.tables = {i: ControlTable(i) for i in ids}
        self.hardware = hardware
        self.reader = dx.PacketReader()
        self._registered: dict[int, tuple[int, bytes]] = {}
        self._handlers = {
            dx.PING: self._ping,
            dx.READ: self._read,
            dx.WRITE: self._write,
            dx.REG_WRITE: self._reg_write,
            dx.ACTION: self._action,
            dx.REBOOT: self._reboot,
            dx.FACTORY_RESET: self._no_op,
            dx.CLEAR: self._no_op,
            dx.SYNC_READ: self._sync_read,
            dx.SYNC_WRITE: self._sync_write,
            dx.FAST_SYNC_READ: self._fast_sync_read,
            dx.BULK_READ: self._bulk_read,
            dx.BULK_WRITE: self._bulk_write,
        }

    def reset_link(self) -> None:
        self.reader.reset()

    def feed(self, data: bytes, now_s: float) -> bytes:
        out = bytearray()
        for packet in self.reader.feed(data):
            if isinstance(packet, dx.CrcError):
                continue  # a servo cannot tell who a corrupted packet was for: it stays silent
            if packet.inst != dx.STATUS:
                out += self._execute(packet, now_s)
        return bytes(out)

    # ------------------------------------------------------------------------------------ dispatch
    def _execute(self, p: dx.Packet, now_s: float) -> bytes:
        handler = self._handlers.get(p.inst)
        if handler is None:
            return self._reply_each(p.dxl_id, lambda i: dx.status(i, dx.ERR_INSTRUCTION))
        return handler(p, now_s)

    def _targets(self, dxl_id: int) -> list[int]:
        if dxl_id == dx.BROADCAST_ID:
            return sorted(self.tables)
        return [dxl_id] if dxl_id in self.tables else []

    def _reply_each(self, dxl_id: int, make) -> bytes:
        return b"".join(make(i) for i in self._targets(dxl_id))

    def _read_bytes(self, dxl_id: int, address: int, length: int, now_s: float) -> tuple[int, bytes]:
        if address + length > dx.CONTROL_TABLE_SIZE:
            return dx.ERR_DATA_RANGE, b""
        table = self.tables[dxl_id]
        if address + length > _RAM_REFRESH_FROM:
            self.hardware.sense(dxl_id, table, now_s)
        return 0, bytes(table.data[address : address + length])

    def _write_bytes(self, dxl_id: int, address: int, data: bytes, now_s: float) -> int:
        table = self.tables[dxl_id]
        if address + len(data) > dx.CONTROL_TABLE_SIZE:
            return dx.ERR_DATA_RANGE
        if address < dx.EEPROM_END and table.torque_on and address != dx.TORQUE_ENABLE[0]:
            return dx.ERR_ACCESS
        table.data[address : address + len(data)] = data
        self.hardware.apply(dxl_id, table, now_s)
        return 0

    # ---------------------------------------------------------------------------------- instructions
    def _ping(self, p: dx.Packet, now_s: float) -> bytes:
        def reply(i: int) -> bytes:
            t = self.tables[i]
            return dx.status(i, 0, struct.pack("<HB", t.get(dx.MODEL_NUMBER), t.get(dx.FIRMWARE_VERSION)))

        return self._reply_each(p.dxl_id, reply)

    def _read(self, p: dx.Packet, now_s: float) -> bytes:
        if p.dxl_id not in self.tables or len(p.params) != 4:
            return b""
        address, length = struct.unpack("<HH", p.params)
        error, data = self._read_bytes(p.dxl_id, address, length, now_s)
        return dx.status(p.dxl_id, error, data)

    def _write(self, p: dx.Packet, now_s: float) -> bytes:
        address = struct.unpack_from("<H", p.params)[0]
        errors = {i: self._write_bytes(i, address, p.params[2:], now_s) for i in self._targets(p.dxl_id)}
        if p.dxl_id == dx.BROADCAST_ID or p.dxl_id not in errors:
            return b""
        return dx.status(p.dxl_id, errors[p.dxl_id])

    def _reg_write(self, p: dx.Packet, now_s: float) -> bytes:
        address = struct.unpack_from("<H", p.params)[0]
        for i in self._targets(p.dxl_id):
            self._registered[i] = (address, p.params[2:])
        return dx.status(p.dxl_id) if p.dxl_id in self.tables else b""

    def _action(self, p: dx.Packet, now_s: float) -> bytes:
        for i in self._targets(p.dxl_id):
            if i in self._registered:
                address, data = self._registered.pop(i)
                self._write_bytes(i, address, data, now_s)
        return dx.status(p.dxl_id) if p.dxl_id in self.tables else b""

    def _reboot(self, p: dx.Packet, now_s: float) -> bytes:
        for i in self._targets(p.dxl_id):
            self.tables[i].set(dx.TORQUE_ENABLE, 0)
            self.tables[i].set(dx.HARDWARE_ERROR_STATUS, 0)
            self.hardware.apply(i, self.tables[i], now_s)
        return dx.status(p.dxl_id) if p.dxl_id in self.tables else b""

    def _no_op(self, p: dx.Packet, now_s: float) -> bytes:
        return dx.status(p.dxl_id) if p.dxl_id in self.tables else b""

    def _sync_read(self, p: dx.Packet, now_s: float) -> bytes:
        address, length = struct.unpack_from("<HH", p.params)
        out = bytearray()
        for i in p.params[4:]:  # in the order asked: the SDK reads one status per ID, in order
            if i in self.tables:
                error, data = self._read_bytes(i, address, length, now_s)
                out += dx.status(i, error, data)
        return bytes(out)

    def _fast_sync_read(self, p: dx.Packet, now_s: float) -> bytes:
        address, length = struct.unpack_from("<HH", p.params)
        replies = []
        for i in p.params[4:]:
            if i not in self.tables:
                return b""  # one missing servo breaks the shared packet: the host times out
            error, data = self._read_bytes(i, address, length, now_s)
            replies.append((error, i, data))
        return dx.fast_sync_read_status(replies)

    def _sync_write(self, p: dx.Packet, now_s: float) -> bytes:
        address, length = struct.unpack_from("<HH", p.params)
        body = p.params[4:]
        for k in range(0, len(body) - length, length + 1):
            i = body[k]
            if i in self.tables:
                self._write_bytes(i, address, body[k + 1 : k + 1 + length], now_s)
        return b""

    def _bulk_read(self, p: dx.Packet, now_s: float) -> bytes:
        out = bytearray()
        for k in range(0, len(p.params) - 4, 5):
            i, address, length = struct.unpack_from("<BHH", p.params, k)
            if i in self.tables:
                error, data = self._read_bytes(i, address, length, now_s)
                out += dx.status(i, error, data)
        return bytes(out)

    def _bulk_write(self, p: dx.Packet, now_s: float) -> bytes:
        k = 0
        while k + 5 <= len(p.params):
            i, address, length = struct.unpack_from("<BHH", p.params, k)
            if i in self.tables:
                self._write_bytes(i, address, p.params[k + 5 : k + 5 + length], now_s)
            k += 5 + length
        return b""


class SimpleServos:
    """Stand-alone servo model (no twin): each joint slews to its goal at its profile velocity."""

    COUNTS_PER_S_PER_UNIT = dx.RAD_S_PER_VELOCITY_UNIT / dx.RAD_PER_POSITION_COUNT  # per 0.229 rpm unit

    def __init__(self) -> None:
        self._pos: dict[int, float] = {}
        self._last: dict[int, float] = {}

    def _advance(self, dxl_id: int, table: ControlTable, now_s: float) -> float:
        pos = self._pos.setdefault(dxl_id, 2048.0)
        dt = now_s - self._last.get(dxl_id, now_s)
        self._last[dxl_id] = now_s
        if table.torque_on:
            goal = table.get(dx.GOAL_POSITION, signed=True)
            speed = table.get(dx.PROFILE_VELOCITY) * self.COUNTS_PER_S_PER_UNIT or 4096.0
            pos += float(np.clip(goal - pos, -speed * dt, speed * dt))
        self._pos[dxl_id] = pos
        return pos

    def apply(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        self._advance(dxl_id, table, now_s)

    def sense(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        pos = self._advance(dxl_id, table, now_s)
        goal = table.get(dx.GOAL_POSITION, signed=True)
        table.set(dx.PRESENT_POSITION, round(pos))
        table.set(dx.MOVING, int(table.torque_on and abs(goal - pos) > 1))
        table.set(dx.PRESENT_CURRENT, 20 if table.torque_on else 0)
        table.set(dx.REALTIME_TICK, int(now_s * 1000) % 32768)


def demo_bus() -> DynamixelBusEmulator:
    """Two XM430s (IDs 1, 2) on the simple model, for ``python -m acquisition.sim.serve``."""
    return DynamixelBusEmulator([1, 2], SimpleServos())
