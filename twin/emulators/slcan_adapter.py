"""A USB-CAN adapter speaking slcan (Lawicel), in front of the twin's CAN bus: what python-can's ``slcan``
interface talks to on the lab's CANable-class adapter, served on a pty.

Closed (as powered up), it takes ``Sn`` (bit rate), ``O`` / ``L`` (open, listen-only), ``V``, ``N``, ``F``
and answers CR, or BEL for what the adapter refuses (a frame while closed or listen-only, ``Sn`` while open,
a malformed line). Open, it puts the host's frames on the bus (``z``/``Z`` when accepted) and sends every
frame the bus carries to the host as a frame line. The bus's bit rate must match the one the host set:
a mismatched adapter sees only errors, so it passes nothing either way (as a real one on a wrong-rate bus).

The adapter queues the host's frames for the bus in order (``TX_QUEUE`` frames, as the CANable 2.0
firmware's transmit ring buffer): on a bus too loaded to take them a frame waits there, and one sent while
the queue is full is refused (BEL, ASSUMED: what the firmware answers a frame it cannot queue; python-can
ignores it) and counted. Received frames wait in a receive FIFO for the next USB transfer (every
millisecond; a 1 Mbit/s bus carries at most ~21 frames in one, so the FIFO never fills while the host reads).
It fills when the host stops reading: the port's buffer full, the frames that found no room are lost, counted
as overrun (``output_refused``). The twin itself answering late (its process not scheduled for a while) is
not the host failing to read: the frames of that while are all passed on. ``F`` reads the Lawicel status
flags latched since the last ``F`` (and clears them, as the SJA1000's interrupt register behind the Lawicel
CANUSB does): ``counters`` keeps the totals. python-can never sends ``F`` (its slcan interface reads no
status), so the bits are the Lawicel manual's, for a tool or a lab that asks. The serial side is USB CDC:
no baud limits it, each received frame costs ``bus_budget.slcan_line_bytes`` characters there.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from acquisition.codecs import slcan
from acquisition.codecs.can import CanFrame
from acquisition.errors import CodecError
from twin.can_bus import CanBus, CanNode
from twin.emulators.base import Emulator

log = logging.getLogger(__name__)

VERSION = b"V1013"  # hardware 1.0, software 1.3 (Lawicel format)
SERIAL = b"NVSL1"
MAX_LINE = 64  # longer input without a CR is dropped (an adapter's command buffer)
TX_QUEUE = 64  # frames: the CANable 2.0 firmware's transmit buffer (canable2-fw inc/can.h, TXQUEUE_LEN)

# Lawicel status flags (``F``; CANUSB manual): bit 0 receive FIFO full, 1 transmit FIFO full, 2 error
# warning, 3 data overrun, 5 error passive, 6 arbitration lost, 7 bus error
RX_FULL, TX_FULL, ERROR_WARNING, DATA_OVERRUN = 0x01, 0x02, 0x04, 0x08
ERROR_PASSIVE, ARBITRATION_LOST, BUS_ERROR = 0x20, 0x40, 0x80


@dataclass
class AdapterCounters:
    """What went wrong at the adapter since it powered up: the host's frames refused on a full transmit
    queue, received frames lost to a receive-FIFO overrun, arbitrations its frames lost."""

    tx_dropped: int = 0
    rx_overrun: int = 0
    arbitration_lost: int = 0


class _HostPort(CanNode):
    """The adapter's controller on the bus: what it receives goes to the host."""

    name = "host"
    tx_queue = TX_QUEUE
    tx_fifo = True  # the firmware's ring buffer: the host's frames go out in the order it sent them

    def __init__(self) -> None:
        self.inbox: list[CanFrame] = []
        self.listening = False
        self.counters = AdapterCounters()
        self.flags = 0  # latched Lawicel status flags

    def receive(self, frame: CanFrame, t: float) -> list[tuple[float, CanFrame]]:
        if not self.listening:  # closed, or at another bit rate: its controller takes nothing
            return []
        self.inbox.append(frame)
        return []

    def overrun(self, frames: int) -> None:
        """``frames`` received that the host never took: lost from the receive FIFO, latched in the flags."""
        if frames > 0:
            self.counters.rx_overrun += frames
            self.flags |= RX_FULL | DATA_OVERRUN

    def tx_dropped(self, frame: CanFrame, t: float) -> None:
        self.counters.tx_dropped += 1
        self.flags |= TX_FULL

    def lost_arbitration(self, frame: CanFrame, t: float) -> None:
        self.counters.arbitration_lost += 1
        self.flags |= ARBITRATION_LOST


class SlcanAdapter(Emulator):
    """The adapter, bridging the host's serial lines and ``bus``."""

    name = "slcan"

    def __init__(self, bus: CanBus) -> None:
        self.bus = bus
        self.port = _HostPort()
        bus.attach(self.port)
        self.bitrate: int | None = None
        self.open = False
        self.listen_only = False
        self._rx = bytearray()

    # the host's side -------------------------------------------------------------------------
    def feed(self, data: bytes, now_s: float) -> bytes:
        self.bus.run_until(now_s)
        self._rx += data
        if len(self._rx) > MAX_LINE and slcan.CR[0] not in self._rx:
            self._rx.clear()
            return slcan.BEL
        replies = [self._command(line, now_s) for line in slcan.split_lines(self._rx)]
        return b"".join(replies) + self._forward()

    def _command(self, line: bytes, now_s: float) -> bytes:
        if not line:
            return slcan.CR  # python-can's empty data-rate code after Sn
        op = line[:1]
        if op in (b"t", b"T", b"r", b"R"):
            return self._transmit(line, now_s)
        if op == b"S" and len(line) == 2 and line[1:].isdigit():
            if self.open:
                return slcan.BEL
            self.bitrate = slcan.BITRATES[int(line[1:])]
            return slcan.CR
        if op in (b"O", b"L") and len(line) == 1:
            if self.bitrate is None and not self.open:
                return slcan.BEL  # no bit rate set: a Lawicel adapter refuses to open
            self.open, self.listen_only = True, op == b"L"
            self.port.inbox.clear()  # nothing received while closed is kept
            self.port.listening = self._rate_matches()
            return slcan.CR
        if op == b"C" and len(line) == 1:
            self.open = self.listen_only = self.port.listening = False
            return slcan.CR
        if op == b"V":
            return VERSION + slcan.CR
        if op == b"N":
            return SERIAL + slcan.CR
        if op == b"F":
            return b"F%02X" % self.status_flags() + slcan.CR
        return slcan.BEL

    def _transmit(self, line: bytes, now_s: float) -> bytes:
        if not self.open or self.listen_only or self.bus.bus_off or not self._rate_matches():
            return slcan.BEL
        try:
            frame = slcan.parse_frame(line)
        except CodecError as exc:
            log.debug("slcan adapter: %s", exc)
            return slcan.BEL
        if not self.bus.offer(self.port, now_s, frame):
            return slcan.BEL  # the transmit queue is full: refused, counted
        return b"Z\r" if frame.extended else b"z\r"

    def status_flags(self) -> int:
        """The Lawicel status flags latched since they were last read (then cleared); a bus-off bus shows
        error passive and bus error for as long as it lasts."""
        flags, self.port.flags = self.port.flags, 0
        return flags | (ERROR_PASSIVE | BUS_ERROR if self.bus.bus_off else 0)

    @property
    def counters(self) -> AdapterCounters:
        """The adapter's error counters (totals since power-up)."""
        return self.port.counters

    def _rate_matches(self) -> bool:
        return self.bitrate == self.bus.bitrate

    # the bus's side --------------------------------------------------------------------------
    def poll(self, now_s: float) -> bytes:
        self.bus.run_until(now_s)
        return self._forward()

    def next_output_s(self, now_s: float) -> float | None:
        return self.bus.next_event_s()

    def _forward(self) -> bytes:
        frames, self.port.inbox = self.port.inbox, []
        if not (self.open and self._rate_matches()):
            return b""
        return b"".join(slcan.encode_frame(f) for f in frames)

    def output_refused(self, data: bytes, now_s: float) -> None:
        """The host stopped reading and the port is full: the frame lines in ``data`` are lost (what a
        reply line, ``z``, CR or BEL, would have said is lost with them, uncounted: not a received frame)."""
        lines = data.split(slcan.CR)
        self.port.overrun(sum(1 for line in lines if line.lstrip(slcan.BEL)[:1] in (b"t", b"T", b"r", b"R")))

    def reset_link(self) -> None:
        """Unplugged and plugged back: the adapter powered up again, closed, with no bit rate."""
        self._rx.clear()
        self.open = self.listen_only = self.port.listening = False
        self.bitrate = None
        self.port.inbox.clear()
