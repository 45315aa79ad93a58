"""A USB-CAN adapter speaking slcan (Lawicel), in front of the twin's CAN bus: what python-can's ``slcan``
interface talks to on the lab's CANable-class adapter, served on a pty.

Closed (as powered up), it takes ``Sn`` (bit rate), ``O`` / ``L`` (open, listen-only), ``V``, ``N``, ``F``
and answers CR, or BEL for what the adapter refuses (a frame while closed or listen-only, ``Sn`` while open,
a malformed line). Open, it puts the host's frames on the bus (``z``/``Z`` when accepted) and sends every
frame the bus carries to the host as a frame line. The bus's bit rate must match the one the host set:
a mismatched adapter sees only errors, so it passes nothing either way (as a real one on a wrong-rate bus).
"""

from __future__ import annotations

import logging

from acquisition.codecs import slcan
from acquisition.codecs.can import CanFrame
from acquisition.errors import CodecError
from twin.can_bus import CanBus, CanNode
from twin.emulators.base import Emulator

log = logging.getLogger(__name__)

VERSION = b"V1013"  # hardware 1.0, software 1.3 (Lawicel format)
SERIAL = b"NVSL1"
MAX_LINE = 64  # longer input without a CR is dropped (an adapter's command buffer)


class _HostPort(CanNode):
    """The adapter's controller on the bus: what it receives goes to the host."""

    name = "host"

    def __init__(self) -> None:
        self.inbox: list[CanFrame] = []

    def receive(self, frame: CanFrame, t: float) -> list[tuple[float, CanFrame]]:
        self.inbox.append(frame)
        return []


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
            return slcan.CR
        if op == b"C" and len(line) == 1:
            self.open = self.listen_only = False
            return slcan.CR
        if op == b"V":
            return VERSION + slcan.CR
        if op == b"N":
            return SERIAL + slcan.CR
        if op == b"F":
            return b"F%02X" % (0x20 if self.bus.bus_off else 0) + slcan.CR  # bit 5: bus error (passive/off)
        return slcan.BEL

    def _transmit(self, line: bytes, now_s: float) -> bytes:
        if not self.open or self.listen_only or self.bus.bus_off or not self._rate_matches():
            return slcan.BEL
        try:
            frame = slcan.parse_frame(line)
        except CodecError as exc:
            log.debug("slcan adapter: %s", exc)
            return slcan.BEL
        self.bus.offer(self.port, now_s, frame)
        return b"Z\r" if frame.extended else b"z\r"

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

    def reset_link(self) -> None:
        """Unplugged and plugged back: the adapter powered up again, closed, with no bit rate."""
        self._rx.clear()
        self.open = self.listen_only = False
        self.bitrate = None
        self.port.inbox.clear()
