"""Emulators speak a device's real wire protocol as a byte-stream state machine.

``feed`` takes the bytes the host wrote and returns the device's reply; ``poll`` returns what the device
sends unprompted (streamed samples). No I/O here: the pty host moves the bytes, so every emulator is
unit-testable byte for byte, and the same object serves a pseudo-terminal in the rig.
"""

from __future__ import annotations

from dataclasses import dataclass


class Emulator:
    """Base of the emulators; ``now_s`` is the rig's clock (seconds since it started)."""

    name = "device"

    def feed(self, data: bytes, now_s: float) -> bytes:
        raise NotImplementedError

    def poll(self, now_s: float) -> bytes:
        """Unsolicited output (default: none)."""
        return b""

    def reset_link(self) -> None:
        """The host reopened the port after an unplug: drop half-received input (default: nothing)."""


@dataclass
class Faults:
    """Faults a test can ask for, applied by the pty host to one device's replies."""

    corrupt_replies: int = 0  # flip one byte in each of the next N replies
    drop_replies: int = 0  # swallow the next N replies
    unplugged: bool = False  # the port is gone
