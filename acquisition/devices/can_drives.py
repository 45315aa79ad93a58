"""POPUP's joint drives: CiA 402 servo drives on a CAN bus, reached through a USB-CAN adapter.

python-can opens the adapter (``interface="slcan"`` on the lab's CANable-class adapter and on the rig's
emulated one alike), canopen speaks CANopen to the drives with their EDS (``configs/can/popup_drive.eds``).
On opening, every drive is checked (it answers SDO, it is a CiA 402 drive), configured by SDO (heartbeat
period, the software position limits of the robot description, cyclic synchronous position mode) and its
PDOs mapped: TPDO1 statusword + position, TPDO2 velocity + torque, both sent on every SYNC; RPDO1
controlword, RPDO2 target position, applied on arrival.

The host is the SYNC producer: :meth:`CanDrives.sync` sends one SYNC and returns what every drive answered
to the previous one, numbered by that SYNC. So the PDO loop runs at the caller's (the daemon's real-time)
rate and a sample a drive did not send is counted lost, not silently repeated. Heartbeats are watched: a
drive silent for ``HEARTBEAT_MISSES`` periods raises :class:`DriveLostError`; an EMCY from a drive raises
:class:`DriveFaultError` naming the fault. Either way the caller safe-stops.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import can
import canopen
import numpy as np
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from acquisition.devices.base import Device, host_now_ns
from acquisition.devices.slcan_bus import SlcanBus
from acquisition.errors import (
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceReplyError,
)
from models.robot import CAN_DIR

log = logging.getLogger(__name__)

EDS = CAN_DIR / "popup_drive.eds"
PROFILE_402 = 0x0192  # low word of the device type 0x1000
SDO_TIMEOUT_S = 1.0  # canopen waits 0.3 s for an SDO answer: a busy host, not reading its port for longer,
# made a powered drive look absent while the bus was set up (seen in a CI run: "host not reading")
# the PDOs the driver maps (object indices): TPDO1 statusword + position and TPDO2 velocity + torque on
# every SYNC; RPDO1 the controlword, RPDO2 the target position (one per SYNC while the joints move)
TPDO_MAP = {1: (0x6041, 0x6064), 2: (0x606C, 0x6077)}
RPDO_MAP = {1: (0x6040,), 2: (0x607A,)}
HEARTBEAT_MISSES = 3  # periods without a heartbeat before a drive counts as lost
FAULT_RESET_DONE = (
    -1
)  # the first step of enabling: no drive left in FAULT (a reset one is switch on disabled)
EMCY_NAMES = {0x2310: "over-current", 0x3220: "under-voltage", 0x4310: "over-temperature",
              0x8611: "following error", 0x8130: "heartbeat or life guard error"}  # fmt: skip


class DriveLostError(DeviceDisconnectedError):
    """A drive stopped sending its heartbeat (power lost, cable cut, bus off)."""


class DriveFaultError(DeviceReplyError):
    """A drive reported a fault by EMCY (its code and meaning in the message)."""


Limits = tuple[float, float]  # a joint's (lower, upper) angle, rad


@dataclass(frozen=True)
class DriveCycle:
    """What the drives answered to SYNC number ``sync`` (the host's count), in ``joints`` order: ``None``
    where a drive sent nothing. ``host_ns``: when the last answer arrived."""

    sync: int
    host_ns: int
    joints: tuple[str, ...]
    position_rad: np.ndarray
    velocity_rad_s: np.ndarray
    torque_nm: np.ndarray
    statusword: np.ndarray  # uint16
    answered: np.ndarray  # bool, per drive


def _reached(statusword: np.ndarray, state: int) -> np.ndarray:
    """Which statuswords show CiA 402 ``state`` (compared under its mask: 0x4F for the states whose bit 5
    is free, 0x6F for the rest); for ``FAULT_RESET_DONE``, which show no fault."""
    if state == FAULT_RESET_DONE:
        return (np.asarray(statusword) & 0x4F) != 0x08
    mask = 0x4F if state in (0x00, 0x40, 0x0F, 0x08) else 0x6F
    return (np.asarray(statusword) & mask) == state


@dataclass
class _Drive:
    joint: str
    node: canopen.BaseNode402
    counts_per_rad: float = 1.0
    rated_nm: float = 1.0
    last_heartbeat: float = field(default_factory=time.monotonic)
    answers: dict[int, tuple[int, list[int]]] = field(default_factory=dict)  # TPDO n → (host_ns, raw values)


def _interpolation_period(period_s: float) -> tuple[int, int]:
    """0x60C2's (value, index) for ``period_s``: value × 10^index s, the finest index whose value fits a
    byte (10 ms → (100, -4))."""
    for index in range(-6, 1):
        value = round(period_s / 10.0**index)
        if value <= 255:
            return max(value, 1), index
    raise ValueError(f"a SYNC period of {period_s} s is beyond 0x60C2's range")


class CanDrives(Device):
    """The joint drives ``ids`` (joint name → node id) on the CAN adapter at ``port``."""

    kind = "CAN drives"

    def __init__(self, port: str, ids: dict[str, int], limits_rad: dict[str, Limits] | None = None,
                 bitrate: int = 1_000_000, heartbeat_ms: int = 100, interface: str = "slcan", eds: Path = EDS,
                 sleep_after_open_s: float = 0.0, retries: int = 2,
                 sync_period_s: float = 0.01) -> None:  # fmt: skip
        super().__init__(port, retries)
        self.sync_period_s = sync_period_s  # the drives interpolate between targets over it (0x60C2)
        self.ids = dict(ids)
        self.limits_rad = dict(limits_rad or {})
        self.bitrate, self.heartbeat_ms, self.interface = bitrate, heartbeat_ms, interface
        self.eds, self.sleep_after_open_s = eds, sleep_after_open_s
        self.network: canopen.Network | None = None
        self.drives: list[_Drive] = []
        self.syncs = 0
        self._lock = threading.Lock()
        self._all_answered = threading.Condition(self._lock)  # every drive sent both PDOs since the SYNC
        self._synced_at = 0.0  # when the last SYNC went out (time.monotonic)
        self._faults: list[tuple[str, int]] = []

    @property
    def joints(self) -> tuple[str, ...]:
        return tuple(self.ids)

    # ---------------------------------------------------------------------------------- lifecycle
    def _open(self) -> None:
        self.network = canopen.Network()
        try:
            if self.interface == "slcan":  # python-can's, reading the adapter in bulk (see slcan_bus)
                self.network.bus = SlcanBus(channel=self.port, bitrate=self.bitrate,
                                            sleep_after_open=self.sleep_after_open_s)  # fmt: skip
                self.network.connect()
            else:
                self.network.connect(interface=self.interface, channel=self.port, bitrate=self.bitrate,
                                     sleep_after_open=self.sleep_after_open_s)  # fmt: skip
        except (can.CanError, ValueError) as exc:
            raise DeviceNotFoundError(
                f"{self.kind} on {self.port}: cannot open the CAN adapter ({exc})"
            ) from exc
        self.network.nmt.state = "PRE-OPERATIONAL"  # every node: configuration by SDO
        self.drives = [self._configure(joint, node_id) for joint, node_id in self.ids.items()]
        self.network.nmt.state = "OPERATIONAL"
        for d in self.drives:
            d.node.nmt.state = "OPERATIONAL"  # canopen's local view (the broadcast above did it on the bus)
            # heartbeats are watched from here: configuring the drives one by one (dozens of SDO round trips)
            # may take longer than a heartbeat's allowance, and a drive's first one may come before its
            # callback was added
            d.last_heartbeat = time.monotonic()
        self.syncs = 0

    def _configure(self, joint: str, node_id: int) -> _Drive:
        node = canopen.BaseNode402(node_id, str(self.eds))
        node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        self.network.add_node(node)
        what = f"{self.kind} on {self.port}: drive {joint} (node {node_id})"
        try:
            device_type = node.sdo[0x1000].raw
            if device_type & 0xFFFF != PROFILE_402:
                raise DeviceProtocolError(f"{what}: device type {device_type:#010x} is not a CiA 402 drive")
            drive = _Drive(joint, node, node.sdo[0x2000].raw / (2 * math.pi), node.sdo[0x6076].raw * 1e-3)
            if joint in self.limits_rad:
                low, high = self.limits_rad[joint]
                node.sdo[0x607D][1].raw = math.ceil(low * drive.counts_per_rad)
                node.sdo[0x607D][2].raw = math.floor(high * drive.counts_per_rad)
            node.sdo[0x1017].raw = self.heartbeat_ms
            node.nmt.state = "PRE-OPERATIONAL"
            self._map_pdos(node)
            node.sdo[0x6060].raw = 8  # cyclic synchronous position
            value, index = _interpolation_period(self.sync_period_s)
            node.sdo[0x60C2][1].raw, node.sdo[0x60C2][2].raw = value, index  # a target per SYNC period
        except SdoCommunicationError as exc:
            raise DeviceNotFoundError(f"{what}: no answer ({exc}); is it powered and on the bus?") from exc
        except SdoAbortedError as exc:
            raise DeviceReplyError(f"{what}: refused its configuration ({exc})") from exc
        node.setup_pdos(upload=False)  # the state machine on the PDOs just mapped (mode by SDO: no warning)
        node.nmt.add_heartbeat_callback(lambda state, d=drive: setattr(d, "last_heartbeat", time.monotonic()))
        node.emcy.add_callback(lambda err, d=drive: self._on_emcy(d, err))
        for n in (1, 2):
            node.tpdo[n].add_callback(lambda pdo, d=drive, n=n: self._on_tpdo(d, n, pdo))
        return drive

    @staticmethod
    def _map_pdos(node: canopen.BaseNode402) -> None:
        node.tpdo.read(from_od=True)
        node.rpdo.read(from_od=True)
        mappings = {**{node.tpdo[n]: objects for n, objects in TPDO_MAP.items()},
                    **{node.rpdo[n]: objects for n, objects in RPDO_MAP.items()}}  # fmt: skip
        for pdo, objects in mappings.items():
            pdo.clear()
            for index in objects:
                pdo.add_variable(index)
            pdo.trans_type = 1 if pdo in (node.tpdo[1], node.tpdo[2]) else 255
            pdo.enabled = True
        for n in (3, 4):
            node.tpdo[n].enabled = node.rpdo[n].enabled = False
        node.tpdo.save()
        node.rpdo.save()

    def _close(self) -> None:
        if self.network is None:
            return
        try:
            for d in self.drives:
                if d.node.state == "OPERATION ENABLED":
                    d.node.controlword = 0x07  # disable operation: the brakes hold
            self.network.nmt.state = "PRE-OPERATIONAL"
        except (can.CanError, SdoAbortedError, SdoCommunicationError, RuntimeError, ValueError) as exc:
            log.info("%s on %s: drives not left disabled: %s", self.kind, self.port, exc)
        finally:
            self.network.disconnect()
            self.network = None
            self.drives = []

    # ------------------------------------------------------------------------------- callbacks
    def _on_tpdo(self, drive: _Drive, n: int, pdo) -> None:
        values = [var.raw for var in pdo]
        with self._lock:
            drive.answers[n] = (host_now_ns(), values)
            if self._answered():
                self._all_answered.notify_all()

    def _on_emcy(self, drive: _Drive, err) -> None:
        if err.code:
            with self._lock:
                self._faults.append((drive.joint, err.code))

    # ------------------------------------------------------------------------------------ cycle
    def _answered(self) -> bool:
        """Whether every drive has sent both its PDOs since the last SYNC (call with the lock held)."""
        return all(len(d.answers) == 2 for d in self.drives)

    def sync(self, wait_s: float = 0.0) -> DriveCycle | None:
        """Send SYNC number ``syncs + 1``; return the drives' answers to the previous SYNC (None before the
        first). The drives answer within a millisecond on the bus, but a busy host (or twin) may read the
        answers later: with ``wait_s`` this first waits for them, up to ``wait_s`` after the previous SYNC
        (the new one then goes out late, as from any master that waits), so a late answer is neither lost
        nor taken for the next SYNC's. Raises :class:`DriveLostError` or :class:`DriveFaultError`."""
        self.check()
        with self._all_answered:
            if self.syncs and wait_s > 0:
                self._all_answered.wait_for(
                    self._answered, max(0.0, self._synced_at + wait_s - time.monotonic())
                )
            answers = [d.answers for d in self.drives]
            for d in self.drives:
                d.answers = {}
        cycle = self._cycle(answers) if self.syncs else None
        self.network.sync.transmit()
        self._synced_at = time.monotonic()
        self.syncs += 1
        return cycle

    def _cycle(self, answers: list[dict]) -> DriveCycle:
        n = len(self.drives)
        position, velocity, torque = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        status, answered, last = np.zeros(n, np.uint16), np.zeros(n, bool), 0
        for k, (d, got) in enumerate(zip(self.drives, answers, strict=True)):
            if 1 in got and 2 in got:
                (t1, (sw, pos)), (t2, (vel, tq)) = got[1], got[2]
                position[k], velocity[k] = pos / d.counts_per_rad, vel / d.counts_per_rad
                torque[k], status[k], answered[k] = tq * 1e-3 * d.rated_nm, sw, True
                last = max(last, t1, t2)
        return DriveCycle(sync=self.syncs - 1, host_ns=last or host_now_ns(), joints=self.joints,
                          position_rad=position, velocity_rad_s=velocity, torque_nm=torque, statusword=status,
                          answered=answered)  # fmt: skip

    def check(self) -> None:
        """Raise if a drive faulted (EMCY) or stopped its heartbeat."""
        with self._lock:
            faults, self._faults = self._faults, []
        if faults:
            joint, code = faults[0]
            raise DriveFaultError(f"{self.kind} on {self.port}: drive {joint} faulted: EMCY {code:#06x} "
                                  f"({EMCY_NAMES.get(code, 'see the drive manual')})")  # fmt: skip
        limit = HEARTBEAT_MISSES * self.heartbeat_ms * 1e-3
        now = time.monotonic()
        for d in self.drives:
            if now - d.last_heartbeat > limit:
                silent = now - d.last_heartbeat
                raise DriveLostError(f"{self.kind} on {self.port}: drive {d.joint} (node {d.node.id}) sent "
                                     f"no heartbeat for {silent:.2f} s (power, cable or bus?)")  # fmt: skip

    # --------------------------------------------------------------------------------- commands
    def enable(self, timeout_s: float = 1.0) -> list[DriveCycle]:
        """Every drive to OPERATION ENABLED (a faulted one reset first), its target first set where it
        stands, so enabling does not jump. The drives answer on SYNC, so this pumps SYNCs (every
        ``sync_period_s``) while it waits; returns the cycles they answered."""
        period_s = self.sync_period_s
        for d in self.drives:
            d.node.rpdo[2]["Target position"].raw = d.node.sdo[0x6064].raw
            d.node.rpdo[2].transmit()
        cycles: list[DriveCycle] = []
        steps = ((0x80, FAULT_RESET_DONE), (0x06, 0x21), (0x07, 0x23), (0x0F, 0x27))  # (controlword, state)
        for controlword, state in steps:
            for d in self.drives:
                d.node.controlword = controlword
            deadline = time.monotonic() + timeout_s
            while True:
                time.sleep(period_s)
                cycle = self.sync(wait_s=2 * period_s)  # late answers (a busy host) still count
                if cycle is not None:
                    cycles.append(cycle)
                    if cycle.answered.all() and _reached(cycle.statusword, state).all():
                        break
                if time.monotonic() > deadline:
                    stuck = [] if cycle is None else [j for j, sw, ok in zip(self.joints, cycle.statusword,
                             _reached(cycle.statusword, state), strict=True) if not ok]  # fmt: skip
                    who = ", ".join(stuck) or "all"
                    raise DeviceReplyError(f"{self.kind} on {self.port}: drive(s) {who} did not reach state "
                                           f"{state:#04x} in {timeout_s} s")  # fmt: skip
            for d in self.drives:
                d.node.controlword = controlword & 0x7F  # the fault-reset bit back to 0: the next edge
        return cycles

    def write_goals(self, position_rad: np.ndarray) -> None:
        """Target positions (rad, in ``joints`` order), sent by RPDO now; a goal that is not a finite number
        is refused before anything is sent."""
        goals = np.asarray(position_rad, float)
        if goals.shape != (len(self.drives),) or not np.isfinite(goals).all():
            raise ValueError(f"{self.kind}: goals must be {len(self.drives)} finite angles, got {goals!r}")
        for d, goal in zip(self.drives, goals, strict=True):
            d.node.rpdo[2]["Target position"].raw = round(float(goal) * d.counts_per_rad)
            d.node.rpdo[2].transmit()

    def quick_stop(self) -> None:
        """Quick stop every drive that still answers (the safe stop)."""
        for d in self.drives:
            d.node.controlword = 0x02
