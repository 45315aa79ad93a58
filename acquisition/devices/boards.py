"""The Arduino boards (firmware/PROTOCOL.md) on pyserial: the pressure board (Uno) and the stepper (Nano).

Each command carries a tag; the driver waits for the reply with that tag and sets streamed sample lines
aside, stamped with the host receive time (int64 ns, the time the chunk holding the line was read). Every
command is idempotent (absolute targets, set-points, rates), so a timed-out or corrupted exchange is simply
repeated by :meth:`Device._retrying`. Samples stay raw (ADC counts, microsteps, the board's ``micros()``);
conversion to Pa/rad and clock alignment belong to the pipeline.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import dataclass

import serial

from acquisition.devices.base import Device, host_now_ns
from acquisition.errors import (
    DeviceDisconnectedError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceReplyError,
    DeviceTimeoutError,
)
from acquisition.protocols import boards as bp

log = logging.getLogger(__name__)
_READ_SLICE_S = 0.005  # serial read timeout: how long one blocking read waits for a first byte
_MAX_RX = 4096  # bytes without a newline before the receive buffer is dropped
_MAX_SAMPLES = 100_000  # samples kept between read_samples() calls (oldest dropped beyond)


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
        self.open_timeout_s = open_timeout_s  # an Uno resets when the port opens: ~1.6 s of bootloader
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

    # ------------------------------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        self._ser = serial.Serial(self.port, self.baud, timeout=_READ_SLICE_S, write_timeout=self.timeout_s)
        self._ser.reset_input_buffer()
        self._rx.clear()
        self._replies.clear()
        self._samples.clear()
        deadline = time.monotonic() + self.open_timeout_s
        last: Exception | None = None
        while time.monotonic() < deadline:
            try:
                ident = self._transact("ID?", min(self.timeout_s, max(0.0, deadline - time.monotonic())))
            except (DeviceTimeoutError, DeviceProtocolError) as exc:
                last = exc
                continue
            except DeviceReplyError as exc:
                raise DeviceNotFoundError(f"{self.kind} on {self.port}: ID? refused ({exc})") from exc
            if not isinstance(ident, bp.Ident) or ident.board != self.board:
                raise DeviceNotFoundError(
                    f"{self.kind} on {self.port}: the board there is not a {self.board} board ({ident})"
                )
            self.identity = BoardIdentity(ident.board, ident.firmware, ident.serial)
            log.info("%s on %s: %s firmware %s serial %s", self.kind, self.port, ident.board, ident.firmware,
                     ident.serial)  # fmt: skip
            return
        raise DeviceNotFoundError(
            f"{self.kind} on {self.port}: no answer to ID? within {self.open_timeout_s} s ({last})"
        )

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
        """Send ``body`` (without tag) and return the board's reply, with retries; ERR → DeviceReplyError."""
        self._require_open()
        return self._retrying(body, lambda: self._transact(body, self.timeout_s))

    def start_stream(self, rate_hz: int) -> None:
        """Stream samples at ``rate_hz`` (1–200 Hz, board clock)."""
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
                    raise DeviceProtocolError(f"the board could not read {body!r} ({reply.name})")
                if getattr(reply, "tag", None) != tag:
                    log.debug("%s on %s: stale reply %s", self.kind, self.port, reply)
                    continue
                if isinstance(reply, bp.Err):
                    raise DeviceReplyError(
                        f"{self.kind} on {self.port}: {body!r} refused: ERR {reply.code} {reply.name}"
                    )
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
        if isinstance(message, bp.PressureLine | bp.StepperLine):
            sample = self._sample(message, host_ns)
            if sample is not None:
                if len(self._samples) == self._samples.maxlen:
                    self.dropped_samples += 1
                self._samples.append(sample)
        elif isinstance(message, bp.Ready):
            log.info("%s on %s: board reset (%s %s)", self.kind, self.port, message.board, message.firmware)
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
        """Regulator ``channel`` (0/1) set-point in gauge Pa (0–400 kPa, sent rounded to 1 Pa)."""
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
