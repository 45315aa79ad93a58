"""What a host link can carry: the time one exchange takes on the wire and through the USB adapter, and the
highest rate a device can be read at, before a session asks for more.

The physics (reference/devices.md, reference/can.md):

- **UART, 8N1**: 10 bits on the wire per byte, so ``n`` bytes take ``10·n/baud`` seconds each way.
- **The device's response time**: a Dynamixel waits its Return Delay Time (2 µs units, factory 250 = 500 µs)
  before each status packet; in a Sync Read the servos answer one after another, each after its own delay.
- **The USB-serial adapter** (FTDI, as in the U2D2 and most USB-UART cables): received bytes go to the host
  in USB packets of up to 62 payload bytes; a packet goes when it is full, and a part-filled one only when
  the adapter's latency timer expires (default 16 ms; 1 ms once set). A reply whose last packet is not full
  therefore reaches the host up to one latency-timer period after its last byte: the budget counts the whole
  period (the worst case, which is what a rate must survive). The model of the timer (a full period after
  the last byte) is this module's assumption; the FTDI application note AN232B-04 describes the timer, not
  how a given chip's firmware aligns it.
- **CAN**: a data frame of ``n`` bytes with an 11-bit identifier is 47 + 8n bits plus the stuff bits the
  controller inserts after five equal bits (at most ⌊(34 + 8n − 1)/4⌋), plus the 3-bit interframe space.

The twin's emulators deliver replies by the same numbers (``twin.wire``): a rate reached on the rig is never
above the ceiling computed here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from models.robot import DeviceSpec, RobotDescription

BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit
USB_PACKET_BYTES = 62  # an FTDI full-speed bulk packet: 64 bytes less its 2 modem-status bytes
FTDI_DEFAULT_LATENCY_S = 0.016  # the latency timer as the driver sets it (16 ms)
DYNAMIXEL_RETURN_DELAY_UNIT_S = 2e-6  # Return Delay Time: 2 µs per unit
DYNAMIXEL_FACTORY_RETURN_DELAY = 250  # 500 µs
DYNAMIXEL_BAUDS = {0: 9_600, 1: 57_600, 2: 115_200, 3: 1_000_000, 4: 2_000_000, 5: 3_000_000, 6: 4_000_000,
                   7: 4_500_000}  # fmt: skip  # the control table's Baud Rate (address 8) codes
DYNAMIXEL_FACTORY_BAUD = 57_600
SERVO_BLOCK_BYTES = 16  # the servo driver's Sync Read block: Realtime Tick (120) … Present Position (135)
AURORA_POLLS_PER_FRAME = 2.5  # the recorder polls the Aurora a little faster than its frames
AURORA_TX_REQUEST_BYTES = 12  # "TX:0801" + 4 hex CRC + CR


@dataclass(frozen=True)
class SerialLink:
    """One serial link from the host to a device: the UART's baud and the USB adapter's latency timer
    (0 for a link without one, such as a USB CDC device that forwards each transfer at once)."""

    baud: int
    latency_timer_s: float = FTDI_DEFAULT_LATENCY_S

    def wire_s(self, n_bytes: int) -> float:
        """Seconds ``n_bytes`` occupy the wire."""
        return BITS_PER_BYTE * n_bytes / self.baud

    def adapter_wait_s(self, reply_bytes: int) -> float:
        """Seconds the adapter holds the end of a ``reply_bytes`` reply after its last byte arrived: a full
        latency-timer period unless the reply ends a USB packet exactly."""
        return self.latency_timer_s if reply_bytes % USB_PACKET_BYTES else 0.0

    def exchange_s(self, request_bytes: int, reply_bytes: list[int], response_s: float = 0.0) -> float:
        """Seconds from the first byte of a request to the host holding its whole reply: the request on the
        wire, each reply packet after the device's ``response_s``, then the adapter's wait."""
        replies = sum(response_s + self.wire_s(n) for n in reply_bytes)
        return self.wire_s(request_bytes) + replies + self.adapter_wait_s(sum(reply_bytes))


# ---------------------------------------------------------------------------------- Dynamixel Protocol 2.0
def sync_read_bytes(n_servos: int, length: int) -> tuple[int, int]:
    """(instruction bytes, bytes of each status packet) of a Sync Read of ``length`` bytes from ``n_servos``:
    header 4 + ID + LEN 2 + INST + address 2 + length 2 + one ID per servo + CRC 2; each status is header 4 +
    ID + LEN 2 + INST + ERR + data + CRC 2 (no stuffing counted: a data word rarely holds FF FF FD)."""
    return 14 + n_servos, 11 + length


def sync_write_bytes(n_servos: int, length: int) -> int:
    """Bytes of a Sync Write of ``length`` bytes to each of ``n_servos`` (no reply by design)."""
    return 14 + n_servos * (1 + length)


def servo_read_s(link: SerialLink, n_servos: int, length: int, return_delay: int) -> float:
    """Seconds one Sync Read of ``length`` bytes from ``n_servos`` takes on ``link``, each servo waiting
    ``return_delay`` (Return Delay Time units, 2 µs) before its status."""
    request, status = sync_read_bytes(n_servos, length)
    delay = return_delay * DYNAMIXEL_RETURN_DELAY_UNIT_S
    return link.exchange_s(request, [status] * n_servos, delay)


def servo_ceiling_hz(link: SerialLink, n_servos: int, length: int, return_delay: int,
                     goal_writes_per_read: float = 0.0, goal_length: int = 4) -> float:  # fmt: skip
    """The most Sync Reads per second ``link`` carries (``goal_writes_per_read``: Sync Writes of goals that
    share the bus, per read)."""
    cycle = servo_read_s(link, n_servos, length, return_delay)
    cycle += goal_writes_per_read * link.wire_s(sync_write_bytes(n_servos, goal_length))
    return 1.0 / cycle


def aurora_tx_reply_bytes(n_tools: int) -> int:
    """Bytes of an Aurora's ``TX:0801`` reply for ``n_tools`` tools: the handle count (2), per tool its
    handle (2), quaternion (4 × 6), position (3 × 7), error (6), port status (8) and frame (8), then LF,
    system status (4), CRC (4) and CR."""
    return 2 + 69 * n_tools + 1 + 4 + 4 + 1


def reply_timeout_s(latency_timer_s: float, floor_s: float = 0.01) -> float:
    """How long a driver should wait for a reply behind an adapter with this latency timer: twice the timer
    plus 2 ms as dynamixel-sdk allows, never under ``floor_s`` (a shorter wait times out on every reply
    the timer holds, and the late reply then answers the next request)."""
    return max(floor_s, 2 * latency_timer_s + 0.002)


# ---------------------------------------------------------------------------- a description's devices
def servo_bus_ceiling_hz(spec: DeviceSpec) -> float:
    """The most Sync Reads per second of the servo driver's block a described servo bus carries."""
    link = SerialLink(spec.baud, spec.host_link.latency_timer_s)
    delay = round(spec.return_delay_s / DYNAMIXEL_RETURN_DELAY_UNIT_S)
    return servo_ceiling_hz(link, len(spec.ids), SERVO_BLOCK_BYTES, delay)


def tracker_ceiling_hz(spec: DeviceSpec) -> float:
    """The highest frame rate a described Aurora can be recorded at: its polls (``AURORA_POLLS_PER_FRAME``
    per frame, one ``TX`` each, at the baud COMM set) take the link's whole time."""
    link = SerialLink(spec.baud, spec.host_link.latency_timer_s)
    poll_s = link.exchange_s(AURORA_TX_REQUEST_BYTES, [aurora_tx_reply_bytes(max(1, len(spec.ids)))])
    return 1.0 / (poll_s * AURORA_POLLS_PER_FRAME)


def rate_refusal(robot: RobotDescription, name: str, rate_hz: float | None = None) -> str | None:
    """Why device ``name`` cannot be read at ``rate_hz`` (default: its description's), in one line
    (:func:`ceiling_line`), or None where its link carries that rate or its kind names no ceiling."""
    from acquisition.devices.kinds import kind_of, resolve

    kind, spec = kind_of(robot, name), robot.devices[name]
    asked = rate_hz if rate_hz is not None else spec.rate_hz
    if kind.ceiling is None or asked is None:
        return None
    ceiling = resolve(kind.ceiling)(spec)
    return ceiling_line(f"{name} ({spec.driver})", asked, ceiling) if asked > ceiling else None


# -------------------------------------------------------------------------------------------------- CAN
def can_frame_bits(n_data: int, extended: bool = False, worst_case: bool = True) -> int:
    """Bits one CAN data frame occupies on the bus, the 3-bit interframe space included: 47 + 8n for an
    11-bit identifier (67 + 8n for a 29-bit one), plus the stuff bits (their most, ⌊(g + 8n − 1)/4⌋ with
    g = 34 or 54 bits under stuffing, or none where ``worst_case`` is False)."""
    if not 0 <= n_data <= 8:
        raise ValueError(f"a classic CAN frame carries 0 to 8 data bytes, not {n_data}")
    base, stuffed = (67, 54) if extended else (47, 34)
    stuff = (stuffed + 8 * n_data - 1) // 4 if worst_case else 0
    return base + 8 * n_data + stuff


def can_bus_load(frames_per_s: dict[int, float], bitrate: int, worst_case: bool = True) -> float:
    """The fraction of a CAN bus's time that frames take: ``frames_per_s`` maps each frame's data length
    (bytes) to how many such frames go per second (all 11-bit identifiers)."""
    bits = sum(rate * can_frame_bits(n, worst_case=worst_case) for n, rate in frames_per_s.items())
    return bits / bitrate


def slcan_line_bytes(n_data: int) -> int:
    """Characters of one received frame on an slcan adapter's serial line: ``t`` + 3 hex id + length digit
    + 2 hex per data byte + ``\\r`` (a timestamped line adds 4)."""
    return 1 + 3 + 1 + 2 * n_data + 1


def ceiling_line(what: str, asked_hz: float, ceiling_hz: float) -> str:
    """One line a user reads when ``asked_hz`` is above ``ceiling_hz``: the ceiling and how to raise it."""
    return (f"{what}: {asked_hz:g} Hz asked, but the link carries at most {math.floor(ceiling_hz):d} Hz "
            "(raise the baud rate, lower the servos' Return Delay Time, set the USB adapter's latency timer "
            "to 1 ms, or record at a lower --rate)")  # fmt: skip
