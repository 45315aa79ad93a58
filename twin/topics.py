"""The twin's device streams (``twin.streams``) as session topic rows, exactly as the real-time
recorder writes what the drivers return: same topics, same units, same stamps and sequence numbers. Each
built-in device kind names its rows function here (``DeviceKind.rows``); :func:`stream_rows` asks every
device's kind."""

from __future__ import annotations

import numpy as np

from acquisition.codecs import dynamixel as dx
from acquisition.devices.kinds import device_kinds, device_of, resolve
from acquisition.schemas import topic_rows as R
from acquisition.schemas import topics as T
from models.robot import RobotDescription
from twin.emulators.cia402_drive import SW_REMOTE, SW_SETPOINT_ACK, SW_VOLTAGE, State
from twin.streams import Stream

# a CiA 402 drive in OPERATION ENABLED following CSP targets, as the emulated drive shows it
DRIVE_ENABLED_STATUSWORD = int(State.OPERATION_ENABLED) | SW_VOLTAGE | SW_REMOTE | SW_SETPOINT_ACK
TopicRows = tuple[np.ndarray, np.ndarray, np.ndarray]  # robot index, host log time (ns), message rows


def stream_rows(robot: RobotDescription, topics: dict[str, T.Topic], streams: dict[str, Stream],
                valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """Topic rows of every device stream, each device's by its kind's ``rows``; ``valve_open`` (B, C) holds
    the valve states of the window."""
    calls = [
        (order, i, resolve(ref), name)
        for i, (name, kind) in enumerate(device_kinds(robot).items())
        for order, ref in kind.rows
    ]
    out: dict[str, TopicRows] = {}
    for _, _, rows, name in sorted(calls, key=lambda c: c[:2]):
        out.update(rows(robot, name, topics, streams, valve_open))
    return out


def servo_rows(robot: RobotDescription, name: str, topics: dict[str, T.Topic], streams: dict[str, Stream],
               valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """The servo bus's Sync Reads in SI, as ``ServoSource`` records what the driver decoded."""
    s = streams.get("servo_bus")
    if s is None or T.SERVO_STATE not in topics:
        return {}
    zero = robot.servo.zero_count
    rows = topics[T.SERVO_STATE].message.pack(
        R.servo_state(
            s["seq"],
            s["tick"],
            (s["position"] - zero) * dx.RAD_PER_POSITION_COUNT,
            s["velocity"] * dx.RAD_S_PER_VELOCITY_UNIT,
            s["current"] * dx.AMP_PER_CURRENT_UNIT,
            s["velocity"] != 0,
        )
    )
    return {T.SERVO_STATE: (s["robot"], s["host_ns"], rows)}


def drive_rows(robot: RobotDescription, name: str, topics: dict[str, T.Topic], streams: dict[str, Stream],
               valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """The CiA 402 drives' answers to SYNC in SI."""
    s = streams.get("drives")
    if s is None or T.JOINT_STATE not in topics:
        return {}
    n = s["position_counts"].shape[1]
    rows = topics[T.JOINT_STATE].message.pack(
        R.joint_state(
            s["seq"],
            s["position_counts"] / s["counts_per_rad"][:, None],
            s["velocity_counts"] / s["counts_per_rad"][:, None],
            s["torque_per_mille"] * 1e-3 * s["rated_nm"][:, None],
            np.full((len(s["seq"]), n), DRIVE_ENABLED_STATUSWORD),
        )
    )
    return {T.JOINT_STATE: (s["robot"], s["host_ns"], rows)}


def link_board_rows(robot: RobotDescription, name: str, topics: dict[str, T.Topic],
                    streams: dict[str, Stream], valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """A link board's orientation and flex sensors."""
    s = streams.get(f"link_board:{name}")
    if s is None:
        return {}
    link = robot.devices[name].link
    orientation = topics[T.link_orientation_topic(link)].message.pack(
        R.link_orientation(s["seq"], s["micros"], s["rpy"])
    )
    flex = topics[T.link_flex_topic(link)].message.pack(R.link_flex(s["seq"], s["micros"], s["flex"]))
    return {
        T.link_orientation_topic(link): (s["robot"], s["host_ns"], orientation),
        T.link_flex_topic(link): (s["robot"], s["host_ns"], flex),
    }


def pressure_rows(robot: RobotDescription, name: str, topics: dict[str, T.Topic], streams: dict[str, Stream],
                  valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """The link pressures: counts, their calibrated Pa, the valves of the window."""
    s = streams.get("pressure_board")
    if s is None:
        return {}
    rows = topics[T.PRESSURE].message.pack(
        R.pressure(robot.sensors.pressure, s["seq"], s["micros"], s["counts"], valve_open[s["robot"]])
    )
    return {T.PRESSURE: (s["robot"], s["host_ns"], rows)}


def stepper_rows(robot: RobotDescription, name: str, topics: dict[str, T.Topic], streams: dict[str, Stream],
                 valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """The stepper board's position reports (moving: the position changed since the last report)."""
    s = streams.get("stepper_board")
    if s is None or T.STEPPER not in topics:
        return {}
    steps = s["position_steps"]
    moving = np.zeros(len(steps), bool)
    same_robot = s["robot"][1:] == s["robot"][:-1]
    moving[1:] = same_robot & np.any(steps[1:] != steps[:-1], axis=1)
    rows = topics[T.STEPPER].message.pack(
        R.stepper(robot.stepper.rad_per_microstep, s["seq"], s["micros"], steps, moving)
    )
    return {T.STEPPER: (s["robot"], s["host_ns"], rows)}


def tracker_rows(robot: RobotDescription, name: str, topics: dict[str, T.Topic], streams: dict[str, Stream],
                 valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """The tracker's frames of the tip coil."""
    s = streams.get("tracker")
    if s is None:
        return {}
    port_handle = robot.devices[name].ids.get("tip", 10)
    values = R.tracker(s["frame"], port_handle, s["port_status"], s["missing"], s["position"],
                       s["quaternion"], s["rms_error"])  # fmt: skip
    rows = topics[T.TRACKER].message.pack(values)
    return {T.TRACKER: (s["robot"], s["host_ns"], rows)}


def accelerometer_rows(robot: RobotDescription, name: str, topics: dict[str, T.Topic],
                       streams: dict[str, Stream], valve_open: np.ndarray,
                       ) -> dict[str, TopicRows]:  # fmt: skip
    """The tip accelerometer's samples."""
    s = streams.get("accelerometer")
    if s is None or T.ACCEL not in topics or device_of(robot, "accelerometer") != name:
        return {}
    rows = topics[T.ACCEL].message.pack(R.acceleration(s["seq"], s["micros"], s["acceleration"]))
    return {T.ACCEL: (s["robot"], s["host_ns"], rows)}
