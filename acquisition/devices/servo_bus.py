"""The Dynamixel bus (U2D2 + XM430s) on the official dynamixel-sdk, Protocol 2.0.

One Sync Read of addresses 120–135 returns each servo's Realtime Tick, current, velocity and position in one
transaction; goals go out in one Sync Write. Values are converted to SI (rad, rad/s, A); every read carries
the host receive time (int64 ns) and the servos' own tick (ms, wraps at 32768).
"""

from __future__ import annotations

import logging
import select
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

from acquisition.devices.base import Device, host_now_ns
from acquisition.errors import (
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceReplyError,
    DeviceTimeoutError,
)
from acquisition.protocols import dynamixel as dx

log = logging.getLogger(__name__)

_BLOCK_START, _BLOCK_LEN = dx.REALTIME_TICK[0], 16  # 120 … 135


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
        data = self.ser.read(length)
        if data:
            return data
        remaining_ms = self.packet_timeout - self.getTimeSinceStart()
        if remaining_ms > 0:
            select.select([self.ser.fileno()], [], [], remaining_ms / 1e3)
            data = self.ser.read(length)
        return data


def _signed(value: int, nbytes: int) -> int:
    bits = 8 * nbytes
    return value - (1 << bits) if value >= 1 << (bits - 1) else value


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

    # ----------------------------------------------------------------------------------- internals
    def _ping(self, dxl_id: int) -> int:
        model, result, error = self._call(self._packet.ping, self._port, dxl_id)
        self._check(result, error, f"ping ID {dxl_id}")
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
            self._check(result, error, f"write address {address} of ID {dxl_id}")

        self._retrying(f"write address {address} of ID {dxl_id}", attempt)

    def _sync_write(self, item: tuple[int, int], values: np.ndarray) -> None:
        address, size = item
        writer = GroupSyncWrite(self._port, self._packet, address, size)
        for dxl_id, value in zip(self.ids, values, strict=True):
            writer.addParam(dxl_id, (int(value) & ((1 << (8 * size)) - 1)).to_bytes(size, "little"))
        result = self._call(writer.txPacket)
        self._check(result, 0, f"sync write address {address}")

    def _sync_read_once(self) -> ServoState:
        result = self._call(self._reader.txRxPacket)
        host_ns = host_now_ns()
        self._check(result, 0, "sync read")
        rows = []
        for dxl_id in self.ids:
            get = self._reader.getData
            rows.append(
                (
                    get(dxl_id, 120, 2),
                    get(dxl_id, 122, 1),
                    _signed(get(dxl_id, 126, 2), 2),
                    _signed(get(dxl_id, 128, 4), 4),
                    _signed(get(dxl_id, 132, 4), 4),
                )
            )
        tick, moving, current, velocity, position = (np.array(col) for col in zip(*rows, strict=True))
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
        )

    def _call(self, fn, *args):
        if self._port is None:
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: not open")
        try:
            return fn(*args)
        except (serial.SerialException, OSError, termios.error) as exc:  # a vanished tty raises termios.error
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: port lost ({exc})") from exc

    def _check(self, result: int, error: int, what: str) -> None:
        if result == COMM_RX_TIMEOUT:
            raise DeviceTimeoutError(f"{what}: no reply")
        if result == COMM_RX_CORRUPT:
            raise DeviceProtocolError(f"{what}: corrupted reply")
        if result != COMM_SUCCESS:
            raise DeviceTimeoutError(f"{what}: {self._packet.getTxRxResult(result)}")
        if error:
            raise DeviceReplyError(
                f"{self.kind} on {self.port}: {what}: {self._packet.getRxPacketError(error)}"
            )
