"""The pty host's side of a serial link: a device whose host stops reading loses whole replies (its output
buffer overflows), never the end of one; a half-sent line would reach the driver as garbage (python-can's
slcan reader dies on one)."""

from __future__ import annotations

import os

import pytest

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
            port.write(line)  # nobody reads: the pty fills, then replies are dropped
        data = _read_all(client)
        for line in lines[10_000:]:
            port.write(line)  # the host reads again: the rest of a reply begun goes out first
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
