"""The wire between a client and an emulated device: when a reply may reach the client.

A reply is due no earlier than the request's bytes on the wire, the device's response time, the reply's bytes
on the wire and the USB adapter's latency-timer wait (:class:`acquisition.devices.bus_budget.SerialLink`:
the formulas are the budget's, so a rate reached on the rig is never above the ceiling it computes), and
never before the end of the reply before it (one wire).

The client's baud is read from the pty master with ``TCGETS2`` (Linux ``struct termios2``). Checked on
Linux 6.18 with pyserial 3.5: ``termios.tcgetattr`` on the master or the slave shows what the client set (the
slave's settings; a pty pair shares them), but only as a ``Bxxx`` code, and a rate without one (250,000, set
with ``BOTHER``) reads as ``BOTHER`` alone; ``TCGETS2`` on the master gives the rate itself in ``c_ospeed``
for standard rates (9,600, 57,600, 1,000,000, 4,000,000) and ``BOTHER`` rates (250,000, 1,234,567) alike.

The adapter's latency timer is a file, as Linux's ``ftdi_sio`` exposes it: ``<run_dir>/sysfs/bus/usb-serial/
devices/<device>/latency_timer`` (milliseconds, text), written by the rig from the description and read each
time a reply is timed, so ``echo 1 > …/latency_timer`` (what a udev rule does) changes the emulated adapter.
"""

from __future__ import annotations

import array
import fcntl
import logging
import os
import struct
from pathlib import Path

from acquisition.devices.bus_budget import USB_PACKET_BYTES, SerialLink

log = logging.getLogger(__name__)

_TCGETS2 = 0x802C542A  # _IOR('T', 0x2A, struct termios2), x86-64 and aarch64
_TERMIOS2 = struct.Struct("4I B 19s 2I")  # iflag, oflag, cflag, lflag, line, cc[19], ispeed, ospeed
SYSFS_DEVICES = Path("sysfs/bus/usb-serial/devices")  # under the run directory


def client_baud(fd: int) -> int | None:
    """The baud the client set on the pty whose master is ``fd`` (None where the kernel does not say)."""
    buf = array.array("B", bytes(_TERMIOS2.size + 8))
    try:
        fcntl.ioctl(fd, _TCGETS2, buf)
    except OSError as exc:
        log.debug("TCGETS2 failed on fd %d: %s", fd, exc)
        return None
    ospeed = _TERMIOS2.unpack_from(buf)[-1]
    return ospeed or None


def latency_timer_path(run_dir: Path, device: str) -> Path:
    """Where the rig keeps ``device``'s adapter latency timer (sysfs' layout under ``run_dir``)."""
    return Path(run_dir) / SYSFS_DEVICES / device / "latency_timer"


class LatencyTimer:
    """One emulated adapter's latency timer, kept in its sysfs-like file (whole milliseconds, 1–255 on an
    FTDI). A file that cannot be read or parsed keeps the last value read."""

    def __init__(self, path: Path, latency_s: float) -> None:
        self.path = path
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._ms = max(1, round(latency_s * 1000))
        self._seen: tuple[int, int, int] | None = None  # the file's (mtime, size, inode) when last read
        self.path.write_text(f"{self._ms}\n")

    def seconds(self) -> float:
        """The timer now: a write to the file takes effect on the next reply (the file is read again when its
        modification time or size changed; a stat a reply, not an open and read: a tenth of the rig's time
        went to reading it at every reply)."""
        try:
            st = os.stat(self.path)
            seen = (st.st_mtime_ns, st.st_size, st.st_ino)
            if seen != self._seen:
                self._ms = max(1, min(255, int(self.path.read_text().strip())))
                self._seen = seen
        except (OSError, ValueError) as exc:
            log.warning("%s unreadable (%s): latency timer stays %d ms", self.path, exc, self._ms)
        return self._ms / 1000.0


class Wire:
    """One device's serial line and its USB adapter: the time each reply is due at the client."""

    def __init__(self, latency: LatencyTimer | None = None) -> None:
        self.latency = latency  # None: a USB CDC device (no latency timer)
        self.free_s = 0.0  # when the wire is done with the last reply
        self.last_due_s = 0.0  # replies reach the client in order

    def link(self, baud: int) -> SerialLink:
        """The link at ``baud`` with the adapter's latency timer as it is now."""
        return SerialLink(baud, 0.0 if self.latency is None else self.latency.seconds())

    def schedule(self, now_s: float, baud: int | None, request: int, response_s: float,
                 reply: int) -> list[tuple[float, int]]:  # fmt: skip
        """When a ``reply``-byte answer to a ``request``-byte command the client finished writing at
        ``now_s`` reaches the client, as the adapter sends it: (due, end offset) of each USB packet (a full
        62-byte one when its last byte has arrived, the last part-filled one a latency-timer period after
        its last byte), after the replies before it (``baud`` None: no UART, only the response time)."""
        if baud is None:
            self.free_s = self.last_due_s = max(now_s + response_s, self.free_s, self.last_due_s)
            return [(self.free_s, reply)]
        link = self.link(baud)
        alone = now_s + link.exchange_s(request, [reply], response_s)  # request, response, reply, adapter
        wait = link.adapter_wait_s(reply)
        queued = self.free_s + link.wire_s(reply) + wait  # behind the reply before it on the one wire
        end = max(alone, queued) - wait  # the reply's last byte at the adapter
        self.free_s = end
        start = end - link.wire_s(reply)
        packets = [(start + link.wire_s(k), k) for k in range(USB_PACKET_BYTES, reply, USB_PACKET_BYTES)]
        packets.append((end + wait, reply))
        packets = [(max(due, self.last_due_s), k) for due, k in packets]
        self.last_due_s = packets[-1][0]
        return packets
