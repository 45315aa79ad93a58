"""The recorder: a supervisor of one OS process per device, plus a writer process, for one MCAP session.

    with Recorder(robot, ports, sessions_dir / "s1", "s1") as rec:
        time.sleep(60)              # or run a plan: rec.latest(topic), rec.command(topic, {...})
    # the session is closed: indexed parts, session.json with every stream's account

Each device the robot description names (``devices:``, with ``ports`` saying where each is plugged in) gets
a daemon (:mod:`acquisition.recorder.daemon`) that owns its port and streams its samples into shared-memory
rings (:mod:`acquisition.recorder.ring`); the writer process (:mod:`acquisition.recorder.writer_process`) is
the only one that writes the file. The supervisor starts them, watches their heartbeats, restarts a daemon
that dies or hangs (the gap marked in ``/events``; the other streams never notice) and a writer that dies (it
goes on in a new part), and stops everything in order: daemons first, then the writer. Every child ends
with the supervisor, even a SIGKILLed one, leaving its device safe: each holds one end of a socket whose
other end only the supervisor process holds (its commands, and its lifeline: the kernel closes it when the
supervisor dies; ``PR_SET_PDEATHSIG`` is no use here, it fires when the thread that started a child ends,
and the watchdog thread restarts children). A plan runner reads the newest samples with
:meth:`latest` and sends commands with :meth:`command`; the daemons record them as sent.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from acquisition.devices.bus_budget import rate_refusal
from acquisition.errors import AcquisitionError
from acquisition.recorder.daemon import EVENT_BYTES, MAX_LAG_S, push_event
from acquisition.recorder.layout import SUPERVISOR, DeviceEntry, Layout
from acquisition.recorder.ring import Ring
from acquisition.recorder.source_base import make_source, source_class
from acquisition.recorder.status import DaemonStatus, Phase
from acquisition.recorder.writer import RotationPolicy
from acquisition.recorder.writer_process import WRITER_FAILED
from acquisition.schemas import topics as T
from acquisition.schemas.events import Event, EventKind
from acquisition.schemas.session_card import as_metadata
from models.robot import RobotDescription

if TYPE_CHECKING:  # the live view (foxglove) is imported only by those who use it
    from acquisition.recorder.live import LiveServer

log = logging.getLogger(__name__)

RING_SECONDS = 30.0  # each ring holds this much of its stream: the writer may stall (or restart) this long


WATCH_S = 0.05  # the supervisor looks at its children this often
SPARE = "spare"  # the waiting daemon's name (its log, before it is told its device)
HANG_S = 2.0  # a daemon whose heartbeat is older than this (while not connecting) is killed and restarted
CONNECT_S = 30.0  # a first connection (the tracker's handshake takes seconds) may take this long
WRITER_RESTARTS = 5  # a writer that keeps dying (disk full, …) is not restarted forever


def ring_slots(entry: DeviceEntry, topic: str) -> int:
    """Slots of ``topic``'s ring: ``RING_SECONDS`` of a sampled stream at its own rate (at least 1024), 4096
    for commands and other sporadic messages."""
    if topic not in entry.sampled:
        return 4096
    return max(1024, int(entry.sampled_rates_hz.get(topic, entry.rate_hz) * RING_SECONDS))


class RecorderError(AcquisitionError, RuntimeError):
    """The recording cannot start (no device to record, a device vslab has no driver for, a session that is
    there already)."""


@dataclass(frozen=True)
class Latest:
    """The newest sample of a topic: host receive time (monotonic ns) and its fields (``values["seq"]``)."""

    host_ns: int
    values: np.void


class _Child:
    """One child process (a daemon or the writer) and, for a daemon, its command socket."""

    def __init__(self, name: str, proc: subprocess.Popen, commands: socket.socket | None) -> None:
        self.name, self.proc, self.commands = name, proc, commands
        self.started = time.monotonic()
        self.ready = False  # a spare: it said it has started up
        self.lock = threading.Lock()

    def send(self, cmd: dict) -> bool:
        if self.commands is None or self.proc.poll() is not None:
            return False
        with self.lock:
            try:
                self.commands.sendall(json.dumps(cmd).encode() + b"\n")
                return True
            except OSError:
                return False

    def close(self) -> None:
        if self.commands is not None:
            self.commands.close()


class Recorder:
    def __init__(
        self,
        robot: RobotDescription,
        ports: dict[str, str],
        directory: Path,
        session_id: str,
        experiment: str = "manual",
        metadata: dict[str, Any] | None = None,  # strings as they are, anything else as JSON
        rates: dict[str, float] | None = None,  # device → Hz, over the robot description's
        rotation: RotationPolicy | None = None,
        batch_s: float = 0.05,
        flush_s: float = 0.1,
        stale_s: float = 0.5,
        live: LiveServer | None = None,  # started by the caller; shown what the file gets
    ) -> None:
        self.robot = robot
        self.directory = Path(directory)
        self.session_id = session_id
        if self.directory.exists() and any(self.directory.glob("*.mcap")):  # never written over
            raise RecorderError(f"session {session_id} exists already in {self.directory.parent}: choose "
                                "another --session")  # fmt: skip
        rates = dict(rates or {})
        unknown = sorted(set(rates) - set(robot.devices))
        if unknown:
            raise RecorderError(f"--rate names {', '.join(unknown)}: {robot.name}'s devices are "
                                f"{', '.join(robot.devices)}")  # fmt: skip
        devices = {}
        for name, port in ports.items():
            if name not in robot.devices:
                continue
            if (refusal := rate_refusal(robot, name, rates.get(name))) is not None:
                raise RecorderError(refusal)  # before any device is opened: the wire cannot carry it
            try:
                source = make_source(robot, name, port, rates.get(name))
            except ValueError as exc:
                raise RecorderError(str(exc)) from None
            driver = robot.devices[name].driver
            devices[name] = DeviceEntry(name, driver, port, source.rate_hz, list(source.topics),
                                        list(source.sampled_topics), source.sampled_rates_hz)  # fmt: skip
        if not devices:
            raise RecorderError(f"none of {robot.name}'s devices ({', '.join(robot.devices)}) is in the port "
                                f"map ({', '.join(ports) or 'empty'})")  # fmt: skip
        rotation = rotation or RotationPolicy()
        now = time.monotonic_ns()
        self.layout = Layout(
            run_dir=Path(), session_dir=self.directory, session_id=session_id, experiment=experiment,
            robot_json=robot.model_dump_json(), parent_pid=os.getpid(), t0_ns=now,
            unix_offset_ns=time.time_ns() - time.monotonic_ns(), devices=devices,
            metadata={**as_metadata(metadata or {}),
                      "rates_hz": json.dumps({n: d.rate_hz for n, d in devices.items()})},
            batch_s=batch_s, flush_s=flush_s, rotate_bytes=rotation.max_bytes,
            rotate_seconds=rotation.max_seconds, stale_s=stale_s,
        )  # fmt: skip
        self._messages = {n: t.message for n, t in T.session_topics(robot).items() if t.message is not None}
        self.live = live
        self.live_errors = 0  # live-view failures: logged once, counted, never stop the recording
        self.write_error: str | None = None
        self.restarts: dict[str, int] = {}
        self.final: dict[str, dict] | None = None
        self.silent: dict[str, str] = {}  # after stop: devices that never gave a sample, and why
        self.behind_ms: dict[str, float] = {}  # after stop: the most each daemon fell behind its schedule
        self.scheduling: dict[str, str] = {}  # after stop: the scheduling each daemon got
        self._children: dict[str, _Child] = {}
        self._spare: _Child | None = None  # a daemon started up and waiting to replace one that dies
        self._rings: dict[str, Ring] = {}
        self._events: Ring | None = None
        self._statuses: dict[str, DaemonStatus] = {}
        self._owner = {topic: name for name, d in devices.items() for topic in d.topics}
        self._event_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._started = self._stopped = False

    # ----------------------------------------------------------------------------------- lifecycle
    def __enter__(self) -> Recorder:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def devices(self) -> list[str]:
        return list(self.layout.devices)

    @property
    def parts(self) -> list[Path]:
        return sorted(self.directory.glob(f"{self.session_id}_[0-9][0-9][0-9].mcap"))

    def start(self) -> None:
        """Create the rings, start the writer and every daemon; return once each device has answered (or
        failed to: it then starts in a gap, and its daemon keeps trying)."""
        layout = self.layout
        self.directory.mkdir(parents=True, exist_ok=True)
        layout.run_dir = Layout.new_run_dir(self.session_id)
        self._started = True
        try:
            for entry in layout.devices.values():
                for topic in entry.topics:
                    message = self._messages[topic]
                    slots = ring_slots(entry, topic)
                    self._rings[topic] = Ring.create(layout.ring(topic), slots, message.size)
                self._statuses[entry.name] = DaemonStatus.create(layout.status(entry.name))
            for producer in layout.producers:
                ring = Ring.create(layout.events(producer), 2048, EVENT_BYTES)
                if producer == SUPERVISOR:
                    self._events = ring
            self._layout_path = layout.save()
            self.event(Event(EventKind.SESSION_START, label=self.session_id))
            self._children["writer"] = self._spawn_writer(restarted=False)
            for name in layout.devices:
                self._children[name] = self._spawn_daemon(name, restarted=False)
            self._wait_connected()
            self._spare = self._spawn_daemon(SPARE, restarted=False)  # after the devices: it slows a start
        except BaseException:
            self.stop()
            raise
        self._threads = [threading.Thread(target=self._watch, name="recorder-watch", daemon=True)]
        if self.live is not None:
            self._threads.append(threading.Thread(target=self._feed_live, name="recorder-live", daemon=True))
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        """Stop the daemons (their devices left as they are), then the writer (it closes the session)."""
        if self._stopped or not self._started:
            return
        self._stopped = True
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        daemons = [c for name, c in self._children.items() if name != "writer"]
        for child in daemons:
            child.send({"op": "stop"})
        for child in daemons:
            _end(child.proc, 5.0)
        self._end_spare()
        self.event(Event(EventKind.SESSION_END, label=self.session_id))
        writer = self._children.get("writer")
        if writer is not None:
            writer.send({"op": "stop"})
            code = _end(writer.proc, 30.0)
            if code == WRITER_FAILED and self.write_error is None:
                self.write_error = _failure(writer) or f"it could not write (see {self.layout.log('writer')})"
            if code != 0 and self.write_error is None:
                self.write_error = f"the session writer exited with {code} (see {self.layout.log('writer')})"
        self.final = self.snapshot()
        self.silent = {
            name: self._statuses[name].error or "no samples"
            for name, entry in self.layout.devices.items()
            if entry.sampled and all(self.final[t]["received"] == 0 for t in entry.sampled)
        }
        for child in self._children.values():
            child.close()
        for ring in [*self._rings.values(), self._events]:
            if ring is not None:
                ring.close()
        self.behind_ms = {name: s.behind_ms for name, s in self._statuses.items()}
        self.scheduling = self.priorities()
        for status in self._statuses.values():
            status.close()
        shutil.rmtree(self.layout.run_dir, ignore_errors=True)

    # ------------------------------------------------------------------------------ for the runner
    def event(self, event: Event, host_ns: int | None = None) -> None:
        """Mark something (plan step, payload change, note) at ``host_ns`` (the monotonic clock's ns, as
        ``host_now_ns``; default now)."""
        if self._events is not None:
            with self._event_lock:
                push_event(self._events, event, host_ns)

    def has(self, topic: str) -> bool:
        """Whether a device of this recording writes (or takes commands on) ``topic``."""
        return topic in self._owner

    def latest(self, topic: str) -> Latest | None:
        """The newest sample of ``topic`` (None before the first, or when no device writes it)."""
        ring = self._rings.get(topic)
        got = ring.latest() if ring is not None else None
        if got is None:
            return None
        message = self._messages[topic]
        return Latest(got[0], np.frombuffer(got[1][: message.size].tobytes(), message.dtype)[0])

    def command(self, topic: str, cmd: dict) -> bool:
        """Send ``cmd`` to the daemon of the device that owns ``topic``; False when it cannot take it (the
        daemon is restarting). A daemon whose device is lost drops it and says so in the events."""
        child = self._children.get(self._owner.get(topic, ""))
        return child is not None and child.send(cmd)

    def connected(self, topic: str) -> bool:
        status = self._statuses.get(self._owner.get(topic, ""))
        return status is not None and status.connected

    def error(self, topic: str) -> str:
        name = self._owner.get(topic, "")
        status = self._statuses.get(name)
        return (status.error if status is not None else "") or f"no device writes {topic}"

    def refusals(self) -> tuple[int, str]:
        """How many commands the daemons' guards refused so far, and the last reason (``device: op: why``)."""
        return self._tally("refusals")

    def faults(self) -> tuple[int, str]:
        """How many faults the devices reported so far (a drive's EMCY), and the last (``device: fault``)."""
        return self._tally("faults")

    def _tally(self, counter: str) -> tuple[int, str]:
        """A status counter (``refusals``, ``faults``) summed over the daemons, with the last reason."""
        total, last = 0, ""
        for name, status in self._statuses.items():
            n, why = getattr(status, counter)
            total += n
            if n and why:
                last = f"{name}: {why}"
        return total, last

    def snapshot(self) -> dict[str, dict[str, int]]:
        """Every stream's account now: expected, received, lost, written, dropped, gaps."""
        if self.final is not None:
            return self.final
        out = {}
        for topic, ring in self._rings.items():
            counts = ring.counts().as_dict()
            if not any(topic in d.sampled for d in self.layout.devices.values()):
                counts["expected"], counts["lost"] = counts["received"], 0
            out[topic] = counts
        return out

    def short_of_time(self) -> dict[str, float]:
        """After the recording: the devices whose every poll is a sample (the servo bus) that fell more than
        half of ``MAX_LAG_S`` behind their schedule, and how far (ms). Past ``MAX_LAG_S`` a daemon skips the
        polls it missed, which count lost: its reads take most of each slot (its rate is near what the wire
        and the host's own time per read allow: ``configs/robots/vsl.yaml``)."""
        devices = self.layout.devices
        sampled = {name for name, entry in devices.items() if source_class(entry.driver).slot_numbered}
        return {name: ms for name, ms in self.behind_ms.items() if name in sampled and ms > 0.5e3 * MAX_LAG_S}

    def priorities(self) -> dict[str, str]:
        """The scheduling each daemon got (SCHED_FIFO, a nice value, or normal)."""
        return {name: s.priority for name, s in self._statuses.items()}

    # -------------------------------------------------------------------------------- children
    def _spawn_daemon(self, name: str, restarted: bool) -> _Child:
        """The daemon of device ``name``; ``name`` ``SPARE``: a spare, told its device later."""
        ours, theirs = socket.socketpair()
        which = ["--spare"] if name == SPARE else [name] + (["--restarted"] if restarted else [])
        cmd = [sys.executable, "-m", "acquisition.recorder.daemon", str(self._layout_path), *which,
               "--commands", str(theirs.fileno())]  # fmt: skip
        proc = self._popen(name, cmd, pass_fds=(theirs.fileno(),))
        theirs.close()
        ours.settimeout(1.0)
        return _Child(name, proc, ours)

    def spare_ready(self, timeout_s: float = 0.0) -> bool:
        """Whether a spare daemon has started up and waits (within ``timeout_s``): a daemon that dies now
        is replaced in the time its device takes to connect. A spare started a moment ago (the last one took
        over) is still importing: a daemon that dies meanwhile waits for it."""
        spare = self._spare
        if spare is None or spare.proc.poll() is not None:
            return False
        if not spare.ready:
            deadline = time.monotonic() + timeout_s
            while not spare.ready:
                left_s = max(0.0, deadline - time.monotonic())
                readable, _, _ = select.select([spare.commands], [], [], left_s)
                if not readable:
                    return False
                said = spare.commands.recv(64, socket.MSG_DONTWAIT)
                if not said:
                    return False
                spare.ready = said.startswith(b"ready")
        return True

    def _end_spare(self) -> None:
        """End the spare (its socket closed, it exits); its log goes with it where it said nothing."""
        spare, self._spare = self._spare, None
        if spare is None:
            return
        spare.close()
        _end(spare.proc, 5.0)
        log_path = self.layout.log(SPARE)
        with contextlib.suppress(OSError):
            if log_path.stat().st_size == 0:
                log_path.unlink()

    def _spawn_writer(self, restarted: bool) -> _Child:
        ours, theirs = socket.socketpair()
        cmd = [sys.executable, "-m", "acquisition.recorder.writer_process", str(self._layout_path),
               "--commands", str(theirs.fileno())] + (["--restarted"] if restarted else [])  # fmt: skip
        proc = self._popen("writer", cmd, pass_fds=(theirs.fileno(),))
        theirs.close()
        ours.settimeout(1.0)
        return _Child("writer", proc, ours)

    def _popen(self, name: str, cmd: list[str], pass_fds: tuple[int, ...] = ()) -> subprocess.Popen:
        log_path = self.layout.log(name)
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "ab") as stderr:  # tracebacks of a crashing child end up beside the session
            return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr,
                                    pass_fds=pass_fds, start_new_session=True)  # fmt: skip

    def _wait_connected(self) -> None:
        deadline = time.monotonic() + CONNECT_S
        for name, status in self._statuses.items():
            while status.phase in (Phase.STARTING, Phase.CONNECTING) and time.monotonic() < deadline:
                if self._children[name].proc.poll() is not None:
                    raise RecorderError(f"the {name} daemon failed to start (see {self.layout.log(name)})")
                time.sleep(0.01)

    def _watch(self) -> None:
        """Restart what died or hangs, until the recording stops."""
        while not self._stop.wait(WATCH_S):
            now = time.monotonic_ns()
            for name, child in list(self._children.items()):
                if self._stop.is_set():
                    return
                code = child.proc.poll()
                if name == "writer":
                    if self._writer_failed(child):
                        return
                    if code is not None:
                        self._restart_writer(code)
                    continue
                status = self._statuses[name]
                if code is not None:
                    self._restart_daemon(name, f"daemon exited ({_exit_text(code)})")
                elif (
                    status.phase in (Phase.STREAMING, Phase.GAP) and now - status.heartbeat_ns > HANG_S * 1e9
                ):
                    log.warning("%s daemon hangs (no heartbeat for %.1f s): killing it", name,
                                (now - status.heartbeat_ns) / 1e9)  # fmt: skip
                    child.proc.kill()
                    child.proc.wait()
                    self._restart_daemon(name, f"daemon hung (no heartbeat for {HANG_S} s)")

    def _restart_daemon(self, name: str, why: str) -> None:
        log.warning("%s: %s; restarting it", name, why)
        self.restarts[name] = self.restarts.get(name, 0) + 1
        entry = self.layout.devices[name]
        if self._statuses[name].phase != Phase.GAP:  # a daemon already in a gap marked it
            self.event(Event(EventKind.DEVICE_GAP_START, label=name, text=why))
            for topic in entry.sampled:
                self._rings[topic].note_gap()
        if not source_class(entry.driver).slot_numbered:
            for topic in entry.sampled:
                self._rings[topic].restart_sequence()
        self._children[name].close()
        spare, self._spare = self._spare, None
        if spare is not None and spare.proc.poll() is None and spare.send({"op": "become", "device": name}):
            spare.name, spare.started = name, time.monotonic()
            self._children[name] = spare
        else:  # none ready (another daemon took it a moment ago): one started from nothing
            self._children[name] = self._spawn_daemon(name, restarted=True)
        self._spare = self._spawn_daemon(SPARE, restarted=False)

    def _writer_failed(self, writer: _Child) -> bool:
        """True once the writer said it could not write (a full disk): the devices are then stopped (left
        safe), the writer counts what they still send as dropped and the session is marked failed."""
        reason = _failure(writer)
        if reason is None:
            return False
        self.write_error = reason
        log.error("the session writer failed: %s; stopping the devices", reason)
        daemons = [c for name, c in self._children.items() if name != "writer"]
        for child in daemons:
            child.send({"op": "stop"})
        for child in daemons:
            _end(child.proc, 5.0)
        return True

    def _restart_writer(self, code: int) -> None:
        self.restarts["writer"] = self.restarts.get("writer", 0) + 1
        if self.restarts["writer"] > WRITER_RESTARTS:
            self.write_error = (
                f"the session writer keeps dying ({_exit_text(code)}; see {self.layout.log('writer')})"
            )
            self._stop.set()
            return
        log.warning("the session writer %s; restarting it (a new part)", _exit_text(code))
        self.event(Event(EventKind.NOTE, label="writer", text=f"writer {_exit_text(code)}; restarted"))
        self._children["writer"] = self._spawn_writer(restarted=True)

    def _feed_live(self) -> None:
        """Show what the daemons produce in the live view (peeking: the writer still gets everything)."""
        peekers = {topic: Ring.attach(ring.path) for topic, ring in self._rings.items()}
        events = [Ring.attach(self.layout.events(p)) for p in self.layout.producers]
        offset = self.layout.unix_offset_ns
        while not self._stop.wait(0.02):
            for topic, ring in peekers.items():
                host_ns, _, payload = ring.peek()
                if len(host_ns):
                    message = self._messages[topic]
                    rows = np.ascontiguousarray(payload[:, : message.size]).view(message.dtype).reshape(-1)
                    self._publish(topic, host_ns + offset, rows)
            for ring in events:
                host_ns, lengths, payload = ring.peek()
                for t, n, data in zip(host_ns, lengths, payload, strict=True):
                    self._publish(T.EVENTS, [int(t) + offset], [bytes(data[:n])])
        for ring in [*peekers.values(), *events]:
            ring.close()

    def _publish(self, topic: str, log_time, messages) -> None:
        try:
            self.live.publish(topic, log_time, messages)
        except Exception:
            self.live_errors += 1
            if self.live_errors == 1:
                log.exception("live view failed on %s; recording goes on without it (counted in live_errors)",
                              topic)  # fmt: skip


def _failure(writer: _Child) -> str | None:
    """The reason a writer sent when it could not write (``{"op": "failed"}``), if it sent one."""
    try:
        if not select.select([writer.commands], [], [], 0)[0]:
            return None
        data = writer.commands.recv(4096)
    except (OSError, ValueError):  # closed
        return None
    for line in data.splitlines():
        with contextlib.suppress(ValueError):
            message = json.loads(line)
            if message.get("op") == "failed":
                return str(message.get("reason", "it could not write"))
    return None


def _end(proc: subprocess.Popen, timeout_s: float) -> int:
    """Wait for ``proc``; SIGTERM, then SIGKILL, if it will not end. Returns its exit code."""
    with contextlib.suppress(subprocess.TimeoutExpired):
        return proc.wait(timeout=timeout_s)
    proc.terminate()
    with contextlib.suppress(subprocess.TimeoutExpired):
        return proc.wait(timeout=2.0)
    proc.kill()
    return proc.wait()


def _exit_text(code: int) -> str:
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exited with code {code}"
