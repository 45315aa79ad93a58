"""The twin behind each emulator: the 'hardware' the rig's emulators drive and sense.

Each adapter brings the twin up to the emulator's time (``rig.advance``), maps the device's commands onto the
world's commands, and reads the world's true state through the same sensor models the simulated streams use
(``streams``/``sensors``), stamped by the device's own clock. A reading depends only on the twin's state,
which changes once per step: the servos are sensed once per step for all of them (a Sync Read of N servos
draws the noise once, vectorised; repeated reads within a step share it), and the device counters are read
with ``Rig.ticks`` (the simulated clock in plain floats).
The boards' adapters also invert their device clock (``micros_due_s``) so the pty host can sleep until the
next streamed line is due.
"""

from __future__ import annotations

import math
import struct
from typing import TYPE_CHECKING

import numpy as np

from acquisition.codecs import dynamixel as dx
from acquisition.devices.kinds import device_of
from twin import kernel, sensors, streams
from twin.clocks import _TICK_EPS as TICK_EPS
from twin.emulators.aurora import TrackerSample
from twin.emulators.dynamixel import ControlTable

if TYPE_CHECKING:
    from twin.rig import Rig

# The present values a read refreshes, packed straight into the control table (what ControlTable.set writes).
_TICK_MOVING = struct.Struct("<HB")  # Realtime Tick, Moving
_PRESENT = struct.Struct("<HII")  # Present Current, Velocity, Position
assert dx.MOVING[0] == dx.REALTIME_TICK[0] + dx.REALTIME_TICK[1]
assert (
    dx.PRESENT_VELOCITY[0] == dx.PRESENT_CURRENT[0] + 2
    and dx.PRESENT_POSITION[0] == dx.PRESENT_VELOCITY[0] + 4
)


def _counter_due_s(rig: Rig, device: str, target: int, now_s: float) -> float:
    """The rig time at which the twin's ``device`` counter (``SimulatedClocks.ticks_at`` at the twin's
    time: it moves once per step) first reads ``target`` (modulo its wrap, within half a wrap); ``now_s``
    if it already does. The clock's arithmetic inverted; float rounding at a step boundary can at worst make
    it one step late, and a not-yet-due answer is always after the next step (so the host never spins)."""
    rig.advance(now_s)
    clocks = rig.world.clocks[device]
    spec = clocks.spec
    drift, offset = float(clocks.drift_ppm[0]), float(clocks.offset_s[0])
    rate = 1.0 + drift * 1e-6
    raw = math.floor((rate * rig.world.t + offset) / spec.tick_s + TICK_EPS)  # unwrapped counter now
    if spec.wrap is None:
        ahead = target - raw
        if ahead <= 0:
            return now_s
    else:
        ahead = (target - raw) % spec.wrap
        if ahead == 0 or ahead >= spec.wrap // 2:
            return now_s
    true_s = ((raw + ahead - TICK_EPS) * spec.tick_s - offset) / rate
    step = max(math.ceil(true_s / rig.world.dt), rig.steps + 1)
    return rig.step_due_s(step)


class TwinServos:
    """The twin's joints behind the Dynamixel control tables."""

    def __init__(self, rig: Rig, joints: dict[int, int], counter: str = "servo_bus") -> None:
        self.rig = rig
        self.joints = joints
        self.counter = counter  # the rig's device counter of the bus (the servos' Realtime Tick)
        self.zero = rig.robot.servo.zero_count
        self._ids = sorted(joints)
        self._columns = np.array([joints[i] for i in self._ids], dtype=np.intp)
        self._sensed_t: float | None = None  # twin time of the cached readings
        self._present: dict[int, tuple[int, int, int, int, float]] = {}

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
        tick, position, velocity, current, speed = self._sensed(now_s)[dxl_id]
        moving = abs(table.get(dx.GOAL_POSITION, signed=True) - position) > 1 or speed > 0.01
        _TICK_MOVING.pack_into(table.data, dx.REALTIME_TICK[0], tick & 0xFFFF, int(moving))
        _PRESENT.pack_into(
            table.data, dx.PRESENT_CURRENT[0], current & 0xFFFF, velocity & 0xFFFFFFFF, position & 0xFFFFFFFF
        )

    def _sensed(self, now_s: float) -> dict[int, tuple[int, int, int, int, float]]:
        """Every servo's (tick, position, velocity, current counts, true speed) at the twin's current step:
        sensed once per step, so the N reads of a Sync Read (and repeated reads within a step) share it."""
        rig = self.rig
        rig.advance(now_s)
        world = rig.world
        if self._sensed_t != world.t:
            st, j = world.state, self._columns
            qd = st.out_vel[0, j]
            rng = world.device_rng(self.counter)
            counts = streams.servo_counts(rig.robot, st.out_pos[0, j], qd, st.torque[0, j], rng)
            tick = rig.ticks(self.counter)
            self._present = {
                i: (tick, p, v, c, s)
                for i, p, v, c, s in zip(
                    self._ids,
                    counts["position"].tolist(),
                    counts["velocity"].tolist(),
                    counts["current"].tolist(),
                    np.abs(qd).tolist(),
                    strict=True,
                )
            }
            self._sensed_t = world.t
        return self._present


class _BoardClock:
    """A board's ``micros()`` on the twin: the rig's device counter ``counter``, read and inverted."""

    rig: Rig
    counter: str

    def micros(self, now_s: float) -> int:
        self.rig.advance(now_s)
        return self.rig.ticks(self.counter)

    def micros_due_s(self, micros: int, now_s: float) -> float:
        return _counter_due_s(self.rig, self.counter, micros, now_s)


class TwinPressure(_BoardClock):
    """Regulators, valves and the transducer/ADS1115 chain of the board that reads the link pressures (the
    VSL pressure board; POPUP's main board)."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.counter = device_of(rig.robot, "pressure")
        self.spec = streams.pressure_spec(rig.robot)

    def set_pressure(self, channel: int, pa: float) -> None:
        self.rig.world.commands.pressure_set[0, channel] = np.clip(
            pa, 0.0, self.rig.robot.pneumatics.regulator_max_pa
        )

    def set_valve(self, channel: int, open_: bool) -> None:
        self.rig.world.commands.valve_open[0, channel] = bool(open_)

    def advance(self, now_s: float) -> None:
        self.rig.advance(now_s)

    def sample(self, now_s: float) -> tuple[int, int]:
        self.rig.advance(now_s)
        counts = sensors.pressure_to_adc_counts(
            self.rig.recent.at(now_s).p_link[:2], self.spec, self.rig.world.device_rng(self.counter)
        )
        return int(counts[0]), int(counts[1])

    def regulating(self, channel: int) -> bool:
        return bool(self.rig.world.commands.valve_open[0, channel])

    def valves(self, channel: int, now_s: float, band_pa: float = 1000.0) -> tuple[bool, bool]:
        """(supply, exhaust) of ``channel``'s valve group as a bang-bang regulator with a ``band_pa``
        dead band drives them: supply below the set-point, exhaust above, both closed in the band or when
        the channel is not regulated (it holds)."""
        if not self.regulating(channel):
            return False, False
        error = self.rig.world.commands.pressure_set[0, channel] - self.rig.recent.at(now_s).p_link[channel]
        return bool(error > band_pa), bool(error < -band_pa)


class TwinStepper(_BoardClock):
    """The J1 stepper behind the Nano: microstep positions of the twin's stepper joint."""

    def __init__(self, rig: Rig, counter: str = "stepper_board") -> None:
        self.rig = rig
        self.counter = counter
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
        """The motor's position (microsteps) at rig time ``now_s``: a late sample's from the step that held
        then (``RecentSteps``)."""
        self.rig.advance(now_s)
        if now_s < self.rig.world.t - self.rig.world.dt:
            return round(float(self.rig.recent.at(now_s).q[self.joint]) / self.quantum)
        return round(float(self.rig.world.state.out_pos[0, self.joint]) / self.quantum)

    def moving(self, now_s: float) -> bool:
        self.rig.advance(now_s)
        st = self.rig.world.state
        return bool(
            abs(st.ref_vel[0, self.joint]) > 0
            or st.ref_pos[0, self.joint] != self.rig.world.commands.goal[0, self.joint]
        )


class TwinTrackerSource:
    """The tip coil as the tracker sees it, at the tracker's own frame counter; ``force_out`` moves the coil
    out of the field volume (the fault a test asks for)."""

    def __init__(self, rig: Rig) -> None:
        self.rig = rig
        self.spec = streams.tracker_spec(rig.robot)
        self.chain = rig.robot.chain()
        self.tool = np.asarray(rig.robot.tool_offset_m)
        self.force_out = False
        self.counter = "tracker"  # the rig's device counter of the tracker (its frame number)
        self._frame_key: tuple[int, bool] | None = None  # (frame number, force_out) of the frame held
        self._frame: TrackerSample | None = None

    def __call__(self, now_s: float) -> TrackerSample:
        """The frame the tracker holds at ``now_s``: measured once, when its first poll comes (as the Aurora
        answers every poll within one frame with that frame's measurement, noise and all)."""
        self.rig.advance(now_s)
        key = (self.rig.ticks(self.counter), self.force_out)
        if key != self._frame_key:
            self._frame, self._frame_key = self._measure(key[0]), key
        return self._frame

    def _measure(self, frame: int) -> TrackerSample:
        st = self.rig.world.state
        pose = self.chain.fk(st.out_pos[0], st.delta[0])
        tip = pose[:3, :3] @ self.tool + pose[:3, 3]
        if self.force_out:
            tip = tip + 10.0  # far outside any field volume
        rng = self.rig.world.device_rng(self.counter)
        reading = sensors.tracker_measurement(tip[None], pose[None, :3, :3], self.spec, rng)
        return TrackerSample(
            frame=frame,
            position_m=reading.position_m[0],
            quaternion=reading.quaternion[0],
            rms_error=float(reading.rms_error[0]) * 1e-3,  # the sensor model reports mm
            missing=bool(reading.missing[0]),
            port_status=int(reading.port_status[0]),
        )


class TwinJoint:
    """One motor joint of the twin behind a CiA 402 drive (POPUP): sensed as the drive's encoder and
    torque estimate see it, moved by the drive's position loop (the twin's servo model), held by its brake."""

    def __init__(self, rig: Rig, joint: str) -> None:
        self.rig = rig
        self.j = rig.robot.actuated_joints.index(joint)

    def sense(self, t: float) -> tuple[float, float, float]:
        self.rig.advance(t)
        st = self.rig.world.state
        return float(st.out_pos[0, self.j]), float(st.out_vel[0, self.j]), float(st.torque[0, self.j])

    def command(self, goal_rad: float, velocity_rad_s: float, acceleration_rad_s2: float, t: float) -> None:
        self.rig.advance(t)
        cmd = self.rig.world.commands
        cmd.goal[0, self.j] = goal_rad
        cmd.profile_vel[0, self.j] = velocity_rad_s
        cmd.profile_acc[0, self.j] = acceleration_rad_s2

    def hold(self, t: float) -> None:
        self.rig.advance(t)
        self.rig.world.commands.goal[0, self.j] = self.rig.world.state.out_pos[0, self.j]


class RecentStep:
    """The twin's true state at one step (robot 0), as the rig keeps it for samples due a little late."""

    __slots__ = ("_i", "delta", "p_link", "q", "t", "tip")

    def __init__(self, ring: RecentSteps, i: int) -> None:
        self._i = i
        self.t, self.q, self.delta = ring.t[i], ring.q[i], ring.delta[i]
        self.tip, self.p_link = ring.tip[i], ring.p_link[i]

    @property
    def slot(self) -> int:
        """Where this step is in its ring."""
        return self._i


class RecentSteps:
    """The last ``capacity`` steps of the twin's trace: a board's sample due at rig time t reads the step
    that held at t, even when the twin has been stepped past t (a busy host wakes late), so a late sample
    is not a later one. A sample older than the ring reads the oldest step kept (and is counted)."""

    def __init__(self, dt: float, capacity: int = 128) -> None:
        self.dt, self.capacity = dt, capacity
        self.t = np.full(capacity, -np.inf)
        self.q = self.delta = self.tip = self.p_link = None
        self.head = 0  # steps appended so far
        self.too_old = 0

    def append(self, trace) -> None:
        n = min(len(trace.t), self.capacity)
        if self.q is None:

            def ring(a):
                return np.zeros((self.capacity, *a.shape[2:]))

            self.q, self.delta, self.tip, self.p_link = (
                ring(trace.q), ring(trace.delta), ring(trace.tip_pos), ring(trace.pressure))  # fmt: skip
            self.tip[:] = trace.tip_pos[0, 0]  # at rest before the first step: no acceleration
        slots = (self.head + len(trace.t) - n + np.arange(n)) % self.capacity
        self.t[slots] = trace.t[-n:]
        self.q[slots], self.delta[slots] = trace.q[0, -n:], trace.delta[0, -n:]
        self.tip[slots], self.p_link[slots] = trace.tip_pos[0, -n:], trace.pressure[0, -n:]
        self.head += len(trace.t)

    def at(self, t: float) -> RecentStep:
        """The step holding at rig time ``t`` (the last that ended at or before it)."""
        newest = (self.head - 1) % self.capacity
        # steps that ended after t (floor here read the step after t whenever the rig was ahead of t)
        back = math.ceil((self.t[newest] - t) / self.dt - 1e-6) if t < self.t[newest] else 0
        # how far behind the newest step a sample may read (two more are kept for its acceleration)
        kept = min(self.head, self.capacity - 2) - 1
        if back > kept:
            self.too_old += 1
            back = kept
        return RecentStep(self, (newest - back) % self.capacity)


class TwinBoardTimer:
    """When a board of the twin takes its samples: every ``period_s`` of its own clock (the rig's device
    clock ``device``: drift and offset), numbered by its clock (sample k at device time k · period)."""

    def __init__(self, rig: Rig, device: str, period_s: float) -> None:
        clocks = rig.world.clocks[device]
        self.rate = 1.0 + float(clocks.drift_ppm[0]) * 1e-6
        self.offset = float(clocks.offset_s[0])
        self.period_s = period_s

    def first_after(self, t: float) -> int:
        return math.floor((self.rate * t + self.offset) / self.period_s) + 1

    def instant(self, k: int) -> float:
        return (k * self.period_s - self.offset) / self.rate


class TwinLinkBoard:
    """What a POPUP link board senses on its link: the IMU at the link's end (specific force in the IMU's
    frame, orientation) and the four flex sensors over the link's two virtual joints (``sensors``)."""

    def __init__(self, rig: Rig, link: str, device: str) -> None:
        robot = rig.robot
        self.rig = rig
        self.rng = rig.world.device_rng(device)  # the board's own noise
        self.frame, self.bend = robot.link_end(link)
        self.accel_spec = robot.sensors.accelerometer
        self.flex_spec = robot.sensors.flex
        self._rotations: np.ndarray | None = None  # the link end's rotation at each step of rig.recent
        self._forces: np.ndarray | None = None  # the specific force in that frame at each step
        self._done = 0  # rig.recent's steps whose rotation and force are kept
        # the first call compiles the kernel's function where numba has no cache yet (0.6 s here): now, as
        # the rig is built, not at the first sample, while the host waits for the drives' first SDO reply
        self._update()

    def _update(self) -> None:
        """The link end's rotation and the specific force in its frame at every step the rig appended since
        the last call, in one batch: computed per sample, the 1 kHz IMU was most of the rig's CPU."""
        recent = self.rig.recent
        if self._done == recent.head:
            return
        cap = recent.capacity
        if self._rotations is None:
            self._rotations, self._forces = np.zeros((cap, 3, 3)), np.zeros((cap, 3))
        # a sample reads at most capacity − 2 steps back (RecentSteps.at): the two before are the ring's
        first = recent.head - min(recent.head - self._done, cap - 2)
        steps = range(first, recent.head)
        kernel.link_end_states(self.rig.world.params, recent.q, recent.delta, recent.tip, steps, self.frame,
                               self._rotations, self._forces)  # fmt: skip
        self._done = recent.head

    def _rotation(self, step: RecentStep) -> np.ndarray:
        """The link end's rotation at ``step``."""
        self._update()
        return self._rotations[step.slot]

    def acceleration(self, t: float) -> np.ndarray:
        """Specific force (m/s², 3) at the chain's tip (link 2's end), as ``streams.accelerometer_stream``."""
        self.rig.advance(t)
        step = self.rig.recent.at(t)
        self._update()
        spec = self.accel_spec
        return sensors.accelerometer_reading(self._forces[step.slot], spec.lsb_m_s2, spec.full_scale_m_s2,
                                             spec.noise_rms_m_s2, self.rng)  # fmt: skip

    def orientation(self, t: float) -> np.ndarray:
        """(roll, pitch, yaw) of the link's end frame in the base frame (rad)."""
        self.rig.advance(t)
        return sensors.rpy_from_rotation(self._rotation(self.rig.recent.at(t)))

    def flex(self, t: float) -> np.ndarray:
        self.rig.advance(t)
        bend = self.rig.recent.at(t).delta[self.bend]
        return sensors.flex_counts(bend, self.flex_spec, self.rng)
