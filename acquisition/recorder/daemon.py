"""A device daemon: one OS process owning one device's port, streaming its samples into shared rings.

    python -m acquisition.recorder.daemon RUN_DIR/layout.json DEVICE --commands FD [--restarted]
    python -m acquisition.recorder.daemon RUN_DIR/layout.json --spare --commands FD

Started (and restarted) by the recorder's supervisor. A spare (``--spare``) does a daemon's start-up — the
imports, the robot description, the start-up heap collected — then waits on its command socket for the
device it is to take over (``{"op": "become", "device": …}``): the supervisor keeps one ready, so a daemon
that dies is replaced in the time its device takes to connect, not the half to one second a new Python
process takes to import on a busy 2-core computer (measured 0.65–0.86 s from a SIGKILL to the new
daemon's first word). It is connected to no device until then.

A daemon connects, then reads its device at its rate — a polled device once per slot of the session's schedule
(slot k is due at ``t0 + k / rate``), a streamed one whenever its port has data — stamps each sample with the
host receive time and puts it in the ring of its topic, counting what the device should have given against
what it gave (``Ring.account``). Commands arrive on a socket (one JSON object a line) and are carried out
between two reads; the rows that record them as sent go into the rings too.

Failures: a read that times out is retried in place (the slot is then lost, and counted); only a device
silent for ``stale_s`` (or gone: unplugged, I/O error) is closed and reconnected, with the gap marked in the
events. A poll that falls behind (the computer was busy) catches up back to back for up to ``MAX_LAG_S``;
slots older than that are skipped and counted lost. When the supervisor dies (SIGKILL included) the daemon
sees its command socket close (the kernel closes the supervisor's end with the process: the socket is the
lifeline, at once and whichever thread started the daemon), leaves its device safe and exits; SIGTERM does
the same; a ``stop`` command ends it without touching the device.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import select
import signal
import socket
import sys
import time
from pathlib import Path

from acquisition.command_guard import CommandRefused
from acquisition.errors import DeviceDisconnectedError, DeviceError, DeviceNotFoundError, DeviceReplyError
from acquisition.processes import elevate, parent_alive, relinquish, settle_heap
from acquisition.recorder.layout import Layout
from acquisition.recorder.ring import Ring
from acquisition.recorder.source_base import SEQ_MODULO, Row, Source, make_source, source_class
from acquisition.recorder.status import DaemonStatus, Phase
from acquisition.schemas.events import Event, EventKind
from models.robot import RobotDescription

log = logging.getLogger(__name__)

MAX_LAG_S = 0.05  # a polled daemon catches up on at most this much of its schedule
IDLE_S = 0.05  # longest wait between two loops (heartbeat, parent check, stale check)
RETRY_S = 0.2  # between two reconnection attempts
EVENT_BYTES = 512  # slot size of the events rings


def push_event(ring: Ring, event: Event, host_ns: int | None = None) -> None:
    """Put one event into an events ring (its text cut to fit a slot)."""
    data = event.encode()
    if len(data) > ring.payload_size:
        cut = max(0, len(event.text) - (len(data) - ring.payload_size) - 4)
        data = Event(event.kind, event.index, event.value, event.label[:64], event.text[:cut]).encode()
    ring.put(time.monotonic_ns() if host_ns is None else host_ns, data)


class Daemon:
    def __init__(self, layout: Layout, device: str, source: Source, commands: socket.socket,
                 restarted: bool = False) -> None:  # fmt: skip
        self.layout, self.device, self.source = layout, device, source
        self.rings = {topic: Ring.attach(layout.ring(topic)) for topic in source.topics}
        self.events = Ring.attach(layout.events(device))
        self.status = DaemonStatus.attach(layout.status(device))
        self.commands = commands
        self.commands.setblocking(False)
        self._inbox = b""
        self.sampled = set(layout.devices[device].sampled)
        self.rate_hz = source.rate_hz
        self.period_ns = int(1e9 / source.poll_hz)
        self.max_lag = max(1, int(MAX_LAG_S * source.poll_hz))
        self.stale_ns = int(max(layout.stale_s, 5.0 / source.rate_hz) * 1e9)
        self.next_slot: int | None = None
        self.connected = False
        self.gap_start_ns: int | None = time.monotonic_ns() if restarted else None  # the supervisor marked it
        self.last_ok_ns = 0
        self.stopping = False  # "stop" command: end, leave the device as it is
        self.terminating = False  # SIGTERM (the supervisor died or killed us): leave the device safe
        self._next_parent_check = 0

    # --------------------------------------------------------------------------------------- loop
    def serve(self) -> None:
        self.status.begin()
        settle_heap()  # the imports' heap, before any device is open
        # elevated before connecting: a bus that carries frames all the time (POPUP's CAN) must be read as
        # fast as it comes while the drives are configured, or their SDO answers wait behind it and time out
        self.status.priority = elevate()
        self.status.phase = Phase.CONNECTING
        while not (self.stopping or self.terminating):
            now = time.monotonic_ns()
            self.status.beat(now)
            self._check_parent(now)
            if not self.connected:
                if not self._connect():
                    self._wait(RETRY_S)
                continue
            try:
                if self.source.polled:
                    self._poll(now)
                else:
                    self._stream(now)
            except DeviceError as exc:
                self._lose(str(exc))
        self._finish()

    def _poll(self, now: int) -> None:
        slot_now = (now - self.layout.t0_ns) // self.period_ns
        if self.next_slot is None:
            self.next_slot = slot_now
        if self.next_slot > slot_now:  # not due: wait for it (or a command)
            due = self.layout.t0_ns + self.next_slot * self.period_ns
            self._wait(min(IDLE_S, (due - now) / 1e9))
            return
        self._wait(0.0)  # a device whose exchanges fill its slots never leaves time to wait: commands now
        if self.stopping or self.terminating:
            return
        late_ns = now - (self.layout.t0_ns + self.next_slot * self.period_ns)
        self.status.behind(late_ns)
        if slot_now - self.next_slot > self.max_lag:  # too far behind: those slots are lost
            self.next_slot = slot_now
        slot, self.next_slot = self.next_slot, self.next_slot + 1
        try:
            rows = self.source.read(slot)
        except (DeviceDisconnectedError, DeviceNotFoundError):
            raise
        except DeviceReplyError as exc:  # the device is there and says it failed (a drive's EMCY)
            self._fault(str(exc))
            return
        except DeviceError as exc:  # a timeout or a corrupted reply: retried in place next slot
            if now - self.last_ok_ns > self.stale_ns:
                raise
            log.info("%s: slot %d lost: %s", self.device, slot, exc)
            return
        self.last_ok_ns = now  # the device answered (a tracker may answer with a frame already taken)
        self._put(rows)

    def _stream(self, now: int) -> None:
        self._wait(IDLE_S, self.source.fileno())
        rows = self.source.read(0)
        if rows:
            self.last_ok_ns = time.monotonic_ns()
            self._put(rows)
        elif time.monotonic_ns() - self.last_ok_ns > self.stale_ns:
            raise DeviceError(
                f"{self.device}: silent for {(time.monotonic_ns() - self.last_ok_ns) / 1e9:.2f} s"
            )

    def _put(self, rows: list[Row]) -> None:
        for row in rows:
            ring = self.rings[row.topic]
            if row.seq is not None and not ring.account(row.seq, row.host_ns, SEQ_MODULO, self.rate_hz):
                log.info("%s: sample %d repeated; kept once", self.device, row.seq)
                continue
            ring.put(row.host_ns, row.data)

    def _wait(self, timeout_s: float, fd: int | None = None) -> None:
        """Sleep until ``timeout_s``, a readable ``fd`` or a command; run the commands that came."""
        fds = [self.commands] if fd is None else [self.commands, fd]
        try:
            readable, _, _ = select.select(fds, [], [], max(0.0, timeout_s))
        except (OSError, ValueError):  # the device's descriptor vanished: the next read says why
            readable = []
        if self.commands in readable:
            self._read_commands()

    # ----------------------------------------------------------------------------------- commands
    def _read_commands(self) -> None:
        try:
            data = self.commands.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the supervisor closed its end: it is gone or stopping us
            self.terminating = True
            return
        self._inbox += data
        *lines, self._inbox = self._inbox.split(b"\n")
        for line in lines:
            if line.strip():
                self._command(json.loads(line))

    def _command(self, cmd: dict) -> None:
        op = cmd.get("op")
        if op == "stop":
            self.stopping = True
            return
        if not self.connected:
            push_event(
                self.events,
                Event(EventKind.NOTE, label=self.device, text=f"command dropped: no device ({op})"),
            )
            return
        try:
            rows = self.source.command(cmd)
        except DeviceReplyError as exc:  # the device answered and refused it: it is there, not lost
            self._refused(f"{op}: the device refused it: {exc}")
            return
        except DeviceError as exc:
            self._lose(f"{op}: {exc}")
            return
        except (CommandRefused, ValueError, KeyError, TypeError) as exc:  # nothing of it was sent
            self._refused(f"{op}: {exc}")
            return
        self._put(rows)

    def _fault(self, why: str) -> None:
        """A fault the device reported: counted (a plan running stops on it), and an event says what."""
        log.warning("%s: fault: %s", self.device, why)
        self.status.fault(why)
        push_event(self.events, Event(EventKind.DEVICE_FAULT, label=self.device, text=why))

    def _refused(self, why: str) -> None:
        """A command refused (by the guard, or by the device): counted, and an event says why."""
        log.warning("%s: command refused: %s", self.device, why)
        self.status.refuse(why)
        push_event(self.events, Event(EventKind.COMMAND_REFUSED, label=self.device, text=why))

    # -------------------------------------------------------------------------------- connection
    def _connect(self) -> bool:
        try:
            self.source.open()
        except DeviceError as exc:
            self.status.error = str(exc)
            if self.gap_start_ns is None:  # the first attempt failed: the stream starts in a gap
                self._open_gap(str(exc))
            if self.status.phase == Phase.CONNECTING:
                self.status.phase = Phase.GAP
            self._safe_close()
            return False
        settle_heap(collect=False)  # what opening built (canopen's object dictionaries)
        self.connected = True
        self.last_ok_ns = time.monotonic_ns()
        self.next_slot = None
        if self.gap_start_ns is not None:
            gap_s = (time.monotonic_ns() - self.gap_start_ns) / 1e9
            push_event(self.events, Event(EventKind.DEVICE_GAP_END, value=gap_s, label=self.device))
            log.warning("%s back after %.2f s", self.device, gap_s)
            self.gap_start_ns = None
        self.status.error = ""
        self.status.phase = Phase.STREAMING
        return True

    def _lose(self, why: str) -> None:
        log.warning("%s lost: %s", self.device, why)
        self.status.error = why
        self._open_gap(why)
        self.connected = False
        self.status.phase = Phase.GAP
        self._safe_close()

    def _open_gap(self, why: str) -> None:
        self.gap_start_ns = time.monotonic_ns()
        push_event(self.events, Event(EventKind.DEVICE_GAP_START, label=self.device, text=why))
        for topic in self.sampled:
            self.rings[topic].note_gap()
            self.rings[topic].start_in_gap(self.gap_start_ns)
            if not self.source.slot_numbered:  # the device may restart its counter when it comes back
                self.rings[topic].restart_sequence()

    def _safe_close(self) -> None:
        try:
            self.source.close()
        except (DeviceError, OSError):
            pass

    def _check_parent(self, now: int) -> None:
        if now >= self._next_parent_check:
            self._next_parent_check = now + 100_000_000
            if not parent_alive(self.layout.parent_pid):
                self.terminating = True

    def _finish(self) -> None:
        relinquish()  # closing and exiting is no real-time work
        if self.terminating and self.connected:
            try:
                self.source.safe()
            except DeviceError as exc:
                log.warning("%s: could not leave the device safe: %s", self.device, exc)
        self._safe_close()
        self.status.phase = Phase.CLOSED


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("layout", type=Path)
    parser.add_argument("device", nargs="?", help="the device (none with --spare: the supervisor names it)")
    parser.add_argument("--commands", type=int, required=True, help="file descriptor of the command socket")
    parser.add_argument("--restarted", action="store_true")
    parser.add_argument("--spare", action="store_true", help="start up, then wait to be told the device")
    args = parser.parse_args(argv)
    if (args.device is None) != args.spare:
        parser.error("name a device, or --spare (not both)")
    layout = Layout.load(args.layout)
    daemon: Daemon | None = None

    def terminate(*_: object) -> None:
        if daemon is not None:
            daemon.terminating = True

    signal.signal(signal.SIGTERM, terminate)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the supervisor, which stops us in order
    robot = RobotDescription.model_validate_json(layout.robot_json)
    commands = socket.socket(fileno=args.commands)
    device, restarted = args.device, args.restarted
    if args.spare:
        order = _told(commands) if _ready(layout, commands) else None
        if order is None:  # the supervisor closed its end: the recording ended without needing us
            return 0
        device, restarted = order
        _stderr_to(layout.log(device))  # a traceback from now on is the device's
    layout.log(device).parent.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(filename=layout.log(device), level=logging.WARNING,
                        format="%(asctime)s %(process)d %(levelname)s %(message)s")  # fmt: skip
    entry = layout.devices[device]
    source = make_source(robot, device, entry.port, entry.rate_hz)
    daemon = Daemon(layout, device, source, commands, restarted=restarted)
    daemon.serve()
    return 0


def _ready(layout: Layout, commands: socket.socket) -> bool:
    """A spare's start-up, all of it before it is needed: every device's source imported (its driver: the
    servo SDK, python-can, canopen…), the start-up heap collected (a start-up's longest pause, ~90 ms), the
    real-time priority taken (waiting costs nothing at it, and from the ``become`` on the daemon runs at
    it), then ``ready`` said on the socket. False where the supervisor has closed it meanwhile (the
    recording ended while the spare started up)."""
    for entry in layout.devices.values():
        with contextlib.suppress(ValueError):  # a device without a source of its own is never a daemon's
            source_class(entry.driver)
    settle_heap()
    elevate()
    try:
        commands.sendall(b"ready\n")
    except OSError:  # the supervisor's end is closed: the recording is over
        return False
    return True


def _told(commands: socket.socket) -> tuple[str, bool] | None:
    """A spare's wait for the device it is to take over: (device, restarted), or None at the socket's end.
    Anything after the ``become`` line stays unread in the socket for the daemon."""
    line = b""
    while not line.endswith(b"\n"):
        try:
            byte = commands.recv(1)  # a byte at a time: the commands that follow are the daemon's to read
        except OSError:  # reset: the supervisor closed its end before reading our "ready"
            return None
        if not byte:
            return None
        line += byte
    order = json.loads(line)
    if order.get("op") != "become":
        raise SystemExit(f"a spare daemon was told {order!r}, not which device to become")
    return str(order["device"]), bool(order.get("restarted", True))


def _stderr_to(path: Path) -> None:
    """Send this process's standard error (tracebacks, the interpreter's own messages) to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 2)
    os.close(fd)


if __name__ == "__main__":
    sys.exit(main())
