"""The Dynamixel bus (U2D2 + XM430s) on the official dynamixel-sdk, Protocol 2.0.

One Sync Read of addresses 120–135 returns each servo's Realtime Tick, current, velocity and position in one
transaction; goals go out in one Sync Write. Values are converted to SI (rad, rad/s, A); every read carries
the host receive time (int64 ns) and the servos' own tick (ms, wraps at 32768).

A servo that answers a ping, read or write with an error status raises a ``ServoStatusError`` subclass
(``servo_errors``: one per Protocol 2.0 error number, and the hardware Alert) whose message names the servo,
the item, what the servo said and what to do. A Sync Read carries each servo's Alert bit in ``ServoState``
instead (the readings are still good); Sync Writes get no status by design, so what a servo refuses there
goes unreported (the command guard checks every goal before it leaves).
"""

from __future__ import annotations

import logging
import os
import select
import struct
import termios
from dataclasses import dataclass

import numpy as np
import serial
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    GroupSyncWrite,
    PacketHandler,
    PortHandler,
)

from acquisition.codecs import dynamixel as dx
from acquisition.devices.base import Device, host_now_ns
from acquisition.devices.bus_budget import SERVO_BLOCK_BYTES
from acquisition.devices.servo_errors import ServoHardwareAlert, ServoStatusError, status_error
from acquisition.errors import (
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceTimeoutError,
)

__all__ = ["ServoBus", "ServoHardwareAlert", "ServoState", "ServoStatusError"]

log = logging.getLogger(__name__)

_BLOCK_START, _BLOCK_LEN = dx.REALTIME_TICK[0], SERVO_BLOCK_BYTES  # 120 … 135
_BLOCK = struct.Struct("<HBBhhii")  # tick, moving, moving status, PWM, current, velocity, position
assert _BLOCK.size == _BLOCK_LEN


@dataclass(frozen=True)
class ServoState:
    """One Sync Read of every servo on the bus (arrays in the order of ``ids``)."""

    host_ns: int
    ids: tuple[int, ...]
    tick_ms: np.ndarray  # servos' Realtime Tick (wraps at 32768)
    position_rad: np.ndarray
    velocity_rad_s: np.ndarray
    current_a: np.ndarray
    position_counts: np.ndarray
    current_counts: np.ndarray
    moving: np.ndarray
    alert: np.ndarray | None = None  # per servo: its status carried the hardware Alert bit


class _WaitingPortHandler(PortHandler):
    """dynamixel-sdk's port handler, with two changes that matter at 1 kHz on a shared computer: a read
    waits for bytes in ``select()`` instead of spinning on a non-blocking read (the SDK's loop burns a core
    while a reply is on its way), and a reply is awaited ``reply_timeout_s`` after the request has gone out
    (the SDK allows twice its 16 ms latency timer + 2 ms: 34 ms of a silent bus per failed poll)."""

    def __init__(self, port_name: str, reply_timeout_s: float) -> None:
        super().__init__(port_name)
        self.reply_timeout_ms = reply_timeout_s * 1e3

    def setPacketTimeout(self, packet_length):  # the SDK's names
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = self.tx_time_per_byte * packet_length + self.reply_timeout_ms

    def readPort(self, length):
        data = self._read_now(length)
        if data:
            return data
        remaining_ms = self.packet_timeout - self.getTimeSinceStart()
        if remaining_ms > 0:
            select.select([self.ser.fileno()], [], [], remaining_ms / 1e3)
            data = self._read_now(length)
        return data

    def _read_now(self, length: int) -> bytes:
        """What the port holds now, up to ``length`` bytes: one read(2) of the descriptor pyserial opened
        non-blocking (pyserial's own ``read`` adds a select and a timeout object to each of the SDK's four or
        five reads per Sync Read: a tenth of the host's time per exchange). A vanished port raises OSError."""
        try:
            return os.read(self.ser.fd, length)
        except BlockingIOError:
            return b""


class ServoBus(Device):
    """XM430 servos on one Protocol 2.0 bus: ``with ServoBus(port, ids=[1, 2]) as bus: bus.read_state()``."""

    kind = "Dynamixel bus"

    def __init__(self, port: str, ids: list[int], baud: int = 1_000_000, zero_count: int = 2048,
                 retries: int = 2, reply_timeout_s: float = 0.01) -> None:  # fmt: skip
        super().__init__(port, retries)
        self.reply_timeout_s = reply_timeout_s
        if not ids:
            raise ValueError("a servo bus needs at least one servo ID")
        self.ids = tuple(ids)
        self.baud = baud
        self.zero_count = zero_count
        self.models: dict[int, int] = {}
        self._port: PortHandler | None = None
        self._packet = PacketHandler(2.0)
        self._reader: GroupSyncRead | None = None

    # ------------------------------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        port = _WaitingPortHandler(self.port, self.reply_timeout_s)
        try:
            opened = port.openPort()
        except serial.SerialException as exc:
            raise DeviceNotFoundError(f"{self.kind} on {self.port}: cannot open port ({exc})") from exc
        if not opened or not port.setBaudRate(self.baud):
            raise DeviceNotFoundError(f"{self.kind} on {self.port}: cannot open port at {self.baud} baud")
        self._port = port
        for dxl_id in self.ids:
            try:
                self.models[dxl_id] = self._retrying(f"ping ID {dxl_id}", lambda i=dxl_id: self._ping(i))
            except DeviceTimeoutError as exc:
                raise DeviceNotFoundError(
                    f"{self.kind} on {self.port}: servo ID {dxl_id} does not answer"
                ) from exc
        self._reader = GroupSyncRead(self._port, self._packet, _BLOCK_START, _BLOCK_LEN)
        for dxl_id in self.ids:
            self._reader.addParam(dxl_id)

    def fileno(self) -> int:
        """The port's file descriptor (for a daemon's select loop)."""
        if self._port is None:
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: not open")
        return self._port.ser.fileno()

    def _close(self) -> None:
        if self._port is not None:
            self._port.closePort()
            self._port = None

    # ----------------------------------------------------------------------------------- commands
    def configure(
        self,
        profile_velocity_rad_s: float = 0.0,
        profile_acceleration_rad_s2: float = 0.0,
        p_gain: int = 800,
        i_gain: int = 0,
        d_gain: int = 0,
        return_delay_us: int = 0,
    ) -> None:
        """Position mode, return delay, position PID gains and profile (0 = unlimited) on every servo.
        Torque is switched off first (EEPROM items are locked while it is on) and left off."""
        self.set_torque(False)
        velocity = round(profile_velocity_rad_s / dx.RAD_S_PER_VELOCITY_UNIT)
        acceleration = round(profile_acceleration_rad_s2 / dx.RAD_S2_PER_ACCELERATION_UNIT)
        for dxl_id in self.ids:
            self._write(dxl_id, dx.OPERATING_MODE, dx.OPERATING_MODE_POSITION)
            self._write(dxl_id, dx.RETURN_DELAY_TIME, return_delay_us // 2)
            self._write(dxl_id, dx.POSITION_P_GAIN, p_gain)
            self._write(dxl_id, dx.POSITION_I_GAIN, i_gain)
            self._write(dxl_id, dx.POSITION_D_GAIN, d_gain)
            self._write(dxl_id, dx.PROFILE_VELOCITY, velocity)
            self._write(dxl_id, dx.PROFILE_ACCELERATION, acceleration)

    def set_torque(self, on: bool) -> None:
        """Torque on/off on every servo."""
        for dxl_id in self.ids:
            self._write(dxl_id, dx.TORQUE_ENABLE, int(on))

    def set_profile_velocity(self, velocity_rad_s: np.ndarray) -> None:
        """Per-servo profile velocity (the paper's Move(q, q̇)); 0 = unlimited."""
        units = np.rint(np.abs(velocity_rad_s) / dx.RAD_S_PER_VELOCITY_UNIT).astype(int)
        self._sync_write(dx.PROFILE_VELOCITY, units)

    def write_goals(self, position_rad: np.ndarray) -> None:
        """Goal positions (rad, in the order of ``ids``) in one Sync Write (no reply by design)."""
        counts = np.rint(np.asarray(position_rad) / dx.RAD_PER_POSITION_COUNT).astype(int) + self.zero_count
        self._sync_write(dx.GOAL_POSITION, counts)

    def read_state(self) -> ServoState:
        """One Sync Read of tick, current, velocity and position of every servo, with retries."""
        return self._retrying("sync read", self._sync_read_once)

    def reboot(self, dxl_id: int) -> None:
        """Reboot one servo (the only way to clear a latched hardware error; its torque comes back off)."""

        def attempt() -> None:
            result, error = self._call(self._packet.reboot, self._port, dxl_id)
            self._check(result, error & ~dx.ERR_HARDWARE_ALERT, dxl_id=dxl_id, doing="a reboot")

        self._retrying(f"reboot ID {dxl_id}", attempt)

    def write_item(self, dxl_id: int, item: tuple[int, int], value: int) -> None:
        """Write one control-table item, (address, size), of one servo; a refusal raises its
        ``ServoStatusError`` (e.g. an EEPROM item with torque on: ``ServoAccessError``)."""
        self._write(dxl_id, item, value)

    def read_item(self, dxl_id: int, item: tuple[int, int], signed: bool = False) -> int:
        """Read one control-table item, (address, size), of one servo (an Alert bit alone does not raise:
        the value is good)."""
        address, size = item

        def attempt() -> int:  # readTxRx, not readNByteTxRx: those index an error reply's missing data
            data, result, error = self._call(self._packet.readTxRx, self._port, dxl_id, address, size)
            error &= ~dx.ERR_HARDWARE_ALERT  # the value read is good all the same (see read_state's alert)
            self._check(result, error, dxl_id=dxl_id, doing="reading", address=address, size=size)
            if len(data) != size:
                raise DeviceProtocolError(
                    f"read address {address} of ID {dxl_id}: {len(data)} of {size} bytes"
                )
            return int.from_bytes(bytes(data), "little", signed=signed)

        return self._retrying(f"read address {address} of ID {dxl_id}", attempt)

    # ----------------------------------------------------------------------------------- internals
    def _ping(self, dxl_id: int) -> int:
        model, result, error = self._call(self._packet.ping, self._port, dxl_id)
        if error == dx.ERR_HARDWARE_ALERT:  # present, but with a hardware error latched: say so, open anyway
            log.warning("%s", self._status_error(dxl_id, error, "a ping"))
            error = 0
        self._check(result, error, dxl_id=dxl_id, doing="a ping")
        return model

    def _write(self, dxl_id: int, item: tuple[int, int], value: int) -> None:
        address, size = item
        write = {
            1: self._packet.write1ByteTxRx,
            2: self._packet.write2ByteTxRx,
            4: self._packet.write4ByteTxRx,
        }
        data = int(value) & ((1 << (8 * size)) - 1)

        def attempt() -> None:
            result, error = self._call(write[size], self._port, dxl_id, address, data)
            if error == dx.ERR_HARDWARE_ALERT and item == dx.TORQUE_ENABLE and not value:
                error = 0  # torque off: what the servo has already done about its hardware error
            self._check(
                result, error, dxl_id=dxl_id, doing=f"writing {int(value)} to", address=address, size=size
            )

        self._retrying(f"write address {address} of ID {dxl_id}", attempt)

    def _sync_write(self, item: tuple[int, int], values: np.ndarray) -> None:
        address, size = item
        writer = GroupSyncWrite(self._port, self._packet, address, size)
        for dxl_id, value in zip(self.ids, values, strict=True):
            writer.addParam(dxl_id, (int(value) & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
        result = self._call(writer.txPacket)
        self._check(result, 0, what=f"sync write address {address}")

    def _sync_read_once(self) -> ServoState:
        # GroupSyncRead.txRxPacket, unrolled: the SDK's own calls, keeping each servo's status byte
        result = self._call(self._reader.txPacket)
        self._check(result, 0, what="sync read")
        rows, alerts = [], []
        for dxl_id in self.ids:
            data, result, error = self._call(self._packet.readRx, self._port, dxl_id, _BLOCK_LEN)
            self._check(result, 0, what="sync read")
            if len(data) != _BLOCK_LEN:
                raise DeviceProtocolError(f"sync read: ID {dxl_id} sent {len(data)} of {_BLOCK_LEN} bytes")
            if error & ~dx.ERR_HARDWARE_ALERT:
                self._check(COMM_SUCCESS, error, dxl_id=dxl_id, doing="reading", address=_BLOCK_START)
            rows.append(_BLOCK.unpack(bytes(data)))
            alerts.append(bool(error & dx.ERR_HARDWARE_ALERT))
        host_ns = host_now_ns()
        tick, moving, _, _, current, velocity, position = np.array(rows, dtype=np.int64).T.copy()
        return ServoState(
            host_ns=host_ns,
            ids=self.ids,
            tick_ms=tick,
            position_rad=(position - self.zero_count) * dx.RAD_PER_POSITION_COUNT,
            velocity_rad_s=velocity * dx.RAD_S_PER_VELOCITY_UNIT,
            current_a=current * dx.AMP_PER_CURRENT_UNIT,
            position_counts=position,
            current_counts=current,
            moving=moving.astype(bool),
            alert=np.array(alerts),
        )

    def _call(self, fn, *args):
        if self._port is None:
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: not open")
        try:
            return fn(*args)
        except (serial.SerialException, OSError, termios.error) as exc:  # a vanished tty raises termios.error
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: port lost ({exc})") from exc

    def _check(self, result: int, error: int, what: str = "", dxl_id: int | None = None, doing: str = "",
               address: int | None = None, size: int | None = None) -> None:  # fmt: skip
        """Raise for a failed transaction (timeout, corrupted reply) or an error status from ``dxl_id``."""
        if not what:
            target = f" address {address}" if address is not None else ""
            what = f"{doing}{target} of ID {dxl_id}"
        if result == COMM_RX_TIMEOUT:
            raise DeviceTimeoutError(f"{what}: no reply")
        if result == COMM_RX_CORRUPT:
            raise DeviceProtocolError(f"{what}: corrupted reply")
        if result != COMM_SUCCESS:
            raise DeviceTimeoutError(f"{what}: {self._packet.getTxRxResult(result)}")
        if error:
            raise self._status_error(dxl_id, error, doing, address, size)

    def _status_error(self, dxl_id: int, error: int, doing: str, address: int | None = None,
                      size: int | None = None) -> ServoStatusError:  # fmt: skip
        """The error for ``dxl_id``'s status byte; after an Alert, Hardware Error Status (70) is read once
        to say which hardware error it is."""
        hardware = None
        if error & dx.ERR_HARDWARE_ALERT:
            try:
                data, result, _ = self._call(self._packet.readTxRx, self._port, dxl_id, 70, 1)
                hardware = data[0] if result == COMM_SUCCESS and len(data) == 1 else None
            except DeviceDisconnectedError:
                hardware = None
        return status_error(f"{self.kind} on {self.port}", dxl_id, error, doing, address, size, hardware)
