"""Emulators speak a device's real wire protocol as a byte-stream state machine.

``feed`` takes the bytes the host wrote and returns the device's reply; ``poll`` returns what the device
sends unprompted (streamed samples) and ``next_output_s`` says when that is next due, so the pty host sleeps
until then instead of polling. No I/O here: the pty host moves the bytes, so every emulator is
unit-testable byte for byte, and the same object serves a pseudo-terminal in the rig.
"""

from __future__ import annotations

from dataclasses import dataclass

LEGACY_POLL_S = 0.001  # how often an emulator that streams but cannot say when is polled


class Emulator:
    """Base of the emulators; ``now_s`` is the rig's clock (seconds since it started)."""

    name = "device"
    baud: int | None = None  # the device's UART baud (its firmware's); None: any (a USB CDC device)

    def feed(self, data: bytes, now_s: float) -> bytes:
        raise NotImplementedError

    def poll(self, now_s: float) -> bytes:
        """Unsolicited output (default: none)."""
        return b""

    def next_output_s(self, now_s: float) -> float | None:
        """Rig time at which ``poll`` next has output (≤ ``now_s``: due now; None: nothing scheduled until the
        next ``feed``). It may be early (``poll`` then returns nothing and is asked again), never late.
        Default: None, or every millisecond for an emulator that overrides ``poll`` but not this."""
        if type(self).poll is Emulator.poll:
            return None
        return now_s + LEGACY_POLL_S

    def device_baud(self) -> int | None:
        """The baud the device's UART runs at now (None: any baud works, as on a USB CDC device)."""
        return self.baud

    def feed_at(self, data: bytes, now_s: float, baud: int | None) -> bytes:
        """``feed``, the bytes having been sent at ``baud`` (None: unknown, taken as the device's). At
        another baud than its own the device's UART sees framing errors and never a command: no reply."""
        device = self.device_baud()
        if baud is not None and device is not None and baud != device:
            return b""
        return self.feed(data, now_s)

    def response_s(self) -> float:
        """The device's response time before the reply the last ``feed`` returned (default: none)."""
        return 0.0

    resets_on_open = False  # an Arduino whose DTR line resets it: the pty host watches its port's opens

    def port_opened(self, now_s: float) -> None:
        """The first client opened the port (called only where ``resets_on_open``; default: nothing)."""

    def output_refused(self, data: bytes, now_s: float) -> None:
        """The host did not read: ``data`` (whole replies or streamed output) found its port full and was
        lost, as a device's output buffer overflows (default: nothing; a device that counts it overrides)."""

    def reset_link(self) -> None:
        """The host reopened the port after an unplug: drop half-received input (default: nothing)."""


@dataclass
class Faults:
    """Faults a test can ask for, applied by the pty host to one device's replies."""

    corrupt_replies: int = 0  # one bit flipped in the checksum of each of the next N replies
    drop_replies: int = 0  # swallow the next N replies
    unplugged: bool = False  # the port is gone
