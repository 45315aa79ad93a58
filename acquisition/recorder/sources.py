"""How each kind of device is acquired: the part of a device daemon that knows its driver.

A source wraps one driver (``acquisition/devices``) and turns its readings into rows of the session's
topics, stamped with the host receive time and numbered (a poll slot, or the device's own sequence or
frame counter, which is how lost samples are counted). It accepts the commands that device takes (goals,
set-points, valves, moves) once the command guard (:mod:`acquisition.command_guard`) has passed them — this
process owns the port, so nothing reaches the device without that check — returns the rows that record them
as sent, and knows the device's safe state
(servos hold where they are, the stepper stops, pressures stay: an inflatable arm must not be vented under
load). A source belongs to its device kind (:mod:`acquisition.devices.kinds`, found by the driver name the
robot description gives each device, ``devices.<name>.driver``), which names it: nothing here lists them.

Two ways of reading: a **polled** source is read once per slot of a host schedule at ``rate_hz`` (the servo
bus's Sync Reads; the tracker, polled faster than its frames); a **streamed** source has a file descriptor
that becomes readable when the device sends (the boards' sample lines).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np

from acquisition.devices.base import host_now_ns
from acquisition.devices.boards import PressureBoard, StepperBoard
from acquisition.devices.bus_budget import AURORA_POLLS_PER_FRAME, reply_timeout_s
from acquisition.devices.servo_bus import ServoBus
from acquisition.devices.tracker import Tracker
from acquisition.recorder.source_base import SEQ_MODULO, Row, Source, make_source
from acquisition.schemas import topic_rows as R
from acquisition.schemas import topics as T

__all__ = ["SEQ_MODULO", "Row", "Source", "make_source"]


# ------------------------------------------------------------------------------------------ servos
class ServoSource(Source):
    """The Dynamixel bus: one Sync Read of every servo per slot; goals in one Sync Write."""

    driver = "dynamixel"
    slot_numbered = True
    sampled_topics = (T.SERVO_STATE,)
    command_topics = (T.SERVO_GOAL,)

    def __init__(self, robot, name, spec, port, rate_hz) -> None:
        super().__init__(robot, name, spec, port, rate_hz)
        self.bus = ServoBus(
            port, ids=list(spec.ids.values()), baud=spec.baud, zero_count=robot.servo.zero_count,
            reply_timeout_s=reply_timeout_s(spec.host_link.latency_timer_s),  # the adapter holds replies
        )  # fmt: skip
        self.joints = list(spec.ids)  # joint names in the bus's id order (the goals' order)
        self.position: np.ndarray | None = None  # the last position read: where a hold holds

    def open(self) -> None:
        self.bus.open()

    def close(self) -> None:
        self.bus.close()

    def read(self, slot: int) -> list[Row]:
        st = self.bus.read_state()
        self.position = st.position_rad
        values = R.servo_state(slot, int(st.tick_ms[0]), st.position_rad, st.velocity_rad_s, st.current_a,
                               st.moving)  # fmt: skip
        return [self.row(T.SERVO_STATE, st.host_ns, slot, **values)]

    def command(self, cmd: dict) -> list[Row]:
        op = cmd["op"]
        if op == "torque":
            self.bus.set_torque(bool(cmd["on"]))
            return []
        if op == "goals":
            position, velocity = self.guard.servo_goals(self.joints, cmd["position"], cmd["profile_velocity"])
            self.bus.set_profile_velocity(velocity)
            self.bus.write_goals(position)
            return [self.row(T.SERVO_GOAL, host_now_ns(), None, seq=int(cmd.get("seq", 0)), position=position,
                             profile_velocity=velocity, profile_acceleration=0.0)]  # fmt: skip
        if op == "hold":
            self.safe()
            return []
        return super().command(cmd)

    def safe(self) -> None:
        if self.position is not None:
            self.bus.write_goals(self.position)


# ------------------------------------------------------------------------------------------- boards
class _BoardSource(Source):
    polled = False
    board_type: ClassVar[type] = PressureBoard

    def __init__(self, robot, name, spec, port, rate_hz) -> None:
        super().__init__(robot, name, spec, port, rate_hz)
        self.board = self.board_type(port, baud=spec.baud)

    def open(self) -> None:
        self.board.open()
        self.board.start_stream(round(self.rate_hz))

    def close(self) -> None:
        self.board.close()

    def fileno(self) -> int:
        return self.board.fileno()

    def read(self, slot: int) -> list[Row]:
        return [self.sample_row(s) for s in self.board.read_samples()]

    def sample_row(self, sample) -> Row:
        raise NotImplementedError


class PressureSource(_BoardSource):
    """The pressure board (Uno): streamed transducer counts, converted with the robot's calibration."""

    driver = "vslab_pressure_board"
    sampled_topics = (T.PRESSURE,)
    command_topics = (T.PRESSURE_COMMAND,)
    board_type = PressureBoard

    def __init__(self, robot, name, spec, port, rate_hz) -> None:
        super().__init__(robot, name, spec, port, rate_hz)
        self.calibration = robot.sensors.pressure
        self.channels = robot.pneumatics.channels

    def sample_row(self, s) -> Row:
        valves = [(s.valves >> c) & 1 == 1 for c in range(self.channels)]
        values = R.pressure(self.calibration, s.seq, s.micros, s.counts, valves)
        return self.row(T.PRESSURE, s.host_ns, s.seq, **values)

    def command(self, cmd: dict) -> list[Row]:
        if cmd["op"] != "pressures":
            return super().command(cmd)
        setpoint, valves = self.guard.pressures(cmd["setpoint"], cmd["valve_open"])
        for ch, (pa, open_) in enumerate(zip(setpoint, valves, strict=True)):
            self.board.set_pressure(ch, float(pa))
            self.board.set_valve(ch, bool(open_))
        sent = dict(seq=int(cmd.get("seq", 0)), setpoint=setpoint, valve_open=valves)
        return [self.row(T.PRESSURE_COMMAND, host_now_ns(), None, **sent)]


class StepperSource(_BoardSource):
    """The stepper board (Nano): streamed position reports; moves; STOP as the safe state."""

    driver = "vslab_stepper_board"
    sampled_topics = (T.STEPPER,)
    board_type = StepperBoard

    def __init__(self, robot, name, spec, port, rate_hz) -> None:
        super().__init__(robot, name, spec, port, rate_hz)
        self.rad_per_step = robot.stepper.rad_per_microstep
        self.joint = next(j.name for j in robot.joints if j.drive == "stepper")

    def sample_row(self, s) -> Row:
        values = R.stepper(self.rad_per_step, s.seq or 0, s.micros, [s.position_steps], s.moving)
        return self.row(T.STEPPER, s.host_ns, s.seq, **values)

    def command(self, cmd: dict) -> list[Row]:
        if cmd["op"] == "move":
            steps, speed, accel = self.guard.stepper_move(
                self.joint, cmd["steps"], cmd["speed"], cmd["accel"]
            )
            self.board.set_speed(speed, accel)
            self.board.move_to(steps)
            return []
        if cmd["op"] == "stop":
            self.board.stop()
            return []
        return super().command(cmd)

    def safe(self) -> None:
        self.board.stop()


# ------------------------------------------------------------------------------------------ tracker
class TrackerSource(Source):
    """The NDI Aurora: polled a little faster than its frames (``rate_hz`` is its frame rate); each new
    frame is kept once, numbered by the tracker's frame counter."""

    driver = "ndi_aurora"
    sampled_topics = (T.TRACKER,)
    POLLS_PER_FRAME = AURORA_POLLS_PER_FRAME  # the link's budget counts the same polls

    def __init__(self, robot, name, spec, port, rate_hz) -> None:
        super().__init__(robot, name, spec, port, rate_hz)
        self.tracker = Tracker(port)
        self.last_frame: int | None = None

    @property
    def poll_hz(self) -> float:
        return self.rate_hz * self.POLLS_PER_FRAME

    def open(self) -> None:
        self.tracker.open()
        self.last_frame = None

    def close(self) -> None:
        self.tracker.close()

    def read(self, slot: int) -> list[Row]:
        out = []
        for f in self.tracker.read_all()[:1]:  # the tip coil: the first wired tool
            if f.frame == self.last_frame:
                continue
            self.last_frame = f.frame
            values = R.tracker(f.frame, f.port_handle, f.port_status, f.missing, f.position_m, f.quaternion,
                               f.rms_error)  # fmt: skip
            out.append(self.row(T.TRACKER, f.host_ns, f.frame % SEQ_MODULO, **values))
        return out
