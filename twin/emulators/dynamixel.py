"""A Dynamixel Protocol 2.0 bus of XM430 servos, byte for byte (the real dynamixel-sdk talks to it).

Each servo keeps the XM430-W350's full control table (``xm430_table``: EEPROM 0–63, RAM 64–227, Indirect
Address/Data to 661) and refuses what the servo refuses, with its error number: read-only items and EEPROM
with torque on (Access Error), values outside an item's range (Data Range Error) or outside its limit items
(Data Limit Error), writes that cut an item (Data Length Error), Action without Reg Write and unknown
instructions (Instruction Error). Nothing is stored on error. Accepted writes go on to the hardware behind
the table (``ServoHardware``: the twin in the rig, a simple model in ``demo_bus``); reads first refresh the
present values from it.

Replies follow the servo and the SDK's expectations (devices.md, errors-and-foxglove.md): status packets in
the order the IDs were asked, stuffed; the Alert bit (0x80) while a hardware error is latched; Status Return
Level 68 honoured (0: ping only, 1: + reads, 2: all); no reply to broadcast writes (nor to a Sync/Bulk
Write, which applies the same checks per servo); a servo that does not exist stays silent. A packet that
fails its CRC is dropped without a reply: a real servo stays silent (a bad-CRC ping gets no answer,
Dynamixel2Arduino issue #93; ROBOTIS's own slave code drops it) although Protocol 2.0 defines a CRC Error
number. A new ID (address 7) is acknowledged from the old one (dynamixel-workbench's ``changeID`` relies on
that ack, and the SDK discards a reply from another ID); the servo answers at the new ID afterwards.

The wire: each servo's UART runs at its Baud Rate (address 8) and hears only a host at that baud
(``feed_at``); a new Baud Rate, like a new ID, takes effect after the status that acknowledges it. Each
status goes after its servo's Return Delay Time (address 9, 2 µs units): ``response_s`` is their sum for the
last reply, which the pty host adds to the bytes' time on the wire. ``factory=True`` builds the bus as it
comes out of the box (every servo ID 1, 57,600 baud, Return Delay Time 250); two servos answering one ID
talk over each other, as on a real bus: the host gets one garbled status (a CRC error) instead of two.
"""

from __future__ import annotations

import struct
from typing import Protocol

import numpy as np

from acquisition.codecs import dynamixel as dx
from acquisition.devices.bus_budget import (
    DYNAMIXEL_BAUDS,
    DYNAMIXEL_FACTORY_BAUD,
    DYNAMIXEL_FACTORY_RETURN_DELAY,
    DYNAMIXEL_RETURN_DELAY_UNIT_S,
)
from twin.emulators.base import Emulator
from twin.emulators.xm430_table import ControlTable

__all__ = ["ControlTable", "DynamixelBusEmulator", "ServoHardware", "SimpleServos", "demo_bus"]

PACKET_TIMEOUT_S = 0.1  # a half-received packet older than this is dropped (the servo's parser resets)
_REPLY_ALL, _REPLY_READ = 2, 1  # Status Return Level
_BAUD_CODES = {baud: code for code, baud in DYNAMIXEL_BAUDS.items()}


def baud_code(baud: int) -> int:
    """The Baud Rate item's code for ``baud`` (a ValueError for a baud an XM430 cannot run at)."""
    if baud not in _BAUD_CODES:
        raise ValueError(f"an XM430 runs at {sorted(_BAUD_CODES)} baud, not {baud}")
    return _BAUD_CODES[baud]


def return_delay_units(return_delay_s: float) -> int:
    """The Return Delay Time item (2 µs units, 0–254) nearest ``return_delay_s``."""
    units = round(return_delay_s / DYNAMIXEL_RETURN_DELAY_UNIT_S)
    if not 0 <= units <= 254:
        raise ValueError(f"a Return Delay Time of {return_delay_s} s is outside 0–508 µs")
    return units


def _status_ids(reply: bytes) -> list[int]:
    """The IDs of the status packets ``reply`` holds, in order (LEN counts the stuffed bytes)."""
    ids, k = [], 0
    while k + 7 <= len(reply):
        ids.append(reply[k + 4])
        k += 7 + int.from_bytes(reply[k + 5 : k + 7], "little")
    return ids


class ServoHardware(Protocol):
    """What stands behind the control tables; ``dxl_id`` is the servo's ``serial`` (its first ID)."""

    def apply(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        """The host wrote to the table: act on goal, profile, torque."""

    def sense(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        """Before a read: write the present values (tick, moving, current, velocity, position)."""


class DynamixelBusEmulator(Emulator):
    """Servos on one bus; ``ids`` are the servos present (each one's ``serial``). ``tables`` maps each
    servo's present ID to its table (rebuilt when the host changes an ID). The tables hold ``baud`` and
    ``return_delay_s`` (the robot description's), or the factory's with ``factory``."""

    name = "servo_bus"

    def __init__(self, ids: list[int], hardware: ServoHardware, factory: bool = False,
                 baud: int = 1_000_000, return_delay_s: float = 0.0) -> None:  # fmt: skip
        self.servos = [ControlTable(i) for i in ids]
        for table in self.servos:
            table.set(dx.ID, 1 if factory else table.serial)
            table.set(dx.BAUD_RATE, baud_code(DYNAMIXEL_FACTORY_BAUD if factory else baud))
            delay = DYNAMIXEL_FACTORY_RETURN_DELAY if factory else return_delay_units(return_delay_s)
            table.set(dx.RETURN_DELAY_TIME, delay)
        self.hardware = hardware
        self.reader = dx.PacketReader()
        self._last_rx_s = 0.0
        self._hearing: int | None = None  # the baud the host sends at (None: every servo hears)
        self.unplugged: set[int] = set()  # serials of servos whose cable is out (``plug``)
        self._response_s = 0.0
        self._registered: dict[int, tuple[int, bytes]] = {}  # serial → Reg Write waiting for Action
        self._index()
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

    def _index(self) -> None:
        """Which servos answer which ID (a servo set to Protocol 1.0 no longer understands any)."""
        self._by_id: dict[int, list[ControlTable]] = {}
        self.tables = {}
        for table in self.servos:
            if table.get(dx.PROTOCOL_VERSION) == 2:
                self.tables.setdefault(table.dxl_id, table)
                heard = self._hearing is None or self.servo_baud(table) == self._hearing
                if heard and table.serial not in self.unplugged:
                    self._by_id.setdefault(table.dxl_id, []).append(table)

    @staticmethod
    def servo_baud(table: ControlTable) -> int:
        """The baud ``table``'s servo runs at now."""
        return DYNAMIXEL_BAUDS[table.get(dx.BAUD_RATE)]

    def device_baud(self) -> int:
        """The baud the bus's servos run at (the first servo's, where a half-configured bus differs)."""
        return self.servo_baud(self.servos[0])

    def response_s(self) -> float:
        """The Return Delay Times of the statuses of the last reply, summed (each servo waits its own)."""
        return self._response_s

    def plug(self, serials: set[int]) -> None:
        """Only the servos of ``serials`` on the bus, the others' cables out: how a lab gives new servos
        (all ID 1) their IDs, connecting one servo at a time."""
        self.unplugged = {t.serial for t in self.servos} - set(serials)
        self._index()

    def reset_link(self) -> None:
        self.reader.reset()

    def feed_at(self, data: bytes, now_s: float, baud: int | None) -> bytes:
        """Only the servos at ``baud`` hear the host (the others see framing errors)."""
        if baud != self._hearing:
            self._hearing = baud
            self._index()
        return self.feed(data, now_s)

    def feed(self, data: bytes, now_s: float) -> bytes:
        if self.reader.pending() and now_s - self._last_rx_s > PACKET_TIMEOUT_S:
            self.reader.reset()  # the rest of a cut packet never came (a corrupted LEN, a reset host)
        self._last_rx_s = now_s
        self._response_s = 0.0
        out = bytearray()
        for packet in self.reader.feed(data):
            if isinstance(packet, dx.PacketError):
                continue  # a servo cannot trust the ID of a corrupted packet: it stays silent
            if packet.inst != dx.STATUS:
                delays = {i: [t.get(dx.RETURN_DELAY_TIME) for t in ts] for i, ts in self._by_id.items()}
                out += self._answered(self._execute(packet, now_s), delays)
        return bytes(out)

    def _answered(self, reply: bytes, delays: dict[int, list[int]]) -> bytes:
        """``reply`` as the bus carries it: each status after its servo's Return Delay Time (``delays``: by
        ID, as the packet found the servos); servos sharing an ID talk over each other, and the host gets
        the first status with a broken CRC in place of theirs."""
        ids = _status_ids(reply)
        for i in ids:
            units = delays.get(i, [0])
            self._response_s += max(units) * DYNAMIXEL_RETURN_DELAY_UNIT_S
        clashes = [i for i in set(ids) if len(delays.get(i, ())) > 1]
        if not clashes:
            return reply
        end = 7 + int.from_bytes(reply[5:7], "little")  # one status survives, garbled: a CRC error
        return reply[: end - 1] + bytes([reply[end - 1] ^ 0xFF])

    # ------------------------------------------------------------------------------------ dispatch
    def _execute(self, p: dx.Packet, now_s: float) -> bytes:
        handler = self._handlers.get(p.inst)
        if handler is None:
            return self._status(p.dxl_id, dx.ERR_INSTRUCTION)
        return handler(p, now_s)

    def _targets(self, dxl_id: int) -> list[ControlTable]:
        if dxl_id == dx.BROADCAST_ID:
            return [t for tables in self._by_id.values() for t in tables]
        return self._by_id.get(dxl_id, [])

    def _status(self, dxl_id: int, error: int = 0, params: bytes = b"", level: int = _REPLY_ALL) -> bytes:
        """Each addressed servo's status (none to a broadcast; none below Status Return Level ``level``)."""
        if dxl_id == dx.BROADCAST_ID:
            return b""
        return b"".join(
            dx.status(dxl_id, error | t.alert, params)
            for t in self._by_id.get(dxl_id, [])
            if t.get(dx.STATUS_RETURN_LEVEL) >= level
        )

    def _read_bytes(self, table: ControlTable, address: int, length: int, now_s: float) -> tuple[int, bytes]:
        if table.senses(address, length):
            self.hardware.sense(table.serial, table, now_s)
        error, data = table.read(address, length)
        return error | table.alert, data

    def _write_bytes(self, table: ControlTable, address: int, data: bytes, now_s: float) -> int:
        error = table.write(address, data)
        if error:
            return error
        if address <= dx.PROTOCOL_VERSION[0]:
            self._index()  # a new ID, Baud Rate or protocol: heard from the next packet on
        self.hardware.apply(table.serial, table, now_s)
        return 0

    # ---------------------------------------------------------------------------------- instructions
    def _ping(self, p: dx.Packet, now_s: float) -> bytes:
        out = bytearray()
        for t in self._targets(p.dxl_id):  # a broadcast ping: every servo answers, in ID order here
            out += dx.status(t.dxl_id, t.alert, struct.pack("<HB", t.get(dx.MODEL_NUMBER), t.data[6]))
        return bytes(out)

    def _read(self, p: dx.Packet, now_s: float) -> bytes:
        if p.dxl_id == dx.BROADCAST_ID:
            return b""
        if len(p.params) != 4:
            return self._status(p.dxl_id, dx.ERR_DATA_LENGTH, level=_REPLY_READ)
        address, length = struct.unpack("<HH", p.params)
        out = bytearray()
        for t in self._targets(p.dxl_id):
            if t.get(dx.STATUS_RETURN_LEVEL) >= _REPLY_READ:
                error, data = self._read_bytes(t, address, length, now_s)
                out += dx.status(p.dxl_id, error, data)
        return bytes(out)

    def _write(self, p: dx.Packet, now_s: float) -> bytes:
        if len(p.params) < 3:
            return self._status(p.dxl_id, dx.ERR_DATA_LENGTH)
        address = struct.unpack_from("<H", p.params)[0]
        # answered as the packet found the servo: from the ID it named (a servo whose ID it changes acks
        # from the old one) and at the Status Return Level it had
        answers = [(t, t.get(dx.STATUS_RETURN_LEVEL) >= _REPLY_ALL) for t in self._targets(p.dxl_id)]
        errors = [self._write_bytes(t, address, p.params[2:], now_s) for t, _ in answers]
        if p.dxl_id == dx.BROADCAST_ID:
            return b""
        return b"".join(
            dx.status(p.dxl_id, error | t.alert)
            for (t, answer), error in zip(answers, errors, strict=True)
            if answer
        )

    def _reg_write(self, p: dx.Packet, now_s: float) -> bytes:
        if len(p.params) < 3:
            return self._status(p.dxl_id, dx.ERR_DATA_LENGTH)
        address, data = struct.unpack_from("<H", p.params)[0], p.params[2:]
        errors = []
        for t in self._targets(p.dxl_id):
            probe = ControlTable(t.serial)  # the checks of a write, on a copy: nothing changes until Action
            probe.data[:] = t.data
            error = probe.write(address, data)
            if not error:
                self._registered[t.serial] = (address, data)
                t.data[69] = 1  # Registered Instruction
            errors.append(error)
        return self._status(p.dxl_id, errors[0] if errors else 0)

    def _action(self, p: dx.Packet, now_s: float) -> bytes:
        error = 0
        for t in self._targets(p.dxl_id):
            if t.serial not in self._registered:
                error = dx.ERR_INSTRUCTION  # Action without Reg Write
                continue
            address, data = self._registered.pop(t.serial)
            t.data[69] = 0
            error = self._write_bytes(t, address, data, now_s)
        return self._status(p.dxl_id, error)

    def _reboot(self, p: dx.Packet, now_s: float) -> bytes:
        for t in self._targets(p.dxl_id):
            t.set(dx.TORQUE_ENABLE, 0)
            t.set(dx.HARDWARE_ERROR_STATUS, 0)
            t.data[69] = 0
            self._registered.pop(t.serial, None)
            self.hardware.apply(t.serial, t, now_s)
        return self._status(p.dxl_id)

    def _no_op(self, p: dx.Packet, now_s: float) -> bytes:
        return self._status(p.dxl_id)

    def _sync_read(self, p: dx.Packet, now_s: float) -> bytes:
        if len(p.params) < 5:
            return b""
        address, length = struct.unpack_from("<HH", p.params)
        out = bytearray()
        for i in p.params[4:]:  # in the order asked: the SDK reads one status per ID, in order
            for t in self._by_id.get(i, ()):
                error, data = self._read_bytes(t, address, length, now_s)
                out += dx.status(i, error, data)
        return bytes(out)

    def _fast_sync_read(self, p: dx.Packet, now_s: float) -> bytes:
        if len(p.params) < 5:
            return b""
        address, length = struct.unpack_from("<HH", p.params)
        replies = []
        for i in p.params[4:]:
            tables = self._by_id.get(i)
            if not tables:
                return b""  # one missing servo breaks the shared packet: the host times out
            error, data = self._read_bytes(tables[0], address, length, now_s)
            replies.append((error, i, data))
        return dx.fast_sync_read_status(replies)

    def _sync_write(self, p: dx.Packet, now_s: float) -> bytes:
        if len(p.params) < 4:
            return b""
        address, length = struct.unpack_from("<HH", p.params)
        body = p.params[4:]
        for k in range(0, len(body) - length, length + 1):  # whole entries only
            for t in self._by_id.get(body[k], ()):
                self._write_bytes(t, address, body[k + 1 : k + 1 + length], now_s)
        return b""

    def _bulk_read(self, p: dx.Packet, now_s: float) -> bytes:
        out = bytearray()
        for k in range(0, len(p.params) - 4, 5):
            i, address, length = struct.unpack_from("<BHH", p.params, k)
            for t in self._by_id.get(i, ()):
                error, data = self._read_bytes(t, address, length, now_s)
                out += dx.status(i, error, data)
        return bytes(out)

    def _bulk_write(self, p: dx.Packet, now_s: float) -> bytes:
        k = 0
        while k + 5 <= len(p.params):
            i, address, length = struct.unpack_from("<BHH", p.params, k)
            data = p.params[k + 5 : k + 5 + length]
            if len(data) == length:
                for t in self._by_id.get(i, ()):
                    self._write_bytes(t, address, data, now_s)
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
    """Two XM430s (IDs 1, 2) on the simple model, for ``python -m twin.serve``."""
    bus = DynamixelBusEmulator([1, 2], SimpleServos())
    for table in bus.servos:  # the goal starts where the shaft is: torque-on does not jump
        table.set(dx.GOAL_POSITION, 2048)
    return bus
