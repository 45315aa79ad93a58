"""The last check before a command leaves the computer: every goal, set-point, valve state and move.

Whatever produced a command — a plan, a compensator (a trained network can output NaN or 1e35), the CLI or
a user's script — it reaches a device only through the daemon that owns the device's port, and that daemon
asks this guard first (:mod:`acquisition.recorder.sources`). The runners ask it too, before sending, so that
a bad command is a safe stop with its reason rather than a refusal found later in the events.

The limits are the robot description's: the joints' ranges (servo goals; the stepper's move target in
microsteps), the servos' top speed, the pneumatics' operating range, the stepper's top speed and
acceleration. A command is refused whole: nothing of it is written.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from acquisition.errors import AcquisitionError
from models.robot import RobotDescription


class CommandRefused(AcquisitionError, ValueError):
    """A command outside the robot's limits, or not a number; nothing of it reached the device."""


class CommandGuard:
    """The command limits of one robot."""

    def __init__(self, robot: RobotDescription) -> None:
        self.robot = robot
        self.joint_names = [j.name for j in robot.joints]
        self.limits = {j.name: (j.lower_rad, j.upper_rad) for j in robot.joints}
        self.servo_speed = robot.servo.max_speed_rad_s if robot.servo is not None else math.inf
        pn = robot.pneumatics
        self.channels = pn.channels
        self.pressure_max = pn.max_operating_pa
        st = robot.stepper
        self.stepper = None
        if st is not None:
            per = st.rad_per_microstep
            # the runner rounds its rates to at least 1 step/s: a robot slower than that is held to 1
            self.stepper = (per, max(st.max_speed_rad_s / per, 1.0), max(st.acceleration_rad_s2 / per, 1.0))

    # ------------------------------------------------------------------------------------ joints
    def joint_goals(self, q: Sequence[float] | np.ndarray, joints: Sequence[str] | None = None) -> np.ndarray:
        """Goals ``q`` (rad) of ``joints`` (default: every joint, in the robot's order), checked."""
        joints = list(self.joint_names if joints is None else joints)
        q = _numbers(q, "joint goal", len(joints))
        for name, value in zip(joints, q, strict=True):
            lo, hi = self.limits[name]
            if not lo <= value <= hi:
                raise CommandRefused(
                    f"joint goal {name} = {value:.6g} rad is outside its range [{lo:.4g}, {hi:.4g}] rad"
                )
        return q

    def servo_goals(self, joints: Sequence[str], position, profile_velocity) -> tuple[np.ndarray, np.ndarray]:
        """A Sync Write of goals: positions inside the joints' ranges, profile speeds 0 (the servo's own top
        speed) up to the servos' top speed."""
        q = self.joint_goals(position, joints)
        v = _numbers(profile_velocity, "profile velocity", len(joints))
        for name, value in zip(joints, v, strict=True):
            if not 0.0 <= value <= self.servo_speed:
                raise CommandRefused(
                    f"profile velocity of {name} = {value:.6g} rad/s is outside "
                    f"[0, {self.servo_speed:.4g}] rad/s"
                )
        return q, v

    # ----------------------------------------------------------------------------------- pressure
    def pressures(self, setpoint, valve_open) -> tuple[np.ndarray, np.ndarray]:
        """Set-points (Pa) inside [0, max_operating_pa] and one open/closed state per channel."""
        p = _numbers(setpoint, "pressure set-point", self.channels)
        for ch, value in enumerate(p):
            if not 0.0 <= value <= self.pressure_max:
                raise CommandRefused(
                    f"pressure set-point of channel {ch} = {value:.6g} Pa is outside "
                    f"[0, {self.pressure_max:.6g}] Pa (the robot's operating range)"
                )
        valves = np.asarray(valve_open, dtype=object).ravel()
        if len(valves) != self.channels or not all(
            isinstance(v, bool | np.bool_) or v in (0, 1) for v in valves
        ):
            raise CommandRefused(f"valve states must be {self.channels} booleans, got {list(valves)!r}")
        return p, valves.astype(bool)

    # ------------------------------------------------------------------------------------ stepper
    def stepper_move(self, joint: str, steps, speed, accel) -> tuple[int, float, float]:
        """A move to ``steps`` (microsteps from zero) at ``speed`` steps/s and ``accel`` steps/s²."""
        if self.stepper is None:
            raise CommandRefused(f"robot {self.robot.name} has no stepper")
        per, top_speed, top_accel = self.stepper
        target, speed, accel = _numbers([steps, speed, accel], "stepper move", 3)
        if target != round(target):
            raise CommandRefused(f"stepper target {target!r} is not a whole number of microsteps")
        lo, hi = self.limits[joint]
        lo_steps, hi_steps = math.floor(lo / per), math.ceil(hi / per)  # the goal is rounded to a step
        if not lo_steps <= target <= hi_steps:
            raise CommandRefused(
                f"stepper target {int(target)} microsteps ({target * per:.4g} rad) is outside the range of "
                f"{joint} [{lo_steps}, {hi_steps}] microsteps"
            )
        if not 0.0 < speed <= top_speed:
            raise CommandRefused(f"stepper speed {speed:.6g} steps/s is outside (0, {top_speed:.6g}]")
        if not 0.0 < accel <= top_accel:
            raise CommandRefused(f"stepper acceleration {accel:.6g} steps/s² is outside (0, {top_accel:.6g}]")
        return int(target), speed, accel


def _numbers(values, what: str, n: int) -> np.ndarray:
    """``values`` as ``n`` finite floats, or :class:`CommandRefused` saying what is wrong."""
    try:
        out = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError) as exc:
        raise CommandRefused(f"{what}: not numbers ({values!r})") from exc
    if len(out) != n:
        raise CommandRefused(f"{what}: {len(out)} values where {n} are expected")
    bad = np.flatnonzero(~np.isfinite(out))
    if len(bad):
        raise CommandRefused(f"{what}: value {bad[0]} is {out[bad[0]]} (not a finite number)")
    return out
