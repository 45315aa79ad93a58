"""The twin behind each emulator: the 'hardware' the rig's emulators drive and sense.

Each adapter brings the twin up to the emulator's time (``rig.advance``), maps the device's commands onto the
world's commands, and reads the world's true state through the same sensor models the simulated streams use
(``streams``/``sensors``), stamped by the device's own clock.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from acquisition.protocols import dynamixel as dx
from acquisition.sim import sensors, streams
from acquisition.sim.emulators.aurora import TrackerSample
from acquisition.sim.emulators.dynamixel import ControlTable

if TYPE_CHECKING:
    from acquisition.sim.rig import Rig

_ROBOT0 = np.array([0])


def _ticks(rig: Rig, device: str) -> int:
    """The device's own counter at the twin's current time."""
    return int(rig.world.clocks[device].ticks_at(_ROBOT0, np.array([rig.world.t]))[0])


class TwinServos:
    """The twin's joints behind the Dynamixel control tables."""

    def __init__(self, rig: Rig, joints: dict[int, int]) -> None:
        self.rig = rig
        self.joints = joints
        self.zero = rig.robot.servo.zero_count

    def apply(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        self.rig.advance(now_s)
        world, j = self.rig.world, self.joints[dxl_id]
        if table.torque_on:
            world.commands.goal[0, j] = sensors.encoder_angle(
                table.get(dx.GOAL_POSITION, signed=True), self.zero
            )
        else:  # limp joints are not modelled: the drive holds where it is
            world.commands.goal[0, j] = world.state.out_pos[0, j]
        world.commands.profile_vel[0, j] = table.get(dx.PROFILE_VELOCITY) * dx.RAD_S_PER_VELOCITY_UNIT
        world.commands.profile_acc[0, j] = (
            table.get(dx.PROFILE_ACCELERATION) * dx.RAD_S2_PER_ACCELERATION_UNIT
        )

    def sense(self, dxl_id: int, table: ControlTable, now_s: float) -> None:
        self.rig.advance(now_s)
        world, j = self.rig.world, self.joints[dxl_id]
        st = world.state
        counts = streams.servo_counts(
            self.rig.robot, st.out_pos[0, j], st.out_vel[0, j], st.torque[0, j], world.rng
        )
        goal = table.get(dx.GOAL_POSITION, signed=True)
        table.set(dx.PRESENT_POSITION, int(counts["position"]))
        table.set(dx.PRESENT_VELOCITY, int(counts["velocity"]))
        table.set(dx.PRESENT_CURRENT, int(counts["current"]))
        table.set(dx.REALTIME_TICK, _ticks(self.rig, "servo_bus"))
        table.set(dx.MOVING, int(abs(goal - int(counts["position"])) > 1 or abs(st.out_vel[0, j]) > 0.01))


class TwinPressure:
    """Regulators, valves and the transducer/ADS1115 chain of the pressure board."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.spec = streams.pressure_spec(rig.robot)

    def set_pressure(self, channel: int, pa: float) -> None:
        self.rig.world.commands.pressure_set[0, channel] = np.clip(
            pa, 0.0, self.rig.robot.pneumatics.regulator_max_pa
        )

    def set_valve(self, channel: int, open_: bool) -> None:
        self.rig.world.commands.valve_open[0, channel] = bool(open_)

    def sample(self, now_s: float) -> tuple[int, int]:
        self.rig.advance(now_s)
        counts = sensors.pressure_to_adc_counts(
            self.rig.world.state.p_link[0, :2], self.spec, self.rig.world.rng
        )
        return int(counts[0]), int(counts[1])

    def micros(self, now_s: float) -> int:
        self.rig.advance(now_s)
        return _ticks(self.rig, "pressure_board")


class TwinStepper:
    """The J1 stepper behind the Nano: microstep positions of the twin's stepper joint."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.joint = next(i for i, j in enumerate(rig.robot.joints) if j.drive == "stepper")
        self.quantum = rig.robot.stepper.rad_per_microstep

    def move_to(self, steps: int) -> None:
        self.rig.world.commands.goal[0, self.joint] = steps * self.quantum

    def set_speed(self, steps_s: float, accel: float) -> None:
        self.rig.world.commands.profile_vel[0, self.joint] = abs(steps_s) * self.quantum
        self.rig.world.commands.profile_acc[0, self.joint] = abs(accel) * self.quantum

    def stop(self) -> None:
        self.rig.world.commands.goal[0, self.joint] = self.rig.world.state.out_pos[0, self.joint]

    def position(self, now_s: float) -> int:
        self.rig.advance(now_s)
        return round(float(self.rig.world.state.out_pos[0, self.joint]) / self.quantum)

    def moving(self, now_s: float) -> bool:
        self.rig.advance(now_s)
        st = self.rig.world.state
        return bool(
            abs(st.ref_vel[0, self.joint]) > 0
            or st.ref_pos[0, self.joint] != self.rig.world.commands.goal[0, self.joint]
        )

    def micros(self, now_s: float) -> int:
        self.rig.advance(now_s)
        return _ticks(self.rig, "stepper_board")


class TwinTrackerSource:
    """The tip coil as the tracker sees it, at the tracker's own frame counter; ``force_out`` moves the coil
    out of the field volume (the fault a test asks for)."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.spec = streams.tracker_spec(rig.robot)
        self.chain = rig.robot.chain()
        self.tool = np.asarray(rig.robot.tool_offset_m)
        self.force_out = False

    def __call__(self, now_s: float) -> TrackerSample:
        self.rig.advance(now_s)
        st = self.rig.world.state
        pose = self.chain.fk(st.out_pos[0], st.delta[0])
        tip = pose[:3, :3] @ self.tool + pose[:3, 3]
        if self.force_out:
            tip = tip + 10.0  # far outside any field volume
        reading = sensors.tracker_measurement(tip[None], pose[None, :3, :3], self.spec, self.rig.world.rng)
        return TrackerSample(
            frame=_ticks(self.rig, "tracker"),
            position_m=reading.position_m[0],
            quaternion=reading.quaternion[0],
            rms_error=float(reading.rms_error[0]) * 1e-3,  # the sensor model reports mm
            missing=bool(reading.missing[0]),
            port_status=int(reading.port_status[0]),
        )
