"""A CiA 402 servo drive on the twin's CAN bus: one of POPUP's joint motors, as a CANopen slave.

The device-control state machine (CiA 402 §6: switch on disabled → ready to switch on → switched on →
operation enabled, quick stop active, fault reaction → fault, fault reset on the rising edge of bit 7) is
driven by the controlword (0x6040) and shown in the statusword (0x6041). Enabled, the drive moves its twin
joint: in cyclic synchronous position (mode 8) to every target position (0x607A) it is sent, linearly over
the interpolation time period (0x60C2, the master's SYNC period); in profile
position (mode 1) to the target when bit 4 (new set-point) rises, with the profile velocity and acceleration.
Not enabled, or faulted, the joint's brake holds it where it is.

It fails as a drive does: a target beyond the software position limits (0x607D) is clamped there and
statusword bit 11 (internal limit) set; an actual position further than the following-error window (0x6065)
from the demand faults the drive (EMCY 0x8611, bit 13 on the way); an injected fault (over-current 0x2310,
over-temperature 0x4310, under-voltage 0x3220) does the same; the EMCY carries the error register (0x1001)
and the error code stays in 0x603F until a fault reset clears it (EMCY 0x0000). Power off: it falls silent
(no heartbeat, no PDO, no SDO), and on power-up boots again in switch-on disabled.

Units are the EDS's: position counts of the output shaft (0x2000 per revolution), velocity counts/s, torque
per mille of the rated torque (0x6076, mN·m).
"""

from __future__ import annotations

import enum
import math
from pathlib import Path
from typing import Protocol

from acquisition.codecs.can import CanFrame
from twin.emulators.canopen_node import CanopenNode

CONTROLWORD, STATUSWORD, ERROR_CODE, ERROR_REGISTER = 0x6040, 0x6041, 0x603F, 0x1001
MODE, MODE_DISPLAY, QUICK_STOP_OPTION = 0x6060, 0x6061, 0x605A
POSITION_ACTUAL, VELOCITY_ACTUAL, TORQUE_ACTUAL = 0x6064, 0x606C, 0x6077
TARGET_POSITION, SOFTWARE_LIMITS, INTERPOLATION_PERIOD = 0x607A, 0x607D, 0x60C2
FOLLOWING_WINDOW, POSITION_WINDOW = 0x6065, 0x6067
PROFILE_VELOCITY, PROFILE_ACCELERATION, QUICK_STOP_DECELERATION = 0x6081, 0x6083, 0x6085
RATED_TORQUE, COUNTS_PER_REV = 0x6076, 0x2000
MODE_PP, MODE_CSP = 1, 8
SUPPORTED_MODES = (MODE_PP, MODE_CSP)

# EMCY codes (CiA 402 / CiA 301) and the error-register bits they set (bit 0 generic always)
FOLLOWING_ERROR = 0x8611
FAULTS = {0x2310: 0x03, 0x4310: 0x09, 0x3220: 0x05, FOLLOWING_ERROR: 0x21}  # code → error register
FAULT_NAMES = {0x2310: "over-current", 0x4310: "over-temperature", 0x3220: "under-voltage",
               FOLLOWING_ERROR: "following error"}  # fmt: skip

SW_VOLTAGE, SW_REMOTE, SW_TARGET_REACHED, SW_LIMIT = 1 << 4, 1 << 9, 1 << 10, 1 << 11
SW_SETPOINT_ACK, SW_FOLLOWING = 1 << 12, 1 << 13  # bit 12: PP set-point acknowledge, CSP "following"
STANDSTILL_RAD_S = 0.01
BOOT_S = 0.05  # from power-up to the boot-up message (ASSUMED)


class State(enum.IntEnum):
    """CiA 402 states, valued as their statusword bits (mask 0x6F)."""

    NOT_READY = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY_TO_SWITCH_ON = 0x21
    SWITCHED_ON = 0x23
    OPERATION_ENABLED = 0x27
    QUICK_STOP_ACTIVE = 0x07
    FAULT_REACTION_ACTIVE = 0x0F
    FAULT = 0x08


class DriveJoint(Protocol):
    """The joint a drive moves: the twin's (``twin.devices.TwinJoint``)."""

    def sense(self, t: float) -> tuple[float, float, float]:
        """(position rad, velocity rad/s, torque N·m) at rig time ``t``."""
        ...

    def command(self, goal_rad: float, velocity_rad_s: float, acceleration_rad_s2: float, t: float) -> None:
        """Move towards ``goal_rad`` (profile velocity and acceleration; 0 = unlimited)."""
        ...

    def hold(self, t: float) -> None:
        """Brake: stay where it is."""
        ...


def command_of(cw: int) -> str | None:
    """The device-control command a controlword gives (CiA 402 Table 'command coding')."""
    if cw & 0b0010 == 0:
        return "disable voltage"
    if cw & 0b0110 == 0b0010:
        return "quick stop"
    if cw & 0b0111 == 0b0110:
        return "shutdown"
    if cw & 0b1111 == 0b0111:
        return "switch on"
    if cw & 0b1111 == 0b1111:
        return "enable operation"
    return None


# state → command → next state (transitions 2–12 of CiA 402; 3+4 combined as drives commonly allow)
TRANSITIONS: dict[State, dict[str, State]] = {
    State.SWITCH_ON_DISABLED: {"shutdown": State.READY_TO_SWITCH_ON},
    State.READY_TO_SWITCH_ON: {
        "switch on": State.SWITCHED_ON,
        "enable operation": State.OPERATION_ENABLED,
        "disable voltage": State.SWITCH_ON_DISABLED,
        "quick stop": State.SWITCH_ON_DISABLED,
    },
    State.SWITCHED_ON: {
        "enable operation": State.OPERATION_ENABLED,
        "shutdown": State.READY_TO_SWITCH_ON,
        "disable voltage": State.SWITCH_ON_DISABLED,
        "quick stop": State.SWITCH_ON_DISABLED,
    },
    State.OPERATION_ENABLED: {
        "switch on": State.SWITCHED_ON,
        "shutdown": State.READY_TO_SWITCH_ON,
        "disable voltage": State.SWITCH_ON_DISABLED,
        "quick stop": State.QUICK_STOP_ACTIVE,
    },
    State.QUICK_STOP_ACTIVE: {
        "disable voltage": State.SWITCH_ON_DISABLED,
        "enable operation": State.OPERATION_ENABLED,
    },
}


class Cia402Drive(CanopenNode):
    """Drive ``node_id`` moving ``joint``, with the object dictionary of ``eds``."""

    def __init__(self, node_id: int, eds: Path | str, joint: DriveJoint, t0: float = 0.0) -> None:
        self.joint = joint
        super().__init__(node_id, eds, t0, name=f"drive {node_id}")
        self.outbox: list[tuple[float, CanFrame]] = []  # EMCYs raised outside a frame's reception
        self.on_reset(comm_only=False)

    # ------------------------------------------------------------------------------- conversion
    @property
    def counts_per_rad(self) -> float:
        return self.get(COUNTS_PER_REV) / (2 * math.pi)

    @property
    def interpolation_period_s(self) -> float:
        """0x60C2: value × 10^index seconds (a zero or nonsensical period: 1 ms)."""
        period = self.get(INTERPOLATION_PERIOD, 1) * 10.0 ** self.get(INTERPOLATION_PERIOD, 2)
        return period if 1e-5 <= period <= 1.0 else 1e-3

    def on_reset(self, comm_only: bool) -> None:
        if comm_only:
            return
        self.ds = State.SWITCH_ON_DISABLED
        self.fault_code = 0
        self.limited = False
        self.following = False
        self._last_cw = 0
        self._ack = False  # PP: the new set-point was taken (statusword bit 12)
        self._demand: int | None = None  # counts the drive is moving to (None: holding)
        self._show()

    def power(self, on: bool, t: float) -> None:
        """Cut the drive's supply (silent on the bus, brake on) or restore it (it boots again)."""
        if not on:
            self.joint.hold(t)
            self.silent = True
            return
        if self.silent:
            self.silent = False
            self.reboot(t + BOOT_S)

    # -------------------------------------------------------------------------- state machine
    def on_write(self, index: int, sub: int, t: float) -> None:
        if index == CONTROLWORD:
            self._controlword(self.get(CONTROLWORD), t)
        elif index == MODE:
            mode = self.get(MODE)
            if mode in SUPPORTED_MODES:
                self.set(MODE_DISPLAY, mode)
        elif (
            index == TARGET_POSITION
            and self.ds == State.OPERATION_ENABLED
            and self.get(MODE_DISPLAY) == MODE_CSP
        ):
            # CSP: from the demand to the new set-point in a straight line over the interpolation period (the
            # master's SYNC period), as a drive's fine interpolator does, not a step the loop jumps at
            target = self.get(TARGET_POSITION)
            step = abs(target - (self._demand if self._demand is not None else target))
            self._move_to(target, t, velocity=max(step, 1) / self.interpolation_period_s, acceleration=0.0)
        self._show()

    def _controlword(self, cw: int, t: float) -> None:
        rising_reset = bool(cw & 0x80) and not self._last_cw & 0x80
        new_setpoint = bool(cw & 0x10) and not self._last_cw & 0x10
        self._last_cw = cw
        if self.ds == State.FAULT:
            if rising_reset:
                self._clear_fault(t)
            return
        if cw & 0x80:
            return  # fault reset outside FAULT: no state change
        command = command_of(cw)
        target = TRANSITIONS.get(self.ds, {}).get(command) if command else None
        if target is not None and target != self.ds:
            self._enter(target, t)
        if self.ds == State.OPERATION_ENABLED and self.get(MODE_DISPLAY) == MODE_PP:
            if new_setpoint:
                self._move_to(
                    self.get(TARGET_POSITION), t, self.get(PROFILE_VELOCITY), self.get(PROFILE_ACCELERATION)
                )
            if not cw & 0x10:
                self._ack = False

    def _enter(self, state: State, t: float) -> None:
        leaving_enabled = self.ds == State.OPERATION_ENABLED
        self.ds = state
        if state == State.OPERATION_ENABLED:
            position, _, _ = self.joint.sense(t)
            self._demand = round(position * self.counts_per_rad)  # enabled where it stands: no jump
            self.joint.hold(t)
        elif state == State.QUICK_STOP_ACTIVE:
            self.joint.hold(t)
            self._demand = None
            if self.get(QUICK_STOP_OPTION) not in (5, 6, 7, 8):  # options 0–4: then switch-on disabled
                self.ds = State.SWITCH_ON_DISABLED
        elif leaving_enabled or state in (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON):
            self.joint.hold(t)
            self._demand = None

    def _move_to(self, counts: int, t: float, velocity: float, acceleration: float) -> None:
        low, high = self.get(SOFTWARE_LIMITS, 1), self.get(SOFTWARE_LIMITS, 2)
        clamped = min(max(counts, low), high)
        self.limited = clamped != counts
        self._demand = clamped
        self._ack = True
        cpr = self.counts_per_rad
        self.joint.command(clamped / cpr, velocity / cpr, acceleration / cpr, t)
        self._check_following(t)

    # ---------------------------------------------------------------------------------- faults
    def fault(self, code: int, t: float) -> None:
        """Fault the drive with EMCY ``code`` (one of ``FAULTS``): fault reaction, brake, EMCY sent."""
        if self.ds == State.FAULT or self.silent:
            return
        self.fault_code = code
        self.set(ERROR_CODE, code)
        self.set(ERROR_REGISTER, FAULTS.get(code, 0x01))
        self.ds = State.FAULT  # the reaction (brake) is immediate in the twin
        self.joint.hold(t)
        self._demand = None
        self._show()
        self.outbox.append((t, self.emcy(code)))

    def _clear_fault(self, t: float) -> None:
        self.fault_code = 0
        self.set(ERROR_CODE, 0)
        self.set(ERROR_REGISTER, 0)
        self.ds = State.SWITCH_ON_DISABLED
        self.following = False
        self._show()
        self.outbox.append((t, self.emcy(0)))

    def _check_following(self, t: float) -> None:
        if self.ds != State.OPERATION_ENABLED or self._demand is None:
            return
        position, _, _ = self.joint.sense(t)
        error = abs(self._demand - position * self.counts_per_rad)
        window = self.get(FOLLOWING_WINDOW)
        self.following = error > window / 2  # a warning first (bit 13), the fault beyond the window
        if error > window:
            self.fault(FOLLOWING_ERROR, t)

    # ------------------------------------------------------------------------ actual values
    def refresh(self, t: float) -> None:
        position, velocity, torque = self.joint.sense(t)
        cpr = self.counts_per_rad
        self.set(POSITION_ACTUAL, round(position * cpr))
        self.set(VELOCITY_ACTUAL, round(velocity * cpr))
        per_mille = round(torque / (self.get(RATED_TORQUE) * 1e-3) * 1000)
        self.set(TORQUE_ACTUAL, max(-32768, min(32767, per_mille)))
        self._show(position * cpr, velocity * cpr)

    def on_sync(self, t: float) -> None:
        self._check_following(t)

    def _show(self, position: float | None = None, velocity: float | None = None) -> None:
        sw = int(self.ds) | SW_REMOTE
        if self.ds in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
                       State.QUICK_STOP_ACTIVE):  # fmt: skip
            sw |= SW_VOLTAGE
        if self.limited:
            sw |= SW_LIMIT
        if self.ds == State.OPERATION_ENABLED:
            if self.get(MODE_DISPLAY) == MODE_CSP:
                sw |= SW_SETPOINT_ACK  # the drive follows the target
            elif self._ack:
                sw |= SW_SETPOINT_ACK
            if self.following:
                sw |= SW_FOLLOWING
            if self._demand is not None and position is not None and velocity is not None:
                near = abs(self._demand - position) <= self.get(POSITION_WINDOW)
                still = abs(velocity) <= STANDSTILL_RAD_S * self.counts_per_rad
                if near and still:
                    sw |= SW_TARGET_REACHED
        self.set(STATUSWORD, sw)

    # ---------------------------------------------------------------------------- bus side
    def next_due_s(self) -> float | None:
        if self.outbox:
            return min(t for t, _ in self.outbox)
        return super().next_due_s()

    def produce(self, t: float) -> list[tuple[float, CanFrame]]:
        out, self.outbox = self.outbox, []
        return out + super().produce(t)
