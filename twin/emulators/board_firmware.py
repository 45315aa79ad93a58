"""The two Arduino boards (pressure: Uno + ADS1115 + L298; stepper: Nano + A4988), byte for byte.

Both speak firmware/PROTOCOL.md the way the firmware does: the receive side is VslLink ported line for line
(buffer, framing, checksum, tokenising, error replies), checked against the host-compiled sketches with the
vector table ``firmware/vectors.json``. Opening the port resets the board as DTR resets an Uno: the pty host
calls ``port_opened``, the bootloader runs ``boot_s`` (input is lost), then the sketch starts from scratch
(streaming off, set-points 0, valves released, stepper count 0, ``micros()`` from 0) and sends READY.

What stands behind a board is a small "hardware" interface (``board_hardware``: the twin in the rig, or
``SimplePressureHardware``/``SimpleStepperHardware``). Setters carry no time, so before each command
the emulator brings the hardware up to ``now_s`` (``advance``/``position``). Streaming is scheduled on the
board's own (drifting, wrapping) clock exactly like the firmware: at most one line per loop, never faster
than the rate, missed periods are skipped. The hardware also inverts its clock (``micros_due_s``), so the
emulator can tell the pty host when the next line is due (``next_output_s``) and the host need not poll.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

from acquisition.codecs import board_lines as bp
from twin.emulators.base import Emulator
from twin.emulators.board_hardware import (
    PressureHardware,
    SimplePressureHardware,
    SimpleStepperHardware,
    StepperHardware,
)

log = logging.getLogger(__name__)
FIRMWARE_VERSION = "1.0.0"
_HALF_WRAP = bp.MICROS_MODULO // 2
CATCH_UP_S = 0.1  # a late rig's samples are taken at their own times this far back (RecentSteps: 128 ms)
_RX_CAPACITY = bp.MAX_BODY + 4  # VslLink rxBuf[MAX_BODY + 5]: bytes kept before the '\n' (NUL last)
STEPPER_SPEED_AT_RESET = 1000.0  # stepper_board.ino setup(): microsteps/s
STEPPER_ACCEL_AT_RESET = 5000.0  # microsteps/s²


class _Cmd(NamedTuple):
    """A tokenised command; ``tag`` is the text the host sent (the firmware echoes it as it came)."""

    tag: str
    verb: str
    args: tuple[str, ...]


class _LineBoard(Emulator):
    """VslLink (firmware/libraries/VslLink) in Python: receive buffer, framing, checksum, tokenising, error
    replies and the micros()-based stream scheduler; and the board's resets (DTR on open, see
    ``port_opened``; a USB replug, see ``reset_link``)."""

    board = ""
    serial_number = ""
    resets_on_open = True

    def __init__(self, boot_s: float = bp.BOOT_S) -> None:
        self.boot_s = boot_s
        self.resets = 0  # DTR resets (port opens) so far
        self._boot_until_s: float | None = None  # while the bootloader runs: when the sketch starts
        self._micros_base = 0  # the hardware clock's count at which the sketch's micros() reads 0
        self._anchor_due = False  # micros() is anchored to the hardware clock when the sketch starts
        self._start_sketch()

    def _start_sketch(self) -> None:
        """The sketch's RAM from scratch (setup()): empty receive buffer, streaming off, seq 0, READY due."""
        self._rx = bytearray()
        self._overflow = False
        self.stream_hz = 0
        self._period_us = 0
        self._next_us = 0
        self.seq = 0
        self._ready_due = True
        self._due_s: float | None = None  # cached rig time of the next streamed line (None: not known)

    # ---------------------------------------------------------------------------------------- resets
    def reset_link(self) -> None:
        """A USB replug: the board was unpowered, its sketch starts again (power-on runs no bootloader; the
        DTR reset when the host opens the new port follows in ``port_opened``)."""
        self._start_sketch()
        self._boot_until_s = None

    def port_opened(self, now_s: float) -> None:
        """DTR rose (a process opened the port that nobody had open): the board resets. Outputs fall to their
        reset state at once, the bootloader owns the UART for ``boot_s`` (bytes sent then are lost), then the
        sketch starts from scratch, its ``micros()`` from 0, and sends READY."""
        self._touch(now_s)
        self._reset_outputs(now_s)
        self._start_sketch()
        self.resets += 1
        self._boot_until_s = now_s + self.boot_s
        boot_us = round(self.boot_s * 1e6)
        self._micros_base = (self._hw_micros(now_s) + boot_us) % bp.MICROS_MODULO
        self._anchor_due = True  # the bootloader's time on the board's own clock is known once it ends
        log.debug("%s reset by a port open at %.3f s", self.name, now_s)

    def booting(self, now_s: float) -> bool:
        """Whether the bootloader still runs (the board ignores input)."""
        return self._boot_until_s is not None and now_s < self._boot_until_s

    # ---------------------------------------------------------------------------------- serial link
    def feed(self, data: bytes, now_s: float) -> bytes:
        """VslLink ``pollSerial``: bytes up to ``\\n`` are one line; a line longer than the buffer is
        discarded and answered MALFORMED; every line gets exactly one reply."""
        self._due_s = None  # a command may change the stream
        if self.booting(now_s):
            return b""  # the bootloader has the UART
        out = bytearray(self._take_ready())
        for byte in data:
            if byte == 0x0A:
                if self._overflow:
                    out += _error("-", bp.E_MALFORMED)
                else:
                    out += self._line(bytes(self._rx), now_s)
                self._rx.clear()
                self._overflow = False
            elif len(self._rx) >= _RX_CAPACITY:
                self._overflow = True  # discard up to the next '\n'
            else:
                self._rx.append(byte)
        return bytes(out)

    def _line(self, line: bytes, now_s: float) -> bytes:
        """VslLink ``handleLine`` + ``dispatch``: framing and checksum, then tag, verb and at most 3 args."""
        error = bp.frame_error(line)
        if error:
            return _error("-", error)
        body = (line[:-1] if line.endswith(b"\r") else line)[:-3].decode("ascii")
        fields = bp.split_fields(body)
        if len(fields) < 2 or not _is_tag(fields[0]):
            return _error("-", bp.E_MALFORMED)
        cmd = _Cmd(fields[0], fields[1], tuple(fields[2:]))
        if len(cmd.args) > bp.MAX_ARGS:
            return _error(cmd.tag, bp.E_ARGS)
        self._touch(now_s)
        try:
            return bp.encode(self._command(cmd, now_s))
        except _Reject as exc:
            return _error(cmd.tag, exc.code)

    def _command(self, cmd: _Cmd, now_s: float) -> str:
        if cmd.verb == "ID?":
            _nargs(cmd, 0)
            return f"ID {cmd.tag} {self.board} {FIRMWARE_VERSION} {self.serial_number}"
        if cmd.verb == "STREAM":
            _nargs(cmd, 1)
            rate = _arg(cmd.args[0], 0, bp.MAX_STREAM_HZ)
            self.stream_hz = rate
            if rate:
                self._period_us = 1_000_000 // rate
                self._next_us = self._micros(now_s)  # first line on the next loop
            return f"OK {cmd.tag} STREAM"
        raise _Reject(bp.E_UNKNOWN)

    # ------------------------------------------------------------------------------------ streaming
    def next_output_s(self, now_s: float) -> float | None:
        """READY when the sketch starts (at once after power-up, ``boot_s`` after a DTR reset); then the next
        streamed line, at the rig time the board's clock reaches it (exact: the hardware inverts its clock;
        cached until the next poll or command)."""
        if self.booting(now_s):
            return self._boot_until_s
        if self._ready_due:
            return now_s
        if not self.stream_hz:
            return None
        if self._due_s is None:
            self._due_s = self._micros_due_s(self._next_us, now_s)
        return self._due_s

    def poll(self, now_s: float) -> bytes:
        """The lines due by ``now_s``: every sample the sketch took since the last poll, each at its own time.
        The board's loop is not late when the rig is (the rig's process waits on the host computer, the
        board on nothing): a sample the rig comes to late is taken at the time it was due (the twin's recent
        steps, ``twin.devices.RecentSteps``) and stamped with the micros() it was due at. Before, one
        sample a poll and a resynchronised schedule dropped the samples of every stretch the rig fell a
        period behind, the numbering going on: CI's pressure stream came to 245 of 250 a second, nothing
        counted lost. Only samples due more than ``CATCH_UP_S`` ago (a rig stopped longer than its recent
        steps reach) are skipped."""
        self._due_s = None
        if self.booting(now_s):
            return b""
        out = self._take_ready()
        if not self.stream_hz:
            return out
        now_us = self._micros(now_s)
        lines = []
        while (now_us - self._next_us) % bp.MICROS_MODULO < _HALF_WRAP:  # due
            at_us = self._next_us
            self._next_us = (self._next_us + self._period_us) % bp.MICROS_MODULO
            late_us = (now_us - at_us) % bp.MICROS_MODULO
            if late_us > round(CATCH_UP_S * 1e6):  # older than the twin's recent steps: skipped, as by
                continue  # a board that stopped
            at_s = now_s - late_us * 1e-6  # on the board's clock: its drift (≤ 0.2 %) moves it ≤ 0.2 ms
            lines.append(bp.encode(self._sample_body(at_s, at_us)))
            self.seq = (self.seq + 1) % bp.SEQ_MODULO
        return out + b"".join(lines)

    def _take_ready(self) -> bytes:
        """READY once after each start of the sketch (setup() sends it before the first loop)."""
        if not self._ready_due:
            return b""
        self._ready_due = False
        return bp.encode(f"READY {self.board} {FIRMWARE_VERSION}")

    # --------------------------------------------------------------------------------------- clocks
    def _micros(self, now_s: float) -> int:
        """The sketch's ``micros()``: the hardware clock since the last reset."""
        self._anchor(now_s)
        return (self._hw_micros(now_s) - self._micros_base) % bp.MICROS_MODULO

    def _anchor(self, now_s: float) -> None:
        """Once the sketch has started after a DTR reset: its ``micros()`` reads 0 at the rig time the
        bootloader ended, on the board's own clock (``boot_s`` of rig time is not ``boot_s`` of a drifting
        board's: a slow board's first sample read up to ms before 0, i.e. just below the wrap)."""
        if self._anchor_due and not self.booting(now_s):
            late_us = round((now_s - self._boot_until_s) * 1e6)
            self._micros_base = (self._hw_micros(now_s) - late_us) % bp.MICROS_MODULO
            self._anchor_due = False

    def _micros_due_s(self, micros: int, now_s: float) -> float:
        """The rig time at which the sketch's ``micros()`` reads ``micros``."""
        self._anchor(now_s)
        return self._hw_micros_due_s((micros + self._micros_base) % bp.MICROS_MODULO, now_s)

    # hooks
    def _touch(self, now_s: float) -> None:
        """Bring the hardware model up to ``now_s`` before a command changes it."""

    def _reset_outputs(self, now_s: float) -> None:
        """Outputs as the board's reset leaves them (pins high-impedance, then ``setup()``)."""

    def _hw_micros(self, now_s: float) -> int:
        raise NotImplementedError

    def _hw_micros_due_s(self, micros: int, now_s: float) -> float:
        """The rig time at which the hardware's clock reads ``micros`` (see ``micros_due_s``)."""
        raise NotImplementedError

    def _sample_body(self, now_s: float, now_us: int) -> str:
        raise NotImplementedError


class _Reject(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(bp.ERROR_NAMES[code])
        self.code = code


def _error(tag: str, code: int) -> bytes:
    """``ERR <tag|-> <code> <name>`` (VslLink ``sendError``)."""
    return bp.encode(f"ERR {tag} {code} {bp.ERROR_NAMES[code]}")


def _is_tag(text: str) -> bool:
    """VslLink ``dispatch``: at most 5 decimal digits, at most 65535."""
    if not text or len(text) > bp.MAX_TAG_DIGITS or any(c not in "0123456789" for c in text):
        return False
    return int(text) < bp.TAG_MODULO


def _nargs(cmd: _Cmd, n: int) -> None:
    if len(cmd.args) != n:
        raise _Reject(bp.E_ARGS)


def _arg(text: str, low: int, high: int) -> int:
    """VslLink ``parseArg``: an optional sign and 1–10 decimal digits (else ERR ARGS), within limits (else
    ERR RANGE)."""
    digits = text[1:] if text[:1] in ("+", "-") else text
    if not digits or len(digits) > 10 or not all(c in "0123456789" for c in digits):
        raise _Reject(bp.E_ARGS)
    value = int(text)
    if not low <= value <= high:
        raise _Reject(bp.E_RANGE)
    return value


class PressureBoardEmulator(_LineBoard):
    """The Uno: SET, VALVE, STREAM, STOP, ID? (PROTOCOL.md). ``max_set_pa`` is the firmware's compiled-in
    set-point limit (``MAX_SET_PA`` in pressure_board.ino)."""

    name = "pressure_board"
    board = bp.BOARD_PRESSURE

    def __init__(self, hardware: PressureHardware, serial_number: str = "VSLP-0001",
                 max_set_pa: int = bp.MAX_SET_PA, boot_s: float = bp.BOOT_S) -> None:  # fmt: skip
        self.hw = hardware
        self.serial_number = serial_number
        self.max_set_pa = max_set_pa
        self.valves = 0
        super().__init__(boot_s)

    def _touch(self, now_s: float) -> None:
        self.hw.advance(now_s)

    def _reset_outputs(self, now_s: float) -> None:
        self._safe_state()

    def _safe_state(self) -> None:
        for channel in (0, 1):
            self.hw.set_pressure(channel, 0.0)
            self.hw.set_valve(channel, False)
        self.valves = 0

    def _hw_micros(self, now_s: float) -> int:
        return self.hw.micros(now_s)

    def _hw_micros_due_s(self, micros: int, now_s: float) -> float:
        return self.hw.micros_due_s(micros, now_s)

    def _command(self, cmd: _Cmd, now_s: float) -> str:
        if cmd.verb == "SET":
            _nargs(cmd, 2)
            channel, pa = _arg(cmd.args[0], 0, 1), _arg(cmd.args[1], 0, self.max_set_pa)
            self.hw.set_pressure(channel, float(pa))
            return f"OK {cmd.tag} SET"
        if cmd.verb == "VALVE":
            _nargs(cmd, 2)
            channel, state = _arg(cmd.args[0], 0, 1), _arg(cmd.args[1], 0, 1)
            self.hw.set_valve(channel, bool(state))
            self.valves = (self.valves & ~(1 << channel)) | (state << channel)
            return f"OK {cmd.tag} VALVE"
        if cmd.verb == "STOP":
            _nargs(cmd, 0)
            self._safe_state()
            self.stream_hz = 0
            return f"OK {cmd.tag} STOP"
        return super()._command(cmd, now_s)

    def _sample_body(self, now_s: float, now_us: int) -> str:
        c0, c1 = self.hw.sample(now_s)
        return f"P {self.seq} {now_us} {c0} {c1} {self.valves}"


class StepperBoardEmulator(_LineBoard):
    """The Nano: MOVE, SPEED, POS?, STOP, STREAM, ID? (PROTOCOL.md). Positions are counted from where the
    board last reset (``setCurrentPosition(0)`` in setup()): the hardware's count minus ``zero``."""

    name = "stepper_board"
    board = bp.BOARD_STEPPER

    def __init__(self, hardware: StepperHardware, serial_number: str = "VSLS-0001",
                 boot_s: float = bp.BOOT_S) -> None:  # fmt: skip
        self.hw = hardware
        self.serial_number = serial_number
        self.zero = 0  # the hardware's position (microsteps) where the board's count reads 0
        super().__init__(boot_s)

    def _touch(self, now_s: float) -> None:
        self.hw.position(now_s)

    def _reset_outputs(self, now_s: float) -> None:
        self.hw.stop()  # no STEP pulses while the board resets
        self.hw.set_speed(STEPPER_SPEED_AT_RESET, STEPPER_ACCEL_AT_RESET)
        self.zero = self.hw.position(now_s)

    def _hw_micros(self, now_s: float) -> int:
        return self.hw.micros(now_s)

    def _hw_micros_due_s(self, micros: int, now_s: float) -> float:
        return self.hw.micros_due_s(micros, now_s)

    def _position(self, now_s: float) -> int:
        return self.hw.position(now_s) - self.zero

    def _command(self, cmd: _Cmd, now_s: float) -> str:
        if cmd.verb == "MOVE":
            _nargs(cmd, 1)
            self.hw.move_to(_arg(cmd.args[0], -bp.MAX_ABS_STEPS, bp.MAX_ABS_STEPS) + self.zero)
            return f"OK {cmd.tag} MOVE"
        if cmd.verb == "SPEED":
            _nargs(cmd, 2)
            speed = _arg(cmd.args[0], 1, bp.MAX_SPEED_STEPS_S)
            accel = _arg(cmd.args[1], 1, bp.MAX_ACCEL_STEPS_S2)
            self.hw.set_speed(float(speed), float(accel))
            return f"OK {cmd.tag} SPEED"
        if cmd.verb == "STOP":
            _nargs(cmd, 0)
            self.hw.stop()
            return f"OK {cmd.tag} STOP"
        if cmd.verb == "POS?":
            _nargs(cmd, 0)
            moving = int(self.hw.moving(now_s))
            return f"POS {cmd.tag} {self._micros(now_s)} {self._position(now_s)} {moving}"
        return super()._command(cmd, now_s)

    def _sample_body(self, now_s: float, now_us: int) -> str:
        moving = int(self.hw.moving(now_s))
        return f"S {self.seq} {now_us} {self._position(now_s)} {moving}"


def demo_pressure_board() -> PressureBoardEmulator:
    """The pressure board on ``SimplePressureHardware`` (+1500 ppm clock), for ``twin.serve``."""
    return PressureBoardEmulator(SimplePressureHardware())


def demo_stepper_board() -> StepperBoardEmulator:
    """The stepper board on ``SimpleStepperHardware``, for ``twin.serve``."""
    return StepperBoardEmulator(SimpleStepperHardware())
