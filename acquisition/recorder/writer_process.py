"""The writer process: the only process that writes a recording's MCAP files.

    python -m acquisition.recorder.writer_process RUN_DIR/layout.json --commands FD [--restarted]

Every ``batch_s`` it takes what the device daemons (and the supervisor's events) put into the rings and
writes each topic as one batch through :class:`SessionWriter`; every ``flush_s`` it makes what it wrote
durable (closes the chunk into the file) and only then counts it written. So a killed writer loses at most
``batch_s + flush_s`` of each stream, and its successor (``--restarted``) counts that loss as dropped and
goes on in a new part. ``session.json`` is rewritten every second with every stream's account.

A ``stop`` on its command socket (the supervisor's ordered stop, after the daemons), the socket's end of file
(the supervisor died) or SIGTERM finishes the session: wait up to ``DAEMON_GRACE_S`` for daemons still
running to leave their devices safe and close, write what they left, and close the file with its summary
and indexes.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import select
import shutil
import signal
import socket
import sys
import time
from pathlib import Path

import numpy as np

from acquisition.processes import parent_alive, settle_heap
from acquisition.recorder.layout import Layout
from acquisition.recorder.ring import Ring
from acquisition.recorder.status import DaemonStatus, Phase
from acquisition.recorder.writer import RotationPolicy, SessionWriter, WriteFailed
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.topics import EVENTS
from models.robot import RobotDescription

log = logging.getLogger(__name__)

DAEMON_GRACE_S = 1.0
CARD_EVERY_S = 1.0
WRITER_FAILED = 3  # exit status of a writer that could not write (a full disk): not restarted


class WriterProcess:
    def __init__(
        self, layout: Layout, commands: socket.socket | None = None, restarted: bool = False
    ) -> None:
        self.layout = layout
        self.commands = commands
        self.supervisor_gone = False
        robot = RobotDescription.model_validate_json(layout.robot_json)
        self.writer = SessionWriter(
            layout.session_dir, robot, layout.session_id, layout.experiment,
            {**layout.metadata, "host_clock": f"log_time = monotonic_ns + {layout.unix_offset_ns}"},
            flush_s=float("inf"),  # this process decides when to flush (and then counts written)
            rotation=RotationPolicy(layout.rotate_bytes, layout.rotate_seconds),
            resume=restarted,
        )  # fmt: skip
        self.messages = {name: t.message for name, t in self.writer.topics.items() if t.message is not None}
        self.rings = {
            topic: Ring.attach(layout.ring(topic))
            for entry in layout.devices.values()
            for topic in entry.topics
        }
        self.event_rings = {p: Ring.attach(layout.events(p)) for p in layout.producers}
        self.statuses = {name: DaemonStatus.attach(layout.status(name)) for name in layout.devices}
        self.pending: dict[str, int] = dict.fromkeys(self.rings, 0)
        self.unwritten_events = 0  # events taken from their rings, not yet written
        self.stopping = False
        if restarted:
            for ring in self.rings.values():
                ring.note_writer_lost()

    def serve(self) -> int:
        """Write until stopped: 0, or WRITER_FAILED once a write failed (the session then ended, marked)."""
        try:
            self._serve()
        except WriteFailed as exc:
            self.failed(str(exc))
            return WRITER_FAILED
        return 0

    def failed(self, reason: str) -> None:
        """The session could not be written: say so to the supervisor (it stops the devices), then take
        what the daemons still send and count it dropped, until stopped; the account adds up."""
        log.error("the session writer failed: %s", reason)
        if self.commands is not None:
            try:
                self.commands.sendall(json.dumps({"op": "failed", "reason": reason}).encode() + b"\n")
            except OSError:
                self.supervisor_gone = self.stopping = True
        while not self.stopping:
            self.discard()
            self._wait(self.layout.batch_s)
        deadline = time.monotonic() + DAEMON_GRACE_S
        while time.monotonic() < deadline and not all(self._daemon_done(s) for s in self.statuses.values()):
            self.discard()
            time.sleep(0.02)
        self.discard()
        self.sync_counters()
        self.writer.close()  # session.json: failed, its reason and this account, where the disk takes it
        if self.supervisor_gone:
            shutil.rmtree(self.layout.run_dir, ignore_errors=True)

    def discard(self) -> None:
        """Take every ring's records and count those never written as dropped (nothing can write them)."""
        for ring in self.rings.values():
            ring.take()
            ring.note_writer_lost()
        events = self.unwritten_events + sum(len(ring.take()[0]) for ring in self.event_rings.values())
        if events:
            self.writer.note_received(EVENTS, events)
            self.writer.note_dropped(EVENTS, events)
        self.pending, self.unwritten_events = dict.fromkeys(self.rings, 0), 0

    def _serve(self) -> None:
        self.writer.open()
        settle_heap()  # a full collection later would stall the drain (the rings then fill)
        last_flush = last_card = time.monotonic()
        while not self.stopping:
            started = time.monotonic()
            self.drain()
            if started - last_flush >= self.layout.flush_s:
                self.flush()
                last_flush = started
            if started - last_card >= CARD_EVERY_S:
                self.sync_counters()
                self.writer.write_card()
                last_card = started
            self._wait(max(0.0, self.layout.batch_s - (time.monotonic() - started)))
        self.finish()

    def _wait(self, timeout_s: float) -> None:
        """Sleep until the next batch, or until the supervisor says stop (or dies: end of file)."""
        if self.commands is None:
            time.sleep(timeout_s)
        elif select.select([self.commands], [], [], timeout_s)[0]:
            data = self.commands.recv(4096)
            self.supervisor_gone = not data
            self.stopping = not data or any(
                json.loads(line).get("op") == "stop" for line in data.splitlines()
            )
        if not parent_alive(self.layout.parent_pid):
            self.supervisor_gone = self.stopping = True

    def drain(self) -> None:
        offset = self.layout.unix_offset_ns
        for topic, ring in self.rings.items():
            host_ns, _, payload = ring.take()
            if len(host_ns) == 0:
                continue
            message = self.messages[topic]
            rows = np.ascontiguousarray(payload[:, : message.size]).view(message.dtype).reshape(-1)
            self.writer.write(topic, host_ns + offset, rows)
            self.pending[topic] += len(host_ns)
        events = []
        for ring in self.event_rings.values():
            host_ns, lengths, payload = ring.take()
            events += [
                (int(t), bytes(payload[i, :n])) for i, (t, n) in enumerate(zip(host_ns, lengths, strict=True))
            ]
        self.unwritten_events = len(events)
        for t, data in sorted(events, key=lambda e: e[0]):
            self.writer.event(Event.decode(data), t + offset)
            self.unwritten_events -= 1

    def flush(self) -> None:
        self.writer.flush()
        for topic, n in self.pending.items():
            if n:
                self.rings[topic].note_written(n)
        self.pending = dict.fromkeys(self.rings, 0)

    def sync_counters(self) -> None:
        """The session's account of each stream, from the rings (cumulative over daemon and writer
        restarts); a command topic expects what was sent."""
        for topic, ring in self.rings.items():
            c, counts = self.writer.counters[topic], ring.counts()
            c.received, c.written, c.dropped, c.gaps = (
                counts.received,
                counts.written,
                counts.dropped,
                counts.gaps,
            )
            sampled = any(topic in e.sampled for e in self.layout.devices.values())
            c.expected, c.lost = (counts.expected, counts.lost) if sampled else (counts.received, 0)

    def finish(self) -> None:
        deadline = time.monotonic() + DAEMON_GRACE_S
        while time.monotonic() < deadline and not all(self._daemon_done(s) for s in self.statuses.values()):
            self.drain()
            time.sleep(0.02)
        self.drain()
        if self.supervisor_gone:
            text = "the supervisor died: daemons left their devices safe, the writer closed the session"
            self.writer.event(Event(EventKind.SESSION_END, label=self.layout.session_id, text=text),
                              time.monotonic_ns() + self.layout.unix_offset_ns)  # fmt: skip
        self.flush()
        self.sync_counters()
        self.writer.close()
        if self.supervisor_gone:  # nobody else is left to remove the rings
            shutil.rmtree(self.layout.run_dir, ignore_errors=True)

    @staticmethod
    def _daemon_done(status: DaemonStatus) -> bool:
        if status.phase == Phase.CLOSED or status.pid <= 0:
            return True
        try:
            os.kill(status.pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:
            pass
        return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("layout", type=Path)
    parser.add_argument("--commands", type=int, help="file descriptor of the command socket (the lifeline)")
    parser.add_argument("--restarted", action="store_true")
    args = parser.parse_args(argv)
    layout = Layout.load(args.layout)
    layout.log("writer").parent.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(filename=layout.log("writer"), level=logging.WARNING,
                        format="%(asctime)s %(process)d %(levelname)s %(message)s")  # fmt: skip
    commands = None if args.commands is None else socket.socket(fileno=args.commands)
    process = WriterProcess(layout, commands, restarted=args.restarted)

    def stop(*_: object) -> None:
        process.stopping = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        return process.serve()
    except Exception:
        log.exception("the session writer failed")
        raise


if __name__ == "__main__":
    sys.exit(main())
