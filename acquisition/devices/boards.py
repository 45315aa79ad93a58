"""The Arduino boards (firmware/PROTOCOL.md) on pyserial: the pressure board (Uno) and the stepper (Nano).

Opening the port resets an Uno/Nano (DTR): ``open`` waits for the board's ``READY`` line (bootloader, then
``setup()``: about 1.4 s) without sending anything the bootloader would swallow, then identifies it with
``ID?``. Each command carries a tag; the driver waits for the reply with that tag and sets streamed sample
lines aside, stamped with the host receive time (int64 ns, the time the chunk holding the line was read).
Every command is idempotent (absolute targets, set-points, rates), so a timed-out or corrupted exchange is
simply repeated by :meth:`Device._retrying`; an ``ERR`` reply with a tag is the board refusing the command
and raises :class:`BoardReplyError` naming the board, the port, the command and what the board said.
Samples stay raw (ADC counts, microsteps, the board's ``micros()``); conversion to Pa/rad and clock
alignment belong to the pipeline.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass

import serial

from acquisition.codecs import board_lines as bp
from acquisition.devices.base import Device, host_now_ns
from acquisition.errors import (
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceReplyError,
    DeviceTimeoutError,
)

log = logging.getLogger(__name__)
_READ_SLICE_S = 0.005  # serial read timeout: how long one blocking read waits for a first byte
_MAX_RX = 4096  # bytes without a newline before the receive buffer is dropped
_MAX_SAMPLES = 100_000  # samples kept between read_samples() calls (oldest dropped beyond)
_STALE_S = 0.1  # lines arriving this soon after opening were sent before the board's reset


class BoardReplyError(DeviceReplyError):
    """The board answered ``ERR <tag> <code> <name>``: it refused the command (nothing was applied)."""

    def __init__(self, message: str, board: str, port: str, command: str, code: int, name: str) -> None:
        super().__init__(message)
        self.board = board
        self.port = port
        self.command = command
        self.code = code
        self.name = name


_VERBS = {
    bp.BOARD_PRESSURE: frozenset({"ID?", "STREAM", "STOP", "SET", "VALVE"}),
    bp.BOARD_STEPPER: frozenset({"ID?", "STREAM", "STOP", "MOVE", "SPEED", "POS?"}),
}


def describe_error(board: str, command: str, err: bp.Err) -> str:
    """What an ``ERR`` reply to ``command`` means, for a message: the code, its meaning and a hint."""
    verb = (command.split() or [""])[0]
    text = f"ERR {err.code} {err.name}: {bp.ERROR_MEANINGS.get(err.code, 'an error code of another version')}"
    if err.code in (bp.E_ARGS, bp.E_RANGE) and verb in bp.VERB_USAGE:
        text += f" (usage: {bp.VERB_USAGE[verb]})"
    elif err.code == bp.E_UNKNOWN:
        other = [name for name, verbs in _VERBS.items() if name != board and verb in verbs]
        if other:
            text += f" ({verb} is a {other[0]} board command: is this the right port?)"
    return text


@dataclass(frozen=True)
class BoardIdentity:
    """The board's answer to ``ID?``."""

    board: str
    firmware: str
    serial: str


@dataclass(frozen=True)
class PressureSample:
    """One streamed pressure line: host receive time, board sequence and clock, raw ADS1115 counts."""

    host_ns: int
    seq: int
    micros: int  # the board's micros() (wraps at 2³²)
    counts: tuple[int, int]
    valves: int  # bit 0: valve 0 open, bit 1: valve 1 open


@dataclass(frozen=True)
class StepperSample:
    """One stepper state: streamed (``seq`` set) or polled with ``POS?`` (``seq`` None)."""

    host_ns: int
    seq: int | None
    micros: int
    position_steps: int  # microsteps (1/16 step)
    moving: bool


class _Board(Device):
    """Framing, tagged commands, identification and the sample buffer shared by both boards."""

    board = ""

    def __init__(self, port: str, baud: int = bp.BAUD, timeout_s: float = 0.2, retries: int = 2,
                 open_timeout_s: float = 2.5) -> None:  # fmt: skip
        super().__init__(port, retries)
        self.baud = baud
        self.timeout_s = timeout_s
        self.open_timeout_s = open_timeout_s  # how long open() waits for READY (the reset takes ~1.4 s)
        self.identity: BoardIdentity | None = None
        self.bad_lines = 0  # lines dropped for a bad checksum or an unknown shape
        self.dropped_samples = 0
        self._ser: serial.Serial | None = None
        self._rx = bytearray()
        self._replies: deque[tuple[int, bp.Message]] = deque(maxlen=64)
        self.last_reply_ns = 0  # host receive time of the last matched reply
        self._samples: deque = deque(maxlen=_MAX_SAMPLES)
        self._tag = 0
        self._corrupt_since_send = False
        self._opening = False
        self._readies = 0  # READY lines received since the port was opened
        self._lines = 0  # valid lines received since the port was opened
        self.resets = 0  # READY lines while open: the board reset and lost its state (streaming, outputs)

    # ------------------------------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        self._ser = serial.Serial(self.port, self.baud, timeout=_READ_SLICE_S, write_timeout=self.timeout_s)
        self._ser.reset_input_buffer()
        self._rx.clear()
        self._replies.clear()
        self._samples.clear()
        self._readies = self._lines = 0
        self._opening = True
        try:
            ready = self._await_ready()
            try:
                ident = self._retrying("ID?", lambda: self._transact("ID?", self.timeout_s))
            except (DeviceTimeoutError, DeviceProtocolError) as exc:
                seen = "after its READY" if ready else f"and no READY within {self.open_timeout_s} s"
                raise DeviceNotFoundError(f"{exc}, {seen}") from exc
            except DeviceReplyError as exc:
                raise DeviceNotFoundError(f"{self.kind} on {self.port}: ID? refused ({exc})") from exc
        finally:
            self._opening = False
        self._samples.clear()  # lines of a stream from before the reset, or of one that will be restarted
        if not isinstance(ident, bp.Ident) or ident.board != self.board:
            raise DeviceNotFoundError(
                f"{self.kind} on {self.port}: the board there is not a {self.board} board ({ident})"
            )
        self.identity = BoardIdentity(ident.board, ident.firmware, ident.serial)
        log.info("%s on %s: %s firmware %s serial %s", self.kind, self.port, ident.board, ident.firmware,
                 ident.serial)  # fmt: skip

    def _await_ready(self) -> bool:
        """Wait up to ``open_timeout_s`` for READY: opening the port reset the board, and bytes sent to the
        bootloader are lost (Optiboot even answers some). True when READY came. Lines in the first
        ``_STALE_S`` were sent before the reset (bridge and tty buffers); a line after that without READY
        means the board did not reset (auto-reset disabled): False at once. A silent board: False at the
        deadline."""
        start = time.monotonic()
        while (now := time.monotonic()) < start + self.open_timeout_s:
            lines = self._lines
            self._pump(block=True)
            if self._readies:
                return True
            if self._lines > lines and now - start > _STALE_S:
                log.info("%s on %s: lines but no READY: the board did not reset", self.kind, self.port)
                return False
        log.info("%s on %s: no READY within %s s, trying ID?", self.kind, self.port, self.open_timeout_s)
        return False

    def fileno(self) -> int:
        """The port's file descriptor: readable when a line (a streamed sample, a reply) arrives."""
        self._require_open()
        return self._ser.fileno()

    def _close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            finally:
                self._ser = None

    # ----------------------------------------------------------------------------------- commands
    def command(self, body: str) -> bp.Message:
        """Send ``body`` (without tag) and return the board's reply, with retries on timeouts and corrupted
        lines; an ``ERR`` reply raises BoardReplyError (board, port, command, code and name)."""
        self._require_open()
        return self._retrying(body, lambda: self._transact(body, self.timeout_s))

    def start_stream(self, rate_hz: int) -> None:
        """Stream samples at ``rate_hz`` (1–250 Hz, board clock)."""
        self.command(f"STREAM {int(rate_hz)}")

    def stop_stream(self) -> None:
        """Stop streaming (samples already received stay readable)."""
        self.command("STREAM 0")

    def stop(self) -> None:
        """The board's STOP (pressure: safe state; stepper: stop the motor)."""
        self.command("STOP")

    def _take_samples(self) -> list:
        self._require_open()
        self._pump(block=False)
        samples = list(self._samples)
        self._samples.clear()
        return samples

    # ----------------------------------------------------------------------------------- internals
    def _require_open(self) -> None:
        if self._ser is None:
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: not open")

    def _transact(self, body: str, timeout_s: float) -> bp.Message:
        self._tag = (self._tag + 1) % bp.TAG_MODULO
        tag = self._tag
        self._corrupt_since_send = False
        self._write(bp.encode(f"{tag} {body}"))
        deadline = time.monotonic() + timeout_s
        while True:
            while self._replies:
                reply_ns, reply = self._replies.popleft()
                if isinstance(reply, bp.Err) and reply.tag is None:
                    raise DeviceProtocolError(
                        f"the board could not read {body!r}: {describe_error(self.board, body, reply)}"
                    )
                if getattr(reply, "tag", None) != tag:
                    log.debug("%s on %s: stale reply %s", self.kind, self.port, reply)
                    continue
                if isinstance(reply, bp.Err):
                    what = describe_error(self.board, body, reply)
                    raise BoardReplyError(f"{self.kind} on {self.port} refused {body!r}: {what}",
                                          self.board, self.port, body, reply.code, reply.name)  # fmt: skip
                self.last_reply_ns = reply_ns
                return reply
            if time.monotonic() >= deadline:
                if self._corrupt_since_send:
                    raise DeviceProtocolError(f"corrupted reply to {body!r}")
                raise DeviceTimeoutError(f"no reply to {body!r} within {timeout_s} s")
            self._pump(block=True)

    def _write(self, data: bytes) -> None:
        try:
            self._ser.write(data)
        except serial.SerialTimeoutException as exc:
            raise DeviceTimeoutError(f"{self.kind} on {self.port}: write timed out") from exc
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: write failed ({exc})") from exc

    def _pump(self, block: bool) -> None:
        """Read what has arrived (``block``: wait up to one read slice for a first byte) and sort lines."""
        try:
            waiting = self._ser.in_waiting
            data = self._ser.read(waiting if waiting else (1 if block else 0))
            if data and not waiting:
                data += self._ser.read(self._ser.in_waiting)
        except (serial.SerialException, OSError) as exc:
            raise DeviceDisconnectedError(f"{self.kind} on {self.port}: read failed ({exc})") from exc
        if not data:
            return
        stamp = host_now_ns()
        self._rx += data
        while (end := self._rx.find(b"\n")) >= 0:
            line = bytes(self._rx[: end + 1])
            del self._rx[: end + 1]
            self._sort(line, stamp)
        if len(self._rx) > _MAX_RX:
            log.warning("%s on %s: %d bytes without a newline dropped", self.kind, self.port, len(self._rx))
            self._rx.clear()
            self.bad_lines += 1

    def _sort(self, line: bytes, host_ns: int) -> None:
        try:
            message = bp.parse_message(bp.decode(line))
        except ValueError as exc:  # BoardChecksumError, BoardSyntaxError
            self.bad_lines += 1
            self._corrupt_since_send = True
            log.warning("%s on %s: bad line dropped: %s", self.kind, self.port, exc)
            return
        self._lines += 1
        if isinstance(message, bp.PressureLine | bp.StepperLine):
            sample = self._sample(message, host_ns)
            if sample is not None:
                if len(self._samples) == self._samples.maxlen:
                    self.dropped_samples += 1
                self._samples.append(sample)
        elif isinstance(message, bp.Ready):
            self._readies += 1
            if self._opening:
                log.info("%s on %s: %s %s ready", self.kind, self.port, message.board, message.firmware)
            else:
                self.resets += 1
                log.warning("%s on %s: the board reset (READY): streaming stopped, outputs at their defaults",
                            self.kind, self.port)  # fmt: skip
        else:
            self._replies.append((host_ns, message))

    def _sample(self, message: bp.Message, host_ns: int) -> object | None:
        """A streamed line → this board's sample type (None: not this board's kind of line)."""
        raise NotImplementedError


class PressureBoard(_Board):
    """The Uno with the regulators, valves and transducers:
    ``with PressureBoard(port) as pb: pb.set_pressure(0, 1.5e5); pb.start_stream(100); pb.read_samples()``."""

    kind = "pressure board"
    board = bp.BOARD_PRESSURE

    def set_pressure(self, channel: int, pa: float) -> None:
        """Regulator ``channel`` (0/1) set-point in gauge Pa, sent rounded to 1 Pa; the board refuses one
        outside its regulators' span (0–300 kPa: BoardReplyError, RANGE)."""
        if channel not in (0, 1) or not math.isfinite(pa):
            raise ValueError(f"{self.kind} on {self.port}: bad set-point channel {channel} / {pa} Pa")
        self.command(f"SET {channel} {round(pa)}")

    def set_valve(self, channel: int, open: bool) -> None:
        """Energise (open) or release solenoid valve ``channel`` (0/1)."""
        if channel not in (0, 1):
            raise ValueError(f"{self.kind} on {self.port}: no valve {channel}")
        self.command(f"VALVE {channel} {int(bool(open))}")

    def read_samples(self) -> list[PressureSample]:
        """Every streamed sample received since the last call (does not wait for more)."""
        return self._take_samples()

    def _sample(self, message: bp.Message, host_ns: int) -> PressureSample | None:
        if not isinstance(message, bp.PressureLine):
            return None
        return PressureSample(host_ns, message.seq, message.micros, (message.counts0, message.counts1),
                              message.valves)  # fmt: skip


class StepperBoard(_Board):
    """The Nano with the A4988 driving J1: ``with StepperBoard(port) as sb: sb.move_to(3200)``."""

    kind = "stepper board"
    board = bp.BOARD_STEPPER

    def move_to(self, steps: int) -> None:
        """Absolute target in microsteps (±2 000 000)."""
        self.command(f"MOVE {int(steps)}")

    def set_speed(self, steps_per_s: float, accel_steps_per_s2: float) -> None:
        """Maximum speed (1–4000 microsteps/s) and acceleration (1–100 000 microsteps/s²)."""
        self.command(f"SPEED {round(steps_per_s)} {round(accel_steps_per_s2)}")

    def position(self) -> StepperSample:
        """Poll the position now (``POS?``); ``seq`` is None."""
        reply = self.command("POS?")
        if not isinstance(reply, bp.Position):
            raise DeviceProtocolError(f"{self.kind} on {self.port}: POS? answered with {reply}")
        return StepperSample(self.last_reply_ns, None, reply.micros, reply.position_steps, reply.moving)

    def read_samples(self) -> list[StepperSample]:
        """Every streamed sample received since the last call (does not wait for more)."""
        return self._take_samples()

    def _sample(self, message: bp.Message, host_ns: int) -> StepperSample | None:
        if not isinstance(message, bp.StepperLine):
            return None
        return StepperSample(host_ns, message.seq, message.micros, message.position_steps, message.moving)
