"""The real-time recorder: device workers → one queue → one writer thread → one MCAP session.

    with Recorder(robot, ports, sessions_dir / "s1", "s1") as rec:
        time.sleep(60)              # or run a plan; rec.snapshot() gives live counters
    # the session is closed: indexed parts, session.json with counters

The writer thread drains the queue every ``batch_s`` and writes each topic's samples as one batch; the session
writer flushes at least every ``flush_s``, so a killed recorder loses at most ``batch_s + flush_s`` of data.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from acquisition.devices.base import host_now_ns
from acquisition.recorder.workers import (
    DeviceWorker,
    PressureWorker,
    Sample,
    ServoWorker,
    StepperWorker,
    TrackerWorker,
)
from acquisition.recorder.writer import RotationPolicy, SessionWriter
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from models.robot import RobotDescription

if TYPE_CHECKING:  # the live view (foxglove) is imported only by those who use it
    from acquisition.recorder.live import LiveServer

log = logging.getLogger(__name__)


def make_workers(robot: RobotDescription, ports: dict[str, str], out: queue.Queue, stop: threading.Event,
                 servo_rate_hz: float = 550.0, board_rate_hz: int = 250) -> list[DeviceWorker]:  # fmt: skip
    """One worker per device the robot has and ``ports`` names."""
    workers: list[DeviceWorker] = []
    if "servo_bus" in ports and "servo_bus" in robot.devices:
        workers.append(ServoWorker(robot, ports["servo_bus"], servo_rate_hz, out, stop))
    if "pressure_board" in ports:
        workers.append(PressureWorker(robot, ports["pressure_board"], board_rate_hz, out, stop))
    if "stepper_board" in ports and robot.stepper is not None:
        rate = min(board_rate_hz, int(robot.stepper.report_rate_hz))
        workers.append(StepperWorker(robot, ports["stepper_board"], rate, out, stop))
    if "tracker" in ports:
        workers.append(TrackerWorker(ports["tracker"], out, stop))
    return workers


class Recorder:
    def __init__(
        self,
        robot: RobotDescription,
        ports: dict[str, str],
        directory: Path,
        session_id: str,
        protocol: str = "manual",
        metadata: dict[str, str] | None = None,
        servo_rate_hz: float = 550.0,  # margin over the 500 Hz the lab needs: other threads steal the GIL
        board_rate_hz: int = 250,
        batch_s: float = 0.1,
        flush_s: float = 0.4,
        rotation: RotationPolicy | None = None,
        queue_size: int = 200_000,
        live: LiveServer | None = None,  # started by the caller; shown what the file gets
    ) -> None:
        self.robot = robot
        # drivers stamp with the monotonic clock (no jumps within a session); the file's log times are UNIX
        # ns: monotonic + this offset, measured once and stored in the metadata
        self.unix_offset_ns = time.time_ns() - time.monotonic_ns()
        metadata = {**(metadata or {}), "host_clock": f"log_time = monotonic_ns + {self.unix_offset_ns}"}
        self.writer = SessionWriter(directory, robot, session_id, protocol, metadata, flush_s=flush_s,
                                    rotation=rotation)  # fmt: skip
        self.queue: queue.Queue[Sample] = queue.Queue(maxsize=queue_size)
        self.stop_event = threading.Event()
        self.workers = make_workers(robot, ports, self.queue, self.stop_event, servo_rate_hz, board_rate_hz)
        self.batch_s = batch_s
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._write_loop, name="session-writer", daemon=True)
        self.write_error: BaseException | None = None
        self.live = live
        self.live_errors = 0  # live-view failures: logged once, counted, never stop the recording

    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> None:
        self.writer.open()
        self.event(Event(EventKind.SESSION_START, label=self.writer.session_id))
        self._thread.start()
        # one device at a time: a slow connection (the tracker's, whose library holds the GIL) must not stall
        # the devices already streaming
        for w in self.workers:
            w.start()
            w.ready.wait(timeout=30.0)

    def worker(self, device: str) -> DeviceWorker | None:
        """The worker that owns ``device`` ("servo_bus", "pressure_board", "stepper_board", "tracker")."""
        return next((w for w in self.workers if w.device_name == device), None)

    def event(self, event: Event) -> None:
        """Mark something (plan step, payload change, note) at the current host time."""
        self.queue.put(Sample(T.EVENTS, host_now_ns(), event))

    def stop(self) -> None:
        """Stop the workers, write what they queued, close the session (summary, counters)."""
        if self._done.is_set():
            return
        self.stop_event.set()
        for w in self.workers:
            w.join(timeout=5.0)
        self.event(Event(EventKind.SESSION_END, label=self.writer.session_id))
        self._done.set()
        self._thread.join()
        for w in self.workers:
            for topic, n in w.received.items():
                self.writer.counters[topic].received = n
            for topic, n in w.dropped.items():
                self.writer.counters[topic].dropped = n
        self.writer.close()

    def snapshot(self) -> dict[str, dict[str, int]]:
        """Live counters per topic: received (workers), written (writer), dropped (queue full)."""
        out: dict[str, dict[str, int]] = defaultdict(lambda: {"received": 0, "written": 0, "dropped": 0})
        for w in self.workers:
            for topic, n in w.received.items():
                out[topic]["received"] += n
            for topic, n in w.dropped.items():
                out[topic]["dropped"] += n
        for topic, c in self.writer.counters.items():
            if c.written or topic in out:
                out[topic]["written"] = c.written
        return dict(out)

    def _write_loop(self) -> None:
        try:
            while not self._done.is_set():
                self._done.wait(self.batch_s)
                self._drain()
            self._drain()
        except BaseException as exc:  # the session must still close; the caller sees the error
            self.write_error = exc
            log.exception("session writer failed")

    def _drain(self) -> None:
        by_topic: dict[str, list[Sample]] = defaultdict(list)
        while True:
            try:
                s = self.queue.get_nowait()
            except queue.Empty:
                break
            by_topic[s.topic].append(s)
        for topic, samples in by_topic.items():
            if topic == T.EVENTS:
                for s in samples:
                    self.writer.event(s.values, s.host_ns + self.unix_offset_ns)
                    self._feed_live(topic, [s.host_ns + self.unix_offset_ns], [s.values.encode()])
                continue
            message = self.writer.topics[topic].message
            columns = {k: np.array([s.values[k] for s in samples]) for k in samples[0].values}
            log_time = np.array([s.host_ns for s in samples], dtype=np.int64) + self.unix_offset_ns
            rows = message.pack(columns, n=len(samples))
            self.writer.write(topic, log_time, rows)
            self._feed_live(topic, log_time, rows)
        self.writer.flush_if_due()

    def _feed_live(self, topic: str, log_time, messages) -> None:
        """Show what was just written in the live view, if any; its failures never reach the file."""
        if self.live is None:
            return
        try:
            self.live.publish(topic, log_time, messages)
        except Exception:
            self.live_errors += 1
            if self.live_errors == 1:
                log.exception("live view failed on %s; recording goes on without it (counted in live_errors)",
                              topic)  # fmt: skip
