"""The pty host's side of a serial link: a device whose host stops reading loses whole replies (its output
buffer overflows), never the end of one; a half-sent line would reach the driver as garbage (python-can's
slcan reader dies on one). An slcan adapter behind such a host counts the frames it lost as overrun."""

from __future__ import annotations

import os

import pytest

from twin.can_bus import CanBus
from twin.emulators import slcan_adapter as A
from twin.emulators.base import Emulator
from twin.ptyhost import _Port


def _read_all(fd: int) -> bytes:
    os.set_blocking(fd, False)
    out = b""
    while True:
        try:
            chunk = os.read(fd, 65536)
        except BlockingIOError:
            return out
        if not chunk:
            return out
        out += chunk


@pytest.mark.slow
def test_a_host_that_does_not_read_loses_whole_replies_never_half_of_one(tmp_path):
    port = _Port("can_bus", Emulator(), tmp_path)
    try:
        client = os.open(os.ttyname(port.slave), os.O_RDWR | os.O_NOCTTY)
        lines = [f"t{k % 0x800:03X}8{k:016X}\r".encode() for k in range(20_000)]  # 22 bytes: no pty fits all
        for line in lines[:10_000]:
            port.write(line, 0.0)  # nobody reads: the pty fills, then replies are dropped
        data = _read_all(client)
        for line in lines[10_000:]:
            port.write(line, 0.0)  # the host reads again: the rest of a reply begun goes out first
            data += _read_all(client)
        received = data.split(b"\r")
        assert received[-1] == b""
        received = [line + b"\r" for line in received[:-1]]
        assert 0 < len(received) < len(lines)  # some were dropped ...
        assert set(received) <= set(lines)  # ... whole: every line that arrived is one that was sent, entire
        assert received == sorted(received, key=lines.index)  # in order
        os.close(client)
    finally:
        port.unplug()


@pytest.mark.slow
def test_an_adapter_whose_host_does_not_read_counts_the_frames_it_lost(tmp_path):
    """What the host never took of the adapter's frame lines is its receive FIFO overrunning: counted, one
    per frame line lost, and latched in the Lawicel flags; nothing is counted while the host reads."""
    bus = CanBus(1_000_000, [])
    adapter = A.SlcanAdapter(bus)
    adapter.feed(b"S8\rO\r", 0.0)
    port = _Port("can_bus", adapter, tmp_path)
    try:
        client = os.open(os.ttyname(port.slave), os.O_RDWR | os.O_NOCTTY)
        lines = [f"t{k % 0x800:03X}8{k:016X}\r".encode() for k in range(20_000)]
        for line in lines[:100]:
            port.write(line, 0.0)
        assert len(_read_all(client).split(b"\r")) == 101 and adapter.counters.rx_overrun == 0
        for line in lines:
            port.write(line, 0.0)  # nobody reads
        received = _read_all(client).count(b"\r")
        pending = port._unsent.count(b"\r")  # the end of a line the pty took in part: it goes out next
        assert 0 < adapter.counters.rx_overrun == len(lines) - received - pending
        assert int(adapter.feed(b"F\r", 0.0)[1:3], 16) & A.DATA_OVERRUN
        os.close(client)
    finally:
        port.unplug()
