"""The slcan adapter read in bulk (``acquisition.devices.slcan_bus``): the frames python-can's own reader
would give, in order, whatever the bytes' arrival; a line cut between two reads waits for its end; an error
reply is a line; and reading the POPUP bus's rate costs the host little CPU (python-can 4.6 took a system
call or two per byte: ~35 % of a core on the rig's bus, which a busy host could not spare)."""

from __future__ import annotations

import os
import pty
import threading
import time
import tty

import pytest

from acquisition.codecs.can import CanFrame
from acquisition.codecs.slcan import encode_frame
from acquisition.devices.slcan_bus import SlcanBus


@pytest.fixture
def adapter():
    """(the bus on a pty, the pty's master end: what the adapter sends is written there)."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    bus = SlcanBus(channel=os.ttyname(slave), bitrate=1_000_000, sleep_after_open=0.0)
    os.read(master, 1000)  # the bus's set-up commands (bitrate, open)
    yield bus, master
    bus.shutdown()
    os.close(master)
    os.close(slave)


def _line(can_id: int, data: bytes) -> bytes:
    return encode_frame(CanFrame(can_id, data))


def test_frames_sent_at_once_come_out_one_by_one_in_order(adapter):
    bus, master = adapter
    sent = [(0x180 + k, bytes([k] * (k % 9))) for k in range(40)]
    os.write(master, b"".join(_line(i, d) for i, d in sent) + b"T1234567821122\r")
    got = [bus.recv(timeout=1.0) for _ in range(41)]
    assert [(m.arbitration_id, bytes(m.data)) for m in got[:40]] == sent
    assert (
        got[40].is_extended_id and got[40].arbitration_id == 0x12345678 and bytes(got[40].data) == b"\x11\x22"
    )
    assert bus.recv(timeout=0.05) is None


def test_a_line_cut_between_reads_waits_for_its_end(adapter):
    bus, master = adapter
    line = _line(0x701, b"\x05")
    os.write(master, line[:4])
    t0 = time.monotonic()
    assert bus.recv(timeout=0.1) is None  # half a frame: nothing yet, after the timeout
    assert time.monotonic() - t0 >= 0.09
    os.write(master, line[4:] + _line(0x702, b"\x7f"))
    assert [bus.recv(timeout=1.0).arbitration_id for _ in range(2)] == [0x701, 0x702]


def test_an_error_reply_is_a_line_and_the_next_frame_follows(adapter):
    bus, master = adapter
    os.write(master, b"\a" + _line(0x181, b"\x01\x02"))
    assert bus._read(1.0) == "\a"
    assert bus.recv(timeout=1.0).arbitration_id == 0x181


def test_a_garbled_line_is_dropped_with_a_warning_and_reading_goes_on(adapter, caplog):
    """A byte flipped on the serial link (slcan has no checksum): that line never becomes a frame, and the
    frames around it arrive (python-can's own reader raised, or kept failing on a non-ASCII byte)."""
    bus, master = adapter
    good = _line(0x181, b"\xaa\xbb")
    for garbled in (good[:2] + b"\xc8" + good[3:], good[:6] + b"G" + good[7:], b"t18125\r"):
        os.write(master, _line(0x180, b"\x01") + garbled + good)
        assert [bus.recv(timeout=1.0).arbitration_id for _ in range(2)] == [0x180, 0x181]
    assert bus.recv(timeout=0.05) is None
    assert sum("garbled" in r.message for r in caplog.records) == 3


def test_reading_the_bus_in_bulk_costs_little_cpu(adapter):
    """2,000 frames (two seconds of the tip IMU's board at 1 kHz) fed as a host would meet them: the reading
    thread's own CPU time, not the wall, so a busy machine does not inflate it."""
    bus, master = adapter
    lines = [_line(0x190, bytes(range(8)))] * 2000
    cpu: list[float] = []

    def read() -> None:
        start = time.thread_time()
        got = sum(bus.recv(timeout=5.0) is not None for _ in lines)
        cpu.append(time.thread_time() - start)
        assert got == len(lines)

    reader = threading.Thread(target=read)
    reader.start()
    for k in range(0, len(lines), 20):  # 20 frames a write, as an adapter's USB packets bunch them
        os.write(master, b"".join(lines[k : k + 20]))
        time.sleep(0.002)
    reader.join(timeout=30)
    assert cpu, "the reader did not finish"
    per_frame_us = cpu[0] / len(lines) * 1e6
    assert per_frame_us < 40, f"{per_frame_us:.0f} µs of CPU a frame"  # python-can 4.6's own: ~190
