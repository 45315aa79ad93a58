"""POPUP's board frames: the main board's and the link boards' messages of ``configs/can/popup_boards.dbc``,
encoded and decoded with cantools (the DBC is the contract; both the twin's boards and the host's driver read
it, so a frame layout is written once).

The boards sit on the bus under CANopen node ids no drive uses (main board 0x10, link board k 0x10 + k) and
send in those nodes' PDO slots; every sampled frame starts with a 16-bit sample counter (the board samples
on a fixed timer of its own clock: the counter numbers its samples, so a gap is a lost frame, and it is that
stream's clock). See ``firmware/PROTOCOL.md`` ("POPUP's CAN bus").
"""

from __future__ import annotations

import functools

import cantools

from acquisition.codecs.can import CanFrame
from acquisition.errors import CodecError
from models.robot import CAN_DIR

DBC = CAN_DIR / "popup_boards.dbc"
MAIN_NODE = 0x10
COUNTER_MODULO = 1 << 16  # every sampled frame's Counter signal
COMMAND_COUNTER_MODULO = 1 << 6  # PressureCommand's Counter
STATUS_PERIOD_S = 0.1  # the main board's status frame (uptime, rejected commands)

MAIN_PRESSURE, MAIN_STATUS, PRESSURE_COMMAND = "MainPressure", "MainStatus", "PressureCommand"
ACCEL, ORIENTATION, FLEX = "Accel", "Orientation", "Flex"


@functools.cache
def database() -> cantools.database.can.Database:
    """The boards' DBC, parsed once per process."""
    return cantools.database.load_file(str(DBC))


HOST = "HOST"  # the DBC's node for the computer


def node_of(can_id: int) -> int:
    """The node id whose PDO slot ``can_id`` is (its low 7 bits)."""
    return can_id & 0x7F


def link_message(node_id: int, what: str) -> str:
    """The name of link board ``node_id``'s message ``what`` (ACCEL, ORIENTATION, FLEX)."""
    k = node_id - MAIN_NODE
    name = f"Link{k}{what}"
    try:
        database().get_message_by_name(name)
    except KeyError:
        raise CodecError(f"node {node_id:#x} is not a link board of {DBC.name} (no message {name})") from None
    return name


def scale(message: str, signal: str) -> float:
    """What one raw unit of ``signal`` of ``message`` is worth (its DBC scale)."""
    return float(database().get_message_by_name(message).get_signal_by_name(signal).scale)


def counter_modulo(message: str) -> int:
    """How many values ``message``'s Counter signal takes before it wraps."""
    return 1 << database().get_message_by_name(message).get_signal_by_name("Counter").length


def setpoint_max_pa() -> float:
    """The largest pressure set-point PressureCommand can carry."""
    return float(database().get_message_by_name(PRESSURE_COMMAND).get_signal_by_name("Setpoint1").maximum)


def encode(name: str, signals: dict[str, float | int], scaling: bool = True) -> CanFrame:
    """The frame of message ``name`` carrying ``signals`` (physical values, or raw with ``scaling=False``);
    a missing or out-of-range signal raises :class:`CodecError`."""
    message = database().get_message_by_name(name)
    try:
        data = message.encode(signals, scaling=scaling)
    except (cantools.database.EncodeError, KeyError, ValueError) as exc:
        raise CodecError(f"{name}: cannot encode {signals}: {exc}") from exc
    return CanFrame(message.frame_id, bytes(data))


def frame_ids() -> dict[int, str]:
    """Every board message's CAN id → its name."""
    return {m.frame_id: m.name for m in database().messages}


def decode(can_id: int, data: bytes) -> dict[str, float | int]:
    """The physical signal values of board frame ``can_id``; a frame that is not one of the DBC's, or is
    too short for its message, raises :class:`CodecError`."""
    try:
        return database().decode_message(can_id, data, decode_choices=False)
    except (KeyError, cantools.database.DecodeError, ValueError) as exc:
        raise CodecError(
            f"CAN frame {can_id:#x} ({data.hex()}): not a board frame of {DBC.name}: {exc}"
        ) from exc
