"""Device workers: one thread per device, each owning its port, turning readings into topic samples.

A worker connects, then polls its device as fast as the device produces data (the servo bus at the Sync
Read rate it is asked for, the boards' and the tracker's own streams), stamping each sample with the host
receive time. When the device fails (unplugged, timeouts, garbage) the worker marks a gap in the events,
keeps retrying the connection with back-off and marks the gap's end when the device answers again; the other
workers never notice. Samples go to a bounded queue; a full queue drops (and counts) rather than blocks.

Commands (a plan runner's goals, set-points) go through the worker that owns the port: ``submit(action)``
queues a callable that the worker runs between two polls; what it returns (a command sample, e.g. the goals
as sent) is recorded like any other sample. Commands queued while the device is lost are dropped, counted,
and marked in the events: a stale goal must never run when the device comes back. ``latest`` holds the last
sample of each topic for the runner's safety checks and compensation.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from acquisition.devices.base import host_now_ns
from acquisition.devices.boards import PressureBoard, StepperBoard
from acquisition.devices.servo_bus import ServoBus
from acquisition.devices.tracker import Tracker
from acquisition.errors import DeviceError
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.sim import sensors  # the pressure transducer's calibration line (counts → Pa)
from acquisition.sim.streams import pressure_spec
from models.robot import RobotDescription

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Sample:
    topic: str
    host_ns: int
    values: dict | Event  # field values of the topic's message, or an event


class DeviceWorker(threading.Thread):
    """Base: ``connect``/``poll``/``disconnect`` are the device-specific parts."""

    device_name = "device"
    topic = ""

    def __init__(self, out: queue.Queue, stop: threading.Event, retry_s: float = 0.5) -> None:
        super().__init__(name=f"worker-{self.device_name}", daemon=True)
        self.out, self.stop_event, self.retry_s = out, stop, retry_s
        self.received: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self.gaps = 0
        self.ready = threading.Event()  # set after the first connection attempt, whatever its outcome
        self.error: str | None = None
        self.connected = False
        self.commands: queue.SimpleQueue[Callable[[], Sample | None]] = queue.SimpleQueue()
        self.commands_dropped = 0
        self.latest: dict[str, Sample] = {}

    def submit(self, action: Callable[[], Sample | None]) -> None:
        """Run ``action`` on this worker's thread before its next poll (it may use the device)."""
        self.commands.put(action)

    # device-specific
    def connect(self) -> None: ...
    def poll(self) -> list[Sample]: ...
    def disconnect(self) -> None: ...

    def emit(self, sample: Sample) -> None:
        self.latest[sample.topic] = sample
        self.received[sample.topic] += 1
        try:
            self.out.put_nowait(sample)
        except queue.Full:
            self.dropped[sample.topic] += 1

    def _event(self, event: Event) -> None:
        self.out.put(Sample(T.EVENTS, host_now_ns(), event))  # events are never dropped

    def run(self) -> None:
        connected = self._try_connect()
        self.ready.set()
        gap_start: float | None = None if connected else time.monotonic()
        if not connected:
            self._event(Event(EventKind.DEVICE_GAP_START, label=self.device_name, text=self.error or ""))
        while not self.stop_event.is_set():
            if gap_start is not None:
                self._run_commands()  # not connected: drops what was queued
                if self.stop_event.wait(self.retry_s) or not self._try_connect():
                    continue
                gap = time.monotonic() - gap_start
                self._event(Event(EventKind.DEVICE_GAP_END, value=gap, label=self.device_name))
                log.warning("%s back after %.1f s", self.device_name, gap)
                gap_start = None
            try:
                samples = self._run_commands() + self.poll()
            except DeviceError as exc:
                self.error = str(exc)
                self.gaps += 1
                gap_start = time.monotonic()
                log.warning("%s lost: %s", self.device_name, exc)
                self._event(Event(EventKind.DEVICE_GAP_START, label=self.device_name, text=str(exc)))
                self._safe_disconnect()
                continue
            for s in samples:
                self.emit(s)
        self._run_commands()  # a last safe stop submitted with the stop request still runs
        self._safe_disconnect()

    def _run_commands(self) -> list[Sample]:
        out = []
        while True:
            try:
                action = self.commands.get_nowait()
            except queue.Empty:
                return out
            if not self.connected:
                self.commands_dropped += 1
                self._event(Event(EventKind.NOTE, label=self.device_name, text="command dropped: no device"))
                continue
            sample = action()
            if sample is not None:
                out.append(sample)

    def _try_connect(self) -> bool:
        try:
            self.connect()
            self.connected = True
            return True
        except DeviceError as exc:
            self.error = str(exc)
            self._safe_disconnect()
            return False

    def _safe_disconnect(self) -> None:
        self.connected = False
        try:
            self.disconnect()
        except DeviceError:
            pass


class ServoWorker(DeviceWorker):
    """Sync Reads of every servo at ``rate_hz`` (paced on the host clock)."""

    device_name = "servo_bus"

    def __init__(self, robot: RobotDescription, port: str, rate_hz: float, out, stop) -> None:
        super().__init__(out, stop)
        ids = robot.devices["servo_bus"].ids
        self.bus = ServoBus(port, ids=list(ids.values()), zero_count=robot.servo.zero_count)
        self.period = 1.0 / rate_hz
        self.seq = 0
        self._next = time.perf_counter()

    def connect(self) -> None:
        self.bus.open()

    def disconnect(self) -> None:
        self.bus.close()

    def poll(self) -> list[Sample]:
        delay = self._next - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        # catch up after a stall (another thread held the GIL) by polling back to back, but never burst
        # more than 50 ms of polls
        self._next = max(self._next + self.period, time.perf_counter() - 0.05)
        st = self.bus.read_state()
        self.seq += 1
        values = {
            "seq": self.seq, "tick_ms": int(st.tick_ms[0]), "position": st.position_rad,
            "velocity": st.velocity_rad_s, "current": st.current_a, "moving": st.moving,
        }  # fmt: skip
        return [Sample(T.SERVO_STATE, st.host_ns, values)]


class _StreamingBoardWorker(DeviceWorker):
    board_type: type = PressureBoard

    def __init__(self, port: str, rate_hz: int, out, stop) -> None:
        super().__init__(out, stop)
        self.board = self.board_type(port)
        self.rate_hz = rate_hz

    def connect(self) -> None:
        self.board.open()
        self.board.start_stream(self.rate_hz)

    def disconnect(self) -> None:
        self.board.close()

    def poll(self) -> list[Sample]:
        samples = self.board.read_samples()
        if not samples:
            time.sleep(0.001)  # the board's lines arrive every few ms: read them close to arrival
        return [self.to_sample(s) for s in samples]


class PressureWorker(_StreamingBoardWorker):
    device_name = "pressure_board"
    board_type = PressureBoard

    def __init__(self, robot: RobotDescription, port: str, rate_hz: int, out, stop) -> None:
        super().__init__(port, rate_hz, out, stop)
        self.spec = pressure_spec(robot)
        self.channels = robot.pneumatics.channels

    def to_sample(self, s) -> Sample:
        counts = np.asarray(s.counts)
        values = {
            "seq": s.seq, "micros": s.micros, "counts": counts,
            "pressure": sensors.adc_counts_to_pressure(counts, self.spec),
            "valve_open": [(s.valves >> c) & 1 == 1 for c in range(self.channels)],
        }  # fmt: skip
        return Sample(T.PRESSURE, s.host_ns, values)


class StepperWorker(_StreamingBoardWorker):
    device_name = "stepper_board"
    board_type = StepperBoard

    def __init__(self, robot: RobotDescription, port: str, rate_hz: int, out, stop) -> None:
        super().__init__(port, rate_hz, out, stop)
        self.rad_per_step = robot.stepper.rad_per_microstep

    def to_sample(self, s) -> Sample:
        values = {
            "seq": s.seq or 0, "micros": s.micros, "position_steps": [s.position_steps],
            "position": [s.position_steps * self.rad_per_step], "moving": s.moving,
        }  # fmt: skip
        return Sample(T.STEPPER, s.host_ns, values)


class TrackerWorker(DeviceWorker):
    """Every new tracker frame (the Aurora's 40 Hz), polled a little faster than it produces them."""

    device_name = "tracker"

    def __init__(self, port: str, out, stop) -> None:
        super().__init__(out, stop)
        self.tracker = Tracker(port)
        self.last_frame: int | None = None

    def connect(self) -> None:
        self.tracker.open()

    def disconnect(self) -> None:
        self.tracker.close()

    def poll(self) -> list[Sample]:
        out = []
        for f in self.tracker.read_all():
            if f.frame == self.last_frame:
                continue
            self.last_frame = f.frame
            values = {
                "frame": f.frame % 2**32, "port_handle": f.port_handle, "port_status": f.port_status,
                "missing": f.missing, "position": f.position_m, "quaternion": f.quaternion,
                "rms_error": f.rms_error,
            }  # fmt: skip
            out.append(Sample(T.TRACKER, f.host_ns, values))
        # ndicapy holds the GIL during its serial transaction (~ms): poll about twice per 40 Hz frame, not
        # in a tight loop, so the servo worker keeps its rate
        time.sleep(0.012)
        return out
