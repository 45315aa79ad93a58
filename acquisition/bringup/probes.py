"""What answers on a serial port, asked only with reads and pings, each awaited no longer than its wire
allows.

Each probe's timeout is the exchange's time on the wire at the baud tried (``bus_budget.SerialLink``), plus
the device's slowest response time, plus a full FTDI latency-timer period at its factory setting (16 ms: an
adapter nobody has set yet), plus ``HOST_SLACK_S`` for a busy host to get round to reading. Nothing here
writes a setting to a device: a Dynamixel broadcast ping and one-byte reads (the real dynamixel-sdk), the
Aurora's ``VER:0`` (CRC-16/ARC, at 9,600 baud, its baud after a reset), a board's ``ID?`` (our line protocol,
firmware/PROTOCOL.md), an slcan adapter's ``V``.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import serial
from dynamixel_sdk import COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler, PortHandler

from acquisition.codecs import board_lines as bp
from acquisition.codecs import dynamixel as dx
from acquisition.codecs import ndi
from acquisition.devices.bus_budget import (
    DYNAMIXEL_BAUDS,
    DYNAMIXEL_FACTORY_BAUD,
    DYNAMIXEL_RETURN_DELAY_UNIT_S,
    FTDI_DEFAULT_LATENCY_S,
    SerialLink,
)
from acquisition.errors import CodecError

log = logging.getLogger(__name__)

HOST_SLACK_S = 0.25  # a busy host's delay between bytes arriving and a probe reading them (every core busy)
PING_SLOT_S = 0.003  # dynamixel-sdk's broadcast-ping allowance per ID (3 ms × MAX_ID in broadcastPing)
MAX_RETURN_DELAY_S = 254 * DYNAMIXEL_RETURN_DELAY_UNIT_S  # the slowest a servo may be told to answer
AURORA_RESET_BAUD = 9_600  # the Aurora after power-up or reset (reference: devices.md)
AURORA_RESPONSE_S = 0.1  # UNVERIFIED: the Aurora's time to answer VER (ndicapi allows ~200 ms for INIT)
AURORA_VER_REPLY_BYTES = 200  # a real ``VER 0`` reply: six lines of text (about 170 bytes) + CRC
BOARD_RESPONSE_S = bp.BOOT_S + 0.2  # opening the port resets an Uno/Nano: its boot, then one loop
BOARD_LINE_BYTES = bp.MAX_BODY + 4  # the longest line either way: body, ``*XX``, newline
SLCAN_BAUD = 115_200  # an slcan adapter is a USB CDC device: the baud is not on any wire
SLCAN_RESPONSE_S = 0.01  # UNVERIFIED: a CANable-class adapter answers ``V`` within a USB frame or so
# (instruction bytes, reply bytes) of a one-byte Read: header 4 + ID + LEN 2 + INST + addr 2 + len 2 + CRC 2;
# status header 4 + ID + LEN 2 + INST + ERR + 1 + CRC 2
_READ1_BYTES = (14, 12)
_PING_BYTES = (10, 14)
STATUS_HEADER = b"\xff\xff\xfd\x00"  # every Protocol 2.0 packet starts so


def dynamixel_bauds(first: int | None = None) -> list[int]:
    """Every standard Dynamixel baud, ``first`` (e.g. the description's) then the factory 57,600 first of the
    rest, then the others from fast to slow."""
    order = [first] if first else []
    order += [DYNAMIXEL_FACTORY_BAUD, *sorted(DYNAMIXEL_BAUDS.values(), reverse=True)]
    return list(dict.fromkeys(b for b in order if b in DYNAMIXEL_BAUDS.values()))


def ping_budget_s(baud: int, max_id: int) -> float:
    """How long a broadcast ping at ``baud`` is awaited: every ID up to ``max_id`` answering in its slot, at
    the slowest return delay, the adapter's factory latency timer, and the host's slack."""
    link = SerialLink(baud, FTDI_DEFAULT_LATENCY_S)
    request, status = _PING_BYTES
    reply = link.exchange_s(request, [status] * max_id, MAX_RETURN_DELAY_S)
    return reply + PING_SLOT_S * max_id + HOST_SLACK_S


def read_budget_s(baud: int) -> float:
    """How long a one-byte Read at ``baud`` is awaited (as :func:`ping_budget_s`, one servo)."""
    request, status = _READ1_BYTES
    link = SerialLink(baud, FTDI_DEFAULT_LATENCY_S)
    return link.exchange_s(request, [status], MAX_RETURN_DELAY_S) + HOST_SLACK_S


def line_budget_s(baud: int, request: int, reply: int, response_s: float) -> float:
    """How long a line-protocol exchange of ``request`` and ``reply`` bytes at ``baud`` is awaited."""
    return SerialLink(baud, FTDI_DEFAULT_LATENCY_S).exchange_s(request, [reply], response_s) + HOST_SLACK_S


@dataclass(frozen=True)
class Servo:
    """A servo that answered: its ID, the baud it answered at and its model number."""

    dxl_id: int
    baud: int
    model: int


@dataclass(frozen=True)
class Answer:
    """What answered on a port: ``kind`` (dynamixel, aurora, board, slcan), the baud it answered at, a short
    identification, and the servos found (a Dynamixel bus)."""

    kind: str
    baud: int
    ident: str
    servos: tuple[Servo, ...] = field(default=())


class _BudgetedPort(PortHandler):
    """dynamixel-sdk's port handler, its packet timeouts held to the probe's wire budget (the SDK's own allow
    0.8 s and more for a broadcast ping: 253 IDs' slots)."""

    def __init__(self, port_name: str) -> None:
        super().__init__(port_name)
        self.budget_ms = 1000.0
        self.received = bytearray()  # what the last exchange read: a status header, or another device's bytes

    def readPort(self, length):
        data = super().readPort(length)
        self.received += data
        return data

    def setPacketTimeout(self, packet_length):  # the SDK's names
        super().setPacketTimeout(packet_length)
        self.packet_timeout = min(self.packet_timeout, self.budget_ms)

    def setPacketTimeoutMillis(self, msec):
        super().setPacketTimeoutMillis(min(msec, self.budget_ms))


@contextlib.contextmanager
def dynamixel_port(port: str) -> Iterator[_BudgetedPort]:
    """The SDK's port handler on ``port``, open for the block; OSError when it cannot be opened."""
    handler = _BudgetedPort(port)
    try:
        if not handler.openPort():
            raise OSError(f"{port}: cannot be opened")
    except serial.SerialException as exc:
        raise OSError(f"{port}: {exc}") from None
    try:
        yield handler
    finally:
        handler.closePort()


def ping_servos(handler: _BudgetedPort, baud: int, max_id: int) -> list[Servo] | None:
    """The servos that answer a broadcast ping at ``baud`` (none: an empty list); None when replies came
    but garbled: servos sharing an ID answer over each other (new servos all have ID 1)."""
    if not handler.setBaudRate(baud):
        return []
    handler.budget_ms = ping_budget_s(baud, max_id) * 1e3
    handler.received.clear()
    found, result = PacketHandler(2.0).broadcastPing(handler)
    if not found:  # bytes with a status header that fail their CRC: statuses on top of each other
        garbled = result not in (COMM_SUCCESS, COMM_RX_TIMEOUT) and STATUS_HEADER in handler.received
        return None if garbled else []
    return [Servo(i, baud, model) for i, (model, _firmware) in sorted(found.items())]


@dataclass(frozen=True)
class BusScan:
    """The servos found on a bus, and the bauds at which replies came garbled (servos sharing an ID)."""

    servos: tuple[Servo, ...]
    garbled: tuple[int, ...] = ()

    @property
    def bauds(self) -> list[int]:
        """Every baud something answered at."""
        return sorted({s.baud for s in self.servos} | set(self.garbled))


def find_servos(port: str, bauds: list[int], max_id: int, every_baud: bool = False) -> BusScan:
    """Servos on ``port``: a broadcast ping at each of ``bauds`` in turn, stopping at the first that answers
    unless ``every_baud`` (servos of one bus may have been set to different bauds)."""
    servos: list[Servo] = []
    garbled: list[int] = []
    with dynamixel_port(port) as handler:
        for baud in bauds:
            found = ping_servos(handler, baud, max_id)
            if found is None:
                garbled.append(baud)
            servos += found or []
            if (found is None or found) and not every_baud:
                break
    return BusScan(tuple(servos), tuple(garbled))


def read_byte(handler: _BudgetedPort, servo: Servo, item: tuple[int, int]) -> int | None:
    """One byte of ``servo``'s control table (``item``: address, 1), None when it does not answer."""
    if not handler.setBaudRate(servo.baud):
        return None
    handler.budget_ms = read_budget_s(servo.baud) * 1e3
    value, result, error = PacketHandler(2.0).read1ByteTxRx(handler, servo.dxl_id, item[0])
    return value if result == COMM_SUCCESS and not error else None


def servo_settings(port: str, servos: list[Servo]) -> dict[int, dict[str, int | None]]:
    """Each servo's ID, Baud Rate code and Return Delay Time as its control table holds them."""
    items = {"id": dx.ID, "baud_code": dx.BAUD_RATE, "return_delay": dx.RETURN_DELAY_TIME}
    with dynamixel_port(port) as handler:
        return {s.dxl_id: {k: read_byte(handler, s, item) for k, item in items.items()} for s in servos}


# ------------------------------------------------------------------------------------- line devices
def _exchange(port: str, baud: int, request: bytes, timeout_s: float, done) -> bytes:
    """Send ``request`` at ``baud`` and collect the reply until ``done(reply)`` or ``timeout_s``."""
    with serial.Serial(port, baud, timeout=0.01, write_timeout=timeout_s) as ser:
        ser.reset_input_buffer()
        ser.write(request)
        reply = bytearray()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not done(reply):
            reply += ser.read(4096)
        return bytes(reply)


def probe_aurora(port: str) -> Answer | None:
    """An NDI Aurora answering ``VER:0`` at 9,600 baud with a valid CRC."""
    request = ndi.format_command("VER", "0")
    budget = line_budget_s(AURORA_RESET_BAUD, len(request), AURORA_VER_REPLY_BYTES, AURORA_RESPONSE_S)
    reply = _exchange(port, AURORA_RESET_BAUD, request, budget, lambda r: r.endswith(b"\r"))
    try:
        text = ndi.parse_reply(reply)
    except CodecError:
        return None
    if "Aurora" not in text and "Freeze Tag" not in text:
        return None
    tag = next((line for line in text.split("\n") if line.startswith("Freeze Tag")), text.split("\n")[0])
    return Answer("aurora", AURORA_RESET_BAUD, tag.strip())


def probe_board(port: str, baud: int = bp.BAUD) -> Answer | None:
    """One of our Arduino boards answering ``ID?`` (after the reset opening its port causes)."""
    request = bp.encode("1 ID?")
    budget = line_budget_s(baud, len(request), BOARD_LINE_BYTES, BOARD_RESPONSE_S)
    with serial.Serial(port, baud, timeout=0.01, write_timeout=budget) as ser:
        deadline = time.monotonic() + budget
        rx = bytearray()
        sent = False
        while time.monotonic() < deadline:
            rx += ser.read(4096)
            *lines, rest = bytes(rx).split(b"\n")
            rx = bytearray(rest)
            for line in lines:
                message = _board_message(line)
                if isinstance(message, bp.Ready) and not sent:
                    ser.write(request)
                    sent = True
                elif isinstance(message, bp.Ident):
                    return Answer("board", baud, f"{message.board} firmware {message.firmware} "
                                                 f"serial {message.serial}")  # fmt: skip
            if not sent and time.monotonic() > deadline - budget + bp.BOOT_S:  # no READY: did not reset
                ser.write(request)
                sent = True
    return None


def _board_message(line: bytes) -> bp.Message | None:
    try:
        return bp.parse_message(bp.decode(line + b"\n"))
    except (CodecError, ValueError):
        return None


def probe_slcan(port: str) -> Answer | None:
    """An slcan adapter answering ``V`` with its version (``Vhhss``)."""
    budget = line_budget_s(SLCAN_BAUD, 2, 6, SLCAN_RESPONSE_S)
    reply = _exchange(port, SLCAN_BAUD, b"V\r", budget, lambda r: b"\r" in r)
    line = reply.split(b"\r")[0]
    if len(line) == 5 and line[:1] == b"V" and line[1:].isalnum():
        return Answer("slcan", SLCAN_BAUD, f"slcan version {line[1:].decode()}")
    return None


def identify(port: str, max_id: int = 8) -> Answer | None:
    """What answers on ``port``: a Dynamixel bus (every baud, the factory one first), an
    slcan adapter, an Aurora, one of our boards; None for silence. OSError when the port cannot be opened."""
    bus = find_servos(port, dynamixel_bauds(), max_id)
    if bus.servos:
        ids = ", ".join(str(s.dxl_id) for s in bus.servos)
        return Answer("dynamixel", bus.servos[0].baud, f"servo IDs {ids}", bus.servos)
    if bus.garbled:
        return Answer("dynamixel", bus.garbled[0], "servos answering over each other (sharing an ID)")
    for probe in (probe_slcan, probe_aurora, probe_board):
        if (answer := probe(port)) is not None:
            return answer
    return None
