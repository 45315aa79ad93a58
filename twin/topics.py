"""The twin's device streams (``twin.streams``) as session topic rows, exactly as the real-time
recorder writes what the drivers return: same topics, same units, same stamps and sequence numbers."""

from __future__ import annotations

import numpy as np

from acquisition.codecs import dynamixel as dx
from acquisition.schemas import topics as T
from models.robot import RobotDescription
from twin.emulators.cia402_drive import SW_REMOTE, SW_SETPOINT_ACK, SW_VOLTAGE, State
from twin.streams import Stream

# a CiA 402 drive in OPERATION ENABLED following CSP targets, as the emulated drive shows it
DRIVE_ENABLED_STATUSWORD = int(State.OPERATION_ENABLED) | SW_VOLTAGE | SW_REMOTE | SW_SETPOINT_ACK
TopicRows = tuple[np.ndarray, np.ndarray, np.ndarray]  # robot index, host log time (ns), message rows


def stream_rows(robot: RobotDescription, topics: dict[str, T.Topic], streams: dict[str, Stream],
                valve_open: np.ndarray) -> dict[str, TopicRows]:  # fmt: skip
    """Topic rows of every device stream; ``valve_open`` (B, C) holds the valve states of the window."""
    out: dict[str, TopicRows] = {}
    if "servo_bus" in streams and T.SERVO_STATE in topics:
        s = streams["servo_bus"]
        zero = robot.servo.zero_count
        rows = topics[T.SERVO_STATE].message.pack(
            {
                "seq": s["seq"] % 2**32,
                "tick_ms": s["tick"],
                "position": (s["position"] - zero) * dx.RAD_PER_POSITION_COUNT,
                "velocity": s["velocity"] * dx.RAD_S_PER_VELOCITY_UNIT,
                "current": s["current"] * dx.AMP_PER_CURRENT_UNIT,
                "moving": s["velocity"] != 0,
            }
        )
        out[T.SERVO_STATE] = (s["robot"], s["host_ns"], rows)
    if "drives" in streams and T.JOINT_STATE in topics:
        s = streams["drives"]
        n = s["position_counts"].shape[1]
        rows = topics[T.JOINT_STATE].message.pack(
            {
                "seq": s["seq"] % 2**32,
                "position": s["position_counts"] / s["counts_per_rad"][:, None],
                "velocity": s["velocity_counts"] / s["counts_per_rad"][:, None],
                "torque": s["torque_per_mille"] * 1e-3 * s["rated_nm"][:, None],
                "statusword": np.full((len(s["seq"]), n), DRIVE_ENABLED_STATUSWORD),
            }
        )
        out[T.JOINT_STATE] = (s["robot"], s["host_ns"], rows)
    for link, board in robot.link_boards().items():
        s = streams.get(f"link_board:{board}")
        if s is None:
            continue
        seq = s["seq"] % 2**32
        orientation = topics[T.link_orientation_topic(link)].message.pack(
            {"seq": seq, "micros": s["micros"], "rpy": s["rpy"]}
        )
        flex = topics[T.link_flex_topic(link)].message.pack(
            {"seq": seq, "micros": s["micros"], "counts": s["flex"]}
        )
        out[T.link_orientation_topic(link)] = (s["robot"], s["host_ns"], orientation)
        out[T.link_flex_topic(link)] = (s["robot"], s["host_ns"], flex)
    if "pressure_board" in streams:
        s = streams["pressure_board"]
        counts = s["counts"]
        rows = topics[T.PRESSURE].message.pack(
            {
                "seq": s["seq"] % 2**32,
                "micros": s["micros"],
                "counts": counts,
                "pressure": robot.sensors.pressure.counts_to_pa(counts),
                "valve_open": valve_open[s["robot"]],
            }
        )
        out[T.PRESSURE] = (s["robot"], s["host_ns"], rows)
    if "stepper_board" in streams and T.STEPPER in topics:
        s = streams["stepper_board"]
        steps = s["position_steps"]
        moving = np.zeros(len(steps), bool)
        same_robot = s["robot"][1:] == s["robot"][:-1]
        moving[1:] = same_robot & np.any(steps[1:] != steps[:-1], axis=1)
        rows = topics[T.STEPPER].message.pack(
            {
                "seq": s["seq"] % 2**32,
                "micros": s["micros"],
                "position_steps": steps,
                "position": steps * robot.stepper.rad_per_microstep,
                "moving": moving,
            }
        )
        out[T.STEPPER] = (s["robot"], s["host_ns"], rows)
    if "tracker" in streams:
        s = streams["tracker"]
        rows = topics[T.TRACKER].message.pack(
            {
                "frame": s["frame"] % 2**32,
                "port_handle": robot.devices["tracker"].ids.get("tip", 10),
                "port_status": s["port_status"],
                "missing": s["missing"],
                "position": s["position"],
                "quaternion": s["quaternion"],
                "rms_error": s["rms_error"],
            }
        )
        out[T.TRACKER] = (s["robot"], s["host_ns"], rows)
    if "accelerometer" in streams and T.ACCEL in topics:
        s = streams["accelerometer"]
        rows = topics[T.ACCEL].message.pack(
            {"seq": s["seq"] % 2**32, "micros": s["micros"], "acceleration": s["acceleration"]}
        )
        out[T.ACCEL] = (s["robot"], s["host_ns"], rows)
    return out
