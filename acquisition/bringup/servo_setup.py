"""Setting a bus's servos as the robot description says: ID, Baud Rate, Return Delay Time (EEPROM, so torque
off first), then a ping at the new baud and ID to verify.

New servos all have ID 1, and two servos with one ID cannot be told apart on a bus (both answer, and a write
reaches both). So a lab gives them their IDs **one at a time**: with every servo's cable out, it connects the
servo of one joint, which gets its ID, baud and return delay, then connects the next one beside it, and so on
(the servo that keeps ID 1 last). ``assign_order`` is that order; the caller connects the servos (an operator
asked to, or a rig's control socket). Only a servo found alone at an unset (ID, baud) is written.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from dynamixel_sdk import COMM_SUCCESS, PacketHandler

from acquisition.bringup.doctor import foreign_device, return_delay_units
from acquisition.bringup.probes import (
    Servo,
    dynamixel_bauds,
    dynamixel_port,
    find_servos,
    ping_servos,
    read_budget_s,
    servo_settings,
)
from acquisition.bringup.scan import BringupError
from acquisition.codecs import dynamixel as dx
from acquisition.devices.bus_budget import DYNAMIXEL_BAUDS
from models.robot import DeviceSpec

log = logging.getLogger(__name__)

BAUD_CODE = {baud: code for code, baud in DYNAMIXEL_BAUDS.items()}
ERROR_NAMES = {1: "result fail", 2: "instruction error", 3: "CRC error", 4: "data range error",
               5: "data length error", 6: "data limit error", 7: "access error (torque on?)"}  # fmt: skip


@dataclass(frozen=True)
class ServoRow:
    """One servo: where it answers now (``servo``), what its table holds, and what the description wants."""

    joint: str
    servo: Servo
    now: dict[str, int | None]
    want: dict[str, int]

    @property
    def changes(self) -> dict[str, int]:
        """The items to write (those whose value differs)."""
        return {k: v for k, v in self.want.items() if self.now.get(k) != v}


def wanted(spec: DeviceSpec, joint: str) -> dict[str, int]:
    """The ID, Baud Rate code and Return Delay Time the description wants for ``joint``'s servo."""
    if spec.baud not in BAUD_CODE:
        raise BringupError(f"the servo bus's baud {spec.baud:,} is not a Dynamixel baud "
                           f"({', '.join(f'{b:,}' for b in BAUD_CODE)})")  # fmt: skip
    delay = return_delay_units(spec.return_delay_s)
    return {"id": spec.ids[joint], "baud_code": BAUD_CODE[spec.baud], "return_delay": delay}


def assign_order(spec: DeviceSpec) -> list[str]:
    """The joints in the order their new servos are connected: highest ID first, so that a new servo (ID 1)
    never shares an ID with one already set."""
    return sorted(spec.ids, key=lambda j: -spec.ids[j])


def all_servos(port: str, max_id: int) -> list[Servo]:
    """Every servo on the bus, at every baud (those sharing an ID answer garbled: not among them)."""
    return list(find_servos(port, dynamixel_bauds(), max_id, every_baud=True).servos)


def read_row(port: str, joint: str, servo: Servo, want: dict[str, int]) -> ServoRow:
    """``servo``'s row: its table's ID, Baud Rate and Return Delay Time beside ``want``."""
    return ServoRow(joint, servo, servo_settings(port, [servo])[servo.dxl_id], want)


def assigned_rows(port: str, spec: DeviceSpec) -> list[ServoRow] | None:
    """Each joint's row when every described ID answers exactly once (the IDs are set), else None."""
    bus = find_servos(port, dynamixel_bauds(), max(spec.ids.values()), every_baud=True)
    if not bus.bauds:
        foreign_device("servo bus", spec, port)
        raise BringupError(f"{port}: no servo answers at any baud (is this the servo bus's port? is the bus "
                           "powered?); `vslab devices scan` finds each device's port")  # fmt: skip
    if bus.garbled:
        return None
    servos = bus.servos
    by_id: dict[int, list[Servo]] = {}
    for s in servos:
        by_id.setdefault(s.dxl_id, []).append(s)
    if sorted(by_id) != sorted(spec.ids.values()) or any(len(v) > 1 for v in by_id.values()):
        return None
    return [read_row(port, j, by_id[i][0], wanted(spec, j)) for j, i in spec.ids.items()]


def new_servo_row(port: str, spec: DeviceSpec, joint: str, done: list[str]) -> ServoRow:
    """The row of the one servo on the bus that is not one of ``done`` (set already): the one just
    connected."""
    servos = all_servos(port, max(spec.ids.values()))
    set_already = {(spec.ids[j], spec.baud) for j in done}
    new = [s for s in servos if (s.dxl_id, s.baud) not in set_already]
    if len(new) != 1:
        seen = ", ".join(f"ID {s.dxl_id} at {s.baud:,}" for s in new) or "none"
        raise BringupError(f"{port}: expected one new servo (the one of {joint}) beside those set already, "
                           f"found {seen}: connect only the servo of {joint}")  # fmt: skip
    return read_row(port, joint, new[0], wanted(spec, joint))


def write_row(port: str, row: ServoRow) -> str | None:
    """Write ``row``'s changes (torque off first; Return Delay Time, ID, then Baud Rate, each acknowledged by
    the servo) and ping it at its new ID and baud; None when done, else one line saying what refused."""
    packet = PacketHandler(2.0)
    changes = row.changes
    dxl_id, baud = row.servo.dxl_id, row.servo.baud
    with dynamixel_port(port) as handler:
        handler.setBaudRate(baud)
        handler.budget_ms = read_budget_s(baud) * 1e3
        steps = [(dx.TORQUE_ENABLE, 0, "Torque Enable")]
        steps += [(item, changes[k], label) for k, item, label in (
            ("return_delay", dx.RETURN_DELAY_TIME, "Return Delay Time"), ("id", dx.ID, "ID"),
            ("baud_code", dx.BAUD_RATE, "Baud Rate")) if k in changes]  # fmt: skip
        for item, value, label in steps:
            result, error = _write_byte(packet, handler, dxl_id, item, value, baud)
            if result != COMM_SUCCESS or error:
                why = ERROR_NAMES.get(error & 0x7F, packet.getTxRxResult(result)) if error else (
                    packet.getTxRxResult(result))  # fmt: skip
                return f"{row.joint}: servo ID {dxl_id} refused {label} = {value}: {why}"
            if item == dx.ID:
                dxl_id = value
        new_baud = DYNAMIXEL_BAUDS[row.want["baud_code"]]
        if not ping_servos_at(handler, dxl_id, new_baud):
            return f"{row.joint}: no answer from ID {dxl_id} at {new_baud:,} baud after the writes"
    log.info("%s: servo set to %s", row.joint, row.want)
    return None


def _write_byte(packet: PacketHandler, handler, dxl_id: int, item: tuple[int, int], value: int, baud: int
                ) -> tuple[int, int]:  # fmt: skip
    """Write one byte, once more if its status was lost (a busy host): (result, error). A lost status of a
    new ID or baud may mean the write took: the servo answering at its new ID, or (a baud) the ping at the
    new baud that follows, says so."""
    result, error = packet.write1ByteTxRx(handler, dxl_id, item[0], value)
    if result == COMM_SUCCESS or error:
        return result, error
    if item == dx.BAUD_RATE or (item == dx.ID and ping_servos_at(handler, value, baud)):
        return COMM_SUCCESS, 0
    return packet.write1ByteTxRx(handler, dxl_id, item[0], value)


def ping_servos_at(handler, dxl_id: int, baud: int) -> bool:
    """Whether servo ``dxl_id`` answers a ping at ``baud``."""
    return any(s.dxl_id == dxl_id for s in ping_servos(handler, baud, dxl_id) or [])
