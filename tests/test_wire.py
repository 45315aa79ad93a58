"""The wire between the drivers and the twin's devices: the client's baud, the devices' response time and the
USB adapter's latency timer, as the pty host delivers them (twin/wire.py), and the emulator state that sets
them (Baud Rate, Return Delay Time and ID in each XM430's control table; the Aurora's COMM), and the
recorder refusing a rate the wire cannot carry."""

from __future__ import annotations

import os
import pty
import statistics
import struct
import time
import tty

import pytest
import serial
from dynamixel_sdk import (
    COMM_RX_CORRUPT,
    COMM_RX_TIMEOUT,
    COMM_SUCCESS,
    GroupSyncRead,
    PacketHandler,
    PortHandler,
)
from typer.testing import CliRunner

from acquisition.codecs import dynamixel as dx
from acquisition.codecs import ndi
from acquisition.devices.bus_budget import SERVO_BLOCK_BYTES, SerialLink, servo_bus_ceiling_hz, servo_read_s
from acquisition.recorder.recorder import Recorder, RecorderError
from twin.emulators.aurora import AuroraEmulator, demo_sample
from twin.emulators.dynamixel import DynamixelBusEmulator, SimpleServos
from twin.wire import LatencyTimer, Wire, client_baud, latency_timer_path
from vslab.cli import app

RIG = {"module": "twin.rig", "extra": ("--robot", "vsl")}
DEMO_BUS = "servo_bus=twin.emulators.dynamixel:demo_bus"  # two XM430s at 1 Mbaud, no latency timer


def _packets(reply: bytes) -> list:
    return list(dx.PacketReader().feed(reply))


def _write(dxl_id: int, item: tuple[int, int], value: int) -> bytes:
    return dx.instruction(dxl_id, dx.WRITE, struct.pack("<H", item[0]) + value.to_bytes(item[1], "little"))


def _ping(dxl_id: int) -> bytes:
    return dx.instruction(dxl_id, dx.PING, b"")


# ------------------------------------------------------------------------------------- the timing model
def test_the_pty_shows_the_clients_baud_standard_and_custom():
    """TCGETS2 on the master reads what pyserial set on the slave, a BOTHER rate (250,000) included."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    try:
        for baud in (9_600, 57_600, 1_000_000, 4_000_000, 250_000):
            with serial.Serial(os.ttyname(slave), baud, timeout=0):
                assert client_baud(master) == baud
    finally:
        os.close(master)
        os.close(slave)


def test_a_reply_is_due_after_the_request_the_response_the_reply_and_the_adapter(tmp_path):
    timer = LatencyTimer(latency_timer_path(tmp_path, "servo_bus"), 0.016)
    assert timer.path.read_text().strip() == "16"
    wire = Wire(timer)
    link = SerialLink(1_000_000, 0.016)
    ((due, end),) = wire.schedule(10.0, 1_000_000, 18, 0.0005, 54)
    assert end == 54 and due == pytest.approx(10.0 + link.exchange_s(18, [54], 0.0005))
    # a second reply asked at once queues behind the first on the one wire
    ((due2, _),) = wire.schedule(10.0, 1_000_000, 18, 0.0, 54)
    assert due2 >= due + link.wire_s(54) - 1e-12
    # a long reply goes in 62-byte USB packets: the full ones as their last byte arrives, no timer wait
    packets = Wire(timer).schedule(0.0, 115_200, 12, 0.0, 200)
    slow = SerialLink(115_200, 0.016)
    assert [k for _, k in packets] == [62, 124, 186, 200]
    assert packets[0][0] == pytest.approx(slow.wire_s(12) + slow.wire_s(62))
    assert packets[-1][0] - packets[-2][0] > 0.016  # the part-filled last packet waits for the timer
    # the file is the adapter: writing 1 to it changes the next reply
    timer.path.write_text("1\n")
    ((due3, _),) = Wire(timer).schedule(0.0, 1_000_000, 18, 0.0, 54)
    assert due3 == pytest.approx(SerialLink(1_000_000, 0.001).exchange_s(18, [54]))


# ---------------------------------------------------------------------------------- the XM430's table
def test_a_factory_bus_has_every_servo_at_id_1_57600_and_return_delay_250():
    bus = DynamixelBusEmulator([1, 2], SimpleServos(), factory=True)
    assert bus.device_baud() == 57_600
    assert [(t.dxl_id, t.get(dx.BAUD_RATE), t.get(dx.RETURN_DELAY_TIME)) for t in bus.servos] == [
        (1, 1, 250)
    ] * 2
    assert bus.feed_at(_ping(1), 0.0, 1_000_000) == b""  # nobody hears 1 Mbaud
    (reply,) = _packets(bus.feed_at(_ping(1), 0.0, 57_600))  # two answers at once: one garbled status
    assert isinstance(reply, dx.CrcError)
    assert bus.response_s() >= 250 * 2e-6


def test_the_description_sets_baud_and_return_delay_and_each_status_waits_its_own():
    bus = DynamixelBusEmulator([1, 2], SimpleServos(), baud=4_000_000, return_delay_s=0.0001)
    assert bus.device_baud() == 4_000_000
    assert [t.get(dx.RETURN_DELAY_TIME) for t in bus.servos] == [50, 50]
    read = dx.instruction(dx.BROADCAST_ID, dx.SYNC_READ, struct.pack("<HH", 120, 16) + bytes([1, 2]))
    assert [p.dxl_id for p in _packets(bus.feed_at(read, 0.0, 4_000_000))] == [1, 2]
    assert bus.response_s() == pytest.approx(2 * 0.0001)


def test_a_new_baud_and_a_new_id_take_effect_after_their_status():
    bus = DynamixelBusEmulator([1, 2], SimpleServos())
    (ack,) = _packets(bus.feed_at(_write(1, dx.BAUD_RATE, 1), 0.0, 1_000_000))  # acked at the old baud
    assert ack.dxl_id == 1 and ack.error == 0
    assert bus.feed_at(_ping(1), 0.0, 1_000_000) == b""
    assert [p.dxl_id for p in _packets(bus.feed_at(_ping(1), 0.0, 57_600))] == [1]
    assert [p.dxl_id for p in _packets(bus.feed_at(_ping(2), 0.0, 1_000_000))] == [2]  # servo 2 kept its baud
    (ack,) = _packets(bus.feed_at(_write(2, dx.ID, 5), 0.0, 1_000_000))
    assert ack.dxl_id == 2
    assert bus.feed_at(_ping(2), 0.0, 1_000_000) == b""
    assert [p.dxl_id for p in _packets(bus.feed_at(_ping(5), 0.0, 1_000_000))] == [5]
    (ack,) = _packets(bus.feed_at(_write(5, dx.RETURN_DELAY_TIME, 0), 0.0, 1_000_000))
    assert ack.error == 0 and bus.tables[5].get(dx.RETURN_DELAY_TIME) == 0


def test_eeprom_items_are_refused_with_torque_on():
    bus = DynamixelBusEmulator([1], SimpleServos())
    bus.feed_at(_write(1, dx.TORQUE_ENABLE, 1), 0.0, 1_000_000)
    (ack,) = _packets(bus.feed_at(_write(1, dx.BAUD_RATE, 1), 0.0, 1_000_000))
    assert ack.error == dx.ERR_ACCESS and bus.device_baud() == 1_000_000


# ------------------------------------------------------------------------------------------ the Aurora
def test_the_aurora_talks_9600_until_comm_then_the_rate_comm_set():
    aurora = AuroraEmulator(demo_sample)
    init, comm, beep = (
        ndi.format_command("INIT"),
        ndi.format_command("COMM", "50000"),
        ndi.format_command("BEEP", "1"),
    )
    assert aurora.feed_at(init, 0.0, 115_200) == b""  # at power-up it hears 9,600 only
    assert aurora.feed_at(init, 0.0, 9_600).startswith(b"OKAY")
    assert aurora.feed_at(comm, 0.0, 9_600).startswith(b"OKAY")  # answered at the old rate
    assert aurora.device_baud() == 115_200
    assert aurora.feed_at(beep, 0.0, 9_600) == b""
    assert aurora.feed_at(beep, 0.0, 115_200) != b""
    aurora.port_opened(1.0)  # a new client's open stands for ndicapi's break: 9,600 again
    assert aurora.device_baud() == 9_600


# --------------------------------------------------------------------------------- the real SDK, on a pty
class _PatientPortHandler(PortHandler):
    """The SDK's port handler waiting 200 ms for a reply, not its 34 ms: a busy test machine may keep the
    rig from answering that fast (a reply's lateness is what these tests measure, not a failure)."""

    def setPacketTimeout(self, packet_length):  # the SDK's names
        self.packet_start_time = self.getCurrentTime()
        self.packet_timeout = 200.0


def _sdk(port: str, baud: int) -> tuple[PortHandler, PacketHandler]:
    """The real SDK on ``port`` at ``baud``, waiting 200 ms for a reply: a test asserting which reply comes
    (none, a corrupt one, the servo's) failed once with the SDK's own 34 ms, the factory rig's reply late
    beside the other test worker (COMM_RX_TIMEOUT for COMM_RX_CORRUPT)."""
    handler = _PatientPortHandler(port)
    assert handler.openPort() and handler.setBaudRate(baud)
    return handler, PacketHandler(2.0)


def test_the_sdk_at_the_wrong_baud_times_out_and_at_the_right_one_is_answered(host_factory):
    with host_factory(DEMO_BUS) as ports:
        handler, packet = _sdk(ports["servo_bus"], 57_600)
        try:
            _, result, _ = packet.ping(handler, 1)
            assert result == COMM_RX_TIMEOUT
            assert handler.setBaudRate(1_000_000)
            model, result, _ = packet.ping(handler, 1)
            assert result == COMM_SUCCESS and model == 1020
            # a new baud written over the wire: the ack comes at the old rate, the servo then at the new
            result, error = packet.write1ByteTxRx(handler, 1, dx.BAUD_RATE[0], 6)
            assert (result, error) == (COMM_SUCCESS, 0)
            assert packet.ping(handler, 1)[1] == COMM_RX_TIMEOUT
            assert handler.setBaudRate(4_000_000)
            assert packet.ping(handler, 1)[1] == COMM_SUCCESS
        finally:
            handler.closePort()


def _sync_read_times(port: str, n: int) -> list[float]:
    handler, packet = _sdk(port, 1_000_000)
    reader = GroupSyncRead(handler, packet, 120, SERVO_BLOCK_BYTES)
    for dxl_id in (1, 2):
        reader.addParam(dxl_id)
    times = []
    try:
        for _ in range(n):
            start = time.perf_counter()
            assert reader.txRxPacket() == COMM_SUCCESS
            times.append(time.perf_counter() - start)
    finally:
        handler.closePort()
    return times


def test_a_sync_read_on_the_rig_takes_what_the_budget_says_and_the_latency_timer_file_sets_it(
    host_factory, tmp_path, vsl
):
    """The vsl description: 1 Mbaud, Return Delay Time 0, latency timer 1 ms. The SDK's round trip is never
    shorter than the budget's exchange, and not absurdly longer (the host's own time on a busy machine);
    ``echo 16 > latency_timer`` makes every round trip at least 16 ms."""
    spec = vsl.devices["servo_bus"]
    budget = servo_read_s(SerialLink(spec.baud, spec.host_link.latency_timer_s), 2, SERVO_BLOCK_BYTES, 0)
    assert 1.0 / budget == pytest.approx(servo_bus_ceiling_hz(spec))
    with host_factory(**RIG) as ports:
        fast = _sync_read_times(ports["servo_bus"], 60)
        latency_timer_path(tmp_path / "run", "servo_bus").write_text("16\n")  # what a udev rule does
        slow = _sync_read_times(ports["servo_bus"], 20)
    assert min(fast) >= budget
    assert statistics.median(fast) < budget + 0.015
    assert min(slow) >= 0.016
    assert statistics.median(slow) < 0.016 + budget + 0.015


# ------------------------------------------------------------------------------------------ the recorder
def test_the_recorder_refuses_a_rate_above_the_ceiling_before_opening_anything(tmp_path, vsl):
    with pytest.raises(RecorderError, match=r"servo_bus \(dynamixel\): 1000 Hz asked, .* at most 588 Hz"):
        Recorder(
            vsl, {"servo_bus": str(tmp_path / "no-such-port")}, tmp_path / "s", "s", rates={"servo_bus": 1000}
        )
    assert not (tmp_path / "s").exists()


def test_record_at_a_rate_above_the_ceiling_is_one_error_line_and_exit_2(tmp_path):
    result = CliRunner().invoke(
        app,
        ["--lab", str(tmp_path / "lab"), "record", "--rig", "--rate", "servo_bus=1000", "--duration", "1"],
    )
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: servo_bus (dynamixel): 1000 Hz asked"), lines
    assert "latency timer" in lines[0]
    assert not (tmp_path / "lab" / "rig").exists() or not any((tmp_path / "lab" / "rig").iterdir())


def test_a_factory_rig_has_its_servos_at_57600_both_at_id_1_behind_a_16_ms_adapter(host_factory, tmp_path):
    """``python -m twin.rig --factory``: nothing answers at the lab's 1 Mbaud; at 57,600 the two ID-1 servos
    answer a ping together and the SDK sees a corrupt reply, as on a new bus; the adapter timers at 16 ms."""
    with host_factory(module="twin.rig", extra=("--robot", "vsl", "--factory")) as ports:
        assert latency_timer_path(tmp_path / "run", "servo_bus").read_text().strip() == "16"
        handler, packet = _sdk(ports["servo_bus"], 1_000_000)
        try:
            assert packet.ping(handler, 1)[1] == COMM_RX_TIMEOUT
            assert handler.setBaudRate(57_600)
            assert packet.ping(handler, 1)[1] == COMM_RX_CORRUPT
        finally:
            handler.closePort()
