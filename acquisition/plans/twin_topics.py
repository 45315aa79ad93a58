"""The twin's device streams (``acquisition.sim.streams``) as session topic rows, exactly as the real-time
recorder writes what the drivers return: same topics, same units, same stamps and sequence numbers."""

from __future__ import annotations

import numpy as np

from acquisition.codecs import dynamixel as dx
from acquisition.schemas import topics as T
from acquisition.sim.streams import Stream
from models.robot import RobotDescription

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
