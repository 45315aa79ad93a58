"""POPUP's CAN bus as one recorded device: the CiA 402 joint drives, the main board and the link boards,
all through one USB-CAN adapter (driver ``popup_can``; the boards are the devices whose ``bus`` names it).

Polled at the bus's SYNC rate: each slot sends one SYNC and records what the drives answered to the previous
one (``/joint/state``, numbered by that SYNC; the SYNC waits up to a period for late answers, and a SYNC not
every drive answered is a hole in the numbers, counted lost), then every board frame that arrived (link
pressures, the tip IMU's acceleration, each link's orientation and flex sensors), numbered by the boards' own
counters.

The drives run in cyclic synchronous position mode, which expects the host to interpolate: a goal is not sent
as one jump (the drive would fault on its following error) but approached at its profile velocity, one step
per SYNC. The safe state holds the joints where they were last measured and leaves the pressures as they are
(an inflatable arm must not be vented under load).
"""

from __future__ import annotations

import logging

import numpy as np

from acquisition.codecs import popup_boards as pb
from acquisition.devices.base import host_now_ns
from acquisition.devices.can_drives import CanDrives
from acquisition.devices.kinds import device_of, kind_of
from acquisition.devices.popup_boards import BoardFrames, BoardSample
from acquisition.recorder.source_base import Row, Source
from acquisition.schemas import topic_rows as R
from acquisition.schemas import topics as T

log = logging.getLogger(__name__)


class PopupCanSource(Source):
    driver = "popup_can"

    def __init__(self, robot, name, spec, port, rate_hz) -> None:
        boards = {n: d for n, d in robot.devices.items() if d.bus == name}
        self.main = next((n for n, d in boards.items() if kind_of(robot, n).role == "pressure"), None)
        accel_board = device_of(robot, "accelerometer")
        # every board message recorded → (its topic, its period on its board's clock: the sample number
        # times it is the board's micros); and each board's slowest period (how long it may stay silent)
        self.board_streams: dict[str, tuple[str, float]] = {}
        slowest_s = {}
        for board, dev in boards.items():
            node, period_us = dev.ids["board"], 1e6 / dev.rate_hz
            if board == self.main:
                self.board_streams[pb.MAIN_PRESSURE] = (T.PRESSURE, period_us)
                slowest_s[board] = pb.STATUS_PERIOD_S
                continue
            if board == accel_board:
                odr_us = 1e6 / robot.sensors.accelerometer.sample_rate_hz
                self.board_streams[pb.link_message(node, pb.ACCEL)] = (T.ACCEL, odr_us)
            self.board_streams[pb.link_message(node, pb.ORIENTATION)] = (T.link_orientation_topic(dev.link),
                                                                         period_us)  # fmt: skip
            self.board_streams[pb.link_message(node, pb.FLEX)] = (T.link_flex_topic(dev.link), period_us)
            slowest_s[board] = 1.0 / dev.rate_hz
        self.sampled_topics = (T.JOINT_STATE, *(topic for topic, _ in self.board_streams.values()))
        self.command_topics = (T.SERVO_GOAL, T.PRESSURE_COMMAND) if self.main else (T.SERVO_GOAL,)
        super().__init__(robot, name, spec, port, rate_hz)
        self.joints = list(spec.ids)
        limits = {j.name: (j.lower_rad, j.upper_rad) for j in robot.joints if j.name in spec.ids}
        self.drives = CanDrives(port, spec.ids, limits, bitrate=spec.baud, sync_period_s=1.0 / self.rate_hz)
        self.boards = BoardFrames({n: d.ids["board"] for n, d in boards.items()}, slowest_s)
        self.calibration = robot.sensors.pressure
        self.position: np.ndarray | None = None  # last measured joint angles: where a hold holds
        self.target: np.ndarray | None = None  # the CSP target sent at the last SYNC
        self.goal: np.ndarray | None = None  # where the targets are heading
        self.speed = np.zeros(len(self.joints))
        self.first_sync = 0

    @property
    def sampled_rates_hz(self) -> dict[str, float]:
        """The joint states at the SYNC rate; each board stream at its own (the accelerometer at 1 kHz)."""
        boards = {topic: 1e6 / period_us for topic, period_us in self.board_streams.values()}
        return {T.JOINT_STATE: self.rate_hz, **boards}

    # ---------------------------------------------------------------------------------- lifecycle
    def open(self) -> None:
        self.drives.open()
        self.boards.attach(self.drives.network)
        cycles = self.drives.enable()
        self.position = np.asarray(cycles[-1].position_rad, float) if cycles else None
        self.target = self.goal = None if self.position is None else self.position.copy()
        self.first_sync = self.drives.syncs  # the SYNCs before were enabling's: their answers are not samples

    def close(self) -> None:
        self.boards.detach()
        self.drives.close()

    # ------------------------------------------------------------------------------------ reading
    def read(self, slot: int) -> list[Row]:
        self.boards.check()
        self._interpolate()
        # a SYNC waits up to a period past its slot for the last one's answers (see CanDrives.sync); one
        # some drive left unanswered past that is no joint state: a hole in the sequence numbers, counted
        # lost (a joint-state vector with a drive missing is not a sample)
        cycle = self.drives.sync(wait_s=2.0 / self.rate_hz)
        if cycle is not None and not cycle.answered.all():
            log.info("%s: SYNC %d not answered by every drive", self.name, cycle.sync)
        rows = []
        if cycle is not None and cycle.sync >= self.first_sync and cycle.answered.all():
            self.position = cycle.position_rad
            values = R.joint_state(cycle.sync, cycle.position_rad, cycle.velocity_rad_s, cycle.torque_nm,
                                   cycle.statusword)  # fmt: skip
            rows.append(self.row(T.JOINT_STATE, cycle.host_ns, cycle.sync, **values))
        rows += [r for s in self.boards.take() if (r := self._board_row(s)) is not None]
        return rows

    def _board_row(self, s: BoardSample) -> Row | None:
        stream = self.board_streams.get(s.message)
        if stream is None:
            return None  # MainStatus: the board's uptime and rejected commands (not a sampled stream)
        topic, period_us = stream
        sig = s.signals
        micros = round(s.seq * period_us) % (1 << 32)
        if topic == T.PRESSURE:
            counts = np.array([sig["Link1Counts"], sig["Link2Counts"]])
            valves = [bool(sig["Regulate1"]), bool(sig["Regulate2"])]
            values = R.pressure(self.calibration, s.seq, micros, counts, valves)
        elif topic == T.ACCEL:
            values = R.acceleration(s.seq, micros, [sig["AccelX"], sig["AccelY"], sig["AccelZ"]])
        elif topic.endswith("/orientation"):
            values = R.link_orientation(s.seq, micros, [sig["Roll"], sig["Pitch"], sig["Yaw"]])
        else:
            values = R.link_flex(s.seq, micros, [sig[f"Flex{i}"] for i in range(1, 5)])
        return self.row(topic, s.host_ns, s.seq, **values)

    def _interpolate(self) -> None:
        """Move the CSP targets one SYNC period toward the goals at their profile speeds."""
        if self.goal is None or self.target is None or np.array_equal(self.target, self.goal):
            return
        step = self.speed / self.rate_hz
        self.target = self.target + np.clip(self.goal - self.target, -step, step)
        self.drives.write_goals(self.target)

    # ----------------------------------------------------------------------------------- commands
    def command(self, cmd: dict) -> list[Row]:
        op = cmd["op"]
        if op == "torque":  # the drives were enabled when the bus opened; disabling is the close
            return []
        if op == "goals":
            position, velocity = self.guard.servo_goals(self.joints, cmd["position"], cmd["profile_velocity"])
            self.speed = np.where(velocity > 0, velocity, self.robot.servo.max_speed_rad_s)
            self.goal = position
            if self.target is None:
                self.target = self.position.copy() if self.position is not None else position.copy()
            return [self.row(T.SERVO_GOAL, host_now_ns(), None, seq=int(cmd.get("seq", 0)), position=position,
                             profile_velocity=velocity, profile_acceleration=0.0)]  # fmt: skip
        if op == "pressures" and self.main:
            setpoint, valves = self.guard.pressures(cmd["setpoint"], cmd["valve_open"])
            self.boards.send_pressures(setpoint.tolist(), valves.tolist())
            sent = dict(seq=int(cmd.get("seq", 0)), setpoint=setpoint, valve_open=valves)
            return [self.row(T.PRESSURE_COMMAND, host_now_ns(), None, **sent)]
        if op == "hold":
            self.safe()
            return []
        return super().command(cmd)

    def safe(self) -> None:
        if self.position is not None and self.drives.network is not None:
            self.goal = self.target = self.position.copy()
            self.drives.write_goals(self.position)
