"""The Arduino boards' ASCII line protocol (firmware/PROTOCOL.md): codec and message parsers.

Every line is ``<BODY>*<XX>\\n`` with XX the XOR of the body bytes as two hex digits (NMEA style). Host
commands start with a tag (0–65535) that the board repeats in its reply; streamed samples carry the board's
sequence number and its wrapping ``micros()`` stamp. Bodies are printable ASCII without ``*``, at most
``MAX_BODY`` bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import reduce
from operator import xor

from acquisition.errors import CodecError

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

# what each error code means (PROTOCOL.md, "Errors"), for messages a user can act on
ERROR_MEANINGS = {
    E_CHECKSUM: "the line's checksum did not match (a transport error: resend)",
    E_MALFORMED: "the board could not read the line (no *XX, too long, non-printable bytes, no tag or verb)",
    E_UNKNOWN: "the board has no such command",
    E_ARGS: "wrong number of arguments, or one is not a decimal integer",
    E_RANGE: "an argument is outside its limits (nothing was applied)",
}

# limits enforced by the firmware (PROTOCOL.md, "Commands"); keep firmware/*.ino in step
MAX_SET_PA = 300_000  # set-point limit: the regulators' 0–3 bar span (robot description: regulator_max_pa)
REGULATOR_FULL_SCALE_PA = 1_000_000  # ASSUMPTION: K8P 0–10 V ↔ 0–10 bar
MAX_STREAM_HZ = 250  # the ADS1115 at 860 SPS, two channels multiplexed: ~430 Hz each; 250 Hz = 11 kB/s of 25
MAX_SPEED_STEPS_S = 4000  # AccelStepper on a 16 MHz AVR
MAX_ACCEL_STEPS_S2 = 100_000
MAX_ABS_STEPS = 2_000_000
MAX_TAG_DIGITS = 5  # the firmware refuses longer tags (leading zeros included) as MALFORMED
MAX_ARGS = 3  # the firmware answers ARGS to a line with more arguments, whatever the verb
BOOT_S = 1.4  # DTR reset → READY: Optiboot's 3 LED flashes (6 × 62.5 ms) + its 1 s watchdog, then setup()
MICROSTEPS = 16  # A4988 with MS1–MS3 high
FULL_STEPS_PER_REV = 200
ADC_LSB_V = 125e-6  # ADS1115 at ±4.096 V

# each verb's arguments and limits, for error messages (PROTOCOL.md, "Commands")
VERB_USAGE = {
    "ID?": "ID? takes no argument",
    "STREAM": f"STREAM <rate_hz 0–{MAX_STREAM_HZ}>",
    "STOP": "STOP takes no argument",
    "SET": f"SET <channel 0–1> <pa 0–{MAX_SET_PA}>",
    "VALVE": "VALVE <channel 0–1> <0|1>",
    "MOVE": f"MOVE <steps −{MAX_ABS_STEPS}…{MAX_ABS_STEPS}>",
    "SPEED": f"SPEED <steps_per_s 1–{MAX_SPEED_STEPS_S}> <accel 1–{MAX_ACCEL_STEPS_S2}>",
    "POS?": "POS? takes no argument",
}


class BoardChecksumError(CodecError):
    """A line is not ``<BODY>*<XX>\\n`` or its checksum does not match."""


class BoardSyntaxError(CodecError):
    """A line's body (checksum fine) is not a message of the protocol."""


def checksum(body: bytes) -> int:
    """XOR of the body bytes (0–255)."""
    return reduce(xor, body, 0)


def encode(body: str) -> bytes:
    """``body`` → ``b'<body>*<XX>\\n'``; raises ValueError on a body the protocol cannot carry."""
    raw = body.encode("ascii")
    if len(raw) > MAX_BODY or b"*" in raw or any(b < 0x20 or b > 0x7E for b in raw):
        raise ValueError(f"not a valid line body: {body!r}")
    return raw + b"*%02X\n" % checksum(raw)


_HEX = frozenset(b"0123456789ABCDEFabcdef")


def frame_error(line: bytes) -> int:
    """The firmware's verdict on one received line (without its ``\\n``): 0 when it is ``<BODY>*<XX>``
    with a matching checksum, else E_MALFORMED or E_CHECKSUM. One ``\\r`` before the end is tolerated;
    the checksum starts at the last ``*``; the body is at most MAX_BODY printable bytes (VslLink
    ``handleLine``)."""
    if line.endswith(b"\r"):
        line = line[:-1]
    if len(line) < 3 or line[-3] != 0x2A or 0x2A in line[-2:] or len(line) - 3 > MAX_BODY:
        return E_MALFORMED
    body = line[:-3]
    if any(b < 0x20 or b > 0x7E for b in body) or line[-2] not in _HEX or line[-1] not in _HEX:
        return E_MALFORMED
    return E_CHECKSUM if checksum(body) != int(line[-2:], 16) else 0


def decode(line: bytes) -> str:
    """``b'<body>*<XX>\\n'`` (``\\r\\n`` accepted) → body, by the firmware's rules (``frame_error``); raises
    BoardChecksumError."""
    stripped = line[:-1] if line.endswith(b"\n") else line
    error = frame_error(stripped)
    body = (stripped[:-1] if stripped.endswith(b"\r") else stripped)[:-3]
    if error == E_CHECKSUM:
        raise BoardChecksumError(f"checksum mismatch in {line!r}: computed {checksum(body):02X}")
    if error:
        raise BoardChecksumError(f"malformed line {line!r}")
    return body.decode("ascii")


# ----------------------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class Command:
    """A host command: ``<tag> <VERB> [args]`` (arguments still text; the board checks them)."""

    tag: int
    verb: str
    args: tuple[str, ...]


@dataclass(frozen=True)
class TaggedReply:
    """A reply to a command the board could read: it repeats the command's tag (an ``Err`` may not)."""

    tag: int


@dataclass(frozen=True)
class Ok(TaggedReply):
    """``OK <tag> <verb>``: the command was applied."""

    verb: str


@dataclass(frozen=True)
class Err:
    """``ERR <tag|-> <code> <name>``; ``tag`` is None when the board could not read it (bad line)."""

    tag: int | None
    code: int
    name: str


@dataclass(frozen=True)
class Ident(TaggedReply):
    """``ID <tag> <board> <firmware> <serial>``."""

    board: str
    firmware: str
    serial: str


@dataclass(frozen=True)
class Position(TaggedReply):
    """``POS <tag> <micros> <position_steps> <moving>`` (stepper board's answer to ``POS?``)."""

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
    """A command/reply tag: 1–5 decimal digits, 0–65535 (the firmware's rule); raises BoardSyntaxError."""
    if not (text.isascii() and text.isdigit() and len(text) <= MAX_TAG_DIGITS):
        raise BoardSyntaxError(f"tag {text!r} is not a decimal number of at most {MAX_TAG_DIGITS} digits")
    return _int(text, 0, TAG_MODULO - 1, "tag")


def split_fields(body: str) -> list[str]:
    """A body's fields: separated by one or more spaces (the firmware's ``strtok(body, " ")``)."""
    return [field for field in body.split(" ") if field]


def parse_command(body: str) -> Command:
    """Host → board body → Command; raises BoardSyntaxError when there is no tag or verb."""
    fields = split_fields(body)
    if len(fields) < 2:
        raise BoardSyntaxError(f"command {body!r} needs a tag and a verb")
    return Command(parse_tag(fields[0]), fields[1], tuple(fields[2:]))


def parse_message(body: str) -> Message:
    """Board → host body → one of the message dataclasses; raises BoardSyntaxError."""
    fields = split_fields(body)
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
