"""How a device's reading becomes the fields of its topic's message: one function per sampled topic, shared by
the recorder's sources (one sample, as the driver returns it) and the twin's simulated runner (a window of
samples as arrays), so the two write the same rows from the same readings.

Each returns the message's fields (``FixedMessage.pack`` and ``Source.row`` take them); numbers are
wrapped to the uint32 fields they go into.
"""

from __future__ import annotations

import numpy as np

from models.robot import PressureSensorSpec

SEQ_MODULO = 1 << 32  # every counter a sample is numbered by is a uint32 field

Values = dict[str, object]


def servo_state(seq, tick_ms, position_rad, velocity_rad_s, current_a, moving) -> Values:
    """``/servo/state``: one Sync Read of the bus (SI)."""
    return {"seq": seq % SEQ_MODULO, "tick_ms": tick_ms, "position": position_rad, "velocity": velocity_rad_s,
            "current": current_a, "moving": moving}  # fmt: skip


def joint_state(seq, position_rad, velocity_rad_s, torque_nm, statusword) -> Values:
    """``/joint/state``: the CiA 402 drives' answers to one SYNC (SI)."""
    return {"seq": seq % SEQ_MODULO, "position": position_rad, "velocity": velocity_rad_s,
            "torque": torque_nm, "statusword": statusword}  # fmt: skip


def pressure(calibration: PressureSensorSpec, seq, micros, counts, valve_open) -> Values:
    """``/pressure/measured``: ADC counts, their gauge pressure by the robot's calibration, the valves."""
    counts = np.asarray(counts)
    return {"seq": seq % SEQ_MODULO, "micros": micros, "counts": counts,
            "pressure": calibration.counts_to_pa(counts), "valve_open": valve_open}  # fmt: skip


def stepper(rad_per_microstep: float, seq, micros, position_steps, moving) -> Values:
    """``/stepper/state``: the Nano's position report, in microsteps and rad."""
    steps = np.asarray(position_steps)
    return {"seq": seq % SEQ_MODULO, "micros": micros, "position_steps": steps,
            "position": steps * rad_per_microstep, "moving": moving}  # fmt: skip


def tracker(frame, port_handle, port_status, missing, position_m, quaternion, rms_error_m) -> Values:
    """``/tracker/pose``: one frame of the tip coil."""
    return {"frame": frame % SEQ_MODULO, "port_handle": port_handle, "port_status": port_status,
            "missing": missing, "position": position_m, "quaternion": quaternion,
            "rms_error": rms_error_m}  # fmt: skip


def acceleration(seq, micros, acceleration_m_s2) -> Values:
    """``/imu/accel``: one accelerometer sample (specific force, sensor frame)."""
    return {"seq": seq % SEQ_MODULO, "micros": micros, "acceleration": acceleration_m_s2}


def link_orientation(seq, micros, rpy_rad) -> Values:
    """``/<link>/orientation``: roll, pitch, yaw of the link's end."""
    return {"seq": seq % SEQ_MODULO, "micros": micros, "rpy": rpy_rad}


def link_flex(seq, micros, counts) -> Values:
    """``/<link>/flex``: the link's four flex sensors."""
    return {"seq": seq % SEQ_MODULO, "micros": micros, "counts": counts}
