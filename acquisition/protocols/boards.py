"""The Arduino boards' ASCII line protocol (firmware/PROTOCOL.md): codec and message parsers.

Every line is ``<BODY>*<XX>\\n`` with XX the XOR of the body bytes as two hex digits (NMEA style). Host
commands start with a tag (0–65535) that the board repeats in its reply; streamed samples carry the board's
sequence number and its wrapping ``micros()`` stamp. Bodies are printable ASCII without ``*``, at most
``MAX_BODY`` bytes.
"""

from __future__ import annotations

from dataclasses import dataclass

BAUD = 250_000  # exact on a 16 MHz AVR (U2X, UBRR = 7)
MAX_BODY = 63  # the firmware's line buffer is 64 bytes (body + NUL)
TAG_MODULO = 65_536
MICROS_MODULO = 1 << 32
SEQ_MODULO = 1 << 32

BOARD_PRESSURE = "PRESSURE"
BOARD_STEPPER = "STEPPER"

# error codes (ERR <tag|-> <code> <name>)
E_CHECKSUM, E_MALFORMED, E_UNKNOWN, E_ARGS, E_RANGE = 1, 2, 3, 4, 5
ERROR_NAMES = {E_CHECKSUM: "CHECKSUM", E_MALFORMED: "MALFORMED", E_UNKNOWN: "UNKNOWN", E_ARGS: "ARGS",
               E_RANGE: "RANGE"}  # fmt: skip

# limits enforced by the firmware (PROTOCOL.md, "Limits")
MAX_SET_PA = 400_000  # set-point limit: the transducers' 0–4 bar range
REGULATOR_FULL_SCALE_PA = 1_000_000  # ASSUMPTION: K8P 0–10 V ↔ 0–10 bar
MAX_STREAM_HZ = 250  # the ADS1115 at 860 SPS, two channels multiplexed: ~430 Hz each; 250 Hz = 11 kB/s of 25
MAX_SPEED_STEPS_S = 4000  # AccelStepper on a 16 MHz AVR
MAX_ACCEL_STEPS_S2 = 100_000
MAX_ABS_STEPS = 2_000_000
MICROSTEPS = 16  # A4988 with MS1–MS3 high
FULL_STEPS_PER_REV = 200
ADC_LSB_V = 125e-6  # ADS1115 at ±4.096 V


class BoardChecksumError(ValueError):
    """A line is not ``<BODY>*<XX>\\n`` or its checksum does not match."""


class BoardSyntaxError(ValueError):
    """A line's body (checksum fine) is not a message of the protocol."""


def checksum(body: bytes) -> int:
    """XOR of the body bytes (0–255)."""
    value = 0
    for byte in body:
        value ^= byte
    return value


def encode(body: str) -> bytes:
    """``body`` → ``b'<body>*<XX>\\n'``; raises ValueError on a body the protocol cannot carry."""
    raw = body.encode("ascii")
    if len(raw) > MAX_BODY or b"*" in raw or any(b < 0x20 or b > 0x7E for b in raw):
        raise ValueError(f"not a valid line body: {body!r}")
    return raw + b"*%02X\n" % checksum(raw)


def decode(line: bytes) -> str:
    """``b'<body>*<XX>\\n'`` (``\\r\\n`` accepted) → body; raises BoardChecksumError."""
    stripped = line.rstrip(b"\r\n")
    body, star, tail = stripped.rpartition(b"*")
    if not star or len(tail) != 2 or len(body) > MAX_BODY:
        raise BoardChecksumError(f"malformed line {line!r}")
    try:
        expected = int(tail, 16)
        text = body.decode("ascii")
    except (ValueError, UnicodeDecodeError) as exc:
        raise BoardChecksumError(f"malformed line {line!r}") from exc
    if checksum(body) != expected:
        raise BoardChecksumError(f"checksum mismatch in {line!r}: computed {checksum(body):02X}")
    return text


# ----------------------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class Command:
    """A host command: ``<tag> <VERB> [args]`` (arguments still text; the board checks them)."""

    tag: int
    verb: str
    args: tuple[str, ...]


@dataclass(frozen=True)
class Ok:
    """``OK <tag> <verb>``: the command was applied."""

    tag: int
    verb: str


@dataclass(frozen=True)
class Err:
    """``ERR <tag|-> <code> <name>``; ``tag`` is None when the board could not read it (bad line)."""

    tag: int | None
    code: int
    name: str


@dataclass(frozen=True)
class Ident:
    """``ID <tag> <board> <firmware> <serial>``."""

    tag: int
    board: str
    firmware: str
    serial: str


@dataclass(frozen=True)
class Position:
    """``POS <tag> <micros> <position_steps> <moving>`` (stepper board's answer to ``POS?``)."""

    tag: int
    micros: int
    position_steps: int
    moving: bool


@dataclass(frozen=True)
class Ready:
    """``READY <board> <firmware>``: sent once after a reset."""

    board: str
    firmware: str


@dataclass(frozen=True)
class PressureLine:
    """``P <seq> <micros> <counts0> <counts1> <valve bits>`` (streamed, raw ADS1115 counts)."""

    seq: int
    micros: int
    counts0: int
    counts1: int
    valves: int


@dataclass(frozen=True)
class StepperLine:
    """``S <seq> <micros> <position_steps> <moving>`` (streamed)."""

    seq: int
    micros: int
    position_steps: int
    moving: bool


Message = Ok | Err | Ident | Position | Ready | PressureLine | StepperLine


def _int(text: str, low: int, high: int, what: str) -> int:
    try:
        value = int(text, 10)
    except ValueError as exc:
        raise BoardSyntaxError(f"{what} {text!r} is not an integer") from exc
    if not low <= value <= high:
        raise BoardSyntaxError(f"{what} {value} outside {low}..{high}")
    return value


def _u32(text: str, what: str) -> int:
    return _int(text, 0, MICROS_MODULO - 1, what)


def _flag(text: str, what: str) -> bool:
    return bool(_int(text, 0, 1, what))


def parse_tag(text: str) -> int:
    """A command/reply tag (0–65535); raises BoardSyntaxError."""
    if not text.isdigit():
        raise BoardSyntaxError(f"tag {text!r} is not a decimal number")
    return _int(text, 0, TAG_MODULO - 1, "tag")


def parse_command(body: str) -> Command:
    """Host → board body → Command; raises BoardSyntaxError when there is no tag or verb."""
    fields = body.split()
    if len(fields) < 2:
        raise BoardSyntaxError(f"command {body!r} needs a tag and a verb")
    return Command(parse_tag(fields[0]), fields[1], tuple(fields[2:]))


def parse_message(body: str) -> Message:
    """Board → host body → one of the message dataclasses; raises BoardSyntaxError."""
    fields = body.split()
    if not fields:
        raise BoardSyntaxError("empty message")
    kind, rest = fields[0], fields[1:]
    shape = {"OK": 2, "ERR": 3, "ID": 4, "POS": 4, "READY": 2, "P": 5, "S": 4}
    if kind not in shape:
        raise BoardSyntaxError(f"unknown message {body!r}")
    if len(rest) != shape[kind]:
        raise BoardSyntaxError(f"{kind} needs {shape[kind]} fields: {body!r}")
    if kind == "OK":
        return Ok(parse_tag(rest[0]), rest[1])
    if kind == "ERR":
        tag = None if rest[0] == "-" else parse_tag(rest[0])
        return Err(tag, _int(rest[1], 0, 255, "error code"), rest[2])
    if kind == "ID":
        return Ident(parse_tag(rest[0]), rest[1], rest[2], rest[3])
    if kind == "POS":
        return Position(parse_tag(rest[0]), _u32(rest[1], "micros"), _int(rest[2], -(1 << 31), (1 << 31) - 1,
                        "position"), _flag(rest[3], "moving"))  # fmt: skip
    if kind == "READY":
        return Ready(rest[0], rest[1])
    if kind == "P":
        return parse_pressure_line(rest)
    return parse_stepper_line(rest)


def parse_pressure_line(fields: list[str]) -> PressureLine:
    """The fields after ``P`` → PressureLine; raises BoardSyntaxError."""
    return PressureLine(
        _u32(fields[0], "seq"),
        _u32(fields[1], "micros"),
        _int(fields[2], -32768, 32767, "counts0"),
        _int(fields[3], -32768, 32767, "counts1"),
        _int(fields[4], 0, 3, "valve bits"),
    )


def parse_stepper_line(fields: list[str]) -> StepperLine:
    """The fields after ``S`` → StepperLine; raises BoardSyntaxError."""
    return StepperLine(
        _u32(fields[0], "seq"),
        _u32(fields[1], "micros"),
        _int(fields[2], -(1 << 31), (1 << 31) - 1, "position"),
        _flag(fields[3], "moving"),
    )
