"""POPUP's main board and link boards on the twin's CAN bus, sending and taking the frames of
``configs/can/popup_boards.dbc`` (``acquisition.codecs.popup_boards``).

- The **main board** (node 0x10) regulates each link's pressure with its valve group (a supply and an
  exhaust valve, normally closed) to the set-point of the last ``PressureCommand`` (a link not regulated
  holds: both valves shut), and streams both links' transducer counts with the valve states
  (``MainPressure``, at its rate) and its uptime with the number of commands it rejected (``MainStatus``,
  10 Hz). A set-point above its regulators' range is rejected: the command is ignored and counted.
- A **link board** (node 0x10 + k) streams its link's end orientation and flex sensors (at its rate) and, on
  the board that carries the arm's accelerometer, the acceleration at the IMU's output data rate.

Each stream samples on a timer of its board's own clock (``TwinBoardTimer``), numbered by it. A board that
loses power (or whose cable is cut) falls silent: its frames stop, which the host must notice.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from acquisition.codecs import popup_boards as pb
from acquisition.codecs.can import CanFrame
from acquisition.errors import CodecError
from twin.can_bus import CanNode


@dataclass
class BoardStream:
    """One timed message of a board: sample ``k`` of ``timer`` is sent at ``timer.instant(k)`` with the
    signals ``sample(t)`` returns (raw values) and Counter ``k`` modulo its width."""

    message: str
    timer: object  # TwinBoardTimer: first_after(t) → k, instant(k) → rig time
    sample: Callable[[float], dict[str, int]]
    counter_modulo: int = pb.COUNTER_MODULO
    k: int = 0
    due_s: float = 0.0  # timer.instant(k), kept with k: the bus asks for it at every event

    def start(self, t: float) -> None:
        self.k = self.timer.first_after(t)
        self.due_s = self.timer.instant(self.k)

    def next(self) -> None:
        """Sample ``k`` was sent: the next one is due."""
        self.k += 1
        self.due_s = self.timer.instant(self.k)


class BoardNode(CanNode):
    """A board sending its ``streams`` on their timers."""

    def __init__(self, name: str, streams: list[BoardStream], t0: float = 0.0) -> None:
        self.name = name
        self.streams = streams
        self.silent = False
        for s in streams:
            s.start(t0)
        self._due = min((s.due_s for s in streams), default=None)  # the bus asks at every event: kept

    def next_due_s(self) -> float | None:
        return self._due

    def produce(self, t: float) -> list[tuple[float, CanFrame]]:
        out = []
        for s in self.streams:
            while (due := s.due_s) <= t:
                signals = s.sample(due)
                signals["Counter"] = s.k % s.counter_modulo
                out.append((due, pb.encode(s.message, signals, scaling=False)))
                s.next()
        self._due = min((s.due_s for s in self.streams), default=None)
        return out

    def power(self, on: bool, t: float) -> None:
        """Cut the board's supply (silent) or restore it: its timers start again from ``t``."""
        if on and self.silent:
            for s in self.streams:
                s.start(t)
            self._due = min((s.due_s for s in self.streams), default=None)
        self.silent = not on


class MainBoard(BoardNode):
    """The main board over ``pneumatics`` (``TwinPressure``: set-points, valves, transducer counts)."""

    def __init__(self, pneumatics, pressure_timer, status_timer, max_set_pa: float, t0: float = 0.0) -> None:
        self.pneumatics = pneumatics
        self.max_set_pa = max_set_pa
        self.rejected = 0
        self.status_timer = status_timer
        streams = [BoardStream(pb.MAIN_PRESSURE, pressure_timer, self._pressure),
                   BoardStream(pb.MAIN_STATUS, status_timer, self._status, counter_modulo=256)]  # fmt: skip
        super().__init__("main board", streams, t0)
        self._command_id = pb.database().get_message_by_name(pb.PRESSURE_COMMAND).frame_id

    def _pressure(self, t: float) -> dict[str, int]:
        c1, c2 = self.pneumatics.sample(t)
        s1, e1 = self.pneumatics.valves(0, t)
        s2, e2 = self.pneumatics.valves(1, t)
        return {"Link1Counts": c1, "Link2Counts": c2, "V1Supply": int(s1), "V1Exhaust": int(e1),
                "V2Supply": int(s2), "V2Exhaust": int(e2), "Regulate1": int(self.pneumatics.regulating(0)),
                "Regulate2": int(self.pneumatics.regulating(1))}  # fmt: skip

    def _status(self, t: float) -> dict[str, int]:
        uptime_ms = int(self.status_timer.instant(self.streams[1].k) * 1000) % (1 << 32)
        return {"UptimeMs": max(uptime_ms, 0), "Rejected": self.rejected % 256}

    def receive(self, frame: CanFrame, t: float) -> list[tuple[float, CanFrame]]:
        if frame.can_id != self._command_id or frame.remote or frame.extended:
            return []
        try:
            cmd = pb.decode(frame.can_id, frame.data)
        except CodecError:
            self.rejected += 1  # a short frame: the firmware drops it
            return []
        setpoints = (cmd["Setpoint1"], cmd["Setpoint2"])
        if max(setpoints) > self.max_set_pa:
            self.rejected += 1
            return []
        self.pneumatics.advance(t)
        for channel, (pa, on) in enumerate(zip(setpoints, (cmd["Regulate1"], cmd["Regulate2"]), strict=True)):
            self.pneumatics.set_pressure(channel, float(pa))
            self.pneumatics.set_valve(channel, bool(on))
        return []


class LinkBoard(BoardNode):
    """Link board ``node_id`` over ``link`` (``TwinLinkBoard``): orientation and flex on ``timer``, and the
    acceleration on ``accel_timer`` where it carries the accelerometer (None: it sends none)."""

    def __init__(self, node_id: int, link, timer, accel_timer=None, t0: float = 0.0) -> None:
        self.link = link
        streams = [BoardStream(pb.link_message(node_id, pb.ORIENTATION), timer, self._orientation),
                   BoardStream(pb.link_message(node_id, pb.FLEX), timer, self._flex)]  # fmt: skip
        if accel_timer is not None:
            streams.insert(0, BoardStream(pb.link_message(node_id, pb.ACCEL), accel_timer, self._accel))
            self._accel_lsb = pb.scale(streams[0].message, "AccelX")
        self._angle_lsb = pb.scale(streams[-2].message, "Roll")
        super().__init__(f"link board {node_id}", streams, t0)

    def _accel(self, t: float) -> dict[str, int]:
        # the sensor's output register is 16-bit: it saturates there
        ax, ay, az = (max(-32768, min(32767, round(v / self._accel_lsb))) for v in self.link.acceleration(t))
        return {"AccelX": ax, "AccelY": ay, "AccelZ": az}

    def _orientation(self, t: float) -> dict[str, int]:
        roll, pitch, yaw = (
            max(-32768, min(32767, round(v / self._angle_lsb))) for v in self.link.orientation(t)
        )
        return {"Roll": roll, "Pitch": pitch, "Yaw": yaw}

    def _flex(self, t: float) -> dict[str, int]:
        return {f"Flex{i + 1}": int(c) for i, c in enumerate(self.link.flex(t))}
