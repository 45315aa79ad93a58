"""Serve emulators on pseudo-terminals: an event-driven select loop, stable port paths, faults, clean SIGTERM.

Each device gets a pty; its path is published as a symlink ``<run_dir>/<name>`` (stable across unplug and
replug, which create a new pty) and listed in ``<run_dir>/ports.json``. A unix socket
``<run_dir>/control.sock`` takes one JSON command per line (faults, operator inputs) and answers one JSON
line. Runs in its own process: client libraries that hold the GIL while blocked (ndicapy) need that.

Opening a port: the host keeps each pty's slave open itself (so the master never sees EIO/POLLHUP and the
host may close and reopen), which hides the client's open and close from the master. For an emulator that
resets when its port opens (an Arduino: DTR), the host watches the slave's ``/dev/pts`` node with inotify
(IN_OPEN/IN_CLOSE: one event per open and per last close of an open file, none for reads or writes), counts
the clients that hold it open, calls ``emulator.port_opened(now)`` when the first one opens it, and drops
that emulator's output while nobody has the port open (as the USB bridge of a closed port does). Where
inotify is missing the ports are served as before, without the reset.

The wire (``twin.wire``): a device with a UART (``Emulator.device_baud``) hears only a client at its baud
(read from the pty, ``feed_at``), and each reply or streamed output is queued until the wire and the USB
adapter would have delivered it (the request's and the reply's bytes at that baud, the device's response
time, the adapter's latency timer, behind the replies before it); the select loop writes it when due.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import pty
import selectors
import signal
import socket
import struct
import tempfile
import time
import tty
from collections import deque
from collections.abc import Callable
from pathlib import Path

from twin.emulators.base import Emulator, Faults
from twin.wire import LatencyTimer, Wire, client_baud, latency_timer_path

log = logging.getLogger(__name__)
PORTS_FILE = "ports.json"
CONTROL_SOCKET = "control.sock"
IN_OPEN, IN_CLOSE_WRITE, IN_CLOSE_NOWRITE = 0x20, 0x08, 0x10  # <sys/inotify.h>
_IN_CLOSE = IN_CLOSE_WRITE | IN_CLOSE_NOWRITE
_INOTIFY_EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (+ len bytes of name: none for a file watch)


class OpenWatch:
    """Opens and closes of pty slaves by other processes, from inotify on their ``/dev/pts`` nodes (Linux).

    The host's own slave fd was opened before the watch, so it is never counted. ``read`` returns
    (port, mask) pairs; the fd is readable only when a watched port was opened or closed."""

    def __init__(self) -> None:
        self._libc = ctypes.CDLL(None, use_errno=True)  # the process's own symbols: libc's inotify_*
        self.fd = self._libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        if self.fd < 0:
            raise OSError(ctypes.get_errno(), "inotify_init1 failed")
        self._ports: dict[int, _Port] = {}

    @classmethod
    def create(cls) -> OpenWatch | None:
        """A watch, or None where inotify is missing (ports are then served without reset-on-open)."""
        try:
            return cls()
        except (OSError, AttributeError) as exc:  # AttributeError: a libc without inotify
            log.warning("no inotify (%s): emulators will not see their ports opened", exc)
            return None

    def add(self, path: str, port: _Port) -> int:
        wd = self._libc.inotify_add_watch(self.fd, os.fsencode(path), IN_OPEN | _IN_CLOSE)
        if wd < 0:
            raise OSError(ctypes.get_errno(), f"inotify_add_watch({path}) failed")
        self._ports[wd] = port
        return wd

    def remove(self, wd: int) -> None:
        self._ports.pop(wd, None)
        self._libc.inotify_rm_watch(self.fd, wd)  # its IN_IGNORED event finds no port

    def read(self) -> list[tuple[_Port, int]]:
        events = []
        while True:
            try:
                data = os.read(self.fd, 4096)
            except BlockingIOError:
                return events
            offset = 0
            while offset < len(data):
                wd, mask, _, length = _INOTIFY_EVENT.unpack_from(data, offset)
                offset += _INOTIFY_EVENT.size + length
                if (port := self._ports.get(wd)) is not None:
                    events.append((port, mask))

    def close(self) -> None:
        os.close(self.fd)


# A sleeping process wakes this late on this kind of machine (a VM's timer: 55 µs at the 10th percentile,
# 75 µs median, 137 µs at the 90th, measured under SCHED_FIFO). Output due sooner is waited for spinning, so
# the wire's time is what the client sees and not the host's wake-up on top of it (never earlier: the spin
# ends at the due time).
WAKE_LATENCY_S = 100e-6


def _spin_until(now, due_s: float) -> None:
    while now() < due_s:
        pass


class _Port:
    """One emulator on one pty (re-created on replug)."""

    def __init__(self, name: str, emulator: Emulator, run_dir: Path, watch: OpenWatch | None = None,
                 latency: LatencyTimer | None = None) -> None:  # fmt: skip
        self.name = name
        self.emulator = emulator
        self.wire = Wire(latency)
        self.queue: deque[tuple[float, bytes]] = deque()  # (due, bytes): output the wire still carries
        self.link = run_dir / name
        self.faults = Faults()
        self.master = -1
        self._unsent = b""  # the rest of a reply the pty had room for only in part: it goes out first
        self.slave = -1
        # emulators that reset when their port opens (``port_opened``) have their slave watched
        self.watch = watch if emulator.resets_on_open else None
        self.wd = -1
        self.clients = 0  # open files of the slave held by other processes (watched ports only)
        self.plug()

    def plug(self) -> None:
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)  # keep the slave open for our whole life: the host may close and reopen it
        os.set_blocking(self.master, False)
        if self.watch is not None:
            self.wd = self.watch.add(os.ttyname(self.slave), self)
            self.clients = 0
        tmp = self.link.with_name(self.link.name + ".tmp")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(self.slave))
        tmp.replace(self.link)
        self.faults.unplugged = False
        self.emulator.reset_link()

    def unplug(self) -> None:
        self.faults.unplugged = True
        self.link.unlink(missing_ok=True)
        if self.watch is not None and self.wd >= 0:
            self.watch.remove(self.wd)
            self.wd, self.clients = -1, 0
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1
        self._unsent = b""
        self.queue.clear()

    def opened_or_closed(self, mask: int, now_s: float) -> None:
        """An inotify event on the slave: the first open resets the device (DTR rises)."""
        if mask & IN_OPEN:
            self.clients += 1
            if self.clients == 1:
                self.emulator.port_opened(now_s)
        if mask & _IN_CLOSE:
            self.clients = max(0, self.clients - 1)

    def send(self, data: bytes, now_s: float, baud: int | None, request: int = 0) -> None:
        """Queue the device's ``data`` (its answer to a ``request``-byte command, or unprompted output) for
        when the wire delivers it to a client at ``baud``; nothing where the device runs at another."""
        if not data:
            return
        if self.faults.corrupt_replies > 0:
            # one bit flipped in the reply's last checksum byte (the Dynamixel CRC's low byte, NDI's and the
            # boards' last hex digit): the client reads the whole reply and finds it corrupt. A flip in a
            # header or terminator would cost the client its reply timeout instead; this fault is not that.
            self.faults.corrupt_replies -= 1
            data = data[:-2] + bytes([data[-2] ^ 0x01]) + data[-1:]
        device = self.emulator.device_baud()
        if device is not None and baud is not None and baud != device and not request:
            return  # streamed bytes at another baud: framing errors, nothing the client can use
        wire_baud = None if device is None else (baud or device)
        response = self.emulator.response_s() if request else 0.0
        begin = 0
        for due, end in self.wire.schedule(now_s, wire_baud, request, response, len(data)):
            self.queue.append((due, data[begin:end]))
            begin = end

    def deliver(self, now_s: float) -> float | None:
        """Write the queued output due by ``now_s``; when the next is due (None: nothing queued)."""
        while self.queue and self.queue[0][0] <= now_s:
            self.write(self.queue.popleft()[1], now_s)
        return self.queue[0][0] if self.queue else None

    def write(self, data: bytes, now_s: float) -> None:
        if not data or self.master < 0:
            return
        if self.watch is not None and self.clients == 0:
            return  # nobody has the port open: the bytes are lost, as behind a closed USB serial port
        if self.faults.drop_replies > 0:
            self.faults.drop_replies -= 1
            return
        # a device whose host does not read drops whole replies (its output buffer overflows), never the
        # end of one: what a full pty took in part is finished before anything newer goes out
        if self._unsent:
            if not self._send(self._unsent, now_s):
                log.warning("%s: host not reading, %d bytes dropped", self.name, len(data))
                self.emulator.output_refused(data, now_s)
                return
        self._send(data, now_s, whole=True)

    def _send(self, data: bytes, now_s: float, whole: bool = False) -> bool:
        """Write ``data``; keep what did not fit of a reply begun (``_unsent``); whether it all went out.
        A reply not begun at all (``whole``) is dropped."""
        try:
            n = os.write(self.master, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:  # EIO: no process has the slave open right now
            log.debug("%s: write failed: %s", self.name, exc)
            self._unsent = b""
            return False
        if whole and n == 0:
            log.warning("%s: host not reading, %d bytes dropped", self.name, len(data))
            self.emulator.output_refused(data, now_s)
        self._unsent = data[n:] if n > 0 else (b"" if whole else data)
        return not self._unsent


class PtyHost:
    """Serve ``emulators`` until SIGTERM/SIGINT, event-driven: the loop sleeps in ``select`` until a port or
    the control socket has input, an emulator's unsolicited output is due (``Emulator.next_output_s``), a
    signal arrives (wake-up fd) or ``housekeeping_s`` has passed, whichever comes first. No fixed-period
    polling: an idle host wakes 1/housekeeping_s times a second.

    ``tick(now)`` brings what stands behind the emulators up to ``now`` (the rig steps its twin there). The
    emulators' hardware advances itself whenever a device is read, written or streams, so the host calls
    ``tick`` only (a) before each control command, so operator inputs and state queries apply at the present
    rather than at the last instant a device was touched, and (b) at least every ``housekeeping_s``, so a
    quiet spell never leaves more than that to catch up at once: the first read after an idle hour would
    otherwise step the twin 3.6 million times (and allocate its trace) before answering.
    ``control(cmd)`` handles commands the host does not know (operator inputs)."""

    def __init__(
        self,
        run_dir: Path,
        emulators: dict[str, Emulator],
        tick: Callable[[float], None] | None = None,
        control: Callable[[dict], dict] | None = None,
        housekeeping_s: float = 0.05,
        latency_timers: dict[str, float] | None = None,
    ) -> None:
        """``latency_timers``: each device's USB adapter latency timer (s; a device missing, or at 0, or
        without a UART has none), kept in ``twin.wire.latency_timer_path(run_dir, device)``."""
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        wants_watch = any(emu.resets_on_open for emu in emulators.values())
        self._watch = OpenWatch.create() if wants_watch else None
        timers = {
            name: LatencyTimer(latency_timer_path(self.run_dir, name), seconds)
            for name, seconds in (latency_timers or {}).items()
            if seconds > 0 and name in emulators and emulators[name].device_baud() is not None
        }
        self.ports = {
            name: _Port(name, emu, self.run_dir, self._watch, timers.get(name))
            for name, emu in emulators.items()
        }
        self.tick = tick
        self.control = control
        self.housekeeping_s = housekeeping_s
        self._stop = False
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    def stop(self, *_: object) -> None:
        self._stop = True

    def serve_forever(self) -> None:
        signal.signal(signal.SIGTERM, self.stop)
        signal.signal(signal.SIGINT, self.stop)
        link = self.run_dir / CONTROL_SOCKET  # what clients open: a link to the socket itself
        link.unlink(missing_ok=True)
        # a socket's address holds ~107 bytes: a lab in a deep folder would not fit, so the socket lives in a
        # private folder of the system's temporary one, and the run directory links to it
        sock_dir = Path(tempfile.mkdtemp(prefix="vslab-rig-"))
        sock_path = sock_dir / CONTROL_SOCKET
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            server.bind(str(sock_path))
            link.symlink_to(sock_path)
        except OSError:
            server.close()
            sock_path.unlink(missing_ok=True)
            sock_dir.rmdir()
            raise
        server.listen()
        server.setblocking(False)
        wake_r, wake_w = socket.socketpair()  # a signal writes here, so select returns at once
        wake_r.setblocking(False)
        wake_w.setblocking(False)
        old_wakeup_fd = signal.set_wakeup_fd(wake_w.fileno(), warn_on_full_buffer=False)
        if self.tick is not None:  # the first tick before the ports are listed: it loads (or compiles) what
            self.tick(self.now())  # the physics runs on, which held a first ping past a driver's 3 tries
        self._publish()
        # select(2), not epoll: epoll_wait rounds its timeout up to whole milliseconds, which would hold
        # each reply up to 1 ms past its due time (a 1 Mbaud Sync Read takes 1.7 ms in all)
        sel = selectors.SelectSelector()
        sel.register(server, selectors.EVENT_READ, ("accept", None))
        sel.register(wake_r, selectors.EVENT_READ, ("wake", wake_r))
        if self._watch is not None:
            sel.register(self._watch.fd, selectors.EVENT_READ, ("opens", None))
        registered: dict[str, int] = {}
        self._sync_registrations(sel, registered)
        next_tick = self.now() + self.housekeeping_s
        try:
            while not self._stop:
                now = self.now()
                if now >= next_tick:
                    if self.tick is not None:
                        self.tick(now)
                    next_tick = now + self.housekeeping_s
                wake_at = next_tick
                due = self._emit_due(now)
                if due is not None and due < wake_at:
                    if due - self.now() < WAKE_LATENCY_S:  # too close to sleep: the wake-up would be late
                        _spin_until(self.now, due)
                        continue
                    wake_at = due - WAKE_LATENCY_S  # wake early; the last stretch above, spinning
                for key, _ in sel.select(timeout=max(0.0, wake_at - self.now())):
                    kind, obj = key.data
                    if kind == "port":
                        self._serve_port(obj)
                    elif kind == "accept":
                        conn, _ = server.accept()
                        conn.setblocking(True)
                        sel.register(conn, selectors.EVENT_READ, ("control", conn))
                    elif kind == "control":
                        self._serve_control(sel, obj)
                        self._sync_registrations(sel, registered)  # a fault may have (un)plugged a port
                    elif kind == "opens":
                        self._serve_opens()
                    else:
                        _drain(obj)
        finally:
            signal.set_wakeup_fd(old_wakeup_fd)
            for port in self.ports.values():
                if not port.faults.unplugged:
                    port.unplug()
            (self.run_dir / PORTS_FILE).unlink(missing_ok=True)
            link.unlink(missing_ok=True)
            sock_path.unlink(missing_ok=True)
            sock_dir.rmdir()
            if self._watch is not None:
                self._watch.close()
            server.close()
            wake_r.close()
            wake_w.close()
            sel.close()

    def _emit_due(self, now: float) -> float | None:
        """Write every plugged emulator's output that is due by ``now``; the earliest next due time. Replies
        already on the wire go out first: a stream's next sample (which may step the twin) waits for them."""
        plugged = [port for port in self.ports.values() if not port.faults.unplugged]
        times = [port.deliver(now) for port in plugged]
        for port in plugged:
            emulator = port.emulator
            due = emulator.next_output_s(now)
            if due is not None and due <= now:
                port.send(emulator.poll(now), now, client_baud(port.master))
                due = emulator.next_output_s(now)
                times.append(port.deliver(now))
            times.append(due)
        return min((t for t in times if t is not None), default=None)

    def _sync_registrations(self, sel: selectors.BaseSelector, registered: dict[str, int]) -> None:
        for name, port in self.ports.items():
            if registered.get(name) != port.master:
                if name in registered and registered[name] >= 0:
                    try:
                        sel.unregister(registered[name])
                    except (KeyError, ValueError):
                        pass
                if port.master >= 0:
                    sel.register(port.master, selectors.EVENT_READ, ("port", port))
                registered[name] = port.master

    def _serve_port(self, port: _Port) -> None:
        try:
            data = os.read(port.master, 65536)
        except BlockingIOError:
            return
        except OSError:  # EIO: the host closed its side; keep serving, it may reopen
            time.sleep(0.001)
            return
        if data:
            if port.watch is not None:
                self._serve_opens()  # an open queued before these bytes resets the device first
            now, baud = self.now(), client_baud(port.master)
            port.send(port.emulator.feed_at(data, now, baud), now, baud, request=len(data))
            port.deliver(self.now())

    def _serve_opens(self) -> None:
        """Pass the ports' opens and closes (inotify) to their emulators."""
        if self._watch is not None:
            for port, mask in self._watch.read():
                port.opened_or_closed(mask, self.now())

    def _serve_control(self, sel: selectors.BaseSelector, conn: socket.socket) -> None:
        data = b""
        while not data.endswith(b"\n"):
            chunk = conn.recv(4096)
            if not chunk:
                sel.unregister(conn)
                conn.close()
                return
            data += chunk
        try:
            reply = self._command(json.loads(data))
        except (ValueError, KeyError, TypeError) as exc:
            reply = {"ok": False, "error": str(exc)}
        conn.sendall(json.dumps(reply).encode() + b"\n")

    def _command(self, cmd: dict) -> dict:
        op = cmd["op"]
        if self.tick is not None:
            self.tick(self.now())  # the command acts at the present, not at the last touched instant
        if op == "fault":
            port = self.ports[cmd["device"]]
            kind = cmd["kind"]
            if kind == "unplug":
                port.unplug()
            elif kind == "plug":
                port.plug()
            elif kind in ("corrupt", "drop"):
                setattr(port.faults, f"{kind}_replies", int(cmd.get("count", 1)))
            else:
                raise ValueError(f"unknown fault {kind!r}")
            self._publish()
            return {"ok": True}
        if op == "ports":
            return {"ok": True, "ports": self._port_paths()}
        if self.control is not None:
            return self.control(cmd)
        raise ValueError(f"unknown command {op!r}")

    def _port_paths(self) -> dict[str, str]:
        return {name: str(p.link) for name, p in self.ports.items() if not p.faults.unplugged}

    def _publish(self) -> None:
        path = self.run_dir / PORTS_FILE
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"pid": os.getpid(), "ports": self._port_paths()}, indent=2))
        tmp.replace(path)


def _drain(sock: socket.socket) -> None:
    """Empty the signal wake-up socket (the handlers have run already)."""
    try:
        while sock.recv(4096):
            pass
    except BlockingIOError:
        pass


def send_control(run_dir: Path, command: dict, timeout_s: float = 5.0) -> dict:
    """Send one command to a running host and return its answer."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout_s)
        sock.connect(str((Path(run_dir) / CONTROL_SOCKET).resolve()))  # the socket the run directory links to
        sock.sendall(json.dumps(command).encode() + b"\n")
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(4096)
            if not chunk:
                break
            data += chunk
    return json.loads(data)


def wait_for_ports(run_dir: Path, timeout_s: float = 30.0) -> dict[str, str]:
    """Block until a host has published its ports (or raise TimeoutError)."""
    path = Path(run_dir) / PORTS_FILE
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists() and (Path(run_dir) / CONTROL_SOCKET).exists():
            return json.loads(path.read_text())["ports"]
        time.sleep(0.05)
    raise TimeoutError(f"no emulator host published its ports in {run_dir} within {timeout_s} s")
